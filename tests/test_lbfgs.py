"""L-BFGS (reverse communication): convergence, limits, cancel, failure paths, compiled driver."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import pytest
from numba import njit

from onboard.planner.lbfgs import (
    EVALUATE,
    INVALID_CALL,
    MAX_PAST,
    N_PARAMS,
    P_MAX_LINESEARCH,
    LbfgsParams,
    LbfgsStatus,
    lbfgs_best_x_into,
    lbfgs_cancel,
    lbfgs_evaluations,
    lbfgs_iterate,
    lbfgs_iterations,
    lbfgs_result_f,
    lbfgs_start,
    lbfgs_status,
    lbfgs_workspace,
    minimize,
    status_message,
)

TIGHT = LbfgsParams(g_epsilon=1e-8, past=0)


@njit
def rosenbrock_nb(x: np.ndarray, g: np.ndarray) -> float:
    """Chained Rosenbrock: sum 100 (x_{i+1} - x_i^2)^2 + (1 - x_i)^2; g overwritten."""
    n = x.shape[0]
    f = 0.0
    for i in range(n):
        g[i] = 0.0
    for i in range(n - 1):
        a = x[i + 1] - x[i] * x[i]
        b = 1.0 - x[i]
        f += 100.0 * a * a + b * b
        g[i] += -400.0 * x[i] * a - 2.0 * b
        g[i + 1] += 200.0 * a
    return f


def rosenbrock(x: np.ndarray) -> tuple[float, np.ndarray]:
    g = np.empty_like(x)
    f = rosenbrock_nb(x, g)
    return f, g


def rosen_start(n: int) -> np.ndarray:
    return np.tile([-1.2, 1.0], n // 2)


class Recorder:
    """Wraps an objective, recording every evaluated point and value."""

    def __init__(self, fun: Callable[[np.ndarray], tuple[float, np.ndarray]]) -> None:
        self.fun = fun
        self.xs: list[np.ndarray] = []
        self.fs: list[float] = []

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = self.fun(x)
        self.xs.append(x.copy())
        self.fs.append(f)
        return f, g


@pytest.mark.parametrize("n", [2, 10])
def test_rosenbrock_converges(n: int) -> None:
    rec = Recorder(rosenbrock)
    r = minimize(rec, rosen_start(n), TIGHT)
    assert r.status == LbfgsStatus.CONVERGENCE
    assert r.message == status_message(LbfgsStatus.CONVERGENCE)
    np.testing.assert_allclose(r.x, 1.0, atol=1e-6)
    assert r.f < 1e-12
    assert r.f == rosenbrock(r.x)[0]
    np.testing.assert_array_equal(r.g, rosenbrock(r.x)[1])
    assert np.linalg.norm(r.g) < 1e-8 * max(1.0, float(np.linalg.norm(r.x)))
    assert r.evaluations == len(rec.fs)
    assert 10 < r.iterations < r.evaluations < 300


def test_rosenbrock_default_params_stop_on_decrease_or_converge() -> None:
    r = minimize(rosenbrock, rosen_start(10))
    assert r.status in (LbfgsStatus.CONVERGENCE, LbfgsStatus.STOP_DECREASE)
    assert r.f < 1e-6


def test_convex_quadratic_50d() -> None:
    rng = np.random.default_rng(0)
    n = 50
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    A = Q @ np.diag(np.logspace(0, 3, n)) @ Q.T
    b = rng.normal(size=n)
    x_star = np.linalg.solve(A, b)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        return 0.5 * x @ A @ x - b @ x, A @ x - b

    # (f's rounding noise starts to dominate its decrease at ||g|| ~ 1e-6 on an Intel host and
    # ~2e-6 on an AMD EPYC one, where 1e-6 ended in a line-search failure: 1e-5 stays clear)
    r = minimize(fun, np.zeros(n), LbfgsParams(g_epsilon=1e-5, past=0))
    assert r.status == LbfgsStatus.CONVERGENCE
    np.testing.assert_allclose(r.x, x_star, rtol=0, atol=1e-6 * float(np.linalg.norm(x_star)))
    assert r.evaluations < 400
    # asking for more than the arithmetic can give ends in a line-search failure, best point kept
    r2 = minimize(fun, np.zeros(n), LbfgsParams(g_epsilon=1e-12, past=0))
    assert r2.status == LbfgsStatus.LINESEARCH_FAILED
    assert r2.f <= r.f
    np.testing.assert_allclose(r2.x, x_star, rtol=0, atol=1e-6 * float(np.linalg.norm(x_star)))


def test_already_converged_start() -> None:
    rec = Recorder(rosenbrock)
    r = minimize(rec, np.ones(4))
    assert r.status == LbfgsStatus.CONVERGENCE
    assert r.iterations == 0 and r.evaluations == 1 and len(rec.fs) == 1
    np.testing.assert_array_equal(r.x, 1.0)


def test_max_iterations_respected() -> None:
    r = minimize(rosenbrock, rosen_start(10), LbfgsParams(max_iterations=5, past=0))
    assert r.status == LbfgsStatus.MAX_ITERATIONS
    assert r.iterations == 5


@pytest.mark.parametrize("max_ev", [1, 2, 7, 30])
def test_max_evaluations_respected(max_ev: int) -> None:
    rec = Recorder(rosenbrock)
    r = minimize(rec, rosen_start(10), LbfgsParams(max_evaluations=max_ev, past=0))
    assert r.status == LbfgsStatus.MAX_EVALUATIONS
    assert r.evaluations == max_ev == len(rec.fs)
    assert r.f == min(rec.fs)


@pytest.mark.parametrize("k", [1, 2, 5, 20])
def test_cancel_callable(k: int) -> None:
    polls = [0]

    def cancel() -> bool:
        polls[0] += 1
        return polls[0] >= k

    rec = Recorder(rosenbrock)
    r = minimize(rec, rosen_start(2), TIGHT, cancel=cancel)
    assert r.status == LbfgsStatus.CANCELED
    assert r.evaluations == k == len(rec.fs)  # start point + (k - 1) polls that said "go on"
    best = int(np.argmin(rec.fs))
    assert r.f == rec.fs[best]
    np.testing.assert_array_equal(r.x, rec.xs[best])
    np.testing.assert_array_equal(r.g, rosenbrock(r.x)[1])


def test_cancel_event_already_set() -> None:
    ev = threading.Event()
    ev.set()
    x0 = rosen_start(2)
    r = minimize(rosenbrock, x0, cancel=ev)
    assert r.status == LbfgsStatus.CANCELED
    assert r.evaluations == 1
    np.testing.assert_array_equal(r.x, x0)
    assert r.f == rosenbrock(x0)[0]


def test_cancel_event_not_set_does_nothing() -> None:
    r = minimize(rosenbrock, rosen_start(2), TIGHT, cancel=threading.Event())
    assert r.status == LbfgsStatus.CONVERGENCE


@pytest.mark.parametrize("bad", ["f", "g", "x"])
def test_non_finite_at_start(bad: str) -> None:
    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = rosenbrock(x)
        if bad == "f":
            f = np.nan
        if bad == "g":
            g[0] = np.inf
        return f, g

    x0 = rosen_start(2)
    if bad == "x":
        x0 = np.array([np.nan, 1.0])
    r = minimize(fun, x0)
    assert r.status == LbfgsStatus.NON_FINITE
    assert r.evaluations == 1 and r.iterations == 0


def test_nan_trial_points_are_survived() -> None:
    """Pseudo-Huber: the steps (doubling, then secant) overshoot into a region where f is NaN."""

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        if np.any(x < -3.0):
            return np.nan, np.full_like(x, np.nan)
        r = np.sqrt(1.0 + x * x)
        return float(np.sum(r)), x / r

    rec = Recorder(fun)
    r = minimize(rec, np.array([100.0, 80.0]), TIGHT)
    assert sum(np.isnan(f) for f in rec.fs) > 3  # the NaN region was really hit
    assert r.status == LbfgsStatus.CONVERGENCE
    np.testing.assert_allclose(r.x, 0.0, atol=1e-7)


def test_wrong_gradient_fails_line_search_in_bounded_evaluations() -> None:
    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        return float(x @ x), -2.0 * x  # wrong sign

    x0 = np.array([1.0, -2.0, 3.0])
    rec = Recorder(fun)
    r = minimize(rec, x0)
    assert r.status == LbfgsStatus.LINESEARCH_FAILED
    assert r.evaluations <= 1 + LbfgsParams().max_linesearch
    np.testing.assert_array_equal(r.x, x0)  # nothing better was found: the start point
    assert r.f == x0 @ x0


@pytest.mark.parametrize("seed", range(5))
def test_numerical_noise_terminates(seed: int) -> None:
    """No stopping test enabled and f, g noisy: the line-search failure exit ends the solve."""
    rng = np.random.default_rng(seed)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        return float(x @ x + 1e-9 * rng.normal()), 2.0 * x + 1e-6 * rng.normal(size=x.shape)

    rec = Recorder(fun)
    r = minimize(rec, np.full(5, 3.0), LbfgsParams(g_epsilon=0.0, past=0))
    assert r.status == LbfgsStatus.LINESEARCH_FAILED
    assert r.f == min(rec.fs)
    assert r.evaluations < 2000


@pytest.mark.parametrize(
    "params",
    [
        LbfgsParams(mem_size=0),
        LbfgsParams(past=MAX_PAST + 1),
        LbfgsParams(past=-1),
        LbfgsParams(g_epsilon=-1.0),
        LbfgsParams(delta=np.nan),
        LbfgsParams(max_linesearch=0),
        LbfgsParams(min_step=0.0),
        LbfgsParams(min_step=1.0, max_step=0.5),
        LbfgsParams(f_dec_coeff=0.9, s_curv_coeff=0.5),
        LbfgsParams(s_curv_coeff=1.0),
    ],
)
def test_invalid_params(params: LbfgsParams) -> None:
    r = minimize(rosenbrock, rosen_start(2), params)
    assert r.status == LbfgsStatus.INVALID_PARAMS
    assert r.evaluations == 1


def test_workspace_mismatch_is_invalid() -> None:
    ws, iw = lbfgs_workspace(3, 4)
    x = np.zeros(4)
    g = np.ones(4)
    p = LbfgsParams(mem_size=4).to_array()
    assert lbfgs_start(ws, iw, p, x, 1.0, g) == LbfgsStatus.INVALID_PARAMS
    ws, iw = lbfgs_workspace(4, 4)
    p = LbfgsParams(mem_size=5).to_array()  # more memory than the workspace holds
    assert lbfgs_start(ws, iw, p, x, 1.0, g) == LbfgsStatus.INVALID_PARAMS
    assert lbfgs_start(ws, iw, p[:-1], x, 1.0, g) == LbfgsStatus.INVALID_PARAMS


def test_iterate_without_running_solve() -> None:
    ws, iw = lbfgs_workspace(2, 3)
    p = LbfgsParams(mem_size=3).to_array()
    x = np.zeros(2)
    g = np.zeros(2)
    assert lbfgs_iterate(ws, iw, p, x, 0.0, g) == INVALID_CALL
    x = rosen_start(2)
    f = rosenbrock_nb(x, g)
    assert lbfgs_start(ws, iw, p, x, f, g) == EVALUATE
    assert lbfgs_cancel(ws, iw, x, g) == LbfgsStatus.CANCELED
    assert lbfgs_status(iw) == LbfgsStatus.CANCELED
    assert lbfgs_iterate(ws, iw, p, x, f, g) == INVALID_CALL
    assert lbfgs_cancel(ws, iw, x, g) == LbfgsStatus.CANCELED


def test_status_messages() -> None:
    msgs = {s: status_message(s) for s in LbfgsStatus}
    assert len(set(msgs.values())) == len(LbfgsStatus)
    assert all(m for m in msgs.values())
    assert "unknown" in status_message(99)
    assert all(s >= 0 for s in LbfgsStatus if s != LbfgsStatus.EVALUATE)


def test_params_array_layout() -> None:
    a = LbfgsParams(max_linesearch=17).to_array()
    assert a.shape == (N_PARAMS,) and a.dtype == np.float64
    assert a[P_MAX_LINESEARCH] == 17.0


def test_bad_x0_and_gradient_shape_raise() -> None:
    with pytest.raises(ValueError, match="1-D"):
        minimize(rosenbrock, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="gradient of shape"):
        minimize(lambda x: (0.0, np.zeros(3)), np.zeros(2))


# ---- compiled driver loop ------------------------------------------------------------------------


@njit
def solve_compiled(
    x: np.ndarray, ws: np.ndarray, iw: np.ndarray, p: np.ndarray, cancel_flag: np.ndarray
) -> tuple[int, float]:
    g = np.empty_like(x)
    f = rosenbrock_nb(x, g)
    status = lbfgs_start(ws, iw, p, x, f, g)
    while status == EVALUATE:
        if cancel_flag[0] != 0:
            status = lbfgs_cancel(ws, iw, x, g)
            break
        f = rosenbrock_nb(x, g)
        status = lbfgs_iterate(ws, iw, p, x, f, g)
    return status, lbfgs_result_f(ws)


@pytest.mark.parametrize("n", [2, 10])
def test_compiled_driver_matches_python_driver(n: int) -> None:
    py = minimize(rosenbrock, rosen_start(n), TIGHT)
    x = rosen_start(n)
    ws, iw = lbfgs_workspace(n, TIGHT.mem_size)
    status, f = solve_compiled(x, ws, iw, TIGHT.to_array(), np.zeros(1, dtype=np.int64))
    assert status == py.status == LbfgsStatus.CONVERGENCE
    np.testing.assert_allclose(x, py.x, rtol=0, atol=1e-10)
    assert f == py.f
    assert lbfgs_evaluations(iw) == py.evaluations
    assert lbfgs_iterations(iw) == py.iterations
    best = np.empty(n)
    lbfgs_best_x_into(ws, best)
    np.testing.assert_array_equal(best, x)

    # the workspace is reusable: a second solve gives the same answer
    x2 = rosen_start(n)
    status2, f2 = solve_compiled(x2, ws, iw, TIGHT.to_array(), np.zeros(1, dtype=np.int64))
    assert status2 == status and f2 == f
    np.testing.assert_array_equal(x2, x)


def test_compiled_driver_cancel_flag() -> None:
    x0 = rosen_start(2)
    x = x0.copy()
    ws, iw = lbfgs_workspace(2, 16)
    status, f = solve_compiled(x, ws, iw, TIGHT.to_array(), np.ones(1, dtype=np.int64))
    assert status == LbfgsStatus.CANCELED
    np.testing.assert_array_equal(x, x0)
    assert f == rosenbrock(x0)[0]
