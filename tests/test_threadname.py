"""OS thread names: the service's own threads and the library threads that run its callbacks
carry names in ``/proc/<pid>/task/*/comm``, so that per-thread CPU figures tell them apart."""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import pytest

from gcs.procstat import stat_cpu_s, thread_cpu_s
from onboard.threadname import name_callback_thread, named_thread

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="OS thread names are read from Linux's /proc"
)


def os_name(native_id: int) -> str:
    return Path(f"/proc/self/task/{native_id}/comm").read_text().strip()


def test_named_thread_carries_its_name_in_the_kernel() -> None:
    seen: list[str] = []
    t = named_thread(lambda: seen.append(os_name(threading.get_native_id())), "svc-longer-name")
    t.start()
    t.join(10.0)
    u = named_thread(lambda: seen.append(os_name(threading.get_native_id())), "svc-longer-name-2")
    u.start()
    u.join(10.0)
    assert seen == ["svc-longer-name", "svc-longer-name"]  # the kernel keeps 15 bytes
    assert (t.name, u.name) == ("svc-longer-name", "svc-longer-name-2")


def test_a_callback_thread_is_named_once() -> None:
    """The first call names the thread; later calls (another callback run in the same thread)
    keep that name; another thread gets its own."""
    names: list[str] = []

    def callback(name: str) -> None:
        name_callback_thread(name)
        names.append(os_name(threading.get_native_id()))

    def run() -> None:
        callback("bus-rx")
        callback("depth-rx")

    t = threading.Thread(target=run)
    t.start()
    t.join(10.0)
    other = threading.Thread(target=callback, args=("depth-rx",))
    other.start()
    other.join(10.0)
    assert names == ["bus-rx", "bus-rx", "depth-rx"]


def test_a_callback_keeps_the_name_of_a_named_thread_and_of_the_main_thread() -> None:
    """A library may run a callback in the thread that triggered it: a ``named_thread`` and the
    main thread keep their names."""
    seen: list[str] = []

    def work() -> None:
        name_callback_thread("bus-rx")
        seen.append(os_name(threading.get_native_id()))

    t = named_thread(work, "svc-planner")
    t.start()
    t.join(10.0)
    main = os_name(threading.get_native_id())
    assert threading.current_thread() is threading.main_thread()
    name_callback_thread("bus-rx")
    assert seen == ["svc-planner"] and os_name(threading.get_native_id()) == main


def test_thread_cpu_by_name_from_proc() -> None:
    """``gcs.procstat``: a named thread that spins shows under its name, and the threads' sum
    stays within the process's total (threads that ended count in the total only)."""
    stop = threading.Event()

    def spin() -> None:
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
        stop.wait(10.0)

    t = named_thread(spin, "test-spinner")
    t.start()
    try:
        deadline = time.monotonic() + 10.0
        while thread_cpu_s(os.getpid()).get("test-spinner", 0.0) < 0.05:
            assert time.monotonic() < deadline, thread_cpu_s(os.getpid())
            time.sleep(0.05)
        threads = thread_cpu_s(os.getpid())
        total = stat_cpu_s(f"/proc/{os.getpid()}/stat")
        assert sum(threads.values()) <= total + 0.02
    finally:
        stop.set()
        t.join(10.0)
    with pytest.raises(OSError):
        stat_cpu_s("/proc/0/stat")
