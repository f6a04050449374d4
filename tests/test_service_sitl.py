"""The service's threads against the SITL mock over real MAVLink (UDP loopback), the swarm bus
in memory: take off, fly to a goal with two simulated peers, land, disarm — judged by the mock's
ground truth. Both autopilot implementations."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from onboard.record import read_record
from onboard.service.adapters import open_autopilot
from onboard.service.config import default_config_path, load_onboard_config
from onboard.service.fakes import FakeBus, straight_trajectory
from onboard.service.ports import PeerInfo
from onboard.service.sdnotify import Notifier
from onboard.service.service import FlightService
from onboard.service.state import FlightState, Goal, Land, SetFormation, Takeoff
from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig

S = FlightState
POINTS = ((0.0, -1.5, 0.0), (0.0, 0.0, 0.0), (0.0, 1.5, 0.0))


def poll(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.02)


@pytest.fixture()
def fleet() -> Iterator[tuple[Fleet, int]]:
    sock = bind_consecutive_udp(1)[0]
    port = sock.getsockname()[1]
    cfg = FleetConfig(
        count=1,
        base_port=port,
        local_port_offset=None,
        speedup=1.0,
        autopilot=AutopilotParams(boot_time_s=0.5),
    )
    f = Fleet(cfg)
    sock.close()
    f.start()
    try:
        yield f, port
    finally:
        f.stop()


@pytest.mark.timeout(90)
@pytest.mark.parametrize("implementation", ["pymavlink", "mavsdk"])
def test_service_flies_the_mock(
    fleet: tuple[Fleet, int], tmp_path: Path, implementation: str
) -> None:
    f, port = fleet
    cfg = load_onboard_config(
        default_config_path(),
        0,
        overrides={
            "autopilot": {"implementation": implementation, "url": f"udp://127.0.0.1:{port}"},
            "depth": {"source": "none"},
            "record": {"directory": str(tmp_path)},
            "planner": {"v_max_m_s": 1.0},
            "flight": {"takeoff_speed_m_s": 1.0},
        },
    )
    ap = open_autopilot(cfg)
    bus = FakeBus()
    bus.gcs_heard = time.time()
    svc = FlightService(cfg, ap, bus, None, notifier=Notifier({}))
    runner = threading.Thread(target=svc.run, kwargs={"ready_timeout_s": 20.0}, daemon=True)
    keep_gcs = threading.Event()

    def gcs_beat() -> None:
        while not keep_gcs.wait(0.2):
            bus.gcs_heard = time.time()

    beat = threading.Thread(target=gcs_beat, daemon=True)
    try:
        runner.start()
        beat.start()
        poll(lambda: svc.ready, 30.0, "READY")
        now = time.time()
        c1 = bus.send(SetFormation(1, now, ((0, 1), (1, 0), (2, 2)), POINTS))
        c2 = bus.send(Takeoff(1.0))
        poll(lambda: len(bus.acks) >= 2, 5.0, "acks")
        assert bus.ack_of(c1) == (True, "") and bus.ack_of(c2) == (True, "")
        poll(lambda: svc.machine.state is S.HOVER, 30.0, "hover after take-off")
        truth = f.latest_truth()[1]
        assert truth.armed and abs(truth.position_m[2] - 1.0) < 0.3
        # two peers fly their slots alongside
        start = np.array(truth.position_m)
        goal_center = start + [3.0, 0.0, 0.0] - (np.array(POINTS[1]) - np.mean(POINTS, axis=0))
        c = np.mean(POINTS, axis=0)
        t = time.time()
        for pid, slot in ((1, 0), (2, 2)):
            off = np.array(POINTS[slot]) - c
            base = start - (np.array(POINTS[1]) - c)
            traj = straight_trajectory(base + off, goal_center + off, t, speed=0.8)
            bus.peer_infos[pid] = PeerInfo(pid, slot, 1, traj, t + 60.0, t)
        c3 = bus.send(Goal(tuple(float(x) for x in goal_center)))
        poll(lambda: len(bus.acks) >= 3, 5.0, "goal ack")
        assert bus.ack_of(c3)[0], bus.ack_of(c3)
        poll(lambda: svc.machine.state is S.FORMATION_FLIGHT, 5.0, "formation flight")
        poll(lambda: svc.machine.state is S.HOVER, 30.0, "arrival")
        truth = f.latest_truth()[1]
        own_goal = start + [3.0, 0.0, 0.0]
        assert np.linalg.norm(np.array(truth.position_m) - own_goal) < 0.4
        # the warm starts were solved on the planner's side thread (planning.side_thread)
        assert cfg.planning.side_thread
        assert any(t.name.startswith("svc-side") for t in threading.enumerate())
        c4 = bus.send(Land())
        poll(lambda: svc.machine.state is S.LANDED, 30.0, "landed")
        assert bus.ack_of(c4) == (True, "")
        poll(lambda: not f.latest_truth()[1].armed, 10.0, "disarmed")
        assert f.collision_events() == []
        assert bus.trajectories and bus.statuses
    finally:
        keep_gcs.set()
        svc.request_stop()
        runner.join(10.0)
        svc.stop()
        ap.close()
    assert not any(t.name.startswith("svc-side") for t in threading.enumerate())  # shut down
    recs = list(tmp_path.glob("*.mcap"))
    assert len(recs) == 1
    rec = read_record(recs[0])
    assert [t for _, _, t, _ in rec.transitions()][-1] == "landed"
    assert len(rec.messages("/setpoint")) > 100
