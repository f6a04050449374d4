"""Estimate each peer's clock offset from the stamps of its messages.

A message stamped ``s`` by the sender's clock and received at ``r`` by ours satisfies
``r - s = offset + latency`` with ``offset = our clock - sender's clock`` and ``latency >= 0``.
The minimum of ``r - s`` over a sliding window is therefore ``offset + (smallest latency in the
window)``: an upper bound of the offset that is tight on a LAN (latency of a few ms). One-way
stamps cannot separate offset from latency, so the estimate includes the smallest latency: a
peer whose clock runs ahead of ours gives a negative estimate, one that lags a positive one.

A positive estimate above the bound is therefore only believed with enough evidence: at least
``min_samples`` messages in the window (the minimum of a few is rarely all latency), or an
excess no latency explains (above ``bound + latency_allowance_s``). A sender that speaks rarely
(a ground station's commands) and a slow or lossy bus would otherwise pass for a clock that
lags: 0-150 ms of bus delay once made a drone refuse a goal over a "+0.146 s offset". A
negative estimate below -bound needs no such evidence: latency only raises the estimate.

Not thread-safe: the owner (``MessageGate``) serialises calls.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PeerClock:
    """The clock estimate of one peer.

    offset_s: min over the window of (receive time - send stamp), i.e. our clock minus the
    peer's plus the smallest latency; samples: messages in the window; exceeded: |offset_s| is
    above the configured bound."""

    offset_s: float
    samples: int
    exceeded: bool


class ClockOffsets:
    """Sliding-window minimum of ``receive - stamp`` per peer, with a warning bound.

    bound_s: |offset| above it sets the peer's ``exceeded`` flag, counts a warning and logs it
    (once per excursion; a log line again when the peer comes back within the bound), a
    positive offset only with ``min_samples`` in the window or above ``bound_s +
    latency_allowance_s`` (see the module docstring); window_s: how far back (in receive time)
    samples count.
    """

    def __init__(
        self,
        bound_s: float = 0.05,
        window_s: float = 10.0,
        name: str = "",
        min_samples: int = 3,
        latency_allowance_s: float = 0.5,
    ) -> None:
        if not bound_s > 0.0 or not window_s > 0.0:
            raise ValueError("clock offset bound_s and window_s must be > 0")
        if min_samples < 1 or not latency_allowance_s >= 0.0:
            raise ValueError("clock offset min_samples must be >= 1, latency_allowance_s >= 0")
        self.bound_s = float(bound_s)
        self.window_s = float(window_s)
        self.min_samples = int(min_samples)
        self.latency_allowance_s = float(latency_allowance_s)
        self.name = name
        self.warnings = 0
        # per peer: deque of (receive_s, receive - stamp), values increasing front to back
        self._mins: dict[int, deque[tuple[float, float]]] = {}
        self._counts: dict[int, deque[float]] = {}
        self._exceeded: dict[int, bool] = {}

    def add(self, peer: int, receive_s: float, stamp_s: float) -> None:
        """One message from ``peer`` stamped ``stamp_s`` and received at ``receive_s``."""
        value = receive_s - stamp_s
        q = self._mins.setdefault(peer, deque())
        while q and q[-1][1] >= value:
            q.pop()
        q.append((receive_s, value))
        cut = receive_s - self.window_s
        while len(q) > 1 and q[0][0] < cut:
            q.popleft()
        c = self._counts.setdefault(peer, deque())
        c.append(receive_s)
        while c and c[0] < cut:
            c.popleft()
        offset = q[0][1]
        if offset < -self.bound_s:
            exceeded = True
        elif offset > self.bound_s:
            exceeded = (
                len(c) >= self.min_samples or offset > self.bound_s + self.latency_allowance_s
            )
        else:
            exceeded = False
        was = self._exceeded.get(peer, False)
        if exceeded and not was:
            self.warnings += 1
            log.warning(
                "%sclock offset to sender %d is %+.3f s (bound %.3f s): check chrony",
                self.name,
                peer,
                offset,
                self.bound_s,
            )
        elif was and not exceeded:
            log.info(
                "%sclock offset to sender %d back within bound: %+.3f s", self.name, peer, offset
            )
        self._exceeded[peer] = exceeded

    def offset(self, peer: int) -> float | None:
        """The current estimate for ``peer`` (None before its first message)."""
        q = self._mins.get(peer)
        return q[0][1] if q else None

    def report(self) -> dict[int, PeerClock]:
        """Every peer heard so far."""
        return {
            p: PeerClock(q[0][1], len(self._counts[p]), self._exceeded[p])
            for p, q in sorted(self._mins.items())
        }

    def exceeded(self) -> set[int]:
        """Peers whose |offset| is above the bound."""
        return {p for p, x in self._exceeded.items() if x}

    def max_abs_offset(self) -> float | None:
        """The largest |offset| over the peers (None before any message)."""
        values = [abs(q[0][1]) for q in self._mins.values() if q]
        return max(values) if values else None
