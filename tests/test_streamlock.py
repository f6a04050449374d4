"""The streamer's lock lets a waiting command through (onboard.autopilot.streamlock).

The rig reproduces what held a take-off's DO_SET_MODE back for 40 s in a three-drone test:
a streamer at real-time priority that holds the lock for 19 of every 20 ms and takes it again
at once, and a command thread on the same core. Where SCHED_FIFO is not permitted the streamer
runs at normal priority, and a plain lock is then seldom starved; with it (as here), a plain
lock was never released to the other thread in 2 s (the test allows 0.5 s).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager

import pytest

from onboard.autopilot import timed_send
from onboard.autopilot.streamlock import YIELD_BEFORE_DEADLINE_S, StreamLock

PERIOD_S = 0.02


def _one_cpu() -> set[int]:
    return {min(os.sched_getaffinity(0))}


def _waits(
    streamer_hold: Callable[[float], AbstractContextManager[object]],
    other_hold: Callable[[], AbstractContextManager[object]],
    tries: int = 10,
    give_up_s: float = 2.0,
) -> list[float]:
    """Seconds the other thread waited for the lock, each of ``tries`` times, while the
    streamer (its own thread) holds it up to each deadline and takes it again at once; both
    on one CPU, the streamer at real-time priority where permitted. ``give_up_s``: a wait this
    long is recorded as inf (the lock then is not taken by that try)."""
    cpu = _one_cpu()
    stop = threading.Event()
    started = threading.Event()

    def streamer() -> None:
        os.sched_setaffinity(threading.get_native_id(), cpu)
        timed_send.request_realtime()
        next_t = time.monotonic() + PERIOD_S
        started.set()
        while not stop.is_set():
            deadline = next_t
            next_t += PERIOD_S
            with streamer_hold(deadline - YIELD_BEFORE_DEADLINE_S):
                left = deadline - time.monotonic()
                if left > 0.0:
                    time.sleep(left)  # the native sender waiting for the deadline

    t = threading.Thread(target=streamer, daemon=True)
    waits: list[float] = []
    old = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(threading.get_native_id(), cpu)
        t.start()
        assert started.wait(5.0)
        for _ in range(tries):
            time.sleep(0.013)  # some phase within the streamer's period
            got = threading.Event()
            t0 = time.monotonic()

            def take(got: threading.Event = got) -> None:
                with other_hold():
                    got.set()

            taker = threading.Thread(target=take, daemon=True)
            taker.start()
            waits.append(time.monotonic() - t0 if got.wait(give_up_s) else float("inf"))
            if not got.is_set():
                stop.set()  # the streamer stops taking it: the taker gets it and ends
            taker.join(5.0)
            assert not taker.is_alive()
            if stop.is_set():
                break
    finally:
        stop.set()
        t.join(5.0)
        os.sched_setaffinity(threading.get_native_id(), old)
    assert not t.is_alive()
    return waits


@pytest.mark.timeout(60)
def test_a_waiting_thread_gets_the_lock_within_a_period() -> None:
    lock = StreamLock()
    waits = _waits(lock.after_waiters, lambda: lock)
    assert len(waits) == 10
    # a plain lock: more than 2 s (the streamer never let go); the bound leaves room for a
    # loaded machine's scheduling (the taker shares its CPU with whatever else runs there)
    assert max(waits) < 25 * PERIOD_S, waits
    assert lock.waiting == 0


@pytest.mark.timeout(60)
def test_after_waiters_waits_no_longer_than_its_bound() -> None:
    """A waiter that never comes to take the lock (it counted itself, then was starved)
    delays the streamer until the bound, not beyond."""
    lock = StreamLock()
    with lock._cond:  # noqa: SLF001 - a waiter that has counted itself and is not scheduled
        lock._waiting += 1  # noqa: SLF001
    t0 = time.monotonic()
    with lock.after_waiters(t0 + 0.05):
        waited = time.monotonic() - t0
    assert 0.04 <= waited < 1.0
    with lock.after_waiters(None):  # no bound: at once
        pass
    t1 = time.monotonic()
    with lock.after_waiters(t1 - 1.0):  # a bound already past: at once
        assert time.monotonic() - t1 < 0.04


@pytest.mark.timeout(60)
def test_the_lock_excludes_as_a_lock() -> None:
    lock = StreamLock()
    inside = 0
    most = 0
    guard = threading.Lock()

    def enter() -> None:
        nonlocal inside, most
        for i in range(300):
            cm = lock.after_waiters(time.monotonic() + 0.001) if i % 2 else lock
            with cm:
                with guard:
                    inside += 1
                    most = max(most, inside)
                time.sleep(0)
                with guard:
                    inside -= 1

    threads = [threading.Thread(target=enter) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(30.0)
    assert most == 1 and inside == 0 and lock.waiting == 0
