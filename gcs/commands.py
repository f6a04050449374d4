"""Operator commands of ``swarm-gcs`` over the Zenoh swarm bus (the same commands fly real drones
and the local demo): ``status``, ``formation``, ``goal``, ``waypoints``, ``takeoff``, ``land``,
``abort``, ``resume``, ``view`` (and, from their own modules, ``report`` and ``demo``).

Every bus command joins the bus (``--swarm``, ``--connect`` / ``--listen``, ``--mode``; over
mutual TLS with ``--tls-ca``, ``--tls-cert``, ``--tls-key``: ``swarm-gcs certs`` makes a demo
PKI), waits up to ``--wait`` seconds to see the drones' liveliness tokens, sends, and reports
each drone's answer; it exits 1 when a drone refused or did not answer within ``--timeout``
(the ids are printed), so that scripts can rely on the exit status. ``--json`` prints the
outcome as one JSON object.

Register them on the ``swarm-gcs`` group with ``for c in COMMANDS: main.add_command(c)``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from gcs.formations import FormationError, per_drone_errors
from gcs.station import CommandOutcome, DroneView, GroundStation, StationConfig, StationError
from onboard.comm.keys import check_swarm
from onboard.comm.zenoh_session import MODES, ZenohEndpoints
from onboard.config import ConfigError, read_yaml

F = TypeVar("F", bound=Callable[..., Any])

ENV_PREFIX = "SWARM_GCS"
"""Environment variables ``SWARM_GCS_SWARM``, ``SWARM_GCS_CONNECT``, ``SWARM_GCS_LISTEN``,
``SWARM_GCS_MODE`` set the bus options' defaults."""


@dataclass(frozen=True)
class BusOptions:
    """How an operator command joins the swarm bus and how long it waits."""

    swarm: str = "swarm"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    mode: str = "peer"
    timeout_s: float = 3.0
    wait_s: float = 3.0
    expect: int | None = None
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None

    def endpoints(self) -> ZenohEndpoints:
        """The Zenoh endpoints; over TLS (``tcp/`` becomes ``tls/``) with the station's
        certificate when ``tls_ca``/``tls_cert``/``tls_key`` are given."""
        eps = ZenohEndpoints(listen=self.listen, connect=self.connect, mode=self.mode)
        given = [x is not None for x in (self.tls_ca, self.tls_cert, self.tls_key)]
        if not any(given):
            return eps
        if not all(given):
            raise click.UsageError("TLS needs all three of --tls-ca, --tls-cert and --tls-key")
        from onboard.comm.security import TlsConfig

        assert self.tls_ca is not None and self.tls_cert is not None and self.tls_key is not None
        try:
            tls = TlsConfig(self.tls_ca, self.tls_cert, self.tls_key)
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--tls-*") from e
        return eps.secured(tls)


def _split(value: str | None) -> tuple[str, ...]:
    return tuple(e.strip() for e in (value or "").split(",") if e.strip())


def bus_options(f: F) -> F:
    """The options every bus command shares; the command receives ``bus: BusOptions``."""

    opts = [
        click.option(
            "--swarm",
            default="swarm",
            show_default=True,
            envvar=f"{ENV_PREFIX}_SWARM",
            help="Swarm name (first part of every key expression).",
        ),
        click.option(
            "--connect",
            default="",
            envvar=f"{ENV_PREFIX}_CONNECT",
            help="Zenoh endpoints to connect to, comma-separated (tcp/HOST:PORT; the drones' "
            "or a router's).",
        ),
        click.option(
            "--listen",
            default="",
            envvar=f"{ENV_PREFIX}_LISTEN",
            help="Zenoh endpoints to listen on, comma-separated.",
        ),
        click.option(
            "--mode",
            type=click.Choice(list(MODES)),
            default="peer",
            show_default=True,
            envvar=f"{ENV_PREFIX}_MODE",
            help="Zenoh mode ('client' through a router).",
        ),
        click.option(
            "--timeout",
            "timeout_s",
            type=click.FloatRange(min=0.05),
            default=3.0,
            show_default=True,
            help="Seconds to wait for every drone's acknowledgement.",
        ),
        click.option(
            "--wait",
            "wait_s",
            type=click.FloatRange(min=0.0),
            default=3.0,
            show_default=True,
            help="Seconds to wait for the drones to show up on the bus.",
        ),
        click.option(
            "--tls-ca",
            default=None,
            envvar=f"{ENV_PREFIX}_TLS_CA",
            help="Swarm CA certificate (PEM): join over mutual TLS (with --tls-cert/--tls-key).",
        ),
        click.option(
            "--tls-cert",
            default=None,
            envvar=f"{ENV_PREFIX}_TLS_CERT",
            help="This ground station's certificate (PEM, common name 'gcs').",
        ),
        click.option(
            "--tls-key",
            default=None,
            envvar=f"{ENV_PREFIX}_TLS_KEY",
            help="Its private key (PEM, mode 0600).",
        ),
        click.option(
            "--expect",
            type=click.IntRange(min=1),
            default=None,
            help="Number of drones to wait for (default: those up after a short settle).",
        ),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _bus(kw: dict[str, Any]) -> BusOptions:
    """Pop the bus options out of a command's keyword arguments."""
    swarm = kw.pop("swarm")
    try:
        check_swarm(swarm)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--swarm") from e
    bus = BusOptions(
        swarm=swarm,
        connect=_split(kw.pop("connect")),
        listen=_split(kw.pop("listen")),
        mode=kw.pop("mode"),
        timeout_s=kw.pop("timeout_s"),
        wait_s=kw.pop("wait_s"),
        expect=kw.pop("expect"),
        tls_ca=kw.pop("tls_ca"),
        tls_cert=kw.pop("tls_cert"),
        tls_key=kw.pop("tls_key"),
    )
    if not bus.connect and not bus.listen:
        raise click.UsageError(
            "say where the swarm is: --connect tcp/HOST:PORT (or --listen, or "
            f"{ENV_PREFIX}_CONNECT)"
        )
    return bus


@contextmanager
def open_station(
    bus: BusOptions,
    *,
    drones: Sequence[int] | None = None,
    with_state: bool = False,
    config: StationConfig | None = None,
) -> Iterator[GroundStation]:
    """A ground station on the bus that has waited for the drones: ``drones`` (all of them),
    ``bus.expect`` of them, or whoever is up once the set has not grown for a short while."""
    cfg = config if config is not None else StationConfig(ack_timeout_s=bus.timeout_s)
    endpoints = bus.endpoints()
    try:
        gs = GroundStation(bus.swarm, endpoints, config=cfg)
    except (RuntimeError, ValueError) as e:
        raise click.ClickException(str(e)) from e
    try:
        if drones is not None:
            gs.wait_for_drones(ids=list(drones), timeout_s=bus.wait_s, with_state=with_state)
        elif bus.expect is not None:
            gs.wait_for_drones(count=bus.expect, timeout_s=bus.wait_s, with_state=with_state)
        else:
            _settle(gs, bus.wait_s, with_state)
        yield gs
    finally:
        gs.close()


def _settle(gs: GroundStation, wait_s: float, with_state: bool, quiet_s: float = 0.5) -> None:
    """Wait for the first drone, then until no new one appeared for ``quiet_s`` (bounded by
    ``wait_s`` overall)."""
    deadline = time.monotonic() + wait_s
    seen = gs.wait_for_drones(timeout_s=wait_s, with_state=with_state)
    last_change = time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - last_change < quiet_s:
        time.sleep(0.05)
        now = gs.drones() & (set(gs.node.latest_states()) if with_state else gs.drones())
        if now != seen:
            seen = now
            last_change = time.monotonic()


def _parse_ids(text: str | None) -> list[int] | None:
    """``"0,2,5-7"`` -> [0, 2, 5, 6, 7]."""
    if text is None or not text.strip():
        return None
    out: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part:
                a, b = part.split("-", 1)
                lo, hi = int(a), int(b)
                if hi < lo:
                    raise ValueError(f"empty range {part}")
                out.extend(range(lo, hi + 1))
            elif part:
                out.append(int(part))
    except ValueError as e:
        raise click.BadParameter(
            f"{text!r} is not a list of drone ids like 0,2,5-7 ({e})", param_hint="--drones"
        ) from e
    if len(set(out)) != len(out):
        raise click.BadParameter(f"{text!r} names a drone twice", param_hint="--drones")
    return out


_drones_opt = click.option(
    "--drones",
    default=None,
    metavar="IDS",
    help="Only these drones, e.g. 0,2,5-7 (default: every drone up).",
)
_json_opt = click.option("--json", "as_json", is_flag=True, help="Print the outcome as JSON.")


def _finish(outcome: CommandOutcome, as_json: bool, extra: dict[str, Any] | None = None) -> None:
    """Print an outcome; exit 1 unless every addressed drone accepted."""
    if as_json:
        data = outcome.to_json()
        data.update(extra or {})
        click.echo(json.dumps(data))
    else:
        click.echo(outcome.describe())
    if not outcome.ok:
        sys.exit(1)


def _send(
    bus: BusOptions,
    as_json: bool,
    drones: str | None,
    send: Callable[[GroundStation, list[int] | None], CommandOutcome],
) -> None:
    ids = _parse_ids(drones)
    with open_station(bus, drones=ids) as gs:
        try:
            outcome = send(gs, ids)
        except StationError as e:
            raise click.ClickException(f"{e} (nothing sent)") from e
    _finish(outcome, as_json)


# --- commands --------------------------------------------------------------------------------


@click.command()
@bus_options
@click.option("--altitude", type=float, default=1.0, show_default=True, help="Metres up.")
@_drones_opt
@_json_opt
def takeoff(altitude: float, drones: str | None, as_json: bool, **kw: Any) -> None:
    """Take off and hover ALTITUDE metres above the take-off point."""
    if not (math.isfinite(altitude) and altitude > 0.0):
        raise click.BadParameter(f"{altitude} is not a positive height", param_hint="--altitude")
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.takeoff(altitude, ids))


@click.command()
@bus_options
@_drones_opt
@_json_opt
def land(drones: str | None, as_json: bool, **kw: Any) -> None:
    """Land where they are."""
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.land(ids))


@click.command()
@bus_options
@_drones_opt
@_json_opt
def abort(drones: str | None, as_json: bool, **kw: Any) -> None:
    """Every drone stops and hovers, then lands."""
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.abort(ids))


@click.command()
@bus_options
@_drones_opt
@_json_opt
def resume(drones: str | None, as_json: bool, **kw: Any) -> None:
    """Take control back after an abort, a pause or a pilot's intervention."""
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.resume(ids))


@click.command()
@click.argument("x", type=float)
@click.argument("y", type=float)
@click.argument("z", type=float)
@click.option("--yaw", "yaw_deg", type=float, default=None, help="Final heading [deg, ENU].")
@bus_options
@_drones_opt
@_json_opt
def goal(
    x: float,
    y: float,
    z: float,
    yaw_deg: float | None,
    drones: str | None,
    as_json: bool,
    **kw: Any,
) -> None:
    """Fly the formation's centre to X Y Z (ENU metres), all drones from one common time."""
    yaw = None if yaw_deg is None else math.radians(yaw_deg)
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.goal((x, y, z), yaw, ids))


def read_waypoints(path: Path) -> list[tuple[float, float, float]]:
    """``points: [[x, y, z], ...]`` (or a bare list) from a YAML/JSON file."""
    try:
        data = read_yaml(path)
    except ConfigError as e:
        raise click.BadParameter(str(e), param_hint="FILE") from e
    pts = data.get("points") if isinstance(data, dict) else data
    if not isinstance(pts, list) or not pts:
        raise click.BadParameter(f"{path}: expected 'points: [[x, y, z], ...]'", param_hint="FILE")
    out = []
    for i, p in enumerate(pts):
        ok = isinstance(p, (list, tuple)) and len(p) == 3
        ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in p)
        if not ok or not all(math.isfinite(float(v)) for v in p):
            raise click.BadParameter(
                f"{path}: points[{i}] = {p!r} is not three finite numbers", param_hint="FILE"
            )
        out.append((float(p[0]), float(p[1]), float(p[2])))
    return out


@click.command()
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@bus_options
@_drones_opt
@_json_opt
def waypoints(file: Path, drones: str | None, as_json: bool, **kw: Any) -> None:
    """Fly the formation's centre through the points of FILE (YAML/JSON ``points:``)."""
    pts = read_waypoints(file)
    _send(_bus(kw), as_json, drones, lambda gs, ids: gs.waypoints(pts, ids))


@click.command()
@click.argument("name")
@click.option("--scale", type=float, default=1.0, show_default=True, help="Scale factor.")
@click.option("--yaw", "yaw_deg", type=float, default=None,
              help="Turn the formation by this [deg] about the up axis [default: the turn "
              "that takes the least travel in all; the shape is the same either way].")  # fmt: skip
@bus_options
@_drones_opt
@_json_opt
def formation(
    name: str, scale: float, yaw_deg: float | None, drones: str | None, as_json: bool, **kw: Any
) -> None:
    """Assign formation NAME (config/formations) or FILE (YAML/JSON ``points:``) to the drones
    up (or --drones), by the least total distance from where they are; all switch at one common
    time. A bad formation is refused before anything is sent."""
    bus = _bus(kw)
    ids = _parse_ids(drones)
    with open_station(bus, drones=ids, with_state=True) as gs:
        try:
            yaw = None if yaw_deg is None else math.radians(yaw_deg)
            a, outcome = gs.formation(name, scale=scale, yaw_rad=yaw, drones=ids)
        except (FormationError, StationError) as e:
            raise click.ClickException(f"{e} (nothing sent)") from e
    if not as_json:
        slots = ", ".join(f"{d}->{s}" for d, s in sorted(a.slots.items()))
        how = "" if yaw_deg is not None else " (least travel)"
        click.echo(
            f"formation {a.name} epoch {a.epoch}, scale {a.scale:g}, "
            f"yaw {math.degrees(a.yaw_rad):.1f} deg{how}, "
            f"centre ({a.center_m[0]:.2f}, {a.center_m[1]:.2f}, {a.center_m[2]:.2f}), "
            f"slots {slots}, total distance {a.cost_m:.2f} m"
        )
    extra = {
        "formation": a.name,
        "epoch": a.epoch,
        "slots": {str(d): s for d, s in sorted(a.slots.items())},
        "yaw_deg": math.degrees(a.yaw_rad),
        "cost_m": a.cost_m,
    }
    _finish(outcome, as_json, extra)


# --- status ----------------------------------------------------------------------------------


def _f(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def status_data(gs: GroundStation) -> dict[str, Any]:
    """What ``status --json`` prints: the drones, the formation in force and its error."""
    views = gs.views()
    known = gs.known_formation()
    err = gs.formation_error()
    per = _per_drone(gs, views)
    return {
        "swarm": gs.swarm,
        "t_s": gs.clock(),
        "drones": [dict(v.to_json(), formation_error_m=per.get(d)) for d, v in views.items()],
        "formation": None
        if known is None
        else {"name": known[0], "epoch": known[1].epoch, "slots": known[1].slots},
        "e_dist_m": None if err is None else err[0],
        "e_sim": None if err is None else err[1],
    }


def _per_drone(gs: GroundStation, views: dict[int, DroneView]) -> dict[int, float]:
    known = gs.known_formation()
    if known is None:
        return {}
    wire = known[1]
    pos = {d: np.asarray(v.position_m) for d, v in views.items() if v.position_m is not None}
    return per_drone_errors(pos, wire.slots, np.asarray(wire.points_m))


def status_table(gs: GroundStation) -> Table:
    """The live table: one row per drone."""
    views = gs.views()
    per = _per_drone(gs, views)
    now = gs.clock()
    t = Table(title=f"swarm {gs.swarm}: {sum(v.alive for v in views.values())} drone(s) up")
    for col in ("id", "state", "position [m]", "speed", "battery", "links", "plan",
                "plan age", "bus", "form. err", "note"):  # fmt: skip
        t.add_column(col, justify="right" if col in ("id", "speed", "plan age") else "left")
    for d, v in views.items():
        pos = "-" if v.position_m is None else "({:.1f}, {:.1f}, {:.1f})".format(*v.position_m)
        bat = "-"
        if v.battery_remaining is not None:
            bat = f"{100 * v.battery_remaining:.0f}%"
        if v.battery_v is not None:
            bat += f" {v.battery_v:.1f} V" if bat != "-" else f"{v.battery_v:.1f} V"
        plan = "-" if not v.plan_status else f"{v.plan_status} {_f(v.plan_ms_last, '.0f')} ms"
        age = None if v.plan_stamp_s is None else now - v.plan_stamp_s
        state = (v.flight_state or "?") + ("" if v.alive else " (DOWN)")
        t.add_row(
            str(d),
            state,
            pos,
            _f(v.speed_m_s),
            bat,
            v.links_text(),
            plan,
            _f(age, ".1f"),
            v.bus_text(),
            _f(per.get(d), ".2f"),
            v.message[:30],
        )
    err = gs.formation_error()
    known = gs.known_formation()
    if known is not None:
        name = known[0] or "(sent elsewhere)"
        ed, es = (None, None) if err is None else err
        t.caption = (
            f"formation {name} epoch {known[1].epoch}: e_dist {_f(ed, '.3f')} m, "
            f"e_sim {_f(es, '.4f')}"
        )
    return t


@click.command()
@bus_options
@click.option("--once", is_flag=True, help="Print once and exit (default: refresh until Ctrl-C).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (one object per refresh).")
@click.option("--period", type=click.FloatRange(min=0.1), default=1.0, show_default=True)
def status(once: bool, as_json: bool, period: float, **kw: Any) -> None:
    """The drones that are up: flight state, position, speed, battery, links, plan, bus
    counters, formation error."""
    bus = _bus(kw)
    console = Console(highlight=False)
    if not console.is_terminal:
        console.width = max(console.width, 160)  # a pipe or a file: do not squeeze the columns
    with open_station(bus, with_state=True) as gs:
        if once:
            _print_status(gs, console, as_json)
            return
        if as_json:
            try:
                while True:
                    _print_status(gs, console, True)
                    time.sleep(period)
            except KeyboardInterrupt:
                return
        from rich.live import Live

        try:
            with Live(status_table(gs), console=console, refresh_per_second=4) as live:
                while True:
                    time.sleep(period)
                    live.update(status_table(gs))
        except KeyboardInterrupt:
            return


def _print_status(gs: GroundStation, console: Console, as_json: bool) -> None:
    if as_json:
        click.echo(json.dumps(status_data(gs)))
    else:
        console.print(status_table(gs))


# --- view ------------------------------------------------------------------------------------


def mock_world(world: str, count: int, seed: int, spacing_m: float) -> Any:
    """The obstacles exactly as ``swarm-sitl --world W --seed S --count N --spacing D`` builds
    them (the generated forest keeps clear of the mock's spawn row and goals)."""
    from sitl_mock.cli import build_world

    try:
        w, _ = build_world(world, count, seed, spacing_m)
    except ConfigError as e:
        raise click.BadParameter(str(e), param_hint="--world") from e
    return w


@click.command()
@bus_options
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to serve on.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True,
              help="WebSocket port (0: any free port).")  # fmt: skip
@click.option("--rate", type=click.FloatRange(min=0.2, max=50.0), default=5.0, show_default=True,
              help="Scene updates per second.")  # fmt: skip
@click.option("--world", default=None, help="World of the flight, to draw its obstacles.")
@click.option("--seed", type=int, default=1, show_default=True, help="Seed of the world.")
@click.option("--count", type=int, default=None,
              help="Vehicles of the mock (its forest keeps clear of their spawn points) "
              "[default: the drones up].")  # fmt: skip
@click.option("--spacing", type=float, default=1.5, show_default=True,
              help="The mock's spawn spacing [m].")  # fmt: skip
def view(
    host: str,
    port: int,
    rate: float,
    world: str | None,
    seed: int,
    count: int | None,
    spacing: float,
    **kw: Any,
) -> None:
    """Serve the swarm to Foxglove (WebSocket): drones, their plans, the formation target and
    the obstacles, until Ctrl-C."""
    from gcs.view import SwarmView, station_input

    bus = _bus(kw)
    with open_station(bus, with_state=True) as gs:
        w = None
        if world is not None:
            w = mock_world(world, count if count is not None else max(len(gs.drones()), 1), seed,
                           spacing)  # fmt: skip
        try:
            sv = SwarmView(station_input(gs), w, host=host, port=port, rate_hz=rate)
        except RuntimeError as e:
            raise click.ClickException(str(e)) from e
        with sv:
            sv.start()
            click.echo(
                f"Foxglove view on {sv.url} ({len(gs.drones())} drone(s) up); Ctrl-C to stop"
            )
            try:
                while True:
                    time.sleep(1.0)
            except KeyboardInterrupt:
                pass


def _all_commands() -> tuple[click.Command, ...]:
    from gcs.demo import demo
    from gcs.report import report

    return (status, formation, goal, waypoints, takeoff, land, abort, resume, view, report, demo)


COMMANDS: tuple[click.Command, ...] = _all_commands()
"""Register on ``swarm-gcs``: ``for c in COMMANDS: main.add_command(c)``."""
