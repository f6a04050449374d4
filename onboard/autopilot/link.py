"""The autopilot link: one interface, the machinery both implementations share.

Threads (all daemon, all stopped and joined by ``close``):

- **streamer** (``autopilot-stream``): a monotonic schedule at ``setpoint_rate_hz`` (absolute
  deadlines, the phase kept). Each tick it checks link health, sends the companion HEARTBEAT
  when due (1 Hz) and, while streaming, samples the setpoint source, passes the result through
  the final guard, converts it to NED and sends it. Where the implementation supports it
  (pymavlink over UDP on Linux), a tick is prepared one period ahead: the source is sampled at
  the tick's time, the message encoded, and the native ``timed_send`` kernel sends it at the
  deadline without the interpreter lock, so the stream's timing does not depend on when the
  thread gets the GIL back from the mapping, planning and decoding threads; elsewhere the loop
  sleeps to the deadline and sends from Python. The streamer thread then asks for real-time
  priority (SCHED_FIFO 10, where permitted) or else a short scheduler slice, so that its
  wake-up at the deadline is not queued behind other processes on a busy machine. Heartbeat
  and setpoints come from this one loop, so if it dies both stop (and PX4's offboard-loss
  failsafe follows). It takes no lock that slow code holds: the source is read through an
  atomic reference, and the only lock it takes (``_send_lock``, to make ``stop_streaming``
  exact) is held by others just long enough to flip a flag; the streamer holds it while a
  timed setpoint waits for its deadline, and whoever stops the stream first cancels that wait
  (the setpoint is then not sent). Since it takes that lock again right after the setpoint
  left, the lock is a ``StreamLock``: the streamer first lets any thread waiting for it through
  (so does the implementation's own transmit lock), else a command could wait as long as the
  stream lasts.
- **receiver**: owned by the implementation (a socket reader for pymavlink, MAVSDK's own
  threads plus a byte pump for MAVSDK). It only decodes and stores telemetry, routes
  acknowledgements and detects mode changes; it never waits on anything slow.
- **events** (``autopilot-events``): calls the listeners, in order, so that a slow listener
  delays no other thread.

Commands (``arm``, ``set_mode``, ...) block the calling thread until acknowledged; they are
serialised by ``_command_lock``, which neither the streamer nor the receiver ever takes.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from onboard.autopilot import px4, timed_send
from onboard.autopilot.config import LinkConfig, message_id
from onboard.autopilot.frames import (
    NedSetpoint,
    attitude_ned_to_enu,
    ned_to_enu,
    position_ned_to_enu,
    setpoint_enu_to_ned,
)
from onboard.autopilot.guard import GuardLimits, guard_setpoint
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
    Vec3,
    VehicleState,
)
from onboard.autopilot.streamlock import YIELD_BEFORE_DEADLINE_S, StreamLock
from onboard.threadname import named_thread

log = logging.getLogger("onboard.autopilot")

Listener = Callable[[LinkEvent], None]


# ---------------------------------------------------------------------------------------------
# Pure pieces (no threads, no clock of their own): tested on their own


class LinkHealth:
    """Connected / lost / regained from the times of the last message and the last heartbeat.

    Lost when connected and nothing valid arrived for ``link_timeout_s`` or no heartbeat for
    ``heartbeat_timeout_s``; regained when both are fresh again.

    Silence is measured up to the receiver's last look (``looked``: every message that had
    arrived by then was handled), not up to ``now``: a receiving thread that did not run for a
    while (the process starved of CPU or of the GIL) leaves the link's messages waiting in the
    socket, and the checking thread, woken first, would call the link lost though nothing is
    missing (seen on a loaded host: "lost" after 1.0 s, "back" 0.02 s later). A receiver that
    has not looked for ``receiver_stall_s`` does not hold the verdict back any longer (a hung
    or dead receiver loses the link as before); without ``looked``, silence runs up to ``now``.
    """

    def __init__(
        self, link_timeout_s: float, heartbeat_timeout_s: float, receiver_stall_s: float = 3.0
    ) -> None:
        self.link_timeout_s = link_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.receiver_stall_s = receiver_stall_s
        self.connected = False
        self.lost = False
        self.lost_since: float | None = None

    def update(
        self,
        now: float,
        last_rx: float | None,
        last_hb: float | None,
        looked: float | None = None,
    ) -> str | None:
        """Advance to ``now``; returns "connected", "lost", "regained" or None."""
        if last_hb is None or last_rx is None:
            return None
        until = now
        if looked is not None and now - looked <= self.receiver_stall_s:
            until = min(now, looked)
        fresh = (until - last_rx <= self.link_timeout_s) and (
            until - last_hb <= self.heartbeat_timeout_s
        )
        if not self.connected:
            if fresh:
                self.connected = True
                return "connected"
            return None
        if not self.lost and not fresh:
            self.lost = True
            self.lost_since = now
            return "lost"
        if self.lost and fresh:
            self.lost = False
            return "regained"
        return None


@dataclass(frozen=True)
class ModeObservation:
    """What a heartbeat's mode means: a change (or None), and whether it is an uncommanded
    exit from OFFBOARD."""

    change: tuple[FlightMode, FlightMode, bool] | None  # (previous, current, commanded)
    offboard_lost: bool


class ModeTracker:
    """Tells mode changes this link asked for from those it did not (pilot, PX4 failsafe)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.mode = FlightMode.UNKNOWN
        self._expected: dict[FlightMode, float] = {}

    def expect(self, mode: FlightMode, now: float) -> None:
        """The link is about to ask for ``mode`` (before the command goes out). Replaces any
        earlier request: only the latest one excuses a change."""
        self._expected = {mode: now}
        if mode == FlightMode.TAKEOFF:  # PX4 switches to Hold by itself after a takeoff
            self._expected[FlightMode.HOLD] = now

    def commanded(self, mode: FlightMode, now: float) -> bool:
        t = self._expected.get(mode)
        return t is not None and now - t <= self.window_s

    def observe(self, mode: FlightMode, now: float) -> ModeObservation:
        prev = self.mode
        if mode == prev:
            return ModeObservation(None, False)
        self.mode = mode
        if prev == FlightMode.UNKNOWN:
            return ModeObservation(None, False)
        commanded = self.commanded(mode, now)
        if commanded:  # a request excuses one change only
            del self._expected[mode]
        lost = prev == FlightMode.OFFBOARD and not commanded
        return ModeObservation((prev, mode, commanded), lost)


def run_command(
    name: str,
    send_once: Callable[[], CommandResult],
    retries: int,
    retry_delay_s: float,
    sleep: Callable[[float], None] = time.sleep,
    on_retry: Callable[[], None] | None = None,
) -> int:
    """Send a command until it is accepted: retry after TEMPORARILY_REJECTED up to
    ``retries`` times, ``retry_delay_s`` apart; any other result is a ``CommandError``.
    Returns the number of attempts."""
    attempts = 0
    while True:
        attempts += 1
        result = send_once()
        if result == CommandResult.ACCEPTED:
            return attempts
        if result == CommandResult.TEMPORARILY_REJECTED and attempts <= retries:
            if on_retry is not None:
                on_retry()
            sleep(retry_delay_s)
            continue
        raise CommandError(name, result, attempts)


# ---------------------------------------------------------------------------------------------


class _Telemetry:
    """Latest decoded values (written by the receiver, read under ``lock``)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.position_ned: Vec3 | None = None
        self.velocity_ned: Vec3 | None = None
        self.position_t: float | None = None
        self.attitude: Vec3 | None = None  # roll, pitch, yaw (NED/FRD)
        self.attitude_t: float | None = None
        self.custom_mode = 0
        self.base_mode = 0
        self.system_status = 0
        self.mode = FlightMode.UNKNOWN
        self.landed = LandedState.UNDEFINED
        self.battery_remaining: float | None = None
        self.battery_voltage_v: float | None = None
        self.health_ok: bool | None = None
        self.prearm_ok: bool | None = None
        self.home_alt_amsl_m: float | None = None


class AutopilotLink(ABC):
    """A MAVLink link to one PX4 as its companion computer, in ENU.

    Use as a context manager, or ``connect()`` ... ``close()``. See the module docstring for
    the threads; every public method may be called from any thread.
    """

    implementation = "abstract"
    timed_setpoints = False
    """Send setpoints from the native timed sender (``timed_send``): implementations that
    support it (``_timed_ready``, ``_send_setpoint_at``) set it; False on an instance before
    ``connect`` sends from Python."""

    def __init__(
        self,
        config: LinkConfig,
        sample_clock: Callable[[], float] = time.time,
        name: str | None = None,
    ) -> None:
        self.config = config
        self.name = name or f"autopilot[{config.system_id}]"
        self._sample_clock = sample_clock
        self._limits = GuardLimits(
            config.geofence_min_enu_m,
            config.geofence_max_enu_m,
            config.max_speed_m_s,
            config.max_accel_m_s2,
        )
        self._tel = _Telemetry()
        self._health = LinkHealth(config.link_timeout_s, config.heartbeat_timeout_s)
        self._modes = ModeTracker(config.commanded_mode_window_s)
        self._modes_lock = threading.Lock()
        self._last_rx: float | None = None
        self._last_hb: float | None = None
        self._rx_looked: float | None = None  # the receiver had handled all arrived by then
        # streaming
        self._source: SetpointSource | None = None
        self._streaming = False
        self._stream_gen = 0
        self._send_lock = StreamLock()
        self._last_good: Setpoint | None = None
        self._last_sent: Setpoint | None = None
        self._last_send_t: float | None = None
        self._periods: deque[float] = deque(maxlen=200_000)
        self._sent_since_start = False
        # counters (each written by one thread)
        self._c: Counter[str] = Counter()
        self._rejected: Counter[str] = Counter()
        self._report_t: dict[str, float] = {}
        # commands
        self._command_lock = threading.Lock()
        self._last_ack_t: dict[int, float] = {}
        # commands whose acknowledgement may come twice: PX4 answers every DO_SET_MODE twice;
        # any other command joins once an unmatched acknowledgement of it was seen
        self._double_acked: set[int] = {px4.CMD_DO_SET_MODE}
        self.telemetry_rate_results: dict[str, CommandResult] = {}
        # threads and events
        self._stop = threading.Event()
        self._events: queue.SimpleQueue[LinkEvent | None] = queue.SimpleQueue()
        self._listeners: tuple[Listener, ...] = ()
        self._listeners_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._opened = False
        self._closed = False
        self._streamer_alive = False
        self._connected_evt = threading.Event()
        self._timed: timed_send.TimedSender | None = None

    # ---- implementation primitives -----------------------------------------------------------
    @abstractmethod
    def _open(self) -> None:
        """Open the transport and start receiving (call the ``_rx_*`` hooks)."""

    @abstractmethod
    def _shutdown(self) -> None:
        """Stop receiving, release everything (idempotent)."""

    @abstractmethod
    def _send_heartbeat(self) -> bool:
        """Send the companion HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER)."""

    @abstractmethod
    def _send_setpoint(self, sp: NedSetpoint) -> bool:
        """Send SET_POSITION_TARGET_LOCAL_NED (frame 1, time_boot_ms 0) for ``sp``."""

    def _timed_capable(self) -> bool:
        """Whether this link, once open, can send setpoints at their deadlines (then the timed
        sender is set up at ``connect``)."""
        return self.timed_setpoints

    def _timed_ready(self) -> bool:
        """Whether ``_send_setpoint_at`` can send at a deadline now (default: never)."""
        return False

    def _send_setpoint_at(self, sp: NedSetpoint, deadline_s: float) -> bool | None:
        """Send ``sp`` at ``deadline_s`` (``time.monotonic`` seconds) without needing the
        interpreter lock at that instant; None when ``_cancel_timed`` ended the wait (nothing
        sent). Called with ``_send_lock`` held, only when ``_timed_ready()``."""
        raise NotImplementedError

    def _cancel_timed(self) -> None:
        timed = self._timed
        if timed is not None:
            timed.cancel()

    @abstractmethod
    def _command_once(self, command: int, params: tuple[float, ...]) -> CommandResult:
        """Send COMMAND_LONG (retransmitted without an answer, waiting on after IN_PROGRESS)
        and return the final result, TIMEOUT or LINK_DOWN."""

    @property
    @abstractmethod
    def transport_description(self) -> str: ...

    # ---- lifecycle ---------------------------------------------------------------------------
    def connect(self, timeout_s: float | None = None) -> VehicleState:
        """Open the link, start the threads, wait for the autopilot's heartbeat, request the
        telemetry rates. ``LinkError`` if the autopilot is not heard within the timeout."""
        if self._closed:
            raise LinkError(f"{self.name}: closed")
        if not self._opened:
            self._open()
            self._opened = True
            if self._timed is None and timed_send.available and self._timed_capable():
                timed_send.start_compile()
                self._timed = timed_send.TimedSender()
            self._start_thread(self._stream_loop, "autopilot-stream")
            self._start_thread(self._event_loop, "autopilot-events")
        wait = self.config.connect_timeout_s if timeout_s is None else timeout_s
        if not self._connected_evt.wait(wait):
            raise LinkError(
                f"{self.name}: no heartbeat from system {self.config.system_id} component "
                f"{self.config.autopilot_component_id} within {wait:g} s on "
                f"{self.transport_description}"
            )
        self.request_telemetry_rates()
        return self.state()

    def close(self) -> None:
        """Stop streaming and every thread, close the transport (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._streaming = False
        self._stop.set()
        self._cancel_timed()
        with self._send_lock:
            self._streaming = False
            self._stream_gen += 1
        self._events.put(None)
        me = threading.current_thread()
        for t in self._threads:
            if t is not me:
                t.join(timeout=5.0)
        self._shutdown()
        timed, self._timed = self._timed, None
        if timed is not None and not self._streamer_alive:
            timed.close()

    def __enter__(self) -> AutopilotLink:
        try:
            self.connect()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start_thread(self, target: Callable[[], None], name: str) -> None:
        t = named_thread(target, f"{name}-{self.config.system_id}")
        self._threads.append(t)
        t.start()

    # ---- receiving hooks (called by the implementation's receiving threads) -------------------
    def _rx(self, now: float) -> None:
        """A valid message from the autopilot arrived."""
        self._last_rx = now
        self._c["messages_received"] += 1

    def _rx_looked_at(self, t: float) -> None:
        """The receiver has handled every message that had arrived by ``t`` (monotonic)."""
        self._rx_looked = t

    def _rx_decode_error(self) -> None:
        self._c["decode_errors"] += 1

    def _rx_heartbeat(self, now: float, custom_mode: int, base_mode: int, status: int) -> None:
        mode = px4.mode_from_custom_mode(custom_mode)
        failsafe = status in (px4.MAV_STATE_CRITICAL, px4.MAV_STATE_EMERGENCY)
        armed = bool(base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED)
        tel = self._tel
        with tel.lock:
            was_armed = bool(tel.base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED)
            tel.custom_mode = custom_mode
            tel.base_mode = base_mode
            tel.system_status = status
            tel.mode = mode
        self._last_hb = now
        self._c["heartbeats_received"] += 1
        with self._modes_lock:
            obs = self._modes.observe(mode, now)
        # (after a landing PX4 returns to OFFBOARD disarmed; leaving it then is no takeover)
        if obs.offboard_lost and (armed or was_armed or self._streaming):
            was = self._streaming
            if self.config.stop_streaming_on_offboard_loss:
                self._halt_streaming(wait=False)
            self._c["offboard_losses"] += 1
            log.warning(
                "%s: vehicle left OFFBOARD for %s without being asked (%s); %s",
                self.name,
                mode.name,
                "failsafe" if failsafe else "pilot or PX4",
                "streaming stopped" if was and not self._streaming else "not streaming",
            )
            self._emit(OffboardLost(now, mode, failsafe, was))
        if obs.change is not None:
            prev, cur, commanded = obs.change
            log.info(
                "%s: mode %s -> %s%s", self.name, prev.name, cur.name, "" if commanded else " (!)"
            )
            self._emit(ModeChanged(now, prev, cur, commanded))

    def _rx_local_position(self, now: float, pos_ned: Vec3, vel_ned: Vec3) -> None:
        if not all(math.isfinite(v) for v in (*pos_ned, *vel_ned)):
            self._rx_decode_error()  # a NaN estimate is no position: keep the last one
            return
        tel = self._tel
        with tel.lock:
            tel.position_ned = pos_ned
            tel.velocity_ned = vel_ned
            tel.position_t = now

    def _rx_attitude(self, now: float, roll: float, pitch: float, yaw_ned: float) -> None:
        if not (math.isfinite(roll) and math.isfinite(pitch) and math.isfinite(yaw_ned)):
            self._rx_decode_error()
            return
        tel = self._tel
        with tel.lock:
            tel.attitude = (roll, pitch, yaw_ned)
            tel.attitude_t = now

    def _rx_landed_state(self, now: float, landed_state: int) -> None:
        try:
            ls = LandedState(landed_state)
        except ValueError:
            ls = LandedState.UNDEFINED
        with self._tel.lock:
            self._tel.landed = ls

    def _rx_health(self, now: float, health_ok: bool | None, prearm_ok: bool | None) -> None:
        with self._tel.lock:
            self._tel.health_ok = health_ok
            self._tel.prearm_ok = prearm_ok

    def _rx_battery(self, now: float, remaining: float | None, voltage_v: float | None) -> None:
        with self._tel.lock:
            self._tel.battery_remaining = remaining
            self._tel.battery_voltage_v = voltage_v

    def _rx_home(self, now: float, altitude_amsl_m: float) -> None:
        if not math.isfinite(altitude_amsl_m):
            self._rx_decode_error()
            return
        with self._tel.lock:
            self._tel.home_alt_amsl_m = altitude_amsl_m

    def _rx_ack(self, now: float, command: int, matched: bool) -> None:
        """An acknowledgement addressed to this link (``matched``: a pending command's)."""
        self._last_ack_t[command] = now
        self._c["acks_received"] += 1
        if not matched:
            self._c["acks_unmatched"] += 1
            self._double_acked.add(command)

    # ---- state ---------------------------------------------------------------------------------
    def state(self) -> VehicleState:
        """A consistent snapshot of what the link knows (ENU, link clock)."""
        now = time.monotonic()
        now_global = self._sample_clock()
        tel = self._tel
        origin = self.config.local_origin_enu_m
        with tel.lock:
            pos_ned, vel_ned, pos_t = tel.position_ned, tel.velocity_ned, tel.position_t
            att, att_t = tel.attitude, tel.attitude_t
            custom_mode, base_mode, status = tel.custom_mode, tel.base_mode, tel.system_status
            mode, landed = tel.mode, tel.landed
            batt, volt = tel.battery_remaining, tel.battery_voltage_v
            health_ok, prearm_ok = tel.health_ok, tel.prearm_ok
        last_rx, last_hb = self._last_rx, self._last_hb
        roll = pitch = yaw = None
        if att is not None:
            roll, pitch, yaw = attitude_ned_to_enu(*att)
        return VehicleState(
            t_s=now,
            t_global_s=now_global,
            connected=self._health.connected,
            link_lost=self._health.lost,
            heartbeat_age_s=math.inf if last_hb is None else now - last_hb,
            rx_age_s=math.inf if last_rx is None else now - last_rx,
            streaming=self._streaming,
            position_enu_m=None if pos_ned is None else position_ned_to_enu(pos_ned, origin),
            velocity_enu_m_s=None if vel_ned is None else ned_to_enu(vel_ned),
            position_t_s=pos_t,
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_enu_rad=yaw,
            attitude_t_s=att_t,
            armed=bool(base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED),
            mode=mode,
            custom_mode=custom_mode,
            system_status=status,
            failsafe=status in (px4.MAV_STATE_CRITICAL, px4.MAV_STATE_EMERGENCY),
            landed_state=landed,
            battery_remaining=batt,
            battery_voltage_v=volt,
            health_ok=health_ok,
            prearm_ok=prearm_ok,
        )

    def wait_until(
        self, pred: Callable[[VehicleState], bool], timeout_s: float, what: str = "condition"
    ) -> VehicleState:
        """Poll ``pred(state())`` every 20 ms; the state once it holds, TimeoutError naming
        ``what`` otherwise."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.state()
            if pred(st):
                return st
            if time.monotonic() >= deadline or self._closed:
                raise TimeoutError(f"{self.name}: {what} not reached within {timeout_s:g} s")
            time.sleep(0.02)

    def wait_healthy(self, timeout_s: float = 30.0) -> VehicleState:
        """Until PX4's pre-arm checks pass, no sensor faults and a position is known."""
        return self.wait_until(
            lambda s: bool(s.prearm_ok and s.health_ok and s.position_enu_m is not None),
            timeout_s,
            "healthy and armable",
        )

    @property
    def connected(self) -> bool:
        return self._health.connected

    @property
    def link_lost(self) -> bool:
        return self._health.lost

    @property
    def streamer_alive(self) -> bool:
        return self._streamer_alive

    def counters(self) -> LinkCounters:
        c = self._c
        return LinkCounters(
            setpoints_sent=c["setpoints_sent"],
            setpoints_rejected=c["setpoints_rejected"],
            setpoints_held=c["setpoints_held"],
            source_errors=c["source_errors"],
            heartbeats_sent=c["heartbeats_sent"],
            heartbeats_received=c["heartbeats_received"],
            messages_received=c["messages_received"],
            decode_errors=c["decode_errors"],
            commands_sent=c["commands_sent"],
            command_retries=c["command_retries"],
            acks_received=c["acks_received"],
            acks_unmatched=c["acks_unmatched"],
            foreign_heartbeats_dropped=c["foreign_heartbeats_dropped"],
            late_ticks=c["late_ticks"],
            link_losses=c["link_losses"],
            offboard_losses=c["offboard_losses"],
            unsigned_rejected=c["unsigned_rejected"],
            bad_signatures=c["bad_signatures"],
            unsigned_accepted=c["unsigned_accepted"],
            frames_ignored=c["frames_ignored"],
            rejected_by_reason=dict(self._rejected),
        )

    @property
    def timed_setpoints_sent(self) -> int:
        """Setpoints sent at their deadline by the native timed sender (``timed_send``)."""
        return self._c["setpoints_timed"]

    def setpoint_period_stats(self, reset: bool = False) -> PeriodStats:
        """Intervals between consecutive setpoints sent while streaming (this side's clock)."""
        periods = list(self._periods)
        if reset:
            self._periods.clear()
        return PeriodStats.of(periods)

    @property
    def last_setpoint(self) -> Setpoint | None:
        """The last setpoint sent (ENU), hold setpoints included."""
        return self._last_sent

    # ---- events --------------------------------------------------------------------------------
    def add_listener(self, listener: Listener) -> None:
        """``listener(event)`` is called on the link's event thread for every ``LinkEvent``."""
        with self._listeners_lock:
            self._listeners = (*self._listeners, listener)

    def remove_listener(self, listener: Listener) -> None:
        with self._listeners_lock:
            self._listeners = tuple(x for x in self._listeners if x is not listener)

    def _emit(self, ev: LinkEvent) -> None:
        self._events.put(ev)

    def _event_loop(self) -> None:
        while True:
            ev = self._events.get()
            if ev is None:
                return
            for listener in self._listeners:
                try:
                    listener(ev)
                except Exception:  # noqa: BLE001 - a listener's bug must not stop the events
                    log.exception("%s: event listener failed on %s", self.name, ev)

    # ---- streaming -----------------------------------------------------------------------------
    @property
    def streaming(self) -> bool:
        return self._streaming

    def set_source(self, source: SetpointSource | None) -> None:
        """Install the setpoint source (an atomic swap; takes effect at the next tick)."""
        self._source = source

    def start_streaming(self, source: SetpointSource | None = None) -> None:
        """Stream setpoints from ``source`` (or the installed one) from the next tick on.

        The hold position for refused setpoints starts as the vehicle's current position.
        ``LinkError`` if the link is not connected or lost: after a loss streaming resumes only
        through this call.
        """
        if source is not None:
            self._source = source
        if self._source is None:
            raise LinkError(f"{self.name}: no setpoint source installed")
        if self._closed or not self._health.connected:
            raise LinkError(f"{self.name}: not connected")
        if self._health.lost:
            raise LinkError(f"{self.name}: link lost; cannot stream")
        st = self.state()
        with self._send_lock:
            if st.position_enu_m is not None and (
                st.position_t_s is not None and st.t_s - st.position_t_s <= 1.0
            ):
                hold = Setpoint.hold(st.position_enu_m, st.yaw_enu_rad)
                self._last_good = (
                    hold if guard_setpoint(hold, None, self._limits).reason is None else None
                )
            else:
                self._last_good = None
            self._last_send_t = None
            self._sent_since_start = False
            self._streaming = True
            self._stream_gen += 1
        log.info("%s: streaming setpoints at %g Hz", self.name, self.config.setpoint_rate_hz)

    def stop_streaming(self) -> None:
        """No setpoint is sent after this returns; the heartbeat goes on."""
        if self._halt_streaming():
            log.info("%s: streaming stopped", self.name)

    def _halt_streaming(self, wait: bool = True) -> bool:
        """Stop streaming. ``wait``: under ``_send_lock``, so that no setpoint leaves after
        the return; receiving threads pass False (flag flips only, never waiting on the
        streamer, which may be inside the implementation's send call): at most the setpoint
        being sent at that instant still goes out."""
        was = self._streaming
        self._streaming = False
        self._cancel_timed()  # a setpoint waiting for its deadline is not sent
        if not wait:
            self._stream_gen += 1
            return was
        with self._send_lock:
            self._streaming = False
            self._stream_gen += 1
        return was

    def _stream_loop(self) -> None:
        self._streamer_alive = True
        if self._timed is not None:
            if timed_send.request_realtime():
                log.info("%s: setpoint streamer at real-time priority", self.name)
            elif timed_send.request_short_slice():
                log.info("%s: setpoint streamer with a short scheduler slice", self.name)
        period = self.config.setpoint_period_s
        hb_period = 1.0 / self.config.heartbeat_rate_hz
        next_t = time.monotonic()
        next_hb = next_t
        stop = self._stop
        try:
            while not stop.is_set():
                now = time.monotonic()
                # timed: this tick is prepared now and sent at its deadline by the native
                # sender (right after the previous one left); else sleep to the deadline
                timed = self._streaming and self._timed_ready()
                if not timed and now < next_t:
                    stop.wait(next_t - now)
                    continue
                if now - next_t > period:  # overran: skip the missed ticks, keep the phase
                    self._c["late_ticks"] += 1
                    next_t += math.ceil((now - next_t) / period) * period
                    deadline = now
                else:
                    deadline = next_t
                    next_t += period
                self._check_health(now)
                if now >= next_hb:
                    if self._send_heartbeat():
                        self._c["heartbeats_sent"] += 1
                    next_hb += hb_period
                    if next_hb <= now:
                        next_hb = now + hb_period
                if self._streaming:
                    self._stream_tick(deadline if timed else None)
                if timed:
                    # a tick that sent nothing (nothing to hold, or stopped meanwhile) did not
                    # wait for its deadline in the sender: wait here, never run ahead of it
                    left = deadline - time.monotonic()
                    if left > 0.0:
                        stop.wait(left)
        except Exception:  # noqa: BLE001 - logged; heartbeat and setpoints stop together
            log.exception(
                "%s: the setpoint streamer died; heartbeat and setpoints stopped", self.name
            )
        finally:
            self._streamer_alive = False

    def _stream_tick(self, deadline: float | None = None) -> None:
        """One setpoint: sent now, or (``deadline``) sampled at and sent at the deadline."""
        gen = self._stream_gen
        source = self._source
        sp: Setpoint | None = None
        if source is not None:
            try:
                t_sample = self._sample_clock()
                if deadline is not None:
                    t_sample += max(deadline - time.monotonic(), 0.0)
                sp = source(t_sample)
            except Exception as e:  # noqa: BLE001 - the service's bug: hold, count, report
                self._c["source_errors"] += 1
                if self._due_report("source"):
                    log.error("%s: setpoint source failed: %r (holding)", self.name, e)
                    self._emit(SourceFailed(time.monotonic(), repr(e), self._c["source_errors"]))
                sp = None
            if sp is not None and not isinstance(sp, Setpoint):
                self._c["source_errors"] += 1
                if self._due_report("source"):
                    self._emit(
                        SourceFailed(
                            time.monotonic(),
                            f"not a Setpoint: {type(sp).__name__}",
                            self._c["source_errors"],
                        )
                    )
                sp = None
        verdict = guard_setpoint(sp, self._last_good, self._limits)
        if verdict.reason is not None:
            self._c["setpoints_rejected"] += 1
            self._rejected[verdict.reason] += 1
            if self._due_report("reject:" + verdict.reason):
                log.warning("%s: setpoint refused (%s); holding", self.name, verdict.reason)
                self._emit(
                    SetpointRejected(
                        time.monotonic(), verdict.reason, self._rejected[verdict.reason]
                    )
                )
        out = verdict.setpoint
        if out is None:
            return
        if out is sp:
            self._last_good = sp
        else:
            self._c["setpoints_held"] += 1
        ned = setpoint_enu_to_ned(
            out.position_enu_m,
            out.velocity_enu_m_s,
            out.accel_enu_m_s2,
            out.yaw_enu_rad,
            self.config.local_origin_enu_m,
        )
        until = None if deadline is None else deadline - YIELD_BEFORE_DEADLINE_S
        with self._send_lock.after_waiters(until):
            timed = self._timed
            if deadline is not None and timed is not None:
                timed.clear()  # a cancel after this line ends the wait below
            if not self._streaming or self._stream_gen != gen:
                return
            if deadline is None:
                ok: bool | None = self._send_setpoint(ned)
            else:
                ok = self._send_setpoint_at(ned, deadline)
                if ok:
                    self._c["setpoints_timed"] += 1
            t = time.monotonic()
        if ok is None:  # cancelled: streaming stopped while it waited
            return
        if ok:
            self._c["setpoints_sent"] += 1
            self._last_sent = out
            if self._last_send_t is not None:
                self._periods.append(t - self._last_send_t)
            self._last_send_t = t
            self._sent_since_start = True

    def _due_report(self, key: str, every_s: float = 1.0) -> bool:
        now = time.monotonic()
        last = self._report_t.get(key)
        if last is not None and now - last < every_s:
            return False
        self._report_t[key] = now
        return True

    def _check_health(self, now: float) -> None:
        change = self._health.update(now, self._last_rx, self._last_hb, self._rx_looked)
        if change == "connected":
            log.info("%s: connected (%s)", self.name, self.transport_description)
            self._connected_evt.set()
            self._emit(Connected(now))
        elif change == "lost":
            was = self._halt_streaming()
            self._c["link_losses"] += 1
            rx_age = math.inf if self._last_rx is None else now - self._last_rx
            hb_age = math.inf if self._last_hb is None else now - self._last_hb
            log.error(
                "%s: link lost (nothing for %.2f s, heartbeat %.2f s ago)%s",
                self.name,
                rx_age,
                hb_age,
                "; streaming stopped" if was else "",
            )
            self._emit(LinkLost(now, rx_age, hb_age, was))
        elif change == "regained":
            lost_for = now - (self._health.lost_since or now)
            log.warning("%s: link back after %.2f s (not streaming)", self.name, lost_for)
            self._emit(LinkRegained(now, lost_for))
            threading.Thread(
                target=self._rerequest_rates, name="autopilot-rates", daemon=True
            ).start()

    def _rerequest_rates(self) -> None:
        try:
            self.request_telemetry_rates()
        except LinkError:
            pass

    # ---- commands ------------------------------------------------------------------------------
    def command(
        self,
        command: int,
        params: tuple[float, ...] = (),
        name: str | None = None,
        expect_mode: FlightMode | None = None,
    ) -> int:
        """Send COMMAND_LONG ``command`` until accepted (see ``run_command``); returns the
        attempts. ``CommandError`` names the command and the result otherwise."""
        if len(params) > 7:
            raise ValueError("params: at most 7")
        p = tuple(float(x) for x in params) + (0.0,) * (7 - len(params))
        label = name or px4.command_name(command, p)
        if self._closed or not self._opened:
            raise CommandError(label, CommandResult.LINK_DOWN, 0, "link not open")
        with self._command_lock:

            def once() -> CommandResult:
                self._wait_duplicate_window(command)
                if expect_mode is not None:
                    with self._modes_lock:
                        self._modes.expect(expect_mode, time.monotonic())
                result = self._command_once(command, p)
                if result not in (CommandResult.TIMEOUT, CommandResult.LINK_DOWN):
                    # the duplicate window runs from here even if the receiving thread has
                    # not reported this acknowledgement yet (MAVSDK: another thread)
                    now = time.monotonic()
                    self._last_ack_t[command] = max(self._last_ack_t.get(command, now), now)
                return result

            def retried() -> None:
                self._c["command_retries"] += 1

            attempts = run_command(
                label,
                once,
                self.config.command_retries,
                self.config.retry_delay_s,
                on_retry=retried,
            )
        log.info(
            "%s: %s accepted (%d attempt%s)",
            self.name,
            label,
            attempts,
            "" if attempts == 1 else "s",
        )
        return attempts

    def _wait_duplicate_window(self, command: int) -> None:
        if command not in self._double_acked:
            return
        last = self._last_ack_t.get(command)
        while last is not None:
            wait = last + self.config.duplicate_ack_window_s - time.monotonic()
            if wait <= 0:
                return
            time.sleep(wait)
            last = self._last_ack_t.get(command)

    def arm(self) -> None:
        """Arm. PX4 refuses (TEMPORARILY_REJECTED) when its checks fail, e.g. in OFFBOARD
        without a setpoint stream (where PX4 returns after landing): select HOLD first."""
        self.command(px4.CMD_COMPONENT_ARM_DISARM, px4.arm_params(True))

    def disarm(self, force: bool = False) -> None:
        self.command(px4.CMD_COMPONENT_ARM_DISARM, px4.arm_params(False, force))

    def set_mode(self, mode: FlightMode) -> None:
        """DO_SET_MODE with PX4's custom mode for ``mode`` (OFFBOARD, HOLD, POSCTL, LAND...)."""
        params = px4.set_mode_params(mode)
        self.command(px4.CMD_DO_SET_MODE, params, expect_mode=mode)

    def hold(self) -> None:
        """Select HOLD (AUTO.LOITER); once accepted, streaming stops."""
        self.set_mode(FlightMode.HOLD)
        self.stop_streaming()

    def land(self) -> None:
        """NAV_LAND where the vehicle is; once accepted, streaming stops."""
        self.command(px4.CMD_NAV_LAND, px4.land_params(), expect_mode=FlightMode.LAND)
        self.stop_streaming()

    def takeoff(self, altitude_m: float | None = None) -> None:
        """NAV_TAKEOFF to ``altitude_m`` above home (None: PX4's MIS_TAKEOFF_ALT). PX4 climbs
        and switches to HOLD by itself; it does not go below its own takeoff altitude."""
        amsl = None
        if altitude_m is not None:
            if not (math.isfinite(altitude_m) and altitude_m > 0.0):
                raise ValueError(f"altitude_m: expected a number > 0, got {altitude_m!r}")
            home = self._home_altitude()
            amsl = home + altitude_m
        self.command(px4.CMD_NAV_TAKEOFF, px4.takeoff_params(amsl), expect_mode=FlightMode.TAKEOFF)

    def start_offboard(self, timeout_s: float = 1.0) -> None:
        """Select OFFBOARD while streaming. Waits (up to ``timeout_s``) until a setpoint has
        gone out, since PX4 accepts OFFBOARD once it has a valid setpoint younger than
        COM_OF_LOSS_T."""
        if not self._streaming:
            raise LinkError(f"{self.name}: start_streaming before start_offboard")
        deadline = time.monotonic() + timeout_s
        while not self._sent_since_start:
            if time.monotonic() > deadline:
                raise LinkError(f"{self.name}: no setpoint sent within {timeout_s:g} s")
            if not self._streaming:
                raise LinkError(f"{self.name}: streaming stopped before OFFBOARD")
            time.sleep(0.005)
        self.set_mode(FlightMode.OFFBOARD)

    def request_message(self, message_name: str) -> None:
        """MAV_CMD_REQUEST_MESSAGE for one message."""
        mid = message_id(message_name)
        if mid is None:
            raise ValueError(f"message_name: unknown MAVLink message {message_name!r}")
        self.command(
            px4.CMD_REQUEST_MESSAGE, (float(mid),), name=f"MAV_CMD_REQUEST_MESSAGE({message_name})"
        )

    def request_telemetry_rates(self) -> dict[str, CommandResult]:
        """SET_MESSAGE_INTERVAL for every configured stream, then interval -1 (off) for each of
        ``telemetry_off``. A refusal is logged and kept in ``telemetry_rate_results``, not
        raised (PX4 keeps its default rate then)."""
        results: dict[str, CommandResult] = {}
        wanted = [(name, 1e6 / hz, f"{hz:g} Hz") for name, hz in self.config.telemetry_rates_hz]
        wanted += [(name, -1.0, "off") for name in self.config.telemetry_off]
        for name, interval_us, what in wanted:
            mid = message_id(name)
            assert mid is not None  # checked by LinkConfig
            try:
                self.command(
                    px4.CMD_SET_MESSAGE_INTERVAL,
                    (float(mid), interval_us),
                    name=f"MAV_CMD_SET_MESSAGE_INTERVAL({name}, {what})",
                )
                results[name] = CommandResult.ACCEPTED
            except CommandError as e:
                log.warning("%s: %s", self.name, e)
                results[name] = e.result
        self.telemetry_rate_results = results
        return results

    def _home_altitude(self) -> float:
        alt = self._tel.home_alt_amsl_m
        if alt is None:
            try:
                self.request_message("HOME_POSITION")
            except CommandError as e:
                raise LinkError(f"{self.name}: home altitude unknown ({e})") from e
            deadline = time.monotonic() + 2.0
            while alt is None and time.monotonic() < deadline:
                time.sleep(0.02)
                alt = self._tel.home_alt_amsl_m
        if alt is None:
            raise LinkError(f"{self.name}: home altitude unknown (no HOME_POSITION)")
        return alt


def open_link(config: LinkConfig, sample_clock: Callable[[], float] = time.time) -> AutopilotLink:
    """The implementation ``config.implementation`` names (not yet connected)."""
    if config.implementation == "mavsdk":
        from onboard.autopilot.mavsdk_link import MavsdkLink

        return MavsdkLink(config, sample_clock=sample_clock)
    from onboard.autopilot.pymavlink_link import PymavlinkLink

    return PymavlinkLink(config, sample_clock=sample_clock)
