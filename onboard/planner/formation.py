"""Differentiable formation similarity metric (paper Sec. III, Eq. 1-9).

The formation of N drones is a weighted graph: edge weight ``w_ij = mask_ij * ||p_i - p_j||^2``
(Eq. 1; the paper uses the complete graph, ``mask`` selects a subgraph), degree
``d_i = sum_j w_ij`` (Eq. 2) and normalised Laplacian ``L^ = I - D^-1/2 A D^-1/2`` (Eq. 3).
The similarity metric between the current and the desired formation is (Eq. 4)

    f = ||L^ - L^_des||_F^2 = sum_{i != j} (S_ij - Sdes_ij)^2,   S_ij = w_ij / sqrt(d_i d_j),

where ``S`` is the normalised adjacency (the off-diagonal of ``-L^``). f is invariant to
translation, rotation and uniform scaling of either formation and to a consistent relabelling of
the drones; f = 0 exactly when the current formation is a similar copy of the desired one.

Regularisation: every degree is used as ``d_i + EPS_DEG`` so that coincident points give a finite
f and gradient (S_ij = 0 for an isolated vertex). The gradient below is exact for that
regularised f. With ``d_i`` the regularised degree, ``G_ij = 2 (S_ij - Sdes_ij)`` (symmetrised when
Sdes is not symmetric), ``h_i = sum_j G_ij S_ij / d_i`` and for every edge
``K_ab = 2 G_ab / sqrt(d_a d_b) - h_a - h_b = df/dw_ab`` (Eq. 5-8), the chain rule through Eq. 1
gives (Eq. 9)

    df/dp_a = sum_b K_ab mask_ab 2 (p_a - p_b).

Everything is O(N^2). Units: points in metres; f is dimensionless; df/dp in 1/m.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

EPS_DEG = 1e-12
"""Regulariser added to every vertex degree [m^2]: keeps S finite for coincident points."""

STACK_N = 32
"""Up to this many points ``metric_kernel`` keeps its scratch on the stack (8.5 KiB, no heap)."""
_STACK_NN = STACK_N * STACK_N


@intrinsic
def _stack_f64(typingctx: Any, size: Any) -> Any:
    """Pointer to ``size`` (a compile-time integer) float64 slots on the caller's stack frame.

    The alloca is placed in the function's entry block, so it is reserved once per call (also
    when LLVM inlines the caller into a loop) and never touches the allocator.
    """
    if not isinstance(size, types.IntegerLiteral):
        return None
    count = size.literal_value
    sig = types.CPointer(types.float64)(size)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return cgutils.alloca_once(builder, context.get_value_type(types.float64), size=count)

    return sig, codegen


@njit(cache=True, nogil=True)
def normalized_adjacency(P: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normalised adjacency ``S = D^-1/2 A D^-1/2`` of the formation graph (Eq. 1-3).

    P: (n, 3) points [m]; mask: (n, n) float64 edge mask (symmetric, 0/1, zero diagonal).
    Returns S: (n, n), symmetric, zero diagonal, ``S_ij = w_ij / sqrt((d_i + EPS) (d_j + EPS))``.
    ``-S`` is the off-diagonal of the normalised Laplacian L^ = I - S.
    """
    n = P.shape[0]
    r = np.empty(n)
    for i in range(n):
        d = 0.0
        for j in range(n):
            if j != i:
                dx = P[i, 0] - P[j, 0]
                dy = P[i, 1] - P[j, 1]
                dz = P[i, 2] - P[j, 2]
                d += mask[i, j] * (dx * dx + dy * dy + dz * dz)
        r[i] = 1.0 / np.sqrt(d + EPS_DEG)
    S = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            dx = P[i, 0] - P[j, 0]
            dy = P[i, 1] - P[j, 1]
            dz = P[i, 2] - P[j, 2]
            s = mask[i, j] * (dx * dx + dy * dy + dz * dz) * r[i] * r[j]
            S[i, j] = s
            S[j, i] = s
    return S


@njit(cache=True, nogil=True, inline="always")
def _metric_core(
    P: np.ndarray,
    Sdes: np.ndarray,
    mask: np.ndarray,
    grad_out: np.ndarray,
    r: np.ndarray,
    h: np.ndarray,
    W: np.ndarray,
    ld: int,
) -> float:
    """Body of ``metric_kernel`` with caller-provided scratch.

    r, h: (>= n,) per-vertex scratch; W: (>= n * ld,) pair scratch, ``W[i * ld + j]`` holds w_ij
    above the diagonal and G_ij below it; ld >= n.
    """
    n = P.shape[0]
    for i in range(n):
        r[i] = 0.0
        h[i] = 0.0
        grad_out[i, 0] = 0.0
        grad_out[i, 1] = 0.0
        grad_out[i, 2] = 0.0
    # Pass 1: w_ij (Eq. 1) and degrees d_i (Eq. 2); then r_i = 1 / sqrt(d_i + EPS_DEG).
    for i in range(n):
        xi = P[i, 0]
        yi = P[i, 1]
        zi = P[i, 2]
        for j in range(i + 1, n):
            dx = xi - P[j, 0]
            dy = yi - P[j, 1]
            dz = zi - P[j, 2]
            w = mask[i, j] * (dx * dx + dy * dy + dz * dz)
            W[i * ld + j] = w
            r[i] += w
            r[j] += w
    for i in range(n):
        r[i] = 1.0 / np.sqrt(r[i] + EPS_DEG)
    # Pass 2: S_ij (Eq. 3), f (Eq. 4), G_ij (symmetrised) and h_i = sum_j G_ij S_ij / d_i.
    f = 0.0
    for i in range(n):
        ri = r[i]
        hi = 0.0
        for j in range(i + 1, n):
            s = W[i * ld + j] * ri * r[j]
            e_ij = s - Sdes[i, j]
            e_ji = s - Sdes[j, i]
            f += e_ij * e_ij + e_ji * e_ji
            g = e_ij + e_ji
            W[j * ld + i] = g
            gs = g * s
            hi += gs
            h[j] += gs
        h[i] += hi
    for i in range(n):
        h[i] *= r[i] * r[i]
    # Pass 3: K_ab = df/dw_ab (Eq. 5-8), df/dp_a = sum_b K_ab mask_ab 2 (p_a - p_b) (Eq. 9).
    for i in range(n):
        xi = P[i, 0]
        yi = P[i, 1]
        zi = P[i, 2]
        ri = r[i]
        hi = h[i]
        gx = 0.0
        gy = 0.0
        gz = 0.0
        for j in range(i + 1, n):
            c = 2.0 * mask[i, j] * (2.0 * W[j * ld + i] * ri * r[j] - hi - h[j])
            cx = c * (xi - P[j, 0])
            cy = c * (yi - P[j, 1])
            cz = c * (zi - P[j, 2])
            gx += cx
            gy += cy
            gz += cz
            grad_out[j, 0] -= cx
            grad_out[j, 1] -= cy
            grad_out[j, 2] -= cz
        grad_out[i, 0] += gx
        grad_out[i, 1] += gy
        grad_out[i, 2] += gz
    return f


@njit(cache=True, nogil=True)
def metric_kernel(P: np.ndarray, Sdes: np.ndarray, mask: np.ndarray, grad_out: np.ndarray) -> float:
    """Similarity metric f (Eq. 4) and its gradient df/dP (Eq. 5-9); the optimiser's hot path.

    P: (n, 3) current points [m]; Sdes: (n, n) = ``normalized_adjacency(desired, mask)``;
    mask: (n, n) float64 edge mask; grad_out: (n, 3), OVERWRITTEN with df/dP [1/m].
    Returns f. No input validation (see ``similarity``). No heap allocation for n <= STACK_N
    (its scratch lives on the stack); larger n falls back to heap scratch.
    """
    n = P.shape[0]
    if n <= STACK_N:
        r = carray(_stack_f64(STACK_N), (STACK_N,))
        h = carray(_stack_f64(STACK_N), (STACK_N,))
        W = carray(_stack_f64(_STACK_NN), (_STACK_NN,))
        return _metric_core(P, Sdes, mask, grad_out, r, h, W, STACK_N)
    r = np.empty(n)
    h = np.empty(n)
    W = np.empty(n * n)
    return _metric_core(P, Sdes, mask, grad_out, r, h, W, n)


def complete_mask(n: int) -> np.ndarray:
    """Edge mask of the complete graph over n vertices: (n, n) float64, ones off the diagonal."""
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    n = int(n)
    return np.ones((n, n)) - np.eye(n)


def _points(name: str, a: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] < 2:
        raise ValueError(f"{name} must hold at least 2 points, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _mask(mask: np.ndarray | None, n: int) -> np.ndarray:
    if mask is None:
        return complete_mask(n)
    m = np.ascontiguousarray(mask, dtype=np.float64)
    if m.shape != (n, n):
        raise ValueError(f"mask must have shape ({n}, {n}), got {m.shape}")
    if not np.all((m == 0.0) | (m == 1.0)):
        raise ValueError("mask entries must be 0 or 1")
    if not np.array_equal(m, m.T):
        raise ValueError("mask must be symmetric")
    if np.any(np.diag(m) != 0.0):
        raise ValueError("mask diagonal must be zero")
    return m


def similarity(
    points: np.ndarray, desired: np.ndarray, mask: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Validated similarity metric: ``(f, df/dpoints)`` with the gradient of shape (N, 3).

    points, desired: (N, 3) finite, N >= 2, same N [m]; mask: (N, N) symmetric 0/1 with zero
    diagonal, default the complete graph. Raises ValueError on bad input.
    """
    P = _points("points", points)
    Q = _points("desired", desired)
    if P.shape != Q.shape:
        raise ValueError(f"points {P.shape} and desired {Q.shape} must have the same shape")
    m = _mask(mask, P.shape[0])
    grad = np.empty_like(P)
    f = metric_kernel(P, normalized_adjacency(Q, m), m, grad)
    return float(f), grad


@njit(cache=True, nogil=True)
def metric_own_rate(
    P: np.ndarray,
    V: np.ndarray,
    Sdes: np.ndarray,
    mask: np.ndarray,
    W: np.ndarray,
    r: np.ndarray,
    h: np.ndarray,
) -> tuple[float, float, float, float, float]:
    """The metric for the optimiser's hot path: f, df/dP[0] and sum_{i>=1} df/dP[i] . V[i].

    The same f and gradient as ``metric_kernel`` (Eq. 4-9), but it returns only what one
    drone's cost term needs: the gradient row of its own point (index 0) and the rate of change
    of f as the peers (rows 1..n-1) move with velocities V (the tau term of Eq. 28; V[0] is not
    read). P, V: (n, 3); Sdes, mask: (n, n); scratch W: (n, n), r, h: (n,), all overwritten.
    Returns (f, gx, gy, gz, rate).

    Two passes over the pairs instead of three. With K_ab = df/dw_ab = 2 (2 g_ab r_a r_b - h_a -
    h_b) (Eq. 5-8; g_ab = e_ab + e_ba, h_a = r_a^2 sum_b g_ab s_ab) and u_ab = m_ab (p_a - p_b) .
    (v_a - v_b), the rate sum_{a<b} K_ab u_ab splits into 4 sum_{a<b} g_ab r_a r_b u_ab, summed
    in the pass that makes g, less 2 sum_a h_a U_a with U_a = sum_b u_ab, summed in the first
    pass; only the own row's n - 1 pairs are visited again for df/dP[0]. W holds w_ab above the
    diagonal (then g_0b r_0 r_b in row 0), u_ab below it and U_a on it.
    """
    n = P.shape[0]
    for i in range(n):
        r[i] = 0.0
        h[i] = 0.0
        W[i, i] = 0.0
    # pass 1: w_ij (Eq. 1), the degrees (Eq. 2) and u_ij, U_i (the own row's velocity is 0)
    for i in range(n):
        xi = P[i, 0]
        yi = P[i, 1]
        zi = P[i, 2]
        vxi = 0.0
        vyi = 0.0
        vzi = 0.0
        if i > 0:
            vxi = V[i, 0]
            vyi = V[i, 1]
            vzi = V[i, 2]
        di = 0.0
        ui = 0.0
        for j in range(i + 1, n):
            m = mask[i, j]
            dx = xi - P[j, 0]
            dy = yi - P[j, 1]
            dz = zi - P[j, 2]
            w = m * (dx * dx + dy * dy + dz * dz)
            u = m * (dx * (vxi - V[j, 0]) + dy * (vyi - V[j, 1]) + dz * (vzi - V[j, 2]))
            W[i, j] = w
            W[j, i] = u
            di += w
            r[j] += w
            ui += u
            W[j, j] += u
        r[i] += di
        W[i, i] += ui
    for i in range(n):
        r[i] = 1.0 / np.sqrt(r[i] + EPS_DEG)
    # pass 2: S_ij (Eq. 3), f (Eq. 4), h_i and the rate's pair sum
    f = 0.0
    acc = 0.0
    for i in range(n):
        ri = r[i]
        hi = 0.0
        for j in range(i + 1, n):
            rr = ri * r[j]
            s = W[i, j] * rr
            e_ij = s - Sdes[i, j]
            e_ji = s - Sdes[j, i]
            f += e_ij * e_ij + e_ji * e_ji
            g = e_ij + e_ji
            gs = g * s
            hi += gs
            h[j] += gs
            grr = g * rr
            acc += grr * W[j, i]
            if i == 0:
                W[0, j] = grr  # w_0j is not read again
        h[i] += hi
    rate = 4.0 * acc
    for i in range(n):
        h[i] *= r[i] * r[i]
        rate -= 2.0 * h[i] * W[i, i]
    # df/dP[0] = sum_j K_0j mask_0j 2 (p_0 - p_j) (Eq. 9)
    gx = 0.0
    gy = 0.0
    gz = 0.0
    h0 = h[0]
    for j in range(1, n):
        m = mask[0, j]
        if m == 0.0:
            continue
        c = 2.0 * m * (2.0 * W[0, j] - h0 - h[j])
        gx += c * (P[0, 0] - P[j, 0])
        gy += c * (P[0, 1] - P[j, 1])
        gz += c * (P[0, 2] - P[j, 2])
    return f, gx, gy, gz, rate
