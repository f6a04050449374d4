"""Fast-time simulation: a small flight end to end, collision counting, a silent drone."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from gcs.fastsim import PlanCall, SimConfig, SimResult, run_sim
from onboard.config import Formation, load_formation, load_world_spec

JSON_KEYS = {
    "success",
    "arrived",
    "collisions",
    "events",
    "min_obstacle_clearance_m",
    "min_drone_distance_m",
    "e_sim_mean",
    "e_sim_max",
    "e_dist_mean",
    "flight_time_s",
    "replan_ms",
    "iterations",
    "status_counts",
}


@pytest.fixture(scope="module")
def small_flight() -> tuple[SimResult, list[PlanCall]]:
    calls: list[PlanCall] = []
    cfg = SimConfig(
        load_formation("triangle-3"), load_world_spec("forest-small"), seed=1, v_max_m_s=1.0
    )
    return run_sim(cfg, recorder=calls.append), calls


def test_small_flight_arrives_without_collision(
    small_flight: tuple[SimResult, list[PlanCall]],
) -> None:
    r, _ = small_flight
    assert r.success, r.to_json()
    assert np.all(r.arrived) and r.collisions == 0 and not r.timed_out
    assert r.min_obstacle_clearance_m > 0.2 and r.min_drone_distance_m > 0.4
    assert np.allclose(r.tracks.pos[-1], r.goals, atol=0.5)
    assert np.allclose(r.tracks.pos[0], r.starts)
    # ~16 m at <= 1 m/s: at least 16 s; far below the time limit.
    assert 16.0 <= r.flight_time_s < 60.0
    assert r.replan_ms["count"] == sum(r.status_counts.values()) > 0
    assert 0.0 <= r.e_sim_mean <= r.e_sim_max


def test_json_schema(small_flight: tuple[SimResult, list[PlanCall]]) -> None:
    r, _ = small_flight
    d = r.to_json()
    assert JSON_KEYS <= set(d)
    assert {"median", "p90", "max"} <= set(d["replan_ms"])
    json.dumps(d, allow_nan=False)
    t = r.to_json(include_tracks=True)["tracks"]
    assert np.asarray(t["pos"]).shape == r.tracks.pos.shape


def test_recorded_calls_see_sensed_obstacles_and_peers(
    small_flight: tuple[SimResult, list[PlanCall]],
) -> None:
    r, calls = small_flight
    assert len(calls) == r.replan_ms["count"]
    full = {tuple(row) for row in r.world.cylinders}
    for c in calls:
        seen = {tuple(row) for row in c.world.cylinders}
        assert seen <= full
        assert {p.drone_id for p in c.peers} <= {0, 1, 2} - {c.drone_id}
    # Drones are staggered by a third of the period (on the 10 ms grid); start 0.1 s ahead.
    assert [c.drone_id for c in calls[:3]] == [0, 1, 2]
    expected = [0.1, 1 / 3 + 0.1, 2 / 3 + 0.1]
    assert [c.t_start_s for c in calls[:3]] == pytest.approx(expected, abs=0.0101)
    # Later replans know every peer and have sensed part of the world, never all of it early.
    late = [c for c in calls if c.t_start_s > 2.0]
    assert all(len(c.peers) == 2 for c in late)
    assert calls[0].world.cylinders.shape[0] < r.world.cylinders.shape[0]


@pytest.mark.parametrize("silent", [0, 1])
def test_silent_drone_flight_is_safe_and_arrives(silent: int) -> None:
    # A drone whose radio fails: its peers never learn its trajectory, it still hears theirs and
    # must keep clear of them; every drone still arrives, without a collision and with the
    # planner's clearances.
    calls: list[PlanCall] = []
    cfg = SimConfig(
        load_formation("triangle-3"),
        load_world_spec("forest-small"),
        seed=1,
        v_max_m_s=1.0,
        silent_drones=(silent,),
    )
    r = run_sim(cfg, recorder=calls.append)
    assert all(silent not in {p.drone_id for p in c.peers} for c in calls if c.drone_id != silent)
    assert any(len(c.peers) == 2 for c in calls if c.drone_id == silent)
    assert r.success and bool(np.all(r.arrived))
    assert r.collisions == 0
    assert r.min_obstacle_clearance_m >= cfg.params.check_obstacle_m - 1e-6
    assert r.min_drone_distance_m >= cfg.params.check_drone_m - 1e-6
    json.dumps(r.to_json(), allow_nan=False)


def test_collisions_are_counted(tmp_path: Path) -> None:
    # Drone 0 starts inside a trunk and 0.35 m from drone 1: one event of each kind at t = 0.
    w = tmp_path / "trap.yaml"
    w.write_text(
        "cylinders: [[0, 0, 0.1, 0, 3]]\n"
        "cluttered_x: [0, 1]\nstart_center: [0, 0, 1]\ngoal_center: [3, 0, 1]\n"
        "starts: [[0, 0, 1], [0, 0.35, 1]]\ngoals: [[3, 0, 1], [3, 0.35, 1]]\n"
    )
    pair = Formation("pair", np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    cfg = SimConfig(pair, load_world_spec(w), time_limit_s=2.0, v_max_m_s=1.0)
    r = run_sim(cfg)
    assert not r.success
    kinds = {(e.kind, e.ids) for e in r.events if e.t_s == 0.0}
    assert kinds == {("obstacle", (0,)), ("drone", (0, 1))}
    assert r.collisions == r.obstacle_collisions + r.drone_collisions >= 2
    assert r.min_obstacle_clearance_m < 0.0
    assert r.min_drone_distance_m <= 0.35 + 1e-9


def test_planner_params_own_the_speed_limit() -> None:
    form, world = load_formation("triangle-3"), load_world_spec("forest-small")
    default = SimConfig(form, world)
    assert default.v_max_m_s == default.params.v_max_m_s == 0.5  # config/planner.yaml
    fast = SimConfig(form, world, v_max_m_s=1.5)  # shorthand for the planner's field
    assert fast.params.v_max_m_s == fast.v_max_m_s == 1.5
    assert fast.params.w_formation == default.params.w_formation
    own = SimConfig(form, world, planner=dataclasses.replace(default.params, v_max_m_s=2.0))
    assert own.v_max_m_s == 2.0  # taken from the planner, never overwritten
    assert SimConfig(form, world, v_max_m_s=2.0, planner=own.params).v_max_m_s == 2.0
    with pytest.raises(ValueError, match="v_max_m_s=1.0 differs from planner.v_max_m_s=2.0"):
        SimConfig(form, world, v_max_m_s=1.0, planner=own.params)
    with pytest.raises(ValueError, match="differs"):
        dataclasses.replace(own, v_max_m_s=1.0)  # a silent half-change is refused
    slow = own.with_v_max(0.3)
    assert slow.v_max_m_s == slow.params.v_max_m_s == 0.3 and slow.seed == own.seed
    with pytest.raises(ValueError, match="v_max_m_s must be > 0"):
        SimConfig(form, world, v_max_m_s=0.0)


def test_refused_attempts_are_counted_by_reason() -> None:
    """A plan that must enter unobserved space at once: every attempt (the first, the A*
    retry, the rescue: its A* path kept less than the rescue's 0.4 m) is refused for it, and
    the flight's counter reads that off the planner's own message."""
    from gcs.fastsim import REFUSAL_KEYS, count_refusals
    from onboard.planner.field import AnalyticField, GridField
    from onboard.planner.params import PlannerParams
    from onboard.planner.planner import (
        APPROACH,
        LAST_RESORT,
        FormationPlanner,
        PlanStatus,
    )
    from onboard.world import World

    exact = AnalyticField(World.empty(0.0))
    grid = GridField.from_function(exact.distance, [-2.0, -2.0, 0.0], [8.0, 2.0, 2.0], 0.1)
    field = GridField(grid.values, grid.origin, grid.res, known=grid.cell_centres()[..., 0] < 0.1)
    line = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
    z = np.zeros(3)
    res = FormationPlanner(PlannerParams(v_max_m_s=1.0), line, slot=1).plan(
        0.0, np.array([0.0, 0.0, 1.0]), z, z, np.array([6.0, 0.0, 1.0]), [], field
    )
    assert res.status == PlanStatus.EMERGENCY
    counts = dict.fromkeys(REFUSAL_KEYS, 0)
    count_refusals(res.message, counts)
    assert counts["attempts"] == counts["unobserved"] == 3
    assert counts == {**dict.fromkeys(REFUSAL_KEYS, 0), "attempts": 3, "unobserved": 3,
                      "unobserved_near": counts["unobserved_near"]}  # fmt: skip
    near = res.message.count(": unobserved space ")  # "unobserved space 0.2 m away ..."
    assert counts["unobserved_near"] == near
    assert "a* retry at the rescue levels" in res.message
    counts = dict.fromkeys(REFUSAL_KEYS, 0)
    count_refusals("formation: obstacle clearance 0.18 m at t=1.70 s; roomier a* way: 0.2 -> "
                   "0.3 m; a* retry without formation: drone 3 at 0.40 m at t=0.50 s; previous: "
                   "obstacle clearance 0.1 m at t=0.10 s", counts)  # fmt: skip
    assert (counts["attempts"], counts["obstacle"], counts["drone"]) == (2, 1, 1)
    assert counts["approach"] == counts["last_resort"] == 0
    for ending, key in ((APPROACH, "approach"), (LAST_RESORT, "last_resort")):
        counts = dict.fromkeys(REFUSAL_KEYS, 0)
        count_refusals(f"formation: obstacle clearance 0.28 m at t=9.10 s; {ending}", counts)
        assert (counts["attempts"], counts["obstacle"], counts[key]) == (1, 1, 1)


def test_a_flight_reports_its_refusals(small_flight: tuple[SimResult, list[PlanCall]]) -> None:
    r = small_flight[0]
    refused = sum(v for k, v in r.status_counts.items() if k != "ok")
    d = r.to_json()["refusals"]
    reasons = {"unobserved", "obstacle", "drone", "altitude", "other"}
    assert set(d) == {"attempts", *reasons, "unobserved_near", "approach", "last_resort"}
    assert d["attempts"] >= refused  # every replan not "ok" refused at least one attempt
    assert d["attempts"] == sum(d[k] for k in reasons)
    assert d["unobserved_near"] <= d["unobserved"]  # the neighbourhood's, of those
    # plans flown although every attempt was refused: counted once each, under their status
    flown = sum(v for k, v in r.status_counts.items() if k in ("ok", "ok-no-formation"))
    assert d["approach"] + d["last_resort"] <= flown


def test_map_overrides_reach_every_drones_map() -> None:
    """``SimConfig.occupancy_overrides`` (``bench demo --set-onboard mapping.occupancy.*``)
    set the drones' map parameters on top of the defaults, for the camera's frame rate; none
    leaves the defaults."""
    from gcs.fastsim import _mapped_perception
    from onboard.mapping.occupancy import OccupancyParams
    from onboard.world import World

    world = World(np.zeros((0, 5)), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    starts = np.array([[0.0, 0.0, 1.0], [0.0, 1.5, 1.0]])
    goals = starts + [10.0, 0.0, 0.0]
    base = SimConfig(
        load_formation("line-3"),
        load_world_spec("forest-small"),
        perception="mapped",
        camera_rate_hz=3.0,
        camera_skip_pixel=3,
    )
    plain = _mapped_perception(base, world, starts, goals)
    want = OccupancyParams(skip_pixel=3).for_frame_rate(3.0)
    assert [e.mapper.params for e in plain] == [want, want]
    over = dataclasses.replace(base, occupancy_overrides=(("occluded_fill_m", 0.2),))
    eyes = _mapped_perception(over, world, starts, goals)
    assert [e.mapper.params for e in eyes] == [dataclasses.replace(want, occluded_fill_m=0.2)] * 2
