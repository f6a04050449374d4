"""The receiving side of the swarm bus: every payload passes one gate before anyone sees it.

``MessageGate.admit(key, payload, receive_s)`` returns a checked :class:`Envelope` or raises
:class:`Rejected`, counting each outcome. Checks, in order: the key expression, then
:func:`onboard.comm.wire.decode` (size, version, structure, finite numbers, durations, pieces,
ranges), then the body kind and sender against the key, a remote message under our own id, the
clock sample (kept for the peer's offset estimate even when the message is refused later), a
stamp from the future, staleness, and the sequence (duplicate / out of order).

Not thread-safe: the owner (``SwarmNode``) holds a lock around ``admit``.
"""

from __future__ import annotations

import logging

from onboard.comm.clock import ClockOffsets
from onboard.comm.keys import SwarmKeys
from onboard.comm.wire import (
    DEFAULT_LIMITS,
    REASONS,
    STREAMS,
    Command,
    Envelope,
    Rejected,
    WireLimits,
    decode,
    kind_of,
)

log = logging.getLogger(__name__)


class MessageGate:
    """Checks payloads from one swarm for a node whose own sender id is ``own_id``.

    resync_after_s: a sender whose incarnation went *down* (its clock stepped back across a
    restart) is accepted again once nothing was accepted from it on that stream for this long.
    counters: ``rx.<kind>`` accepted, ``reject.<reason>`` refused, ``resync``.
    """

    def __init__(
        self,
        swarm: str,
        own_id: int | None,
        limits: WireLimits = DEFAULT_LIMITS,
        clock: ClockOffsets | None = None,
        resync_after_s: float = 5.0,
        name: str = "",
    ) -> None:
        self.keys = SwarmKeys(swarm)
        self.own_id = own_id
        self.limits = limits
        self.clock = clock if clock is not None else ClockOffsets()
        self.resync_after_s = float(resync_after_s)
        self.name = name
        self.counters: dict[str, int] = {f"reject.{r}": 0 for r in REASONS}
        self.counters.update({f"rx.{k}": 0 for k in STREAMS})
        self.counters["resync"] = 0
        # (stream, sender) -> (incarnation, seq, receive_s) of the last accepted message
        self._last: dict[tuple[str, int], tuple[int, int, float]] = {}
        self._warned: set[tuple[str, str]] = set()

    def admit(
        self, key: str, payload: bytes | bytearray | memoryview, receive_s: float
    ) -> Envelope:
        """The checked message, or :class:`Rejected` (counted and logged)."""
        try:
            env = self._admit(key, payload, receive_s)
        except Rejected as r:
            self.counters[f"reject.{r.reason}"] += 1
            first = (r.reason, key) not in self._warned
            if first:
                self._warned.add((r.reason, key))
            log.log(
                logging.WARNING if first else logging.DEBUG,
                "%srejected message on %s: %s",
                self.name,
                key,
                r,
            )
            raise
        self.counters[f"rx.{env.kind}"] += 1
        return env

    def _admit(self, key: str, payload: bytes | bytearray | memoryview, now: float) -> Envelope:
        stream, what = self.keys.parse(key)
        env = decode(payload, self.limits, kind=stream)
        kind = kind_of(env.body)
        if kind != stream:
            raise Rejected("kind_mismatch", f"a {kind} message on {key}")
        if stream == "cmd":
            assert isinstance(env.body, Command)
            action = kind_of(env.body.action)
            if action != what:
                raise Rejected("kind_mismatch", f"a {action} command on {key}")
        elif env.sender != what:
            raise Rejected("sender_mismatch", f"sender {env.sender} on {key}")
        if self.own_id is not None and env.sender == self.own_id:
            raise Rejected("own_id", f"another session sends as our id {env.sender} on {key}")
        self.clock.add(env.sender, now, env.stamp_s)
        if env.stamp_s > now + self.limits.max_future_s:
            raise Rejected(
                "future_stamp", f"stamp {env.stamp_s - now:+.3f} s ahead of our clock on {key}"
            )
        if now > env.valid_until_s:
            raise Rejected(
                "stale", f"received {now - env.valid_until_s:.3f} s after its validity on {key}"
            )
        self._check_sequence(stream, env, now, key)
        return env

    def _check_sequence(self, stream: str, env: Envelope, now: float, key: str) -> None:
        slot = (stream, env.sender)
        last = self._last.get(slot)
        here = (env.incarnation, env.seq)
        if last is not None:
            before = (last[0], last[1])
            if here == before:
                raise Rejected("duplicate", f"seq {env.seq} again on {key}")
            if here < before:
                if env.incarnation < last[0] and now - last[2] > self.resync_after_s:
                    self.counters["resync"] += 1
                    log.warning(
                        "%ssender %d restarted with a smaller incarnation on %s: resynchronised",
                        self.name,
                        env.sender,
                        key,
                    )
                else:
                    raise Rejected("out_of_order", f"seq {here} after {before} on {key}")
        self._last[slot] = (env.incarnation, env.seq, now)
