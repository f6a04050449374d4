"""The mapping pipeline's fast paths give exactly what the plain ones give: the mapper ray casts
an uncleaned depth image (validate_frame, no copy) into the same map as the cleaned one
(check_frame); the planning field computed in the ESDF's own pass equals ``inflated``; the
depth codec's one-pass conversion equals astype + divide."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.mapping import (
    DepthFrame,
    EsdfBuilder,
    FrameRejected,
    LocalMapper,
    OccupancyMap,
    OccupancyParams,
    SimCameraParams,
    SimulatedDepthCamera,
    check_frame,
    look_rotation,
    validate_frame,
)
from onboard.sensors.zenoh_depth import DepthImage
from onboard.world import World

SMALL = OccupancyParams(size_m=(6.0, 6.0, 3.0))


def _world() -> World:
    return World(
        cylinders=np.array([[2.5, 0.6, 0.3, 0.0, 2.5], [3.2, -1.0, 0.2, 0.0, 2.5]]),
        rings=np.zeros((0, 7)),
        boxes=np.array([[2.0, -2.2, 0.0, 2.6, -1.6, 1.5]]),
        ground_z=0.0,
    )


def _spoiled(frame: DepthFrame, rng: np.random.Generator) -> DepthFrame:
    """The frame with every kind of invalid pixel sprinkled in (NaN, +-inf, negative, zero,
    below the minimum depth, a huge finite value)."""
    d = np.array(frame.depth_m, dtype=np.float32, copy=True)
    bad = [np.nan, np.inf, -np.inf, -1.0, 0.0, 0.1, 3e38]
    idx = rng.integers(0, d.size, size=4000)
    d.reshape(-1)[idx] = np.array(bad, dtype=np.float32)[rng.integers(0, len(bad), idx.size)]
    return DepthFrame(d, frame.stamp_s, frame.position, frame.rotation, frame.intrinsics)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_uncleaned_frames_map_exactly_as_cleaned_ones(dtype: type) -> None:
    cam = SimulatedDepthCamera(_world(), params=SimCameraParams(noise_std_1m_m=0.004), seed=2)
    rng = np.random.default_rng(7)
    raw = LocalMapper(SMALL, center=np.array([2.0, 0.0, 1.0]))
    clean = LocalMapper(SMALL, center=np.array([2.0, 0.0, 1.0]))
    for k in range(6):
        f = cam.capture(np.array([0.1 * k, 0.2, 1.0]), look_rotation(0.1 * k), 0.1 * k)
        f = _spoiled(f, rng)
        f = DepthFrame(f.depth_m.astype(dtype), f.stamp_s, f.position, f.rotation, f.intrinsics)
        cleaned = DepthFrame(check_frame(f), f.stamp_s, f.position, f.rotation, f.intrinsics)
        a = raw.ingest(f, step=2)
        b = clean.ingest(cleaned, step=2)
        assert a.accepted and b.accepted and a == b
    np.testing.assert_array_equal(raw.map.logodds, clean.map.logodds)
    np.testing.assert_array_equal(raw.map.surf, clean.map.surf)


def test_validate_frame_copies_nothing_and_refuses_what_check_frame_refuses() -> None:
    cam = SimulatedDepthCamera(_world())
    f = cam.capture(np.array([0.0, 0.0, 1.0]), look_rotation(0.0), 0.0)
    assert validate_frame(f) is f.depth_m  # float32, contiguous: the frame's own array
    bad_pose = DepthFrame(f.depth_m, 0.0, np.array([np.nan, 0, 0]), f.rotation, f.intrinsics)
    for fn in (validate_frame, check_frame):
        with pytest.raises(FrameRejected, match="position"):
            fn(bad_pose)


def _random_map(rng: np.random.Generator) -> OccupancyMap:
    p = OccupancyParams(size_m=(2.4, 2.0, 1.6))
    om = OccupancyMap(p, center=rng.normal(size=3) * 3)
    u = rng.random(om.shape)
    om.logodds[...] = np.where(u < 0.05, 2.0, np.where(u < 0.6, -1.0, -100.0))
    om.surf[:, :3] = rng.uniform(-0.05, 0.05, size=(om.surf.shape[0], 3))
    om.surf[:, 3] = rng.integers(0, 3, size=om.surf.shape[0])
    return om


@pytest.mark.parametrize("sub_cell", [True, False])
def test_planning_field_of_the_same_pass_equals_inflated(sub_cell: bool) -> None:
    rng = np.random.default_rng(3)
    for _ in range(3):
        om = _random_map(rng)
        plain = EsdfBuilder(sub_cell=sub_cell).build(om)
        fused = EsdfBuilder(sub_cell=sub_cell).build(om, inflate_m=0.1)
        np.testing.assert_array_equal(plain.values, fused.values)
        want = plain.inflated(0.1)
        got = fused.inflated(0.1)
        assert got is fused.inflated(0.1)  # computed once, with the field
        np.testing.assert_array_equal(want.values, got.values)
        assert want.known is not None and got.known is not None
        np.testing.assert_array_equal(want.known, got.known)
        np.testing.assert_array_equal(want.occupied, got.occupied)
        assert want.inflation_m == got.inflation_m == 0.0
        # another margin still works (computed on demand)
        np.testing.assert_array_equal(plain.inflated(0.3).values, fused.inflated(0.3).values)


def test_depth_codec_converts_millimetres_in_one_pass_as_before() -> None:
    rng = np.random.default_rng(0)
    d = rng.uniform(0.0, 65.0, size=(48, 64)).astype(np.float32)
    intr = {"width": 64.0, "height": 48.0, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0}
    img = DepthImage(3, 1.5, d, np.zeros(3), np.eye(3), {**intr, "min_depth_m": 0.2})
    back = DepthImage.from_bytes(img.to_bytes())
    mm = np.clip(np.rint(d.astype(np.float64) * 1000.0), 0, 65535).astype("<u2")
    np.testing.assert_array_equal(back.depth_m, mm.astype(np.float32) / np.float32(1000.0))
    assert back.depth_m.dtype == np.float32


def _column(om: OccupancyMap) -> tuple[np.ndarray, ...]:
    from onboard.mapping.esdf import _column_pass

    shape = om.shape
    f_out = np.empty(shape, np.float32)
    feat = np.empty(shape, np.int32)
    f_in = np.empty(shape, np.float32)
    occ = np.empty(shape, np.bool_)
    known = np.empty(shape, np.bool_)
    spt = np.empty((int(np.prod(shape)), 3), np.float32)
    n = _column_pass(
        om.logodds, om.surf, om.lo, om.params.l_occ, om.res, f_out, feat, f_in, occ, known, spt
    )
    return f_in, feat, occ, n


def test_inside_search_equals_the_envelope_transform_or_leaves_it_to_it() -> None:
    from onboard.mapping.esdf import _envelope_pass, _inside_local

    rng = np.random.default_rng(11)
    searched = fell_back = 0
    for t in range(12):
        p = OccupancyParams(size_m=(3.2, 2.8, 2.4), floor_z_m=None)
        om = OccupancyMap(p, center=rng.normal(size=3))
        dens = [0.01, 0.05, 0.2, 0.5, 0.8, 0.95, 1.0, 0.3, 0.02, 0.1, 0.6, 0.4][t]
        lo = np.where(rng.random(om.shape) < dens, 2.0, -1.0).astype(np.float32)
        if t in (3, 8):  # a solid block: inside distances beyond the search radius
            lo[2:30, 1:27, 1:23] = 2.0
        om.logodds[...] = lo
        f_in, feat, occ, n = _column(om)
        ref = f_in.copy()
        _envelope_pass(ref, 1, 0.0, feat, False)
        _envelope_pass(ref, 0, 0.0, feat, False)
        before = f_in.copy()
        if _inside_local(occ, f_in, n, 8):
            searched += 1
            np.testing.assert_array_equal(f_in[occ], ref[occ])
        else:
            fell_back += 1
            np.testing.assert_array_equal(f_in, before)  # untouched: the envelope runs
    assert searched >= 6 and fell_back >= 2
