"""L-BFGS with a weak-Wolfe line search, driven by reverse communication.

The solver never calls the objective. The caller evaluates ``f`` and ``g = df/dx`` at ``x`` and
hands them over; the solver answers with a status. ``EVALUATE`` (-1) means "x now holds the next
trial point: evaluate it and call ``lbfgs_iterate`` again"; any status >= 0 is final, and then
``x`` and ``g`` hold the best (lowest f) point evaluated and ``lbfgs_result_f(ws)`` its value.
This keeps every solver function a plain ``@njit(cache=True)`` function of arrays, so a compiled
planner can run the whole solve in one compiled loop (numba cannot cache a function that takes
another jitted function as an argument). Intended compiled driver (the lead's planner owns its
own version)::

    @njit(cache=True, nogil=True)
    def solve(x, g, ws, iw, params_arr, cancel_flag, data):
        f = objective(x, g, data)                    # f at x, g overwritten with df/dx
        status = lbfgs_start(ws, iw, params_arr, x, f, g)
        while status == EVALUATE:
            if cancel_flag[0] != 0:                  # int64 array written by another thread
                status = lbfgs_cancel(ws, iw, x, g)  # best point so far into x, g
                break
            f = objective(x, g, data)
            status = lbfgs_iterate(ws, iw, params_arr, x, f, g)
        return status, lbfgs_result_f(ws)            # x, g: best point found

with ``ws, iw = lbfgs_workspace(x.shape[0], params.mem_size)`` and
``params_arr = params.to_array()`` made once (the workspace can be reused by every solve of the
same size; ``lbfgs_start`` resets it). Nothing is allocated per iteration.

Algorithm: two-loop recursion over the last ``mem_size`` curvature pairs (s, y), scaled by
``s.y / y.y`` of the newest pair; the first direction is ``-g`` with step ``1 / ||g||``. A
direction that is not a descent direction resets the memory and falls back to ``-g``. Pairs with
``s.y <= 1e-12 ||s|| ||y||`` are skipped (the memory is kept). The line search is the weak-Wolfe
bracketing/bisection of Lewis and Overton: a trial that fails Armijo (``f > f0 + c1 t g0.d``, or a
non-finite f or g) becomes the upper bracket and the step is bisected; one that fails the
curvature condition (``g.d < c2 g0.d``) becomes the lower bracket and the step is doubled (no
upper bracket yet) or bisected. It fails (``LINESEARCH_FAILED``, best point kept) after
``max_linesearch`` trials, when the step falls below ``min_step``, when it must grow beyond
``max_step``, or when the bracket collapses to machine precision.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numba import njit

# ---- statuses (plain ints for compiled code; LbfgsStatus mirrors them) -------------------------
EVALUATE = -1
CONVERGENCE = 0
STOP_DECREASE = 1
MAX_ITERATIONS = 2
MAX_EVALUATIONS = 3
CANCELED = 4
LINESEARCH_FAILED = 5
NON_FINITE = 6
INVALID_PARAMS = 7
INVALID_CALL = 8


class LbfgsStatus(enum.IntEnum):
    """Solver status: ``EVALUATE`` asks for an evaluation, every other value is final (>= 0)."""

    EVALUATE = EVALUATE
    CONVERGENCE = CONVERGENCE
    STOP_DECREASE = STOP_DECREASE
    MAX_ITERATIONS = MAX_ITERATIONS
    MAX_EVALUATIONS = MAX_EVALUATIONS
    CANCELED = CANCELED
    LINESEARCH_FAILED = LINESEARCH_FAILED
    NON_FINITE = NON_FINITE
    INVALID_PARAMS = INVALID_PARAMS
    INVALID_CALL = INVALID_CALL


_MESSAGES = {
    EVALUATE: "evaluate f and g at x and call lbfgs_iterate again",
    CONVERGENCE: "converged: ||g|| / max(1, ||x||) below g_epsilon",
    STOP_DECREASE: "stopped: relative decrease of f over the last `past` iterations below delta",
    MAX_ITERATIONS: "stopped: reached max_iterations",
    MAX_EVALUATIONS: "stopped: reached max_evaluations",
    CANCELED: "canceled by the caller",
    LINESEARCH_FAILED: "line search failed: no step satisfies the weak Wolfe conditions "
    "(too many trials, step out of [min_step, max_step], or bracket collapsed); "
    "often a wrong gradient or numerical noise",
    NON_FINITE: "x, f or g is not finite (or ||g|| overflows) at the start point",
    INVALID_PARAMS: "invalid parameters or workspace size",
    INVALID_CALL: "lbfgs_iterate called while no solve was running (call lbfgs_start first)",
}


def status_message(status: int) -> str:
    """Human-readable explanation of a status code."""
    return _MESSAGES.get(int(status), f"unknown status {int(status)}")


# ---- packed parameter array layout (LbfgsParams.to_array) --------------------------------------
P_MEM_SIZE = 0
P_G_EPSILON = 1
P_PAST = 2
P_DELTA = 3
P_MAX_ITERATIONS = 4
P_MAX_EVALUATIONS = 5
P_MAX_LINESEARCH = 6
P_MIN_STEP = 7
P_MAX_STEP = 8
P_F_DEC_COEFF = 9
P_S_CURV_COEFF = 10
N_PARAMS = 11

MAX_PAST = 64
"""Largest accepted ``past`` (size of the f-history ring in the workspace)."""

# ---- int workspace layout -----------------------------------------------------------------------
IW_N = 0  # number of variables
IW_M = 1  # memory capacity of the workspace
IW_STATE = 2  # EVALUATE while a solve runs, else the last final status
IW_ITERATIONS = 3  # accepted iterations
IW_EVALUATIONS = 4  # evaluations of f, g, including the start point
IW_LS_TRIALS = 5  # trials in the current line search
IW_MEM_END = 6  # next memory slot to write
IW_MEM_COUNT = 7  # valid (s, y) pairs in memory
IW_MEM_SIZE = 8  # memory used by this solve (params mem_size)
IW_PAST = 9  # params past
N_IW = 10

# ---- float workspace layout: header, f-history ring, then the vectors --------------------------
WS_F0 = 0  # f at the start of the line search
WS_DG0 = 1  # g.d at the start of the line search
WS_STEP = 2  # current trial step
WS_LO = 3  # lower bracket of the step
WS_HI = 4  # upper bracket of the step (inf until an Armijo failure)
WS_F_BEST = 5  # lowest f evaluated
N_WS_HEADER = 8
WS_PF = N_WS_HEADER  # f history ring, MAX_PAST slots
WS_VEC = WS_PF + MAX_PAST  # vectors: xp, gp, d, x_best, g_best (n each),
# s, y (mem capacity m times n each, slot j at j*n), rho, alpha (m each)

_SY_REL_TOL = 1e-12
_MACHEPS = 2.220446049250313e-16


@dataclass(frozen=True)
class LbfgsParams:
    """Solver parameters; ``to_array`` packs them for the compiled functions.

    mem_size: number of curvature pairs kept by the two-loop recursion (default 16).
    g_epsilon: stop with CONVERGENCE when ``||g|| / max(1, ||x||) < g_epsilon`` (default 1e-5).
    past: window in iterations of the relative-decrease test; 0 disables it (default 3,
        at most MAX_PAST).
    delta: stop with STOP_DECREASE when ``(f_{k-past} - f_k) / max(1, |f_k|) < delta``
        (default 1e-4).
    max_iterations: stop with MAX_ITERATIONS after this many accepted iterations; 0 = unlimited
        (default 0).
    max_evaluations: stop with MAX_EVALUATIONS rather than exceed this many evaluations of f and g
        (the start point included); 0 = unlimited (default 0).
    max_linesearch: trials per line search before LINESEARCH_FAILED (default 64).
    min_step: smallest step tried; below it the line search fails (default 1e-20).
    max_step: largest step tried (default 1e20).
    f_dec_coeff: Armijo (sufficient decrease) coefficient c1, 0 < c1 < c2 (default 1e-4).
    s_curv_coeff: weak Wolfe curvature coefficient c2, c1 < c2 < 1 (default 0.9).
    """

    mem_size: int = 16
    g_epsilon: float = 1e-5
    past: int = 3
    delta: float = 1e-4
    max_iterations: int = 0
    max_evaluations: int = 0
    max_linesearch: int = 64
    min_step: float = 1e-20
    max_step: float = 1e20
    f_dec_coeff: float = 1e-4
    s_curv_coeff: float = 0.9

    def to_array(self) -> np.ndarray:
        """Parameters packed as float64 (N_PARAMS,) at the indices P_MEM_SIZE .. P_S_CURV_COEFF."""
        a = np.empty(N_PARAMS)
        a[P_MEM_SIZE] = self.mem_size
        a[P_G_EPSILON] = self.g_epsilon
        a[P_PAST] = self.past
        a[P_DELTA] = self.delta
        a[P_MAX_ITERATIONS] = self.max_iterations
        a[P_MAX_EVALUATIONS] = self.max_evaluations
        a[P_MAX_LINESEARCH] = self.max_linesearch
        a[P_MIN_STEP] = self.min_step
        a[P_MAX_STEP] = self.max_step
        a[P_F_DEC_COEFF] = self.f_dec_coeff
        a[P_S_CURV_COEFF] = self.s_curv_coeff
        return a


@dataclass(frozen=True)
class LbfgsResult:
    """Outcome of ``minimize``: the best point found, its f and g, and how the solve ended."""

    x: np.ndarray
    f: float
    g: np.ndarray
    status: LbfgsStatus
    iterations: int
    evaluations: int
    message: str


# ---- compiled core ------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def lbfgs_workspace(n: int, mem_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Float and int workspaces for n variables and up to mem_size curvature pairs."""
    ws = np.zeros(WS_VEC + 5 * n + 2 * mem_size * n + 2 * mem_size)
    iw = np.zeros(N_IW, dtype=np.int64)
    iw[IW_N] = n
    iw[IW_M] = mem_size
    iw[IW_STATE] = INVALID_CALL
    return ws, iw


@njit(cache=True, nogil=True)
def lbfgs_result_f(ws: np.ndarray) -> float:
    """Lowest f evaluated so far (the f of the point returned on a final status)."""
    return ws[WS_F_BEST]


@njit(cache=True, nogil=True)
def lbfgs_iterations(iw: np.ndarray) -> int:
    """Accepted iterations of the current or last solve."""
    return iw[IW_ITERATIONS]


@njit(cache=True, nogil=True)
def lbfgs_evaluations(iw: np.ndarray) -> int:
    """Evaluations of f and g of the current or last solve, the start point included."""
    return iw[IW_EVALUATIONS]


@njit(cache=True, nogil=True)
def lbfgs_status(iw: np.ndarray) -> int:
    """EVALUATE while a solve runs, else its final status."""
    return iw[IW_STATE]


@njit(cache=True, nogil=True)
def lbfgs_best_x_into(ws: np.ndarray, x: np.ndarray) -> None:
    """Copy the best point evaluated so far into x (n,)."""
    n = x.shape[0]
    xb = WS_VEC + 3 * n
    for i in range(n):
        x[i] = ws[xb + i]


@njit(cache=True, nogil=True)
def _finish(ws: np.ndarray, iw: np.ndarray, x: np.ndarray, g: np.ndarray, status: int) -> int:
    """End the solve with ``status``, restoring the best point into x and g."""
    n = iw[IW_N]
    xb = WS_VEC + 3 * n
    gb = WS_VEC + 4 * n
    for i in range(n):
        x[i] = ws[xb + i]
        g[i] = ws[gb + i]
    iw[IW_STATE] = status
    return status


@njit(cache=True, nogil=True)
def _keep_best(ws: np.ndarray, n: int, x: np.ndarray, f: float, g: np.ndarray) -> None:
    ws[WS_F_BEST] = f
    xb = WS_VEC + 3 * n
    gb = WS_VEC + 4 * n
    for i in range(n):
        ws[xb + i] = x[i]
        ws[gb + i] = g[i]


@njit(cache=True, nogil=True)
def _trial(ws: np.ndarray, iw: np.ndarray, p: np.ndarray, x: np.ndarray, g: np.ndarray) -> int:
    """Put the trial point xp + step d into x and ask for it (unless evaluations are exhausted)."""
    max_ev = p[P_MAX_EVALUATIONS]
    if max_ev > 0.0 and iw[IW_EVALUATIONS] >= max_ev:
        return _finish(ws, iw, x, g, MAX_EVALUATIONS)
    n = iw[IW_N]
    xp = WS_VEC
    d = WS_VEC + 2 * n
    step = ws[WS_STEP]
    for i in range(n):
        x[i] = ws[xp + i] + step * ws[d + i]
    iw[IW_STATE] = EVALUATE
    return EVALUATE


@njit(cache=True, nogil=True)
def _launch(
    ws: np.ndarray,
    iw: np.ndarray,
    p: np.ndarray,
    x: np.ndarray,
    f: float,
    g: np.ndarray,
    dg0: float,
    step: float,
) -> int:
    """Start a line search from (x, f, g) along the direction already stored in ws."""
    n = iw[IW_N]
    xp = WS_VEC
    gp = WS_VEC + n
    for i in range(n):
        ws[xp + i] = x[i]
        ws[gp + i] = g[i]
    step = min(max(step, p[P_MIN_STEP]), p[P_MAX_STEP])
    ws[WS_F0] = f
    ws[WS_DG0] = dg0
    ws[WS_STEP] = step
    ws[WS_LO] = 0.0
    ws[WS_HI] = np.inf
    iw[IW_LS_TRIALS] = 0
    return _trial(ws, iw, p, x, g)


@njit(cache=True, nogil=True)
def _params_ok(ws: np.ndarray, iw: np.ndarray, p: np.ndarray, x: np.ndarray, g: np.ndarray) -> bool:
    if p.shape[0] != N_PARAMS:
        return False
    n = iw[IW_N]
    cap = iw[IW_M]
    if n < 1 or x.shape[0] != n or g.shape[0] != n:
        return False
    if ws.shape[0] != WS_VEC + 5 * n + 2 * cap * n + 2 * cap:
        return False
    for k in range(N_PARAMS):
        if np.isnan(p[k]):
            return False
    m = p[P_MEM_SIZE]
    past = p[P_PAST]
    for v in (m, past, p[P_MAX_ITERATIONS], p[P_MAX_EVALUATIONS], p[P_MAX_LINESEARCH]):
        if v != np.floor(v) or v < 0.0:
            return False
    if m < 1.0 or m > cap or past > MAX_PAST or p[P_MAX_LINESEARCH] < 1.0:
        return False
    if p[P_G_EPSILON] < 0.0 or p[P_DELTA] < 0.0:
        return False
    if not (p[P_MIN_STEP] > 0.0 and p[P_MAX_STEP] >= p[P_MIN_STEP]):
        return False
    c1 = p[P_F_DEC_COEFF]
    c2 = p[P_S_CURV_COEFF]
    return 0.0 < c1 < c2 < 1.0


@njit(cache=True, nogil=True)
def lbfgs_start(
    ws: np.ndarray, iw: np.ndarray, params_arr: np.ndarray, x: np.ndarray, f: float, g: np.ndarray
) -> int:
    """Begin a solve from x (n,) with f = f(x) and g = df/dx (n,) already evaluated there.

    Resets the workspace. Returns EVALUATE with x moved in place to the first trial point, or a
    final status: CONVERGENCE (g already small), NON_FINITE (f, g or x not finite),
    INVALID_PARAMS (bad parameters or a workspace of another size), MAX_EVALUATIONS.
    """
    if iw.shape[0] != N_IW or ws.shape[0] < WS_VEC:
        return INVALID_PARAMS
    ws[WS_F_BEST] = f
    iw[IW_ITERATIONS] = 0
    iw[IW_EVALUATIONS] = 1
    iw[IW_LS_TRIALS] = 0
    iw[IW_MEM_END] = 0
    iw[IW_MEM_COUNT] = 0
    if not _params_ok(ws, iw, params_arr, x, g):
        iw[IW_STATE] = INVALID_PARAMS
        return INVALID_PARAMS
    n = iw[IW_N]
    iw[IW_MEM_SIZE] = int(params_arr[P_MEM_SIZE])
    iw[IW_PAST] = int(params_arr[P_PAST])
    finite = np.isfinite(f)
    gg = 0.0
    xx = 0.0
    for i in range(n):
        finite = finite and np.isfinite(x[i]) and np.isfinite(g[i])
        gg += g[i] * g[i]
        xx += x[i] * x[i]
    if not (finite and np.isfinite(gg) and np.isfinite(xx)):
        iw[IW_STATE] = NON_FINITE
        return NON_FINITE
    _keep_best(ws, n, x, f, g)
    gnorm = np.sqrt(gg)
    if gnorm == 0.0 or gnorm / max(1.0, np.sqrt(xx)) < params_arr[P_G_EPSILON]:
        return _finish(ws, iw, x, g, CONVERGENCE)
    ws[WS_PF] = f
    d = WS_VEC + 2 * n
    for i in range(n):
        ws[d + i] = -g[i]
    return _launch(ws, iw, params_arr, x, f, g, -gg, 1.0 / gnorm)


@njit(cache=True, nogil=True)
def _direction(ws: np.ndarray, iw: np.ndarray, g: np.ndarray) -> float:
    """d = -H g by the two-loop recursion over the stored pairs; returns g.d."""
    n = iw[IW_N]
    m = iw[IW_MEM_SIZE]
    count = iw[IW_MEM_COUNT]
    end = iw[IW_MEM_END]
    d = WS_VEC + 2 * n
    s0 = WS_VEC + 5 * n
    y0 = s0 + m * n
    rho0 = y0 + m * n
    alpha0 = rho0 + m
    for i in range(n):
        ws[d + i] = -g[i]
    j = end
    for _ in range(count):
        j = (j - 1) % m
        s = s0 + j * n
        y = y0 + j * n
        sd = 0.0
        for i in range(n):
            sd += ws[s + i] * ws[d + i]
        a = ws[rho0 + j] * sd
        ws[alpha0 + j] = a
        for i in range(n):
            ws[d + i] -= a * ws[y + i]
    if count > 0:
        newest = (end - 1) % m
        y = y0 + newest * n
        yy = 0.0
        for i in range(n):
            yy += ws[y + i] * ws[y + i]
        gamma = 1.0 / (ws[rho0 + newest] * yy)  # s.y / y.y
        for i in range(n):
            ws[d + i] *= gamma
    j = (end - count) % m
    for _ in range(count):
        s = s0 + j * n
        y = y0 + j * n
        yd = 0.0
        for i in range(n):
            yd += ws[y + i] * ws[d + i]
        b = ws[alpha0 + j] - ws[rho0 + j] * yd
        for i in range(n):
            ws[d + i] += b * ws[s + i]
        j = (j + 1) % m
    dg = 0.0
    for i in range(n):
        dg += ws[d + i] * g[i]
    return dg


@njit(cache=True, nogil=True)
def _accept(
    ws: np.ndarray, iw: np.ndarray, p: np.ndarray, x: np.ndarray, f: float, g: np.ndarray
) -> int:
    """The trial (x, f, g) passed the line search: update memory, test stops, next direction."""
    n = iw[IW_N]
    m = iw[IW_MEM_SIZE]
    xp = WS_VEC
    gp = WS_VEC + n
    iw[IW_ITERATIONS] += 1
    k = iw[IW_ITERATIONS]
    # Curvature pair s = x - xp, y = g - gp, stored only if s.y is safely positive.
    sy = 0.0
    ss = 0.0
    yy = 0.0
    for i in range(n):
        si = x[i] - ws[xp + i]
        yi = g[i] - ws[gp + i]
        sy += si * yi
        ss += si * si
        yy += yi * yi
    if sy > _SY_REL_TOL * np.sqrt(ss * yy) and np.isfinite(sy):
        end = iw[IW_MEM_END]
        s = WS_VEC + 5 * n + end * n
        y = WS_VEC + 5 * n + m * n + end * n
        for i in range(n):
            ws[s + i] = x[i] - ws[xp + i]
            ws[y + i] = g[i] - ws[gp + i]
        ws[WS_VEC + 5 * n + 2 * m * n + end] = 1.0 / sy
        iw[IW_MEM_END] = (end + 1) % m
        iw[IW_MEM_COUNT] = min(iw[IW_MEM_COUNT] + 1, m)
    # Stopping tests.
    gg = 0.0
    xx = 0.0
    for i in range(n):
        gg += g[i] * g[i]
        xx += x[i] * x[i]
    gnorm = np.sqrt(gg)
    if gnorm == 0.0 or gnorm / max(1.0, np.sqrt(xx)) < p[P_G_EPSILON]:
        return _finish(ws, iw, x, g, CONVERGENCE)
    past = iw[IW_PAST]
    if past > 0:
        slot = WS_PF + k % past
        if k >= past and (ws[slot] - f) / max(1.0, abs(f)) < p[P_DELTA]:
            return _finish(ws, iw, x, g, STOP_DECREASE)
        ws[slot] = f
    if p[P_MAX_ITERATIONS] > 0.0 and k >= p[P_MAX_ITERATIONS]:
        return _finish(ws, iw, x, g, MAX_ITERATIONS)
    # Next direction; fall back to steepest descent if it is not a descent direction.
    dg = _direction(ws, iw, g)
    step = 1.0
    if not (dg < 0.0 and np.isfinite(dg)) or iw[IW_MEM_COUNT] == 0:
        if not (dg < 0.0 and np.isfinite(dg)):
            iw[IW_MEM_COUNT] = 0
            iw[IW_MEM_END] = 0
        d = WS_VEC + 2 * n
        for i in range(n):
            ws[d + i] = -g[i]
        dg = -gg
        step = 1.0 / gnorm
    return _launch(ws, iw, p, x, f, g, dg, step)


@njit(cache=True, nogil=True)
def lbfgs_iterate(
    ws: np.ndarray, iw: np.ndarray, params_arr: np.ndarray, x: np.ndarray, f: float, g: np.ndarray
) -> int:
    """Continue the solve with f = f(x) and g = df/dx (n,) at the trial point in x.

    Returns EVALUATE (x now holds the next trial point) or a final status, with x and g then
    holding the best point evaluated and ``lbfgs_result_f(ws)`` its f. Returns INVALID_CALL and
    changes nothing when no solve is running.
    """
    if iw[IW_STATE] != EVALUATE:
        return INVALID_CALL
    n = iw[IW_N]
    iw[IW_EVALUATIONS] += 1
    iw[IW_LS_TRIALS] += 1
    d = WS_VEC + 2 * n
    dg = 0.0
    for i in range(n):
        dg += g[i] * ws[d + i]
    finite = np.isfinite(f) and np.isfinite(dg)
    if finite:
        for i in range(n):
            if not np.isfinite(g[i]):
                finite = False
                break
    if finite and f < ws[WS_F_BEST]:
        _keep_best(ws, n, x, f, g)
    step = ws[WS_STEP]
    lo = ws[WS_LO]
    hi = ws[WS_HI]
    dg0 = ws[WS_DG0]
    if not finite or f > ws[WS_F0] + params_arr[P_F_DEC_COEFF] * step * dg0:
        hi = step  # Armijo failed (or non-finite): shrink
    elif dg < params_arr[P_S_CURV_COEFF] * dg0:
        lo = step  # curvature failed: grow
    else:
        return _accept(ws, iw, params_arr, x, f, g)
    if hi < np.inf:
        step = 0.5 * (lo + hi)
        if hi - lo <= _MACHEPS * hi:
            return _finish(ws, iw, x, g, LINESEARCH_FAILED)
    else:
        step = 2.0 * lo
    max_step = params_arr[P_MAX_STEP]
    if step > max_step:
        if lo >= max_step:
            return _finish(ws, iw, x, g, LINESEARCH_FAILED)
        step = max_step
    if step < params_arr[P_MIN_STEP] or iw[IW_LS_TRIALS] >= params_arr[P_MAX_LINESEARCH]:
        return _finish(ws, iw, x, g, LINESEARCH_FAILED)
    ws[WS_STEP] = step
    ws[WS_LO] = lo
    ws[WS_HI] = hi
    return _trial(ws, iw, params_arr, x, g)


@njit(cache=True, nogil=True)
def lbfgs_cancel(ws: np.ndarray, iw: np.ndarray, x: np.ndarray, g: np.ndarray) -> int:
    """Cancel a running solve: x, g get the best point so far; returns CANCELED.

    When no solve is running, changes nothing and returns its final status.
    """
    if iw[IW_STATE] != EVALUATE:
        return iw[IW_STATE]
    return _finish(ws, iw, x, g, CANCELED)


# ---- Python driver ------------------------------------------------------------------------------


class _CancelFlag(Protocol):
    def is_set(self) -> bool: ...


def _cancel_poll(cancel: Callable[[], bool] | _CancelFlag | None) -> Callable[[], bool]:
    """A poll function for ``cancel``: None, an object with ``is_set()`` (a threading.Event, duck
    typed so this module needs no threading) or a callable returning bool."""
    if cancel is None:
        return lambda: False
    is_set = getattr(cancel, "is_set", None)
    if callable(is_set):
        return is_set
    if callable(cancel):
        return cancel
    raise TypeError("cancel must be None, an object with is_set() or a callable returning bool")


def minimize(
    fun: Callable[[np.ndarray], tuple[float, np.ndarray]],
    x0: np.ndarray,
    params: LbfgsParams = LbfgsParams(),  # noqa: B008 (frozen, immutable)
    cancel: Callable[[], bool] | _CancelFlag | None = None,
) -> LbfgsResult:
    """Minimise ``fun`` from ``x0`` (n,) with the compiled solver; ``fun(x) -> (f, df/dx)``.

    ``fun`` receives a fresh copy of the point each time. The start point is always evaluated;
    ``cancel`` is polled before every further evaluation and, once true/set, the solve ends
    with CANCELED and the best point so far. Never raises for a failed solve: the status says
    what happened (``LbfgsResult.message`` explains it). Raises ValueError if x0 is not a
    non-empty 1-D array or ``fun`` returns a gradient of the wrong shape.
    """
    x = np.array(x0, dtype=np.float64)
    if x.ndim != 1 or x.shape[0] == 0:
        raise ValueError(f"x0 must be a non-empty 1-D array, got shape {x.shape}")
    n = x.shape[0]
    is_canceled = _cancel_poll(cancel)
    ws, iw = lbfgs_workspace(n, max(1, int(params.mem_size)))
    p = params.to_array()
    g = np.empty(n)

    def evaluate() -> float:
        fv, gv = fun(x.copy())
        ga = np.asarray(gv, dtype=np.float64)
        if ga.shape != (n,):
            raise ValueError(f"fun returned a gradient of shape {ga.shape}, expected ({n},)")
        g[:] = ga
        return float(fv)

    status = lbfgs_start(ws, iw, p, x, evaluate(), g)
    while status == EVALUATE:
        if is_canceled():
            status = lbfgs_cancel(ws, iw, x, g)
            break
        status = lbfgs_iterate(ws, iw, p, x, evaluate(), g)
    return LbfgsResult(
        x=x,
        f=float(lbfgs_result_f(ws)),
        g=g,
        status=LbfgsStatus(status),
        iterations=int(lbfgs_iterations(iw)),
        evaluations=int(lbfgs_evaluations(iw)),
        message=status_message(status),
    )
