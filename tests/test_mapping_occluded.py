"""The shadow of an obstacle (``OccupancyParams.occluded_fill_m``): never-observed cells next to
an occupied one count as occupied in the ESDF, so the side of a trunk the camera never faced
is not free space beside the side it saw."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage

from onboard.mapping import EsdfBuilder, LocalMapper, OccupancyMap, OccupancyParams, look_rotation
from onboard.mapping.camera import CameraIntrinsics
from onboard.mapping.esdf import fill_occluded
from onboard.mapping.occupancy import UNKNOWN_LOGODDS, _incidence_cos
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
    n_occ, n_all = fill_occluded(
        omap.logodds, omap.lo, prm.l_occ, cells, out, queue, omap.surf, False
    )
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


def _passed_trunk(
    fill_m: float, behind_hits: bool = False, chord_m: float = 0.0
) -> tuple[LocalMapper, float]:
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
        OccupancyParams(skip_pixel=3).for_band(0.3, 3.1, 0.45),
        occluded_fill_m=fill_m,
        occluded_fill_behind_hits=behind_hits,
        occluded_fill_chord_m=chord_m,
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


def _filled_centres(mapper: LocalMapper) -> np.ndarray:
    """Centres (K, 3) of the field's filled cells: occupied for the distances, never observed."""
    f = mapper.field()
    return f.origin + (np.argwhere(f.occupied & ~f.known) + 0.5) * f.res


def test_the_fill_behind_hits_covers_the_unseen_side_without_widening_the_trunk() -> None:
    """``occluded_fill_behind_hits``: only cells behind a hit along its ray, each ray's fill cut
    to ``occluded_fill_chord_m`` times the cosine of its incidence. It covers the unseen side
    as the square fill does, but keeps the filled cells at the trunk: the square fill also
    takes never-observed cells beside it that no ray passed behind it."""
    square, r = _passed_trunk(0.2)
    rays, _ = _passed_trunk(0.4, behind_hits=True, chord_m=0.7)
    world = World(
        cylinders=np.array([[5.0, 1.0, r, 0.0, 3.0]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    out_square, _ = world.distance(_filled_centres(square))
    out_rays, _ = world.distance(_filled_centres(rays))
    assert out_rays.size > 100
    # a trunk 0.6 m thick, the chord rule's 0.7 m: at most 0.1 m * cos(i) past its far side
    # along a ray, and half a cell's diagonal from a point to its cell's centre
    assert np.max(out_rays) < 0.11
    assert np.max(out_square) > 0.2
    for d in (0.05, 0.15):
        assert _overestimate(rays, r, 330.0, d) < 0.05
    # with the chord rule off, the full length behind grazing rays reaches further out
    long_rays, _ = _passed_trunk(0.4, behind_hits=True)
    assert np.max(world.distance(_filled_centres(long_rays))[0]) > 0.15


def _plane_depth(
    intr: CameraIntrinsics, normal: np.ndarray, dist: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth image (float32) of the plane n . p = dist (camera frame, n unit) and the
    normalised pixel coordinates."""
    xn, yn = intr.normalized_coords()
    ray = np.stack(np.broadcast_arrays(xn[None, :], yn[:, None], 1.0), -1)
    return (dist / (ray @ normal)).astype(np.float32), xn, yn


@pytest.mark.parametrize("tilt_deg", [0.0, 20.0, 35.0])
@pytest.mark.parametrize("pixel", [(240, 320), (100, 500), (0, 0), (479, 639)])
def test_incidence_cos_of_a_plane(tilt_deg: float, pixel: tuple[int, int]) -> None:
    """On a plane (central differences, one-sided at the image's edge) it is the exact
    |cos| between the ray and the plane's normal."""
    intr = CameraIntrinsics()
    t = math.radians(tilt_deg)
    normal = np.array([math.sin(t), 0.2 * math.cos(t), math.cos(t)])
    normal /= np.linalg.norm(normal)
    depth, xn, yn = _plane_depth(intr, normal, 2.0)
    v, u = pixel
    ray = np.array([xn[u], yn[v], 1.0])
    expect = abs(ray @ normal) / np.linalg.norm(ray)
    assert np.all(depth > 0.0) and np.max(depth) < 20.0  # the plane fills the view
    assert _incidence_cos(depth, u, v, 6, xn, yn) == pytest.approx(expect, abs=2e-3)


def test_incidence_cos_is_zero_at_an_edge_or_a_hole() -> None:
    intr = CameraIntrinsics()
    depth, xn, yn = _plane_depth(intr, np.array([0.0, 0.0, 1.0]), 2.0)
    assert _incidence_cos(depth, 320, 240, 6, xn, yn) == pytest.approx(1.0, abs=1e-3)
    step = depth.copy()
    step[:, 323:] = 3.0  # a trunk's silhouette: the background 1 m behind it
    assert _incidence_cos(step, 320, 240, 6, xn, yn) == 0.0
    for bad in (0.0, math.nan, math.inf, -1.0):
        hole = depth.copy()
        hole[234, 320] = bad
        assert _incidence_cos(hole, 320, 240, 6, xn, yn) == 0.0


def test_a_shadow_is_forgotten_once_its_cell_is_observed() -> None:
    """The points a hit leaves behind it in never-observed cells make them fill cells; the
    cell's first hit starts its surface point afresh, and a cell a ray crosses is free."""
    prm = OccupancyParams(
        size_m=(4.0, 4.0, 2.0),
        floor_z_m=None,
        occluded_fill_m=0.4,
        occluded_fill_behind_hits=True,
    )
    omap = OccupancyMap(prm, center=np.zeros(3))
    hit = np.array([[0.55, 0.05, 0.05]])
    for _ in range(3):  # occupied after three hits
        assert omap.ingest_points(np.array([-1.0, 0.05, 0.05]), hit).accepted
    behind = np.array([[0.75, 0.05, 0.05], [0.85, 0.05, 0.05]])  # two cell centres behind it
    slots = omap.storage_index(np.floor(behind / prm.resolution_m))
    flat = np.ravel_multi_index(slots, omap.shape)
    assert np.all(omap.logodds[slots] == UNKNOWN_LOGODDS)
    assert np.all(omap.surf[flat, 3] > 0)  # shadow points, the cells still never observed
    f = EsdfBuilder().build(omap)
    assert not np.any(f.is_known(behind))
    assert np.all(f.distance(behind)[0] <= 0.0)  # obstacles to the distances
    # the first cell's first hit, from the side: its surface point is that hit alone
    q = np.array([[0.77, 0.02, 0.08]])
    assert omap.ingest_points(np.array([0.77, -1.0, 0.08]), q).accepted
    centre = (np.floor(q[0] / prm.resolution_m) + 0.5) * prm.resolution_m
    np.testing.assert_allclose(omap.surf[flat[0]], [*(q[0] - centre), 1.0], atol=1e-6)
    # a ray through the second cell: observed free, so no longer filled
    assert omap.ingest_points(np.array([0.85, -1.0, 0.05]), np.array([[0.85, 1.5, 0.05]])).accepted
    f = EsdfBuilder().build(omap)
    assert f.is_known(behind[1:])[0]
    assert f.distance(behind[1:])[0][0] > 0.0


@pytest.mark.parametrize("behind_hits", [False, True])
def test_the_fill_only_lowers_distances(behind_hits: bool) -> None:
    """Filling shadows adds occupied cells and nothing else: the occupied cells are a superset,
    and every value of the field (and of the planning field) is at most what it is without, but
    for what the nearest cell by centres costs. A free cell whose nearest occupied cell becomes
    a filled one reads that cell's surface point, where its former nearest had a measured
    surface point up to half a cell nearer. With the square rule that point is the filled
    cell's centre: at most half a cell more. Behind hits it is the mean of the points the rays
    marked in the cell, anywhere in it: at most a cell's diagonal more, and rarely more than
    half a cell."""
    world = World(
        cylinders=np.array([[2.5, 0.6, 0.3, 0.0, 2.5], [3.2, -1.0, 0.2, 0.0, 2.5]]),
        rings=np.array([[3.5, 1.5, 1.2, 0.3, 0.5, 0.4, 0.08]]),
        boxes=np.array([[2.0, -2.2, 0.0, 2.6, -1.6, 1.5]]),
        ground_z=0.0,
    )
    fields = []
    for fill in (0.0, 0.4 if behind_hits else 0.2):
        cam = SimulatedDepthCamera(
            world, params=dataclasses.replace(D435_TYPICAL, step=2), seed=3
        )  # the same frames (noise, holes) for both maps
        prm = OccupancyParams(
            size_m=(6.0, 6.0, 3.0), occluded_fill_m=fill, occluded_fill_behind_hits=behind_hits
        )
        mapper = LocalMapper(prm, center=np.array([2.0, 0.0, 1.0]))
        for k, yaw in enumerate((0.0, -0.3, 0.3, 0.5)):
            frame = cam.capture(np.array([0.0, 0.2 * k - 0.3, 1.0]), look_rotation(yaw), 0.1 * k)
            assert mapper.ingest(frame, recenter=False).accepted
        fields.append((mapper.field(), mapper.planning_field()))
    (f0, p0), (f1, p1) = fields
    half = 0.5 * f0.res
    bound = math.sqrt(3.0) * f0.res if behind_hits else half
    assert np.all(f1.values <= f0.values + bound) and np.all(p1.values <= p0.values + bound)
    assert np.count_nonzero(f1.values > f0.values + half) <= 1e-4 * f0.values.size
    assert np.count_nonzero(f1.values < f0.values - 0.05) > 1e-2 * f0.values.size
    assert np.all(f1.occupied[f0.occupied])
    np.testing.assert_array_equal(f1.known, f0.known)


@pytest.mark.parametrize("value", [-0.1, 1.5, math.nan])
def test_occluded_fill_is_checked(value: float) -> None:
    with pytest.raises(ValueError, match="occluded_fill_m"):
        OccupancyParams(occluded_fill_m=value)
