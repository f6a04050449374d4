"""The autopilot link: PX4 over MAVLink, the only place in ``onboard/`` that knows NED.

``open_link(LinkConfig(...))`` gives the implementation the config names (pymavlink, the
default, or MAVSDK 4.x); both behave the same behind ``AutopilotLink``.
"""

from onboard.autopilot.config import LinkConfig, parse_url
from onboard.autopilot.frames import (
    NedSetpoint,
    enu_to_ned,
    ned_to_enu,
    setpoint_enu_to_ned,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)
from onboard.autopilot.guard import GuardLimits, GuardVerdict, guard_setpoint, setpoint_problem
from onboard.autopilot.link import AutopilotLink, open_link
from onboard.autopilot.model import (
    CommandError,
    CommandResult,
    Connected,
    FlightMode,
    LandedState,
    LinkCounters,
    LinkError,
    LinkEvent,
    LinkLost,
    LinkRegained,
    ModeChanged,
    OffboardLost,
    PeriodStats,
    Setpoint,
    SetpointRejected,
    SetpointSource,
    SourceFailed,
    VehicleState,
)
from onboard.autopilot.source import TrajectorySource

__all__ = [
    "AutopilotLink",
    "CommandError",
    "CommandResult",
    "Connected",
    "FlightMode",
    "GuardLimits",
    "GuardVerdict",
    "LandedState",
    "LinkConfig",
    "LinkCounters",
    "LinkError",
    "LinkEvent",
    "LinkLost",
    "LinkRegained",
    "ModeChanged",
    "NedSetpoint",
    "OffboardLost",
    "PeriodStats",
    "Setpoint",
    "SetpointRejected",
    "SetpointSource",
    "SourceFailed",
    "TrajectorySource",
    "VehicleState",
    "enu_to_ned",
    "guard_setpoint",
    "ned_to_enu",
    "open_link",
    "parse_url",
    "setpoint_enu_to_ned",
    "setpoint_problem",
    "yaw_enu_to_ned",
    "yaw_ned_to_enu",
]
