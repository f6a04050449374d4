"""Time diffeomorphism between unconstrained variables tau and positive piece durations T [s].

The optimiser works on tau in R; durations are (paper Sec. IV-A: T must stay in R_>0^M)

    T(tau) = tau^2 / 2 + tau + 1            for tau > 0,
    T(tau) = 1 / (tau^2 / 2 - tau + 1)      for tau <= 0,

a C1 bijection R -> (0, inf) with T(0) = 1 and dT/dtau(0) = 1. Its inverse is

    tau(T) = sqrt(2 T - 1) - 1              for T > 1,
    tau(T) = 1 - sqrt(2 / T - 1)            for 0 < T <= 1,

evaluated below in cancellation-free forms. The gradient map is dJ/dtau = dJ/dT * dT/dtau with

    dT/dtau = tau + 1                       for tau > 0,
    dT/dtau = (1 - tau) / (tau^2 / 2 - tau + 1)^2   for tau <= 0.

All functions are numba-compiled and can be called from other compiled code or from Python.
The array versions take and return (M,) float64 arrays; the ``*_into`` versions write into a
caller-provided (M,) output (no allocation, for the optimiser's hot loop); the ``*_scalar``
versions work on one float.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_T_MIN = 2.2250738585072014e-308
"""Smallest positive normal float64: T(tau) never rounds to 0, even for absurd negative tau."""


@njit(cache=True, nogil=True)
def T_from_tau_scalar(tau: float) -> float:
    """Duration T > 0 [s] for one unconstrained variable tau."""
    if tau > 0.0:
        return (0.5 * tau + 1.0) * tau + 1.0
    den = (0.5 * tau - 1.0) * tau + 1.0
    return max(1.0 / den, _T_MIN)


@njit(cache=True, nogil=True)
def dT_dtau_scalar(tau: float) -> float:
    """Derivative dT/dtau at tau (continuous, equal to 1 at tau = 0)."""
    if tau > 0.0:
        return tau + 1.0
    den = (0.5 * tau - 1.0) * tau + 1.0
    return (1.0 - tau) / (den * den)


@njit(cache=True, nogil=True)
def tau_from_T_scalar(T: float) -> float:
    """Inverse map for one duration; T must be > 0 and finite (not checked here)."""
    if T > 1.0:
        # sqrt(2T - 1) - 1 without cancellation near T = 1
        return 2.0 * (T - 1.0) / (np.sqrt(2.0 * T - 1.0) + 1.0)
    # 1 - sqrt(2/T - 1) without cancellation near T = 1
    return 2.0 * (T - 1.0) / T / (1.0 + np.sqrt(2.0 / T - 1.0))


@njit(cache=True, nogil=True)
def T_from_tau_into(tau: np.ndarray, out: np.ndarray) -> None:
    """out[i] = T(tau[i]); tau, out: (M,)."""
    for i in range(tau.shape[0]):
        out[i] = T_from_tau_scalar(tau[i])


@njit(cache=True, nogil=True)
def grad_tau_from_grad_T_into(tau: np.ndarray, gT: np.ndarray, out: np.ndarray) -> None:
    """out[i] = gT[i] * dT/dtau(tau[i]); tau, gT, out: (M,). ``out`` may alias ``gT``."""
    for i in range(tau.shape[0]):
        out[i] = gT[i] * dT_dtau_scalar(tau[i])


@njit(cache=True, nogil=True)
def T_from_tau(tau: np.ndarray) -> np.ndarray:
    """Durations T (M,) [s], all > 0, from unconstrained tau (M,)."""
    out = np.empty(tau.shape[0])
    T_from_tau_into(tau, out)
    return out


@njit(cache=True, nogil=True)
def tau_from_T(T: np.ndarray) -> np.ndarray:
    """Unconstrained tau (M,) from durations T (M,) [s]; ValueError unless every 0 < T < inf."""
    out = np.empty(T.shape[0])
    for i in range(T.shape[0]):
        if not (T[i] > 0.0 and T[i] < np.inf):
            raise ValueError("tau_from_T: every duration T must be finite and > 0")
        out[i] = tau_from_T_scalar(T[i])
    return out


@njit(cache=True, nogil=True)
def grad_tau_from_grad_T(tau: np.ndarray, gT: np.ndarray) -> np.ndarray:
    """Chain rule dJ/dtau (M,) = dJ/dT (M,) * dT/dtau evaluated at tau (M,)."""
    out = np.empty(tau.shape[0])
    grad_tau_from_grad_T_into(tau, gT, out)
    return out
