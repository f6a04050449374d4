"""The API link of one mock vehicle: MAVLink 2 over UDP, as PX4 v1.16 presents it to a companion.

NED lives here and only here: incoming setpoints are resolved into ENU by
``parse_position_target_local_ned`` and outgoing telemetry comes from ``sitl_mock.telemetry``
(already NED / FRD).

- Socket: bound to ``(host, local_port)`` (PX4: 14580 + i); telemetry goes to the partner,
  initially ``(host, client_port)`` (PX4: 14540 + i), then whoever last sent a valid message
  (PX4's UDP behaviour, so MAVSDK's ``udpin://`` and pymavlink's ``udpin:`` both work).
- Dialect: ``development`` (+ PROTOCOL_VERSION, LINK_NODE_STATUS), see ``sitl_mock.px4_dialect``.
- Each datagram is parsed on its own (a garbage datagram cannot swallow the next one). Three
  counters keep failures apart: ``rx_bad`` (bytes that are not a MAVLink message: bad CRC,
  truncated, unknown framing), ``rx_malformed`` (well-formed messages whose content is refused:
  NaN parameters, unsupported frames, ...; answered as PX4 answers them) and
  ``handler_errors`` (an exception in the mock's own handling: a bug, logged at error level with
  its traceback; the tests fail on any).
- Streams at the rates a real PX4 v1.16 sends on its onboard API link (``PX4_STREAM_RATES_HZ``,
  simulated time), changeable with SET_MESSAGE_INTERVAL; telemetry is sent every
  ``flush_interval_s`` (10 ms), the messages due since then sharing datagrams, as PX4 packs
  them; replies to commands are sent at once.
- STATUSTEXT only once the link has heard a GCS heartbeat (MAV_TYPE_GCS), as PX4 v1.16 does.
- Signing: PX4 v1.16 has none (its receiver ignores SETUP_SIGNING; observed). Signing here is an
  explicit option imitating PX4 v1.17+, off by default: outgoing messages are signed with the
  key; when signing is required, unsigned or wrongly signed messages are dropped (only
  RADIO_STATUS may be unsigned, as the MAVLink signing rules allow).
"""

from __future__ import annotations

import dataclasses
import hashlib
import heapq
import logging
import math
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sitl_mock import dynamics as dyn
from sitl_mock import telemetry as tm
from sitl_mock.autopilot import (
    AUTO_MODES,
    OFFBOARD_LOSS_ACTION_CODES,
    Autopilot,
    Mode,
    OffboardSetpoint,
    Result,
    Severity,
    StatusEvent,
    offboard_loss_action_from_code,
)
from sitl_mock.frames import (
    enu_ned,
    geodetic_from_enu,
    quaternion_from_matrix,
    rotation_ned_frd,
    yaw_enu_ned,
)
from sitl_mock.px4_dialect import (
    MessageDecoder,
    MessageEncoder,
    frame,
    mavlink,
    message_class,
    new_mavlink,
)
from sitl_mock.px4_dialect import message_id_by_name as message_id_by_name

log = logging.getLogger("sitl_mock")

# MAV_CMD values handled here
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_COMPONENT_ARM_DISARM = 400
CMD_GET_MESSAGE_INTERVAL = 510
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512
CMD_REQUEST_PROTOCOL_VERSION = 519
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
ARM_FORCE_MAGIC = 21196

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (1 = ignore)
IGNORE_PX, IGNORE_PY, IGNORE_PZ = 1, 2, 4
IGNORE_VX, IGNORE_VY, IGNORE_VZ = 8, 16, 32
IGNORE_AX, IGNORE_AY, IGNORE_AZ = 64, 128, 256
FORCE_SETPOINT = 512
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048
IGNORE_VELOCITY = IGNORE_VX | IGNORE_VY | IGNORE_VZ
IGNORE_ACCELERATION = IGNORE_AX | IGNORE_AY | IGNORE_AZ

FRAME_LOCAL_NED = 1
FRAME_LOCAL_OFFSET_NED = 7
FRAME_BODY_NED = 8
FRAME_BODY_OFFSET_NED = 9
FRAME_BODY_FRD = 12

# HEARTBEAT base_mode bits per mode besides CUSTOM_MODE_ENABLED (1), as a real PX4 v1.16 sent
# them (REFERENCE_NOTES section 5: Hold 29 / armed 157, Offboard 17 / armed 145, Land 157) and,
# for the manual modes, as PX4's mavlink_main.cpp sets them (Position: manual input, stabilize,
# guided; Altitude: manual input, stabilize).
PX4_BASE_MODE_AUTO = 16 | 8 | 4  # stabilize, guided, auto
PX4_BASE_MODE_OFFBOARD = 16
PX4_BASE_MODE_POSCTL = 64 | 16 | 8
PX4_BASE_MODE_ALTCTL = 64 | 16

SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_SENSOR_LASER_POSITION
)
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK  # in the health field only, as PX4 reports it
RC_RECEIVER = mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER

# AUTOPILOT_VERSION.capabilities of a real PX4 v1.16 (observed: 59647): MISSION_FLOAT,
# PARAM_FLOAT, MISSION_INT, COMMAND_INT, PARAM_ENCODE_BYTEWISE, FTP, SET_ATTITUDE_TARGET,
# SET_POSITION_TARGET_LOCAL_NED, FLIGHT_TERMINATION, MAVLINK2, MISSION_FENCE, MISSION_RALLY.
PX4_CAPABILITIES = 0xE8FF
PX4_FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 255  # v1.16.0, official release

_ID = message_id_by_name
# Default stream rates [Hz, simulated time]: what a real PX4 v1.16 (SITL, SIH) sent on its API
# (onboard) link while armed in Offboard (REFERENCE_NOTES section 5; the onboard profile of
# mavlink_main.cpp lists the same streams, some sent only when their data exists).
PX4_STREAM_RATES_HZ: dict[int, float] = {
    _ID("ATTITUDE"): 100.0,
    _ID("ATTITUDE_QUATERNION"): 50.0,
    _ID("HIGHRES_IMU"): 50.0,
    _ID("GLOBAL_POSITION_INT"): 50.0,
    _ID("LOCAL_POSITION_NED"): 30.0,
    _ID("ODOMETRY"): 30.0,
    _ID("TIMESYNC"): 10.0,
    _ID("ALTITUDE"): 10.0,
    _ID("DISTANCE_SENSOR"): 10.0,
    _ID("ATTITUDE_TARGET"): 10.0,
    _ID("POSITION_TARGET_LOCAL_NED"): 10.0,
    _ID("SERVO_OUTPUT_RAW"): 10.0,
    _ID("VFR_HUD"): 10.0,
    _ID("GPS_RAW_INT"): 8.0,
    _ID("SYS_STATUS"): 5.0,
    _ID("EXTENDED_SYS_STATE"): 5.0,
    _ID("HEARTBEAT"): 1.0,
    _ID("MISSION_CURRENT"): 1.0,
    _ID("ESTIMATOR_STATUS"): 1.0,
    _ID("SYSTEM_TIME"): 1.0,
    _ID("PING"): 1.0,
    _ID("SCALED_PRESSURE"): 1.0,
    _ID("LINK_NODE_STATUS"): 1.0,
    _ID("BATTERY_STATUS"): 0.5,
    _ID("CURRENT_MODE"): 0.5,
    _ID("HOME_POSITION"): 0.5,
    _ID("VIBRATION"): 0.5,
}
# one-off messages (REQUEST_MESSAGE and their own commands), never streamed
ONE_SHOT_MESSAGES = frozenset({_ID("AUTOPILOT_VERSION"), _ID("PROTOCOL_VERSION")})

# MAV_STANDARD_MODE of each PX4 mode (PX4's standard-mode mapping; the others are 0)
_STANDARD_MODE = {
    Mode.POSCTL: mavlink.MAV_STANDARD_MODE_POSITION_HOLD,
    Mode.ALTCTL: mavlink.MAV_STANDARD_MODE_ALTITUDE_HOLD,
    Mode.RTL: mavlink.MAV_STANDARD_MODE_SAFE_RECOVERY,
    Mode.MISSION: mavlink.MAV_STANDARD_MODE_MISSION,
    Mode.LAND: mavlink.MAV_STANDARD_MODE_LAND,
    Mode.TAKEOFF: mavlink.MAV_STANDARD_MODE_TAKEOFF,
}

MAX_DATAGRAM_BYTES = 1200
STATUSTEXT_LEN = 50
_SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01T00:00:00Z
_ESTIMATOR_FLAGS = 1 | 2 | 4 | 8 | 16 | 32 | 64 | 256 | 512  # att, vel, pos (rel/abs/agl), pred


def signing_timestamp_now() -> int:
    """MAVLink 2 signing timestamp: 10 us units since 2015-01-01 (wall clock)."""
    return int((time.time() - _SIGNING_EPOCH_UNIX_S) * 100_000)


# ---------------------------------------------------------------------------------------------
# Setpoints: MAVLink NED -> ENU world, as PX4 v1.16's mavlink_receiver.cpp parses them


@dataclass(frozen=True)
class ParsedSetpoint:
    """A SET_POSITION_TARGET_LOCAL_NED after PX4's parsing: the setpoint, or why it is ignored
    (``error``: PX4's status text)."""

    setpoint: OffboardSetpoint | None
    error: str = ""


_EYE3 = np.eye(3)


def _rot_z(psi: float) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def parse_position_target_local_ned(
    type_mask: int,
    frame_id: int,
    pos_ned: Sequence[float],
    vel_ned: Sequence[float],
    acc_ned: Sequence[float],
    yaw_ned: float,
    yaw_rate_ned: float,
    origin_enu: np.ndarray,
    r_ned_frd: np.ndarray,
) -> ParsedSetpoint:
    """Resolve a SET_POSITION_TARGET_LOCAL_NED as PX4 v1.16 does
    (``MavlinkReceiver::handle_message_set_position_target_local_ned``).

    - MAV_FRAME_LOCAL_NED (1): each component whose ignore bit is clear counts (a non-finite
      value counts as not set); positions are relative to the local origin ``origin_enu``.
    - MAV_FRAME_BODY_NED (8): positions are never used; the velocity is used only as a whole
      vector (any of its three ignore bits drops all three) and turned by the heading; the
      acceleration likewise, turned by the whole attitude ``r_ned_frd`` (FRD body -> NED).
    - Every other frame (7 LOCAL_OFFSET_NED, 9 BODY_OFFSET_NED, ...): ignored, "coordinate
      frame N unsupported".
    - FORCE with an acceleration: ignored, "force not supported".
    - Nothing set (no position, velocity or acceleration component): ignored, "invalid".
    Yaw and yaw rate are absolute in every frame; a NED yaw rate (clockwise) becomes an ENU one.
    Setpoints that leave an axis uncontrolled are *not* refused here: they keep the stream
    alive, and PX4's position controller then stops (``OffboardSetpoint.valid``).
    """
    name = "SET_POSITION_TARGET_LOCAL_NED"
    nan = math.nan
    m = type_mask

    def comp(values: Sequence[float], bits: tuple[int, int, int]) -> list[float]:
        out = [nan, nan, nan]
        for k in range(3):
            v = float(values[k])
            if not (m & bits[k]) and math.isfinite(v):
                out[k] = v
        return out

    if frame_id == FRAME_LOCAL_NED:
        p = comp(pos_ned, (IGNORE_PX, IGNORE_PY, IGNORE_PZ))
        v = comp(vel_ned, (IGNORE_VX, IGNORE_VY, IGNORE_VZ))
        a = comp(acc_ned, (IGNORE_AX, IGNORE_AY, IGNORE_AZ))
    elif frame_id == FRAME_BODY_NED:
        p = [nan, nan, nan]
        v = [nan, nan, nan]
        a = [nan, nan, nan]
        r = np.asarray(r_ned_frd, dtype=np.float64)
        vb = np.array([float(x) for x in vel_ned[:3]])
        ab = np.array([float(x) for x in acc_ned[:3]])
        # a non-finite component spoils the rotated vector: the mock treats it as not set
        if not m & IGNORE_VELOCITY and np.all(np.isfinite(vb)):
            v = (_rot_z(math.atan2(r[1, 0], r[0, 0])) @ vb).tolist()
        if not m & IGNORE_ACCELERATION and np.all(np.isfinite(ab)):
            a = (r @ ab).tolist()
    else:
        return ParsedSetpoint(None, f"{name} coordinate frame {frame_id} unsupported")
    has_acc = a[0] == a[0] or a[1] == a[1] or a[2] == a[2]  # NaN != NaN
    if has_acc and m & FORCE_SETPOINT:
        return ParsedSetpoint(None, f"{name} force not supported")
    if not (has_acc or any(x == x for x in p) or any(x == x for x in v)):
        return ParsedSetpoint(None, f"{name} invalid")
    yaw = nan
    yaw_rate = nan
    if not (m & IGNORE_YAW) and math.isfinite(yaw_ned):
        yaw = yaw_enu_ned(yaw_ned)
    if not (m & IGNORE_YAW_RATE) and math.isfinite(yaw_rate_ned):
        yaw_rate = -yaw_rate_ned
    o = origin_enu
    # NED -> ENU: (n, e, d) -> (e, n, -d); positions relative to the local origin
    pos_enu = np.array([o[0] + p[1], o[1] + p[0], o[2] - p[2]])
    return ParsedSetpoint(
        OffboardSetpoint(
            pos_enu,
            np.array([v[1], v[0], -v[2]]),
            np.array([a[1], a[0], -a[2]]),
            yaw,
            yaw_rate,
        )
    )


def setpoint_from_local_ned(
    type_mask: int,
    frame: int,
    pos_ned: tuple[float, float, float],
    vel_ned: tuple[float, float, float],
    acc_ned: tuple[float, float, float],
    yaw_ned: float,
    yaw_rate_ned: float,
    origin_enu: np.ndarray,
    position_enu: np.ndarray,
    yaw_enu: float,
    r_ned_frd: np.ndarray | None = None,
) -> OffboardSetpoint | None:
    """``parse_position_target_local_ned`` returning only the setpoint (None when PX4 ignores
    the message). ``r_ned_frd`` defaults to a level attitude with heading ``yaw_enu``;
    ``position_enu`` is unused since PX4 v1.16 refuses the offset frames (kept for callers)."""
    del position_enu
    r = _rot_z(yaw_enu_ned(yaw_enu)) if r_ned_frd is None else r_ned_frd
    return parse_position_target_local_ned(
        type_mask, frame, pos_ned, vel_ned, acc_ned, yaw_ned, yaw_rate_ned, origin_enu, r
    ).setpoint


# ---------------------------------------------------------------------------------------------
# Per-tick view of a vehicle


class VehicleView:
    """One vehicle at one tick: rows of the fleet arrays plus the derived MAVLink quantities
    (``tel``: a row of ``sitl_mock.telemetry``, as a list of floats; computed if not given)."""

    def __init__(
        self,
        t_s: float,
        state: np.ndarray,
        att: np.ndarray,
        cmd: np.ndarray,
        origin_enu: np.ndarray,
        home_enu: np.ndarray,
        geo_ref: tuple[float, float, float],
        ground_z: float,
        f_max: float,
        tel: list[float] | None = None,
    ) -> None:
        self.t_s = t_s
        self.s = state
        self.att = att
        self.cmd = cmd
        self.origin_enu = origin_enu
        self.home_enu = home_enu
        self.geo_ref = geo_ref
        self.ground_z = ground_z
        self.f_max = f_max
        if tel is None:
            out = np.empty((1, tm.NT))
            tm.telemetry_fleet(
                state.reshape(1, dyn.NS),
                att.reshape(1, dyn.NA),
                np.asarray(origin_enu, dtype=np.float64).reshape(1, 3),
                np.array([float(ground_z)]),
                np.array(geo_ref, dtype=np.float64),
                out,
            )
            tel = out[0].tolist()
        self.tel = tel
        self.boot_ms = int(t_s * 1000.0) & 0xFFFFFFFF
        self.usec = int(t_s * 1e6)

    @property
    def est_enu(self) -> np.ndarray:
        return self.s[dyn.S_P : dyn.S_P + 3] + self.s[dyn.S_E : dyn.S_E + 3]

    @property
    def vel_enu(self) -> np.ndarray:
        return self.s[dyn.S_V : dyn.S_V + 3].copy()

    @property
    def pos_ned(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_PN], t[tm.T_PN + 1], t[tm.T_PN + 2]

    @property
    def vel_ned(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_VN], t[tm.T_VN + 1], t[tm.T_VN + 2]

    @property
    def r_ned_frd(self) -> np.ndarray:
        return rotation_ned_frd(self.att[dyn.A_R : dyn.A_R + 9].reshape(3, 3))

    @property
    def euler(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_ROLL], t[tm.T_PITCH], t[tm.T_YAW]

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        t = self.tel
        return t[tm.T_Q], t[tm.T_Q + 1], t[tm.T_Q + 2], t[tm.T_Q + 3]

    @property
    def rates_frd(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_W], t[tm.T_W + 1], t[tm.T_W + 2]

    @property
    def specific_force_frd(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_F], t[tm.T_F + 1], t[tm.T_F + 2]

    @property
    def geodetic(self) -> tuple[float, float, float]:
        t = self.tel
        return t[tm.T_LAT], t[tm.T_LON], t[tm.T_ALT]

    @property
    def home_geodetic(self) -> tuple[float, float, float]:
        return geodetic_from_enu(self.home_enu, *self.geo_ref)

    @property
    def relative_alt_m(self) -> float:
        return float(self.tel[tm.T_ALT] - self.geo_ref[2] - self.home_enu[2])

    @property
    def heading_deg(self) -> float:
        return math.degrees(self.tel[tm.T_YAW]) % 360.0


# ---------------------------------------------------------------------------------------------
# The link


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink 2 signing of one vehicle (imitates PX4 v1.17+; PX4 v1.16 has none): 32-byte key;
    ``require``: refuse unsigned messages."""

    key: bytes
    require: bool = True

    def __post_init__(self) -> None:
        if len(self.key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")


@dataclass
class LinkStats:
    rx_datagrams: int = 0
    rx_messages: int = 0
    rx_bad: int = 0  # not a decodable MAVLink message
    rx_malformed: int = 0  # decoded, content refused (answered as PX4 answers it)
    rx_rejected_unsigned: int = 0
    rx_ignored: int = 0  # not for this vehicle, or not handled by the mock
    handler_errors: int = 0  # exceptions in the mock's handlers (bugs)
    tx_messages: int = 0
    tx_datagrams: int = 0
    tx_bytes: int = 0
    setpoints: int = 0
    setpoints_malformed: int = 0  # setpoints PX4 ignores (unsupported frame, FORCE, nothing set)
    commands: int = 0
    statustexts_suppressed: int = 0  # not sent: no GCS heartbeat heard on this link
    tx_by_message: dict[str, int] = field(default_factory=dict)


# PX4 parameters exposed through the parameter protocol: name -> (AutopilotParams field, int?)
_PARAMS: dict[str, tuple[str, bool]] = {
    "MIS_TAKEOFF_ALT": ("takeoff_alt_m", False),
    "MPC_TKO_SPEED": ("takeoff_speed_m_s", False),
    "MPC_LAND_SPEED": ("land_speed_m_s", False),
    "MPC_XY_CRUISE": ("auto_speed_m_s", False),
    "RTL_RETURN_ALT": ("rtl_return_alt_m", False),
    "COM_OF_LOSS_T": ("offboard_loss_timeout_s", False),
    "COM_OBL_RC_ACT": ("offboard_loss_action", True),
    "COM_DISARM_LAND": ("disarm_land_s", False),
    "COM_DISARM_PRFLT": ("disarm_preflight_s", False),
    "COM_SPOOLUP_TIME": ("spoolup_s", False),
    "LNDMC_TRIG_TIME": ("land_detect_s", False),
}


def _float_bits_of_int(v: int) -> float:
    """PX4's bytewise parameter encoding: the int32's bytes read as a float32."""
    return float(struct.unpack("<f", struct.pack("<i", int(v)))[0])


def _int_of_float_bits(f: float) -> int:
    return int(struct.unpack("<i", struct.pack("<f", float(f)))[0])


def _text(field_value: Any) -> str:
    """A MAVLink char[] field as text (pymavlink gives str or bytes)."""
    if isinstance(field_value, bytes):
        field_value = field_value.decode("utf-8", errors="replace")
    return str(field_value).split("\x00", 1)[0]


_ENCODER_CACHE: dict[int, MessageEncoder] = {}


def _enc(name: str) -> MessageEncoder:
    mid = message_id_by_name(name)
    e = _ENCODER_CACHE.get(mid)
    if e is None:
        e = _ENCODER_CACHE[mid] = MessageEncoder(message_class(mid))
    return e


E_HEARTBEAT = _enc("HEARTBEAT")
E_SYS_STATUS = _enc("SYS_STATUS")
E_ATTITUDE = _enc("ATTITUDE")
E_ATTITUDE_QUATERNION = _enc("ATTITUDE_QUATERNION")
E_HIGHRES_IMU = _enc("HIGHRES_IMU")
E_GLOBAL_POSITION_INT = _enc("GLOBAL_POSITION_INT")
E_LOCAL_POSITION_NED = _enc("LOCAL_POSITION_NED")
E_ODOMETRY = _enc("ODOMETRY")
E_TIMESYNC = _enc("TIMESYNC")
E_ALTITUDE = _enc("ALTITUDE")
E_DISTANCE_SENSOR = _enc("DISTANCE_SENSOR")
E_ATTITUDE_TARGET = _enc("ATTITUDE_TARGET")
E_POSITION_TARGET_LOCAL_NED = _enc("POSITION_TARGET_LOCAL_NED")
E_SERVO_OUTPUT_RAW = _enc("SERVO_OUTPUT_RAW")
E_VFR_HUD = _enc("VFR_HUD")
E_GPS_RAW_INT = _enc("GPS_RAW_INT")
E_EXTENDED_SYS_STATE = _enc("EXTENDED_SYS_STATE")
E_MISSION_CURRENT = _enc("MISSION_CURRENT")
E_ESTIMATOR_STATUS = _enc("ESTIMATOR_STATUS")
E_SYSTEM_TIME = _enc("SYSTEM_TIME")
E_PING = _enc("PING")
E_SCALED_PRESSURE = _enc("SCALED_PRESSURE")
E_LINK_NODE_STATUS = _enc("LINK_NODE_STATUS")
E_BATTERY_STATUS = _enc("BATTERY_STATUS")
E_CURRENT_MODE = _enc("CURRENT_MODE")
E_HOME_POSITION = _enc("HOME_POSITION")
E_VIBRATION = _enc("VIBRATION")
E_AUTOPILOT_VERSION = _enc("AUTOPILOT_VERSION")
E_PROTOCOL_VERSION = _enc("PROTOCOL_VERSION")
E_COMMAND_ACK = _enc("COMMAND_ACK")
E_STATUSTEXT = _enc("STATUSTEXT")
E_PARAM_VALUE = _enc("PARAM_VALUE")
E_PARAM_ERROR = _enc("PARAM_ERROR")
E_MESSAGE_INTERVAL = _enc("MESSAGE_INTERVAL")

_SETPOINT_DECODER = MessageDecoder(
    message_class(mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED)
)
_NAN21 = [math.nan] + [0.0] * 20
_ZERO4 = [0.0, 0.0, 0.0, 0.0]


class VehicleLink:
    """MAVLink endpoint of one vehicle (autopilot component 1)."""

    def __init__(
        self,
        system_id: int,
        autopilot: Autopilot,
        host: str,
        client_port: int,
        local_port: int,
        origin_enu: np.ndarray,
        home_enu: np.ndarray,
        geo_ref: tuple[float, float, float],
        signing: SigningConfig | None = None,
        accept_setup_signing: bool = False,
        stream_rates_hz: dict[int, float] | None = None,
        duplicate_mode_ack: bool = True,
        batch_datagrams: bool = True,
        flush_interval_s: float = 0.01,
    ) -> None:
        self.system_id = int(system_id)
        self.ap = autopilot
        self.host = host
        self.client_port = int(client_port)
        self.local_port = int(local_port)
        self.partner: tuple[str, int] = (host, self.client_port)
        self.origin_enu = np.asarray(origin_enu, dtype=np.float64).reshape(3)
        # the autopilot owns the home position (PX4 resets it at arming and after takeoff)
        self.ap.home_m = np.asarray(home_enu, dtype=np.float64).reshape(3).copy()
        self.geo_ref = geo_ref
        self.accept_setup_signing = accept_setup_signing
        self.duplicate_mode_ack = duplicate_mode_ack
        self.batch_datagrams = batch_datagrams
        # telemetry is sent at most this often (simulated time; replies go out at once)
        self.flush_interval_s = float(flush_interval_s)
        self._next_flush = 0.0
        self.stats = LinkStats()
        self.mav = new_mavlink(self.system_id, 1)
        self.mav.check_signature = self._check_signature
        self.signing: SigningConfig | None = None
        if signing is not None:
            self.set_signing(signing)
        rates = dict(PX4_STREAM_RATES_HZ)
        self.default_rates_hz = dict(rates)
        if stream_rates_hz:
            rates.update(stream_rates_hz)
        self.intervals_s: dict[int, float] = {
            m: (1.0 / r if r > 0 else math.inf) for m, r in rates.items()
        }
        # stream schedule: a heap of (due time, version, message id); a changed interval bumps
        # the stream's version, which retires its old entry
        self._version: dict[int, int] = {m: 0 for m in self.intervals_s}
        self._schedule: list[tuple[float, int, int]] = [(0.0, 0, m) for m in self.intervals_s]
        heapq.heapify(self._schedule)
        self._out: list[bytes] = []
        self._deferred: list[Callable[[], None]] = []
        self._encoders: dict[int, Callable[[VehicleView], None]] = {
            E_HEARTBEAT.msg_id: self._heartbeat,
            E_SYS_STATUS.msg_id: self._sys_status,
            E_ATTITUDE.msg_id: self._attitude,
            E_ATTITUDE_QUATERNION.msg_id: self._attitude_quaternion,
            E_HIGHRES_IMU.msg_id: self._highres_imu,
            E_GLOBAL_POSITION_INT.msg_id: self._global_position_int,
            E_LOCAL_POSITION_NED.msg_id: self._local_position_ned,
            E_ODOMETRY.msg_id: self._odometry,
            E_TIMESYNC.msg_id: self._timesync_request,
            E_ALTITUDE.msg_id: self._altitude,
            E_DISTANCE_SENSOR.msg_id: self._distance_sensor,
            E_ATTITUDE_TARGET.msg_id: self._attitude_target,
            E_POSITION_TARGET_LOCAL_NED.msg_id: self._position_target,
            E_SERVO_OUTPUT_RAW.msg_id: self._servo_output_raw,
            E_VFR_HUD.msg_id: self._vfr_hud,
            E_GPS_RAW_INT.msg_id: self._gps_raw_int,
            E_EXTENDED_SYS_STATE.msg_id: self._extended_sys_state,
            E_MISSION_CURRENT.msg_id: self._mission_current,
            E_ESTIMATOR_STATUS.msg_id: self._estimator_status,
            E_SYSTEM_TIME.msg_id: self._system_time,
            E_PING.msg_id: self._ping_request,
            E_SCALED_PRESSURE.msg_id: self._scaled_pressure,
            E_LINK_NODE_STATUS.msg_id: self._link_node_status,
            E_BATTERY_STATUS.msg_id: self._battery_status,
            E_CURRENT_MODE.msg_id: self._current_mode,
            E_HOME_POSITION.msg_id: self._home_position,
            E_VIBRATION.msg_id: self._vibration,
            E_AUTOPILOT_VERSION.msg_id: self._autopilot_version,
            E_PROTOCOL_VERSION.msg_id: self._protocol_version,
        }
        missing = set(self.intervals_s) - set(self._encoders)
        if missing:
            raise ValueError(f"no encoder for streams {sorted(missing)}")
        self.sock: socket.socket | None = None
        self.view: VehicleView | None = None
        # called with every frame the link emits, socket or not (tests, recorders)
        self.tap: Callable[[bytes], None] | None = None
        self.gcs_heartbeats = 0  # HEARTBEATs of type MAV_TYPE_GCS heard
        self.gcs_seen = False  # STATUSTEXT is sent once a GCS heartbeat was heard
        self._ping_seq = 0
        self._statustext_id = 0
        self._lns_last: tuple[float, int, int] | None = None  # (t, tx bytes, rx bytes)
        self._lns_rates = (0, 0)
        self.rx_bytes = 0

    @property
    def home_enu(self) -> np.ndarray:
        """The vehicle's home (ENU), owned by the autopilot."""
        return self.ap.home_m

    # ---- socket --------------------------------------------------------------------------
    def open(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        except OSError:  # pragma: no cover - the default buffer is fine too
            pass
        s.bind((self.host, self.local_port))
        self.local_port = s.getsockname()[1]
        self.sock = s

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    @property
    def address(self) -> tuple[str, int]:
        """Where the vehicle listens."""
        return self.host, self.local_port

    # ---- signing (imitates PX4 v1.17+) ---------------------------------------------------
    def set_signing(self, cfg: SigningConfig | None) -> None:
        self.signing = cfg
        sg = self.mav.signing
        if cfg is None:
            sg.secret_key = None
            sg.sign_outgoing = False
            sg.allow_unsigned_callback = None
            return
        sg.secret_key = bytes(cfg.key)
        sg.sign_outgoing = True
        sg.link_id = 0
        sg.timestamp = max(sg.timestamp, signing_timestamp_now())
        sg.allow_unsigned_callback = self._allow_unsigned

    def _check_signature(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        """Verify an incoming signature, then its timestamp (replays are refused).

        Unlike pymavlink's own check, a stream's timestamp only advances on a correctly signed
        message, so a forged packet cannot lock the legitimate sender out.
        """
        sg = self.mav.signing
        if sg.secret_key is None:
            return False
        h = hashlib.sha256()
        h.update(sg.secret_key)
        h.update(msgbuf[:-6])
        if h.digest()[:6] != bytes(msgbuf[-6:]):
            return False
        link_id = msgbuf[-13]
        tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        stamp = tlow + (thigh << 32)
        key = (link_id, src_system, src_component)
        last = sg.stream_timestamps.get(key)
        if last is not None and stamp <= last:
            return False
        if last is None and stamp + 6_000_000 < sg.timestamp:  # a new stream over 1 min old
            return False
        sg.stream_timestamps[key] = stamp
        sg.timestamp = max(sg.timestamp, stamp)
        return True

    def _allow_unsigned(self, _mav: Any, msg_id: int) -> bool:
        if self.signing is None or not self.signing.require:
            return True
        return msg_id == mavlink.MAVLINK_MSG_ID_RADIO_STATUS

    # ---- receive -------------------------------------------------------------------------
    def receive(self, max_datagrams: int = 256) -> int:
        """Drain the socket; handle every message. Returns the number of datagrams read."""
        if self.sock is None:
            return 0
        n = 0
        while n < max_datagrams:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error surfacing on the socket
                break
            n += 1
            self.on_datagram(data, addr)
        if n:
            self.flush()
        return n

    def on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        """Parse one datagram on its own and handle its messages."""
        st = self.stats
        st.rx_datagrams += 1
        self.rx_bytes += len(data)
        mav = self.mav
        fast = None if self.signing is not None else _SETPOINT_DECODER.decode(data)
        if fast is not None:  # the setpoint stream: one unsigned frame per datagram
            msgs = [fast]
        else:
            mav.buf = bytearray()
            mav.buf_index = 0
            mav.expected_length = mavlink.HEADER_LEN_V1 + 2
            rejected_before = mav.signing.reject_count
            try:
                msgs = mav.parse_buffer(data) or []
            except mavlink.MAVError:  # robust parsing turns these into BAD_DATA; count anyway
                msgs = []
                st.rx_bad += 1
            st.rx_rejected_unsigned += mav.signing.reject_count - rejected_before
        for msg in msgs:
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                st.rx_bad += 1
                continue
            if mtype.startswith("UNKNOWN"):  # a message id outside the dialect
                st.rx_ignored += 1
                continue
            st.rx_messages += 1
            if addr != self.partner:
                log.info("vehicle %d: partner %s:%d", self.system_id, addr[0], addr[1])
                self.partner = (addr[0], addr[1])
            try:
                self.handle(msg)
            except Exception:
                # a bug in the mock, never "bad input": counted apart, logged with traceback
                st.handler_errors += 1
                log.exception("vehicle %d: handling %s failed", self.system_id, mtype)

    def handle(self, msg: Any) -> None:
        """Act on one decoded message (exceptions propagate: they are bugs)."""
        mid = msg.get_msgId()
        st = self.stats
        if mid == mavlink.MAVLINK_MSG_ID_COMMAND_LONG:
            if self._for_me(msg.target_system, msg.target_component):
                p = (
                    msg.param1,
                    msg.param2,
                    msg.param3,
                    msg.param4,
                    msg.param5,
                    msg.param6,
                    msg.param7,
                )
                self._command(msg.command, p, msg.get_srcSystem(), msg.get_srcComponent())
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_COMMAND_INT:
            if self._for_me(msg.target_system, msg.target_component):
                p = (
                    msg.param1,
                    msg.param2,
                    msg.param3,
                    msg.param4,
                    float(msg.x),
                    float(msg.y),
                    msg.z,
                )
                self._command(msg.command, p, msg.get_srcSystem(), msg.get_srcComponent())
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED:
            if self._for_me(msg.target_system, msg.target_component):
                self._setpoint(msg)
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_SET_MODE:
            if msg.target_system == self.system_id:
                self._set_mode_message(msg)
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_TIMESYNC:
            if msg.tc1 == 0:
                self._emit(E_TIMESYNC, (self._now_ns(), msg.ts1))
        elif mid == mavlink.MAVLINK_MSG_ID_PING:
            if msg.target_system == 0 and msg.target_component == 0:  # a request: answer it
                self._emit(
                    E_PING, (msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent())
                )
        elif mid == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            if msg.type == mavlink.MAV_TYPE_GCS:
                self.gcs_heartbeats += 1
                self.gcs_seen = True
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            if self._for_me(msg.target_system, msg.target_component):
                for i, name in enumerate(_PARAMS):
                    self._param_value(name, i)
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ:
            if self._for_me(msg.target_system, msg.target_component):
                self._param_read(msg)
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_SET:
            if self._for_me(msg.target_system, msg.target_component):
                self._param_set(msg)
            else:
                st.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_SETUP_SIGNING:
            self._setup_signing(msg)
        else:
            st.rx_ignored += 1

    def _for_me(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.system_id) and target_component in (0, 1)

    def _now_ns(self) -> int:
        return int((self.view.t_s if self.view is not None else 0.0) * 1e9)

    @property
    def _t(self) -> float:
        return self.view.t_s if self.view is not None else 0.0

    def _setup_signing(self, msg: Any) -> None:
        if not self.accept_setup_signing:
            # PX4 v1.16's receiver has no signing: the message changes nothing (observed)
            self.stats.rx_ignored += 1
            log.info("vehicle %d: SETUP_SIGNING ignored (PX4 v1.16 has no signing)", self.system_id)
            return
        if not self._for_me(msg.target_system, msg.target_component):
            self.stats.rx_ignored += 1
            return
        key = bytes(msg.secret_key)
        if key == bytes(32):
            self.set_signing(None)
            log.warning("vehicle %d: signing disabled by SETUP_SIGNING", self.system_id)
        else:
            self.set_signing(SigningConfig(key, require=True))
            self.mav.signing.timestamp = max(self.mav.signing.timestamp, int(msg.initial_timestamp))
            log.warning("vehicle %d: signing key set by SETUP_SIGNING", self.system_id)

    # ---- commands ------------------------------------------------------------------------
    def _command(
        self,
        command: int,
        p: tuple[float, ...],
        src_sys: int,
        src_comp: int,
    ) -> None:
        self.stats.commands += 1
        t = self._t
        ap = self.ap
        result: int
        after: list[Callable[[], None]] = []
        if command == CMD_COMPONENT_ARM_DISARM:
            action = p[0]
            if action not in (0.0, 1.0):
                result = Result.DENIED
                self.stats.rx_malformed += 1
            else:
                force = math.isfinite(p[1]) and int(round(p[1])) == ARM_FORCE_MAGIC
                result = ap.command_arm(t, action == 1.0, force)
        elif command == CMD_DO_SET_MODE:
            result = self._set_mode(p[0], p[1], p[2])
        elif command == CMD_NAV_TAKEOFF:
            alt = p[6]
            rel = None if not math.isfinite(alt) else alt - self.home_amsl_m
            result = ap.command_takeoff(t, rel)
        elif command == CMD_NAV_LAND:
            result = ap.command_land(t)
        elif command == CMD_NAV_RETURN_TO_LAUNCH:
            result = ap.command_rtl(t)
        elif command == CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(p[0], p[1])
        elif command == CMD_GET_MESSAGE_INTERVAL:
            mid = int(p[0]) if math.isfinite(p[0]) and abs(p[0]) < 2**24 else -1
            if mid in self._encoders:
                iv = self.intervals_s.get(mid, math.inf)
                us = -1 if not math.isfinite(iv) else int(round(iv * 1e6))
                result = Result.ACCEPTED
                after.append(lambda: self._emit(E_MESSAGE_INTERVAL, (mid, us)))
            else:
                result = Result.DENIED
                self.stats.rx_malformed += 1
        elif command == CMD_REQUEST_MESSAGE:
            mid = int(p[0]) if math.isfinite(p[0]) and abs(p[0]) < 2**24 else -1
            if mid in self._encoders and self.view is not None:
                result = Result.ACCEPTED
                view = self.view
                after.append(lambda: self._encoders[mid](view))
            else:
                result = Result.DENIED
                self.stats.rx_malformed += 1
        elif command == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result = Result.ACCEPTED
            after.append(lambda: self._autopilot_version(None))
        elif command == CMD_REQUEST_PROTOCOL_VERSION:
            result = Result.ACCEPTED
            after.append(lambda: self._protocol_version(None))
        else:
            result = Result.UNSUPPORTED
        self._ack(command, int(result), src_sys, src_comp)
        for f in after:
            f()
        if command == CMD_DO_SET_MODE and self.duplicate_mode_ack:
            self._deferred.append(lambda: self._ack(command, int(result), src_sys, src_comp))
        self._drain_events()

    def _set_mode(self, base_mode: float, main: float, sub: float) -> int:
        if not (math.isfinite(base_mode) and int(base_mode) & 1):
            return Result.DENIED  # only PX4 custom modes are supported
        mm = int(main) if math.isfinite(main) and 0 <= main < 256 else -1
        sm = int(sub) if math.isfinite(sub) and 0 <= sub < 256 else 0
        return self.ap.command_set_mode(self._t, Mode.from_main_sub(mm, sm))

    def _set_mode_message(self, msg: Any) -> None:
        if not msg.base_mode & 1:
            result = int(Result.DENIED)
        else:
            result = int(self.ap.command_set_mode(self._t, Mode.from_custom_mode(msg.custom_mode)))
        self._ack(CMD_DO_SET_MODE, result, msg.get_srcSystem(), msg.get_srcComponent())
        self._drain_events()

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not (math.isfinite(msg_id) and math.isfinite(interval_us) and 0 <= msg_id < 2**24):
            self.stats.rx_malformed += 1
            return Result.DENIED
        mid = int(msg_id)
        if mid not in self._encoders or mid in ONE_SHOT_MESSAGES:
            self.stats.rx_malformed += 1
            return Result.DENIED
        if interval_us < 0:
            self.intervals_s[mid] = math.inf
        elif interval_us == 0:
            r = self.default_rates_hz.get(mid, 0.0)
            self.intervals_s[mid] = 1.0 / r if r > 0 else math.inf
        else:
            self.intervals_s[mid] = interval_us * 1e-6
        ver = self._version.get(mid, 0) + 1
        self._version[mid] = ver
        heapq.heappush(self._schedule, (self._t, ver, mid))
        return Result.ACCEPTED

    def _ack(self, command: int, result: int, src_sys: int, src_comp: int) -> None:
        self._emit(E_COMMAND_ACK, (command, result, 0, 0, src_sys, src_comp))

    @property
    def home_amsl_m(self) -> float:
        return self.geo_ref[2] + float(self.home_enu[2])

    # ---- setpoints -----------------------------------------------------------------------
    def _setpoint(self, msg: Any) -> None:
        st = self.stats
        view = self.view
        frame_id = int(msg.coordinate_frame)
        if frame_id != FRAME_BODY_NED:
            r = _EYE3  # the attitude matters only in the body frame
        elif view is not None:
            r = view.r_ned_frd
        else:
            r = _rot_z(yaw_enu_ned(self.ap.yaw0_rad))
        parsed = parse_position_target_local_ned(
            int(msg.type_mask),
            frame_id,
            (msg.x, msg.y, msg.z),
            (msg.vx, msg.vy, msg.vz),
            (msg.afx, msg.afy, msg.afz),
            msg.yaw,
            msg.yaw_rate,
            self.origin_enu,
            r,
        )
        if parsed.setpoint is None or not self.ap.on_setpoint(self._t, parsed.setpoint):
            st.setpoints_malformed += 1
            st.rx_malformed += 1
            self.statustext(int(Severity.CRITICAL), parsed.error or "setpoint refused")
            return
        st.setpoints += 1

    # ---- parameters ----------------------------------------------------------------------
    def _param_value(self, name: str, index: int) -> None:
        fname, is_int = _PARAMS[name]
        value = getattr(self.ap.params, fname)
        if is_int:
            code = (
                OFFBOARD_LOSS_ACTION_CODES[value] if fname == "offboard_loss_action" else int(value)
            )
            args: tuple[Any, ...] = (
                name.encode(),
                _float_bits_of_int(code),
                mavlink.MAV_PARAM_TYPE_INT32,
                len(_PARAMS),
                index,
            )
        else:
            args = (name.encode(), float(value), mavlink.MAV_PARAM_TYPE_REAL32, len(_PARAMS), index)
        self._emit(E_PARAM_VALUE, args)

    def _param_read(self, msg: Any) -> None:
        names = list(_PARAMS)
        pid = _text(msg.param_id)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._param_value(names[msg.param_index], msg.param_index)
            else:
                self._param_error(msg, pid, mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
        elif pid in _PARAMS:
            self._param_value(pid, names.index(pid))
        else:
            self._param_error(msg, pid, mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)

    def _param_error(self, msg: Any, pid: str, error: int, index: int = -1) -> None:
        self._emit(
            E_PARAM_ERROR,
            (
                msg.get_srcSystem(),
                msg.get_srcComponent(),
                pid.encode()[:16],
                index,
                error,
            ),
        )

    def _param_set(self, msg: Any) -> None:
        """PARAM_SET: applied and echoed (PARAM_VALUE); a value the mock cannot honour is
        answered with PARAM_ERROR, the PARAM_VALUE in force and a status text, never silently
        dropped."""
        pid = _text(msg.param_id)
        if pid not in _PARAMS:
            self.stats.rx_malformed += 1
            self._param_error(msg, pid, mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            return
        index = list(_PARAMS).index(pid)
        fname, is_int = _PARAMS[pid]
        value: Any
        problem = ""
        if is_int:
            # PX4 copies the four bytes whatever param_type says (bytewise encoding)
            code = _int_of_float_bits(msg.param_value)
            try:
                value = offboard_loss_action_from_code(code)
            except ValueError as e:
                problem = str(e)
        else:
            value = float(msg.param_value)
            if msg.param_type != mavlink.MAV_PARAM_TYPE_REAL32:
                problem = f"{pid} is a float parameter (param_type {msg.param_type} given)"
        if not problem:
            try:
                self.ap.params = dataclasses.replace(self.ap.params, **{fname: value})
            except (ValueError, TypeError) as e:
                problem = f"{pid}: {e}"
        if problem:
            self.stats.rx_malformed += 1
            log.warning("vehicle %d: PARAM_SET refused: %s", self.system_id, problem)
            self._param_error(msg, pid, mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE, index)
            self.statustext(int(Severity.ERROR), f"{pid}: value not supported")
        self._param_value(pid, index)

    # ---- outgoing ------------------------------------------------------------------------
    def _emit(self, enc: MessageEncoder, args: Sequence[Any]) -> None:
        buf = frame(self.mav, enc, args)
        self._out.append(buf)
        if self.tap is not None:
            self.tap(buf)
        st = self.stats
        st.tx_messages += 1
        by = st.tx_by_message
        by[enc.name] = by.get(enc.name, 0) + 1

    def flush(self) -> None:
        """Send everything queued, several messages per datagram."""
        if not self._out or self.sock is None:
            self._out.clear()
            return
        chunks: list[bytes] = []
        if self.batch_datagrams:
            cur = bytearray()
            for b in self._out:
                if cur and len(cur) + len(b) > MAX_DATAGRAM_BYTES:
                    chunks.append(bytes(cur))
                    cur = bytearray()
                cur += b
            if cur:
                chunks.append(bytes(cur))
        else:
            chunks = list(self._out)
        self._out.clear()
        for c in chunks:
            try:
                self.sock.sendto(c, self.partner)
            except OSError:
                continue
            self.stats.tx_datagrams += 1
            self.stats.tx_bytes += len(c)

    def statustext(self, severity: int, text: str) -> None:
        """A STATUSTEXT (split into 50-byte chunks with an id, as PX4 does for long texts),
        sent only once the link has heard a GCS heartbeat, as PX4 v1.16 does."""
        if not self.gcs_seen:
            self.stats.statustexts_suppressed += 1
            return
        raw = text.encode("utf-8", errors="replace")
        if len(raw) <= STATUSTEXT_LEN:
            self._emit(E_STATUSTEXT, (int(severity), raw, 0, 0))
            return
        self._statustext_id = self._statustext_id % 65535 + 1
        chunks = [raw[i : i + STATUSTEXT_LEN] for i in range(0, len(raw), STATUSTEXT_LEN)]
        for k, chunk in enumerate(chunks):
            self._emit(E_STATUSTEXT, (int(severity), chunk, self._statustext_id, k))

    def _drain_events(self) -> None:
        for ev in self.ap.drain_events():
            self._log_event(ev)
            self.statustext(int(ev.severity), ev.text)

    def _log_event(self, ev: StatusEvent) -> None:
        level = logging.WARNING if ev.severity <= 3 else logging.INFO
        log.log(level, "vehicle %d: %s", self.system_id, ev.text)

    def tick(self, view: VehicleView) -> None:
        """Emit the streams due at ``view.t_s``, deferred replies and status texts; send."""
        self.view = view
        if self.signing is not None:
            sg = self.mav.signing
            sg.timestamp = max(sg.timestamp, signing_timestamp_now())
        if self._deferred:
            for f in self._deferred:
                f()
            self._deferred.clear()
        if self.ap.events:
            self._drain_events()
        t = view.t_s
        limit = t + 1e-9
        heap = self._schedule
        while heap and heap[0][0] <= limit:
            due, ver, mid = heapq.heappop(heap)
            interval = self.intervals_s.get(mid, math.inf)
            if ver != self._version[mid] or interval == math.inf:
                continue  # retired entry, or a stopped stream
            self._encoders[mid](view)
            due += interval
            if due <= t:
                due = t + interval
            heapq.heappush(heap, (due, ver, mid))
        if t + 1e-9 >= self._next_flush:
            self.flush()
            self._next_flush = max(self._next_flush + self.flush_interval_s, t)

    # ---- encoders (each emits one message from the view) ---------------------------------
    def _heartbeat(self, v: VehicleView) -> None:
        ap = self.ap
        mode = ap.mode
        base = 1
        if mode in AUTO_MODES:
            base |= PX4_BASE_MODE_AUTO
        elif mode == Mode.OFFBOARD:
            base |= PX4_BASE_MODE_OFFBOARD
        elif mode == Mode.POSCTL:
            base |= PX4_BASE_MODE_POSCTL
        elif mode == Mode.ALTCTL:
            base |= PX4_BASE_MODE_ALTCTL
        if ap.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            status = mavlink.MAV_STATE_CRITICAL if ap.failsafe else mavlink.MAV_STATE_ACTIVE
        elif ap.prearm_ok(v.t_s):
            status = mavlink.MAV_STATE_STANDBY
        else:  # observed: 0 after the auto-disarm in Offboard, where arming is refused
            status = mavlink.MAV_STATE_UNINIT
        self._emit(
            E_HEARTBEAT,
            (
                mavlink.MAV_TYPE_QUADROTOR,
                mavlink.MAV_AUTOPILOT_PX4,
                base,
                mode.custom_mode,
                status,
                3,
            ),
        )

    def _sys_status(self, v: VehicleView) -> None:
        ap = self.ap
        present = SENSORS | (RC_RECEIVER if ap.params.rc_present else 0)
        health = present
        if not ap.booted(v.t_s):
            health &= ~(
                mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
                | mavlink.MAV_SYS_STATUS_SENSOR_GPS
                | mavlink.MAV_SYS_STATUS_AHRS
            )
        if ap.prearm_ok(v.t_s):
            health |= PREARM
        volt_mv, current_ca = self._battery_electrics(v)
        self._emit(
            E_SYS_STATUS,
            (
                present,
                present,
                health,
                250,
                volt_mv,
                current_ca,
                int(round(ap.battery_fraction * 100)),
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            ),
        )

    def _battery_electrics(self, v: VehicleView) -> tuple[int, int]:
        frac = self.ap.battery_fraction
        volt = 4 * (3.5 + 0.7 * frac)
        thrust = v.tel[tm.T_THRUST] if self.ap.armed else 0.0
        current_a = 0.3 + 20.0 * thrust
        return int(volt * 1000), int(current_a * 100)

    def _attitude(self, v: VehicleView) -> None:
        t = v.tel
        self._emit(
            E_ATTITUDE,
            (
                v.boot_ms,
                t[tm.T_ROLL],
                t[tm.T_PITCH],
                t[tm.T_YAW],
                t[tm.T_W],
                t[tm.T_W + 1],
                t[tm.T_W + 2],
            ),
        )

    def _attitude_quaternion(self, v: VehicleView) -> None:
        t = v.tel
        self._emit(
            E_ATTITUDE_QUATERNION,
            (
                v.boot_ms,
                t[tm.T_Q],
                t[tm.T_Q + 1],
                t[tm.T_Q + 2],
                t[tm.T_Q + 3],
                t[tm.T_W],
                t[tm.T_W + 1],
                t[tm.T_W + 2],
                _ZERO4,
            ),
        )

    def _highres_imu(self, v: VehicleView) -> None:
        t = v.tel
        alt = t[tm.T_ALT]
        self._emit(
            E_HIGHRES_IMU,
            (
                v.usec,
                t[tm.T_F],
                t[tm.T_F + 1],
                t[tm.T_F + 2],
                t[tm.T_W],
                t[tm.T_W + 1],
                t[tm.T_W + 2],
                t[tm.T_MAG],
                t[tm.T_MAG + 1],
                t[tm.T_MAG + 2],
                tm.pressure_hpa(alt),
                0.0,
                alt,
                25.0,
                0x1FFF,
                0,
            ),
        )

    def _global_position_int(self, v: VehicleView) -> None:
        t = v.tel
        self._emit(
            E_GLOBAL_POSITION_INT,
            (
                v.boot_ms,
                int(round(t[tm.T_LAT] * 1e7)),
                int(round(t[tm.T_LON] * 1e7)),
                int(round(t[tm.T_ALT] * 1000)),
                int(round(v.relative_alt_m * 1000)),
                int(round(t[tm.T_VN] * 100)),
                int(round(t[tm.T_VN + 1] * 100)),
                int(round(t[tm.T_VN + 2] * 100)),
                int(round(v.heading_deg * 100)) % 36000,
            ),
        )

    def _local_position_ned(self, v: VehicleView) -> None:
        t = v.tel
        self._emit(
            E_LOCAL_POSITION_NED,
            (
                v.boot_ms,
                t[tm.T_PN],
                t[tm.T_PN + 1],
                t[tm.T_PN + 2],
                t[tm.T_VN],
                t[tm.T_VN + 1],
                t[tm.T_VN + 2],
            ),
        )

    def _odometry(self, v: VehicleView) -> None:
        t = v.tel
        self._emit(
            E_ODOMETRY,
            (
                v.usec,
                FRAME_LOCAL_NED,
                FRAME_BODY_FRD,
                t[tm.T_PN],
                t[tm.T_PN + 1],
                t[tm.T_PN + 2],
                t[tm.T_Q : tm.T_Q + 4],
                t[tm.T_VB],
                t[tm.T_VB + 1],
                t[tm.T_VB + 2],
                t[tm.T_W],
                t[tm.T_W + 1],
                t[tm.T_W + 2],
                _NAN21,
                _NAN21,
                0,
                mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT,
                100,
            ),
        )

    def _timesync_request(self, v: VehicleView) -> None:
        self._emit(E_TIMESYNC, (0, self._now_ns()))

    def _altitude(self, v: VehicleView) -> None:
        t = v.tel
        alt = t[tm.T_ALT]
        self._emit(
            E_ALTITUDE,
            (
                v.usec,
                alt,
                alt,
                -t[tm.T_PN + 2],
                v.relative_alt_m,
                math.nan,
                t[tm.T_HAG],
            ),
        )

    def _distance_sensor(self, v: VehicleView) -> None:
        """A downward rangefinder (SIH simulates one): distance along the tilted body axis."""
        t = v.tel
        cos_tilt = max(t[tm.T_COS_TILT], 0.1)
        d_cm = int(round(max(t[tm.T_HAG], 0.0) / cos_tilt * 100.0))
        d_cm = min(max(d_cm, 10), 4000)
        self._emit(
            E_DISTANCE_SENSOR,
            (
                v.boot_ms,
                10,
                4000,
                d_cm,
                mavlink.MAV_DISTANCE_SENSOR_LASER,
                0,
                mavlink.MAV_SENSOR_ROTATION_PITCH_270,
                0,
                0.0,
                0.0,
                _ZERO4,
                100,
            ),
        )

    def _attitude_target(self, v: VehicleView) -> None:
        fc = v.s[dyn.S_FCMD : dyn.S_FCMD + 3]
        yaw = float(v.cmd[dyn.C_YAW])
        if not math.isfinite(yaw):
            yaw = float(v.s[dyn.S_YAW])
        r = dyn.rotation_from_thrust(float(fc[0]), float(fc[1]), float(fc[2]), yaw)
        q = quaternion_from_matrix(rotation_ned_frd(r))
        thrust = min(max(float(np.linalg.norm(fc)) / v.f_max, 0.0), 1.0)
        self._emit(E_ATTITUDE_TARGET, (v.boot_ms, 7, q, 0.0, 0.0, 0.0, thrust))

    def _position_target(self, v: VehicleView) -> None:
        c = v.cmd
        pos = enu_ned(c[dyn.C_POS : dyn.C_POS + 3] - self.origin_enu)
        vel_cmd = c[dyn.C_VEL : dyn.C_VEL + 3].copy()
        vc = v.s[dyn.S_VCMD : dyn.S_VCMD + 3]
        use_vc = np.isnan(vel_cmd) & ~np.isnan(vc)
        vel_cmd[use_vc] = vc[use_vc]
        vel = enu_ned(vel_cmd)
        acc = enu_ned(c[dyn.C_ACC : dyn.C_ACC + 3])
        mask = 0
        for k, bit in enumerate((IGNORE_PX, IGNORE_PY, IGNORE_PZ)):
            mask |= bit if math.isnan(pos[k]) else 0
        for k, bit in enumerate((IGNORE_VX, IGNORE_VY, IGNORE_VZ)):
            mask |= bit if math.isnan(vel[k]) else 0
        for k, bit in enumerate((IGNORE_AX, IGNORE_AY, IGNORE_AZ)):
            mask |= bit if math.isnan(acc[k]) else 0
        yaw = float(c[dyn.C_YAW])
        yaw_rate = float(c[dyn.C_YAWRATE])
        mask |= IGNORE_YAW if math.isnan(yaw) else 0
        mask |= IGNORE_YAW_RATE if math.isnan(yaw_rate) else 0
        yaw_ned = yaw_enu_ned(yaw) if math.isfinite(yaw) else math.nan
        self._emit(
            E_POSITION_TARGET_LOCAL_NED,
            (
                v.boot_ms,
                FRAME_LOCAL_NED,
                mask,
                float(pos[0]),
                float(pos[1]),
                float(pos[2]),
                float(vel[0]),
                float(vel[1]),
                float(vel[2]),
                float(acc[0]),
                float(acc[1]),
                float(acc[2]),
                yaw_ned,
                -yaw_rate,
            ),
        )

    def _servo_output_raw(self, v: VehicleView) -> None:
        """Four motors' PWM: 900 us disarmed (PWM_MAIN_DISn), 1000-2000 us with thrust."""
        if self.ap.armed:
            pwm = 1000 + int(round(1000.0 * min(max(v.tel[tm.T_THRUST], 0.0), 1.0)))
        else:
            pwm = 900
        self._emit(
            E_SERVO_OUTPUT_RAW,
            (v.usec & 0xFFFFFFFF, 0, pwm, pwm, pwm, pwm, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        )

    def _vfr_hud(self, v: VehicleView) -> None:
        t = v.tel
        gs = math.hypot(t[tm.T_VN], t[tm.T_VN + 1])
        throttle = int(round(t[tm.T_THRUST] * 100))
        self._emit(
            E_VFR_HUD,
            (gs, gs, int(v.heading_deg) % 360, throttle, t[tm.T_ALT], -t[tm.T_VN + 2]),
        )

    def _gps_raw_int(self, v: VehicleView) -> None:
        t = v.tel
        vn, ve = t[tm.T_VN], t[tm.T_VN + 1]
        gs = math.hypot(vn, ve)
        cog = int(round((math.degrees(math.atan2(ve, vn)) % 360.0) * 100)) % 36000
        self._emit(
            E_GPS_RAW_INT,
            (
                v.usec,
                mavlink.GPS_FIX_TYPE_3D_FIX,
                int(round(t[tm.T_LAT] * 1e7)),
                int(round(t[tm.T_LON] * 1e7)),
                int(round(t[tm.T_ALT] * 1000)),
                80,
                120,
                int(round(gs * 100)),
                cog,
                12,
                int(round(t[tm.T_ALT] * 1000)),
                500,
                800,
                100,
                0,
                0,
            ),
        )

    def _extended_sys_state(self, v: VehicleView) -> None:
        # a multicopter reports MAV_VTOL_STATE_UNDEFINED (observed)
        self._emit(
            E_EXTENDED_SYS_STATE,
            (mavlink.MAV_VTOL_STATE_UNDEFINED, int(self.ap.landed_state())),
        )

    def _mission_current(self, v: VehicleView) -> None:
        mode = 1 if self.ap.mode == Mode.MISSION else 0
        self._emit(E_MISSION_CURRENT, (0, 0, mavlink.MISSION_STATE_NO_MISSION, mode))

    def _estimator_status(self, v: VehicleView) -> None:
        self._emit(
            E_ESTIMATOR_STATUS,
            (v.usec, _ESTIMATOR_FLAGS, 0.05, 0.05, 0.1, 0.05, 0.02, 0.0, 0.5, 0.8),
        )

    def _system_time(self, v: VehicleView) -> None:
        self._emit(E_SYSTEM_TIME, (int(time.time() * 1e6), v.boot_ms))

    def _ping_request(self, v: VehicleView) -> None:
        self._ping_seq = (self._ping_seq + 1) & 0xFFFFFFFF
        self._emit(E_PING, (v.usec, self._ping_seq, 0, 0))

    def _scaled_pressure(self, v: VehicleView) -> None:
        self._emit(E_SCALED_PRESSURE, (v.boot_ms, tm.pressure_hpa(v.tel[tm.T_ALT]), 0.0, 2500, 0))

    def _link_node_status(self, v: VehicleView) -> None:
        st = self.stats
        now = (v.t_s, st.tx_bytes, self.rx_bytes)
        last = self._lns_last
        if last is not None and now[0] > last[0]:
            dt = now[0] - last[0]
            self._lns_rates = (int((now[1] - last[1]) / dt), int((now[2] - last[2]) / dt))
        self._lns_last = now
        self._emit(
            E_LINK_NODE_STATUS,
            (
                v.boot_ms,
                100,
                100,
                self._lns_rates[0],
                self._lns_rates[1],
                min(st.rx_bad, 65535),
                0,
                0,
                st.tx_messages & 0xFFFFFFFF,
                st.rx_messages & 0xFFFFFFFF,
                0,
            ),
        )

    def _battery_status(self, v: VehicleView) -> None:
        volt_mv, current_ca = self._battery_electrics(v)
        frac = self.ap.battery_fraction
        voltages = [volt_mv] + [65535] * 9
        used_mah = int((1.0 - frac) * 5000)
        self._emit(
            E_BATTERY_STATUS,
            (
                0,
                mavlink.MAV_BATTERY_FUNCTION_ALL,
                mavlink.MAV_BATTERY_TYPE_LIPO,
                32767,
                voltages,
                current_ca,
                used_mah,
                -1,
                int(round(frac * 100)),
                0,
                mavlink.MAV_BATTERY_CHARGE_STATE_OK,
                [0, 0, 0, 0],
                0,
                0,
            ),
        )

    def _current_mode(self, v: VehicleView) -> None:
        """The mode flown and the mode the user chose (still Offboard during the offboard-loss
        failsafe, as observed)."""
        ap = self.ap
        std = _STANDARD_MODE.get(ap.mode, mavlink.MAV_STANDARD_MODE_NON_STANDARD)
        self._emit(E_CURRENT_MODE, (std, ap.mode.custom_mode, ap.user_mode.custom_mode))

    def _home_position(self, v: VehicleView) -> None:
        lat, lon, alt = v.home_geodetic
        h = enu_ned(self.home_enu - self.origin_enu)
        self._emit(
            E_HOME_POSITION,
            (
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round(alt * 1000)),
                float(h[0]),
                float(h[1]),
                float(h[2]),
                (1.0, 0.0, 0.0, 0.0),
                0.0,
                0.0,
                0.0,
                v.usec,
            ),
        )

    def _vibration(self, v: VehicleView) -> None:
        vib = 0.02 + 0.3 * v.tel[tm.T_THRUST] if self.ap.armed else 0.01
        self._emit(E_VIBRATION, (v.usec, vib, vib, vib, 0, 0, 0))

    def _autopilot_version(self, v: VehicleView | None) -> None:
        self._emit(
            E_AUTOPILOT_VERSION,
            (
                PX4_CAPABILITIES,
                PX4_FLIGHT_SW_VERSION,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0,
                0,
                1000 + self.system_id,
                [0] * 18,
            ),
        )

    def _protocol_version(self, v: VehicleView | None) -> None:
        """MAVLink 2 (200), supporting 1.0-2.0 (observed on PX4 v1.16)."""
        self._emit(E_PROTOCOL_VERSION, (200, 100, 200, [0] * 8, [0] * 8))
