"""e_dist (Sim(3)-aligned formation error) and the summary statistics."""

from __future__ import annotations

import numpy as np

from gcs.metrics import e_dist, summary


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_similar_copies_have_zero_error() -> None:
    rng = np.random.default_rng(0)
    desired = rng.normal(size=(7, 3))
    current = 2.5 * desired @ _rotation(rng).T + np.array([3.0, -1.0, 4.0])
    assert e_dist(current, desired) < 1e-9
    # A planar formation and its mirror image are related by a rotation in 3-D.
    planar = desired.copy()
    planar[:, 2] = 0.0
    mirrored = planar * np.array([1.0, -1.0, 1.0])
    assert e_dist(mirrored, planar) < 1e-9


def test_error_matches_a_known_residual() -> None:
    desired = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    current = desired.copy()
    current[2, 1] += 0.1
    current[3, 1] -= 0.1
    # Brute force over scale and in-plane rotation (the optimum is in the plane here).
    best = np.inf
    c0 = current - current.mean(axis=0)
    for s in np.linspace(0.8, 1.1, 301):
        for a in np.linspace(-0.05, 0.05, 21):
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            best = min(best, float(np.sum((desired - s * c0 @ R.T) ** 2)))
    assert abs(e_dist(current, desired) ** 2 - best) < 1e-5
    assert e_dist(np.zeros((4, 3)), desired) == np.sqrt(4.0)


def test_summary() -> None:
    s = summary([1.0, 2.0, 3.0, 4.0])
    assert s["median"] == 2.5 and s["max"] == 4.0 and s["count"] == 4
    assert np.isnan(summary([])["median"]) and summary([])["count"] == 0
