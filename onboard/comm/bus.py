"""Peer buses: how a drone publishes its trajectory and reads its peers' latest ones."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from onboard.comm.messages import TrajectoryMsg


class PeerBus(Protocol):
    """Broadcast of trajectories; the clock is passed in (``now_s``, global seconds)."""

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        """Broadcast ``msg`` at time ``now_s``."""
        ...

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        """Latest message from each peer received by ``drone_id`` by ``now_s`` (own excluded)."""
        ...


@dataclass
class _Entry:
    visible_s: float
    msg: TrajectoryMsg


@dataclass
class _Inbox:
    """What one receiver has taken from each sender's log: next index and latest delivered."""

    cursor: dict[int, int] = field(default_factory=dict)
    latest: dict[int, TrajectoryMsg] = field(default_factory=dict)


class InMemoryBus:
    """An in-process bus with a fixed delivery delay and an optional per-link drop rule.

    A message published at ``t`` becomes visible at ``t + delay_s``. ``drop(sender, receiver)``
    is asked once per message and receiver; True loses that message for that receiver (the
    receiver keeps the previous one), e.g. ``drop=lambda s, r: s == 3`` silences drone 3.
    Each receiver sees only the latest visible message per sender. Messages every known receiver
    has passed are pruned (the newest is always kept for receivers that join later, whose first
    call starts at the oldest message still logged), so memory stays bounded by the messages in
    flight.
    """

    def __init__(
        self, delay_s: float = 0.0, drop: Callable[[int, int], bool] | None = None
    ) -> None:
        if not delay_s >= 0.0:
            raise ValueError("delay_s must be >= 0")
        self.delay_s = float(delay_s)
        self.drop = drop
        self._log: dict[int, list[_Entry]] = {}
        self._base: dict[int, int] = {}  # absolute index of _log[sender][0]
        self._inboxes: dict[int, _Inbox] = {}

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        log = self._log.setdefault(msg.drone_id, [])
        self._base.setdefault(msg.drone_id, 0)
        visible = float(now_s) + self.delay_s
        if log and visible < log[-1].visible_s:  # keep the log ordered by visibility
            visible = log[-1].visible_s
        log.append(_Entry(visible, msg))

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        inbox = self._inboxes.setdefault(drone_id, _Inbox())
        for sender, log in self._log.items():
            if sender == drone_id:
                continue
            base = self._base[sender]
            i = max(inbox.cursor.get(sender, base), base)
            while i - base < len(log) and log[i - base].visible_s <= now_s:
                m = log[i - base].msg
                if self.drop is None or not self.drop(sender, drone_id):
                    inbox.latest[sender] = m
                i += 1
            inbox.cursor[sender] = i
            self._prune(sender)
        return dict(inbox.latest)

    def _prune(self, sender: int) -> None:
        log = self._log[sender]
        base = self._base[sender]
        receivers = [d for d in self._inboxes if d != sender]
        if not receivers:
            return
        done = min(self._inboxes[d].cursor.get(sender, base) for d in receivers)
        k = min(done - base, len(log) - 1)  # the newest stays for receivers joining later
        if k > 0:
            del log[:k]
            self._base[sender] = done
