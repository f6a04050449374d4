"""The mock's quadrotor model and PX4-like position controller, without autopilot or network."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl_mock import dynamics as dyn
from sitl_mock.dynamics import DynamicsParams, simulate_setpoint, step_metrics

QUIET = DynamicsParams(wind_sigma_m_s2=0.0, pos_noise_sigma_m=0.0)
NO_DRAG = DynamicsParams(wind_sigma_m_s2=0.0, pos_noise_sigma_m=0.0, drag_per_s=0.0)


Vec = tuple[float, float, float]
NAN3: Vec = (math.nan, math.nan, math.nan)


def command(
    pos: Vec = NAN3,
    vel: Vec = NAN3,
    acc: Vec = NAN3,
    yaw: float = math.nan,
    yaw_rate: float = math.nan,
    motor: float = dyn.MOTOR_RUN,
) -> np.ndarray:
    c = np.full(dyn.NC, np.nan)
    c[dyn.C_POS : dyn.C_POS + 3] = pos
    c[dyn.C_VEL : dyn.C_VEL + 3] = vel
    c[dyn.C_ACC : dyn.C_ACC + 3] = acc
    c[dyn.C_YAW] = yaw
    c[dyn.C_YAWRATE] = yaw_rate
    c[dyn.C_MOTOR] = motor
    return c


def test_hover_holds_position() -> None:
    t, p = simulate_setpoint(QUIET, np.array([1.0, 2.0, 3.0]), command(pos=(1.0, 2.0, 3.0)), 5.0)
    np.testing.assert_allclose(p[-1], [1.0, 2.0, 3.0], atol=1e-6)


def test_position_step_like_a_small_px4_quadrotor() -> None:
    t, p = simulate_setpoint(QUIET, np.zeros(3) + [0, 0, 2], command(pos=(0.0, 2.0, 2.0)), 10.0)
    m = step_metrics(t, p[:, 1], 0.0, 2.0)
    assert 0.8 < m["rise_time_s"] < 2.5
    assert m["overshoot_fraction"] < 0.15
    assert m["settling_time_s"] < 6.0 and m["final_error_m"] < 0.01
    assert np.max(np.abs(p[:, 2] - 2.0)) < 0.05  # altitude held during the horizontal move


def test_seeded_runs_repeat_exactly_and_seeds_differ() -> None:
    c = command(pos=(3.0, 0.0, 2.0))
    a = simulate_setpoint(DynamicsParams(), np.array([0, 0, 2.0]), c, 3.0, seed=7)[1]
    b = simulate_setpoint(DynamicsParams(), np.array([0, 0, 2.0]), c, 3.0, seed=7)[1]
    d = simulate_setpoint(DynamicsParams(), np.array([0, 0, 2.0]), c, 3.0, seed=8)[1]
    np.testing.assert_array_equal(a, b)
    assert np.max(np.abs(a - d)) > 1e-4


def _fly(
    params: DynamicsParams,
    start: np.ndarray,
    c: np.ndarray,
    seconds: float,
    dt: float = 0.005,
    ground: float = -1e9,
) -> tuple[np.ndarray, list[np.ndarray]]:
    st = dyn.initial_state(start.reshape(1, 3))
    st[0, dyn.S_GROUND] = 0.0 if start[2] > ground else 1.0
    st[0, dyn.S_F + 2] = params.g_m_s2 if start[2] > ground else 0.0
    prm = params.as_array()
    nsub = dyn.substeps(dt, params)
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(int(round(seconds / dt))):
        dyn.step_fleet(
            st,
            c.reshape(1, -1),
            prm,
            np.array([ground]),
            dt,
            rng.standard_normal((1, nsub, dyn.NOISE_PER_SUBSTEP)),
        )
        rows.append(st[0].copy())
    return st, rows


def test_tilt_speed_and_acceleration_limits() -> None:
    p = QUIET
    _, rows = _fly(p, np.array([0, 0, 5.0]), command(pos=(100.0, 0.0, 5.0)), 8.0)
    tilt = [
        math.degrees(math.atan2(math.hypot(r[dyn.S_FCMD], r[dyn.S_FCMD + 1]), r[dyn.S_FCMD + 2]))
        for r in rows
    ]
    assert max(tilt) <= p.tilt_max_deg + 1e-9
    acc_xy = [math.hypot(r[dyn.S_FCMD], r[dyn.S_FCMD + 1]) for r in rows]
    assert max(acc_xy) <= p.acc_xy_max_m_s2 + 1e-9
    speed = [math.hypot(r[dyn.S_V], r[dyn.S_V + 1]) for r in rows]
    assert max(speed) <= p.v_xy_max_m_s + 0.5
    climb = DynamicsParams(wind_sigma_m_s2=0.0, pos_noise_sigma_m=0.0, v_up_max_m_s=2.0)
    _, rows = _fly(climb, np.array([0, 0, 1.0]), command(pos=(0.0, 0.0, 30.0)), 8.0)
    assert max(r[dyn.S_V + 2] for r in rows) <= 2.0 + 0.1


def test_velocity_and_mixed_axes() -> None:
    # velocity east + position north + position up
    st, _ = _fly(
        QUIET,
        np.array([0, 0, 2.0]),
        command(pos=(math.nan, 1.0, 2.5), vel=(2.0, math.nan, math.nan)),
        6.0,
    )
    assert st[0, dyn.S_V] == pytest.approx(2.0, abs=0.02)
    assert st[0, dyn.S_P + 1] == pytest.approx(1.0, abs=0.02)
    assert st[0, dyn.S_P + 2] == pytest.approx(2.5, abs=0.02)
    # acceleration-only horizontal axes: constant acceleration, vertical held by position
    st, _ = _fly(
        NO_DRAG,
        np.array([0, 0, 2.0]),
        command(pos=(math.nan, math.nan, 2.0), acc=(0.5, 0.0, math.nan)),
        2.0,
    )
    assert st[0, dyn.S_V] == pytest.approx(0.5 * 2.0, rel=0.1)  # lagged by the attitude loop


def test_yaw_setpoint_and_rate() -> None:
    st, _ = _fly(QUIET, np.array([0, 0, 2.0]), command(pos=(0, 0, 2.0), yaw=1.0), 3.0)
    assert st[0, dyn.S_YAW] == pytest.approx(1.0, abs=1e-3)
    st, _ = _fly(QUIET, np.array([0, 0, 2.0]), command(pos=(0, 0, 2.0), yaw_rate=0.5), 2.0)
    assert st[0, dyn.S_YAWRATE] == pytest.approx(0.5, abs=1e-3)


def test_ground_contact_and_impact() -> None:
    # motors off at 3 m: free fall onto the ground at z = 0, no penetration, impact recorded
    st, rows = _fly(NO_DRAG, np.array([0, 0, 3.0]), command(motor=dyn.MOTOR_OFF), 2.0, ground=0.0)
    assert min(r[dyn.S_P + 2] for r in rows) >= 0.0
    assert st[0, dyn.S_GROUND] == 1.0 and st[0, dyn.S_V + 2] == 0.0
    assert st[0, dyn.S_IMPACT] == pytest.approx(math.sqrt(2 * 9.80665 * 3.0), rel=0.05)
    # idle motors on the ground: stays put; a setpoint above lifts it off
    st, _ = _fly(QUIET, np.array([0, 0, 0.0]), command(motor=dyn.MOTOR_IDLE), 1.0, ground=0.0)
    assert st[0, dyn.S_P + 2] == 0.0
    st, _ = _fly(QUIET, np.array([0, 0, 0.0]), command(pos=(0, 0, 1.0)), 5.0, ground=0.0)
    assert st[0, dyn.S_P + 2] == pytest.approx(1.0, abs=0.02) and st[0, dyn.S_GROUND] == 0.0


def test_attitude_outputs() -> None:
    st = dyn.initial_state(np.zeros((2, 3)), np.array([0.0, math.pi / 2]))
    st[:, dyn.S_F + 2] = 9.80665
    prm = DynamicsParams().as_array()
    out = np.zeros((2, dyn.NA))
    r_prev = np.zeros((2, 9))
    dyn.attitude_fleet(st, prm, r_prev, 0.0, out)
    np.testing.assert_allclose(
        out[1, :9].reshape(3, 3), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )
    assert out[0, dyn.A_THRUST] == pytest.approx(0.5)
    np.testing.assert_allclose(out[0, dyn.A_SPECIFIC : dyn.A_SPECIFIC + 3], [0, 0, 9.80665])
    st[:, dyn.S_YAW] += 0.01  # a yaw step over 0.01 s: 1 rad/s about body z
    dyn.attitude_fleet(st, prm, r_prev, 0.01, out)
    assert out[0, dyn.A_OMEGA + 2] == pytest.approx(1.0, rel=1e-3)


def test_params_validated() -> None:
    with pytest.raises(ValueError):
        DynamicsParams(hover_thrust=1.5)
    with pytest.raises(ValueError):
        DynamicsParams(tilt_max_deg=95.0)
    with pytest.raises(ValueError):
        step_metrics(np.arange(3.0), np.zeros(3), 1.0, 1.0)
