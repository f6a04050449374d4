"""What the autopilot link hands to the service: ENU values, enums, events, errors, counters.

Nothing here knows NED or MAVLink framing; the values are already converted.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

Vec3 = tuple[float, float, float]


def _vec3(name: str, v: Sequence[float]) -> Vec3:
    try:
        n = len(v)
    except TypeError:
        raise ValueError(f"{name}: expected 3 numbers, got {v!r}") from None
    if n != 3:
        raise ValueError(f"{name}: expected 3 numbers, got {n}")
    return (float(v[0]), float(v[1]), float(v[2]))


class FlightMode(enum.Enum):
    """The autopilot's flight mode, reduced to what the service acts on."""

    UNKNOWN = "unknown"  # no heartbeat yet
    OFFBOARD = "offboard"
    HOLD = "hold"  # PX4 AUTO.LOITER
    POSCTL = "posctl"
    ALTCTL = "altctl"
    MANUAL = "manual"  # also stabilized / acro
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "rtl"
    MISSION = "mission"
    OTHER = "other"


class LandedState(enum.IntEnum):
    """MAV_LANDED_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class CommandResult(enum.Enum):
    """The outcome of a command: a MAV_RESULT, or what happened when none came."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5
    CANCELLED = 6
    TIMEOUT = -1  # no final acknowledgement in time
    LINK_DOWN = -2  # not sent: the link is lost or closed

    @staticmethod
    def from_mav_result(value: int) -> CommandResult:
        for r in CommandResult:
            if r.value == value and value >= 0:
                return r
        return CommandResult.FAILED


class LinkError(RuntimeError):
    """The link cannot do what was asked (cannot open, not connected, lost, closed)."""


class CommandError(RuntimeError):
    """A command was not accepted: names the command, the result and the attempts."""

    def __init__(self, command: str, result: CommandResult, attempts: int, detail: str = ""):
        self.command = command
        self.result = result
        self.attempts = attempts
        self.detail = detail
        text = f"{command}: {result.name} after {attempts} attempt{'s' if attempts != 1 else ''}"
        super().__init__(text + (f" ({detail})" if detail else ""))


@dataclass(frozen=True)
class Setpoint:
    """One setpoint in the service's ENU frame (metres, m/s, m/s^2, radians).

    ``yaw_enu_rad`` None leaves the heading to the autopilot. Values are not checked here:
    the link's final guard checks every setpoint before it goes on the wire.
    """

    position_enu_m: Vec3
    velocity_enu_m_s: Vec3 = (0.0, 0.0, 0.0)
    accel_enu_m_s2: Vec3 = (0.0, 0.0, 0.0)
    yaw_enu_rad: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_enu_m", _vec3("position_enu_m", self.position_enu_m))
        object.__setattr__(
            self, "velocity_enu_m_s", _vec3("velocity_enu_m_s", self.velocity_enu_m_s)
        )
        object.__setattr__(self, "accel_enu_m_s2", _vec3("accel_enu_m_s2", self.accel_enu_m_s2))
        if self.yaw_enu_rad is not None:
            object.__setattr__(self, "yaw_enu_rad", float(self.yaw_enu_rad))

    @staticmethod
    def hold(position_enu_m: Sequence[float], yaw_enu_rad: float | None = None) -> Setpoint:
        """Stay at ``position_enu_m`` (zero velocity and acceleration)."""
        return Setpoint(_vec3("position_enu_m", position_enu_m), yaw_enu_rad=yaw_enu_rad)


SetpointSource = Callable[[float], "Setpoint | None"]
"""What the streamer samples every tick: ``source(now_s) -> Setpoint | None``.

``now_s`` comes from the link's ``sample_clock`` (the system clock by default, the time base of
trajectories). None means "nothing new": the link holds the last good setpoint's position.
The callable runs in the streamer thread and must be quick and lock-free (read an immutable
trajectory, evaluate it): it must never wait for planning or mapping.
"""


@dataclass(frozen=True)
class VehicleState:
    """What the link knows of the vehicle, in ENU, stamped with the link clock
    (``time.monotonic``) at arrival. None: not received yet."""

    t_s: float
    """When this snapshot was taken (``time.monotonic``)."""
    t_global_s: float
    """The same instant on the link's ``sample_clock`` (the trajectories' time base)."""
    connected: bool
    """A heartbeat from the autopilot has been seen since ``connect``."""
    link_lost: bool
    heartbeat_age_s: float
    """Since the last HEARTBEAT of the autopilot (inf before the first)."""
    rx_age_s: float
    """Since the last valid message of any kind from the autopilot (inf before the first)."""
    streaming: bool
    position_enu_m: Vec3 | None = None
    velocity_enu_m_s: Vec3 | None = None
    position_t_s: float | None = None
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_enu_rad: float | None = None
    """Body FLU in ENU, ZYX Euler angles (yaw counter-clockwise from east)."""
    attitude_t_s: float | None = None
    armed: bool = False
    mode: FlightMode = FlightMode.UNKNOWN
    custom_mode: int = 0
    """PX4's raw custom mode of the last heartbeat."""
    system_status: int = 0
    """MAV_STATE of the last heartbeat (5 critical: PX4 in failsafe)."""
    failsafe: bool = False
    landed_state: LandedState = LandedState.UNDEFINED
    battery_remaining: float | None = None
    """Fraction 0..1."""
    battery_voltage_v: float | None = None
    health_ok: bool | None = None
    """No sensor that is present and enabled reports a fault."""
    prearm_ok: bool | None = None
    """PX4's pre-arm checks pass (SYS_STATUS pre-arm bit)."""

    def global_time(self, t_s: float | None) -> float | None:
        """A link-clock stamp of this snapshot (e.g. ``position_t_s``) on the sample clock."""
        return None if t_s is None else self.t_global_s - (self.t_s - t_s)


# ---- events ------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinkEvent:
    """Base of the events the link reports (on its event thread, in order)."""

    t_s: float


@dataclass(frozen=True)
class Connected(LinkEvent):
    """The first heartbeat of the autopilot arrived."""


@dataclass(frozen=True)
class LinkLost(LinkEvent):
    """Nothing from the autopilot for ``link_timeout_s`` (or no heartbeat for
    ``heartbeat_timeout_s``). Streaming was stopped; it stays stopped after the link returns."""

    rx_age_s: float
    heartbeat_age_s: float
    was_streaming: bool


@dataclass(frozen=True)
class LinkRegained(LinkEvent):
    """The autopilot is heard again. Nothing is streamed until ``start_streaming``."""

    lost_for_s: float


@dataclass(frozen=True)
class ModeChanged(LinkEvent):
    """The heartbeat shows a new mode; ``commanded`` if this link asked for it recently."""

    previous: FlightMode
    current: FlightMode
    commanded: bool


@dataclass(frozen=True)
class OffboardLost(LinkEvent):
    """The vehicle left OFFBOARD without this link asking, while armed or streaming: a pilot
    took over, or PX4 entered a failsafe (``failsafe``: the heartbeat's system status is
    critical or emergency). Streaming was stopped at once (``stop_streaming_on_offboard_loss``);
    the link never re-enters OFFBOARD by itself. Seen through PX4's 1 Hz heartbeat, so up to
    about a second after the switch (PX4 ignores offboard setpoints outside OFFBOARD meanwhile).
    """

    current: FlightMode
    failsafe: bool
    was_streaming: bool


@dataclass(frozen=True)
class SetpointRejected(LinkEvent):
    """The final guard refused a setpoint (reported at most once a second per reason)."""

    reason: str
    count: int


@dataclass(frozen=True)
class SourceFailed(LinkEvent):
    """The setpoint source raised (reported at most once a second); the link holds."""

    error: str
    count: int


# ---- counters ----------------------------------------------------------------------------


@dataclass(frozen=True)
class LinkCounters:
    """Monotonic counters since ``connect``."""

    setpoints_sent: int = 0
    setpoints_rejected: int = 0
    """Refused by the final guard and replaced by a hold (or not sent at all)."""
    setpoints_held: int = 0
    """Hold setpoints sent in place of a rejected one, a None or a failing source."""
    source_errors: int = 0
    heartbeats_sent: int = 0
    heartbeats_received: int = 0
    messages_received: int = 0
    decode_errors: int = 0
    commands_sent: int = 0
    """Transmissions, retransmissions included."""
    command_retries: int = 0
    """Retries after TEMPORARILY_REJECTED."""
    acks_received: int = 0
    acks_unmatched: int = 0
    """Acknowledgements for no pending command (e.g. PX4's second ACK of a set-mode)."""
    foreign_heartbeats_dropped: int = 0
    """(MAVSDK) heartbeats MAVSDK generated itself and the link withheld."""
    late_ticks: int = 0
    """Streamer ticks that started more than one period late (ticks were skipped)."""
    link_losses: int = 0
    offboard_losses: int = 0
    unsigned_rejected: int = 0
    """(signing required) unsigned frames refused."""
    bad_signatures: int = 0
    """Signed frames whose signature or timestamp did not verify (wrong key, replay)."""
    unsigned_accepted: int = 0
    """(signing not required) unsigned frames let through."""
    frames_ignored: int = 0
    """(pymavlink over UDP) frames of message types the link does not use, skipped undecoded
    (and unverified: nothing in them is acted on)."""
    rejected_by_reason: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class PeriodStats:
    """Intervals between consecutive setpoint sends while streaming (milliseconds)."""

    count: int
    mean_ms: float
    p50_ms: float
    p99_ms: float
    max_ms: float

    @staticmethod
    def of(periods_s: Sequence[float]) -> PeriodStats:
        n = len(periods_s)
        if n == 0:
            return PeriodStats(0, math.nan, math.nan, math.nan, math.nan)
        xs = sorted(periods_s)

        def q(p: float) -> float:
            k = min(n - 1, max(0, math.ceil(p * n) - 1))
            return xs[k] * 1e3

        return PeriodStats(n, sum(xs) / n * 1e3, q(0.5), q(0.99), xs[-1] * 1e3)
