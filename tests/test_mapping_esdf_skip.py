"""A frame that changes nothing the ESDF reads leaves the mapper's field as it is (the same
object), and that field is bit for bit what a refresh would compute: the ray casting counts
the cells whose state as the ESDF reads it changed (unknown / free / occupied, or the surface
point of an occupied cell: every hit on one counts)."""

from __future__ import annotations

import math

import numpy as np

from onboard.mapping import (
    DepthFrame,
    EsdfBuilder,
    LocalMapper,
    OccupancyParams,
    SimCameraParams,
    SimulatedDepthCamera,
    look_rotation,
)
from onboard.world import World

PARAMS = OccupancyParams(size_m=(5.0, 5.0, 3.0))


def _world() -> World:
    return World(
        cylinders=np.array([[2.0, 0.3, 0.25, 0.0, 3.0], [1.5, -1.0, 0.2, 0.0, 3.0]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )


def _esdf_state(m: LocalMapper) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per storage cell: the class the ESDF reads (0 unknown, 1 free, 2 occupied), and the
    surface accumulators."""
    lg = m.map.logodds.reshape(-1).astype(np.float64)  # compared in float64, as the ESDF does
    cls = np.where(lg > -50.0, np.where(lg >= m.params.l_occ, 2, 1), 0)
    return cls, m.map.surf.copy(), m.map.lo.copy()


def _expected_changes(before: tuple[np.ndarray, ...], after: tuple[np.ndarray, ...]) -> int:
    cls0, surf0, _ = before
    cls1, surf1, _ = after
    moved_surface = (cls1 == 2) & np.any(surf1 != surf0, axis=1)
    return int(np.count_nonzero((cls1 != cls0) | moved_surface))


def _same_as_a_refresh(m: LocalMapper) -> None:
    fresh = EsdfBuilder().build(m.map, inflate_m=m.params.inflation_m)
    got = m.field()
    assert got.values.tobytes() == fresh.values.tobytes()
    assert got.occupied.tobytes() == fresh.occupied.tobytes()
    assert got.known is not None and fresh.known is not None
    assert got.known.tobytes() == fresh.known.tobytes()
    assert (
        m.planning_field().values.tobytes() == fresh.inflated(m.params.inflation_m).values.tobytes()
    )
    np.testing.assert_array_equal(got.origin, fresh.origin)


def test_changes_counted_are_exactly_the_cells_the_esdf_reads_differently() -> None:
    cam = SimulatedDepthCamera(
        _world(), params=SimCameraParams(noise_std_1m_m=0.004, hole_count=2), seed=1
    )
    m = LocalMapper(PARAMS, center=np.array([0.0, 0.0, 1.0]))
    for k in range(20):
        pos = np.array([0.05 * k, 0.1 * math.sin(k), 1.0])
        f = cam.capture(pos, look_rotation(0.3 * math.sin(0.5 * k)), k / 30.0)
        m.recenter(f.position)
        before = _esdf_state(m)
        res = m.ingest(f, recenter=False)
        assert res.accepted
        assert res.esdf_changes == _expected_changes(before, _esdf_state(m))
        assert res.esdf_changes > 0  # it sees trunks and the ground: hits on occupied cells


def test_frames_that_change_nothing_the_esdf_reads_keep_the_field() -> None:
    cam = SimulatedDepthCamera(_world(), params=SimCameraParams(noise_std_1m_m=0.0), seed=2)
    m = LocalMapper(PARAMS, center=np.array([0.0, 0.0, 1.0]))
    pos = np.array([0.0, 0.0, 1.0])
    # hover: looking up at the sky (no pixel measures anything, so not even no-return rays
    # are cast: the frames change nothing), every 10th frame at the trunks again (hits on
    # occupied cells: a refresh)
    for k in range(6):
        m.ingest(cam.capture(pos, look_rotation(0.0), k / 30.0))
    kept = rebuilt = 0
    last = m.field()
    sky = look_rotation(0.0, 1.55)  # pitched up: the sky only
    t = 6 / 30.0
    for k in range(40):
        t += 1 / 30.0
        f = cam.capture(pos, look_rotation(0.0) if k % 10 == 5 else sky, t)
        before = _esdf_state(m)
        res = m.ingest(f)
        assert res.accepted
        # every hit on an occupied cell counts: without noise the same points again can
        # leave a full accumulator as it was (a refresh that changes nothing, never a miss)
        assert res.esdf_changes >= _expected_changes(before, _esdf_state(m))
        fld = m.field()
        if res.esdf_changes == 0:
            assert fld is last
            kept += 1
        else:
            assert fld is not last
            rebuilt += 1
        _same_as_a_refresh(m)
        last = fld
    assert rebuilt == 4 and kept == 36
    # a frame without a single valid pixel changes nothing either
    blank = DepthFrame(
        np.full_like(f.depth_m, np.nan), t + 0.1, f.position, f.rotation, f.intrinsics
    )
    res = m.ingest(blank)
    assert res.accepted and res.esdf_changes == 0
    assert m.field() is last
    # and moving the window refreshes it
    m.recenter(pos + np.array([0.35, 0.0, 0.0]))
    assert m.field() is not last
    _same_as_a_refresh(m)
