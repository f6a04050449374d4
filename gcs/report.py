"""Flight report: the drones' MCAP flight records (``onboard.record``) into plots and a summary.

``swarm-gcs report FLIGHT_DIR_OR_FILES`` reads every ``*.mcap`` record given (a directory is
searched recursively), samples the drones' states on one 10 Hz time grid (global time, which the
records carry) and writes:

- ``top_view.png``: obstacles (when the world is known) and every drone's track;
- ``formation_error.png``: e_dist and e_sim of the assignment in force over time (when the
  assignments are known: ``mission.json``);
- ``clearance.png``: the smallest obstacle clearance and the smallest distance between two
  drones over time;
- ``setpoint_period.png``: histogram of the period of the setpoint stream of every drone;
- ``plan_time.png``: every replan's duration over time, by drone;
- ``summary.json`` and ``summary.txt``.

What the records do not hold comes from a ``mission.json`` beside them (written by ``swarm-gcs
demo``; optional): the world (name, seed, vehicle count and spawn spacing of the mock, to rebuild
exactly the mock's obstacles), the formation assignments (name, epoch, effective time, placed
points, slots), the goal, and the mock's own collision count. ``--world``/``--seed`` give the
world when there is no mission file.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.formations import formation_errors
from gcs.metrics import summary
from onboard.comm.latency import BIN_KEY, LatencyFigures
from onboard.record import FlightRecord, read_record

if TYPE_CHECKING:
    from onboard.world import World

MISSION_FILE = "mission.json"
SAMPLE_PERIOD_S = 0.1
STREAM_GAP_S = 0.5
"""Setpoint periods longer than this are pauses of the stream (not flying offboard), counted
apart from the period statistics."""
COLLISION_OBSTACLE_M = 0.2
COLLISION_DRONE_M = 0.4
GOAL_TOLERANCE_M = 0.5
GROUND_STATES = ("idle", "landed")
TRACKED_STATES = ("hover", "formation-flight")
"""Flight states in which the vehicle follows the service's own setpoints (the tracking error is
taken there: in take-off and landing the autopilot's own climb and descent lead them)."""
PEER_LATENCY_PREFIX = "bus.peer_latency."
"""The service's peer trajectory latency histogram in its ``/counters`` (publish -> the
planner's inbox, ``onboard.comm.latency``)."""


class ReportError(ValueError):
    """Nothing to report (no readable record) or a bad mission file."""


@dataclass(frozen=True, eq=False)
class DroneFlight:
    """One drone's record as arrays (times in global seconds, ENU metres)."""

    drone_id: int
    path: Path
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    flight_state: tuple[str, ...]
    setpoint_t: np.ndarray
    plan_t: np.ndarray
    plan_ms: np.ndarray
    plan_status: tuple[str, ...]
    plan_goal: np.ndarray
    transitions: tuple[tuple[float, str, str, str], ...]
    events: tuple[tuple[float, int, str], ...]
    counters: Mapping[str, float]
    read_error: str | None = None
    setpoint_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(len(setpoint_t), 3) the commanded positions (ENU), NaN where a message had none."""
    plan_cpu_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(len(plan_t),) the planning thread's CPU time of each plan (NaN: not recorded, e.g.
    a record of an older service); against ``plan_ms``, the time spent waiting."""
    plan_reason: tuple[str, ...] = ()
    """(len(plan_t),) each plan's message: its refused attempts and why (``plan_refusals``)."""

    @staticmethod
    def from_record(rec: FlightRecord) -> DroneFlight:
        states = rec.topics.get("/state", [])
        t = np.array([ts for ts, _ in states], dtype=np.float64)
        pos = _vecs([m.get("position_enu_m") for _, m in states])
        vel = _vecs([m.get("velocity_enu_m_s") for _, m in states])
        plans = rec.topics.get("/plan", [])
        counters = rec.messages("/counters")
        return DroneFlight(
            drone_id=_drone_id(rec),
            path=rec.path,
            t=t,
            pos=pos,
            vel=vel,
            flight_state=tuple(str(m.get("flight_state", "")) for _, m in states),
            setpoint_t=np.array(rec.times("/setpoint"), dtype=np.float64),
            plan_t=np.array([ts for ts, _ in plans], dtype=np.float64),
            plan_ms=np.array([_num(m.get("plan_ms")) for _, m in plans], dtype=np.float64),
            plan_status=tuple(str(m.get("status", "")) for _, m in plans),
            plan_goal=_vecs([m.get("goal_enu_m") for _, m in plans]),
            transitions=tuple(rec.transitions()),
            events=tuple(rec.events()),
            counters=dict(counters[-1].get("counters", {})) if counters else {},
            read_error=rec.metadata.get("read_error"),
            setpoint_pos=_vecs([m.get("position_enu_m") for m in rec.messages("/setpoint")]),
            plan_cpu_ms=np.array([_num(m.get("plan_cpu_ms")) for _, m in plans], dtype=np.float64),
            plan_reason=tuple(str(m.get("reason", "")) for _, m in plans),
        )

    def airborne(self) -> np.ndarray:
        """(T,) bool: the state samples where the drone is not on the ground."""
        return np.array([s not in GROUND_STATES for s in self.flight_state], dtype=bool)

    def position_at(self, times: np.ndarray) -> np.ndarray:
        """(len(times), 3) positions interpolated at ``times``; NaN outside the record."""
        out = np.full((times.shape[0], 3), np.nan)
        if self.t.shape[0] < 2:
            return out
        inside = (times >= self.t[0]) & (times <= self.t[-1])
        for k in range(3):
            out[inside, k] = np.interp(times[inside], self.t, self.pos[:, k])
        return out

    def airborne_at(self, times: np.ndarray) -> np.ndarray:
        """(len(times),) bool from the latest state sample at or before each time."""
        if self.t.shape[0] == 0:
            return np.zeros(times.shape[0], dtype=bool)
        k = np.searchsorted(self.t, times, side="right") - 1
        air = self.airborne()
        return (k >= 0) & (times <= self.t[-1]) & air[np.clip(k, 0, None)]

    def setpoint_at(self, times: np.ndarray) -> np.ndarray:
        """(len(times), 3) the commanded position interpolated at ``times``; NaN outside the
        stream and inside its pauses (setpoints more than ``STREAM_GAP_S`` apart)."""
        out = np.full((times.shape[0], 3), np.nan)
        ts = self.setpoint_t
        if ts.shape[0] < 2 or self.setpoint_pos.shape[0] != ts.shape[0]:
            return out
        k = np.searchsorted(ts, times, side="right")
        kk = np.clip(k, 1, ts.shape[0] - 1)
        short = ts[kk] - ts[kk - 1] <= STREAM_GAP_S
        at_one = (times == ts[kk - 1]) | (times == ts[kk])  # a setpoint's own time: known
        inside = (times >= ts[0]) & (times <= ts[-1]) & (short | at_one)
        for a in range(3):
            out[inside, a] = np.interp(times[inside], ts, self.setpoint_pos[:, a])
        return out

    def tracking_error_m(self) -> np.ndarray:
        """At every state sample in ``TRACKED_STATES`` inside the setpoint stream: the distance
        [m] from the vehicle's position to the position commanded then (how well the autopilot
        follows the plan; a close pass with a small tracking error was planned that close)."""
        tracked = np.array([s in TRACKED_STATES for s in self.flight_state], dtype=bool)
        if not tracked.any():
            return np.zeros(0)
        err = np.linalg.norm(self.pos[tracked] - self.setpoint_at(self.t[tracked]), axis=1)
        return err[np.isfinite(err)]

    def setpoint_periods(self) -> tuple[np.ndarray, int]:
        """(periods [s] while streaming, number of pauses longer than STREAM_GAP_S)."""
        d = np.diff(self.setpoint_t)
        return d[d <= STREAM_GAP_S], int(np.sum(d > STREAM_GAP_S))

    def flight_time_s(self) -> float | None:
        """From the first take-off transition (or airborne sample) to the last landing."""
        ups = [t for t, _s, d, _r in self.transitions if d == "takeoff"]
        downs = [t for t, _s, d, _r in self.transitions if d == "landed"]
        air = self.airborne()
        if ups:
            start = ups[0]
        elif air.any():
            start = float(self.t[np.argmax(air)])
        else:
            return None
        end = (
            downs[-1]
            if downs and downs[-1] > start
            else (float(self.t[-1]) if self.t.size else start)
        )
        return float(end - start)

    def peer_latency(self) -> LatencyFigures | None:
        """Peer trajectory latency, publish -> this service's planner inbox, from the start of
        the service to its last ``/counters`` (a service publishes no trajectory on the ground,
        so for its first flight: that flight); None in a record without it."""
        return LatencyFigures.from_counters(self.counters, PEER_LATENCY_PREFIX)

    def path_length_m(self) -> float:
        air = self.airborne()
        if air.sum() < 2:
            return 0.0
        p = self.pos[air]
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def _drone_id(rec: FlightRecord) -> int:
    """The record's drone id: its metadata, else its states (a record cut short by a crash has
    no summary section, so its metadata may be lost), else its file name (``droneI-...``)."""
    if rec.drone_id >= 0:
        return rec.drone_id
    for m in rec.messages("/state"):
        d = m.get("drone_id")
        if isinstance(d, int) and not isinstance(d, bool) and d >= 0:
            return d
    match = re.match(r"drone(\d+)", rec.path.name)
    if match:
        return int(match.group(1))
    raise ReportError(f"{rec.path}: cannot tell which drone it is from (no drone id)")


def _num(x: Any) -> float:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else math.nan


def _vecs(rows: Sequence[Any]) -> np.ndarray:
    out = np.full((len(rows), 3), np.nan)
    for i, r in enumerate(rows):
        if isinstance(r, (list, tuple)) and len(r) == 3:
            out[i] = [_num(v) for v in r]
    return out


# --- inputs ----------------------------------------------------------------------------------


def find_records(inputs: Sequence[str | Path]) -> list[Path]:
    """Every ``*.mcap`` among ``inputs`` (files, or directories searched recursively)."""
    out: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            out.extend(sorted(p.rglob("*.mcap")))
        elif p.is_file():
            out.append(p)
        else:
            raise ReportError(f"{p}: no such file or directory")
    if not out:
        raise ReportError(f"no flight record (*.mcap) in {[str(i) for i in inputs]}")
    return out


def find_mission(inputs: Sequence[str | Path]) -> Path | None:
    """The ``mission.json`` in (or beside) the first input that has one."""
    for item in inputs:
        p = Path(item)
        for d in (p, p.parent) if p.is_dir() else (p.parent, p.parent.parent):
            f = d / MISSION_FILE
            if f.is_file():
                return f
    return None


def read_flight_record(path: Path) -> FlightRecord:
    """``onboard.record.read_record``, falling back to reading the file as a stream when it has
    no usable summary section (a record cut short by a crash or a power loss): every message of
    the whole chunks before the cut is kept."""
    rec = read_record(path)
    if "read_error" not in rec.metadata or rec.topics:
        return rec
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    out = FlightRecord(path, metadata={"read_error": rec.metadata["read_error"]})
    with open(path, "rb") as f:
        try:
            for schema, channel, msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                if schema is not None:
                    out.schemas[channel.topic] = schema.name
                out.topics.setdefault(channel.topic, []).append(
                    (msg.log_time / 1e9, json.loads(msg.data))
                )
        except (McapError, EOFError, ValueError):
            pass  # the cut: what came before it is kept (read_error says the file is cut)
    for msgs in out.topics.values():
        msgs.sort(key=lambda x: x[0])
    with open(path, "rb") as f:
        try:
            for m in NonSeekingReader(f).iter_metadata():
                if m.name == "flight":
                    out.metadata.update(m.metadata)
        except (McapError, EOFError, ValueError):
            pass
    return out


def load_flights(paths: Sequence[Path]) -> list[DroneFlight]:
    """One :class:`DroneFlight` per record; several records of one drone are concatenated."""
    by_id: dict[int, list[DroneFlight]] = {}
    for p in paths:
        f = DroneFlight.from_record(read_flight_record(p))
        by_id.setdefault(f.drone_id, []).append(f)
    return [_concat(fs) for _, fs in sorted(by_id.items())]


def _concat(fs: list[DroneFlight]) -> DroneFlight:
    if len(fs) == 1:
        return fs[0]
    fs = sorted(fs, key=lambda f: f.t[0] if f.t.size else math.inf)

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(f, name) for f in fs])

    def tup(name: str) -> tuple[Any, ...]:
        return tuple(x for f in fs for x in getattr(f, name))

    errors = [f.read_error for f in fs if f.read_error]
    return DroneFlight(
        drone_id=fs[0].drone_id,
        path=fs[0].path,
        t=cat("t"),
        pos=cat("pos"),
        vel=cat("vel"),
        flight_state=tup("flight_state"),
        setpoint_t=cat("setpoint_t"),
        plan_t=cat("plan_t"),
        plan_ms=cat("plan_ms"),
        plan_status=tup("plan_status"),
        plan_goal=cat("plan_goal"),
        transitions=tup("transitions"),
        events=tup("events"),
        counters=fs[-1].counters,
        read_error="; ".join(errors) if errors else None,
        setpoint_pos=cat("setpoint_pos"),
        plan_cpu_ms=cat("plan_cpu_ms"),
        plan_reason=tup("plan_reason"),
    )


def load_mission(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ReportError(f"{path}: cannot read the mission file: {e}") from e
    if not isinstance(data, dict):
        raise ReportError(f"{path}: expected a JSON object")
    return data


def mission_world(mission: Mapping[str, Any]) -> World | None:
    """The mock's world of a mission (``world``, ``seed``, ``count``, ``spacing_m``)."""
    name = mission.get("world")
    if not name:
        return None
    from sitl_mock.cli import build_world

    w, _ = build_world(
        str(name),
        int(mission.get("count", 1)),
        int(mission.get("seed", 1)),
        float(mission.get("spacing_m", 1.5)),
    )
    return w


# --- analysis --------------------------------------------------------------------------------


@dataclass
class Analysis:
    """Everything the plots and the summary need."""

    flights: list[DroneFlight]
    world: World | None
    mission: dict[str, Any]
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    airborne: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    e_dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    e_sim: np.ndarray = field(default_factory=lambda: np.zeros(0))
    min_obstacle_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    min_pair_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    closest: list[dict[str, Any] | None] = field(default_factory=list)
    """Per drone, its closest approach to an obstacle while airborne (None without a world or
    a sample): ``t_s``, ``clearance_m``, the clearance of the position commanded then
    (``setpoint_clearance_m``, None outside the stream) and the ``tracking_error_m`` then."""

    @property
    def ids(self) -> list[int]:
        return [f.drone_id for f in self.flights]


def analyse(
    flights: list[DroneFlight], world: World | None = None, mission: Mapping[str, Any] | None = None
) -> Analysis:
    """Sample every drone on one grid and compute the formation error and clearances."""
    m = dict(mission or {})
    a = Analysis(flights, world, m)
    starts = [f.t[0] for f in flights if f.t.size]
    ends = [f.t[-1] for f in flights if f.t.size]
    if not starts:
        return a
    t = np.arange(min(starts), max(ends) + 1e-9, SAMPLE_PERIOD_S)
    n = len(flights)
    pos = np.stack([f.position_at(t) for f in flights], axis=1)  # (T, N, 3)
    air = np.stack([f.airborne_at(t) for f in flights], axis=1)  # (T, N)
    a.t, a.pos, a.airborne = t, pos, air
    # clearances: obstacles (no ground) for airborne drones; every pair with both positions
    obst = np.full(t.shape[0], np.nan)
    if world is not None:
        solid = world.without_ground()
        if solid.n_primitives:
            flat = pos.reshape(-1, 3)
            ok = np.isfinite(flat).all(axis=1) & air.reshape(-1)
            d = np.full(flat.shape[0], np.inf)
            if ok.any():
                d[ok] = solid.distance(flat[ok])[0]
            per = d.reshape(t.shape[0], n)
            a.closest = [_closest(f, t, per[:, i], pos[:, i], solid) for i, f in enumerate(flights)]
            d = per.min(axis=1)
            obst = np.where(np.isfinite(d), d, np.nan)
    a.min_obstacle_m = obst
    pair = np.full(t.shape[0], np.nan)
    if n >= 2:
        iu, ju = np.triu_indices(n, 1)
        dd = np.linalg.norm(pos[:, iu] - pos[:, ju], axis=2)  # (T, pairs), NaN where unknown
        both = air[:, iu] | air[:, ju]  # on the ground side by side is not a near miss
        dd = np.where(both, dd, np.nan)
        with np.errstate(invalid="ignore"):
            has = np.isfinite(dd).any(axis=1)
            pair[has] = np.nanmin(dd[has], axis=1)
    a.min_pair_m = pair
    # formation error of the assignment in force at each sample
    a.e_dist = np.full(t.shape[0], np.nan)
    a.e_sim = np.full(t.shape[0], np.nan)
    assignments = sorted(m.get("assignments", []), key=lambda x: float(x["effective_s"]))
    if assignments:
        index = {d: i for i, d in enumerate(a.ids)}
        eff = np.array([float(x["effective_s"]) for x in assignments])
        for k in range(t.shape[0]):
            j = int(np.searchsorted(eff, t[k], side="right")) - 1
            if j < 0:
                continue
            asg = assignments[j]
            slots = {int(d): int(s) for d, s in asg["slots"].items()}
            p = {
                d: pos[k, index[d]]
                for d in slots
                if d in index and air[k, index[d]] and np.isfinite(pos[k, index[d]]).all()
            }
            if len(p) != len(slots):
                continue
            e = formation_errors(p, slots, np.asarray(asg["points_m"], dtype=np.float64))
            if e is not None:
                a.e_dist[k], a.e_sim[k] = e
    return a


def _closest(
    f: DroneFlight, t: np.ndarray, clearance: np.ndarray, pos: np.ndarray, solid: World
) -> dict[str, Any] | None:
    """Drone ``f``'s closest approach on the grid ``t`` (its ``clearance`` per sample, inf
    where it is not airborne): time, clearance, the commanded position's clearance and the
    tracking error then."""
    if not np.isfinite(clearance).any():
        return None
    k = int(np.argmin(clearance))
    sp = f.setpoint_at(t[k : k + 1])[0]
    out: dict[str, Any] = {"t_s": float(t[k]), "clearance_m": float(clearance[k])}
    if np.isfinite(sp).all():
        out["setpoint_clearance_m"] = float(solid.distance(sp.reshape(1, 3))[0][0])
        out["tracking_error_m"] = float(np.linalg.norm(pos[k] - sp))
    else:
        out["setpoint_clearance_m"] = out["tracking_error_m"] = None
    return out


def _stat(values: np.ndarray | Sequence[float]) -> dict[str, float]:
    """``gcs.metrics.summary`` of the finite values, plus the 99th percentile."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    out = summary(v)
    out["p99"] = float(np.percentile(v, 99)) if v.size else math.nan
    return out


def _stat_ms(seconds: np.ndarray) -> dict[str, float]:
    """:func:`_stat` of durations in seconds, reported in milliseconds (count unchanged)."""
    return {k: v if k == "count" else v * 1000.0 for k, v in _stat(seconds).items()}


def _min(values: np.ndarray) -> float | None:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.min()) if v.size else None


def _goal_of(a: Analysis, f: DroneFlight) -> np.ndarray | None:
    """Where drone ``f`` should end: the mission goal plus its slot's offset in the last
    assignment, else its last planned goal."""
    g = a.mission.get("goal_m")
    assignments = a.mission.get("assignments") or []
    if g is not None and assignments and np.all(np.isfinite(np.asarray(g, dtype=np.float64))):
        last = max(assignments, key=lambda x: float(x["effective_s"]))
        slot = last["slots"].get(str(f.drone_id), last["slots"].get(f.drone_id))
        if slot is not None:
            pts = np.asarray(last["points_m"], dtype=np.float64)
            return np.asarray(g, dtype=np.float64) + pts[int(slot)] - pts.mean(axis=0)
    ok = np.isfinite(f.plan_goal).all(axis=1)
    return f.plan_goal[ok][-1] if ok.any() else None


def summarise(a: Analysis) -> dict[str, Any]:
    """The JSON summary of a flight."""
    drones: list[dict[str, Any]] = []
    all_periods: list[np.ndarray] = []
    all_tracking: list[np.ndarray] = []
    for i, f in enumerate(a.flights):
        periods, pauses = f.setpoint_periods()
        all_periods.append(periods)
        tracking = f.tracking_error_m()
        all_tracking.append(tracking)
        goal = _goal_of(a, f)
        end = a.pos[-1, i] if a.pos.shape[0] else np.full(3, np.nan)
        last_known = f.pos[np.isfinite(f.pos).all(axis=1)]
        end = last_known[-1] if last_known.shape[0] else end
        miss = None if goal is None else float(np.linalg.norm(end[:2] - goal[:2]))
        statuses: dict[str, int] = {}
        for s in f.plan_status:
            statuses[s] = statuses.get(s, 0) + 1
        ft = f.flight_time_s()
        speed = np.linalg.norm(f.vel, axis=1)
        drones.append(
            {
                "id": f.drone_id,
                "record": str(f.path),
                "read_error": f.read_error,
                "states": int(f.t.shape[0]),
                "final_state": f.flight_state[-1] if f.flight_state else None,
                "final_position_m": [float(x) for x in end],
                "goal_m": None if goal is None else [float(x) for x in goal],
                "goal_miss_xy_m": miss,
                "arrived": miss is not None and miss <= GOAL_TOLERANCE_M,
                "flight_time_s": ft,
                "path_length_m": f.path_length_m(),
                "max_speed_m_s": float(np.nanmax(speed)) if speed.size else None,
                "setpoints": int(f.setpoint_t.shape[0]),
                "setpoint_period_ms": _stat_ms(periods),
                "setpoint_pauses": pauses,
                "tracking_error_m": _stat(tracking),
                "closest_obstacle": a.closest[i] if i < len(a.closest) else None,
                "plan_ms": _stat(f.plan_ms),
                "plan_cpu_ms": _stat(f.plan_cpu_ms),
                "plan_statuses": statuses,
                "plan_refusals": plan_refusals([f]),
                "transitions": [list(x) for x in f.transitions],
                "warnings": [m for _, lvl, m in f.events if lvl >= 3][:20],
                "peer_latency_ms": _latency_ms(f.peer_latency()),
                # the latency histogram's bins stay in the record (peer_latency_ms sums them up)
                "counters": {k: v for k, v in f.counters.items() if f".{BIN_KEY}" not in k},
            }
        )
    periods = np.concatenate(all_periods) if all_periods else np.zeros(0)
    e_dist_s, e_sim_s = _stat(a.e_dist), _stat(a.e_sim)
    obst_min, pair_min = _min(a.min_obstacle_m), _min(a.min_pair_m)
    collisions = _record_collisions(a)
    flight_times = [float(d["flight_time_s"]) for d in drones if d["flight_time_s"] is not None]
    out: dict[str, Any] = {
        "drones": drones,
        "n_drones": len(drones),
        "world": a.mission.get("world"),
        "seed": a.mission.get("seed"),
        "duration_s": float(a.t[-1] - a.t[0]) if a.t.size else 0.0,
        "flight_time_s": max(flight_times) if flight_times else None,
        "arrived": bool(drones) and all(d["arrived"] for d in drones),
        "min_obstacle_clearance_m": obst_min,
        "min_drone_distance_m": pair_min,
        "collisions_from_records": collisions,
        "collisions_reported_by_mock": a.mission.get("sitl", {}).get("collisions"),
        "e_dist_m": e_dist_s,
        "e_sim": e_sim_s,
        "cluttered": _cluttered(a),
        "setpoint_period_ms": _stat_ms(periods),
        "tracking_error_m": _stat(np.concatenate(all_tracking) if all_tracking else []),
        "closest_obstacle": _closest_of_all(drones),
        "plan_ms": _stat(np.concatenate([f.plan_ms for f in a.flights]) if a.flights else []),
        "plan_cpu_ms": _stat(
            np.concatenate([f.plan_cpu_ms for f in a.flights]) if a.flights else []
        ),
        "peer_latency_ms": _latency_ms(
            LatencyFigures.merge(x for f in a.flights if (x := f.peer_latency()) is not None)
        ),
        "monitor": monitor_counts(a.flights),
        "depth_holds": depth_hold_counts(a.flights),
        # the drones' counts added up (each plan's message parsed once, above)
        "plan_refusals": {k: sum(d["plan_refusals"][k] for d in drones) for k in plan_refusals([])},
        "kernels_after_ready": _service_counter_sums(a.flights, ("kernels_after_ready",), "")[
            "kernels_after_ready"
        ],
        # stops the setpoint threads made: a safety monitor silent, a pause of the stream
        "stream_guard_stops": _service_counter_sums(
            a.flights, ("stream_guard_stops", "stream_gap_stops"), ""
        ),
        "assignments": [
            {k: x.get(k) for k in ("name", "epoch", "effective_s")}
            for x in a.mission.get("assignments", [])
        ],
    }
    return out


MONITOR_COUNTERS = ("monitor_brakes", "monitor_replans", "monitor_shallow_replans")
"""The services' safety monitor counters a flight's summary adds up (``monitor_counts``)."""


def monitor_counts(flights: Sequence[DroneFlight]) -> dict[str, int]:
    """What the drones' safety monitors did over the flight, summed from each record's last
    ``/counters``: braking stops (each a stop and a second's hover in flight), the monitor's
    looks (100 a second) that asked for a replan for a conflict, and the replans asked for an
    obstacle within the check's distance but not within the brake's slack
    (``planning.monitor_obstacle_slack_m``). A record of an older service
    without a counter adds 0 for it."""
    return _service_counter_sums(flights, MONITOR_COUNTERS, "monitor_")


def plan_refusals(flights: Sequence[DroneFlight]) -> dict[str, int]:
    """The planners' refused attempts over the flights, by why the safety check refused them
    (``gcs.fastsim.REFUSAL_KEYS``: an obstacle, a peer, unobserved space and of those its
    neighbourhood, the altitude band), with the plans flown anyway toward a conflict
    (``approach``) or as a last resort; read from each plan's message in the records, as the
    fast-time simulator counts them."""
    from gcs.fastsim import REFUSAL_KEYS, count_refusals

    counts = dict.fromkeys(REFUSAL_KEYS, 0)
    for f in flights:
        for message in f.plan_reason:
            count_refusals(message, counts)
    return counts


def _service_counter_sums(
    flights: Sequence[DroneFlight], names: Sequence[str], strip: str
) -> dict[str, int]:
    """Each of the services' counters ``names`` summed over the flights' last ``/counters``
    (0 for a record without it), keyed by its name less the prefix ``strip``."""
    return {
        k.removeprefix(strip): int(sum(f.counters.get(f"service.{k}", 0) for f in flights))
        for k in names
    }


DEPTH_COUNTERS = ("depth_holds", "map_lag_holds", "map_lag_rides", "frames_missed")
"""The services' depth reaction counters a flight's summary adds up (``depth_hold_counts``)."""


def depth_hold_counts(flights: Sequence[DroneFlight]) -> dict[str, int]:
    """The drones' holds for lost depth over the flight, summed from each record's last
    ``/counters``: ``holds`` (a stop and a hover until frames come again), of them
    ``map_lag_holds`` for a map more than ``map_lag_s`` behind a live camera, ``map_lag_rides``
    (the map more than the camera's ``timeout_s`` behind frames that kept arriving, which
    held no drone then: a starved mapping thread), ``frames_missed`` (frames the mapping
    never saw). An older service's record adds 0 for a counter it lacks."""
    return _service_counter_sums(flights, DEPTH_COUNTERS, "depth_")


def _closest_of_all(drones: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """The closest approach of the drone that came closest (with its id), None without one."""
    got = [(d["closest_obstacle"], d["id"]) for d in drones if d.get("closest_obstacle")]
    if not got:
        return None
    c, i = min(got, key=lambda x: x[0]["clearance_m"])
    return {"id": i, **c}


def _latency_ms(fig: LatencyFigures | None) -> dict[str, Any]:
    """median, p90, p99, max, mean (ms) and count of a latency histogram (None: count 0)."""
    return (fig or LatencyFigures()).summary_ms()


def _cluttered(a: Analysis) -> dict[str, Any] | None:
    """e_dist and e_sim while the swarm's centroid is inside the cluttered x span (how the
    fast-time simulator and the paper average them); None without a span."""
    span = a.mission.get("cluttered_x")
    if not span or not a.t.size:
        return None
    with np.errstate(invalid="ignore"):
        cx = np.nanmean(np.where(a.airborne, a.pos[:, :, 0], np.nan), axis=1)
    inside = (cx >= float(span[0])) & (cx <= float(span[1]))
    return {
        "x_span_m": [float(span[0]), float(span[1])],
        "e_dist_m": _stat(a.e_dist[inside]),
        "e_sim": _stat(a.e_sim[inside]),
    }


def _record_collisions(a: Analysis) -> dict[str, int]:
    """Collision starts seen in the recorded (estimated) positions at the sample rate."""

    def starts(hit: np.ndarray) -> int:
        h = np.nan_to_num(hit, nan=0).astype(bool)
        return int(np.sum(h[1:] & ~h[:-1]) + (h[0] if h.size else 0))

    with np.errstate(invalid="ignore"):
        obst = starts(a.min_obstacle_m < COLLISION_OBSTACLE_M) if a.t.size else 0
        pair = starts(a.min_pair_m < COLLISION_DRONE_M) if a.t.size else 0
    return {"obstacle": obst, "drone": pair}


def refusals_text(r: Mapping[str, int]) -> str:
    """``plan_refusals`` as one line."""
    return (
        f"refused plan attempts: {r.get('attempts', 0)} ({r.get('obstacle', 0)} for an obstacle, "
        f"{r.get('drone', 0)} for a peer, {r.get('unobserved', 0)} for unobserved space, "
        f"{r.get('unobserved_near', 0)} of them for its neighbourhood, {r.get('altitude', 0)} "
        f"for the altitude band, {r.get('other', 0)} other); flown anyway: "
        f"{r.get('approach', 0)} toward a conflict, {r.get('last_resort', 0)} as a last resort"
    )


def summary_text(s: Mapping[str, Any]) -> str:
    """The summary as lines for a terminal."""

    def f(x: Any, spec: str = ".2f") -> str:
        return (
            "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)
        )

    lines = [
        f"flight of {s['n_drones']} drone(s)"
        + (f" in {s['world']} (seed {s['seed']})" if s.get("world") else "")
        + f": {f(s['duration_s'], '.1f')} s recorded, flight time {f(s['flight_time_s'], '.1f')} s",
        f"arrived: {'yes' if s['arrived'] else 'NO'}; collisions reported by the mock: "
        f"{f(s.get('collisions_reported_by_mock'), 'd')}; in the records: "
        f"{s['collisions_from_records']['obstacle']} obstacle, "
        f"{s['collisions_from_records']['drone']} drone",
        f"min clearance: obstacles {f(s['min_obstacle_clearance_m'])} m, "
        f"drones {f(s['min_drone_distance_m'])} m",
        f"e_dist mean {f(s['e_dist_m']['mean'], '.3f')} m (max {f(s['e_dist_m']['max'], '.3f')}), "
        f"e_sim mean {f(s['e_sim']['mean'], '.4f')} (max {f(s['e_sim']['max'], '.4f')})"
        + (
            f"; in the cluttered span: e_dist {f(s['cluttered']['e_dist_m']['mean'], '.3f')} m, "
            f"e_sim {f(s['cluttered']['e_sim']['mean'], '.4f')}"
            if s.get("cluttered")
            else ""
        ),
        f"setpoint period: median {f(s['setpoint_period_ms']['median'], '.1f')} ms, "
        f"p99 {f(s['setpoint_period_ms']['p99'], '.1f')} ms, "
        f"max {f(s['setpoint_period_ms']['max'], '.1f')} ms "
        f"({s['setpoint_period_ms']['count']} periods)",
        f"tracking (position - setpoint): median {f(s['tracking_error_m']['median'], '.3f')} m, "
        f"p99 {f(s['tracking_error_m']['p99'], '.3f')} m, "
        f"max {f(s['tracking_error_m']['max'], '.3f')} m",
        f"plan time: median {f(s['plan_ms']['median'], '.0f')} ms, "
        f"p90 {f(s['plan_ms']['p90'], '.0f')} ms, max {f(s['plan_ms']['max'], '.0f')} ms "
        f"({s['plan_ms']['count']} plans)"
        + (
            f"; the planning thread's CPU: median {f(cpu['median'], '.1f')} ms, "
            f"p90 {f(cpu['p90'], '.1f')} ms (the rest is waiting for a core or the lock)"
            if (cpu := s.get("plan_cpu_ms")) and cpu.get("count")
            else ""
        ),
    ]
    c = s.get("closest_obstacle")
    if c:
        lines.append(
            f"closest to an obstacle: drone {c['id']}, {f(c['clearance_m'], '.3f')} m; "
            f"the position commanded then {f(c['setpoint_clearance_m'], '.3f')} m, "
            f"tracking error {f(c['tracking_error_m'], '.3f')} m"
        )
    ref = s.get("plan_refusals")
    if ref and ref.get("attempts"):
        lines.append(refusals_text(ref))
    peer = s.get("peer_latency_ms") or {}
    if peer.get("count"):
        lines.append(
            f"peer trajectory latency (publish -> the planner's inbox): median "
            f"{f(peer['median'])} ms, p99 {f(peer['p99'])} ms, max {f(peer['max'])} ms "
            f"({peer['count']} trajectories)"
        )
    for d in s["drones"]:
        lines.append(
            f"  drone {d['id']}: {d['final_state']}, goal miss {f(d['goal_miss_xy_m'])} m, "
            f"flight {f(d['flight_time_s'], '.1f')} s, path {f(d['path_length_m'], '.1f')} m, "
            f"setpoints {d['setpoints']} (pauses {d['setpoint_pauses']}), "
            f"plans {d['plan_statuses']}"
            + (f", READ ERROR {d['read_error']}" if d["read_error"] else "")
        )
    return "\n".join(lines)


# --- plots -----------------------------------------------------------------------------------


def _cmap(n: int) -> Any:
    import matplotlib.pyplot as plt

    return plt.get_cmap("tab10" if n <= 10 else "tab20")


def plot_top(a: Analysis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    from gcs.plots import _draw_world, _save

    fig, ax = plt.subplots(figsize=(12, 6), dpi=110)
    pts = [np.zeros((0, 2))]
    if a.world is not None:
        cl = a.mission.get("cluttered_x")
        span = (float(cl[0]), float(cl[1])) if cl else (0.0, 0.0)
        cyl = _draw_world(ax, a.world, span)
        if cyl.shape[0]:
            pts.append(cyl[:, :2])
    cmap = _cmap(len(a.flights))
    for i, f in enumerate(a.flights):
        c = cmap(i % cmap.N)
        ok = np.isfinite(f.pos).all(axis=1)
        p = f.pos[ok]
        if p.shape[0]:
            ax.plot(p[:, 0], p[:, 1], color=c, linewidth=1.2, label=f"drone {f.drone_id}")
            ax.plot(p[0, 0], p[0, 1], "o", color=c, markersize=5)
            ax.plot(p[-1, 0], p[-1, 1], "s", color=c, markersize=5)
            pts.append(p[:, :2])
        g = _goal_of(a, f)
        if g is not None and np.all(np.isfinite(g)):
            ax.plot(g[0], g[1], "x", color=c, markersize=7, mew=2)
            pts.append(g[None, :2])
    allp = np.concatenate(pts)
    allp = allp[np.isfinite(allp).all(axis=1)]
    if allp.shape[0]:
        ax.set_xlim(float(allp[:, 0].min()) - 1.5, float(allp[:, 0].max()) + 1.5)
        ax.set_ylim(float(allp[:, 1].min()) - 1.5, float(allp[:, 1].max()) + 1.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title("tracks (circle: first sample, square: last, cross: goal)", fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def _rel(a: Analysis) -> np.ndarray:
    return a.t - (a.t[0] if a.t.size else 0.0)


def plot_formation_error(a: Analysis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    from gcs.plots import _save

    fig, ax = plt.subplots(figsize=(10, 4), dpi=110)
    t = _rel(a)
    ax.plot(t, a.e_dist, color="tab:blue", label="e_dist [m]")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("e_dist [m]", color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(t, a.e_sim, color="tab:orange", label="e_sim")
    ax2.set_ylabel("e_sim", color="tab:orange")
    for x in a.mission.get("assignments", []):
        if a.t.size:
            ax.axvline(float(x["effective_s"]) - a.t[0], color="0.5", linestyle=":")
            ax.annotate(str(x.get("name", "")), (float(x["effective_s"]) - a.t[0], 0), fontsize=7)
    if not np.isfinite(a.e_dist).any():
        ax.set_title("formation error: no assignment known (no mission.json)", fontsize=9)
    else:
        ax.set_title("formation error of the assignment in force (dotted: switches)", fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    return _save(fig, path)


def plot_clearance(a: Analysis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    from gcs.plots import _save

    fig, ax = plt.subplots(figsize=(10, 4), dpi=110)
    t = _rel(a)
    ax.plot(t, a.min_obstacle_m, label="nearest obstacle (any drone)")
    ax.plot(t, a.min_pair_m, label="nearest pair of drones")
    ax.axhline(COLLISION_OBSTACLE_M, color="tab:red", linestyle="--", linewidth=0.8,
               label=f"obstacle collision {COLLISION_OBSTACLE_M} m")  # fmt: skip
    ax.axhline(COLLISION_DRONE_M, color="tab:purple", linestyle="--", linewidth=0.8,
               label=f"drone collision {COLLISION_DRONE_M} m")  # fmt: skip
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("distance [m]")
    ax.set_title("clearances (airborne drones)", fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_setpoint_period(a: Analysis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    from gcs.plots import _save

    fig, ax = plt.subplots(figsize=(8, 4), dpi=110)
    periods = [f.setpoint_periods()[0] * 1000.0 for f in a.flights]
    allp = np.concatenate(periods) if periods else np.zeros(0)
    if allp.size:
        bins = np.linspace(0.0, max(60.0, float(allp.max()) * 1.05), 60).tolist()
        ax.hist(allp, bins=bins, color="tab:blue", alpha=0.8)
        ax.set_yscale("log")
    ax.set_xlabel("setpoint period [ms]")
    ax.set_ylabel("count")
    ax.set_title(f"setpoint stream, {allp.size} periods of {len(a.flights)} drone(s)", fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    return _save(fig, path)


def plot_plan_time(a: Analysis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    from gcs.plots import _save

    fig, ax = plt.subplots(figsize=(10, 4), dpi=110)
    t0 = a.t[0] if a.t.size else 0.0
    cmap = _cmap(len(a.flights))
    for i, f in enumerate(a.flights):
        if f.plan_t.size:
            ax.plot(f.plan_t - t0, f.plan_ms, ".", color=cmap(i % cmap.N), markersize=4,
                    label=f"drone {f.drone_id}")  # fmt: skip
        if f.plan_cpu_ms.size == f.plan_t.size and np.isfinite(f.plan_cpu_ms).any():
            ax.plot(f.plan_t - t0, f.plan_cpu_ms, "x", color=cmap(i % cmap.N), markersize=3,
                    alpha=0.6)  # fmt: skip
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("plan time [ms]")
    ax.set_title(
        "replan durations (dots: wall time; crosses: the planning thread's CPU)", fontsize=9
    )
    ax.grid(True, linewidth=0.3, alpha=0.5)
    if a.flights:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path)


PLOTS = {
    "top_view.png": plot_top,
    "formation_error.png": plot_formation_error,
    "clearance.png": plot_clearance,
    "setpoint_period.png": plot_setpoint_period,
    "plan_time.png": plot_plan_time,
}


def write_report(
    inputs: Sequence[str | Path],
    out_dir: str | Path | None = None,
    *,
    world: str | None = None,
    seed: int | None = None,
    mission: Mapping[str, Any] | None = None,
    plots: bool = True,
) -> tuple[dict[str, Any], Path]:
    """Read the records, write the plots (unless ``plots`` is False) and
    ``summary.json``/``summary.txt`` into ``out_dir`` (default: ``report/`` in the first input
    directory); returns (summary, out_dir). ``world``/``seed`` override the mission file's."""
    paths = find_records(inputs)
    m = dict(mission) if mission is not None else load_mission(find_mission(inputs))
    if world is not None:
        m["world"] = world
        m.setdefault("count", None)
    if seed is not None:
        m["seed"] = seed
    flights = load_flights(paths)
    if m.get("world") and not m.get("count"):
        m["count"] = len(flights)
    w = mission_world(m) if m.get("world") else None
    if w is not None and "cluttered_x" not in m:
        from onboard.config import load_world_spec

        m["cluttered_x"] = list(load_world_spec(str(m["world"])).cluttered_x)
    a = analyse(flights, w, m)
    s = summarise(a)
    first = Path(inputs[0])
    out = (
        Path(out_dir)
        if out_dir is not None
        else (first if first.is_dir() else first.parent) / "report"
    )
    out.mkdir(parents=True, exist_ok=True)
    s["plots"] = [str(fn(a, out / name)) for name, fn in PLOTS.items()] if plots else []
    (out / "summary.json").write_text(json.dumps(_clean(s), indent=2) + "\n", encoding="utf-8")
    (out / "summary.txt").write_text(summary_text(s) + "\n", encoding="utf-8")
    return s, out


def _clean(x: Any) -> Any:
    """JSON-safe: NaN and infinities as null."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _clean(x.item())
    return x


def report_command() -> Any:
    """The ``report`` click command (built lazily so that importing this module stays light)."""
    import click

    @click.command("report")
    @click.argument("flight", nargs=-1, required=True, type=click.Path(path_type=Path))
    @click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
                  default=None, help="Output directory [default: FLIGHT_DIR/report].")  # fmt: skip
    @click.option("--world", default=None, help="World of the flight (name or file), if no "
                  "mission.json says it.")  # fmt: skip
    @click.option("--seed", type=int, default=None, help="Seed of the world.")
    @click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
    @click.option("--no-plots", is_flag=True, help="Only the summary.")
    def report(
        flight: tuple[Path, ...], out_dir: Path | None, world: str | None, seed: int | None,
        as_json: bool, no_plots: bool,
    ) -> None:  # fmt: skip
        """Plots and a summary of a flight from the drones' MCAP records (FLIGHT: record files
        or directories holding them)."""
        try:
            s, out = write_report(flight, out_dir, world=world, seed=seed, plots=not no_plots)
        except ReportError as e:
            raise click.ClickException(str(e)) from e
        if as_json:
            click.echo(json.dumps(_clean(s)))
        else:
            click.echo(summary_text(s))
            click.echo(f"report written to {out}")

    return report


report = report_command()
