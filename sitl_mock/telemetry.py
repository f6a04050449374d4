"""What the autopilot reports about each vehicle, computed for the whole fleet in one kernel.

Pure numerics (no sockets, clocks or files): from the fleet's state and attitude arrays
(``sitl_mock.dynamics``) one numba call per tick fills a row per vehicle with the quantities the
MAVLink streams need, already in MAVLink's frames (NED world, FRD body) and units, so that the
per-message Python work is only reading floats. The same conversions as ``sitl_mock.frames``
(ENU <-> NED, FLU <-> FRD, flat-earth geodetic positions); a test checks the two agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sitl_mock import dynamics as dyn
from sitl_mock.frames import EARTH_RADIUS_M

# ---- telemetry columns (N, NT) --------------------------------------------------------------
T_PN = 0  # 0..2 estimated position NED relative to the local origin [m]
T_VN = 3  # 3..5 velocity NED [m/s]
T_ROLL = 6  # roll [rad]
T_PITCH = 7  # pitch [rad]
T_YAW = 8  # yaw (heading from north, clockwise) [rad], in (-pi, pi]
T_Q = 9  # 9..12 attitude quaternion FRD body -> NED (w, x, y, z), w >= 0
T_W = 13  # 13..15 body rates FRD [rad/s]
T_F = 16  # 16..18 specific force FRD (accelerometer) [m/s^2]
T_VB = 19  # 19..21 velocity in the FRD body frame [m/s]
T_MAG = 22  # 22..24 magnetic field in the FRD body frame [gauss]
T_LAT = 25  # latitude [deg]
T_LON = 26  # longitude [deg]
T_ALT = 27  # altitude AMSL [m]
T_HAG = 28  # height of the estimate above the ground under the vehicle [m]
T_THRUST = 29  # normalised collective thrust 0..1
T_COS_TILT = 30  # cosine of the tilt (body z axis vs vertical)
NT = 31

# Earth's field at the default home (Zurich), NED [gauss]
MAG_NED_GAUSS = (0.21, 0.015, 0.42)


@njit(cache=True, nogil=True)
def telemetry_fleet(
    state: np.ndarray,
    att: np.ndarray,
    origin_enu: np.ndarray,
    ground_z: np.ndarray,
    geo_ref: np.ndarray,
    out: np.ndarray,
) -> None:
    """Fill ``out`` (N, NT) from ``state`` (N, NS) and ``att`` (N, NA).

    ``origin_enu`` (N, 3): each vehicle's local origin; ``ground_z`` (N,); ``geo_ref`` (3,):
    latitude, longitude [deg] and altitude [m] of the ENU world origin.
    """
    n = state.shape[0]
    lat0 = geo_ref[0]
    lon0 = geo_ref[1]
    alt0 = geo_ref[2]
    cos_lat0 = math.cos(math.radians(lat0))
    rd = np.empty((3, 3))  # FRD body -> NED world
    for i in range(n):
        s = state[i]
        a = att[i]
        ex = s[dyn.S_P] + s[dyn.S_E]
        ey = s[dyn.S_P + 1] + s[dyn.S_E + 1]
        ez = s[dyn.S_P + 2] + s[dyn.S_E + 2]
        o = out[i]
        # ENU -> NED: (x, y, z) -> (y, x, -z)
        o[T_PN] = ey - origin_enu[i, 1]
        o[T_PN + 1] = ex - origin_enu[i, 0]
        o[T_PN + 2] = -(ez - origin_enu[i, 2])
        o[T_VN] = s[dyn.S_V + 1]
        o[T_VN + 1] = s[dyn.S_V]
        o[T_VN + 2] = -s[dyn.S_V + 2]
        # R_ned_frd = P R_enu_flu F, P swaps rows 0/1 and negates row 2, F negates columns 1, 2
        for c in range(3):
            sign = 1.0 if c == 0 else -1.0
            rd[0, c] = sign * a[dyn.A_R + 3 + c]
            rd[1, c] = sign * a[dyn.A_R + c]
            rd[2, c] = -sign * a[dyn.A_R + 6 + c]
        # Euler ZYX
        r20 = min(1.0, max(-1.0, rd[2, 0]))
        o[T_PITCH] = -math.asin(r20)
        o[T_ROLL] = math.atan2(rd[2, 1], rd[2, 2])
        o[T_YAW] = math.atan2(rd[1, 0], rd[0, 0])
        # quaternion (Shepperd), w >= 0
        tr = rd[0, 0] + rd[1, 1] + rd[2, 2]
        if tr > 0.0:
            q = math.sqrt(tr + 1.0) * 2.0
            qw = 0.25 * q
            qx = (rd[2, 1] - rd[1, 2]) / q
            qy = (rd[0, 2] - rd[2, 0]) / q
            qz = (rd[1, 0] - rd[0, 1]) / q
        elif rd[0, 0] > rd[1, 1] and rd[0, 0] > rd[2, 2]:
            q = math.sqrt(1.0 + rd[0, 0] - rd[1, 1] - rd[2, 2]) * 2.0
            qw = (rd[2, 1] - rd[1, 2]) / q
            qx = 0.25 * q
            qy = (rd[0, 1] + rd[1, 0]) / q
            qz = (rd[0, 2] + rd[2, 0]) / q
        elif rd[1, 1] > rd[2, 2]:
            q = math.sqrt(1.0 + rd[1, 1] - rd[0, 0] - rd[2, 2]) * 2.0
            qw = (rd[0, 2] - rd[2, 0]) / q
            qx = (rd[0, 1] + rd[1, 0]) / q
            qy = 0.25 * q
            qz = (rd[1, 2] + rd[2, 1]) / q
        else:
            q = math.sqrt(1.0 + rd[2, 2] - rd[0, 0] - rd[1, 1]) * 2.0
            qw = (rd[1, 0] - rd[0, 1]) / q
            qx = (rd[0, 2] + rd[2, 0]) / q
            qy = (rd[1, 2] + rd[2, 1]) / q
            qz = 0.25 * q
        if qw < 0.0:
            qw, qx, qy, qz = -qw, -qx, -qy, -qz
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        o[T_Q] = qw / qn
        o[T_Q + 1] = qx / qn
        o[T_Q + 2] = qy / qn
        o[T_Q + 3] = qz / qn
        # body vectors FLU -> FRD: (x, y, z) -> (x, -y, -z)
        o[T_W] = a[dyn.A_OMEGA]
        o[T_W + 1] = -a[dyn.A_OMEGA + 1]
        o[T_W + 2] = -a[dyn.A_OMEGA + 2]
        o[T_F] = a[dyn.A_SPECIFIC]
        o[T_F + 1] = -a[dyn.A_SPECIFIC + 1]
        o[T_F + 2] = -a[dyn.A_SPECIFIC + 2]
        # world vectors into the body: R^T v
        for c in range(3):
            o[T_VB + c] = rd[0, c] * o[T_VN] + rd[1, c] * o[T_VN + 1] + rd[2, c] * o[T_VN + 2]
            o[T_MAG + c] = (
                rd[0, c] * MAG_NED_GAUSS[0]
                + rd[1, c] * MAG_NED_GAUSS[1]
                + rd[2, c] * MAG_NED_GAUSS[2]
            )
        # geodetic (flat earth around the world origin)
        lat = lat0 + math.degrees(ey / EARTH_RADIUS_M)
        o[T_LAT] = lat
        o[T_LON] = lon0 + math.degrees(ex / (EARTH_RADIUS_M * cos_lat0))
        o[T_ALT] = alt0 + ez
        o[T_HAG] = ez - ground_z[i]
        o[T_THRUST] = a[dyn.A_THRUST]
        o[T_COS_TILT] = rd[2, 2]


def pressure_hpa(altitude_amsl_m: float) -> float:
    """International standard atmosphere pressure at an altitude [hPa]."""
    return 1013.25 * (1.0 - 2.25577e-5 * altitude_amsl_m) ** 5.25588
