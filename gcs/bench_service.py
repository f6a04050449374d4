"""Flight service benchmark (``swarm-gcs bench service``): one ``swarm-onboard run`` process
against the SITL mock (``swarm-sitl``, its own process) with depth frames at 30 frames/s over
Zenoh, flying back and forth through a small forest, so that it maps and replans all the time.

Measured:

- the setpoint stream's period *as the mock receives it*: a UDP tap between the service and the
  mock (``SetpointTap``) forwards every datagram both ways and timestamps the arrival of each
  SET_POSITION_TARGET_LOCAL_NED (message 84) on its way to the mock; p50 / p99 / max of the
  intervals during the measurement window (target: p99 < 25 ms, max < 50 ms at 50 Hz);
- the service's CPU (its process CPU time over the window's wall time, in cores; goal <= 0.5)
  and memory (RSS at the end of the window, and the peak);
- start to READY with a warm numba cache: the time from starting the process to its
  ``READY=1`` on a ``NOTIFY_SOCKET`` datagram socket the benchmark creates (``NotifySocket``),
  after a first start that warmed every cache (target < 5 s);
- for context: depth frames the service ingested per second, replans, plan times, the mock's
  collisions and the machine's load average.

The helpers (tap, notify socket, service process, configs, world file) are used by the service
integration tests too.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import click
import numpy as np
import yaml

from gcs.procstat import stat_cpu_s

SET_POSITION_TARGET_LOCAL_NED = 84
TARGETS = {
    "setpoint_p99_ms": 25.0,
    "setpoint_max_ms": 50.0,
    "start_to_ready_s": 5.0,
    "cpu_cores": 0.5,
}
BIN = Path(sys.executable).parent
# Linux's SO_TIMESTAMPNS (also the control message's type); Python's socket module lacks it
_SO_TIMESTAMPNS: int | None = getattr(
    socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None
)


# ---- MAVLink on the wire ------------------------------------------------------------------------
def mavlink_msgids(data: bytes) -> list[int]:
    """Message ids of the MAVLink 1/2 frames in one datagram (stops at the first byte that does
    not start a frame)."""
    ids: list[int] = []
    i = 0
    n = len(data)
    while i < n:
        magic = data[i]
        if magic == 0xFD and i + 10 <= n:
            plen = data[i + 1]
            signed = data[i + 2] & 0x01
            ids.append(data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16)
            i += 10 + plen + 2 + (13 if signed else 0)
        elif magic == 0xFE and i + 6 <= n:
            plen = data[i + 1]
            ids.append(data[i + 5])
            i += 6 + plen + 2
        else:
            break
    return ids


class SetpointTap:
    """A UDP forwarder between an autopilot (the mock) and the service.

    The mock sends its telemetry to ``front_port`` (its ``--base-port``); the tap forwards it to
    the service at ``service_addr`` from its own back socket, and forwards whatever the service
    answers to the mock's address (learned from the mock's datagrams). The arrival time
    (``time.monotonic()``) of every datagram from the service that carries message ``msgid``
    is kept in ``arrivals``. ``cut = True`` cuts the path: every datagram, both ways, is
    dropped (counted in ``cut_dropped``) and none is recorded. Runs in its own thread;
    ``close`` stops it.
    """

    def __init__(
        self, service_addr: tuple[str, int], msgid: int = SET_POSITION_TARGET_LOCAL_NED
    ) -> None:
        self.service_addr = service_addr
        self.msgid = msgid
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back.bind(("127.0.0.1", 0))
        self.front_port = int(self.front.getsockname()[1])
        self.mock_addr: tuple[str, int] | None = None
        self.arrivals: list[float] = []
        # the kernel's receive stamp of the same datagrams (SO_TIMESTAMPNS, CLOCK_REALTIME),
        # moved to the monotonic clock: when the datagram reached this socket, before the tap's
        # own thread (which shares an interpreter with the ground station) was scheduled
        self.kernel_arrivals: list[float] = []
        self._rt_minus_mono = time.time() - time.monotonic()
        self._kernel_stamps = _SO_TIMESTAMPNS is not None
        if _SO_TIMESTAMPNS is not None:
            self.back.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        self.to_service = 0
        self.to_mock = 0
        self.dropped = 0  # datagrams from the service before the mock was heard
        self.cut = False
        self.cut_dropped = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="setpoint-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.front, selectors.EVENT_READ, "front")
        sel.register(self.back, selectors.EVENT_READ, "back")
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(0.2):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    kt = math.nan
                    try:
                        if key.data == "back" and self._kernel_stamps:
                            data, anc, _, addr = sock.recvmsg(65535, 64)
                            kt = _kernel_stamp(anc) - self._rt_minus_mono
                        else:
                            data, addr = sock.recvfrom(65535)
                    except OSError:
                        continue
                    if self.cut:
                        self.cut_dropped += 1
                        continue
                    t = time.monotonic()
                    if key.data == "front":
                        self.mock_addr = addr
                        self.back.sendto(data, self.service_addr)
                        self.to_service += 1
                    else:
                        if self.msgid in mavlink_msgids(data):
                            with self._lock:
                                self.arrivals.append(t)
                                self.kernel_arrivals.append(kt)
                        if self.mock_addr is None:
                            self.dropped += 1
                        else:
                            self.front.sendto(data, self.mock_addr)
                            self.to_mock += 1
        finally:
            sel.close()

    def arrivals_between(self, t0: float, t1: float, kernel: bool = False) -> np.ndarray:
        """Arrival times in [t0, t1] (by the tap thread's stamp); ``kernel``: the kernel's
        stamps of the same datagrams instead (NaN where the platform gives none)."""
        with self._lock:
            a = np.array(self.arrivals)
            k = np.array(self.kernel_arrivals)
        sel = (a >= t0) & (a <= t1)
        return k[sel] if kernel else a[sel]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.front.close()
        self.back.close()

    def __enter__(self) -> SetpointTap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _kernel_stamp(ancillary: list[tuple[int, int, bytes]]) -> float:
    """CLOCK_REALTIME seconds of an SO_TIMESTAMPNS control message (NaN without one)."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = struct.unpack("@qq", data[:16])
            return sec + nsec * 1e-9
    return math.nan


# ---- systemd's notify socket -------------------------------------------------------------------
class NotifySocket:
    """A datagram socket for ``NOTIFY_SOCKET`` (what systemd gives a ``Type=notify`` service):
    every datagram received is kept with its arrival time (``time.monotonic()``)."""

    def __init__(self) -> None:
        self._dir = tempfile.mkdtemp(prefix="notify-")
        self.path = os.path.join(self._dir, "notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.setblocking(False)
        self.received: list[tuple[float, str]] = []

    def poll(self, timeout_s: float = 0.0) -> list[tuple[float, str]]:
        """Read what arrived (waiting up to ``timeout_s`` for the first datagram)."""
        sel = selectors.DefaultSelector()
        sel.register(self.sock, selectors.EVENT_READ)
        try:
            new: list[tuple[float, str]] = []
            wait = timeout_s
            while sel.select(wait):
                try:
                    data = self.sock.recv(65535)
                except BlockingIOError:
                    break
                new.append((time.monotonic(), data.decode(errors="replace")))
                wait = 0.0
            self.received.extend(new)
            return new
        finally:
            sel.close()

    def first(self, key: str) -> float | None:
        """Arrival time of the first datagram that holds the line ``key`` (e.g. ``READY=1``)."""
        for t, text in self.received:
            if key in text.splitlines():
                return t
        return None

    def close(self) -> None:
        self.sock.close()
        try:
            os.unlink(self.path)
            os.rmdir(self._dir)
        except OSError:
            pass


# ---- the service as a process -------------------------------------------------------------------
def service_config(
    *,
    swarm: str,
    autopilot_port: int,
    zenoh_listen: Sequence[str],
    zenoh_connect: Sequence[str],
    record_dir: str | Path,
    depth: Mapping[str, Any] | None = None,
    port_plus_id: bool = False,
    implementation: str = "pymavlink",
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """``config/onboard.yaml`` (the drone's configuration: a file given to the service replaces
    it, so it is the base here) for a service on loopback: autopilot on UDP ``autopilot_port``
    (+ id with ``port_plus_id``), the swarm bus on the given endpoints, ``depth`` (None: no
    camera), records in ``record_dir``, JSON log lines; ``extra`` is merged in last (nested
    mappings key by key)."""
    from onboard.config import merge_mappings
    from onboard.service.config import config_data

    data: dict[str, Any] = {
        "drone": {"swarm": swarm},
        "autopilot": {
            "implementation": implementation,
            "url": f"udp://127.0.0.1:{autopilot_port}",
            "port_plus_id": port_plus_id,
        },
        "zenoh": {"listen": list(zenoh_listen), "connect": list(zenoh_connect)},
        "depth": dict(depth) if depth is not None else {"source": "none"},
        "record": {"directory": str(record_dir)},
        "logging": {"format": "json"},
    }
    base = config_data()
    if depth is None:
        base = {k: v for k, v in base.items() if k != "depth"}  # no camera: none of its keys
    return merge_mappings(merge_mappings(base, data), extra or {})


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process, all its threads (Linux ``/proc``)."""
    return stat_cpu_s(f"/proc/{pid}/stat")


def proc_memory_kb(pid: int) -> dict[str, int]:
    """``VmRSS`` (now) and ``VmHWM`` (peak) of a process, kB."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0])
    return out


class ServiceProcess:
    """``swarm-onboard run --id ID --config FILE`` with a notify socket; output to ``log_path``.
    Use as a context manager: it is always stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(
        self,
        drone_id: int,
        config: Mapping[str, Any],
        workdir: Path,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.drone_id = drone_id
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.config_path = self.workdir / f"onboard-{drone_id}.yaml"
        self.config_path.write_text(yaml.safe_dump(dict(config), sort_keys=False))
        self.log_path = self.workdir / f"service-{drone_id}.log"
        self.env = dict(env or {})
        self.notify = NotifySocket()
        self.proc: subprocess.Popen[bytes] | None = None
        self.started_at = 0.0
        self.returncode: int | None = None

    def start(self) -> ServiceProcess:
        env = {
            **os.environ,
            "OPENBLAS_NUM_THREADS": "1",
            "NOTIFY_SOCKET": self.notify.path,
            **self.env,
        }
        with open(self.log_path, "ab") as log:
            self.started_at = time.monotonic()
            self.proc = subprocess.Popen(
                [
                    str(BIN / "swarm-onboard"),
                    "run",
                    "--id",
                    str(self.drone_id),
                    "--config",
                    str(self.config_path),
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
            )
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def wait_ready(self, timeout_s: float) -> float:
        """Seconds from the start of the process to its READY=1 (raises if it exits first or
        the time is up)."""
        deadline = time.monotonic() + timeout_s
        while self.notify.first("READY=1") is None:
            if not self.alive():
                raise RuntimeError(
                    f"service {self.drone_id} exited ({self.proc and self.proc.returncode}) "
                    f"before READY:\n{self.log_tail()}"
                )
            if time.monotonic() > deadline:
                raise TimeoutError(f"service {self.drone_id} not READY in {timeout_s} s")
            self.notify.poll(0.05)
        t = self.notify.first("READY=1")
        assert t is not None
        return t - self.started_at

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def log_events(self, name: str) -> list[dict[str, Any]]:
        """The service's JSON log lines of ``event`` ``name``."""
        out = []
        for line in self.log_path.read_text(errors="replace").splitlines():
            if f'"event": "{name}"' in line:
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    continue
        return out

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM, wait, SIGKILL if needed; the exit code."""
        p = self.proc
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5.0)
        if p is not None:
            self.returncode = p.returncode
        self.notify.close()
        return self.returncode

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def write_world(
    path: Path,
    cylinders: Sequence[Sequence[float]],
    starts: Sequence[Sequence[float]],
    goals: Sequence[Sequence[float]],
) -> Path:
    """A world file (``cylinders: [[x, y, r, z_min, z_max], ...]``, per-drone starts/goals)."""
    xs = [c[0] for c in cylinders] or [0.0]
    data = {
        "description": "benchmark/test forest",
        "cylinders": [[float(v) for v in c] for c in cylinders],
        "cluttered_x": [float(min(xs)), float(max(xs))],
        "starts": [[float(v) for v in p] for p in starts],
        "goals": [[float(v) for v in p] for p in goals],
        "ground_z": 0.0,
    }
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def stop_process(p: subprocess.Popen[Any], timeout_s: float = 10.0) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5.0)


class MockProcess:
    """``swarm-sitl`` in a process of its own (its loop and depth renderer never share an
    interpreter with the caller): vehicles in the world file ``world`` (spawned at its
    ``starts``), telemetry to UDP ``base_port + i``, their local frame the world frame (as the
    depth frames are), facing +x; true poses (and depth frames at ``depth_rate_hz``, 0: none)
    over Zenoh on ``truth_endpoint`` under ``prefix``. ``latest_truth()`` gives the newest pose
    of every vehicle (system id -> ``TruthSample``, with its collision count); after ``stop()``,
    ``summary`` holds the mock's own report (collisions, clearances, depth frames)."""

    def __init__(
        self,
        world: Path,
        count: int,
        base_port: int,
        truth_endpoint: str,
        prefix: str,
        workdir: Path,
        depth_rate_hz: float = 0.0,
        extra_args: Sequence[str] = (),
        depth_step: int = 3,
    ) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.stats_path = self.workdir / "sitl-stats.json"
        self.log_path = self.workdir / "sitl.log"
        self.prefix = prefix
        self.truth_endpoint = truth_endpoint
        self.summary: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._truth: dict[int, Any] = {}
        self._sub: Any = None
        self._session: Any = None
        depth = (
            ["--depth", "--depth-rate", str(depth_rate_hz), "--depth-step", str(depth_step)]
            if depth_rate_hz > 0
            else []
        )
        self.args = [
            str(BIN / "swarm-sitl"),
            *("--count", str(count), "--world", str(world), "--base-port", str(base_port)),
            *("--local-port-offset", "-1", "--truth", "zenoh"),
            *("--zenoh-listen", truth_endpoint, "--zenoh-prefix", prefix),
            *depth,
            *("--set", "local_origin=world", "--set", "spawn_yaw_deg=0"),
            *("--set", "autopilot.boot_time_s=0.5"),
            *("--stats-json", str(self.stats_path), "--quiet"),
            *extra_args,
        ]
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> MockProcess:
        from onboard.comm.zenoh_session import ZenohEndpoints, open_session

        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                self.args,
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
            )
        # poses only (the depth frames are the services' business)
        self._session = open_session(ZenohEndpoints(connect=(self.truth_endpoint,)))
        self._sub = self._session.declare_subscriber(f"{self.prefix}/*/pose", self._on_pose)
        return self

    def _on_pose(self, sample: Any) -> None:
        from onboard.sensors.zenoh_depth import DecodeError, TruthSample

        try:
            t = TruthSample.from_bytes(sample.payload.to_bytes())
        except DecodeError:
            return
        with self._lock:
            self._truth[t.system_id] = t

    def latest_truth(self) -> dict[int, Any]:
        with self._lock:
            return dict(self._truth)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> dict[str, Any]:
        """Stop the mock (SIGINT: it writes its report) and the subscriber; the report."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        if self._session is not None:
            self._session.close()
            self._session = None
        if self.proc is not None:
            stop_process(self.proc)
        try:
            self.summary = json.loads(self.stats_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            self.summary = {"error": f"no report from the mock: {e}"}
        return self.summary

    def __enter__(self) -> MockProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def poll_until(
    cond: Callable[[], bool],
    timeout_s: float,
    what: str,
    alive: Callable[[], bool] | None = None,
    period_s: float = 0.05,
    describe: Callable[[], str] | None = None,
) -> None:
    """Wait (real time) for ``cond``; TimeoutError naming ``what``; RuntimeError when
    ``alive()`` turns False first. ``describe()``, when given, is appended to either error
    (what the waited-for thing looked like when the wait gave up)."""
    deadline = time.monotonic() + timeout_s

    def seen() -> str:
        return f"; last seen: {describe()}" if describe is not None else ""

    while not cond():
        if alive is not None and not alive():
            raise RuntimeError(f"a process died while waiting for {what}{seen()}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}{seen()}")
        time.sleep(period_s)


def swarm_summary(station: Any) -> str:
    """One line per drone of what a ``GroundStation`` last heard (state, mode, armed,
    position, plan status, message, ages): for the error of a wait that gave up."""
    parts = []
    for d, v in sorted(station.views().items()):
        pos = "-" if v.position_m is None else ",".join(f"{x:.2f}" for x in v.position_m)
        age = "-" if v.state_age_s is None else f"{v.state_age_s:.1f}s"
        parts.append(
            f"[{d}: {v.flight_state} {v.autopilot_mode} armed={v.armed} at ({pos}) state {age} old,"
            f" plan {v.plan_status} ({v.replans} replans), links {v.links_text()},"
            f" message {v.message!r}]"
        )
    return " ".join(parts) or "no drone heard"


# ---- the benchmark ------------------------------------------------------------------------------
# a small forest across the back-and-forth leg (x from 0 to 8 m at y = 0)
BENCH_TRUNKS = (
    (2.0, 0.4, 0.25, 0.0, 3.0),
    (3.5, -0.5, 0.2, 0.0, 3.0),
    (5.0, 0.3, 0.3, 0.0, 3.0),
    (6.5, -0.6, 0.2, 0.0, 3.0),
    (4.0, 2.0, 0.3, 0.0, 3.0),
    (4.5, -2.2, 0.25, 0.0, 3.0),
)
LEG_A = (-0.5, 0.0, 1.0)
LEG_B = (8.5, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class ServiceBenchConfig:
    seconds: float = 30.0
    """Measurement window, while the drone flies back and forth."""
    depth_rate_hz: float = 30.0
    depth_step: int = 3
    """Every n-th pixel row and column: rendered by the mock and ray cast by the service."""
    v_max_m_s: float = 1.0
    implementation: str = "pymavlink"
    setpoint_rate_hz: float = 50.0
    nice: int = 0
    """Niceness of the benchmark and everything it starts (negative: priority over the rest of
    a shared machine, as a drone's systemd unit may give the service; needs privileges)."""
    window: str = "band"
    """The map window's vertical placement: 'band' (the service's default,
    ``mapping.window_band_margin_m``) or 'floor' (4 m from 0.5 m below the ground, the window
    before it: ``window_band_margin_m: null``), for comparing the two."""

    def __post_init__(self) -> None:
        if self.window not in ("band", "floor"):
            raise ValueError(f"window must be 'band' or 'floor', got {self.window!r}")
        if not self.seconds > 0.0:
            raise ValueError("seconds must be > 0")
        if not (self.depth_rate_hz == 0.0 or 1.0 <= self.depth_rate_hz <= 90.0):
            raise ValueError("depth_rate_hz must be 0 (no camera) or in [1, 90]")
        if not 1 <= self.depth_step <= 16:
            raise ValueError("depth_step must be in [1, 16]")


def _per_op_ms(cpu_us: int, ops: int) -> float | None:
    """Milliseconds of CPU per operation, None without an operation."""
    return cpu_us / 1e3 / ops if ops > 0 else None


def _stats(x: np.ndarray) -> dict[str, float | None]:
    if x.size == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None, "mean": None}
    return {
        "n": int(x.size),
        "p50": float(np.percentile(x, 50)),
        "p99": float(np.percentile(x, 99)),
        "max": float(x.max()),
        "mean": float(x.mean()),
    }


def run_service_bench(
    cfg: ServiceBenchConfig, workdir: Path, progress: Callable[[str], None] = lambda s: None
) -> dict[str, Any]:
    """Run the benchmark in ``workdir``; the report as a JSON-ready dict."""
    from gcs.station import GroundStation, StationConfig
    from onboard.comm import wire
    from onboard.comm.zenoh_session import free_loopback_endpoint, peer_mesh

    workdir.mkdir(parents=True, exist_ok=True)
    if cfg.nice:
        try:  # inherited by the mock and the service
            os.setpriority(os.PRIO_PROCESS, 0, cfg.nice)
        except PermissionError as e:
            raise RuntimeError(f"cannot set niceness {cfg.nice}: {e}") from e
    swarm = f"bench{os.getpid()}"
    truth_ep = free_loopback_endpoint()
    prefix = f"{swarm}/sim"
    depth = cfg.depth_rate_hz > 0.0
    # without a camera the service plans on the ground alone: no trunks then (a baseline)
    trunks = BENCH_TRUNKS if depth else ()
    world = write_world(workdir / "world.yaml", trunks, [(0.0, 0.0, 0.0)], [LEG_B])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        service_port = int(s.getsockname()[1])
    load0 = os.getloadavg()
    tap = SetpointTap(("127.0.0.1", service_port))
    mock = MockProcess(
        world,
        1,
        tap.front_port,
        truth_ep,
        prefix,
        workdir,
        depth_rate_hz=cfg.depth_rate_hz,
        depth_step=cfg.depth_step,
    ).start()
    mesh = peer_mesh(2)
    svc_ep, gcs_ep = mesh
    config = service_config(
        swarm=swarm,
        autopilot_port=service_port,
        zenoh_listen=svc_ep.listen,
        zenoh_connect=svc_ep.connect,
        record_dir=workdir / "records",
        depth={
            "source": "zenoh-sim",
            "rate_hz": cfg.depth_rate_hz,
            "step": cfg.depth_step,
            "sim_prefix": prefix,
            "sim_connect": [truth_ep],
        }
        if depth
        else None,
        implementation=cfg.implementation,
        extra={
            "planner": {"v_max_m_s": cfg.v_max_m_s},
            "autopilot": {"setpoint_rate_hz": cfg.setpoint_rate_hz},
            "flight": {"takeoff_speed_m_s": 1.0},
            "geofence": {"min_enu_m": [-5.0, -5.0, 0.0], "max_enu_m": [14.0, 5.0, 3.0]},
            **({"mapping": {"window_band_margin_m": None}} if cfg.window == "floor" else {}),
        },
    )
    report: dict[str, Any] = {"benchmark": "service", "config": dataclasses.asdict(cfg)}
    station = None
    try:
        # a first start warms every numba cache (planner, mapping); the second is measured
        progress("first start (warming the caches)")
        with ServiceProcess(0, config, workdir / "warm") as warm:
            report["first_start_to_ready_s"] = warm.wait_ready(120.0)
        svc = ServiceProcess(0, config, workdir)
        with svc:
            progress("measured start")
            ready_s = svc.wait_ready(60.0)
            report["start_to_ready_s"] = ready_s
            ev = svc.log_events("ready")
            report["service_ready_event"] = ev[0] if ev else None
            station = GroundStation(swarm, gcs_ep, config=StationConfig(lead_s=0.5))
            up = station.wait_for_drones(ids=[0], timeout_s=15.0, with_state=True)
            if 0 not in up:
                raise RuntimeError("the service did not show up on the bus")

            def state() -> str:
                v = station.views().get(0)
                return "" if v is None or v.flight_state is None else str(v.flight_state)

            def ok(outcome: Any) -> None:
                if not outcome.ok:
                    raise RuntimeError(outcome.describe())

            ok(
                station.send(
                    wire.FormationAssignment(
                        [(0.0, 0.0, 0.0), (0.0, 3.0, 0.0)],
                        1.0,
                        0.0,
                        {0: 0},
                        1,
                        time.time(),
                    ),
                    [0],
                )
            )
            progress("take-off")
            ok(station.takeoff(1.0, [0]))
            poll_until(lambda: state() == "hover", 30.0, "hover", svc.alive)
            # the formation's centre is 1.5 m north of slot 0: goals for the centre
            legs = [LEG_B, LEG_A] * 20
            centre = [(x, y + 1.5, z) for x, y, z in legs]
            ok(station.waypoints(centre, [0]))
            poll_until(lambda: state() == "formation-flight", 10.0, "flight", svc.alive)
            progress(f"measuring for {cfg.seconds:g} s")
            c0 = station.views()[0].counters
            t0 = time.monotonic()
            cpu0 = proc_cpu_s(svc.pid)
            states: set[str] = set()
            cut_short = ""
            while time.monotonic() - t0 < cfg.seconds:
                time.sleep(0.1)
                st = state()
                states.add(st)
                if not svc.alive():
                    raise RuntimeError(f"the service died:\n{svc.log_tail()}")
                if st not in ("formation-flight", "hover", "emergency"):
                    # the stream stops (PX4 lands by itself, or the link or the pilot took
                    # over): measure what was streamed until then
                    cut_short = f"window ended early: the service went to {st!r}"
                    progress(cut_short)
                    break
            t1 = time.monotonic()
            cpu1 = proc_cpu_s(svc.pid)
            mem = proc_memory_kb(svc.pid)
            time.sleep(1.2)  # one more status
            view = station.views()[0]
            c1 = view.counters
            arr = tap.arrivals_between(t0, t1)
            periods_ms = np.diff(arr) * 1e3
            karr = tap.arrivals_between(t0, t1, kernel=True)
            kernel_periods_ms = np.diff(karr) * 1e3
            if not np.all(np.isfinite(kernel_periods_ms)):
                kernel_periods_ms = np.zeros(0)
            wall = t1 - t0
            frames = (c1.get("service.frames", 0) - c0.get("service.frames", 0)) / wall

            def delta(key: str) -> int:
                return int(c1.get(key, 0)) - int(c0.get(key, 0))

            # the service's own CPU accounting per worker thread (statuses at 1 Hz: the window
            # they span is about the measurement window)
            workers = {
                k[len("service.cpu_us.") :]: delta(k) / 1e6 / wall
                for k in c1
                if k.startswith("service.cpu_us.")
            }
            report.update(
                {
                    "window_s": wall,
                    "window_cut_short": cut_short,
                    "states_seen": sorted(states),
                    "setpoint_period_ms": _stats(periods_ms),
                    "setpoint_period_kernel_stamp_ms": _stats(kernel_periods_ms),
                    "setpoints_in_window": int(arr.size),
                    "setpoint_rate_hz": float(arr.size / wall),
                    "periods_over_25ms": int(np.sum(periods_ms > 25.0)),
                    "periods_over_50ms": int(np.sum(periods_ms > 50.0)),
                    "cpu_cores": (cpu1 - cpu0) / wall,
                    "rss_mb": mem.get("VmRSS", 0) / 1024.0,
                    "peak_rss_mb": mem.get("VmHWM", 0) / 1024.0,
                    "depth_frames_per_s": frames,
                    "depth_frames_missed_per_s": delta("service.frames_missed") / wall,
                    "esdf_refreshes_per_s": delta("service.esdf_builds") / wall,
                    "esdf_new_buffer_sets": delta("service.esdf_new_buffer_sets"),
                    "esdf_refreshes_skipped": delta("service.esdf_skipped"),
                    # CPU per operation (the thread counters over the operations counted)
                    "ingest_cpu_ms_per_frame": _per_op_ms(
                        delta("service.cpu_us.depth_ingest"), delta("service.frames")
                    ),
                    "esdf_cpu_ms_per_refresh": _per_op_ms(
                        delta("service.cpu_us.esdf"), delta("service.esdf_builds")
                    ),
                    "cpu_cores_by_worker": workers,
                    "autopilot_late_ticks": delta("autopilot.late_ticks"),
                    "replans": c1.get("service.replans", 0) - c0.get("service.replans", 0),
                    "plans_failed": c1.get("service.plans_failed", 0)
                    - c0.get("service.plans_failed", 0),
                    "plan_ms_max_last_status": view.plan_ms_max,
                    "tap": {
                        "to_service": tap.to_service,
                        "to_mock": tap.to_mock,
                        "dropped": tap.dropped,
                    },
                }
            )
            progress("landing")
            station.land([0])
            poll_until(lambda: state() == "landed", 30.0, "landed", svc.alive)
        report["service_exit_code"] = svc.returncode
    finally:
        if station is not None:
            station.close()
        sitl = mock.stop()
        tap.close()
    report["mock"] = {
        k: sitl.get(k)
        for k in ("collisions", "min_obstacle_distance_m", "depth", "process_cpu_s", "error")
        if k in sitl
    }
    # the setpoint period as the mock's side sees it: the kernel's receive stamp of each
    # datagram where the platform gives one (the tap thread's own stamp adds the delay of this
    # bench process, which shares the machine)
    kp = report.get("setpoint_period_kernel_stamp_ms", {})
    sp = kp if kp.get("n") else report.get("setpoint_period_ms", {})
    report["setpoint_period_judged_on"] = "kernel receive stamp" if sp is kp else "tap stamp"
    # the CPU figure stands for the configured frame rate only if the frames were mapped
    mapped = report.get("depth_frames_per_s", 0.0) >= 0.9 * cfg.depth_rate_hz
    report["targets"] = TARGETS
    report["met"] = {
        "setpoint_p99_ms": sp.get("p99") is not None and sp["p99"] < TARGETS["setpoint_p99_ms"],
        "setpoint_max_ms": sp.get("max") is not None and sp["max"] < TARGETS["setpoint_max_ms"],
        "start_to_ready_s": report.get("start_to_ready_s", 1e9) < TARGETS["start_to_ready_s"],
        "cpu_cores": mapped and report.get("cpu_cores", 1e9) <= TARGETS["cpu_cores"],
    }
    report["load_average"] = {"start": list(load0), "end": list(os.getloadavg())}
    report["host"] = {"cpus": os.cpu_count(), "python": platform.python_version()}
    report["when"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return report


def _fmt(x: Any, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


@click.command("service")
@click.option(
    "--seconds",
    default=30.0,
    show_default=True,
    type=click.FloatRange(min=1.0),
    help="Measurement window while the drone flies back and forth.",
)
@click.option(
    "--depth-rate",
    default=30.0,
    show_default=True,
    type=click.FloatRange(0.0, 90.0),
    help="Depth frames per second (0: no camera and no trunks, a baseline).",
)
@click.option(
    "--depth-step",
    default=3,
    show_default=True,
    type=click.IntRange(1, 16),
    help="Every n-th pixel row and column, rendered by the mock and ray cast by the service.",
)
@click.option(
    "--implementation",
    type=click.Choice(["pymavlink", "mavsdk"]),
    default="pymavlink",
    show_default=True,
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option(
    "--workdir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Keep configs, logs and records here (default: a temporary directory).",
)
@click.option(
    "--nice",
    default=0,
    show_default=True,
    type=click.IntRange(-20, 19),
    help="Run the benchmark, the mock and the service at this niceness (negative: ahead of the "
    "rest of a shared machine; needs privileges).",
)
@click.option(
    "--window",
    type=click.Choice(["band", "floor"]),
    default="band",
    show_default=True,
    help="The map window's vertical placement: the planner's altitude band plus "
    "mapping.window_band_margin_m each side (the service's default), or 4 m from 0.5 m below "
    "the ground (the window before it).",
)
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_service(
    seconds: float,
    depth_rate: float,
    depth_step: int,
    implementation: str,
    json_path: Path | None,
    workdir: Path | None,
    nice: int,
    window: str,
    quiet: bool,
) -> None:
    """One flight service against the SITL mock with depth frames: setpoint period at the mock,
    CPU, memory, start to READY."""
    from rich.console import Console
    from rich.table import Table

    console = Console(quiet=quiet, highlight=False)
    cfg = ServiceBenchConfig(
        seconds=seconds,
        depth_rate_hz=depth_rate,
        depth_step=depth_step,
        implementation=implementation,
        nice=nice,
        window=window,
    )
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-service-")
        workdir = Path(tmp.name)
    try:
        with console.status("bench service") as status:
            try:
                report = run_service_bench(cfg, workdir, lambda s: status.update(s))
            except (RuntimeError, TimeoutError) as e:
                raise click.ClickException(str(e)) from e
    finally:
        if tmp is not None:
            tmp.cleanup()
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2) + "\n")
    sp = report["setpoint_period_ms"]
    t = Table(title=f"flight service: {implementation}, {depth_rate:g} depth frames/s "
              f"(step {depth_step}), {report['window_s']:.0f} s window, nice {nice}, "
              f"map window {window}")  # fmt: skip
    t.add_column("measure")
    t.add_column("value", justify="right")
    t.add_column("target", justify="right")
    t.add_row("setpoint period p50, ms", _fmt(sp["p50"], ".2f"), "20 (50 Hz)")
    t.add_row("setpoint period p99, ms", _fmt(sp["p99"], ".2f"), "< 25")
    t.add_row("setpoint period max, ms", _fmt(sp["max"], ".2f"), "< 50")
    kp = report.get("setpoint_period_kernel_stamp_ms", {})
    if kp.get("n"):
        t.add_row(
            "  same, kernel receive stamps: p99 / max, ms",
            f"{_fmt(kp['p99'], '.2f')} / {_fmt(kp['max'], '.2f')}",
            "",
        )
    t.add_row("setpoints received per s", _fmt(report["setpoint_rate_hz"]), "50")
    t.add_row("service CPU, cores", _fmt(report["cpu_cores"], ".2f"), "<= 0.5")
    t.add_row("service RSS / peak, MB", f"{report['rss_mb']:.0f} / {report['peak_rss_mb']:.0f}", "")
    t.add_row("start to READY (warm cache), s", _fmt(report["start_to_ready_s"], ".2f"), "< 5")
    t.add_row("first start to READY, s", _fmt(report["first_start_to_ready_s"], ".2f"), "")
    t.add_row("depth frames mapped per s", _fmt(report["depth_frames_per_s"]), f"{depth_rate:g}")
    t.add_row("depth frames missed per s", _fmt(report["depth_frames_missed_per_s"]), "0")
    t.add_row(
        "ESDF refreshes per s (of them kept: nothing changed)",
        f"{_fmt(report.get('esdf_refreshes_per_s'))} ({report.get('esdf_refreshes_skipped', 0)})",
        ">= 10",
    )
    t.add_row(
        "  CPU per frame ingested / per ESDF refresh, ms",
        f"{_fmt(report.get('ingest_cpu_ms_per_frame'), '.2f')} / "
        f"{_fmt(report.get('esdf_cpu_ms_per_refresh'), '.1f')}",
        "",
    )
    for name, cores in sorted(report["cpu_cores_by_worker"].items()):
        t.add_row(f"  CPU of the {name} thread, cores", _fmt(cores, ".3f"), "")
    t.add_row("replans (failed)", f"{report['replans']} ({report['plans_failed']})", "")
    t.add_row("mock collisions", str(len(report["mock"].get("collisions", []))), "0")
    console.print(t)
    console.print(
        "targets: "
        + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in report["met"].items())
    )
    if report["window_cut_short"]:
        console.print(report["window_cut_short"])
    la = report["load_average"]
    console.print(
        f"load average {la['start'][0]:.1f} -> {la['end'][0]:.1f} on {os.cpu_count()} CPUs"
    )
