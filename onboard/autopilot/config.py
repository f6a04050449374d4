"""Settings of the autopilot link: one frozen object, checked when built.

Errors are ``ValueError`` naming the field (``onboard.config.from_mapping`` turns them into
``ConfigError`` with the key path when the object comes from a file).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Vec3 = tuple[float, float, float]

DEFAULT_TELEMETRY_RATES_HZ: tuple[tuple[str, float], ...] = (
    ("LOCAL_POSITION_NED", 50.0),
    ("ATTITUDE", 50.0),
    ("EXTENDED_SYS_STATE", 5.0),
    ("SYS_STATUS", 5.0),
)

# Streams of PX4's onboard link profile that the service never reads (its receiver skips them
# undecoded): turned off at connect with SET_MESSAGE_INTERVAL(-1), which PX4 honours for every
# stream but HEARTBEAT (mavlink_receiver.cpp, set_message_interval: a negative interval stops the
# stream). About 265 of PX4's ~380 messages/s on that link; both ends then spend less on them.
# The messages the links read (HEARTBEAT, LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE,
# SYS_STATUS, HOME_POSITION, COMMAND_ACK, ...) can never be listed here.
DEFAULT_TELEMETRY_OFF: tuple[str, ...] = (
    "ATTITUDE_QUATERNION",
    "HIGHRES_IMU",
    "GLOBAL_POSITION_INT",
    "ODOMETRY",
    "TIMESYNC",
    "ALTITUDE",
    "DISTANCE_SENSOR",
    "ATTITUDE_TARGET",
    "POSITION_TARGET_LOCAL_NED",
    "SERVO_OUTPUT_RAW",
    "VFR_HUD",
    "GPS_RAW_INT",
    "MISSION_CURRENT",
    "ESTIMATOR_STATUS",
    "SYSTEM_TIME",
    "SCALED_PRESSURE",
    "LINK_NODE_STATUS",
    "BATTERY_STATUS",
    "CURRENT_MODE",
    "VIBRATION",
)
TELEMETRY_NEEDED: frozenset[str] = frozenset(
    {
        "HEARTBEAT",
        "LOCAL_POSITION_NED",
        "ATTITUDE",
        "EXTENDED_SYS_STATE",
        "SYS_STATUS",
        "HOME_POSITION",
        "COMMAND_ACK",
        "MESSAGE_INTERVAL",
        "AUTOPILOT_VERSION",
        "PROTOCOL_VERSION",
        "STATUSTEXT",
    }
)
"""Messages a link reads: never turned off."""

MAX_ABS_COORD_M = 10_000.0
"""Largest geofence / origin coordinate (the swarm bus's bound too)."""
MAX_SPEED_M_S = 30.0
MAX_ACCEL_M_S2 = 30.0

BAUD_RATES = (
    9600,
    19200,
    38400,
    57600,
    115200,
    230400,
    460800,
    500000,
    576000,
    921600,
    1000000,
    1152000,
    1500000,
    2000000,
    2500000,
    3000000,
    3500000,
    4000000,
)


def _positive(name: str, v: float) -> None:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name}: expected a number > 0, got {v!r}")


def _non_negative(name: str, v: float) -> None:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name}: expected a number >= 0, got {v!r}")


def _int_range(name: str, v: int, lo: int, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not (lo <= v <= hi):
        raise ValueError(f"{name}: expected an integer in [{lo}, {hi}], got {v!r}")


# Messages PX4 v1.16 streams that pymavlink 2.4.50's dialect files lack (LINK_NODE_STATUS, 1 Hz
# on the onboard link; id from the MAVLink definitions)
_EXTRA_MESSAGE_IDS = {"LINK_NODE_STATUS": 8}


def message_id(name: str) -> int | None:
    """The id of a MAVLink message by name: the common dialect, then ``development`` (what PX4
    is built with: CURRENT_MODE, ...), then the few PX4 sends that pymavlink lacks (None if
    unknown)."""
    from pymavlink.dialects.v20 import common, development

    for dialect in (common, development):
        v = getattr(dialect, f"MAVLINK_MSG_ID_{name}", None)
        if isinstance(v, int):
            return v
    return _EXTRA_MESSAGE_IDS.get(name)


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection url."""

    kind: Literal["udpin", "udpout", "serial"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0


def parse_url(url: str, baud: int = 921600) -> Endpoint:
    """``udpin://HOST:PORT`` (or ``udp://``): bind there and answer whoever the autopilot is
    (PX4's API link, MAVSDK's default); ``udpout://HOST:PORT``: send there from an ephemeral
    port; ``serial:///dev/ttyTHS0`` or ``serial:///dev/ttyTHS0:921600`` (the baud in the url
    wins over ``baud``)."""
    if not isinstance(url, str):
        raise ValueError(f"url: expected a string, got {url!r}")
    scheme, sep, rest = url.partition("://")
    if not sep:
        raise ValueError(f"url: expected SCHEME://..., got {url!r}")
    if scheme in ("udp", "udpin", "udpout"):
        host, colon, port_s = rest.rpartition(":")
        if not colon or not port_s.isdigit():
            raise ValueError(f"url: expected {scheme}://HOST:PORT, got {url!r}")
        port = int(port_s)
        if not (0 <= port <= 65535) or (scheme == "udpout" and port == 0):
            raise ValueError(f"url: port out of range in {url!r}")
        return Endpoint("udpout" if scheme == "udpout" else "udpin", host or "0.0.0.0", port)
    if scheme == "serial":
        device = rest
        b = baud
        head, colon, tail = rest.rpartition(":")
        if colon and tail.isdigit():
            device, b = head, int(tail)
        if not device.startswith("/"):
            raise ValueError(f"url: expected serial:///dev/DEVICE[:BAUD], got {url!r}")
        if b not in BAUD_RATES:
            raise ValueError(f"baud: expected one of {list(BAUD_RATES)}, got {b!r}")
        return Endpoint("serial", device=device, baud=b)
    raise ValueError(f"url: expected udpin://, udpout://, udp:// or serial://, got {url!r}")


@dataclass(frozen=True)
class LinkConfig:
    """Everything the autopilot link needs. Positions are ENU metres in the service's frame."""

    url: str = "udpin://127.0.0.1:14540"
    """See ``parse_url``. PX4 multi-vehicle: vehicle i's API link is UDP 14540 + i."""
    implementation: Literal["pymavlink", "mavsdk"] = "pymavlink"
    baud: int = 921600
    system_id: int = 1
    """The autopilot's MAVLink system id (PX4 multi-vehicle: i + 1)."""
    autopilot_component_id: int = 1
    source_system_id: int | None = None
    """This link's system id; None: the autopilot's (PX4 registers an onboard controller only
    from its own system id)."""
    component_id: int = 191
    """MAV_COMP_ID_ONBOARD_COMPUTER."""

    setpoint_rate_hz: float = 50.0
    heartbeat_rate_hz: float = 1.0
    link_timeout_s: float = 1.0
    """No valid message from the autopilot for this long: the link is lost (PX4 sends hundreds
    a second; the telemetry rates requested below guarantee tens)."""
    heartbeat_timeout_s: float = 3.0
    """No HEARTBEAT for this long: lost too. PX4's heartbeat is fixed at 1 Hz (it refuses a new
    interval), so a 1 s heartbeat timeout would fire on every late heartbeat."""
    connect_timeout_s: float = 10.0

    ack_timeout_s: float = 0.5
    """Per transmission of a command."""
    max_transmissions: int = 3
    in_progress_timeout_s: float = 10.0
    """After an IN_PROGRESS acknowledgement, the wait for the final one."""
    command_retries: int = 3
    """Retries after TEMPORARILY_REJECTED (then a CommandError)."""
    retry_delay_s: float = 0.5
    duplicate_ack_window_s: float = 0.2
    """A command is not sent again until this long after its last acknowledgement, so that
    PX4's second ACK of the previous one (10 ms later) is never taken for the new one's."""
    commanded_mode_window_s: float = 5.0
    """A mode change this long after the link asked for that mode counts as commanded."""
    telemetry_rates_hz: tuple[tuple[str, float], ...] = DEFAULT_TELEMETRY_RATES_HZ
    telemetry_off: tuple[str, ...] = ()
    """Streams turned off at connect (SET_MESSAGE_INTERVAL -1), e.g. ``DEFAULT_TELEMETRY_OFF``:
    the flight service's choice (``autopilot.trim_telemetry``); none by default here, since
    another program on the same MAVLink instance may read them."""

    local_origin_enu_m: Vec3 = (0.0, 0.0, 0.0)
    """Where PX4's local-frame origin lies in the service's ENU frame."""
    geofence_min_enu_m: Vec3 = (-50.0, -50.0, -1.0)
    geofence_max_enu_m: Vec3 = (50.0, 50.0, 10.0)
    max_speed_m_s: float = 3.0
    """Largest setpoint velocity (norm) the guard lets through."""
    max_accel_m_s2: float = 5.0
    stop_streaming_on_offboard_loss: bool = True
    """Yield at once when the vehicle leaves OFFBOARD without this link asking."""

    signing_key_file: str | None = None
    """MAVLink 2 signing key (32 raw bytes or 64 hex digits, mode 0600; see
    ``onboard.autopilot.signing``): every message this link sends is signed. Only the pymavlink
    implementation signs (MAVSDK 4.x cannot). Autopilots that sign: PX4 v1.17+ (not v1.16)."""
    signing_required: bool | None = None
    """With a key: refuse unsigned or wrongly signed telemetry (counted) and refuse to connect
    to an autopilot that does not sign. None: True when a key is given. False: sign, but accept
    unsigned telemetry (counted; for a migration only)."""
    signing_link_id: int = 1
    """The link id in this link's signatures (0..255; PX4's own links use their own)."""

    def __post_init__(self) -> None:
        parse_url(self.url, self.baud)
        if self.implementation not in ("pymavlink", "mavsdk"):
            raise ValueError(
                f"implementation: expected 'pymavlink' or 'mavsdk', got {self.implementation!r}"
            )
        if self.baud not in BAUD_RATES:
            raise ValueError(f"baud: expected one of {list(BAUD_RATES)}, got {self.baud!r}")
        _int_range("system_id", self.system_id, 1, 255)
        _int_range("autopilot_component_id", self.autopilot_component_id, 1, 255)
        if self.source_system_id is not None:
            _int_range("source_system_id", self.source_system_id, 1, 255)
        _int_range("component_id", self.component_id, 1, 255)
        if self.component_id == self.autopilot_component_id and (
            self.source_system_id in (None, self.system_id)
        ):
            raise ValueError("component_id: must differ from the autopilot's component id")
        for name in (
            "setpoint_rate_hz",
            "heartbeat_rate_hz",
            "link_timeout_s",
            "heartbeat_timeout_s",
            "connect_timeout_s",
            "ack_timeout_s",
            "in_progress_timeout_s",
            "max_speed_m_s",
            "max_accel_m_s2",
        ):
            _positive(name, getattr(self, name))
        if self.setpoint_rate_hz > 500.0:
            raise ValueError(f"setpoint_rate_hz: expected at most 500, got {self.setpoint_rate_hz}")
        if self.setpoint_rate_hz < 2.0:
            raise ValueError(
                f"setpoint_rate_hz: expected at least 2 (PX4 needs > 2 Hz), got "
                f"{self.setpoint_rate_hz}"
            )
        for name in ("retry_delay_s", "duplicate_ack_window_s", "commanded_mode_window_s"):
            _non_negative(name, getattr(self, name))
        _int_range("max_transmissions", self.max_transmissions, 1, 20)
        _int_range("command_retries", self.command_retries, 0, 50)
        for i, item in enumerate(self.telemetry_rates_hz):
            if len(item) != 2 or not isinstance(item[0], str):
                raise ValueError(f"telemetry_rates_hz[{i}]: expected [MESSAGE_NAME, Hz]")
            _positive(f"telemetry_rates_hz[{i}]", item[1])
            if message_id(item[0]) is None:
                raise ValueError(f"telemetry_rates_hz[{i}]: unknown MAVLink message {item[0]!r}")
        rated = {item[0] for item in self.telemetry_rates_hz}
        for i, name in enumerate(self.telemetry_off):
            if not isinstance(name, str) or message_id(name) is None:
                raise ValueError(f"telemetry_off[{i}]: unknown MAVLink message {name!r}")
            if name in TELEMETRY_NEEDED or name in rated:
                raise ValueError(f"telemetry_off[{i}]: {name} is read by the link, cannot be off")
        for name in ("local_origin_enu_m", "geofence_min_enu_m", "geofence_max_enu_m"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(float(x)) for x in v):
                raise ValueError(f"{name}: expected 3 finite numbers, got {v!r}")
            if any(abs(float(x)) > MAX_ABS_COORD_M for x in v):
                raise ValueError(
                    f"{name}: expected coordinates within {MAX_ABS_COORD_M:g} m, got {v!r}"
                )
        if self.max_speed_m_s > MAX_SPEED_M_S:
            raise ValueError(
                f"max_speed_m_s: expected at most {MAX_SPEED_M_S:g}, got {self.max_speed_m_s}"
            )
        if self.max_accel_m_s2 > MAX_ACCEL_M_S2:
            raise ValueError(
                f"max_accel_m_s2: expected at most {MAX_ACCEL_M_S2:g}, got {self.max_accel_m_s2}"
            )
        for k, axis in enumerate("xyz"):
            if not self.geofence_min_enu_m[k] < self.geofence_max_enu_m[k]:
                raise ValueError(
                    f"geofence_max_enu_m: {axis} must exceed geofence_min_enu_m's "
                    f"({self.geofence_max_enu_m[k]} <= {self.geofence_min_enu_m[k]})"
                )

        _int_range("signing_link_id", self.signing_link_id, 0, 255)
        if self.signing_key_file is not None:
            if self.implementation != "pymavlink":
                raise ValueError(
                    "signing_key_file: the mavsdk implementation cannot sign (MAVSDK 4.x has no "
                    "MAVLink signing API); use implementation: pymavlink"
                )
            from onboard.autopilot.signing import load_signing_key

            load_signing_key(self.signing_key_file)  # checks permissions and format now
        elif self.signing_required:
            raise ValueError("signing_required: needs signing_key_file")
        if self.signing_required is not None and not isinstance(self.signing_required, bool):
            raise ValueError(
                f"signing_required: expected true or false, got {self.signing_required!r}"
            )

    @property
    def requires_signing(self) -> bool:
        """True if this link refuses unsigned telemetry (a key given, not opted out)."""
        return self.signing_key_file is not None and self.signing_required is not False

    @property
    def endpoint(self) -> Endpoint:
        return parse_url(self.url, self.baud)

    @property
    def own_system_id(self) -> int:
        return self.system_id if self.source_system_id is None else self.source_system_id

    @property
    def setpoint_period_s(self) -> float:
        return 1.0 / self.setpoint_rate_hz
