"""A drone its peers do not hear (``swarm-gcs bench hidden``): fast-time twins of the bus-faults
flight on the real processes (``tests/test_bus_faults_process.py``).

Three drones in a line across the way, the ends' slots crossed, so that drones 0 and 2 swap
sides while the line flies 11 m at 1 m/s; every message (trajectories, states) crosses a bus
that loses 20 % and delays up to 0.3 s; drone 2's uplink is out for ``--outage-s`` from
``--outage-from`` (nothing it sends reaches anyone, it hears its peers), so that the crossing
falls in the outage. The starts are jittered up to 0.3 m by the seed, and the bus faults are
seeded by it. The 1 Hz statuses tell drone 2 that its peers do not hear it
(``onboard.comm.hearing``); ``--set unheard_margin_m=0`` flies without the wider berth that
follows. ``--resend-s`` / ``--resend-plans`` set which trajectories go out again
(``DroneAgent.resend``), ``--deviation-ahead-s`` when a peer counts as off its trajectory.

Per flight and in total: arrivals, collisions, the hidden drone's closest approach to a peer,
the closest approach of the two drones that hear each other, flight time, the plans made while
told that a peer did not hear us. Positions in fast time are the flown plans (no tracking
error).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from gcs.pools import sigterm_interrupts
from onboard.agent import PEER_DEVIATION_AHEAD_S, RESEND_S, resend_delays
from onboard.planner.params import PlannerParams

POINTS = ((0.0, 1.5, 0.0), (0.0, 0.0, 0.0), (0.0, -1.5, 0.0))
"""The line; drone i takes point i, so drones 0 and 2 start on the far side of their slots."""
SPAWNS = ((0.0, -2.0, 1.0), (-1.5, 0.0, 1.0), (0.0, 2.0, 1.0))
GOAL_CENTRE = (11.0, 0.0, 1.0)
JITTER_M = 0.3
HIDDEN = 2
LOSS = 0.2
DELAY_MAX_S = 0.3


@dataclass(frozen=True)
class HiddenTrial:
    seed: int
    outage_from_s: float
    outage_s: float
    params: PlannerParams
    time_limit_s: float
    resend_s: tuple[float, ...] = RESEND_S
    deviation_ahead_s: float = PEER_DEVIATION_AHEAD_S
    resend_plans: bool = False


def fly_hidden(trial: HiddenTrial) -> dict[str, Any]:
    """One flight (see the module docstring); its figures."""
    from gcs.bench_service import write_world
    from gcs.fastsim import SimConfig, run_sim
    from onboard.comm.faults import BusFaults
    from onboard.config import Formation, load_world_spec

    line = Formation("line-3-crossed", np.array(POINTS))
    rng = np.random.default_rng(trial.seed)
    starts = np.array(SPAWNS) + np.c_[rng.uniform(-JITTER_M, JITTER_M, (3, 2)), np.zeros(3)]
    goals = np.array(GOAL_CENTRE) + line.points
    outages = {}
    if trial.outage_s > 0.0:
        outages = {HIDDEN: (trial.outage_from_s, trial.outage_from_s + trial.outage_s)}
    with tempfile.TemporaryDirectory() as tmp:
        world = write_world(Path(tmp) / "swap.yaml", [], starts.tolist(), goals.tolist())
        spec = load_world_spec(world)
    cfg = SimConfig(
        line,
        spec,
        seed=trial.seed,
        planner=trial.params,
        bus_faults=BusFaults(loss=LOSS, delay_max_s=DELAY_MAX_S),
        fault_seed=trial.seed,
        radio_outages=outages,
        monitor_rate_hz=100.0,
        time_limit_s=trial.time_limit_s,
        resend_s=trial.resend_s,
        peer_deviation_ahead_s=trial.deviation_ahead_s,
        resend_plans=trial.resend_plans,
    )
    r = run_sim(cfg)
    pos = r.tracks.pos

    def closest(i: int, j: int) -> float:
        return float(np.linalg.norm(pos[:, i] - pos[:, j], axis=1).min())

    f = r.to_json()["faults"]
    return {
        "seed": trial.seed,
        "success": bool(r.success),
        "arrived": int(np.sum(r.arrived)),
        "collisions": int(r.collisions),
        "hidden_closest_m": min(closest(HIDDEN, 0), closest(HIDDEN, 1)),
        "others_closest_m": closest(0, 1),
        "flight_time_s": float(r.flight_time_s),
        "timed_out": bool(r.timed_out),
        "unheard_plans": int(f["unheard_plans"]),
        "radio_dropped": int(f["radio_dropped"]),
        "monitor_brakes": int(f["monitor_brakes"]),
        "resent": int(f["resent"]),
    }


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over the flights."""
    hid = np.array([r["hidden_closest_m"] for r in rows])
    oth = np.array([r["others_closest_m"] for r in rows])
    t = np.array([r["flight_time_s"] for r in rows])
    return {
        "flights": len(rows),
        "success": sum(r["success"] for r in rows),
        "collisions": sum(r["collisions"] for r in rows),
        "collision_seeds": [r["seed"] for r in rows if r["collisions"]],
        "hidden_closest_m": {
            "min": float(hid.min()),
            "p10": float(np.percentile(hid, 10)),
            "median": float(np.median(hid)),
        },
        "hidden_under_0_5_m": int((hid < 0.5).sum()),
        "hidden_under_0_6_m": int((hid < 0.6).sum()),
        "others_closest_m": float(oth.min()),
        "others_under_0_5_m": int((oth < 0.5).sum()),
        "flight_time_s": {"median": float(np.median(t)), "max": float(t.max())},
        "unheard_plans": sum(r["unheard_plans"] for r in rows),
        "monitor_brakes": sum(r["monitor_brakes"] for r in rows),
    }


@click.command("hidden")
@click.option("--seeds", default=50, show_default=True, help="Flights (seeds first, first+1...).")
@click.option("--first", default=1, show_default=True, help="The first seed.")
@click.option(
    "--outage-from", default=1.0, show_default=True, help="Drone 2's uplink out from [s]."
)
@click.option("--outage-s", default=7.5, show_default=True, help="... for this long (0: none).")
@click.option("--jobs", default=2, show_default=True, help="Flights in parallel.")
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a planner parameter, e.g. --set unheard_margin_m=0 (repeatable).",
)
@click.option(
    "--resend-s",
    default=",".join(f"{d:g}" for d in RESEND_S),
    show_default=True,
    help="A braking stop or hover (with --resend-plans, every plan) goes out again this long "
    "after it, comma-separated [s] ('' once).",
)
@click.option(
    "--resend-plans/--resend-stops-only",
    default=False,
    show_default=True,
    help="Send plans again too, or only braking stops and hovers.",
)
@click.option(
    "--deviation-ahead-s",
    default=PEER_DEVIATION_AHEAD_S,
    show_default=True,
    help="A peer that would be off its trajectory this long later if both went straight on "
    "is avoided where it reported itself [s] (0: positions only).",
)
@click.option("--time-limit", "time_limit_s", default=80.0, show_default=True, help="[s]")
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option("--quiet", "-q", is_flag=True, help="Print only the totals.")
def bench_hidden(
    seeds: int,
    first: int,
    outage_from: float,
    outage_s: float,
    jobs: int,
    sets: tuple[str, ...],
    resend_s: str,
    resend_plans: bool,
    deviation_ahead_s: float,
    time_limit_s: float,
    json_path: Path | None,
    quiet: bool,
) -> None:
    """A drone whose uplink fails while it crosses a peer, in fast time: its closest approach,
    with and without the wider berth (``--set unheard_margin_m=0``)."""
    if seeds < 1:
        raise click.BadParameter("must be >= 1", param_hint="--seeds")
    if jobs < 1:
        raise click.BadParameter("must be >= 1", param_hint="--jobs")
    if not (math.isfinite(outage_from) and outage_from >= 0.0):
        raise click.BadParameter("must be >= 0", param_hint="--outage-from")
    if not (math.isfinite(outage_s) and outage_s >= 0.0):
        raise click.BadParameter("must be >= 0", param_hint="--outage-s")
    if not (math.isfinite(time_limit_s) and time_limit_s > 0.0):
        raise click.BadParameter("must be > 0", param_hint="--time-limit")
    try:
        resends = tuple(float(x) for x in resend_s.split(",") if x.strip())
    except ValueError:
        raise click.BadParameter(f"not numbers: {resend_s!r}", param_hint="--resend-s") from None
    try:
        resend_delays(resends)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--resend-s") from None
    if not (math.isfinite(deviation_ahead_s) and 0.0 <= deviation_ahead_s <= 5.0):
        raise click.BadParameter("must be in [0, 5]", param_hint="--deviation-ahead-s")
    from gcs.cli import _planner_params, _sets_v_max
    from onboard.config import ConfigError

    try:
        params = _planner_params(None, sets, None if _sets_v_max(sets) else 1.0)
    except ConfigError as exc:
        raise click.ClickException(str(exc)) from exc
    trials = [
        HiddenTrial(
            s, outage_from, outage_s, params, time_limit_s, resends, deviation_ahead_s, resend_plans
        )
        for s in range(first, first + seeds)
    ]
    rows: list[dict[str, Any]] = []
    if jobs == 1:
        for row in map(fly_hidden, trials):
            rows.append(row)
            _echo_row(row, quiet)
    else:
        ctx = multiprocessing.get_context("spawn")
        with sigterm_interrupts(), ctx.Pool(jobs) as pool:
            for row in pool.imap(fly_hidden, trials):
                rows.append(row)
                _echo_row(row, quiet)
    total = summarise(rows)
    h = total["hidden_closest_m"]
    click.echo(
        f"{total['flights']} flights, uplink of drone {HIDDEN} out {outage_s:g} s from "
        f"{outage_from:g} s, unheard_margin_m {params.unheard_margin_m:g}, resends "
        f"{resend_s or 'none'} s{'' if resend_plans else ' (stops only)'}, deviation ahead "
        f"{deviation_ahead_s:g} s: success "
        f"{total['success']}, collisions {total['collisions']} (seeds "
        f"{', '.join(map(str, total['collision_seeds'])) or '-'}); the hidden drone's closest "
        f"peer min {h['min']:.3f} / p10 {h['p10']:.3f} / median {h['median']:.3f} m, flights "
        f"under 0.5 / 0.6 m {total['hidden_under_0_5_m']} / {total['hidden_under_0_6_m']}; "
        f"the others' closest {total['others_closest_m']:.3f} m (under 0.5 m in "
        f"{total['others_under_0_5_m']}); flight median "
        f"{total['flight_time_s']['median']:.1f} s, max {total['flight_time_s']['max']:.1f} s; "
        f"plans told a peer did not hear them {total['unheard_plans']}"
    )
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        data = {
            "seeds": [first, first + seeds - 1],
            "outage_from_s": outage_from,
            "outage_s": outage_s,
            "unheard_margin_m": params.unheard_margin_m,
            "resend_s": list(resends),
            "resend_plans": resend_plans,
            "deviation_ahead_s": deviation_ahead_s,
            "total": total,
            "flights": rows,
        }
        json_path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
        click.echo(f"wrote {json_path}")


def _echo_row(row: dict[str, Any], quiet: bool) -> None:
    if quiet:
        return
    click.echo(
        f"seed {row['seed']:3d}: {'success' if row['success'] else 'FAILED'}, arrived "
        f"{row['arrived']}/3, collisions {row['collisions']}, hidden drone's closest peer "
        f"{row['hidden_closest_m']:.3f} m, others {row['others_closest_m']:.3f} m, "
        f"t {row['flight_time_s']:.1f} s, unheard plans {row['unheard_plans']}"
    )
