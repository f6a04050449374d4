"""Time diffeomorphism tau <-> T: inverse, positivity, gradient on both branches."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from onboard.planner.timemap import (
    T_from_tau,
    T_from_tau_into,
    T_from_tau_scalar,
    dT_dtau_scalar,
    grad_tau_from_grad_T,
    grad_tau_from_grad_T_into,
    tau_from_T,
    tau_from_T_scalar,
)


def test_known_values() -> None:
    tau = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    expected = np.array([1.0 / 5.0, 1.0 / 2.5, 1.0, 2.5, 5.0])
    np.testing.assert_allclose(T_from_tau(tau), expected, rtol=1e-15)


def test_round_trips() -> None:
    rng = np.random.default_rng(0)
    tau = np.concatenate(
        [rng.normal(scale=3.0, size=200), [0.0, 1e-12, -1e-12, 1e-6, -1e-6, 50.0, -50.0]]
    )
    np.testing.assert_allclose(tau_from_T(T_from_tau(tau)), tau, rtol=1e-12, atol=1e-15)
    T = np.concatenate([np.exp(rng.normal(scale=3.0, size=200)), [1.0, 1 + 1e-12, 1 - 1e-12]])
    np.testing.assert_allclose(T_from_tau(tau_from_T(T)), T, rtol=1e-12)


def test_positive_for_any_tau() -> None:
    tau = np.concatenate([np.linspace(-1e6, 1e6, 10001), [-1e300, -1e160, 1e150, -np.inf]])
    T = T_from_tau(tau)
    assert np.all(T > 0.0)


def test_monotone() -> None:
    tau = np.linspace(-20.0, 20.0, 4001)
    assert np.all(np.diff(T_from_tau(tau)) > 0.0)


@pytest.mark.parametrize("tau0", [-30.0, -3.0, -0.7, -1e-3, -1e-7, 0.0, 1e-7, 1e-3, 0.7, 3.0, 30.0])
def test_derivative_by_central_differences(tau0: float) -> None:
    h = 1e-6 * max(1.0, abs(tau0))
    num = (T_from_tau_scalar(tau0 + h) - T_from_tau_scalar(tau0 - h)) / (2 * h)
    assert dT_dtau_scalar(tau0) == pytest.approx(num, rel=1e-5)


def test_derivative_is_continuous_at_zero() -> None:
    assert T_from_tau_scalar(0.0) == 1.0
    assert dT_dtau_scalar(0.0) == 1.0
    assert dT_dtau_scalar(1e-12) == pytest.approx(1.0, abs=1e-11)
    assert dT_dtau_scalar(-1e-12) == pytest.approx(1.0, abs=1e-11)


def test_grad_tau_chain_rule() -> None:
    """dJ/dtau for J = sum_i c_i T_i^2 against central differences in tau."""
    rng = np.random.default_rng(1)
    tau = rng.normal(scale=2.0, size=9)
    tau[0] = 0.0
    c = rng.normal(size=9)

    def J(t: np.ndarray) -> float:
        return float(np.sum(c * T_from_tau(t) ** 2))

    gT = 2.0 * c * T_from_tau(tau)
    g = grad_tau_from_grad_T(tau, gT)
    h = 1e-6
    num = np.array([(J(tau + h * e) - J(tau - h * e)) / (2 * h) for e in np.eye(9)])
    assert np.linalg.norm(g - num) <= 1e-5 * np.linalg.norm(num)
    out = np.empty(9)
    grad_tau_from_grad_T_into(tau, gT, out)
    np.testing.assert_array_equal(out, g)
    T_from_tau_into(tau, out)
    np.testing.assert_array_equal(out, T_from_tau(tau))


def test_scalar_inverse() -> None:
    for T in (0.01, 0.5, 1.0, 2.0, 100.0):
        assert T_from_tau_scalar(tau_from_T_scalar(T)) == pytest.approx(T, rel=1e-14)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.inf, np.nan])
def test_tau_from_T_rejects_non_positive(bad: float) -> None:
    with pytest.raises(ValueError, match="> 0"):
        tau_from_T(np.array([1.0, bad]))


def test_callable_from_compiled_code() -> None:
    @njit
    def pipeline(tau: np.ndarray, gT: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        T = T_from_tau(tau)
        return T, tau_from_T(T), grad_tau_from_grad_T(tau, gT)

    tau = np.array([-1.5, 0.0, 2.0])
    T, back, g = pipeline(tau, np.ones(3))
    np.testing.assert_allclose(back, tau, atol=1e-15)
    np.testing.assert_array_equal(g, [dT_dtau_scalar(t) for t in tau])
