"""The flight state machine of one drone: pure logic, the clock passed in, no I/O.

    IDLE ──takeoff──> TAKEOFF ──altitude reached──> HOVER ──goal──> FORMATION_FLIGHT
      ^                                              ^  │               │ goal reached
      │                                              │  └─────land──┐   v
    (resume on the ground)                          HOVER (at goal) ─┴─> LANDING ──landed──> LANDED
    EMERGENCY: braking stop, hover ``emergency_hover_s``, then LANDING (abort, or planning failing
               for ``max_failed_s``)
    PILOT:     the vehicle left the mode the service set, by someone else's decision: yield at
               once; only ``resume`` (or ``takeoff`` on the ground) gives control back
    LINK_LOST: no autopilot heartbeat: stop commanding; after the link returns nothing is streamed
               until a command (resume, land) says so

FORMATION_FLIGHT pauses into HOVER (the goal kept) while a *hold* is active: ``depth`` (no depth
frames: stop and hover until they return) or ``plan`` (an 'emergency' plan: hover, retry after
``retry_after_s``). When every hold is gone the flight continues. A 'kept-previous' plan (the
trajectory in control, which the check still accepts, flies on) holds nothing; like an
'emergency' one it runs the failure clock: planning failing for ``max_failed_s`` in a row is an
EMERGENCY.

Swarm-wide changes take effect at one common time: a ``SetFormation``, ``Goal`` or ``Waypoints``
whose ``effective_s`` lies ahead is checked and acknowledged at once, kept *pending*, and applied
by ``tick`` when the clock reaches it (every drone switches together, not as the messages
arrive). A pending goal is dropped with the current one (land, abort, pilot, link loss ...).

Ground-station commands (``Takeoff``, ``SetFormation``, ``Goal``, ``Waypoints``, ``Land``,
``Abort``, ``Resume``) return a ``CommandResult``: accepted, or rejected with the reason (which the
service acks back). Every transition is reported to the listener (the service logs, publishes and
records it) and kept in ``history``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


class FlightState(str, enum.Enum):
    IDLE = "idle"
    """On the ground, the autopilot link up, waiting for a take-off command."""
    TAKEOFF = "takeoff"
    HOVER = "hover"
    FORMATION_FLIGHT = "formation-flight"
    LANDING = "landing"
    LANDED = "landed"
    EMERGENCY = "emergency"
    PILOT = "pilot"
    LINK_LOST = "link-lost"


COMMANDING = frozenset(
    {FlightState.TAKEOFF, FlightState.HOVER, FlightState.FORMATION_FLIGHT, FlightState.EMERGENCY}
)
"""States in which the service streams setpoints (LANDING uses the autopilot's land mode)."""
AIRBORNE_CONTROLLED = COMMANDING | {FlightState.LANDING}


# ---- commands ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Takeoff:
    altitude_m: float | None = None
    """Climb this high above the take-off point; None: the configured altitude."""


@dataclass(frozen=True)
class SetFormation:
    """A swarm-wide formation assignment that takes effect at ``effective_s`` (global time) on
    every drone. ``slots``: (drone id, slot) pairs; ``points``: the template, slot k = row k.
    A drone accepts only epochs newer than every epoch it knows."""

    epoch: int
    effective_s: float
    slots: tuple[tuple[int, int], ...]
    points: tuple[Vec3, ...]


@dataclass(frozen=True)
class Goal:
    """Fly the formation's centre to ``position``, from the global time ``effective_s`` on (the
    same on every drone; a time already past: at once). Checked when it arrives; until its
    time the drone goes on with what it was doing."""

    position: Vec3
    effective_s: float = -math.inf


@dataclass(frozen=True)
class Waypoints:
    """Fly through ``positions`` in order, from ``effective_s`` on (see ``Goal``)."""

    positions: tuple[Vec3, ...]
    effective_s: float = -math.inf


@dataclass(frozen=True)
class Land:
    pass


@dataclass(frozen=True)
class Abort:
    pass


@dataclass(frozen=True)
class Resume:
    pass


Command = Takeoff | SetFormation | Goal | Waypoints | Land | Abort | Resume


@dataclass(frozen=True)
class CommandResult:
    accepted: bool
    reason: str = ""


@dataclass(frozen=True)
class Transition:
    t_s: float
    source: FlightState
    target: FlightState
    reason: str


@dataclass(frozen=True)
class Assignment:
    """The formation in force: epoch, template points and this drone's slot."""

    epoch: int
    effective_s: float
    slots: tuple[tuple[int, int], ...]
    points: tuple[Vec3, ...]

    def slot_of(self, drone_id: int) -> int | None:
        for d, s in self.slots:
            if d == drone_id:
                return s
        return None

    def drone_of_slot(self) -> dict[int, int]:
        return {s: d for d, s in self.slots}


RETRY_AFTER_S = 1.0
"""The default of ``planning.retry_after_s`` (``MachineParams.retry_after_s``): how long the
hover after a failed plan lasts before the retry (the fast-time twin's
``SimConfig.retry_after_s`` too)."""


@dataclass(frozen=True)
class MachineParams:
    emergency_hover_s: float = 5.0
    retry_after_s: float = RETRY_AFTER_S
    max_failed_s: float = 15.0
    gcs_lost_action: str = "hover"
    """'hover': finish the current goal and hover; 'land': then land."""


HOLD_DEPTH = "depth"
HOLD_PLAN = "plan"
HOLD_CLOCK = "clock"


class FlightStateMachine:
    """The flight logic of drone ``drone_id``. ``clock()``: the current time in seconds;
    ``inside_geofence(p)``: whether a goal may be flown to; ``listener``: gets every transition."""

    def __init__(
        self,
        drone_id: int,
        clock: Callable[[], float],
        params: MachineParams | None = None,
        inside_geofence: Callable[[Vec3], bool] | None = None,
        listener: Callable[[Transition], None] | None = None,
    ) -> None:
        self.drone_id = drone_id
        self.clock = clock
        self.params = params if params is not None else MachineParams()
        if self.params.gcs_lost_action not in ("hover", "land"):
            raise ValueError("gcs_lost_action must be 'hover' or 'land'")
        self.inside_geofence = inside_geofence if inside_geofence is not None else (lambda p: True)
        self.listener = listener
        self.state = FlightState.IDLE
        self.since_s = clock()
        self.history: list[Transition] = []
        self.goal: Vec3 | None = None
        self.waypoints: list[Vec3] = []
        self.takeoff_altitude_m: float | None = None
        self.assignment: Assignment | None = None
        self.pending: Assignment | None = None
        self.pending_goals: tuple[tuple[Vec3, ...], float] | None = None
        """Goal(s) accepted for a common time still ahead: (positions, effective_s)."""
        self.holds: set[str] = set()
        self.link_ok = True
        self.gcs_ok = True
        self.on_ground = True
        self._retry_at_s = math.inf
        self._failing_since_s: float | None = None
        self.clock_problem: str | None = None
        """Why formation flight is refused (a peer's clock beyond the bound), or None."""

    # ---- queries -----------------------------------------------------------------------------
    @property
    def commanding(self) -> bool:
        """Whether setpoints are to be streamed now."""
        return self.state in COMMANDING

    @property
    def paused(self) -> bool:
        """HOVER with a goal still to fly, waiting for its holds to clear."""
        return self.state is FlightState.HOVER and self.goal is not None and bool(self.holds)

    def slot(self) -> int | None:
        return None if self.assignment is None else self.assignment.slot_of(self.drone_id)

    # ---- internals ---------------------------------------------------------------------------
    def _go(self, target: FlightState, reason: str) -> None:
        if target is self.state:
            return
        now = self.clock()
        tr = Transition(now, self.state, target, reason)
        self.state = target
        self.since_s = now
        self.history.append(tr)
        if target is not FlightState.HOVER and target is not FlightState.FORMATION_FLIGHT:
            self.holds.discard(HOLD_PLAN)  # the depth hold lasts as long as the frames are missing
            self._retry_at_s = math.inf
        if target in (FlightState.LANDING, FlightState.LANDED, FlightState.IDLE):
            self._clear_goals()
        if self.listener is not None:
            self.listener(tr)

    def _clear_goals(self) -> None:
        """Forget the goal, the waypoints and a goal waiting for its effective time."""
        self.goal = None
        self.waypoints.clear()
        self.pending_goals = None

    def _reject(self, reason: str) -> CommandResult:
        return CommandResult(False, reason)

    def _not_airborne_reason(self) -> str | None:
        s = self.state
        if s in (FlightState.IDLE, FlightState.LANDED):
            return "on the ground: take off first"
        if s is FlightState.PILOT:
            return "the pilot has control: send resume first"
        if s is FlightState.LINK_LOST:
            return "autopilot link lost: send resume once it is back"
        return None

    # ---- commands ----------------------------------------------------------------------------
    def command(self, cmd: Command) -> CommandResult:
        """Apply a ground-station command; a rejection names the reason."""
        if isinstance(cmd, SetFormation):
            return self._set_formation(cmd)
        if isinstance(cmd, Takeoff):
            return self._takeoff(cmd)
        if isinstance(cmd, Goal):
            return self._goals([cmd.position], cmd.effective_s)
        if isinstance(cmd, Waypoints):
            return self._goals(list(cmd.positions), cmd.effective_s)
        if isinstance(cmd, Land):
            return self._land()
        if isinstance(cmd, Abort):
            return self._abort()
        if isinstance(cmd, Resume):
            return self._resume()
        return self._reject(f"unknown command {type(cmd).__name__}")

    def _set_formation(self, cmd: SetFormation) -> CommandResult:
        known = max((a.epoch for a in (self.assignment, self.pending) if a is not None), default=-1)
        if cmd.epoch <= known:
            return self._reject(f"stale formation epoch {cmd.epoch} (have {known})")
        n = len(cmd.points)
        if n < 2:
            return self._reject(f"a formation needs at least 2 points, got {n}")
        drones = [d for d, _ in cmd.slots]
        slots = [s for _, s in cmd.slots]
        if len(set(drones)) != len(drones):
            return self._reject("a drone is assigned twice")
        if len(set(slots)) != len(slots):
            return self._reject("a slot is assigned twice")
        if any(not 0 <= s < n for s in slots):
            return self._reject(f"slot out of range 0..{n - 1}")
        if self.drone_id not in drones:
            return self._reject(f"drone {self.drone_id} has no slot in epoch {cmd.epoch}")
        if not math.isfinite(cmd.effective_s):
            return self._reject("effective time is not finite")
        self.pending = Assignment(cmd.epoch, cmd.effective_s, cmd.slots, cmd.points)
        self._activate_assignment()
        return CommandResult(True)

    def _activate_assignment(self) -> bool:
        p = self.pending
        if p is not None and self.clock() >= p.effective_s:
            self.assignment = p
            self.pending = None
            return True
        return False

    def _takeoff(self, cmd: Takeoff) -> CommandResult:
        if self.state not in (FlightState.IDLE, FlightState.LANDED):
            return self._reject(f"cannot take off in state {self.state.value}")
        if not self.link_ok:
            return self._reject("autopilot link is down")
        if not self.on_ground:
            return self._reject("the vehicle is not on the ground")
        if cmd.altitude_m is not None and not (0.0 < cmd.altitude_m < 1e3):
            return self._reject(f"bad take-off altitude {cmd.altitude_m}")
        self.takeoff_altitude_m = cmd.altitude_m
        self._go(FlightState.TAKEOFF, "take-off command")
        return CommandResult(True)

    def _goals(self, positions: list[Vec3], effective_s: float) -> CommandResult:
        why = self._not_airborne_reason()
        if why is not None:
            return self._reject(why)
        if self.state in (FlightState.TAKEOFF, FlightState.LANDING, FlightState.EMERGENCY):
            return self._reject(f"cannot take a goal in state {self.state.value}")
        if not positions:
            return self._reject("no waypoint given")
        for p in positions:
            if len(p) != 3 or not all(math.isfinite(float(v)) for v in p):
                return self._reject(f"goal {list(p)} is not a finite 3-vector")
            if not self.inside_geofence(p):
                return self._reject(f"goal {[round(float(v), 2) for v in p]} outside the geofence")
        if self.assignment is None and self.pending is None:
            return self._reject("no formation assigned yet")
        if self.clock_problem is not None:
            return self._reject(f"refusing formation flight: {self.clock_problem}")
        if math.isnan(effective_s):
            return self._reject("effective time is not a number")
        if self.clock() >= effective_s:
            self.pending_goals = None
            self._apply_goals(positions, "goal command")
        else:
            self.pending_goals = (tuple(positions), effective_s)
        return CommandResult(True)

    def _apply_goals(self, positions: Sequence[Vec3], reason: str) -> None:
        self.goal = positions[0]
        self.waypoints = list(positions[1:])
        if not self.holds:
            self._go(FlightState.FORMATION_FLIGHT, reason)

    def _activate_goals(self) -> None:
        pg = self.pending_goals
        if pg is None or self.clock() < pg[1]:
            return
        self.pending_goals = None
        if self._not_airborne_reason() is None and self.state in (
            FlightState.HOVER,
            FlightState.FORMATION_FLIGHT,
        ):
            self._apply_goals(pg[0], "goal at its effective time")

    def _land(self) -> CommandResult:
        s = self.state
        if s in (FlightState.IDLE, FlightState.LANDED):
            return self._reject("already on the ground")
        if s is FlightState.LANDING:
            return self._reject("already landing")
        if s is FlightState.PILOT:
            return self._reject("the pilot has control")
        if s is FlightState.LINK_LOST and not self.link_ok:
            return self._reject("autopilot link lost")
        self._go(FlightState.LANDING, "land command")
        return CommandResult(True)

    def _abort(self) -> CommandResult:
        s = self.state
        if s in (FlightState.IDLE, FlightState.LANDED):
            return self._reject("on the ground: nothing to abort")
        if s is FlightState.EMERGENCY:
            return self._reject("already in emergency")
        if s is FlightState.PILOT:
            return self._reject("the pilot has control")
        if s is FlightState.LINK_LOST:
            return self._reject("autopilot link lost")
        self._clear_goals()
        self._go(FlightState.EMERGENCY, "abort command")
        return CommandResult(True)

    def _resume(self) -> CommandResult:
        s = self.state
        if s not in (FlightState.PILOT, FlightState.LINK_LOST, FlightState.EMERGENCY):
            return self._reject(f"nothing to resume in state {s.value}")
        if not self.link_ok:
            return self._reject("autopilot link is down")
        self._clear_goals()
        if self.on_ground:
            self._go(FlightState.IDLE, "resume on the ground")
        else:
            self._go(FlightState.HOVER, "resume command")
        return CommandResult(True)

    # ---- events from the service -------------------------------------------------------------
    def set_on_ground(self, on_ground: bool) -> None:
        """The autopilot's landed state (landed and, for LANDING, disarmed or idle)."""
        self.on_ground = on_ground
        if on_ground and self.state in (FlightState.LANDING, FlightState.EMERGENCY):
            self._go(FlightState.LANDED, "landed")

    def takeoff_reached(self) -> None:
        if self.state is FlightState.TAKEOFF:
            self._go(FlightState.HOVER, "take-off altitude reached")

    def takeoff_failed(self, reason: str) -> None:
        if self.state is FlightState.TAKEOFF:
            self._go(FlightState.IDLE, f"take-off failed: {reason}")

    def goal_reached(self) -> None:
        if self.state is not FlightState.FORMATION_FLIGHT:
            return
        if self.waypoints and self.gcs_ok:
            self.goal = self.waypoints.pop(0)
            return
        self.goal = None
        self.waypoints.clear()  # a pending goal (a later common time) stays
        self._go(FlightState.HOVER, "goal reached")
        self._gcs_lost_policy()

    def pilot_took_over(self, detail: str = "") -> None:
        """The vehicle left the service's mode without the service asking: yield at once."""
        if self.state in AIRBORNE_CONTROLLED:
            self._clear_goals()
            self._go(FlightState.PILOT, "pilot took over" + (f" ({detail})" if detail else ""))

    def found_airborne(self, mode: str) -> None:
        """In IDLE the vehicle is armed and off the ground: someone else flies it (the
        autopilot's failsafe after this service was restarted, or a pilot). Nothing of an old
        plan is resumed: the service stays out of control until a ``resume`` command."""
        if self.state is FlightState.IDLE:
            self._go(
                FlightState.PILOT,
                f"vehicle airborne under the autopilot's control ({mode}): resume to take over",
            )

    def link_lost(self) -> None:
        self.link_ok = False
        if self.state in AIRBORNE_CONTROLLED:
            self._clear_goals()
            self._go(FlightState.LINK_LOST, "autopilot heartbeat lost")
        elif self.state is FlightState.TAKEOFF:  # pragma: no cover - TAKEOFF is controlled
            self._go(FlightState.LINK_LOST, "autopilot heartbeat lost")

    def link_restored(self) -> None:
        """The link is back; nothing changes until a command says so."""
        self.link_ok = True

    def depth_lost(self, why: str = "no depth frames") -> None:
        self._hold(HOLD_DEPTH, why)

    def depth_restored(self) -> None:
        self._release(HOLD_DEPTH, "depth frames back")

    def clock_out_of_bound(self, detail: str) -> None:
        """A peer's (or the ground station's) clock differs from ours by more than the bound:
        peers' trajectories and common start times cannot be trusted, so the drone refuses to
        fly in formation (hovers, goals refused) and says why until the clocks agree again."""
        self.clock_problem = detail
        self._hold(HOLD_CLOCK, f"refusing formation flight: {detail}")

    def clock_in_bound(self) -> None:
        self.clock_problem = None
        self._release(HOLD_CLOCK, "clocks within bound again")

    def plan_failed(self, status: str, hover: bool = True) -> None:
        """A replan returned 'kept-previous' or 'emergency': hover, retry later (``hover``
        False: no hover, the trajectory in control flies on and the next replan comes on its
        grid); failing for ``max_failed_s`` in a row: EMERGENCY."""
        now = self.clock()
        if self._failing_since_s is None:
            self._failing_since_s = now
        if now - self._failing_since_s >= self.params.max_failed_s and self.state in (
            FlightState.HOVER,
            FlightState.FORMATION_FLIGHT,
        ):
            self._clear_goals()
            self._go(
                FlightState.EMERGENCY, f"planning failing for {now - self._failing_since_s:.1f} s"
            )
            return
        if hover and (self.state is FlightState.FORMATION_FLIGHT or self.paused):
            self._retry_at_s = now + self.params.retry_after_s
            self._hold(HOLD_PLAN, f"plan {status}: hover, retry")

    def retry_now(self, reason: str) -> bool:
        """The retry of a failed plan at once instead of ``retry_after_s`` into its hover: the
        monitor found the hover in a conflict (a peer coming at it: one that does not hear us
        flies through where we hold). True when a failed plan's hover was cut short (the
        failure clock of ``max_failed_s`` runs on)."""
        if HOLD_PLAN not in self.holds:
            return False
        self._release(HOLD_PLAN, reason)
        return True

    def plan_ok(self) -> None:
        self._failing_since_s = None

    def gcs_lost(self) -> None:
        if not self.gcs_ok:
            return
        self.gcs_ok = False
        self.waypoints.clear()  # finish the current goal only
        self._gcs_lost_policy()

    def gcs_restored(self) -> None:
        self.gcs_ok = True

    def _gcs_lost_policy(self) -> None:
        if (
            not self.gcs_ok
            and self.params.gcs_lost_action == "land"
            and self.state is FlightState.HOVER
            and self.goal is None
        ):
            self._go(FlightState.LANDING, "ground station lost: land")

    def _hold(self, name: str, reason: str) -> None:
        self.holds.add(name)
        if self.state is FlightState.FORMATION_FLIGHT:
            self._go(FlightState.HOVER, reason)

    def _release(self, name: str, reason: str) -> None:
        if name not in self.holds:
            return
        self.holds.discard(name)
        if name == HOLD_PLAN:
            self._retry_at_s = math.inf
        if not self.holds and self.state is FlightState.HOVER and self.goal is not None:
            self._go(FlightState.FORMATION_FLIGHT, reason)

    def tick(self) -> None:
        """Time-driven transitions: formation and goal activation at their effective times,
        plan retry, emergency landing."""
        self._activate_assignment()
        self._activate_goals()
        now = self.clock()
        if HOLD_PLAN in self.holds and now >= self._retry_at_s:
            self._release(HOLD_PLAN, "retrying the plan")
        if (
            self.state is FlightState.EMERGENCY
            and now - self.since_s >= self.params.emergency_hover_s
        ):
            self._go(FlightState.LANDING, "emergency: hover time over, landing")
        self._gcs_lost_policy()


def parse_vec3(v: Sequence[float]) -> Vec3:
    return float(v[0]), float(v[1]), float(v[2])
