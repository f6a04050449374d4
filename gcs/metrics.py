"""Evaluation metrics of the paper's benchmark (Sec. V) and small statistics helpers."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def umeyama(current: np.ndarray, desired: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) minimising ``sum_i ||desired_i - (s R current_i + t)||^2``.

    Umeyama's closed form: with centred X (current), Y (desired), ``Sigma = Y^T X / N = U D V^T``
    and ``S = diag(1, 1, sign(det U det V))``: ``R = U S V^T``, ``s = tr(D S) / var_X``,
    ``t = mean_Y - s R mean_X``. current, desired: (N, 3). Returns (s, R (3, 3), t (3,)).
    """
    X = np.asarray(current, dtype=np.float64)
    Y = np.asarray(desired, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"current {X.shape} and desired {Y.shape} must both be (N, 3)")
    n = X.shape[0]
    mx = X.mean(axis=0)
    my = Y.mean(axis=0)
    Xc = X - mx
    Yc = Y - my
    var_x = float(np.sum(Xc * Xc)) / n
    if var_x <= 1e-18:
        return 0.0, np.eye(3), my
    U, D, Vt = np.linalg.svd(Yc.T @ Xc / n)
    S = np.diag([1.0, 1.0, 1.0 if np.linalg.det(U) * np.linalg.det(Vt) >= 0.0 else -1.0])
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S)) / var_x
    return scale, R, my - scale * R @ mx


def e_dist(current: np.ndarray, desired: np.ndarray) -> float:
    """Formation position error after the best Sim(3) alignment (paper Eq. 11).

    current, desired: (N, 3) [m], row i = drone/slot i. Returns
    ``sqrt(min_{s, R, t} sum_i ||desired_i - (s R current_i + t)||^2)`` [m] (the square root, as
    the reference numbers are reported), with R in SO(3) and s >= 0, by Umeyama's closed form
    (``umeyama``); the residual is evaluated from the transform, which keeps it exact for
    similar copies (the closed-form ``N (var_Y - tr(DS)^2 / var_X)`` cancels badly there).
    A degenerate current formation (all points coincident) cannot be scaled: residual = N var_Y.
    """
    X = np.asarray(current, dtype=np.float64)
    Y = np.asarray(desired, dtype=np.float64)
    s, R, t = umeyama(X, Y)
    r = Y - (s * X @ R.T + t)
    return float(np.sqrt(np.sum(r * r)))


def summary(values: Sequence[float] | np.ndarray) -> dict[str, float]:
    """{median, p90, max, mean, count} of ``values`` (NaN statistics when empty)."""
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    if a.size == 0:
        nan = float("nan")
        return {"median": nan, "p90": nan, "max": nan, "mean": nan, "count": 0}
    return {
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "max": float(np.max(a)),
        "mean": float(np.mean(a)),
        "count": int(a.size),
    }
