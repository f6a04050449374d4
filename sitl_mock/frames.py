"""Frame conventions of the mock: ENU inside, NED (and FRD bodies) only on the MAVLink side.

The world and the physics use ENU (x east, y north, z up) with FLU bodies (x forward, y left,
z up); MAVLink fields are NED (x north, y east, z down) with FRD bodies. ``enu_ned`` is the one
conversion of vectors: it swaps the first two components and negates the third, which maps ENU
to NED and, being its own inverse, NED back to ENU. Every other conversion here is built on it.

Geodetic positions use a local flat-earth (equirectangular) approximation around a reference
point, accurate to millimetres over the few hundred metres a swarm flies.
"""

from __future__ import annotations

import math

import numpy as np

EARTH_RADIUS_M = 6_378_137.0  # WGS-84 equatorial radius

# FLU <-> FRD body axes: x kept, y and z negated (its own inverse, like enu_ned)
_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def enu_ned(v: np.ndarray) -> np.ndarray:
    """ENU -> NED, and NED -> ENU (the map is an involution): ``(a, b, c) -> (b, a, -c)``.

    ``v``: (..., 3) array; returns a new float64 array of the same shape.
    """
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1] != 3:
        raise ValueError(f"expected (..., 3), got {a.shape}")
    out = np.empty_like(a)
    out[..., 0] = a[..., 1]
    out[..., 1] = a[..., 0]
    out[..., 2] = -a[..., 2]
    return out


# the enu_ned map as a matrix (columns: images of the basis vectors)
_ENU_NED = enu_ned(np.eye(3)).T


def yaw_enu_ned(yaw_rad: float) -> float:
    """Yaw ENU (from east, counter-clockwise) <-> NED (from north, clockwise), wrapped to
    [-pi, pi). Also an involution: ``yaw_ned = pi/2 - yaw_enu`` and back."""
    return wrap_pi(math.pi / 2.0 - yaw_rad)


def wrap_pi(angle_rad: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def rotation_ned_frd(r_enu_flu: np.ndarray) -> np.ndarray:
    """Attitude FLU-body -> ENU-world as a matrix, re-expressed as FRD-body -> NED-world.

    ``R_ned_frd = P R_enu_flu F`` with ``P`` the ``enu_ned`` map and ``F`` the FLU/FRD flip.
    The same formula converts back (both maps are involutions).
    """
    return _ENU_NED @ np.asarray(r_enu_flu, dtype=np.float64) @ _FLU_FRD


def euler_zyx(r: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of a rotation matrix, aerospace ZYX order."""
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return roll, pitch, yaw


def quaternion_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix, w >= 0 (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        w, x, y, z = (
            0.25 * s,
            (m[2, 1] - m[1, 2]) / s,
            (m[0, 2] - m[2, 0]) / s,
            (m[1, 0] - m[0, 1]) / s,
        )
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        w, x, y, z = (
            (m[2, 1] - m[1, 2]) / s,
            0.25 * s,
            (m[0, 1] + m[1, 0]) / s,
            (m[0, 2] + m[2, 0]) / s,
        )
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        w, x, y, z = (
            (m[0, 2] - m[2, 0]) / s,
            (m[0, 1] + m[1, 0]) / s,
            0.25 * s,
            (m[1, 2] + m[2, 1]) / s,
        )
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        w, x, y, z = (
            (m[1, 0] - m[0, 1]) / s,
            (m[0, 2] + m[2, 0]) / s,
            (m[1, 2] + m[2, 1]) / s,
            0.25 * s,
        )
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return float(w / n), float(x / n), float(y / n), float(z / n)


def matrix_from_quaternion(q: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(c) for c in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def geodetic_from_enu(
    enu_m: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m AMSL) of an ENU point relative to the reference (flat earth)."""
    e, n, u = (float(c) for c in np.asarray(enu_m, dtype=np.float64).reshape(3))
    lat = lat0_deg + math.degrees(n / EARTH_RADIUS_M)
    lon = lon0_deg + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))))
    return lat, lon, alt0_m + u


def enu_from_geodetic(
    lat_deg: float, lon_deg: float, alt_m: float, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> np.ndarray:
    """Inverse of ``geodetic_from_enu``."""
    n = math.radians(lat_deg - lat0_deg) * EARTH_RADIUS_M
    e = math.radians(lon_deg - lon0_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))
    return np.array([e, n, alt_m - alt0_m])
