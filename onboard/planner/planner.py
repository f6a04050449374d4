"""One drone's formation planner: ``plan(...)`` -> status + trajectory (paper Sec. IV).

A replan picks a local target ``horizon_m`` along the way to the goal, builds an initial guess
(the previous trajectory, else a straight line, else an A* path when the line is blocked),
optimises waypoints and durations of a MINCO trajectory with L-BFGS over the seven cost terms,
and accepts the result only if it passes a safety check against the distance field and the
peers' trajectories. An accepted solution from the previous trajectory is solved once more from
a fresh start (``fresh_alternative``: the straight line by default; where a ``SideExecutor`` is
given, the warm start's solve and check run on it meanwhile) and the cheaper of the two that
the check accepts is flown.
A refused solution is first solved again from where it is (tight tolerances; where it passes
too close to an obstacle, also on denser constraint points with stiffer obstacle and limit
penalties: ``refine_kappa_factor``, ``refine_penalty_scale``). A
failed attempt is retried from an A* path with the formation term
(``astar_keeps_formation``), optionally once more with the formation weight scaled down
(``soft_formation_scale``), then from an A* path without it (A* paths keep the optimiser's
clearance, else the check's: ``astar_ladder_m``). When every attempt was refused, a safe
previous trajectory that still moves the drone (``KEEP_MOVING_M``) is kept. Otherwise, if the
A* path kept only the check's distance, one rescue attempt without the formation term starts
from an A* path at the largest of the clearances in between that finds one
(``astar_rescue_ladder_m``): the roomier way around a gap that the check refuses every plan
through. Failing that a refused trajectory that the check accepts over its first
``APPROACH_S`` is flown (the drone approaches and looks again), else a safe previous trajectory
(a hover) is kept; else, where the stop would meet a peer, an evasion (``EVADE``: a short move
to rest straight away from where the drone is, in one of a fixed set of directions) that the
check accepts outright; else the last resort (``MARGINAL``: the optimised ones, and those
evasions) that keeps farthest beyond the check's distances, else an emergency stop. A caller
short of time passes ``give_up``: once it says so, no further attempt starts while the previous
trajectory is safe and moves the drone on; that trajectory is kept (``OVER_BUDGET``). A drone
ahead of its slot relative to its peers plans with a lower speed limit (``lead_slowdown_m``), so
the swarm waits for a drone left behind rather than stretching the shape for the rest of the
flight. But for an emergency stop, the planner never returns a trajectory that the check
refuses within ``APPROACH_S``, nor one refused later while the previous trajectory is safe and
moves the drone on; it reads no clock and does no I/O; failure is a status, never an exception
(bad *inputs* raise ValueError).

The set-up (local target, initial guess), the solve and the safety check run in compiled code
(``kernels``, ``objective``; the GIL is released there); this module validates the inputs,
packs the peers once per replan and chooses between the attempts.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from onboard.planner import kernels as kn
from onboard.planner import objective as obj
from onboard.planner.astar import astar_path_levels
from onboard.planner.field import AnalyticField, DistanceField, FieldData, GridField
from onboard.planner.formation import complete_mask, normalized_adjacency
from onboard.planner.lbfgs import LbfgsStatus
from onboard.planner.params import PlannerParams
from onboard.planner.trajectory import Trajectory, braking_duration_s

COMFORT_LOOKAHEAD_S = 1.0
"""``comfort_obstacle_m`` looks at the trajectory from this long after its start (the replan
period): an approach sooner than that is flown before another way could be taken."""
MARGINAL = "inside the check's distance, no closer than a stop: "
"""How ``check``'s reason begins for a trajectory it accepts only as a last resort: it comes
inside the check's distance of an obstacle or a peer, but no closer than a braking stop from
the same start would (``kernels.BAND_MARGINAL``)."""
LAST_RESORT = "flown as a last resort"
"""How the message of a plan flown as a last resort ends (a ``MARGINAL`` trajectory, when no
attempt stayed outside the check's distances)."""
COMFORT_ASTAR_MARGIN_M = 1.5
"""The A* box of the comfort alternative grows the start-target box by this much (3 m for the
fallbacks): a neighbouring gap, not a detour, and a quarter of the grid nodes."""
APPROACH_S = 3.0
"""When every attempt of a replan was refused and the drone would otherwise hold where it is
(or brake to a stop), a refused trajectory that the check accepts over its first this long is
flown (``APPROACH``): the drone approaches what it cannot pass yet and looks again at the next
replan, rather than holding still forever in front of a way that every plan is refused for far
ahead (mapped forest-medium seed 3, 2026-11-29: a drone hovered 150 s 0.78 m from a trunk,
every plan refused for 0.26-0.30 m from an obstacle 9-15 s ahead). Three replan periods: the
next replans can still stop it short of the conflict, and the service's monitor, which looks
2 s ahead, never meets it. Not for plans in general: a check lenient far ahead for every plan
let trunks closer and loosened the shape (BENCHMARKS, 2026-11-28)."""
APPROACH = f"flown toward a conflict at least {APPROACH_S:g} s ahead, to look again"
"""How the message of a plan flown that way ends."""
STILL_S = 4.0
STILL_M = 0.05
"""A peer out of the formation term whose trajectory stays within ``STILL_M`` of where it is
over the next ``STILL_S`` holds still; the A* search treats it as an obstacle
(``_still_peers``). The field does not know peers, and the optimiser avoids them only near the
way it starts from: a drone behind where a killed peer may have stopped (hovers along its last
trajectory) refused every way through them for 35 s, from an A* path that led straight through
(bench faults seed 1000, trial 45, 2026-11-29)."""
KEEP_MOVING_M = 0.1
"""When every attempt of a replan was refused, a safe previous trajectory whose end lies at
least this far from the replan's start is kept before the rescue attempt is tried (as before
the rescue existed: the drone flies on and the next replan tries again); one that holds the
drone where it is (a kept hover, a finished stop) is kept only if the rescue fails too."""
SPEED_CAP_SAMPLES = 16
"""``PlannerParams.speed_cap_frac``: a plan's speed is sampled on this many intervals of each
piece (its pieces last 0.5-4 s; the speed varies little within 1/16 of one)."""
SPEED_CAP_KAPPA_FACTOR = 2
SPEED_CAP_HARD_SCALE = 100.0
"""... and a plan over the cap is solved again with this many times the constraint points and
J_d's steep part this many times stiffer (``Problem.cap_prob``)."""
SPEED_CAP = "speed capped"
"""How the message of a plan slowed to the cap starts."""
SWARM_TARGET_MIN_M = 1.0
"""A swarm-consistent local target (``PlannerParams.swarm_target``) lies at least this far ahead
of the drone along the shared path: a drone far ahead of the reference still plans a trajectory
that moves on, rather than one that ends where it stands or turns back."""
_REF_MODES = {
    "own-goal": kn.REF_OWN_GOAL,
    "centroid": kn.REF_CENTROID,
    "slowest": kn.REF_SLOWEST,
}
"""``PlannerParams.swarm_target`` -> ``kernels.swarm_setup``'s reference mode."""
_RESCUE = "a* retry at the rescue levels"
"""How messages name the rescue attempt (``PlannerParams.astar_rescue_ladder_m``) when the
check refuses it: "<attempt>: <reason>" like the others (``gcs.fastsim.count_refusals`` counts
the attempts named "formation..." and "a* retry..."). An accepted rescue adds "a* rescue: path
at <clearance> m" to the message instead, which is no refusal."""

EVADE = "evasion"
"""How the message of a plan flown as an evasion begins its last part: "evasion <D> m toward
(x, y, z)", then ``LAST_RESORT`` when the check accepts it only as one."""
EVADE_DISTANCES_M = (0.8, 1.6)
"""How far the evasions go (``FormationPlanner._evasions``): a step aside and a longer move."""
EVADE_GROWTH = 1.3
EVADE_TRIES = 8
"""An evasion's duration starts at the hardest braking stop's from the start's speed (at least
0.5 s) and grows by ``EVADE_GROWTH`` up to ``EVADE_TRIES`` times until the move keeps within the
speed, acceleration and jerk limits; one that never does is not offered."""


def _evade_directions() -> np.ndarray:
    """The evasions' directions: eight level ones, 45 degrees apart, and up and down."""
    ang = np.arange(8) * (math.pi / 4.0)
    level = np.stack([np.cos(ang), np.sin(ang), np.zeros(8)], axis=1)
    return np.vstack([level, [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])


_EVADE_DIRECTIONS = _evade_directions()
_NO_COEFFS = np.zeros((1, 6, 3))
_NO_DURATIONS = np.ones(1)
_NO_KNOWN = np.ones((1, 1, 1), dtype=bool)
_ZERO3 = np.zeros(3)
for _a in (_NO_COEFFS, _NO_DURATIONS, _NO_KNOWN, _ZERO3):
    _a.setflags(write=False)  # read-only like a Trajectory's arrays and a field's mask


class PlanStatus(str, enum.Enum):
    """Outcome of one replan."""

    OK = "ok"
    """New optimised trajectory, formation term on, passed the safety check."""
    OK_NO_FORMATION = "ok-no-formation"
    """The formation attempts failed the check; the A* retry (or rescue) without formation
    passed."""
    KEPT_PREVIOUS = "kept-previous"
    """Every attempt failed; the previous trajectory is still safe and is kept."""
    EMERGENCY = "emergency"
    """Nothing safe was found: the trajectory is a braking stop; the service should hover/land."""
    OVER_BUDGET = "over-budget"
    """The caller's time budget (``plan``'s ``give_up``) ran out after a refused attempt: no
    further attempt was made, and the previous trajectory, which the check still accepts and
    which moves the drone on, is kept. Not a failure: the caller replans at once."""
    LATE = "late"
    """Set by the flight's cycle (``DroneAgent``), not the planner: the plan came back after
    its start time, and flying it would have moved the setpoint away from the trajectory in
    control (the two diverge from the start on). It is not flown nor published; the
    trajectory in control flies on and a replan follows at once."""


@dataclass(frozen=True)
class PeerTrajectory:
    """A peer's latest broadcast trajectory (global times) and its formation slot."""

    drone_id: int
    slot: int
    trajectory: Trajectory


@dataclass(frozen=True)
class PlanResult:
    """What one replan produced. ``trajectory`` is always set (new, previous or a stop)."""

    status: PlanStatus
    trajectory: Trajectory
    iterations: int = 0
    evaluations: int = 0
    solver_status: LbfgsStatus | None = None
    message: str = ""
    cost_terms: Callable[[], dict[str, float]] | None = field(
        default=None, repr=False, compare=False
    )
    """Computes ``costs`` (the replan does not spend an objective evaluation on them)."""
    resume_at: int = 0
    """``OVER_BUDGET``: the index of the first attempt it gave up (``FormationPlanner.plan``'s
    ``first_attempt`` for the replan that follows); else 0."""

    @functools.cached_property
    def costs(self) -> dict[str, float]:
        """The weighted value of each cost term at the solution (empty when the trajectory is
        not a new solution); computed on first access."""
        return {} if self.cost_terms is None else self.cost_terms()


class Problem:
    """One optimisation problem, ready to evaluate or solve (x = [q.ravel(), tau])."""

    def __init__(
        self,
        params: PlannerParams,
        t_start_s: float,
        head: np.ndarray,
        tail: np.ndarray,
        x0: np.ndarray,
        prob: tuple,
        fld: tuple,
        lb_prm: np.ndarray,
    ) -> None:
        self.params = params
        self.t_start_s = t_start_s
        self.M = (int(x0.shape[0]) + 3) // 4  # x0 holds 3 (M - 1) + M values
        self.head = head
        self.tail = tail
        self.tau_scale = float(prob[3][obj.P_TAU_SCALE])
        self.x0 = x0
        self.prob = prob
        self.fld = fld
        M = self.M
        self.work = obj.workspace(M)
        self.lb_prm = lb_prm
        self.cancel_flag = np.zeros(1, dtype=np.int64)
        self.iterations = 0
        self.evaluations = 0
        self._solved: tuple[np.ndarray, float] | None = None  # (x, f) of the last solve
        self.astar_clearance_m = math.nan
        """The clearance [m] of the A* path the initial guess follows (NaN: no A* path)."""
        self.coarse: tuple[tuple, np.ndarray] | None = None
        """(problem, solver parameters) of a coarse pass that ``solve`` from x0 runs first
        (``PlannerParams.fresh_coarse_kappa``; None: none)."""

    def objective(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(f, df/dx) at x."""
        g = np.empty_like(x)
        f = obj.objective(
            np.ascontiguousarray(x, dtype=np.float64), self.prob, self.fld, self.work, g
        )
        return float(f), g

    def cost_terms(self, x: np.ndarray) -> dict[str, float]:
        """The weighted value of each of the seven terms at x."""
        self.objective(x)
        return {name: float(v) for name, v in zip(obj.TERM_NAMES, self.work[5], strict=True)}

    def refine_prob(self) -> tuple:
        """The problem a refused solution is solved again on (``PlannerParams.refine_*``):
        ``refine_kappa_factor`` times the constraint points (the check samples every
        ``check_step_s``, the objective every ``1 / kappa`` of a piece: a long piece passed a
        trunk between its points) and the obstacle and limit penalties ``refine_penalty_scale``
        times stiffer."""
        p = self.params
        if p.refine_kappa_factor == 1 and p.refine_penalty_scale == 1.0:
            return self.prob  # the option off (the defaults)
        weights = [obj.P_W_OBS, obj.P_W_FEAS, obj.P_W_HARD]
        return self._stiffer(p.refine_kappa_factor, weights, p.refine_penalty_scale)

    def cap_prob(self) -> tuple:
        """The problem a solution faster than the speed cap is solved again on
        (``PlannerParams.speed_cap_frac``): ``SPEED_CAP_KAPPA_FACTOR`` times the constraint
        points and J_d's steep part (beyond the limits themselves) ``SPEED_CAP_HARD_SCALE``
        times stiffer."""
        return self._stiffer(SPEED_CAP_KAPPA_FACTOR, [obj.P_W_HARD], SPEED_CAP_HARD_SCALE)

    def _stiffer(self, kappa_factor: int, weights: list[int], scale: float) -> tuple:
        """This problem on ``kappa_factor`` times the constraint points, with the packed weights
        ``weights`` (``objective.P_W_*``) ``scale`` times stiffer."""
        head, tail, kappa, prm, *rest = self.prob
        if scale != 1.0:
            prm = prm.copy()
            prm[weights] *= scale
            prm.setflags(write=False)  # as the planner's: one compiled version
        return (head, tail, kappa * kappa_factor, prm, *rest)

    def solve(
        self,
        x_start: np.ndarray | None = None,
        lb_prm: np.ndarray | None = None,
        prob: tuple | None = None,
    ) -> tuple[np.ndarray, LbfgsStatus]:
        """Run L-BFGS from x_start (default x0) with the packed solver parameters lb_prm
        (default the planner's) on ``prob`` (default this problem's; ``refine_prob``); returns
        (best x, solver status). Counters accumulate. From x0 with the defaults, a ``coarse``
        pass runs first when there is one, and the solve goes on from where it stopped (unless
        it was canceled)."""
        x = (self.x0 if x_start is None else x_start).copy()
        if self.coarse is not None and x_start is None and lb_prm is None and prob is None:
            c_prob, c_prm = self.coarse
            status, iters, evals, _ = obj.solve_counted(
                x, c_prob, self.fld, self.work, c_prm, self.params.lbfgs.mem_size, self.cancel_flag
            )
            self.iterations += iters
            self.evaluations += evals
            if status == LbfgsStatus.CANCELED:
                self._solved = None
                return x, LbfgsStatus(status)
        prm = self.lb_prm if lb_prm is None else lb_prm
        prob = self.prob if prob is None else prob
        status, iters, evals, f = obj.solve_counted(
            x, prob, self.fld, self.work, prm, self.params.lbfgs.mem_size, self.cancel_flag
        )
        self.iterations += iters
        self.evaluations += evals
        # the solver's f of the point it returns, on this problem's own objective
        self._solved = (x.copy(), float(f)) if prob is self.prob else None
        return x, LbfgsStatus(status)

    def cost(self, x: np.ndarray) -> float:
        """f(x): the solver's own value when x is the point the last ``solve`` on this
        problem's objective returned (the same arithmetic, so the same value), else evaluated."""
        if self._solved is not None and np.array_equal(self._solved[0], x):
            return self._solved[1]
        return self.objective(x)[0]

    def trajectory(self, x: np.ndarray) -> Trajectory:
        """The trajectory that x describes."""
        coeffs, T, finite = kn.trajectory_from_x(
            np.ascontiguousarray(x, dtype=np.float64), self.head, self.tail, self.tau_scale
        )
        if not finite:
            raise ValueError("durations must be positive and all parameters finite")
        return Trajectory.trusted(self.t_start_s, coeffs, T)


@dataclass(frozen=True)
class _PeerPack:
    """The peers' trajectories as the compiled code reads them: ``c (P, K, 6, 3)`` and
    ``T (P, K)``, the first ``n[k]`` pieces the peer's own, the rest a hover at its end point
    (1 s each); ``t0 (P,)`` global start times; ``vb (P,)`` a bound of each one's speed
    (``kernels.peer_speed_bounds``)."""

    c: np.ndarray
    T: np.ndarray
    n: np.ndarray
    t0: np.ndarray
    vb: np.ndarray


@dataclass(frozen=True)
class _FieldView:
    """A distance field as the compiled code reads it: the objective's tuple ``fld`` and how
    the check's unknown-space test runs (``kernels.KNOWN_*`` with the grid's mask, or in
    Python through ``field.is_known`` for other field types: ``python_known``)."""

    fld: tuple
    known_mode: int
    known: np.ndarray
    python_known: bool
    seen: np.ndarray = field(default_factory=lambda: _NO_KNOWN)
    """KNOWN_MASK: cells observed or counted occupied (an ``EsdfField``'s ``occupied``: the
    shadow behind a hit), for the neighbourhood test (``check_known_margin_m``)."""


def _pack_peers(peers: Sequence[PeerTrajectory]) -> _PeerPack:
    if not peers:  # writable arrays like a full pack's (one compiled signature)
        return _PeerPack(
            np.zeros((0, 1, 6, 3)),
            np.ones((0, 1)),
            np.zeros(0, dtype=np.int64),
            np.zeros(0),
            np.zeros(0),
        )
    trs = [pt.trajectory for pt in peers]
    ns = [tr.durations_s.shape[0] for tr in trs]
    P = len(trs)
    K = max(ns)
    t0 = np.array([tr.t0_s for tr in trs], dtype=np.float64)
    n = np.array(ns, dtype=np.int64)
    flat_c = np.concatenate([tr.coeffs for tr in trs])
    flat_T = np.concatenate([tr.durations_s for tr in trs])
    if min(ns) == K:
        ends = np.zeros((P, 3))  # no padding
    else:  # unused pieces continue as a hover at the end point (zero velocity)
        ends = np.array(
            [tr.end_position if k < K else _ZERO3 for tr, k in zip(trs, ns, strict=True)]
        )
    # compiled also when no padding is needed, so that every replan with peers loads it
    pc, pT = kn.pad_peers(flat_c, flat_T, n, ends, K)
    return _PeerPack(pc, pT, n, t0, kn.peer_speed_bounds(pc, pT))


def _vectors(
    start_p: np.ndarray, start_v: np.ndarray, start_a: np.ndarray, goal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The four input vectors as float64 3-vectors (rows of one new array), checked finite;
    ValueError naming the first bad one."""
    try:
        a = np.array((start_p, start_v, start_a, goal), dtype=np.float64)
        ok = a.shape == (4, 3) and all(map(math.isfinite, a.ravel().tolist()))
    except (TypeError, ValueError):
        ok = False
    if not ok:  # the per-vector checks say which one
        return (
            _vec3("start_p", start_p),
            _vec3("start_v", start_v),
            _vec3("start_a", start_a),
            _vec3("goal", goal),
        )
    return a[0], a[1], a[2], a[3]


def _still_peers(peers: Sequence[PeerTrajectory], t_s: float) -> np.ndarray:
    """(K, 3) where the peers that hold still from ``t_s`` on stand: a peer whose trajectory
    stays within ``STILL_M`` of its position at ``t_s`` over the next ``STILL_S`` (a hover
    where a silent peer may have stopped, a stuck drone's re-announced hover, a peer at rest
    at the end of its plan)."""
    ts = t_s + np.linspace(0.0, STILL_S, 5)
    out = []
    for peer in peers:
        pts = peer.trajectory.sample(ts)
        if float(np.max(np.linalg.norm(pts - pts[0], axis=1))) < STILL_M:
            out.append(pts[0])
    return np.array(out, dtype=np.float64).reshape(-1, 3)


class _WithPoints:
    """A field with vertical cylinders added (radius ``radius`` about each of ``points``):
    what the A* guide path searches, so that it leads around peers that hold still, which the
    field does not know, rather than over them (the drones fly at one altitude; the trajectory
    keeps it). Used for A* only (distance, and unknown space as the field's)."""

    def __init__(self, field: DistanceField, points: np.ndarray, radius: float) -> None:
        self.field = field
        self.points = points
        self.radius = radius

    def distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, g = self.field.distance(points)
        d = np.array(d, dtype=np.float64)
        g = np.array(g, dtype=np.float64)
        for q in self.points:
            off = points - q
            off[:, 2] = 0.0
            r = np.linalg.norm(off, axis=1)
            dq = r - self.radius
            closer = dq < d
            d[closer] = dq[closer]
            g[closer] = off[closer] / np.maximum(r[closer], 1e-12)[:, None]
        return d, g

    def kernel_data(self) -> FieldData:
        raise NotImplementedError("a field for the A* search only")

    def is_known(self, points: np.ndarray) -> np.ndarray:
        return self.field.is_known(points)


_Finished = tuple[Trajectory | None, bool, str, float, float]
"""A ``FormationPlanner._finish`` result: (trajectory, safe, why, clearance, ahead)."""


def _standing(finished: _Finished) -> int:
    """How a ``FormationPlanner._finish`` result stands: 2 accepted outright, 1 a last resort
    (safe with a reason), 0 refused, -1 no trajectory."""
    traj, safe, why = finished[0], finished[1], finished[2]
    if traj is None:
        return -1
    return (1 if why else 2) if safe else 0


def _vec3(name: str, v: np.ndarray | Sequence[float]) -> np.ndarray:
    try:
        a = np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not all(map(math.isfinite, a.tolist())):
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    return a


class Pending(Protocol):
    """A call started elsewhere (``concurrent.futures.Future`` is one)."""

    def result(self) -> Any: ...


class SideExecutor(Protocol):
    """Where the warm start's part of an attempt runs while the calling thread solves the fresh
    start (``fresh_alternative``): anything that starts a call and hands back its ``Pending``
    result (``concurrent.futures.ThreadPoolExecutor`` is one; the compiled solver and checks
    release the GIL). The caller owns it: the planner starts no thread."""

    def submit(self, fn: Callable[[], Any], /) -> Pending: ...


class _Beside:
    """The fresh start's ``problem`` solved in the calling thread (``solve``) while ``work``,
    the warm start's part of the attempt, runs on a ``SideExecutor``. The fresh solve sets a
    replan's time, so it starts at once, not when another thread wakes up; the warm part, the
    shorter, takes the hand-off. ``work`` returns (its outcome, whether the fresh solution is
    still wanted); when it is not, the fresh solve is stopped at its next evaluation."""

    def __init__(
        self, problem: Problem, side: SideExecutor, work: Callable[[], tuple[Any, bool]]
    ) -> None:
        self.problem = problem
        self._x = np.zeros(0)
        self._status = LbfgsStatus.CANCELED

        def run() -> Any:
            wanted = False
            try:
                out, wanted = work()
                return out
            finally:
                if not wanted:
                    problem.cancel_flag[0] = 1

        self._pending = side.submit(run)

    def solve(self) -> Any:
        """Solve the fresh start here, then wait for the warm part: its outcome. The warm part
        is waited for also when the solve fails, so that no planner code outlives the replan."""
        try:
            self._x, self._status = self.problem.solve()
        finally:
            out = self._pending.result()
        return out

    def take(self) -> tuple[np.ndarray, LbfgsStatus]:
        """(x, status) of the fresh solve, after ``solve``."""
        return self._x, self._status


class FormationPlanner:
    """Plans one drone's trajectory in the formation (its ``slot`` of ``formation``).

    ``side``: where the warm start's part of an attempt runs while the calling thread solves the
    fresh start (``fresh_alternative``; None: one after the other, in the calling thread). The
    plans are the same either way; with a free core they come sooner."""

    def __init__(
        self,
        params: PlannerParams,
        formation: np.ndarray,
        slot: int,
        edge_mask: np.ndarray | None = None,
        side: SideExecutor | None = None,
    ) -> None:
        F = np.asarray(formation, dtype=np.float64)
        if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] < 1 or not np.all(np.isfinite(F)):
            raise ValueError(f"formation must be a finite (N, 3) array, got shape {F.shape}")
        if not 0 <= slot < F.shape[0]:
            raise ValueError(f"slot {slot} is outside the formation of {F.shape[0]} drones")
        mask = complete_mask(F.shape[0]) if edge_mask is None else np.asarray(edge_mask, float)
        if mask.shape != (F.shape[0], F.shape[0]):
            raise ValueError("edge_mask must be (N, N)")
        self.params = params
        self.formation = F
        self.slot = slot
        self.mask = mask
        self._active: Problem | None = None
        self._side = side
        self._aside: Problem | None = None  # the fresh start solved beside the warm one
        self._prm_formation = self._param_vector(use_formation=True)
        self._prm_no_formation = self._param_vector(use_formation=False)
        self._lb_prm = params.lbfgs.to_array()
        # a solution that fails the safety check is refined with tight tolerances first
        self._lb_prm_refine = dataclasses.replace(
            params.lbfgs, delta=min(params.lbfgs.delta, 1e-6), g_epsilon=1e-7
        ).to_array()
        # the fresh start's coarse pass stops early (``fresh_coarse_delta``)
        self._lb_prm_coarse = dataclasses.replace(
            params.lbfgs, delta=params.fresh_coarse_delta
        ).to_array()
        self._desired_cache: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._view: tuple[weakref.ref[DistanceField], _FieldView] | None = None

    def _param_vector(self, use_formation: bool) -> np.ndarray:
        """The packed weights and limits the compiled objective reads."""
        p = self.params
        prm = np.zeros(obj.N_PRM)
        prm[obj.P_W_TIME] = p.w_time
        prm[obj.P_W_OBS] = p.w_obstacle
        prm[obj.P_D_OBS] = p.obstacle_clearance_m
        prm[obj.P_W_SWARM] = p.w_swarm
        prm[obj.P_D_SWARM] = p.swarm_clearance_m
        prm[obj.P_Z_SCALE] = p.swarm_z_scale
        prm[obj.P_W_FEAS] = p.w_feasibility
        prm[obj.P_V_MAX] = p.v_max_m_s * p.limit_margin
        prm[obj.P_A_MAX] = p.a_max_m_s2 * p.limit_margin
        prm[obj.P_J_MAX] = p.j_max_m_s3 * p.limit_margin
        prm[obj.P_W_UNIF] = p.w_uniform
        prm[obj.P_W_FORM] = p.w_formation if use_formation else 0.0
        prm[obj.P_FORM_MODE] = obj.FORM_MODES[p.formation_penalty]
        prm[obj.P_TAU_SCALE] = p.tau_scale
        prm[obj.P_FORM_STRIDE] = p.formation_stride
        prm[obj.P_FORM_FRONT] = p.formation_front_gain
        prm[obj.P_FORM_FRONT_S] = p.formation_front_s
        prm[obj.P_W_ALT] = p.w_altitude
        prm[obj.P_Z_LO], prm[obj.P_Z_HI] = p.altitude_band_inner_m
        prm[obj.P_W_HOLD] = p.w_altitude_hold  # P_Z_HOLD: set per problem (the goal's z)
        prm[obj.P_HOLD_KNEE] = p.altitude_hold_knee_m
        prm[obj.P_W_HARD] = p.w_limit_hard
        prm[obj.P_V_HARD] = p.v_max_m_s
        prm[obj.P_A_HARD] = p.a_max_m_s2
        prm[obj.P_J_HARD] = p.j_max_m_s3
        prm.setflags(write=False)
        return prm

    def _desired(self, slots: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired normalised adjacency, edge mask and points of the sub-formation
        [own, peers...]."""
        hit = self._desired_cache.get(slots)
        if hit is None:
            idx = np.array(slots)
            m = np.ascontiguousarray(self.mask[np.ix_(idx, idx)])
            pts = np.ascontiguousarray(self.formation[idx])
            sdes = normalized_adjacency(pts, m)
            if len(self._desired_cache) > 256:
                self._desired_cache.clear()
            hit = (sdes, m, pts)
            self._desired_cache[slots] = hit
        return hit

    def _into_band(self, point: np.ndarray) -> np.ndarray:
        """``point`` with its z moved into the altitude band ``z_limits_m`` (a goal outside
        the band is approached as close as the band allows)."""
        lo, hi = self.params.z_limits_m
        point[2] = min(max(float(point[2]), lo), hi)
        return point

    def cancel(self) -> None:
        """Ask a running solve (in another thread), and the fresh start's solved beside it, to
        stop at their next evaluation."""
        for problem in (self._active, self._aside):
            if problem is not None:
                problem.cancel_flag[0] = 1

    # --- problem set-up ---------------------------------------------------------------------

    def _initial_x(
        self,
        t_start: float,
        sp: np.ndarray,
        sv: np.ndarray,
        goal: np.ndarray,
        field: DistanceField,
        fld: tuple,
        previous: Trajectory | None,
        force_astar: bool,
        astar_margin_m: float,
        ladder: tuple[float, ...],
        horizon_m: float,
        peers: Sequence[PeerTrajectory] = (),
        v_guess: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """(local target, solver start x0, clearance of the A* path or NaN). The initial path is the
        previous trajectory (the warm start keeps its timing), else a straight line, else an A* path
        (at the largest of the clearances ``ladder`` that finds one; none when the ladder is empty)
        when the line is blocked; it is resampled into MINCO pieces of about ``piece_length_m``. The
        local target lies ``horizon_m`` along the line to ``goal`` (``_swarm_setup``). The A* search
        treats the peers outside the formation term (avoided only: silent, stuck, expired, the
        hovers where a silent one may have stopped) that hold still (``_still_peers``) as obstacles
        too; formation peers move on with the swarm. A path without times is timed at
        ``v_guess`` (default ``v_max_m_s``)."""
        p = self.params
        v = p.v_max_m_s if v_guess is None else v_guess
        lo, hi = p.z_limits_m
        use_prev = previous is not None and not force_astar
        code, target, x0 = kn.initial_guess(
            t_start,
            sp,
            sv,
            goal,
            horizon_m,
            p.obstacle_clearance_m,
            lo,
            hi,
            fld,
            previous.coeffs if previous is not None else _NO_COEFFS,
            previous.durations_s if previous is not None else _NO_DURATIONS,
            previous.t0_s if previous is not None else 0.0,
            use_prev,
            not force_astar,
            p.check_obstacle_m,
            v,
            p.a_max_m_s2,
            p.piece_length_m,
            p.max_pieces,
            p.tau_scale,
        )
        clearance = math.nan
        if code == kn.GUESS_NEEDS_ASTAR:
            if ladder:
                row = self.mask[self.slot]
                still = _still_peers([pt for pt in peers if not row[pt.slot] > 0.0], t_start)
                if still.shape[0]:
                    radius = max(p.swarm_clearance_m, p.check_drone_m) - p.obstacle_clearance_m
                    field = _WithPoints(field, still, max(radius, 0.0))
                path, clearance = self._astar(sp, target, field, astar_margin_m, ladder)
                path[0] = sp
            else:  # no clearance to search at: the line, as a search that finds nothing gives
                path = np.vstack([sp, target])
            x0 = kn.path_guess(
                path,
                _NO_DURATIONS,
                False,
                sv,
                v,
                p.a_max_m_s2,
                p.piece_length_m,
                p.max_pieces,
                p.tau_scale,
            )
        return target, x0, clearance

    def _astar(
        self,
        start: np.ndarray,
        target: np.ndarray,
        field: DistanceField,
        margin_m: float,
        ladder: tuple[float, ...],
    ) -> tuple[np.ndarray, float]:
        """(path (K, 3), its clearance): an A* path start-target at the first of the
        clearances ``ladder`` that finds one, else the straight line and NaN."""
        p = self.params
        path, clearance = astar_path_levels(
            field,
            start,
            target,
            ladder,
            resolution_m=p.astar_resolution_m,
            margin_m=margin_m,
            z_limits=p.altitude_band_inner_m,
        )
        if path is None:
            return np.vstack([start, target]), math.nan
        return np.ascontiguousarray(path, dtype=np.float64), clearance

    def _swarm_setup(
        self,
        t_s: float,
        sp: np.ndarray,
        goal: np.ndarray,
        peers: Sequence[PeerTrajectory],
        pack: _PeerPack,
        lead: bool,
    ) -> tuple[np.ndarray, float, float]:
        """(goal, horizon, lead) of ``kernels.swarm_setup`` for this drone at ``sp`` and its
        formation peers (those with an edge to its slot) at ``t_s``."""
        n = self.formation.shape[0]
        row = self.mask[self.slot]
        rows = [j for j, pt in enumerate(peers) if pt.slot < n and row[pt.slot] > 0.0]
        slots = [self.slot] + [peers[j].slot for j in rows]
        p = self.params
        goal_t, horizon, amount = kn.swarm_setup(
            pack.c,
            pack.T,
            pack.n,
            pack.t0,
            float(t_s),
            np.array(rows, dtype=np.int64),
            self.formation[slots],
            sp,
            goal,
            p.horizon_m,
            SWARM_TARGET_MIN_M,
            _REF_MODES[p.swarm_target],
            lead,
            p.lead_from_slowest,
            p.lead_turned,
            p.lead_slowest_beyond_m,
        )
        return goal_t, float(horizon), float(amount)

    def _check_time_and_peers(self, t_start_s: float, peers: Sequence[PeerTrajectory]) -> None:
        """ValueError unless t_start_s is finite and every peer has its own formation slot."""
        if not math.isfinite(t_start_s):
            raise ValueError("t_start_s must be finite")
        n = self.formation.shape[0]
        slots = [pt.slot for pt in peers]
        if not slots or (
            min(slots) >= 0
            and max(slots) < n
            and self.slot not in slots
            and len(set(slots)) == len(slots)
        ):
            return
        seen: set[int] = {self.slot}
        for pt in peers:
            if not 0 <= pt.slot < n:
                raise ValueError(f"peer {pt.drone_id} has slot {pt.slot} outside the formation")
            if pt.slot in seen:
                raise ValueError(f"peer {pt.drone_id} has slot {pt.slot}, already taken")
            seen.add(pt.slot)

    def _vectors_in_band(
        self, start_p: np.ndarray, start_v: np.ndarray, start_a: np.ndarray, goal: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        sp, sv, sa, gl = _vectors(start_p, start_v, start_a, goal)
        return sp, sv, sa, self._into_band(gl)

    def prepare(
        self,
        t_start_s: float,
        start_p: np.ndarray,
        start_v: np.ndarray,
        start_a: np.ndarray,
        goal: np.ndarray,
        peers: Sequence[PeerTrajectory],
        field: DistanceField,
        previous: Trajectory | None = None,
        use_formation: bool = True,
        force_astar: bool = False,
        astar_margin_m: float = 3.0,
        astar_ladder_m: Sequence[float] | None = None,
        fresh: bool = False,
    ) -> Problem:
        """Build the optimisation problem of one replan (validated inputs, initial guess).
        An A* initial path tries the clearances ``astar_ladder_m`` (default
        ``params.astar_ladder_m``; the rescue attempt's are ``params.astar_rescue_ladder_m``).
        ``fresh``: the problem of ``fresh_alternative``'s second solve instead, as ``plan``
        builds it (``previous`` not read; from the straight line when ``fresh_alternative`` is
        'line', else from an A* path on the ladder), for benchmarks that time that solve."""
        self._check_time_and_peers(t_start_s, peers)
        ladder = self.params.astar_ladder_m if astar_ladder_m is None else astar_ladder_m
        levels = tuple(float(c) for c in ladder)
        if not levels or not all(math.isfinite(c) and c > 0.0 for c in levels):
            raise ValueError(f"astar_ladder_m must hold positive numbers, got {ladder!r}")
        if not isinstance(fresh, bool):
            raise ValueError(f"fresh must be a bool, got {fresh!r}")
        return self._prepare(
            t_start_s,
            *self._vectors_in_band(start_p, start_v, start_a, goal),
            peers,
            _pack_peers(peers),
            field,
            obj.field_args(field.kernel_data()),
            None if fresh else previous,
            use_formation,
            force_astar,
            astar_margin_m,
            levels,
            fresh=fresh,
        )

    def _prepare(
        self,
        t_start_s: float,
        sp: np.ndarray,
        sv: np.ndarray,
        sa: np.ndarray,
        gl: np.ndarray,
        peers: Sequence[PeerTrajectory],
        pack: _PeerPack,
        field: DistanceField,
        fld: tuple,
        previous: Trajectory | None,
        use_formation: bool,
        force_astar: bool,
        astar_margin_m: float,
        ladder: tuple[float, ...],
        formation_scale: float = 1.0,
        setups: dict[bool, tuple[np.ndarray, float, float]] | None = None,
        fresh: bool = False,
    ) -> Problem:
        """``prepare`` on validated inputs, the peers packed and the field's kernel tuple;
        ``formation_scale``: the formation weight times this (with ``use_formation``);
        ``setups``: the swarm set-up (``_swarm_setup``) of the same start and peers, by its
        ``lead`` flag, kept from one attempt of a replan to the next (filled here); ``fresh``:
        the problem is ``fresh_alternative``'s second solve (``previous`` None): its guess is
        timed at ``fresh_guess_speed_frac`` of the speed limit, it searches no A* path where
        ``fresh_alternative`` is 'line' (``ladder`` not read) and it gets the coarse pass of
        ``fresh_coarse_kappa``."""
        p = self.params
        if fresh and p.fresh_alternative == "line":
            ladder = ()
        formation_on = use_formation and p.w_formation > 0 and len(peers) > 0
        want_lead = formation_on and p.lead_slowdown_m > 0.0
        if len(peers) > 0:
            known = None if setups is None else setups.get(want_lead)
            if known is None:
                known = self._swarm_setup(t_start_s, sp, gl, peers, pack, want_lead)
                if setups is not None:
                    setups[want_lead] = known
            goal_t, horizon, lead = known[0].copy(), known[1], known[2]
        else:
            goal_t, horizon, lead = gl, p.horizon_m, 0.0
        # the lead slow-down's factor on the speed limit (1: none)
        lead_factor = 1.0
        if want_lead:
            lead -= p.lead_deadband_m
            if lead > 0.0:
                lead_factor = max(p.lead_min_speed_frac, 1.0 - lead / p.lead_slowdown_m)
        v_guess = None
        if fresh and p.fresh_guess_speed_frac > 0.0:
            v_guess = p.fresh_guess_speed_frac * p.v_max_m_s * p.limit_margin * lead_factor
        target, x0, astar_clearance = self._initial_x(
            t_start_s,
            sp,
            sv,
            goal_t,
            field,
            fld,
            previous,
            force_astar,
            astar_margin_m,
            ladder,
            horizon,
            peers,
            v_guess,
        )
        head = np.array((sp, sv, sa))
        tail = np.zeros((3, 3))
        tail[0] = target
        if formation_on:
            sdes, m, fpts = self._desired((self.slot, *(pt.slot for pt in peers)))
        else:
            m = np.zeros((1, 1))
            sdes = np.zeros((1, 1))
            fpts = np.zeros((1, 3))
        prm = self._prm_formation if use_formation else self._prm_no_formation
        if use_formation and formation_scale != 1.0:
            prm = prm.copy()
            prm[obj.P_W_FORM] *= formation_scale
        if lead_factor != 1.0:
            prm = prm.copy()
            prm[obj.P_V_MAX] *= lead_factor
        if p.pace_floor_frac > 0.0 and formation_on and bool(np.all(goal_t == gl)):
            # the pace floor, where the local target is the drone's own goal: no plan slower
            # than this on average to it (with the time to brake and a slack), so that drones
            # that follow each other's plans through the formation term cannot settle on an
            # ever later common arrival (without the term nothing holds a plan back)
            prm = prm.copy()
            dist = float(np.linalg.norm(target - sp))
            brake = float(np.linalg.norm(sv)) / (p.a_max_m_s2 * p.limit_margin)
            prm[obj.P_W_PACE] = p.w_pace
            prm[obj.P_T_CAP] = (
                dist / (p.pace_floor_frac * p.v_max_m_s * p.limit_margin) + brake + p.pace_slack_s
            )
        if p.target_speed_frac > 0.0:
            # the local target passed at speed along the way on, as long as the goal lies far
            # enough beyond it to stop there: plans that end at rest make every drone's
            # prediction of its peers slow down, and the formation term follows them
            on = gl - target
            rest = float(np.linalg.norm(on))
            v_end = float(prm[obj.P_V_MAX]) * p.target_speed_frac
            if rest > 1e-6 and rest >= v_end * v_end / (2.0 * p.a_max_m_s2 * p.limit_margin):
                tail[1] = v_end * on / rest
        if p.w_altitude_hold > 0.0:
            prm = prm.copy()
            prm[obj.P_Z_HOLD] = gl[2]
        if prm.flags.writeable:
            # read-only like the shared vector it was copied from: numba types an array's
            # writability, and a second type of the problem would compile the objective anew
            # (tens of seconds) at the first replan that copies, or does not copy, it
            prm.setflags(write=False)
        pt0 = pack.t0 - t_start_s
        prob = (head, tail, p.kappa, prm, pack.c, pack.T, pt0, sdes, m, fpts, pack.vb)
        problem = Problem(p, float(t_start_s), head, tail, x0, prob, fld, self._lb_prm)
        problem.astar_clearance_m = astar_clearance
        if fresh and p.fresh_coarse_kappa > 0:
            # the pass from the guess on a few constraint points, the formation term at each
            c_prm = prm.copy()
            c_prm[obj.P_FORM_STRIDE] = 1.0
            c_prm.setflags(write=False)  # as the planner's: one compiled version
            problem.coarse = (
                (head, tail, p.fresh_coarse_kappa, c_prm, *prob[4:]),
                self._lb_prm_coarse,
            )
        return problem

    # --- acceptance -------------------------------------------------------------------------

    def check(
        self,
        traj: Trajectory,
        t_from_s: float,
        field: DistanceField,
        peers: Sequence[PeerTrajectory],
    ) -> tuple[bool, str]:
        """Is ``traj`` safe to fly from ``t_from_s`` on? (ok, reason when not).

        Safe means: (0) inside the altitude band ``z_limits_m`` (a start outside it may fly
        back in, never farther out); (1) clear of obstacles by ``check_obstacle_m`` (over its
        first ``check_obstacle_horizon_s`` when that is > 0) and of every peer by
        ``check_drone_m`` to its end (over its first ``check_drone_horizon_s`` when that is
        > 0; held there to ``brake_reference_s`` at least: a stop or a
        hover is judged against the peers that come on meanwhile); a drone that is already
        closer than that
        at ``t_from_s`` (pushed in by a peer, a late-mapped trunk, an emergency stop), even
        inside a mapped (inflated) obstacle, may fly a trajectory that never comes closer than
        it starts (or than a braking stop from there would within ``brake_reference_s``, if
        that is closer: still moving inward, or a peer coming on) and leaves the band, so it
        can always back out; a trajectory that starts outside and comes inside, but no closer
        than that stop, is accepted with a reason (``MARGINAL``), which ``plan`` flies only as
        a last resort; (2) during the first
        ``check_known_s`` (the part flown before the next replan can replace it) it does not
        enter space the field has not observed (``field.is_known``); a start in unobserved
        space may be left. Positions are sampled every ``check_step_s`` from
        ``t_from_s`` to the end; obstacle distances are those of ``field.kernel_data()`` (the
        field the optimiser sees).
        """
        view = self._field_view(field)
        ok, why, _, _ = self._check(traj, t_from_s, field, view, peers, _pack_peers(peers))
        return ok, why

    def _field_view(self, field: DistanceField) -> _FieldView:
        """The field's view for the compiled code; the last one is kept for a field of the
        immutable kinds (an exact field, a grid or ESDF), whose maps are new objects when
        they change."""
        cached = self._view
        if cached is not None and cached[0]() is field:
            return cached[1]
        view = self._make_field_view(field)
        kernel_data = getattr(type(field), "kernel_data", None)
        if kernel_data is AnalyticField.kernel_data or kernel_data is GridField.kernel_data:
            self._view = (weakref.ref(field), view)
        return view

    def _make_field_view(self, field: DistanceField) -> _FieldView:
        fld = obj.field_args(field.kernel_data())
        if self.params.check_known_s <= 0.0:
            return _FieldView(fld, kn.KNOWN_SKIP, _NO_KNOWN, False)
        is_known = getattr(type(field), "is_known", None)
        if isinstance(field, AnalyticField) and is_known is AnalyticField.is_known:
            return _FieldView(fld, kn.KNOWN_SKIP, _NO_KNOWN, False)  # known everywhere
        if isinstance(field, GridField) and is_known is GridField.is_known:
            if field.known is None:
                return _FieldView(fld, kn.KNOWN_BOX, _NO_KNOWN, False)
            seen = field.known
            occupied = getattr(field, "occupied", None)
            if self.params.check_known_margin_m > 0.0 and isinstance(occupied, np.ndarray):
                if occupied.shape == seen.shape and occupied.dtype == np.bool_:
                    seen = seen | occupied
                    # read-only like the mask alone: one compiled check for both (a writable
                    # mask is another type to numba; on a cold cache each flight service
                    # compiled the check again in flight, and the first plan took 65 s)
                    seen.setflags(write=False)
            return _FieldView(fld, kn.KNOWN_MASK, field.known, False, seen)
        return _FieldView(fld, kn.KNOWN_SKIP, _NO_KNOWN, True)

    def _check(
        self,
        traj: Trajectory,
        t_from_s: float,
        field: DistanceField,
        view: _FieldView,
        peers: Sequence[PeerTrajectory],
        pack: _PeerPack,
        brake: Trajectory | None = None,
    ) -> tuple[bool, str, float, float]:
        """``check`` plus the trajectory's closest approach to an obstacle, over all of it and
        from ``COMFORT_LOOKAHEAD_S`` on (NaN when the test stopped before the distances).
        ``brake``: the braking stop from ``traj``'s state at ``t_from_s`` (``_stop``; made
        here when not given), the alternative a start inside a threshold is judged against."""
        p = self.params
        if brake is None:
            brake = self._stop(t_from_s, *traj.state(t_from_s))
        res = kn.check_trajectory(
            traj.coeffs,
            traj.durations_s,
            traj.t0_s,
            float(t_from_s),
            p.check_step_s,
            p.z_limits_m[0],
            p.z_limits_m[1],
            view.fld,
            p.check_obstacle_m,
            p.check_obstacle_horizon_s,
            pack.c,
            pack.T,
            pack.n,
            pack.t0,
            p.check_drone_m,
            p.check_drone_horizon_s,
            COMFORT_LOOKAHEAD_S,
            view.known_mode,
            p.check_known_s,
            view.known,
            brake.coeffs,
            brake.durations_s,
            brake.t0_s,
            p.brake_reference_s,
            p.check_known_margin_m,
            view.seen,
        )
        return self._verdict(res, traj, t_from_s, field, view, peers)

    def _verdict(
        self,
        res: tuple,
        traj: Trajectory,
        t_from_s: float,
        field: DistanceField,
        view: _FieldView,
        peers: Sequence[PeerTrajectory],
    ) -> tuple[bool, str, float, float]:
        """(ok, reason, clearance, ahead) from ``kernels.check_trajectory``'s answer (the
        unknown-space test (2) in Python when the kernel could not run it)."""
        code, band, k, ph, value, start, t_k, clearance, ahead, n = res
        if code == kn.CHECK_OK:
            why = self._unknown_space(traj, t_from_s, field) if view.python_known else ""
            if why or band != kn.BAND_MARGINAL:
                return not why, why, clearance, ahead
            what = "obstacle clearance" if ph < 0 else f"drone {peers[ph].drone_id} at"
            why = f"{MARGINAL}{what} {value:.2f} m at t={t_k:.2f} s (a braking stop: {start:.2f} m)"
            return True, why, clearance, ahead
        if code == kn.CHECK_UNKNOWN:
            return False, f"enters unobserved space at t={t_k:.2f} s", clearance, ahead
        if code == kn.CHECK_UNKNOWN_NEAR:
            why = f"unobserved space {value:.2f} m away at t={t_k:.2f} s (from {start:.2f} m)"
            return False, why, clearance, ahead
        if code == kn.CHECK_NON_FINITE:
            return False, "non-finite trajectory", clearance, ahead
        if code == kn.CHECK_ALTITUDE:
            lo, hi = self.params.z_limits_m
            return (
                False,
                f"altitude {value:.2f} m at t={t_k:.2f} s outside the band [{lo:g}, {hi:g}] m",
                clearance,
                ahead,
            )
        if band == kn.BAND_COMES_CLOSER:
            why = f" (started inside at {start:.2f} m and comes closer)"
        elif band == kn.BAND_NO_BACK_OUT:
            why = f" (started inside at {start:.2f} m and does not back out)"
        else:
            why = ""
        if code == kn.CHECK_OBSTACLE:
            reason = f"obstacle clearance {value:.2f} m at t={t_k:.2f} s{why}"
        else:
            reason = f"drone {peers[ph].drone_id} at {value:.2f} m at t={t_k:.2f} s{why}"
        return False, reason, clearance, ahead

    def _unknown_space(self, traj: Trajectory, t_from_s: float, field: DistanceField) -> str:
        """Test (2) of ``check`` through ``field.is_known`` (fields the kernel does not know):
        the reason when ``traj`` enters unobserved space during its first ``check_known_s``
        from t_from_s, else ""."""
        p = self.params
        if p.check_known_s <= 0.0:
            return ""
        t_end = max(traj.t_end_s, t_from_s)
        ts = np.append(np.arange(t_from_s, t_end, p.check_step_s), t_end)
        n = int(np.searchsorted(ts, t_from_s + p.check_known_s, side="right"))
        known = field.is_known(traj.sample(ts[:n]))
        if not np.all(known):
            first_known = int(np.argmax(known)) if np.any(known) else n
            entered = np.nonzero(~known[first_known:])[0]
            if entered.size:
                k = first_known + int(entered[0])
                return f"enters unobserved space at t={ts[k] - t_from_s:.2f} s"
        return ""

    def _finish(
        self,
        problem: Problem,
        x: np.ndarray,
        field: DistanceField,
        view: _FieldView,
        peers: Sequence[PeerTrajectory],
        pack: _PeerPack,
        brake: Trajectory | None = None,
    ) -> tuple[Trajectory | None, bool, str, float, float]:
        """(trajectory, safe, reason, clearance, ahead) of an attempt's solution x (trajectory
        None and not safe when x or its trajectory is not finite)."""
        coeffs, T, finite = kn.trajectory_from_x(x, problem.head, problem.tail, problem.tau_scale)
        if not finite:
            return None, False, "non-finite solution", math.nan, math.nan
        traj = Trajectory.trusted(problem.t_start_s, coeffs, T)
        safe, why, clearance, ahead = self._check(
            traj, problem.t_start_s, field, view, peers, pack, brake
        )
        return traj, safe, why, clearance, ahead

    def _cap_speed(
        self,
        problem: Problem,
        x: np.ndarray,
        traj: Trajectory,
        again: Callable[
            [Problem, np.ndarray, np.ndarray | None, tuple | None], tuple[np.ndarray, LbfgsStatus]
        ],
        field: DistanceField,
        view: _FieldView,
        peers: Sequence[PeerTrajectory],
        pack: _PeerPack,
        brake: Trajectory | None,
    ) -> tuple[np.ndarray, Trajectory, str] | None:
        """``PlannerParams.speed_cap_frac``: (x, trajectory, message) of the accepted solution
        ``x`` (trajectory ``traj``) solved again from there on ``Problem.cap_prob`` (through
        ``again``: ``Problem.solve``'s call, the replan's work counted) when it is faster than
        the cap; None when it keeps the cap, or when the new solution is no slower or the
        safety check does not accept it outright (then ``traj`` is flown as it is: a few per
        cent over the limit is a lesser harm than a plan the check refuses)."""
        p = self.params
        if p.speed_cap_frac <= 0.0:
            return None
        cap = p.v_max_m_s * p.speed_cap_frac
        peak = kn.peak_speed(traj.coeffs, traj.durations_s, SPEED_CAP_SAMPLES)
        if peak <= cap:
            return None
        x2, status = again(problem, x, None, problem.cap_prob())
        if status == LbfgsStatus.CANCELED:
            return None
        slow, safe, why, _, _ = self._finish(problem, x2, field, view, peers, pack, brake)
        if slow is None or not safe or why:
            return None
        reached = kn.peak_speed(slow.coeffs, slow.durations_s, SPEED_CAP_SAMPLES)
        if reached >= peak:
            return None
        return x2, slow, f"{SPEED_CAP}: {peak:.3f} -> {reached:.3f} m/s"

    def _margin(
        self,
        traj: Trajectory,
        t_from_s: float,
        peers: Sequence[PeerTrajectory],
        clearance: float,
    ) -> float:
        """How far ``traj`` keeps beyond the check's distances, the least over the obstacles
        (its ``clearance`` from the check) and every peer (sampled every ``check_step_s`` from
        ``t_from_s`` to its end, held there to ``brake_reference_s`` at least, as the check
        does): what ranks the trajectories accepted only as a last resort."""
        p = self.params
        margin = clearance - p.check_obstacle_m if math.isfinite(clearance) else math.inf
        if peers:
            t_end = max(traj.t_end_s, t_from_s + p.brake_reference_s)
            ts = np.append(np.arange(t_from_s, t_end, p.check_step_s), t_end)
            own = traj.sample(ts)
            for pt in peers:
                d = np.linalg.norm(own - pt.trajectory.sample(ts), axis=1)
                margin = min(margin, float(d.min()) - p.check_drone_m)
        return margin

    def _evasions(
        self, t_start: float, sp: np.ndarray, sv: np.ndarray, sa: np.ndarray
    ) -> list[tuple[str, Trajectory]]:
        """Short moves to rest from the start (p, v, a) straight toward ``EVADE_DISTANCES_M``
        away in each of ``_EVADE_DIRECTIONS``, each as fast as the limits allow (to the
        nearest ``EVADE_GROWTH`` step): what a drone may fly when every optimised way comes
        inside the check's distances, a peer that does not see it coming on (the optimiser
        starts from the way to the goal and stays near it; such a move may be the one way that
        keeps clear). (label, trajectory) pairs; the safety check judges them."""
        p = self.params
        v_lim = p.v_max_m_s
        a_lim = p.a_max_m_s2
        j_lim = p.j_max_m_s3
        speed = float(np.linalg.norm(sv))
        t0 = braking_duration_s(speed, a_lim, 1.0)
        out: list[tuple[str, Trajectory]] = []
        for dist in EVADE_DISTANCES_M:
            for u in _EVADE_DIRECTIONS:
                end = sp + dist * u
                T = t0
                for _ in range(EVADE_TRIES):
                    traj = Trajectory.to_rest(t_start, sp, sv, sa, end, T)
                    ts = t_start + np.linspace(0.0, T, 25)
                    if (
                        np.linalg.norm(traj.sample(ts, 1), axis=1).max() <= v_lim
                        and np.linalg.norm(traj.sample(ts, 2), axis=1).max() <= a_lim
                        and np.linalg.norm(traj.sample(ts, 3), axis=1).max() <= j_lim
                    ):
                        x, y, z = (np.round(u, 2) + 0.0).tolist()  # no -0
                        out.append((f"{EVADE} {dist:g} m toward ({x:g}, {y:g}, {z:g})", traj))
                        break
                    T *= EVADE_GROWTH
        return out

    def fresh_due(self, t_start_s: float, previous: Trajectory | None) -> bool:
        """Whether a replan starting at ``t_start_s`` from ``previous`` may solve the fresh
        start (``fresh_alternative``) by ``fresh_period_s``: a multiple of the period lies
        after the previous trajectory's start and at or before the replan's (always with no
        period or no previous trajectory)."""
        period = self.params.fresh_period_s
        if period <= 0.0 or previous is None:
            return True
        return math.floor(t_start_s / period) != math.floor(previous.t0_s / period)

    def fresh_wanted(self, t_start_s: float, previous: Trajectory | None) -> bool:
        """Whether a replan starting at ``t_start_s`` from ``previous`` solves the fresh start
        beside the warm one where an attempt with the formation term is accepted (``plan``):
        there is a previous trajectory, ``fresh_alternative`` is not 'never' and the period is
        due (``fresh_due``); the time budget aside."""
        return (
            previous is not None
            and self.params.fresh_alternative != "never"
            and self.fresh_due(t_start_s, previous)
        )

    def _stop(self, t_start: float, sp: np.ndarray, sv: np.ndarray, sa: np.ndarray) -> Trajectory:
        """A one-piece braking trajectory to rest (a gentle stop, as the service's)."""
        return Trajectory.braking(t_start, sp, sv, sa, self.params.a_max_m_s2)

    # --- the replan -------------------------------------------------------------------------

    def plan(
        self,
        t_start_s: float,
        start_p: np.ndarray,
        start_v: np.ndarray,
        start_a: np.ndarray,
        goal: np.ndarray,
        peers: Sequence[PeerTrajectory],
        field: DistanceField,
        previous: Trajectory | None = None,
        give_up: Callable[[], bool] | None = None,
        first_attempt: int = 0,
    ) -> PlanResult:
        """One replan; see the module docstring for the sequence of attempts. ``give_up``
        (a time budget; the planner reads no clock itself) is asked before every attempt but
        the first: once it returns True, a ``previous`` that the check accepts and that moves
        the drone on is kept (``PlanStatus.OVER_BUDGET``, with the index of the attempt it gave
        up in ``resume_at``) instead of trying on; without one the attempts go on as usual,
        since the alternative would be a stop. An accepted plan then skips the comfort
        alternative (``comfort_obstacle_m``). ``first_attempt``: the sequence starts at that
        optimised attempt (the last one where there are fewer), so that the replan after one
        that gave up goes on with the attempts it gave up, from its newer start, instead of
        trying again, on a starved CPU again past the budget, those the check just refused."""
        if isinstance(first_attempt, bool) or not isinstance(first_attempt, int):
            raise ValueError(f"first_attempt must be an int, got {first_attempt!r}")
        if first_attempt < 0:
            raise ValueError(f"first_attempt must be >= 0, got {first_attempt}")
        sp, sv, sa, gl = self._vectors_in_band(start_p, start_v, start_a, goal)
        gx, gy, gz = (gl - sp).tolist()
        vx, vy, vz = sv.tolist()
        # np.linalg.norm's arithmetic on Python floats
        if math.sqrt((gx * gx + gy * gy) + gz * gz) < 0.02 and (
            math.sqrt((vx * vx + vy * vy) + vz * vz) < 0.05
        ):
            hover = Trajectory.hover(gl, t_start_s, duration_s=1.0)
            return PlanResult(PlanStatus.OK, hover, message="at goal")
        self._check_time_and_peers(t_start_s, peers)
        pack = _pack_peers(peers)
        view = self._field_view(field)

        @functools.cache
        def brake() -> Trajectory:
            """The stop flown if every attempt is refused: what a start inside the check's
            distance compares its ways out with. Made on first use, by the warm start's part
            of the attempt (``attempt``): not on the way to the fresh start's solve, which sets
            the replan's time."""
            return self._stop(t_start_s, sp, sv, sa)

        iters = evals = 0
        messages: list[str] = []
        last_status: LbfgsStatus | None = None
        # trajectories the check accepts only as a last resort (``MARGINAL``), with how far
        # each keeps beyond the check's distances (``_margin``)
        last_resorts: list[
            tuple[float, tuple[PlanStatus, Trajectory, LbfgsStatus | None, Problem, np.ndarray]]
        ] = []
        refused: list[tuple[PlanStatus, Trajectory, LbfgsStatus | None, Problem, np.ndarray]] = []
        # the swarm set-up of this start and these peers, shared by the attempts
        setups: dict[bool, tuple[np.ndarray, float, float]] = {}

        fresh_wanted = self.fresh_wanted(t_start_s, previous)

        def late() -> bool:
            """Whether the caller's time budget (``give_up``) says stop trying."""
            return give_up is not None and give_up()

        def prepare(
            use_formation: bool,
            force_astar: bool,
            astar_margin_m: float = 3.0,
            ladder: tuple[float, ...] = self.params.astar_ladder_m,
            fresh: bool = False,
            formation_scale: float = 1.0,
        ) -> Problem:
            """The problem of one attempt; ``fresh``: from the straight line, not from
            ``previous`` (where the line is blocked, an A* path on ``ladder``; an empty ladder
            keeps the line); ``formation_scale``: of the formation weight."""
            return self._prepare(
                t_start_s,
                sp,
                sv,
                sa,
                gl,
                peers,
                pack,
                field,
                view.fld,
                None if fresh else previous,
                use_formation,
                force_astar,
                astar_margin_m,
                ladder,
                formation_scale,
                setups,
                fresh,
            )

        def solve(problem: Problem) -> tuple[Problem, np.ndarray, LbfgsStatus]:
            """Solve one attempt's problem (``prepare``; cancellable meanwhile), counting its
            work."""
            nonlocal iters, evals
            self._active = problem
            try:
                x, status = problem.solve()
            finally:
                self._active = None
            iters += problem.iterations
            evals += problem.evaluations
            return problem, x, status

        def again(
            problem: Problem, x: np.ndarray, lb_prm: np.ndarray | None, prob: tuple | None
        ) -> tuple[np.ndarray, LbfgsStatus]:
            """Solve an attempt's problem again from ``x`` (``Problem.solve``'s arguments;
            cancellable meanwhile), its work counted in the result, as every solve's."""
            nonlocal iters, evals
            done = (problem.iterations, problem.evaluations)
            self._active = problem
            try:
                return problem.solve(x, lb_prm, prob)
            finally:
                self._active = None
                iters += problem.iterations - done[0]
                evals += problem.evaluations - done[1]

        def prepare_fresh(use_formation: bool, formation_scale: float) -> Problem:
            """The problem of ``fresh_alternative``'s second solve of an attempt."""
            return prepare(use_formation, False, fresh=True, formation_scale=formation_scale)

        def wants_fresh(use_formation: bool, force_astar: bool) -> bool:
            """Whether an attempt accepted from the warm start is solved again from a fresh
            start (``fresh_alternative``), but for the time budget."""
            return use_formation and not force_astar and fresh_wanted

        def collect(side: _Beside) -> tuple[Problem, np.ndarray, LbfgsStatus]:
            """The fresh start solved beside the warm one, taken, its work counted (that of
            one not taken is not: one solve after the other would not have started it, and how
            far it got before it was stopped depends on the timing)."""
            nonlocal iters, evals
            x, status = side.take()
            iters += side.problem.iterations
            evals += side.problem.evaluations
            return side.problem, x, status

        def alternative(
            solved: tuple[Problem, np.ndarray, LbfgsStatus],
        ) -> tuple[Problem, np.ndarray, LbfgsStatus, Trajectory, float, float] | None:
            """A second solve of an accepted attempt (what ``solve`` returned): (problem, x,
            status, trajectory, clearance, ahead) when the check accepts it outright, else None
            (refused, a last resort, not finite or canceled)."""
            alt, x_alt, st_alt = solved
            if st_alt == LbfgsStatus.CANCELED:
                return None
            traj_alt, ok_alt, why_alt, clr_alt, ahead_alt = self._finish(
                alt, x_alt, field, view, peers, pack, brake()
            )
            if traj_alt is None or not ok_alt or why_alt:
                return None
            return alt, x_alt, st_alt, traj_alt, clr_alt, ahead_alt

        def attempt(
            use_formation: bool,
            force_astar: bool,
            ok_status: PlanStatus,
            what: str,
            ladder: tuple[float, ...] = self.params.astar_ladder_m,
            formation_scale: float = 1.0,
        ) -> tuple[PlanResult | None, Problem, bool]:
            """One attempt: (its result when the check accepts it, else None with the reason
            in ``messages``; its problem; whether it was canceled). An accepted rescue says so
            in the message, with the clearance of its A* path. A trajectory the check accepts
            only as a last resort (``MARGINAL``) is kept in ``last_resorts``
            and the attempt counts as refused."""
            nonlocal last_status
            label = what if use_formation else f"{what} without formation"
            # the fresh start's problem, solved beside the warm one when it is wanted (the
            # same result as one after the other: neither reads the other's work)
            fresh_problem: Problem | None = None
            if self._side is not None and wants_fresh(use_formation, force_astar) and not late():
                fresh_problem = prepare_fresh(use_formation, formation_scale)
            # each candidate's ``_margin``, computed once (the candidate held, so that its id
            # is not reused)
            margins: dict[int, tuple[_Finished, float]] = {}

            def margin_of(c: _Finished) -> float:
                if id(c) not in margins:
                    assert c[0] is not None
                    margins[id(c)] = (c, self._margin(c[0], t_start_s, peers, c[3]))
                return margins[id(c)][1]

            def beats(new: _Finished, old: _Finished, on_refused_tie: bool) -> bool:
                """Whether ``new`` stands higher than ``old`` (``_standing``: accepted
                outright, a last resort, refused, none); of two last resorts the one that
                keeps farther beyond the check's distances; of two refused ones
                ``on_refused_tie``."""
                s_new, s_old = _standing(new), _standing(old)
                if s_new != s_old:
                    return s_new > s_old
                if s_new == 1:
                    return margin_of(new) > margin_of(old)
                return s_new == 0 and on_refused_tie

            def warm() -> tuple[tuple[Problem, np.ndarray, _Finished], bool]:
                """The warm start's part: its solve, check and refinement. ((problem, x, the
                candidate flown: no trajectory when the solve was canceled, ``last_status``
                then says so), whether the fresh start's solution is still wanted: only beside
                an attempt accepted outright)."""
                nonlocal last_status
                problem, x, last_status = solve(
                    prepare(
                        use_formation, force_astar, ladder=ladder, formation_scale=formation_scale
                    )
                )
                if last_status == LbfgsStatus.CANCELED:
                    return (problem, x, (None, False, "canceled", math.nan, math.nan)), False
                first = self._finish(problem, x, field, view, peers, pack, brake())
                traj, safe, why, clearance, ahead = first
                if traj is None:
                    return (problem, x, first), False
                chosen: _Finished = first  # what is flown: the first solution or a refinement
                if not safe or why:
                    # tighter; where it passes too close to an obstacle also on denser points
                    # and stiffer (NaN: the test stopped before the distances); a last resort
                    # is replaced by a trajectory the check accepts outright, or by a last
                    # resort that keeps farther beyond the check's distances, a refused one by
                    # any
                    close = clearance < self.params.check_obstacle_m
                    stiffer = problem.refine_prob() if close else None
                    x2, st2 = again(problem, x, self._lb_prm_refine, stiffer)
                    if st2 != LbfgsStatus.CANCELED:
                        refined = self._finish(problem, x2, field, view, peers, pack, brake())
                        if (
                            stiffer is not None
                            and stiffer is not problem.prob
                            and _standing(refined) != 2
                            and not late()
                        ):
                            # the stiffer solve (``refine_penalty_scale``,
                            # ``refine_kappa_factor``) not accepted outright: the plain tight
                            # one too, and of the two the one standing higher (the stiffer one
                            # on a tie). The stiffer obstacle term alone can hold a drone in the
                            # middle of a corridor of trunks, where a peer overtaking it flies
                            # (0.37 m from it against 0.55 m)
                            x3, st3 = again(problem, x, self._lb_prm_refine, None)
                            if st3 != LbfgsStatus.CANCELED:
                                plain = self._finish(problem, x3, field, view, peers, pack, brake())
                                if beats(plain, refined, on_refused_tie=False):
                                    x2, st2, refined = x3, st3, plain
                        if beats(refined, first, on_refused_tie=True):
                            if _standing(refined) == 2:
                                # flown as refined: the first solution's refusal stays on
                                # record (not counted as a refused attempt: it names no attempt
                                # first)
                                messages.append(f"refined {label}: {why}")
                            x, last_status = x2, st2
                            chosen = refined
                return (problem, x, chosen), _standing(chosen) == 2

            beside: _Beside | None = None
            if fresh_problem is None or self._side is None:
                (problem, x, chosen), _ = warm()
            else:
                self._aside = fresh_problem
                try:
                    beside = _Beside(fresh_problem, self._side, warm)
                    problem, x, chosen = beside.solve()
                finally:
                    self._aside = None  # its solve is over (it is counted once taken)
            traj, safe, why, clearance, ahead = chosen
            if last_status == LbfgsStatus.CANCELED:  # the warm solve (a refinement keeps none)
                messages.append(why)
                return None, problem, True
            if traj is None:
                messages.append(why)
                return None, problem, False
            if safe and why:  # a last resort
                assert traj is not None
                last_resorts.append((margin_of(chosen), (ok_status, traj, last_status, problem, x)))
                messages.append(f"{label}: {why}")
                return None, problem, False
            if safe and wants_fresh(use_formation, force_astar) and not late():
                solved = (
                    collect(beside)
                    if beside is not None
                    else solve(prepare_fresh(use_formation, formation_scale))
                )
                # the costs first (the solver's own values): a fresh plan that costs no less
                # than the warm one is not flown whatever the check says, so it is checked
                # only when it would be (it wins in a third to a half of the replans)
                if solved[2] != LbfgsStatus.CANCELED:
                    f_warm = problem.cost(x)
                    f_alt = solved[0].cost(solved[1])
                    fresh = alternative(solved) if f_alt < f_warm else None
                    if fresh is not None:
                        problem, x, last_status, traj, clearance, ahead = fresh
                        messages.append(f"fresh start: cost {f_warm:.4g} -> {f_alt:.4g}")
            if safe and not force_astar and ahead < self.params.comfort_obstacle_m:
                # it threads a gap narrower than comfortable (the warm start keeps the way it
                # chose when the gap was far) far enough ahead to choose another: try the way
                # an A* path at the optimiser's clearance takes, with the same terms, and fly
                # the roomier of the two
                start_d = float(field.distance(sp[None, :])[0][0])
                if ahead < start_d - 1e-3 and not late():
                    roomy = alternative(
                        solve(
                            prepare(
                                use_formation,
                                True,
                                astar_margin_m=COMFORT_ASTAR_MARGIN_M,
                                formation_scale=formation_scale,
                            )
                        )
                    )
                    if roomy is not None and roomy[4] > clearance:
                        problem, x, last_status, traj = roomy[:4]
                        messages.append(f"roomier a* way: {clearance:.2f} -> {roomy[4]:.2f} m")
            if safe:
                assert traj is not None
                # over the budget: the plan as it is, as for the alternatives
                capped = (
                    None
                    if late()
                    else self._cap_speed(problem, x, traj, again, field, view, peers, pack, brake())
                )
                if capped is not None:
                    x, traj, note = capped
                    messages.append(note)
                if what == _RESCUE:
                    messages.append(f"a* rescue: path at {problem.astar_clearance_m:.2f} m")
                elif formation_scale != 1.0:
                    messages.append(f"flown: {label}")
                result = PlanResult(
                    ok_status,
                    traj,
                    iters,
                    evals,
                    last_status,
                    "; ".join(messages),
                    functools.partial(problem.cost_terms, x),
                )
                return result, problem, False
            assert traj is not None
            refused.append((ok_status, traj, last_status, problem, x))
            messages.append(f"{label}: {why}")
            return None, problem, False

        def flown(
            entry: tuple[PlanStatus, Trajectory, LbfgsStatus | None, Problem, np.ndarray],
            ending: str,
        ) -> PlanResult:
            """A kept attempt (a last resort, a refused one) flown; its message ends with
            ``ending``."""
            status, traj, lb_status, problem, x = entry
            return PlanResult(
                status,
                traj,
                iters,
                evals,
                lb_status,
                "; ".join([*messages, ending]),
                functools.partial(problem.cost_terms, x),
            )

        def approach() -> PlanResult | None:
            """The first refused trajectory that the check accepts outright over its first
            ``APPROACH_S`` (``APPROACH``), else None."""
            t_cut = t_start_s + APPROACH_S
            for entry in refused:
                traj = entry[1]
                if traj.t_end_s <= t_cut:
                    continue  # refused before its end: within APPROACH_S
                safe, why, _, _ = self._check(
                    traj.until(t_cut), t_start_s, field, view, peers, pack, brake()
                )
                if safe and not why:
                    return flown(entry, APPROACH)
            return None

        attempts = [(True, False, PlanStatus.OK, "formation", 1.0)]
        if self.params.astar_keeps_formation and self.params.w_formation > 0 and peers:
            attempts.append((True, True, PlanStatus.OK, "a* retry", 1.0))
        soft = self.params.soft_formation_scale
        if soft > 0.0 and self.params.w_formation > 0 and peers:
            # the pull of the shape that took the drone too close, softened, before none
            attempts.append((True, False, PlanStatus.OK, f"formation x{soft:g}", soft))
        attempts.append((False, True, PlanStatus.OK_NO_FORMATION, "a* retry", 1.0))
        canceled = False
        kept_checked = False  # ``previous`` checked already (safe: ``kept``)
        kept: Trajectory | None = None

        def keep_previous() -> Trajectory | None:
            """``previous`` if the check still accepts it (checked once per replan)."""
            nonlocal kept_checked, kept
            if not kept_checked and previous is not None:
                kept_checked = True
                safe, why, _, _ = self._check(
                    previous, t_start_s, field, view, peers, pack, brake()
                )
                if safe and not why:
                    kept = previous
                else:
                    messages.append(f"previous: {why}")
            return kept

        def moves_on(traj: Trajectory) -> bool:
            """Whether ``traj`` ends at least ``KEEP_MOVING_M`` from the replan's start."""
            return math.dist(traj.end_position.tolist(), sp.tolist()) >= KEEP_MOVING_M

        def over_budget(k: int) -> PlanResult | None:
            """The kept previous trajectory when ``give_up`` says stop before attempt ``k``
            and it moves on."""
            if not late():
                return None
            safe_prev = keep_previous()
            if safe_prev is None or not moves_on(safe_prev):
                return None
            return PlanResult(
                PlanStatus.OVER_BUDGET,
                safe_prev,
                iters,
                evals,
                last_status,
                "; ".join(messages),
                resume_at=k,
            )

        first = min(first_attempt, len(attempts) - 1)
        if first > 0:
            use_formation, _, _, what, _ = attempts[first]
            messages.append(f"resumed at {what}{'' if use_formation else ' without formation'}")
        for k in range(first, len(attempts)):
            use_formation, force_astar, ok_status, what, scale = attempts[k]
            if k > first and (stop := over_budget(k)) is not None:
                return stop
            result, problem, canceled = attempt(
                use_formation, force_astar, ok_status, what, formation_scale=scale
            )
            if result is not None:
                return result
            if canceled:
                break
        # Every attempt was refused. A safe previous trajectory that still takes the drone
        # somewhere is kept, as before the rescue existed (the next replan tries again).
        prev = keep_previous()
        if prev is not None and moves_on(prev):
            return PlanResult(
                PlanStatus.KEPT_PREVIOUS, prev, iters, evals, last_status, "; ".join(messages)
            )
        # Otherwise the drone would hold where it is (a kept hover, a finished stop) or stop.
        # When the A* retry's path kept only the check's distance, the way it offered may be a
        # gap that the check refuses every plan through (a mapped gap is narrower than the true
        # one): one more attempt starts from the roomiest A* path at the rescue levels. Before
        # keeping a hover: the drone stuck in front of such a gap (mapped forest-medium seed 3)
        # kept a hover the check accepted, replan after replan.
        rescue = self.params.astar_rescue_ladder_m
        if not canceled and rescue and problem.astar_clearance_m < min(rescue):
            result, _, canceled = attempt(
                False, True, PlanStatus.OK_NO_FORMATION, _RESCUE, ladder=rescue
            )
            if result is not None:
                return result
        # Rather than hold or stop in front of a way refused only far ahead: approach it.
        if not canceled and (result := approach()) is not None:
            return result
        if prev is not None:
            return PlanResult(
                PlanStatus.KEPT_PREVIOUS, prev, iters, evals, last_status, "; ".join(messages)
            )
        # Nothing optimised stays outside the check's distances. Where the stop itself comes
        # inside the check's distance of a peer (one coming on), a move straight away may:
        # one the check accepts outright is flown (the one that keeps farthest), else the
        # last resort, optimised or such a move, that keeps farthest beyond those distances
        # (a way that comes no closer than the stop). Before, the optimised last resort alone:
        # a drone its peers did not hear flew one to 0.43 m of a peer coming on, when a move
        # aside kept more (``bench hidden``). Not for obstacles, which do not come on: there
        # the stop is as safe, and such moves would wander.
        outright: list[tuple[float, str, Trajectory]] = []
        marginal: list[tuple[float, str, Trajectory]] = []
        if not canceled and self._margin(brake(), t_start_s, peers, math.inf) < 0.0:
            for label, traj in self._evasions(t_start_s, sp, sv, sa):
                safe, why, clearance, _ = self._check(
                    traj, t_start_s, field, view, peers, pack, brake()
                )
                if safe:
                    margin = self._margin(traj, t_start_s, peers, clearance)
                    (marginal if why else outright).append((margin, label, traj))

        def evade(traj: Trajectory, *ending: str) -> PlanResult:
            """An evasion flown; its message ends with ``ending``."""
            return PlanResult(
                PlanStatus.OK_NO_FORMATION,
                traj,
                iters,
                evals,
                last_status,
                "; ".join([*messages, *ending]),
            )

        if outright:
            _, label, traj = max(outright, key=lambda e: e[0])
            return evade(traj, label)
        best_evasion = max(marginal, key=lambda e: e[0]) if marginal else None
        best_last = max(last_resorts, key=lambda m_e: m_e[0]) if last_resorts else None
        if best_evasion is not None and (best_last is None or best_evasion[0] > best_last[0]):
            _, label, traj = best_evasion
            return evade(traj, label, LAST_RESORT)
        if best_last is not None:
            # the one that keeps farthest beyond the check's distances (the first of equals);
            # nothing stays outside the check's distances; this comes no closer than the stop
            return flown(best_last[1], LAST_RESORT)
        return PlanResult(
            PlanStatus.EMERGENCY,
            brake(),
            iters,
            evals,
            last_status,
            "; ".join(messages),
        )
