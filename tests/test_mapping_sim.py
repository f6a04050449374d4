"""Perception in the fast-time simulation, the mapping benchmark command and its CLI options."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from gcs.bench_mapping import bench_mapping, perception_options, perception_overrides
from gcs.fastsim import SimConfig, run_sim
from onboard.config import load_formation, load_world_spec
from onboard.mapping import EsdfBuilder
from onboard.planner.trajectory import Trajectory
from onboard.sensors.simulated import (
    LOOK_AHEAD_S,
    SWEEP_PERIOD_S,
    SWEEP_RAD,
    SimulatedPerception,
    heading_yaw,
    look_velocity,
)
from onboard.world import World


def test_default_perception_is_ground_truth() -> None:
    cfg = SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"))
    assert cfg.perception == "ground-truth"
    for bad in ({"perception": "lidar"}, {"camera_rate_hz": 0.0}, {"camera_skip_pixel": 0}):
        try:
            dataclasses.replace(cfg, **bad)
        except ValueError:
            continue
        raise AssertionError(f"{bad} accepted")


def test_small_flight_on_mapped_fields() -> None:
    cfg = SimConfig(
        load_formation("triangle-3"),
        load_world_spec("forest-small"),
        seed=1,
        v_max_m_s=1.0,
        perception="mapped",
        camera_rate_hz=10.0,
        camera_skip_pixel=4,
    )
    r = run_sim(cfg)
    assert r.success and r.collisions == 0
    assert r.min_obstacle_clearance_m > 0.2
    assert r.to_json()["config"]["perception"] == "mapped"


def test_camera_looks_where_the_trajectory_goes_next() -> None:
    # flying +x now, turning to +y: the camera already looks into the turn, not along the
    # velocity of the moment
    c = np.zeros((2, 6, 3))
    c[0, 0] = (0.0, 0.0, 1.0)  # 0.5 m/s along +x for 1 s
    c[0, 1] = (0.5, 0.0, 0.0)
    c[1, 0] = (0.5, 0.0, 1.0)  # then 0.5 m/s along +y
    c[1, 1] = (0.0, 0.5, 0.0)
    turn = Trajectory(0.0, c, np.array([1.0, 3.0]))
    t = 0.8
    p, v, _ = turn.state(t)
    look = look_velocity(turn, t, p)
    np.testing.assert_allclose(look, (turn.sample(t + LOOK_AHEAD_S) - p) / LOOK_AHEAD_S)
    yaw_now = heading_yaw(v, p, None, 0.0)
    yaw_look = heading_yaw(look, p, None, 0.0)
    assert yaw_look > yaw_now + 0.3
    # a hover looks towards the goal
    hover = Trajectory.hover(np.array([0.0, 0.0, 1.0]), 0.0, 5.0)
    g = np.array([0.0, -4.0, 1.0])
    assert heading_yaw(look_velocity(hover, 1.0, hover.sample(1.0)), hover.sample(1.0), g, 0.0) == (
        -np.pi / 2
    )


def test_a_drone_holding_still_short_of_its_goal_looks_around() -> None:
    p = np.zeros(3)
    behind = np.array([-3.0, 0.0, 0.0])  # the goal's direction is pi: the swing wraps
    yaws = [heading_yaw(np.zeros(3), p, behind, 0.0, t) for t in np.arange(0.0, 6.0, 0.05)]
    assert all(-np.pi <= y <= np.pi for y in yaws)
    off = [math.remainder(y - np.pi, 2 * np.pi) for y in yaws]
    assert max(off) == pytest.approx(SWEEP_RAD, abs=1e-3)
    assert min(off) == pytest.approx(-SWEEP_RAD, abs=1e-3)
    assert off[0] == pytest.approx(0.0, abs=1e-12)  # it starts facing the goal
    rate = np.max(np.abs(np.diff(off))) / 0.05
    assert rate <= 2 * np.pi / SWEEP_PERIOD_S * SWEEP_RAD + 1e-6 < np.radians(60.0)
    # moving, or at the goal: no swing
    assert heading_yaw(np.array([0.5, 0.0, 0.0]), p, behind, 0.0, 1.5) == 0.0
    assert heading_yaw(np.zeros(3), p, np.array([0.1, 0.0, 0.0]), 0.7, 1.5) == 0.7
    # the camera of a simulated drone that holds still sees the sides of where it waits
    w = World(np.array([[0.0, 2.5, 0.3, 0.0, 2.5]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    goal = np.array([5.0, 0.0, 1.0])
    still = SimulatedPerception(w, skip_pixel=4)
    for k in range(31):
        still.observe(k / 5.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), goal)
    probe = np.array([[0.0, 2.5 - 0.3 - 0.5, 1.0]])  # 90 deg left of the goal's direction
    d, _ = still.mapper.field().distance(probe)
    assert abs(d[0] - 0.5) < 0.15


def test_drone_camera_faces_where_it_flies() -> None:
    p = np.zeros(3)
    assert heading_yaw(np.array([0.0, 0.5, 0.0]), p, None, 0.0) == np.pi / 2
    assert heading_yaw(np.zeros(3), p, np.array([-3.0, 0.0, 0.0]), 0.0) == np.pi
    assert heading_yaw(np.zeros(3), p, np.array([0.1, 0.0, 0.0]), 0.7) == 0.7
    w = World(np.array([[3.0, 0.0, 0.3, 0.0, 2.5]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    eyes = SimulatedPerception(w, skip_pixel=4)
    for k in range(3):
        eyes.observe(k / 30, np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), None)
    probe = np.array([[3.0 - 0.3 - 0.5, 0.0, 1.0]])
    # the trunk where it is, in the distances to what the camera saw ...
    seen = EsdfBuilder().build(eyes.mapper.map, fill_cells=0)
    d_seen, _ = seen.distance(probe)
    assert abs(d_seen[0] - 0.5) < 0.1 and eyes.frames == 3
    # ... and no further in the field with the shadow fill (occluded_fill_m 0.2 m), which is
    # nearer where the camera's holes left cells in front of the trunk unobserved
    d, _ = eyes.mapper.field().distance(probe)
    assert d_seen[0] - 0.3 < d[0] <= d_seen[0] + 0.05
    # the planner reads the obstacles grown by the drone's radius (0.1 m)
    d_plan, _ = eyes.field().distance(probe)
    assert d_plan[0] == pytest.approx(d[0] - 0.1)


def test_bench_mapping_command_writes_the_json_keys(tmp_path: Path) -> None:
    out = tmp_path / "m.json"
    ply = tmp_path / "m.ply"
    res = CliRunner().invoke(
        bench_mapping,
        ["--world", "forest-small", "--max-frames", "60", "--json", str(out), "--ply", str(ply)],
    )
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    for key in ("ingest_ms", "esdf_ms", "render_ms"):
        assert data[key]["median"] > 0.0
    assert 0.0 <= data["esdf_error_m"]["p95"] < 1.0 and data["esdf_error_m"]["n"] > 1000
    assert set(data["targets"]) == {"ingest_ms.median", "esdf_ms.median", "esdf_error_m.p95"}
    assert data["scenario"]["frames"] == 60 and ply.stat().st_size > 0
    assert "ESDF error" in res.output


def test_perception_cli_options() -> None:
    seen: dict[str, object] = {}

    @click.command()
    @perception_options
    def cmd(perception: str, camera_rate_hz: float, camera_skip_pixel: int) -> None:
        seen.update(perception_overrides(perception, camera_rate_hz, camera_skip_pixel))

    r = CliRunner().invoke(cmd, [])
    assert r.exit_code == 0 and seen == {
        "perception": "ground-truth",
        "camera_rate_hz": 30.0,
        "camera_skip_pixel": 2,
    }
    r = CliRunner().invoke(
        cmd, ["--perception", "mapped", "--camera-rate", "10", "--skip-pixel", "4"]
    )
    assert r.exit_code == 0 and seen["perception"] == "mapped" and seen["camera_skip_pixel"] == 4
    cfg = SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"))
    assert dataclasses.replace(cfg, **seen).camera_rate_hz == 10.0
    assert CliRunner().invoke(cmd, ["--perception", "sonar"]).exit_code != 0
    assert CliRunner().invoke(cmd, ["--skip-pixel", "0"]).exit_code != 0
