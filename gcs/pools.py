"""What the benchmarks' process pools and the demo share: SIGTERM handled as Ctrl-C."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM ends a run as Ctrl-C does (KeyboardInterrupt), so that its cleanup runs: a
    pool's workers are terminated on the way out (SIGTERM's default action ends this process
    alone; the workers went on flying the trials already queued to them, for minutes), the
    demo stops its processes. Only from the main thread, where signals are handled; elsewhere
    nothing changes. (Raising is all the handler does: it takes no lock, see
    ``onboard/stopsignal.py``.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
