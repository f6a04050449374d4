"""``swarm-sitl``: a fleet of PX4-like mock autopilots speaking MAVLink 2 on loopback.

Vehicle i (0-based) has system id i + 1, listens on ``base_port + 40 + i`` and sends its
telemetry to ``base_port + i`` (PX4 SITL's API-link convention: MAVSDK connects with
``udpin://127.0.0.1:14540``, pymavlink with ``udpin:127.0.0.1:14540``). Ctrl-C or SIGTERM stop
it cleanly; SIGUSR1 restarts the loop counters written by ``--stats-json`` (for benchmarks).
The vehicles behave as PX4 v1.16 does (``sitl_mock/README.md``: conformance table).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

import click
import numpy as np

from onboard.config import ConfigError, from_mapping, merge_mappings, parse_overrides, read_yaml
from onboard.stopsignal import SignalStop


def build_world(
    world: str, count: int, seed: int, spacing_m: float
) -> tuple[Any, tuple[tuple[float, float, float], ...]]:
    """(World, spawn points) from a world name or file: the vehicles stand in a row along y
    (north) at the world's start centre (or at its per-drone ``starts``), on its ground."""
    from onboard.config import Formation, load_world_spec

    spec = load_world_spec(world)
    ground = 0.0 if spec.ground_z is None else float(spec.ground_z)
    if spec.starts is not None and len(spec.starts) == count:
        spawn = np.array(spec.starts, dtype=np.float64)
    else:
        off = (np.arange(count) - (count - 1) / 2.0) * spacing_m
        spawn = np.tile(np.asarray(spec.start_center, dtype=np.float64), (count, 1))
        spawn[:, 1] += off
    spawn[:, 2] = ground
    # the generated obstacles keep clear of the spawn points and of the goals
    pts = spawn if count >= 2 else np.vstack([spawn, spawn + [0.0, spacing_m, 0.0]])
    goal = np.asarray(spec.goal_center, dtype=np.float64)
    goals = pts - pts.mean(axis=0) + goal
    formation = Formation("sitl", pts - pts.mean(axis=0) + [0.0, 0.0, 1.0])
    spec = dataclasses.replace(spec, starts=tuple(map(tuple, pts)), goals=tuple(map(tuple, goals)))
    w, _, _ = spec.build(seed, formation)
    return w, tuple((float(p[0]), float(p[1]), float(p[2])) for p in spawn)


def parse_signing(values: Sequence[str], require: bool) -> tuple[Any, ...]:
    """``--signing-key [SYSID:]HEX`` options into ``SigningSpec``s."""
    from sitl_mock.fleet import SigningSpec

    out = []
    for v in values:
        sid: int | None = None
        key = v
        if ":" in v:
            a, key = v.split(":", 1)
            try:
                sid = int(a)
            except ValueError as e:
                raise click.BadParameter(f"{v!r}: expected [SYSID:]HEX") from e
        try:
            out.append(SigningSpec(key.strip(), require, sid))
        except ValueError as e:
            raise click.BadParameter(f"{v!r}: {e}", param_hint="--signing-key") from e
    return tuple(out)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--count", "-n", default=1, show_default=True, help="Number of vehicles.")
@click.option("--world", default=None, help="World name (config/worlds) or YAML/JSON file.")
@click.option("--seed", default=1, show_default=True, help="Seed of the world and the noise.")
@click.option("--base-port", default=14540, show_default=True, help="Vehicle i sends to this + i.")
@click.option(
    "--local-port-offset",
    default=40,
    show_default=True,
    help="Vehicle i listens on base port + this + i; negative: any free port.",
)
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to bind and send to.")
@click.option("--speedup", default=1.0, show_default=True, help="Simulated seconds per second.")
@click.option(
    "--spacing", default=1.5, show_default=True, help="Distance between spawn points [m]."
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="YAML file with FleetConfig keys (autopilot: {...}, dynamics: {...}, ...).",
)
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a setting, e.g. --set autopilot.offboard_loss_action=land.",
)
@click.option(
    "--signing-key",
    multiple=True,
    metavar="[SYSID:]HEX",
    help="MAVLink 2 signing key (64 hex digits) for all vehicles or one (repeatable). "
    "Imitates PX4 v1.17+: PX4 v1.16 has no signing.",
)
@click.option("--allow-unsigned", is_flag=True, help="Sign telemetry but accept unsigned input.")
@click.option(
    "--accept-setup-signing",
    is_flag=True,
    help="Let SETUP_SIGNING set a key (PX4 v1.17+); by default it is ignored, as by PX4 v1.16.",
)
@click.option(
    "--truth",
    type=click.Choice(["none", "zenoh"]),
    default="none",
    show_default=True,
    help="Publish true poses (and depth frames) over Zenoh.",
)
@click.option(
    "--zenoh-listen",
    default="tcp/127.0.0.1:7447",
    show_default=True,
    help="Zenoh endpoint to listen on (comma-separated for several).",
)
@click.option("--zenoh-prefix", default="swarm/sim", show_default=True, help="Zenoh key prefix.")
@click.option("--depth", is_flag=True, help="Render simulated D435 depth frames (needs --world).")
@click.option("--depth-rate", default=15.0, show_default=True, help="Depth frames per second.")
@click.option(
    "--depth-step",
    default=3,
    show_default=True,
    help="A camera of every n-th pixel row and column of the D435's image (the same rays, an "
    "n-times smaller image; the flight service ray casts every 3rd pixel of the D435's by "
    "default, so every pixel of this one).",
)
@click.option(
    "--depth-idle-rate",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Depth frames per second of a disarmed vehicle [default: --depth-rate].",
)
@click.option("--duration", type=float, default=None, help="Stop after this many seconds.")
@click.option(
    "--stats-json",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write counters (CPU, ticks, messages, collisions) here on exit.",
)
@click.option("--quiet", "-q", is_flag=True, help="Print only warnings.")
def main(
    count: int,
    world: str | None,
    seed: int,
    base_port: int,
    local_port_offset: int,
    host: str,
    speedup: float,
    spacing: float,
    config_file: Path | None,
    sets: tuple[str, ...],
    signing_key: tuple[str, ...],
    allow_unsigned: bool,
    accept_setup_signing: bool,
    truth: str,
    zenoh_listen: str,
    zenoh_prefix: str,
    depth: bool,
    depth_rate: float,
    depth_step: int,
    depth_idle_rate: float | None,
    duration: float | None,
    stats_json: Path | None,
    quiet: bool,
) -> None:
    """Run N PX4-like vehicles (system ids 1..N) on MAVLink 2 / UDP."""
    from sitl_mock.fleet import Fleet, FleetConfig
    from sitl_mock.truth import TruthSink, ZenohTruth, simulated_d435

    logging.basicConfig(
        level=logging.WARNING if quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    try:
        data: dict[str, Any] = {}
        if config_file is not None:
            loaded = read_yaml(config_file) or {}
            if not isinstance(loaded, dict):
                raise ConfigError(f"{config_file}: expected a mapping")
            data = loaded
        data = parse_overrides(sets, data)
        data = merge_mappings(
            data,
            {
                "count": count,
                "host": host,
                "base_port": base_port,
                "local_port_offset": None if local_port_offset < 0 else local_port_offset,
                "speedup": speedup,
                "seed": seed,
                "spawn_spacing_m": spacing,
            },
        )
        w = None
        if world is not None:
            w, spawns = build_world(world, count, seed, spacing)
            data["spawn_enu_m"] = [list(p) for p in spawns]
        if accept_setup_signing:
            data["accept_setup_signing"] = True
        if signing_key:
            data["signing"] = [
                dataclasses.asdict(s) for s in parse_signing(signing_key, not allow_unsigned)
            ]
        cfg = from_mapping(FleetConfig, data, "sitl")
    except ConfigError as e:
        raise click.ClickException(str(e)) from e
    if depth and w is None:
        raise click.BadParameter("depth frames need a --world", param_hint="--depth")
    if depth and truth != "zenoh":
        raise click.BadParameter(
            "depth frames are published with --truth zenoh", param_hint="--depth"
        )

    sinks: list[TruthSink] = []
    if truth == "zenoh":
        try:
            sinks.append(ZenohTruth(zenoh_prefix, [e for e in zenoh_listen.split(",") if e]))
        except Exception as e:  # noqa: BLE001 - report any Zenoh failure plainly
            raise click.ClickException(f"cannot open Zenoh on {zenoh_listen}: {e}") from e
    cameras = None
    if depth:
        try:
            cameras = {i + 1: simulated_d435(w, seed + i, depth_step) for i in range(count)}
        except RuntimeError as e:
            raise click.ClickException(str(e)) from e

    fleet = Fleet(cfg, w, sinks, cameras, depth_rate, depth_idle_rate)
    try:
        fleet.open()
    except OSError as e:
        fleet.close()
        raise click.ClickException(f"cannot bind the vehicles' ports: {e}") from e

    def on_usr1(signum: int, _frame: FrameType | None) -> None:
        fleet.request_stats_reset()  # sets a flag, takes no lock (safe in a handler)

    def give_up() -> None:
        click.echo(
            f"swarm-sitl: the fleet did not stop within {stopping.deadline_s:.0f} s of the "
            "signal: exiting",
            err=True,
        )

    # SIGTERM / SIGINT stop the loop in order, a second one or 10 s without an end stop the
    # process (onboard/stopsignal.py: a handler that took Event.set's lock once left the mock
    # running for ever after the demo that started it was killed)
    stopping = SignalStop(fleet.request_stop, 10.0, give_up, thread_name="sitl-stopper")
    usr1 = getattr(signal, "SIGUSR1", None)
    if usr1 is not None:
        signal.signal(usr1, on_usr1)
    with stopping:
        if not quiet:
            click.echo(
                f"swarm-sitl: {count} vehicle(s), speedup {speedup:g}"
                + (f", world {world} ({w.n_primitives} obstacles)" if w is not None else "")
            )
            for link, sp in zip(fleet.links, fleet.spawns, strict=True):
                click.echo(
                    f"  sysid {link.system_id}: listens {link.host}:{link.local_port}, sends to "
                    f"{link.partner[0]}:{link.partner[1]}, spawn ENU ({sp[0]:.2f}, "
                    f"{sp[1]:.2f}, {sp[2]:.2f})"
                )
            click.echo("Ctrl-C to stop")
        try:
            if cameras:
                assert fleet._depth is not None
                fleet._depth.start()
            fleet.run(duration)
        finally:
            if fleet._depth is not None:
                fleet._depth.stop()
            fleet.close()
            if usr1 is not None:
                # ignored from here to the process's end, not handed back: the default action
                # of SIGUSR1 ends the process, and a reset asked for during the teardown (a
                # benchmark's, an operator's) killed the mock before it wrote its statistics;
                # after the loop there is nothing left to reset
                signal.signal(usr1, signal.SIG_IGN)
    summary = fleet.summary()
    summary["process_cpu_s"] = _process_cpu_s()
    if stats_json is not None:
        stats_json.parent.mkdir(parents=True, exist_ok=True)
        stats_json.write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    if not quiet:
        cols = summary["collisions"]
        click.echo(
            f"stopped after {summary['wall_s']:.1f} s ({summary['sim_s']:.1f} s simulated), "
            f"{len(cols)} collision(s), loop CPU {summary['loop_cpu_s']:.2f} s"
        )
        for c in cols:
            click.echo(f"  collision t={c['t_s']:.2f} s {c['kind']} vehicles {c['system_ids']}")


def _process_cpu_s() -> float:
    import os

    t = os.times()
    return float(t.user + t.system)


def _json_default(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


if __name__ == "__main__":  # pragma: no cover
    main()
