"""Perception: simulated D435, occupancy window, ESDF against the exact distance, bad frames."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from typing import Any

import numpy as np
import pytest

from onboard.mapping import (
    CameraIntrinsics,
    DepthFrame,
    EsdfBuilder,
    LocalMapper,
    OccupancyMap,
    OccupancyParams,
    SimCameraParams,
    SimulatedDepthCamera,
    backproject,
    check_frame,
    look_rotation,
)
from onboard.mapping.evaluate import esdf_errors
from onboard.planner.field import FIELD_GRID, UNKNOWN_DISTANCE, field_eval
from onboard.world import World

SMALL = OccupancyParams(size_m=(6.0, 6.0, 3.0))


def _scene() -> World:
    """Two trunks, a box and a ring in front of a camera at the origin looking along +x."""
    return World(
        cylinders=np.array([[2.5, 0.6, 0.3, 0.0, 2.5], [3.2, -1.0, 0.2, 0.0, 2.5]]),
        rings=np.array([[3.5, 1.5, 1.2, 0.3, 0.5, 0.4, 0.08]]),
        boxes=np.array([[2.0, -2.2, 0.0, 2.6, -1.6, 1.5]]),
        ground_z=0.0,
    )


def _poses() -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses sweeping the scene from a few places (several frames each)."""
    out = []
    for x, y, yaw in ((0.0, 0.0, 0.0), (0.3, 0.8, -0.3), (0.3, -0.8, 0.3), (0.0, 0.0, 0.5)):
        for k in range(4):
            out.append((np.array([x + 0.02 * k, y, 1.0]), look_rotation(yaw - 0.05 * k)))
    return out


def _mapped(
    world: World, noise: float = 0.0, params: OccupancyParams = SMALL
) -> tuple[LocalMapper, list[DepthFrame]]:
    cam = SimulatedDepthCamera(world, params=SimCameraParams(noise_std_1m_m=noise), seed=3)
    mapper = LocalMapper(params, center=np.array([2.0, 0.0, 1.0]))
    frames = []
    for k, (p, r) in enumerate(_poses()):
        f = cam.capture(p, r, 0.1 * k)
        frames.append(f)
        assert mapper.ingest(f, recenter=False).accepted
    return mapper, frames


# --- simulated camera -------------------------------------------------------------------------


def test_rendered_depth_lies_on_the_shapes() -> None:
    world = _scene()
    cam = SimulatedDepthCamera(world)
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.1, -0.05)
    depth = cam.render(p, r)
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    pts = backproject(depth, cam.intrinsics, p, r, max_depth_m=cam.params.far_m)
    assert pts.shape[0] > 0.5 * depth.size  # ground, trunks, box, ring (the rest is sky)
    d, _ = world.distance(pts)
    assert np.max(np.abs(d)) < 2e-3  # float32 depth, sphere-traced ring to 1e-4
    # every primitive shows up
    for prim in (world.cylinders[:1], world.boxes, world.rings):
        sub = World(
            prim if prim.shape[1] == 5 else np.zeros((0, 5)),
            prim if prim.shape[1] == 7 else np.zeros((0, 7)),
            prim if prim.shape[1] == 6 else np.zeros((0, 6)),
            None,
        )
        assert np.sum(np.abs(sub.distance(pts)[0]) < 2e-3) > 100
    # nothing to see: no return (0), never a made-up depth
    up = SimulatedDepthCamera(World.empty(None)).render(p, r)
    assert not np.any(up)


def test_render_step_fills_only_the_skip_grid() -> None:
    world = _scene()
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    full = SimulatedDepthCamera(world).render(p, r)
    step3 = SimulatedDepthCamera(world, params=SimCameraParams(step=3)).render(p, r)
    np.testing.assert_array_equal(step3[::3, ::3], full[::3, ::3])
    mask = np.ones_like(step3, dtype=bool)
    mask[::3, ::3] = False
    assert not np.any(step3[mask])


def test_noise_and_holes_are_seeded_and_bounded() -> None:
    world = _scene()
    prm = SimCameraParams(noise_std_1m_m=0.01, dropout=0.1, hole_count=3, hole_size_px=30)
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    a = SimulatedDepthCamera(world, params=prm, seed=5).capture(p, r, 0.0)
    b = SimulatedDepthCamera(world, params=prm, seed=5).capture(p, r, 0.0)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    clean = SimulatedDepthCamera(world).render(p, r)
    both = (a.depth_m > 0) & (clean > 0)
    assert 0.8 < np.mean(a.depth_m[clean > 0] > 0) < 0.92  # ~10 % dropout + holes
    rel = (a.depth_m[both] - clean[both]) / (0.01 * clean[both] ** 2)
    assert 0.8 < np.std(rel) < 1.2
    assert np.all((a.depth_m == 0) | (a.depth_m >= 0.2))


def test_intrinsics_defaults_are_the_d435() -> None:
    i = CameraIntrinsics()
    assert (i.width, i.height, i.fx, i.fy, i.cx, i.cy) == (
        640,
        480,
        387.229,
        387.229,
        321.046,
        243.45,
    )
    assert (i.min_depth_m, i.max_depth_m) == (0.2, 5.0)
    r = look_rotation(0.7, 0.2)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(
        r[:, 2], [math.cos(0.7) * math.cos(0.2), math.sin(0.7) * math.cos(0.2), math.sin(0.2)]
    )
    assert r[2, 0] == pytest.approx(0.0)  # image rows stay horizontal


# --- ESDF -------------------------------------------------------------------------------------


def test_esdf_matches_exact_distance_in_observed_space() -> None:
    """The distances to what the camera saw (without the fill of the obstacles' shadows,
    which only lowers them: ``test_mapping_occluded.py``)."""
    world = _scene()
    mapper, frames = _mapped(
        world, noise=0.002, params=dataclasses.replace(SMALL, occluded_fill_m=0.0)
    )
    field = mapper.field()
    err = esdf_errors(field, world, frames, step=2, max_range_m=SMALL.max_ray_m)
    assert err.free.size > 5_000 and err.occupied.size > 1_000
    assert np.percentile(np.abs(err.all), 95) <= 0.1
    assert np.percentile(np.abs(err.free), 95) <= 0.1
    assert abs(float(np.mean(err.all))) < 0.03  # no systematic bias
    # the trunks are in the map where they are
    occ = mapper.map.surface_points()
    d, _ = world.distance(occ)
    assert np.percentile(np.abs(d), 95) < 0.1


def test_esdf_is_the_exact_transform_of_the_occupancy() -> None:
    """Cube-read values (no sub-cell refinement, no offset) equal brute-force centre
    distances: outside to the nearest occupied cell, inside to the nearest free one."""
    prm = OccupancyParams(size_m=(1.6, 1.2, 0.8), floor_z_m=None)
    omap = OccupancyMap(prm, center=np.array([0.3, -0.2, 0.1]))
    rng = np.random.default_rng(1)
    occ_w = rng.random(omap.shape) < 0.03
    occ_w[3:7, 4:8, 2:6] = True  # a solid block: inside distances up to 2 cells
    lo_w = omap.window_logodds()
    lo_w[...] = prm.l_min
    lo_w[occ_w] = prm.l_max
    # write back into ring-buffer storage order
    g = np.stack(
        np.meshgrid(*[omap.lo[a] + np.arange(omap.shape[a]) for a in range(3)], indexing="ij"), -1
    )
    omap.logodds[omap.storage_index(g.reshape(-1, 3))] = lo_w.reshape(-1)
    field = EsdfBuilder(surface_offset_m=0.0, sub_cell=False).build(omap)
    np.testing.assert_array_equal(field.occupied, occ_w)
    c = field.cell_centres().reshape(-1, 3)
    occ_pts, free_pts = c[occ_w.reshape(-1)], c[~occ_w.reshape(-1)]
    d_out = np.min(np.linalg.norm(c[:, None, :] - occ_pts[None, :, :], axis=2), axis=1)
    d_in = np.min(np.linalg.norm(c[:, None, :] - free_pts[None, :, :], axis=2), axis=1)
    expect = np.where(occ_w.reshape(-1), -d_in, d_out)
    np.testing.assert_allclose(field.values.reshape(-1), expect, atol=1e-5)


def test_esdf_is_a_planner_grid_field() -> None:
    world = _scene()
    mapper, _ = _mapped(world)
    field = mapper.field()
    data = field.kernel_data()
    assert data.kind == FIELD_GRID and data.grid.dtype == np.float64
    assert not data.grid.flags.writeable and np.all(np.isfinite(data.grid))
    np.testing.assert_allclose(data.origin, mapper.map.origin)
    pts = np.random.default_rng(2).uniform([0.5, -2, 0.3], [4, 2, 2.5], size=(50, 3))
    d, g = field.distance(pts)
    for p, dk, gk in zip(pts, d, g, strict=True):
        assert field_eval(*data, *p) == pytest.approx((dk, *gk))
    # outside the window: the free value the optimiser expects, and unknown
    far = np.array([[50.0, 0.0, 1.0]])
    assert field.distance(far)[0][0] == UNKNOWN_DISTANCE and not field.is_known(far)[0]
    # unchanged map: the same field object; a new frame: a new one
    assert mapper.field() is field


def test_planner_flies_around_a_mapped_trunk() -> None:
    from onboard.config import load_planner_params
    from onboard.planner.planner import FormationPlanner, PlanStatus

    world = World(np.array([[3.0, 0.05, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    mapper, _ = _mapped(world)
    field = mapper.field()
    planner = FormationPlanner(load_planner_params(), np.zeros((1, 3)), 0)
    z3 = np.zeros(3)
    res = planner.plan(0.0, np.array([0.5, 0.0, 1.0]), z3, z3, np.array([5.5, 0.0, 1.0]), [], field)
    assert res.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION)
    tr = res.trajectory
    pos = tr.sample(np.linspace(tr.t0_s, tr.t_end_s, 400))
    assert np.min(world.distance(pos)[0]) > 0.3


# --- rolling window ---------------------------------------------------------------------------


def test_window_keeps_cells_while_they_stay_and_forgets_them_when_they_leave() -> None:
    world = _scene()
    rolling = dataclasses.replace(SMALL, floor_z_m=None)  # rolls along all three axes
    omap = OccupancyMap(rolling, center=np.array([2.0, 0.0, 1.0]))
    cam = SimulatedDepthCamera(world)
    for k in range(4):
        f = cam.capture(np.array([0.0, 0.0, 1.0]), look_rotation(0.0), k)
        omap.ingest_depth(f.depth_m, f.intrinsics, f.position, f.rotation)
    occ0 = omap.surface_points()
    centres0 = omap.cell_centres()[omap.occupied()]
    known0 = omap.cell_centres()[omap.known()]
    assert occ0.shape[0] > 500
    # move 2.6 m along +x and 0.6 m up: what stays inside is kept, cell for cell
    omap.recenter(np.array([4.6, 0.0, 1.6]))
    inside = omap.contains(centres0)
    assert 0 < np.sum(inside) < centres0.shape[0]
    assert np.all(omap.state_at(centres0[inside]) == 1)
    assert np.all(omap.state_at(known0[omap.contains(known0)]) >= 0)
    np.testing.assert_allclose(
        np.sort(omap.surface_points(), axis=0),
        np.sort(occ0[omap.contains(occ0)], axis=0),
        atol=1e-5,
    )
    # what entered is unknown, what left is lost: back at the start it stays unknown
    c = omap.cell_centres().reshape(-1, 3)
    entered = c[(c[:, 0] >= 5.0) | (c[:, 2] >= 2.5)]  # beyond the old window's edges
    assert entered.shape[0] > 0 and np.all(omap.state_at(entered) == -1)
    omap.recenter(np.array([2.0, 0.0, 1.0]))
    assert np.all(omap.state_at(centres0[~inside]) == -1)
    assert np.all(omap.state_at(centres0[inside]) == 1)
    # a jump farther than the window: everything forgotten
    omap.recenter(np.array([40.0, 0.0, 1.0]))
    assert not np.any(omap.known())


def test_window_follows_the_camera_on_ingest() -> None:
    world = _scene()
    mapper = LocalMapper(SMALL)
    cam = SimulatedDepthCamera(world)
    p = np.array([1.0, 0.2, 1.1])
    res = mapper.ingest(cam.capture(p, look_rotation(0.0), 0.0))
    assert res.accepted and res.rays > 10_000
    centre = mapper.map.origin + np.array(SMALL.size_m) / 2
    np.testing.assert_allclose(centre[:2], p[:2], atol=0.1)
    # in z the window holds the ground while the drone flies low, then keeps 1 m above it
    assert mapper.map.origin[2] == pytest.approx(-0.5)
    for z, bottom in ((1.4, -0.5), (1.8, -0.2), (4.0, 2.0)):
        mapper.recenter(np.array([1.0, 0.2, z]))
        assert mapper.map.origin[2] == pytest.approx(bottom)
        assert mapper.map.upper[2] == pytest.approx(max(z + 1.0, 2.5))
    mapper.recenter(np.array([1.0, 0.2, 1.0]))
    assert mapper.map.origin[2] == pytest.approx(-0.5)


# --- bad frames -------------------------------------------------------------------------------


def _frame(
    depth: np.ndarray,
    stamp: float = 1.0,
    pos: np.ndarray | None = None,
    rot: np.ndarray | None = None,
) -> DepthFrame:
    return DepthFrame(
        depth,
        stamp,
        np.array([0.0, 0.0, 1.0]) if pos is None else pos,
        look_rotation(0.0) if rot is None else rot,
        CameraIntrinsics(),
    )


def test_bad_frames_are_refused_without_touching_the_map() -> None:
    world = _scene()
    good = SimulatedDepthCamera(world).render(np.array([0.0, 0.0, 1.0]), look_rotation(0.0))
    mapper = LocalMapper(SMALL)
    assert mapper.ingest(_frame(good, 1.0)).accepted
    before = mapper.map.logodds.copy()
    bad = [
        _frame(good[:, :600]),  # wrong shape
        _frame(good.T.copy()),
        _frame(good[..., None]),
        _frame((good * 1000).astype(np.uint16)),  # millimetres: wrong dtype
        _frame(good.astype(np.int32)),
        _frame(good.tolist()),
        _frame(good, stamp=math.nan),
        _frame(good, stamp=0.5),  # older than the last frame
        _frame(good, pos=np.array([0.0, math.inf, 1.0])),
        _frame(good, rot=2.0 * np.eye(3)),
        _frame(good, rot=np.diag([1.0, 1.0, -1.0])),  # a reflection
        _frame(good, rot=np.full((3, 3), math.nan)),
    ]
    for f in bad:
        res = mapper.ingest(f)
        assert not res.accepted and res.reason
    np.testing.assert_array_equal(mapper.map.logodds, before)
    assert mapper.rejected == len(bad)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 0.0, -1.0, 0.1])
def test_invalid_pixels_mark_nothing(value: float) -> None:
    mapper = LocalMapper(SMALL)
    depth = np.full((480, 640), value, dtype=np.float32)
    res = mapper.ingest(_frame(depth))
    assert res.accepted and res.rays == 0 and res.cells_updated == 0
    assert not np.any(mapper.map.known())
    known = mapper.field().known
    assert known is not None and not np.any(known)


def test_masked_pixels_leave_their_space_unknown() -> None:
    """Half a frame of garbage: only the valid half's rays are cast, nothing else turns free
    (the zeros among the garbage cast nothing either: invalid values around them stop them)."""
    world = _scene()
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    good = SimulatedDepthCamera(world).render(p, r)
    half = good.copy()
    half[:, 320:] = np.array([np.nan, np.inf, 0.0, -2.0], dtype=np.float32)[np.arange(320) % 4]
    left_only = good.copy()
    left_only[:, 320:] = np.nan
    a = LocalMapper(SMALL, center=p)
    b = LocalMapper(SMALL, center=p)
    a.ingest(_frame(half))
    b.ingest(_frame(left_only))
    np.testing.assert_array_equal(a.map.logodds, b.map.logodds)
    # the right half of the view (negative y in front of the camera) stays unknown
    probe = np.array([[3.0, -1.2, 1.0], [2.0, -0.9, 0.8], [4.0, -2.0, 1.2]])
    assert np.all(a.map.state_at(probe) == -1)
    assert np.all(a.map.state_at(np.array([[2.0, 0.6, 1.8], [1.5, 0.4, 1.0]])) >= 0)


# --- pixels without a return ------------------------------------------------------------------


def _trunk_world() -> World:
    """One trunk 2.5 m in front of a camera at the origin (1 m up, looking along +x)."""
    return World(
        cylinders=np.array([[2.5, 0.0, 0.3, 0.0, 2.5]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )


_TRUNK_POSES = [
    (np.array([0.0, y, 1.0]), look_rotation(a)) for y, a in ((0, 0), (0.3, -0.1), (-0.3, 0.1))
]


def _cells_inside_trunk(om: OccupancyMap, world: World, depth_m: float) -> np.ndarray:
    """Window-order bool grid: cell centres deeper than depth_m inside the world's trunks."""
    trunks = World(world.cylinders, world.rings, world.boxes, None)
    d, _ = trunks.distance(om.cell_centres().reshape(-1, 3))
    return (d < -depth_m).reshape(om.shape)


def _free(om: OccupancyMap) -> np.ndarray:
    lw = om.window_logodds()
    return (lw > -50.0) & (lw < 0.0)


def test_no_return_pixels_clear_free_space_up_to_their_range() -> None:
    """Sky and far space (0 in a D435 frame) turn free along the ray up to no_return_m, as in
    the reference's grid map; with no_return_m 0 they stay unknown, as before."""
    world = World.empty(0.0)  # the ground only: everything above the horizon is "no return"
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    depth = SimulatedDepthCamera(world).render(p, r)
    assert 0.3 < np.mean(depth == 0.0) < 0.7
    on = LocalMapper(SMALL, center=p)
    off = LocalMapper(dataclasses.replace(SMALL, no_return_m=0.0), center=p)
    res = on.ingest(_frame(depth, pos=p, rot=r))
    assert res.clear_rays > 100
    assert off.ingest(_frame(depth, pos=p, rot=r)).clear_rays == 0
    ahead = np.array([[1.0, 0.0, 1.0], [2.5, 0.5, 1.3], [2.9, -0.5, 1.8]])  # in the view, in air
    assert np.all(on.map.state_at(ahead) == 0)
    assert np.all(off.map.state_at(ahead) == -1)
    short = LocalMapper(dataclasses.replace(SMALL, no_return_m=2.0), center=p)
    short.ingest(_frame(depth, pos=p, rot=r))
    assert short.map.state_at(np.array([[1.5, 0.0, 1.2]]))[0] == 0
    assert short.map.state_at(np.array([[2.5, 0.0, 1.5]]))[0] == -1  # beyond 2 m
    # the ground the frame measured stays what its hits made it
    np.testing.assert_array_equal(on.map.occupied(), off.map.occupied())


def test_a_hole_in_a_trunk_does_not_carve_free_space_through_it() -> None:
    """A hole (0) in the middle of a trunk's image: its rays stop no_return_margin_m in front of
    the depths measured around it, so the trunk's inside stays unknown on a map that never saw
    the trunk before. Without the image rule (no neighbourhood) the same frame carves it."""
    world = _trunk_world()
    p, r = _TRUNK_POSES[0]
    depth = SimulatedDepthCamera(world).render(p, r)
    depth[200:240, 300:340] = 0.0  # a 40 px hole on the trunk (it spans about 60 px)
    assert np.all(depth[195, 300:340] > 0) and np.all(depth[245, 300:340] > 0)
    safe = LocalMapper(SMALL, center=p)
    blind = LocalMapper(dataclasses.replace(SMALL, no_return_radius_px=0), center=p)
    assert safe.ingest(_frame(depth, pos=p, rot=r)).clear_rays > 0
    blind.ingest(_frame(depth, pos=p, rot=r))
    inside = _cells_inside_trunk(safe.map, world, 0.05)
    assert not np.any(_free(safe.map) & inside)
    assert np.any(_free(blind.map) & inside)  # the frame would carve it: the rule matters


def test_no_return_frames_never_erase_a_mapped_trunk() -> None:
    """A trunk mapped from frames with D435 holes and dropout, then frames in which the trunk
    and 170 px around it give no return at all (a texture-less or too-close surface reads 0
    like the sky): every cell of the trunk stays occupied and none inside it turns free. The
    same frames on a map that never saw the trunk do carve into it: the map is what stops them
    (an obstacle never seen and never returning is the rule's known limit)."""
    world = _trunk_world()
    prm = SimCameraParams(noise_std_1m_m=0.004, dropout=0.05, hole_count=6, hole_size_px=40)
    cam = SimulatedDepthCamera(world, params=prm, seed=5)
    mapper = LocalMapper(SMALL, center=np.array([1.5, 0.0, 1.0]))
    t = 0.0
    for k in range(12):
        p, r = _TRUNK_POSES[k % 3]
        assert mapper.ingest(cam.capture(p, r, t), recenter=False).accepted
        t += 0.1
    om = mapper.map
    trunks = World(world.cylinders, world.rings, world.boxes, None)
    d, _ = trunks.distance(om.cell_centres().reshape(-1, 3))
    trunk_cells = om.occupied() & (np.abs(d) < 0.1).reshape(om.shape)
    assert trunk_cells.sum() > 100
    inside = _cells_inside_trunk(om, world, 0.05)
    assert not np.any(_free(om) & inside)
    fresh = LocalMapper(SMALL, center=np.array([1.5, 0.0, 1.0]))
    for k in range(9):
        p, r = _TRUNK_POSES[k % 3]
        f = cam.capture(p, r, t)
        blank = f.depth_m.copy()
        blank[:, 150:490] = 0.0
        bf = DepthFrame(blank, t, f.position, f.rotation, f.intrinsics)
        assert mapper.ingest(bf, recenter=False).clear_rays > 0
        fresh.ingest(bf, recenter=False)
        t += 0.1
    assert np.all(om.occupied()[trunk_cells])
    assert not np.any(_free(om) & inside)
    assert np.any(_free(fresh.map) & inside)


def test_at_a_low_frame_rate_one_sighting_maps_a_trunk_and_a_miss_still_clears_it() -> None:
    """The reference's p_hit needs 3 hits (0.1 s at 30 frames/s): at 3 frames/s a trunk seen
    in one frame (at the edge of the view, in a turn) stayed known but free to the planner.
    ``for_frame_rate`` makes one hit enough there; the misses that clear a cell are unchanged
    (one frame that sees through it frees it again), and at 30 frames/s nothing changes."""
    assert SMALL.for_frame_rate(30.0) == SMALL and SMALL.for_frame_rate(60.0) == SMALL
    slow = SMALL.for_frame_rate(3.0)
    assert slow.p_hit > SMALL.p_hit and slow.l_hit > slow.l_occ > slow.l_hit + slow.l_miss
    assert SMALL.for_frame_rate(15.0).l_hit * 2 > slow.l_occ > SMALL.for_frame_rate(15.0).l_hit
    assert dataclasses.replace(SMALL, p_hit=0.9).for_frame_rate(3.0).p_hit == 0.9  # not lowered
    for bad in (0.0, -3.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="rate_hz"):
            SMALL.for_frame_rate(bad)
    with pytest.raises(ValueError, match="occupied_after_s"):
        dataclasses.replace(SMALL, occupied_after_s=-0.1)
    cam = SimulatedDepthCamera(_trunk_world(), params=SimCameraParams(noise_std_1m_m=0.0), seed=3)
    frame = cam.capture(*_TRUNK_POSES[0], 0.0)
    face = np.array([[2.25, 0.0, 1.0]])  # in the trunk's cell facing the camera
    ahead = np.array([[1.5, 0.0, 1.0]])  # 0.7 m in front of the trunk
    maps = {}
    for name, prm in (("30 Hz", SMALL), ("3 Hz", slow)):
        m = LocalMapper(prm, center=np.array([1.5, 0.0, 1.0]))
        assert m.ingest(frame, recenter=False).accepted
        maps[name] = m
    assert maps["30 Hz"].map.state_at(face)[0] == 0  # seen, one hit: not an obstacle
    assert maps["3 Hz"].map.state_at(face)[0] == 1
    d_slow = float(maps["3 Hz"].planning_field().distance(ahead)[0][0])
    assert d_slow == pytest.approx(0.7 - slow.inflation_m, abs=0.1)
    assert float(maps["30 Hz"].planning_field().distance(ahead)[0][0]) > d_slow + 0.5
    # the trunk gone (a moved obstacle): one frame that sees through its cell to a wall
    # behind frees it (a ray without a return would stop in front of it)
    wall = World(
        np.zeros((0, 5)), np.zeros((0, 7)), np.array([[4.0, -2.0, 0.0, 4.3, 2.0, 2.5]]), 0.0
    )
    cam2 = SimulatedDepthCamera(wall, params=SimCameraParams(noise_std_1m_m=0.0), seed=3)
    assert maps["3 Hz"].ingest(cam2.capture(*_TRUNK_POSES[0], 0.1), recenter=False).accepted
    assert maps["3 Hz"].map.state_at(face)[0] == 0


def test_no_return_rays_need_a_frame_that_measured_something() -> None:
    """A frame with too few measured pixels (a covered lens, an obstacle too close to see
    filling the view) casts no no-return ray; a frame of invalid values (NaN) casts nothing."""
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    ground = SimulatedDepthCamera(World.empty(0.0)).render(p, r)
    few = np.zeros_like(ground)
    few[-20:, :] = ground[-20:, :]  # the bottom 20 rows: 4 % of the pixels
    mapper = LocalMapper(SMALL, center=p)
    res = mapper.ingest(_frame(few, pos=p, rot=r))
    assert res.rays > 0 and res.clear_rays == 0
    assert mapper.map.state_at(np.array([[2.0, 0.0, 1.2]]))[0] == -1
    nan = LocalMapper(SMALL, center=p)
    res = nan.ingest(_frame(np.where(ground > 0, ground, np.nan).astype(np.float32)))
    assert res.clear_rays == 0


def test_no_return_rays_are_cast_at_most_every_period() -> None:
    """At 30 frames/s and no_return_period_s 0.1 every 3rd frame casts them (a fixed phase);
    with period 0 every frame does."""
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    depth = SimulatedDepthCamera(World.empty(0.0)).render(p, r)
    every = {}
    for period in (0.1, 0.0):
        mapper = LocalMapper(dataclasses.replace(SMALL, no_return_period_s=period), center=p)
        cast = [
            mapper.ingest(_frame(depth, stamp=k / 30.0, pos=p, rot=r)).clear_rays > 0
            for k in range(12)
        ]
        every[period] = [k for k, c in enumerate(cast) if c]
    assert every[0.1] == [0, 3, 6, 9]
    assert every[0.0] == list(range(12))


def test_check_frame_keeps_no_return_and_marks_invalid_values() -> None:
    depth = np.array([[0.0, np.nan, np.inf, -1.0, 0.1, 2.0, 7.0]], dtype=np.float32)
    intr = CameraIntrinsics(width=7, height=1, cx=3.0, cy=0.0)
    out = check_frame(DepthFrame(depth, 0.0, np.zeros(3), np.eye(3), intr))
    assert out[0, 0] == 0.0 and np.all(np.isnan(out[0, 1:5]))
    np.testing.assert_array_equal(out[0, 5:], [2.0, 7.0])


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("no_return_m", -1.0),
        ("no_return_m", 6.0),
        ("no_return_step", 0),
        ("no_return_radius_px", -1),
        ("no_return_margin_m", -0.1),
        ("no_return_min_valid", 1.5),
        ("no_return_period_s", -1.0),
    ],
)
def test_no_return_parameters_are_checked(field: str, value: float) -> None:
    bad: dict[str, Any] = {field: value}
    with pytest.raises(ValueError, match=field):
        OccupancyParams(**bad)


# --- unknown space and the collision check ----------------------------------------------------


def test_unknown_space_is_never_free_for_the_collision_check() -> None:
    world = _scene()
    mapper, _ = _mapped(world)
    field = mapper.field()
    behind = np.array([[-1.5, 0.0, 1.0], [-0.8, 1.5, 1.5], [1.0, 0.0, 2.9]])  # outside the views
    assert not np.any(field.is_known(behind))
    d, _ = field.distance(behind)
    assert np.all(d > 0.6)  # the optimiser may treat it as free ...
    assert not np.any(field.collision_free(behind))  # ... the collision check may not
    seen_free = np.array([[1.53, 0.02, 1.01], [1.03, -0.47, 1.23]])
    assert np.all(field.collision_free(seen_free, clearance_m=0.2))
    at_trunk = np.array([[2.5 - 0.3, 0.6, 1.0], [3.2 - 0.25, -1.0, 1.0]])
    assert not np.any(field.collision_free(at_trunk))
    assert not field.collision_free(np.array([[100.0, 0.0, 1.0]]))[0]
    infl = field.inflated_occupied()
    assert infl.sum() > field.occupied.sum()
    # the planning field: obstacles grown by the drone's radius, unknown still not free
    plan = mapper.planning_field()
    np.testing.assert_allclose(plan.values, np.clip(field.values - 0.1, -10.0, 10.0))
    assert plan.inflation_m == 0.0 and mapper.planning_field() is plan
    assert np.array_equal(plan.collision_free(seen_free, 0.3), field.collision_free(seen_free, 0.2))
    assert not np.any(plan.collision_free(behind))


# --- Open3D and the RealSense source ----------------------------------------------------------


def test_open3d_backprojection_and_ply_roundtrip(tmp_path: object) -> None:
    from pathlib import Path

    from onboard.sensors.cloud import (
        cloud_points,
        frame_to_cloud,
        ingest_cloud,
        load_points_ply,
        save_map_ply,
    )

    world = _scene()
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.2)
    f = SimulatedDepthCamera(world).capture(p, r, 0.0)
    ours = backproject(f.depth_m, f.intrinsics, p, r, step=4)
    theirs = cloud_points(frame_to_cloud(f, step=4))
    assert ours.shape == theirs.shape
    np.testing.assert_allclose(np.sort(ours, axis=0), np.sort(theirs, axis=0), atol=1e-4)
    down = cloud_points(frame_to_cloud(f, step=1, voxel_m=0.1))
    assert 0 < down.shape[0] < theirs.shape[0]
    omap = OccupancyMap(SMALL, center=p)
    for _ in range(3):
        res = ingest_cloud(omap, f, step=2, voxel_m=0.05)
        assert res.accepted and res.rays > 1000
    pts = omap.surface_points()
    assert pts.shape[0] > 300 and np.percentile(np.abs(world.distance(pts)[0]), 95) < 0.1
    out = Path(str(tmp_path)) / "map.ply"
    n = save_map_ply(out, omap)
    back = load_points_ply(out)
    assert n == back.shape[0] == pts.shape[0]
    np.testing.assert_allclose(np.sort(back, axis=0), np.sort(pts, axis=0), atol=1e-5)


def test_realsense_without_a_camera_fails_with_a_clear_message(tmp_path: object) -> None:
    from pathlib import Path

    from onboard.sensors.realsense import RealSenseSource, RealSenseUnavailable, _open3d_io

    pose = lambda t: (np.zeros(3), np.eye(3))  # noqa: E731
    if _open3d_io().RealSenseSensor.list_devices():  # pragma: no cover - a camera is attached
        pytest.skip("a RealSense camera is attached")
    with pytest.raises(RealSenseUnavailable, match="no RealSense camera found"):
        RealSenseSource(pose)
    with pytest.raises(RealSenseUnavailable, match="not found"):
        RealSenseSource(pose, Path(str(tmp_path)) / "missing.bag")
    junk = Path(str(tmp_path)) / "junk.bag"
    junk.write_bytes(b"not a rosbag")
    with pytest.raises(RealSenseUnavailable, match="cannot open"):
        RealSenseSource(pose, junk)
    txt = Path(str(tmp_path)) / "depth.txt"
    txt.write_text("x")
    with pytest.raises(RealSenseUnavailable, match=r"\.bag expected"):
        RealSenseSource(pose, txt)


def test_realsense_bag_replay_feeds_the_map() -> None:
    """A recorded software-D435 .bag (tests/data/make_realsense_bag.py): a wall at 2 m, a
    closer square at 1.5 m, missing depth along the top rows."""
    from pathlib import Path

    from onboard.sensors.realsense import RealSenseSource

    bag = Path(__file__).parent / "data" / "realsense_wall.bag"
    p, r = np.array([0.0, 0.0, 1.0]), look_rotation(0.0)
    frames: list[DepthFrame] = []
    for _ in range(5):  # real-time playback may drop every frame of a short recording: retry
        src = RealSenseSource(lambda t: (p, r), bag)
        assert src.intrinsics.shape == (480, 640)
        assert src.intrinsics.fx == pytest.approx(387.229, abs=1e-3)
        assert src.depth_scale == pytest.approx(1000.0, rel=1e-6)
        while (f := src.read()) is not None and len(frames) < 12:
            frames.append(f)
        src.close()
        if frames:
            break
    assert frames
    stamps = [f.stamp_s for f in frames]
    assert stamps == sorted(stamps)
    d = frames[0].depth_m
    assert d.dtype == np.float32 and not np.any(d[:12])
    np.testing.assert_allclose(np.unique(d[12:]), [1.5, 2.0], atol=1e-3)
    mapper = LocalMapper(SMALL)
    for rep in range(3):  # the same frames again, later: enough hits to occupy the cells
        for f in frames:
            assert mapper.ingest(dataclasses.replace(f, stamp_s=f.stamp_s + 10.0 * rep)).accepted
    pts = mapper.map.surface_points()
    assert pts.shape[0] > 300
    assert set(np.round(pts[:, 0], 1)) == {1.5, 2.0}


def test_realsense_depth_units_to_metres() -> None:
    from onboard.sensors.realsense import depth_to_metres

    raw = np.array([[0, 1000, 2500]], dtype=np.uint16)[..., None]
    np.testing.assert_allclose(depth_to_metres(raw, 1000.0), [[0.0, 1.0, 2.5]])
    assert depth_to_metres(raw, 1000.0).dtype == np.float32


def test_simulated_source_reads_frames_at_the_provided_pose() -> None:
    from onboard.sensors import DepthSource, SimulatedD435Source

    t = [0.0]
    src: DepthSource = SimulatedD435Source(
        SimulatedDepthCamera(_scene()),
        lambda s: (np.array([s, 0.0, 1.0]), look_rotation(0.0)),
        lambda: t[0],
    )
    t[0] = 0.5
    f = src.read()
    assert f is not None and f.stamp_s == 0.5 and f.position[0] == 0.5
    assert f.depth_m.shape == src.intrinsics.shape
    src.close()


def test_mapping_core_imports_no_io_libraries() -> None:
    code = (
        "import sys\n"
        "import onboard.mapping, onboard.mapping.evaluate\n"
        "bad = [m for m in ('open3d', 'zenoh', 'pymavlink', 'mavsdk', 'matplotlib', 'gcs',"
        " 'onboard.config', 'onboard.comm', 'onboard.sensors') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
