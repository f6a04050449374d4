"""Faults on the real Zenoh path: a UDP proxy that loses, delays, duplicates, reorders and holds
datagrams between a Zenoh client and its router, and a loopback router for a star topology.

Topology (``FaultyStar``): one Zenoh session in router mode listens on loopback (TCP for clients
that should see a clean path, e.g. the ground station; UDP for the faulty ones). Each faulty
client (a flight service in ``zenoh.mode: client``, no listen endpoint, multicast scouting off)
connects only to its own :class:`UdpFaultProxy`, whose front socket it takes for the router;
the proxy forwards every datagram to the router's UDP endpoint from a back socket of its own
(one per client address) and the router's answers back to the client. Clients never connect
to each other (a Zenoh client has one link, to the router), so every message between two
faulty clients crosses two proxies: the sender's uplink and the receiver's downlink.

Zenoh over ``udp/`` unicast is best effort hop to hop: no retransmission (even for messages
published as reliable) and, in the receiving transport, a frame whose sequence number does not
come after the last one accepted is dropped; so the second copy of a duplicated datagram, and
a datagram overtaken by a later one, reach no application: Zenoh turns both into loss
(``tests/test_bus_faults_process.py`` pins it). Independent delays per datagram reorder
everything closer together than the delay spread (0-300 ms at 100 messages/s: 27 of 200
delivered), hence ``keep_order``. Datagrams delayed in order arrive late; datagrams held
longer than a message's validity arrive stale and the receiving gate refuses them
(``reject.stale``). Zenoh sends declarations (subscribers, liveliness tokens) once: let the
sessions come up on clean links, then turn the faults on.

Faults per datagram and per direction (``up``: client to router, ``down``: router to client),
drawn from a seeded generator in arrival order (:class:`LinkFaults`): loss; a delay uniform in
``[delay_min_s, delay_max_s]`` (``keep_order``: never released before the previous datagram of
the same direction, so delays alone do not reorder); a second copy ``duplicate_lag_s`` after
the first; a hold of ``reorder_hold_s`` more than its own delay, so that the following datagrams
overtake it. :meth:`UdpFaultProxy.hold` keeps everything of a direction for some seconds and
then releases it in order (a link that buffers through an outage). Counters per direction say
what was applied (:meth:`UdpFaultProxy.counters`), so that a test can check the faults happened.

Everything binds 127.0.0.1 on ports the kernel picks; each proxy runs one thread; ``close``
(or the context manager) stops it and closes its sockets.
"""

from __future__ import annotations

import heapq
import math
import random
import selectors
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

DIRECTIONS = ("up", "down")
"""``up``: from the client (front) to the target; ``down``: from the target to the client."""

RCVBUF_BYTES = 4 << 20
"""Receive buffer asked for each proxy socket (the kernel caps it at net.core.rmem_max)."""

COUNTERS = (
    "received",  # datagrams that reached the proxy
    "sent",  # copies forwarded (duplicates included)
    "dropped",  # lost by the loss fault
    "delayed",  # given a delay > 0 (own delay, hold or reorder hold)
    "duplicated",  # a second copy scheduled
    "held_back",  # held back by the reorder fault
    "reordered",  # sent after a datagram of the same direction that arrived later
    "held",  # kept by hold()
    "send_errors",  # the kernel refused to send (nobody listening on loopback)
)


@dataclass(frozen=True)
class LinkFaults:
    """Faults applied to every datagram of one direction.

    loss: probability a datagram is dropped; delay_min_s / delay_max_s: its delay, uniform;
    keep_order: a datagram is never released before the one that arrived before it (delays
    then do not reorder); duplicate: probability of a second copy, ``duplicate_lag_s`` after
    the first; reorder: probability a datagram is held back ``reorder_hold_s`` more than its
    delay (outside the order kept by ``keep_order``), so that later ones overtake it."""

    loss: float = 0.0
    delay_min_s: float = 0.0
    delay_max_s: float = 0.0
    keep_order: bool = True
    duplicate: float = 0.0
    duplicate_lag_s: float = 0.01
    reorder: float = 0.0
    reorder_hold_s: float = 0.05

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder"):
            p = getattr(self, name)
            if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
                raise ValueError(f"faults.{name} is a probability in [0, 1], got {p!r}")
        for name in ("delay_min_s", "delay_max_s", "duplicate_lag_s", "reorder_hold_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 60.0):
                raise ValueError(f"faults.{name} must be in [0, 60] s, got {v!r}")
        if self.delay_max_s < self.delay_min_s:
            raise ValueError(
                f"faults.delay_max_s ({self.delay_max_s}) must be >= faults.delay_min_s "
                f"({self.delay_min_s})"
            )


CLEAN = LinkFaults()


@dataclass
class _Direction:
    faults: LinkFaults
    rng: random.Random
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTERS, 0))
    last_due: float = 0.0  # release time of the previous in-order datagram
    hold_until: float = 0.0
    arrivals: int = 0  # arrival index of the next datagram
    max_sent_arrival: int = -1  # highest arrival index sent so far (first copies)
    max_bytes: int = 0
    late_max_s: float = 0.0  # the proxy's own lateness: send time minus release time


class UdpFaultProxy:
    """A UDP forwarder with faults between clients and ``target`` (host, port).

    Clients send to ``port`` on 127.0.0.1 (``endpoint`` is the Zenoh form,
    ``udp/127.0.0.1:PORT``); each client address gets its own back socket towards ``target``,
    so that the target tells the clients apart. ``faults`` apply to both directions unless
    ``up`` / ``down`` are given; ``seed`` makes the draws repeatable (one generator per
    direction, in arrival order)."""

    def __init__(
        self,
        target: tuple[str, int],
        faults: LinkFaults = CLEAN,
        *,
        up: LinkFaults | None = None,
        down: LinkFaults | None = None,
        seed: int = 0,
        name: str = "",
    ) -> None:
        self.target = (str(target[0]), int(target[1]))
        self.name = name or f"proxy->{self.target[1]}"
        self._dirs = {
            "up": _Direction(up or faults, random.Random(f"{seed}/up")),
            "down": _Direction(down or faults, random.Random(f"{seed}/down")),
        }
        self._lock = threading.Lock()
        self._sel = selectors.DefaultSelector()
        self.front = _udp_socket()
        self.front.setblocking(False)
        self.port = int(self.front.getsockname()[1])
        self._sel.register(self.front, selectors.EVENT_READ, None)
        self._backs: dict[tuple[str, int], socket.socket] = {}
        self._queue: list[tuple[float, int, str, int, bool, bytes, Any]] = []
        self._n = 0
        # a socketpair wakes the thread when the schedule changes (set_faults, hold, close)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"faultproxy-{self.port}")
        self._thread.daemon = True
        self._thread.start()

    # --- configuration ---------------------------------------------------------------------

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint a client connects to: ``udp/127.0.0.1:PORT``."""
        return f"udp/127.0.0.1:{self.port}"

    def _which(self, direction: str) -> tuple[str, ...]:
        if direction == "both":
            return DIRECTIONS
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be 'up', 'down' or 'both', got {direction!r}")
        return (direction,)

    def set_faults(self, faults: LinkFaults, direction: str = "both") -> None:
        """Apply ``faults`` from now on to datagrams arriving in ``direction``."""
        with self._lock:
            for d in self._which(direction):
                self._dirs[d].faults = faults

    def faults(self, direction: str) -> LinkFaults:
        (d,) = self._which(direction)
        with self._lock:
            return self._dirs[d].faults

    def hold(self, seconds: float, direction: str = "both") -> None:
        """Keep every datagram of ``direction`` that arrives in the next ``seconds`` and release
        them all, in order and with their own faults, when the time is up."""
        if not (math.isfinite(seconds) and 0.0 <= seconds <= 60.0):
            raise ValueError(f"hold seconds must be in [0, 60], got {seconds!r}")
        with self._lock:
            until = time.monotonic() + seconds
            for d in self._which(direction):
                self._dirs[d].hold_until = max(self._dirs[d].hold_until, until)

    def counters(self, direction: str = "both") -> dict[str, int]:
        """The counters (``COUNTERS``) of one direction, or their sums over both."""
        with self._lock:
            out = dict.fromkeys(COUNTERS, 0)
            for d in self._which(direction):
                for k, v in self._dirs[d].counters.items():
                    out[k] += v
            return out

    def pending(self) -> int:
        """Copies queued and not sent yet (both directions)."""
        with self._lock:
            return len(self._queue)

    def stats(self) -> dict[str, Any]:
        """Counters per direction, the largest datagram and the proxy's own worst lateness."""
        with self._lock:
            return {
                d: {
                    **s.counters,
                    "max_bytes": s.max_bytes,
                    "late_max_ms": s.late_max_s * 1e3,
                }
                for d, s in self._dirs.items()
            }

    # --- the forwarding thread -------------------------------------------------------------

    def _back_for(self, client: tuple[str, int]) -> socket.socket:
        sock = self._backs.get(client)
        if sock is None:
            sock = _udp_socket()
            sock.setblocking(False)
            self._backs[client] = sock
            self._sel.register(sock, selectors.EVENT_READ, client)
        return sock

    def _schedule(self, direction: str, data: bytes, sock: socket.socket, dest: Any) -> None:
        """Draw this datagram's faults and queue its copies (lock held)."""
        s = self._dirs[direction]
        f = s.faults
        c = s.counters
        now = time.monotonic()
        c["received"] += 1
        s.max_bytes = max(s.max_bytes, len(data))
        index = s.arrivals
        s.arrivals += 1
        # the draws happen in this order for every datagram, whatever the outcome, so that a
        # seed gives the same faults to the same arrival
        lost = s.rng.random() < f.loss
        delay = s.rng.uniform(f.delay_min_s, f.delay_max_s)
        dup = s.rng.random() < f.duplicate
        back = s.rng.random() < f.reorder
        if lost:
            c["dropped"] += 1
            return
        due = now + delay
        if now < s.hold_until:
            due = max(due, s.hold_until)
            c["held"] += 1
        if f.keep_order:
            due = max(due, s.last_due)
        s.last_due = max(s.last_due, due)
        if back:
            due += f.reorder_hold_s
            c["held_back"] += 1
        if due > now:
            c["delayed"] += 1
        self._push(due, direction, index, True, data, (sock, dest))
        if dup:
            c["duplicated"] += 1
            self._push(due + f.duplicate_lag_s, direction, index, False, data, (sock, dest))

    def _push(
        self, due: float, direction: str, index: int, first: bool, data: bytes, route: Any
    ) -> None:
        heapq.heappush(self._queue, (due, self._n, direction, index, first, data, route))
        self._n += 1

    def _release(self) -> float:
        """Send every copy that is due; seconds until the next one (inf: none)."""
        while True:
            with self._lock:
                if not self._queue:
                    return math.inf
                now = time.monotonic()
                due = self._queue[0][0]
                if due > now:
                    return due - now
                _, _, direction, index, first, data, (sock, dest) = heapq.heappop(self._queue)
                s = self._dirs[direction]
                s.late_max_s = max(s.late_max_s, now - due)
                if first:
                    if index < s.max_sent_arrival:
                        s.counters["reordered"] += 1
                    s.max_sent_arrival = max(s.max_sent_arrival, index)
            try:
                sock.sendto(data, dest)
            except OSError:  # ICMP port unreachable on loopback: the receiver is gone
                with self._lock:
                    s.counters["send_errors"] += 1
                continue
            with self._lock:
                s.counters["sent"] += 1

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                wait = min(self._release(), 0.2)
                for key, _ in self._sel.select(wait):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    if key.data == "wake":
                        try:
                            sock.recv(64)
                        except BlockingIOError:
                            pass
                        continue
                    self._drain(sock, key.data)
        finally:
            self._sel.close()

    def _drain(self, sock: socket.socket, client: tuple[str, int] | None) -> None:
        """Read every datagram waiting on ``sock`` (the front socket when ``client`` is None,
        else the back socket of ``client``) and schedule it."""
        while True:
            try:
                data, addr = sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                # a previous send from this socket hit a closed port (ICMP error reported on
                # the next receive): nothing to read from it now
                return
            with self._lock:
                if client is None:
                    self._schedule("up", data, self._back_for(addr), self.target)
                else:
                    self._schedule("down", data, self.front, client)

    def close(self) -> None:
        """Stop the thread and close every socket (idempotent). Datagrams still queued are
        discarded."""
        if self._stop.is_set():
            return
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._thread.join(5.0)
        for sock in (self.front, *self._backs.values(), self._wake_r, self._wake_w):
            sock.close()

    def __enter__(self) -> UdpFaultProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _udp_socket() -> socket.socket:
    """A UDP socket on 127.0.0.1 (a port the kernel picks) with a receive buffer that holds a
    burst (Zenoh fragments, a released hold) while the proxy's thread waits for the CPU."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
    sock.bind(("127.0.0.1", 0))
    return sock


class FaultyStar:
    """A Zenoh router on loopback and one :class:`UdpFaultProxy` per faulty client.

    ``client_zenoh(i)``: the ``zenoh`` section of client ``i``'s service config (client mode,
    connected only to its proxy); ``client_endpoints(i)``: the same as ``ZenohEndpoints``;
    ``direct_endpoints()``: a clean TCP path to the router (ground station, observers).
    ``faults`` apply to every proxy from the start (usually ``CLEAN``: set them once the
    sessions are up with :meth:`set_faults`, so that the sessions' declarations, which Zenoh
    sends once and never repeats, are not lost). Proxy ``i`` draws with seed ``seed + i``.
    """

    def __init__(self, clients: int, faults: LinkFaults = CLEAN, seed: int = 0) -> None:
        from onboard.comm.loopback import free_port
        from onboard.comm.zenoh_session import ZenohEndpoints, free_loopback_endpoint, open_session

        if clients < 1:
            raise ValueError(f"clients must be >= 1, got {clients}")
        self.tcp_endpoint = free_loopback_endpoint()
        self.udp_port = free_port(socket.SOCK_DGRAM)  # outside the ephemeral range
        self.router_endpoints = ZenohEndpoints(
            mode="router",
            listen=(self.tcp_endpoint, f"udp/127.0.0.1:{self.udp_port}"),
        )
        self.router: Any = open_session(self.router_endpoints)
        self.proxies: list[UdpFaultProxy] = []
        try:
            for i in range(clients):
                self.proxies.append(
                    UdpFaultProxy(
                        ("127.0.0.1", self.udp_port), faults, seed=seed + i, name=f"client{i}"
                    )
                )
        except BaseException:
            self.close()
            raise

    def client_zenoh(self, i: int) -> dict[str, Any]:
        return {
            "mode": "client",
            "listen": [],
            "connect": [self.proxies[i].endpoint],
            "multicast_scouting": False,
        }

    def client_endpoints(self, i: int) -> Any:
        from onboard.comm.zenoh_session import ZenohEndpoints

        return ZenohEndpoints(mode="client", connect=(self.proxies[i].endpoint,))

    def direct_endpoints(self) -> Any:
        from onboard.comm.zenoh_session import ZenohEndpoints

        return ZenohEndpoints(mode="client", connect=(self.tcp_endpoint,))

    def set_faults(self, faults: LinkFaults, direction: str = "both") -> None:
        for p in self.proxies:
            p.set_faults(faults, direction)

    def counters(self, direction: str = "both") -> dict[str, int]:
        """Every proxy's counters summed."""
        out = dict.fromkeys(COUNTERS, 0)
        for p in self.proxies:
            for k, v in p.counters(direction).items():
                out[k] += v
        return out

    def stats(self) -> Mapping[str, Any]:
        return {p.name: p.stats() for p in self.proxies}

    def close(self) -> None:
        for p in self.proxies:
            p.close()
        if self.router is not None:
            self.router.close()
            self.router = None

    def __enter__(self) -> FaultyStar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
