"""``swarm-onboard``: the companion-computer side.

- ``run --id I [--config FILE]``: the flight service of drone I (``onboard.service``);
- ``check-config FILE``: validate a service config, print OK or the error (exit 1);
- ``warmup [--config FILE]``: compile the service's kernels (planner, and mapping when the config
  has a camera) into numba's on-disk cache, so that a freshly started service on the drone is
  ready in about a second (run it once after installing or upgrading; the warm-up unit does).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])

STOP_DEADLINE_S = 8.0
"""A stop that has not ended this long after SIGTERM ends the process (with a ``stop_timeout``
log line). Below the unit's ``TimeoutStopSec`` (10 s, systemd/swarm-onboard@.service), so that
the line is out before systemd's SIGKILL."""


def _config_option(help_text: str) -> Callable[[F], F]:
    """The ``--config FILE`` option of the commands that read a flight-service config."""
    return click.option(
        "--config",
        "config_file",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help=help_text,
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Onboard tools of the swarm formation system."""


@main.command()
@_config_option("Service config whose planner and map are warmed (default: config/onboard.yaml).")
def warmup(config_file: Path | None) -> None:
    """Compile (or load from numba's cache) every kernel the flight service runs: the planner's
    paths (the service's own warm-up) and, when the config has a depth source, the mapping
    path (ray casting, ESDF). Run once per boot and after an upgrade (the warm-up unit)."""
    t0 = time.perf_counter()
    from onboard.config import ConfigError
    from onboard.service.config import load_onboard_config
    from onboard.service.planning import warm_mapping, warm_up

    try:
        cfg = load_onboard_config(config_file, None)
    except ConfigError as e:
        click.echo(f"config: {e}", err=True)
        sys.exit(2)
    t1 = time.perf_counter()
    plan_s = warm_up(cfg.planner)
    line = f"planner ready: import {t1 - t0:.2f} s, planning paths {plan_s:.2f} s"
    mapping = cfg.camera_map_params
    if mapping is not None:
        map_s = warm_mapping(mapping, cfg.depth.step)
        line += f", mapping path {map_s:.2f} s"
    click.echo(line)


@main.command("check-config")
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--id", "drone_id", type=int, default=None, help="Check as drone I.")
def check_config(file: Path, drone_id: int | None) -> None:
    """Validate a flight-service config FILE: prints OK, or the error and exits with 1."""
    from onboard.config import ConfigError
    from onboard.service.config import load_onboard_config

    try:
        cfg = load_onboard_config(file, drone_id)
    except ConfigError as e:
        click.echo(f"{file}: {e}", err=True)
        sys.exit(1)
    click.echo(
        f"OK: drone {cfg.drone.id} of swarm {cfg.drone.swarm!r}, autopilot "
        f"{cfg.autopilot.implementation} at {cfg.autopilot.endpoint(cfg.drone.id)}, depth "
        f"{cfg.depth.source}"
    )


@main.command()
@click.option("--id", "drone_id", type=int, required=True, help="This drone's id (0-based).")
@_config_option("Service config (default: config/onboard.yaml).")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Override a setting.")
@click.option("--duration", type=float, default=None, help="Stop after this many seconds.")
def run(
    drone_id: int, config_file: Path | None, sets: tuple[str, ...], duration: float | None
) -> None:
    """The flight service of drone ID: autopilot link, swarm bus, depth, planner, reactions.

    Tells systemd READY=1 once the link, the map and a warm planner are up; stops cleanly on
    SIGTERM or SIGINT."""
    import logging
    import os

    from onboard.config import ConfigError, parse_overrides
    from onboard.service.adapters import open_autopilot, open_bus, open_depth
    from onboard.service.config import load_onboard_config
    from onboard.service.logs import event, setup_logging
    from onboard.service.planning import WarmUp
    from onboard.service.sdnotify import Notifier
    from onboard.service.service import FlightService
    from onboard.stopsignal import SignalStop

    try:
        cfg = load_onboard_config(config_file, drone_id, parse_overrides(sets))
    except ConfigError as e:
        click.echo(f"config: {e}", err=True)
        sys.exit(2)
    setup_logging(cfg.drone.id, cfg.logging.level, cfg.logging.format)
    log = logging.getLogger("onboard.service")
    notifier = Notifier()
    notifier.status("connecting to the autopilot")
    event(log, "starting", swarm=cfg.drone.swarm, autopilot=cfg.autopilot.endpoint(drone_id))
    # load the planner's kernels while the edges connect (mostly waiting for the autopilot)
    # and the mapping kernels too when there is a camera (the depth thread would otherwise
    # compile them on its first frame, cold: tens of seconds before READY)
    warming = (
        WarmUp(cfg.planner, cfg.camera_map_params, cfg.depth.step).start()
        if cfg.planning.warm_up
        else None
    )
    closers: list = []
    try:
        ap = open_autopilot(cfg)
        closers.append(ap.close)
        bus = open_bus(cfg)
        closers.append(bus.close)
        depth = open_depth(cfg)
        if depth is not None:
            closers.append(depth.close)
    except Exception as e:  # noqa: BLE001 - any edge that cannot open ends the process
        event(log, "start_failed", logging.ERROR, why=f"{type(e).__name__}: {e}")
        for c in reversed(closers):
            c()
        sys.exit(1)
    svc = FlightService(cfg, ap, bus, depth, notifier=notifier, warming=warming)
    # threads waiting for the interpreter (the 50 Hz setpoint stream) get it within about a
    # millisecond instead of 5 while mapping, planning and decoding threads are busy
    sys.setswitchinterval(0.001)

    def give_up() -> None:
        event(log, "stop_timeout", logging.ERROR, after_s=stopping.deadline_s)

    # SIGTERM / SIGINT stop the service in order, a second one or STOP_DEADLINE_S without an
    # end stop the process (onboard/stopsignal.py: why the handler itself takes no lock)
    stopping = SignalStop(svc.request_stop, STOP_DEADLINE_S, give_up, thread_name="svc-stopper")
    rc = 1
    with stopping:
        try:
            rc = svc.run(duration_s=duration)
        finally:
            notifier.stopping()
            svc.stop()
            for c in reversed(closers):
                c()
            event(log, "stopped", code=rc)
    if svc.stuck_threads or (warming is not None and warming.running()):
        # the interpreter's teardown with a thread inside numba's compiler (a stop before a
        # cold warm-up ended) crashed the process (SIGSEGV, "corrupted double-linked list"):
        # leave without it, the record and the links are closed already
        event(log, "exit_with_running_threads", logging.WARNING, threads=svc.stuck_threads)
        logging.shutdown()
        os._exit(rc)
    sys.exit(rc)
