"""Piecewise quintic trajectories in ENU metres with a global start time.

A trajectory is M pieces; piece i is ``p_i(t) = sum_k coeffs[i, k] * t**k`` for
``t in [0, durations_s[i]]``. Before its start a trajectory stays at its first point, after its end
at its last point with zero derivatives (a drone that finished its plan hovers).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

N_COEFFS = 6  # degree 5
END_TOL_S = 1e-9
"""A time this little past a trajectory's end still samples its end state (rounding of the
piece search), not the hold after it."""


@njit(cache=True, nogil=True)
def _piece_at(durations: np.ndarray, t_rel: float) -> tuple[int, float, bool]:
    """(piece i, time t on it, inside): the piece search and the clamping at both ends that every
    evaluation here shares."""
    m = durations.shape[0]
    inside = True
    if t_rel <= 0.0:
        i = 0
        t = 0.0
        inside = t_rel == 0.0
    else:
        i = 0
        t = t_rel
        while i < m - 1 and t > durations[i]:
            t -= durations[i]
            i += 1
        if t > durations[i]:
            # the end itself is inside: the subtractions above may leave t an ulp past it
            inside = t - durations[i] <= END_TOL_S
            t = durations[i]
    return i, t, inside


@njit(cache=True)
def eval_piecewise(
    coeffs: np.ndarray, durations: np.ndarray, t_rel: float, out: np.ndarray
) -> None:
    """Position, velocity, acceleration, jerk of a piecewise quintic at ``t_rel`` from its start.

    coeffs: (M, 6, 3); durations: (M,); out: (4, 3) receives p, v, a, j. Clamped at both ends
    (derivatives are zero outside [0, sum(durations)]).
    """
    i, t, inside = _piece_at(durations, t_rel)
    t2 = t * t
    t3 = t2 * t
    t4 = t3 * t
    t5 = t4 * t
    for d in range(3):
        c0 = coeffs[i, 0, d]
        c1 = coeffs[i, 1, d]
        c2 = coeffs[i, 2, d]
        c3 = coeffs[i, 3, d]
        c4 = coeffs[i, 4, d]
        c5 = coeffs[i, 5, d]
        out[0, d] = c0 + c1 * t + c2 * t2 + c3 * t3 + c4 * t4 + c5 * t5
        if inside:
            out[1, d] = c1 + 2.0 * c2 * t + 3.0 * c3 * t2 + 4.0 * c4 * t3 + 5.0 * c5 * t4
            out[2, d] = 2.0 * c2 + 6.0 * c3 * t + 12.0 * c4 * t2 + 20.0 * c5 * t3
            out[3, d] = 6.0 * c3 + 24.0 * c4 * t + 60.0 * c5 * t2
        else:
            out[1, d] = 0.0
            out[2, d] = 0.0
            out[3, d] = 0.0


@njit(cache=True, nogil=True)
def eval_position_velocity(
    coeffs: np.ndarray, durations: np.ndarray, t_rel: float, out: np.ndarray
) -> None:
    """Rows p and v of ``eval_piecewise`` (the same arithmetic, so the same values) into
    out[0] and out[1]; the rows below are left alone."""
    i, t, inside = _piece_at(durations, t_rel)
    t2 = t * t
    t3 = t2 * t
    t4 = t3 * t
    t5 = t4 * t
    for d in range(3):
        c0 = coeffs[i, 0, d]
        c1 = coeffs[i, 1, d]
        c2 = coeffs[i, 2, d]
        c3 = coeffs[i, 3, d]
        c4 = coeffs[i, 4, d]
        c5 = coeffs[i, 5, d]
        out[0, d] = c0 + c1 * t + c2 * t2 + c3 * t3 + c4 * t4 + c5 * t5
        if inside:
            out[1, d] = c1 + 2.0 * c2 * t + 3.0 * c3 * t2 + 4.0 * c4 * t3 + 5.0 * c5 * t4
        else:
            out[1, d] = 0.0


@njit(cache=True, nogil=True)
def eval_position(
    coeffs: np.ndarray, durations: np.ndarray, t_rel: float
) -> tuple[float, float, float]:
    """Position of ``eval_piecewise`` (the same arithmetic, so the same values)."""
    i, t, _ = _piece_at(durations, t_rel)
    t2 = t * t
    t3 = t2 * t
    t4 = t3 * t
    t5 = t4 * t
    x = (
        coeffs[i, 0, 0]
        + coeffs[i, 1, 0] * t
        + coeffs[i, 2, 0] * t2
        + coeffs[i, 3, 0] * t3
        + coeffs[i, 4, 0] * t4
        + coeffs[i, 5, 0] * t5
    )
    y = (
        coeffs[i, 0, 1]
        + coeffs[i, 1, 1] * t
        + coeffs[i, 2, 1] * t2
        + coeffs[i, 3, 1] * t3
        + coeffs[i, 4, 1] * t4
        + coeffs[i, 5, 1] * t5
    )
    z = (
        coeffs[i, 0, 2]
        + coeffs[i, 1, 2] * t
        + coeffs[i, 2, 2] * t2
        + coeffs[i, 3, 2] * t3
        + coeffs[i, 4, 2] * t4
        + coeffs[i, 5, 2] * t5
    )
    return x, y, z


@njit(cache=True)
def eval_piecewise_many(
    coeffs: np.ndarray, durations: np.ndarray, t_rel: np.ndarray, order: int
) -> np.ndarray:
    """Derivative ``order`` (0..3) at each of ``t_rel`` (K,), returned as (K, 3)."""
    out = np.empty((t_rel.shape[0], 3))
    buf = np.empty((4, 3))
    for k in range(t_rel.shape[0]):
        eval_piecewise(coeffs, durations, t_rel[k], buf)
        for d in range(3):
            out[k, d] = buf[order, d]
    return out


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A piecewise quintic in ENU metres, starting at global time ``t0_s``.

    coeffs: (M, 6, 3), ``coeffs[i, k]`` multiplies ``t**k`` on piece i (t from the piece start).
    durations_s: (M,), all strictly positive.
    """

    t0_s: float
    coeffs: np.ndarray
    durations_s: np.ndarray

    def __post_init__(self) -> None:
        c = np.ascontiguousarray(self.coeffs, dtype=np.float64)
        T = np.ascontiguousarray(self.durations_s, dtype=np.float64).reshape(-1)
        if c.ndim != 3 or c.shape[1:] != (N_COEFFS, 3):
            raise ValueError(f"coeffs must have shape (M, 6, 3), got {c.shape}")
        if T.shape[0] != c.shape[0] or T.shape[0] == 0:
            raise ValueError(f"durations_s must have shape ({c.shape[0]},), got {T.shape}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(T))):
            raise ValueError("trajectory contains non-finite values")
        if np.any(T <= 0.0):
            raise ValueError("trajectory durations must be strictly positive")
        if not np.isfinite(self.t0_s):
            raise ValueError("trajectory start time must be finite")
        c.setflags(write=False)
        T.setflags(write=False)
        object.__setattr__(self, "coeffs", c)
        object.__setattr__(self, "durations_s", T)
        object.__setattr__(self, "t0_s", float(self.t0_s))

    @classmethod
    def trusted(cls, t0_s: float, coeffs: np.ndarray, durations_s: np.ndarray) -> Trajectory:
        """A trajectory of arrays already known valid, without the checks of the constructor
        (the planner's compiled code made them and checked them finite): coeffs (M, 6, 3) and
        durations_s (M,) C-contiguous float64, finite, durations > 0, t0_s finite. They are
        made read-only, not copied."""
        tr = object.__new__(cls)
        coeffs.setflags(write=False)
        durations_s.setflags(write=False)
        object.__setattr__(tr, "t0_s", float(t0_s))
        object.__setattr__(tr, "coeffs", coeffs)
        object.__setattr__(tr, "durations_s", durations_s)
        return tr

    @property
    def n_pieces(self) -> int:
        return int(self.durations_s.shape[0])

    @property
    def duration_s(self) -> float:
        return float(np.sum(self.durations_s))

    @property
    def t_end_s(self) -> float:
        return self.t0_s + self.duration_s

    def sample(self, t_global: np.ndarray | float, order: int = 0) -> np.ndarray:
        """Derivative ``order`` (0 position .. 3 jerk) at global time(s): (3,) or (K, 3)."""
        if not 0 <= order <= 3:
            raise ValueError("order must be 0..3")
        t = np.atleast_1d(np.asarray(t_global, dtype=np.float64)) - self.t0_s
        out = eval_piecewise_many(self.coeffs, self.durations_s, t, order)
        return out[0] if np.ndim(t_global) == 0 else out

    def state(self, t_global: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, velocity, acceleration) at a global time."""
        buf = np.empty((4, 3))
        eval_piecewise(self.coeffs, self.durations_s, float(t_global) - self.t0_s, buf)
        return buf[0].copy(), buf[1].copy(), buf[2].copy()

    @functools.cached_property
    def end_position(self) -> np.ndarray:
        """Where the trajectory ends (and stays)."""
        c = self.coeffs[-1]
        T = float(self.durations_s[-1])
        return c.T @ (T ** np.arange(N_COEFFS))

    def waypoints(self) -> np.ndarray:
        """Positions at the piece boundaries, (M + 1, 3)."""
        ends = np.concatenate([[0.0], np.cumsum(self.durations_s)])
        return self.sample(self.t0_s + ends)

    def until(self, t_global: float) -> Trajectory:
        """The part of the trajectory up to ``t_global`` (after its start): the same pieces,
        the last one cut short; the whole trajectory when it ends before ``t_global``."""
        cut = float(t_global) - self.t0_s
        if not cut > 0.0:
            raise ValueError(f"until({t_global!r}) is not after the start {self.t0_s!r}")
        ends = np.cumsum(self.durations_s)
        if cut >= ends[-1]:
            return self
        m = int(np.searchsorted(ends, cut, side="left")) + 1
        T = self.durations_s[:m].copy()
        T[-1] = cut - (float(ends[m - 2]) if m > 1 else 0.0)  # > 0: ends[m - 2] < cut
        return Trajectory.trusted(self.t0_s, self.coeffs[:m].copy(), T)

    def stop_along(self, t_s: float, duration_s: float, pieces: int = 4) -> Trajectory | None:
        """A stop from this trajectory's state at ``t_s`` to rest ``duration_s`` later that keeps
        to its path: the trajectory replayed ever slower, at the rate ``1 - 3 u^2 + 2 u^3``
        (``u``: the stop's elapsed fraction), as ``pieces`` quintic pieces that match the
        replay's position, velocity and acceleration at their ends. It ends where this
        trajectory is ``duration_s / 2`` after ``t_s``: as far along as a straight braking stop
        (``braking``) of the same duration goes at the same speed, with the same peak
        deceleration along the way, but on the path the plan was checked on, not across a turn.
        None when this trajectory ends before that point."""
        T = float(duration_s)
        if not (T > 0.0 and math.isfinite(T) and math.isfinite(t_s)) or pieces < 1:
            raise ValueError(f"stop_along needs a finite duration > 0, got {duration_s!r}")
        if t_s + 0.5 * T > self.t_end_s:
            return None
        u = np.linspace(0.0, 1.0, pieces + 1)
        rate = 1.0 - 3.0 * u**2 + 2.0 * u**3  # d(replay time)/dt
        rate_dot = (-6.0 * u + 6.0 * u**2) / T
        at = t_s + T * (u - u**3 + 0.5 * u**4)  # the replay's time: the rate's integral
        pos = self.sample(at)
        vel0 = self.sample(at, 1)
        vel = vel0 * rate[:, None]
        acc = self.sample(at, 2) * (rate**2)[:, None] + vel0 * rate_dot[:, None]
        h = T / pieces
        h2, h3 = h * h, h * h * h
        c = np.empty((pieces, N_COEFFS, 3))
        for i in range(pieces):
            p0, v0, a0 = pos[i], vel[i], acc[i]
            p1, v1, a1 = pos[i + 1], vel[i + 1], acc[i + 1]
            dp = p1 - p0
            c[i, 0] = p0
            c[i, 1] = v0
            c[i, 2] = 0.5 * a0
            c[i, 3] = (20.0 * dp - (8.0 * v1 + 12.0 * v0) * h - (3.0 * a0 - a1) * h2) / (2.0 * h3)
            c[i, 4] = (-30.0 * dp + (14.0 * v1 + 16.0 * v0) * h + (3.0 * a0 - 2.0 * a1) * h2) / (
                2.0 * h3 * h
            )
            c[i, 5] = (12.0 * dp - 6.0 * (v1 + v0) * h - (a0 - a1) * h2) / (2.0 * h3 * h2)
        return Trajectory(t_s, c, np.full(pieces, h))

    @staticmethod
    def hover(position: np.ndarray, t0_s: float, duration_s: float = 1.0) -> Trajectory:
        """A one-piece trajectory that stays at ``position``."""
        c = np.zeros((1, N_COEFFS, 3))
        c[0, 0] = np.asarray(position, dtype=np.float64).reshape(3)
        return Trajectory(t0_s, c, np.array([duration_s]))

    @staticmethod
    def braking(
        t0_s: float,
        p: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        a_max_m_s2: float,
        peak_fraction: float = 0.5,
    ) -> Trajectory:
        """A braking stop from (p, v, a) (3,) at ``t0_s``: ``to_rest`` over
        ``braking_duration_s``, ending ``braking_distance_m`` along v."""
        p = np.asarray(p, dtype=np.float64).reshape(3)
        v = np.asarray(v, dtype=np.float64).reshape(3)
        a = np.asarray(a, dtype=np.float64).reshape(3)
        tb = braking_duration_s(float(np.linalg.norm(v)), a_max_m_s2, peak_fraction)
        return Trajectory.to_rest(t0_s, p, v, a, p + 0.5 * tb * v, tb)

    @staticmethod
    def to_rest(
        t0_s: float,
        p: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        end: np.ndarray,
        duration_s: float,
    ) -> Trajectory:
        """The one quintic piece from (p, v, a) (3,) float64 at ``t0_s`` to rest at ``end``
        after ``duration_s`` (> 0): what a one-piece MINCO with both ends fixed is, in closed
        form, a tenth of the time of ``Minco(1)`` (the planner and the monitor make one braking
        stop per replan and per look)."""
        T = float(duration_s)
        if not (T > 0.0 and math.isfinite(T)):
            raise ValueError(f"duration_s must be positive and finite, got {duration_s!r}")
        T2 = T * T
        T3 = T2 * T
        dp = end - p
        c = np.empty((1, N_COEFFS, 3))
        c[0, 0] = p
        c[0, 1] = v
        c[0, 2] = 0.5 * a
        c[0, 3] = (20.0 * dp - 12.0 * T * v - 3.0 * T2 * a) / (2.0 * T3)
        c[0, 4] = (-30.0 * dp + 16.0 * T * v + 3.0 * T2 * a) / (2.0 * T3 * T)
        c[0, 5] = (12.0 * dp - 6.0 * T * v - T2 * a) / (2.0 * T3 * T2)
        if not (np.isfinite(c).all() and math.isfinite(t0_s)):
            raise ValueError("trajectory contains non-finite values")
        return Trajectory.trusted(t0_s, c, np.array([T]))


def braking_duration_s(speed_m_s: float, a_max_m_s2: float, peak_fraction: float = 0.5) -> float:
    """How long a braking stop from ``speed_m_s`` lasts when its deceleration peaks at about
    ``peak_fraction`` of ``a_max_m_s2`` (a rest-to-rest-like quintic over tb peaks at 1.5 v /
    tb; from a steady speed the default, a gentle stop, averages a third of the limit; 1.0 is
    the hardest stop within it): at least 0.5 s. The planner's own stop, the flight service's
    brakes and the agent's model of a peer's failsafe stop all brake this way."""
    if not 0.0 < peak_fraction <= 1.0:
        raise ValueError(f"peak_fraction must be in (0, 1], got {peak_fraction!r}")
    return max(0.5, 1.5 * speed_m_s / (peak_fraction * max(a_max_m_s2, 1e-3)))


def braking_distance_m(speed_m_s: float, a_max_m_s2: float, peak_fraction: float = 0.5) -> float:
    """How far a braking stop (``braking_duration_s``) from ``speed_m_s`` carries on."""
    return 0.5 * speed_m_s * braking_duration_s(speed_m_s, a_max_m_s2, peak_fraction)
