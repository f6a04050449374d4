"""Send a datagram at an absolute deadline without holding the interpreter lock.

The setpoint streamer prepares each setpoint ahead of its tick and hands the encoded bytes to
``TimedSender.send_at``: one native call (a numba kernel, ``nogil``) that sleeps until the
deadline on ``CLOCK_MONOTONIC`` (the clock of ``time.monotonic``) and then sends. The instant the
datagram leaves no longer depends on when the streamer thread gets the GIL back from the
mapping, planning and decoding threads (with a sleep-based loop in Python, measured in the
flight service: the streamer woke up to 16 ms late, p99 7.6 ms, at load 3.5 on 2 cores).

The sleep is a ``ppoll`` on a pipe, so ``cancel`` (any thread) ends it at once without sending:
a stopping link never waits a whole period for it, and never sends after it stopped.

Linux only (the layouts of ``timespec``, ``pollfd`` and ``sockaddr_in`` below are Linux's on
64-bit little-endian machines: x86-64 and the Jetson's aarch64); elsewhere ``available`` is
False and the streamer sends from Python as before. The kernel calls libc through ctypes, which
numba cannot cache, so it is compiled once per process (about 0.5 s) in a background thread
(``start_compile``); until it is ready the streamer sends from Python.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform
import socket
import struct
import sys
import threading
from typing import Any

import numpy as np

log = logging.getLogger("onboard.autopilot")

CANCELLED = -2
"""``send_at``'s result when ``cancel`` ended the wait (nothing was sent)."""

_CLOCK_MONOTONIC = 1
_POLLIN = 1
_MSG_DONTWAIT = 0x40

available = (
    sys.platform.startswith("linux")
    and sys.byteorder == "little"
    and (ctypes.sizeof(ctypes.c_void_p) == 8)
)

_kernel: Any = None
_kernel_error: BaseException | None = None
_compile_lock = threading.Lock()
_compiled = threading.Event()
_started = False


def _build_kernel() -> Any:
    from numba import njit

    libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    clock_gettime = libc.clock_gettime
    clock_gettime.argtypes = [ctypes.c_int, ctypes.c_void_p]
    clock_gettime.restype = ctypes.c_int
    ppoll = libc.ppoll
    ppoll.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_void_p, ctypes.c_void_p]
    ppoll.restype = ctypes.c_int
    sendto = libc.sendto
    sendto.argtypes = [
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_size_t,
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_uint,
    ]
    sendto.restype = ctypes.c_ssize_t

    @njit(nogil=True)
    def send_at(
        deadline_ns: int,
        fd: int,
        buf: np.ndarray,
        addr: np.ndarray,
        cancel_fd: int,
        ts: np.ndarray,
        pfd: np.ndarray,
    ) -> int:
        while True:
            clock_gettime(_CLOCK_MONOTONIC, ts.ctypes.data)
            rem = deadline_ns - (ts[0] * 1_000_000_000 + ts[1])
            if rem <= 0:
                break
            ts[0] = rem // 1_000_000_000
            ts[1] = rem % 1_000_000_000
            pfd[0] = cancel_fd
            pfd[1] = _POLLIN  # events (low 16 bits), revents (high 16 bits) cleared
            if ppoll(pfd.ctypes.data, 1, ts.ctypes.data, 0) > 0:
                return CANCELLED
            # 0: the deadline; -1: a signal (EINTR): look at the clock again
        return sendto(fd, buf.ctypes.data, buf.size, _MSG_DONTWAIT, addr.ctypes.data, addr.size)

    # compile now, for the argument types TimedSender.send_at passes (read-only byte views:
    # another type would compile again, holding the GIL, in the streamer's first tick)
    ts = np.zeros(2, dtype=np.int64)
    pfd = np.zeros(2, dtype=np.int32)
    b = np.frombuffer(bytes(1), dtype=np.uint8)
    send_at(0, -1, b, b, -1, ts, pfd)  # deadline passed: one sendto on fd -1 (EBADF)
    if len(send_at.signatures) != 1:
        raise RuntimeError(f"unexpected kernel signatures {send_at.signatures}")
    return send_at


def _compile() -> None:
    global _kernel, _kernel_error
    try:
        k = _build_kernel()
    except Exception as e:  # noqa: BLE001 - the streamer keeps sending from Python
        _kernel_error = e
        log.warning("timed setpoint send unavailable (%r): sending from Python", e)
    else:
        _kernel = k
    finally:
        _compiled.set()


def start_compile() -> None:
    """Compile the kernel in a background thread (once per process; idempotent)."""
    if not available:
        return
    with _compile_lock:
        global _started
        if _started:
            return
        _started = True
    threading.Thread(target=_compile, name="autopilot-timed-send-jit", daemon=True).start()


def wait_compiled(timeout_s: float) -> bool:
    """Whether the kernel is ready, waiting up to ``timeout_s`` (tests)."""
    start_compile()
    _compiled.wait(timeout_s)
    return _kernel is not None


_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}

REALTIME_PRIORITY = 10
"""SCHED_FIFO priority the streamer thread asks for (low among real-time priorities: kernel
threads and audio run higher)."""


def request_realtime(priority: int = REALTIME_PRIORITY) -> bool:
    """Run the calling thread under SCHED_FIFO at ``priority`` (threads it starts do not
    inherit it), so that its wake-up at a setpoint's deadline preempts whatever runs: with a
    normal policy, on a loaded 2-core machine the native sender woke up to 11 ms late at the
    99th percentile. The streamer sleeps almost all the time (about 0.4 ms of work per 20 ms
    tick), and the kernel's real-time throttling bounds it anyway. Needs CAP_SYS_NICE or an
    RLIMIT_RTPRIO (systemd: ``LimitRTPRIO=``); False without them (nothing changes)."""
    if not available or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(threading.get_native_id(), policy, os.sched_param(priority))
    except (OSError, AttributeError):
        return False
    return True


def request_short_slice(slice_s: float = 2e-4) -> bool:
    """Ask the scheduler for a short time slice for the calling thread (Linux >= 6.12, EEVDF:
    ``sched_attr.sched_runtime`` of a normal thread is its slice request, and a waking thread
    with a shorter slice preempts the running one). The streamer sleeps almost all the time,
    so this only moves its wake-ups ahead of long-running threads on a busy machine (the
    default slice is a few milliseconds); its CPU share does not change. The thread's nice
    value is kept. False where unsupported (other kernels ignore the value)."""
    nr = _SYS_SCHED_SETATTR.get(platform.machine())
    if not available or nr is None:
        return False
    try:
        tid = threading.get_native_id()
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        # struct sched_attr (version 0, 48 bytes): size, policy (SCHED_OTHER), flags, nice,
        # priority, runtime (ns), deadline, period
        attr = struct.pack("=IIQiIQQQ", 48, 0, 0, nice, 0, int(slice_s * 1e9), 0, 0)
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        buf = ctypes.create_string_buffer(attr, len(attr))
        return int(libc.syscall(nr, tid, buf, 0)) == 0
    except (OSError, AttributeError):
        return False


def sockaddr_in(host: str, port: int) -> bytes:
    """Linux ``struct sockaddr_in`` of an IPv4 address."""
    return (
        socket.AF_INET.to_bytes(2, "little")
        + int(port).to_bytes(2, "big")
        + socket.inet_aton(host)
        + bytes(8)
    )


class TimedSender:
    """Per link: the cancel pipe and the kernel's work buffers. ``send_at`` is called by one
    thread (the streamer); ``cancel`` by any."""

    def __init__(self) -> None:
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self._r: int | None = r
        self._w: int | None = w
        self._ts = np.zeros(2, dtype=np.int64)
        self._pfd = np.zeros(2, dtype=np.int32)
        self._addr_key: tuple[str, int] | None = None
        self._addr = np.zeros(0, dtype=np.uint8)

    @property
    def ready(self) -> bool:
        return _kernel is not None and self._r is not None

    def send_at(self, deadline_s: float, fd: int, data: bytes, remote: tuple[str, int]) -> int:
        """Send ``data`` to ``remote`` on the datagram socket ``fd`` at ``deadline_s``
        (``time.monotonic`` seconds; at once if it passed). Bytes sent, -1 on a send error,
        ``CANCELLED`` when ``cancel`` ended the wait (a cancel before this call counts: call
        ``clear`` first)."""
        if _kernel is None or self._r is None:
            raise RuntimeError("timed send is not ready")
        if remote != self._addr_key:
            self._addr = np.frombuffer(sockaddr_in(remote[0], remote[1]), dtype=np.uint8)
            self._addr_key = remote
        buf = np.frombuffer(bytes(data), dtype=np.uint8)
        return int(
            _kernel(int(round(deadline_s * 1e9)), fd, buf, self._addr, self._r, self._ts, self._pfd)
        )

    def cancel(self) -> None:
        """End a ``send_at`` wait now (or the next one, if none is waiting)."""
        w = self._w
        if w is not None:
            try:
                os.write(w, b"x")
            except (BlockingIOError, OSError):
                pass  # the pipe is full: a cancel is pending anyway

    def clear(self) -> None:
        """Forget pending cancels."""
        r = self._r
        if r is None:
            return
        try:
            while os.read(r, 64):
                pass
        except (BlockingIOError, OSError):
            pass

    def close(self) -> None:
        r, w = self._r, self._w
        self._r = self._w = None
        for fd in (r, w):
            if fd is not None:
                os.close(fd)
