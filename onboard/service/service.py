"""The flight service of one drone: the loops around the flight state machine.

Threads (each loop is a ``*_step`` method the tests call directly with an injected clock):

- the autopilot link's own receive and setpoint threads (``AutopilotPort``): the setpoint thread
  calls ``sample_setpoint`` at 50 Hz, which only evaluates the trajectory in control (no lock
  held by anyone for long, no I/O);
- ``depth``: frames at camera rate into the rolling map; the planner's ESDF snapshot refreshed
  at ``mapping.esdf_rate_hz`` (a new immutable field object each time: the planner and the
  monitor always read a consistent one);
- ``planner``: the per-drone cycle, ``onboard.agent.DroneAgent`` — the same class the fast-time
  simulator runs N of: a replan on the agent's grid every ``planning.replan_period_s`` and at
  once when asked (new goal or formation at its effective time, the monitor's prediction); the
  agent publishes every new trajectory and schedules it; the service's policy for the outcome
  (geofence, hover-and-retry, emergency) hangs on the agent's ``on_plan``. While the drone is
  airborne without a goal, the trajectory in control is re-announced every period so that
  peers keep avoiding it;
- ``monitor``: at ``planning.monitor_rate_hz`` the trajectory in control is checked against the
  map, the peers as the agent avoids them (``DroneAgent.peer_view``: their latest trajectories,
  the silent peers' ghosts, where deviating peers reported themselves) and the geofence over
  ``monitor_horizon_s``; a predicted conflict asks for a replan at once, and if a fresh plan
  still meets it less than ``onboard.agent.MONITOR_BRAKE_WITHIN_S`` ahead, brakes (further
  ahead, another replan 0.3 s later); an obstacle that comes within the check's distance by
  less than ``planning.monitor_obstacle_slack_m`` only asks for replans;
- ``actions``: autopilot commands that wait for acknowledgements (offboard, arm, land), so the
  main loop never blocks;
- the main loop (``main_step``): ground-station commands, the reactions, the peers' states
  handed to the agent as signs of life (``reactions.peer_lost``: a peer that falls silent or
  leaves its trajectory asks for a replan at once), the state machine's timers, state (10 Hz)
  and status (1 Hz) publishing, the flight record, the watchdog.

Only the main loop touches the state machine; the other threads read an immutable ``Intent``
that it publishes, and post their results back through a queue. The trajectory in control is
the agent's (``agent.flying``/``advance``); the service overrides it (take-off climb, braking
stop, hover) through ``_control``, and a plan whose cycle began before an override never
replaces it.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from onboard.agent import (
    MONITOR_REPLAN_AFTER_S,
    MONITOR_RETRY_S,
    DroneAgent,
    PeerView,
    PlanReport,
    monitor_action,
    monitor_step_index,
    monitor_times,
    obstacle_conflict,
    peer_conflict,
    peer_links,
    replan_asked_s,
    same_peers,
)
from onboard.comm.hearing import not_hearing
from onboard.jitcache import kernel_census, kernels_added
from onboard.planner.planner import APPROACH, LAST_RESORT, PlanStatus
from onboard.planner.trajectory import Trajectory
from onboard.record import FlightRecorder, flight_file_name
from onboard.sensors.simulated import heading_yaw, look_velocity
from onboard.service.config import OnboardConfig
from onboard.service.logs import event
from onboard.service.planning import (
    FieldSource,
    PortPeerBus,
    StateRelay,
    WarmUp,
    inside_box,
    warm_up,
)
from onboard.service.ports import (
    AutopilotPort,
    CommandFailed,
    IncomingCommand,
    Setpoint,
    SwarmBusPort,
    VehicleSnapshot,
    braking_trajectory,
    climb_trajectory,
)
from onboard.service.sdnotify import Notifier
from onboard.service.state import (
    AIRBORNE_CONTROLLED,
    COMMANDING,
    HOLD_PLAN,
    Assignment,
    Command,
    CommandResult,
    FlightState,
    FlightStateMachine,
    Goal,
    MachineParams,
    Transition,
    Waypoints,
)
from onboard.threadname import named_thread, set_os_thread_name

log = logging.getLogger("onboard.service")

S = FlightState
_OK = (PlanStatus.OK, PlanStatus.OK_NO_FORMATION)
HOLDING_STILL_M = 0.01
"""A plan whose positions over the monitor's horizon stay within this (and whose velocity is
nil now) holds still: the monitor does not brake it (see ``monitor_step``)."""
ANSWERS_KEPT = 256
"""The answers to this many recent commands are kept, so that a resend of one (the ground
station resends what it heard no answer to) is answered again, not applied again."""


@dataclass(frozen=True)
class Intent:
    """What the main loop wants the planner to do (immutable; swapped as a whole)."""

    state: FlightState
    goal: np.ndarray | None = None
    """This drone's own goal: the formation goal plus its slot's offset."""
    slot: int = -1
    epoch: int = -1
    points: tuple[tuple[float, float, float], ...] = ()
    held_for_retry: bool = False
    """The hover of a failed plan, which is retried later (``FlightStateMachine.retry_now``
    retries it at once)."""


@dataclass
class Health:
    """Last time each worker thread reported (monotonic seconds)."""

    beats: dict[str, float] = field(default_factory=dict)

    def beat(self, name: str) -> None:
        self.beats[name] = time.monotonic()

    def stalled(self, stall_s: float) -> list[str]:
        now = time.monotonic()
        return [k for k, t in self.beats.items() if now - t > stall_s]


class FlightService:
    """One drone's service. Edges are passed in (``autopilot``, ``bus``, ``depth`` a
    ``onboard.sensors.DepthSource`` or None); ``clock`` is global time (seconds); ``warming``:
    a planner warm-up already started (``WarmUp``), waited for before READY."""

    def __init__(
        self,
        config: OnboardConfig,
        autopilot: AutopilotPort,
        bus: SwarmBusPort,
        depth: Any = None,
        clock: Callable[[], float] = time.time,
        notifier: Notifier | None = None,
        record_dir: Path | None = None,
        warming: WarmUp | None = None,
    ) -> None:
        self.cfg = config
        self.id = config.drone.id
        self.ap = autopilot
        self.bus = bus
        self.depth = depth
        self.clock = clock
        self.notifier = notifier if notifier is not None else Notifier()
        rec = config.record
        self.record_dir = record_dir if record_dir is not None else Path(rec.directory)
        self._record_enabled = rec.enabled
        gf = config.geofence
        self.machine = FlightStateMachine(
            self.id,
            clock,
            MachineParams(
                emergency_hover_s=config.flight.emergency_hover_s,
                retry_after_s=config.planning.retry_after_s,
                max_failed_s=config.planning.max_failed_s,
                gcs_lost_action=config.reactions.gcs_lost.action,
            ),
            inside_geofence=lambda p: gf.contains(self._own_goal(np.asarray(p, dtype=float))),
            listener=self._on_transition,
        )
        pc = config.planning
        rc = config.reactions.peer_lost
        # the planner's side thread (``planning.side_thread``), owned here, shut down in stop()
        self._side_pool = (
            ThreadPoolExecutor(
                max_workers=1,
                thread_name_prefix="svc-side",
                initializer=set_os_thread_name,
                initargs=("svc-side",),
            )
            if pc.side_thread
            else None
        )
        # the per-drone cycle: the same class the fast-time simulator runs. Until a formation is
        # assigned it holds a one-point template; until take-off nothing is in control.
        self.agent = DroneAgent(
            self.id,
            config.planner,
            np.zeros((1, 3)),
            0,
            Trajectory.hover(np.zeros(3), clock(), 1.0),
            PortPeerBus(bus),
            FieldSource(self.field),
            replan_period_s=pc.replan_period_s,
            plan_ahead_s=pc.plan_ahead_s,
            validity_s=rc.validity_s,
            peer_forget_s=rc.avoid_for_s,
            peer_silence_s=rc.peer_silence_s,
            peer_silence_in_way_s=rc.peer_silence_in_way_s,
            peer_silence_max_s=rc.peer_silence_max_s,
            ghost_window_s=rc.ghost_window_s,
            ghost_forget_s=rc.ghost_forget_s,
            peer_deviation_m=rc.peer_deviation_m,
            peer_deviation_ahead_s=rc.peer_deviation_ahead_s,
            avoid_reported=True,  # a peer with states but no trajectory (stuck long, by hand)
            on_plan=self._on_plan,
            clock=clock,  # a plan that comes back after its start may not be flown
            plan_budget_s=pc.plan_budget_s,
            resend_s=pc.resend_s,
            resend_plans=pc.resend_plans,
            side=self._side_pool,
        )
        self._frame_reject_reason = ""
        self._relay = StateRelay(bus, self.agent)  # the peers' states: their signs of life
        self.peer_view: PeerView | None = None
        """The peers as the agent avoids them, at the last look (``peers_now``)."""
        self._view_at = -math.inf  # when peer_view was last computed (it may be older)
        self._logged_view: PeerView | None = None
        self._view_age_s = 0.5 / config.bus.state_rate_hz
        self._agent_assignment: Assignment | None = None
        self._transitions: list[Transition] = []
        self._intent = Intent(S.IDLE)
        self._results: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._actions: queue.Queue[tuple[str, Callable[[], None]] | None] = queue.Queue()
        self._wake = threading.Event()  # the planner thread: a replan or an announcement asked
        self._stop = threading.Event()
        # overrides of the trajectory in control (take-off, braking, hover) against plans
        self._ctl_lock = threading.Lock()
        self._in_control = False  # nothing is in control before the first override
        self._gen = 0  # overrides so far
        self._cycle_gen = 0  # overrides when the running cycle began
        self._override: Trajectory | None = None
        self._announce = False
        self._last_pub_s = -math.inf
        self._yaw = 0.0
        self._field: Any = None
        self._ground_field: Any = None
        self.mapper: Any = None
        self._last_frame_s = -math.inf
        self._last_frame_stamp = -math.inf
        self._read_stamp = -math.inf  # the last frame the depth thread ingested (mapped or not)
        self._arrival_stamp: float | None = None  # the newest frame the source told of
        self._last_arrival_s = -math.inf  # when that moved on (frames arriving)
        self._map_lag_riding = False  # the map over timeout_s behind a live camera
        self._next_esdf_s = -math.inf  # the ESDF refresh's next deadline (a fixed phase)
        self._offboard_seen = False
        self._land_seen = False
        self._depth_lost = False
        self._depth_back_since: float | None = None  # first frame after a loss
        self._link_ok = True
        self._gcs_ok = True
        self._started_s = clock()
        self._last_state_pub = -math.inf
        self._last_status_pub = -math.inf
        self._last_plan_s = -math.inf
        self._last_map_record_s = -math.inf
        self._monitor_brake_at = -math.inf
        self._braking_retry_for = -math.inf  # the brake whose hover was retried early
        self._monitor_retry_s = -math.inf  # when the monitor last cut a failed plan's hover
        self._monitor_asked_s = -math.inf  # when the monitor asked for the replan awaited
        # the monitor's last check: (field, peers view, plan, 0.1 s grid step) -> problem
        self._monitor_key: tuple[object, ...] = ()
        # the conflict found for _monitor_key, whether that plan holds still, whether a
        # braking stop would come less close than it (else the monitor does not brake), and a
        # shallow obstacle conflict (within the check's distance, not its slack) when no other
        self._monitor_problem: tuple[str, float, bool, bool, str] = (
            "", math.inf, False, True, ""
        )  # fmt: skip
        self._plan_ms: list[float] = []
        self._plan_status = ""
        self._plan_stamp: float | None = None
        self._last_event = ""
        self.recorder: FlightRecorder | None = None
        self.health = Health()
        self._answers: OrderedDict[tuple[int, int], CommandResult] = OrderedDict()
        self.counters: dict[str, int] = {
            "replans": 0,
            "plans_failed": 0,
            "plans_late": 0,  # came back after their start too far off the flown one: not flown
            "plans_over_budget": 0,  # gave up retrying at plan_budget_s: the safe plan flies on
            "monitor_replans": 0,
            "monitor_brakes": 0,
            "monitor_shallow_replans": 0,  # asked for an obstacle within the brake's slack
            "monitor_braking_retries": 0,
            "monitor_holding": 0,
            "monitor_no_better_stop": 0,
            "plans_last_resort": 0,
            "plans_approach": 0,  # flown toward a conflict over APPROACH_S ahead, to look again
            "frames": 0,
            "frames_rejected": 0,
            "frames_missed": 0,
            "depth_holds": 0,  # holds for lost depth, for a silent camera or a lagging map
            "map_lag_holds": 0,  # of those: a live camera, the map over map_lag_s behind
            "map_lag_rides": 0,  # the map over timeout_s behind a live camera, no hold (yet)
            "esdf_builds": 0,
            "esdf_skipped": 0,  # refreshes that kept the field (nothing it reads changed)
            "esdf_new_buffer_sets": 0,
            "commands": 0,
            "commands_rejected": 0,
            "commands_repeated": 0,  # resends answered with the first answer, not applied again
            "setpoints_sampled": 0,
            # peers now (gauges): silent, reported off their trajectory, ghost hovers avoided
            "peers_silent": 0,
            "peers_deviating": 0,
            "peer_ghosts": 0,
            "peers_not_hearing_us": 0,  # their statuses say they do not hear us (a gauge)
            # peers that fell silent / left their trajectory so far
            "peers_fell_silent": 0,
            "peers_left_trajectory": 0,
            "peers_stopped_hearing_us": 0,
            "plans_superseded": 0,
            "announcements": 0,
            "resent": 0,
            "map_occupied_cells": 0,
            "kernels_after_ready": 0,  # numba kernels compiled or loaded in flight (_check_kernels)
            "stream_guard_stops": 0,  # stops by the setpoint thread, the monitor silent
            "stream_gap_stops": 0,  # stops by the setpoint thread after a pause of its own
            # CPU time of each worker thread, microseconds (time.thread_time)
            "cpu_us.depth_ingest": 0,
            "cpu_us.esdf": 0,
            "cpu_us.planner": 0,
            "cpu_us.monitor": 0,
            "cpu_us.main": 0,
        }
        self.ready = False
        self._threads: list[threading.Thread] = []
        self.stuck_threads: list[str] = []
        """Workers that had not ended 5 s after ``stop`` (see ``stop``)."""
        self._climbing = False
        """The take-off's climb is in control (set by the actions thread after arming; cleared
        on entering TAKEOFF): until then the trajectory in control is the hold on the ground
        that PX4's OFFBOARD needs streamed first, which must not count as the take-off reached."""
        self._warm_s = 0.0
        self._warming = warming
        self._kernels_at_ready: dict[str, int] | None = None
        """The numba kernels' compiled versions when READY (``jitcache.kernel_census``): a
        kernel compiled or loaded later is one the warm-up missed (``_check_kernels``)."""
        self._kernels_added: dict[str, int] = {}
        self._guard_fired = False
        """The setpoint thread has put a stop in control while the monitor is silent
        (``_stream_guard``); False again once the monitor looks."""
        self._guard_note: tuple[str, float] | None = None
        """(what, the gap or the monitor's silence in s) of the setpoint thread's last stop,
        for the main loop's log."""
        self._last_sample: tuple[float, np.ndarray, np.ndarray] | None = None
        """(time, position, velocity) of the last setpoint sampled (``_stream_guard``)."""
        self._slot_offset: tuple[Any, np.ndarray | None] | None = None
        """(assignment, this drone's slot point minus the template's centroid) (``_own_goal``)."""
        self._last_watchdog = -math.inf

    # ---- geometry helpers --------------------------------------------------------------------
    def _own_goal(self, formation_goal: np.ndarray) -> np.ndarray:
        """The formation goal plus this drone's offset in the formation (its slot's point minus
        the template's centroid); the goal itself when no formation is known."""
        m = self.machine
        a = m.assignment if m.assignment is not None else m.pending
        if a is None:
            return formation_goal
        cached = self._slot_offset
        if cached is not None and cached[0] is a:
            offset = cached[1]
        else:  # once per assignment (the main loop asks three times per step)
            slot = a.slot_of(self.id)
            if slot is None:
                offset = None
            else:
                pts = np.asarray(a.points, dtype=np.float64)
                offset = pts[slot] - pts.mean(axis=0)
            self._slot_offset = (a, offset)
        if offset is None:
            return formation_goal
        return formation_goal + offset

    # ---- trajectory in control (any thread) --------------------------------------------------
    def _control(self, traj: Trajectory) -> None:
        """``traj`` takes control now (take-off, braking stop, hover): the agent's queue is
        dropped, a plan whose cycle is running will not replace it, and peers hear of it."""
        self._take_control(traj)
        if self._intent.state in AIRBORNE_CONTROLLED:
            # now, from this thread, not by the planner thread once its running cycle is done
            # (seconds on a starved CPU, in which the peers would plan around a trajectory this
            # drone no longer flies); a plan that cycle publishes meanwhile is superseded and
            # announced over again by _on_plan
            self._announce_now(self.clock())
        else:
            self._announce = True  # by the planner thread once airborne
        self._wake.set()

    def _take_control(self, traj: Trajectory) -> None:
        """``traj`` in control now, as an override: the agent's queue is dropped and a plan
        whose cycle is running will not replace it (``_on_plan``). No I/O: the setpoint
        thread's guards call it too."""
        with self._ctl_lock:
            self._gen += 1
            self._override = traj
            self.agent.reset(traj)
            self._in_control = True

    def flying(self, t_s: float) -> Trajectory | None:
        """The trajectory in control at ``t_s`` (>= now); None before the first take-off."""
        if not self._in_control:
            return None
        return self.agent.flying(t_s)

    def sample_setpoint(self, t_s: float) -> Setpoint | None:
        """Called by the setpoint thread at 50 Hz: the trajectory in control at ``t_s``."""
        if not self._in_control:
            return None
        traj = self._stream_guard(t_s, self.agent.advance(t_s))
        p, v, a = traj.state(t_s)
        self._last_sample = (t_s, p, v)
        # the camera looks where the drone will be in a second (the vehicle's yaw lags its
        # setpoint in a turn), or, holding still short of its goal, around the goal's direction
        # (the same policy as the simulated drones: what the planner needs observed is ahead)
        look = look_velocity(traj, t_s, p)
        self._yaw = heading_yaw(look, p, self.agent.goal, self._yaw, t_s)
        self.counters["setpoints_sampled"] += 1
        rec = self.recorder
        if rec is not None:
            rec.setpoint(t_s, p, v, a, self._yaw)
        return Setpoint(p, v, a, self._yaw)

    def _stream_guard(self, t_s: float, traj: Trajectory) -> Trajectory:
        """The setpoint thread's guards, in formation flight. (1) A sample more than
        ``planning.stream_gap_s`` after the one before (the whole process stalled): a braking
        stop from the last setpoint sent, not the plan's point of now, which may lie metres
        ahead of the vehicle. (2) The safety monitor's thread silent for over
        ``planning.stream_guard_s``: a stop along ``traj`` from ``t_s``, once until the monitor
        looks again. Either takes control as the service's brakes do (the next plan starts
        from it; a plan cycle running meanwhile does not replace it). Returns the trajectory
        to sample."""
        cfg = self.cfg.planning
        last, self._last_sample = self._last_sample, None
        last_beat = self.health.beats.get("monitor")
        silent_s = math.inf if last_beat is None else time.monotonic() - last_beat
        if silent_s <= cfg.stream_guard_s:
            self._guard_fired = False
        if self._intent.state is not S.FORMATION_FLIGHT:
            return traj
        a_max = self.cfg.planner.a_max_m_s2
        gap_s = math.inf if last is None else t_s - last[0]
        if cfg.stream_gap_s > 0.0 and last is not None and gap_s > cfg.stream_gap_s:
            stop = braking_trajectory(t_s, last[1], last[2], np.zeros(3), a_max)
            note = ("stream_gap_stop", gap_s)
        elif (
            cfg.stream_guard_s > 0.0
            and last_beat is not None
            and silent_s > cfg.stream_guard_s
            and not self._guard_fired
        ):
            p, v, a = traj.state(t_s)
            straight = braking_trajectory(t_s, p, v, a, a_max)
            stop = traj.stop_along(t_s, straight.duration_s) or straight
            note = ("stream_guard_stop", silent_s)
        else:
            return traj
        self._take_control(stop)
        self._guard_fired = True
        self._guard_note = note
        self.counters[f"{note[0]}s"] += 1
        self._announce = True  # by the planner thread when it runs again
        self._wake.set()
        return stop

    # ---- transitions -------------------------------------------------------------------------
    def _on_transition(self, tr: Transition) -> None:
        self._transitions.append(tr)

    def _apply_transitions(self, veh: VehicleSnapshot | None) -> None:
        while self._transitions:
            tr = self._transitions.pop(0)
            event(
                log,
                "transition",
                source=tr.source.value,
                target=tr.target.value,
                reason=tr.reason,
            )
            self._last_event = f"{tr.source.value}->{tr.target.value}: {tr.reason}"
            if tr.target is S.TAKEOFF:
                self._open_record(tr.t_s)
            if self.recorder is not None:
                self.recorder.transition(tr.t_s, tr.source.value, tr.target.value, tr.reason)
            self._enter(tr, veh)
            if tr.target in (S.LANDED, S.IDLE) and self.recorder is not None:
                self._close_record()
        self._publish_intent()

    def _enter(self, tr: Transition, veh: VehicleSnapshot | None) -> None:
        """Actions on entering a state."""
        now = tr.t_s
        target = tr.target
        if target not in COMMANDING:
            self._offboard_seen = False
        if target in (S.PILOT, S.LINK_LOST, S.IDLE, S.LANDED):
            self.ap.stream(None)  # at once: never fight the pilot, never stream blind
            return
        if target is S.TAKEOFF:
            self._climbing = False  # not the last take-off's climb: this one's, once armed
            self._queue_action("takeoff", self._do_takeoff)
            return
        if target is S.LANDING:
            self.ap.stream(None)
            self._land_seen = False
            self._queue_action("land", self.ap.land)
            return
        if target in (S.HOVER, S.EMERGENCY):
            if tr.source in (S.PILOT, S.LINK_LOST) and veh is not None:
                # someone else flew the vehicle: hold where it is, not where the plan was
                self._control(Trajectory.hover(veh.position_m, now, 1.0))
            else:
                self._brake(now, veh, keep_hover=tr.source is S.TAKEOFF)
            if tr.source in (S.PILOT, S.LINK_LOST, S.EMERGENCY) and target is S.HOVER:
                self._queue_action("resume", self._do_resume)
            return
        if target is S.FORMATION_FLIGHT:
            self._ask_replan()

    def _brake(self, now: float, veh: VehicleSnapshot | None, keep_hover: bool = False) -> None:
        """A braking stop from the state of the trajectory in control (or the vehicle): along
        that trajectory's path where it goes on long enough (``Trajectory.stop_along``) unless
        the map puts the straight stop along the velocity further from every obstacle. A
        straight stop cuts the corner of a turn: a drone held for lost depth frames while its
        plan turned round a trunk stopped 0.03 m from it and touched it (the real stack on a
        starved host, BENCHMARKS.md section 10, 2026-12-02)."""
        traj = self.flying(now)
        if keep_hover and traj is not None:
            end = traj.end_position
            self._control(Trajectory.hover(end, now, 1.0))
            return
        if traj is not None:
            p, v, a = traj.state(now)
        elif veh is not None:
            p, v, a = veh.position_m, veh.velocity_m_s, np.zeros(3)
        else:
            return
        straight = braking_trajectory(now, p, v, a, self.cfg.planner.a_max_m_s2)
        along = None if traj is None else traj.stop_along(now, straight.duration_s)
        fld = None if along is None else self.field()
        if along is not None and fld is not None:
            ts = now + np.linspace(0.0, straight.duration_s, 21)
            d, _ = fld.distance(np.concatenate([along.sample(ts), straight.sample(ts)]))
            if float(d[21:].min()) > float(d[:21].min()):
                along = None  # the straight stop keeps further from every obstacle
        self._control(straight if along is None else along)

    def _ask_replan(self) -> None:
        self.agent.request_replan()
        self._wake.set()

    def _publish_intent(self) -> None:
        m = self.machine
        a = m.assignment
        slot = None if a is None else a.slot_of(self.id)
        flying_to = m.state is S.FORMATION_FLIGHT and m.goal is not None and slot is not None
        goal = None if m.goal is None else self._own_goal(np.asarray(m.goal, dtype=float))
        # the agent first (thread-safe setters), then the intent the other threads read
        if a is not None and slot is not None and a is not self._agent_assignment:
            points = np.asarray(a.points, dtype=np.float64)
            if np.array_equal(points, self.agent.formation):
                self.agent.set_slot(slot, a.epoch)  # same template, new epoch
            else:
                self.agent.set_formation(points, slot, a.epoch)
            self._agent_assignment = a
        target = goal if flying_to else None
        current = self.agent.goal
        if target is None:
            if current is not None:
                self.agent.set_goal(None)
        elif current is None or not np.array_equal(current, target):
            self.agent.set_goal(target)
            self._wake.set()
        self._intent = Intent(
            m.state,
            goal,
            -1 if slot is None else slot,
            -1 if a is None else a.epoch,
            () if a is None else a.points,
            HOLD_PLAN in m.holds,
        )

    # ---- actions (the actions thread) --------------------------------------------------------
    def _queue_action(self, name: str, fn: Callable[[], None]) -> None:
        self._actions.put((name, fn))

    def _do_takeoff(self) -> None:
        veh = self.ap.vehicle()
        if veh is None:
            raise CommandFailed("no telemetry")
        start = veh.position_m.copy()
        self._yaw = veh.yaw_rad
        now = self.clock()
        self._control(Trajectory.hover(start, now, 1.0))
        self.ap.stream(self.sample_setpoint)
        self.ap.request_offboard()
        self.ap.arm()
        alt = self.machine.takeoff_altitude_m or self.cfg.flight.takeoff_altitude_m
        self._control(climb_trajectory(self.clock(), start, alt, self.cfg.flight.takeoff_speed_m_s))
        self._climbing = True

    def _do_resume(self) -> None:
        veh = self.ap.vehicle()
        if veh is None:
            raise CommandFailed("no telemetry")
        if self.flying(self.clock()) is None:
            self._control(Trajectory.hover(veh.position_m, self.clock(), 1.0))
        self.ap.stream(self.sample_setpoint)
        self.ap.request_offboard()

    def actions_step(self, timeout_s: float = 0.2) -> bool:
        """Run one queued action (the actions thread); False when there was none."""
        try:
            item = self._actions.get(timeout=timeout_s)
        except queue.Empty:
            return False
        if item is None:
            return False
        name, fn = item
        try:
            fn()
        except CommandFailed as e:
            self._results.put(("action_failed", (name, str(e))))
        else:
            self._results.put(("action_done", name))
        return True

    # ---- depth (the depth thread) ------------------------------------------------------------
    def _make_mapper(self) -> Any:
        from onboard.mapping import LocalMapper

        return LocalMapper(self.cfg.map_params)

    def depth_step(self) -> bool:
        """Read and ingest one frame if there is one; refresh the ESDF when due."""
        if self.depth is None:
            return False
        c0 = time.thread_time()
        frame = self.depth.read()
        if frame is None:
            return False
        if self.mapper is None:
            self.mapper = self._make_mapper()
        try:
            res = self.mapper.ingest(frame, step=self.cfg.depth.step)
        finally:
            # read only once ingested (mapped, refused or failed): a frame in hand, its ingest
            # starved, is a frame waiting, as those the thread has not read yet
            self._read_stamp = float(frame.stamp_s)
        now = self.clock()
        c1 = time.thread_time()
        self._cpu("depth_ingest", c1 - c0)
        if not res.accepted:
            self.counters["frames_rejected"] += 1
            if res.reason != self._frame_reject_reason:  # each new reason once, not per frame
                self._frame_reject_reason = res.reason
                log.warning("depth frame refused: %s", res.reason)
            return True
        self._frame_reject_reason = ""
        self.counters["frames"] += 1
        stamp = float(frame.stamp_s)
        if math.isfinite(self._last_frame_stamp):
            # frames the camera made that this thread never saw (it was busy, or starved)
            gap = (stamp - self._last_frame_stamp) * self.cfg.depth.rate_hz
            self.counters["frames_missed"] += max(0, int(round(gap)) - 1)
        self._last_frame_stamp = stamp
        self._last_frame_s = now
        if now >= self._next_esdf_s:
            before = self._field
            # the same object when no frame since the last refresh changed what the ESDF
            # reads (and the window did not move): the field is current either way
            self._field = self.mapper.planning_field()
            if self._field is before:
                self.counters["esdf_skipped"] += 1
            # deadlines a period apart, each refresh at the first frame at or after one: the
            # refreshes keep esdf_rate_hz on average whatever the frames' jitter (a period
            # measured from the last refresh lost a whole frame interval to a frame that came
            # a little early); after a stall the schedule restarts from now
            period = 1.0 / self.cfg.mapping.esdf_rate_hz
            nxt = self._next_esdf_s + period
            self._next_esdf_s = nxt if now < nxt else now + period
            self.counters["esdf_builds"] += 1
            self.counters["esdf_new_buffer_sets"] = self.mapper.esdf_new_buffer_sets
            self._cpu("esdf", time.thread_time() - c1)
            if now - self._last_map_record_s >= 0.5:
                self._last_map_record_s = now
                self._record_map(now, np.asarray(frame.position, dtype=np.float64))
        return True

    def _frames_arrived(self, now: float) -> tuple[float, bool]:
        """When the newest depth frame arrived (our clock; the main loop notes when the
        source's ``newest_stamp_s`` moves on) and whether frames wait that the depth thread
        has not ingested yet, unread or in hand (a map lagging a live camera). A source that
        cannot tell: the last frame mapped, none waiting (frames judged by ``timeout_s``
        alone)."""
        newest = getattr(self.depth, "newest_stamp_s", None)
        stamp = newest() if newest is not None else None
        if stamp is None:
            return self._last_frame_s, False
        if stamp != self._arrival_stamp:
            self._arrival_stamp = stamp
            self._last_arrival_s = now
        return max(self._last_arrival_s, self._last_frame_s), stamp > self._read_stamp

    def _cpu(self, name: str, seconds: float) -> None:
        """Add a worker's CPU time (its thread's) to the ``cpu_us.<name>`` counter."""
        key = f"cpu_us.{name}"
        self.counters[key] = self.counters.get(key, 0) + int(seconds * 1e6)

    def _record_map(self, now: float, camera: np.ndarray) -> None:
        """Twice a second: what the map holds (occupied cells; the nearest mapped surface to the
        camera and where it is), in the counters and the flight record."""
        # the field just built holds the occupied cells (no copy of the whole log-odds grid)
        occupied = int(np.count_nonzero(self.mapper.field().occupied))
        self.counters["map_occupied_cells"] = occupied
        rec = self.recorder
        if rec is None:
            return
        d, g = self.mapper.field().distance(camera.reshape(1, 3))
        dist = float(d[0])
        nearest = camera - dist * np.asarray(g[0], dtype=np.float64)
        rec.map(
            now,
            frames=self.counters["frames"],
            occupied_cells=occupied,
            camera_enu_m=camera,
            nearest_obstacle_m=dist,
            nearest_obstacle_enu_m=nearest,
        )

    def field(self) -> Any:
        """The distance field to plan on: the latest ESDF snapshot, or the ground alone when the
        service has no camera."""
        if self._field is not None:
            return self._field
        if self.depth is None:
            if self._ground_field is None:
                from onboard.planner.field import AnalyticField
                from onboard.world import World

                self._ground_field = AnalyticField(World.empty(self.cfg.geofence.min_enu_m[2]))
            return self._ground_field
        return None

    # ---- planning (the planner thread) -------------------------------------------------------
    def plan_step(self) -> PlanReport | None:
        """The planner thread's step: the agent's cycle when a replan is due in formation flight
        (the report, else None); then, while airborne, the trajectory in control announced when
        an override asks for it or nothing was published for a replan period."""
        now = self.clock()
        it = self._intent
        report = None
        if (
            it.state is S.FORMATION_FLIGHT
            and it.goal is not None
            and self._in_control
            and self.field() is not None
        ):
            self._relay()  # the states that have arrived by now
            with self._ctl_lock:
                self._cycle_gen = self._gen
            try:
                report = self.agent.step(now)
            except ValueError:
                if self.agent.goal is not None:
                    raise
                # the main loop cleared the goal between the due check and the cycle
        if it.state in AIRBORNE_CONTROLLED and self._in_control:
            period = self.cfg.planning.replan_period_s
            if self._announce or now - self._last_pub_s >= period:
                self._announce = False
                self._announce_now(now)
        return report

    def _announce_now(self, now: float) -> None:
        """Publish the trajectory in control to the peers (any thread)."""
        self.agent.announce(now)
        self._last_pub_s = now
        self.counters["announcements"] += 1

    def _on_plan(self, rep: PlanReport) -> None:
        """The agent's report, inside its cycle (planner thread): the new trajectory is already
        published and scheduled. An override made meanwhile wins; a plan leaving the geofence
        is replaced by a braking stop; the outcome goes to the main loop and the record."""
        status, why = rep.status, rep.message
        traj = rep.trajectory
        with self._ctl_lock:
            superseded = self._gen != self._cycle_gen and self._override is not None
            if superseded:
                self.agent.reset(self._override)  # type: ignore[arg-type]
                self._announce = True
        if (
            not superseded
            and status in _OK
            and not inside_box(traj, rep.t_start_s, self.cfg.geofence)
        ):
            status, why = PlanStatus.EMERGENCY, "plan leaves the geofence"
            now = self.clock()
            p, v, a = self.agent.flying(now).state(now)
            self._control(braking_trajectory(now, p, v, a, self.cfg.planner.a_max_m_s2))
        if status is not PlanStatus.LATE:  # a late plan took no control and was not published
            self._last_plan_s = rep.planned_at_s
            self._last_pub_s = rep.planned_at_s
        self._results.put(("plan", (status, rep.plan_ms, why, superseded)))
        rec = self.recorder
        if rec is not None:
            rec.plan(
                rep.planned_at_s,
                status=status.value,
                traj_id=rep.seq,
                reason=why + (" (superseded by an override)" if superseded else ""),
                plan_ms=rep.plan_ms,
                plan_cpu_ms=rep.plan_cpu_ms,
                cycle_ms=rep.cycle_ms,
                iterations=rep.iterations,
                evaluations=rep.evaluations,
                n_peers=len(rep.formation_peers),
                formation_peers=list(rep.formation_peers),
                avoided_peers=list(rep.avoided_peers),
                silent_peers=list(rep.silent_peers),
                deviating_peers=list(rep.deviating_peers),
                slot=rep.slot,
                formation_epoch=rep.formation_epoch,
                reforming=rep.reforming,
                recovering=rep.recovering,
                unheard_by=list(rep.unheard_by),
                t0_s=traj.t0_s,
                durations_s=traj.durations_s,
                coeffs=traj.coeffs.ravel(),
                goal_enu_m=rep.goal,
            )

    # ---- the safety monitor (the monitor thread) ---------------------------------------------
    def monitor_step(self) -> str:
        """Check the plan in flight (the trajectory in control, then the queued ones) over the
        horizon; '' when clear, else what was done ('replan' or 'brake') and why. First, a copy
        of the last published trajectory goes out if one is due (``planning.resend_s``)."""
        if self.agent.resend(self.clock()):
            self.counters["resent"] += 1
        it = self._intent
        if it.state not in (S.FORMATION_FLIGHT, S.HOVER, S.EMERGENCY):
            return ""
        fld = self.field()
        now = self.clock()
        traj = self.flying(now)
        if traj is None:
            return ""
        p = self.cfg.planner
        view = self.peers_now(now)
        # sampled on a fixed 0.1 s grid: a look with the same map, peers view, plan and grid
        # step would find what the last one found, so it is not computed again (the map
        # changes at the ESDF rate, the view every half state period)
        g = monitor_step_index(now)
        plan = self.agent.plan_token
        last = self._monitor_key  # the same objects (views hold arrays: not ==), same step
        if not (last and last[0] is fld and last[1] is view and last[2] is plan and last[3] == g):
            ts = monitor_times(g, self.cfg.planning.monitor_horizon_s)
            # the plan as it will be flown: a plan made a moment ago takes control plan_ahead_s
            # later, and judging the one it replaces would brake for what it already avoids
            pos = self.agent.planned(ts)
            # where the brake below would take the drone: a start inside a limit may fly a
            # way out that comes as close as that stop would (the planner's rule)
            brake = braking_trajectory(now, *traj.state(now), p.a_max_m_s2, peak_fraction=1.0)
            brake_pos = brake.sample(ts)
            # the earliest conflict, when, and whether the brake would come less close; an
            # obstacle within the check's distance but not within its slack is only shallow
            # (a plan checked on an older map): it asks for a replan, never a brake
            problem, at, helps = "", math.inf, True
            shallow = ""
            if fld is not None:
                d, _ = fld.distance(np.concatenate([pos, brake_pos]))
                slack = self.cfg.planning.monitor_obstacle_slack_m
                problem, at, helps = obstacle_conflict(
                    d[: len(ts)], ts, now, p.check_obstacle_m - slack, d[len(ts) :],
                    self.agent.brake_reference_s,
                )  # fmt: skip
                if not problem and slack > 0.0:
                    shallow = obstacle_conflict(
                        d[: len(ts)], ts, now, p.check_obstacle_m, d[len(ts) :],
                        self.agent.brake_reference_s,
                    )[0]  # fmt: skip
            # the check the plans keep (wider while a peer does not hear us)
            peer, peer_at, peer_helps = peer_conflict(
                view, now, ts, pos, self.agent.check_drone_m, brake_pos,
                self.agent.brake_reference_s,
            )  # fmt: skip
            if peer_at < at:
                problem, at, helps = peer, peer_at, peer_helps
            lo = np.asarray(self.cfg.geofence.min_enu_m)
            hi = np.asarray(self.cfg.geofence.max_enu_m)
            out = ~np.all((pos >= lo) & (pos <= hi), axis=1)
            if out.any() and ts[int(np.argmax(out))] < at:
                problem, at, helps = "geofence", ts[int(np.argmax(out))], True
            self._monitor_key = (fld, view, plan, g)
            still = float(np.ptp(pos, axis=0).max()) < HOLDING_STILL_M
            self._monitor_problem = (problem, float(at), still, helps, shallow)
        problem, at, still, helps, shallow = self._monitor_problem
        if not problem:
            if not shallow or it.state is not S.FORMATION_FLIGHT:
                return ""
            if now - self._last_plan_s <= MONITOR_REPLAN_AFTER_S:
                return f"watching: {shallow}"
            if self._monitor_asked_s <= self._last_plan_s:
                self.counters["monitor_shallow_replans"] += 1
            self._monitor_asked_s = replan_asked_s(self._monitor_asked_s, self._last_plan_s, now)
            self._ask_replan()
            return f"replan: {shallow}"
        action = monitor_action(
            now,
            at,
            self._last_plan_s,
            self._monitor_brake_at,
            it.state is S.FORMATION_FLIGHT,
            asked_s=self._monitor_asked_s,
        )
        if action == "replan":
            self.counters["monitor_replans"] += 1
            self._monitor_asked_s = replan_asked_s(self._monitor_asked_s, self._last_plan_s, now)
            self._ask_replan()
        if (
            action == "braking"
            and it.held_for_retry
            and self._braking_retry_for < self._monitor_brake_at
        ):
            # the stop and hover after a brake are in a conflict themselves (a peer coming on:
            # one that does not hear us flies through where we hold): retry the plan now, not
            # after the hover's second (the real bus-faults flight, 2026-12-01: a drone braked
            # 1.7 m in front of such a peer and held there until it was 0.96 m away; 0.20 m)
            self._braking_retry_for = self._monitor_brake_at
            self.counters["monitor_braking_retries"] += 1
            self._monitor_retry(now, problem)
        if action != "brake":
            return f"{action}: {problem}"
        pp, vv, aa = traj.state(now)
        if still and np.linalg.norm(vv) < 0.05:
            # the plan in control already holds still: a braking stop would be the same hover,
            # and counting it as a failed plan would put off every retry, whose plan may back
            # out (a drone stopped inside the check distance hovered there until it gave up)
            self.counters["monitor_holding"] += 1
            if it.state is S.FORMATION_FLIGHT:
                self._ask_replan()
            elif it.held_for_retry and now - self._monitor_retry_s >= MONITOR_RETRY_S:
                # the hover after a failed plan is in the way: retry the plan now (if that plan
                # fails too, its hover is retried again at most every MONITOR_RETRY_S: not at
                # every look, as fast as plans fail)
                self._monitor_retry(now, problem)
            return f"holding: {problem}"
        if not helps:
            # the plan comes inside the check's distance, but a braking stop would come as
            # close (a peer that does not hear us coming on): the stop is no way out, a
            # replan may be
            self.counters["monitor_no_better_stop"] += 1
            if it.state is S.FORMATION_FLIGHT:
                if now - self._last_plan_s >= MONITOR_RETRY_S:
                    self._ask_replan()
            elif it.held_for_retry and now - self._monitor_retry_s >= MONITOR_RETRY_S:
                self._monitor_retry(now, problem)
            return f"no better stop: {problem}"
        self._monitor_brake_at = now
        self.counters["monitor_brakes"] += 1
        # a conflict ahead: the hardest stop within the acceleration limit
        self._control(braking_trajectory(now, pp, vv, aa, p.a_max_m_s2, peak_fraction=1.0))
        self._results.put(("monitor_brake", problem))
        return f"brake: {problem}"

    def _monitor_retry(self, now: float, problem: str) -> None:
        """Ask the main loop to retry a failed plan at once (``FlightMachine.retry_now``)."""
        self._monitor_retry_s = now
        self._results.put(("monitor_retry", problem))

    # ---- peers (the main loop; the monitor) --------------------------------------------------
    def peers_now(self, now: float, fresh: bool = False) -> PeerView:
        """The peers as the agent avoids them at ``now`` (``DroneAgent.peer_view``, after the
        states that have arrived are handed over); unless ``fresh``, a view computed less than
        half a state period ago is reused (the monitor looks at 100 Hz, peers speak at 10 Hz).
        A new view that holds the same peers (``same_peers``) is not kept: the old object is
        returned, whose ``t_s`` is then older than the look."""
        view = self.peer_view
        if fresh or view is None or not 0.0 <= now - self._view_at < self._view_age_s:
            self._relay()
            new = self.agent.peer_view(now)
            self._view_at = now
            # the same peers as before: the same object, so that the monitor, which does not
            # look again at what it looked at (by identity), looks on its grid only
            if view is None or not same_peers(view, new):
                view = new
                self.peer_view = view
        return view

    def _watch_peers(self, now: float) -> None:
        """The peers' new states to the agent (signs of life), its watch (a peer that fell
        silent or left its trajectory asks for a replan at once), then what changed logged and
        counted (``reactions.peer_lost``)."""
        self._relay()
        if self.agent.watch(now):
            self._wake.set()  # the planner thread: the agent asked for a replan
        view = self.peers_now(now, fresh=True)
        old = self._logged_view
        self._logged_view = view
        was_silent = set() if old is None else set(old.silent)
        was_off = set() if old is None else set(old.deviating)
        for pid in view.silent:
            if pid not in was_silent:
                self.counters["peers_fell_silent"] += 1
                ago = now - self.agent.heard_s(pid)
                self._peer_event(
                    now,
                    "peer_silent",
                    pid,
                    f"drone {pid} silent for {ago:.2f} s: out of the formation, avoided at "
                    "its last trajectory and where it may have stopped",
                    heard_s_ago=round(ago, 3),
                )
        for pid in sorted(was_silent - set(view.silent)):
            back = now - self.agent.heard_s(pid) <= self.cfg.reactions.peer_lost.peer_silence_s
            self._peer_event(
                now,
                "peer_heard_again" if back else "peer_forgotten",
                pid,
                f"drone {pid} heard again" if back else f"drone {pid} forgotten (silent)",
            )
        for pid in view.deviating:
            if pid not in was_off:
                self.counters["peers_left_trajectory"] += 1
                self._peer_event(
                    now,
                    "peer_off_trajectory",
                    pid,
                    f"drone {pid} reported off its trajectory: avoided where it reported itself",
                )
        self._update_hearing(now)
        self.counters["peers_silent"] = len(view.silent)
        self.counters["peers_deviating"] = len(view.deviating)
        self.counters["peer_ghosts"] = len(view.hover_ids) - len(view.deviating)

    def _update_hearing(self, now: float) -> None:
        """Which peers report that they do not hear us (``onboard.comm.hearing``), to the agent
        (it then plans with a wider berth), counted and logged as it changes."""
        ag = self.agent
        reports = list(self.bus.hearing_reports().values())
        deaf = not_hearing(reports, now, ag.first_published_s, ag.last_published_s)
        old = ag.unheard_by
        if deaf == old:
            return
        ag.set_unheard(deaf)
        self.counters["peers_not_hearing_us"] = len(deaf)
        for pid in sorted(deaf - old):
            self.counters["peers_stopped_hearing_us"] += 1
            self._peer_event(
                now,
                "peer_not_hearing_us",
                pid,
                f"drone {pid} reports it does not hear us: planning "
                f"{self.cfg.planner.unheard_margin_m:.2f} m further from every peer",
            )
        for pid in sorted(old - deaf):
            self._peer_event(now, "peer_hears_us_again", pid, f"drone {pid} hears us again")
        if deaf and not old:
            ag.request_replan()  # with the wider berth, now
            self._wake.set()

    def _peer_event(self, now: float, name: str, pid: int, text: str, **fields: Any) -> None:
        quiet_news = ("peer_heard_again", "peer_forgotten", "peer_hears_us_again")
        level = logging.INFO if name in quiet_news else logging.WARNING
        event(log, name, level, peer=pid, **fields)
        if self.recorder is not None:
            self.recorder.event(now, text, "info" if level == logging.INFO else "warning")

    def _peer_links(self, now: float) -> list[tuple[str, bool, float | None]]:
        """``peer/<id>`` links for the status (``onboard.agent.peer_links``)."""
        view = self.peer_view
        if view is None:
            return []
        return peer_links(view, self.agent.heard_s, now)

    # ---- the main loop -----------------------------------------------------------------------
    def _handle_command(self, inc: IncomingCommand) -> CommandResult:
        cmd: Command = inc.command
        self.counters["commands"] += 1
        if isinstance(cmd, (Goal, Waypoints)) and self.depth is not None:
            if self._field is None:
                return CommandResult(False, "no map yet")
        res = self.machine.command(cmd)
        if not res.accepted:
            self.counters["commands_rejected"] += 1
        event(
            log,
            "command",
            cmd_id=inc.cmd_id,
            kind=type(cmd).__name__.lower(),
            accepted=res.accepted,
            reason=res.reason,
        )
        if self.recorder is not None:
            self.recorder.event(
                self.clock(),
                f"command {inc.cmd_id} {type(cmd).__name__}: "
                + ("accepted" if res.accepted else f"rejected ({res.reason})"),
            )
        return res

    def _react(self, now: float, veh: VehicleSnapshot | None) -> None:
        m = self.machine
        # autopilot heartbeat
        age = self.ap.link_age_s()
        hb_timeout = self.cfg.autopilot.heartbeat_timeout_s
        if age > hb_timeout and self._link_ok:
            self._link_ok = False
            event(log, "autopilot_lost", logging.WARNING, heartbeat_age_s=age)
            self.ap.stream(None)
            m.link_lost()
        elif age <= hb_timeout and not self._link_ok:
            self._link_ok = True
            event(log, "autopilot_back", heartbeat_age_s=age)
            m.link_restored()
        if veh is not None and self._link_ok:
            m.set_on_ground(veh.on_ground)
            if m.state is S.IDLE and veh.armed and not veh.landed:
                m.found_airborne(veh.mode)
            # the pilot (or PX4 itself) took the vehicle out of the service's mode
            if m.state in COMMANDING:
                if veh.mode == "OFFBOARD":
                    self._offboard_seen = True
                elif self._offboard_seen:
                    m.pilot_took_over(veh.mode)
            elif m.state is S.LANDING:
                if veh.mode.endswith("LAND"):
                    self._land_seen = True
                elif self._land_seen and not veh.landed:
                    m.pilot_took_over(veh.mode)
        # depth frames: the camera by its frames' arrival, the map by the last one mapped
        if self.depth is not None and m.state in COMMANDING:
            rx = self.cfg.reactions.depth_lost
            arrived, waiting = self._frames_arrived(now)
            silent = now - max(arrived, self._started_s)
            lag = now - max(self._last_frame_s, self._started_s)
            camera_ok = silent <= rx.timeout_s
            behind = waiting and camera_ok  # frames wait (unread or in hand) behind a live camera
            riding = behind and lag > rx.timeout_s
            if riding and not self._map_lag_riding and not self._depth_lost:
                self.counters["map_lag_rides"] += 1
            self._map_lag_riding = riding
            if not camera_ok or lag > (rx.map_lag_s if behind else rx.timeout_s):
                self._depth_back_since = None  # (still) lost: the recovery starts over
                if not self._depth_lost:
                    self._depth_lost = True
                    why = f"map {lag:.1f} s behind the camera" if behind else "no depth frames"
                    event(
                        log, "depth_lost", logging.WARNING, silent_s=silent, map_lag_s=lag,
                        why=why,
                    )  # fmt: skip
                    self.counters["depth_holds"] += 1
                    if behind:
                        self.counters["map_lag_holds"] += 1
                    m.depth_lost(why)
            elif self._depth_lost:
                if self._depth_back_since is None:
                    self._depth_back_since = arrived
                if arrived - self._depth_back_since >= rx.recover_s and lag <= rx.timeout_s:
                    self._depth_lost = False
                    self._depth_back_since = None
                    event(log, "depth_back")
                    m.depth_restored()
        # ground station
        heard = self.bus.gcs_last_heard_s()
        since = now - (heard if heard is not None else self._started_s)
        if since > self.cfg.reactions.gcs_lost.timeout_s and self._gcs_ok:
            self._gcs_ok = False
            event(log, "gcs_lost", logging.WARNING, silent_s=since)
            m.gcs_lost()
        elif since <= self.cfg.reactions.gcs_lost.timeout_s and not self._gcs_ok:
            self._gcs_ok = True
            event(log, "gcs_back")
            m.gcs_restored()
        # clocks: peers' trajectories and common start times are in global time
        bad = self.bus.clock_exceeded()
        if bad:
            from onboard.comm.wire import GCS_ID

            k = max(bad, key=lambda p: abs(bad[p]))
            who = "the ground station" if k >= GCS_ID else f"drone {k}"
            detail = (
                f"clock offset to {who} is {bad[k]:+.3f} s, beyond the bound "
                f"{self.cfg.bus.clock_offset_bound_s:.3f} s (synchronise the clocks: chrony)"
            )
            if m.clock_problem is None:
                event(log, "clock_out_of_bound", logging.WARNING, sender=k, offset_s=bad[k])
                self._last_event = f"refusing formation flight: {detail}"
            m.clock_out_of_bound(detail)
        elif m.clock_problem is not None:
            event(log, "clock_in_bound")
            m.clock_in_bound()
        # progress
        if veh is not None:
            # (the ground hold streamed before OFFBOARD may have ended while the arming was
            # acknowledged, on the ground: only the climb's end counts)
            if m.state is S.TAKEOFF and self.ap.streaming and self._climbing:
                traj = self.flying(now)
                if traj is not None and now >= traj.t_end_s and veh.armed:
                    err = float(np.linalg.norm(veh.position_m - traj.end_position))
                    if err < 0.25 and float(np.linalg.norm(veh.velocity_m_s)) < 0.3:
                        m.takeoff_reached()
            elif m.state is S.FORMATION_FLIGHT and m.goal is not None:
                goal = self._own_goal(np.asarray(m.goal, dtype=float))
                pc = self.cfg.planning
                if (
                    float(np.linalg.norm(veh.position_m - goal)) < pc.goal_tolerance_m
                    and float(np.linalg.norm(veh.velocity_m_s)) < pc.arrival_speed_m_s
                ):
                    m.goal_reached()

    def _drain_results(self) -> None:
        m = self.machine
        while True:
            try:
                kind, payload = self._results.get_nowait()
            except queue.Empty:
                return
            if kind == "plan":
                status, plan_ms, why, superseded = payload
                self.counters["replans"] += 1
                self._plan_ms.append(plan_ms)
                self._plan_status = status.value
                self._plan_stamp = self.clock()
                if superseded:  # the state changed while it was made: nothing to decide
                    self.counters["plans_superseded"] += 1
                elif status is PlanStatus.LATE:  # the trajectory in control flies on
                    self.counters["plans_late"] += 1
                    event(log, "plan_late", logging.WARNING, why=why)
                elif status is PlanStatus.OVER_BUDGET:  # likewise, and a replan follows
                    self.counters["plans_over_budget"] += 1
                    event(log, "plan_over_budget", logging.INFO, plan_ms=round(plan_ms), why=why)
                elif status in _OK:
                    if why.endswith(LAST_RESORT):  # inside a check distance, less than a stop
                        self.counters["plans_last_resort"] += 1
                        event(log, "plan_last_resort", logging.WARNING, why=why)
                    elif why.endswith(APPROACH):  # refused far ahead, else holding still
                        self.counters["plans_approach"] += 1
                        event(log, "plan_approach", logging.INFO, why=why)
                    m.plan_ok()
                else:  # a kept previous trajectory flies on (it passed the check), as in fast time
                    self.counters["plans_failed"] += 1
                    event(log, "plan_failed", logging.WARNING, status=status.value, why=why)
                    m.plan_failed(status.value, hover=status is not PlanStatus.KEPT_PREVIOUS)
            elif kind == "monitor_brake":
                event(log, "monitor_brake", logging.WARNING, why=payload)
                m.plan_failed("emergency")
            elif kind == "monitor_retry":
                if m.retry_now(f"the hover is in a conflict: {payload}"):
                    event(log, "plan_retry_early", logging.WARNING, why=payload)
            elif kind == "action_failed":
                name, why = payload
                event(log, "action_failed", logging.ERROR, action=name, why=why)
                if self.recorder is not None:
                    self.recorder.event(self.clock(), f"{name} failed: {why}", "error")
                if name == "takeoff":
                    self.ap.stream(None)
                    m.takeoff_failed(why)
            elif kind == "action_done":
                event(log, "action_done", action=payload)

    def main_step(self) -> None:
        """One iteration of the main loop."""
        now = self.clock()
        veh = self.ap.vehicle()
        for inc in self.bus.poll_commands():
            key = (inc.sender, inc.cmd_id)
            res = self._answers.get(key)
            if res is None:
                res = self._handle_command(inc)
                self._answers[key] = res
                if len(self._answers) > ANSWERS_KEPT:
                    self._answers.popitem(last=False)
            else:
                # a resend whose first copy was applied (its answer was late or lost): the same
                # answer again; applied twice, a formation would be refused as stale and a
                # take-off as out of state, and the ground station would report that instead
                self.counters["commands_repeated"] += 1
            self.bus.ack(inc.cmd_id, res.accepted, res.reason)
            self._apply_transitions(veh)
        self._drain_results()
        note, self._guard_note = self._guard_note, None
        if note is not None:
            what, seconds = note
            event(log, what, logging.WARNING, seconds=round(seconds, 2))
            self._last_event = (
                f"stopped: the setpoint stream paused {seconds:.1f} s"
                if what == "stream_gap_stop"
                else f"stopped along the plan: the monitor silent {seconds:.1f} s"
            )
        self._apply_transitions(veh)
        self._react(now, veh)
        self._apply_transitions(veh)
        self._watch_peers(now)
        self.machine.tick()
        self._apply_transitions(veh)
        self._publish(now, veh)
        if self.recorder is not None:
            self.recorder.flush()

    # ---- publishing --------------------------------------------------------------------------
    def _publish(self, now: float, veh: VehicleSnapshot | None) -> None:
        m = self.machine
        a = m.assignment
        slot = m.slot()
        if veh is not None and now - self._last_state_pub >= 1.0 / self.cfg.bus.state_rate_hz:
            self._last_state_pub = now
            self.bus.publish_state(
                {
                    "flight_state": m.state.value,
                    "measured_s": veh.t_s,
                    "position_m": tuple(float(x) for x in veh.position_m),
                    "velocity_m_s": tuple(float(x) for x in veh.velocity_m_s),
                    "attitude_wxyz": veh.attitude_wxyz,
                    "armed": veh.armed,
                    "autopilot_mode": veh.mode,
                    "slot": -1 if slot is None else slot,
                    "formation_epoch": 0 if a is None else a.epoch,
                }
            )
            if self.recorder is not None:
                self.recorder.state(
                    now,
                    flight_state=m.state.value,
                    position_enu_m=veh.position_m,
                    velocity_enu_m_s=veh.velocity_m_s,
                    yaw_enu_rad=veh.yaw_rad,
                    armed=veh.armed,
                    landed=veh.landed,
                    mode=veh.mode,
                    battery_v=veh.battery_v if veh.battery_v is not None else math.nan,
                    quaternion_wxyz=veh.attitude_wxyz,
                )
        if now - self._last_status_pub >= 1.0 / self.cfg.bus.status_rate_hz:
            self._last_status_pub = now
            self._check_kernels()
            counters = self.all_counters()
            ms = self._plan_ms
            self.bus.publish_status(
                {
                    "flight_state": m.state.value,
                    "plan_status": self._plan_status,
                    "plan_stamp_s": self._plan_stamp,
                    "plan_ms_last": ms[-1] if ms else 0.0,
                    "plan_ms_max": max(ms) if ms else 0.0,
                    "replans": self.counters["replans"],
                    "links": [
                        ("autopilot", self._link_ok, self.ap.link_age_s()),
                        ("gcs", self._gcs_ok, None),
                        ("depth", not self._depth_lost, None),
                        *self._peer_links(now),
                    ],
                    "battery_v": None if veh is None else veh.battery_v,
                    "counters": counters,
                    "message": self._last_event[:200],
                }
            )
            self._plan_ms = ms[-1:]
            if self.recorder is not None:
                self.recorder.counters(now, counters)

    def _check_kernels(self) -> None:
        """Counts (``kernels_after_ready``) and logs the numba kernels compiled or loaded
        since READY: each one held a thread (the planner's, the mapping's) while numba made
        it, tens of seconds when compiled (a cold cache: seven services' first plans took
        65 s when the planner's check met a mask type the warm-up had not). 0 is the rule
        after a warm-up; without one (``planning.warm_up`` false) the flight compiles them."""
        if self._kernels_at_ready is None:
            return
        added = kernels_added(self._kernels_at_ready, kernel_census())
        if added == self._kernels_added:
            return
        fresh = {k: n for k, n in added.items() if n > self._kernels_added.get(k, 0)}
        self._kernels_added = added
        self.counters["kernels_after_ready"] = sum(added.values())
        event(
            log,
            "kernels_after_ready",
            logging.WARNING if self._warm_s > 0.0 else logging.INFO,
            kernels=",".join(sorted(fresh)),
            total=self.counters["kernels_after_ready"],
        )

    def all_counters(self) -> dict[str, int]:
        out = {f"service.{k}": int(v) for k, v in dict(self.counters).items()}
        out.update({f"bus.{k}": int(v) for k, v in self.bus.counters().items()})
        out.update({f"autopilot.{k}": int(v) for k, v in self.ap.counters().items()})
        out.update({f"agent.{k}": int(v) for k, v in self.agent.counters().items()})
        return out

    # ---- flight records ----------------------------------------------------------------------
    def _open_record(self, t_s: float) -> None:
        if not self._record_enabled or self.recorder is not None:
            return
        path = self.record_dir / flight_file_name(self.id, t_s)
        try:
            self.recorder = FlightRecorder(
                path,
                self.id,
                metadata={
                    "swarm": self.cfg.drone.swarm,
                    "autopilot": self.cfg.autopilot.implementation,
                    "start_s": t_s,
                },
            )
        except OSError as e:
            event(log, "record_failed", logging.ERROR, path=str(path), why=str(e))
            return
        event(log, "record_open", path=str(path))

    def _close_record(self) -> None:
        rec = self.recorder
        self.recorder = None
        if rec is not None:
            rec.close()
            event(log, "record_closed", path=str(rec.path), messages=rec.written)

    # ---- readiness and the process -----------------------------------------------------------
    def link_up(self) -> bool:
        return (
            self.ap.link_age_s() <= self.cfg.autopilot.heartbeat_timeout_s
            and self.ap.vehicle() is not None
        )

    def map_up(self) -> bool:
        return self.depth is None or self._field is not None

    def warm(self) -> float:
        """Warm the planner (numba's cache) unless the config says not to; waits for the
        warm-up started early (``warming``) when there is one. Seconds it took."""
        if self._warming is not None:
            self._warm_s = self._warming.wait()
        elif self.cfg.planning.warm_up:
            self._warm_s = warm_up(self.cfg.planner)
        return self._warm_s

    def _loop(self, name: str, period_s: float, step: Callable[[], Any]) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.health.beat(name)
            c0 = time.thread_time()
            try:
                step()
            except Exception:  # a worker that dies silently is worse: log, count, go on
                log.exception("%s step failed", name)
                self.counters[f"{name}_errors"] = self.counters.get(f"{name}_errors", 0) + 1
            self._cpu(name, time.thread_time() - c0)
            next_t += period_s
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def _planner_loop(self) -> None:
        while not self._stop.is_set():
            self.health.beat("planner")
            # sleep until the agent's next replan (its grid or a request), a wake-up (goal,
            # override, monitor) or a quarter second (announcements, the watchdog's beat)
            if self.agent.goal is None:
                wait = 0.25
            else:
                wait = min(max(self.agent.next_replan_s - self.clock(), 0.02), 0.25)
            self._wake.wait(wait)
            self._wake.clear()
            if self._stop.is_set():
                return
            c0 = time.thread_time()
            try:
                self.plan_step()
            except Exception:
                log.exception("planner step failed")
                self.counters["planner_errors"] = self.counters.get("planner_errors", 0) + 1
                self._stop.wait(0.1)
            self._cpu("planner", time.thread_time() - c0)

    def _depth_loop(self) -> None:
        period = 1.0 / (2.0 * self.cfg.depth.rate_hz)
        nice = self.cfg.mapping.thread_nice
        if nice and hasattr(os, "setpriority"):
            try:  # Linux: a thread's niceness is set through its own id
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
            except OSError as e:
                event(log, "thread_nice_failed", logging.WARNING, why=str(e))
        while not self._stop.is_set():
            self.health.beat("depth")
            try:
                got = self.depth_step()
            except Exception:
                log.exception("depth step failed")
                self.counters["depth_errors"] = self.counters.get("depth_errors", 0) + 1
                got = False
            if not got:
                self._stop.wait(period)

    def _actions_loop(self) -> None:
        # not watched by the watchdog: an autopilot command may wait seconds for its ack
        while not self._stop.is_set():
            self.actions_step(0.2)

    def start_threads(self) -> None:
        specs: list[tuple[str, Callable[[], None]]] = [
            ("planner", self._planner_loop),
            ("actions", self._actions_loop),
            (
                "monitor",
                lambda: self._loop(
                    "monitor", 1.0 / self.cfg.planning.monitor_rate_hz, self.monitor_step
                ),
            ),
        ]
        if self.depth is not None:
            specs.append(("depth", self._depth_loop))
        for name, target in specs:
            t = named_thread(target, f"svc-{name}")
            t.start()
            self._threads.append(t)

    def run(self, ready_timeout_s: float = 60.0, duration_s: float | None = None) -> int:
        """Start the workers, wait for READY, then run the main loop until ``stop()``."""
        t0 = time.monotonic()
        self.notifier.status("warming the planner")
        warm_s = self.warm()
        self.start_threads()
        self.notifier.status("waiting for the autopilot and the map")
        while not (self.link_up() and self.map_up()):
            if self._stop.wait(0.05):
                return 0
            if time.monotonic() - t0 > ready_timeout_s:
                event(
                    log,
                    "not_ready",
                    logging.ERROR,
                    link=self.link_up(),
                    map=self.map_up(),
                    waited_s=ready_timeout_s,
                )
                return 1
        # the objects made so far (modules, kernels, the warm-up) live as long as the process:
        # keep them out of the collector's full passes, which would otherwise pause every
        # thread (the setpoint stream too) for longer as the heap grows
        gc.collect()
        gc.freeze()
        self._kernels_at_ready = kernel_census()
        self.ready = True
        ready_s = time.monotonic() - t0
        self.notifier.ready(f"drone {self.id} ready")
        event(log, "ready", start_to_ready_s=ready_s, warm_up_s=warm_s)
        period = 1.0 / self.cfg.watchdog.main_loop_hz
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        next_t = time.monotonic()
        while not self._stop.is_set() and time.monotonic() < end:
            self.health.beat("main")
            c0 = time.thread_time()
            self.main_step()
            self._cpu("main", time.thread_time() - c0)
            self._feed_watchdog()
            next_t += period
            self._stop.wait(max(next_t - time.monotonic(), 0.0))
        return 0

    def _feed_watchdog(self) -> None:
        period = self.notifier.watchdog_period_s
        if period is None:
            return
        stalled = self.health.stalled(self.cfg.watchdog.stall_s)
        if stalled:
            if time.monotonic() - self._last_watchdog > period:
                event(log, "unhealthy", logging.ERROR, stalled=",".join(stalled))
            return
        if time.monotonic() - self._last_watchdog >= period / 2.0:
            self._last_watchdog = time.monotonic()
            self.notifier.watchdog()

    def stop(self) -> None:
        """Stop the workers and the stream; close the record (safe from a signal handler's
        thread via ``request_stop``)."""
        self._stop.set()
        self._wake.set()
        self._actions.put(None)
        for t in self._threads:
            t.join(5.0)
        # a worker still inside native code (numba compiling a kernel, a blocking driver call)
        # cannot be interrupted: the caller must not run the interpreter's teardown under it
        self.stuck_threads = [t.name for t in self._threads if t.is_alive()]
        self._threads.clear()
        if self._side_pool is not None:
            # idle once the planner thread has stopped; not waited for behind a stuck one, and
            # a solve it has queued is still run (not cancelled): that plan comes back as usual,
            # and the planner thread's loop ends on the stop flag before starting another
            self._side_pool.shutdown(wait=not self.stuck_threads, cancel_futures=False)
        self.ap.stream(None)
        if self.recorder is not None:
            self.recorder.flush()
            self._close_record()

    def request_stop(self) -> None:
        self._stop.set()
        self._wake.set()

    def stop_requested(self) -> bool:
        return self._stop.is_set()
