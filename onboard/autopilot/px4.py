"""PX4's MAVLink dialect as a companion computer meets it (values from PX4 v1.16's source).

- custom_mode = main_mode << 16 | sub_mode << 24 (px4_custom_mode.h); DO_SET_MODE (176) takes
  param1 = 1 (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), param2 = main mode, param3 = sub mode.
- PX4 counts a heartbeat as its onboard controller's only from the vehicle's own system id
  with type MAV_TYPE_ONBOARD_CONTROLLER (mavlink_receiver.cpp, handle_message_heartbeat).
- SET_POSITION_TARGET_LOCAL_NED: PX4 ignores ``time_boot_ms`` and stamps the setpoint with its
  own clock on receipt (offboard_control_mode / trajectory_setpoint .timestamp =
  hrt_absolute_time()), so the link sends 0 there.
- SET_MESSAGE_INTERVAL for HEARTBEAT is refused (FAILED): PX4's heartbeat stays at 1 Hz.
- A refused arm is TEMPORARILY_REJECTED (commander: TRANSITION_DENIED), not DENIED.
"""

from __future__ import annotations

import math

from onboard.autopilot.model import FlightMode

# MAV_CMD
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_COMPONENT_ARM_DISARM = 400
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512

COMMAND_NAMES = {
    CMD_NAV_LAND: "MAV_CMD_NAV_LAND",
    CMD_NAV_TAKEOFF: "MAV_CMD_NAV_TAKEOFF",
    CMD_DO_SET_MODE: "MAV_CMD_DO_SET_MODE",
    CMD_COMPONENT_ARM_DISARM: "MAV_CMD_COMPONENT_ARM_DISARM",
    CMD_SET_MESSAGE_INTERVAL: "MAV_CMD_SET_MESSAGE_INTERVAL",
    CMD_REQUEST_MESSAGE: "MAV_CMD_REQUEST_MESSAGE",
}

ARM_FORCE_MAGIC = 21196.0

MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5
MAV_STATE_EMERGENCY = 6
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_LOCAL_NED = 1

# SET_POSITION_TARGET_LOCAL_NED type_mask: a set bit means "ignore"
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048
TYPE_MASK_PVA_YAW = IGNORE_YAW_RATE  # position, velocity, acceleration and yaw
TYPE_MASK_PVA = IGNORE_YAW_RATE | IGNORE_YAW

# SYS_STATUS
SENSOR_PREARM_CHECK = 0x10000000

# main modes and the sub modes of AUTO (4)
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO = 1, 2, 3, 4
MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED, MAIN_RATTITUDE = 5, 6, 7, 8
AUTO_READY, AUTO_TAKEOFF, AUTO_LOITER, AUTO_MISSION, AUTO_RTL, AUTO_LAND = 1, 2, 3, 4, 5, 6

_SETTABLE: dict[FlightMode, tuple[int, int]] = {
    FlightMode.OFFBOARD: (MAIN_OFFBOARD, 0),
    FlightMode.HOLD: (MAIN_AUTO, AUTO_LOITER),
    FlightMode.POSCTL: (MAIN_POSCTL, 0),
    FlightMode.ALTCTL: (MAIN_ALTCTL, 0),
    FlightMode.MANUAL: (MAIN_MANUAL, 0),
    FlightMode.TAKEOFF: (MAIN_AUTO, AUTO_TAKEOFF),
    FlightMode.LAND: (MAIN_AUTO, AUTO_LAND),
    FlightMode.RTL: (MAIN_AUTO, AUTO_RTL),
    FlightMode.MISSION: (MAIN_AUTO, AUTO_MISSION),
}


def mode_from_custom_mode(custom_mode: int) -> FlightMode:
    """The flight mode a PX4 heartbeat's custom_mode names."""
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    if main == MAIN_OFFBOARD:
        return FlightMode.OFFBOARD
    if main == MAIN_POSCTL:
        return FlightMode.POSCTL
    if main == MAIN_ALTCTL:
        return FlightMode.ALTCTL
    if main in (MAIN_MANUAL, MAIN_ACRO, MAIN_STABILIZED, MAIN_RATTITUDE):
        return FlightMode.MANUAL
    if main == MAIN_AUTO:
        return {
            AUTO_TAKEOFF: FlightMode.TAKEOFF,
            AUTO_LOITER: FlightMode.HOLD,
            AUTO_MISSION: FlightMode.MISSION,
            AUTO_RTL: FlightMode.RTL,
            AUTO_LAND: FlightMode.LAND,
        }.get(sub, FlightMode.OTHER)
    return FlightMode.OTHER


def main_sub_of(mode: FlightMode) -> tuple[int, int]:
    """(main, sub) for DO_SET_MODE; ValueError for modes that cannot be selected."""
    try:
        return _SETTABLE[mode]
    except KeyError:
        raise ValueError(f"mode: {mode.name} cannot be selected by DO_SET_MODE") from None


def custom_mode_of(mode: FlightMode) -> int:
    main, sub = main_sub_of(mode)
    return (main << 16) | (sub << 24)


def set_mode_params(mode: FlightMode) -> tuple[float, ...]:
    """COMMAND_LONG params of DO_SET_MODE for ``mode``."""
    main, sub = main_sub_of(mode)
    return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub), 0.0, 0.0, 0.0, 0.0)


def takeoff_params(altitude_amsl_m: float | None) -> tuple[float, ...]:
    """NAV_TAKEOFF params: lat/lon NaN (take off where the vehicle is), yaw NaN (keep), param7
    the altitude AMSL (NaN: PX4's MIS_TAKEOFF_ALT above home)."""
    alt = math.nan if altitude_amsl_m is None else float(altitude_amsl_m)
    return (math.nan, 0.0, 0.0, math.nan, math.nan, math.nan, alt)


def land_params() -> tuple[float, ...]:
    """NAV_LAND params: land where the vehicle is (NaN position and yaw)."""
    return (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, math.nan)


def arm_params(arm: bool, force: bool = False) -> tuple[float, ...]:
    return (1.0 if arm else 0.0, ARM_FORCE_MAGIC if force else 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def command_name(command: int, params: tuple[float, ...] = ()) -> str:
    """Readable name of a command, e.g. ``MAV_CMD_DO_SET_MODE(OFFBOARD)``."""
    base = COMMAND_NAMES.get(command, f"MAV_CMD_{command}")
    if command == CMD_COMPONENT_ARM_DISARM and params:
        return f"{base}({'arm' if params[0] == 1.0 else 'disarm'})"
    if command == CMD_DO_SET_MODE and len(params) >= 3:
        custom = (int(params[1]) << 16) | (int(params[2]) << 24)
        return f"{base}({mode_from_custom_mode(custom).name})"
    if command == CMD_SET_MESSAGE_INTERVAL and params:
        return f"{base}(message {int(params[0])})"
    return base
