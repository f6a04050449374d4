"""``onboard.stopsignal.SignalStop``: the first signal asks for a stop, a second one or the
deadline ends the process, and the handler stays safe wherever the main thread is."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from onboard.stopsignal import SignalStop


class _Exit:
    def __init__(self) -> None:
        self.codes: list[int] = []
        self.done = threading.Event()

    def __call__(self, code: int) -> None:
        self.codes.append(code)
        self.done.set()


def test_first_signal_requests_a_stop_and_a_second_ends_the_process() -> None:
    asked = threading.Event()
    ex = _Exit()
    stop = SignalStop(asked.set, 30.0, exit=ex)
    with stop:
        assert signal.getsignal(signal.SIGTERM) == stop.handle
        stop.handle(signal.SIGTERM)
        assert asked.wait(5.0)
        assert not ex.done.is_set()  # the process stops in its own order
        stop.handle(signal.SIGINT)
        assert ex.done.wait(5.0)  # long before the 30 s deadline
    assert ex.codes == [1]
    assert stop.received == [signal.SIGTERM, signal.SIGINT]
    assert signal.getsignal(signal.SIGTERM) != stop.handle  # restored on leaving


def test_the_deadline_ends_a_stop_that_hangs() -> None:
    ex = _Exit()
    late: list[float] = []
    t0 = time.monotonic()
    stop = SignalStop(lambda: None, 0.3, lambda: late.append(time.monotonic() - t0), exit=ex)
    with stop:
        stop.handle(signal.SIGTERM)
        assert ex.done.wait(10.0)
    assert ex.codes == [1]
    assert len(late) == 1 and late[0] >= 0.3


def test_bad_deadline_and_thread() -> None:
    with pytest.raises(ValueError, match="deadline_s"):
        SignalStop(lambda: None, 0.0)
    errors: list[BaseException] = []

    def other() -> None:
        try:
            SignalStop(lambda: None, 1.0).__enter__()
        except RuntimeError as e:
            errors.append(e)

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert len(errors) == 1 and "main thread" in str(errors[0])


# A process whose main thread spends its time inside Event.set / Event.clear (holding their
# lock), as the mock's loop and the service's did when a handler that called Event.set
# deadlocked them; ``request_stop`` is a no-op when HANG is set, so only the deadline ends it.
CHILD = textwrap.dedent(
    """
    import sys, threading
    from onboard.stopsignal import SignalStop

    hang = sys.argv[1] == "hang"
    stop = threading.Event()
    busy = threading.Event()

    def gave_up():
        print("deadline", flush=True)

    with SignalStop((lambda: None) if hang else stop.set, 1.0, gave_up):
        print("ready", flush=True)
        while not stop.is_set():
            busy.set()
            busy.clear()
    print("stopped", flush=True)
    """
)


def _signalled_child(mode: str, signals: int) -> tuple[int, str, float]:
    """CHILD in ``mode``, sent ``signals`` SIGTERMs once ready: (exit status, output, seconds
    from the first signal to its end). Killed if it outlives the test."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, mode], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        t0 = time.monotonic()
        for _ in range(signals):
            proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20.0)
        return proc.returncode, out, time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("burst", [1, 30])
def test_a_process_stops_in_order_also_under_a_burst_of_signals(burst: int) -> None:
    rc, out, _ = _signalled_child("run", burst)
    if burst == 1:
        assert rc == 0 and "stopped" in out  # its own order, to the end
    else:
        assert rc in (0, 1)  # the second signal may end it first


def test_a_process_whose_stop_hangs_ends_at_the_deadline() -> None:
    rc, out, waited = _signalled_child("hang", 1)
    assert rc == 1
    assert "deadline" in out and "stopped" not in out
    assert waited >= 1.0
