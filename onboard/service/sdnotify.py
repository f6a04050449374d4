"""systemd's notify protocol without a dependency: READY, WATCHDOG, STATUS, STOPPING.

A datagram ``KEY=VALUE\\n...`` to the Unix socket named by ``$NOTIFY_SOCKET`` (a path, or an
abstract socket when it starts with ``@``). Outside systemd (no variable) every call does nothing.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping


def sd_notify(state: str, env: Mapping[str, str] | None = None) -> bool:
    """Send ``state`` (e.g. ``"READY=1\\nSTATUS=flying"``); False when not run by systemd or the
    socket is gone (never raises: a dead notify socket must not take the service down)."""
    e = os.environ if env is None else env
    addr = e.get("NOTIFY_SOCKET", "")
    if not addr:
        return False
    if addr[0] == "@":
        addr = "\0" + addr[1:]
    elif addr[0] != "/":
        return False  # vsock or other addresses: not supported here
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(state.encode())
    except OSError:
        return False
    return True


def watchdog_period_s(env: Mapping[str, str] | None = None) -> float | None:
    """Seconds between watchdog pings systemd expects (``WatchdogSec``), or None when the
    watchdog is off or meant for another process (``WATCHDOG_PID``)."""
    e = os.environ if env is None else env
    usec = e.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = e.get("WATCHDOG_PID")
    if pid and pid.isdigit() and int(pid) != os.getpid():
        return None
    try:
        v = int(usec)
    except ValueError:
        return None
    return v / 1e6 if v > 0 else None


class Notifier:
    """The service's side of the protocol: ``ready``, ``watchdog`` (fed only while healthy),
    ``status`` and ``stopping``; counts what it sent (for tests and status messages)."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        self.env = env
        self.sent: list[str] = []
        period = watchdog_period_s(env)
        self.watchdog_period_s = period

    def _send(self, state: str) -> bool:
        ok = sd_notify(state, self.env)
        if ok:
            self.sent.append(state)
        return ok

    def ready(self, status: str = "") -> bool:
        return self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        return self._send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self._send(f"STATUS={text}")

    def stopping(self) -> bool:
        return self._send("STOPPING=1")
