"""PX4-like flight logic of one vehicle: arming, modes, offboard rules, failsafe, takeoff, land.

Pure logic (no sockets, no clocks: every method takes the simulated time ``t_s``), ENU metres.
The MAVLink layer turns messages into calls here and reports what it returns; each tick
``update`` turns the mode into the controller command row of ``sitl_mock.dynamics``.

The specification is PX4 v1.16's code and what a real PX4 v1.16 (SITL, SIH quadrotor) did when
observed (``sitl_mock/README.md`` has the conformance table, with sources):

- boots into Hold and reports ready (pre-arm checks pass) after ``boot_time_s``;
- Offboard (and arming in it) is accepted once one setpoint younger than COM_OF_LOSS_T has
  arrived (PX4's ``OffboardChecks``: ``offboard_control_mode`` newer than COM_OF_LOSS_T). PX4's
  documentation asks clients to stream above 2 Hz for ~1 s first; that is advice, not a check,
  and the code and the observation win. A stricter warm-up exists only as an explicit option;
- in Offboard, armed, no setpoint for COM_OF_LOSS_T triggers the COM_OBL_RC_ACT action (PX4's
  value codes, default 0 = Position mode; without RC input that mode descends at the landing
  speed, as observed). The action is a *mode fallback*: the mode the user chose stays Offboard
  (CURRENT_MODE's intended mode) and when setpoints come back the vehicle returns to Offboard
  by itself (``failsafe.cpp: checkModeFallback``); choosing another mode ends it;
- arming is refused while not ready, in Land / Return, and in Offboard without a live stream;
  the force value 21196 changes nothing for arming over MAVLink (observed on v1.16); disarming
  in the air needs the force flag;
- arming and takeoff detection reset the home position;
- Takeoff climbs to the takeoff altitude and switches to Hold by itself; Land descends (faster
  high up), the land detector declares the landing after LNDMC_TRIG_TIME of ground contact and
  the vehicle disarms COM_DISARM_LAND later; after that the mode returns to the last mode the
  user chose that is not Takeoff / Land / Return (e.g. Offboard, where arming then needs a
  stream again);
- a vehicle armed on the ground that does not take off disarms after COM_DISARM_PRFLT;
- on the ground the motors idle until the setpoint asks to climb (PX4's takeoff trigger);
- status texts use PX4's wording ("Armed by external command", "Failsafe activated", ...).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sitl_mock import dynamics as dyn


class Mode(enum.Enum):
    """PX4 flight modes as (main mode, sub mode) of the custom_mode field."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    MISSION = (4, 4)
    TAKEOFF = (4, 2)
    HOLD = (4, 3)  # AUTO.LOITER
    RTL = (4, 5)
    LAND = (4, 6)
    ACRO = (5, 0)
    OFFBOARD = (6, 0)
    STABILIZED = (7, 0)

    @property
    def custom_mode(self) -> int:
        """PX4's encoding: ``main << 16 | sub << 24``."""
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @staticmethod
    def from_main_sub(main: int, sub: int) -> Mode | None:
        """The mode a DO_SET_MODE (param2 main, param3 sub) selects; None if unknown.

        Main mode AUTO with sub mode 0 is Mission, as in PX4.
        """
        if main == 4 and sub == 0:
            sub = 4
        if main != 4:
            sub = 0
        for m in Mode:
            if m.value == (main, sub):
                return m
        return None

    @staticmethod
    def from_custom_mode(custom_mode: int) -> Mode | None:
        return Mode.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)


SUPPORTED_MODES = frozenset(
    {Mode.POSCTL, Mode.ALTCTL, Mode.TAKEOFF, Mode.HOLD, Mode.RTL, Mode.LAND, Mode.OFFBOARD}
)
AUTO_MODES = frozenset({Mode.TAKEOFF, Mode.HOLD, Mode.RTL, Mode.LAND, Mode.MISSION})
MANUAL_INPUT_MODES = frozenset({Mode.POSCTL, Mode.ALTCTL})  # need RC (stick) input to be chosen
# user choices that are not restored after landing and disarming
_TRANSIENT_USER_MODES = frozenset({Mode.TAKEOFF, Mode.LAND, Mode.RTL})


class Result(enum.IntEnum):
    """MAV_RESULT of a command."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


class LandedState(enum.IntEnum):
    """MAV_LANDED_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class Severity(enum.IntEnum):
    """MAV_SEVERITY of a status text."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


LossAction = Literal["position", "altitude", "rtl", "land", "hold", "disarm"]
# COM_OBL_RC_ACT value codes (PX4 v1.16 commander parameters): the actions the mock can perform
OFFBOARD_LOSS_ACTION_CODES: dict[str, int] = {
    "position": 0,
    "altitude": 1,
    "rtl": 3,
    "land": 4,
    "hold": 5,
    "disarm": 7,
}
# PX4 codes the mock does not perform (no attitude-only flight, no flight termination)
OFFBOARD_LOSS_UNSUPPORTED_CODES: dict[int, str] = {2: "Stabilized", 6: "Terminate"}
_FALLBACK_MODE: dict[str, Mode] = {
    "position": Mode.POSCTL,
    "altitude": Mode.ALTCTL,
    "rtl": Mode.RTL,
    "land": Mode.LAND,
    "hold": Mode.HOLD,
}
MAX_TAKEOFF_ALT_M = 1000.0  # takeoff targets above this (relative to home) are denied
ARMING_DENIED_TEXT = "Arming denied: Resolve system health failures first"  # observed on v1.16


def offboard_loss_action_from_code(code: int) -> LossAction:
    """The action of a COM_OBL_RC_ACT value; ValueError for codes the mock cannot perform."""
    for name, c in OFFBOARD_LOSS_ACTION_CODES.items():
        if c == code:
            return name  # type: ignore[return-value]
    if code in OFFBOARD_LOSS_UNSUPPORTED_CODES:
        raise ValueError(
            f"COM_OBL_RC_ACT {code} ({OFFBOARD_LOSS_UNSUPPORTED_CODES[code]}) is not supported "
            "by the mock"
        )
    raise ValueError(f"COM_OBL_RC_ACT {code} is not a PX4 value (0-7)")


@dataclass(frozen=True)
class AutopilotParams:
    """Flight-logic settings, named after the PX4 parameters they stand for; defaults are PX4
    v1.16's (multicopter)."""

    boot_time_s: float = 5.0  # time until pre-arm checks pass (observed ~5 s)
    takeoff_alt_m: float = 2.5  # MIS_TAKEOFF_ALT, above home
    takeoff_speed_m_s: float = 1.5  # MPC_TKO_SPEED
    takeoff_acceptance_m: float = 0.8  # NAV_MC_ALT_RAD
    land_speed_m_s: float = 0.7  # MPC_LAND_SPEED (below land_alt2_m)
    land_speed_high_m_s: float = 1.5  # MPC_Z_V_AUTO_DN (above land_alt1_m)
    land_alt1_m: float = 10.0  # MPC_LAND_ALT1
    land_alt2_m: float = 5.0  # MPC_LAND_ALT2
    auto_speed_m_s: float = 5.0  # MPC_XY_CRUISE
    auto_acc_m_s2: float = 3.0  # MPC_ACC_HOR
    rtl_return_alt_m: float = 60.0  # RTL_RETURN_ALT
    offboard_loss_timeout_s: float = 1.0  # COM_OF_LOSS_T
    # COM_OBL_RC_ACT, by name (codes: OFFBOARD_LOSS_ACTION_CODES); PX4's default 0 = Position
    offboard_loss_action: LossAction = "position"
    # Not PX4 (v1.16 has no warm-up): an optional stricter rule for testing clients: Offboard
    # and arming in it need setpoints for this long, with gaps below 1 / offboard_min_rate_hz.
    # 0 (the default) = PX4's rule, one setpoint younger than COM_OF_LOSS_T.
    offboard_stream_min_s: float = 0.0
    offboard_min_rate_hz: float = 0.0
    disarm_land_s: float = 2.0  # COM_DISARM_LAND (<= 0: never)
    disarm_preflight_s: float = 10.0  # COM_DISARM_PRFLT (<= 0: never)
    spoolup_s: float = 1.0  # COM_SPOOLUP_TIME
    land_detect_s: float = 1.0  # LNDMC_TRIG_TIME: ground contact this long = landed
    takeoff_trigger_m: float = 0.2  # a setpoint this far above starts a takeoff
    rc_present: bool = False  # without RC, Position / Altitude mode cannot be chosen
    battery_hover_time_s: float = 1200.0  # full battery at hover thrust
    battery_min_arm_fraction: float = 0.1  # arming refused below this charge

    def __post_init__(self) -> None:
        for name in (
            "takeoff_alt_m",
            "takeoff_speed_m_s",
            "land_speed_m_s",
            "land_speed_high_m_s",
            "auto_speed_m_s",
            "auto_acc_m_s2",
            "offboard_loss_timeout_s",
            "battery_hover_time_s",
            "takeoff_acceptance_m",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in (
            "boot_time_s",
            "offboard_stream_min_s",
            "offboard_min_rate_hz",
            "spoolup_s",
            "land_detect_s",
            "takeoff_trigger_m",
            "rtl_return_alt_m",
            "land_alt1_m",
            "land_alt2_m",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        for name in ("disarm_land_s", "disarm_preflight_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"{name} must be a number, got {v!r}")
        if self.offboard_loss_action not in OFFBOARD_LOSS_ACTION_CODES:
            raise ValueError(
                f"offboard_loss_action must be one of {sorted(OFFBOARD_LOSS_ACTION_CODES)} "
                f"(COM_OBL_RC_ACT {sorted(OFFBOARD_LOSS_ACTION_CODES.values())}), "
                f"got {self.offboard_loss_action!r}"
            )
        if self.offboard_stream_min_s > 0.0 and self.offboard_min_rate_hz <= 0.0:
            raise ValueError("offboard_stream_min_s > 0 needs offboard_min_rate_hz > 0")
        if self.land_alt1_m < self.land_alt2_m:
            raise ValueError("land_alt1_m must be >= land_alt2_m")
        if not 0.0 <= self.battery_min_arm_fraction < 1.0:
            raise ValueError("battery_min_arm_fraction must be in [0, 1)")

    @property
    def offboard_loss_action_code(self) -> int:
        """COM_OBL_RC_ACT as PX4 encodes it."""
        return OFFBOARD_LOSS_ACTION_CODES[self.offboard_loss_action]


@dataclass
class Estimate:
    """What the autopilot knows of its vehicle at one tick (ENU, its estimate)."""

    position_m: np.ndarray  # (3,)
    velocity_m_s: np.ndarray  # (3,)
    yaw_rad: float
    on_ground: bool
    thrust: float = 0.0  # normalised collective thrust


@dataclass(frozen=True)
class OffboardSetpoint:
    """An offboard setpoint resolved into absolute ENU world values; NaN = not controlled.

    ``position_m`` (3,), ``velocity_m_s`` (3,) (feed-forward where a position is set),
    ``acceleration_m_s2`` (3,), ``yaw_rad`` / ``yaw_rate_rad_s`` (ENU: counter-clockwise).
    """

    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    yaw_rad: float = math.nan
    yaw_rate_rad_s: float = math.nan

    def __post_init__(self) -> None:
        # computed once: the controller reads them every tick
        p = np.asarray(self.position_m, dtype=np.float64).reshape(3).tolist()
        v = np.asarray(self.velocity_m_s, dtype=np.float64).reshape(3).tolist()
        a = np.asarray(self.acceleration_m_s2, dtype=np.float64).reshape(3).tolist()
        fp = [math.isfinite(x) for x in p]
        fv = [math.isfinite(x) for x in v]
        fa = [math.isfinite(x) for x in a]
        any_set = any(fp) or any(fv) or any(fa)
        valid = (
            all(fp[k] or fv[k] or fa[k] for k in range(3))
            and fp[0] == fp[1]
            and fv[0] == fv[1]
            and fa[0] == fa[1]
        )
        object.__setattr__(self, "_any", any_set)
        object.__setattr__(self, "_valid", valid)
        object.__setattr__(self, "_pva", p + v + a)  # C_POS, C_VEL, C_ACC columns

    def controls_any(self) -> bool:
        """At least one position, velocity or acceleration component is set: PX4 publishes
        ``offboard_control_mode`` for it, so it keeps the offboard stream alive."""
        return bool(self._any)  # type: ignore[attr-defined]

    def valid(self) -> bool:
        """PX4's position controller accepts it (``PositionControl::_inputValid``): every axis
        has a position, velocity or acceleration, and x / y come in pairs for each of them.
        Otherwise PX4 flies its "stop and wait" failsafe (zero velocity) while the stream
        still counts as alive."""
        return bool(self._valid)  # type: ignore[attr-defined]


@dataclass
class StatusEvent:
    severity: Severity
    text: str


@dataclass
class _Ramp:
    """A point moving along a straight line to a goal with a trapezoidal speed profile."""

    point: np.ndarray
    goal: np.ndarray
    v_max: float
    a_max: float
    speed: float = 0.0

    def advance(self, dt: float) -> np.ndarray:
        """Move by ``dt``; returns the velocity feed-forward (3,)."""
        d = self.goal - self.point
        dist = float(np.linalg.norm(d))
        if dist < 1e-9:
            self.speed = 0.0
            self.point = self.goal.copy()
            return np.zeros(3)
        self.speed = min(
            self.speed + self.a_max * dt, self.v_max, math.sqrt(2.0 * self.a_max * dist)
        )
        step = self.speed * dt
        if step >= dist:
            self.point = self.goal.copy()
            self.speed = 0.0
            return np.zeros(3)
        u = d / dist
        self.point = self.point + u * step
        return u * self.speed

    @property
    def done(self) -> bool:
        return bool(np.all(self.point == self.goal))


@dataclass
class _StreamMonitor:
    """Arrival times of offboard setpoints: is the stream live, and since when."""

    last_s: float | None = None
    run_start_s: float | None = None
    count: int = 0

    def note(self, t_s: float, max_gap_s: float) -> None:
        if self.last_s is None or t_s - self.last_s > max_gap_s or t_s < self.last_s:
            self.run_start_s = t_s
        self.last_s = t_s
        self.count += 1

    def live(self, t_s: float, max_gap_s: float, min_duration_s: float) -> bool:
        if self.last_s is None or self.run_start_s is None:
            return False
        return t_s - self.last_s <= max_gap_s and self.last_s - self.run_start_s >= min_duration_s

    def age(self, t_s: float) -> float:
        return math.inf if self.last_s is None else t_s - self.last_s


@dataclass
class Autopilot:
    """Flight logic of one vehicle. ``home_m``: ENU home (spawn point on the ground; PX4 resets
    it at arming and just after takeoff)."""

    params: AutopilotParams
    home_m: np.ndarray
    ground_z_m: float
    armed: bool = False
    mode: Mode = Mode.HOLD  # the mode flown (PX4's nav_state)
    user_mode: Mode = Mode.HOLD  # the mode the user chose (PX4's user intended mode)
    persistent_user_mode: Mode = Mode.HOLD  # last user choice restored after disarming
    failsafe: str | None = None
    landed: bool = True
    battery_fraction: float = 1.0
    yaw0_rad: float = 0.0  # heading at start (ENU)
    hover_thrust: float = 0.5  # normalised thrust at hover, for the battery model
    events: list[StatusEvent] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.home_m = np.asarray(self.home_m, dtype=np.float64).reshape(3).copy()
        self.home_updates = 0  # times the home position was (re)set
        self.last_arm_denial = ""  # why the last arming was refused (the mock's words)
        # every status event with its time (the MAVLink layer drains ``events`` to send them)
        self.event_log: deque[tuple[float, StatusEvent]] = deque(maxlen=1000)
        self._t_s = 0.0
        self._est = Estimate(self.home_m.copy(), np.zeros(3), self.yaw0_rad, True)
        self._stream = _StreamMonitor()
        self._setpoint: OffboardSetpoint | None = None  # last one received
        self._active_setpoint: OffboardSetpoint | None = None  # received while in Offboard
        self._t_arm = -math.inf
        self._airborne_since_arm = False
        self._ground_since: float | None = 0.0
        self._landed_since = 0.0
        self._hold_target: np.ndarray | None = None
        self._hold_yaw = self.yaw0_rad
        self._ramp: _Ramp | None = None
        self._takeoff_goal_z = 0.0
        self._land_xy: np.ndarray | None = None
        self._rtl_phase = ""
        self._last_update_s: float | None = None

    # ---- queries -------------------------------------------------------------------------
    def ready(self, t_s: float) -> bool:
        """Pre-arm checks pass (booted, battery above the arming threshold)."""
        return t_s >= self.params.boot_time_s and (
            self.battery_fraction >= self.params.battery_min_arm_fraction
        )

    def booted(self, t_s: float) -> bool:
        return t_s >= self.params.boot_time_s

    def prearm_ok(self, t_s: float) -> bool:
        """The vehicle could be armed in its current mode now (SYS_STATUS's pre-arm bit)."""
        return not self._arm_denial(t_s)

    def stream_live(self, t_s: float) -> bool:
        """Offboard may be entered (and armed in): a setpoint younger than COM_OF_LOSS_T
        (plus the optional non-PX4 warm-up rule)."""
        p = self.params
        if self._stream.age(t_s) > p.offboard_loss_timeout_s:
            return False
        if p.offboard_stream_min_s <= 0.0:
            return True
        return self._stream.live(t_s, 1.0 / p.offboard_min_rate_hz, p.offboard_stream_min_s)

    def setpoint_age_s(self, t_s: float) -> float:
        """Time since the last accepted offboard setpoint (inf if none)."""
        return self._stream.age(t_s)

    @property
    def offboard_setpoint(self) -> OffboardSetpoint | None:
        """The last offboard setpoint received (in any mode)."""
        return self._setpoint

    def landed_state(self) -> LandedState:
        if self.landed:
            return LandedState.ON_GROUND
        if self.mode == Mode.TAKEOFF:
            return LandedState.TAKEOFF
        if self.mode == Mode.LAND or (self.mode == Mode.RTL and self._rtl_phase == "land"):
            return LandedState.LANDING
        return LandedState.IN_AIR

    # ---- inputs --------------------------------------------------------------------------
    def on_setpoint(self, t_s: float, sp: OffboardSetpoint) -> bool:
        """An offboard setpoint arrived. False (and ignored, as PX4's "invalid") if it sets no
        position, velocity or acceleration at all. As in PX4, it is flown only if it arrives
        while in Offboard; before that it only keeps the stream alive."""
        if not sp.controls_any():
            return False
        p = self.params
        gap = 1.0 / p.offboard_min_rate_hz if p.offboard_min_rate_hz > 0 else math.inf
        self._stream.note(t_s, gap)
        self._setpoint = sp
        if self.mode == Mode.OFFBOARD:
            self._active_setpoint = sp
        return True

    def command_arm(self, t_s: float, arm: bool, force: bool = False) -> Result:
        """ARM_DISARM. ``force`` only matters for disarming (in the air): PX4 v1.16 ignores the
        force value for arming commands that arrive over MAVLink (observed)."""
        if arm:
            if self.armed:
                return Result.ACCEPTED
            reason = self._arm_denial(t_s)
            if reason:
                self.last_arm_denial = reason
                self._event(Severity.CRITICAL, ARMING_DENIED_TEXT)
                return Result.TEMPORARILY_REJECTED
            self._set_armed(t_s, True, "external command")
            return Result.ACCEPTED
        if not self.armed:
            return Result.ACCEPTED
        if not (self.landed or self._est.on_ground or force):
            self._event(Severity.CRITICAL, "Disarming denied: not landed")
            return Result.TEMPORARILY_REJECTED
        self._set_armed(t_s, False, "external command")
        return Result.ACCEPTED

    def command_set_mode(self, t_s: float, mode: Mode | None) -> Result:
        if mode is None or mode not in SUPPORTED_MODES:
            return Result.DENIED
        if mode == Mode.TAKEOFF:
            return self.command_takeoff(t_s, None)
        if not self.booted(t_s):
            return Result.TEMPORARILY_REJECTED
        if mode == Mode.OFFBOARD and not self.stream_live(t_s):
            self._event(Severity.CRITICAL, "Switching to Offboard is currently not possible")
            return Result.TEMPORARILY_REJECTED
        if mode in MANUAL_INPUT_MODES and not self.params.rc_present:
            name = "Position" if mode == Mode.POSCTL else "Altitude"
            self._event(
                Severity.CRITICAL,
                f"Switching to {name} is currently not possible: no manual control input",
            )
            return Result.TEMPORARILY_REJECTED
        if mode == Mode.LAND:
            return self.command_land(t_s)
        if mode == Mode.RTL:
            return self.command_rtl(t_s)
        self._user_choice(mode)
        self.failsafe = None
        if mode != self.mode:
            self._enter(t_s, mode)
        return Result.ACCEPTED

    def command_takeoff(self, t_s: float, altitude_above_home_m: float | None) -> Result:
        """NAV_TAKEOFF. As PX4, the target is at least the takeoff altitude parameter above
        home; None (or NaN) takes that altitude; more than ``MAX_TAKEOFF_ALT_M`` is denied."""
        if not self.booted(t_s):
            return Result.TEMPORARILY_REJECTED
        alt = self.params.takeoff_alt_m
        if altitude_above_home_m is not None and math.isfinite(altitude_above_home_m):
            if altitude_above_home_m > MAX_TAKEOFF_ALT_M:
                return Result.DENIED
            if altitude_above_home_m < alt:
                self._event(Severity.WARNING, f"Using minimum takeoff altitude: {alt:.2f} m")
            alt = max(alt, altitude_above_home_m)
        else:
            self._event(Severity.INFO, f"Using default takeoff altitude: {alt:.1f} m")
        self._takeoff_goal_z = self.home_m[2] + alt
        self._user_choice(Mode.TAKEOFF)
        self.failsafe = None
        self._enter(t_s, Mode.TAKEOFF)
        return Result.ACCEPTED

    def command_land(self, t_s: float) -> Result:
        if not self.booted(t_s):
            return Result.TEMPORARILY_REJECTED
        self._user_choice(Mode.LAND)
        self.failsafe = None
        self._enter(t_s, Mode.LAND)
        return Result.ACCEPTED

    def command_rtl(self, t_s: float) -> Result:
        if not self.booted(t_s):
            return Result.TEMPORARILY_REJECTED
        self._user_choice(Mode.RTL)
        self.failsafe = None
        self._enter(t_s, Mode.RTL)
        return Result.ACCEPTED

    def drain_events(self) -> list[StatusEvent]:
        ev, self.events = self.events, []
        return ev

    # ---- the tick ------------------------------------------------------------------------
    def update(self, t_s: float, est: Estimate, cmd_row: np.ndarray) -> None:
        """Advance the logic to ``t_s`` with the current estimate; write the command row."""
        dt = 0.0 if self._last_update_s is None else max(t_s - self._last_update_s, 0.0)
        self._last_update_s = t_s
        self._t_s = t_s
        self._est = est
        p = self.params
        # land detector (takeoff is detected at once, a landing after LNDMC_TRIG_TIME)
        if est.on_ground:
            if self._ground_since is None:
                self._ground_since = t_s
        else:
            self._ground_since = None
        was_landed = self.landed
        if self._ground_since is None:
            self.landed = False
        elif not self.armed or t_s - self._ground_since >= p.land_detect_s:
            self.landed = True
        if self.landed and not was_landed:
            self._landed_since = t_s
            if self.armed:
                self._event(Severity.INFO, "Landing detected")
        if was_landed and not self.landed and self.armed:
            self._airborne_since_arm = True
            self._event(Severity.INFO, "Takeoff detected")
            self._set_home(est.position_m)  # PX4 resets home just after takeoff
        # battery
        if self.armed:
            use = max(est.thrust, 0.05) / self.hover_thrust
            self.battery_fraction = max(
                0.0, self.battery_fraction - use * dt / p.battery_hover_time_s
            )
        # automatic disarming
        if self.armed and self.landed:
            if self._airborne_since_arm:
                if p.disarm_land_s > 0 and t_s - self._landed_since >= p.disarm_land_s:
                    self._set_armed(t_s, False, "landing")
            elif p.disarm_preflight_s > 0 and t_s - self._t_arm >= p.disarm_preflight_s:
                self._set_armed(t_s, False, "auto preflight disarming")
        # offboard loss: a mode fallback while the user's mode is Offboard and the stream is lost
        if self.armed and self.user_mode == Mode.OFFBOARD:
            lost = self._stream.age(t_s) > p.offboard_loss_timeout_s
            if lost and self.failsafe is None:
                self._offboard_lost(t_s)
            elif not lost and self.failsafe == "offboard_loss":
                self.failsafe = None  # the condition cleared: back to the user's mode
                self._enter(t_s, Mode.OFFBOARD)
        self._command(t_s, dt, est, cmd_row)

    # ---- internals -----------------------------------------------------------------------
    def _offboard_lost(self, t_s: float) -> None:
        action = self.params.offboard_loss_action
        self._event(Severity.CRITICAL, "Failsafe activated")
        self.failsafe = "offboard_loss"
        if action == "disarm":
            self._set_armed(t_s, False, "failsafe")
            return
        self._enter(t_s, _FALLBACK_MODE[action])

    def _arm_denial(self, t_s: float) -> str:
        if not self.booted(t_s):
            return "system not ready (pre-arm checks)"
        if self.battery_fraction < self.params.battery_min_arm_fraction:
            return "battery low"
        if self.mode == Mode.OFFBOARD and not self.stream_live(t_s):
            return "offboard signal lost"
        if self.mode in (Mode.LAND, Mode.RTL):
            return f"not possible in {self.mode.name.title()} mode"
        if self.mode in MANUAL_INPUT_MODES and not self.params.rc_present:
            return "no manual control input"
        return ""

    def _set_home(self, position_m: np.ndarray) -> None:
        self.home_m = np.asarray(position_m, dtype=np.float64).reshape(3).copy()
        self.home_updates += 1

    def _set_armed(self, t_s: float, armed: bool, reason: str) -> None:
        self.armed = armed
        if armed:
            self._t_arm = t_s
            self._airborne_since_arm = False
            self._set_home(self._est.position_m)  # PX4 sets home at arming
            self._event(Severity.INFO, f"Armed by {reason}")
            if self.mode in (Mode.HOLD, Mode.POSCTL, Mode.ALTCTL):
                self._enter(t_s, self.mode)
            return
        self._event(Severity.INFO, f"Disarmed by {reason}")
        self.failsafe = None
        target = (
            self.persistent_user_mode if self.user_mode in _TRANSIENT_USER_MODES else self.user_mode
        )
        self.user_mode = target
        if self.mode != target:
            self._enter(t_s, target)

    def _user_choice(self, mode: Mode) -> None:
        self.user_mode = mode
        if mode not in _TRANSIENT_USER_MODES:
            self.persistent_user_mode = mode

    def _stop_point(self) -> np.ndarray:
        e = self._est
        if self.landed or e.on_ground:
            return e.position_m.copy()
        v = e.velocity_m_s
        sp = float(np.linalg.norm(v))
        a = self.params.auto_acc_m_s2
        return e.position_m + (v * sp / (2.0 * a) if sp > 0 else 0.0)

    def _enter(self, t_s: float, mode: Mode) -> None:
        """Switch to ``mode`` and set up its targets from the current estimate."""
        self.mode = mode
        e = self._est
        self._hold_yaw = e.yaw_rad
        self._ramp = None
        self._active_setpoint = None
        if mode in (Mode.HOLD, Mode.POSCTL, Mode.ALTCTL, Mode.OFFBOARD):
            self._hold_target = self._stop_point()
        elif mode == Mode.TAKEOFF:
            start = e.position_m.copy()
            goal = start.copy()
            goal[2] = max(self._takeoff_goal_z, start[2])
            self._ramp = _Ramp(
                start, goal, self.params.takeoff_speed_m_s, self.params.auto_acc_m_s2
            )
        elif mode == Mode.LAND:
            self._land_xy = self._stop_point()[:2]
            if self.armed and not self.landed:
                self._event(Severity.INFO, "Landing at current position")
        elif mode == Mode.RTL:
            start = self._stop_point()
            goal = start.copy()
            goal[2] = max(start[2], self.home_m[2] + self.params.rtl_return_alt_m)
            self._rtl_phase = "climb"
            self._ramp = _Ramp(
                e.position_m.copy(), goal, self.params.auto_speed_m_s, self.params.auto_acc_m_s2
            )

    def _land_speed(self, height_m: float) -> float:
        p = self.params
        if height_m >= p.land_alt1_m:
            return p.land_speed_high_m_s
        if height_m <= p.land_alt2_m or p.land_alt1_m <= p.land_alt2_m:
            return p.land_speed_m_s
        w = (height_m - p.land_alt2_m) / (p.land_alt1_m - p.land_alt2_m)
        return p.land_speed_m_s + w * (p.land_speed_high_m_s - p.land_speed_m_s)

    def _command(self, t_s: float, dt: float, est: Estimate, c: np.ndarray) -> None:
        """Write the controller command row ``c`` for the current mode (one numpy write)."""
        nan = math.nan
        v = [nan] * dyn.NC
        v[dyn.C_YAW] = self._hold_yaw
        if not self.armed:
            v[dyn.C_MOTOR] = dyn.MOTOR_OFF
            c[:] = v
            return
        P, V, A = dyn.C_POS, dyn.C_VEL, dyn.C_ACC  # noqa: N806 - column offsets
        spooling = t_s - self._t_arm < self.params.spoolup_s
        mode = self.mode
        if self._hold_target is None:
            self._hold_target = self._stop_point()
        if mode == Mode.HOLD:
            v[P : P + 3] = self._hold_target.tolist()
        elif mode in MANUAL_INPUT_MODES:
            if self.params.rc_present:  # sticks centred: hold (Altitude: hold the height only)
                if mode == Mode.POSCTL:
                    v[P : P + 3] = self._hold_target.tolist()
                else:
                    v[V] = v[V + 1] = 0.0
                    v[P + 2] = float(self._hold_target[2])
            else:
                # observed on PX4 v1.16 SIH without RC: the Position-mode fallback of the
                # offboard failsafe descends at about MPC_LAND_SPEED
                v[V : V + 3] = [0.0, 0.0, -self.params.land_speed_m_s]
        elif mode == Mode.TAKEOFF:
            if self._ramp is None:
                self._enter(t_s, Mode.TAKEOFF)
            assert self._ramp is not None
            if not spooling:
                v[V : V + 3] = self._ramp.advance(dt).tolist()
            v[P : P + 3] = self._ramp.point.tolist()
            goal_z = self._ramp.goal[2]
            if (
                self._ramp.done
                and abs(est.position_m[2] - goal_z) < self.params.takeoff_acceptance_m
            ):
                self.mode = Mode.HOLD  # PX4 switches to Hold (Loiter) by itself
                self._user_choice(Mode.HOLD)
                self._hold_target = self._ramp.goal.copy()
                self._ramp = None
        elif mode == Mode.LAND or (mode == Mode.RTL and self._rtl_phase == "land"):
            if self._land_xy is None:
                self._land_xy = est.position_m[:2].copy()
            v[P] = float(self._land_xy[0])
            v[P + 1] = float(self._land_xy[1])
            v[V + 2] = -self._land_speed(float(est.position_m[2]) - self.ground_z_m)
        elif mode == Mode.RTL:
            if self._ramp is None:
                self._enter(t_s, Mode.RTL)
            assert self._ramp is not None
            v[V : V + 3] = self._ramp.advance(dt).tolist()
            v[P : P + 3] = self._ramp.point.tolist()
            if self._ramp.done:
                if self._rtl_phase == "climb":
                    goal = self._ramp.goal.copy()
                    goal[:2] = self.home_m[:2]
                    self._rtl_phase = "return"
                    self._ramp = _Ramp(
                        self._ramp.point.copy(),
                        goal,
                        self.params.auto_speed_m_s,
                        self.params.auto_acc_m_s2,
                    )
                elif (
                    self._rtl_phase == "return"
                    and np.linalg.norm(est.position_m[:2] - self.home_m[:2]) < 0.5
                ):
                    self._rtl_phase = "land"
                    self._land_xy = self.home_m[:2].copy()
        elif mode == Mode.OFFBOARD:
            sp = self._active_setpoint
            if sp is None:
                # no setpoint since Offboard began: PX4 keeps the last trajectory setpoint
                # of the previous mode; the mock holds where Offboard began
                v[P : P + 3] = self._hold_target.tolist()
            elif not sp.valid():
                # PX4's position controller rejects it and stops: "Failsafe: stop and wait"
                v[V : V + 3] = [0.0, 0.0, 0.0]
                self._hold_yaw = est.yaw_rad
                v[dyn.C_YAW] = self._hold_yaw
            else:
                v[P : A + 3] = sp._pva  # type: ignore[attr-defined]
                if not math.isnan(sp.yaw_rad):
                    v[dyn.C_YAW] = sp.yaw_rad
                    self._hold_yaw = sp.yaw_rad
                elif not math.isnan(sp.yaw_rate_rad_s):
                    v[dyn.C_YAW] = nan
                    v[dyn.C_YAWRATE] = sp.yaw_rate_rad_s
                    self._hold_yaw = est.yaw_rad
        else:  # pragma: no cover - unsupported modes are never entered
            v[P : P + 3] = est.position_m.tolist()
        if spooling:
            v[dyn.C_MOTOR] = dyn.MOTOR_IDLE
        elif self.landed and not self._wants_takeoff(est, v):
            v[dyn.C_MOTOR] = dyn.MOTOR_IDLE
        else:
            v[dyn.C_MOTOR] = dyn.MOTOR_RUN
        c[:] = v

    def _wants_takeoff(self, est: Estimate, c: Sequence[float]) -> bool:
        """PX4's takeoff trigger: the setpoint asks to climb."""
        trig = self.params.takeoff_trigger_m
        pz, vz, az = c[dyn.C_POS + 2], c[dyn.C_VEL + 2], c[dyn.C_ACC + 2]
        if not math.isnan(pz) and pz > est.position_m[2] + trig:
            return True
        if math.isnan(pz) and not math.isnan(vz) and vz > 0.3:
            return True
        return math.isnan(pz) and math.isnan(vz) and not math.isnan(az) and az > 0.5

    def _event(self, severity: Severity, text: str) -> None:
        ev = StatusEvent(severity, text)
        self.events.append(ev)
        self.event_log.append((self._t_s, ev))
