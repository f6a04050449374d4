"""Faults on the real processes (issue #12): a flight service SIGKILLed mid-flight.

Two ``swarm-onboard run`` processes fly two mock vehicles (``swarm-sitl``, its own process) over
real UDP and a real Zenoh bus on loopback; a ground-station client sends the commands. Drone 1's
service is killed with SIGKILL while the pair flies: PX4's offboard-loss failsafe (COM_OF_LOSS_T,
COM_OBL_RC_ACT) must take its vehicle, drone 0 must fly on and arrive without a collision, and
the restarted service (what systemd's Restart=on-failure does) must come back out of control of
the vehicle (no stream, no old plan) until the ground station resumes it; then it rejoins the
formation. Judged on the mock's ground truth.
"""

from __future__ import annotations

import os
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.bench_service import (
    MockProcess,
    ServiceProcess,
    SetpointTap,
    poll_until,
    service_config,
    swarm_summary,
    write_world,
)
from gcs.station import GroundStation, StationConfig
from onboard.comm import wire
from onboard.comm.zenoh_session import free_loopback_endpoint, peer_mesh
from sitl_mock.client import bind_consecutive_udp

BODY_RADIUS_M = 0.2  # the mock's default
POINTS = [(0.0, -1.5, 0.0), (0.0, 1.5, 0.0)]
SPAWNS = [(0.0, -1.5, 0.0), (0.0, 1.5, 0.0)]


def _config(swarm: str, port: int, ep: Any, record_dir: Path) -> dict[str, Any]:
    return service_config(
        swarm=swarm,
        autopilot_port=port,
        port_plus_id=True,
        zenoh_listen=ep.listen,
        zenoh_connect=ep.connect,
        record_dir=record_dir,
        extra={
            "planner": {"v_max_m_s": 1.0},
            "flight": {"takeoff_speed_m_s": 1.0},
            "geofence": {"min_enu_m": [-5.0, -6.0, 0.0], "max_enu_m": [15.0, 6.0, 3.0]},
        },
    )


def _ok(outcome: Any) -> None:
    assert outcome.ok, outcome.describe()


def _states(gs: GroundStation) -> dict[int, str]:
    return {d: str(v.flight_state or "") for d, v in gs.views().items()}


def _assign(gs: GroundStation, epoch: int) -> None:
    _ok(gs.send(wire.FormationAssignment(POINTS, 1.0, 0.0, {0: 0, 1: 1}, epoch, time.time())))


@pytest.mark.slow
@pytest.mark.fleet
@pytest.mark.timeout(300)
@pytest.mark.parametrize("loss_action", ["hold", "position"])
def test_a_killed_service_fails_safe_comes_back_out_of_control_and_rejoins(
    tmp_path: Path, loss_action: str
) -> None:
    """COM_OBL_RC_ACT ``hold``: the vehicle holds where it was, the restarted service finds it
    airborne and waits for ``resume``. PX4's default ``position`` without RC (observed on v1.16
    SIH): it descends, lands and disarms; the restarted service is IDLE and takes off again."""
    swarm = f"k{os.getpid()}"
    prefix = f"{swarm}/sim"
    world = write_world(tmp_path / "world.yaml", [], SPAWNS, SPAWNS)
    socks = bind_consecutive_udp(2)
    port = socks[0].getsockname()[1]
    for s in socks:
        s.close()
    mesh = peer_mesh(3)
    goal_centre = np.array([8.0, 0.0, 1.0])
    goals = goal_centre + np.array(POINTS) - np.mean(POINTS, axis=0)
    with ExitStack() as stack:
        mock = stack.enter_context(
            MockProcess(
                world,
                2,
                port,
                free_loopback_endpoint(),
                prefix,
                tmp_path / "mock",
                extra_args=["--set", f"autopilot.offboard_loss_action={loss_action}"],
            )
        )
        cfgs = [_config(swarm, port, mesh[d], tmp_path / f"d{d}") for d in (0, 1)]
        services = [
            stack.enter_context(ServiceProcess(d, cfgs[d], tmp_path / f"d{d}")) for d in (0, 1)
        ]
        gs = stack.enter_context(
            GroundStation(swarm, mesh[2], config=StationConfig(lead_s=1.0, ack_timeout_s=5.0))
        )
        for s in services:
            s.wait_ready(90.0)
        assert gs.wait_for_drones(ids=[0, 1], timeout_s=20.0, with_state=True) == {0, 1}
        _assign(gs, 1)
        _ok(gs.takeoff(1.0, [0, 1]))
        poll_until(
            lambda: set(_states(gs).values()) == {"hover"},
            40.0,
            "hover",
            mock.alive,
            describe=lambda: swarm_summary(gs),
        )
        _ok(gs.goal(tuple(goal_centre), targets=[0, 1]))
        poll_until(lambda: mock.latest_truth()[2].position_m[0] > 2.5, 30.0, "drone 1 under way")

        # SIGKILL drone 1's service in flight
        services[1].proc.kill()  # type: ignore[union-attr]
        services[1].proc.wait(5.0)  # type: ignore[union-attr]
        t_kill = time.monotonic()
        poll_until(
            lambda: mock.latest_truth()[2].mode != "OFFBOARD", 3.0, "PX4's offboard failsafe"
        )
        assert time.monotonic() - t_kill < 3.0
        time.sleep(2.0)  # the failsafe brakes
        held = np.array(mock.latest_truth()[2].position_m)

        # drone 0 flies on to its goal, around where drone 1 holds or descends
        min_sep = np.inf

        def arrived() -> bool:
            nonlocal min_sep
            t = mock.latest_truth()
            p0, p1 = np.array(t[1].position_m), np.array(t[2].position_m)
            min_sep = min(min_sep, float(np.linalg.norm(p0 - p1)))
            return bool(np.linalg.norm(p0 - goals[0]) < 0.4) and _states(gs).get(0) == "hover"

        poll_until(arrived, 60.0, "drone 0 at its goal", services[0].alive)
        assert min_sep > 2 * BODY_RADIUS_M + 0.1, min_sep
        if loss_action == "position":
            poll_until(
                lambda: not mock.latest_truth()[2].armed, 30.0, "drone 1 landed and disarmed"
            )

        # systemd restarts the service: it never resumes an old plan by itself
        services[1] = stack.enter_context(ServiceProcess(1, cfgs[1], tmp_path / "d1-restart"))
        services[1].wait_ready(90.0)
        expected = "pilot" if loss_action == "hold" else "idle"
        poll_until(lambda: _states(gs).get(1) == expected, 20.0, f"restarted drone 1 {expected}")
        time.sleep(2.0)
        t1 = mock.latest_truth()[2]
        assert t1.mode != "OFFBOARD" or not t1.armed
        if loss_action == "hold":
            assert t1.armed and np.linalg.norm(np.array(t1.position_m) - held) < 0.3
        else:
            assert t1.landed and not t1.armed
        assert not gs.goal(tuple(goal_centre), targets=[1]).ok  # refused until taken over

        if loss_action == "hold":
            _ok(gs.resume([1]))  # take the vehicle over where it holds
        else:
            _ok(gs.takeoff(1.0, [1]))
        poll_until(lambda: _states(gs).get(1) == "hover", 30.0, "drone 1 hovers in OFFBOARD")
        poll_until(lambda: mock.latest_truth()[2].mode == "OFFBOARD", 5.0, "OFFBOARD again")
        # rejoin: a new formation epoch for both, and a common goal
        _assign(gs, 2)
        rejoin = np.array([5.0, 0.0, 1.0])
        rejoin_goals = rejoin + np.array(POINTS) - np.mean(POINTS, axis=0)
        _ok(gs.goal(tuple(rejoin), targets=[0, 1]))

        def both_there() -> bool:
            t = mock.latest_truth()
            return all(
                np.linalg.norm(np.array(t[d + 1].position_m) - rejoin_goals[d]) < 0.4
                and _states(gs).get(d) == "hover"
                for d in (0, 1)
            )

        poll_until(both_there, 60.0, "both at the rejoin goals", mock.alive)
        _ok(gs.land([0, 1]))
        poll_until(lambda: set(_states(gs).values()) == {"landed"}, 30.0, "landed", mock.alive)
        truth = mock.latest_truth()
        assert truth[1].collisions == 0 and truth[2].collisions == 0


@pytest.mark.slow
@pytest.mark.vehicle  # one vehicle and its one flight service: light, beside the fleet's flights
@pytest.mark.timeout(240)
def test_a_cut_autopilot_link_stops_commanding_and_never_takes_the_vehicle_back(
    tmp_path: Path,
) -> None:
    """The UDP path to PX4 is cut in flight: the service notices (heartbeat timeout 1 s) and
    stops commanding, PX4's offboard failsafe holds the vehicle; when the path returns the
    service sends no setpoint (PX4 would re-enter OFFBOARD by itself if setpoints flowed) until
    resume, which takes the vehicle over where it is, without a jump to an old setpoint. Then
    the ground station goes away during a goal: the drone finishes it and hovers."""
    swarm = f"c{os.getpid()}"
    spawn = [(0.0, 0.0, 0.0)]
    world = write_world(tmp_path / "world.yaml", [], spawn, spawn)
    svc_port = bind_consecutive_udp(1)[0]
    port = svc_port.getsockname()[1]
    svc_port.close()
    mesh = peer_mesh(2)
    with ExitStack() as stack:
        path = stack.enter_context(SetpointTap(("127.0.0.1", port)))
        mock = stack.enter_context(
            MockProcess(
                world,
                1,
                path.front_port,
                free_loopback_endpoint(),
                f"{swarm}/sim",
                tmp_path / "mock",
                extra_args=["--set", "autopilot.offboard_loss_action=hold"],
            )
        )
        cfg = service_config(
            swarm=swarm,
            autopilot_port=port,
            zenoh_listen=mesh[0].listen,
            zenoh_connect=mesh[0].connect,
            record_dir=tmp_path / "d0",
            extra={
                "planner": {"v_max_m_s": 1.0},
                "flight": {"takeoff_speed_m_s": 1.0},
                "reactions": {"gcs_lost": {"timeout_s": 1.0, "action": "hover"}},
            },
        )
        svc = stack.enter_context(ServiceProcess(0, cfg, tmp_path / "d0"))
        gs = stack.enter_context(
            GroundStation(swarm, mesh[1], config=StationConfig(lead_s=1.0, ack_timeout_s=5.0))
        )
        svc.wait_ready(90.0)
        assert gs.wait_for_drones(ids=[0], timeout_s=20.0, with_state=True) == {0}
        _ok(gs.send(wire.FormationAssignment(POINTS, 1.0, 0.0, {0: 0}, 1, time.time())))
        _ok(gs.takeoff(1.0, [0]))
        poll_until(
            lambda: _states(gs).get(0) == "hover",
            40.0,
            "hover",
            svc.alive,
            describe=lambda: swarm_summary(gs),
        )
        _ok(gs.goal((8.0, 0.0, 1.0), targets=[0]))
        poll_until(lambda: mock.latest_truth()[1].position_m[0] > 1.5, 30.0, "under way")

        path.cut = True
        t_cut = time.monotonic()
        poll_until(lambda: _states(gs).get(0) == "link-lost", 5.0, "link-lost", svc.alive)
        noticed_s = time.monotonic() - t_cut
        assert noticed_s < 2.5, noticed_s  # 1 s heartbeat timeout + the 10 Hz state message
        poll_until(lambda: mock.latest_truth()[1].mode != "OFFBOARD", 5.0, "PX4's failsafe")
        time.sleep(1.5)
        held = np.array(mock.latest_truth()[1].position_m)
        assert held[0] < 6.0  # stopped well short of the goal

        path.cut = False
        t_back = time.monotonic()
        time.sleep(3.0)
        t = mock.latest_truth()[1]
        sent = path.arrivals_between(t_back, time.monotonic())
        assert sent.size == 0, "setpoints flowed again without a command"
        assert t.mode != "OFFBOARD" and _states(gs).get(0) == "link-lost"
        assert np.linalg.norm(np.array(t.position_m) - held) < 0.3

        _ok(gs.resume([0]))
        poll_until(lambda: mock.latest_truth()[1].mode == "OFFBOARD", 10.0, "OFFBOARD on resume")
        time.sleep(2.0)
        assert _states(gs).get(0) == "hover"
        assert np.linalg.norm(np.array(mock.latest_truth()[1].position_m) - held) < 0.3

        # the ground station goes away mid-goal: the drone finishes the goal and hovers there
        goal = (held[0] + 2.0, 0.0, 1.0)
        _ok(gs.goal(goal, targets=[0]))
        poll_until(lambda: _states(gs).get(0) == "formation-flight", 10.0, "flying to the goal")
        gs.close()
        time.sleep(1.0)
        assert svc.alive()
        poll_until(lambda: svc.log_events("gcs_lost"), 10.0, "gcs_lost noticed", svc.alive)
        own_goal = np.array(goal) + np.array(POINTS[0]) - np.mean(POINTS, axis=0)
        poll_until(
            lambda: np.linalg.norm(np.array(mock.latest_truth()[1].position_m) - own_goal) < 0.3,
            30.0,
            "the goal finished without the ground station",
            svc.alive,
        )
        gs = stack.enter_context(
            GroundStation(swarm, mesh[1], config=StationConfig(lead_s=1.0, ack_timeout_s=5.0))
        )
        assert gs.wait_for_drones(ids=[0], timeout_s=20.0, with_state=True) == {0}
        poll_until(lambda: _states(gs).get(0) == "hover", 10.0, "hover at the goal", svc.alive)
        assert mock.latest_truth()[1].mode == "OFFBOARD"
        _ok(gs.land([0]))
        poll_until(lambda: _states(gs).get(0) == "landed", 30.0, "landed", svc.alive)
        assert mock.latest_truth()[1].collisions == 0
