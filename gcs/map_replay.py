"""Replay a drone's flight through its map: where the map said an obstacle was farther than it is.

``swarm-gcs bench map-replay FLIGHT_DIR --drone N`` reads one drone's recorded poses (``/pose``
in its MCAP record), renders the mock's simulated depth camera (``sitl_mock.truth
.simulated_d435``) from the camera pose of each at the service's frame rate, and feeds a fresh
mapper with the service's own map parameters (``onboard.yaml`` beside the record, else the
drone's default configuration). After each frame it compares the map's distance at the drone
(``LocalMapper.field``, before the planner's inflation) with the exact distance to the mission's
world, and says where the nearest true surface point lies in the map (unknown, free or
occupied) and how far off the camera's axis it is.

What it is for: a real-stack flight is not repeatable (its timing decides its path), but its
record is. A close pass to a trunk found in a real-stack flight can be taken apart here, frame
by frame and the same every time, and a change of the map's parameters or the camera's yaw tried
on the very poses that flew it. The frames are rendered from the recorded poses at the nominal
rate, not at the instants the service received them, and without the mock's timing: the map is
the one such a camera would build along that path, not a copy of the service's.

The planner plans on the map's distance less ``inflation_m`` (``LocalMapper.planning_field``):
where the map's distance exceeds the truth by more than that, a plan the check accepts at its
distance may come closer to the true surface than the check's distance
(``overestimate_over_inflation``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

STATE_NAMES = {-1: "unknown", 0: "free", 1: "occupied"}
INSIDE_M = 0.03
"""The nearest true surface point's cell is read this far inside the surface (a point on the
surface lies on a cell boundary as often as not)."""


class MapReplayError(ValueError):
    """Nothing to replay: no record of the drone, no pose in the window, no world."""


@dataclass(frozen=True)
class ReplayFrame:
    """One replayed frame: the map against the truth at the drone's position."""

    t_s: float
    """Global time of the pose the frame was rendered from."""
    position_enu_m: tuple[float, float, float]
    map_m: float
    """The map's distance at the drone (no inflation)."""
    true_m: float
    """The exact distance to the world's surfaces (no ground)."""
    nearest_state: str
    """The map's cell just inside the nearest true surface point: unknown, free or occupied."""
    off_axis_deg: float
    """Angle between the camera's axis and the direction from the camera to that point."""

    @property
    def overestimate_m(self) -> float:
        return self.map_m - self.true_m


def replay_poses(
    poses: Sequence[tuple[float, Sequence[float], Sequence[float]]],
    world: Any,
    occ: Any,
    step: int,
    rate_hz: float,
    camera: Any = None,
) -> list[ReplayFrame]:
    """Replay ``poses`` (global time, body ENU position, FLU body -> ENU attitude quaternion
    w, x, y, z), in time order, one frame at most every ``1 / rate_hz`` s, through ``camera``
    (default: the mock's simulated D435 of ``world``, every ``step``-th pixel) into a fresh
    ``LocalMapper(occ)``. ``world``: an ``onboard.world.World``; its ground is left out of the
    truth (the map's window stops above it)."""
    from onboard.mapping.mapper import LocalMapper
    from onboard.sensors.mount import camera_pose
    from sitl_mock.truth import simulated_d435

    if not rate_hz > 0.0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    solid = world.without_ground()
    cam = camera if camera is not None else simulated_d435(world, seed=0, step=step)
    mapper = LocalMapper(occ)
    out: list[ReplayFrame] = []
    last = -math.inf
    for t, p, q in poses:
        if t - last < 1.0 / rate_hz - 1e-9:
            continue
        last = t
        body = np.asarray(p, dtype=np.float64).reshape(3)
        pos, rot = camera_pose(body, np.asarray(q, dtype=np.float64))
        mapper.recenter(pos)
        res = mapper.ingest(cam.capture(pos, rot, t), step=step)
        if not res.accepted:
            raise MapReplayError(f"frame at {t:.2f} s refused by the mapper: {res.reason}")
        d_map = float(mapper.field().distance(body.reshape(1, 3))[0][0])
        d, g = solid.distance(body.reshape(1, 3))
        nearest = body - float(d[0]) * g[0]
        state = int(mapper.map.state_at((nearest - INSIDE_M * g[0]).reshape(1, 3))[0])
        to = nearest - pos
        n = float(np.linalg.norm(to))
        cos = float(to @ rot[:, 2]) / n if n > 1e-9 else 1.0
        out.append(
            ReplayFrame(
                t_s=float(t),
                position_enu_m=(float(body[0]), float(body[1]), float(body[2])),
                map_m=d_map,
                true_m=float(d[0]),
                nearest_state=STATE_NAMES[state],
                off_axis_deg=math.degrees(math.acos(max(-1.0, min(1.0, cos)))),
            )
        )
    return out


def summarise(frames: Sequence[ReplayFrame], inflation_m: float, near_m: float) -> dict[str, Any]:
    """Figures of a replay: over the frames where the drone was within ``near_m`` of a true
    surface (where an overestimate matters), the largest overestimate and when, how many
    exceed ``inflation_m``, and where those frames' nearest true surface lay in the map."""
    near = [f for f in frames if f.true_m <= near_m]
    over = [f for f in near if f.overestimate_m > inflation_m]
    worst = max(near, key=lambda f: f.overestimate_m, default=None)
    states = {s: sum(1 for f in over if f.nearest_state == s) for s in STATE_NAMES.values()}
    return {
        "frames": len(frames),
        "near_frames": len(near),
        "near_m": near_m,
        "inflation_m": inflation_m,
        "max_overestimate_m": None if worst is None else worst.overestimate_m,
        "max_overestimate_t_s": None if worst is None else worst.t_s,
        "overestimate_over_inflation": len(over),
        "over_inflation_nearest_state": states,
    }


def _record_poses(rec: Any) -> list[tuple[float, list[float], list[float]]]:
    """(time, position, quaternion w, x, y, z) of each ``/pose`` of a ``FlightRecord``."""
    out = []
    for t, m in rec.topics.get("/pose", []):
        pose = m.get("pose", {})
        p, q = pose.get("position", {}), pose.get("orientation", {})
        try:
            out.append(
                (
                    float(t),
                    [float(p["x"]), float(p["y"]), float(p["z"])],
                    [float(q["w"]), float(q["x"]), float(q["y"]), float(q["z"])],
                )
            )
        except (KeyError, TypeError, ValueError):
            continue  # a pose without its fields: nothing to render
    return out


def replay_flight(
    flight: Path,
    drone_id: int,
    t_from_s: float | None = None,
    t_to_s: float | None = None,
    overrides: dict[str, Any] | None = None,
) -> tuple[list[ReplayFrame], dict[str, Any]]:
    """``replay_poses`` of drone ``drone_id``'s record in ``flight`` (a flight directory of
    ``swarm-gcs demo``: the records, ``mission.json``, ``onboard.yaml``), the frames between
    ``t_from_s`` and ``t_to_s`` seconds after the mission's first assignment (``t0_s`` in what
    it returns; the record's own times without one; default: the whole record; the map is
    built from the record's first pose on, as the drone's was, not from an empty one at
    ``t_from_s``, which would read the surfaces seen before as unknown), with the drone's
    configuration changed by ``overrides`` (nested, as ``--set-onboard`` gives them: a map
    parameter tried on the poses that flew). Also returns what it replayed with (the mission's
    changes of formation, the map's parameters)."""
    from gcs.report import find_mission, find_records, load_mission, mission_world
    from onboard.record import read_record
    from onboard.service.config import load_onboard_config

    mission = load_mission(find_mission([flight]))
    world = mission_world(mission)
    if world is None:
        raise MapReplayError(f"{flight}: no mission.json with the world")
    record = next(
        (r for r in map(read_record, find_records([flight])) if r.drone_id == drone_id), None
    )
    if record is None:
        raise MapReplayError(f"{flight}: no record of drone {drone_id}")
    cfg_file = Path(flight) / "onboard.yaml"
    cfg = load_onboard_config(
        cfg_file if cfg_file.is_file() else None, drone_id=drone_id, overrides=overrides
    )
    changes = sorted(float(a["effective_s"]) for a in mission.get("assignments", []))
    t0 = changes[0] if changes else 0.0
    poses = [x for x in _record_poses(record) if t_to_s is None or x[0] <= t0 + t_to_s]
    if t_from_s is not None and poses and poses[-1][0] < t0 + t_from_s:
        poses = []
    if not poses:
        raise MapReplayError(f"{record.path}: no pose between the times asked")
    occ = cfg.map_params
    frames = replay_poses(poses, world, occ, cfg.depth.step, cfg.depth.rate_hz)
    if t_from_s is not None:
        frames = [f for f in frames if f.t_s >= t0 + t_from_s]
        if not frames:
            raise MapReplayError(f"{record.path}: no frame between the times asked")
    meta = {
        "record": str(record.path),
        "drone": drone_id,
        "assignments_effective_s": changes,
        "t0_s": t0,
        "rate_hz": cfg.depth.rate_hz,
        "step": cfg.depth.step,
        "inflation_m": occ.inflation_m,
        "check_obstacle_m": cfg.planner.check_obstacle_m,
        "occluded_fill_m": occ.occluded_fill_m,
    }
    return frames, meta


@click.command("map-replay")
@click.argument("flight", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--drone", "drone_id", type=int, required=True, help="The drone's id.")
@click.option(
    "--from",
    "t_from",
    type=float,
    default=None,
    help="Report from here, seconds after the first assignment (the map is built from the start).",
)
@click.option("--to", "t_to", type=float, default=None, help="End, seconds after it.")
@click.option(
    "--near",
    "near_m",
    type=float,
    default=1.0,
    show_default=True,
    help="Judge the frames where the drone was within this of a true surface [m].",
)
@click.option(
    "--show-over",
    type=float,
    default=None,
    help="List the frames whose overestimate exceeds this [m] (default: the map's inflation).",
)
@click.option(
    "--set-onboard",
    "onboard_sets",
    multiple=True,
    metavar="KEY=VALUE",
    help="Change the drone's configuration, e.g. mapping.occupancy.occluded_fill_m=0.2.",
)
@click.option("--json", "json_path", type=click.Path(path_type=Path), default=None)
def bench_map_replay(
    flight: Path,
    drone_id: int,
    t_from: float | None,
    t_to: float | None,
    near_m: float,
    show_over: float | None,
    onboard_sets: tuple[str, ...],
    json_path: Path | None,
) -> None:
    """Replay a flight's poses through the drone's map and compare it with the truth.

    FLIGHT is a flight directory of `swarm-gcs demo` (`bench demo` keeps one per seed). Times
    are seconds after the mission's first assignment (the goal's); the formation changes are
    printed beside them."""
    import json

    from gcs.report import ReportError
    from onboard.config import ConfigError, parse_overrides

    try:
        frames, meta = replay_flight(flight, drone_id, t_from, t_to, parse_overrides(onboard_sets))
    except (MapReplayError, ReportError, ConfigError) as e:
        raise click.ClickException(str(e)) from e
    t0, eff = float(meta["t0_s"]), meta["assignments_effective_s"]
    infl = float(meta["inflation_m"])
    s = summarise(frames, infl, near_m)
    limit = infl if show_over is None else show_over
    click.echo(
        f"drone {drone_id}: {s['frames']} frames at {meta['rate_hz']:g}/s; formation "
        f"assignments at {', '.join(f'{x - t0:.1f}' for x in eff)} s"
    )
    for f in frames:
        if f.true_m <= near_m and f.overestimate_m > limit:
            click.echo(
                f"  {f.t_s - t0:7.2f} s  map {f.map_m:.3f} m  true {f.true_m:.3f} m  "
                f"over {f.overestimate_m:+.3f} m  nearest surface {f.nearest_state}, "
                f"{f.off_axis_deg:.0f} deg off the camera's axis"
            )
    if s["max_overestimate_m"] is None:
        click.echo(f"never within {near_m:g} m of a surface")
    else:
        click.echo(
            f"largest overestimate within {near_m:g} m of a surface: "
            f"{s['max_overestimate_m']:+.3f} m at {s['max_overestimate_t_s'] - t0:.2f} s; "
            f"{s['overestimate_over_inflation']} of {s['near_frames']} frames over the "
            f"inflation ({infl:g} m), their nearest surface {s['over_inflation_nearest_state']}"
        )
    if json_path is not None:
        out = {
            **meta,
            "summary": s,
            "frames": [{**asdict(f), "overestimate_m": f.overestimate_m} for f in frames],
        }
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(out, indent=1), encoding="utf-8")
        click.echo(f"wrote {json_path}")
