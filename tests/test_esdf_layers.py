"""The ESDF of some of the window's layers (``OccupancyParams.esdf_z_m``, ``esdf_layers``): each
layer it covers is, bit for bit, that layer of the whole window's ESDF (the pass along z runs
over the whole window, the passes after it layer by layer)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.mapping import (
    EsdfBuilder,
    LocalMapper,
    OccupancyMap,
    OccupancyParams,
    SimCameraParams,
    look_rotation,
)
from onboard.mapping.esdf import esdf_kernel, esdf_layers
from onboard.mapping.simcam import SimulatedDepthCamera
from onboard.planner.field import UNKNOWN_DISTANCE
from onboard.world import World


def _run(om: OccupancyMap, sub_cell: bool, k0: int, k1: int) -> tuple[np.ndarray, ...]:
    sh = om.shape
    nk = (k1 if k1 >= 0 else sh[2]) - k0
    rng = np.random.default_rng(1)  # work buffers full of garbage, as a reused builder's are
    f_out = rng.normal(size=sh).astype(np.float32)
    feat = rng.integers(-5, 5, size=sh).astype(np.int32)
    f_in = rng.normal(size=sh).astype(np.float32)
    spt = rng.normal(size=(int(np.prod(sh)), 3)).astype(np.float32)
    occ = rng.random(sh) < 0.5
    known = rng.random(sh) < 0.5
    values = rng.normal(size=(sh[0], sh[1], nk))
    inflated = rng.normal(size=(sh[0], sh[1], nk))
    n_occ, bad = esdf_kernel(
        om.logodds,
        om.surf,
        om.lo,
        om.params.l_occ,
        om.res,
        0.5 * om.res,
        sub_cell,
        UNKNOWN_DISTANCE,
        f_out,
        feat,
        f_in,
        occ,
        known,
        spt,
        values,
        0.1,
        inflated,
        k0,
        k1,
    )
    assert bad == 0
    return values, inflated, occ, known


def _assert_layers_equal_the_whole(om: OccupancyMap) -> None:
    nz = om.shape[2]
    for sub_cell in (True, False):
        whole = _run(om, sub_cell, 0, -1)
        for k0, k1 in ((0, nz), (1, nz - 1), (2, 5), (0, 1), (nz - 1, nz), (3, nz)):
            part = _run(om, sub_cell, k0, k1)
            for name, a, b in zip(("values", "inflated"), part[:2], whole[:2], strict=True):
                # bit for bit (array_equal would let -0.0 pass for 0.0)
                assert a.tobytes() == b[:, :, k0:k1].copy().tobytes(), (name, k0, k1)
            assert np.array_equal(part[2], whole[2]) and np.array_equal(part[3], whole[3])


def _random_map(rng: np.random.Generator, density: float) -> OccupancyMap:
    p = OccupancyParams(size_m=(2.3, 1.9, 1.3), floor_z_m=None)
    om = OccupancyMap(p, center=rng.normal(scale=3.0, size=3))
    u = rng.random(om.shape)
    lg = np.where(u < density, 2.0, np.where(u < density + 0.4, -1.5, -100.0))
    nx, ny, _ = om.shape
    lg[rng.integers(nx), rng.integers(ny), :] = 2.0  # a solid column
    lg[:, rng.integers(ny), :] = -1.5  # a free slab
    om.logodds[...] = lg.astype(np.float32)
    om.surf[:, :3] = rng.uniform(-0.05, 0.05, size=(om.surf.shape[0], 3))
    om.surf[:, 3] = rng.integers(0, 4, size=om.surf.shape[0])
    return om


def test_layers_equal_the_whole_windows_on_random_maps() -> None:
    rng = np.random.default_rng(11)
    # up to solid blocks, whose inside transform falls back to the envelope passes
    for density in (0.0, 0.01, 0.1, 0.5, 0.95, 1.0):
        _assert_layers_equal_the_whole(_random_map(rng, density))


def _mapped_forest() -> LocalMapper:
    world = World(
        cylinders=np.array(
            [[2.0, 0.4, 0.25, 0.0, 3.0], [3.5, -0.5, 0.2, 0.0, 3.0], [4.0, 2.0, 0.3, 0.0, 1.6]]
        ),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    cam = SimulatedDepthCamera(world, params=SimCameraParams(step=2), seed=3)
    base = OccupancyParams(size_m=(6.0, 5.0, 4.0))
    mapper = LocalMapper(base.for_band(0.3, 2.1, 0.4))
    for k in range(24):  # along x, so the window rolls
        p = np.array([-0.5 + 0.05 * k, 0.2, 1.0])
        mapper.ingest(cam.capture(p, look_rotation(0.1 * np.sin(k)), k / 30.0))
    return mapper


def test_layers_equal_the_whole_windows_on_a_mapped_forest_and_through_the_builder() -> None:
    mapper = _mapped_forest()
    om = mapper.map
    assert np.count_nonzero(om.logodds >= om.params.l_occ) > 200
    assert np.any(om.lo % np.array(om.shape) != 0)  # a rolled ring buffer
    _assert_layers_equal_the_whole(om)
    # the builder: window -0.1 .. 2.5 m, the field the band's layers 0.2 .. 2.2 m
    assert om.shape[2] == 26 and om.origin[2] == pytest.approx(-0.1)
    assert esdf_layers(om) == (3, 23)
    part = EsdfBuilder().build(om, inflate_m=0.1)
    whole_map = dataclasses.replace(om.params, esdf_z_m=None)
    om.params = whole_map  # the same cells, the whole window's ESDF
    whole = EsdfBuilder().build(om, inflate_m=0.1)
    assert part.shape == (60, 50, 20) and whole.shape == (60, 50, 26)
    assert part.origin == pytest.approx(whole.origin + [0.0, 0.0, 0.3])
    assert part.upper[2] == pytest.approx(2.2)
    assert part.values.tobytes() == whole.values[:, :, 3:23].copy().tobytes()
    assert part.inflated(0.1).values.tobytes() == whole.inflated(0.1).values[:, :, 3:23].tobytes()
    assert part.known is not None and whole.known is not None
    assert np.array_equal(part.known, whole.known[:, :, 3:23])
    assert np.array_equal(part.occupied, whole.occupied[:, :, 3:23])
    assert part.known.flags.c_contiguous and part.occupied.flags.c_contiguous
    # queries in the band read the same; below the field's box, unknown space
    rng = np.random.default_rng(2)
    pts = om.origin + rng.random((3000, 3)) * (om.upper - om.origin)
    pts[:, 2] = rng.uniform(0.3, 2.1, 3000)
    dp, gp = part.distance(pts)
    dw, gw = whole.distance(pts)
    assert np.allclose(dp, dw, rtol=0.0, atol=1e-9) and np.allclose(gp, gw, atol=1e-6)
    assert np.array_equal(part.is_known(pts), whole.is_known(pts))
    assert not part.is_known(np.array([[1.0, 0.2, 0.1]]))[0]


def test_esdf_layers_cover_every_centre_the_band_interpolates_from() -> None:
    p = OccupancyParams().for_band(0.3, 3.1, 0.4)
    om = OccupancyMap(p, center=np.array([0.0, 0.0, 1.0]))
    k0, k1 = esdf_layers(om)
    zc = om.origin[2] + (np.arange(om.shape[2]) + 0.5) * om.res
    assert zc[k0] == pytest.approx(0.25) and zc[k1 - 1] == pytest.approx(3.15)
    assert (k0, k1) == (3, 33)
    # a band edge on a cell centre: that centre is in (one more cell below, to be safe)
    om2 = OccupancyMap(dataclasses.replace(p, esdf_z_m=(0.25, 3.15)), np.array([0.0, 0.0, 1.0]))
    a, b = esdf_layers(om2)
    assert zc[a] <= 0.25 + 1e-9 and zc[b - 1] >= 3.15 - 1e-9
    # a window that reaches (almost) none of the band: the whole window
    om3 = OccupancyMap(dataclasses.replace(p, esdf_z_m=(10.0, 11.0)), np.array([0.0, 0.0, 1.0]))
    assert esdf_layers(om3) == (0, om3.shape[2])
    assert esdf_layers(OccupancyMap(OccupancyParams())) == (0, 40)
    with pytest.raises(ValueError, match="esdf_z_m"):
        OccupancyParams(esdf_z_m=(2.0, 1.0))
