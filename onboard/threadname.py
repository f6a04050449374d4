"""OS-level names for the service's threads, so that ``top -H``, ``ps -L`` and the per-thread
CPU figures in ``/proc/<pid>/task/*/comm`` tell the workers apart (Python only names its own
``threading.Thread`` objects; before 3.14 the kernel sees every thread as the process)."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import threading
from collections.abc import Callable

_PR_SET_NAME = 15
_libc: ctypes.CDLL | None = None
if sys.platform.startswith("linux"):
    _path = ctypes.util.find_library("c")
    if _path is not None:
        _libc = ctypes.CDLL(_path, use_errno=True)


def set_os_thread_name(name: str) -> bool:
    """Give the calling thread the kernel name ``name`` (cut to 15 bytes, the kernel's limit);
    False where the platform has no such name."""
    if _libc is None:
        return False
    raw = name.encode("ascii", "replace")[:15]
    return int(_libc.prctl(_PR_SET_NAME, ctypes.c_char_p(raw), 0, 0, 0)) == 0


_named = threading.local()
"""``done``: this thread has its name (``named_thread``, or a first ``name_callback_thread``)."""


def named_thread(target: Callable[[], None], name: str, daemon: bool = True) -> threading.Thread:
    """A ``threading.Thread`` called ``name`` whose OS thread carries the same name."""

    def run() -> None:
        set_os_thread_name(name)
        _named.done = True  # named here: never renamed by a callback it runs
        target()

    return threading.Thread(target=run, name=name, daemon=daemon)


def name_callback_thread(name: str) -> None:
    """Give the calling thread the OS name ``name`` the first time it calls this: for threads
    that a library starts and runs our callbacks in (Zenoh's Python handlers run each
    subscriber's callback in a thread of their own), which would otherwise count their CPU
    under the process's name in ``/proc/<pid>/task/*``. A thread-local flag after that (tens
    of nanoseconds a call). The main thread and the threads of ``named_thread`` keep their
    names (a library may run a callback in the thread that triggered it)."""
    if getattr(_named, "done", False):
        return
    _named.done = True
    if threading.current_thread() is not threading.main_thread():
        set_os_thread_name(name)
