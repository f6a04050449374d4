"""A lock that the setpoint streamer holds most of the time without shutting others out.

With timed setpoints (``timed_send``) the streamer prepares a tick right after the previous one
left and holds the link's send locks while the native sender waits for the deadline: about 19
of every 20 ms, taken again within microseconds of their release. Python's locks are not fair.
A thread woken by the release takes the lock only if it runs before the streamer takes it
again, and the streamer runs at real-time priority. With both threads on one busy core, a
command could wait behind the stream for as long as the stream went on: a take-off's
DO_SET_MODE was seen 40 s late in a three-drone test on 2 cores. ``StreamLock`` makes the
streamer let the other threads through first: every other thread counts itself as waiting
before it blocks, and the streamer's ``after_waiters`` waits until no one is waiting before it
takes the lock. It waits at most until a bound that the caller sets shortly before the
setpoint's deadline, so the stream stays on time. The other threads hold the lock only to send
one message or to flip a flag.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from types import TracebackType

YIELD_BEFORE_DEADLINE_S = 0.002
"""The streamer lets waiting threads through until this long before its setpoint's deadline."""


class StreamLock:
    """``with lock:`` for every thread but the streamer; ``with lock.after_waiters(t):`` for
    the streamer (not reentrant, like ``threading.Lock``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cond = threading.Condition(threading.Lock())
        self._waiting = 0

    def __enter__(self) -> StreamLock:
        with self._cond:
            self._waiting += 1
        try:
            self._lock.acquire()
        finally:
            with self._cond:
                self._waiting -= 1
                if not self._waiting:
                    self._cond.notify_all()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._lock.release()

    @property
    def waiting(self) -> int:
        """Threads other than the streamer waiting for the lock now."""
        return self._waiting

    @contextmanager
    def after_waiters(self, until_s: float | None) -> Iterator[None]:
        """Hold the lock, taken once no other thread waits for it or at ``until_s``
        (``time.monotonic`` seconds) at the latest (None: at once, as a plain lock)."""
        if until_s is not None and self._waiting:
            with self._cond:
                while self._waiting:
                    left = until_s - time.monotonic()
                    if left <= 0.0:
                        break
                    self._cond.wait(left)
        self._lock.acquire()
        try:
            yield
        finally:
            self._lock.release()
