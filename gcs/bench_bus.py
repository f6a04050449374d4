"""Swarm bus latency benchmark (``swarm-gcs bench bus``): peer trajectory, publish -> inbox.

N drones (default 7), each a ``SwarmNode`` in its own process (or each its own Zenoh session in
this process, ``--mode sessions``), joined in a full peer mesh on loopback. Every drone publishes
``--messages`` realistic trajectories (``--pieces`` quintic pieces, default 6: about 1 KB on the
wire) at ``--rate`` Hz, staggered so that the drones do not all publish at once. The latency of a
message at a receiver is its ``on_trajectory`` callback time (the trajectory is then in the
inbox the planner reads) minus the stamp taken just before ``publish``: encoding, Zenoh,
the gate's checks and building the ``TrajectoryMsg`` are all inside. Both times come from the
same system clock (one machine). The first ``--warmup`` messages of each drone are not counted.

Target (issue #9): median < 5 ms, p99 < 20 ms.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

TARGETS_MS = {"median": 5.0, "p99": 20.0}
SWARM = "bench/bus"


@dataclasses.dataclass(frozen=True)
class BusBenchConfig:
    drones: int = 7
    messages: int = 200
    """Trajectories each drone publishes (after the warm-up)."""
    rate_hz: float = 10.0
    """Publications per second per drone."""
    pieces: int = 6
    warmup: int = 5
    mode: str = "processes"
    """'processes': one process per drone; 'sessions': one Zenoh session per drone in this one."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.drones < 2:
            raise ValueError("drones must be >= 2")
        if self.messages < 1 or self.warmup < 0 or self.pieces < 1:
            raise ValueError("messages and pieces must be >= 1, warmup >= 0")
        if not self.rate_hz > 0.0:
            raise ValueError("rate_hz must be > 0")
        if self.mode not in ("processes", "sessions"):
            raise ValueError("mode must be 'processes' or 'sessions'")


def _trajectory_coeffs(rng: np.random.Generator, drone: int, pieces: int) -> np.ndarray:
    """Coefficients of a plausible plan: a slow curve near the drone's slot, 1.2 s pieces."""
    c = np.zeros((pieces, 6, 3))
    c[:, 0] = [2.0 * np.cos(drone), 2.0 * np.sin(drone), 1.0]
    c[:, 0, 0] += 0.6 * np.arange(pieces)
    c[:, 1] = [0.5, 0.0, 0.0]
    c[:, 2:] = rng.normal(scale=0.01, size=(pieces, 4, 3))
    return c


class _Drone:
    """One drone of the benchmark: a node, its publication schedule and its latency record."""

    def __init__(self, drone: int, endpoints: Any, cfg: BusBenchConfig) -> None:
        from onboard.comm.zenoh_bus import SwarmNode

        self.i = drone
        self.cfg = cfg
        self.rng = np.random.default_rng([cfg.seed, drone])
        self.node = SwarmNode(SWARM, drone, endpoints)
        self.samples: list[tuple[int, int, float]] = []  # (sender, seq, latency_s)
        self._lock = threading.Lock()
        self.node.on_trajectory(self._on_traj)

    def _on_traj(self, env: Any, _receive_s: float) -> None:
        latency = time.time() - env.stamp_s
        with self._lock:
            self.samples.append((env.sender, env.seq, latency))

    def publish(self, k: int) -> None:
        from onboard.comm.messages import TrajectoryMsg
        from onboard.planner.trajectory import Trajectory

        c = _trajectory_coeffs(self.rng, self.i, self.cfg.pieces)
        now = time.time()
        tr = Trajectory(now, c, np.full(self.cfg.pieces, 1.2))
        self.node.publish(TrajectoryMsg(self.i, k, self.i, tr, formation_epoch=1), now)

    def received(self) -> int:
        with self._lock:
            return len(self.samples)

    def result(self) -> dict[str, Any]:
        with self._lock:
            kept = [s for s in self.samples if s[1] >= self.cfg.warmup]
        return {
            "drone": self.i,
            "latencies_s": [s[2] for s in kept],
            "counters": self.node.counters(),
        }


def _offset_s(cfg: BusBenchConfig, drone: int, k: int) -> float:
    """Publication time of message k of a drone, after the common start."""
    return (k + drone / cfg.drones) / cfg.rate_hz


def _wait(cond: Callable[[], bool], timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def _drain(drones: list[_Drone], cfg: BusBenchConfig) -> None:
    want = (cfg.drones - 1) * (cfg.messages + cfg.warmup)
    _wait(lambda: all(d.received() >= want for d in drones), 10.0)


def _worker(drone: int, endpoints: Any, cfg: BusBenchConfig) -> None:
    """One drone in its own process (``python -m gcs.bench_bus DRONE CONFIG ENDPOINTS``):
    join, print ``ready``, read the common start time from stdin, publish on schedule, print
    the result as one JSON line, stay up until stdin says ``done`` (peers still receive)."""
    d = _Drone(drone, endpoints, cfg)
    try:
        every = set(range(cfg.drones))
        if not _wait(lambda: d.node.alive_drones() == every, 60.0):
            raise RuntimeError(f"drone {drone} sees {sorted(d.node.alive_drones())} only")
        if not _wait(d.node.heard_by_someone, 30.0):  # subscriptions lag liveliness
            raise RuntimeError(f"drone {drone}: nobody subscribes to its trajectories")
        print("ready", flush=True)
        start = float(sys.stdin.readline())
        for k in range(cfg.messages + cfg.warmup):
            delay = start + _offset_s(cfg, drone, k) - time.time()
            if delay > 0:
                time.sleep(delay)
            d.publish(k)
        _drain([d], cfg)
        print(json.dumps(d.result()), flush=True)
        sys.stdin.readline()
    finally:
        d.node.close()


def _read_line(proc: subprocess.Popen[str], drone: int, what: str, timeout_s: float) -> str:
    """The next stdout line of a worker, or a RuntimeError naming what went wrong."""
    out = proc.stdout
    assert out is not None
    box: list[str] = []
    reader = threading.Thread(target=lambda: box.append(out.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    line = box[0] if box else ""
    if not line:
        err = ""
        if proc.poll() is not None and proc.stderr is not None:
            err = proc.stderr.read()[-2000:]
        raise RuntimeError(f"no {what} from drone process {drone}: {err or 'timed out'}")
    return line


def _run_processes(cfg: BusBenchConfig, eps: list[Any]) -> list[dict[str, Any]]:
    conf = json.dumps(dataclasses.asdict(cfg))
    procs: list[subprocess.Popen[str]] = []
    try:
        for i in range(cfg.drones):
            ep = json.dumps({"listen": list(eps[i].listen), "connect": list(eps[i].connect)})
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-m", "gcs.bench_bus", str(i), conf, ep],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                )
            )
        for i, p in enumerate(procs):
            line = _read_line(p, i, "ready", 120.0).strip()
            if line != "ready":
                raise RuntimeError(f"drone process {i} said {line!r} instead of ready")
        start = time.time() + 0.5
        for p in procs:
            assert p.stdin is not None
            p.stdin.write(f"{start!r}\n")
            p.stdin.flush()
        duration = _offset_s(cfg, cfg.drones, cfg.messages + cfg.warmup)
        results = [
            json.loads(_read_line(p, i, "result", duration + 30.0)) for i, p in enumerate(procs)
        ]
        for p in procs:
            assert p.stdin is not None
            p.stdin.write("done\n")
            p.stdin.flush()
        for p in procs:
            p.wait(15.0)
        return results
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
            for f in (p.stdin, p.stdout, p.stderr):
                if f is not None:
                    f.close()


def _run_sessions(cfg: BusBenchConfig, eps: list[Any]) -> list[dict[str, Any]]:
    drones: list[_Drone] = []
    try:
        for i in range(cfg.drones):
            drones.append(_Drone(i, eps[i], cfg))
        every = set(range(cfg.drones))
        if not _wait(
            lambda: all(
                d.node.alive_drones() == every and d.node.heard_by_someone() for d in drones
            ),
            30.0,
        ):
            raise RuntimeError("the sessions did not all see each other")
        schedule = sorted(
            (_offset_s(cfg, d.i, k), d.i, k)
            for d in drones
            for k in range(cfg.messages + cfg.warmup)
        )
        start = time.time() + 0.2
        for at, i, k in schedule:
            delay = start + at - time.time()
            if delay > 0:
                time.sleep(delay)
            drones[i].publish(k)
        _drain(drones, cfg)
        return [d.result() for d in drones]
    finally:
        for d in drones:
            d.node.close()


def _stats_ms(values_s: list[float]) -> dict[str, float | int | None]:
    if not values_s:
        return {"count": 0, "median": None, "p90": None, "p99": None, "max": None, "min": None}
    a = np.asarray(values_s) * 1e3
    return {
        "count": int(a.size),
        "min": float(a.min()),
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def run_bus_bench(cfg: BusBenchConfig) -> dict[str, Any]:
    """Run the benchmark; the report (latencies in ms) as a JSON-ready dict."""
    from onboard.comm.zenoh_session import peer_mesh

    eps = peer_mesh(cfg.drones)
    t0 = time.time()
    if cfg.mode == "processes":
        results = _run_processes(cfg, eps)
    else:
        results = _run_sessions(cfg, eps)
    wall = time.time() - t0
    all_lat = [x for r in results for x in r["latencies_s"]]
    expected = cfg.drones * (cfg.drones - 1) * cfg.messages
    rejected = sum(
        v for r in results for k, v in r["counters"].items() if k.startswith(("reject.", "error."))
    )
    stats = _stats_ms(all_lat)
    met = {
        k: (stats[k] is not None and float(stats[k]) < v)  # type: ignore[arg-type]
        for k, v in TARGETS_MS.items()
    }
    return {
        "benchmark": "bus",
        "config": dataclasses.asdict(cfg),
        "message_bytes": _message_bytes(cfg),
        "latency_ms": stats,
        "per_receiver_ms": {str(r["drone"]): _stats_ms(r["latencies_s"]) for r in results},
        "expected": expected,
        "received": len(all_lat),
        "lost": expected - len(all_lat),
        "rejected_or_errors": rejected,
        "targets_ms": TARGETS_MS,
        "met": met,
        "wall_s": wall,
        "host": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _message_bytes(cfg: BusBenchConfig) -> int:
    from onboard.comm.messages import TrajectoryMsg
    from onboard.comm.wire import WIRE_VERSION, Envelope, encode
    from onboard.planner.trajectory import Trajectory

    now = time.time()
    c = _trajectory_coeffs(np.random.default_rng(0), 0, cfg.pieces)
    body = TrajectoryMsg(0, 0, 0, Trajectory(now, c, np.full(cfg.pieces, 1.2))).to_body()
    return len(encode(Envelope(WIRE_VERSION, 0, 1, 0, now, 3.0, body)))


def _fmt(x: Any) -> str:
    return "-" if x is None else f"{x:.2f}"


@click.command("bus")
@click.option("--drones", default=7, show_default=True, type=click.IntRange(2, 32))
@click.option(
    "--messages",
    default=200,
    show_default=True,
    type=click.IntRange(min=1),
    help="Trajectories each drone publishes (after the warm-up).",
)
@click.option(
    "--rate",
    "rate_hz",
    default=10.0,
    show_default=True,
    type=click.FloatRange(min=0.0, min_open=True),
    help="Publications per second per drone.",
)
@click.option("--pieces", default=6, show_default=True, type=click.IntRange(1, 64))
@click.option("--warmup", default=5, show_default=True, type=click.IntRange(min=0))
@click.option(
    "--mode",
    type=click.Choice(["processes", "sessions"]),
    default="processes",
    show_default=True,
    help="One process per drone, or one Zenoh session per drone in this process.",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_bus(
    drones: int,
    messages: int,
    rate_hz: float,
    pieces: int,
    warmup: int,
    mode: str,
    json_path: Path | None,
    quiet: bool,
) -> None:
    """Peer trajectory latency over Zenoh on loopback: publish -> the receiver's inbox."""
    from rich.console import Console
    from rich.table import Table

    console = Console(quiet=quiet, highlight=False)
    cfg = BusBenchConfig(drones, messages, rate_hz, pieces, warmup, mode)
    with console.status(f"{drones} drones x {messages + warmup} trajectories ({mode})"):
        try:
            report = run_bus_bench(cfg)
        except RuntimeError as e:
            raise click.ClickException(str(e)) from e
    s = report["latency_ms"]
    t = Table(
        title=f"bus latency: {drones} drones ({mode}), {pieces}-piece trajectories "
        f"({report['message_bytes']} B), {rate_hz:g} Hz each"
    )
    for col in ("received", "lost", "min", "median", "p90", "p99", "max [ms]"):
        t.add_column(col, justify="right")
    t.add_row(
        str(report["received"]),
        str(report["lost"]),
        _fmt(s["min"]),
        _fmt(s["median"]),
        _fmt(s["p90"]),
        _fmt(s["p99"]),
        _fmt(s["max"]),
    )
    console.print(t)
    console.print(
        "targets: median < {median:g} ms, p99 < {p99:g} ms -> ".format(**TARGETS_MS)
        + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in report["met"].items())
    )
    if report["rejected_or_errors"]:
        console.print(f"[red]{report['rejected_or_errors']} messages rejected or errors[/red]")
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2) + "\n")
        console.print(f"wrote {json_path}")


if __name__ == "__main__":  # a drone process of the benchmark (see _run_processes)
    from onboard.comm.zenoh_session import ZenohEndpoints

    _ep = json.loads(sys.argv[3])
    _worker(
        int(sys.argv[1]),
        ZenohEndpoints(listen=tuple(_ep["listen"]), connect=tuple(_ep["connect"])),
        BusBenchConfig(**json.loads(sys.argv[2])),
    )
