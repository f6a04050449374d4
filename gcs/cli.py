"""``swarm-gcs``: ground-side tools — fast-time swarm simulation and planner benchmark."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from gcs.bench_mapping import perception_options, perception_overrides
from onboard.agent import REPLAN_PERIOD_S
from onboard.config import (
    ConfigError,
    load_formation,
    load_planner_params,
    load_scenario,
    load_world_spec,
    parse_override,
    parse_overrides,
)

if TYPE_CHECKING:
    from gcs.fastsim import SimConfig, SimResult
    from onboard.planner.params import PlannerParams


def _console(quiet: bool) -> Console:
    return Console(quiet=quiet, highlight=False)


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def _planner_params(
    planner_file: Path | None, sets: Sequence[str], v_max: float | None = None
) -> PlannerParams:
    """The planner parameters: the file, then ``--set`` overrides, then ``--v-max`` (shorthand
    for ``--set v_max_m_s=``; both with different values is an error)."""
    overrides = parse_overrides(sets)
    if v_max is not None:
        given = overrides.get("v_max_m_s")
        if given is not None and given != v_max:
            raise ConfigError(
                f"--v-max {v_max} and --set v_max_m_s={given} disagree: give the speed limit once"
            )
        overrides["v_max_m_s"] = v_max
    return load_planner_params(planner_file, **overrides)


def _sets_v_max(sets: Sequence[str]) -> bool:
    """Does one of the ``--set`` overrides give the speed limit?"""
    return any("v_max_m_s" in parse_override(s) for s in sets)


@contextmanager
def _sim_progress(console: Console, label: str) -> Iterator[Any]:
    """A rich progress bar over simulated time; yields the callback run_sim wants."""
    if console.quiet:
        yield None
        return
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:6.1f} / {task.total:.0f} s simulated"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=1.0)

        def update(t_s: float, limit_s: float) -> None:
            bar.update(task, completed=t_s, total=limit_s)

        yield update


def _flight_counter(console: Console) -> Progress:
    """A progress bar that counts finished flights (N / total, elapsed time)."""
    return Progress(
        TextColumn("flights"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )


def _fmt(x: float | None, spec: str = ".3f") -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return format(x, spec)


def _sim_table(r: SimResult) -> Table:
    t = Table(title=f"{r.formation_name} through {r.world_name}, seed {r.seed}", show_header=False)
    t.add_column("metric", style="bold")
    t.add_column("value")
    arrived = int(np.sum(r.arrived))
    ok = "[green]yes[/green]" if r.success else "[red]no[/red]"
    t.add_row("success", ok)
    t.add_row("arrived", f"{arrived} / {r.arrived.shape[0]}" + (" (timed out)" * r.timed_out))
    t.add_row(
        "collisions",
        f"{r.collisions} (obstacle {r.obstacle_collisions}, drone {r.drone_collisions})",
    )
    t.add_row("min obstacle clearance", f"{_fmt(r.min_obstacle_clearance_m)} m")
    t.add_row("min drone distance", f"{_fmt(r.min_drone_distance_m)} m")
    t.add_row("max speed", f"{_fmt(r.max_speed_m_s, '.2f')} m/s")
    z = r.tracks.pos[:, :, 2]
    if z.size:
        spread = r.tracks.z_spread_max()
        t.add_row("altitude", f"{z.min():.2f} to {z.max():.2f} m (spread at most {spread:.2f} m)")
    t.add_row(
        "e_sim mean / max",
        f"{_fmt(r.e_sim_mean, '.4f')} / {_fmt(r.e_sim_max, '.4f')}"
        f"  (cluttered {_fmt(r.e_sim_mean_cluttered, '.4f')})",
    )
    t.add_row("e_dist mean / max", f"{_fmt(r.e_dist_mean)} / {_fmt(r.e_dist_max)} m")
    t.add_row("flight time", f"{_fmt(r.flight_time_s, '.1f')} s")
    fc = r.formation_change
    if fc:
        reached = fc["reached_s"]
        t.add_row(
            "formation change",
            f"to {fc['name']} at {fc['at_s']:.1f} s, "
            + ("never reached" if reached is None else f"reached after {reached:.1f} s")
            + " (e_sim < 0.01)",
        )
    rm = r.replan_ms
    t.add_row(
        "replan ms median / p90 / max",
        f"{_fmt(rm['median'], '.2f')} / {_fmt(rm['p90'], '.2f')} / {_fmt(rm['max'], '.2f')}"
        f"  ({rm['count']} replans)",
    )
    it = r.iterations
    t.add_row(
        "iterations median / p90 / max",
        f"{_fmt(it['median'], '.0f')} / {_fmt(it['p90'], '.0f')} / {_fmt(it['max'], '.0f')}",
    )
    t.add_row("plan status", ", ".join(f"{k} {v}" for k, v in sorted(r.status_counts.items())))
    t.add_row("wall time", f"{_fmt(r.sim_wall_s, '.1f')} s (planner warm-up {r.warmup_s:.1f} s)")
    return t


def _radio_outages(specs: Sequence[str]) -> dict[int, tuple[float, float]]:
    """``--radio-outage DRONE@FROM-TO`` values (one span per drone)."""
    out: dict[int, tuple[float, float]] = {}
    for spec in specs:
        drone, sep, span = spec.partition("@")
        a, dash, b = span.partition("-")
        try:
            i, t0, t1 = int(drone), float(a), float(b)
        except ValueError:
            raise ValueError(f"expected DRONE@FROM-TO (e.g. 2@20-27.5), got {spec!r}") from None
        if not (sep and dash):
            raise ValueError(f"expected DRONE@FROM-TO (e.g. 2@20-27.5), got {spec!r}")
        if i in out:
            raise ValueError(f"drone {i} is given two outages")
        out[i] = (t0, t1)
    return out


def _sim_config(
    formation: str,
    world: str,
    seed: int,
    params: PlannerParams,
    time_limit: float | None = None,
    silent: Sequence[int] = (),
) -> SimConfig:
    from gcs.fastsim import SimConfig

    f = load_formation(formation)
    w = load_world_spec(world)
    bad = [i for i in silent if not 0 <= i < f.n]
    if bad:
        raise ConfigError(f"--silent: drones {bad} are not in the {f.n}-drone formation")
    return SimConfig(
        formation=f,
        world=w,
        seed=seed,
        planner=params,
        time_limit_s=time_limit,
        silent_drones=tuple(silent),
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Ground-side tools of the swarm formation system."""


_formation_opt = click.option(
    "--formation",
    default="hexagon-7",
    show_default=True,
    help="Formation name (config/formations) or YAML/JSON file.",
)
_world_opt = click.option(
    "--world",
    default="forest-medium",
    show_default=True,
    help="World name (config/worlds) or YAML/JSON file.",
)
_seed_opt = click.option("--seed", default=1, show_default=True, help="Seed of the world.")
_start_z_jitter_opt = click.option(
    "--start-z-jitter",
    "start_z_jitter",
    type=click.FloatRange(0.0, 0.5),
    default=0.0,
    show_default=True,
    help="Every drone starts up to this far [m] above or below its start altitude (seeded): "
    "exactly level starts hide a formation that tilts.",
)
_replan_period_opt = click.option(
    "--replan-period",
    "replan_period",
    type=click.FloatRange(0.1, 10.0),
    default=REPLAN_PERIOD_S,
    show_default=True,
    help="Seconds between a drone's replans (the flight service's planning.replan_period_s).",
)
_vmax_opt = click.option(
    "--v-max",
    "v_max",
    default=None,
    type=float,
    help="Speed limit [m/s], shorthand for --set v_max_m_s=V [default: the planner's, 0.5].",
)
_planner_opt = click.option(
    "--planner",
    "planner_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Planner parameter file (default config/planner.yaml).",
)
_set_opt = click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a planner parameter, e.g. --set w_formation=1e6 (repeatable).",
)


@main.command()
@_formation_opt
@_world_opt
@click.option(
    "--scenario",
    default=None,
    help="A named scenario (config/scenarios: tetrahedron-corridor, heart-forest) or file; it "
    "sets the formation, world and speed unless those are given too.",
)
@_seed_opt
@_vmax_opt
@_planner_opt
@_set_opt
@click.option("--time-limit", type=float, default=None, help="Simulated seconds [default: auto].")
@click.option(
    "--silent",
    type=int,
    multiple=True,
    help="Drone whose broadcasts are lost (repeatable): a failed radio.",
)
@click.option(
    "--radio-outage",
    "outages",
    multiple=True,
    metavar="DRONE@FROM-TO",
    help="Drone whose uplink is out from FROM to TO simulated seconds (repeatable): nothing it "
    "sends then reaches anyone, it still hears its peers.",
)
@click.option(
    "--formation-change",
    "change",
    default=None,
    metavar="NAME@SECONDS",
    help="Change to this formation (name or file) at this simulated time; slots by minimum "
    "total distance, as the ground station assigns them.",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option(
    "--tracks",
    "tracks_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the flown positions at 10 Hz as .npz: t (T,), pos (T, N, 3), goals, formation.",
)
@click.option(
    "--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), help="Write a PNG."
)
@click.option("--check", is_flag=True, help="Exit with status 1 unless the flight succeeded.")
@perception_options
@_start_z_jitter_opt
@_replan_period_opt
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def sim(
    formation: str,
    world: str,
    scenario: str | None,
    seed: int,
    v_max: float | None,
    planner_file: Path | None,
    sets: tuple[str, ...],
    time_limit: float | None,
    silent: tuple[int, ...],
    outages: tuple[str, ...],
    change: str | None,
    json_path: Path | None,
    tracks_path: Path | None,
    plot_path: Path | None,
    check: bool,
    perception: str,
    camera_rate_hz: float,
    camera_skip_pixel: int,
    start_z_jitter: float,
    replan_period: float,
    quiet: bool,
) -> None:
    """Fly a formation through a world in fast simulated time and score the flight."""
    from gcs.fastsim import run_sim

    console = _console(quiet)
    try:
        params = _planner_params(planner_file, sets, v_max)
        cfg = _sim_config(formation, world, seed, params, time_limit, silent)
        if scenario is not None:
            sc = load_scenario(scenario)
            ctx = click.get_current_context()

            def given(name: str) -> bool:
                return ctx.get_parameter_source(name) == click.core.ParameterSource.COMMANDLINE

            cfg = dataclasses.replace(
                cfg,
                formation=cfg.formation if given("formation") else sc.formation,
                world=cfg.world if given("world") else sc.world,
            )
            if v_max is None and not _sets_v_max(sets):  # the scenario's speed, unless given
                cfg = cfg.with_v_max(sc.v_max_m_s)
        cfg = dataclasses.replace(
            cfg,
            start_z_jitter_m=start_z_jitter,
            replan_period_s=replan_period,
            **perception_overrides(perception, camera_rate_hz, camera_skip_pixel),
        )
        if outages:
            try:
                cfg = dataclasses.replace(cfg, radio_outages=_radio_outages(outages))
            except ValueError as e:
                raise click.BadParameter(str(e), param_hint="--radio-outage") from e
        if change is not None:
            cfg = dataclasses.replace(cfg, formation_change=_formation_change(change))
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--formation-change") from e
    try:
        with _sim_progress(console, f"{cfg.formation.name} / {cfg.world.name}") as cb:
            result = run_sim(cfg, progress=cb)
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    console.print(_sim_table(result))
    for ev in result.events:
        console.print(
            f"  collision t={ev.t_s:.2f} s {ev.kind} {list(ev.ids)} at {ev.distance_m:.3f} m"
        )
    if json_path is not None:
        _write_json(json_path, result.to_json())
        console.print(f"wrote {json_path}")
    if tracks_path is not None:
        tracks_path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            tracks_path,
            t=result.tracks.t,
            pos=result.tracks.pos,
            goals=result.goals,
            formation=cfg.formation.points,
            starts=result.starts,
            e_sim=result.tracks.e_sim,
        )
        console.print(f"wrote {tracks_path}")
    if plot_path is not None:
        from gcs.plots import plot_top_view

        plot_top_view(result, plot_path)
        console.print(f"wrote {plot_path}")
    if check and not result.success:
        raise SystemExit(1)


def _formation_change(text: str) -> tuple[Any, float]:
    """``NAME@SECONDS`` -> (the formation, the time); ``ValueError`` or ``ConfigError``."""
    from gcs.demo import parse_change

    parsed = parse_change(text)
    if parsed is None:
        raise ValueError("expected NAME@SECONDS, e.g. arrow-7@20")
    return load_formation(parsed[0]), parsed[1]


@main.group()
def world() -> None:
    """World files: export a seeded built-in world as an explicit file."""


@world.command("export")
@_world_opt
@_formation_opt
@_seed_opt
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
def world_export(world: str, formation: str, seed: int, out: Path) -> None:
    """Write the world of --world/--seed/--formation as an explicit YAML (or .json) world file
    that `sim --world FILE` and `bench table --world FILE` (or any other tool) can fly."""
    import yaml

    from onboard.config import world_file

    try:
        spec = load_world_spec(world)
        form = load_formation(formation)
        built, starts, goals = spec.build(seed, form)
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    data = world_file(
        built, spec, starts, goals, f"{spec.name} seed {seed} for {form.name}: {spec.description}"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".json":
        out.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    else:
        out.write_text(yaml.safe_dump(data, sort_keys=False, width=100), encoding="utf-8")
    click.echo(
        f"wrote {out}: {built.cylinders.shape[0]} cylinders, {built.rings.shape[0]} rings, "
        f"{built.boxes.shape[0]} boxes, {form.n} starts and goals"
    )


@main.group()
def bench() -> None:
    """Benchmarks: print a table and write JSON to compare run to run."""


@bench.command("flights")
@_formation_opt
@_world_opt
@click.option("--seeds", default=10, show_default=True, help="Flights (one world each).")
@click.option(
    "--first-seed",
    default=1,
    show_default=True,
    type=click.IntRange(min=0),
    help="Seed of the first flight (seeds S..S+N-1).",
)
@click.option(
    "--jobs",
    default=1,
    show_default=True,
    type=click.IntRange(min=1),
    help="Flights run in parallel processes (fast time: the figures do not depend on it).",
)
@_vmax_opt
@_planner_opt
@_set_opt
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@perception_options
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_flights(
    formation: str,
    world: str,
    seeds: int,
    first_seed: int,
    jobs: int,
    v_max: float | None,
    planner_file: Path | None,
    sets: tuple[str, ...],
    json_path: Path | None,
    perception: str,
    camera_rate_hz: float,
    camera_skip_pixel: int,
    quiet: bool,
) -> None:
    """Fly one scenario over seeds 1..N (or S..S+N-1) and report success, collisions and
    clearances."""
    from gcs.metrics import summary

    console = _console(quiet)
    if seeds < 1:
        raise click.BadParameter("must be >= 1", param_hint="--seeds")
    try:
        params = _planner_params(planner_file, sets, v_max)
        extra = perception_overrides(perception, camera_rate_hz, camera_skip_pixel)
        cfgs = [
            dataclasses.replace(_sim_config(formation, world, s, params), **extra)
            for s in range(first_seed, first_seed + seeds)
        ]
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    rows: list[dict[str, Any]] = []
    with _flight_counter(console) as bar:
        task = bar.add_task("flights", total=len(cfgs))
        try:
            if jobs == 1:
                for cfg in cfgs:
                    rows.append(_flight_row(cfg))
                    bar.advance(task)
            else:
                from gcs.pools import sigterm_interrupts

                # a Pool, not an executor: leaving it on Ctrl-C or SIGTERM terminates the
                # workers (an executor waits for their flights, minutes each when mapped)
                ctx = multiprocessing.get_context("spawn")
                with sigterm_interrupts(), ctx.Pool(jobs) as pool:
                    for row in pool.imap(_flight_row, cfgs):  # in the seeds' order
                        rows.append(row)
                        bar.advance(task)
        except ConfigError as e:
            raise click.ClickException(str(e)) from e
    v_max_m_s = params.v_max_m_s
    last = first_seed + seeds - 1
    t = Table(
        title=f"{formation} through {world}, v_max {v_max_m_s} m/s, seeds {first_seed}..{last}"
    )
    for col in ("seed", "success", "collisions", "min obst. m", "min drone m", "e_sim", "time s"):
        t.add_column(col, justify="right")
    for row in rows:
        t.add_row(
            str(row["seed"]),
            "yes" if row["success"] else "NO",
            str(row["collisions"]),
            _fmt(row["min_obstacle_clearance_m"]),
            _fmt(row["min_drone_distance_m"]),
            _fmt(row["e_sim_mean"], ".4f"),
            _fmt(row["flight_time_s"], ".1f"),
        )
    console.print(t)
    n_ok = sum(1 for row in rows if row["success"])
    n_clean = sum(1 for row in rows if row["collisions"] == 0)
    report = {
        "formation": formation,
        "world": world,
        "v_max_m_s": v_max_m_s,
        "seeds": seeds,
        "first_seed": first_seed,
        "jobs": jobs,
        "success_count": n_ok,
        "collision_free_count": n_clean,
        "min_obstacle_clearance_m": min(row["min_obstacle_clearance_m"] for row in rows),
        "min_drone_distance_m": min(row["min_drone_distance_m"] for row in rows),
        "max_speed_m_s": max(row["max_speed_m_s"] for row in rows),
        "e_sim_mean": summary([row["e_sim_mean"] for row in rows]),
        "replan_ms_median": summary([row["replan_ms"]["median"] for row in rows]),
        "flights": rows,
    }
    console.print(
        f"success {n_ok}/{seeds}, collision-free {n_clean}/{seeds}, "
        f"min obstacle clearance {report['min_obstacle_clearance_m']:.3f} m, "
        f"min drone distance {report['min_drone_distance_m']:.3f} m, "
        f"max speed {report['max_speed_m_s']:.2f} m/s"
    )
    if json_path is not None:
        _write_json(json_path, report)
        console.print(f"wrote {json_path}")


def _flight_row(cfg: Any) -> dict[str, Any]:
    """One fast-time flight of ``bench flights`` (a module-level function: run in a worker
    process with ``--jobs``): its seed and the figures of ``_FLIGHT_KEYS``."""
    from gcs.fastsim import run_sim

    d = run_sim(cfg).to_json()
    return {"seed": cfg.seed, **{k: d[k] for k in _FLIGHT_KEYS if k in d}}


_FLIGHT_KEYS = (
    "success",
    "collisions",
    "min_obstacle_clearance_m",
    "min_drone_distance_m",
    "max_speed_m_s",
    "e_sim_mean",
    "flight_time_s",
    "replan_ms",
    "status_counts",
    "refusals",
)


@bench.command("table")
@click.option("--trials", default=20, show_default=True, help="Trials (worlds) per density.")
@click.option("--seed", default=1, show_default=True, help="Trial k flies the world of seed+k.")
@click.option(
    "--density",
    type=click.Choice(["sparse", "medium", "dense", "all"]),
    default="all",
    show_default=True,
)
@click.option(
    "--method",
    type=click.Choice(["ours", "turpin", "zhou", "all"]),
    default="all",
    show_default=True,
)
@click.option(
    "--world",
    "world_override",
    default=None,
    help="A world name or YAML/JSON file to use instead of the density worlds.",
)
@_formation_opt
@_vmax_opt
@_planner_opt
@_set_opt
@click.option("--jobs", default=1, show_default=True, help="Flights run in parallel processes.")
@_start_z_jitter_opt
@_replan_period_opt
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option(
    "--plots",
    "plots_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Write PNG plots (top views, formation snapshots, e_sim over time) here.",
)
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_table(
    trials: int,
    seed: int,
    density: str,
    method: str,
    world_override: str | None,
    formation: str,
    v_max: float | None,
    planner_file: Path | None,
    sets: tuple[str, ...],
    jobs: int,
    start_z_jitter: float,
    replan_period: float,
    json_path: Path | None,
    plots_dir: Path | None,
    quiet: bool,
) -> None:
    """Reproduce the paper's Table I: ours vs Turpin 2012 vs Zhou 2018 on seeded worlds."""
    from gcs.table import DENSITIES, METHOD_LABELS, METHODS, run_table

    console = _console(quiet)
    if trials < 1:
        raise click.BadParameter("must be >= 1", param_hint="--trials")
    try:
        params = _planner_params(planner_file, sets, v_max)
        form = load_formation(formation)
        if world_override is not None:
            spec = load_world_spec(world_override)
            worlds = [(spec.name, spec)]
        else:
            names = DENSITIES if density == "all" else (density,)
            worlds = [(d, load_world_spec(f"forest-{d}")) for d in names]
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    methods = METHODS if method == "all" else (method,)
    total = len(worlds) * len(methods) * trials
    with _flight_counter(console) as bar:
        task = bar.add_task("flights", total=total)
        try:
            report, kept = run_table(
                form,
                worlds,
                methods,
                trials,
                seed,
                params,
                jobs,
                progress=lambda done, _n: bar.update(task, completed=done),
                start_z_jitter_m=start_z_jitter,
                replan_period_s=replan_period,
            )
        except (ConfigError, ValueError) as e:
            raise click.ClickException(str(e)) from e

    t = Table(
        title=f"{form.name}, {trials} trials per cell, v_max {params.v_max_m_s} m/s "
        "(paper in brackets)"
    )
    cols = ("scenario", "method", "success %", "e_dist (m)", "e_sim", "min obst. m", "z spread m")
    for col in (*cols, "time s"):
        t.add_column(col, justify="right" if col not in ("scenario", "method") else "left")

    def pv(x: float | None, spec: str) -> str:
        return "-" if x is None else format(x, spec)

    for row in report["summary"]:
        p = row["paper"] or {}
        paper_s = f" ({p['success_rate'] * 100:.0f})" if p else ""
        paper_d = f" ({pv(p.get('e_dist'), '.2f')})" if p else ""
        paper_e = f" ({pv(p.get('e_sim'), '.4f')})" if p else ""
        t.add_row(
            row["density"],
            METHOD_LABELS.get(row["method"], row["method"]),
            f"{row['success_rate'] * 100:.0f}{paper_s}",
            f"{pv(row['e_dist'], '.2f')}{paper_d}",
            f"{pv(row['e_sim'], '.4f')}{paper_e}",
            _fmt(row["min_obstacle_clearance_m"], ".2f"),
            _fmt(row["z_spread_max_m"], ".2f"),
            pv(row["flight_time_s"], ".1f"),
        )
    console.print(t)
    console.print(
        f"{total} flights in {report['wall_s'] / 60:.1f} min ({jobs} job(s)); e_dist and e_sim "
        "over successful trials, inside the cluttered span"
    )
    if json_path is not None:
        _write_json(json_path, report)
        console.print(f"wrote {json_path}")
    if plots_dir is not None:
        from gcs.plots import plot_esim, plot_snapshots, plot_top_view

        for label, _spec in worlds:
            per_method = {m: kept[(label, m)] for m in methods if (label, m) in kept}
            for m, res in per_method.items():
                plot_top_view(
                    res,
                    plots_dir / f"top_{label}_{m}.png",
                    title=f"{label}, {METHOD_LABELS[m]}, seed {res.seed}: "
                    f"{'success' if res.success else 'FAILED'}",
                )
                plot_snapshots(
                    res,
                    plots_dir / f"snapshots_{label}_{m}.png",
                    title=f"formation snapshots: {label}, {METHOD_LABELS[m]}",
                )
            plot_esim(
                {METHOD_LABELS[m]: r for m, r in per_method.items()},
                plots_dir / f"esim_{label}.png",
                title=f"e_sim over time, {label}, trial 0",
            )
        console.print(f"wrote plots to {plots_dir}")


@bench.command("planner")
@_formation_opt
@_world_opt
@_seed_opt
@_vmax_opt
@_planner_opt
@_set_opt
@click.option("--repeats", default=5, show_default=True, help="Timed solves per problem.")
@click.option(
    "--skip-s",
    default=5.0,
    show_default=True,
    help="Use replans starting after this simulated time (peers known).",
)
@click.option(
    "--max-problems",
    default=300,
    show_default=True,
    help="Replay at most this many recorded replans (evenly spread; 0 = all).",
)
@click.option(
    "--eval-calls",
    default=200,
    show_default=True,
    help="Objective evaluations timed per problem for eval_us.",
)
@click.option(
    "--startup/--no-startup",
    default=True,
    show_default=True,
    help="Measure a fresh process's import + first plan.",
)
@click.option(
    "--side-thread/--no-side-thread",
    default=True,
    show_default=True,
    help="Solve the fresh start beside the warm one, which runs on a second thread, as the "
    "flight service does (planning.side_thread).",
)
@click.option(
    "--term-costs",
    is_flag=True,
    help="Also time one evaluation with each cost term off: where its microseconds go.",
)
@click.option(
    "--time-limit",
    type=float,
    default=None,
    help="Simulated seconds of the recorded flight [default: auto].",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@perception_options
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_planner(
    formation: str,
    world: str,
    seed: int,
    v_max: float | None,
    planner_file: Path | None,
    sets: tuple[str, ...],
    repeats: int,
    skip_s: float,
    max_problems: int,
    eval_calls: int,
    startup: bool,
    side_thread: bool,
    term_costs: bool,
    time_limit: float | None,
    json_path: Path | None,
    perception: str,
    camera_rate_hz: float,
    camera_skip_pixel: int,
    quiet: bool,
) -> None:
    """Replay the replans of a recorded flight and time the planner.

    Records a seeded flight, keeps the replans made after --skip-s with all peers known, and
    times each one's prepare() + solve() --repeats times after one untimed warm-up run
    (medians per problem), plus the full plan() call and one objective evaluation. With
    --perception mapped each replan is replayed on the ESDF its drone planned on (at most
    --max-problems, 100 when 0: each keeps its field, about 5 MB).
    """
    from gcs import bench as gb

    if repeats < 1:
        raise click.BadParameter("must be >= 1", param_hint="--repeats")
    console = _console(quiet)
    try:
        params = _planner_params(planner_file, sets, v_max)
        cfg = dataclasses.replace(
            _sim_config(formation, world, seed, params, time_limit),
            **perception_overrides(perception, camera_rate_hz, camera_skip_pixel),
        )
    except ConfigError as e:
        raise click.ClickException(str(e)) from e

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=quiet,
    ) as bar:
        sim_task = bar.add_task("recording flight [s]", total=None)
        replay_task = bar.add_task("replaying replans", total=None, visible=False)

        def sim_cb(t_s: float, limit_s: float) -> None:
            bar.update(sim_task, completed=t_s, total=limit_s)

        def replay_cb(done: int, total: int) -> None:
            bar.update(sim_task, visible=False)
            bar.update(replay_task, completed=done, total=total, visible=True)

        try:
            report = gb.bench_planner(
                cfg,
                repeats=repeats,
                skip_s=skip_s,
                max_problems=max_problems,
                eval_calls=eval_calls,
                startup=startup,
                sim_progress=sim_cb,
                replay_progress=replay_cb,
                side_thread=side_thread,
                term_costs=term_costs,
            )
        except (RuntimeError, ConfigError) as e:
            raise click.ClickException(str(e)) from e

    t = Table(
        title=f"planner benchmark: {report['problems']} replans x {repeats} on the "
        f"{'ESDF the drones built' if perception == 'mapped' else 'exact field'}"
    )
    t.add_column("quantity")
    t.add_column("median", justify="right")
    t.add_column("p90", justify="right")
    t.add_column("max", justify="right")
    for name, key in (
        ("replan, whole plan() (ms)", "replan_ms"),
        ("  of which solve (ms)", "solve_ms"),
        ("iterations", "iterations"),
        ("evaluations", "evaluations"),
    ):
        s = report[key]
        t.add_row(name, _fmt(s["median"], ".2f"), _fmt(s["p90"], ".2f"), _fmt(s["max"], ".2f"))
    console.print(t)
    b = report["breakdown"]
    console.print(
        f"median replan = set-up {_fmt(b['setup_ms_median'], '.2f')} ms + solve "
        f"{_fmt(b['solve_ms_median'], '.2f')} ms (cost evaluations "
        f"{_fmt(b['cost_eval_ms_median'], '.2f')} ms at {_fmt(report['eval_us'], '.1f')} us "
        f"each, solver {_fmt(b['solver_overhead_ms_median'], '.2f')} ms) + the rest "
        f"{_fmt(b['check_and_rest_ms_median'], '.2f')} ms (checks, the fresh start, result); "
        f"pieces median {_fmt(report['pieces']['median'], '.0f')}"
    )
    fr = report["fresh_ms"]
    if fr["solve"] is not None:
        console.print(
            f"the fresh start, in {report['fresh_share']:.0%} of the replans: set-up "
            f"{_fmt(fr['setup_median'], '.2f')} ms + solve {_fmt(fr['solve']['median'], '.2f')} "
            f"ms median (p90 {_fmt(fr['solve']['p90'], '.2f')}; "
            f"{_fmt(fr['evaluations_median'], '.0f')} evaluations), "
            + (
                "beside the warm start's solve and check (side thread): the longer of the two "
                "sets the replan"
                if side_thread
                else "after the warm solve"
            )
        )
        fc = report["fresh_cheaper"]
        if fc["gain_pct"] is not None:
            g = fc["gain_pct"]
            console.print(
                f"its solution costs less than the warm start's in {fc['share']:.0%} of them, by "
                f"{_fmt(g['median'], '.2f')} % median (p90 {_fmt(g['p90'], '.1f')} %, max "
                f"{_fmt(g['max'], '.1f')} %); more than 5 % in {fc['over_5pct']}"
            )
    if "eval_us_by_term" in report:
        by = report["eval_us_by_term"]
        console.print(
            "one evaluation at the solution, median us: "
            + ", ".join(f"{k} {_fmt(v, '.1f')}" for k, v in by.items())
        )
    console.print(
        f"solver statuses: {report['solver_status_counts']}; "
        f"plan statuses: {report['plan_status_counts']}"
    )
    if report["startup_s"] is not None:
        st = report["startup"]
        console.print(
            f"fresh process: import + first plan {st['startup_s']:.2f} s "
            f"(import {st['import_s']:.2f} s, first plan {st['first_plan_ms']:.1f} ms)"
        )
    m = report["machine"]
    console.print(f"{m['cpu']} x{m['cpu_count']}, Python {m['python']}, numba {m['numba']}")
    if json_path is not None:
        _write_json(json_path, report)
        console.print(f"wrote {json_path}")


def _register_bench_plugins() -> None:
    """Benchmarks that live in their own modules (their dependencies load only when run)."""
    from gcs.bench_bus import bench_bus
    from gcs.bench_demo import bench_demo
    from gcs.bench_faults import bench_faults
    from gcs.bench_fuzz import fuzz_command
    from gcs.bench_hidden import bench_hidden
    from gcs.bench_mapping import bench_mapping
    from gcs.bench_service import bench_service
    from gcs.bench_sitl import sitl
    from gcs.map_replay import bench_map_replay

    bench.add_command(sitl)
    bench.add_command(bench_mapping)
    bench.add_command(bench_map_replay)
    bench.add_command(bench_bus)
    bench.add_command(fuzz_command)
    bench.add_command(bench_service)
    bench.add_command(bench_faults)
    bench.add_command(bench_hidden)
    bench.add_command(bench_demo)


_register_bench_plugins()


def _register_operator_commands() -> None:
    """The ground station's operator commands, the live view, the report and the demo."""
    from gcs.certs import certs_command
    from gcs.commands import COMMANDS

    for command in COMMANDS:
        main.add_command(command)
    main.add_command(certs_command)


_register_operator_commands()

if __name__ == "__main__":  # pragma: no cover
    main()
