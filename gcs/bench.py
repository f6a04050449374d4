"""Planner benchmark: replay the replans of a recorded flight and time them.

The problems are replayed on the field the drones planned on: the exact distance to the
obstacles each drone had sensed (perception 'ground-truth'), or the ESDF of the drone's own
map at that replan (perception 'mapped': the flight keeps an evenly spread subset of its
replans' fields, ``FieldKeeper``, since each is about 5 MB).

Timings use ``time.perf_counter``; on a shared machine they are noisy, so each problem's time
is the median of its repeats (after one untimed warm-up run) and one objective evaluation is the
fastest of several batches.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import platform
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.fastsim import PlanCall, SimConfig, replay_inputs, run_sim
from gcs.metrics import summary

if TYPE_CHECKING:
    from onboard.planner.params import PlannerParams


def machine_info() -> dict[str, Any]:
    """Platform, CPU model, core count and library versions."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def version(pkg: str) -> str:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return "absent"

    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": version("numpy"),
        "scipy": version("scipy"),
        "numba": version("numba"),
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }


_STARTUP_SCRIPT = textwrap.dedent(
    """
    import time
    t0 = time.perf_counter()
    import pickle, sys
    from onboard.planner.field import AnalyticField
    from onboard.planner.planner import FormationPlanner
    t_import = time.perf_counter() - t0
    with open(sys.argv[1], "rb") as fh:
        params, formation, call = pickle.load(fh)
    planner = FormationPlanner(params, formation, call.slot)
    t1 = time.perf_counter()
    res = planner.plan(call.t_start_s, call.start_p, call.start_v, call.start_a, call.goal,
                       list(call.peers), AnalyticField(call.world), call.previous)
    t2 = time.perf_counter()
    print(f"{t_import} {t2 - t1} {t2 - t0} {res.status.value}")
    """
)


def measure_startup(
    params: PlannerParams, formation: np.ndarray, call: PlanCall, runs: int = 2
) -> dict[str, Any]:
    """Wall time for fresh interpreters to import the planner and finish one plan.

    Runs ``runs`` processes one after the other (the first one may still fill numba's cache);
    ``startup_s`` is the last one, measured from outside (interpreter start included).
    Raises RuntimeError when the probe fails.
    """
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    walls: list[float] = []
    lines: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        blob = Path(tmp) / "problem.pkl"
        blob.write_bytes(pickle.dumps((params, formation, call)))
        for _ in range(runs):
            w0 = time.perf_counter()
            out = subprocess.run(
                [sys.executable, "-c", _STARTUP_SCRIPT, str(blob)],
                capture_output=True,
                text=True,
                env=env,
                check=False,
            )
            walls.append(time.perf_counter() - w0)
            if out.returncode != 0:
                raise RuntimeError(f"startup probe failed:\n{out.stderr[-2000:]}")
            lines.append(out.stdout.strip().splitlines()[-1])
    t_import, t_plan, t_total, status = lines[-1].split()
    return {
        "startup_s": walls[-1],
        "startup_runs_s": walls,
        "import_s": float(t_import),
        "first_plan_ms": float(t_plan) * 1e3,
        "in_process_s": float(t_total),
        "first_plan_status": status,
    }


def select_calls(
    calls: Sequence[PlanCall], n_drones: int, skip_s: float, max_problems: int
) -> list[PlanCall]:
    """Replans from ``skip_s`` on with every peer known, evenly thinned to ``max_problems``.

    Falls back to all replans after ``skip_s`` (then to all) when none has every peer.
    """
    chosen = [c for c in calls if c.t_start_s >= skip_s and len(c.peers) == n_drones - 1]
    if not chosen:
        chosen = [c for c in calls if c.t_start_s >= skip_s] or list(calls)
    if max_problems > 0 and len(chosen) > max_problems:
        idx = np.unique(np.linspace(0, len(chosen) - 1, max_problems).round().astype(int))
        chosen = [chosen[i] for i in idx]
    return chosen


MAPPED_MAX_PROBLEMS = 100
"""Replans a mapped replay keeps when ``max_problems`` is 0 (all): each holds its ESDF."""


class FieldKeeper:
    """A flight recorder (``run_sim(recorder=...)``) for a mapped flight: every call is kept
    without its field, and the replans ``select_calls`` would choose (from ``skip_s`` on, every
    peer known) with it, evenly spread, at most ``cap``: every ``stride``-th such replan is kept,
    and when more than ``cap`` are, every other one is dropped and the stride doubles."""

    def __init__(self, n_drones: int, skip_s: float, cap: int) -> None:
        if cap < 1:
            raise ValueError(f"cap must be >= 1, got {cap}")
        self.n_drones = n_drones
        self.skip_s = skip_s
        self.cap = cap
        self.calls: list[PlanCall] = []
        self.kept: list[PlanCall] = []
        self.stride = 1
        self._eligible = 0

    def __call__(self, call: PlanCall) -> None:
        self.calls.append(dataclasses.replace(call, mapped_field=None))
        if call.t_start_s < self.skip_s or len(call.peers) != self.n_drones - 1:
            return
        if self._eligible % self.stride == 0:
            self.kept.append(call)
            if len(self.kept) > self.cap:
                self.kept = self.kept[::2]
                self.stride *= 2
        self._eligible += 1


def _pick(values: Sequence[float], keys: Sequence[str] = ("median", "p90", "max")) -> dict:
    s = summary(values)
    return {k: s[k] for k in keys}


def _fresh_cheaper(gains: Sequence[float]) -> dict[str, Any]:
    """``bench_planner``'s ``fresh_cheaper`` from the fresh start's relative gains over the warm
    start (``(f_warm - f_fresh) / f_warm`` per problem): the share with a gain, the gain's
    median / p90 / max among them in percent, and how many gain more than 5 %."""
    g = np.asarray(gains, dtype=np.float64)
    won = g[g > 0.0] * 100.0
    return {
        "share": float(won.size / g.size) if g.size else None,
        "gain_pct": _pick(won.tolist()) if won.size else None,
        "over_5pct": int(np.sum(g > 0.05)),
    }


def _objective_us(x: np.ndarray, prob: tuple, problem: Any, calls: int) -> float:
    """Time [us] of one evaluation of the objective ``prob`` (on ``problem``'s field and work
    arrays) at x inside compiled code: one untimed call, then the median of 5 batches of
    ``calls / 10`` evaluations."""
    from onboard.planner.objective import repeat_objective

    per = max(1, calls // 10)
    x = x.copy()
    repeat_objective(x, prob, problem.fld, problem.work, 1)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        repeat_objective(x, prob, problem.fld, problem.work, per)
        times.append((time.perf_counter() - t0) / per)
    return float(np.median(times)) * 1e6


def _eval_us(problem: Any, x_end: np.ndarray, calls: int) -> float:
    """Time [us] of one objective evaluation inside compiled code, as the solver sees it: the
    mean of its cost at the initial guess and at the solution (penalties active at each differ;
    ``_objective_us`` each)."""
    return float(
        np.mean([_objective_us(x, problem.prob, problem, calls) for x in (problem.x0, x_end)])
    )


# each cost term's packed weights (``objective.P_*``): zeroed, the kernel skips that term
_TERM_WEIGHTS: dict[str, tuple[str, ...]] = {
    "obstacle": ("P_W_OBS",),
    "formation": ("P_W_FORM",),
    "swarm": ("P_W_SWARM",),
    "feasibility": ("P_W_FEAS", "P_W_HARD"),
    "uniformity": ("P_W_UNIF",),
    "altitude": ("P_W_ALT", "P_W_HOLD"),
}


def _term_eval_us(problem: Any, x_end: np.ndarray, calls: int) -> dict[str, float]:
    """Where an objective evaluation's time goes, at the solution: ``all``, then each term's
    share (``all`` less the time with that term's weights at zero, so that the kernel skips
    it), ``peers`` (the peers' positions sampled where no term reads them: the time with every
    weight zero less that with no peer either; about 0 since the objective samples a peer only
    where a term may read it, and that sampling counts in the term's share) and ``base`` (the
    rest: MINCO's coefficients, the own samples, the gradient's way back). Each time is
    ``_objective_us``'s [us]."""
    from onboard.planner import objective as obj

    head, tail, kappa, prm, peer_c, peer_T, peer_t0, sdes, fmask, fpts, peer_vb = problem.prob

    def timed(zero: tuple[str, ...], peers: bool = True) -> float:
        w = prm.copy()
        for name in zero:
            w[getattr(obj, name)] = 0.0
        w.setflags(write=False)  # as the planner's: the same compiled version
        pc, pT, p0, vb = (
            (peer_c, peer_T, peer_t0, peer_vb)
            if peers
            else (peer_c[:0], peer_T[:0], peer_t0[:0], peer_vb[:0])
        )
        prob = (head, tail, kappa, w, pc, pT, p0, sdes, fmask, fpts, vb)
        return _objective_us(x_end, prob, problem, calls)

    every = tuple(n for names in _TERM_WEIGHTS.values() for n in names)
    out = {"all": timed(())}
    for term, names in _TERM_WEIGHTS.items():
        out[term] = out["all"] - timed(names)
    bare = timed(every)
    out["base"] = timed(every, peers=False)
    out["peers"] = bare - out["base"]
    return out


def bench_planner(
    cfg: SimConfig,
    repeats: int = 5,
    skip_s: float = 5.0,
    max_problems: int = 300,
    eval_calls: int = 200,
    startup: bool = True,
    term_costs: bool = False,
    sim_progress: Callable[[float, float], None] | None = None,
    replay_progress: Callable[[int, int], None] | None = None,
    side_thread: bool = True,
) -> dict[str, Any]:
    """Record the flight ``cfg``, replay the chosen replans and return the report (JSON-able).

    ``side_thread``: the replayed planners solve the fresh start beside the warm one, which
    runs on a second thread, as the flight service does by default (``planning.side_thread``);
    the recorded flight is the same either way. ``term_costs``: also where an evaluation's time
    goes, by cost term (``_term_eval_us``; ``eval_us_by_term``, medians over the problems).

    Per problem: ``prepare(...) + solve()`` timed ``repeats`` times after one untimed run
    (median), the full ``plan(...)`` likewise, solver iterations and evaluations, the piece
    count, and one objective evaluation at x0 (``eval_us``). Breakdown per problem:
    cost = evaluations x eval_us, solver and set-up overhead = replan - cost (medians reported).
    Where ``plan`` also solves the fresh start (``fresh_alternative``, a previous trajectory),
    its set-up and solve alone are timed the same way (``prepare(..., fresh=True)``): with the
    side thread that solve runs beside the warm one (in the calling thread, the warm one's solve
    and check on the side thread), and the longer of the two sets the replan's time
    (``fresh_ms`` over the problems that have one, ``fresh_share``: how many do).

    ``cfg.perception`` 'mapped': the replans are replayed on the ESDF each drone planned on
    (at most ``max_problems``, or ``MAPPED_MAX_PROBLEMS`` when it is 0), only replans from
    ``skip_s`` on with every peer known (RuntimeError when there is none).
    """
    from onboard.planner.planner import FormationPlanner

    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    mapped = cfg.perception == "mapped"
    calls: list[PlanCall] = []
    if mapped:
        keeper = FieldKeeper(
            cfg.formation.n, skip_s, max_problems if max_problems > 0 else MAPPED_MAX_PROBLEMS
        )
        flight = run_sim(cfg, recorder=keeper, progress=sim_progress)
        calls = keeper.calls
        chosen = select_calls(keeper.kept, cfg.formation.n, skip_s, max_problems)
        if not chosen:
            raise RuntimeError(
                f"no replan after --skip-s {skip_s} s with every peer known to replay on its map"
            )
    else:
        flight = run_sim(cfg, recorder=calls.append, progress=sim_progress)
        chosen = select_calls(calls, cfg.formation.n, skip_s, max_problems)
    params = cfg.params

    replan_ms: list[float] = []  # the whole plan() call
    solve_ms: list[float] = []  # Problem.solve() alone
    setup_ms: list[float] = []  # prepare(): local target, guess, packing
    iters: list[float] = []
    evals: list[float] = []
    eval_us: list[float] = []
    cost_ms: list[float] = []
    overhead_ms: list[float] = []
    term_us: list[dict[str, float]] = []  # --term-costs: one evaluation's time by term
    pieces: list[float] = []
    fresh_prep_ms: list[float] = []  # the fresh start's prepare(..., fresh=True)
    fresh_solve_ms: list[float] = []  # and its solve (beside the warm one)
    fresh_evals: list[float] = []
    # where plan() also solves the fresh start: how much cheaper than the warm start's solution
    # its solution is, relative to the warm one (negative: dearer; the solvers' own values)
    fresh_gain: list[float] = []
    statuses: dict[str, int] = {}
    solver_statuses: dict[str, int] = {}
    rejected = 0  # first-attempt solutions the safety check refused
    clearance: list[float] = []  # their closest approach to an obstacle
    # the flight service's side thread, for the warm start's part (planning.side_thread)
    side_pool = (
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="side")
        if side_thread
        else contextlib.nullcontext()
    )
    with side_pool as side:
        planners = [
            FormationPlanner(params, cfg.formation.points, i, side=side)
            for i in range(cfg.formation.n)
        ]
        for k_call, call in enumerate(chosen):
            planner = planners[call.slot]
            args = replay_inputs(call)  # the distance field is built here, outside the timing
            t_prep: list[float] = []
            t_solve: list[float] = []
            t_plan: list[float] = []
            t_fprep: list[float] = []
            t_fsolve: list[float] = []
            # the fresh start's second solve (plan() makes it for every accepted attempt with
            # the formation term from a previous trajectory)
            with_fresh = planner.fresh_wanted(args[0], args[7])
            problem = None
            res = None
            x_end = np.zeros(0)
            for k in range(repeats + 1):  # the first round is a warm-up, not timed
                t0 = time.perf_counter()
                problem = planner.prepare(*args)
                t1 = time.perf_counter()
                x_end, _ = problem.solve()
                t2 = time.perf_counter()
                res = planner.plan(*args)
                t3 = time.perf_counter()
                if with_fresh:
                    t_s, p, v, a, goal, peers, field, previous = args
                    fresh = planner.prepare(t_s, p, v, a, goal, peers, field, previous, fresh=True)
                    t4 = time.perf_counter()
                    x_fresh, _ = fresh.solve()
                    t5 = time.perf_counter()
                if k > 0:
                    t_prep.append((t1 - t0) * 1e3)
                    t_solve.append((t2 - t1) * 1e3)
                    t_plan.append((t3 - t2) * 1e3)
                    if with_fresh:
                        t_fprep.append((t4 - t3) * 1e3)
                        t_fsolve.append((t5 - t4) * 1e3)
            if with_fresh:
                fresh_prep_ms.append(float(np.median(t_fprep)))
                fresh_solve_ms.append(float(np.median(t_fsolve)))
                fresh_evals.append(fresh.evaluations)
            assert problem is not None and res is not None
            if with_fresh:
                f_warm = problem.cost(x_end)
                fresh_gain.append((f_warm - fresh.cost(x_fresh)) / f_warm)
            statuses[str(res.status.value)] = statuses.get(str(res.status.value), 0) + 1
            sname = res.solver_status.name if res.solver_status is not None else "none"
            solver_statuses[sname] = solver_statuses.get(sname, 0) + 1
            first = problem.trajectory(x_end)
            t_from = float(args[0])
            if not planner.check(first, t_from, args[6], args[5])[0]:
                rejected += 1
            ts = np.append(np.arange(t_from, first.t_end_s, params.check_step_s), first.t_end_s)
            clearance.append(float(np.min(args[6].distance(first.sample(ts))[0])))
            e_us = _eval_us(problem, x_end, eval_calls)
            if term_costs:
                term_us.append(_term_eval_us(problem, x_end, eval_calls))
            s_ms = float(np.median(t_solve))
            c_ms = problem.evaluations * e_us * 1e-3
            replan_ms.append(float(np.median(t_plan)))
            solve_ms.append(s_ms)
            setup_ms.append(float(np.median(t_prep)))
            iters.append(res.iterations)
            evals.append(res.evaluations)
            eval_us.append(e_us)
            cost_ms.append(c_ms)
            overhead_ms.append(s_ms - c_ms)
            pieces.append(problem.M)
            if replay_progress is not None:
                replay_progress(k_call + 1, len(chosen))

    report: dict[str, Any] = {
        "scenario": {
            "formation": cfg.formation.name,
            "world": cfg.world.name,
            "seed": cfg.seed,
            "v_max_m_s": params.v_max_m_s,
            "perception": cfg.perception,
            "field": "esdf" if mapped else "exact",
            "flight_success": flight.success,
            "flight_replans": len(calls),
            "skip_s": skip_s,
            "side_thread": side_thread,
        },
        "problems": len(chosen),
        "repeats": repeats,
        "replan_ms": _pick(replan_ms, ("median", "p90", "max", "mean")),
        "solve_ms": _pick(solve_ms, ("median", "p90", "max", "mean")),
        "iterations": _pick(iters),
        "evaluations": _pick(evals),
        "eval_us": summary(eval_us)["median"],
        "breakdown": {
            "setup_ms_median": summary(setup_ms)["median"],
            "solve_ms_median": summary(solve_ms)["median"],
            "cost_eval_ms_median": summary(cost_ms)["median"],
            "solver_overhead_ms_median": summary(overhead_ms)["median"],
            "check_and_rest_ms_median": summary(
                [r - s - p for r, s, p in zip(replan_ms, solve_ms, setup_ms, strict=True)]
            )["median"],
        },
        # the fresh start's set-up and solve alone, over the problems where plan() makes one
        "fresh_ms": {
            "setup_median": summary(fresh_prep_ms)["median"] if fresh_prep_ms else None,
            "solve": _pick(fresh_solve_ms, ("median", "p90", "max")) if fresh_solve_ms else None,
            "evaluations_median": summary(fresh_evals)["median"] if fresh_evals else None,
        },
        "fresh_share": len(fresh_solve_ms) / len(chosen) if chosen else 0.0,
        # what the fresh start buys: the share of those problems where its solution costs less
        # than the warm start's, and by how much there (percent of the warm one's cost)
        "fresh_cheaper": _fresh_cheaper(fresh_gain),
        "solver_status_counts": solver_statuses,
        "pieces": {"median": summary(pieces)["median"]},
        "plan_status_counts": statuses,
        "check": {
            # how often the safety check has to act: the first attempt's solution (formation
            # term on, from the usual initial guess) refused, and its closest approach to an
            # obstacle (the optimiser's own margin, before any refinement or fallback)
            "first_attempt_rejected": rejected,
            "first_attempt_clearance_m": {
                "min": float(np.min(clearance)) if clearance else None,
                "p10": float(np.percentile(clearance, 10)) if clearance else None,
                "median": float(np.median(clearance)) if clearance else None,
            },
            "check_obstacle_m": params.check_obstacle_m,
        },
        "machine": machine_info(),
        "startup_s": None,
    }
    if term_costs and term_us:
        report["eval_us_by_term"] = {
            k: summary([t[k] for t in term_us])["median"] for k in term_us[0]
        }
    if startup and chosen:
        # (on the exact field of the first problem's obstacles: the probe times the import and
        # the first plan, whatever the field)
        probe = dataclasses.replace(chosen[0], mapped_field=None)
        st = measure_startup(params, cfg.formation.points, probe)
        report["startup_s"] = st["startup_s"]
        report["startup"] = st
    return report
