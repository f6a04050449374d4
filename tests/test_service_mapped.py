"""Flight service processes on mapped perception: the SITL mock renders depth frames from the true
poses and publishes them (and the poses) over Zenoh; each ``swarm-onboard run`` process maps
them (``depth: zenoh-sim``) and plans on its own map only. A ground-station client
(``gcs.station.GroundStation``) sends the commands over the swarm bus.

Three services crossing a forest together, each on its own map, is the demo's test
(``tests/test_demo.py``, which also checks their records' maps and peers).

Judged on the mock's ground truth (collision count, clearances, true positions) and on the
services' flight records, not on exit codes alone.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.bench_service import MockProcess, ServiceProcess, poll_until, service_config, write_world
from gcs.station import GroundStation, StationConfig
from onboard.comm import wire
from onboard.comm.zenoh_session import free_loopback_endpoint, peer_mesh
from onboard.record import read_record
from sitl_mock.client import bind_consecutive_udp

BODY_RADIUS_M = 0.2  # the mock's default
DEPTH_HZ = 15.0


@contextmanager
def mapped_mock(
    tmp_path: Path,
    cylinders: Sequence[Sequence[float]],
    spawns: Sequence[Sequence[float]],
    prefix: str,
) -> Iterator[tuple[MockProcess, int]]:
    """``swarm-sitl`` (its own process) with vehicles 1..N at ``spawns`` among ``cylinders``,
    rendering depth frames and publishing them with the true poses over Zenoh under
    ``prefix``; yields (the mock, the UDP base port the services bind)."""
    world = write_world(tmp_path / "world.yaml", cylinders, spawns, spawns)
    socks = bind_consecutive_udp(len(spawns))
    port = socks[0].getsockname()[1]
    for s in socks:
        s.close()
    mock = MockProcess(
        world,
        len(spawns),
        port,
        free_loopback_endpoint(),
        prefix,
        tmp_path / "mock",
        depth_rate_hz=DEPTH_HZ,
    )
    with mock:
        yield mock, port


def _config(
    swarm: str, port: int, ep: Any, truth_ep: str, prefix: str, record_dir: Path
) -> dict[str, Any]:
    return service_config(
        swarm=swarm,
        autopilot_port=port,
        port_plus_id=True,
        zenoh_listen=ep.listen,
        zenoh_connect=ep.connect,
        record_dir=record_dir,
        depth={
            "source": "zenoh-sim",
            "rate_hz": DEPTH_HZ,
            "sim_prefix": prefix,
            "sim_connect": [truth_ep],
        },
        extra={
            "planner": {"v_max_m_s": 1.0},
            "flight": {"takeoff_speed_m_s": 1.0},
            "geofence": {"min_enu_m": [-5.0, -6.0, 0.0], "max_enu_m": [15.0, 6.0, 3.0]},
        },
    )


def _states(gs: GroundStation) -> dict[int, str]:
    return {d: str(v.flight_state or "") for d, v in gs.views().items()}


def _ok(outcome: Any) -> None:
    assert outcome.ok, outcome.describe()


def _fly(
    gs: GroundStation,
    mock: MockProcess,
    drones: list[int],
    points: list[tuple[float, float, float]],
    centre: tuple[float, float, float],
    alive: Any,
    flight_timeout_s: float,
) -> np.ndarray:
    """Formation, take-off, goal; the true positions (T, N, 3) sampled until every drone hovers
    at its own goal (a hover elsewhere is a hold: the flight goes on after it)."""
    goals = np.array(centre) + np.array(points)[drones] - np.mean(points, axis=0)
    _ok(
        gs.send(
            wire.FormationAssignment(points, 1.0, 0.0, {d: d for d in drones}, 1, time.time()),
            drones,
        )
    )
    _ok(gs.takeoff(1.0, drones))
    poll_until(
        lambda: all(_states(gs).get(d) == "hover" for d in drones), 40.0, "hover", alive, 0.1
    )
    _ok(gs.goal(centre, targets=drones))
    poll_until(
        lambda: all(_states(gs).get(d) == "formation-flight" for d in drones),
        30.0,
        "formation flight",
        alive,
        0.05,
    )
    track = []
    deadline = time.monotonic() + flight_timeout_s
    while True:
        truth = mock.latest_truth()
        pos = np.array([truth[d + 1].position_m for d in drones], dtype=np.float64)
        track.append(pos)
        states = _states(gs)
        at_goal = np.linalg.norm(pos - goals, axis=1) < 0.4
        if all(states.get(d) == "hover" for d in drones) and np.all(at_goal):
            break
        assert alive(), "a service died in flight"
        gave_up = [d for d in drones if states.get(d) in ("emergency", "landing", "landed")]
        assert not gave_up and time.monotonic() < deadline, (
            f"not arrived (drones {gave_up} gave up) after {flight_timeout_s} s: {states}, "
            f"true positions {pos.round(2).tolist()}; last events: "
            + "; ".join(f"{d}: {v.plan_status} / {v.message}" for d, v in gs.views().items())
        )
        time.sleep(0.05)
    return np.array(track, dtype=np.float64)


def _land(gs: GroundStation, mock: MockProcess, drones: list[int], alive: Any) -> None:
    _ok(gs.land(drones))
    poll_until(
        lambda: all(_states(gs).get(d) == "landed" for d in drones), 30.0, "landed", alive, 0.1
    )
    poll_until(
        lambda: not any(mock.latest_truth()[d + 1].armed for d in drones),
        10.0,
        "disarmed",
        alive,
        0.1,
    )


@pytest.mark.slow
@pytest.mark.vehicle  # one vehicle and its flight service: beside the fleet's flights
@pytest.mark.timeout(300)
def test_service_maps_the_mocks_depth_frames_and_flies_around_a_trunk(tmp_path: Path) -> None:
    trunk = (2.5, 0.0, 0.25, 0.0, 3.0)  # on the straight line from the start to the goal
    swarm = f"m{os.getpid()}"
    prefix = f"{swarm}/sim"
    points = [(0.0, 0.0, 0.0), (0.0, 3.0, 0.0)]  # drone 0 alone in slot 0 (no peer needed)
    own_goal = np.array([5.0, 0.0, 1.0])
    centre = tuple(float(v) for v in own_goal - (np.array(points[0]) - np.mean(points, axis=0)))
    svc_ep, gcs_ep = peer_mesh(2)
    with ExitStack() as stack:
        mock, port = stack.enter_context(mapped_mock(tmp_path, [trunk], [(0, 0, 0)], prefix))
        cfg = _config(swarm, port, svc_ep, mock.truth_endpoint, prefix, tmp_path)
        svc = stack.enter_context(ServiceProcess(0, cfg, tmp_path))
        gs = stack.enter_context(
            GroundStation(swarm, gcs_ep, config=StationConfig(lead_s=0.5, ack_timeout_s=5.0))
        )
        svc.wait_ready(60.0)
        assert gs.wait_for_drones(ids=[0], timeout_s=15.0, with_state=True) == {0}
        track = _fly(gs, mock, [0], points, centre, svc.alive, 120.0)[:, 0, :]
        final = mock.latest_truth()[1]
        assert np.linalg.norm(np.array(final.position_m) - own_goal) < 0.4
        assert final.collisions == 0
        # the straight line went through the trunk: the flight went around it
        near = track[np.abs(track[:, 0] - trunk[0]) < 0.3]
        assert near.size and np.min(np.abs(near[:, 1] - trunk[1])) > trunk[2] + BODY_RADIUS_M
        _land(gs, mock, [0], svc.alive)
    assert svc.returncode == 0, svc.log_tail()
    report = mock.summary
    assert report["collisions"] == []
    assert report["min_obstacle_distance_m"] > 0.1  # body surface to trunk surface, all flight
    (rec_path,) = tmp_path.glob("drone0-*.mcap")
    rec = read_record(rec_path)
    maps = rec.messages("/map")
    assert maps and max(m["occupied_cells"] for m in maps) > 100
    # the map put the trunk where it is: the nearest mapped surface, seen from near it, lies on
    # the trunk's surface (within the map's resolution and inflation)
    on_trunk = [
        m
        for m in maps
        if m["nearest_obstacle_m"] < 1.5
        and abs(np.hypot(*(np.array(m["nearest_obstacle_enu_m"][:2]) - trunk[:2])) - trunk[2]) < 0.2
    ]
    assert on_trunk, [(m["camera_enu_m"], m["nearest_obstacle_enu_m"]) for m in maps]
    plans = rec.messages("/plan")
    assert plans and all(p["n_peers"] == 0 for p in plans)
