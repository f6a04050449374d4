"""One ``swarm-onboard run`` process against one mock vehicle over real UDP and a real Zenoh bus
on loopback: a small test client sends the commands, two simulated peers publish trajectories.
Take off, hover, fly to a goal in formation, land, disarm — judged by the mock's ground truth."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from onboard.comm import wire
from onboard.comm.messages import TrajectoryMsg
from onboard.comm.zenoh_bus import SwarmNode
from onboard.comm.zenoh_session import peer_mesh
from onboard.record import read_record
from onboard.service.fakes import straight_trajectory
from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig

POINTS = [(0.0, -1.5, 0.0), (0.0, 0.0, 0.0), (0.0, 1.5, 0.0)]
EXE = Path(sys.executable).parent / "swarm-onboard"


def poll(cond: Callable[[], bool], timeout_s: float, what: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"the service exited ({proc.returncode}) waiting for {what}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _state(gcs: SwarmNode, drone: int) -> str:
    st = gcs.latest_states().get(drone)
    return "" if st is None else st[0].body.flight_state


def _command(gcs: SwarmNode, action: object, proc: subprocess.Popen) -> None:
    cmd = gcs.send_command(action, [0])  # type: ignore[arg-type]
    poll(lambda: 0 in gcs.acks(cmd.cmd_id), 5.0, f"ack of {type(action).__name__}", proc)
    ack = gcs.acks(cmd.cmd_id)[0]
    assert ack.accepted, ack.reason


@pytest.mark.slow
@pytest.mark.fleet
@pytest.mark.timeout(120)
# MAVSDK only: the demo's test flies service processes on pymavlink (the default) end to end
@pytest.mark.parametrize("implementation", ["mavsdk"])
def test_service_process_flies_in_formation(tmp_path: Path, implementation: str) -> None:
    sock = bind_consecutive_udp(1)[0]
    port = sock.getsockname()[1]
    fleet = Fleet(
        FleetConfig(
            count=1,
            base_port=port,
            local_port_offset=None,
            autopilot=AutopilotParams(boot_time_s=0.5),
        )
    )
    sock.close()
    mesh = peer_mesh(4)  # the service, the ground station, two simulated peers
    cfg_file = tmp_path / "onboard.yaml"
    svc_ep, gcs_ep, p1_ep, p2_ep = mesh
    cfg_file.write_text(
        f"""
drone: {{swarm: t{os.getpid()}}}
autopilot: {{implementation: {implementation}, url: "udp://127.0.0.1:{port}"}}
zenoh: {{listen: {list(svc_ep.listen)}, connect: {list(svc_ep.connect)}}}
depth: {{source: none}}
planner: {{v_max_m_s: 1.0}}
flight: {{takeoff_speed_m_s: 1.0}}
record: {{directory: "{tmp_path}"}}
logging: {{format: json}}
""".replace("'", '"')
    )
    swarm = f"t{os.getpid()}"
    log_file = open(tmp_path / "service.log", "w")  # noqa: SIM115 - closed below
    fleet.start()
    gcs = SwarmNode(swarm, None, gcs_ep)
    peers = [SwarmNode(swarm, 1, p1_ep), SwarmNode(swarm, 2, p2_ep)]
    proc = subprocess.Popen(
        [str(EXE), "run", "--id", "0", "--config", str(cfg_file)],
        stdout=log_file,
        stderr=subprocess.STDOUT,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    try:
        poll(lambda: 0 in gcs.alive_drones(), 30.0, "the drone's liveliness", proc)
        poll(lambda: _state(gcs, 0) == "idle", 30.0, "state idle", proc)
        now = time.time()
        _command(
            gcs,
            wire.FormationAssignment(POINTS, 1.0, 0.0, {0: 1, 1: 0, 2: 2}, 1, now),
            proc,
        )
        _command(gcs, wire.Takeoff(1.0), proc)
        poll(lambda: _state(gcs, 0) == "hover", 30.0, "hover", proc)
        truth = fleet.latest_truth()[1]
        assert truth.armed and abs(truth.position_m[2] - 1.0) < 0.3
        start = np.array(truth.position_m)
        c = np.mean(POINTS, axis=0)
        base = start - (np.array(POINTS[1]) - c)
        goal_center = base + [3.0, 0.0, 0.0]
        t = time.time()
        # drones 1 and 2 fly slots 0 and 2 alongside
        for node, slot in zip(peers, (0, 2), strict=True):
            off = np.array(POINTS[slot]) - c
            traj = straight_trajectory(base + off, goal_center + off, t, speed=0.8)
            node.publish_trajectory(TrajectoryMsg(node.drone_id, 1, slot, traj, 1, t + 20.0))
        _command(gcs, wire.Goal(tuple(float(x) for x in goal_center), None, t), proc)
        poll(lambda: _state(gcs, 0) == "formation-flight", 5.0, "formation flight", proc)
        poll(lambda: _state(gcs, 0) == "hover", 30.0, "arrival", proc)
        truth = fleet.latest_truth()[1]
        assert np.linalg.norm(np.array(truth.position_m) - (start + [3.0, 0, 0])) < 0.4
        _command(gcs, wire.Land(), proc)
        poll(lambda: _state(gcs, 0) == "landed", 30.0, "landed", proc)
        poll(lambda: not fleet.latest_truth()[1].armed, 10.0, "disarmed", proc)
        assert fleet.collision_events() == []
        status = gcs.latest_statuses()[0][0].body
        assert status.replans >= 1
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5.0)
        for p in peers:
            p.close()
        gcs.close()
        fleet.stop()
        log_file.close()
    assert proc.returncode == 0, (tmp_path / "service.log").read_text()[-3000:]
    lines = (tmp_path / "service.log").read_text().splitlines()
    assert any('"event": "ready"' in ln and '"drone": 0' in ln for ln in lines)
    recs = list(tmp_path.glob("drone0-*.mcap"))
    assert len(recs) == 1
    rec = read_record(recs[0])
    assert [t for _, _, t, _ in rec.transitions()][-1] == "landed"
    assert max(m["n_peers"] for m in rec.messages("/plan")) == 2  # both peers in the formation
