"""A* guide paths on distance fields."""

from __future__ import annotations

import math

import numpy as np

from onboard.planner.astar import (
    ASTAR_FOUND,
    ASTAR_NO_PATH,
    astar_grid,
    astar_path,
    octile_distance,
    segment_is_free,
)
from onboard.planner.field import AnalyticField, DistanceField, GridField
from onboard.world import World, random_forest

NO_RING = np.zeros((0, 7))
NO_BOX = np.zeros((0, 6))


def _wall_world() -> World:
    """A wall of touching cylinders across y in [-3, 3] at x = 5, taller than the z limits."""
    ys = np.arange(-3.0, 3.01, 0.5)
    cyl = np.column_stack([np.full_like(ys, 5.0), ys, np.full_like(ys, 0.3), 0 * ys, 4 + 0 * ys])
    return World(cyl, NO_RING, NO_BOX, 0.0)


def _check_path(
    field: DistanceField,
    path: np.ndarray,
    start: np.ndarray,
    goal: np.ndarray,
    clr: float,
    res: float,
) -> None:
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    guaranteed = clr - res * math.sqrt(3) / 2
    for a, b in zip(path[:-1], path[1:], strict=True):
        assert segment_is_free(field, a, b, guaranteed, step_m=0.01)


def test_path_around_a_wall() -> None:
    field = AnalyticField(_wall_world())
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([10.0, 0.0, 1.0])
    assert not segment_is_free(field, start, goal, 0.4)
    # the default 3 m margin keeps the search within |y| <= 3: the wall closes it
    assert astar_path(field, start, goal, 0.4, resolution_m=0.2, z_limits=(0.5, 2.0)) is None
    path = astar_path(field, start, goal, 0.4, 0.2, margin_m=5.0, z_limits=(0.5, 2.0))
    assert path is not None
    _check_path(field, path, start, goal, 0.4, 0.2)
    assert np.abs(path[:, 1]).max() > 3.3 + 0.4 - 0.2  # it went round an end of the wall
    assert np.all((path[1:-1, 2] >= 0.5) & (path[1:-1, 2] <= 2.0))
    length = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))
    assert length < 2 * math.hypot(5.0, 3.8) + 0.5  # close to the shortest way round
    assert len(path) <= 6  # simplified


def test_path_through_a_forest_on_a_grid_field() -> None:
    start, goal = np.array([-1.0, 4.0, 1.0]), np.array([13.0, 4.0, 1.0])
    world = random_forest(5, 45, (0.0, 12.0), (0.0, 8.0), keep_clear=[(start, 1.0), (goal, 1.0)])
    truth = AnalyticField(world)
    grid = GridField.from_function(truth.distance, [-5.0, -4, 0], [17.0, 12, 3], 0.1)
    for field in (truth, grid):
        path = astar_path(field, start, goal, 0.35, resolution_m=0.2, z_limits=(0.5, 1.8))
        assert path is not None
        _check_path(field, path, start, goal, 0.35, 0.2)
        # with the true distance (the grid interpolates it within a few centimetres)
        _check_path(truth, path, start, goal, 0.3, 0.2)


def test_blocked_returns_none() -> None:
    wall = World(np.zeros((0, 5)), NO_RING, np.array([[4.0, -50, -50, 6.0, 50, 50]]), None)
    path = astar_path(AnalyticField(wall), np.array([0.0, 0, 1]), np.array([10.0, 0, 1]), 0.3)
    assert path is None


def test_expansion_limit_returns_none() -> None:
    field = AnalyticField(_wall_world())
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([10.0, 0.0, 1.0])
    for limit, found in ((50, False), (50_000, True)):
        path = astar_path(field, start, goal, 0.4, 0.2, 5.0, (0.5, 2.0), max_expansions=limit)
        assert (path is not None) == found


def test_trivial_cases() -> None:
    field = AnalyticField(World.empty(0.0))
    p = np.array([1.0, 2.0, 1.5])
    path = astar_path(field, p, p.copy(), 0.5)
    assert path is not None
    np.testing.assert_array_equal(path, [p, p])
    goal = np.array([6.0, -3.0, 2.0])
    path = astar_path(field, p, goal, 0.5)
    assert path is not None
    np.testing.assert_array_equal(path, [p, goal])  # free straight line: nothing in between


def test_start_inside_clearance_zone() -> None:
    field = AnalyticField(_wall_world())
    start, goal = np.array([4.6, 0.0, 1.0]), np.array([10.0, 0.0, 1.0])  # 0.1 m from a trunk
    path = astar_path(field, start, goal, 0.4, margin_m=5.0, z_limits=(0.5, 2.0))
    assert path is not None
    np.testing.assert_array_equal(path[0], start)
    guaranteed = 0.4 - 0.2 * math.sqrt(3) / 2
    for a, b in zip(path[1:-1], path[2:], strict=True):
        assert segment_is_free(field, a, b, guaranteed, step_m=0.01)


def test_astar_grid_kernel() -> None:
    occ = np.zeros((10, 10, 1), dtype=bool)
    occ[5, :9, 0] = True
    cells, status = astar_grid(occ, np.array([0, 0, 0]), np.array([9, 0, 0]), 10_000)
    assert status == ASTAR_FOUND
    assert tuple(cells[0]) == (0, 0, 0) and tuple(cells[-1]) == (9, 0, 0)
    steps = np.abs(np.diff(cells, axis=0))
    assert steps.max() == 1 and not occ[cells[:, 0], cells[:, 1], cells[:, 2]].any()
    assert (9, 0) in {(c[0], c[1]) for c in cells}
    occ[5, 9, 0] = True
    _, status = astar_grid(occ, np.array([0, 0, 0]), np.array([9, 0, 0]), 10_000)
    assert status == ASTAR_NO_PATH
    assert math.isclose(octile_distance(3, -1, 2), math.sqrt(3) + math.sqrt(2) + 1)


def test_segment_is_free() -> None:
    field = AnalyticField(_wall_world())
    assert segment_is_free(field, np.array([0.0, 0, 1]), np.array([4.0, 0, 1]), 0.5)
    assert not segment_is_free(field, np.array([0.0, 0, 1]), np.array([6.0, 0, 1]), 0.5)
    assert segment_is_free(field, np.array([1.0, 1, 1]), np.array([1.0, 1, 1]), 0.5)
