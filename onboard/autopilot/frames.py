"""ENU <-> NED: the one place in ``onboard/`` where NED exists.

Inside the project everything is ENU (x east, y north, z up; yaw counter-clockwise from east).
PX4 speaks NED (x north, y east, z down; yaw clockwise from north) in its local frame, whose
origin is PX4's EKF origin. ``origin_enu_m`` is where that origin lies in the service's ENU frame
(zero when the service works in the autopilot's local frame).

The axis swap is its own inverse, so ``enu_to_ned`` and ``ned_to_enu`` are one mapping under two
names; the yaw map ``pi/2 - yaw`` is its own inverse too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


def enu_to_ned(v: Sequence[float]) -> Vec3:
    """A vector (position, velocity, acceleration) from ENU to NED: north = y, east = x,
    down = -z."""
    return (float(v[1]), float(v[0]), -float(v[2]))


def ned_to_enu(v: Sequence[float]) -> Vec3:
    """A vector from NED to ENU: x = east, y = north, z = -down (the inverse of ``enu_to_ned``,
    which is the same swap)."""
    return enu_to_ned(v)


def wrap_pi(angle_rad: float) -> float:
    """``angle_rad`` wrapped into (-pi, pi]; NaN stays NaN."""
    a = math.remainder(angle_rad, math.tau)  # [-pi, pi]
    return math.pi if a == -math.pi else a


def yaw_enu_to_ned(yaw_enu_rad: float) -> float:
    """Heading from ENU (counter-clockwise from east) to NED (clockwise from north), wrapped."""
    return wrap_pi(math.pi / 2.0 - yaw_enu_rad)


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """Heading from NED to ENU, wrapped (the same map as ``yaw_enu_to_ned``)."""
    return wrap_pi(math.pi / 2.0 - yaw_ned_rad)


def attitude_ned_to_enu(roll_rad: float, pitch_rad: float, yaw_ned_rad: float) -> Vec3:
    """ZYX Euler angles of the body (FRD) in NED to those of the body (FLU) in ENU:
    roll is kept, pitch changes sign (nose up is positive in FRD, negative about FLU's left
    axis), yaw becomes ``pi/2 - yaw``."""
    return (float(roll_rad), -float(pitch_rad), yaw_ned_to_enu(yaw_ned_rad))


@dataclass(frozen=True)
class NedSetpoint:
    """A setpoint as SET_POSITION_TARGET_LOCAL_NED carries it (PX4's local NED frame).

    ``yaw_ned_rad`` None: yaw not controlled (the type mask says so).
    """

    position_ned_m: Vec3
    velocity_ned_m_s: Vec3
    accel_ned_m_s2: Vec3
    yaw_ned_rad: float | None


def setpoint_enu_to_ned(
    position_enu_m: Sequence[float],
    velocity_enu_m_s: Sequence[float],
    accel_enu_m_s2: Sequence[float],
    yaw_enu_rad: float | None,
    origin_enu_m: Sequence[float] = (0.0, 0.0, 0.0),
) -> NedSetpoint:
    """The one conversion of an outgoing setpoint: translate the position into PX4's local
    frame (``origin_enu_m`` is its origin in ENU), then swap every vector and the yaw."""
    local = (
        float(position_enu_m[0]) - float(origin_enu_m[0]),
        float(position_enu_m[1]) - float(origin_enu_m[1]),
        float(position_enu_m[2]) - float(origin_enu_m[2]),
    )
    return NedSetpoint(
        enu_to_ned(local),
        enu_to_ned(velocity_enu_m_s),
        enu_to_ned(accel_enu_m_s2),
        None if yaw_enu_rad is None else yaw_enu_to_ned(yaw_enu_rad),
    )


def position_ned_to_enu(
    position_ned_m: Sequence[float], origin_enu_m: Sequence[float] = (0.0, 0.0, 0.0)
) -> Vec3:
    """A position in PX4's local NED frame to the service's ENU frame."""
    e = ned_to_enu(position_ned_m)
    return (
        e[0] + float(origin_enu_m[0]),
        e[1] + float(origin_enu_m[1]),
        e[2] + float(origin_enu_m[2]),
    )
