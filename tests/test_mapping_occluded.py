"""The shadow of an obstacle (``OccupancyParams.occluded_fill_m``): never-observed cells next to
an occupied one count as occupied in the ESDF, so the side of a trunk the camera never faced
is not free space beside the side it saw."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage

from onboard.mapping import LocalMapper, OccupancyMap, OccupancyParams, look_rotation
from onboard.mapping.esdf import fill_occluded
from onboard.mapping.occupancy import UNKNOWN_LOGODDS
from onboard.mapping.simcam import D435_TYPICAL, SimulatedDepthCamera
from onboard.world import World


def _slots(omap: OccupancyMap) -> tuple[np.ndarray, ...]:
    """The ring buffer's storage slots of the window's cells, in window order."""
    g = np.stack(
        np.meshgrid(*[omap.lo[a] + np.arange(omap.shape[a]) for a in range(3)], indexing="ij"), -1
    )
    return omap.storage_index(g.reshape(-1, 3))


@pytest.mark.parametrize("cells", [1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fill_is_the_layer_dilation_kept_to_unknown_cells(cells: int, seed: int) -> None:
    """The kernel against scipy's binary dilation by a square of 2 * cells + 1 in each layer,
    kept to the never-observed cells, in window order: the ring buffer's wrap (a window whose
    corner is not a multiple of its size) never carries a fill across the window's edges."""
    rng = np.random.default_rng(seed)
    prm = OccupancyParams(size_m=(1.3, 1.1, 0.7), floor_z_m=None)
    omap = OccupancyMap(prm, center=rng.uniform(-3.0, 3.0, 3))
    state = rng.choice(3, size=omap.shape, p=[0.6, 0.3, 0.1])  # unknown, free, occupied
    state[:, 0, :] = 2  # a full slab at the window's y edge: nothing wraps to its other side
    window = np.where(state == 0, UNKNOWN_LOGODDS, np.where(state == 1, prm.l_min, prm.l_max))
    window = window.astype(np.float32)
    omap.logodds[_slots(omap)] = window.reshape(-1)
    unknown = state == 0
    square = np.ones((2 * cells + 1, 2 * cells + 1, 1), bool)
    expect = (state == 2) | (ndimage.binary_dilation(state == 2, structure=square) & unknown)
    out = np.empty_like(omap.logodds)
    queue = np.empty(omap.logodds.size, np.int64)
    n_occ, n_all = fill_occluded(omap.logodds, omap.lo, prm.l_occ, cells, out, queue)
    got = out[_slots(omap)].reshape(omap.shape)
    np.testing.assert_array_equal(got >= prm.l_occ, expect)
    assert n_occ == int(np.count_nonzero(state == 2))
    # the queue lists the filled cells (window order), each once
    filled = np.zeros(omap.shape, bool).reshape(-1)
    filled[queue[n_occ:n_all]] = True
    assert n_all - n_occ == int(np.count_nonzero(filled)) > 0
    np.testing.assert_array_equal(filled.reshape(omap.shape), expect & unknown)
    # observed cells keep their values; the filled ones read exactly l_occ
    np.testing.assert_array_equal(got[~unknown], window[~unknown])
    assert np.all(got[expect & unknown] == np.float32(prm.l_occ))
    assert np.all(got[unknown & ~expect] == UNKNOWN_LOGODDS)


def _passed_trunk(fill_m: float) -> tuple[LocalMapper, float]:
    """A camera at 1 m height flies along +x past a trunk (radius 0.3 m) 1 m to its left at
    5 frames/s and 0.5 m/s, looking ahead: the trunk leaves the view before the part of it
    turned towards the path behind it faces the camera."""
    r = 0.3
    world = World(
        cylinders=np.array([[5.0, 1.0, r, 0.0, 3.0]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    cam = SimulatedDepthCamera(
        world,
        params=dataclasses.replace(D435_TYPICAL, step=3, noise_std_1m_m=0.0, dropout=0.0),
        seed=1,
    )
    prm = dataclasses.replace(
        OccupancyParams(skip_pixel=3).for_band(0.3, 3.1, 0.45), occluded_fill_m=fill_m
    )
    mapper = LocalMapper(prm)
    for k, x in enumerate(np.arange(0.0, 10.0, 0.1)):
        assert mapper.ingest(
            cam.capture(np.array([x, 0.0, 1.0]), look_rotation(0.0), k / 5)
        ).accepted
    return mapper, r


def _overestimate(mapper: LocalMapper, r: float, angle_deg: float, d: float) -> float:
    """The planning field's value at ``d`` from the trunk's surface at ``angle_deg`` (from +x)
    minus what it should read there (the true distance less the inflation)."""
    a = math.radians(angle_deg)
    p = np.array([[5.0 + (r + d) * math.cos(a), 1.0 + (r + d) * math.sin(a), 1.0]])
    f = mapper.planning_field()
    assert f.is_known(p)[0]
    return float(f.distance(p)[0][0]) - (d - mapper.params.inflation_m)


def test_the_unseen_side_of_a_passed_trunk_is_not_free() -> None:
    with_fill, r = _passed_trunk(0.2)
    without, _ = _passed_trunk(0.0)
    for d in (0.05, 0.15, 0.3):
        # beside the path behind the trunk: observed free space, the trunk's surface unseen
        assert _overestimate(without, r, 330.0, d) > 0.08
        assert _overestimate(with_fill, r, 330.0, d) < 0.05  # within the grid's own error
        # the side the camera faced reads the same either way
        assert _overestimate(with_fill, r, 270.0, d) == pytest.approx(
            _overestimate(without, r, 270.0, d), abs=1e-6
        )
    # the filled cells are obstacles to the distances, but still unobserved space
    f, g = without.field(), with_fill.field()
    np.testing.assert_array_equal(f.known, g.known)
    assert np.count_nonzero(g.occupied & ~g.known) > 0 == np.count_nonzero(f.occupied & ~f.known)
    assert np.count_nonzero(g.occupied) > np.count_nonzero(f.occupied)


def test_the_fill_only_lowers_distances() -> None:
    """Filling shadows adds occupied cells and nothing else: the occupied cells are a superset,
    and every value of the field (and of the planning field) is at most what it is without, but
    for half a cell: a free cell whose nearest occupied cell (by centres) becomes a filled one
    reads that cell's centre, where its former nearest had a measured surface point up to half
    a cell nearer."""
    world = World(
        cylinders=np.array([[2.5, 0.6, 0.3, 0.0, 2.5], [3.2, -1.0, 0.2, 0.0, 2.5]]),
        rings=np.array([[3.5, 1.5, 1.2, 0.3, 0.5, 0.4, 0.08]]),
        boxes=np.array([[2.0, -2.2, 0.0, 2.6, -1.6, 1.5]]),
        ground_z=0.0,
    )
    fields = []
    for fill in (0.0, 0.2):
        cam = SimulatedDepthCamera(
            world, params=dataclasses.replace(D435_TYPICAL, step=2), seed=3
        )  # the same frames (noise, holes) for both maps
        prm = OccupancyParams(size_m=(6.0, 6.0, 3.0), occluded_fill_m=fill)
        mapper = LocalMapper(prm, center=np.array([2.0, 0.0, 1.0]))
        for k, yaw in enumerate((0.0, -0.3, 0.3, 0.5)):
            frame = cam.capture(np.array([0.0, 0.2 * k - 0.3, 1.0]), look_rotation(yaw), 0.1 * k)
            assert mapper.ingest(frame, recenter=False).accepted
        fields.append((mapper.field(), mapper.planning_field()))
    (f0, p0), (f1, p1) = fields
    half = 0.5 * f0.res
    assert np.all(f1.values <= f0.values + half) and np.all(p1.values <= p0.values + half)
    assert np.any(f1.values < f0.values - 0.05)
    assert np.all(f1.occupied[f0.occupied])
    np.testing.assert_array_equal(f1.known, f0.known)


@pytest.mark.parametrize("value", [-0.1, 1.5, math.nan])
def test_occluded_fill_is_checked(value: float) -> None:
    with pytest.raises(ValueError, match="occluded_fill_m"):
        OccupancyParams(occluded_fill_m=value)
