"""One drone's formation planner: ``plan(...)`` -> status + trajectory (paper Sec. IV).

A replan picks a local target ``horizon_m`` along the way to the goal, builds an initial guess
(the previous trajectory, else a straight line, else an A* path when the line is blocked),
optimises waypoints and durations of a MINCO trajectory with L-BFGS over the seven cost terms,
and accepts the result only if it passes a safety check against the distance field and the
peers' trajectories. A failed attempt is retried from an A* path with the formation term
(``astar_keeps_formation``), then from an A* path without it; failing that the previous
trajectory is kept if it is still safe, else an emergency stop is returned. A drone ahead of
its slot relative to its peers plans with a lower speed limit (``lead_slowdown_m``), so the
swarm waits for a drone left behind rather than stretching the shape for the rest of the
flight. The planner never replaces a safe trajectory with an unsafe one, reads no clock and
does no I/O; failure is a status, never an exception (bad *inputs* raise ValueError).
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from onboard.planner import objective as obj
from onboard.planner.astar import astar_path, segment_is_free
from onboard.planner.field import DistanceField
from onboard.planner.formation import complete_mask, normalized_adjacency
from onboard.planner.lbfgs import (
    LbfgsStatus,
    lbfgs_evaluations,
    lbfgs_iterations,
    lbfgs_workspace,
)
from onboard.planner.minco import BAND_COLS, Minco
from onboard.planner.params import PlannerParams
from onboard.planner.timemap import T_from_tau, tau_from_T
from onboard.planner.trajectory import Trajectory

COMFORT_LOOKAHEAD_S = 1.0
"""``comfort_obstacle_m`` looks at the trajectory from this long after its start (the replan
period): an approach sooner than that is flown before another way could be taken."""
COMFORT_ASTAR_MARGIN_M = 1.5
"""The A* box of the comfort alternative grows the start-target box by this much (3 m for the
fallbacks): a neighbouring gap, not a detour, and a quarter of the grid nodes."""


class PlanStatus(str, enum.Enum):
    """Outcome of one replan."""

    OK = "ok"
    """New optimised trajectory, formation term on, passed the safety check."""
    OK_NO_FORMATION = "ok-no-formation"
    """The formation attempts failed the check; the A* retry without formation passed."""
    KEPT_PREVIOUS = "kept-previous"
    """Both attempts failed; the previous trajectory is still safe and is kept."""
    EMERGENCY = "emergency"
    """Nothing safe was found: the trajectory is a braking stop; the service should hover/land."""


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
    costs: dict[str, float] = field(default_factory=dict)


class Problem:
    """One optimisation problem, ready to evaluate or solve (x = [q.ravel(), tau])."""

    def __init__(
        self,
        params: PlannerParams,
        t_start_s: float,
        head: np.ndarray,
        tail: np.ndarray,
        q0: np.ndarray,
        T0: np.ndarray,
        prob: tuple,
        fld: tuple,
        lb_prm: np.ndarray,
    ) -> None:
        self.params = params
        self.t_start_s = t_start_s
        self.M = int(T0.shape[0])
        self.head = head
        self.tail = tail
        self.tau_scale = float(prob[3][obj.P_TAU_SCALE])
        self.x0 = np.concatenate([q0.ravel(), tau_from_T(T0) / self.tau_scale])
        self.prob = prob
        self.fld = fld
        M = self.M
        self.work = (
            np.zeros((6 * M, BAND_COLS)),
            np.zeros((6 * M, 3)),
            np.zeros((6 * M, 3)),
            np.zeros(M),
            np.zeros((M - 1, 3)),
            np.zeros(obj.N_TERMS),
        )
        self.lb_prm = lb_prm
        self.cancel_flag = np.zeros(1, dtype=np.int64)
        self.iterations = 0
        self.evaluations = 0

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

    def solve(
        self, x_start: np.ndarray | None = None, lb_prm: np.ndarray | None = None
    ) -> tuple[np.ndarray, LbfgsStatus]:
        """Run L-BFGS from x_start (default x0) with the packed solver parameters lb_prm
        (default the planner's); returns (best x, solver status). Counters accumulate."""
        x = (self.x0 if x_start is None else x_start).copy()
        ws, iw = lbfgs_workspace(x.shape[0], self.params.lbfgs.mem_size)
        prm = self.lb_prm if lb_prm is None else lb_prm
        status = obj.solve(x, self.prob, self.fld, self.work, prm, ws, iw, self.cancel_flag)
        self.iterations += int(lbfgs_iterations(iw))
        self.evaluations += int(lbfgs_evaluations(iw))
        return x, LbfgsStatus(status)

    def trajectory(self, x: np.ndarray) -> Trajectory:
        """The trajectory that x describes."""
        M = self.M
        q = x[: 3 * (M - 1)].reshape(M - 1, 3)
        T = T_from_tau(np.ascontiguousarray(x[3 * (M - 1) :]) * self.tau_scale)
        m = Minco(M)
        m.set_conditions(self.head, self.tail)
        m.set_parameters(q, T)
        return Trajectory(self.t_start_s, m.coeffs, T)


def _vec3(name: str, v: np.ndarray | Sequence[float]) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    return a.copy()


def _resample_polyline(path: np.ndarray, n_pieces: int) -> tuple[np.ndarray, np.ndarray]:
    """n_pieces + 1 points equally spaced in arc length along a polyline (K, 3), and their
    arc lengths."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    targets = np.linspace(0.0, s[-1], n_pieces + 1)
    if s[-1] <= 0.0:
        return np.repeat(path[:1], n_pieces + 1, axis=0), targets
    pts = np.stack([np.interp(targets, s, path[:, d]) for d in range(3)], axis=1)
    return pts, targets


def _band_check(d: np.ndarray, threshold: float) -> tuple[bool, str]:
    """Distances d (K,) along a trajectory, d[0] at its start: (ok, reason suffix).

    Clear of ``threshold`` everywhere; or, starting inside it but not inside the obstacle itself
    (d[0] >= 0), never closer than the start (1 mm tolerance) and outside the threshold at some
    point (the trajectory backs out). Inside an obstacle nothing is safe."""
    d0 = float(d[0])
    if d0 >= threshold or d0 < 0.0:
        return bool(np.min(d) >= threshold), ""
    if np.min(d) < d0 - 1e-3:
        return False, f" (started inside at {d0:.2f} m and comes closer)"
    if np.max(d) < threshold:
        return False, f" (started inside at {d0:.2f} m and does not back out)"
    return True, ""


def _altitude_check(z: np.ndarray, lo: float, hi: float) -> tuple[bool, int]:
    """Altitudes z (K,) along a trajectory, z[0] at its start: (ok, index of the worst sample).

    Inside [lo, hi] everywhere (1 um tolerance for a tail placed on the edge); or, starting
    outside, never farther outside than the start (1 mm tolerance) and inside at some point."""
    s = np.minimum(z - lo, hi - z)  # signed distance into the band
    k = int(np.argmin(s))
    s0 = float(s[0])
    if s0 >= 0.0:
        return bool(s[k] >= -1e-6), k
    return bool(s[k] >= s0 - 1e-3 and np.max(s) >= 0.0), k


def _polyline_length(path: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))


class FormationPlanner:
    """Plans one drone's trajectory in the formation (its ``slot`` of ``formation``)."""

    def __init__(
        self,
        params: PlannerParams,
        formation: np.ndarray,
        slot: int,
        edge_mask: np.ndarray | None = None,
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
        self._prm_formation = self._param_vector(use_formation=True)
        self._prm_no_formation = self._param_vector(use_formation=False)
        self._lb_prm = params.lbfgs.to_array()
        # a solution that fails the safety check is refined with tight tolerances first
        self._lb_prm_refine = dataclasses.replace(
            params.lbfgs, delta=min(params.lbfgs.delta, 1e-6), g_epsilon=1e-7
        ).to_array()
        self._desired_cache: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

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
        prm[obj.P_W_ALT] = p.w_altitude
        prm[obj.P_Z_LO], prm[obj.P_Z_HI] = p.altitude_band_inner_m
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
        point[2] = min(max(point[2], lo), hi)
        return point

    def cancel(self) -> None:
        """Ask a running solve (in another thread) to stop at its next evaluation."""
        if self._active is not None:
            self._active.cancel_flag[0] = 1

    # --- problem set-up ---------------------------------------------------------------------

    def _local_target(
        self, start: np.ndarray, goal: np.ndarray, field: DistanceField
    ) -> np.ndarray:
        """Goal if within the horizon, else the point horizon_m along the line, moved along the
        line to the nearest point clear of obstacles by the optimiser's clearance."""
        d = goal - start
        dist = float(np.linalg.norm(d))
        p = self.params
        if dist <= p.horizon_m:
            return goal.copy()
        # into the altitude band (the line from a start outside it may leave it)
        return self._into_band(self._local_target_on_line(start, goal, d, dist, field))

    def _local_target_on_line(
        self, start: np.ndarray, goal: np.ndarray, d: np.ndarray, dist: float, field: DistanceField
    ) -> np.ndarray:
        p = self.params
        u = d / dist
        first = start + p.horizon_m * u
        dd0, _ = field.distance(first[None, :])
        if dd0[0] >= p.obstacle_clearance_m:
            return first
        offsets = np.arange(0.0, dist - p.horizon_m, 0.1)
        cand = np.concatenate([p.horizon_m + offsets, p.horizon_m - np.arange(0.1, 3.0, 0.1)])
        cand = cand[(cand > 0.5) & (cand <= dist)]
        pts = start + cand[:, None] * u
        dd, _ = field.distance(pts)
        ok = np.nonzero(dd >= p.obstacle_clearance_m)[0]
        if ok.size == 0:
            return start + p.horizon_m * u
        return pts[ok[np.argmin(np.abs(cand[ok] - p.horizon_m))]]

    def _guess_path(
        self,
        t_start: float,
        start: np.ndarray,
        target: np.ndarray,
        field: DistanceField,
        previous: Trajectory | None,
        force_astar: bool,
        astar_margin_m: float = 3.0,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Initial path (K, 3) and, when it follows the previous trajectory, its times (K,)
        relative to t_start (the warm start keeps the previous timing)."""
        p = self.params
        if not force_astar and previous is not None and previous.t_end_s > t_start + 0.2:
            ts = np.linspace(t_start, previous.t_end_s, 24)
            path = previous.sample(ts)
            times = ts - t_start
            extra = float(np.linalg.norm(path[-1] - target))
            if extra > 1e-3:
                path = np.vstack([path, target])
                times = np.append(times, times[-1] + extra / p.v_max_m_s + 0.5)
            return path, times
        line = np.vstack([start, target])
        if not force_astar and segment_is_free(field, start, target, p.check_obstacle_m):
            return line, None
        astar = astar_path(
            field,
            start,
            target,
            clearance_m=p.obstacle_clearance_m,
            resolution_m=p.astar_resolution_m,
            margin_m=astar_margin_m,
            z_limits=p.altitude_band_inner_m,
        )
        if astar is None and p.obstacle_clearance_m > p.check_obstacle_m:
            astar = astar_path(
                field,
                start,
                target,
                clearance_m=p.check_obstacle_m,
                resolution_m=p.astar_resolution_m,
                margin_m=astar_margin_m,
                z_limits=p.altitude_band_inner_m,
            )
        return (line if astar is None else astar), None

    def _peer_arrays(self, t_start: float, peers: Sequence[PeerTrajectory]) -> tuple:
        P = len(peers)
        K = max((pt.trajectory.n_pieces for pt in peers), default=1)
        pc = np.zeros((P, K, 6, 3))
        pT = np.ones((P, K))
        pt0 = np.zeros(P)
        for k, pt in enumerate(peers):
            tr = pt.trajectory
            n = tr.n_pieces
            pc[k, :n] = tr.coeffs
            pT[k, :n] = tr.durations_s
            # unused pieces continue as a hover at the end point (zero velocity)
            pc[k, n:, 0] = tr.end_position
            pt0[k] = tr.t0_s - t_start
        return pc, pT, pt0

    def _lead(
        self, t_s: float, sp: np.ndarray, goal: np.ndarray, peers: Sequence[PeerTrajectory]
    ) -> float:
        """How far [m] this drone is ahead of its slot along its way to the goal: its offset
        from the centroid of itself and its peers (at t_s) minus its slot's offset from the
        centroid of the same slots of the formation, projected on the direction to the goal."""
        d = goal - sp
        dist = float(np.linalg.norm(d))
        if dist < 1e-6:
            return 0.0
        u = d / dist
        n = self.formation.shape[0]
        pts = [sp]
        slots = [self.slot]
        for pt in peers:
            if pt.slot < n and self.mask[self.slot, pt.slot] > 0.0:
                pts.append(pt.trajectory.sample(t_s))
                slots.append(pt.slot)
        if len(pts) < 2:
            return 0.0
        P = np.asarray(pts)
        F = self.formation[np.array(slots)]
        off = (sp - P.mean(axis=0)) - (F[0] - F.mean(axis=0))
        return float(off @ u)

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
    ) -> Problem:
        """Build the optimisation problem of one replan (validated inputs, initial guess)."""
        p = self.params
        if not np.isfinite(t_start_s):
            raise ValueError("t_start_s must be finite")
        sp = _vec3("start_p", start_p)
        sv = _vec3("start_v", start_v)
        sa = _vec3("start_a", start_a)
        gl = self._into_band(_vec3("goal", goal))
        seen: set[int] = {self.slot}
        for pt in peers:
            if not 0 <= pt.slot < self.formation.shape[0]:
                raise ValueError(f"peer {pt.drone_id} has slot {pt.slot} outside the formation")
            if pt.slot in seen:
                raise ValueError(f"peer {pt.drone_id} has slot {pt.slot}, already taken")
            seen.add(pt.slot)
        target = self._local_target(sp, gl, field)
        path, times = self._guess_path(
            t_start_s, sp, target, field, previous, force_astar, astar_margin_m
        )
        path[0] = sp
        length = _polyline_length(path)
        M = int(np.clip(np.ceil(length / p.piece_length_m), 1, p.max_pieces))
        wps, arc = _resample_polyline(path, M)
        if times is not None:
            # keep the previous timing along the path (arc length -> time)
            s_path = np.concatenate(
                [[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
            )
            T0 = np.maximum(np.diff(np.interp(arc, s_path, times)), 0.2)
        else:
            seg = np.diff(arc)
            T0 = np.maximum(seg / p.v_max_m_s, 0.3)
            T0[0] += 2.0 * max(0.0, p.v_max_m_s - float(np.linalg.norm(sv))) / p.a_max_m_s2
            T0[-1] += 1.0  # braking at the target
        head = np.stack([sp, sv, sa])
        tail = np.stack([target, np.zeros(3), np.zeros(3)])
        pc, pT, pt0 = self._peer_arrays(t_start_s, peers)
        if use_formation and p.w_formation > 0 and len(peers) > 0:
            sdes, m, fpts = self._desired((self.slot, *(pt.slot for pt in peers)))
        else:
            m = np.zeros((1, 1))
            sdes = np.zeros((1, 1))
            fpts = np.zeros((1, 3))
        prm = self._prm_formation if use_formation else self._prm_no_formation
        if use_formation and p.w_formation > 0 and p.lead_slowdown_m > 0.0 and len(peers) > 0:
            lead = self._lead(t_start_s, sp, gl, peers)
            if lead > 0.0:
                prm = prm.copy()
                prm[obj.P_V_MAX] *= max(p.lead_min_speed_frac, 1.0 - lead / p.lead_slowdown_m)
        prob = (head, tail, p.kappa, prm, pc, pT, pt0, sdes, m, fpts)
        fld = obj.field_args(field.kernel_data())
        problem = Problem(p, float(t_start_s), head, tail, wps[1:-1], T0, prob, fld, self._lb_prm)
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
        back in, never farther out); (1) clear of obstacles by ``check_obstacle_m`` and of
        every peer by ``check_drone_m`` to its end; a drone that is already closer than that
        at ``t_from_s`` (pushed in by a peer, a late-mapped trunk, an emergency stop), but not
        inside an obstacle, may fly a trajectory that never comes closer than it starts and
        leaves the band, so it can always back out; (2) during the first ``check_known_s``
        (the part flown before the next replan can replace it) it does not enter space the
        field has not observed (``field.is_known``); a start in
        unobserved space may be left.
        """
        ok, why, _, _ = self._check(traj, t_from_s, field, peers)
        return ok, why

    def _check(
        self,
        traj: Trajectory,
        t_from_s: float,
        field: DistanceField,
        peers: Sequence[PeerTrajectory],
    ) -> tuple[bool, str, float, float]:
        """``check`` plus the trajectory's closest approach to an obstacle, over all of it and
        from ``COMFORT_LOOKAHEAD_S`` on (NaN when the test stopped before the distances)."""
        p = self.params
        t_end = max(traj.t_end_s, t_from_s)
        ts = np.append(np.arange(t_from_s, t_end, p.check_step_s), t_end)
        pos = traj.sample(ts)
        if not np.all(np.isfinite(pos)):
            return False, "non-finite trajectory", float("nan"), float("nan")
        lo, hi = p.z_limits_m
        ok, k = _altitude_check(pos[:, 2], lo, hi)
        if not ok:
            return (
                False,
                f"altitude {pos[k, 2]:.2f} m at t={ts[k] - t_from_s:.2f} s outside the band "
                f"[{lo:g}, {hi:g}] m",
                float("nan"),
                float("nan"),
            )
        d, _ = field.distance(pos)
        clearance = float(np.min(d))
        later = ts >= t_from_s + COMFORT_LOOKAHEAD_S
        ahead = float(np.min(d[later])) if np.any(later) else float("inf")
        ok, why = _band_check(d, p.check_obstacle_m)
        if not ok:
            k = int(np.argmin(d))
            reason = f"obstacle clearance {d[k]:.2f} m at t={ts[k] - t_from_s:.2f} s{why}"
            return False, reason, clearance, ahead
        for pt in peers:
            other = pt.trajectory.sample(ts)
            dd = np.linalg.norm(pos - other, axis=1)
            ok, why = _band_check(dd, p.check_drone_m)
            if not ok:
                k = int(np.argmin(dd))
                reason = f"drone {pt.drone_id} at {dd[k]:.2f} m at t={ts[k] - t_from_s:.2f} s{why}"
                return False, reason, clearance, ahead
        if p.check_known_s > 0.0:
            n = int(np.searchsorted(ts, t_from_s + p.check_known_s, side="right"))
            known = field.is_known(pos[:n])
            if not np.all(known):
                first_known = int(np.argmax(known)) if np.any(known) else n
                entered = np.nonzero(~known[first_known:])[0]
                if entered.size:
                    k = first_known + int(entered[0])
                    reason = f"enters unobserved space at t={ts[k] - t_from_s:.2f} s"
                    return False, reason, clearance, ahead
        return True, "", clearance, ahead

    def _stop(self, t_start: float, sp: np.ndarray, sv: np.ndarray, sa: np.ndarray) -> Trajectory:
        """A one-piece braking trajectory to rest."""
        speed = float(np.linalg.norm(sv))
        Tb = max(0.5, 3.0 * speed / self.params.a_max_m_s2)
        m = Minco(1)
        m.set_conditions(np.stack([sp, sv, sa]), np.stack([sp + 0.5 * Tb * sv, 0 * sv, 0 * sv]))
        m.set_parameters(np.zeros((0, 3)), np.array([Tb]))
        return Trajectory(t_start, m.coeffs, np.array([Tb]))

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
    ) -> PlanResult:
        """One replan; see the module docstring for the sequence of attempts."""
        sp = _vec3("start_p", start_p)
        sv = _vec3("start_v", start_v)
        sa = _vec3("start_a", start_a)
        gl = self._into_band(_vec3("goal", goal))
        if np.linalg.norm(gl - sp) < 0.02 and np.linalg.norm(sv) < 0.05:
            hover = Trajectory.hover(gl, t_start_s, duration_s=1.0)
            return PlanResult(PlanStatus.OK, hover, message="at goal")
        iters = evals = 0

        def solve(
            use_formation: bool, force_astar: bool, **kw: float
        ) -> tuple[Problem, np.ndarray, LbfgsStatus]:
            """Prepare and solve one attempt (cancellable meanwhile), counting its work."""
            nonlocal iters, evals
            problem = self.prepare(
                t_start_s,
                sp,
                sv,
                sa,
                gl,
                peers,
                field,
                previous,
                use_formation=use_formation,
                force_astar=force_astar,
                **kw,
            )
            self._active = problem
            x, status = problem.solve()
            self._active = None
            iters += problem.iterations
            evals += problem.evaluations
            return problem, x, status

        messages = []
        last_status: LbfgsStatus | None = None
        attempts = [(True, False, PlanStatus.OK)]
        if self.params.astar_keeps_formation and self.params.w_formation > 0 and peers:
            attempts.append((True, True, PlanStatus.OK))
        attempts.append((False, True, PlanStatus.OK_NO_FORMATION))
        for use_formation, force_astar, ok_status in attempts:
            problem, x, last_status = solve(use_formation, force_astar)
            if last_status == LbfgsStatus.CANCELED:
                messages.append("canceled")
                break
            if not np.all(np.isfinite(x)):
                messages.append("non-finite solution")
                continue
            traj = problem.trajectory(x)
            safe, why, clearance, ahead = self._check(traj, t_start_s, field, peers)
            if not safe:
                x2, st2 = problem.solve(x, self._lb_prm_refine)
                if st2 != LbfgsStatus.CANCELED and np.all(np.isfinite(x2)):
                    x, last_status = x2, st2
                    traj = problem.trajectory(x)
                    safe, why, clearance, ahead = self._check(traj, t_start_s, field, peers)
            if safe and not force_astar and ahead < self.params.comfort_obstacle_m:
                # it threads a gap narrower than comfortable (the warm start keeps the way it
                # chose when the gap was far) far enough ahead to choose another: try the way
                # an A* path at the optimiser's clearance takes, with the same terms, and fly
                # the roomier of the two
                start_d = float(field.distance(sp[None, :])[0][0])
                if ahead < start_d - 1e-3:
                    alt, x_alt, st_alt = solve(
                        use_formation, True, astar_margin_m=COMFORT_ASTAR_MARGIN_M
                    )
                    if st_alt != LbfgsStatus.CANCELED and np.all(np.isfinite(x_alt)):
                        traj_alt = alt.trajectory(x_alt)
                        ok_alt, _, clr_alt, _ = self._check(traj_alt, t_start_s, field, peers)
                        if ok_alt and clr_alt > clearance:
                            problem, x, traj, last_status = alt, x_alt, traj_alt, st_alt
                            messages.append(f"roomier a* way: {clearance:.2f} -> {clr_alt:.2f} m")
            if safe:
                return PlanResult(
                    ok_status,
                    traj,
                    iters,
                    evals,
                    last_status,
                    "; ".join(messages),
                    problem.cost_terms(x),
                )
            what = "a* retry" if force_astar else "formation"
            messages.append(f"{what}{'' if use_formation else ' without formation'}: {why}")
        if previous is not None:
            safe, why = self.check(previous, t_start_s, field, peers)
            if safe:
                return PlanResult(
                    PlanStatus.KEPT_PREVIOUS,
                    previous,
                    iters,
                    evals,
                    last_status,
                    "; ".join(messages),
                )
            messages.append(f"previous: {why}")
        return PlanResult(
            PlanStatus.EMERGENCY,
            self._stop(t_start_s, sp, sv, sa),
            iters,
            evals,
            last_status,
            "; ".join(messages),
        )
