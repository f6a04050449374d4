"""The map window fitted to the planner's altitude band (``OccupancyParams.for_band``, the
service's ``mapping.window_band_margin_m``): where it lies, that it drops only layers that hold
nothing, and that the planner's field inside the band is what the taller window gives."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from onboard.config import ConfigError, load_formation, load_world_spec
from onboard.mapping import LocalMapper, OccupancyParams, look_rotation
from onboard.mapping.simcam import D435_TYPICAL, SimulatedDepthCamera
from onboard.service.config import load_onboard_config

BAND = (0.3, 3.1)


def _z_range(mapper: LocalMapper) -> tuple[float, float]:
    return float(mapper.map.origin[2]), float(mapper.map.upper[2])


def test_default_band_gives_the_old_top_without_the_layers_under_the_ground() -> None:
    p = OccupancyParams().for_band(*BAND, 0.4)
    assert p.shape == (110, 110, 36)
    assert p.size_m[:2] == (11.0, 11.0)
    m = LocalMapper(p)
    for z in (0.0, 0.3, 1.0, 2.6, 3.1):  # anywhere in the band (and on the ground): fixed
        m.recenter(np.array([5.0, -2.0, z]))
        assert _z_range(m) == pytest.approx((-0.1, 3.5))
    # the default window, for comparison: same top while the drone flies below 2.5 m ...
    old = LocalMapper(OccupancyParams())
    old.recenter(np.array([0.0, 0.0, 1.0]))
    assert _z_range(old) == pytest.approx((-0.5, 3.5))
    # ... but it rises off the ground above that, where the band window stays
    old.recenter(np.array([0.0, 0.0, 3.0]))
    assert _z_range(old)[0] == pytest.approx(0.0)


def test_band_window_rises_above_the_band_and_follows_a_camera_below_its_floor() -> None:
    m = LocalMapper(OccupancyParams().for_band(*BAND, 0.4))
    m.recenter(np.array([0.0, 0.0, 3.45]))  # 0.35 m above the band: keeps 0.4 m above it
    lo, hi = _z_range(m)
    assert hi > 3.45 + 0.4 - 0.1 and hi - lo == pytest.approx(3.6)  # (to a cell)
    m.recenter(np.array([0.0, 0.0, -0.35]))  # a drone standing below the map's ground
    lo, hi = _z_range(m)
    assert lo <= -0.35 - 0.1 + 1e-9 and hi - lo == pytest.approx(3.6)
    assert bool(m.map.contains(np.array([[0.0, 0.0, -0.35]]))[0])


def test_for_band_rounds_out_to_whole_cells_and_refuses_bad_input() -> None:
    p = OccupancyParams().for_band(0.33, 2.01, 0.25)
    assert p.floor_z_m == pytest.approx(0.0) and p.shape[2] == 23  # 0.0 .. 2.3 m
    assert p.headroom_m == pytest.approx(2.3 - 2.01)
    with pytest.raises(ValueError, match="margin_m"):
        OccupancyParams().for_band(*BAND, 0.0)
    with pytest.raises(ValueError, match="z_lo < z_hi"):
        OccupancyParams().for_band(2.0, 1.0, 0.4)


def test_planning_field_in_the_band_is_the_taller_windows() -> None:
    """The same frames of a flight at 1 m through the small forest into the default window and
    the band window: the layers the band window leaves out (under -0.1 m) were never observed,
    and the planning fields agree inside the band (to float rounding: the surface points are
    kept relative to the window's corner) with the same known cells. The band window's field
    covers the cells the band interpolates from (0.2 .. 3.2 m)."""
    world, _, _ = load_world_spec("forest-small").build(1, load_formation("triangle-3"))
    cam = SimulatedDepthCamera(world, params=dataclasses.replace(D435_TYPICAL, step=3), seed=1)
    base = OccupancyParams(size_m=(8.0, 8.0, 4.0), skip_pixel=3)
    tall = LocalMapper(base)
    band = LocalMapper(base.for_band(*BAND, 0.4))
    for k in range(24):
        pos = np.array([-1.5 + 0.05 * k, 0.3 * np.sin(0.2 * k), 1.0])
        frame = cam.capture(pos, look_rotation(0.15 * np.sin(0.3 * k)), k / 30.0)
        assert tall.ingest(frame, step=3).accepted and band.ingest(frame, step=3).accepted
    ft, fb = tall.planning_field(), band.planning_field()
    assert _z_range(tall) == pytest.approx((-0.5, 3.5))
    assert _z_range(band) == pytest.approx((-0.1, 3.5))
    assert ft.known is not None and fb.known is not None
    # (the field fills the ground's shadow under it: OccupancyParams.occluded_fill_m)
    assert not np.any(ft.known[:, :, :4]) and not np.any(tall.map.occupied()[:, :, :4])
    assert np.any(band.map.occupied()[:, :, 0])  # the ground is still in the window
    assert fb.origin[2] == pytest.approx(0.2) and fb.upper[2] == pytest.approx(3.2)
    # cell centres 0.25 .. 3.15 m: every one the planner interpolates from inside the band
    k_t = slice(7, 37)
    k_b = slice(0, 30)
    assert np.allclose(ft.values[:, :, k_t], fb.values[:, :, k_b], rtol=0.0, atol=1e-5)
    assert np.array_equal(ft.known[:, :, k_t], fb.known[:, :, k_b])
    rng = np.random.default_rng(3)
    pts = np.column_stack(
        [rng.uniform(-5.0, 3.0, 2000), rng.uniform(-4.0, 4.0, 2000), rng.uniform(*BAND, 2000)]
    )
    inside = tall.map.contains(pts) & band.map.contains(pts)
    dt, gt = ft.distance(pts[inside])
    db, gb = fb.distance(pts[inside])
    assert np.allclose(dt, db, rtol=0.0, atol=1e-5) and np.allclose(gt, gb, atol=1e-3)
    assert np.array_equal(ft.is_known(pts), fb.is_known(pts))


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "onboard.yaml"
    p.write_text(text, encoding="utf-8")
    return p


def test_service_maps_the_band_window(tmp_path: Path) -> None:
    cfg = load_onboard_config(_write(tmp_path, ""))
    assert cfg.mapping.window_band_margin_m == pytest.approx(0.45)
    assert cfg.map_params.shape == (110, 110, 38)
    assert cfg.map_params.floor_z_m == pytest.approx(-0.2)
    # the shipped config file maps the same window
    assert load_onboard_config().map_params == cfg.map_params
    # the band cut to the geofence: the window follows (0.3 .. 2.5 m, -0.2 .. 3.0 m)
    cut = load_onboard_config(_write(tmp_path, "geofence:\n  max_enu_m: [50, 50, 2.5]\n"))
    assert cut.map_params.shape[2] == 32 and cut.map_params.floor_z_m == pytest.approx(-0.2)
    # null: the window as occupancy places it
    off = load_onboard_config(_write(tmp_path, "mapping:\n  window_band_margin_m: null\n"))
    assert off.map_params == off.mapping.occupancy == OccupancyParams()
    # what the service maps (and its warm-up compiles): that window with a camera, none without
    assert cfg.depth.source != "none" and cfg.camera_map_params == cfg.map_params
    blind = load_onboard_config(_write(tmp_path, "depth:\n  source: none\n"))
    assert blind.camera_map_params is None
    # the map's hit weight follows the camera's frame rate (30 by default: the reference's)
    assert cfg.depth.rate_hz == 30.0 and cfg.map_params.p_hit == OccupancyParams().p_hit
    slow = load_onboard_config(_write(tmp_path, "depth:\n  rate_hz: 3\n"))
    assert slow.map_params.p_hit == OccupancyParams().for_frame_rate(3.0).p_hit > 0.8
    assert slow.map_params.shape == cfg.map_params.shape


@pytest.mark.parametrize(
    ("text", "where", "what"),
    [
        ("mapping:\n  window_band_margin_m: 0.4\n", "mapping.window_band_margin_m", "0.45"),
        (
            "planner:\n  check_obstacle_m: 0.35\n",
            "mapping.window_band_margin_m",
            "safety check",
        ),
        (
            "mapping:\n  occupancy: {size_m: [11, 11, 3.0]}\n",
            "mapping.occupancy.size_m",
            "3.8 m tall",
        ),
        ("mapping:\n  occupancy: {floor_z_m: -0.3}\n", "mapping", "occupancy.floor_z_m"),
        ("mapping:\n  occupancy: {headroom_m: 0.5}\n", "mapping", "occupancy.headroom_m"),
    ],
)
def test_band_window_config_errors(tmp_path: Path, text: str, where: str, what: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_onboard_config(_write(tmp_path, text))
    msg = str(e.value)
    assert where + ":" in msg and what in msg, msg


def test_bench_mapping_compares_the_windows(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from gcs.bench_mapping import bench_mapping

    out = tmp_path / "w.json"
    # a margin whose band window lies inside the floor window (-0.5 to 3.5 m), so that the two
    # observe the same cells (the service's 0.45 m reaches 0.1 m above it)
    args = [
        "--band-margin",
        "0.4",
        "--world",
        "forest-small",
        "--skip-pixel",
        "3",
        "--max-frames",
        "60",
        "--esdf-every",
        "6",
    ]
    res = CliRunner().invoke(bench_mapping, [*args, "--compare-windows", "--json", str(out)])
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    floor, band = data["windows"]["floor"], data["windows"]["band"]
    assert floor["window_cells"][2] == 40 and band["window_cells"][2] == 36
    assert band["z_range_m"] == pytest.approx([-0.1, 3.5])
    for w in (floor, band):
        assert w["esdf_cpu_ms"]["n"] == 10 and w["ingest_cpu_ms"]["n"] == 60
        assert w["esdf_error_band_m"]["n"] > 1000
    assert band["known_cells_band_final"] == floor["known_cells_band_final"] > 0
    diff = data["band_field_diff_m"]
    assert diff["refreshes"] == 10 and diff["max"] < 1e-5 and diff["known_flags_differing"] == 0
    assert data["band_over_floor"]["esdf_cpu_median_pair_ratio"] > 0.0
    # one window on its own: the band errors and the ESDF's CPU are in the report too
    res = CliRunner().invoke(bench_mapping, [*args, "--window", "band", "--json", str(out)])
    assert res.exit_code == 0, res.output
    one = json.loads(out.read_text())
    assert one["scenario"]["window_cells"][2] == 36 and one["esdf_cpu_ms"]["n"] == 10
    assert one["esdf_error_band_m"]["n"] > 1000
