"""The systemd units pass ``systemd-analyze verify``; sd_notify speaks the notify protocol."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.cli import STOP_DEADLINE_S
from onboard.service.sdnotify import Notifier, sd_notify, watchdog_period_s

UNITS = Path(__file__).resolve().parents[1] / "systemd"
INSTALLED_BIN = "/opt/swarm-formation/.venv/bin/swarm-onboard"


def _keys(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")) and "=" in line:
            k, v = line.split("=", 1)
            out.setdefault(k, []).append(v)
    return out


def test_service_unit_settings() -> None:
    svc = _keys((UNITS / "swarm-onboard@.service").read_text())
    warm = _keys((UNITS / "swarm-onboard-warmup.service").read_text())
    assert svc["Type"] == ["notify"]
    assert svc["Restart"] == ["on-failure"]
    assert float(svc["WatchdogSec"][0]) > 0
    # the service's own stop deadline ends it (and logs stop_timeout) before systemd's SIGKILL
    assert float(svc["TimeoutStopSec"][0]) >= STOP_DEADLINE_S + 1.0
    assert "--id %i" in svc["ExecStart"][0]
    assert "/dev/ttyTHS0 rw" in svc["DeviceAllow"]
    assert "dialout" in svc["SupplementaryGroups"][0]
    assert "AF_INET" in svc["RestrictAddressFamilies"][0].split()
    assert svc["MemoryDenyWriteExecute"] == ["no"]  # numba's JIT writes code, then runs it
    assert "swarm-onboard-warmup.service" in svc["After"][0]
    numba_env = [e for e in svc["Environment"] if e.startswith("NUMBA_CACHE_DIR=")]
    assert numba_env and numba_env == [
        e for e in warm["Environment"] if e.startswith("NUMBA_CACHE_DIR=")
    ]
    # the warm-up compiles for the config the service flies (its map: the mapping kernels)
    config = svc["ExecStart"][0].split("--config", 1)[1].split()[0]
    assert warm["ExecStart"][0].split("--config", 1)[1].split()[0] == config


def test_units_pass_systemd_analyze_verify(tmp_path: Path) -> None:
    tool = shutil.which("systemd-analyze")
    if tool is None:  # the Debian package `systemd` provides it (make system-deps)
        pytest.skip("systemd-analyze is not installed (Debian package: systemd)")
    exe = Path(sys.executable).parent / "swarm-onboard"
    assert exe.exists()
    names = []
    for unit, target in (
        ("swarm-onboard@.service", "swarm-onboard@3.service"),
        ("swarm-onboard-warmup.service", "swarm-onboard-warmup.service"),
    ):
        text = (UNITS / unit).read_text()
        assert INSTALLED_BIN in text
        (tmp_path / target).write_text(text.replace(INSTALLED_BIN, str(exe)))
        names.append(str(tmp_path / target))
    res = subprocess.run(
        [tool, "verify", *names],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "SYSTEMD_LOG_COLOR": "0"},
    )
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 0, out
    assert out == "", out  # unknown keys are only warnings: none allowed


def _listen(path: str) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(5.0)
    return s


def test_sd_notify_sends_to_the_notify_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with _listen(path) as s:
        assert sd_notify("READY=1\nSTATUS=up", {"NOTIFY_SOCKET": path})
        assert s.recv(4096) == b"READY=1\nSTATUS=up"


def test_sd_notify_abstract_socket() -> None:
    name = f"swarm-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind("\0" + name)
        s.settimeout(5.0)
        assert sd_notify("WATCHDOG=1", {"NOTIFY_SOCKET": "@" + name})
        assert s.recv(4096) == b"WATCHDOG=1"


def test_sd_notify_outside_systemd_does_nothing(tmp_path: Path) -> None:
    assert not sd_notify("READY=1", {})
    assert not sd_notify("READY=1", {"NOTIFY_SOCKET": str(tmp_path / "gone")})


def test_watchdog_period() -> None:
    assert watchdog_period_s({}) is None
    assert watchdog_period_s({"WATCHDOG_USEC": "3000000"}) == 3.0
    assert watchdog_period_s({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"}) is None
    env = {"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid())}
    assert watchdog_period_s(env) == 0.5


def test_notifier_messages(tmp_path: Path) -> None:
    path = str(tmp_path / "n")
    with _listen(path) as s:
        n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert n.watchdog_period_s == 2.0
        n.ready("link up")
        n.watchdog()
        n.status("flying")
        n.stopping()
        got = [s.recv(4096) for _ in range(4)]
    assert got == [b"READY=1\nSTATUS=link up", b"WATCHDOG=1", b"STATUS=flying", b"STOPPING=1"]
    assert n.sent == [g.decode() for g in got]
