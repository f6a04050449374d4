"""e_dist (Sim(3)-aligned formation error) and the summary statistics."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_umeyama_recovers_a_known_similarity_exactly() -> None:
    from gcs.metrics import umeyama

    rng = np.random.default_rng(3)
    for _ in range(5):
        current = rng.normal(size=(7, 3)) * 2.0
        R = _rotation(rng)
        s = float(rng.uniform(0.3, 3.0))
        t = rng.normal(size=3) * 5.0
        desired = s * current @ R.T + t
        s_hat, R_hat, t_hat = umeyama(current, desired)
        assert abs(s_hat - s) < 1e-9
        np.testing.assert_allclose(R_hat, R, atol=1e-9)
        np.testing.assert_allclose(t_hat, t, atol=1e-9)
        assert e_dist(current, desired) < 1e-9


def test_e_dist_is_the_residual_of_the_umeyama_alignment() -> None:
    from gcs.metrics import umeyama

    rng = np.random.default_rng(4)
    desired = rng.normal(size=(7, 3))
    current = desired + rng.normal(scale=0.3, size=(7, 3))
    s, R, t = umeyama(current, desired)
    residual = float(np.sum((desired - (s * current @ R.T + t)) ** 2))
    assert abs(e_dist(current, desired) - np.sqrt(residual)) < 1e-9
    # no other similarity does better (random perturbations of the optimum)
    for _ in range(50):
        s2 = s * float(rng.uniform(0.95, 1.05))
        t2 = t + rng.normal(scale=0.05, size=3)
        other = float(np.sum((desired - (s2 * current @ R.T + t2)) ** 2))
        assert other >= residual - 1e-12


def _laplacian_distance(current: np.ndarray, desired: np.ndarray) -> float:
    """Paper Eq. 1-4 written out densely with numpy, independent of the planner's kernel."""

    def lap(p: np.ndarray) -> np.ndarray:
        diff = p[:, None, :] - p[None, :, :]
        a = np.einsum("ijk,ijk->ij", diff, diff)  # w_ij = ||p_i - p_j||^2, zero diagonal
        d = a.sum(axis=1)
        dm = np.diag(1.0 / np.sqrt(d))
        return np.eye(len(p)) - dm @ a @ dm

    return float(np.linalg.norm(lap(current) - lap(desired), "fro") ** 2)


def test_flight_e_sim_is_the_papers_metric() -> None:
    from gcs.fastsim import SimConfig, run_sim
    from onboard.config import load_formation, load_world_spec

    form = load_formation("triangle-3")
    cfg = SimConfig(formation=form, world=load_world_spec("forest-small"), seed=2, v_max_m_s=1.0)
    r = run_sim(cfg)
    ks = range(0, r.tracks.pos.shape[0], 25)
    expected = np.array([_laplacian_distance(r.tracks.pos[k], form.points) for k in ks])
    np.testing.assert_allclose(r.tracks.e_sim[list(ks)], expected, rtol=1e-9, atol=1e-12)
    # the flight is not trivially in shape: the comparison covers non-zero values
    assert expected.max() > 1e-4
    # and the recorded mean is the mean of the recorded samples
    assert r.e_sim_mean == pytest.approx(float(np.mean(r.tracks.e_sim)), rel=1e-12)
