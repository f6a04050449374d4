"""Formation similarity metric (paper Sec. III): gradient, invariances, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.planner.formation import (
    EPS_DEG,
    STACK_N,
    complete_mask,
    metric_kernel,
    normalized_adjacency,
    similarity,
)

HEXAGON = np.array(
    [
        [0.0, 0.0, 0.0],
        [1.7321, 1.0, 0.0],
        [1.7321, -1.0, 0.0],
        [0.0, 2.0, 0.0],
        [0.0, -2.0, 0.0],
        [-1.7321, 1.0, 0.0],
        [-1.7321, -1.0, 0.0],
    ]
)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def sparse_mask(n: int, rng: np.random.Generator) -> np.ndarray:
    """A connected, non-complete symmetric mask: a ring plus some random chords."""
    m = np.zeros((n, n))
    for i in range(n):
        j = (i + 1) % n
        m[i, j] = m[j, i] = 1.0
    for _ in range(n // 2):
        i, j = rng.choice(n, size=2, replace=False)
        m[i, j] = m[j, i] = 1.0
    assert m.sum() < n * (n - 1)
    return m


def numeric_grad(P: np.ndarray, Q: np.ndarray, mask: np.ndarray, h: float = 1e-6) -> np.ndarray:
    g = np.zeros_like(P)
    for i in range(P.shape[0]):
        for k in range(3):
            Pp = P.copy()
            Pm = P.copy()
            Pp[i, k] += h
            Pm[i, k] -= h
            g[i, k] = (similarity(Pp, Q, mask)[0] - similarity(Pm, Q, mask)[0]) / (2 * h)
    return g


@pytest.mark.parametrize("n", [3, 4, 7, 10])
@pytest.mark.parametrize("use_mask", [False, True])
def test_gradient_matches_central_differences(n: int, use_mask: bool) -> None:
    rng = np.random.default_rng(100 + n + 1000 * use_mask)
    mask = sparse_mask(n, rng) if use_mask and n >= 4 else complete_mask(n)
    for _ in range(3):
        P = rng.normal(scale=2.0, size=(n, 3))
        Q = rng.normal(scale=2.0, size=(n, 3))
        f, g = similarity(P, Q, mask)
        assert f > 1e-4
        gn = numeric_grad(P, Q, mask)
        assert np.linalg.norm(g - gn) <= 1e-5 * np.linalg.norm(gn)


def test_kernel_matches_wrapper_and_overwrites_output() -> None:
    rng = np.random.default_rng(1)
    P = rng.normal(size=(7, 3))
    Q = rng.normal(size=(7, 3))
    mask = complete_mask(7)
    f, g = similarity(P, Q)
    out = np.full((7, 3), np.nan)
    assert metric_kernel(P, normalized_adjacency(Q, mask), mask, out) == f
    np.testing.assert_array_equal(out, g)


@pytest.mark.parametrize("n", [STACK_N, STACK_N + 1, 70])
def test_kernel_stack_limit_and_heap_fallback(n: int) -> None:
    rng = np.random.default_rng(2)
    P = rng.normal(size=(n, 3))
    Q = rng.normal(size=(n, 3))
    f, g = similarity(P, Q)
    gn = numeric_grad(P, Q, complete_mask(n))
    assert np.isfinite(f)
    assert np.linalg.norm(g - gn) <= 1e-5 * np.linalg.norm(gn)


def test_metric_definition_matches_laplacian() -> None:
    """f equals ||L^ - L^_des||_F^2 computed directly with dense matrices (Eq. 1-4)."""
    rng = np.random.default_rng(3)
    P = rng.normal(size=(6, 3))
    Q = rng.normal(size=(6, 3))

    def lap(X: np.ndarray) -> np.ndarray:
        W = np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=2)
        r = 1.0 / np.sqrt(W.sum(axis=1) + EPS_DEG)
        return np.eye(len(X)) - r[:, None] * W * r[None, :]

    f, _ = similarity(P, Q)
    assert f == pytest.approx(np.sum((lap(P) - lap(Q)) ** 2), rel=1e-12)


def test_invariances() -> None:
    rng = np.random.default_rng(4)
    for n in (3, 7, 10):
        P = rng.normal(scale=3.0, size=(n, 3))
        Q = rng.normal(scale=3.0, size=(n, 3))
        f, _ = similarity(P, Q)
        R = random_rotation(rng)
        t = rng.normal(scale=10.0, size=3)
        # (scale invariance holds up to the regulariser, a relative EPS_DEG / degree ~ 1e-13 here)
        for P2 in (P + t, P @ R.T, 7.3 * P, 0.3 * P, 2.5 * P @ R.T + t):
            assert similarity(P2, Q)[0] == pytest.approx(f, rel=1e-12, abs=1e-12)
        # the desired formation is only defined up to similarity as well
        assert similarity(P, 4.0 * Q @ R.T - t)[0] == pytest.approx(f, rel=1e-12, abs=1e-12)


def test_zero_at_desired_and_similar_copies() -> None:
    rng = np.random.default_rng(5)
    f, g = similarity(HEXAGON, HEXAGON)
    assert f == 0.0
    np.testing.assert_allclose(g, 0.0, atol=1e-12)
    for _ in range(5):
        R = random_rotation(rng)
        P = rng.uniform(0.2, 20.0) * HEXAGON @ R.T + rng.normal(scale=50.0, size=3)
        f, g = similarity(P, HEXAGON)
        assert f <= 1e-24
        np.testing.assert_allclose(g, 0.0, atol=1e-10)


def test_two_points_are_always_similar() -> None:
    rng = np.random.default_rng(9)
    f, g = similarity(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)))
    assert f == pytest.approx(0.0, abs=1e-24)
    np.testing.assert_allclose(g, 0.0, atol=1e-10)


def test_positive_for_a_different_shape() -> None:
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    rectangle = square * np.array([2.0, 1.0, 1.0])
    assert similarity(rectangle, square)[0] > 1e-3


@pytest.mark.parametrize("use_mask", [False, True])
def test_consistent_permutation_leaves_f_unchanged(use_mask: bool) -> None:
    rng = np.random.default_rng(6)
    n = 7
    mask = sparse_mask(n, rng) if use_mask else complete_mask(n)
    P = rng.normal(size=(n, 3))
    Q = rng.normal(size=(n, 3))
    f, g = similarity(P, Q, mask)
    perm = rng.permutation(n)
    f2, g2 = similarity(P[perm], Q[perm], mask[np.ix_(perm, perm)])
    assert f2 == pytest.approx(f, rel=1e-12)
    np.testing.assert_allclose(g2, g[perm], rtol=1e-10, atol=1e-12)


def test_coincident_points_are_finite() -> None:
    rng = np.random.default_rng(7)
    P = rng.normal(size=(5, 3))
    P[3] = P[1]
    f, g = similarity(P, HEXAGON[:5])
    assert np.isfinite(f) and np.all(np.isfinite(g))
    # still the exact gradient of the (regularised) metric
    gn = numeric_grad(P, HEXAGON[:5], complete_mask(5))
    assert np.linalg.norm(g - gn) <= 1e-5 * np.linalg.norm(gn)

    same = np.ones((5, 3))
    f, g = similarity(same, HEXAGON[:5])
    assert np.isfinite(f) and np.all(np.isfinite(g))
    np.testing.assert_array_equal(g, 0.0)
    # all points coincide: S = 0, so f is the squared norm of the desired S
    S_des = normalized_adjacency(HEXAGON[:5], complete_mask(5))
    assert f == pytest.approx(np.sum(S_des**2), rel=1e-12)
    # a desired formation with coincident points is accepted too
    f, g = similarity(P, same)
    assert np.isfinite(f) and np.all(np.isfinite(g))


def test_normalized_adjacency_properties() -> None:
    rng = np.random.default_rng(8)
    P = rng.normal(size=(6, 3))
    mask = sparse_mask(6, rng)
    S = normalized_adjacency(P, mask)
    np.testing.assert_array_equal(S, S.T)
    np.testing.assert_array_equal(np.diag(S), 0.0)
    np.testing.assert_array_equal(S[mask == 0.0], 0.0)
    # largest eigenvalue of D^-1/2 A D^-1/2 is 1 (eigenvector sqrt(d))
    assert np.max(np.linalg.eigvalsh(S)) == pytest.approx(1.0, rel=1e-9)


def test_complete_mask() -> None:
    m = complete_mask(3)
    np.testing.assert_array_equal(m, [[0, 1, 1], [1, 0, 1], [1, 1, 0]])
    assert m.dtype == np.float64
    with pytest.raises(ValueError):
        complete_mask(0)


@pytest.mark.parametrize(
    ("points", "desired", "mask", "match"),
    [
        (np.zeros((4, 2)), np.zeros((4, 3)), None, "shape"),
        (np.zeros(3), np.zeros((1, 3)), None, "shape"),
        (np.zeros((1, 3)), np.zeros((1, 3)), None, "at least 2"),
        (np.zeros((4, 3)), np.zeros((5, 3)), None, "same shape"),
        (np.full((4, 3), np.nan), np.zeros((4, 3)), None, "non-finite"),
        (np.zeros((4, 3)), np.full((4, 3), np.inf), None, "non-finite"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.ones((3, 3)), "mask must have shape"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.ones((4, 4)), "diagonal"),
        (np.zeros((4, 3)), np.zeros((4, 3)), 0.5 * complete_mask(4), "0 or 1"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.triu(complete_mask(4)), "symmetric"),
    ],
)
def test_bad_inputs_raise(
    points: np.ndarray, desired: np.ndarray, mask: np.ndarray | None, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        similarity(points, desired, mask)


def test_hot_path_kernel_matches_the_full_gradient() -> None:
    from onboard.planner.formation import metric_kernel, metric_own_rate, normalized_adjacency

    rng = np.random.default_rng(99)
    for n in (2, 4, 7, 10):
        P = rng.normal(size=(n, 3)) * 2.0
        V = rng.normal(size=(n, 3))
        desired = rng.normal(size=(n, 3))
        mask = complete_mask(n)
        if n > 3:
            mask[0, 2] = mask[2, 0] = 0.0
        sdes = normalized_adjacency(desired, mask)
        G = np.empty((n, 3))
        f_full = metric_kernel(P, sdes, mask, G)
        f, gx, gy, gz, rate = metric_own_rate(
            P, V, sdes, mask, np.empty((n, n)), np.empty(n), np.empty(n)
        )
        assert f == pytest.approx(f_full, rel=1e-12, abs=1e-15)
        np.testing.assert_allclose([gx, gy, gz], G[0], rtol=1e-10, atol=1e-13)
        assert rate == pytest.approx(float(np.sum(G[1:] * V[1:])), rel=1e-10, abs=1e-13)
