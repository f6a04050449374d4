"""World model: exact signed distances, gradients, random forests, within() and merged()."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from onboard.world import (
    FAR_DISTANCE_M,
    World,
    _each_primitive_distance,
    primitives_distance,
    random_forest,
)

NO_CYL = np.zeros((0, 5))
NO_RING = np.zeros((0, 7))
NO_BOX = np.zeros((0, 6))


def _world(cyl: object = NO_CYL, rings: object = NO_RING, boxes: object = NO_BOX) -> World:
    return World(np.array(cyl, float), np.array(rings, float), np.array(boxes, float), None)


def _check(world: World, p: tuple[float, float, float], d: float, g: tuple[float, ...]) -> None:
    dd, gg = world.distance(np.array([p], dtype=float))
    assert dd[0] == pytest.approx(d, abs=1e-12)
    np.testing.assert_allclose(gg[0], g, atol=1e-12)


# ------------------------------------------------------------------ exact values


def test_cylinder_exact_values() -> None:
    w = _world(cyl=[[0.0, 0.0, 1.0, 0.0, 2.0]])
    _check(w, (3.0, 0.0, 1.0), 2.0, (1, 0, 0))  # side
    _check(w, (0.0, -2.0, 0.5), 1.0, (0, -1, 0))  # side, other direction
    _check(w, (0.5, 0.0, 3.0), 1.0, (0, 0, 1))  # above the top disc
    _check(w, (0.0, 0.5, -1.5), 1.5, (0, 0, -1))  # below the bottom disc
    _check(w, (4.0, 0.0, 6.0), 5.0, (0.6, 0, 0.8))  # nearest the top rim
    _check(w, (0.0, -4.0, -4.0), 5.0, (0, -0.6, -0.8))  # nearest the bottom rim
    _check(w, (0.5, 0.0, 1.8), -0.2, (0, 0, 1))  # inside, nearer the top
    _check(w, (0.0, 0.9, 1.0), -0.1, (0, 1, 0))  # inside, nearer the side
    _check(w, (0.0, 0.0, 0.3), -0.3, (0, 0, -1))  # inside on the axis, nearer the bottom


def test_box_exact_values() -> None:
    w = _world(boxes=[[0.0, 0.0, 0.0, 2.0, 4.0, 6.0]])
    _check(w, (1.5, 1.0, 3.0), -0.5, (1, 0, 0))  # inside
    _check(w, (1.0, 3.8, 3.0), -0.2, (0, 1, 0))  # inside
    _check(w, (1.0, 2.0, 0.1), -0.1, (0, 0, -1))  # inside
    _check(w, (3.0, 2.0, 3.0), 1.0, (1, 0, 0))  # outside a face
    _check(w, (3.0, 5.0, 3.0), math.sqrt(2), (1 / math.sqrt(2), 1 / math.sqrt(2), 0))  # edge
    _check(w, (-1.0, -2.0, 8.0), 3.0, (-1 / 3, -2 / 3, 2 / 3))  # corner


def test_ground_and_empty() -> None:
    w = World.empty(0.5)
    _check(w, (1.0, 2.0, 2.0), 1.5, (0, 0, 1))
    _check(w, (1.0, 2.0, 0.0), -0.5, (0, 0, 1))
    d, g = World.empty(None).distance(np.zeros((3, 3)))
    assert np.all(d == FAR_DISTANCE_M) and np.all(g == 0.0)
    # the ground competes with the primitives
    w2 = World(np.array([[0.0, 0.0, 0.5, 0.0, 2.0]]), NO_RING, NO_BOX, 0.0)
    _check(w2, (3.0, 0.0, 1.0), 1.0, (0, 0, 1))


def test_ring_exact_values() -> None:
    # circle of radius 1 in the plane x = 0 (yaw 0: normal +x, u = +y), tube 0.1
    w = _world(rings=[[0.0, 0.0, 2.0, 0.0, 1.0, 1.0, 0.1]])
    _check(w, (0.0, 2.0, 2.0), 0.9, (0, 1, 0))
    _check(w, (0.0, 0.0, 2.5), 0.4, (0, 0, -1))
    _check(w, (0.5, 0.0, 3.0), 0.4, (1, 0, 0))  # in front of the top of the circle
    d, g = w.distance(np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]]))  # centre, on the axis
    np.testing.assert_allclose(d, [0.9, math.sqrt(1.25) - 0.1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0)
    # ellipse 2 (horizontal) x 1 (vertical), yaw 90 deg: normal +y, u = -x
    w = _world(rings=[[1.0, 1.0, 2.0, math.pi / 2, 2.0, 1.0, 0.0]])
    _check(w, (1.0 + 3.0, 1.0, 2.0), 1.0, (1, 0, 0))  # beyond the end of the major axis
    _check(w, (1.0, 1.0, 5.0), 2.0, (0, 0, 1))  # above, on the minor axis
    _check(w, (1.0, 1.0, 2.0), 1.0, (0, 0, -1))  # centre: nearest at the minor vertices
    # inside, on the major axis near the centre: the nearest point leaves the axis
    x0 = 4.0 * 0.5 / 3.0
    x1 = math.sqrt(1.0 - (x0 / 2.0) ** 2)
    d, g = w.distance(np.array([[1.0 - 0.5, 1.0, 2.0]]))
    assert d[0] == pytest.approx(math.hypot(x0 - 0.5, x1), abs=1e-12)
    # tall ellipse (vertical axis longer): symmetric case through the swapped branch
    w = _world(rings=[[0.0, 0.0, 3.0, 0.0, 1.0, 2.0, 0.0]])
    _check(w, (0.0, 0.0, 6.0), 1.0, (0, 0, 1))
    _check(w, (0.0, -3.0, 3.0), 2.0, (0, -1, 0))


def _brute_ring_distance(ring: np.ndarray, p: np.ndarray) -> float:
    """Distance to the ellipse curve by dense sampling of its angle plus a bounded refinement."""
    cx, cy, cz, yaw, rh, rv, tube = ring
    u = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    c = np.array([cx, cy, cz])

    def dist(theta: float | np.ndarray) -> np.ndarray:
        th = np.atleast_1d(theta)
        q = c + np.outer(rh * np.cos(th), u) + np.outer(rv * np.sin(th), [0.0, 0.0, 1.0])
        return np.linalg.norm(q - p, axis=1)

    th = np.linspace(-math.pi, math.pi, 20001)
    dd = dist(th)
    k = int(np.argmin(dd))
    step = th[1] - th[0]
    res = minimize_scalar(
        lambda t: float(dist(t)[0]),
        bounds=(th[k] - 2 * step, th[k] + 2 * step),
        method="bounded",
        options={"xatol": 1e-13},
    )
    return min(float(res.fun), float(dd[k])) - tube


def test_ring_against_brute_force() -> None:
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(60):
        ring = np.array(
            [
                *rng.uniform(-1, 1, 2),
                rng.uniform(1, 2),
                rng.uniform(-math.pi, math.pi),
                rng.uniform(0.3, 2.0),
                rng.uniform(0.3, 2.0),
                rng.choice([0.0, 0.1]),
            ]
        )
        if rng.random() < 0.2:
            ring[5] = ring[4]  # circles too
        w = _world(rings=[ring])
        # points near the ring: inside the ellipse, outside it, off the plane
        pts = ring[:3] + rng.normal(size=(8, 3)) * max(ring[4], ring[5])
        d, g = w.distance(pts)
        for p, dp in zip(pts, d, strict=True):
            worst = max(worst, abs(dp - _brute_ring_distance(ring, p)))
        np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    assert worst < 1e-6


# ------------------------------------------------------------------ gradients


def _mixed_world() -> World:
    return World(
        np.array([[0.0, 0.0, 0.4, 0.0, 2.5], [2.0, 1.0, 0.3, 0.5, 3.0]]),
        np.array(
            [
                [1.0, -1.5, 1.5, 0.4, 1.2, 0.7, 0.1],
                [-2.0, 1.0, 2.0, -1.0, 0.8, 0.8, 0.0],
                [3.0, -2.0, 1.8, 2.0, 0.6, 1.1, 0.05],
            ]
        ),
        np.array([[-3.0, -3.0, 0.0, -2.0, -2.0, 1.0], [1.5, 2.0, 1.0, 2.5, 3.0, 2.0]]),
        -0.5,
    )


def test_gradient_central_differences() -> None:
    w = _mixed_world()
    args = (w.cylinders, w.rings, w.boxes, w.ground_z_or_nan)
    rng = np.random.default_rng(3)
    h = 1e-6
    checked = 0
    for p in rng.uniform([-4, -4, -0.5], [4, 4, 3.5], size=(600, 3)):
        d, *g = primitives_distance(*args, *p)
        fd = np.empty(3)
        kink = False
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            dp = primitives_distance(*args, *(p + e))[0]
            dm = primitives_distance(*args, *(p - e))[0]
            # skip points on a kink (two primitives tie, medial axes): one-sided slopes differ
            if abs((dp - d) - (d - dm)) > 1e-3 * h:
                kink = True
            fd[a] = (dp - dm) / (2 * h)
        if kink:
            continue
        checked += 1
        assert np.linalg.norm(np.array(g) - fd) <= 1e-5 * max(float(np.linalg.norm(fd)), 1e-3)
    assert checked > 550


def test_gradient_unit_and_finite_at_degeneracies() -> None:
    w = _mixed_world()
    pts = np.array(
        [
            [0.0, 0.0, 1.0],  # cylinder axis
            [0.0, 0.0, 1.25],  # cylinder centre
            [-2.0, 1.0, 2.0],  # circle ring centre
            [1.0, -1.5, 1.5],  # ellipse ring centre
            [-2.0, 1.0, 2.8],  # on the ring curve (tube 0)
            [-2.5, -2.5, 0.5],  # box centre
            [2.0, 2.5, 1.5],  # box centre
        ]
    )
    d, g = w.distance(pts)
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(g))
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    assert d[4] == pytest.approx(0.0, abs=1e-12)


# ------------------------------------------------------------------ World API


def test_validation_errors() -> None:
    with pytest.raises(ValueError, match="radius"):
        _world(cyl=[[0, 0, -1, 0, 1]])
    with pytest.raises(ValueError, match="z_min"):
        _world(cyl=[[0, 0, 1, 2, 1]])
    with pytest.raises(ValueError, match="shape"):
        _world(cyl=[[0, 0, 1, 2]])
    with pytest.raises(ValueError, match="non-finite"):
        _world(cyl=[[0, 0, np.nan, 0, 1]])
    with pytest.raises(ValueError, match="ellipse radii"):
        _world(rings=[[0, 0, 1, 0, 0.0, 1, 0.1]])
    with pytest.raises(ValueError, match="tube"):
        _world(rings=[[0, 0, 1, 0, 1, 1, -0.1]])
    with pytest.raises(ValueError, match="min must be < max"):
        _world(boxes=[[0, 0, 0, 1, 0, 1]])
    with pytest.raises(ValueError, match="ground_z"):
        World(NO_CYL, NO_RING, NO_BOX, math.inf)
    with pytest.raises(ValueError, match="points"):
        World.empty().distance(np.zeros((4, 2)))
    w = _world(cyl=[[0, 0, 1, 0, 1]])
    assert not w.cylinders.flags.writeable and w.cylinders.dtype == np.float64


def test_within_keeps_everything_that_matters() -> None:
    world = random_forest(
        11, 80, (0.0, 20.0), (0.0, 10.0), n_rings=3, ring_height_range=(1.0, 2.0)
    ).merged(
        World(NO_CYL, NO_RING, np.array([[5.0, 5.0, 0.0, 6.0, 6.5, 1.0], [15, 1, 2, 16, 2, 3]]))
    )
    rng = np.random.default_rng(5)
    for _ in range(10):
        centre = rng.uniform([0, 0, 0], [20, 10, 3])
        radius = rng.uniform(1.0, 4.0)
        local = world.within(centre, radius)
        assert local.n_primitives < world.n_primitives
        assert local.ground_z == world.ground_z
        # points within the radius: the local field equals the full one wherever the true
        # distance is below radius - |p - centre| (the most a dropped primitive could affect)
        dirs = rng.normal(size=(2000, 3))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        pts = centre + dirs * radius * rng.random((2000, 1)) ** (1 / 3)
        d_full, _ = world.distance(pts)
        d_loc, _ = local.distance(pts)
        slack = radius - np.linalg.norm(pts - centre, axis=1)
        assert np.all(d_loc >= d_full - 1e-12)
        np.testing.assert_array_equal(np.minimum(d_loc, slack), np.minimum(d_full, slack))
        # and the exact selection rule: every primitive kept is within the radius
        dc, dr, db = _each_primitive_distance(local.cylinders, local.rings, local.boxes, *centre)
        assert np.all(dc <= radius) and np.all(dr <= radius) and np.all(db <= radius)


def test_merged_dedupes_and_checks_ground() -> None:
    w = random_forest(2, 20, (0.0, 10.0), (0.0, 10.0), n_rings=2)
    a = World(w.cylinders[:12], w.rings[:1], NO_BOX, 0.0)
    b = World(w.cylinders[8:], w.rings, NO_BOX, None)
    m = a.merged(b)
    np.testing.assert_array_equal(m.cylinders, w.cylinders)
    np.testing.assert_array_equal(m.rings, w.rings)
    assert m.ground_z == 0.0
    mm = m.merged(m)
    np.testing.assert_array_equal(mm.cylinders, w.cylinders)
    with pytest.raises(ValueError, match="ground"):
        a.merged(World.empty(1.0))


# ------------------------------------------------------------------ random forest


def _ring_curve(ring: np.ndarray, n: int = 720) -> np.ndarray:
    cx, cy, cz, yaw, rh, rv, _ = ring
    th = np.linspace(0, 2 * math.pi, n, endpoint=False)
    u = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    return (
        np.array([cx, cy, cz])
        + np.outer(rh * np.cos(th), u)
        + np.outer(rv * np.sin(th), [0, 0, 1.0])
    )


def test_random_forest_properties() -> None:
    start = np.array([0.0, 5.0, 1.0])
    goal = np.array([20.0, 5.0, 1.0])
    clear = [(start, 1.5), (goal, 1.5)]

    def forest(seed: int) -> World:
        return random_forest(seed, 50, (0.0, 20.0), (0.0, 10.0), n_rings=3, keep_clear=clear)

    w, w2, w3 = forest(4), forest(4), forest(5)
    np.testing.assert_array_equal(w.cylinders, w2.cylinders)
    np.testing.assert_array_equal(w.rings, w2.rings)
    assert not np.array_equal(w.cylinders, w3.cylinders)
    c = w.cylinders
    assert c.shape == (50, 5) and w.rings.shape == (3, 7)
    assert np.all((c[:, 0] >= 0) & (c[:, 0] <= 20) & (c[:, 1] >= 0) & (c[:, 1] <= 10))
    assert np.all((2 * c[:, 2] >= 0.25) & (2 * c[:, 2] <= 0.75))
    assert np.all(c[:, 3] == 0.0) and np.all((c[:, 4] >= 2.0) & (c[:, 4] <= 3.0))
    gaps = np.linalg.norm(c[:, None, :2] - c[None, :, :2], axis=2) + np.eye(50) * 1.0e9
    assert gaps.min() >= 0.8
    for centre, radius in clear:
        assert np.all(np.linalg.norm(c[:, :2] - centre[:2], axis=1) - c[:, 2] >= radius)
        for ring in w.rings:
            horiz = np.linalg.norm(_ring_curve(ring)[:, :2] - centre[:2], axis=1)
            assert horiz.min() - ring[6] >= radius - 1e-9
    cyl_only = World(c, NO_RING, NO_BOX, None)
    for ring in w.rings:
        assert ring[2] - ring[5] - ring[6] >= 0.0  # above the ground
        d, _ = cyl_only.distance(_ring_curve(ring))
        assert d.min() > ring[6]  # the tube does not touch a cylinder


def test_random_forest_impossible_request_raises() -> None:
    with pytest.raises(ValueError, match="could not place cylinder"):
        random_forest(0, 200, (0.0, 5.0), (0.0, 5.0))
    with pytest.raises(ValueError, match="could not place ring"):
        random_forest(0, 0, (0.0, 2.0), (0.0, 2.0), n_rings=5)
