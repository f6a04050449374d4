"""The ESDF kernel's faster passes give bit for bit what the plain passes gave.

The reference below is the kernel as it was before those passes were cut (a column pass that
scans every column twice, the envelope along x over lines a plane apart in memory, no line
skipped: its float64 "nothing here" never equalled the grid's float32 one); what did not change
(the envelope along y, the inside search, the combination) is shared. Both run on the same
maps: random ones of every density, with unknown cells, solid columns, empty columns and a
rolled window, and a window mapped from rendered depth frames of a small forest.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from numba import njit

from onboard.mapping import (
    EsdfBuilder,
    LocalMapper,
    OccupancyMap,
    OccupancyParams,
    SimCameraParams,
    SimulatedDepthCamera,
    look_rotation,
)
from onboard.mapping.esdf import (
    _INSIDE_SEARCH_CELLS,
    _combine,
    _envelope_pass,
    _inside_local,
    esdf_kernel,
    fill_occluded,
)
from onboard.planner.field import UNKNOWN_DISTANCE
from onboard.world import World

_UNKNOWN_BELOW = -50.0


@njit(cache=True)
def _reference_column_pass(
    logodds: np.ndarray,
    surf: np.ndarray,
    lo: np.ndarray,
    l_occ: float,
    res: float,
    f_out: np.ndarray,
    feat: np.ndarray,
    f_in: np.ndarray,
    occ: np.ndarray,
    known: np.ndarray,
    spt: np.ndarray,
) -> int:
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    big = 1e30
    n_occ = 0
    sz_of = np.empty(nz, dtype=np.int64)
    for wk in range(nz):
        s = (lo[2] + wk) % nz
        sz_of[wk] = s + nz if s < 0 else s
    for wi in range(nx):
        si = (lo[0] + wi) % nx
        if si < 0:
            si += nx
        for wj in range(ny):
            sj = (lo[1] + wj) % ny
            if sj < 0:
                sj += ny
            last_occ = -1
            last_free = -1
            for wk in range(nz):
                v = logodds[si, sj, sz_of[wk]]
                o = v >= l_occ
                occ[wi, wj, wk] = o
                known[wi, wj, wk] = v > _UNKNOWN_BELOW
                if o:
                    n_occ += 1
                    last_occ = wk
                    e = (si * ny + sj) * nz + sz_of[wk]
                    c = surf[e, 3]
                    spt[wi, wj, wk, 0] = (wi + 0.5) * res
                    spt[wi, wj, wk, 1] = (wj + 0.5) * res
                    spt[wi, wj, wk, 2] = (wk + 0.5) * res
                    if c > 0.0:
                        spt[wi, wj, wk, 0] += surf[e, 0] / c
                        spt[wi, wj, wk, 1] += surf[e, 1] / c
                        spt[wi, wj, wk, 2] += surf[e, 2] / c
                else:
                    last_free = wk
                f_out[wi, wj, wk] = (wk - last_occ) if last_occ >= 0 else big
                f_in[wi, wj, wk] = (wk - last_free) if last_free >= 0 else big
                feat[wi, wj, wk] = (wi * ny + wj) * nz + last_occ
            last_occ = -1
            last_free = -1
            for wk in range(nz - 1, -1, -1):
                if occ[wi, wj, wk]:
                    last_occ = wk
                else:
                    last_free = wk
                if last_occ >= 0 and last_occ - wk < f_out[wi, wj, wk]:
                    f_out[wi, wj, wk] = last_occ - wk
                if last_free >= 0:
                    f_in[wi, wj, wk] = min(f_in[wi, wj, wk], last_free - wk)
                if last_occ >= 0 and last_occ - wk <= f_out[wi, wj, wk]:
                    feat[wi, wj, wk] = (wi * ny + wj) * nz + last_occ
                a = f_out[wi, wj, wk]
                b = f_in[wi, wj, wk]
                f_out[wi, wj, wk] = a * a if a < big else big
                f_in[wi, wj, wk] = b * b if b < big else big
    return n_occ


def _reference(
    om: OccupancyMap, sub_cell: bool, margin: float
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    sh = om.shape
    f_out = np.empty(sh, dtype=np.float32)
    feat = np.empty(sh, dtype=np.int32)
    f_in = np.empty(sh, dtype=np.float32)
    occ = np.empty(sh, dtype=np.bool_)
    known = np.empty(sh, dtype=np.bool_)
    spt = np.empty((*sh, 3), dtype=np.float32)
    values = np.empty(sh)
    inflated = np.empty(sh)
    res = om.res
    n_occ = _reference_column_pass(
        om.logodds, om.surf, om.lo, om.params.l_occ, res, f_out, feat, f_in, occ, known, spt
    )
    _envelope_pass(f_out, 1, 1e30, feat, sub_cell)
    _envelope_pass(f_out, 0, 1e30, feat, sub_cell)
    if n_occ > 0 and not _inside_local(occ, f_in, n_occ, _INSIDE_SEARCH_CELLS):
        _envelope_pass(f_in, 1, 0.0, feat, False)
        _envelope_pass(f_in, 0, 0.0, feat, False)
    bad = _combine(
        f_out,
        feat,
        f_in,
        occ,
        known,
        spt,
        res,
        0.5 * res,
        sub_cell,
        UNKNOWN_DISTANCE,
        values,
        margin,
        inflated,
        True,
    )
    assert bad == 0
    return n_occ, values, inflated, occ, known


def _kernel(
    om: OccupancyMap, sub_cell: bool, margin: float
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    sh = om.shape
    # work buffers full of garbage, as a reused builder's are
    rng = np.random.default_rng(0)
    f_out = rng.normal(size=sh).astype(np.float32)
    feat = rng.integers(-5, 5, size=sh).astype(np.int32)
    f_in = rng.normal(size=sh).astype(np.float32)
    spt = rng.normal(size=(int(np.prod(sh)), 3)).astype(np.float32)
    occ = rng.random(sh) < 0.5
    known = rng.random(sh) < 0.5
    values = rng.normal(size=sh)
    inflated = rng.normal(size=sh)
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
        margin,
        inflated,
    )
    assert bad == 0
    return n_occ, values, inflated, occ, known


def _assert_same(om: OccupancyMap, sub_cell: bool) -> None:
    ref = _reference(om, sub_cell, 0.1)
    got = _kernel(om, sub_cell, 0.1)
    assert got[0] == ref[0]
    for name, a, b in zip(("values", "inflated", "occ", "known"), got[1:], ref[1:], strict=True):
        assert a.dtype == b.dtype, name
        # bit for bit (array_equal would let -0.0 pass for 0.0)
        assert a.tobytes() == b.tobytes(), name


def _random_map(rng: np.random.Generator, density: float) -> OccupancyMap:
    p = OccupancyParams(size_m=(2.3, 1.9, 1.3), floor_z_m=None)
    om = OccupancyMap(p, center=rng.normal(scale=3.0, size=3))
    u = rng.random(om.shape)
    lg = np.where(u < density, 2.0, np.where(u < density + 0.4, -1.5, -100.0))
    # exactly at the threshold, just below it, cleared, clamped
    lg[rng.random(om.shape) < 0.03] = p.l_occ
    lg[rng.random(om.shape) < 0.03] = np.nextafter(np.float32(p.l_occ), np.float32(0.0))
    nx, ny, _ = om.shape
    lg[rng.integers(nx), rng.integers(ny), :] = 2.0  # a solid column
    lg[rng.integers(nx), rng.integers(ny), :] = -100.0  # an unknown one
    lg[:, rng.integers(ny), :] = -1.5  # a free slab
    om.logodds[...] = lg.astype(np.float32)
    om.surf[:, :3] = rng.uniform(-0.05, 0.05, size=(om.surf.shape[0], 3))
    om.surf[:, 3] = rng.integers(0, 4, size=om.surf.shape[0])
    return om


@pytest.mark.parametrize("sub_cell", [True, False])
def test_esdf_kernel_equals_the_plain_passes_on_random_maps(sub_cell: bool) -> None:
    rng = np.random.default_rng(5)
    for density in (0.0, 0.002, 0.02, 0.1, 0.3, 0.6, 0.9, 1.0):
        _assert_same(_random_map(rng, density), sub_cell)


def test_esdf_kernel_equals_the_plain_passes_on_a_mapped_forest() -> None:
    world = World(
        cylinders=np.array(
            [[2.0, 0.4, 0.25, 0.0, 3.0], [3.5, -0.5, 0.2, 0.0, 3.0], [4.0, 2.0, 0.3, 0.0, 3.0]]
        ),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    cam = SimulatedDepthCamera(world, params=SimCameraParams(step=2), seed=3)
    mapper = LocalMapper(OccupancyParams(size_m=(6.0, 5.0, 3.0)))
    for k in range(24):  # along x, so the window rolls
        p = np.array([-0.5 + 0.05 * k, 0.2, 1.0])
        mapper.ingest(cam.capture(p, look_rotation(0.1 * np.sin(k)), k / 30.0))
    om = mapper.map
    assert np.count_nonzero(om.logodds >= om.params.l_occ) > 200
    assert np.any(om.lo % np.array(om.shape) != 0)  # a rolled ring buffer
    for sub_cell in (True, False):
        _assert_same(om, sub_cell)
    # and through the builder the service uses: the transform of the map with the shadows of
    # its obstacles filled (OccupancyParams.occluded_fill_m, behind hits: the cells that hold
    # the points their rays marked, whose mean is the filled cell's surface point), the filled
    # cells still unknown
    prm = om.params
    assert prm.occluded_fill_cells == 4 and prm.occluded_fill_behind_hits
    f = EsdfBuilder().build(om, inflate_m=0.1)
    filled = copy.copy(om)
    filled.logodds = np.empty_like(om.logodds)
    queue = np.empty(om.logodds.size, dtype=np.int64)
    n_occ, n_all = fill_occluded(
        om.logodds, om.lo, prm.l_occ, 4, filled.logodds, queue, om.surf, True
    )
    assert n_all - n_occ > 100
    ref = _reference(filled, True, 0.1)
    assert f.values.tobytes() == ref[1].tobytes()
    assert f.inflated(0.1).values.tobytes() == ref[2].tobytes()
    known = ref[4].copy()
    known.reshape(-1)[queue[n_occ:n_all]] = False
    np.testing.assert_array_equal(f.known, known)
    np.testing.assert_array_equal(f.known, _reference(om, True, 0.1)[4])
