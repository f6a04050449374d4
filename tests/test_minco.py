"""MINCO: boundary conditions, optimality (C^4 at inner waypoints), energy, adjoint gradients."""

import numpy as np
import pytest
from scipy.integrate import trapezoid

from onboard.planner.minco import Minco
from onboard.planner.trajectory import Trajectory


def _random_minco(seed: int, M: int) -> Minco:
    rng = np.random.default_rng(seed)
    m = Minco(M)
    head = rng.normal(size=(3, 3))
    tail = rng.normal(size=(3, 3))
    m.set_conditions(head, tail)
    q = np.cumsum(rng.normal(size=(M - 1, 3)) + 1.0, axis=0)
    T = rng.uniform(0.5, 2.0, size=M)
    m.set_parameters(q, T)
    return m


def _derivs(c: np.ndarray, t: float) -> np.ndarray:
    """Derivatives 0..4 of one piece (6, 3) at t, as (5, 3)."""
    out = np.zeros((5, 3))
    for k in range(5):
        for j in range(k, 6):
            fac = np.prod(np.arange(j - k + 1, j + 1)) if k > 0 else 1.0
            out[k] += fac * c[j] * t ** (j - k)
    return out


@pytest.mark.parametrize("M", [1, 2, 5])
def test_boundary_conditions_and_waypoints(M: int) -> None:
    m = _random_minco(1, M)
    c = m.coeffs
    start = _derivs(c[0], 0.0)
    end = _derivs(c[-1], m.T[-1])
    np.testing.assert_allclose(start[:3], m.head, atol=1e-9)
    np.testing.assert_allclose(end[:3], m.tail, atol=1e-8)
    for i in range(M - 1):
        np.testing.assert_allclose(_derivs(c[i], m.T[i])[0], m.q[i], atol=1e-8)


def test_a_trajectory_sampled_at_its_end_time_gives_its_end_state() -> None:
    """At ``t_end_s`` (t0 plus the sum of the durations, rounded) the end state, not the hold
    after it: a plan ending at speed is sampled there; a little later, the hold."""
    hits = 0
    for seed in range(40):
        m = _random_minco(seed, 3)
        tr = Trajectory(1.0e4 + 0.1 * seed, m.coeffs, m.T)
        np.testing.assert_allclose(tr.sample(tr.t_end_s, order=1), m.tail[1], atol=1e-7)
        p, v, a = tr.state(tr.t_end_s)
        np.testing.assert_allclose(np.stack([p, v, a]), m.tail, atol=1e-6)
        after = tr.sample(tr.t_end_s + 1e-6, order=1)
        np.testing.assert_array_equal(after, np.zeros(3))
        # the rounding this guards against: the piece search overshoots the last duration
        rest = tr.t_end_s - tr.t0_s
        for T in m.T[:-1]:
            rest -= T
        hits += rest > m.T[-1]
    assert hits > 0, "no case where the piece search rounds past the end"


def test_derivatives_zero_to_four_continuous_at_inner_waypoints() -> None:
    m = _random_minco(2, 6)
    c = m.coeffs
    for i in range(5):
        left = _derivs(c[i], m.T[i])
        right = _derivs(c[i + 1], 0.0)
        np.testing.assert_allclose(left, right, rtol=1e-7, atol=1e-7)


def test_energy_equals_numerical_integral_of_squared_jerk() -> None:
    m = _random_minco(3, 4)
    e, _, _ = m.energy()
    traj = Trajectory(0.0, m.coeffs, m.T)
    t = np.linspace(0.0, traj.duration_s, 200_001)
    j = traj.sample(t, order=3)
    numeric = trapezoid(np.sum(j * j, axis=1), t)
    assert e == pytest.approx(numeric, rel=1e-6)


def _central_diff(fun, x: np.ndarray, h: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    g = np.zeros_like(x)
    for k in range(x.size):
        e = np.zeros_like(x)
        e.flat[k] = h
        g.flat[k] = (fun(x + e) - fun(x - e)) / (2 * h)
    return g


def test_adjoint_gradient_of_energy_and_arbitrary_cost() -> None:
    """dJ/dq, dJ/dT through c = C(q, T) for J = energy + a random linear + quadratic in c, T."""
    M = 5
    base = _random_minco(4, M)
    rng = np.random.default_rng(5)
    Wc = rng.normal(size=(M, 6, 3))
    wT = rng.normal(size=M)

    def J_and_grads(q: np.ndarray, T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        m = Minco(M)
        m.set_conditions(base.head, base.tail)
        m.set_parameters(q, T)
        e, gce, gTe = m.energy()
        c = m.coeffs
        val = e + np.sum(Wc * c) + 0.1 * np.sum(c**2) + np.sum(wT * T**2)
        gc = gce + Wc + 0.2 * c
        gT = gTe + 2 * wT * T
        gq, gTt = m.propagate(gc, gT)
        return val, gq, gTt

    q0, T0 = base.q.copy(), base.T.copy()
    _, gq, gT = J_and_grads(q0, T0)
    num_q = _central_diff(lambda q: J_and_grads(q, T0)[0], q0)
    num_T = _central_diff(lambda T: J_and_grads(q0, T)[0], T0)
    np.testing.assert_allclose(gq, num_q, rtol=1e-5, atol=1e-5 * np.abs(num_q).max())
    np.testing.assert_allclose(gT, num_T, rtol=1e-5, atol=1e-5 * np.abs(num_T).max())


def test_invalid_parameters_are_rejected() -> None:
    m = Minco(2)
    with pytest.raises(ValueError):
        m.set_parameters(np.zeros((1, 3)), np.array([1.0, 0.0]))
    with pytest.raises(ValueError):
        Minco(0)


def test_the_closed_form_stop_is_the_one_piece_minco() -> None:
    """``Trajectory.to_rest`` (the braking stops of the planner and the monitor) gives the
    coefficients of ``Minco(1)`` with the same two end states, to rounding."""
    rng = np.random.default_rng(7)
    for _ in range(50):
        p, v, a, end = rng.normal(0.0, 2.0, (4, 3))
        T = float(rng.uniform(0.2, 4.0))
        m = Minco(1)
        m.set_conditions(np.stack([p, v, a]), np.stack([end, np.zeros(3), np.zeros(3)]))
        m.set_parameters(np.zeros((0, 3)), np.array([T]))
        tr = Trajectory.to_rest(3.0, p, v, a, end, T)
        np.testing.assert_allclose(tr.coeffs, m.coeffs, rtol=1e-9, atol=1e-9)
        pe, ve, ae = tr.state(3.0 + T)
        np.testing.assert_allclose(pe, end, atol=1e-9)
        np.testing.assert_allclose(np.concatenate([ve, ae]), 0.0, atol=1e-9)
    with pytest.raises(ValueError):
        Trajectory.to_rest(0.0, p, v, a, end, 0.0)
    with pytest.raises(ValueError):
        Trajectory.to_rest(0.0, p, v * np.nan, a, end, 1.0)


def test_the_take_off_climb_rises_from_rest_to_rest_at_about_the_speed() -> None:
    """The flight service's take-off climb (``climb_trajectory``, the closed-form piece): from
    rest at the start to rest ``height_m`` above it, straight up, its peak speed the one asked
    for (at least 1 s: a short hop does not jump)."""
    from onboard.service.ports import climb_trajectory

    start = np.array([1.0, -2.0, 0.05])
    tr = climb_trajectory(4.0, start, 1.5, 0.5)
    assert tr.t0_s == 4.0 and tr.n_pieces == 1
    np.testing.assert_allclose(tr.state(4.0)[0], start, atol=1e-12)
    p, v, a = tr.state(tr.t_end_s)
    np.testing.assert_allclose(p, start + [0.0, 0.0, 1.5], atol=1e-9)
    np.testing.assert_allclose(np.concatenate([v, a]), 0.0, atol=1e-9)
    ts = np.linspace(tr.t0_s, tr.t_end_s, 201)
    np.testing.assert_allclose(tr.sample(ts)[:, :2] - start[:2], 0.0, atol=1e-12)
    assert np.linalg.norm(tr.sample(ts, 1), axis=1).max() == pytest.approx(0.5, rel=1e-3)
    assert climb_trajectory(0.0, start, 0.1, 0.5).duration_s == 1.0


def test_a_trajectory_cut_short_is_the_same_up_to_the_cut() -> None:
    """``Trajectory.until`` (the planner's check of a way over its first seconds): the same
    states up to the cut, which becomes its end, on a cut inside a piece and on a boundary."""
    rng = np.random.default_rng(11)
    m = Minco(4)
    m.set_conditions(rng.normal(0.0, 1.0, (3, 3)), rng.normal(0.0, 1.0, (3, 3)))
    m.set_parameters(rng.normal(0.0, 2.0, (3, 3)), np.array([0.7, 1.1, 0.4, 0.9]))
    tr = Trajectory(5.0, m.coeffs, np.array([0.7, 1.1, 0.4, 0.9]))
    for cut in (0.3, 0.7, 1.2, 1.8, 2.5, 3.09):
        part = tr.until(5.0 + cut)
        assert part.t0_s == tr.t0_s
        assert part.t_end_s == pytest.approx(5.0 + cut, abs=1e-12)
        ts = np.linspace(5.0, 5.0 + cut, 57)
        for order in range(4):
            np.testing.assert_allclose(part.sample(ts, order), tr.sample(ts, order), atol=1e-9)
    assert tr.until(5.0 + 3.2) is tr and tr.until(100.0) is tr
    with pytest.raises(ValueError):
        tr.until(5.0)


def _turn(t0: float = 10.0) -> Trajectory:
    """Three pieces turning from +x to +y at about 0.5 m/s."""
    m = Minco(3)
    z = np.zeros(3)
    m.set_conditions(
        np.stack([np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), z]),
        np.stack([np.array([2.0, 2.0, 1.0]), np.array([0.0, 0.5, 0.0]), z]),
    )
    T = np.array([2.5, 2.5, 2.5])
    m.set_parameters(np.array([[1.2, 0.2, 1.0], [1.8, 0.8, 1.0]]), T)
    return Trajectory(t0, m.coeffs, T)


@pytest.mark.parametrize("t", [10.0, 11.3, 12.5, 14.9])
def test_a_stop_along_a_path_keeps_to_it_and_ends_at_rest(t: float) -> None:
    """``Trajectory.stop_along`` (the flight service's hold): it starts in the trajectory's
    state, ends at rest where the trajectory is half the stop's duration later (as far as a
    straight braking stop of that duration goes), stays on the path in between, decelerates
    no harder than the straight stop's peak plus the turn's own, and is None when the path
    ends first."""
    from onboard.planner.trajectory import braking_duration_s

    tr = _turn()
    p, v, a = tr.state(t)
    tb = braking_duration_s(float(np.linalg.norm(v)), 3.0)
    st = tr.stop_along(t, tb)
    assert st is not None and st.t0_s == t and st.duration_s == pytest.approx(tb)
    for got, want in zip(st.state(t), (p, v, a), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-9)
    end, v_end, a_end = st.state(t + tb)
    np.testing.assert_allclose(end, tr.sample(t + 0.5 * tb), atol=1e-9)
    np.testing.assert_allclose(v_end, 0.0, atol=1e-9)
    np.testing.assert_allclose(a_end, 0.0, atol=1e-9)
    # on the path: every point of the stop within 0.1 mm of the path it replays
    path = tr.sample(np.linspace(t, t + 0.5 * tb, 4001))
    stop = st.sample(np.linspace(t, t + tb, 101))
    off = np.min(np.linalg.norm(path[None, :, :] - stop[:, None, :], axis=2), axis=1)
    assert off.max() < 1e-4
    # the straight stop goes as far, but off the path in a turn
    straight = Trajectory.braking(t, p, v, a, 3.0)
    far = np.linalg.norm(straight.sample(t + tb) - p)
    assert np.linalg.norm(end - p) == pytest.approx(far, rel=0.05)
    acc = np.linalg.norm(st.sample(np.linspace(t, t + tb, 101), 2), axis=1)
    assert acc.max() <= 1.5 * np.linalg.norm(v) / tb + np.linalg.norm(a) + 0.2
    assert tr.stop_along(tr.t_end_s - 0.1, 0.5) is None
    with pytest.raises(ValueError):
        tr.stop_along(t, 0.0)
