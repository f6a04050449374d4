"""Mapping benchmark (``swarm-gcs bench mapping``) and the perception options of the simulator.

The benchmark flies one simulated D435 through a world (medium forest by default) along a path
that keeps 0.6 m from the trunks (A* on the exact field, at 1 m height, 0.5 m/s, 30 frames/s,
yaw along the path), feeds every frame to a ``LocalMapper`` and measures:

- ``render_ms``: one 640 x 480 simulated frame (all pixels), noise and holes included;
- ``ingest_ms``: validating and ray casting one frame into the occupancy window (skip 2);
  ``ingest_cpu_ms`` the same call's CPU time in its thread (``time.thread_time``: on a shared
  machine it leaves out the time other processes held the core, so before/after comparisons
  of the mapper agree run to run better than the wall time);
- ``esdf_ms``: one ESDF refresh of the whole window (every ``--esdf-every`` frames);
- ``esdf_error_m``: ESDF value minus exact distance at the cell centres of observed space (see
  ``onboard.mapping.evaluate``), at snapshots every ``--error-every-s`` seconds;
  ``esdf_error_band_m`` the same for the cells whose centres lie in the planner's altitude band
  (the only space it plans in).

``--window`` places the window vertically: ``floor`` (the mapper's default: 4 m from 0.5 m below
the ground) or ``band`` (the planner's altitude band plus ``--band-margin`` each side, what the
flight service maps). ``--compare-windows`` feeds every frame to both, in alternating order,
and reports each one's CPU per frame and per ESDF refresh (``time.thread_time``, in one process,
so both see the same machine), its map quality, and how far their planning fields differ at
the cell centres of the band (``band_field_diff_m``).

Timings use ``time.perf_counter`` around single calls after one untimed warm-up frame.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from onboard.config import ConfigError, load_formation, load_world_spec
from onboard.mapping.simcam import D435_TYPICAL

TARGETS = {"ingest_ms.median": 15.0, "esdf_ms.median": 25.0, "esdf_error_m.p95": 0.1}


# --------------------------------------------------------------------------------------------
# Perception options for `swarm-gcs sim` and `swarm-gcs bench flights`
# --------------------------------------------------------------------------------------------

perception_option = click.option(
    "--perception",
    type=click.Choice(["ground-truth", "mapped"]),
    default="ground-truth",
    show_default=True,
    help="Distance field the drones plan on: exact obstacles within the sensing radius, or "
    "each drone's own map built from simulated D435 depth frames.",
)
camera_rate_option = click.option(
    "--camera-rate",
    "camera_rate_hz",
    type=click.FloatRange(min=0.0, min_open=True),
    default=30.0,
    show_default=True,
    help="Depth frames per second per drone (--perception mapped).",
)
skip_pixel_option = click.option(
    "--skip-pixel",
    "camera_skip_pixel",
    type=click.IntRange(min=1),
    default=2,
    show_default=True,
    help="Use every n-th pixel row and column of a depth frame (--perception mapped).",
)


def perception_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator adding --perception, --camera-rate and --skip-pixel to a click command; the
    command receives ``perception``, ``camera_rate_hz`` and ``camera_skip_pixel``."""
    return perception_option(camera_rate_option(skip_pixel_option(f)))


def perception_overrides(
    perception: str, camera_rate_hz: float, camera_skip_pixel: int
) -> dict[str, Any]:
    """Keyword arguments for ``dataclasses.replace(sim_config, **...)``."""
    return {
        "perception": perception,
        "camera_rate_hz": float(camera_rate_hz),
        "camera_skip_pixel": int(camera_skip_pixel),
    }


# --------------------------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MappingBenchConfig:
    """One benchmark run. Lengths in metres, times in seconds."""

    world: str = "forest-medium"
    seed: int = 1
    speed_m_s: float = 0.5
    rate_hz: float = 30.0
    height_m: float = 1.0
    skip_pixel: int = 2
    noise_std_1m_m: float = D435_TYPICAL.noise_std_1m_m
    """Depth noise at 1 m (grows with depth squared), see ``D435_TYPICAL``."""
    dropout: float = D435_TYPICAL.dropout
    holes: int = D435_TYPICAL.hole_count
    esdf_every: int = 3
    no_return_m: float | None = None
    """``OccupancyParams.no_return_m`` (None: its default; 0: pixels without a return clear
    nothing, the mapper before issue #11)."""
    error_every_s: float = 2.0
    error_band_m: float = 2.0
    max_frames: int = 0
    """0: the whole path."""
    window: str = "floor"
    """'floor': the ``OccupancyParams`` default window; 'band': fitted to ``band_m`` plus
    ``band_margin_m`` (``OccupancyParams.for_band``)."""
    band_m: tuple[float, float] = (0.3, 3.1)
    """The planner's altitude band (``PlannerParams.z_limits_m``' default)."""
    band_margin_m: float = 0.45
    """The service's ``mapping.window_band_margin_m`` default."""
    occluded_fill_m: float | None = None
    """``OccupancyParams.occluded_fill_m`` (None: its default)."""
    occluded_fill_behind_hits: bool | None = None
    """``OccupancyParams.occluded_fill_behind_hits`` (None: its default)."""
    occluded_fill_chord_m: float | None = None
    """``OccupancyParams.occluded_fill_chord_m`` (None: its default)."""


def flight_path(
    world: Any, start: np.ndarray, goal: np.ndarray, speed_m_s: float, rate_hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """Camera positions (K, 3) and yaws (K,) at ``rate_hz`` along an A* path that keeps 0.6 m
    from the obstacles (near the start's height); yaw follows the path, smoothed over 1 s."""
    from onboard.planner.astar import astar_path
    from onboard.planner.field import AnalyticField

    z = float(start[2])
    path = astar_path(
        AnalyticField(world), start, goal, clearance_m=0.6, z_limits=(z - 0.1, z + 0.1)
    )
    if path is None:
        raise ConfigError("no obstacle-free path from start to goal in this world")
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    ss = np.arange(0.0, s[-1], speed_m_s / rate_hz)
    pos = np.stack([np.interp(ss, s, path[:, a]) for a in range(3)], axis=1)
    heading = np.gradient(pos, axis=0)
    yaw = np.unwrap(np.arctan2(heading[:, 1], heading[:, 0]))
    k = max(1, int(round(rate_hz / 2)))
    yaw = np.convolve(np.pad(yaw, (k, k), mode="edge"), np.ones(2 * k + 1) / (2 * k + 1), "valid")
    return pos, yaw


def _stats(values: list[float] | np.ndarray) -> dict[str, float | None]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"median": None, "p90": None, "max": None, "mean": None, "n": 0}
    return {
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "max": float(np.max(a)),
        "mean": float(np.mean(a)),
        "n": int(a.size),
    }


def _error_stats(err: np.ndarray) -> dict[str, float | None]:
    if err.size == 0:
        return {"p50": None, "p95": None, "p99": None, "max": None, "mean_signed": None, "n": 0}
    a = np.abs(err)
    return {
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "max": float(np.max(a)),
        "mean_signed": float(np.mean(err)),
        "n": int(err.size),
    }


NEAR_PROBE_RADIUS_M = 1.5
NEAR_SURFACE_M = 0.6


def near_probe_offsets(res_m: float = 0.05) -> np.ndarray:
    """Offsets (K, 3) of a horizontal disc of ``NEAR_PROBE_RADIUS_M`` around the camera, on a
    ``res_m`` grid: where the drone's next plans lie."""
    g = np.arange(-NEAR_PROBE_RADIUS_M, NEAR_PROBE_RADIUS_M + 1e-9, res_m)
    x, y = np.meshgrid(g, g)
    keep = x**2 + y**2 <= NEAR_PROBE_RADIUS_M**2
    return np.stack([x[keep], y[keep], np.zeros(int(np.count_nonzero(keep)))], axis=1)


def near_overestimate(
    field: Any, world: Any, centre: np.ndarray, offsets: np.ndarray, inflation_m: float
) -> Any:
    """How much further than the truth the planning field puts the obstacles beside the drone:
    at the observed points of ``centre + offsets`` within ``NEAR_SURFACE_M`` of an obstacle
    surface, the field's value minus (the exact distance less the field's ``inflation_m``). Above
    0 the map has an obstacle short; above 0.1 m the drone's radius no longer covers it."""
    p = centre + offsets
    exact, _ = world.distance(p)
    near = (exact > 0.0) & (exact < NEAR_SURFACE_M)
    p, exact = p[near], exact[near]
    known = field.is_known(p)
    p, exact = p[known], exact[known]
    if p.shape[0] == 0:
        return np.zeros(0)
    d, _ = field.distance(p)
    return d - (exact - inflation_m)


def _overestimate_stats(e: np.ndarray) -> dict[str, float | None]:
    """Both tails: above 0 the map has an obstacle short (``over_0.1``: beyond the drone's
    radius), below 0 it has one too wide (``under_0.05`` / ``under_0.1``: by more than that)."""
    keys = ("p1", "p5", "p50", "p95", "p99", "max", "over_0.1", "under_0.05", "under_0.1")
    if e.size == 0:
        return {"n": 0, **{k: None for k in keys}}
    return {
        "n": int(e.size),
        "p1": float(np.percentile(e, 1)),
        "p5": float(np.percentile(e, 5)),
        "p50": float(np.percentile(e, 50)),
        "p95": float(np.percentile(e, 95)),
        "p99": float(np.percentile(e, 99)),
        "max": float(np.max(e)),
        "over_0.1": float(np.mean(e > 0.1)),
        "under_0.05": float(np.mean(e < -0.05)),
        "under_0.1": float(np.mean(e < -0.1)),
    }


WINDOWS = ("floor", "band")


def window_params(cfg: MappingBenchConfig, window: str | None = None) -> Any:
    """The ``OccupancyParams`` of the run (``window``: 'floor' or 'band', default
    ``cfg.window``)."""
    from onboard.mapping import OccupancyParams

    occ = OccupancyParams(skip_pixel=cfg.skip_pixel).for_frame_rate(cfg.rate_hz)
    if cfg.no_return_m is not None:
        occ = dataclasses.replace(occ, no_return_m=cfg.no_return_m)
    if cfg.occluded_fill_m is not None:
        occ = dataclasses.replace(occ, occluded_fill_m=cfg.occluded_fill_m)
    if cfg.occluded_fill_behind_hits is not None:
        occ = dataclasses.replace(occ, occluded_fill_behind_hits=cfg.occluded_fill_behind_hits)
    if cfg.occluded_fill_chord_m is not None:
        occ = dataclasses.replace(occ, occluded_fill_chord_m=cfg.occluded_fill_chord_m)
    w = cfg.window if window is None else window
    if w == "band":
        return occ.for_band(cfg.band_m[0], cfg.band_m[1], cfg.band_margin_m)
    if w != "floor":
        raise ConfigError(f"window: expected one of {', '.join(WINDOWS)}, got {w!r}")
    return occ


def band_crop(field: Any, band: tuple[float, float]) -> Any:
    """The field's cells whose centres lie in ``band`` (z), as an ``EsdfField`` of their own (the
    same values and masks), for measuring the map where the planner flies."""
    from onboard.mapping.esdf import EsdfField

    k = _band_cells(field, band)
    if k.size == 0:
        raise ValueError(f"no cell of the window lies in the band {band}")
    sl = slice(int(k[0]), int(k[-1]) + 1)
    origin = field.origin + np.array([0.0, 0.0, k[0] * field.res])
    return EsdfField(
        field.values[:, :, sl],
        origin,
        field.res,
        field.known[:, :, sl],
        field.occupied[:, :, sl],
        field.inflation_m,
        field.stamp_s,
    )


def _window_summary(occ: Any) -> dict[str, Any]:
    lo = occ.floor_z_m
    return {
        "window_cells": list(occ.shape),
        "floor_z_m": lo,
        "headroom_m": occ.headroom_m,
        "z_range_m": None if lo is None else [lo, lo + occ.shape[2] * occ.resolution_m],
    }


def _planning_diff(a: Any, b: Any, band: tuple[float, float]) -> tuple[float, int, int, int]:
    """(max |a - b|, cells compared, cells differing by more than 1e-6 m, cells whose known
    flag differs) over the cell centres in ``band`` that both fields hold (the same cell grid,
    shifted in z)."""
    res = a.res
    ka = np.rint(a.origin / res).astype(np.int64)
    kb = np.rint(b.origin / res).astype(np.int64)
    if np.any(ka[:2] != kb[:2]):
        raise ValueError("the two windows differ in x or y")
    lo_k = max(ka[2], kb[2], int(math.floor(band[0] / res)))
    hi_k = min(ka[2] + a.shape[2], kb[2] + b.shape[2], int(math.ceil(band[1] / res)))
    va = a.values[:, :, lo_k - ka[2] : hi_k - ka[2]]
    vb = b.values[:, :, lo_k - kb[2] : hi_k - kb[2]]
    kna = a.known[:, :, lo_k - ka[2] : hi_k - ka[2]]
    knb = b.known[:, :, lo_k - kb[2] : hi_k - kb[2]]
    d = np.abs(va - vb)
    return (
        float(d.max()) if d.size else 0.0,
        int(d.size),
        int(np.count_nonzero(d > 1e-6)),
        int(np.count_nonzero(kna != knb)),
    )


def _flight(cfg: MappingBenchConfig) -> tuple[Any, np.ndarray, np.ndarray, Any]:
    """World, camera positions and yaws, and the simulated camera of a run."""
    from onboard.mapping import SimCameraParams
    from onboard.mapping.simcam import SimulatedDepthCamera

    spec = load_world_spec(cfg.world)
    world, starts, goals = spec.build(cfg.seed, load_formation("triangle-3"))
    c_start = spec.start_center if spec.start_center is not None else starts.mean(axis=0)
    c_goal = spec.goal_center if spec.goal_center is not None else goals.mean(axis=0)
    start = np.array([*c_start[:2], cfg.height_m])
    goal = np.array([*c_goal[:2], cfg.height_m])
    pos, yaw = flight_path(world, start, goal, cfg.speed_m_s, cfg.rate_hz)
    if cfg.max_frames > 0:
        pos, yaw = pos[: cfg.max_frames], yaw[: cfg.max_frames]
    cam = SimulatedDepthCamera(
        world,
        params=SimCameraParams(
            noise_std_1m_m=cfg.noise_std_1m_m, dropout=cfg.dropout, hole_count=cfg.holes
        ),
        seed=cfg.seed,
    )
    return world, pos, yaw, cam


def run_window_comparison(
    cfg: MappingBenchConfig, progress: Callable[[int, int], None] | None = None
) -> dict[str, Any]:
    """Both windows (``WINDOWS``) on the same frames of one flight, fed in alternating order
    (frame k: 'floor' first when k is even), each refreshing its ESDF every ``esdf_every``
    frames: CPU per frame and per refresh (thread time), map quality (as
    ``run_mapping_bench``) and the difference of their planning fields in the band."""
    from onboard.mapping import LocalMapper, look_rotation
    from onboard.mapping.evaluate import esdf_errors

    world, pos, yaw, cam = _flight(cfg)
    occs = {w: window_params(cfg, w) for w in WINDOWS}
    mappers = {w: LocalMapper(occs[w]) for w in WINDOWS}
    for w in WINDOWS:  # warm-up: load the kernels outside the timings
        LocalMapper(occs[w]).ingest(cam.capture(pos[0], look_rotation(yaw[0]), -1.0))
        LocalMapper(occs[w]).field()
    ingest_cpu: dict[str, list[float]] = {w: [] for w in WINDOWS}
    esdf_cpu: dict[str, list[float]] = {w: [] for w in WINDOWS}
    err: dict[str, list[np.ndarray]] = {w: [] for w in WINDOWS}
    err_band: dict[str, list[np.ndarray]] = {w: [] for w in WINDOWS}
    diffs: list[tuple[float, int, int, int]] = []
    recent: list[Any] = []
    keep = int(round(5.0 * cfg.rate_hz))
    error_every = max(1, int(round(cfg.error_every_s * cfg.rate_hz)))
    n = pos.shape[0]
    for k in range(n):
        frame = cam.capture(pos[k], look_rotation(float(yaw[k])), k / cfg.rate_hz)
        recent.append(frame)
        if len(recent) > keep:
            recent.pop(0)
        order = WINDOWS if k % 2 == 0 else WINDOWS[::-1]
        for w in order:
            c0 = time.thread_time()
            mappers[w].ingest(frame)
            ingest_cpu[w].append((time.thread_time() - c0) * 1e3)
        if (k + 1) % cfg.esdf_every == 0:
            fields = {}
            for w in order:
                c0 = time.thread_time()
                mappers[w].field()
                esdf_cpu[w].append((time.thread_time() - c0) * 1e3)
                fields[w] = mappers[w].planning_field()
            diffs.append(_planning_diff(fields["floor"], fields["band"], cfg.band_m))
            if (k + 1) % error_every == 0:
                for w in WINDOWS:
                    f = mappers[w].field()
                    for acc, g in ((err, f), (err_band, band_crop(f, cfg.band_m))):
                        ee = esdf_errors(
                            g,
                            world,
                            recent[::3],
                            cfg.skip_pixel,
                            band_m=cfg.error_band_m,
                            max_range_m=occs[w].max_ray_m,
                        )
                        acc[w].append(ee.all)
        if progress is not None:
            progress(k + 1, n)
    from gcs.bench import machine_info

    out: dict[str, Any] = {
        "scenario": {
            **dataclasses.asdict(cfg),
            "world_name": world.name,
            "frames": int(n),
            "alternation": "frame k: floor first when k is even, band first when odd",
        },
        "windows": {},
        "band_field_diff_m": {
            "max": max((d[0] for d in diffs), default=0.0),
            "cells_compared_per_refresh": diffs[0][1] if diffs else 0,
            "cells_differing_over_1e-6": int(sum(d[2] for d in diffs)),
            "known_flags_differing": int(sum(d[3] for d in diffs)),
            "refreshes": len(diffs),
        },
        "machine": machine_info(),
    }
    for w in WINDOWS:
        m = mappers[w]
        f = m.field()
        band_k = _band_cells(f, cfg.band_m)
        ea = np.concatenate(err[w]) if err[w] else np.zeros(0)
        eb = np.concatenate(err_band[w]) if err_band[w] else np.zeros(0)
        known = _known(f)
        out["windows"][w] = {
            **_window_summary(occs[w]),
            "ingest_cpu_ms": _stats(ingest_cpu[w]),
            "esdf_cpu_ms": _stats(esdf_cpu[w]),
            "esdf_error_m": _error_stats(ea),
            "esdf_error_band_m": _error_stats(eb),
            "known_cells_final": int(np.count_nonzero(known)),
            "known_cells_band_final": int(np.count_nonzero(known[:, :, band_k])),
            "occupied_cells_final": int(np.count_nonzero(f.occupied)),
        }
    a, b = esdf_cpu["floor"], esdf_cpu["band"]
    ratios = np.asarray(b) / np.maximum(np.asarray(a), 1e-9)
    ia, ib = ingest_cpu["floor"], ingest_cpu["band"]
    out["band_over_floor"] = {
        "esdf_cpu_median_pair_ratio": float(np.median(ratios)) if ratios.size else None,
        "esdf_cpu_mean_ratio": float(np.mean(b) / np.mean(a)) if a else None,
        "ingest_cpu_mean_ratio": float(np.mean(ib) / np.mean(ia)) if ia else None,
    }
    return out


def _known(field: Any) -> np.ndarray:
    known = field.known
    if known is None:  # an EsdfField always has its mask
        raise ValueError("the field has no known mask")
    return np.asarray(known)


def _band_cells(field: Any, band: tuple[float, float]) -> np.ndarray:
    """z indices of the field's cells whose centres lie in the band."""
    zc = field.origin[2] + (np.arange(field.shape[2]) + 0.5) * field.res
    return np.flatnonzero((zc >= band[0]) & (zc <= band[1]))


def run_mapping_bench(
    cfg: MappingBenchConfig,
    progress: Callable[[int, int], None] | None = None,
    ply_path: Path | None = None,
) -> dict[str, Any]:
    """Run the benchmark; returns the JSON-able report."""
    from onboard.mapping import EsdfBuilder, LocalMapper, look_rotation
    from onboard.mapping.evaluate import esdf_errors

    world, pos, yaw, cam = _flight(cfg)
    occ = window_params(cfg)
    mapper = LocalMapper(occ)
    # warm-up: compile / load the kernels outside the timings
    LocalMapper(occ).ingest(cam.capture(pos[0], look_rotation(yaw[0]), -1.0))
    LocalMapper(occ).field()

    render_ms: list[float] = []
    ingest_ms: list[float] = []
    ingest_cpu_ms: list[float] = []
    clear_rays: list[float] = []
    esdf_ms: list[float] = []
    esdf_cpu_ms: list[float] = []
    rejected = 0
    errors_free: list[np.ndarray] = []
    errors_occ: list[np.ndarray] = []
    errors_band: list[np.ndarray] = []
    over_near: list[np.ndarray] = []
    errors_filled: list[np.ndarray] = []
    fill = occ.occluded_fill_cells
    observed_builder = EsdfBuilder()
    probes = near_probe_offsets()
    recent: list[Any] = []
    keep = int(round(5.0 * cfg.rate_hz))  # frames of the last 5 s define "observed"

    def errors_of(f: Any) -> Any:
        """The field's errors in the space the recent frames observed."""
        return esdf_errors(
            f,
            world,
            recent[::3],
            cfg.skip_pixel,
            band_m=cfg.error_band_m,
            max_range_m=occ.max_ray_m,
        )

    error_every = max(1, int(round(cfg.error_every_s * cfg.rate_hz)))
    n = pos.shape[0]
    for k in range(n):
        t_s = k / cfg.rate_hz
        t0 = time.perf_counter()
        frame = cam.capture(pos[k], look_rotation(float(yaw[k])), t_s)
        c1 = time.thread_time()
        t1 = time.perf_counter()
        res = mapper.ingest(frame)
        t2 = time.perf_counter()
        c2 = time.thread_time()
        render_ms.append((t1 - t0) * 1e3)
        ingest_ms.append((t2 - t1) * 1e3)
        ingest_cpu_ms.append((c2 - c1) * 1e3)
        clear_rays.append(float(res.clear_rays))
        rejected += 0 if res.accepted else 1
        recent.append(frame)
        if len(recent) > keep:
            recent.pop(0)
        if (k + 1) % cfg.esdf_every == 0:
            t3 = time.perf_counter()
            c3 = time.thread_time()
            field = mapper.field()
            esdf_cpu_ms.append((time.thread_time() - c3) * 1e3)
            esdf_ms.append((time.perf_counter() - t3) * 1e3)
            if (k + 1) % error_every == 0:
                # the accuracy of the distances to what was observed (the field without the
                # shadow fill, whose distances are lower on purpose beside unobserved space)
                observed = field if fill == 0 else observed_builder.build(mapper.map, fill_cells=0)
                e = errors_of(observed)
                errors_free.append(e.free)
                errors_occ.append(e.occupied)
                errors_filled.append(e.all if observed is field else errors_of(field).all)
                eb = errors_of(band_crop(observed, cfg.band_m))
                errors_band.append(eb.all)
                over_near.append(
                    near_overestimate(
                        mapper.planning_field(), world, pos[k], probes, occ.inflation_m
                    )
                )
        if progress is not None:
            progress(k + 1, n)
    from gcs.bench import machine_info

    err_f = np.concatenate(errors_free) if errors_free else np.zeros(0)
    err_o = np.concatenate(errors_occ) if errors_occ else np.zeros(0)
    report: dict[str, Any] = {
        "scenario": {
            **dataclasses.asdict(cfg),
            "world_name": world.name,
            "path_length_m": float(np.sum(np.linalg.norm(np.diff(pos, axis=0), axis=1))),
            "frames": int(n),
            **_window_summary(occ),
            "resolution_m": occ.resolution_m,
            "no_return_m": occ.no_return_m,
            "occluded_fill_m": occ.occluded_fill_m,
            "occluded_fill_behind_hits": occ.occluded_fill_behind_hits,
            "occluded_fill_chord_m": occ.occluded_fill_chord_m,
        },
        "render_ms": _stats(render_ms),
        "ingest_ms": _stats(ingest_ms),
        "ingest_cpu_ms": _stats(ingest_cpu_ms),
        "no_return_rays": _stats(clear_rays),
        "known_cells_final": int(np.count_nonzero(mapper.map.known())),
        "known_cells_band_final": int(
            np.count_nonzero(_known(mapper.field())[:, :, _band_cells(mapper.field(), cfg.band_m)])
        ),
        "esdf_ms": _stats(esdf_ms),
        "esdf_cpu_ms": _stats(esdf_cpu_ms),
        "esdf_error_m": _error_stats(np.concatenate([err_f, err_o])),
        "esdf_error_band_m": _error_stats(
            np.concatenate(errors_band) if errors_band else np.zeros(0)
        ),
        "esdf_error_filled_m": _error_stats(
            np.concatenate(errors_filled) if errors_filled else np.zeros(0)
        ),
        "near_overestimate_m": _overestimate_stats(
            np.concatenate(over_near) if over_near else np.zeros(0)
        ),
        "esdf_error_free_m": _error_stats(err_f),
        "esdf_error_occupied_m": _error_stats(err_o),
        "rejected_frames": rejected,
        "occupied_cells_final": int(np.count_nonzero(mapper.map.occupied())),
        "machine": machine_info(),
    }
    report["targets"] = {
        key: {
            "target": limit,
            "value": _lookup(report, key),
            "met": _lookup(report, key) is not None and _lookup(report, key) <= limit,
        }
        for key, limit in TARGETS.items()
    }
    if ply_path is not None:
        from onboard.sensors.cloud import save_map_ply

        report["ply_points"] = save_map_ply(ply_path, mapper.map)
        report["ply_path"] = str(ply_path)
    return report


def _lookup(report: dict[str, Any], dotted: str) -> Any:
    out: Any = report
    for part in dotted.split("."):
        out = out[part]
    return out


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


@click.command("mapping")
@click.option("--world", default="forest-medium", show_default=True, help="World name or file.")
@click.option("--seed", default=1, show_default=True, help="Seed of the world.")
@click.option(
    "--skip-pixel",
    default=2,
    show_default=True,
    type=click.IntRange(min=1),
    help="Ray cast every n-th pixel row and column.",
)
@click.option(
    "--noise-1m",
    "noise_1m",
    default=D435_TYPICAL.noise_std_1m_m,
    show_default=True,
    type=click.FloatRange(min=0.0),
    help="Depth noise std at 1 m [m] (grows with depth squared).",
)
@click.option(
    "--dropout",
    default=D435_TYPICAL.dropout,
    show_default=True,
    type=click.FloatRange(0.0, 1.0),
    help="Fraction of pixels without a measurement.",
)
@click.option(
    "--holes",
    default=D435_TYPICAL.hole_count,
    show_default=True,
    type=click.IntRange(min=0),
    help="Rectangular holes per frame.",
)
@click.option(
    "--rate",
    "rate_hz",
    default=30.0,
    show_default=True,
    type=click.FloatRange(min=0.0, min_open=True),
    help="Depth frames per second (the flight is at 0.5 m/s).",
)
@click.option(
    "--occluded-fill",
    "occluded_fill_m",
    default=None,
    type=click.FloatRange(0.0, 1.0),
    help="Never-observed cells this close to an obstacle count as occupied [m] (0: none) "
    "[default: the mapper's].",
)
@click.option(
    "--fill-behind-hits/--fill-square",
    "occluded_fill_behind_hits",
    default=None,
    help="Fill only never-observed cells behind a hit along its ray, or every one near an "
    "obstacle in its layer [default: the mapper's].",
)
@click.option(
    "--fill-chord",
    "occluded_fill_chord_m",
    default=None,
    type=click.FloatRange(0.0, 5.0),
    help="Behind hits: a ray's fill reaches at most this times the cosine of its incidence "
    "[m] (0: the whole --occluded-fill) [default: the mapper's].",
)
@click.option(
    "--esdf-every",
    default=3,
    show_default=True,
    type=click.IntRange(min=1),
    help="Refresh the ESDF every n-th frame (3: 10 Hz at 30 frames/s).",
)
@click.option(
    "--no-return-m",
    "no_return_m",
    default=None,
    type=click.FloatRange(min=0.0),
    help="Pixels without a return clear free space up to this length [m] (0: none, the "
    "mapper before issue #11) [default: the mapper's, 5].",
)
@click.option(
    "--max-frames",
    default=0,
    show_default=True,
    type=click.IntRange(min=0),
    help="Stop after this many frames (0: the whole crossing).",
)
@click.option(
    "--window",
    type=click.Choice(WINDOWS),
    default="floor",
    show_default=True,
    help="Vertical placement of the window: the mapper's default (4 m from 0.5 m below the "
    "ground) or the planner's altitude band plus --band-margin each side (the service's).",
)
@click.option(
    "--band",
    "band_m",
    nargs=2,
    type=float,
    default=(0.3, 3.1),
    show_default=True,
    help="The planner's altitude band [m] (--window band, errors in the band).",
)
@click.option(
    "--band-margin",
    "band_margin_m",
    default=0.45,
    show_default=True,
    type=click.FloatRange(min=0.0, min_open=True),
    help="Window margin below and above the band [m] (--window band).",
)
@click.option(
    "--compare-windows",
    is_flag=True,
    help="Map every frame into both windows (alternating which goes first) and compare "
    "their CPU per frame and per ESDF refresh, quality, and planning fields in the band.",
)
@click.option(
    "--ply",
    "ply_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Save the final map as a .ply point cloud.",
)
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write JSON."
)
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
def bench_mapping(
    world: str,
    seed: int,
    skip_pixel: int,
    noise_1m: float,
    dropout: float,
    holes: int,
    rate_hz: float,
    occluded_fill_m: float | None,
    occluded_fill_behind_hits: bool | None,
    occluded_fill_chord_m: float | None,
    esdf_every: int,
    no_return_m: float | None,
    max_frames: int,
    window: str,
    band_m: tuple[float, float],
    band_margin_m: float,
    compare_windows: bool,
    ply_path: Path | None,
    json_path: Path | None,
    quiet: bool,
) -> None:
    """Fly a simulated D435 through a world; time frame ingest and ESDF refresh, and measure
    the ESDF against the exact distance in observed space."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    console = Console(quiet=quiet, highlight=False)
    cfg = MappingBenchConfig(
        world=world,
        seed=seed,
        skip_pixel=skip_pixel,
        noise_std_1m_m=noise_1m,
        dropout=dropout,
        holes=holes,
        rate_hz=rate_hz,
        occluded_fill_m=occluded_fill_m,
        occluded_fill_behind_hits=occluded_fill_behind_hits,
        occluded_fill_chord_m=occluded_fill_chord_m,
        esdf_every=esdf_every,
        no_return_m=no_return_m,
        max_frames=max_frames,
        window=window,
        band_m=(float(band_m[0]), float(band_m[1])),
        band_margin_m=band_margin_m,
    )
    if not cfg.band_m[0] < cfg.band_m[1]:
        raise click.BadParameter("need low < high", param_hint="--band")
    with Progress(
        TextColumn("frames"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=quiet,
    ) as bar:
        task = bar.add_task("frames", total=None)

        def cb(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        try:
            if compare_windows:
                report = run_window_comparison(cfg, progress=cb)
            else:
                report = run_mapping_bench(cfg, progress=cb, ply_path=ply_path)
        except ConfigError as e:
            raise click.ClickException(str(e)) from e
    if compare_windows:
        _print_comparison(console, report)
        _write_json(console, json_path, report)
        return

    sc = report["scenario"]
    t = Table(
        title=f"mapping: {sc['frames']} frames through {sc['world_name']}, "
        f"window {'x'.join(str(c) for c in sc['window_cells'])} cells of {sc['resolution_m']} m"
    )
    t.add_column("quantity")
    for col in ("median", "p90", "max", "target", "met"):
        t.add_column(col, justify="right")
    for name, key in (
        ("render one 640x480 frame [ms]", "render_ms"),
        (f"ingest one frame, skip {skip_pixel} [ms]", "ingest_ms"),
        ("  CPU time of it [ms]", "ingest_cpu_ms"),
        ("ESDF refresh of the window [ms]", "esdf_ms"),
    ):
        s = report[key]
        tgt = report["targets"].get(f"{key}.median")
        t.add_row(
            name,
            _fmt(s["median"]),
            _fmt(s["p90"]),
            _fmt(s["max"]),
            _fmt(tgt["target"], ".0f") if tgt else "",
            ("yes" if tgt["met"] else "NO") if tgt else "",
        )
    console.print(t)
    etab = Table(title="ESDF error in observed space [m] (|estimate - exact|, cells within 2 m)")
    etab.add_column("cells")
    for col in ("n", "p50", "p95", "p99", "max", "mean signed"):
        etab.add_column(col, justify="right")
    for name, key in (
        ("all observed", "esdf_error_m"),
        ("free", "esdf_error_free_m"),
        ("occupied", "esdf_error_occupied_m"),
        ("all, shadows filled (planned on)", "esdf_error_filled_m"),
    ):
        s = report[key]
        etab.add_row(
            name,
            str(s["n"]),
            _fmt(s["p50"], ".3f"),
            _fmt(s["p95"], ".3f"),
            _fmt(s["p99"], ".3f"),
            _fmt(s["max"], ".3f"),
            _fmt(s["mean_signed"], "+.3f"),
        )
    console.print(etab)
    ov = report["near_overestimate_m"]
    console.print(
        f"beside the drone (observed points within {NEAR_SURFACE_M} m of a surface, "
        f"{NEAR_PROBE_RADIUS_M} m around it; {ov['n']}): the planning field reads the obstacle "
        f"further than it is by p50 {_fmt(ov['p50'], '+.3f')}, p95 {_fmt(ov['p95'], '+.3f')}, "
        f"p99 {_fmt(ov['p99'], '+.3f')} m; more than the inflation at "
        f"{_fmt(None if ov['over_0.1'] is None else 100 * ov['over_0.1'], '.1f')} %; nearer "
        f"than it is by p5 {_fmt(ov['p5'], '+.3f')}, p1 {_fmt(ov['p1'], '+.3f')} m, by more "
        f"than 0.05 / 0.1 m at "
        f"{_fmt(None if ov['under_0.05'] is None else 100 * ov['under_0.05'], '.1f')} / "
        f"{_fmt(None if ov['under_0.1'] is None else 100 * ov['under_0.1'], '.1f')} % "
        f"(occluded fill {sc['occluded_fill_m']:g} m, "
        + (
            f"behind hits, chord {sc['occluded_fill_chord_m']:g} m)"
            if sc["occluded_fill_behind_hits"]
            else "square)"
        )
    )
    tg = report["targets"]["esdf_error_m.p95"]
    console.print(
        f"ESDF error p95 {_fmt(tg['value'], '.3f')} m (target <= {tg['target']} m: "
        f"{'met' if tg['met'] else 'NOT met'}); rejected frames {report['rejected_frames']}"
    )
    ic, nr = report["ingest_cpu_ms"], report["no_return_rays"]
    console.print(
        f"ingest CPU mean {_fmt(ic['mean'])} ms; no-return rays (up to "
        f"{sc['no_return_m']:g} m) per frame mean {_fmt(nr['mean'], '.0f')}; known cells at the "
        f"end {report['known_cells_final']}"
    )
    m = report["machine"]
    console.print(f"{m['cpu']} x{m['cpu_count']}, Python {m['python']}, numba {m['numba']}")
    if ply_path is not None:
        console.print(f"wrote {ply_path} ({report['ply_points']} points)")
    _write_json(console, json_path, report)


def _write_json(console: Any, json_path: Path | None, report: dict[str, Any]) -> None:
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        console.print(f"wrote {json_path}")


def _print_comparison(console: Any, report: dict[str, Any]) -> None:
    from rich.table import Table

    sc = report["scenario"]
    t = Table(title=f"windows compared: {sc['frames']} frames through {sc['world_name']}")
    t.add_column("quantity")
    for w in WINDOWS:
        t.add_column(w, justify="right")
    ws = report["windows"]

    def row(name: str, get: Callable[[dict[str, Any]], Any], spec: str = ".2f") -> None:
        t.add_row(name, *(_fmt(get(ws[w]), spec) for w in WINDOWS))

    t.add_row("cells", *("x".join(str(c) for c in ws[w]["window_cells"]) for w in WINDOWS))
    t.add_row(
        "z range (m)",
        *(
            "-" if ws[w]["z_range_m"] is None else "{:.2f}..{:.2f}".format(*ws[w]["z_range_m"])
            for w in WINDOWS
        ),
    )
    row("ingest CPU per frame, mean [ms]", lambda r: r["ingest_cpu_ms"]["mean"])
    row("ESDF CPU per refresh, median [ms]", lambda r: r["esdf_cpu_ms"]["median"])
    row("ESDF CPU per refresh, mean [ms]", lambda r: r["esdf_cpu_ms"]["mean"])
    row("ESDF error p95, all observed [m]", lambda r: r["esdf_error_m"]["p95"], ".3f")
    row("ESDF error p99, all observed [m]", lambda r: r["esdf_error_m"]["p99"], ".3f")
    row("ESDF error p95, in the band [m]", lambda r: r["esdf_error_band_m"]["p95"], ".3f")
    row("ESDF error p99, in the band [m]", lambda r: r["esdf_error_band_m"]["p99"], ".3f")
    row("known cells at the end", lambda r: r["known_cells_final"], ".0f")
    row("  of them in the band", lambda r: r["known_cells_band_final"], ".0f")
    console.print(t)
    r = report["band_over_floor"]
    d = report["band_field_diff_m"]
    console.print(
        f"band / floor: ESDF CPU median pair ratio {_fmt(r['esdf_cpu_median_pair_ratio'], '.3f')}"
        f", mean ratio {_fmt(r['esdf_cpu_mean_ratio'], '.3f')}; ingest CPU mean ratio "
        f"{_fmt(r['ingest_cpu_mean_ratio'], '.3f')}"
    )
    console.print(
        f"planning fields in the band, {d['refreshes']} refreshes x "
        f"{d['cells_compared_per_refresh']} cells: max |difference| {d['max']:.3g} m, "
        f"{d['cells_differing_over_1e-6']} cell values differ by more than 1e-6 m, "
        f"{d['known_flags_differing']} known flags differ"
    )
