"""MINCO minimum-jerk trajectories (s = 3, degree 5, m = 3), paper Sec. IV-A.

The trajectory class is parameterised by inner waypoints ``q`` (M-1, 3) and piece durations ``T``
(M,) with fixed (p, v, a) at both ends. The coefficients ``c = C(q, T)`` solve one banded linear
system ``A(T) c = b(q)``: its rows ask for the start state, then for every inner waypoint i the
continuity of jerk and snap, the position ``q_i``, and the continuity of position, velocity and
acceleration, then the end state. These are the optimality conditions of minimum jerk, so the
solution is the unique minimum-jerk trajectory through ``q`` with durations ``T``.

Gradients of any cost ``J(c, T)`` flow back to ``(q, T)`` by the adjoint: with ``G = A^-T dJ/dc``,
``dJ/dq_i = G[row of q_i]`` and ``dJ/dT_i = dJ/dT_i|_c - sum_rows G[r] . (dA[r]/dT_i) c``; a row
that asks for derivative k at the end of piece i has ``(dA[r]/dT_i) c = p_i^(k+1)(T_i)``.

The band is stored as ``band[r, col - r + BW]`` and factorised in place by LU without pivoting
(the row order above keeps every pivot away from zero).
"""

from __future__ import annotations

import numpy as np
from numba import njit

BW = 6  # lower and upper bandwidth
BAND_COLS = 2 * BW + 1


@njit(cache=True, nogil=True)
def _set(band: np.ndarray, r: int, c: int, v: float) -> None:
    band[r, c - r + BW] = v


@njit(cache=True, nogil=True)
def _basis_row(band: np.ndarray, r: int, col0: int, k: int, T: float) -> None:
    """Row r gets the k-th derivative of [1, t, ..., t^5] at t = T in columns col0..col0+5."""
    t2 = T * T
    t3 = t2 * T
    t4 = t3 * T
    t5 = t4 * T
    if k == 0:
        vals = (1.0, T, t2, t3, t4, t5)
    elif k == 1:
        vals = (0.0, 1.0, 2.0 * T, 3.0 * t2, 4.0 * t3, 5.0 * t4)
    elif k == 2:
        vals = (0.0, 0.0, 2.0, 6.0 * T, 12.0 * t2, 20.0 * t3)
    elif k == 3:
        vals = (0.0, 0.0, 0.0, 6.0, 24.0 * T, 60.0 * t2)
    else:
        vals = (0.0, 0.0, 0.0, 0.0, 24.0, 120.0 * T)
    lo = max(k, 0)
    for j in range(lo, 6):
        c = col0 + j
        if abs(c - r) <= BW:
            band[r, c - r + BW] = vals[j]


@njit(cache=True, nogil=True)
def build_system(
    head: np.ndarray,
    tail: np.ndarray,
    q: np.ndarray,
    T: np.ndarray,
    band: np.ndarray,
    rhs: np.ndarray,
) -> None:
    """Fill the band (6M, 13) and right-hand side (6M, 3) of A(T) c = b(q).

    head, tail: (3, 3) rows p, v, a at start and end; q: (M-1, 3); T: (M,).
    """
    M = T.shape[0]
    band[:, :] = 0.0
    rhs[:, :] = 0.0
    _set(band, 0, 0, 1.0)
    _set(band, 1, 1, 1.0)
    _set(band, 2, 2, 2.0)
    for d in range(3):
        rhs[0, d] = head[0, d]
        rhs[1, d] = head[1, d]
        rhs[2, d] = head[2, d]
    for i in range(M - 1):
        r = 6 * i + 3
        c0 = 6 * i
        c1 = 6 * i + 6
        Ti = T[i]
        _basis_row(band, r, c0, 3, Ti)  # jerk continuity
        _set(band, r, c1 + 3, -6.0)
        _basis_row(band, r + 1, c0, 4, Ti)  # snap continuity
        _set(band, r + 1, c1 + 4, -24.0)
        _basis_row(band, r + 2, c0, 0, Ti)  # position = q_i
        _basis_row(band, r + 3, c0, 0, Ti)  # position continuity
        _set(band, r + 3, c1, -1.0)
        _basis_row(band, r + 4, c0, 1, Ti)  # velocity continuity
        _set(band, r + 4, c1 + 1, -1.0)
        _basis_row(band, r + 5, c0, 2, Ti)  # acceleration continuity
        _set(band, r + 5, c1 + 2, -2.0)
        for d in range(3):
            rhs[r + 2, d] = q[i, d]
    r = 6 * M - 3
    c0 = 6 * (M - 1)
    for k in range(3):
        _basis_row(band, r + k, c0, k, T[M - 1])
        for d in range(3):
            rhs[r + k, d] = tail[k, d]


@njit(cache=True, nogil=True)
def band_lu(band: np.ndarray) -> bool:
    """In-place LU factorisation without pivoting (unit lower L below the diagonal). False,
    with the factorisation left unfinished, at a zero pivot: durations of absurd ratios (a
    line search's trial step once gave pieces of 6e7 s and 2e-9 s side by side) cancel a
    pivot to zero, where the division would raise out of the compiled code."""
    n = band.shape[0]
    for k in range(n):
        piv = band[k, BW]
        if piv == 0.0:
            return False
        for i in range(k + 1, min(k + BW + 1, n)):
            lik = band[i, k - i + BW]
            if lik == 0.0:
                continue
            lik /= piv
            band[i, k - i + BW] = lik
            for j in range(k + 1, min(k + BW + 1, n)):
                band[i, j - i + BW] -= lik * band[k, j - k + BW]
    return True


@njit(cache=True, nogil=True)
def band_solve(band: np.ndarray, b: np.ndarray) -> None:
    """Solve (LU) x = b in place; b is (n, 3)."""
    n = band.shape[0]
    for i in range(n):
        for k in range(max(0, i - BW), i):
            lik = band[i, k - i + BW]
            if lik != 0.0:
                for d in range(3):
                    b[i, d] -= lik * b[k, d]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, min(i + BW + 1, n)):
            uij = band[i, j - i + BW]
            if uij != 0.0:
                for d in range(3):
                    b[i, d] -= uij * b[j, d]
        inv = 1.0 / band[i, BW]
        for d in range(3):
            b[i, d] *= inv


@njit(cache=True, nogil=True)
def band_solve_transpose(band: np.ndarray, b: np.ndarray) -> None:
    """Solve (LU)^T x = b in place: U^T w = b (forward), then L^T x = w (backward)."""
    n = band.shape[0]
    for i in range(n):
        for k in range(max(0, i - BW), i):
            uki = band[k, i - k + BW]
            if uki != 0.0:
                for d in range(3):
                    b[i, d] -= uki * b[k, d]
        inv = 1.0 / band[i, BW]
        for d in range(3):
            b[i, d] *= inv
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, min(i + BW + 1, n)):
            lki = band[k, i - k + BW]
            if lki != 0.0:
                for d in range(3):
                    b[i, d] -= lki * b[k, d]


@njit(cache=True, nogil=True)
def solve_coeffs(
    head: np.ndarray,
    tail: np.ndarray,
    q: np.ndarray,
    T: np.ndarray,
    band: np.ndarray,
    coeffs: np.ndarray,
) -> bool:
    """c = C(q, T): fills ``coeffs`` (6M, 3) and leaves the LU factors in ``band``; False, with
    ``coeffs`` all NaN, when the system is singular to working precision (``band_lu``)."""
    build_system(head, tail, q, T, band, coeffs)
    if not band_lu(band):
        coeffs[:, :] = np.nan
        return False
    band_solve(band, coeffs)
    return True


@njit(cache=True, nogil=True)
def energy(coeffs: np.ndarray, T: np.ndarray, gc: np.ndarray, gT: np.ndarray) -> float:
    """J_e = sum_i int_0^T_i ||p_i'''||^2 dt (paper Eq. 11-13), gradients ADDED to gc, gT.

    coeffs, gc: (6M, 3); T, gT: (M,).
    """
    M = T.shape[0]
    total = 0.0
    for i in range(M):
        t1 = T[i]
        t2 = t1 * t1
        t3 = t2 * t1
        t4 = t3 * t1
        t5 = t4 * t1
        b = 6 * i
        jT2 = 0.0
        for d in range(3):
            c3 = coeffs[b + 3, d]
            c4 = coeffs[b + 4, d]
            c5 = coeffs[b + 5, d]
            total += (
                36.0 * c3 * c3 * t1
                + 144.0 * c3 * c4 * t2
                + 192.0 * c4 * c4 * t3
                + 240.0 * c3 * c5 * t3
                + 720.0 * c4 * c5 * t4
                + 720.0 * c5 * c5 * t5
            )
            gc[b + 3, d] += 72.0 * c3 * t1 + 144.0 * c4 * t2 + 240.0 * c5 * t3
            gc[b + 4, d] += 144.0 * c3 * t2 + 384.0 * c4 * t3 + 720.0 * c5 * t4
            gc[b + 5, d] += 240.0 * c3 * t3 + 720.0 * c4 * t4 + 1440.0 * c5 * t5
            jerk_end = 6.0 * c3 + 24.0 * c4 * t1 + 60.0 * c5 * t2
            jT2 += jerk_end * jerk_end
        gT[i] += jT2
    return total


@njit(cache=True, nogil=True)
def _deriv_at(coeffs: np.ndarray, b: int, k: int, t: float, d: int) -> float:
    """k-th derivative (0..5) of coordinate d of the piece whose coefficients start at row b."""
    acc = 0.0
    tp = 1.0
    for j in range(k, 6):
        fac = 1.0
        for m in range(j - k + 1, j + 1):
            fac *= m
        acc += fac * coeffs[b + j, d] * tp
        tp *= t
    return acc


@njit(cache=True, nogil=True)
def propagate_gradient(
    band: np.ndarray,
    coeffs: np.ndarray,
    T: np.ndarray,
    gc: np.ndarray,
    gT: np.ndarray,
    gq: np.ndarray,
) -> None:
    """Adjoint: turn dJ/dc (gc, overwritten) and partial dJ/dT (gT) into total dJ/dq, dJ/dT.

    band holds the LU factors of A(T) from ``solve_coeffs``; gq (M-1, 3) is overwritten,
    gT (M,) is updated in place to the total derivative.
    """
    M = T.shape[0]
    band_solve_transpose(band, gc)  # gc now holds G = A^-T dJ/dc
    for i in range(M - 1):
        r = 6 * i + 3
        b = 6 * i
        Ti = T[i]
        s = 0.0
        for d in range(3):
            s += gc[r, d] * _deriv_at(coeffs, b, 4, Ti, d)  # jerk row -> snap
            s += gc[r + 1, d] * _deriv_at(coeffs, b, 5, Ti, d)  # snap row -> crackle
            vel = _deriv_at(coeffs, b, 1, Ti, d)
            s += (gc[r + 2, d] + gc[r + 3, d]) * vel  # both position rows
            s += gc[r + 4, d] * _deriv_at(coeffs, b, 2, Ti, d)
            s += gc[r + 5, d] * _deriv_at(coeffs, b, 3, Ti, d)
            gq[i, d] = gc[r + 2, d]
        gT[i] -= s
    r = 6 * M - 3
    b = 6 * (M - 1)
    s = 0.0
    for d in range(3):
        for k in range(3):
            s += gc[r + k, d] * _deriv_at(coeffs, b, k + 1, T[M - 1], d)
    gT[M - 1] -= s


class Minco:
    """A minimum-jerk trajectory with a small lifecycle (the compiled objective uses the kernels).

    1. ``set_conditions(head, tail)`` with (3, 3) arrays of rows p, v, a;
    2. ``set_parameters(q, T)``;
    3. read ``coeffs``, ``energy()`` and its gradients;
    4. ``propagate(gc, gT)`` turns any dJ/dc, dJ/dT into dJ/dq, dJ/dT.
    """

    def __init__(self, n_pieces: int) -> None:
        if n_pieces < 1:
            raise ValueError("a trajectory needs at least one piece")
        self.M = n_pieces
        self.band = np.zeros((6 * n_pieces, BAND_COLS))
        self.c = np.zeros((6 * n_pieces, 3))
        self.head = np.zeros((3, 3))
        self.tail = np.zeros((3, 3))
        self.q = np.zeros((max(n_pieces - 1, 0), 3))
        self.T = np.ones(n_pieces)

    def set_conditions(self, head: np.ndarray, tail: np.ndarray) -> None:
        self.head = np.array(head, dtype=np.float64).reshape(3, 3)
        self.tail = np.array(tail, dtype=np.float64).reshape(3, 3)

    def set_parameters(self, q: np.ndarray, T: np.ndarray) -> None:
        q = np.array(q, dtype=np.float64).reshape(self.M - 1, 3)
        T = np.array(T, dtype=np.float64).reshape(self.M)
        if np.any(T <= 0) or not np.all(np.isfinite(T)) or not np.all(np.isfinite(q)):
            raise ValueError("durations must be positive and all parameters finite")
        band = np.zeros_like(self.band)
        c = np.zeros_like(self.c)
        if not solve_coeffs(self.head, self.tail, q, T, band, c):  # the state stays as it was
            raise ValueError("durations too far apart: the MINCO system is singular")
        self.q, self.T, self.band, self.c = q, T, band, c

    @property
    def coeffs(self) -> np.ndarray:
        """Coefficients as (M, 6, 3)."""
        return self.c.reshape(self.M, 6, 3).copy()

    def energy(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(J_e, dJ_e/dc (M, 6, 3), dJ_e/dT (M,)) at fixed coefficients."""
        gc = np.zeros_like(self.c)
        gT = np.zeros(self.M)
        e = energy(self.c, self.T, gc, gT)
        return e, gc.reshape(self.M, 6, 3), gT

    def propagate(self, gc: np.ndarray, gT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dJ/dq (M-1, 3), dJ/dT (M,)) from dJ/dc (M, 6, 3) and the partial dJ/dT (M,)."""
        g = np.array(gc, dtype=np.float64).reshape(6 * self.M, 3)
        gt = np.array(gT, dtype=np.float64).reshape(self.M)
        gq = np.zeros((self.M - 1, 3))
        propagate_gradient(self.band, self.c, self.T, g, gt, gq)
        return gq, gt
