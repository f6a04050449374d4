"""The fast-time simulator's fault models and safety monitor (issue #12): a killed drone's
vehicle flies PX4's offboard-loss failsafe (``kill_model`` 'px4'), and every flying drone
checks the plan it will fly against its peers between replans, as the flight service does."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gcs.bench_faults import bench_faults
from gcs.fastsim import SafetyMonitor, SimConfig, offboard_loss_trajectory, run_sim
from onboard.agent import DroneAgent, StaticMap
from onboard.comm import InMemoryBus, TrajectoryMsg
from onboard.config import load_formation, load_world_spec
from onboard.planner.field import AnalyticField
from onboard.planner.params import PlannerParams
from onboard.planner.trajectory import Trajectory
from onboard.world import World

PARAMS = PlannerParams(v_max_m_s=1.0)
TRIANGLE = np.array([[0.0, 0.0, 0.0], [-1.0, 1.5, 0.0], [-1.0, -1.5, 0.0]])


def _line(p0: np.ndarray, v: np.ndarray, t0: float, duration: float = 600.0) -> Trajectory:
    c = np.zeros((1, 6, 3))
    c[0, 0] = p0
    c[0, 1] = v
    return Trajectory(t0, c, np.array([duration]))


def test_offboard_loss_carries_the_vehicle_on_then_brakes_it_to_a_hold() -> None:
    p = np.array([1.0, 2.0, 1.0])
    v = np.array([0.6, 0.8, 0.0])  # 1 m/s
    a = np.array([0.1, -0.2, 0.0])
    loss, gain = 1.0, 0.95
    tr = offboard_loss_trajectory(5.0, p, v, a, loss, gain, 3.0, 30.0)
    p0, v0, a0 = tr.state(5.0)
    np.testing.assert_allclose(p0, p, atol=1e-12)  # no jump in position, speed or acceleration
    np.testing.assert_allclose(v0, v, atol=1e-12)
    np.testing.assert_allclose(a0, a, atol=1e-12)
    # during COM_OF_LOSS_T: close to PX4's position loop on the held setpoint (within
    # millimetres when the vehicle's acceleration already was the loop's, -gain * v)
    ts = np.linspace(0.0, loss, 51)
    exact = p + np.outer((1.0 - np.exp(-gain * ts)) / gain, v)
    assert float(np.max(np.linalg.norm(tr.sample(5.0 + ts) - exact, axis=1))) < 0.02
    loop = offboard_loss_trajectory(5.0, p, v, -gain * v, loss, gain, 3.0, 30.0)
    assert float(np.max(np.linalg.norm(loop.sample(5.0 + ts) - exact, axis=1))) < 0.002
    # then it slows to rest and holds; it never turns back along its way
    along = (tr.sample(np.linspace(5.0, 12.0, 701)) - p) @ (v / np.linalg.norm(v))
    assert bool(np.all(np.diff(along) >= -1e-9))
    end = tr.t0_s + float(np.sum(tr.durations_s[:2]))
    rest = tr.sample(end)
    np.testing.assert_allclose(tr.sample(end + 20.0), rest, atol=1e-12)
    np.testing.assert_allclose(tr.sample(end, order=1), np.zeros(3), atol=1e-9)
    travelled = float(np.linalg.norm(rest - p))
    assert 0.6 < travelled < 1.0 / gain  # it carries on, but less than the loop's lag
    # standing still: it stays where it is
    still = offboard_loss_trajectory(0.0, p, np.zeros(3), np.zeros(3), loss, gain, 3.0, 5.0)
    np.testing.assert_allclose(still.sample(np.linspace(0.0, 8.0, 9)), [p] * 9, atol=1e-12)


def test_planned_follows_the_queue() -> None:
    bus = InMemoryBus()
    a = DroneAgent(
        0,
        PARAMS,
        TRIANGLE,
        0,
        _line(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.0),
        bus,
        StaticMap(AnalyticField(World.empty(0.0))),
    )
    a.schedule(Trajectory.hover(np.array([5.0, 5.0, 1.0]), 1.0, 10.0))
    ts = np.array([0.0, 0.5, 0.99, 1.0, 1.5])
    got = a.planned(ts)
    np.testing.assert_allclose(got[:3, 0], [0.0, 0.5, 0.99])
    np.testing.assert_allclose(got[3:], [[5.0, 5.0, 1.0]] * 2)
    for t, q in zip(ts, got, strict=True):  # what flying() will say at each time
        np.testing.assert_allclose(a.flying(float(t)).sample(float(t)), q)


def _flying_along_x() -> tuple[InMemoryBus, DroneAgent, SafetyMonitor]:
    """Drone 0 of the triangle flying +x at 1 m/s from (0, 0, 1) in open space (its first
    replan far off), on a bus of its own, with a fast-time monitor."""
    bus = InMemoryBus(0.0)
    cfg = SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"))
    agent = DroneAgent(
        0,
        PARAMS,
        TRIANGLE,
        0,
        _line(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.0),
        bus,
        StaticMap(AnalyticField(World.empty(0.0))),
        goal=np.array([10.0, 0.0, 1.0]),
        first_replan_s=100.0,
    )
    return bus, agent, SafetyMonitor(cfg, 0.1)


def test_the_monitor_replans_at_once_then_brakes_for_a_peer_stopped_in_its_way() -> None:
    """Drone 0 flies +x at 1 m/s; peer 1 stops 0.7 m ahead and announces its hover: the monitor
    asks for a replan at once; if a plan made a moment ago still runs into it, it brakes as hard
    as the planner's acceleration limit allows (peers hear the braking trajectory)."""
    bus, agent, mon = _flying_along_x()
    far = Trajectory.hover(np.array([0.0, 5.0, 1.0]), 0.0, 600.0)
    bus.publish(TrajectoryMsg(1, 1, 0, far), 0.0)
    assert mon.look(agent, 0.0) == ""
    assert not agent.due(0.0)
    stop = Trajectory.hover(np.array([0.7, 0.0, 1.0]), 0.05, 600.0)
    bus.publish(TrajectoryMsg(1, 1, 1, stop), 0.05)
    what = mon.look(agent, 0.05)
    assert what.startswith("replan: drone 1"), what
    assert agent.due(0.05) and mon.replans == 1 and mon.brakes == 0
    mon.last_plan_s = 0.05  # the replan did not clear it
    what = mon.look(agent, 0.06)
    assert what.startswith("brake: drone 1"), what
    assert mon.brakes == 1
    ts = np.linspace(0.06, 5.0, 200)
    path = agent.planned(ts)
    # 1 m/s to rest in 0.25 m (peak deceleration a_max = 3 m/s^2), not the gentle stop's 0.5 m
    gap = float(np.min(np.linalg.norm(path - [0.7, 0.0, 1.0], axis=1)))
    assert gap == pytest.approx(0.7 - 0.06 - 0.25, abs=0.01)
    acc = agent.flying(0.06).sample(np.linspace(0.06, 0.56, 51), order=2)
    assert float(np.max(np.linalg.norm(acc, axis=1))) <= PARAMS.a_max_m_s2 + 1e-6
    np.testing.assert_allclose(agent.planned(np.array([5.0]))[0], path[-1])
    heard = bus.receive(1, 0.06)[0]
    assert heard.trajectory.t0_s == pytest.approx(0.06)  # the braking stop was announced
    assert mon.look(agent, 0.07).startswith("braking")  # still in the way: one brake a second
    assert mon.brakes == 1


def test_the_fast_time_monitor_keeps_the_wider_distance_while_unheard() -> None:
    """As the flight service's: while a peer does not hear us, the monitor judges peers at
    ``check_drone_m`` plus ``unheard_margin_m`` (0.8 m), not the plain 0.5 m. A peer hovering
    0.6 m beside our straight path is no conflict until it stops hearing us."""
    bus, agent, mon = _flying_along_x()
    beside = Trajectory.hover(np.array([1.0, 0.6, 1.0]), 0.0, 600.0)
    bus.publish(TrajectoryMsg(1, 1, 0, beside), 0.0)
    assert PARAMS.check_drone_m < 0.6 < PARAMS.check_drone_m + PARAMS.unheard_margin_m
    assert mon.look(agent, 0.0) == ""
    agent.set_unheard([1])
    what = mon.look(agent, 0.0)  # the same view, plan and step: looked at again
    assert what.startswith("replan: drone 1"), what


def test_a_killed_drone_flies_px4s_failsafe_and_its_peers_keep_clear() -> None:
    """Drone 1 of the hexagon is killed 4 s into the small forest, in front of a follower; its
    vehicle carries on along its last setpoint for COM_OF_LOSS_T, brakes and holds: the
    simulator's track is that path, and the healthy drones keep clear of it and arrive."""
    cfg = SimConfig(
        load_formation("hexagon-7"),
        load_world_spec("forest-small"),
        seed=1,
        v_max_m_s=1.0,
        validity_s=3.0,
        peer_forget_s=10.0,
        killed_drones={1: 4.0},
        monitor_rate_hz=100.0,
    )
    assert cfg.kill_model == "px4"
    r = run_sim(cfg)
    assert r.collisions == 0, r.events
    assert r.min_drone_distance_m >= cfg.collision_drone_m
    healthy = [0, 2, 3, 4, 5, 6]
    assert not r.timed_out and bool(np.all(r.arrived[healthy]))
    t_kill, p_kill = r.faults["killed"]["1"]
    t = r.tracks.t
    track = r.tracks.pos[:, 1]
    before = track[t <= t_kill + 1e-9][-2:]
    v_kill = (before[1] - before[0]) / cfg.sample_period_s
    assert float(np.linalg.norm(v_kill)) > 0.3  # it was flying when it died
    expect = offboard_loss_trajectory(
        t_kill,
        np.asarray(p_kill),
        v_kill,
        np.zeros(3),
        cfg.offboard_loss_s,
        cfg.px4_position_gain,
        cfg.params.a_max_m_s2,
        100.0,
    )
    after = t >= t_kill
    # the sampled velocity is a finite difference: centimetres
    assert float(np.max(np.linalg.norm(track[after] - expect.sample(t[after]), axis=1))) < 0.05
    assert float(np.linalg.norm(track[-1] - np.asarray(p_kill))) > 0.3  # it carried on
    np.testing.assert_allclose(
        track[t >= t_kill + 4.0], [track[-1]] * int(np.sum(t >= t_kill + 4.0))
    )


def test_sim_config_refuses_bad_fault_models() -> None:
    base = SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"))
    with pytest.raises(ValueError, match="kill_model"):
        dataclasses.replace(base, kill_model="explode")
    for name in ("offboard_loss_s", "px4_position_gain", "monitor_horizon_s"):
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(base, **{name: 0.0})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="resend_s"):
        dataclasses.replace(base, resend_s=(0.05, 0.0))
    for name in ("monitor_rate_hz", "monitor_brake_after_s", "retry_after_s"):
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(base, **{name: -1.0})  # type: ignore[arg-type]
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(base, **{name: math.nan})  # type: ignore[arg-type]


def test_bench_faults_flies_one_trial_of_a_run_again(tmp_path: Path) -> None:
    out = tmp_path / "one.json"
    args = ["--trials", "1", "--jobs", "1", "--seed", "3", "--time-limit", "3"]
    res = CliRunner().invoke(
        bench_faults, [*args, "--first", "5", "--kill-model", "instant", "--json", str(out)]
    )
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert [r["index"] for r in rep["trials"]] == [5]
    assert rep["kill_model"] == "instant" and rep["monitor_hz"] == 100.0 and rep["first"] == 5
    assert "monitor_replans" in rep and "monitor_brakes" in rep["trials"][0]
    res = CliRunner().invoke(bench_faults, [*args, "--monitor-hz", "-1"])
    assert res.exit_code != 0 and "--monitor-hz" in res.output
    res = CliRunner().invoke(bench_faults, [*args, "--first", "-1"])
    assert res.exit_code != 0 and "--first" in res.output


@pytest.mark.parametrize("fraction", [0.5, 1.0])
def test_braking_stop_peaks_at_its_fraction_of_the_limit(fraction: float) -> None:
    from onboard.service.ports import braking_trajectory

    v = np.array([0.6, -0.8, 0.0])  # 1 m/s
    tr = braking_trajectory(2.0, np.zeros(3), v, np.zeros(3), 3.0, peak_fraction=fraction)
    ts = np.linspace(2.0, 2.0 + float(tr.durations_s[0]), 2001)
    peak = float(np.max(np.linalg.norm(tr.sample(ts, order=2), axis=1)))
    assert peak == pytest.approx(fraction * 3.0, rel=1e-3)
    np.testing.assert_allclose(tr.sample(ts[-1], order=1), np.zeros(3), atol=1e-9)
    along = tr.sample(ts) @ v
    assert bool(np.all(np.diff(along) >= -1e-12))  # it never turns back
    slow = braking_trajectory(0.0, np.zeros(3), 0.1 * v, np.zeros(3), 3.0, peak_fraction=fraction)
    assert float(slow.durations_s[0]) == pytest.approx(0.5)  # never shorter than 0.5 s
    with pytest.raises(ValueError, match="peak_fraction"):
        braking_trajectory(0.0, np.zeros(3), v, np.zeros(3), 3.0, peak_fraction=1.5)


def test_with_no_better_stop_the_monitor_asks_for_a_plan_at_most_every_retry_period() -> None:
    """A peer that does not see us runs through where a stop would leave us: our plan comes
    inside the check's distance, but a brake would come closer still ('no better stop'). The
    monitor does not brake; it asks for a new plan, but not at every look (100 Hz): a drone
    flying a last resort replanned, and broadcast, a hundred times a second. At most every
    ``MONITOR_RETRY_S`` after the last plan."""
    from onboard.agent import MONITOR_RETRY_S

    bus, agent, mon = _flying_along_x()
    # across our way at x = 0.25 (where a hard stop from 1 m/s leaves us), at 1.5 m/s
    charging = _line(np.array([0.25, 0.9, 1.0]), np.array([0.0, -1.5, 0.0]), 0.0)
    bus.publish(TrajectoryMsg(1, 1, 0, charging), 0.0)
    mon.last_plan_s = 0.0  # a plan made just now
    what = mon.look(agent, 0.0)
    assert what.startswith("no better stop: drone 1"), what
    assert mon.brakes == 0 and mon.no_better_stop == 1
    assert not agent.due(0.0)  # not asked again straight after a plan
    t = MONITOR_RETRY_S
    what = mon.look(agent, t)
    assert what.startswith("no better stop: drone 1"), what
    assert agent.due(t) and mon.brakes == 0


def test_after_a_brake_the_twin_holds_as_the_service_unless_the_stop_meets_a_peer() -> None:
    """A brake of the monitor is a failed plan to the flight service, which hovers
    ``retry_after_s`` before it replans; the twin replanned on its grid at once, and so missed
    a real-stack collision (2026-12-01): a drone held there while a peer that could not see it
    flew at it. The twin holds too (``hold_until_s``, which ``run_sim`` obeys), and, as the
    service now does, retries at once when the stop itself meets a peer."""
    bus, agent, mon = _flying_along_x()
    ahead = Trajectory.hover(np.array([0.9, 0.0, 1.0]), 0.0, 600.0)
    bus.publish(TrajectoryMsg(1, 1, 0, ahead), 0.0)
    mon.last_plan_s = 0.0  # a plan made just now still runs into it
    what = mon.look(agent, 0.0)
    assert what.startswith("brake: drone 1"), what
    assert mon.hold_until_s == pytest.approx(1.0) and not agent.due(0.0)
    # the stop keeps clear of that hover (0.25 m on, 0.65 m short of it): the hold stands
    assert mon.look(agent, 0.1) == ""
    assert mon.hold_until_s == pytest.approx(1.0) and mon.braking_retries == 0
    # a peer that runs through where the stop holds (the last plan 0.5 s old, which in flight
    # would ask for a replan; holding, the service does not): retried at once, once
    crossing = _line(np.array([0.25, 1.0, 1.0]), np.array([0.0, -1.0, 0.0]), 0.5)
    bus.publish(TrajectoryMsg(2, 2, 0, crossing), 0.5)
    what = mon.look(agent, 0.5)
    assert what.startswith("braking: drone 2"), what
    assert mon.hold_until_s == pytest.approx(0.5) and mon.braking_retries == 1
    assert agent.due(0.5)
