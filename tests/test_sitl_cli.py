"""``swarm-sitl`` as a process (clean stop on SIGTERM) and the ``bench sitl`` command."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from sitl_mock.client import MavClient, bind_consecutive_udp


def test_sigterm_stops_the_fleet_cleanly(tmp_path: Path) -> None:
    (sock,) = bind_consecutive_udp(1)
    client = MavClient(sock=sock)
    js = tmp_path / "stats.json"
    cmd = [
        sys.executable,
        "-m",
        "sitl_mock.cli",
        "--base-port",
        str(client.port),
        "--local-port-offset",
        "-1",
        "--stats-json",
        str(js),
        "--quiet",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        hb = client.connect(timeout_s=30.0)
        assert hb.get_srcSystem() == 1
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        client.close()
    assert proc.returncode == 0, err.decode()
    data = json.loads(js.read_text())
    assert data["vehicles"] == 1 and data["links"][0]["tx_messages"] > 0


@pytest.mark.slow
def test_bench_sitl_small(tmp_path: Path) -> None:
    from gcs.bench_sitl import sitl

    js = tmp_path / "bench.json"
    args = ["--vehicles", "2", "--seconds", "1", "--speedup", "2", "--step-m", "1"]
    args += ["--step-seconds", "3", "--json", str(js)]
    out = CliRunner().invoke(sitl, args)
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert data["vehicles"] == 2
    assert data["fleet_cpu_percent"] > 0
    assert data["setpoints_accepted_fraction"] > 0.99
    assert data["fleet"]["setpoints_malformed"] == 0 and data["fleet"]["collisions"] == 0
    rates = data["telemetry_hz_sim"]
    assert len(rates) == 27  # the streams of a real PX4 v1.16's onboard link
    for name in ("LOCAL_POSITION_NED", "ATTITUDE", "SYS_STATUS", "GPS_RAW_INT"):
        assert rates[name]["min_hz"] > 0, name
    step = data["step"]
    assert step["samples"] > 10 and step["rise_time_s"] > 0
    assert data["step_model"]["rise_time_s"] > 0


def _signalled_mock(
    extra: list[str], send: Callable[[subprocess.Popen[bytes]], object]
) -> subprocess.Popen[bytes]:
    """One mock vehicle on loopback (``extra``: more options), connected to, then signalled by
    ``send``; waits for its end (killed if it has not ended 20 s on) and returns the process."""
    (sock,) = bind_consecutive_udp(1)
    client = MavClient(sock=sock)
    cmd = [sys.executable, "-m", "sitl_mock.cli", "--base-port", str(client.port),
           "--local-port-offset", "-1", "--quiet", *extra]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        client.connect(timeout_s=30.0)
        send(proc)
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        client.close()
    return proc


def test_a_burst_of_signals_still_stops_the_fleet() -> None:
    """SIGTERMs and SIGUSR1s close together (a killed demo's children get SIGTERM from the
    kernel, an operator presses Ctrl-C twice): the mock ends. Its handlers used to take
    ``Event.set``'s lock, and one nested in another left the process running for ever."""

    def burst(proc: subprocess.Popen[bytes]) -> None:
        for i in range(40):
            proc.send_signal(signal.SIGUSR1 if i % 4 else signal.SIGTERM)

    proc = _signalled_mock([], burst)
    # in order, at once on the second SIGTERM (1), or by its default action when the fleet's
    # loop had already ended and handed SIGTERM back (a loaded machine: the teardown ran
    # between two signals of the burst); never hanging, never killed by a SIGUSR1
    assert proc.returncode in (0, 1, -signal.SIGTERM)


def test_a_stats_reset_signal_while_the_fleet_shuts_down_does_not_kill_it(tmp_path: Path) -> None:
    """SIGUSR1 (reset the statistics) keeps coming while the mock ends on its own (``--duration``):
    the mock ends with status 0 and writes its statistics. Its teardown used to put SIGUSR1's
    default action back before the process ended, and a SIGUSR1 in that window killed it (status
    -10, no statistics: seen in a burst of signals on a loaded CI machine)."""
    stats = tmp_path / "stats.json"
    sent = 0

    def until_it_ends(proc: subprocess.Popen[bytes]) -> None:
        nonlocal sent
        deadline = time.monotonic() + 30.0
        while proc.poll() is None and time.monotonic() < deadline:
            proc.send_signal(signal.SIGUSR1)
            sent += 1
            time.sleep(0.0005)

    proc = _signalled_mock(["--duration", "1.0", "--stats-json", str(stats)], until_it_ends)
    assert sent > 100  # the signals kept coming through the end
    assert proc.returncode == 0
    assert json.loads(stats.read_text())["wall_s"] > 0
