"""The last check every setpoint passes before it goes on the wire.

A setpoint is sent only if every number is finite, the position lies inside the geofence box and
the velocity and acceleration are within the limits. Anything else is replaced by holding the
last good position (zero velocity and acceleration, the last good yaw) and counted; the bad one
is never sent. Without a last good setpoint nothing is sent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.autopilot.model import Setpoint, Vec3


@dataclass(frozen=True)
class GuardLimits:
    """The box (ENU, service frame) and the magnitude limits a setpoint must respect."""

    geofence_min_enu_m: Vec3
    geofence_max_enu_m: Vec3
    max_speed_m_s: float
    max_accel_m_s2: float


@dataclass(frozen=True)
class GuardVerdict:
    """What to send (None: nothing) and why the input was refused (None: it was not)."""

    setpoint: Setpoint | None
    reason: str | None


def setpoint_problem(sp: Setpoint, limits: GuardLimits) -> str | None:
    """Why ``sp`` must not be sent (a short reason key), or None if it may."""
    values = (*sp.position_enu_m, *sp.velocity_enu_m_s, *sp.accel_enu_m_s2)
    if not all(math.isfinite(v) for v in values):
        return "non-finite"
    if sp.yaw_enu_rad is not None and not math.isfinite(sp.yaw_enu_rad):
        return "non-finite"
    lo, hi = limits.geofence_min_enu_m, limits.geofence_max_enu_m
    p = sp.position_enu_m
    if not all(lo[k] <= p[k] <= hi[k] for k in range(3)):
        return "outside-geofence"
    if math.hypot(*sp.velocity_enu_m_s) > limits.max_speed_m_s:
        return "speed-limit"
    if math.hypot(*sp.accel_enu_m_s2) > limits.max_accel_m_s2:
        return "accel-limit"
    return None


def guard_setpoint(
    sp: Setpoint | None, last_good: Setpoint | None, limits: GuardLimits
) -> GuardVerdict:
    """The final check: ``sp`` itself if it passes; otherwise a hold at ``last_good``'s position
    (or nothing without one), with the reason. ``sp`` None (the source had nothing) holds too,
    without a reason."""
    if sp is not None:
        problem = setpoint_problem(sp, limits)
        if problem is None:
            return GuardVerdict(sp, None)
    else:
        problem = None
    if last_good is None:
        return GuardVerdict(None, problem)
    return GuardVerdict(Setpoint.hold(last_good.position_enu_m, last_good.yaw_enu_rad), problem)
