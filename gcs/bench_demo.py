"""``swarm-gcs bench demo``: the end-to-end demo over seeds, beside the fast-time simulator.

Issue #10's numbers: the real stack (``swarm-gcs demo``: the mock fleet, one flight service per
drone, the ground station) over seeds 1..N, optionally with a formation change in flight, and
for each seed the fast-time simulator (``gcs.fastsim``) on the same world: the same formation,
obstacles, starts and goals, mapped perception at the demo's depth rate and pixel step, the
same change at the same time after the goal. One demo runs at a time (each takes the whole
machine), its own process (``swarm-gcs demo --json``, so that an interrupted run cleans up as
the demo does); the fast-time flight runs after it. ``--fastsim-only`` flies the fast-time
twins alone, ``--jobs`` of them at a time: the twin of the real stack in minutes, for
comparing changes (issue #10's figure stays the real stack's).

Clearances differ in kind: the demo's ``body`` clearance is the mock's (trunk surface to the
vehicle's body, its radius off the centre's); ``centre`` clearances (the flight records' for
the demo, the simulator's own) are the drone centre to the surface, which is what the
fast-time simulator measures.
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import click
import numpy as np
import psutil

from gcs.demo import DEMO_LEAD_MAX_S, DEMO_LEAD_S
from gcs.fastsim import FORMATION_REACHED_E_SIM
from gcs.pools import sigterm_interrupts
from onboard.agent import REPLAN_PERIOD_S

REACHED_WITHIN_S = 10.0
"""Issue #10: the new shape (e_sim below ``FORMATION_REACHED_E_SIM``) within this long."""


def _num(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def host_cpu_share(before: Any, after: Any) -> dict[str, float | None]:
    """The host's CPU time between two ``psutil.cpu_times()`` samples, as shares of all of it
    (every core): ``busy`` (neither idle nor waiting for I/O) and ``steal`` (taken by the
    hypervisor for other guests: a busy neighbour slows a real-stack run the way a busy stack
    does; None where the platform does not report it). Both None when no time passed. As
    psutil's ``cpu_percent``: a guest's time (Linux) is counted in ``user`` already, not twice."""

    def whole(t: Any) -> float:
        return float(sum(t)) - getattr(t, "guest", 0.0) - getattr(t, "guest_nice", 0.0)

    total = whole(after) - whole(before)
    if not total > 0.0:
        return {"busy": None, "steal": None}
    idle = (after.idle - before.idle) + (
        getattr(after, "iowait", 0.0) - getattr(before, "iowait", 0.0)
    )
    steal = getattr(after, "steal", None)
    return {
        "busy": min(max(1.0 - idle / total, 0.0), 1.0),
        "steal": None
        if steal is None
        else min(max((steal - getattr(before, "steal", 0.0)) / total, 0.0), 1.0),
    }


def run_demo_seed(seed: int, argv: list[str], out_dir: Path, timeout_s: float) -> dict[str, Any]:
    """One ``swarm-gcs demo`` process for ``seed``; its JSON result (or, when it failed
    before printing one, its ``result.json`` and the tail of its error output) plus the
    centre clearance of its flight records and the host's CPU over the run (``host_cpu``:
    ``host_cpu_share``)."""
    cmd = [sys.executable, "-m", "gcs.cli", "demo", *argv, "--seed", str(seed)]
    cmd += ["--json", "-q", "--out", str(out_dir)]
    cpu0 = psutil.cpu_times()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except BaseException:
        # Ctrl-C or our timeout: the demo stops every process it started on SIGINT
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=60.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
        raise
    wall = time.monotonic() - t0
    host_cpu = host_cpu_share(cpu0, psutil.cpu_times())
    result: dict[str, Any] = {}
    for line in reversed(out.splitlines()):
        if line.startswith("{"):
            result = json.loads(line)
            break
    if not result and (out_dir / "result.json").exists():
        result = json.loads((out_dir / "result.json").read_text())
    if not result:
        result = {"success": False}
    result.setdefault("error", None)
    if proc.returncode != 0 and not result.get("error"):
        if result.get("collisions"):
            result["error"] = f"{result['collisions']} collision(s) reported by the mock"
        elif err.strip():
            result["error"] = err.strip().splitlines()[-1]
        else:
            result["error"] = f"exit {proc.returncode}"
    result["exit_code"] = proc.returncode
    result["bench_wall_s"] = wall
    result["host_cpu"] = host_cpu
    summary = out_dir / "report" / "summary.json"
    centre = None
    if summary.exists():
        centre = _num(json.loads(summary.read_text()).get("min_obstacle_clearance_m"))
    result["min_obstacle_clearance_centre_m"] = centre
    return result


def run_fastsim_seed(
    seed: int,
    formation: str,
    world: str,
    change: tuple[str, float] | None,
    depth_rate_hz: float,
    depth_step: int,
    planner: Any,
    replan_period_s: float = REPLAN_PERIOD_S,
    occupancy_overrides: tuple[tuple[str, Any], ...] = (),
) -> dict[str, Any]:
    """The fast-time flight of the demo's world for ``seed``: mapped perception at the demo's
    depth rate and step, the demo's planner parameters and replan period (the flight service's
    ``planning.replan_period_s``), the same formation change; ``occupancy_overrides``: the map
    parameters set on the command line (``--set-onboard mapping.occupancy.NAME=VALUE``)."""
    from gcs.fastsim import SimConfig, run_sim
    from onboard.config import load_formation, load_world_spec

    cfg = SimConfig(
        load_formation(formation),
        load_world_spec(world),
        seed=seed,
        planner=planner,
        perception="mapped",
        camera_rate_hz=depth_rate_hz,
        camera_skip_pixel=depth_step,
        formation_change=None if change is None else (load_formation(change[0]), change[1]),
        replan_period_s=replan_period_s,
        occupancy_overrides=occupancy_overrides,
    )
    r = run_sim(cfg)
    return {
        "success": bool(r.success),
        "arrived": int(np.sum(r.arrived)),
        "collisions": int(r.collisions),
        "flight_time_s": _num(r.flight_time_s),
        "e_sim": _num(r.e_sim_mean_cluttered),
        "e_dist_m": _num(r.e_dist_mean_cluttered),
        "min_obstacle_clearance_centre_m": _num(r.min_obstacle_clearance_m),
        "min_drone_distance_m": _num(r.min_drone_distance_m),
        "max_speed_m_s": _num(r.max_speed_m_s),
        # fast time switches at the change itself (no lead): both clocks are one
        "formation_change_reached_s": (r.formation_change or {}).get("reached_s"),
        "formation_change_reached_after_switch_s": (r.formation_change or {}).get("reached_s"),
        "replan_ms_median": _num(r.replan_ms.get("median")),
        "sim_wall_s": _num(r.sim_wall_s),
        "refusals": dict(r.refusals),
    }


def _demo_row(d: dict[str, Any]) -> dict[str, Any]:
    """The figures of a demo result the bench reports (the full result stays in its flight
    directory)."""
    sp = d.get("setpoint_period_ms") or {}
    plan = d.get("plan_ms") or {}
    depth = d.get("depth") or {}
    return {
        "success": bool(d.get("success")),
        "error": d.get("error"),
        "collisions": d.get("collisions"),
        "wall_s": _num(d.get("wall_s", d.get("bench_wall_s"))),
        "flight_time_s": _num(d.get("flight_time_s")),
        "crossing_time_s": _num(d.get("crossing_time_s")),
        "e_sim": _num(d.get("e_sim")),
        "e_dist_m": _num(d.get("e_dist_m")),
        "min_obstacle_clearance_body_m": _num(d.get("min_obstacle_clearance_m")),
        "min_obstacle_clearance_centre_m": _num(d.get("min_obstacle_clearance_centre_m")),
        "min_drone_distance_m": _num(d.get("min_drone_distance_m")),
        "formation_change_reached_s": _num(d.get("formation_change_reached_s")),
        "formation_change_reached_after_switch_s": _num(
            d.get("formation_change_reached_after_switch_s")
        ),
        "setpoint_period_p99_ms": _num(sp.get("p99")),
        "setpoint_period_max_ms": _num(sp.get("max")),
        "plan_ms_median": _num(plan.get("median")),
        "plan_ms_p90": _num(plan.get("p90")),
        "plan_cpu_ms_median": _num((d.get("plan_cpu_ms") or {}).get("median")),
        "monitor_brakes": (d.get("monitor") or {}).get("brakes"),
        "depth_holds": (d.get("depth_holds") or {}).get("holds"),
        "map_lag_rides": (d.get("depth_holds") or {}).get("map_lag_rides"),
        "kernels_after_ready": d.get("kernels_after_ready"),
        "stream_guard_stops": d.get("stream_guard_stops"),
        "plan_refusals": d.get("plan_refusals"),
        "depth_frames": depth.get("frames"),
        "depth_frames_skipped": depth.get("skipped"),
        "cpu_s": sum((d.get("cpu_s") or {}).values()) or None,
        "host_cpu": d.get("host_cpu"),
        "flight_dir": d.get("flight_dir"),
    }


def _reached(row: dict[str, Any], key: str = "formation_change_reached_s") -> bool:
    """The new shape within ``REACHED_WITHIN_S`` by ``key``'s clock: from the command (issue
    #10's figure), or ``formation_change_reached_after_switch_s``: from the common switch time
    the command carries (the station's lead later), the fast-time twin's clock."""
    r = row.get(key)
    return r is not None and r <= REACHED_WITHIN_S


def summarise(rows: list[dict[str, Any]], change: bool) -> dict[str, Any]:
    """Counts over the seeds: demo successes (and, with a change, those that reached the new
    shape within ``REACHED_WITHIN_S``), the same for the fast-time flights; whether issue #10's
    target is met (None when only the fast-time flights were flown)."""
    out: dict[str, Any] = {"seeds": len(rows)}
    for side in ("demo", "fastsim"):
        got = [r[side] for r in rows if r.get(side) is not None]
        out[side] = {
            "flown": len(got),
            "success": sum(1 for g in got if g["success"]),
            "collisions": sum(int(g.get("collisions") or 0) for g in got),
        }
        if change:
            out[side]["reached_within_10_s"] = sum(1 for g in got if g["success"] and _reached(g))
            out[side]["reached_within_10_s_of_the_switch"] = sum(
                1
                for g in got
                if g["success"] and _reached(g, "formation_change_reached_after_switch_s")
            )
    if rows and out["demo"]["flown"] == 0:
        out["demo_target_met"] = None  # fast time only: the real stack was not flown
        return out
    met = out["demo"]["success"] == len(rows) and out["demo"]["collisions"] == 0
    if change:
        met = met and out["demo"]["reached_within_10_s"] == len(rows)
    out["demo_target_met"] = bool(rows) and met
    return out


def _fastsim_job(args: tuple[Any, ...]) -> dict[str, Any]:
    """``run_fastsim_seed(*args)`` (a worker process's task with ``--jobs``)."""
    return run_fastsim_seed(*args)


def fly_twins(args: list[tuple[Any, ...]], jobs: int) -> list[dict[str, Any]]:
    """``run_fastsim_seed`` on each of ``args``, in order; ``jobs`` at a time in spawned worker
    processes when over 1 (a SIGTERM ends them too, as in ``bench faults``)."""
    if jobs == 1:
        return [_fastsim_job(a) for a in args]
    with sigterm_interrupts(), multiprocessing.get_context("spawn").Pool(jobs) as pool:
        return pool.map(_fastsim_job, args, chunksize=1)


def _pct(x: float | None) -> float | None:
    return None if x is None else 100.0 * x


def _fmt(x: Any, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


@click.command("demo")
@click.option("--seeds", type=click.IntRange(1, 100), default=5, show_default=True,
              help="How many seeds (one world each).")  # fmt: skip
@click.option("--first-seed", type=int, default=1, show_default=True,
              help="Seeds first-seed .. first-seed + seeds - 1.")  # fmt: skip
@click.option("--drones", type=click.IntRange(2, 64), default=7, show_default=True)
@click.option("--formation", default="hexagon-7", show_default=True)
@click.option("--world", default="forest-medium", show_default=True)
@click.option("--formation-change", "change", default=None, metavar="NAME@SECONDS",
              help="Change formation this many seconds after the goal (the fast-time flight: "
              "after its start, where it has its goal).")  # fmt: skip
@click.option("--depth-rate", type=click.FloatRange(1.0, 30.0), default=None,
              help="Depth frames per second and drone [default: the demo's].")  # fmt: skip
@click.option("--altitude-band", type=float, nargs=2, default=None, metavar="BELOW ABOVE",
              help="The planner's altitude band around the cruise altitude [default: the "
              "demo's]; 0 0: config/onboard.yaml's.")  # fmt: skip
@click.option("--set-onboard", "onboard_sets", multiple=True, metavar="KEY=VALUE",
              help="Override a flight-service setting of every drone, as the demo's option of "
              "that name (repeatable); the fast-time flight takes its planner and replan "
              "period too.")  # fmt: skip
@click.option("--lead", "lead_s", type=click.FloatRange(0.0, DEMO_LEAD_MAX_S),
              default=DEMO_LEAD_S, show_default=True,
              help="Seconds from a command to the drones' common switch, as the demo's "
              "option.")  # fmt: skip
@click.option("--no-fastsim", is_flag=True, help="Fly only the real stack.")
@click.option("--fastsim-only", is_flag=True,
              help="Fly only the fast-time twins (minutes instead of hours; not issue #10's "
              "figure, which is the real stack's).")  # fmt: skip
@click.option("--jobs", type=click.IntRange(1, 64), default=1, show_default=True,
              help="With --fastsim-only: twins flown in parallel processes (each demo takes "
              "the whole machine, so the real stack flies one at a time).")  # fmt: skip
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None,
              help="Flight directories go here [default: flights/bench-demo-TIME].")  # fmt: skip
@click.option("--timeout", "timeout_s", type=float, default=900.0, show_default=True,
              help="Seconds one demo may take before it is interrupted.")  # fmt: skip
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write JSON.")  # fmt: skip
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_demo(
    seeds: int, first_seed: int, drones: int, formation: str, world: str, change: str | None,
    depth_rate: float | None, altitude_band: tuple[float, float] | None,
    onboard_sets: tuple[str, ...], lead_s: float, no_fastsim: bool, fastsim_only: bool,
    jobs: int,
    out_dir: Path | None, timeout_s: float, json_path: Path | None, quiet: bool,
) -> None:  # fmt: skip
    """The end-to-end demo over seeds (1..N by default), each beside the fast-time simulator
    on the same world (issue #10: 5 of 5 seeds; with a formation change, the new shape within
    10 s)."""
    from rich.console import Console
    from rich.table import Table

    from gcs.demo import (
        DemoConfig,
        DemoError,
        default_band,
        default_depth_rate,
        demo_templates,
        parse_change,
        planner_z_limits,
    )
    from onboard.config import ConfigError, load_world_spec, parse_overrides
    from onboard.service.config import load_onboard_config

    # a wide table when written to a file or a pipe (rich's default there is 80 columns)
    console = Console(quiet=quiet, highlight=False, width=None if sys.stdout.isatty() else 180)
    if no_fastsim and fastsim_only:
        raise click.UsageError("--no-fastsim and --fastsim-only exclude each other")
    if jobs > 1 and not fastsim_only:
        raise click.BadParameter(
            "more than one job needs --fastsim-only: a demo takes the whole machine",
            param_hint="--jobs",
        )
    try:
        fc = parse_change(change)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--formation-change") from e
    try:
        demo_templates(drones, formation, fc)  # the demo's own check, before the first seed
        overrides = parse_overrides(onboard_sets)
        service = load_onboard_config(None, drone_id=0, overrides=overrides)
    except (DemoError, ConfigError) as e:
        raise click.ClickException(str(e)) from e
    demo_cfg = DemoConfig(drones=drones, depth_rate_hz=depth_rate, altitude_band_m=altitude_band)
    rate = default_depth_rate(demo_cfg)
    planner = service.planner
    try:
        band = default_band(demo_cfg)
        z_limits = planner_z_limits(demo_cfg, load_world_spec(world))
        if z_limits is not None:  # the demo's band, for the fast-time flights too
            planner = dataclasses.replace(planner, z_limits_m=z_limits)
    except (DemoError, ConfigError, ValueError) as e:
        raise click.ClickException(str(e)) from e
    step = int(service.depth.step)
    base = (
        out_dir
        if out_dir is not None
        else Path("flights") / time.strftime("bench-demo-%Y%m%d-%H%M%S")
    )
    if not fastsim_only:
        base.mkdir(parents=True, exist_ok=True)
    argv = ["--drones", str(drones), "--formation", formation, "--world", world]
    argv += ["--depth-rate", str(rate)]
    argv += ["--altitude-band", *(str(x) for x in (band if band is not None else (0, 0)))]
    if change is not None:
        argv += ["--formation-change", change]
    for s_ in onboard_sets:
        argv += ["--set-onboard", s_]
    argv += ["--lead", str(lead_s)]
    replan_s = float(service.planning.replan_period_s)
    load0 = os.getloadavg()
    seed_list = list(range(first_seed, first_seed + seeds))
    # the map's parameters set on the command line (as the service read them) reach the twins'
    occ = service.mapping.occupancy
    occ_keys = sorted(overrides.get("mapping", {}).get("occupancy", {}))
    occ_over = tuple((str(k), getattr(occ, k)) for k in occ_keys)
    twin_args = [(seed, formation, world, fc, rate, step, planner, replan_s, occ_over)
                 for seed in seed_list]  # fmt: skip
    rows: list[dict[str, Any]] = []
    if fastsim_only:
        console.print(f"{seeds} fast-time flights, {jobs} at a time ...")
        twins = fly_twins(twin_args, jobs)
        rows = [{"seed": sd, "demo": None, "fastsim": tw}
                for sd, tw in zip(seed_list, twins, strict=True)]  # fmt: skip
    else:
        for seed, args in zip(seed_list, twin_args, strict=True):
            console.print(f"seed {seed}: demo ...")
            d = run_demo_seed(seed, argv, base / f"seed-{seed}", timeout_s)
            row: dict[str, Any] = {"seed": seed, "demo": _demo_row(d), "fastsim": None}
            hc = d.get("host_cpu") or {}
            console.print(
                f"seed {seed}: the host's CPU busy {_fmt(_pct(hc.get('busy')), '.0f')} %, "
                f"stolen by the hypervisor {_fmt(_pct(hc.get('steal')), '.1f')} %"
            )
            if not no_fastsim:
                console.print(f"seed {seed}: fast-time flight ...")
                row["fastsim"] = _fastsim_job(args)
            rows.append(row)
    report: dict[str, Any] = {
        "benchmark": "demo",
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "config": {
            "drones": drones,
            "formation": formation,
            "world": world,
            "formation_change": change,
            "seeds": seed_list,
            "real_stack": not fastsim_only,
            "depth_rate_hz": rate,
            "depth_step": step,
            "v_max_m_s": planner.v_max_m_s,
            "altitude_band_m": list(planner.z_limits_m),
            "replan_period_s": replan_s,
            "onboard_sets": list(onboard_sets),
            # the real stack's command-to-switch lead (the twins switch at the change itself)
            "lead_s": None if fastsim_only else lead_s,
            "fastsim_perception": None if no_fastsim else "mapped",
        },
        "rows": rows,
        "summary": summarise(rows, fc is not None),
        "load_average": {"start": list(load0), "end": list(os.getloadavg())},
        "host": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "out_dir": None if fastsim_only else str(base),
    }
    t = Table(title=f"{formation} ({drones} drones) through {world}"
              + (f", change to {change}" if change else ""))  # fmt: skip
    cols = ["seed", "run", "result", "wall s", "flight s", "e_dist m", "e_sim",
            "clear. centre / body m", "min pair m"]  # fmt: skip
    if fc is not None:
        cols.append("new shape after s (command / switch)")
    cols += ["plans med ms", "brakes / depth holds", "depth frames / skipped"]
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        for side in ("demo", "fastsim"):
            g = r[side]
            if g is None:
                continue
            ok = "[green]success[/green]" if g["success"] else "[red]failed[/red]"
            cells = [
                str(r["seed"]) if side == "demo" or r["demo"] is None else "",
                "real stack" if side == "demo" else "fast time",
                ok,
                _fmt(g.get("wall_s", g.get("sim_wall_s")), ".0f"),
                _fmt(g.get("flight_time_s"), ".1f"),
                _fmt(g.get("e_dist_m"), ".3f"),
                _fmt(g.get("e_sim"), ".4f"),
                f"{_fmt(g.get('min_obstacle_clearance_centre_m'), '.3f')} / "
                f"{_fmt(g.get('min_obstacle_clearance_body_m'), '.3f')}",
                _fmt(g.get("min_drone_distance_m")),
            ]
            if fc is not None:
                cells.append(
                    f"{_fmt(g.get('formation_change_reached_s'), '.1f')} / "
                    f"{_fmt(g.get('formation_change_reached_after_switch_s'), '.1f')}"
                )
            cells += [
                _fmt(g.get("plan_ms_median", g.get("replan_ms_median")), ".1f"),
                f"{_fmt(g.get('monitor_brakes'), 'd')} / {_fmt(g.get('depth_holds'), 'd')}"
                if side == "demo"
                else "",
                f"{g.get('depth_frames', '-')} / {g.get('depth_frames_skipped', '-')}"
                if side == "demo"
                else "",
            ]
            t.add_row(*cells)
    console.print(t)
    s = report["summary"]
    parts = []
    for side, name, flown in (("demo", "real stack", not fastsim_only),
                              ("fastsim", "fast time", not no_fastsim)):  # fmt: skip
        if not flown:
            continue
        part = f"{name}: {s[side]['success']} of {seeds} seeds succeeded"
        if fc is not None:
            part += (
                f", {s[side]['reached_within_10_s']} reached the new shape within 10 s "
                f"({s[side]['reached_within_10_s_of_the_switch']} within 10 s of the switch)"
            )
        parts.append(part)
    console.print("; ".join(parts))
    console.print(
        f"e_sim: mean over the cluttered span; new shape: e_sim < {FORMATION_REACHED_E_SIM}"
    )
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        console.print(f"wrote {json_path}")
