"""Distance-field interface of the planner: field_eval for both kinds, GridField, AnalyticField."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.planner.field import (
    FIELD_GRID,
    FIELD_PRIMITIVES,
    UNKNOWN_DISTANCE,
    AnalyticField,
    DistanceField,
    FieldData,
    GridField,
    field_eval,
)
from onboard.world import World, _each_primitive_distance, primitives_distance, random_forest


def _forest() -> World:
    return random_forest(8, 30, (0.0, 8.0), (0.0, 6.0), min_spacing_m=1.0, n_rings=1)


def test_primitives_kind_matches_world() -> None:
    world = _forest()
    field: DistanceField = AnalyticField(world)
    data = field.kernel_data()
    assert data.kind == FIELD_PRIMITIVES
    pts = np.random.default_rng(0).uniform([0, 0, -0.5], [8, 6, 3.5], size=(200, 3))
    d, g = field.distance(pts)
    d_w, g_w = world.distance(pts)
    np.testing.assert_array_equal(d, d_w)
    np.testing.assert_array_equal(g, g_w)
    for p in pts[:20]:
        assert field_eval(*data, *p) == primitives_distance(
            world.cylinders, world.rings, world.boxes, 0.0, *p
        )
    assert field.is_known(pts).all()


def test_kernel_data_layout_is_uniform() -> None:
    """Both kinds give arrays of the same dtype, ndim and flags (one numba specialisation)."""
    analytic = AnalyticField(_forest()).kernel_data()
    grid = GridField(np.zeros((2, 3, 4)), np.zeros(3), 0.5).kernel_data()
    no_ground = AnalyticField(World.empty(None)).kernel_data()
    assert grid.kind == FIELD_GRID and math.isnan(grid.ground_z)
    assert math.isnan(no_ground.ground_z) and analytic.ground_z == 0.0
    for a, b in zip(analytic, grid, strict=True):
        if isinstance(a, np.ndarray):
            assert isinstance(b, np.ndarray)
            assert a.dtype == b.dtype == np.float64 and a.ndim == b.ndim
            assert a.flags.c_contiguous and b.flags.c_contiguous
            assert not a.flags.writeable and not b.flags.writeable
    assert grid.cylinders.shape == (0, 5) and grid.rings.shape == (0, 7)
    assert grid.boxes.shape == (0, 6) and analytic.grid.shape == (1, 1, 1)
    assert isinstance(grid, FieldData)


def test_grid_reproduces_linear_function_exactly() -> None:
    a = np.array([0.3, -1.2, 0.7])
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 1.5, 3.0])
    field = GridField.from_function(lambda p: p @ a + 0.25, lo, hi, 0.1)
    assert field.shape == (20, 15, 10)
    np.testing.assert_allclose(field.upper, hi)
    rng = np.random.default_rng(1)
    pts = rng.uniform(lo + 0.05, hi - 0.05, size=(300, 3))  # between the outer cell centres
    d, g = field.distance(pts)
    np.testing.assert_allclose(d, pts @ a + 0.25, atol=1e-12)
    np.testing.assert_allclose(g, np.broadcast_to(a, g.shape), atol=1e-10)


def test_grid_gradient_central_differences() -> None:
    rng = np.random.default_rng(2)
    res = 0.25
    values = rng.normal(size=(6, 5, 4))
    origin = np.array([1.0, -2.0, 0.5])
    field = GridField(values, origin, res)
    data = field.kernel_data()
    h = 1e-6
    checked = 0
    for p in rng.uniform(origin, origin + np.array(values.shape) * res, size=(500, 3)):
        frac = (p - origin) / res - 0.5
        if np.any(np.abs(frac - np.rint(frac)) < 1e-4):  # on a face of the interpolant's cells
            continue
        d, *g = field_eval(*data, *p)
        fd = np.empty(3)
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd[k] = (field_eval(*data, *(p + e))[0] - field_eval(*data, *(p - e))[0]) / (2 * h)
        checked += 1
        assert np.linalg.norm(np.array(g) - fd) <= 1e-5 * max(float(np.linalg.norm(fd)), 1.0)
    assert checked > 450


def test_grid_from_analytic_agrees_with_it() -> None:
    world = _forest()
    truth = AnalyticField(world)
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([8.0, 6.0, 3.0])
    res = 0.1
    grid = GridField.from_function(truth.distance, lo, hi, res)
    pts = np.random.default_rng(4).uniform(lo + res, hi - res, size=(5000, 3))
    d_true, _ = truth.distance(pts)
    d_grid, _ = grid.distance(pts)
    err = np.abs(d_grid - d_true)
    # anywhere: a convex combination of samples at most res * sqrt(3) away (1-Lipschitz field)
    assert np.max(err) <= res * math.sqrt(3) / 2
    # outside the solids and off the ridges where two primitives tie (the distance is smooth
    # over the whole interpolation cell there): only the curvature error is left
    second_gap = np.empty(len(pts))
    for i, p in enumerate(pts):
        dc, dr, db = _each_primitive_distance(world.cylinders, world.rings, world.boxes, *p)
        two = np.sort(np.concatenate([dc, dr, db, [p[2]]]))[:2]
        second_gap[i] = two[1] - two[0]
    smooth = (d_true > 2 * res) & (second_gap > 2 * math.sqrt(3) * res)
    assert smooth.sum() > 500
    assert np.max(err[smooth]) <= res / 8  # ~res^2 / (8 * radius of curvature)
    assert grid.is_known(pts).all()


def test_grid_outside_and_known_mask() -> None:
    values = np.full((4, 4, 2), 0.7)
    known = np.ones((4, 4, 2), dtype=bool)
    known[0, 0, 0] = False
    field = GridField(values, np.zeros(3), 0.5, known)
    outside = np.array([[-0.01, 1.0, 0.5], [1.0, 2.01, 0.5], [1.0, 1.0, 1.2], [1.0, 1.0, -3.0]])
    d, g = field.distance(outside)
    assert np.all(d == UNKNOWN_DISTANCE) and np.all(g == 0.0)
    assert not field.is_known(outside).any()
    inside = np.array([[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [2.0, 2.0, 1.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(field.is_known(inside), [False, True, True, False])
    d, g = field.distance(inside)
    np.testing.assert_allclose(d, 0.7)
    np.testing.assert_array_equal(g, 0.0)
    # without a mask everything inside the box is known
    assert GridField(values, np.zeros(3), 0.5).is_known(inside).all()


def test_grid_single_cell_axes() -> None:
    values = np.arange(3.0).reshape(3, 1, 1)
    field = GridField(values, np.zeros(3), 1.0)
    d, g = field.distance(np.array([[1.0, 0.5, 0.5], [0.2, 0.9, 0.1]]))
    np.testing.assert_allclose(d, [0.5, 0.0])
    np.testing.assert_allclose(g, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def test_grid_validation() -> None:
    with pytest.raises(ValueError, match="shape"):
        GridField(np.zeros((3, 3)), np.zeros(3), 0.1)
    with pytest.raises(ValueError, match="finite"):
        GridField(np.full((2, 2, 2), np.nan), np.zeros(3), 0.1)
    with pytest.raises(ValueError, match="res"):
        GridField(np.zeros((2, 2, 2)), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="origin"):
        GridField(np.zeros((2, 2, 2)), np.zeros(2), 0.1)
    with pytest.raises(ValueError, match="known"):
        GridField(np.zeros((2, 2, 2)), np.zeros(3), 0.1, np.ones((2, 2), dtype=bool))
    with pytest.raises(ValueError, match="points"):
        GridField(np.zeros((2, 2, 2)), np.zeros(3), 0.1).distance(np.zeros(3))
