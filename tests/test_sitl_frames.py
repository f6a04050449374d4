"""The one ENU <-> NED conversion of the SITL mock, and what is built on it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl_mock.dynamics import rotation_from_thrust
from sitl_mock.frames import (
    enu_from_geodetic,
    enu_ned,
    euler_zyx,
    geodetic_from_enu,
    matrix_from_quaternion,
    quaternion_from_matrix,
    rotation_ned_frd,
    yaw_enu_ned,
)


def test_enu_ned_values_and_involution() -> None:
    east, north, up = 1.0, 2.0, 3.0
    ned = enu_ned(np.array([east, north, up]))
    np.testing.assert_array_equal(ned, [north, east, -up])
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 4, 3))
    np.testing.assert_array_equal(enu_ned(enu_ned(v)), v)
    # NaN (an uncontrolled axis) stays in its own axis
    out = enu_ned(np.array([np.nan, 1.0, 2.0]))
    assert out[0] == 1.0 and math.isnan(out[1]) and out[2] == -2.0
    with pytest.raises(ValueError):
        enu_ned(np.zeros(2))


def test_yaw_conversion() -> None:
    # facing north: ENU pi/2, NED 0; facing east: ENU 0, NED pi/2
    assert yaw_enu_ned(math.pi / 2) == pytest.approx(0.0)
    assert yaw_enu_ned(0.0) == pytest.approx(math.pi / 2)
    for y in np.linspace(-3.1, 3.1, 13):
        assert yaw_enu_ned(yaw_enu_ned(y)) == pytest.approx(y, abs=1e-12)


def test_attitude_conversion() -> None:
    # level, facing north: NED/FRD attitude is the identity
    r_enu = rotation_from_thrust(0.0, 0.0, 9.8, math.pi / 2)
    np.testing.assert_allclose(rotation_ned_frd(r_enu), np.eye(3), atol=1e-12)
    # level, facing east: NED yaw +90 degrees
    roll, pitch, yaw = euler_zyx(rotation_ned_frd(rotation_from_thrust(0, 0, 9.8, 0.0)))
    assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert yaw == pytest.approx(math.pi / 2)
    # facing north, accelerating north: thrust tilted north -> nose down (negative pitch)
    roll, pitch, yaw = euler_zyx(rotation_ned_frd(rotation_from_thrust(0.0, 2.0, 9.8, math.pi / 2)))
    assert pitch == pytest.approx(-math.atan2(2.0, 9.8)) and abs(roll) < 1e-12 and abs(yaw) < 1e-9
    # facing north, accelerating east (to the right): roll right (positive)
    roll, pitch, _ = euler_zyx(rotation_ned_frd(rotation_from_thrust(2.0, 0.0, 9.8, math.pi / 2)))
    assert roll == pytest.approx(math.atan2(2.0, 9.8)) and abs(pitch) < 1e-12
    # the conversion is its own inverse and gives proper rotations
    r = rotation_from_thrust(1.0, -2.0, 8.0, 0.7)
    np.testing.assert_allclose(rotation_ned_frd(rotation_ned_frd(r)), r, atol=1e-12)
    rn = rotation_ned_frd(r)
    np.testing.assert_allclose(rn.T @ rn, np.eye(3), atol=1e-12)
    assert np.linalg.det(rn) == pytest.approx(1.0)


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        f = rng.normal(size=3) + [0, 0, 9.0]
        r = rotation_ned_frd(rotation_from_thrust(f[0], f[1], f[2], rng.uniform(-3, 3)))
        q = quaternion_from_matrix(r)
        assert q[0] >= 0 and sum(c * c for c in q) == pytest.approx(1.0)
        np.testing.assert_allclose(matrix_from_quaternion(q), r, atol=1e-12)


def test_geodetic_round_trip() -> None:
    ref = (47.397742, 8.545594, 488.0)
    p = np.array([120.0, -35.0, 12.5])
    lat, lon, alt = geodetic_from_enu(p, *ref)
    assert lat < ref[0] and lon > ref[1] and alt == pytest.approx(500.5)
    np.testing.assert_allclose(enu_from_geodetic(lat, lon, alt, *ref), p, atol=1e-9)
