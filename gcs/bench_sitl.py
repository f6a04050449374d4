"""``swarm-gcs bench sitl``: CPU and real-time behaviour of the SITL mock fleet, and its
position-step response.

The fleet runs as its own process (``python -m sitl_mock.cli``), so its CPU use is measured
alone (from ``/proc/<pid>/stat`` over the measurement window). This process plays N companion
computers: one UDP socket per vehicle (as MAVSDK's ``udpin://`` binds), a position setpoint
stream at ``--rate`` Hz to every vehicle (slow circles, so the controllers work), offboard mode,
arming, takeoff by setpoint; then it measures for ``--seconds``: the fleet's CPU, the telemetry
rates every vehicle delivers, the setpoints the fleet accepted, and how simulated time kept up
with the wall clock. Last, vehicle 1 gets a position step of ``--step-m`` to the south (away from
the others: the vehicles stand in a row along north, vehicle 1 southmost) and its response
(LOCAL_POSITION_NED, timed by the vehicle's own clock) gives rise time and overshoot; the same
step through the model alone (no network, no estimate noise) is reported next to it.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from gcs.procstat import stat_cpu_s

# telemetry rates a real PX4 v1.16 SITL (SIH) sent on its API link, armed in Offboard, Hz
# (REFERENCE_NOTES section 5): the observation, kept apart from the mock's own table
PX4_RATES_HZ = {
    "ATTITUDE": 100.0,
    "ATTITUDE_QUATERNION": 50.0,
    "HIGHRES_IMU": 50.0,
    "GLOBAL_POSITION_INT": 50.0,
    "LOCAL_POSITION_NED": 30.0,
    "ODOMETRY": 30.0,
    "TIMESYNC": 10.0,
    "ALTITUDE": 10.0,
    "DISTANCE_SENSOR": 10.0,
    "ATTITUDE_TARGET": 10.0,
    "POSITION_TARGET_LOCAL_NED": 10.0,
    "SERVO_OUTPUT_RAW": 10.0,
    "VFR_HUD": 10.0,
    "GPS_RAW_INT": 8.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "HEARTBEAT": 1.0,
    "MISSION_CURRENT": 1.0,
    "ESTIMATOR_STATUS": 1.0,
    "SYSTEM_TIME": 1.0,
    "PING": 1.0,
    "SCALED_PRESSURE": 1.0,
    "LINK_NODE_STATUS": 1.0,
    "BATTERY_STATUS": 0.5,
    "CURRENT_MODE": 0.5,
    "HOME_POSITION": 0.5,
    "VIBRATION": 0.5,
}
PX4_OFFBOARD = 6
HOVER_ALT_M = 2.0


def _proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (Linux /proc), None elsewhere."""
    try:
        return stat_cpu_s(f"/proc/{pid}/stat")
    except OSError:
        return None


class _Swarm:
    """The N companion stand-ins and their shared poll loop."""

    def __init__(self, clients: list[Any]) -> None:
        self.clients = clients
        self.by_fd = {c.sock.fileno(): c for c in clients}

    def pump(self, until: float) -> None:
        """Read every socket until the monotonic time ``until``."""
        while True:
            rem = until - time.monotonic()
            ready, _, _ = select.select(list(self.by_fd), [], [], max(rem, 0.0))
            for fd in ready:
                self.by_fd[fd].poll(0.0)
            if rem <= 0:
                return

    def counts(self) -> list[Counter[str]]:
        return [Counter(c.counts) for c in self.clients]


def run_bench(
    vehicles: int,
    seconds: float,
    rate_hz: float,
    speedup: float,
    step_m: float,
    step_seconds: float,
    log: Any = None,
) -> dict[str, Any]:
    """Run the benchmark; returns the report (see the module docstring)."""
    from gcs.bench import machine_info
    from sitl_mock.client import MavClient, bind_consecutive_udp
    from sitl_mock.dynamics import (
        C_MOTOR,
        C_POS,
        C_YAW,
        NC,
        DynamicsParams,
        simulate_setpoint,
        step_metrics,
    )

    say = log or (lambda _msg: None)
    socks = bind_consecutive_udp(vehicles)
    base = socks[0].getsockname()[1]
    clients = [MavClient(sock=s, record=("LOCAL_POSITION_NED",)) for s in socks]
    swarm = _Swarm(clients)
    tmp = tempfile.TemporaryDirectory(prefix="bench_sitl_")
    stats_path = Path(tmp.name) / "stats.json"
    cmd = [
        sys.executable,
        "-m",
        "sitl_mock.cli",
        "--count",
        str(vehicles),
        "--base-port",
        str(base),
        "--local-port-offset",
        "-1",
        "--speedup",
        str(speedup),
        "--stats-json",
        str(stats_path),
        "--quiet",
        "--set",
        "autopilot.boot_time_s=1.0",
    ]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    t_launch = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    report: dict[str, Any] = {
        "vehicles": vehicles,
        "seconds": seconds,
        "setpoint_rate_hz": rate_hz,
        "speedup": speedup,
    }
    sent = [0] * vehicles
    try:
        say("waiting for heartbeats")
        for c in clients:
            c.connect(60.0)
        report["startup_s"] = time.monotonic() - t_launch
        for c in clients:
            c.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & 0x10000000, 30.0)
        period = 1.0 / rate_hz
        t0 = time.monotonic()

        def stream(duration_wall: float, target: Any) -> None:
            nonlocal sent
            end = time.monotonic() + duration_wall
            nxt = time.monotonic()
            while nxt < end:
                t_sim = (time.monotonic() - t0) * speedup
                for i, c in enumerate(clients):
                    n, e, d = target(i, t_sim)
                    c.setpoint(i + 1, (n, e, d), yaw_rad=0.0)
                    sent[i] += 1
                nxt += period
                swarm.pump(nxt)

        def hover(i: int, t: float) -> tuple[float, float, float]:
            return (0.0, 0.0, -HOVER_ALT_M)

        say("setpoints, offboard, arm")
        stream(0.1 / speedup, hover)  # PX4 v1.16 needs one setpoint younger than COM_OF_LOSS_T
        for i, c in enumerate(clients):
            c.set_mode(PX4_OFFBOARD, 0, target_system=i + 1, wait_ack=False)
            c.command_long(400, (1.0,), target_system=i + 1, wait_ack=False)
        end_climb = time.monotonic() + 30.0
        while time.monotonic() < end_climb:
            stream(0.2, hover)
            ok = all(
                "LOCAL_POSITION_NED" in c.latest
                and c.latest["LOCAL_POSITION_NED"].z < -0.9 * HOVER_ALT_M
                and c.latest.get("HEARTBEAT") is not None
                and c.latest["HEARTBEAT"].base_mode & 128
                for c in clients
            )
            if ok:
                break
        else:
            raise RuntimeError("the vehicles did not climb to the hover altitude")
        report["airborne_after_s"] = time.monotonic() - t0

        t_circle = (time.monotonic() - t0) * speedup

        def circle(i: int, t: float) -> tuple[float, float, float]:
            """A 1 m radius circle in 10 s, starting where the vehicle hovers."""
            a = 2.0 * math.pi / 10.0 * (t - t_circle)
            return (math.sin(a), 1.0 - math.cos(a), -HOVER_ALT_M)

        # ---- measurement window ------------------------------------------------------
        say(f"measuring for {seconds:g} s")
        c0 = swarm.counts()
        sent0 = list(sent)
        lpn0 = clients[0].latest["LOCAL_POSITION_NED"].time_boot_ms
        if hasattr(signal, "SIGUSR1"):
            proc.send_signal(signal.SIGUSR1)  # the fleet restarts its loop counters
        cpu0 = _proc_cpu_s(proc.pid)
        me0 = time.process_time()
        w0 = time.monotonic()
        stream(seconds, circle)
        w1 = time.monotonic()
        cpu1 = _proc_cpu_s(proc.pid)
        me1 = time.process_time()
        lpn1 = clients[0].latest["LOCAL_POSITION_NED"].time_boot_ms
        c1 = swarm.counts()
        wall = w1 - w0
        if cpu0 is not None and cpu1 is not None:
            report["fleet_cpu_percent"] = 100.0 * (cpu1 - cpu0) / wall
        report["client_cpu_percent"] = 100.0 * (me1 - me0) / wall
        report["sim_per_wall"] = (lpn1 - lpn0) / 1000.0 / wall
        rates: dict[str, Any] = {}
        for name, px4 in PX4_RATES_HZ.items():
            per = [(c1[i][name] - c0[i][name]) / (wall * speedup) for i in range(vehicles)]
            rates[name] = {"px4_hz": px4, "min_hz": min(per), "mean_hz": float(np.mean(per))}
        report["telemetry_hz_sim"] = rates
        report["telemetry_msgs_per_s_total"] = (
            sum((sum(c1[i].values()) - sum(c0[i].values())) for i in range(vehicles)) / wall
        )
        report["setpoints_sent_hz"] = float(
            np.mean([(sent[i] - sent0[i]) / wall for i in range(vehicles)])
        )

        # ---- step response -----------------------------------------------------------
        if step_m > 0:
            say(f"position step of {step_m:g} m on vehicle 1")
            p1 = clients[0].latest["LOCAL_POSITION_NED"]
            start = (round(p1.x, 1), round(p1.y, 1), -HOVER_ALT_M)
            goal = (start[0] - step_m, start[1], start[2])  # south: away from the others
            target = start
            # the others stop where they are: all flew the same circle in phase, so they stay
            # north of vehicle 1 by their spawn spacing while it steps south
            t_stop = (time.monotonic() - t0) * speedup

            def step_target(i: int, t: float) -> tuple[float, float, float]:
                return target if i == 0 else circle(i, t_stop)

            stream(3.0 / speedup, step_target)  # settle at the start point
            target = goal
            clients[0].recorded.clear()
            t_step_ms = clients[0].latest["LOCAL_POSITION_NED"].time_boot_ms
            stream(step_seconds / speedup, step_target)
            rec = [m for _, m in clients[0].recorded if m.time_boot_ms >= t_step_ms]
            ts = np.array([(m.time_boot_ms - t_step_ms) / 1000.0 for m in rec])
            xs = np.array([m.x for m in rec])
            report["step"] = {
                "size_m": step_m,
                "samples": len(rec),
                **step_metrics(ts, xs, start[0], goal[0]),
            }
            # the model alone, no estimate noise, sampled at 1 kHz
            dp = DynamicsParams(pos_noise_sigma_m=0.0, wind_sigma_m_s2=0.0)
            command = np.full(NC, np.nan)
            command[C_POS : C_POS + 3] = (0.0, -step_m, HOVER_ALT_M)  # ENU: south is -y
            command[C_YAW] = math.pi / 2
            command[C_MOTOR] = 2.0
            tm, pm = simulate_setpoint(
                dp, np.array([0.0, 0.0, HOVER_ALT_M]), command, step_seconds, 0.001
            )
            report["step_model"] = step_metrics(tm, pm[:, 1], 0.0, -step_m)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        for c in clients:
            c.close()
    if stats_path.is_file():
        st = json.loads(stats_path.read_text())
        links = st["links"]
        report["fleet"] = {  # from the start of the window to the end of the run
            "loop_cpu_s": st["loop_cpu_s"],
            "process_cpu_s": st.get("process_cpu_s"),
            "wall_s": st["wall_s"],
            "sim_s": st["sim_s"],
            "ticks": st["ticks"],
            "late_ticks": st["late_ticks"],
            "skipped_ticks": st["skipped_ticks"],
            "max_lateness_ms": st["max_lateness_ms"],
            "setpoints_received": sum(x["setpoints"] for x in links),
            "setpoints_malformed": sum(x["setpoints_malformed"] for x in links),
            "rx_bad": sum(x["rx_bad"] for x in links),
            "collisions": len(st["collisions"]),
        }
        report["setpoints_sent"] = int(sum(sent))
        report["setpoints_accepted_fraction"] = report["fleet"]["setpoints_received"] / max(
            sum(sent), 1
        )
    elif proc.returncode not in (0, None):
        raise RuntimeError(f"the fleet failed: {err.decode(errors='replace')[-2000:]}")
    tmp.cleanup()
    report["machine"] = machine_info()
    return report


def _fmt(x: Any, spec: str = ".2f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


@click.command("sitl")
@click.option("--vehicles", default=10, show_default=True, help="Vehicles in the fleet.")
@click.option("--seconds", default=30.0, show_default=True, help="Measurement window [s].")
@click.option(
    "--rate",
    "rate_hz",
    default=50.0,
    show_default=True,
    help="Setpoints per second to each vehicle.",
)
@click.option(
    "--speedup",
    default=1.0,
    show_default=True,
    help="Simulated seconds per second (1 = real time, the benchmark's condition).",
)
@click.option("--step-m", default=2.0, show_default=True, help="Position step [m]; 0: none.")
@click.option(
    "--step-seconds",
    default=8.0,
    show_default=True,
    help="Simulated seconds recorded after the step.",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def sitl(
    vehicles: int,
    seconds: float,
    rate_hz: float,
    speedup: float,
    step_m: float,
    step_seconds: float,
    json_path: Path | None,
    quiet: bool,
) -> None:
    """SITL mock fleet: CPU in real time with setpoint streams, telemetry rates, step response."""
    console = Console(quiet=quiet, highlight=False)
    if vehicles < 1 or seconds <= 0 or rate_hz <= 0 or speedup <= 0:
        raise click.BadParameter("--vehicles, --seconds, --rate and --speedup must be positive")
    try:
        r = run_bench(
            vehicles,
            seconds,
            rate_hz,
            speedup,
            step_m,
            step_seconds,
            log=(lambda m: console.print(f"[dim]{m}[/dim]")),
        )
    except (RuntimeError, TimeoutError, OSError) as e:
        raise click.ClickException(str(e)) from e
    t = Table(
        title=f"SITL mock: {vehicles} vehicles, setpoints at {rate_hz:g} Hz each, "
        f"speedup {speedup:g}, {seconds:g} s window"
    )
    t.add_column("quantity")
    t.add_column("value", justify="right")
    t.add_row("fleet CPU (one process, % of one core)", _fmt(r.get("fleet_cpu_percent"), ".1f"))
    t.add_row("simulated s per wall s (target = speedup)", _fmt(r.get("sim_per_wall"), ".3f"))
    fl = r.get("fleet", {})
    t.add_row(
        "late / skipped / all ticks (window and step)",
        f"{fl.get('late_ticks', '-')} / {fl.get('skipped_ticks', '-')} / {fl.get('ticks', '-')}",
    )
    t.add_row("max tick lateness, window and step (ms)", _fmt(fl.get("max_lateness_ms"), ".1f"))
    t.add_row("collisions (window and step)", str(fl.get("collisions", "-")))
    t.add_row("setpoints sent per vehicle (Hz)", _fmt(r.get("setpoints_sent_hz"), ".1f"))
    t.add_row("setpoints accepted / sent", _fmt(r.get("setpoints_accepted_fraction"), ".4f"))
    t.add_row(
        "telemetry messages / s received (all)", _fmt(r.get("telemetry_msgs_per_s_total"), ".0f")
    )
    t.add_row("client CPU (this process, %)", _fmt(r.get("client_cpu_percent"), ".1f"))
    t.add_row("fleet start-up to first heartbeats (s)", _fmt(r.get("startup_s"), ".2f"))
    console.print(t)
    tr = Table(title="telemetry per vehicle (Hz of simulated time): min over vehicles / PX4")
    tr.add_column("message")
    tr.add_column("min", justify="right")
    tr.add_column("PX4", justify="right")
    for name, v in r.get("telemetry_hz_sim", {}).items():
        tr.add_row(name, _fmt(v["min_hz"], ".1f"), _fmt(v["px4_hz"], ".1f"))
    console.print(tr)
    if "step" in r:
        s, m = r["step"], r["step_model"]
        ts = Table(title=f"position step {step_m:g} m (south), vehicle 1")
        for col in ("", "rise 10-90 % (s)", "overshoot (%)", "settling 5 % (s)", "final err (m)"):
            ts.add_column(col, justify="right")
        for name, d in (("through MAVLink (LOCAL_POSITION_NED)", s), ("model alone", m)):
            ts.add_row(
                name,
                _fmt(d["rise_time_s"]),
                _fmt(100 * d["overshoot_fraction"], ".1f"),
                _fmt(d["settling_time_s"]),
                _fmt(d["final_error_m"], ".3f"),
            )
        console.print(ts)
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(_json_safe(r), indent=2) + "\n", encoding="utf-8")
        console.print(f"wrote {json_path}")
