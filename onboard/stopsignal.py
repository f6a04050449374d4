"""SIGINT and SIGTERM end a long-running process in order, and for certain.

A Python signal handler runs in the main thread between two bytecodes, wherever that thread is,
possibly inside ``Event.set`` or ``Event.clear`` holding the lock the handler would take, and a
handler may run again inside itself when signals come close together. A handler that takes a
lock can therefore deadlock the process for good. It was seen twice: a flight service silent
for 20 s after SIGTERM, and the mock fleet alive for ever after its parent, the demo, was
killed (each child then gets SIGTERM from the kernel; the handler, nested four deep, waited on
the lock of ``Event.set``).

So the handler here only puts the signal number on a ``queue.SimpleQueue`` (whose ``put`` is
safe in a signal handler), and a thread started beforehand does the rest:

- the first signal calls ``request_stop`` (the process then stops in its own order);
- a second signal ends the process at once (an operator's second Ctrl-C);
- if the process has not ended ``deadline_s`` after the first signal, ``on_deadline`` runs
  (say why, in the log) and the process ends, with status 1: a stop that hangs (a thread or a
  session close blocking on a vanished peer) must not leave the process behind; systemd would
  SIGKILL it after TimeoutStopSec, a demo or a test has nobody to do that.
"""

from __future__ import annotations

import os
import queue
import signal
import threading
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any

from onboard.threadname import named_thread

STOP_SIGNALS: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)


class SignalStop:
    """Stop on SIGINT / SIGTERM through a thread of its own, with a deadline (module doc).

    Use as a context manager in the main thread around the process's work; leaving it restores
    the previous handlers, while the thread and its deadline stay (they cover the teardown after
    the work too). ``exit`` is ``os._exit`` except in tests."""

    def __init__(
        self,
        request_stop: Callable[[], None],
        deadline_s: float,
        on_deadline: Callable[[], None] | None = None,
        signals: Sequence[int] = STOP_SIGNALS,
        thread_name: str = "stopper",
        exit: Callable[[int], Any] = os._exit,  # noqa: A002 - what it stands for
    ) -> None:
        if not deadline_s > 0.0:
            raise ValueError(f"deadline_s must be > 0, got {deadline_s!r}")
        self.request_stop = request_stop
        self.deadline_s = float(deadline_s)
        self.on_deadline = on_deadline
        self.signals = tuple(signals)
        self.thread_name = thread_name
        self._exit = exit
        self._queue: queue.SimpleQueue[int] = queue.SimpleQueue()
        self._old: dict[int, Any] = {}
        self._thread: threading.Thread | None = None
        self.received: list[int] = []  # by the thread, not the handler (no lock in a handler)

    def handle(self, signum: int, _frame: FrameType | None = None) -> None:
        """The signal handler: safe to run anywhere, also inside itself."""
        self._queue.put(signum)

    def _run(self) -> None:
        self.received.append(self._queue.get())
        self.request_stop()
        try:
            self.received.append(self._queue.get(timeout=self.deadline_s))
        except queue.Empty:
            if self.on_deadline is not None:
                self.on_deadline()
        self._exit(1)

    def __enter__(self) -> SignalStop:
        if threading.current_thread() is not threading.main_thread():
            raise RuntimeError("signal handlers can only be installed from the main thread")
        if self._thread is None:
            self._thread = named_thread(self._run, self.thread_name, daemon=True)
            self._thread.start()
        self._old = {s: signal.signal(s, self.handle) for s in self.signals}
        return self

    def __exit__(self, *exc: object) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old = {}
