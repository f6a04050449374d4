"""`swarm-gcs bench map-replay`: a drone's recorded poses replayed through the simulated camera
and the service's map, compared with the truth. The geometry below is built so that the answer
is known: a drone that flies at a trunk with its camera on it maps it to within a cell; one that
backs into it, its camera looking away, has nothing of it in its map."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from gcs.cli import main
from gcs.map_replay import MapReplayError, ReplayFrame, replay_flight, replay_poses, summarise
from onboard.record import FlightRecorder
from onboard.service.config import OnboardConfig, load_onboard_config
from onboard.world import World

TRUNK = (3.0, 0.0, 0.2)  # x, y, radius
RATE_HZ = 3.0  # the demo's camera
FORWARD = (1.0, 0.0, 0.0, 0.0)  # FLU body = ENU: the camera looks along +x
BACKWARD = (0.0, 0.0, 0.0, 1.0)  # yawed 180 deg: the camera looks along -x


def _cfg() -> OnboardConfig:
    return load_onboard_config(overrides={"depth": {"rate_hz": RATE_HZ}})


def _poses(q: tuple[float, ...]) -> list[tuple[float, list[float], tuple[float, ...]]]:
    """Along y = 0 at 1 m height, 0.5 m/s from x = 0 to 2.6 (0.2 m from the trunk's surface), a
    pose every 0.1 s, with the attitude ``q``."""
    return [(0.1 * k, [0.05 * k, 0.0, 1.0], q) for k in range(53)]


def _replay(q: tuple[float, ...]) -> list[ReplayFrame]:
    x, y, r = TRUNK
    world = World(np.array([[x, y, r, 0.0, 4.0]]), np.zeros((0, 7)), np.zeros((0, 6)), None)
    cfg = _cfg()
    return replay_poses(_poses(q), world, cfg.map_params, cfg.depth.step, RATE_HZ)


def test_a_trunk_in_view_is_mapped_to_within_a_cell() -> None:
    frames = _replay(FORWARD)
    # a frame at the first pose at least 1 / rate after the last: every 4th of 0.1 s
    assert [f.t_s for f in frames] == pytest.approx([0.4 * k for k in range(14)])
    for f in frames:
        assert f.true_m == pytest.approx(TRUNK[0] - TRUNK[2] - f.position_enu_m[0], abs=1e-9)
    near = [f for f in frames if f.true_m <= 2.0]
    assert len(near) >= 8
    for f in near:
        assert abs(f.overestimate_m) < 0.03
        assert f.nearest_state == "occupied" and f.off_axis_deg < 1.0
    s = summarise(frames, inflation_m=0.1, near_m=2.0)
    assert s["near_frames"] == len(near) and s["overestimate_over_inflation"] == 0
    assert s["max_overestimate_m"] == pytest.approx(max(f.overestimate_m for f in near))


def test_a_trunk_behind_the_camera_is_not_in_the_map() -> None:
    frames = _replay(BACKWARD)
    near = [f for f in frames if f.true_m <= 1.0]
    assert len(near) >= 4
    for f in near:
        assert f.nearest_state == "unknown" and f.off_axis_deg > 179.0
        assert f.overestimate_m > 1.0  # nothing mapped near it
    s = summarise(frames, inflation_m=0.1, near_m=1.0)
    assert s["overestimate_over_inflation"] == len(near)
    assert s["over_inflation_nearest_state"] == {"unknown": len(near), "free": 0, "occupied": 0}
    worst = max(near, key=lambda f: f.overestimate_m)
    assert s["max_overestimate_t_s"] == worst.t_s


def test_no_frame_and_no_near_frame_give_empty_figures() -> None:
    s = summarise([], inflation_m=0.1, near_m=1.0)
    assert s["frames"] == 0 and s["max_overestimate_m"] is None
    with pytest.raises(ValueError, match="rate_hz"):
        replay_poses([], None, None, 3, 0.0)


def _write_flight(d: Path, drone: int, n: int = 12) -> None:
    """One drone's record (states with poses every 0.1 s, 1 m over the spawn line of
    forest-small, flying +x) and the mission file, as `swarm-gcs demo` leaves them."""
    mission: dict[str, Any] = {
        "world": "forest-small",
        "seed": 3,
        "count": 3,
        "spacing_m": 1.5,
        "assignments": [{"effective_s": 100.0}, {"effective_s": 110.0}],
    }
    (d / "mission.json").write_text(json.dumps(mission))
    with FlightRecorder(d / f"drone{drone}.mcap", drone, {"swarm": "t"}) as rec:
        for k in range(n):
            rec.state(
                100.0 + 0.1 * k,
                flight_state="formation-flight",
                position_enu_m=[-6.0 + 0.05 * k, 0.0, 1.0],
                velocity_enu_m_s=[0.5, 0.0, 0.0],
                quaternion_wxyz=[1.0, 0.0, 0.0, 0.0],
            )


def test_a_flight_directory_is_replayed_and_bad_requests_are_refused(tmp_path: Path) -> None:
    _write_flight(tmp_path, drone=1)
    frames, meta = replay_flight(tmp_path, 1)
    # the default configuration's camera (no onboard.yaml beside the record): a frame a pose
    rate = load_onboard_config().depth.rate_hz
    assert meta["rate_hz"] == rate and rate >= 10.0
    assert len(frames) == 12 and meta["assignments_effective_s"] == [100.0, 110.0]
    assert all(math.isfinite(f.map_m) and math.isfinite(f.true_m) for f in frames)
    whole = frames
    frames, meta = replay_flight(tmp_path, 1, t_from_s=0.5)  # after the first assignment
    assert meta["t0_s"] == 100.0
    assert [f.t_s for f in frames] == pytest.approx([100.5 + 0.1 * k for k in range(7)])
    # the window's frames are the whole replay's: its map was built from the first pose on
    assert frames == whole[5:]
    frames, _ = replay_flight(tmp_path, 1, t_from_s=0.25, t_to_s=0.55)
    assert frames == whole[3:6]
    with pytest.raises(MapReplayError, match="no record of drone 4"):
        replay_flight(tmp_path, 4)
    with pytest.raises(MapReplayError, match="no pose"):
        replay_flight(tmp_path, 1, t_from_s=100.0)
    (tmp_path / "mission.json").write_text("{}")
    with pytest.raises(MapReplayError, match="no mission.json with the world"):
        replay_flight(tmp_path, 1)


def test_the_command_prints_the_figures_and_writes_json(tmp_path: Path) -> None:
    _write_flight(tmp_path, drone=0)
    out = tmp_path / "out" / "replay.json"
    r = CliRunner().invoke(
        main, ["bench", "map-replay", str(tmp_path), "--drone", "0", "--json", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert "drone 0: 12 frames" in r.output and "assignments at 0.0, 10.0 s" in r.output
    data = json.loads(out.read_text())
    assert len(data["frames"]) == 12 and data["t0_s"] == 100.0
    assert data["summary"]["frames"] == 12
    r = CliRunner().invoke(main, ["bench", "map-replay", str(tmp_path), "--drone", "5"])
    assert r.exit_code != 0 and "no record of drone 5" in r.output
    # a directory without records: a one-line error, not a traceback
    empty = tmp_path / "empty"
    empty.mkdir()
    r = CliRunner().invoke(main, ["bench", "map-replay", str(empty), "--drone", "0"])
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output
    assert r.output.startswith("Error: ")


def test_a_map_parameter_is_tried_on_the_recorded_poses(tmp_path: Path) -> None:
    _write_flight(tmp_path, drone=0)
    out = tmp_path / "near.json"
    args = ["bench", "map-replay", str(tmp_path), "--drone", "0", "--json", str(out)]
    r = CliRunner().invoke(main, [*args, "--set-onboard", "mapping.occupancy.occluded_fill_m=0.2"])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["occluded_fill_m"] == 0.2
    bad = CliRunner().invoke(
        main, [*args, "--set-onboard", "mapping.occupancy.occluded_fill_m=2.0"]
    )
    assert bad.exit_code != 0 and "occluded_fill_m" in bad.output
