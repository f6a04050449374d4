"""Fault injection for the fast-time path: a ``PeerBus`` wrapper that loses, delays, duplicates
and reorders trajectory messages, with a seeded random generator.

``FaultyBus(inner, BusFaults(...), seed)`` draws, for every published message and in publication
order, whether it is lost, its delay, whether a second copy follows, and whether it is held back
(so that later messages overtake it); surviving copies are handed to ``inner`` at their release
time, when the clock passed to ``publish`` / ``receive`` reaches it. The faults hit a message on
every link at once; for independent losses per link, give the inner ``InMemoryBus`` a
``drop=link_loss(p, seed)``.

``receive`` then behaves as the Zenoh node's inbox does: per receiver it never goes back to an
older trajectory of a sender (the real gate refuses out-of-order and duplicate sequence numbers)
and leaves out trajectories whose validity passed (``TrajectoryMsg.valid_until_s``).

Calls must come with non-decreasing times, as in the fast-time simulator. With ``gate=False``
the wrapper passes on whatever the inner bus delivers and needs of a message only its
``drone_id``: the simulator sends its 10 Hz state messages through a second one (receivers keep
the newest by the sender's stamp).
"""

from __future__ import annotations

import heapq
import random
from collections.abc import Callable
from dataclasses import dataclass

from onboard.comm.bus import PeerBus
from onboard.comm.messages import TrajectoryMsg


@dataclass(frozen=True)
class BusFaults:
    """loss: probability a message is lost; delay_min_s / delay_max_s: uniform delay of each
    copy; duplicate: probability of a second copy (released ``duplicate_lag_s`` after the
    first); reorder: probability a message is held back ``reorder_hold_s`` more, so that the
    next ones overtake it."""

    loss: float = 0.0
    delay_min_s: float = 0.0
    delay_max_s: float = 0.0
    duplicate: float = 0.0
    duplicate_lag_s: float = 0.05
    reorder: float = 0.0
    reorder_hold_s: float = 1.5

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"faults.{name} is a probability in [0, 1], got {p}")
        for name in ("delay_min_s", "delay_max_s", "duplicate_lag_s", "reorder_hold_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"faults.{name} must be >= 0")
        if self.delay_max_s < self.delay_min_s:
            raise ValueError("faults.delay_max_s must be >= faults.delay_min_s")


class FaultyBus:
    """A ``PeerBus`` that injects :class:`BusFaults` in front of ``inner``.

    counters: ``published``, ``lost``, ``duplicated``, ``held_back`` (reordered), ``released``
    (copies handed to the inner bus), ``refused_older`` (an older trajectory than one already
    delivered came out of the inner bus and was not given to the receiver), ``expired``.
    """

    def __init__(
        self, inner: PeerBus, faults: BusFaults | None = None, seed: int = 0, gate: bool = True
    ) -> None:
        self.inner = inner
        self.faults = faults if faults is not None else BusFaults()
        self.gate = gate
        self._rng = random.Random(seed)
        self._pending: list[tuple[float, int, TrajectoryMsg]] = []
        self._n = 0
        self._delivered: dict[int, dict[int, TrajectoryMsg]] = {}
        self._noted: dict[tuple[int, int, str], TrajectoryMsg] = {}  # count each event once
        self.counters = dict.fromkeys(
            (
                "published",
                "lost",
                "duplicated",
                "held_back",
                "released",
                "refused_older",
                "expired",
            ),
            0,
        )

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        f = self.faults
        r = self._rng
        self.counters["published"] += 1
        # Always draw the same number of values, so one fault does not shift the others.
        lost = r.random() < f.loss
        delay = f.delay_min_s + (f.delay_max_s - f.delay_min_s) * r.random()
        dup = r.random() < f.duplicate
        held = r.random() < f.reorder
        if lost:
            self.counters["lost"] += 1
        else:
            release = now_s + delay + (f.reorder_hold_s if held else 0.0)
            self.counters["held_back"] += held
            self._push(release, msg)
            if dup:
                self.counters["duplicated"] += 1
                self._push(release + f.duplicate_lag_s, msg)
        self._flush(now_s)

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        self._flush(now_s)
        got = self.inner.receive(drone_id, now_s)
        if not self.gate:
            return got
        seen = self._delivered.setdefault(drone_id, {})
        for sender, m in got.items():
            prev = seen.get(sender)
            if prev is not None and m.traj_id < prev.traj_id:
                if self._noted.get((drone_id, sender, "older")) is not m:
                    self._noted[(drone_id, sender, "older")] = m
                    self.counters["refused_older"] += 1
                continue
            seen[sender] = m
        out = {}
        for sender, m in sorted(seen.items()):
            if now_s <= m.valid_until_s:
                out[sender] = m
            elif self._noted.get((drone_id, sender, "expired")) is not m:
                self._noted[(drone_id, sender, "expired")] = m
                self.counters["expired"] += 1
        return out

    @property
    def pending(self) -> int:
        """Copies not yet released to the inner bus."""
        return len(self._pending)

    def _push(self, release_s: float, msg: TrajectoryMsg) -> None:
        heapq.heappush(self._pending, (release_s, self._n, msg))
        self._n += 1

    def _flush(self, now_s: float) -> None:
        while self._pending and self._pending[0][0] <= now_s:
            release, _, msg = heapq.heappop(self._pending)
            self.inner.publish(msg, release)
            self.counters["released"] += 1


def link_loss(p: float, seed: int = 0) -> Callable[[int, int], bool]:
    """A ``drop(sender, receiver)`` rule for ``InMemoryBus`` losing each message on each link
    independently with probability ``p`` (seeded; deterministic for a given call order)."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"link loss is a probability in [0, 1], got {p}")
    rng = random.Random(seed)
    return lambda sender, receiver: rng.random() < p
