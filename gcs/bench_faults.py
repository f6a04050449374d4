"""Fault-survival benchmark (``swarm-gcs bench faults``, issue #12): fast-time flights with
random faults.

Each trial flies the hexagon-7 through a forest (forest-sparse and forest-medium in turn, world
seeded by the trial) in ``gcs.fastsim`` with faults drawn from the trial's seed, alone or
combined:

- a **killed** drone (its onboard process dies: it publishes nothing from then on and its
  vehicle flies PX4's offboard-loss failsafe: the last setpoint for COM_OF_LOSS_T, then a
  braking stop to a hold, ``SimConfig.kill_model`` 'px4'; ``--kill-model instant`` stops it
  dead instead);
- a **stuck** drone (its vehicle stops and hovers where it is, still publishing that hover);
- **bus faults** on every trajectory message: 20 % loss, a uniform delay up to 300 ms,
  duplication and reordering (each present or not).

Every drone whose process runs also broadcasts its state at 10 Hz through the same faults, and
checks the plan it flies against its peers between replans as the flight service's monitor
does (``--monitor-hz``, 100 by default; 0 leaves it out).
A peer heard of nothing newer (trajectory or state) for ``SimConfig.peer_silence_s`` (0.5 s) is
quiet: its peers avoid it both along its last trajectory and at hovers 0.25 m apart where it
may have stopped, and replan at once if those lie on their path; once unheard longer than its
recent quiet spells allow (at most ``onboard.agent.PEER_SILENCE_MAX_S``, 1.5 s) it is silent
and leaves the formation term (``DroneAgent``); a peer whose message's validity (3 s, the
service's ``reactions.peer_lost.validity_s``) has passed, or whose plan started longer ago than
that (a stuck drone re-announcing its hover), leaves the formation term too; a silent or
expired peer is still avoided for 10 s (``avoid_for_s``).

Per trial and in total: collisions (every drone, the hovering faulty ones included: they are
still in the air), arrivals of the healthy drones, e_sim of the remaining (healthy) formation,
the minimum obstacle clearance (of every drone, and of the healthy ones alone: a killed drone's
failsafe stop is the autopilot's, not the planner's) and drone distance, and the audit of peer
trajectories used by the planner: a message past its validity used in the formation term is a
failure (``stale_formation_uses``, must be 0); past its validity but only avoided is the
designed ``peer_lost`` reaction (``expired_avoided_uses``, counted). The reaction to the faulty
drones (``ReactionLog``): how long after the fault each healthy drone first planned against the
faulty one as a hover where it stopped, and first left it out of the formation term; and the
false alarms: replans with a silent peer in trials without a kill, plans that avoided a healthy
drone at hovers the agent added (quiet or deviating) or left it out of the formation term.

Trials are shortened by a time limit (``--time-limit``, default 60 s simulated) and flown at
``--v-max`` (default 1 m/s) so that 100 of them fit in minutes on two cores.
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from gcs.pools import sigterm_interrupts
from onboard.comm.faults import BusFaults

WORLDS = ("forest-sparse", "forest-medium")
FORMATION = "hexagon-7"
VALIDITY_S = 3.0
"""Validity of every published trajectory (the service's ``reactions.peer_lost.validity_s``)."""
AVOID_FOR_S = 10.0
"""An expired peer is still avoided this long (``reactions.peer_lost.avoid_for_s``)."""


@dataclass(frozen=True)
class FaultTrial:
    """One trial: which flight and which faults (drawn by ``draw_trial``)."""

    index: int
    seed: int
    world: str
    killed: dict[int, float]
    stuck: dict[int, float]
    bus: BusFaults | None

    def kinds(self) -> list[str]:
        """Names of the faults in this trial ('killed', 'stuck', 'loss', 'delay', ...)."""
        out = []
        if self.killed:
            out.append("killed")
        if self.stuck:
            out.append("stuck")
        b = self.bus
        if b is not None:
            if b.loss > 0.0:
                out.append("loss")
            if b.delay_max_s > 0.0:
                out.append("delay")
            if b.duplicate > 0.0:
                out.append("duplicate")
            if b.reorder > 0.0:
                out.append("reorder")
        return out

    def to_json(self) -> dict[str, Any]:
        b = self.bus
        return {
            "index": self.index,
            "seed": self.seed,
            "world": self.world,
            "killed": {str(k): v for k, v in self.killed.items()},
            "stuck": {str(k): v for k, v in self.stuck.items()},
            "bus": None
            if b is None
            else {
                "loss": b.loss,
                "delay_min_s": b.delay_min_s,
                "delay_max_s": b.delay_max_s,
                "duplicate": b.duplicate,
                "reorder": b.reorder,
                "reorder_hold_s": b.reorder_hold_s,
            },
            "kinds": self.kinds(),
        }


def draw_trial(
    base_seed: int,
    index: int,
    n_drones: int,
    fault_window_s: tuple[float, float],
    worlds: Sequence[str] = WORLDS,
) -> FaultTrial:
    """Trial ``index``'s flight and faults, drawn from ``(base_seed, index)`` only.

    Each of killed drone, stuck drone and bus faults is present with probability 1/2 (at least
    one); a killed and a stuck drone are different drones, their fault times uniform in
    ``fault_window_s``. Bus faults: each of 20 % loss, a delay up to 300 ms (uniform from 0),
    duplication (20 %) and reordering (10 %, held 1.5 s) with probability 1/2, at least one.
    """
    if n_drones < 3:
        raise ValueError(f"n_drones must be >= 3 (a killed, a stuck and a healthy), got {n_drones}")
    lo, hi = fault_window_s
    if not 0.0 <= lo <= hi:
        raise ValueError(f"fault_window_s must be 0 <= lo <= hi, got {fault_window_s}")
    if not worlds:
        raise ValueError("worlds must not be empty")
    rng = np.random.default_rng([int(base_seed), int(index)])
    kinds = rng.random(3) < 0.5
    if not kinds.any():
        kinds[int(rng.integers(3))] = True
    drones = rng.permutation(n_drones)
    times = rng.uniform(lo, hi, size=2)
    killed = {int(drones[0]): round(float(times[0]), 2)} if kinds[0] else {}
    stuck = {int(drones[1]): round(float(times[1]), 2)} if kinds[1] else {}
    bus = None
    if kinds[2]:
        parts = rng.random(4) < 0.5
        if not parts.any():
            parts[int(rng.integers(4))] = True
        bus = BusFaults(
            loss=0.2 if parts[0] else 0.0,
            delay_max_s=0.3 if parts[1] else 0.0,
            duplicate=0.2 if parts[2] else 0.0,
            reorder=0.1 if parts[3] else 0.0,
        )
    return FaultTrial(
        index=int(index),
        seed=int(base_seed) + int(index),
        world=worlds[int(index) % len(worlds)],
        killed=killed,
        stuck=stuck,
        bus=bus,
    )


def trial_config(
    trial: FaultTrial,
    v_max_m_s: float,
    time_limit_s: float | None,
    kill_model: str = "px4",
    monitor_hz: float = 100.0,
    planner: Any = None,
    peer_silence_s: float | None = None,
) -> Any:
    """The ``SimConfig`` of a trial (hexagon-7, its world and seed, its faults); ``planner``:
    the planner's parameters (None: config/planner.yaml), flown at ``v_max_m_s``;
    ``peer_silence_s``: None for the simulator's default."""
    from gcs.fastsim import SimConfig
    from onboard.config import load_formation, load_world_spec

    extra: dict[str, Any] = {}
    if planner is not None:
        extra["planner"] = dataclasses.replace(planner, v_max_m_s=v_max_m_s)
    else:
        extra["v_max_m_s"] = v_max_m_s
    if peer_silence_s is not None:
        extra["peer_silence_s"] = peer_silence_s
    return SimConfig(
        load_formation(FORMATION),
        load_world_spec(trial.world),
        seed=trial.seed,
        time_limit_s=time_limit_s,
        bus_faults=trial.bus,
        fault_seed=trial.seed,
        killed_drones=dict(trial.killed),
        stuck_drones=dict(trial.stuck),
        validity_s=VALIDITY_S,
        peer_forget_s=AVOID_FOR_S,
        kill_model=kill_model,
        monitor_rate_hz=monitor_hz,
        **extra,
    )


def remaining_esim(tracks_pos: np.ndarray, formation: np.ndarray, keep: Sequence[int]) -> Any:
    """e_sim (``onboard.planner.formation.similarity``) of the drones ``keep`` against their
    template rows at every sample: (T,)."""
    from onboard.planner.formation import similarity

    idx = list(keep)
    F = formation[idx]
    return np.array([similarity(p[idx], F)[0] for p in tracks_pos])


def judge(trial: FaultTrial, cfg: Any, result: Any) -> dict[str, Any]:
    """One trial's report from its flight (see the module docstring)."""
    n = cfg.formation.n
    faulty = set(trial.killed) | set(trial.stuck)
    healthy = [i for i in range(n) if i not in faulty]
    f = result.faults
    e = remaining_esim(result.tracks.pos, cfg.formation.points, healthy)
    arrived = [bool(result.arrived[i]) for i in healthy]
    return {
        **trial.to_json(),
        "collisions": int(result.collisions),
        "obstacle_collisions": int(result.obstacle_collisions),
        "drone_collisions": int(result.drone_collisions),
        "events": [
            {"t_s": ev.t_s, "kind": ev.kind, "ids": list(ev.ids), "distance_m": ev.distance_m}
            for ev in result.events
        ],
        "healthy": healthy,
        "healthy_arrived": int(sum(arrived)),
        "healthy_total": len(healthy),
        "healthy_success": bool(all(arrived) and result.collisions == 0),
        "e_sim_remaining_mean": float(np.mean(e)) if e.size else math.nan,
        "e_sim_remaining_max": float(np.max(e)) if e.size else math.nan,
        "min_obstacle_clearance_m": float(result.min_obstacle_clearance_m),
        "healthy_min_obstacle_clearance_m": float(
            min(result.min_obstacle_clearance_by_drone_m[i] for i in healthy)
        )
        if healthy
        else math.nan,
        "min_drone_distance_m": float(result.min_drone_distance_m),
        "stale_formation_uses": int(f["stale_formation_uses"]),
        "expired_avoided_uses": int(f["expired_avoided_uses"]),
        "unknown_uses": int(f["unknown_uses"]),
        "ghost_uses": int(f.get("ghost_uses", 0)),
        "silent_replans": int(f.get("agents", {}).get("silent", 0)),
        "replans": int(sum(result.status_counts.values())),
        "status_counts": dict(result.status_counts),
        "refused_older": int(f["refused_older"]) + int(f.get("agents", {}).get("refused_older", 0)),
        "monitor_replans": int(f.get("monitor_replans", 0)),
        "monitor_brakes": int(f.get("monitor_brakes", 0)),
        "unheard_plans": int(f.get("unheard_plans", 0)),
        "peer_uses_audited": int(f["peer_uses_audited"]),
        "bus_counters": dict(f.get("bus", {})),
        "state_bus_counters": dict(f.get("state_bus", {})),
        "flight_time_s": float(result.flight_time_s),
        "timed_out": bool(result.timed_out),
        "sim_wall_s": float(result.sim_wall_s),
    }


class ReactionLog:
    """A ``run_sim`` recorder that keeps, of every plan call and faulty drone, where the call
    avoided it as a hover (its own hover trajectory, a silent peer's ghosts, a deviating
    peer's reported position) and whether it was in the formation term. ``reactions`` then
    tells, per faulty drone, how long after its fault each healthy drone first planned against
    it where it stopped; ``healthy_hover_plans`` counts plans that avoided a healthy drone as
    a hover the agent added (starting at the call's time, lasting ``HOVER_S``: a false alarm,
    silent or deviating), ``healthy_dropped_plans`` plans that left a healthy drone out of the
    formation term (silent, or its trajectory expired or older than the validity)."""

    def __init__(self, n_form: int, plan_ahead_s: float, faulty: Sequence[int]) -> None:
        self.n_form = n_form
        self.plan_ahead_s = plan_ahead_s
        self.faulty = frozenset(faulty)
        # (drone, time of the plan, peer, its hover points (K, 3), whether it was formed with)
        self.rows: list[tuple[int, float, int, np.ndarray, bool]] = []
        self.healthy_hover_plans = 0
        self.healthy_dropped_plans = 0

    def __call__(self, call: Any) -> None:
        from onboard.agent import HOVER_S

        now = float(call.t_start_s) - self.plan_ahead_s
        hovers: dict[int, list[np.ndarray]] = {}  # any constant row: where it may hold
        added = False  # a hover the agent added for a healthy drone
        formed: dict[int, bool] = {}
        for q in call.peers:
            tr = q.trajectory
            pid = int(q.drone_id)
            formed[pid] = formed.get(pid, False) or int(q.slot) < self.n_form
            if tr.n_pieces == 1 and not np.any(tr.coeffs[0, 1:]):
                hovers.setdefault(pid, []).append(tr.coeffs[0, 0].copy())
                if pid not in self.faulty:
                    added = added or (abs(tr.t0_s - now) < 1e-6 and tr.duration_s >= HOVER_S - 1e-6)
        self.healthy_hover_plans += int(added)
        self.healthy_dropped_plans += int(
            any(pid not in self.faulty and not f for pid, f in formed.items())
        )
        for pid in self.faulty:
            if pid in formed and pid != call.drone_id:
                pts = np.array(hovers.get(pid, []), dtype=np.float64).reshape(-1, 3)
                self.rows.append((int(call.drone_id), now, pid, pts, formed[pid]))

    def reactions(
        self, stopped: dict[int, tuple[float, Sequence[float]]], within_m: float = 0.3
    ) -> dict[str, Any]:
        """Per faulty drone (stopped: id -> (time, position) from ``SimResult.faults``): for
        each other drone that planned after the fault, the delay from the fault to its first
        plan avoiding a hover within ``within_m`` of where the faulty drone stopped
        (``hover_s``; None: never) and to its first plan without it in the formation term
        (``dropped_s``)."""
        out: dict[str, Any] = {}
        for pid, (t_f, p_f) in sorted(stopped.items()):
            p = np.asarray(p_f, dtype=np.float64)
            per: dict[str, dict[str, float | None]] = {}
            for drone, now, q, pts, formed in self.rows:
                if q != pid or now < t_f - 1e-9 or drone in self.faulty:
                    continue
                d = per.setdefault(str(drone), {"hover_s": None, "dropped_s": None})
                near = pts.size and float(np.min(np.linalg.norm(pts - p, axis=1))) <= within_m
                if d["hover_s"] is None and near:
                    d["hover_s"] = round(now - t_f, 3)
                if d["dropped_s"] is None and not formed:
                    d["dropped_s"] = round(now - t_f, 3)
            out[str(pid)] = per
        return out


def _run_one(
    args: tuple[FaultTrial, float, float | None, str, float, Any, float | None],
) -> dict[str, Any]:
    from gcs.fastsim import run_sim

    trial, v_max, limit, kill_model, monitor_hz, planner, peer_silence_s = args
    cfg = trial_config(trial, v_max, limit, kill_model, monitor_hz, planner, peer_silence_s)
    log = ReactionLog(
        cfg.formation.n, cfg.plan_ahead_s, sorted(set(trial.killed) | set(trial.stuck))
    )
    result = run_sim(cfg, recorder=log)
    row = judge(trial, cfg, result)
    f = result.faults
    stopped = {int(k): v for k, v in {**f["killed"], **f["stuck"]}.items()}
    row["reactions"] = log.reactions(stopped)
    row["healthy_hover_plans"] = log.healthy_hover_plans
    row["healthy_dropped_plans"] = log.healthy_dropped_plans
    # what was flown: the planner's parameters that differ from config/planner.yaml's
    from onboard.config import load_planner_params

    base = dataclasses.asdict(load_planner_params(v_max_m_s=cfg.params.v_max_m_s))
    row["planner_changes"] = {
        k: v for k, v in dataclasses.asdict(cfg.params).items() if not _same(v, base[k])
    }
    row["v_max_m_s"] = cfg.params.v_max_m_s
    row["peer_silence_s"] = cfg.peer_silence_s
    return row


def _same(a: Any, b: Any) -> bool:
    return bool(np.array_equal(a, b)) if isinstance(a, np.ndarray) else bool(a == b)


def run_bench(
    trials: int,
    jobs: int,
    seed: int,
    v_max_m_s: float = 1.0,
    time_limit_s: float | None = 60.0,
    fault_window_s: tuple[float, float] = (3.0, 25.0),
    worlds: Sequence[str] = WORLDS,
    on_trial: Any = None,
    first: int = 0,
    kill_model: str = "px4",
    monitor_hz: float = 100.0,
    planner: Any = None,
    peer_silence_s: float | None = None,
) -> dict[str, Any]:
    """Fly ``trials`` trials (indices ``first`` ... ``first + trials - 1``) on ``jobs``
    processes; the whole report (see ``summarise``). ``planner`` and ``peer_silence_s`` as in
    ``trial_config``."""
    from onboard.config import load_formation

    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if first < 0:
        raise ValueError(f"first must be >= 0, got {first}")
    n = load_formation(FORMATION).n
    todo = [
        (
            draw_trial(seed, k, n, fault_window_s, worlds),
            v_max_m_s,
            time_limit_s,
            kill_model,
            monitor_hz,
            planner,
            peer_silence_s,
        )
        for k in range(first, first + trials)
    ]
    wall0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    if jobs == 1:
        for a in todo:
            rows.append(_run_one(a))
            if on_trial is not None:
                on_trial(rows[-1])
    else:
        ctx = multiprocessing.get_context("spawn")
        with sigterm_interrupts(), ctx.Pool(jobs) as pool:
            for row in pool.imap_unordered(_run_one, todo):
                rows.append(row)
                if on_trial is not None:
                    on_trial(row)
    rows.sort(key=lambda r: r["index"])
    out = summarise(rows)
    out.update(
        {
            "formation": FORMATION,
            "worlds": list(worlds),
            "seed": seed,
            "v_max_m_s": v_max_m_s,
            "time_limit_s": time_limit_s,
            "first": first,
            "kill_model": kill_model,
            "monitor_hz": monitor_hz,
            "fault_window_s": list(fault_window_s),
            "validity_s": VALIDITY_S,
            "avoid_for_s": AVOID_FOR_S,
            "jobs": jobs,
            "wall_s": time.perf_counter() - wall0,
            "trials": rows,
        }
    )
    return out


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Totals over trials."""
    from gcs.metrics import summary

    kinds: dict[str, int] = {}
    for r in rows:
        for k in r["kinds"]:
            kinds[k] = kinds.get(k, 0) + 1
    return {
        "n_trials": len(rows),
        "fault_counts": kinds,
        "collisions": int(sum(r["collisions"] for r in rows)),
        "trials_with_collision": [r["index"] for r in rows if r["collisions"]],
        "healthy_arrived": int(sum(r["healthy_arrived"] for r in rows)),
        "healthy_total": int(sum(r["healthy_total"] for r in rows)),
        "healthy_success_trials": int(sum(r["healthy_success"] for r in rows)),
        "e_sim_remaining_mean": summary([r["e_sim_remaining_mean"] for r in rows]),
        "e_sim_remaining_max": summary([r["e_sim_remaining_max"] for r in rows]),
        "min_obstacle_clearance_m": min(r["min_obstacle_clearance_m"] for r in rows),
        # a trial with no healthy drone has NaN here, which Python's min would keep or drop
        # by where it stands
        "healthy_min_obstacle_clearance_m": min(
            (
                r["healthy_min_obstacle_clearance_m"]
                for r in rows
                if not math.isnan(r["healthy_min_obstacle_clearance_m"])
            ),
            default=math.nan,
        ),
        "min_drone_distance_m": min(r["min_drone_distance_m"] for r in rows),
        "stale_formation_uses": int(sum(r["stale_formation_uses"] for r in rows)),
        "expired_avoided_uses": int(sum(r["expired_avoided_uses"] for r in rows)),
        "unknown_uses": int(sum(r.get("unknown_uses", 0) for r in rows)),
        "ghost_uses": int(sum(r.get("ghost_uses", 0) for r in rows)),
        "silent_replans": int(sum(r.get("silent_replans", 0) for r in rows)),
        "refused_older": int(sum(r.get("refused_older", 0) for r in rows)),
        "monitor_replans": int(sum(r.get("monitor_replans", 0) for r in rows)),
        "monitor_brakes": int(sum(r.get("monitor_brakes", 0) for r in rows)),
        "unheard_plans": int(sum(r.get("unheard_plans", 0) for r in rows)),
        "silent_replans_no_kill": int(
            sum(r.get("silent_replans", 0) for r in rows if not r["killed"])
        ),
        "trials_no_kill": int(sum(1 for r in rows if not r["killed"])),
        "trials_no_kill_with_silent": int(
            sum(1 for r in rows if not r["killed"] and r.get("silent_replans", 0))
        ),
        "silent_replans_bus_only": int(
            sum(r.get("silent_replans", 0) for r in rows if not r["killed"] and not r["stuck"])
        ),
        "replans": int(sum(r.get("replans", 0) for r in rows)),
        "replans_bus_only": int(
            sum(r.get("replans", 0) for r in rows if not r["killed"] and not r["stuck"])
        ),
        "healthy_hover_plans": int(sum(r.get("healthy_hover_plans", 0) for r in rows)),
        "healthy_dropped_plans": int(sum(r.get("healthy_dropped_plans", 0) for r in rows)),
        "reaction_killed": _reaction_summary(rows, "killed"),
        "reaction_stuck": _reaction_summary(rows, "stuck"),
        "max_flight_time_s": max(r["flight_time_s"] for r in rows),
        "timed_out_trials": int(sum(r["timed_out"] for r in rows)),
        "sim_wall_s": summary([r["sim_wall_s"] for r in rows]),
    }


def _reaction_summary(rows: Sequence[dict[str, Any]], kind: str) -> dict[str, Any]:
    """Over the trials' ``kind`` ('killed', 'stuck') drones: the delays from the fault to each
    healthy drone's first plan avoiding it as a hover where it stopped (``hover_s``) and to its
    first plan without it in the formation term (``dropped_s``), and how many healthy drones
    that planned after the fault never did either."""
    from gcs.metrics import summary

    out: dict[str, Any] = {}
    for key in ("hover_s", "dropped_s"):
        vals: list[float] = []
        never = 0
        for r in rows:
            for pid in r[kind]:
                for d in r.get("reactions", {}).get(str(pid), {}).values():
                    if d[key] is None:
                        never += 1
                    else:
                        vals.append(float(d[key]))
        out[key] = summary(vals) if vals else None
        out[f"{key}_never"] = never
    return out


@click.command("faults")
@click.option("--trials", default=100, show_default=True, help="Number of trials.")
@click.option("--jobs", default=2, show_default=True, help="Worker processes.")
@click.option("--seed", default=0, show_default=True, help="Base seed (trial k: seed + k).")
@click.option(
    "--first",
    default=0,
    show_default=True,
    help="Index of the first trial (to fly one trial of a run again: --first K --trials 1).",
)
@click.option(
    "--kill-model",
    type=click.Choice(["px4", "instant"]),
    default="px4",
    show_default=True,
    help="How a killed drone's vehicle moves on: PX4's offboard-loss failsafe, or stopping dead.",
)
@click.option(
    "--monitor-hz",
    default=100.0,
    show_default=True,
    help="Rate of the flight service's safety monitor between replans (0: off).",
)
@click.option(
    "--v-max",
    "v_max",
    default=None,
    type=float,
    help="Speed limit, m/s [default: 1.0, unless --set v_max_m_s= gives it].",
)
@click.option(
    "--planner",
    "planner_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Planner parameter file (default config/planner.yaml).",
)
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a planner parameter, e.g. --set lead_turned=true (repeatable).",
)
@click.option(
    "--peer-silence",
    "peer_silence_s",
    default=None,
    type=float,
    help="Heard of nothing newer for this long [s], a peer is quiet: avoided where it may "
    "have stopped [default: the simulator's, 0.5].",
)
@click.option(
    "--time-limit",
    "time_limit_s",
    default=60.0,
    show_default=True,
    help="Simulated seconds per trial (0: the simulator's default).",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option("--quiet", "-q", is_flag=True, help="Print only the totals.")
def bench_faults(
    trials: int,
    jobs: int,
    seed: int,
    first: int,
    kill_model: str,
    monitor_hz: float,
    v_max: float | None,
    planner_file: Path | None,
    sets: tuple[str, ...],
    peer_silence_s: float | None,
    time_limit_s: float,
    json_path: Path | None,
    quiet: bool,
) -> None:
    """Fast-time flights with random faults (killed and stuck drones, bus loss, delay,
    duplication, reordering): collisions, healthy arrivals, e_sim of the remaining formation,
    clearances and stale-trajectory uses."""
    if trials < 1:
        raise click.BadParameter("must be >= 1", param_hint="--trials")
    if jobs < 1:
        raise click.BadParameter("must be >= 1", param_hint="--jobs")
    if first < 0:
        raise click.BadParameter("must be >= 0", param_hint="--first")
    if not (math.isfinite(monitor_hz) and monitor_hz >= 0.0):
        raise click.BadParameter("must be >= 0", param_hint="--monitor-hz")
    if v_max is not None and not (math.isfinite(v_max) and v_max > 0.0):
        raise click.BadParameter("must be > 0", param_hint="--v-max")
    if peer_silence_s is not None and not (math.isfinite(peer_silence_s) and peer_silence_s > 0.0):
        raise click.BadParameter("must be > 0", param_hint="--peer-silence")
    from gcs.cli import _planner_params, _sets_v_max
    from onboard.config import ConfigError

    if v_max is None and not _sets_v_max(sets):
        v_max = 1.0
    try:
        planner = _planner_params(planner_file, sets, v_max)
    except ConfigError as exc:
        raise click.ClickException(str(exc)) from exc
    if not time_limit_s >= 0.0:
        raise click.BadParameter("must be >= 0", param_hint="--time-limit")

    def line(r: dict[str, Any]) -> None:
        if quiet:
            return
        click.echo(
            f"trial {r['index']:3d} {r['world']:13s} {'+'.join(r['kinds']):28s} "
            f"coll {r['collisions']} arrived {r['healthy_arrived']}/{r['healthy_total']} "
            f"e_sim {r['e_sim_remaining_mean']:.4f} clear {r['min_obstacle_clearance_m']:.3f} "
            f"(healthy {r['healthy_min_obstacle_clearance_m']:.3f}) "
            f"pair {r['min_drone_distance_m']:.2f} stale {r['stale_formation_uses']} "
            f"t {r['flight_time_s']:.0f}s wall {r['sim_wall_s']:.0f}s",
            err=False,
        )

    rep = run_bench(
        trials,
        jobs,
        seed,
        planner.v_max_m_s,
        time_limit_s or None,
        on_trial=line,
        first=first,
        kill_model=kill_model,
        monitor_hz=monitor_hz,
        planner=planner,
        peer_silence_s=peer_silence_s,
    )
    rep["settings"] = {
        "planner_file": None if planner_file is None else str(planner_file),
        "set": list(sets),
        "v_max_m_s": planner.v_max_m_s,
        "peer_silence_s": peer_silence_s,
    }
    es = rep["e_sim_remaining_mean"]
    click.echo(
        f"{rep['n_trials']} trials in {rep['wall_s']:.0f} s ({jobs} jobs), faults "
        f"{rep['fault_counts']}: collisions {rep['collisions']}, healthy arrived "
        f"{rep['healthy_arrived']}/{rep['healthy_total']} (all healthy arrived in "
        f"{rep['healthy_success_trials']} trials), e_sim of the remaining formation mean "
        f"{es['mean']:.4f} (median {es['median']:.4f}, max {es['max']:.4f}), min obstacle "
        f"clearance {rep['min_obstacle_clearance_m']:.3f} m (healthy drones "
        f"{rep['healthy_min_obstacle_clearance_m']:.3f} m), min drone distance "
        f"{rep['min_drone_distance_m']:.3f} m, stale formation uses "
        f"{rep['stale_formation_uses']}, expired peers avoided {rep['expired_avoided_uses']}, "
        f"replans with a silent peer {rep['silent_replans']} (ghost hovers avoided "
        f"{rep['ghost_uses']}), older trajectories refused {rep['refused_older']}, monitor "
        f"replans / brakes {rep['monitor_replans']} / {rep['monitor_brakes']}"
    )
    click.echo(
        f"false alarms: replans with a silent peer in the {rep['trials_no_kill']} trials "
        f"without a kill {rep['silent_replans_no_kill']} (in "
        f"{rep['trials_no_kill_with_silent']} trials; bus faults only "
        f"{rep['silent_replans_bus_only']}), plans avoiding a healthy drone as a hover "
        f"{rep['healthy_hover_plans']}, plans leaving a healthy drone out of the formation "
        f"{rep['healthy_dropped_plans']}, plans told a peer did not hear them "
        f"{rep['unheard_plans']}; replans {rep['replans']} (bus faults only "
        f"{rep['replans_bus_only']})"
    )
    for kind in ("killed", "stuck"):
        rs = rep[f"reaction_{kind}"]
        parts = []
        for key, what in (("hover_s", "avoided where it stopped"), ("dropped_s", "dropped")):
            sm = rs[key]
            if sm is not None:
                parts.append(
                    f"{what} after median {sm['median']:.2f} s, max {sm['max']:.2f} s "
                    f"({sm['count']} drones, never {rs[f'{key}_never']})"
                )
        click.echo(f"{kind} drones: " + ("; ".join(parts) or "none"))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(rep, indent=1, default=_json_default) + "\n")
        click.echo(f"wrote {json_path}")
    if rep["collisions"] or rep["stale_formation_uses"] or rep["unknown_uses"]:
        raise SystemExit(1)


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")
