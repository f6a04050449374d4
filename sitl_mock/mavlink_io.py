"""The API link of one mock vehicle: MAVLink 2 over UDP, as PX4 presents it to a companion.

NED lives here and only here: incoming setpoints are resolved into ENU by
``setpoint_from_local_ned`` and outgoing telemetry is converted with ``sitl_mock.frames``.

- Socket: bound to ``(host, local_port)`` (PX4: 14580 + i); telemetry goes to the partner,
  initially ``(host, client_port)`` (PX4: 14540 + i), then whoever last sent a valid message
  (PX4's UDP behaviour, so MAVSDK's ``udpin://`` and pymavlink's ``udpin:`` both work).
- Each datagram is parsed on its own (a garbage datagram cannot swallow the next one); bad
  bytes, bad CRCs, unknown messages and malformed fields are counted and dropped.
- Signing (optional, per vehicle): outgoing messages are signed with the key; when signing is
  required, unsigned or wrongly signed messages are dropped (only RADIO_STATUS may be
  unsigned, as the MAVLink signing rules allow), so unsigned commands are never executed or
  acknowledged.
- Streams at PX4's observed rates (simulated time), changeable with SET_MESSAGE_INTERVAL;
  messages due in the same tick share a datagram, as PX4 packs them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from sitl_mock import dynamics as dyn
from sitl_mock.autopilot import (
    AUTO_MODES,
    Autopilot,
    Mode,
    OffboardSetpoint,
    Result,
    StatusEvent,
)
from sitl_mock.frames import (
    enu_ned,
    euler_zyx,
    geodetic_from_enu,
    quaternion_from_matrix,
    rotation_ned_frd,
    yaw_enu_ned,
)

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
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
ARM_FORCE_MAGIC = 21196

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (1 = ignore)
IGNORE_PX, IGNORE_PY, IGNORE_PZ = 1, 2, 4
IGNORE_VX, IGNORE_VY, IGNORE_VZ = 8, 16, 32
IGNORE_AX, IGNORE_AY, IGNORE_AZ = 64, 128, 256
FORCE_SETPOINT = 512
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048

FRAME_LOCAL_NED = 1
FRAME_LOCAL_OFFSET_NED = 7
FRAME_BODY_NED = 8
FRAME_BODY_OFFSET_NED = 9
FRAME_BODY_FRD = 12

PX4_BASE_MODE_AUTO = 16 | 8 | 4  # stabilize, guided, auto
PX4_BASE_MODE_OFFBOARD = 16
PX4_BASE_MODE_POSCTL = 64 | 16

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
)
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
RC_RECEIVER = mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER

# Default stream rates [Hz, simulated time]: what PX4 v1.16 SITL sends on its API link.
PX4_STREAM_RATES_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 100.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mavlink.MAVLINK_MSG_ID_TIMESYNC: 10.0,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 10.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: 10.0,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 10.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 10.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 8.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
}
# one-off messages REQUEST_MESSAGE can ask for besides the streams
_REQUESTABLE_EXTRA = (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)

MAX_DATAGRAM_BYTES = 1200
_SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01T00:00:00Z


def signing_timestamp_now() -> int:
    """MAVLink 2 signing timestamp: 10 us units since 2015-01-01 (wall clock)."""
    return int((time.time() - _SIGNING_EPOCH_UNIX_S) * 100_000)


def message_id_by_name(name: str) -> int:
    """MAVLINK_MSG_ID of a message name such as ``"ATTITUDE"``."""
    try:
        return int(getattr(mavlink, f"MAVLINK_MSG_ID_{name.upper()}"))
    except AttributeError as e:
        raise ValueError(f"unknown MAVLink message {name!r}") from e


# ---------------------------------------------------------------------------------------------
# Setpoints: MAVLink NED -> ENU world


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
) -> OffboardSetpoint | None:
    """Resolve a SET_POSITION_TARGET_LOCAL_NED into an absolute ENU setpoint.

    A component counts when its ignore bit is clear and its value finite. Frames:
    LOCAL_NED (positions relative to the vehicle's local origin ``origin_enu``), LOCAL_OFFSET_NED
    (positions relative to the current ``position_enu``), BODY_NED / BODY_OFFSET_NED (x forward,
    y right, z down, rotated by the current heading; positions relative to the current
    position). With the FORCE bit set, accelerations are ignored (forces are not supported).
    Yaw is absolute in every frame; a NED yaw rate (clockwise) becomes an ENU rate
    (counter-clockwise). Returns None for an unsupported frame.
    """
    if frame not in (
        FRAME_LOCAL_NED,
        FRAME_LOCAL_OFFSET_NED,
        FRAME_BODY_NED,
        FRAME_BODY_OFFSET_NED,
    ):
        return None

    def pick(values: tuple[float, float, float], bits: tuple[int, int, int]) -> np.ndarray:
        out = np.full(3, np.nan)
        for k in range(3):
            v = float(values[k])
            if not (type_mask & bits[k]) and math.isfinite(v):
                out[k] = v
        return out

    p = pick(pos_ned, (IGNORE_PX, IGNORE_PY, IGNORE_PZ))
    v = pick(vel_ned, (IGNORE_VX, IGNORE_VY, IGNORE_VZ))
    a = pick(acc_ned, (IGNORE_AX, IGNORE_AY, IGNORE_AZ))
    if type_mask & FORCE_SETPOINT:
        a[:] = np.nan
    if frame in (FRAME_BODY_NED, FRAME_BODY_OFFSET_NED):
        psi = yaw_enu_ned(yaw_enu)  # heading in NED
        c, s = math.cos(psi), math.sin(psi)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # body (FRD-level) -> NED
        p, v, a = rot @ p, rot @ v, rot @ a  # NaN in x or y spreads to both, as it should
    if frame == FRAME_LOCAL_NED:
        pos_enu = origin_enu + enu_ned(p)
    else:
        pos_enu = position_enu + enu_ned(p)
    yaw = math.nan
    yaw_rate = math.nan
    if not (type_mask & IGNORE_YAW) and math.isfinite(yaw_ned):
        yaw = yaw_enu_ned(yaw_ned)
    if not (type_mask & IGNORE_YAW_RATE) and math.isfinite(yaw_rate_ned):
        yaw_rate = -yaw_rate_ned
    return OffboardSetpoint(pos_enu, enu_ned(v), enu_ned(a), yaw, yaw_rate)


# ---------------------------------------------------------------------------------------------
# Per-tick view of a vehicle, with the MAVLink quantities derived on demand


class VehicleView:
    """One vehicle at one tick: rows of the fleet arrays plus derived NED quantities."""

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

    @property
    def boot_ms(self) -> int:
        return int(self.t_s * 1000.0) & 0xFFFFFFFF

    @property
    def usec(self) -> int:
        return int(self.t_s * 1e6)

    @cached_property
    def est_enu(self) -> np.ndarray:
        return self.s[dyn.S_P : dyn.S_P + 3] + self.s[dyn.S_E : dyn.S_E + 3]

    @cached_property
    def vel_enu(self) -> np.ndarray:
        return self.s[dyn.S_V : dyn.S_V + 3].copy()

    @cached_property
    def pos_ned(self) -> np.ndarray:
        return enu_ned(self.est_enu - self.origin_enu)

    @cached_property
    def vel_ned(self) -> np.ndarray:
        return enu_ned(self.vel_enu)

    @cached_property
    def r_ned_frd(self) -> np.ndarray:
        return rotation_ned_frd(self.att[dyn.A_R : dyn.A_R + 9].reshape(3, 3))

    @cached_property
    def euler(self) -> tuple[float, float, float]:
        return euler_zyx(self.r_ned_frd)

    @cached_property
    def quaternion(self) -> tuple[float, float, float, float]:
        return quaternion_from_matrix(self.r_ned_frd)

    @cached_property
    def rates_frd(self) -> np.ndarray:
        w = self.att[dyn.A_OMEGA : dyn.A_OMEGA + 3]
        return np.array([w[0], -w[1], -w[2]])

    @cached_property
    def specific_force_frd(self) -> np.ndarray:
        f = self.att[dyn.A_SPECIFIC : dyn.A_SPECIFIC + 3]
        return np.array([f[0], -f[1], -f[2]])

    @cached_property
    def geodetic(self) -> tuple[float, float, float]:
        return geodetic_from_enu(self.est_enu, *self.geo_ref)

    @cached_property
    def home_geodetic(self) -> tuple[float, float, float]:
        return geodetic_from_enu(self.home_enu, *self.geo_ref)

    @property
    def relative_alt_m(self) -> float:
        return float(self.est_enu[2] - self.home_enu[2])

    @property
    def heading_deg(self) -> float:
        return math.degrees(self.euler[2]) % 360.0


# ---------------------------------------------------------------------------------------------
# The link


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink 2 signing of one vehicle: 32-byte key; ``require``: refuse unsigned messages."""

    key: bytes
    require: bool = True

    def __post_init__(self) -> None:
        if len(self.key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")


@dataclass
class LinkStats:
    rx_datagrams: int = 0
    rx_messages: int = 0
    rx_bad: int = 0
    rx_rejected_unsigned: int = 0
    rx_ignored: int = 0
    tx_messages: int = 0
    tx_datagrams: int = 0
    tx_bytes: int = 0
    setpoints: int = 0
    setpoints_malformed: int = 0
    commands: int = 0


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
}
_LOSS_ACTION_CODE = {"hold": 5, "land": 4, "rtl": 2}
_LOSS_ACTION_FROM_CODE = {0: "hold", 5: "hold", 4: "land", 2: "rtl"}


def _float_bits_of_int(v: int) -> float:
    """PX4's bytewise parameter encoding: the int32's bytes read as a float32."""
    return float(struct.unpack("<f", struct.pack("<i", int(v)))[0])


def _int_of_float_bits(f: float) -> int:
    return int(struct.unpack("<i", struct.pack("<f", float(f)))[0])


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
        accept_setup_signing: bool = True,
        stream_rates_hz: dict[int, float] | None = None,
        duplicate_mode_ack: bool = True,
        batch_datagrams: bool = True,
    ) -> None:
        self.system_id = int(system_id)
        self.ap = autopilot
        self.host = host
        self.client_port = int(client_port)
        self.local_port = int(local_port)
        self.partner: tuple[str, int] = (host, self.client_port)
        self.origin_enu = np.asarray(origin_enu, dtype=np.float64).reshape(3)
        self.home_enu = np.asarray(home_enu, dtype=np.float64).reshape(3)
        self.geo_ref = geo_ref
        self.accept_setup_signing = accept_setup_signing
        self.duplicate_mode_ack = duplicate_mode_ack
        self.batch_datagrams = batch_datagrams
        self.stats = LinkStats()
        self.mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=1)
        self.mav.robust_parsing = True
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
        self._next_due: dict[int, float] = {m: 0.0 for m in self.intervals_s}
        self._out: list[bytes] = []
        self._deferred: list[Callable[[], None]] = []
        self._encoders: dict[int, Callable[[VehicleView], Any]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: self._highres_imu,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position_int,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mavlink.MAVLINK_MSG_ID_ODOMETRY: self._odometry,
            mavlink.MAVLINK_MSG_ID_TIMESYNC: self._timesync_request,
            mavlink.MAVLINK_MSG_ID_ALTITUDE: self._altitude,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: self._attitude_target,
            mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: self._position_target,
            mavlink.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw_int,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: self._battery_status,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }
        self.sock: socket.socket | None = None
        self.view: VehicleView | None = None
        self.gcs_heartbeats = 0

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

    # ---- signing -------------------------------------------------------------------------
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
        mav = self.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        rejected_before = mav.signing.reject_count
        try:
            msgs = mav.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - a parser failure must never stop the vehicle
            msgs = []
            st.rx_bad += 1
        st.rx_rejected_unsigned += mav.signing.reject_count - rejected_before
        for msg in msgs:
            if msg.get_type() == "BAD_DATA" or msg.get_type().startswith("UNKNOWN"):
                st.rx_bad += 1
                continue
            st.rx_messages += 1
            if addr != self.partner:
                log.info("vehicle %d: partner %s:%d", self.system_id, addr[0], addr[1])
                self.partner = (addr[0], addr[1])
            try:
                self.handle(msg)
            except Exception:  # noqa: BLE001 - malformed content must never stop the vehicle
                st.rx_bad += 1
                log.debug(
                    "vehicle %d: failed to handle %s", self.system_id, msg.get_type(), exc_info=True
                )

    def handle(self, msg: Any) -> None:
        mid = msg.get_msgId()
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
                self.stats.rx_ignored += 1
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
                self.stats.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED:
            if self._for_me(msg.target_system, msg.target_component):
                self._setpoint(msg)
            else:
                self.stats.rx_ignored += 1
        elif mid == mavlink.MAVLINK_MSG_ID_SET_MODE:
            if msg.target_system == self.system_id:
                self._set_mode_message(msg)
        elif mid == mavlink.MAVLINK_MSG_ID_TIMESYNC:
            if msg.tc1 == 0:
                self._queue(self.mav.timesync_encode(self._now_ns(), msg.ts1))
        elif mid == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            self.gcs_heartbeats += 1
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            if self._for_me(msg.target_system, msg.target_component):
                for i, name in enumerate(_PARAMS):
                    self._queue(self._param_value(name, i))
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ:
            if self._for_me(msg.target_system, msg.target_component):
                self._param_read(msg)
        elif mid == mavlink.MAVLINK_MSG_ID_PARAM_SET:
            if self._for_me(msg.target_system, msg.target_component):
                self._param_set(msg)
        elif mid == mavlink.MAVLINK_MSG_ID_SETUP_SIGNING:
            if self.accept_setup_signing and self._for_me(msg.target_system, msg.target_component):
                key = bytes(msg.secret_key)
                if key == bytes(32):
                    self.set_signing(None)
                    log.warning("vehicle %d: signing disabled by SETUP_SIGNING", self.system_id)
                else:
                    self.set_signing(SigningConfig(key, require=True))
                    self.mav.signing.timestamp = max(
                        self.mav.signing.timestamp, int(msg.initial_timestamp)
                    )
                    log.warning("vehicle %d: signing key set by SETUP_SIGNING", self.system_id)
        else:
            self.stats.rx_ignored += 1

    def _for_me(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.system_id) and target_component in (0, 1)

    def _now_ns(self) -> int:
        return int((self.view.t_s if self.view is not None else 0.0) * 1e9)

    @property
    def _t(self) -> float:
        return self.view.t_s if self.view is not None else 0.0

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
            mid = int(p[0]) if math.isfinite(p[0]) else -1
            if mid in self._encoders:
                iv = self.intervals_s.get(mid, math.inf)
                us = -1 if not math.isfinite(iv) else int(round(iv * 1e6))
                result = Result.ACCEPTED
                after.append(lambda: self._queue(self.mav.message_interval_encode(mid, us)))
            else:
                result = Result.DENIED
        elif command == CMD_REQUEST_MESSAGE:
            mid = int(p[0]) if math.isfinite(p[0]) else -1
            if mid in self._encoders and self.view is not None:
                result = Result.ACCEPTED
                view = self.view
                after.append(lambda: self._queue(self._encoders[mid](view)))
            else:
                result = Result.DENIED
        elif command == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result = Result.ACCEPTED
            after.append(lambda: self._queue(self._autopilot_version(None)))
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
        mm = int(main) if math.isfinite(main) else -1
        sm = int(sub) if math.isfinite(sub) else 0
        return self.ap.command_set_mode(self._t, Mode.from_main_sub(mm, sm))

    def _set_mode_message(self, msg: Any) -> None:
        if not msg.base_mode & 1:
            result = int(Result.DENIED)
        else:
            result = int(self.ap.command_set_mode(self._t, Mode.from_custom_mode(msg.custom_mode)))
        self._ack(CMD_DO_SET_MODE, result, msg.get_srcSystem(), msg.get_srcComponent())
        self._drain_events()

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not (math.isfinite(msg_id) and math.isfinite(interval_us)):
            return Result.DENIED
        mid = int(msg_id)
        if mid not in self._encoders or mid == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return Result.DENIED
        if interval_us < 0:
            self.intervals_s[mid] = math.inf
        elif interval_us == 0:
            r = self.default_rates_hz.get(mid, 0.0)
            self.intervals_s[mid] = 1.0 / r if r > 0 else math.inf
        else:
            self.intervals_s[mid] = interval_us * 1e-6
        self._next_due[mid] = self._t
        return Result.ACCEPTED

    def _ack(self, command: int, result: int, src_sys: int, src_comp: int) -> None:
        self._queue(self.mav.command_ack_encode(command, result, 0, 0, src_sys, src_comp))

    @property
    def home_amsl_m(self) -> float:
        return self.geo_ref[2] + float(self.home_enu[2])

    # ---- setpoints -----------------------------------------------------------------------
    def _setpoint(self, msg: Any) -> None:
        st = self.stats
        view = self.view
        pos = view.est_enu if view is not None else self.home_enu
        yaw = float(view.s[dyn.S_YAW]) if view is not None else 0.0
        sp = setpoint_from_local_ned(
            int(msg.type_mask),
            int(msg.coordinate_frame),
            (msg.x, msg.y, msg.z),
            (msg.vx, msg.vy, msg.vz),
            (msg.afx, msg.afy, msg.afz),
            msg.yaw,
            msg.yaw_rate,
            self.origin_enu,
            pos,
            yaw,
        )
        if sp is None or not self.ap.on_setpoint(self._t, sp):
            st.setpoints_malformed += 1
            return
        st.setpoints += 1

    # ---- parameters ----------------------------------------------------------------------
    def _param_value(self, name: str, index: int) -> Any:
        field, is_int = _PARAMS[name]
        value = getattr(self.ap.params, field)
        if is_int:
            code = _LOSS_ACTION_CODE[value] if field == "offboard_loss_action" else int(value)
            return self.mav.param_value_encode(
                name.encode(),
                _float_bits_of_int(code),
                mavlink.MAV_PARAM_TYPE_INT32,
                len(_PARAMS),
                index,
            )
        return self.mav.param_value_encode(
            name.encode(), float(value), mavlink.MAV_PARAM_TYPE_REAL32, len(_PARAMS), index
        )

    def _param_read(self, msg: Any) -> None:
        names = list(_PARAMS)
        pid = (
            msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        )
        pid = pid.rstrip("\x00")
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._queue(self._param_value(names[msg.param_index], msg.param_index))
        elif pid in _PARAMS:
            self._queue(self._param_value(pid, names.index(pid)))

    def _param_set(self, msg: Any) -> None:
        pid = (
            msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        )
        pid = pid.rstrip("\x00")
        if pid not in _PARAMS:
            return
        field, is_int = _PARAMS[pid]
        value: Any
        if is_int:
            code = (
                _int_of_float_bits(msg.param_value)
                if msg.param_type == mavlink.MAV_PARAM_TYPE_INT32
                else int(round(msg.param_value))
            )
            value = _LOSS_ACTION_FROM_CODE.get(code)
        else:
            value = float(msg.param_value)
        if value is not None:
            try:
                self.ap.params = dataclasses.replace(self.ap.params, **{field: value})
            except (ValueError, TypeError):
                pass  # invalid: keep the value; the reply tells the sender what is in force
        self._queue(self._param_value(pid, list(_PARAMS).index(pid)))

    # ---- outgoing ------------------------------------------------------------------------
    def _queue(self, msg: Any) -> None:
        mav = self.mav
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self._out.append(buf)
        self.stats.tx_messages += 1

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
        self._queue(self.mav.statustext_encode(int(severity), text.encode()[:50]))

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
        for f in self._deferred:
            f()
        self._deferred.clear()
        self._drain_events()
        t = view.t_s
        for mid, interval in self.intervals_s.items():
            if not math.isfinite(interval):
                continue
            due = self._next_due[mid]
            if t + 1e-9 >= due:
                self._queue(self._encoders[mid](view))
                nxt = due + interval
                self._next_due[mid] = nxt if nxt > t else t + interval
        self.flush()

    # ---- encoders ------------------------------------------------------------------------
    def _heartbeat(self, v: VehicleView) -> Any:
        ap = self.ap
        mode = ap.mode
        base = 1
        if mode in AUTO_MODES:
            base |= PX4_BASE_MODE_AUTO
        elif mode == Mode.OFFBOARD:
            base |= PX4_BASE_MODE_OFFBOARD
        elif mode == Mode.POSCTL:
            base |= PX4_BASE_MODE_POSCTL
        if ap.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            status = mavlink.MAV_STATE_CRITICAL if ap.failsafe else mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, mode.custom_mode, status, 3
        )

    def _sys_status(self, v: VehicleView) -> Any:
        ap = self.ap
        present = SENSORS | PREARM | (RC_RECEIVER if ap.params.rc_present else 0)
        health = present & ~PREARM
        if not ap.booted(v.t_s):
            health &= ~(
                mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
                | mavlink.MAV_SYS_STATUS_SENSOR_GPS
                | mavlink.MAV_SYS_STATUS_AHRS
            )
        if ap.ready(v.t_s):
            health |= PREARM
        volt_mv, current_ca = self._battery_electrics(v)
        return self.mav.sys_status_encode(
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
        )

    def _battery_electrics(self, v: VehicleView) -> tuple[int, int]:
        frac = self.ap.battery_fraction
        volt = 4 * (3.5 + 0.7 * frac)
        thrust = float(v.att[dyn.A_THRUST]) if self.ap.armed else 0.0
        current_a = 0.3 + 20.0 * thrust
        return int(volt * 1000), int(current_a * 100)

    def _attitude(self, v: VehicleView) -> Any:
        r, p, y = v.euler
        w = v.rates_frd
        return self.mav.attitude_encode(v.boot_ms, r, p, y, w[0], w[1], w[2])

    def _attitude_quaternion(self, v: VehicleView) -> Any:
        q = v.quaternion
        w = v.rates_frd
        return self.mav.attitude_quaternion_encode(
            v.boot_ms, q[0], q[1], q[2], q[3], w[0], w[1], w[2], (0.0, 0.0, 0.0, 0.0)
        )

    def _highres_imu(self, v: VehicleView) -> Any:
        f = v.specific_force_frd
        w = v.rates_frd
        mag = v.r_ned_frd.T @ np.array([0.21, 0.015, 0.42])  # a mid-latitude field [gauss]
        alt = v.geodetic[2]
        press = 1013.25 * (1.0 - 2.25577e-5 * alt) ** 5.25588
        return self.mav.highres_imu_encode(
            v.usec,
            f[0],
            f[1],
            f[2],
            w[0],
            w[1],
            w[2],
            mag[0],
            mag[1],
            mag[2],
            press,
            0.0,
            alt,
            25.0,
            0x1FFF,
            0,
        )

    def _global_position_int(self, v: VehicleView) -> Any:
        lat, lon, alt = v.geodetic
        vn = v.vel_ned
        return self.mav.global_position_int_encode(
            v.boot_ms,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            int(round(v.relative_alt_m * 1000)),
            int(round(vn[0] * 100)),
            int(round(vn[1] * 100)),
            int(round(vn[2] * 100)),
            int(round(v.heading_deg * 100)) % 36000,
        )

    def _local_position_ned(self, v: VehicleView) -> Any:
        p = v.pos_ned
        u = v.vel_ned
        return self.mav.local_position_ned_encode(v.boot_ms, p[0], p[1], p[2], u[0], u[1], u[2])

    def _odometry(self, v: VehicleView) -> Any:
        p = v.pos_ned
        q = v.quaternion
        vb = v.r_ned_frd.T @ v.vel_ned
        w = v.rates_frd
        nan21 = [math.nan] + [0.0] * 20
        return self.mav.odometry_encode(
            v.usec,
            FRAME_LOCAL_NED,
            FRAME_BODY_FRD,
            p[0],
            p[1],
            p[2],
            q,
            vb[0],
            vb[1],
            vb[2],
            w[0],
            w[1],
            w[2],
            nan21,
            nan21,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT,
            100,
        )

    def _timesync_request(self, v: VehicleView) -> Any:
        return self.mav.timesync_encode(0, self._now_ns())

    def _altitude(self, v: VehicleView) -> Any:
        alt = v.geodetic[2]
        return self.mav.altitude_encode(
            v.usec,
            alt,
            alt,
            -float(v.pos_ned[2]),
            v.relative_alt_m,
            math.nan,
            float(v.est_enu[2] - v.ground_z),
        )

    def _attitude_target(self, v: VehicleView) -> Any:
        fc = v.s[dyn.S_FCMD : dyn.S_FCMD + 3]
        yaw = float(v.cmd[dyn.C_YAW])
        if not math.isfinite(yaw):
            yaw = float(v.s[dyn.S_YAW])
        r = dyn.rotation_from_thrust(float(fc[0]), float(fc[1]), float(fc[2]), yaw)
        q = quaternion_from_matrix(rotation_ned_frd(r))
        thrust = min(max(float(np.linalg.norm(fc)) / v.f_max, 0.0), 1.0)
        return self.mav.attitude_target_encode(v.boot_ms, 7, q, 0.0, 0.0, 0.0, thrust)

    def _position_target(self, v: VehicleView) -> Any:
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
        return self.mav.position_target_local_ned_encode(
            v.boot_ms,
            FRAME_LOCAL_NED,
            mask,
            pos[0],
            pos[1],
            pos[2],
            vel[0],
            vel[1],
            vel[2],
            acc[0],
            acc[1],
            acc[2],
            yaw_ned,
            -yaw_rate,
        )

    def _vfr_hud(self, v: VehicleView) -> Any:
        u = v.vel_enu
        gs = float(math.hypot(u[0], u[1]))
        throttle = int(round(float(v.att[dyn.A_THRUST]) * 100))
        return self.mav.vfr_hud_encode(
            gs, gs, int(v.heading_deg) % 360, throttle, v.geodetic[2], float(u[2])
        )

    def _gps_raw_int(self, v: VehicleView) -> Any:
        lat, lon, alt = v.geodetic
        u = v.vel_enu
        gs = math.hypot(u[0], u[1])
        cog = int(round((math.degrees(math.atan2(u[0], u[1])) % 360.0) * 100)) % 36000
        return self.mav.gps_raw_int_encode(
            v.usec,
            mavlink.GPS_FIX_TYPE_3D_FIX,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            80,
            120,
            int(round(gs * 100)),
            cog,
            12,
        )

    def _extended_sys_state(self, v: VehicleView) -> Any:
        return self.mav.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_MC, int(self.ap.landed_state())
        )

    def _system_time(self, v: VehicleView) -> Any:
        return self.mav.system_time_encode(int(time.time() * 1e6), v.boot_ms)

    def _battery_status(self, v: VehicleView) -> Any:
        volt_mv, current_ca = self._battery_electrics(v)
        frac = self.ap.battery_fraction
        voltages = [volt_mv] + [65535] * 9
        used_mah = int((1.0 - frac) * 5000)
        return self.mav.battery_status_encode(
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
        )

    def _home_position(self, v: VehicleView) -> Any:
        lat, lon, alt = v.home_geodetic
        h = enu_ned(self.home_enu - self.origin_enu)
        return self.mav.home_position_encode(
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            h[0],
            h[1],
            h[2],
            (1.0, 0.0, 0.0, 0.0),
            0.0,
            0.0,
            0.0,
            v.usec,
        )

    def _autopilot_version(self, v: VehicleView | None) -> Any:
        caps = (
            mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
            | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        )
        version = (1 << 24) | (16 << 16) | (0 << 8) | 255  # 1.16.0 release
        return self.mav.autopilot_version_encode(
            caps,
            version,
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            1000 + self.system_id,
        )
