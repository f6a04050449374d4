"""Compiled set-up and safety check of one replan (``planner.FormationPlanner`` calls them).

Each follows, operation for operation, the numpy code the planner ran before (kept as the
oracle in ``tests/test_planner_kernels.py``), with the numpy routines replaced by their
rounding-exact twins of ``npexact``: plans are bit-identical, without the ~70 interpreted
numpy calls that took 0.5 ms of a 1.2 ms median replan on a quiet machine (issue #11).
Distances come from the field's kernel data (``field_eval``), which is what ``distance()``
evaluates for the library's fields.

- ``local_target``: the point ``horizon`` along the line to the goal, moved along the line to
  the nearest point clear of obstacles by ``clearance``, then into the altitude band;
- ``initial_guess``: the local target and the initial path (the previous trajectory, else the
  straight line if it is clear) resampled into MINCO pieces, as the solver's start vector x0;
- ``path_guess``: x0 from a given path (the A* fallback's);
- ``pad_peers``: the peers' trajectories padded to one piece count;
- ``swarm_setup``: the swarm's reference (the formation members' positions at the plan's
  start, their centroid or the slowest member), the goal and horizon that make the local
  target the swarm-consistent one, and the drone's lead for the lead slow-down;
- ``trajectory_from_x``: MINCO coefficients and durations of a solution vector;
- ``peak_speed``: a trajectory's largest speed, sampled (the planner's speed cap);
- ``check_trajectory``: the safety check of ``FormationPlanner.check`` (its unknown-space test
  for grid fields), answering with a code and the numbers of its reason.

The planner calls ``initial_guess``, ``trajectory_from_x``, ``check_trajectory`` and
``peak_speed`` in every replan, ``pad_peers`` and ``swarm_setup`` in every replan with peers
and ``path_guess`` after an A* search, so the service's warm-up
(``onboard.service.planning.warm_up``: an A* guess, peers) loads them all before flight.

``fld`` is the objective's field tuple (``objective.field_args``); peers are packed as
``peer_c (P, K, 6, 3)``, ``peer_T (P, K)`` (the first ``peer_n[k]`` pieces are the peer's own)
and ``peer_t0 (P,)`` (global start times).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from onboard.planner.field import field_eval
from onboard.planner.minco import BAND_COLS, solve_coeffs
from onboard.planner.npexact import interp_at, norm3, np_arange, np_linspace, np_sum
from onboard.planner.timemap import T_from_tau, tau_from_T
from onboard.planner.trajectory import eval_piecewise, eval_position

# initial_guess codes
GUESS_OK = 0
GUESS_NEEDS_ASTAR = 1
"""The line to the target is blocked (or A* was asked for): the caller finds an A* path and
calls ``path_guess`` with it."""

# check_trajectory codes
CHECK_OK = 0
CHECK_NON_FINITE = 1
CHECK_ALTITUDE = 2
CHECK_OBSTACLE = 3
CHECK_DRONE = 4
CHECK_UNKNOWN = 5
CHECK_UNKNOWN_NEAR = 6
"""Comes within ``known_r`` of unobserved space, and closer to it than it starts (the
unknown-space test's neighbourhood: a surface the camera never faced beside the way)."""
# what the unknown-space test (2) of the check looks at
KNOWN_SKIP = 0
"""No test: ``check_known_s`` is 0 or the field is known everywhere."""
KNOWN_BOX = 1
"""A grid field without a mask: known inside its box (``GridField.is_known``)."""
KNOWN_MASK = 2
"""A grid field with a mask of observed cells (``GridField.is_known``)."""
# how a band check failed (``_band``)
BAND_OK = 0
BAND_INSIDE = 1
"""Closer than the threshold, started outside it."""
BAND_COMES_CLOSER = 2
"""Started inside the threshold and comes closer than the start."""
BAND_NO_BACK_OUT = 3
"""Started inside the threshold and never leaves it."""
BAND_MARGINAL = 4
"""Started outside the threshold and comes inside it, but no closer than the braking stop
from the same start would (``_band``'s floor); for a peer, also a start inside that backs
out but first comes closer than it starts, no closer than the stop: a way the planner takes
only when no attempt stays outside (``FormationPlanner.plan``)."""

GUESS_SAMPLES = 24
"""Points sampled along the previous trajectory for the warm start."""


@njit(cache=True, nogil=True)
def _dist(fld: tuple, x: float, y: float, z: float) -> float:
    kind, grid, origin, res, cyl, rings, boxes, ground_z = fld
    return field_eval(kind, grid, origin, res, cyl, rings, boxes, ground_z, x, y, z)[0]


@njit(cache=True, nogil=True)
def into_band(z: float, lo: float, hi: float) -> float:
    """``min(max(z, lo), hi)`` with Python's choice of argument on ties."""
    m = lo if lo > z else z
    return hi if hi < m else m


@njit(cache=True, nogil=True)
def local_target(
    start: np.ndarray,
    goal: np.ndarray,
    horizon: float,
    clearance: float,
    z_lo: float,
    z_hi: float,
    fld: tuple,
) -> np.ndarray:
    """Goal if within ``horizon``, else the point ``horizon`` along the line to it, moved along
    the line (0.1 m steps, up to the goal, back to 2.9 m before, never nearer than 0.5 m to the
    start) to the nearest point whose field distance is >= ``clearance`` (the horizon point
    when there is none), with its z moved into [z_lo, z_hi]. start, goal: (3,)."""
    d0 = goal[0] - start[0]
    d1 = goal[1] - start[1]
    d2 = goal[2] - start[2]
    dist = norm3(d0, d1, d2)
    out = np.empty(3)
    if dist <= horizon:
        out[:] = goal
        return out
    u0 = d0 / dist
    u1 = d1 / dist
    u2 = d2 / dist
    out[0] = start[0] + horizon * u0
    out[1] = start[1] + horizon * u1
    out[2] = start[2] + horizon * u2
    if not _dist(fld, out[0], out[1], out[2]) >= clearance:
        offsets = np_arange(0.0, dist - horizon, 0.1)
        back = np_arange(0.1, 3.0, 0.1)
        best = -1.0
        best_gap = 0.0
        for k in range(offsets.shape[0] + back.shape[0]):
            if k < offsets.shape[0]:
                c = horizon + offsets[k]
            else:
                c = horizon - back[k - offsets.shape[0]]
            if not (c > 0.5 and c <= dist):
                continue
            p0 = start[0] + c * u0
            p1 = start[1] + c * u1
            p2 = start[2] + c * u2
            if _dist(fld, p0, p1, p2) >= clearance:
                gap = abs(c - horizon)
                if best < 0.0 or gap < best_gap:  # the first of equal gaps, as np.argmin
                    best = c
                    best_gap = gap
                    out[0] = p0
                    out[1] = p1
                    out[2] = p2
    out[2] = into_band(out[2], z_lo, z_hi)
    return out


@njit(cache=True, nogil=True)
def segment_is_free(
    fld: tuple, a: np.ndarray, b: np.ndarray, clearance: float, step: float = 0.05
) -> bool:
    """``astar.segment_is_free`` on the field tuple: distance >= clearance at samples every
    <= step along a-b, both ends included."""
    e0 = b[0] - a[0]
    e1 = b[1] - a[1]
    e2 = b[2] - a[2]
    n = max(1, int(math.ceil(norm3(e0, e1, e2) / step)))
    s = np_linspace(0.0, 1.0, n + 1)
    for i in range(n + 1):
        if not _dist(fld, a[0] + s[i] * e0, a[1] + s[i] * e1, a[2] + s[i] * e2) >= clearance:
            return False
    return True


@njit(cache=True, nogil=True)
def path_guess(
    path: np.ndarray,
    times: np.ndarray,
    has_times: bool,
    sv: np.ndarray,
    v_max: float,
    a_max: float,
    piece_length: float,
    max_pieces: int,
    tau_scale: float,
) -> np.ndarray:
    """Solver start x0 = [q0.ravel(), tau(T0) / tau_scale] from an initial path (K, 3) whose
    first point is the start: M = ceil(length / piece_length) pieces (1..max_pieces) of equal
    arc length; durations from ``times`` (K,) along the path when ``has_times`` (at least
    0.2 s), else from the speed limit (at least 0.3 s; the first one gets time to accelerate
    from the start speed |sv|, the last one 1 s to brake)."""
    K = path.shape[0]
    s = np.empty(K)  # arc length at each path point
    s[0] = 0.0
    seg = np.empty(max(K - 1, 0))
    for k in range(K - 1):
        seg[k] = norm3(
            path[k + 1, 0] - path[k, 0], path[k + 1, 1] - path[k, 1], path[k + 1, 2] - path[k, 2]
        )
        s[k + 1] = s[k] + seg[k]
    length = np_sum(seg)
    c = np.ceil(length / piece_length)
    c = max(c, 1.0)
    c = min(c, float(max_pieces))
    M = int(c)
    arc = np_linspace(0.0, s[K - 1], M + 1)
    wps = np.empty((M + 1, 3))
    if s[K - 1] <= 0.0:
        for i in range(M + 1):
            wps[i] = path[0]
    else:
        col = np.empty(K)
        for d in range(3):
            for k in range(K):
                col[k] = path[k, d]
            for i in range(M + 1):
                wps[i, d] = interp_at(arc[i], s, col)
    T0 = np.empty(M)
    if has_times:
        t_arc = np.empty(M + 1)
        for i in range(M + 1):
            t_arc[i] = interp_at(arc[i], s, times)
        for i in range(M):
            T0[i] = max(t_arc[i + 1] - t_arc[i], 0.2)
    else:
        for i in range(M):
            T0[i] = max((arc[i + 1] - arc[i]) / v_max, 0.3)
        speed = norm3(sv[0], sv[1], sv[2])
        room = v_max - speed
        T0[0] += 2.0 * (room if room > 0.0 else 0.0) / a_max
        T0[M - 1] += 1.0
    nq = 3 * (M - 1)
    x0 = np.empty(nq + M)
    for i in range(M - 1):
        for d in range(3):
            x0[3 * i + d] = wps[i + 1, d]
    tau = tau_from_T(T0)
    for i in range(M):
        x0[nq + i] = tau[i] / tau_scale
    return x0


@njit(cache=True, nogil=True)
def initial_guess(
    t_start: float,
    sp: np.ndarray,
    sv: np.ndarray,
    goal: np.ndarray,
    horizon: float,
    clearance: float,
    z_lo: float,
    z_hi: float,
    fld: tuple,
    prev_c: np.ndarray,
    prev_T: np.ndarray,
    prev_t0: float,
    use_prev: bool,
    try_line: bool,
    check_obstacle: float,
    v_max: float,
    a_max: float,
    piece_length: float,
    max_pieces: int,
    tau_scale: float,
) -> tuple[int, np.ndarray, np.ndarray]:
    """(code, local target, x0): the target is ``local_target(sp, goal, horizon, clearance,
    z_lo, z_hi, fld)``; x0 the warm start along the previous trajectory (``use_prev`` and it
    lasts more than 0.2 s after t_start; its timing kept, the target appended when it ends
    elsewhere), else along the line start-target when ``try_line`` and it is clear by
    ``check_obstacle``, else code ``GUESS_NEEDS_ASTAR`` and an empty x0."""
    target = local_target(sp, goal, horizon, clearance, z_lo, z_hi, fld)
    if use_prev and prev_t0 + np_sum(prev_T) > t_start + 0.2:
        t_end = prev_t0 + np_sum(prev_T)
        ts = np_linspace(t_start, t_end, GUESS_SAMPLES)
        x, y, z = eval_position(prev_c, prev_T, ts[GUESS_SAMPLES - 1] - prev_t0)
        extra = norm3(x - target[0], y - target[1], z - target[2])
        K = GUESS_SAMPLES + 1 if extra > 1e-3 else GUESS_SAMPLES
        path = np.empty((K, 3))
        times = np.empty(K)
        for k in range(GUESS_SAMPLES):
            path[k, 0], path[k, 1], path[k, 2] = eval_position(prev_c, prev_T, ts[k] - prev_t0)
            times[k] = ts[k] - t_start
        if K > GUESS_SAMPLES:
            path[K - 1] = target
            times[K - 1] = times[K - 2] + extra / v_max + 0.5
        path[0] = sp
        x0 = path_guess(path, times, True, sv, v_max, a_max, piece_length, max_pieces, tau_scale)
        return GUESS_OK, target, x0
    if try_line and segment_is_free(fld, sp, target, check_obstacle):
        path = np.empty((2, 3))
        path[0] = sp
        path[1] = target
        x0 = path_guess(
            path, np.empty(0), False, sv, v_max, a_max, piece_length, max_pieces, tau_scale
        )
        return GUESS_OK, target, x0
    return GUESS_NEEDS_ASTAR, target, np.empty(0)


@njit(cache=True, nogil=True)
def pad_peers(
    flat_c: np.ndarray, flat_T: np.ndarray, n: np.ndarray, ends: np.ndarray, K: int
) -> tuple[np.ndarray, np.ndarray]:
    """The peers' pieces, concatenated (flat_c (sum n, 6, 3), flat_T (sum n,), n (P,) pieces
    each), padded to K pieces: (c (P, K, 6, 3), T (P, K)); a padding piece is a hover at the
    peer's end point ``ends[k]`` lasting 1 s."""
    P = n.shape[0]
    c = np.zeros((P, K, 6, 3))
    T = np.ones((P, K))
    r = 0
    for k in range(P):
        for i in range(n[k]):
            c[k, i] = flat_c[r + i]
            T[k, i] = flat_T[r + i]
        for i in range(n[k], K):
            c[k, i, 0] = ends[k]
        r += n[k]
    return c, T


@njit(cache=True, nogil=True)
def peer_speed_bounds(c: np.ndarray, T: np.ndarray) -> np.ndarray:
    """An upper bound of each packed peer's speed at any time (P,): over its pieces (c (P, K,
    6, 3), T (P, K)), per axis sum_k k |c_k| T^(k-1), the bound of that axis' velocity
    polynomial on [0, T]; the norm of the three. Outside its pieces a peer stands still. The
    objective skips a peer's position at a constraint point that no term reads unless it is
    near (``objective.sampled_costs``), from where it was at an earlier point."""
    P = c.shape[0]
    K = c.shape[1]
    out = np.zeros(P)
    for k in range(P):
        for i in range(K):
            Ti = T[k, i]
            sq = 0.0
            for d in range(3):
                b = 0.0
                tp = 1.0
                for m in range(1, 6):
                    b += m * abs(c[k, i, m, d]) * tp
                    tp *= Ti
                sq += b * b
            v = np.sqrt(sq)
            if v > out[k]:
                out[k] = v
    return out


@njit(cache=True, nogil=True)
def peer_positions(
    c: np.ndarray, T: np.ndarray, n: np.ndarray, t0: np.ndarray, t: float
) -> np.ndarray:
    """Every packed peer's position at global time ``t`` (P, 3): the peer's own ``n[k]``
    pieces evaluated as ``Trajectory.sample`` does (the same routine, bit for bit)."""
    P = n.shape[0]
    out = np.empty((P, 3))
    buf = np.empty((4, 3))
    for k in range(P):
        eval_piecewise(c[k, : n[k]], T[k, : n[k]], t - t0[k], buf)
        for d in range(3):
            out[k, d] = buf[0, d]
    return out


@njit(cache=True, nogil=True)
def _dot3(a: np.ndarray, b: np.ndarray) -> float:
    """``a @ b`` of two 3-vectors as numpy rounds it (in index order, like ``norm3``)."""
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


@njit(cache=True, nogil=True)
def _row_mean(a: np.ndarray) -> np.ndarray:
    """``a.mean(axis=0)`` of a (K, 3) array: the rows summed in order, then divided by K."""
    out = a[0].copy()
    for k in range(1, a.shape[0]):
        for d in range(3):
            out[d] = out[d] + a[k, d]
    for d in range(3):
        out[d] = out[d] / a.shape[0]
    return out


REF_OWN_GOAL = 0
REF_CENTROID = 1
REF_SLOWEST = 2
"""``swarm_setup``'s reference modes (``PlannerParams.swarm_target``)."""


@njit(cache=True, nogil=True)
def _slowest_back(origins: np.ndarray, r: np.ndarray, u: np.ndarray) -> float:
    """How far along ``u`` from ``r`` the least advanced of the members' origin estimates
    ``origins`` (K, 3) lies (negative: behind). A BLAS matrix-vector product, as numpy's: a
    plain loop of products and sums rounded otherwise (1 of 1 200 recorded replans planned
    differently in its last bits)."""
    return np.min((origins - r) @ u)


@njit(cache=True, nogil=True)
def _turned(F: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The template points ``F`` (K, 3) turned about the vertical through their centroid by the
    yaw that fits them best (least squares) to the members' positions ``P`` (K, 3): the
    formation's slots as the swarm holds them, which the formation term (like e_sim and e_dist)
    does not tell from the template's own yaw."""
    k = F.shape[0]
    mf = _row_mean(F)
    mp = _row_mean(P)
    fx, fy, px, py = mf[0], mf[1], mp[0], mp[1]
    a = 0.0
    b = 0.0
    for j in range(k):
        gx = F[j, 0] - fx
        gy = F[j, 1] - fy
        qx = P[j, 0] - px
        qy = P[j, 1] - py
        a += gx * qx + gy * qy
        b += gx * qy - gy * qx
    out = F.copy()
    if a == 0.0 and b == 0.0:
        return out
    th = math.atan2(b, a)
    c = math.cos(th)
    s = math.sin(th)
    for j in range(k):
        gx = F[j, 0] - fx
        gy = F[j, 1] - fy
        out[j, 0] = fx + c * gx - s * gy
        out[j, 1] = fy + s * gx + c * gy
    return out


@njit(cache=True, nogil=True)
def _swarm_reference(
    P: np.ndarray, F: np.ndarray, goal: np.ndarray, slowest: bool
) -> tuple[bool, np.ndarray, np.ndarray, float]:
    """(found, origin r, unit direction u, distance left) of the swarm's reference: each member
    j's origin estimate ``P[j] - F[j]``, their mean (the centroid), moved back along u to the
    member least advanced when ``slowest``; u points from the centroid to the goal's origin
    ``goal - F[0]``. Not found with fewer than two members or at the goal's origin."""
    u = np.zeros(3)
    if P.shape[0] < 2:
        return False, u, u, 0.0
    origins = P - F
    r = _row_mean(origins)
    d = (goal - F[0]) - r
    dist = norm3(d[0], d[1], d[2])
    if dist < 1e-6:
        return False, u, u, 0.0
    u = d / dist
    if slowest:
        back = _slowest_back(origins, r, u)
        r = r + back * u
        dist = dist - back
    return True, r, u, dist


@njit(cache=True, nogil=True)
def _lead(
    P: np.ndarray,
    F: np.ndarray,
    sp: np.ndarray,
    goal: np.ndarray,
    found: bool,
    r: np.ndarray,
    u: np.ndarray,
    ref_mode: int,
    from_slowest: bool,
    turned: bool,
) -> float:
    """``swarm_setup``'s lead of the member at ``sp`` (``P[0]``, template point ``F[0]``) from
    the local target's reference (``found``, ``r``, ``u``, of ``ref_mode``), or from the
    slowest member's with ``from_slowest`` (against the turned template with ``turned``)."""
    K = P.shape[0]
    if from_slowest and turned and K >= 2:
        # from the centroid reference (the direction u of every mode), each member's origin
        # estimate with the template turned to the swarm's yaw, which keeps its centroid
        found_c, r_c, u_c, _ = _swarm_reference(P, F, goal, False)
        if found_c:
            O = P - _turned(F, P)
            return _dot3(O[0] - r_c, u_c) - _slowest_back(O, r_c, u_c)
    # the slowest reference: the local target's one already, moved back from the centroid
    # one, or computed afresh (a centroid one that was not found is not found either)
    if from_slowest and found and ref_mode == REF_CENTROID:
        r = r + _slowest_back(P - F, r, u) * u
    elif from_slowest and ref_mode == REF_OWN_GOAL:
        found, r, u, _ = _swarm_reference(P, F, goal, True)
    if found:
        return _dot3((sp - F[0]) - r, u)
    d = goal - sp
    gd = norm3(d[0], d[1], d[2])
    if gd < 1e-6 or K < 2:
        return 0.0
    off = (sp - _row_mean(P)) - (F[0] - _row_mean(F))
    return _dot3(off, d / gd)


@njit(cache=True, nogil=True)
def swarm_setup(
    c: np.ndarray,
    T: np.ndarray,
    n: np.ndarray,
    t0: np.ndarray,
    t: float,
    rows: np.ndarray,
    F: np.ndarray,
    sp: np.ndarray,
    goal: np.ndarray,
    horizon_m: float,
    target_min_m: float,
    ref_mode: int,
    lead: bool,
    lead_from_slowest: bool,
    lead_turned: bool,
    slowest_beyond_m: float,
) -> tuple[np.ndarray, float, float]:
    """(goal, horizon, lead) of a replan at global time ``t`` from the packed peers (``c``,
    ``T``, ``n``, ``t0``): the members are this drone at ``sp`` and the packed peers ``rows``
    (its formation peers); ``F`` their template points, this drone's first.

    The goal and horizon make the local target the swarm-consistent one of ``ref_mode``: the
    reference origin advanced ``horizon_m`` along the shared path plus this drone's slot, held
    at least ``target_min_m`` ahead of the drone (a target at or behind it would stop it dead or
    turn it back), the goal passed on beyond it by the rest of the path; the drone's own goal
    when the origin is within ``horizon_m`` of the goal's origin; without a reference
    (``REF_OWN_GOAL``, no member, at the goal's origin) ``goal`` and ``horizon_m``.

    The lead (only with ``lead``, else NaN): how far [m] this drone's origin estimate lies
    ahead of the reference along the shared path: the slowest member's reference with
    ``lead_from_slowest``, else the local target's. Without that reference: its offset from
    the members' centroid minus its slot's offset from their template's, projected on the
    direction to ``goal`` (0 at the goal or alone). With ``lead_from_slowest`` and
    ``lead_turned`` the origin estimates of the lead take the template turned to the members'
    yaw (``_turned``): a formation flown turned is no member ahead of another. Without
    ``lead_from_slowest`` and with ``slowest_beyond_m`` > 0 the lead is the larger of that and
    the lead from the slowest member less ``slowest_beyond_m`` (a member far behind is waited
    for)."""
    K = rows.shape[0] + 1
    pos = peer_positions(c, T, n, t0, t)
    P = np.empty((K, 3))
    for d in range(3):
        P[0, d] = sp[d]
        for j in range(K - 1):
            P[j + 1, d] = pos[rows[j], d]
    found = False
    r = np.zeros(3)
    u = np.zeros(3)
    dist = 0.0
    if ref_mode != REF_OWN_GOAL:
        found, r, u, dist = _swarm_reference(P, F, goal, ref_mode == REF_SLOWEST)
    goal_t = goal.copy()
    horizon = horizon_m
    if found:
        if dist <= horizon_m:
            w = goal - sp
            horizon = max(norm3(w[0], w[1], w[2]), horizon_m)
        else:
            target = (r + horizon_m * u) + F[0]
            ahead = _dot3(target - sp, u)
            if ahead < target_min_m:
                target = target + (target_min_m - ahead) * u
            w = target - sp
            reach = norm3(w[0], w[1], w[2])
            w = w / reach
            goal_t = sp + ((reach + (dist - horizon_m)) + 1.0) * w
            horizon = reach
    if not lead:
        return goal_t, horizon, math.nan
    amount = _lead(P, F, sp, goal, found, r, u, ref_mode, lead_from_slowest, lead_turned)
    if not lead_from_slowest and slowest_beyond_m > 0.0:
        behind = _lead(P, F, sp, goal, found, r, u, ref_mode, True, lead_turned)
        amount = max(amount, behind - slowest_beyond_m)
    return goal_t, horizon, amount


@njit(cache=True, nogil=True)
def trajectory_from_x(
    x: np.ndarray, head: np.ndarray, tail: np.ndarray, tau_scale: float
) -> tuple[np.ndarray, np.ndarray, bool]:
    """(coeffs (M, 6, 3), T (M,), finite) of the MINCO trajectory x = [q.ravel(), tau / scale]
    describes (``finite``: every coefficient and duration is finite, so is x)."""
    M = (x.shape[0] + 3) // 4
    nq = 3 * (M - 1)
    q = x[:nq].copy().reshape((M - 1, 3))
    T = T_from_tau(x[nq:] * tau_scale)
    band = np.zeros((6 * M, BAND_COLS))
    c = np.zeros((6 * M, 3))
    solve_coeffs(head, tail, q, T, band, c)
    finite = True
    for i in range(M):
        if not (math.isfinite(T[i]) and T[i] > 0.0):
            finite = False
    for r in range(6 * M):
        for d in range(3):
            if not math.isfinite(c[r, d]):
                finite = False
    return c.reshape((M, 6, 3)), T, finite


@njit(cache=True, nogil=True)
def peak_speed(coeffs: np.ndarray, T: np.ndarray, n: int) -> float:
    """The largest speed of the trajectory (coeffs (M, 6, 3), durations T (M,)) on ``n + 1``
    evenly spaced points of every piece, its ends included."""
    peak2 = 0.0
    for i in range(coeffs.shape[0]):
        for s in range(n + 1):
            t = T[i] * s / n
            sq = 0.0
            for d in range(3):
                v = 0.0
                tk = 1.0
                for k in range(1, 6):
                    v += k * coeffs[i, k, d] * tk
                    tk *= t
                sq += v * v
            if sq > peak2:
                peak2 = sq
    return math.sqrt(peak2)


def band_state(
    d: np.ndarray, threshold: float, floor: float = math.inf, closer_marginal: bool = False
) -> int:
    """``_band`` from Python (BAND_*): the safety check's rule for a trajectory's distances
    to obstacles or a peer, which the flight service's monitor applies too (``floor``,
    ``closer_marginal``: see ``_band``; floor inf: the start)."""
    d = np.ascontiguousarray(d, dtype=np.float64)
    return int(_band(d, float(threshold), float(floor), bool(closer_marginal)))


@njit(cache=True, nogil=True)
def _band(d: np.ndarray, threshold: float, floor: float, closer_marginal: bool) -> int:
    """Distances d (K,) along a trajectory, d[0] at its start, against ``threshold``: clear of
    it everywhere; or, starting inside it, never closer than the start or ``floor`` if that is
    less (1 mm tolerance), and outside it at some point (the trajectory backs out). That holds
    for a start inside the obstacle as well (d[0] < 0): on the drone's own map an obstacle is
    inflated (``OccupancyParams.inflation_m``) and a trunk mapped late may put the drone inside
    it, where holding still, refusing every plan out, is the one thing sure not to end well
    (the real stack, 2026-11-29: a drone hovered 18 s inside a late-mapped trunk's inflation,
    then touched it). ``floor`` is how close the alternative to the trajectory, a braking stop
    from the same start, comes (``check_trajectory``'s reference): a drone still moving
    inward, or a peer moving toward it, makes every way out dip below the start, and refusing
    them all leaves the drone to the stop, which comes closer still (the real stack's bus
    faults test, 2026-11-29: two drones 0.42 m apart refused every plan apart, and touched).
    A start outside the threshold that comes inside it but no closer than ``floor`` is
    BAND_MARGINAL (no better way may exist: a peer that does not hear us coming on).
    ``closer_marginal`` (the rule for peers): a start inside that comes closer than it starts,
    though no closer than ``floor``, is BAND_MARGINAL too, not a way out: the floor is low
    when the peer comes on through the stop, and a way that only matches a stop is no way
    out from a peer that flies on (a drone its peers do not hear flew such ways, accepted
    outright, to 0.32 m of a peer that could not see it: ``bench hidden`` seed 13).
    Obstacles keep the plain rule: they do not come on."""
    d0 = d[0]
    lo = d[0]
    hi = d[0]
    for k in range(1, d.shape[0]):
        lo = min(lo, d[k])
        hi = max(hi, d[k])
    if d0 >= threshold:
        if lo >= threshold:
            return BAND_OK
        return BAND_MARGINAL if lo >= floor - 1e-3 else BAND_INSIDE
    if lo < min(d0, floor) - 1e-3:
        return BAND_COMES_CLOSER
    if hi < threshold:
        return BAND_NO_BACK_OUT
    if closer_marginal and lo < d0 - 1e-3:
        return BAND_MARGINAL
    return BAND_OK


@njit(cache=True, nogil=True)
def _samples_through(ts: np.ndarray, t_end: float) -> int:
    """How many of the increasing sample times ``ts`` lie at or before ``t_end`` (1 ns
    tolerance), at least the first."""
    n = 1
    while n < ts.shape[0] and ts[n] <= t_end + 1e-9:
        n += 1
    return n


@njit(cache=True, nogil=True)
def _argmin(d: np.ndarray) -> int:
    k = 0
    for i in range(1, d.shape[0]):
        if d[i] < d[k]:
            k = i
    return k


@njit(cache=True, nogil=True)
def _is_known(fld: tuple, mode: int, known: np.ndarray, x: float, y: float, z: float) -> bool:
    """``GridField.is_known`` at one point: inside the grid box of ``fld`` and, with a mask
    (KNOWN_MASK), in an observed cell."""
    grid = fld[1]
    origin = fld[2]
    res = fld[3]
    nx = grid.shape[0]
    ny = grid.shape[1]
    nz = grid.shape[2]
    fx = (x - origin[0]) / res
    fy = (y - origin[1]) / res
    fz = (z - origin[2]) / res
    if not (fx >= 0.0 and fx <= nx and fy >= 0.0 and fy <= ny and fz >= 0.0 and fz <= nz):
        return False
    if mode != KNOWN_MASK:
        return True
    i = min(max(int(math.floor(fx)), 0), nx - 1)
    j = min(max(int(math.floor(fy)), 0), ny - 1)
    k = min(max(int(math.floor(fz)), 0), nz - 1)
    return bool(known[i, j, k])


@njit(cache=True, nogil=True)
def _unseen_within(
    fld: tuple, seen: np.ndarray, px: float, py: float, pz: float, r: float
) -> float:
    """The distance from (px, py, pz) to the centre of the nearest grid cell within ``r`` that
    ``seen`` says was not observed, in the point's layer or the next one up or down (trunks
    stand: their layer shows them); ``r`` without one. Cells outside the grid are not judged
    (the check's own test covers leaving the grid's box)."""
    grid = fld[1]
    origin = fld[2]
    res = fld[3]
    nx = grid.shape[0]
    ny = grid.shape[1]
    nz = grid.shape[2]
    m = int(math.ceil(r / res))
    best2 = r * r
    ci = int(math.floor((px - origin[0]) / res))
    cj = int(math.floor((py - origin[1]) / res))
    ck = int(math.floor((pz - origin[2]) / res))
    for a in range(max(ci - m, 0), min(ci + m + 1, nx)):
        dx = origin[0] + (a + 0.5) * res - px
        for b in range(max(cj - m, 0), min(cj + m + 1, ny)):
            dy = origin[1] + (b + 0.5) * res - py
            dxy = dx * dx + dy * dy
            if dxy >= best2:
                continue
            for c in range(max(ck - 1, 0), min(ck + 2, nz)):
                if seen[a, b, c]:
                    continue
                dz = origin[2] + (c + 0.5) * res - pz
                d2 = dxy + dz * dz
                if d2 < best2:
                    best2 = d2
    return math.sqrt(best2)


@njit(cache=True, nogil=True)
def _near_unseen(
    fld: tuple, seen: np.ndarray, pos: np.ndarray, n: int, r: float
) -> tuple[int, float, float]:
    """The first of the samples ``pos[1:n]`` within ``r`` of unobserved space (a grid cell
    that ``seen`` says was not observed, in the sample's layer or the next one up or down;
    ``_unseen_within``) and at least ``r / 2`` closer to it than ``pos[0]`` is to unobserved
    space (looked for within ``2 r``): a way that approaches unobserved space, as a trunk the
    camera never faced (trunks stand: its layer shows one). A way that starts about as close
    to unobserved space as it comes is not judged: beside a drone that has not moved yet, and
    above and below its camera's field of view, space is unobserved at any start; nor one that
    starts in it and leaves it (a drone whose camera never faced behind it). Returns (sample,
    its distance to unobserved space, the first sample's); (-1, nan, nan) without one."""
    d0 = _unseen_within(fld, seen, pos[0, 0], pos[0, 1], pos[0, 2], 2.0 * r)
    t = min(r, d0 - 0.5 * r)
    if t <= 0.0:
        return -1, math.nan, math.nan
    for s_i in range(1, n):
        d = _unseen_within(fld, seen, pos[s_i, 0], pos[s_i, 1], pos[s_i, 2], t)
        if d < t:
            return s_i, d, d0
    return -1, math.nan, math.nan


@njit(cache=True, nogil=True)
def _positions(coeffs: np.ndarray, T: np.ndarray, t_rel: np.ndarray) -> np.ndarray:
    """Positions (K, 3) of the trajectory (coeffs, T) at the times ``t_rel`` (K,) from its
    start."""
    out = np.empty((t_rel.shape[0], 3))
    for i in range(t_rel.shape[0]):
        x, y, z = eval_position(coeffs, T, t_rel[i])
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z
    return out


@njit(cache=True, nogil=True)
def check_trajectory(
    coeffs: np.ndarray,
    T: np.ndarray,
    t0: float,
    t_from: float,
    step: float,
    z_lo: float,
    z_hi: float,
    fld: tuple,
    check_obstacle: float,
    obstacle_s: float,
    peer_c: np.ndarray,
    peer_T: np.ndarray,
    peer_n: np.ndarray,
    peer_t0: np.ndarray,
    check_drone: float,
    drone_s: float,
    lookahead: float,
    known_mode: int,
    known_s: float,
    known: np.ndarray,
    ref_c: np.ndarray,
    ref_T: np.ndarray,
    ref_t0: float,
    ref_s: float,
    known_r: float,
    seen_mask: np.ndarray,
) -> tuple[int, int, int, int, float, float, float, float, float, int]:
    """The safety check of ``FormationPlanner.check`` on the samples ``ts`` = every ``step``
    from t_from to the end (the end included) of the trajectory (coeffs (M, 6, 3), T (M,),
    starting at global time t0), or to t_from + ``ref_s`` if that is later (the drone holds at
    the end meanwhile: a short stop or hover is judged against the peers that come on over the
    stop's window, not only while it moves), the obstacles only on those up to t_from +
    obstacle_s when obstacle_s > 0, the peers only on those up to t_from + drone_s (or ref_s
    if that is later) when drone_s > 0; the unknown-space test (2) with ``known_mode`` (KNOWN_*), on
    the samples up to t_from + known_s, for a grid field (``fld``) and its mask ``known``
    (nx, ny, nz) bool (any array for KNOWN_SKIP and KNOWN_BOX), and with KNOWN_MASK and
    ``known_r`` > 0 its neighbourhood (``_near_unseen``): no such sample within ``known_r`` of
    cells that ``seen_mask`` (the grid's shape: observed, or counted occupied) says are not, in
    its layer, and half of that closer to them than the first sample (CHECK_UNKNOWN_NEAR; the
    value is that distance, the value at the start the first sample's, at most 2 known_r). A
    trajectory that comes closer than the threshold to an obstacle or a peer is judged by
    ``_band`` with the floor of the reference (ref_c (M, 6, 3), ref_T (M,), from global time
    ref_t0: the braking stop that would be flown instead): its closest approach to that
    obstacle or peer over the
    samples up to t_from + ref_s.

    Returns (code, band code, sample k, peer index, value at k, value at the start, t_k -
    t_from, clearance, ahead, samples): the value is the altitude (CHECK_ALTITUDE), the obstacle
    distance (CHECK_OBSTACLE) or the peer distance (CHECK_DRONE) at the worst sample k, and k
    the first sample in unobserved space after one in observed space (CHECK_UNKNOWN); CHECK_OK
    with BAND_MARGINAL: the first obstacle or peer (index -1: an obstacle) met that way, its
    closest approach, and in place of the value at the start the braking stop's (the floor);
    clearance is the closest approach to an obstacle over all samples and ahead from
    ``lookahead`` after t_from on (inf without such samples; both NaN when the check stopped
    before the obstacle distances); ``samples`` is how many of ``ts`` there are.
    """
    nan = math.nan
    t_end = t0 + np_sum(T)
    if not t_end > t_from + ref_s:
        t_end = t_from + ref_s
    head = np_arange(t_from, t_end, step)
    n = head.shape[0] + 1
    ts = np.empty(n)
    ts[: n - 1] = head
    ts[n - 1] = t_end
    pos = np.empty((n, 3))
    finite = True
    for k in range(n):
        x, y, z = eval_position(coeffs, T, ts[k] - t0)
        pos[k, 0] = x
        pos[k, 1] = y
        pos[k, 2] = z
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            finite = False
    if not finite:
        return CHECK_NON_FINITE, BAND_OK, 0, -1, nan, nan, nan, nan, nan, n
    # (0) altitude band: signed distance into it
    s = np.empty(n)
    for k in range(n):
        s[k] = min(pos[k, 2] - z_lo, z_hi - pos[k, 2])
    k = _argmin(s)
    s0 = s[0]
    if s0 >= 0.0:
        ok = s[k] >= -1e-6
    else:
        hi = s[0]
        for i in range(1, n):
            hi = max(hi, s[i])
        ok = s[k] >= s0 - 1e-3 and hi >= 0.0
    if not ok:
        return CHECK_ALTITUDE, BAND_OK, k, -1, pos[k, 2], pos[0, 2], ts[k] - t_from, nan, nan, n
    # (1) obstacles
    dist = np.empty(n)
    for i in range(n):
        dist[i] = _dist(fld, pos[i, 0], pos[i, 1], pos[i, 2])
    clearance = dist[0]
    ahead = math.inf
    t_ahead = t_from + lookahead
    for i in range(n):
        clearance = min(clearance, dist[i])
        if ts[i] >= t_ahead:
            ahead = min(ahead, dist[i])
    # the reference's positions on the samples up to t_from + ref_s, made when a distance
    # first comes inside its threshold
    n_ref = _samples_through(ts, t_from + ref_s)
    ref = np.empty((0, 3))
    # a way that comes inside a threshold but no closer than the braking stop: taken only
    # when nothing better is found (the first such, returned with CHECK_OK)
    m_band = BAND_OK
    m_k = 0
    m_ph = -1
    m_value = nan
    m_floor = nan
    n_obs = _samples_through(ts, t_from + obstacle_s) if obstacle_s > 0.0 else n
    judged = dist[:n_obs]
    k = _argmin(judged)
    floor = math.inf
    if judged[k] < check_obstacle:
        ref = _positions(ref_c, ref_T, ts[:n_ref] - ref_t0)
        for i in range(n_ref):
            floor = min(floor, _dist(fld, ref[i, 0], ref[i, 1], ref[i, 2]))
    band = _band(judged, check_obstacle, floor, False)
    if band == BAND_MARGINAL:
        m_band, m_k, m_value, m_floor = band, k, dist[k], floor
    elif band != BAND_OK:
        return CHECK_OBSTACLE, band, k, -1, dist[k], dist[0], ts[k] - t_from, clearance, ahead, n
    # (1) peers, on the samples up to t_from + drone_s (at least the stop's window) when
    # drone_s > 0
    n_dr = _samples_through(ts, t_from + max(drone_s, ref_s)) if drone_s > 0.0 else n
    dd = np.empty(n_dr)
    for ph in range(peer_c.shape[0]):
        m = peer_n[ph]
        pc = peer_c[ph, :m]
        pT = peer_T[ph, :m]
        for i in range(n_dr):
            x, y, z = eval_position(pc, pT, ts[i] - peer_t0[ph])
            dd[i] = norm3(pos[i, 0] - x, pos[i, 1] - y, pos[i, 2] - z)
        k = _argmin(dd)
        floor = math.inf
        if dd[k] < check_drone:
            if ref.shape[0] == 0:
                ref = _positions(ref_c, ref_T, ts[:n_ref] - ref_t0)
            for i in range(n_ref):
                x, y, z = eval_position(pc, pT, ts[i] - peer_t0[ph])
                floor = min(floor, norm3(ref[i, 0] - x, ref[i, 1] - y, ref[i, 2] - z))
        band = _band(dd, check_drone, floor, True)
        if band == BAND_MARGINAL:
            if m_band == BAND_OK:
                m_band, m_k, m_ph, m_value, m_floor = band, k, ph, dd[k], floor
        elif band != BAND_OK:
            return CHECK_DRONE, band, k, ph, dd[k], dd[0], ts[k] - t_from, clearance, ahead, n
    # (2) unknown space in the samples up to t_from + known_s
    if known_mode != KNOWN_SKIP:
        key = t_from + known_s
        lo = 0
        hi = n
        while lo < hi:  # np.searchsorted(ts, key, side="right")
            mid = lo + ((hi - lo) >> 1)
            if key < ts[mid]:
                hi = mid
            else:
                lo = mid + 1
        seen = False  # a known sample came before
        for i in range(lo):
            if _is_known(fld, known_mode, known, pos[i, 0], pos[i, 1], pos[i, 2]):
                seen = True
            elif seen:
                return CHECK_UNKNOWN, BAND_OK, i, -1, nan, nan, ts[i] - t_from, clearance, ahead, n
        if known_mode == KNOWN_MASK and known_r > 0.0 and lo > 1:
            i, d_i, d_0 = _near_unseen(fld, seen_mask, pos, lo, known_r)
            if i >= 0:
                return (
                    CHECK_UNKNOWN_NEAR, BAND_OK, i, -1, d_i, d_0, ts[i] - t_from, clearance,
                    ahead, n,
                )  # fmt: skip
    if m_band != BAND_OK:
        t_m = ts[m_k] - t_from
        return CHECK_OK, m_band, m_k, m_ph, m_value, m_floor, t_m, clearance, ahead, n
    return CHECK_OK, BAND_OK, 0, -1, nan, nan, nan, clearance, ahead, n
