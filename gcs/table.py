"""The paper's comparison (Table I), reproduced: ours vs Turpin 2012 vs Zhou 2018 per density.

Every trial builds its own seeded world (trial k uses seed ``seed + k``); every method flies the
same worlds. Metrics come from the flown positions sampled at 10 Hz (``SimResult.tracks``):

- success: every drone rests within 0.5 m of its goal before the time limit, no drone centre
  closer than 0.2 m to an obstacle surface, no two centres closer than 0.4 m (checked at 100 Hz);
- e_dist: ``sqrt(min_{s,R,t} sum_i ||D_i - (s R C_i + t)||^2)`` with D the template at its
  configured size, averaged over the samples whose swarm centroid is inside the cluttered x
  span; e_dist_rms is the same per drone (divided by sqrt(N) inside the root);
- e_sim: the formation metric f over the same samples.

Summary rows average e_dist, e_sim and the times over the *successful* trials (the paper leaves
them blank when almost no trial succeeds); ``*_all`` keys average over every trial.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcs.fastsim import SimConfig, SimResult, run_sim
from gcs.metrics import summary
from onboard.agent import REPLAN_PERIOD_S
from onboard.config import Formation, WorldSpec, load_planner_params
from onboard.planner.params import PlannerParams

METHODS = ("ours", "turpin", "zhou")
DENSITIES = ("sparse", "medium", "dense")
METHOD_LABELS = {"ours": "ours", "turpin": "Turpin 2012", "zhou": "Zhou 2018"}
METHOD_DESCRIPTIONS = {
    "ours": "similarity metric, spatial-temporal optimisation",
    "turpin": "fixed relative positions, our obstacle and reciprocal avoidance",
    "zhou": "virtual structure with potential fields",
}
# Table I of the paper: success %, e_dist [m], e_sim (None: not reported)
PAPER: dict[tuple[str, str], tuple[float, float | None, float | None]] = {
    ("sparse", "zhou"): (65, 1.47, 0.0162),
    ("sparse", "turpin"): (85, 1.08, 0.0066),
    ("sparse", "ours"): (100, 0.77, 0.0032),
    ("medium", "zhou"): (15, None, None),
    ("medium", "turpin"): (75, 1.55, 0.0162),
    ("medium", "ours"): (100, 0.90, 0.0045),
    ("dense", "zhou"): (0, None, None),
    ("dense", "turpin"): (60, 2.01, 0.0278),
    ("dense", "ours"): (95, 1.25, 0.0107),
}
TURPIN_W_FORMATION = 300.0
"""Weight of Turpin's relative-position term: best of 30 / 300 / 3000 on 4 medium forests."""


@dataclass(frozen=True)
class TrialResult:
    """Figures of one flight (JSON row of ``trials``)."""

    density: str
    method: str
    trial: int
    seed: int
    success: bool
    n_arrived: int
    collisions: int
    min_obstacle_clearance_m: float
    min_drone_distance_m: float
    max_speed_m_s: float
    e_dist_m: float
    e_dist_rms_m: float
    e_sim: float
    e_sim_whole_flight: float
    z_spread_max_m: float
    """``Tracks.z_spread_max``: the largest altitude difference between two drones."""
    flight_time_s: float
    path_length_m: float
    replan_ms_median: float
    wall_s: float


def score(result: SimResult, formation: np.ndarray) -> dict[str, float]:
    """e_dist, e_dist_rms, e_sim over the cluttered span and the mean path length per drone."""
    tr = result.tracks
    n = formation.shape[0]
    lo, hi = result.cluttered_x
    if tr.pos.shape[0]:
        cx = tr.pos[:, :, 0].mean(axis=1)
        inside = (cx >= lo) & (cx <= hi)
        steps = np.linalg.norm(np.diff(tr.pos, axis=0), axis=2)
        path = float(np.mean(np.sum(steps, axis=0))) if steps.size else 0.0
    else:
        inside = np.zeros(0, dtype=bool)
        path = 0.0
    if np.any(inside):
        ed = float(np.mean(tr.e_dist[inside]))
        es = float(np.mean(tr.e_sim[inside]))
    else:
        ed = es = math.nan
    return {
        "e_dist_m": ed,
        "e_dist_rms_m": ed / math.sqrt(n) if math.isfinite(ed) else math.nan,
        "e_sim": es,
        "path_length_m": path,
    }


def method_params(method: str, base: PlannerParams) -> PlannerParams:
    """Planner parameters of a planner-based method."""
    if method == "turpin":
        return dataclasses.replace(
            base, formation_penalty="relative", w_formation=TURPIN_W_FORMATION
        )
    return base


def run_trial(
    method: str,
    label: str,
    trial: int,
    seed: int,
    formation: Formation,
    world: WorldSpec,
    base: PlannerParams,
    keep_result: bool,
    start_z_jitter_m: float = 0.0,
    replan_period_s: float = REPLAN_PERIOD_S,
) -> tuple[TrialResult, SimResult | None]:
    """Fly one trial with one method (speed limit: ``base.v_max_m_s``); the full SimResult only
    when ``keep_result``. ``start_z_jitter_m``, ``replan_period_s``: those of ``SimConfig``."""
    cfg = SimConfig(
        formation=formation,
        world=world,
        seed=seed,
        planner=method_params(method, base),
        start_z_jitter_m=start_z_jitter_m,
        replan_period_s=replan_period_s,
    )
    if method == "zhou":
        from gcs.baselines import run_virtual_structure

        res = run_virtual_structure(cfg)
    elif method in ("ours", "turpin"):
        res = run_sim(cfg)
    else:
        raise ValueError(f"unknown method {method!r}; choose from {METHODS}")
    s = score(res, formation.points)
    row = TrialResult(
        density=label,
        method=method,
        trial=trial,
        seed=seed,
        success=res.success,
        n_arrived=int(np.sum(res.arrived)),
        collisions=res.collisions,
        min_obstacle_clearance_m=res.min_obstacle_clearance_m,
        min_drone_distance_m=res.min_drone_distance_m,
        max_speed_m_s=res.max_speed_m_s,
        e_dist_m=s["e_dist_m"],
        e_dist_rms_m=s["e_dist_rms_m"],
        e_sim=s["e_sim"],
        e_sim_whole_flight=res.e_sim_mean,
        z_spread_max_m=res.tracks.z_spread_max(),
        flight_time_s=res.flight_time_s,
        path_length_m=s["path_length_m"],
        replan_ms_median=res.replan_ms["median"],
        wall_s=res.sim_wall_s,
    )
    return row, (res if keep_result else None)


def _mean(values: Sequence[float]) -> float | None:
    a = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(a)) if a else None


def summarize(rows: Sequence[TrialResult]) -> list[dict[str, Any]]:
    """One summary row per (density, method), in the order they first appear."""
    keys: list[tuple[str, str]] = []
    for r in rows:
        if (r.density, r.method) not in keys:
            keys.append((r.density, r.method))
    out = []
    for density, method in keys:
        rs = [r for r in rows if r.density == density and r.method == method]
        ok = [r for r in rs if r.success]
        paper = PAPER.get((density, method))
        out.append(
            {
                "density": density,
                "method": method,
                "trials": len(rs),
                "success_rate": len(ok) / len(rs),
                "e_dist": _mean([r.e_dist_m for r in ok]),
                "e_dist_rms": _mean([r.e_dist_rms_m for r in ok]),
                "e_sim": _mean([r.e_sim for r in ok]),
                "e_dist_all": _mean([r.e_dist_m for r in rs]),
                "e_sim_all": _mean([r.e_sim for r in rs]),
                "min_obstacle_clearance_m": min(r.min_obstacle_clearance_m for r in rs),
                "min_drone_distance_m": min(r.min_drone_distance_m for r in rs),
                "max_speed_m_s": max(r.max_speed_m_s for r in rs),
                "z_spread_max_m": max(r.z_spread_max_m for r in rs),
                "collisions": sum(r.collisions for r in rs),
                "flight_time_s": _mean([r.flight_time_s for r in ok]),
                "path_length_m": _mean([r.path_length_m for r in ok]),
                "replan_ms_median": _mean([r.replan_ms_median for r in rs]),
                "paper": (
                    None
                    if paper is None
                    else {"success_rate": paper[0] / 100.0, "e_dist": paper[1], "e_sim": paper[2]}
                ),
            }
        )
    return out


def _trial_job(args: tuple) -> tuple[TrialResult, SimResult | None]:
    return run_trial(*args)


def run_table(
    formation: Formation,
    worlds: Sequence[tuple[str, WorldSpec]],
    methods: Sequence[str],
    trials: int,
    seed: int,
    base: PlannerParams | None = None,
    jobs: int = 1,
    progress: Callable[[int, int], None] | None = None,
    start_z_jitter_m: float = 0.0,
    replan_period_s: float = REPLAN_PERIOD_S,
) -> tuple[dict[str, Any], dict[tuple[str, str], SimResult]]:
    """Run every (world, method, trial) with the planner parameters ``base`` (default
    config/planner.yaml; its ``v_max_m_s`` is the speed limit of every method); returns (report,
    the first trial's SimResult of every (world label, method) for the plots).
    ``start_z_jitter_m``: every flight's drones start up to this far off their start altitude
    (``SimConfig.start_z_jitter_m``); ``replan_period_s``: every drone replans this often
    (``SimConfig.replan_period_s``; the zhou baseline has no replans)."""
    if trials < 1:
        raise ValueError("trials must be >= 1")
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; choose from {METHODS}")
    params = base if base is not None else load_planner_params()
    jobs_args = [
        (m, label, k, seed + k, formation, spec, params, k == 0, start_z_jitter_m, replan_period_s)
        for label, spec in worlds
        for k in range(trials)
        for m in methods
    ]
    t0 = time.perf_counter()
    results: list[tuple[TrialResult, SimResult | None]] = []
    if jobs <= 1:
        for i, a in enumerate(jobs_args):
            results.append(_trial_job(a))
            if progress is not None:
                progress(i + 1, len(jobs_args))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            for i, r in enumerate(pool.map(_trial_job, jobs_args)):
                results.append(r)
                if progress is not None:
                    progress(i + 1, len(jobs_args))
    rows = [r for r, _ in results]
    kept = {(r.density, r.method): s for r, s in results if s is not None}
    report = {
        "formation": formation.name,
        "v_max_m_s": params.v_max_m_s,
        "seed": seed,
        "trials_per_cell": trials,
        "methods": list(methods),
        "worlds": [label for label, _ in worlds],
        "wall_s": time.perf_counter() - t0,
        "jobs": jobs,
        "start_z_jitter_m": start_z_jitter_m,
        "replan_period_s": replan_period_s,
        "definitions": {
            "success": "all drones within 0.5 m of their goals at rest before the time limit, "
            "no centre within 0.2 m of an obstacle surface, no two centres within 0.4 m",
            "e_dist": "sqrt of the residual after the best Sim(3) alignment onto the template "
            "at its configured size, mean over 10 Hz samples with the centroid in the cluttered "
            "span, mean over successful trials",
            "e_sim": "formation similarity metric over the same samples",
        },
        "summary": summarize(rows),
        "trials": [dataclasses.asdict(r) for r in rows],
        "replan_ms": summary([r.replan_ms_median for r in rows if r.method != "zhou"]),
    }
    return report, kept
