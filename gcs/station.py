"""The ground-station client of the swarm bus: who is up, commands with acknowledgements, the
latest state of every drone.

:class:`GroundStation` wraps one ground-station :class:`~onboard.comm.zenoh_bus.SwarmNode`
(``drone_id=None``). Drones are discovered by their liveliness tokens. A command goes to every
drone (empty target list) or to some; the station waits for an answer from each addressed drone
that is up, resends the same command (same ``cmd_id`` and issue time) to the silent ones every
``resend_every_s``, and returns a :class:`CommandOutcome` that names the drones that accepted,
refused (with their reasons) or did not answer within ``ack_timeout_s``.

Swarm-wide changes (formation, goal, waypoints) carry one effective global time ``lead_s`` in
the future, the same on every drone, so that drones switch together rather than one after
another as the messages arrive. Formation assignments are made by
:class:`gcs.formations.FormationAssigner` (validated before anything is sent; epochs above any
epoch a drone reports).

The station also listens to formation commands sent by other ground-station processes (a
``swarm-gcs formation`` run while ``swarm-gcs status`` shows the swarm), so that it can report
the formation error of the assignment in force.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from gcs.formations import (
    DEFAULT_MIN_SPACING_M,
    Assignment,
    FormationAssigner,
    FormationError,
    formation_errors,
)
from onboard.comm.wire import (
    Abort,
    Action,
    Command,
    Envelope,
    FormationAssignment,
    Goal,
    Land,
    LinkHealth,
    Rejected,
    Resume,
    StateBody,
    StatusBody,
    Takeoff,
    Waypoints,
    decode,
    kind_of,
)
from onboard.comm.zenoh_bus import BusConfig, SwarmNode
from onboard.comm.zenoh_session import ZenohEndpoints, open_session
from onboard.config import Formation

log = logging.getLogger(__name__)


class StationError(RuntimeError):
    """A command that cannot be sent (no drone up, unknown drone, closed station)."""


@dataclass(frozen=True)
class StationConfig:
    """ack_timeout_s: how long to wait for every addressed drone's answer; resend_every_s: resend
    period to the drones that have not answered; lead_s: how far in the future swarm-wide
    changes take effect (longer than a normal acknowledgement round trip); min_spacing_m:
    closest two formation points may be; bus: the node's settings."""

    ack_timeout_s: float = 3.0
    resend_every_s: float = 0.5
    lead_s: float = 1.5
    min_spacing_m: float = DEFAULT_MIN_SPACING_M
    bus: BusConfig = field(default_factory=BusConfig)

    def __post_init__(self) -> None:
        for name in ("ack_timeout_s", "resend_every_s", "min_spacing_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"station.{name} must be > 0, got {v}")
        if not (math.isfinite(self.lead_s) and self.lead_s >= 0.0):
            raise ValueError(f"station.lead_s must be >= 0, got {self.lead_s}")


@dataclass(frozen=True)
class CommandOutcome:
    """What became of one command.

    addressed: the drones expected to answer (the targets, or every drone up when the command
    went to all); accepted / rejected (id -> reason) / missing: their answers; sends: how many
    times it was sent; effective_s: the common switch time of a swarm-wide change (None for
    immediate commands)."""

    cmd_id: int
    action: str
    addressed: tuple[int, ...]
    accepted: tuple[int, ...]
    rejected: Mapping[int, str]
    missing: tuple[int, ...]
    sends: int
    effective_s: float | None = None

    @property
    def ok(self) -> bool:
        """Every addressed drone accepted."""
        return not self.rejected and not self.missing and bool(self.accepted)

    def describe(self) -> str:
        """One line for an operator."""
        head = f"{self.action} (command {self.cmd_id}) to drones {list(self.addressed)}"
        if self.ok:
            return f"{head}: accepted by all"
        parts = [f"accepted by {list(self.accepted)}"] if self.accepted else []
        for d, why in sorted(self.rejected.items()):
            parts.append(f"REFUSED by {d}: {why}")
        if self.missing:
            parts.append(f"NO ANSWER from {list(self.missing)}")
        return f"{head}: " + "; ".join(parts)

    def to_json(self) -> dict[str, Any]:
        return {
            "cmd_id": self.cmd_id,
            "action": self.action,
            "addressed": list(self.addressed),
            "accepted": list(self.accepted),
            "rejected": {str(k): v for k, v in sorted(self.rejected.items())},
            "missing": list(self.missing),
            "sends": self.sends,
            "effective_s": self.effective_s,
            "ok": self.ok,
        }


@dataclass(frozen=True)
class DroneView:
    """What the ground station knows of one drone (None: not heard yet).

    state_age_s / status_age_s: seconds since the last state / status arrived; links: the
    drone's own view of its links; counters: its bus and service counters."""

    drone_id: int
    alive: bool
    flight_state: str | None = None
    position_m: tuple[float, float, float] | None = None
    velocity_m_s: tuple[float, float, float] | None = None
    armed: bool | None = None
    autopilot_mode: str | None = None
    slot: int | None = None
    formation_epoch: int | None = None
    state_age_s: float | None = None
    battery_v: float | None = None
    battery_remaining: float | None = None
    links: tuple[LinkHealth, ...] = ()
    plan_status: str | None = None
    plan_stamp_s: float | None = None
    plan_ms_last: float | None = None
    plan_ms_max: float | None = None
    replans: int | None = None
    counters: Mapping[str, int] = field(default_factory=dict)
    message: str = ""
    status_age_s: float | None = None
    clock_offset_s: float | None = None

    @property
    def speed_m_s(self) -> float | None:
        v = self.velocity_m_s
        return None if v is None else float(math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2))

    def links_text(self) -> str:
        """``ok`` when every link is up, else the names of those down."""
        if not self.links:
            return "-"
        down = [ln.name for ln in self.links if not ln.up]
        return "ok" if not down else "down: " + ",".join(down)

    def bus_text(self) -> str:
        c = self.counters
        if not c:
            return "-"
        tx = sum(v for k, v in c.items() if k.startswith("tx."))
        rx = sum(v for k, v in c.items() if k.startswith("rx."))
        rej = sum(v for k, v in c.items() if k.startswith("reject."))
        return f"tx {tx} rx {rx} rej {rej}"

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.drone_id,
            "alive": self.alive,
            "flight_state": self.flight_state,
            "position_m": None if self.position_m is None else list(self.position_m),
            "velocity_m_s": None if self.velocity_m_s is None else list(self.velocity_m_s),
            "speed_m_s": self.speed_m_s,
            "armed": self.armed,
            "autopilot_mode": self.autopilot_mode,
            "slot": self.slot,
            "formation_epoch": self.formation_epoch,
            "state_age_s": self.state_age_s,
            "battery_v": self.battery_v,
            "battery_remaining": self.battery_remaining,
            "links": [{"name": ln.name, "up": ln.up, "age_s": ln.age_s} for ln in self.links],
            "plan_status": self.plan_status,
            "plan_stamp_s": self.plan_stamp_s,
            "plan_ms_last": self.plan_ms_last,
            "plan_ms_max": self.plan_ms_max,
            "replans": self.replans,
            "counters": dict(self.counters),
            "message": self.message,
            "status_age_s": self.status_age_s,
            "clock_offset_s": self.clock_offset_s,
        }


class GroundStation:
    """A ground station on the swarm ``swarm``.

    endpoints: how to join Zenoh (``ZenohEndpoints``), or pass an open ``session`` (then the
    caller closes it); clock: global time (the system clock, which drones keep in sync with
    chrony). Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        swarm: str,
        endpoints: ZenohEndpoints | None = None,
        *,
        config: StationConfig | None = None,
        clock: Callable[[], float] = time.time,
        session: Any = None,
    ) -> None:
        self.config = cfg = config if config is not None else StationConfig()
        self.clock = clock
        self._owns_session = session is None
        self._session = open_session(endpoints) if session is None else session
        self._lock = threading.Lock()
        self._alive_changed = threading.Condition(self._lock)
        self._known: FormationAssignment | None = None
        self._known_name = ""
        self._entities: list[Any] = []
        self.assigner = FormationAssigner(clock, cfg.lead_s, cfg.min_spacing_m)
        self.outcomes: list[CommandOutcome] = []
        try:
            self.node = SwarmNode(swarm, None, session=self._session, config=cfg.bus, clock=clock)
            self.node.on_alive(self._on_alive)
            self.node.on_state(self._on_state)
            self._entities.append(
                self._session.declare_subscriber(
                    self.node.keys.cmd("formation"),
                    self._on_formation_cmd,
                    allowed_origin=zenoh.Locality.REMOTE,
                )
            )
        except BaseException:
            self.close()
            raise

    # --- lifecycle -------------------------------------------------------------------------

    def close(self) -> None:
        """Leave the bus (idempotent)."""
        for e in self._entities:
            try:
                e.undeclare()
            except Exception:  # the session may already be gone
                log.debug("undeclare failed during close", exc_info=True)
        self._entities.clear()
        node = getattr(self, "node", None)
        if node is not None:
            node.close()
        if self._owns_session and self._session is not None:
            self._session.close()
            self._session = None
        with self._lock:
            self._alive_changed.notify_all()

    def __enter__(self) -> GroundStation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def swarm(self) -> str:
        return self.node.keys.swarm

    # --- callbacks (Zenoh threads) ---------------------------------------------------------

    def _on_alive(self, kind: str, drone: int | None, up: bool) -> None:
        with self._lock:
            self._alive_changed.notify_all()

    def _on_state(self, env: Envelope, _rx: float) -> None:
        body = env.body
        if isinstance(body, StateBody) and body.formation_epoch > 0:
            with self._lock:
                self.assigner.observe_epoch(body.formation_epoch)

    def _on_formation_cmd(self, sample: Any) -> None:
        try:
            env = decode(sample.payload.to_bytes(), self.node.config.limits, kind="cmd")
        except Rejected as r:
            log.debug("ignored a formation command from another station: %s", r)
            return
        body = env.body
        if isinstance(body, Command) and isinstance(body.action, FormationAssignment):
            with self._lock:
                if self._known is None or body.action.epoch > self._known.epoch:
                    self._known = body.action
                    self._known_name = ""
                self.assigner.observe_epoch(body.action.epoch)

    # --- discovery -------------------------------------------------------------------------

    def drones(self) -> set[int]:
        """Drones whose liveliness token is up."""
        return self.node.alive_drones()

    def wait_for_drones(
        self,
        count: int | None = None,
        ids: Sequence[int] | None = None,
        timeout_s: float = 5.0,
        with_state: bool = False,
    ) -> set[int]:
        """Wait (real time) until ``count`` drones (or every drone of ``ids``) are up and, with
        ``with_state``, have reported a state; returns the drones up at the end (the caller
        checks whether that is enough). Without ``count`` and ``ids``: wait ``timeout_s`` for
        the first drone."""
        deadline = time.monotonic() + timeout_s
        want = set(ids) if ids is not None else None
        while True:
            up = self.drones()
            if with_state:
                up &= set(self.node.latest_states())
            if want is not None:
                done = want <= up
            elif count is not None:
                done = len(up) >= count
            else:
                done = bool(up)
            left = deadline - time.monotonic()
            if done or left <= 0:
                return up
            with self._lock:
                # liveliness changes notify; states do not, so wake up regularly too
                self._alive_changed.wait(min(left, 0.05))

    # --- commands --------------------------------------------------------------------------

    def send(
        self,
        action: Action,
        targets: Sequence[int] | None = None,
        *,
        timeout_s: float | None = None,
    ) -> CommandOutcome:
        """Send ``action`` to ``targets`` (None: every drone), collect the answers and resend to
        the silent drones until every addressed drone answered or ``timeout_s`` (default
        ``config.ack_timeout_s``) passed. Raises :class:`StationError` when nobody is up to
        answer."""
        cfg = self.config
        timeout = cfg.ack_timeout_s if timeout_s is None else float(timeout_s)
        if targets is not None and len(targets) == 0:
            raise StationError("an empty list of target drones")
        addressed = sorted(set(targets)) if targets is not None else sorted(self.drones())
        if not addressed:
            raise StationError(f"no drone is up on swarm {self.swarm!r}")
        tag = kind_of(action)
        cmd = self.node.send_command(action, [] if targets is None else addressed)
        sends = 1
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            missing = self.node.wait_acks(
                cmd.cmd_id, addressed, max(0.0, min(cfg.resend_every_s, left))
            )
            if not missing or time.monotonic() >= deadline or self.node.closed:
                break
            self.node.send_command(
                action, sorted(missing), cmd_id=cmd.cmd_id, issued_s=cmd.issued_s
            )
            sends += 1
        answers = self.node.acks(cmd.cmd_id)
        outcome = CommandOutcome(
            cmd_id=cmd.cmd_id,
            action=tag,
            addressed=tuple(addressed),
            accepted=tuple(d for d in addressed if d in answers and answers[d].accepted),
            rejected={
                d: answers[d].reason for d in addressed if d in answers and not answers[d].accepted
            },
            missing=tuple(d for d in addressed if d not in answers),
            sends=sends,
            effective_s=getattr(action, "effective_s", None),
        )
        self.outcomes.append(outcome)
        log.log(logging.INFO if outcome.ok else logging.WARNING, "%s", outcome.describe())
        return outcome

    def effective_time(self) -> float:
        """The common switch time of a swarm-wide change sent now."""
        return float(self.clock()) + self.config.lead_s

    def takeoff(
        self, altitude_m: float, targets: Sequence[int] | None = None, **kw: Any
    ) -> CommandOutcome:
        return self.send(Takeoff(float(altitude_m)), targets, **kw)

    def land(self, targets: Sequence[int] | None = None, **kw: Any) -> CommandOutcome:
        return self.send(Land(), targets, **kw)

    def abort(self, targets: Sequence[int] | None = None, **kw: Any) -> CommandOutcome:
        """Every addressed drone stops and hovers, then lands."""
        return self.send(Abort(), targets, **kw)

    def resume(self, targets: Sequence[int] | None = None, **kw: Any) -> CommandOutcome:
        return self.send(Resume(), targets, **kw)

    def goal(
        self,
        position_m: Sequence[float],
        yaw_rad: float | None = None,
        targets: Sequence[int] | None = None,
        **kw: Any,
    ) -> CommandOutcome:
        """Fly the formation's centre to ``position_m`` (ENU), switching at one common time."""
        p = _vec3("goal", position_m)
        if yaw_rad is not None and not math.isfinite(yaw_rad):
            raise StationError(f"goal yaw {yaw_rad} is not finite")
        return self.send(Goal(p, yaw_rad, self.effective_time()), targets, **kw)

    def waypoints(
        self,
        points_m: Sequence[Sequence[float]],
        targets: Sequence[int] | None = None,
        **kw: Any,
    ) -> CommandOutcome:
        """Fly the formation's centre through ``points_m`` (ENU), from one common time."""
        pts = [_vec3(f"waypoint {i}", p) for i, p in enumerate(points_m)]
        if not pts:
            raise StationError("no waypoints")
        return self.send(Waypoints(pts, self.effective_time()), targets, **kw)

    def positions(self, ids: Sequence[int] | None = None) -> dict[int, np.ndarray]:
        """The latest reported position of every drone up (or of ``ids``) that reported one."""
        states = self.node.latest_states()
        want = self.drones() if ids is None else set(ids)
        out = {}
        for d in sorted(want):
            body = states[d][0].body if d in states else None
            if isinstance(body, StateBody):
                out[d] = np.asarray(body.position_m, dtype=np.float64)
        return out

    def plan_formation(
        self,
        formation: Formation | str | Path,
        *,
        scale: float = 1.0,
        yaw_rad: float | None = None,
        drones: Sequence[int] | None = None,
    ) -> Assignment:
        """A validated assignment of ``formation`` to the drones up (or ``drones``) from their
        reported positions, turned by ``yaw_rad`` (None: the turn nearest in total travel,
        :func:`gcs.formations.best_yaw`); raises :class:`gcs.formations.FormationError` and
        sends nothing on any problem."""
        up = self.drones()
        ids = sorted(up) if drones is None else sorted(set(drones))
        down = sorted(set(ids) - up)
        if down:
            raise FormationError(f"drones {down} are not up (up: {sorted(up)})")
        pos = self.positions(ids)
        silent = sorted(set(ids) - set(pos))
        if silent:
            raise FormationError(f"drones {silent} have not reported a position yet")
        with self._lock:
            return self.assigner.assign(formation, pos, scale=scale, yaw_rad=yaw_rad, drones=drones)

    def formation(
        self,
        formation: Formation | str | Path,
        *,
        scale: float = 1.0,
        yaw_rad: float | None = None,
        drones: Sequence[int] | None = None,
        **kw: Any,
    ) -> tuple[Assignment, CommandOutcome]:
        """Validate, assign slots (Hungarian, from the current positions) and send a formation to
        the drones up (or ``drones``), effective at one common time."""
        a = self.plan_formation(formation, scale=scale, yaw_rad=yaw_rad, drones=drones)
        wire = a.to_wire()
        outcome = self.send(wire, sorted(a.slots), **kw)
        with self._lock:
            if self._known is None or wire.epoch >= self._known.epoch:
                self._known = wire
                self._known_name = a.name
        return a, outcome

    # --- what the drones report ------------------------------------------------------------

    def known_formation(self) -> tuple[str, FormationAssignment] | None:
        """The newest formation assignment sent by this or another ground station: (template
        name, '' when it came from elsewhere; the wire action)."""
        with self._lock:
            return None if self._known is None else (self._known_name, self._known)

    def views(self) -> dict[int, DroneView]:
        """Every drone up or heard from, by id."""
        now = float(self.clock())
        alive = self.drones()
        states = self.node.latest_states()
        statuses = self.node.latest_statuses()
        clocks = self.node.clock_report()
        out: dict[int, DroneView] = {}
        for d in sorted(alive | set(states) | set(statuses)):
            kw: dict[str, Any] = {"drone_id": d, "alive": d in alive}
            if d in states and isinstance(states[d][0].body, StateBody):
                env, rx = states[d]
                s = env.body
                assert isinstance(s, StateBody)
                kw.update(
                    flight_state=s.flight_state,
                    position_m=tuple(s.position_m),
                    velocity_m_s=tuple(s.velocity_m_s),
                    armed=s.armed,
                    autopilot_mode=s.autopilot_mode,
                    slot=s.slot,
                    formation_epoch=s.formation_epoch,
                    state_age_s=max(0.0, now - rx),
                )
            if d in statuses and isinstance(statuses[d][0].body, StatusBody):
                env, rx = statuses[d]
                st = env.body
                assert isinstance(st, StatusBody)
                kw.update(
                    battery_v=st.battery_v,
                    battery_remaining=st.battery_remaining,
                    links=tuple(st.links),
                    plan_status=st.plan_status,
                    plan_stamp_s=st.plan_stamp_s,
                    plan_ms_last=st.plan_ms_last,
                    plan_ms_max=st.plan_ms_max,
                    replans=st.replans,
                    counters=dict(st.counters),
                    message=st.message,
                    status_age_s=max(0.0, now - rx),
                )
                if "flight_state" not in kw:
                    kw["flight_state"] = st.flight_state
            if d in clocks:
                kw["clock_offset_s"] = clocks[d].offset_s
            out[d] = DroneView(**kw)
        return out

    def formation_error(self) -> tuple[float, float] | None:
        """(e_dist [m], e_sim) of the drones up against the newest known assignment (None when
        no assignment is known or fewer than 2 of its drones reported a position)."""
        known = self.known_formation()
        if known is None:
            return None
        wire = known[1]
        return formation_errors(
            self.positions(list(wire.slots)), wire.slots, np.asarray(wire.points_m)
        )


def _vec3(name: str, v: Sequence[float]) -> tuple[float, float, float]:
    if len(v) != 3:
        raise StationError(f"{name} must have 3 coordinates (x y z), got {len(v)}")
    p = (float(v[0]), float(v[1]), float(v[2]))
    if not all(math.isfinite(x) for x in p):
        raise StationError(f"{name} {list(p)} is not finite")
    return p
