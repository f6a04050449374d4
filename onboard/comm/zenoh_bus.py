"""The swarm bus over Zenoh: one :class:`SwarmNode` per process (a drone or the ground station).

A drone node publishes its trajectory, state, status and acknowledgements, keeps an inbox of
its peers' latest valid trajectories (it is the ``PeerBus`` of the planner: ``publish`` /
``receive``) and hands ground-station commands addressed to it to ``on_command`` callbacks. A
ground-station node (``drone_id=None``) sends commands, collects acknowledgements, and keeps the
latest state and status of every drone. Both see who is up through liveliness tokens and
estimate every sender's clock offset from message stamps.

Threads: Zenoh runs subscriber callbacks on its own threads. Every received payload passes the
:class:`~onboard.comm.gate.MessageGate` under the node's lock; the inbox and the latest states
are read under the same lock, so ``receive`` from the planner's thread sees whole messages only.
User callbacks run on Zenoh's thread after the lock is released: keep them short and
thread-safe. A rejected payload is counted (``reject.<reason>``); an exception raised by a user
callback is logged with its traceback and counted (``error.callback``), as is one raised inside
the node itself (``error.internal``); neither ever reaches Zenoh.

Clock: ``clock`` (default ``time.time``, the system clock kept by chrony) stamps outgoing
messages and times arrivals; it is injectable for tests.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from onboard.comm.clock import ClockOffsets, PeerClock
from onboard.comm.gate import MessageGate
from onboard.comm.keys import SwarmKeys
from onboard.comm.messages import TrajectoryMsg
from onboard.comm.wire import (
    DEFAULT_LIMITS,
    GCS_ID,
    WIRE_VERSION,
    Ack,
    Action,
    Body,
    Command,
    Envelope,
    Rejected,
    StateBody,
    StatusBody,
    WireLimits,
    encode,
    kind_of,
)
from onboard.comm.zenoh_session import ZenohEndpoints, declare_liveliness, open_session
from onboard.threadname import name_callback_thread

log = logging.getLogger(__name__)

Callback = Callable[[Envelope, float], None]
"""``cb(envelope, receive_s)``: a checked message and our clock when it arrived."""
AliveCallback = Callable[[str, "int | None", bool], None]
"""``cb(kind, drone_id, alive)``: kind ``"drone"`` (with its id) or ``"gcs"`` (id None)."""


@dataclass(frozen=True)
class BusConfig:
    """Swarm bus settings of one node.

    *_valid_for_s: validity given to outgoing messages (a trajectory's validity is also how long
    peers keep using it without a newer one); clock_offset_bound_s: |offset| to a sender above
    which a warning is raised; clock_window_s: window of the offset estimate; resync_after_s: see
    ``MessageGate``; gcs_id: this ground station's sender id; subscribe_states: receive every
    drone's state and status (None: ground stations yes, drones no); limits: the wire bounds.
    """

    traj_valid_for_s: float = 3.0
    state_valid_for_s: float = 1.0
    status_valid_for_s: float = 5.0
    cmd_valid_for_s: float = 10.0
    ack_valid_for_s: float = 10.0
    clock_offset_bound_s: float = 0.05
    clock_window_s: float = 10.0
    resync_after_s: float = 5.0
    gcs_id: int = GCS_ID
    subscribe_states: bool | None = None
    limits: WireLimits = field(default_factory=lambda: DEFAULT_LIMITS)

    def __post_init__(self) -> None:
        for name in (
            "traj_valid_for_s",
            "state_valid_for_s",
            "status_valid_for_s",
            "cmd_valid_for_s",
            "ack_valid_for_s",
        ):
            v = getattr(self, name)
            if not 0.0 < v <= self.limits.max_valid_for_s:
                raise ValueError(f"bus.{name} must be in (0, {self.limits.max_valid_for_s}]")
        for name in ("clock_offset_bound_s", "clock_window_s", "resync_after_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"bus.{name} must be > 0")
        if self.gcs_id < GCS_ID:
            raise ValueError(f"bus.gcs_id must be >= {GCS_ID}")


@dataclass
class _Peer:
    msg: TrajectoryMsg
    receive_s: float


class SwarmNode:
    """One process on the swarm bus; implements ``PeerBus`` (``publish`` / ``receive``).

    swarm: the swarm name (key prefix); drone_id: this drone's id, or None for the ground
    station; endpoints: how to join Zenoh (``onboard.comm.zenoh_session``), or pass an open
    ``session`` (then the caller closes it, and must not give it to a second node: a node does
    not hear its own session); clock: global time in seconds; incarnation: see
    ``onboard.comm.wire`` (default: the clock at start, in microseconds).
    """

    def __init__(
        self,
        swarm: str,
        drone_id: int | None,
        endpoints: ZenohEndpoints | None = None,
        *,
        config: BusConfig | None = None,
        clock: Callable[[], float] = time.time,
        session: Any = None,
        incarnation: int | None = None,
    ) -> None:
        self.config = cfg = config if config is not None else BusConfig()
        self.keys = SwarmKeys(swarm)
        self.drone_id = drone_id
        self.is_gcs = drone_id is None
        self.sender_id = cfg.gcs_id if drone_id is None else drone_id
        if drone_id is not None:
            self.keys.traj(drone_id)  # checks the id
        self.name = "[gcs] " if drone_id is None else f"[drone {drone_id}] "
        self._clock = clock
        self.incarnation = int(clock() * 1e6) if incarnation is None else int(incarnation)
        self.clock_offsets = ClockOffsets(cfg.clock_offset_bound_s, cfg.clock_window_s, self.name)
        self._gate = MessageGate(
            swarm, self.sender_id, cfg.limits, self.clock_offsets, cfg.resync_after_s, self.name
        )
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._acked = threading.Condition(self._lock)
        self._counters: dict[str, int] = {
            "tx.traj": 0,
            "tx.state": 0,
            "tx.status": 0,
            "tx.cmd": 0,
            "tx.ack": 0,
            "cmd.not_addressed": 0,
            "error.callback": 0,
            "error.internal": 0,
        }
        self._seq: dict[str, int] = {}
        self._next_cmd_id = max(self.incarnation, 1)
        self._inbox: dict[int, _Peer] = {}
        self._states: dict[int, tuple[Envelope, float]] = {}
        self._statuses: dict[int, tuple[Envelope, float]] = {}
        self._acks: OrderedDict[int, dict[int, Ack]] = OrderedDict()
        self._alive: set[int] = set()
        self._gcs_up = False
        self._callbacks: dict[str, list[Any]] = {
            k: [] for k in ("traj", "state", "status", "cmd", "ack", "alive")
        }
        self._closed = False
        self._owns_session = session is None
        self._session = open_session(endpoints) if session is None else session
        self._entities: list[Any] = []
        self._pubs: dict[str, Any] = {}
        try:
            self._declare(cfg)
        except BaseException:
            self.close()
            raise

    # --- setup / teardown ----------------------------------------------------------------

    def _declare(self, cfg: BusConfig) -> None:
        s = self._session
        remote = zenoh.Locality.REMOTE
        k = self.keys
        self._entities.append(
            s.declare_subscriber(k.all_traj, self._on_sample, allowed_origin=remote)
        )
        if self.is_gcs:
            self._entities.append(
                s.declare_subscriber(k.all_ack, self._on_sample, allowed_origin=remote)
            )
        else:
            self._entities.append(
                s.declare_subscriber(k.all_cmd, self._on_sample, allowed_origin=remote)
            )
        states = cfg.subscribe_states if cfg.subscribe_states is not None else self.is_gcs
        if states:
            for key in (k.all_state, k.all_status):
                self._entities.append(
                    s.declare_subscriber(key, self._on_sample, allowed_origin=remote)
                )
        self._entities.append(
            s.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True)
        )
        if self.drone_id is not None:
            d = self.drone_id
            fast = {"express": True, "congestion_control": zenoh.CongestionControl.DROP}
            self._pubs["traj"] = s.declare_publisher(
                k.traj(d), priority=zenoh.Priority.DATA_HIGH, **fast
            )
            self._pubs["state"] = s.declare_publisher(
                k.state(d), priority=zenoh.Priority.DATA, **fast
            )
            self._pubs["status"] = s.declare_publisher(
                k.status(d), priority=zenoh.Priority.DATA_LOW
            )
            self._pubs["ack"] = s.declare_publisher(
                k.ack(d),
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                express=True,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            self._token = declare_liveliness(s, k.alive_drone(d))
        else:
            self._token = declare_liveliness(s, k.alive_gcs)

    def close(self) -> None:
        """Withdraw the liveliness token, undeclare everything, close the session if owned.
        Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._acked.notify_all()
        things = [getattr(self, "_token", None), *self._entities, *self._pubs.values()]
        for thing in things:
            if thing is not None:
                try:
                    thing.undeclare()
                except Exception:  # already gone with a closed session: nothing left to free
                    log.debug("%sundeclare failed during close", self.name, exc_info=True)
        self._entities.clear()
        self._pubs.clear()
        if self._owns_session and self._session is not None:
            self._session.close()

    def __enter__(self) -> SwarmNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    # --- PeerBus ---------------------------------------------------------------------------

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        """``PeerBus.publish``: send our trajectory stamped ``now_s``."""
        self.publish_trajectory(msg, now_s)

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        """``PeerBus.receive``: every peer's latest valid trajectory still valid at ``now_s``
        (validity = its stamp + valid_for_s), ``drone_id``'s own excluded."""
        with self._lock:
            return {
                d: p.msg
                for d, p in sorted(self._inbox.items())
                if d != drone_id and now_s <= p.msg.valid_until_s
            }

    def trajectories(self, now_s: float) -> dict[int, TrajectoryMsg]:
        """Every drone's latest trajectory still valid at ``now_s`` (e.g. for a ground-station
        view)."""
        return self.receive(-1, now_s)

    def expired(self, now_s: float, keep_s: float) -> dict[int, TrajectoryMsg]:
        """Peers whose latest trajectory expired less than ``keep_s`` ago (silent peers, still
        to be avoided for a bounded time)."""
        with self._lock:
            return {
                d: p.msg
                for d, p in sorted(self._inbox.items())
                if p.msg.valid_until_s < now_s <= p.msg.valid_until_s + keep_s
            }

    # --- publishing ------------------------------------------------------------------------

    def publish_trajectory(self, msg: TrajectoryMsg, now_s: float | None = None) -> Envelope:
        """Send our trajectory. Its validity is ``msg.valid_until_s - now`` when finite, else
        ``config.traj_valid_for_s``."""
        self._need_drone("publish trajectories")
        if msg.drone_id != self.drone_id:
            raise ValueError(f"trajectory of drone {msg.drone_id} published by {self.drone_id}")
        now = self._clock() if now_s is None else float(now_s)
        valid = msg.valid_until_s - now if math.isfinite(msg.valid_until_s) else None
        return self._send("traj", self.keys.traj(self.sender_id), msg.to_body(), now, valid)

    def publish_state(self, body: StateBody, now_s: float | None = None) -> Envelope:
        self._need_drone("publish states")
        return self._send("state", self.keys.state(self.sender_id), body, now_s)

    def publish_status(self, body: StatusBody, now_s: float | None = None) -> Envelope:
        self._need_drone("publish statuses")
        return self._send("status", self.keys.status(self.sender_id), body, now_s)

    def send_ack(self, cmd_id: int, accepted: bool, reason: str = "") -> Envelope:
        """Answer command ``cmd_id`` (on ``<swarm>/ack/<our id>``)."""
        self._need_drone("acknowledge commands")
        return self._send("ack", self.keys.ack(self.sender_id), Ack(cmd_id, accepted, reason), None)

    def send_command(
        self,
        action: Action,
        targets: Sequence[int] = (),
        *,
        cmd_id: int | None = None,
        issued_s: float | None = None,
        now_s: float | None = None,
    ) -> Command:
        """Send ``action`` to ``targets`` (empty: every drone) on ``<swarm>/cmd/<action>``.
        A resend passes the first send's ``cmd_id`` and ``issued_s``. Returns the command."""
        if not self.is_gcs:
            raise RuntimeError(f"{self.name}only a ground-station node sends commands")
        now = self._clock() if now_s is None else float(now_s)
        if cmd_id is None:
            with self._lock:
                cmd_id = self._next_cmd_id
                self._next_cmd_id += 1
        command = Command(
            int(cmd_id), [int(t) for t in targets], now if issued_s is None else issued_s, action
        )
        tag = kind_of(action)
        with self._send_lock:
            pub = self._pubs.get(f"cmd/{tag}")
            if pub is None and not self._closed:
                pub = self._session.declare_publisher(
                    self.keys.cmd(tag),
                    priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                self._pubs[f"cmd/{tag}"] = pub
        self._send("cmd", self.keys.cmd(tag), command, now, pub=pub)
        return command

    def _need_drone(self, what: str) -> None:
        if self.drone_id is None:
            raise RuntimeError(f"{self.name}a ground-station node does not {what}")

    def _send(
        self,
        kind: str,
        key: str,
        body: Body,
        now_s: float | None,
        valid_for_s: float | None = None,
        pub: Any = None,
    ) -> Envelope:
        if self._closed:
            raise RuntimeError(f"{self.name}swarm bus is closed")
        now = self._clock() if now_s is None else float(now_s)
        valid = getattr(self.config, f"{kind}_valid_for_s") if valid_for_s is None else valid_for_s
        with self._send_lock:  # one sequence order per stream, also on the wire
            seq = self._seq.get(kind, 0)
            env = Envelope(WIRE_VERSION, self.sender_id, self.incarnation, seq, now, valid, body)
            data = encode(env, self.config.limits)  # Rejected names the bad field
            (pub if pub is not None else self._pubs[kind]).put(data)
            self._seq[kind] = seq + 1
        with self._lock:
            self._counters[f"tx.{kind}"] += 1
        return env

    # --- receiving -------------------------------------------------------------------------

    def _on_sample(self, sample: Any) -> None:
        """Zenoh's callback for every data key: gate, store, then user callbacks."""
        name_callback_thread("bus-rx")
        if self._closed:
            return
        try:
            now = self._clock()
            key = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            with self._lock:
                try:
                    env = self._gate.admit(key, payload, now)
                except Rejected:
                    return  # counted and logged by the gate
                callbacks = self._store(env, now)
        except Exception:
            self._count_error("error.internal", "while receiving a message")
            return
        for cb in callbacks:
            self._call(cb, env, now)

    def _store(self, env: Envelope, now: float) -> list[Callback]:
        """Keep what the node remembers of ``env``; the callbacks to run (lock held)."""
        body = env.body
        kind = env.kind
        if kind == "traj":
            self._inbox[env.sender] = _Peer(TrajectoryMsg.from_envelope(env), now)
        elif kind == "state":
            self._states[env.sender] = (env, now)
        elif kind == "status":
            self._statuses[env.sender] = (env, now)
        elif kind == "cmd":
            assert isinstance(body, Command)
            if body.targets and self.drone_id not in body.targets:
                self._counters["cmd.not_addressed"] += 1
                return []
        elif kind == "ack":
            assert isinstance(body, Ack)
            answers = self._acks.setdefault(body.cmd_id, {})
            answers[env.sender] = body
            self._acks.move_to_end(body.cmd_id)
            while len(self._acks) > 256:
                self._acks.popitem(last=False)
            self._acked.notify_all()
        return list(self._callbacks[kind])

    def _on_alive(self, sample: Any) -> None:
        name_callback_thread("bus-alive")
        if self._closed:
            return
        try:
            who = self.keys.parse_alive(str(sample.key_expr))
            if who is None:
                return
            up = sample.kind == zenoh.SampleKind.PUT
            kind, drone = who
            with self._lock:
                if drone is None:
                    self._gcs_up = up
                elif up:
                    self._alive.add(drone)
                else:
                    self._alive.discard(drone)
                callbacks = list(self._callbacks["alive"])
        except Exception:
            self._count_error("error.internal", "while handling a liveliness change")
            return
        log.info(
            "%s%s %s is %s", self.name, kind, "" if drone is None else drone, "up" if up else "down"
        )
        for cb in callbacks:
            try:
                cb(kind, drone, up)
            except Exception:
                self._count_error("error.callback", f"in an on_alive callback {cb!r}")

    def _call(self, cb: Callback, env: Envelope, now: float) -> None:
        try:
            cb(env, now)
        except Exception:
            self._count_error("error.callback", f"in a {env.kind} callback {cb!r}")

    def _count_error(self, counter: str, what: str) -> None:
        with self._lock:
            self._counters[counter] += 1
        log.exception("%sunexpected error %s", self.name, what)

    # --- callbacks -------------------------------------------------------------------------

    def on_trajectory(self, cb: Callback) -> None:
        """``cb(env, receive_s)`` after each accepted peer trajectory entered the inbox."""
        self._add("traj", cb)

    def on_state(self, cb: Callback) -> None:
        """``cb(env, receive_s)`` for each accepted state (needs ``subscribe_states``)."""
        self._add("state", cb)

    def on_status(self, cb: Callback) -> None:
        """``cb(env, receive_s)`` for each accepted status (needs ``subscribe_states``)."""
        self._add("status", cb)

    def on_command(self, cb: Callback) -> None:
        """``cb(env, receive_s)`` for each accepted command addressed to this drone; the
        receiver answers with ``send_ack(env.body.cmd_id, ...)``. A resent command arrives
        again with the same ``cmd_id``."""
        self._need_drone("receive commands")
        self._add("cmd", cb)

    def on_ack(self, cb: Callback) -> None:
        """``cb(env, receive_s)`` for each accepted acknowledgement (ground station)."""
        if not self.is_gcs:
            raise RuntimeError(f"{self.name}only a ground-station node receives acks")
        self._add("ack", cb)

    def on_alive(self, cb: AliveCallback) -> None:
        """``cb(kind, drone_id, alive)`` on every liveliness change (also for tokens present
        when the node started)."""
        self._add("alive", cb)

    def _add(self, kind: str, cb: Any) -> None:
        with self._lock:
            self._callbacks[kind].append(cb)

    # --- queries ---------------------------------------------------------------------------

    def alive_drones(self) -> set[int]:
        """Drones whose liveliness token is up (this drone included)."""
        with self._lock:
            return set(self._alive)

    def gcs_alive(self) -> bool:
        with self._lock:
            return self._gcs_up

    def heard_by_someone(self, kind: str = "traj") -> bool:
        """Whether some other session subscribes to this drone's ``kind`` messages (``traj``,
        ``state``, ``status``, ``ack``): Zenoh's matching status. A liveliness token can arrive
        before the subscriptions, so a message put right after a peer shows up may reach
        nobody; False for a ground-station node (it publishes no such kind)."""
        pub = self._pubs.get(kind)
        return bool(pub is not None and pub.matching_status.matching)

    def query_alive(self, timeout_s: float = 1.0) -> tuple[set[int], bool]:
        """Ask the network now: (drones up, ground station up)."""
        drones: set[int] = set()
        gcs = False
        for reply in self._session.liveliness().get(self.keys.all_alive, timeout=timeout_s):
            if reply.ok is None:
                continue
            who = self.keys.parse_alive(str(reply.ok.key_expr))
            if who is not None and who[0] == "gcs":
                gcs = True
            elif who is not None and who[1] is not None:
                drones.add(who[1])
        return drones, gcs

    def latest_states(self) -> dict[int, tuple[Envelope, float]]:
        """Each drone's latest state envelope and when it arrived."""
        with self._lock:
            return dict(self._states)

    def latest_statuses(self) -> dict[int, tuple[Envelope, float]]:
        with self._lock:
            return dict(self._statuses)

    def acks(self, cmd_id: int) -> dict[int, Ack]:
        """Answers to command ``cmd_id`` so far, by drone id."""
        with self._lock:
            return dict(self._acks.get(cmd_id, {}))

    def wait_acks(self, cmd_id: int, drone_ids: Sequence[int], timeout_s: float) -> set[int]:
        """Wait (real time) until every drone of ``drone_ids`` answered ``cmd_id``; returns the
        ids that did not answer within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        want = set(drone_ids)
        with self._acked:
            while True:
                missing = want - set(self._acks.get(cmd_id, {}))
                left = deadline - time.monotonic()
                if not missing or left <= 0 or self._closed:
                    return missing
                self._acked.wait(left)

    def clock_report(self) -> dict[int, PeerClock]:
        """Estimated clock offset of every sender heard (our clock minus theirs plus the
        smallest latency), with the ``exceeded`` flag of the configured bound."""
        with self._lock:
            return self.clock_offsets.report()

    def clock_exceeded(self) -> set[int]:
        """Senders whose |offset| is above ``config.clock_offset_bound_s``."""
        with self._lock:
            return self.clock_offsets.exceeded()

    def counters(self) -> dict[str, int]:
        """Every counter: ``tx.<kind>``, ``rx.<kind>``, ``reject.<reason>``, ``resync``,
        ``cmd.not_addressed``, ``clock.warnings``, ``error.callback``, ``error.internal``."""
        with self._lock:
            out = dict(self._gate.counters)
            out.update(self._counters)
            out["clock.warnings"] = self.clock_offsets.warnings
            return dict(sorted(out.items()))


ZenohBus = SwarmNode
"""The ``PeerBus`` over Zenoh (the same class: a drone's ``SwarmNode``)."""
