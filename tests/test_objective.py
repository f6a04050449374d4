"""Central-difference checks of every cost term (in c, T), of the whole objective (in x = q, tau),
and of the global-time gradient through earlier pieces (peers' motion included)."""

from collections.abc import Callable

import numpy as np
import pytest

from onboard.planner import objective as obj
from onboard.planner.field import AnalyticField
from onboard.planner.formation import complete_mask, normalized_adjacency
from onboard.planner.kernels import peer_speed_bounds
from onboard.planner.minco import BAND_COLS, Minco, solve_coeffs
from onboard.planner.timemap import T_from_tau, tau_from_T
from onboard.world import World

RTOL = 1e-5


def _peer(rng: np.random.Generator, offset: np.ndarray, n_pieces: int) -> Minco:
    m = Minco(n_pieces)
    head = np.stack([offset, [0.4, 0.05, 0.0], [0.0, 0.0, 0.0]])
    tail = np.stack([offset + [4.0, 0.3, 0.1], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    m.set_conditions(head, tail)
    q = np.linspace(head[0], tail[0], n_pieces + 1)[1:-1] + rng.normal(
        scale=0.1, size=(n_pieces - 1, 3)
    )
    m.set_parameters(q, rng.uniform(1.5, 2.5, n_pieces))
    return m


def _pack(peers: list[Minco], K: int) -> tuple[np.ndarray, np.ndarray]:
    """The peers padded to K pieces as the planner packs them (hovers at the end point)."""
    pc = np.zeros((len(peers), K, 6, 3))
    pT = np.ones((len(peers), K))
    for k, p in enumerate(peers):
        pc[k, : p.M] = p.coeffs
        pT[k, : p.M] = p.T
        pc[k, p.M :, 0] = p.tail[0]
    return pc, pT


def _setup(seed: int, weights: dict[str, float], mode: str = "cubic", stride: int = 1,  # type: ignore[no-untyped-def]
           front: float = 0.0):  # fmt: skip
    rng = np.random.default_rng(seed)
    M = 4
    head = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 0.0], [0.0, 0.1, 0.0]])
    tail = np.array([[5.0, 0.5, 1.2], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    q = np.linspace(head[0], tail[0], M + 1)[1:-1] + rng.normal(scale=0.2, size=(M - 1, 3))
    T = rng.uniform(1.0, 2.0, M)
    # peers close enough for J_r to be active, with their own start times and piece counts
    peers = [
        _peer(rng, np.array([0.2, 0.5, 1.1]), 3),
        _peer(rng, np.array([-0.3, -0.4, 0.9]), 2),
        _peer(rng, np.array([0.5, 1.5, 1.0]), 4),
    ]
    pc, pT = _pack(peers, max(p.M for p in peers))
    pt0 = np.array([-0.4, 0.3, 0.0])
    formation = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 2.0, 0.0]])
    mask = complete_mask(4)
    sdes = normalized_adjacency(formation, mask)
    prm = np.zeros(obj.N_PRM)
    prm[obj.P_D_OBS] = 0.9
    prm[obj.P_D_SWARM] = 0.9
    prm[obj.P_Z_SCALE] = 0.5
    prm[obj.P_V_MAX] = 0.5
    prm[obj.P_A_MAX] = 0.3
    prm[obj.P_J_MAX] = 0.4
    # the limits themselves, a little above the soft ones (J_d's steep part)
    prm[obj.P_V_HARD] = 0.52
    prm[obj.P_A_HARD] = 0.31
    prm[obj.P_J_HARD] = 0.41
    prm[obj.P_FORM_MODE] = obj.FORM_MODES[mode]
    prm[obj.P_TAU_SCALE] = 1.0
    prm[obj.P_FORM_STRIDE] = stride
    prm[obj.P_FORM_FRONT] = front  # J_f heavier near the start, decaying over 1.5 s
    prm[obj.P_FORM_FRONT_S] = 1.5
    # a band narrower than the trajectory's climb from 1.0 to 1.2 m: J_z active on both sides
    prm[obj.P_Z_LO] = 1.05
    prm[obj.P_Z_HI] = 1.12
    prm[obj.P_Z_HOLD] = 1.3  # above the whole climb (1.0 -> 1.2): the hold pulls every point up
    prm[obj.P_HOLD_KNEE] = 0.2  # quadratic near the end of the climb, linear before
    for key, idx in (
        ("time", obj.P_W_TIME),
        ("obstacle", obj.P_W_OBS),
        ("swarm", obj.P_W_SWARM),
        ("feasibility", obj.P_W_FEAS),
        ("feasibility-hard", obj.P_W_HARD),
        ("uniformity", obj.P_W_UNIF),
        ("formation", obj.P_W_FORM),
        ("altitude", obj.P_W_ALT),
        ("altitude-hold", obj.P_W_HOLD),
        ("pace", obj.P_W_PACE),
    ):
        prm[idx] = weights.get(key, 0.0)
    prm[obj.P_T_CAP] = 4.0  # under the durations drawn below (4 pieces of 1-2 s): the floor acts
    prm.setflags(write=False)  # as the planner's (numba compiles a writable one anew)
    prob = (head, tail, 5, prm, pc, pT, pt0, sdes, mask, formation, peer_speed_bounds(pc, pT))
    world = World(
        cylinders=np.array([[1.5, 0.6, 0.3, 0.0, 3.0], [3.2, -0.2, 0.25, 0.0, 3.0]]),
        rings=np.array([[4.2, 0.4, 1.3, 0.3, 0.7, 0.5, 0.05]]),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    fld = obj.field_args(AnalyticField(world).kernel_data())
    return M, head, tail, q, T, prob, fld


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


def _num_grad(fun: Callable[[np.ndarray], float], x: np.ndarray, h: float) -> np.ndarray:
    g = np.zeros_like(x)
    for k in range(x.size):
        e = np.zeros_like(x)
        e.flat[k] = h
        g.flat[k] = (fun(x + e) - fun(x - e)) / (2 * h)
    return g


TERMS = {
    "energy+time": {"time": 3.0},
    "obstacle": {"obstacle": 50.0},
    "swarm": {"swarm": 50.0},
    "feasibility": {"feasibility": 20.0},
    "feasibility-hard": {"feasibility": 20.0, "feasibility-hard": 2e3},
    "uniformity": {"uniformity": 30.0},
    "formation": {"formation": 1e3},
    "altitude": {"altitude": 1e4},
    "altitude-hold": {"altitude-hold": 50.0},
    "pace": {"time": 3.0, "pace": 50.0},
}


@pytest.mark.parametrize("term", list(TERMS))
def test_cost_term_gradient_in_c_and_T(term: str) -> None:
    M, head, tail, q, T, prob, fld = _setup(11, TERMS[term])
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    c0 = m.c.copy()
    costs = np.zeros(obj.N_TERMS)

    def f_c(c: np.ndarray) -> float:
        return obj.cost_c_T(c, T, prob, fld, np.zeros_like(c), np.zeros(M), costs)

    def f_T(TT: np.ndarray) -> float:
        return obj.cost_c_T(c0, TT, prob, fld, np.zeros_like(c0), np.zeros(M), costs)

    gc = np.zeros_like(c0)
    gT = np.zeros(M)
    obj.cost_c_T(c0, T, prob, fld, gc, gT, costs)
    if term == "pace":
        # the pace floor is part of J_t: beyond w_t sum(T) by the squared excess over the cap
        over = float(np.sum(T)) - 4.0
        assert over > 0.0
        assert costs[obj.C_T] == pytest.approx(3.0 * np.sum(T) + 50.0 * over * over)
    elif term != "energy+time":
        # J_z holds the altitude band and the hold; J_d both parts of the limits
        name = {"altitude-hold": "altitude", "feasibility-hard": "feasibility"}.get(term, term)
        assert costs[obj.TERM_NAMES.index(name)] > 0.0, f"{term} not active in the test setup"
    if term == "feasibility-hard":
        soft = _setup(11, TERMS["feasibility"])[5]
        costs_soft = np.zeros(obj.N_TERMS)
        obj.cost_c_T(c0, T, soft, fld, np.zeros_like(c0), np.zeros(M), costs_soft)
        assert costs[obj.C_D] > 2.0 * costs_soft[obj.C_D], "the steep part is not active"
    assert _rel_err(gc, _num_grad(f_c, c0, 1e-6)) <= RTOL
    assert _rel_err(gT, _num_grad(f_T, T, 1e-6)) <= RTOL


@pytest.mark.parametrize(
    ("mode", "stride", "front"),
    [("linear", 1, 0.0), ("linear", 5, 0.0), ("cubic", 5, 0.0), ("relative", 1, 0.0),
     ("relative", 5, 0.0), ("linear", 1, 4.0), ("linear", 5, 4.0), ("cubic", 5, 4.0)],
)  # fmt: skip
def test_formation_variant_gradient(mode: str, stride: int, front: float) -> None:
    """Each form of J_f, also weighted heavier near the plan's start (``front``: the weight's
    decay with the sample's time enters the time gradient)."""
    M, head, tail, q, T, prob, fld = _setup(
        12, {"formation": 10.0}, mode=mode, stride=stride, front=front
    )
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    c0 = m.c.copy()
    costs = np.zeros(obj.N_TERMS)
    gc = np.zeros_like(c0)
    gT = np.zeros(M)
    obj.cost_c_T(c0, T, prob, fld, gc, gT, costs)
    assert costs[obj.C_F] > 0.0
    num_c = _num_grad(
        lambda cc: obj.cost_c_T(cc, T, prob, fld, np.zeros_like(c0), np.zeros(M), costs), c0, 1e-6
    )
    assert _rel_err(gc, num_c) <= RTOL
    num_T = _num_grad(
        lambda TT: obj.cost_c_T(c0, TT, prob, fld, np.zeros_like(c0), np.zeros(M), costs), T, 1e-6
    )
    assert _rel_err(gT, num_T) <= RTOL


def test_the_front_weight_scales_the_formation_cost_by_its_decay() -> None:
    """``P_FORM_FRONT`` g with time constant tau: each sample's J_f times 1 + g exp(-t / tau);
    the total lies between the uniform cost and 1 + g times it, and nearer the top for a
    slower decay."""
    M, head, tail, q, T, prob, fld = _setup(12, {"formation": 10.0}, mode="linear")
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)

    def j_f(front: float, tau: float) -> float:
        prm = prob[3].copy()
        prm[obj.P_FORM_FRONT] = front
        prm[obj.P_FORM_FRONT_S] = tau
        prm.setflags(write=False)
        costs = np.zeros(obj.N_TERMS)
        p2 = (*prob[:3], prm, *prob[4:])
        obj.cost_c_T(m.c, T, p2, fld, np.zeros_like(m.c), np.zeros(M), costs)
        return float(costs[obj.C_F])

    base = j_f(0.0, 1.5)
    fast, slow = j_f(4.0, 0.5), j_f(4.0, 50.0)
    assert base < fast < slow < 5.0 * base
    assert slow > 4.5 * base  # over 4-8 s of plan a 50 s decay is nearly flat
    assert j_f(4.0, 0.0) == base  # no time constant: off


def test_time_gradient_includes_peer_motion() -> None:
    """With the formation term on, dJ/dT_0 must move when the peers' velocity is ignored."""
    M, head, tail, q, T, prob, fld = _setup(13, {"formation": 1e3})
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    gT = np.zeros(M)
    costs = np.zeros(obj.N_TERMS)
    obj.cost_c_T(m.c, T, prob, fld, np.zeros_like(m.c), gT, costs)
    still = list(prob)
    pc = prob[4].copy()
    pc[:, :, 1:] = 0.0  # frozen peers
    still[4] = pc
    gT_still = np.zeros(M)
    obj.cost_c_T(m.c, T, tuple(still), fld, np.zeros_like(m.c), gT_still, costs)
    assert np.abs(gT[0] - gT_still[0]) > 1e-6 * np.abs(gT).max()


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_whole_objective_gradient_in_q_and_tau(seed: int) -> None:
    weights = {
        "time": 5.0,
        "obstacle": 50.0,
        "swarm": 50.0,
        "feasibility": 20.0,
        "uniformity": 30.0,
        "formation": 1e3,
        "altitude": 1e4,
        "altitude-hold": 50.0,
    }
    M, head, tail, q, T, prob, fld = _setup(seed, weights)
    x = np.concatenate([q.ravel(), tau_from_T(T)])
    work = obj.workspace(M)
    g = np.empty_like(x)
    obj.objective(x, prob, fld, work, g)

    def f(xx: np.ndarray) -> float:
        return obj.objective(xx, prob, fld, work, np.empty_like(xx))

    assert _rel_err(g, _num_grad(f, x, 1e-6)) <= RTOL


def test_absurd_durations_give_an_infinite_cost_not_an_error() -> None:
    """A line search's trial point may take a duration's tau anywhere. At a duration whose
    powers underflow, MINCO's matrix had a zero pivot and the compiled objective raised
    ZeroDivisionError out of the planner (``bench hidden`` seed 183, 2026-12-01); now such a
    point costs +inf with a zero gradient (the line search shrinks its step), as does one
    whose durations overflow."""
    M, head, tail, q, T, prob, fld = _setup(21, {"time": 5.0, "feasibility": 20.0})
    work = obj.workspace(M)
    sc = prob[3][obj.P_TAU_SCALE]
    x = np.concatenate([q.ravel(), tau_from_T(T) / sc])
    g = np.empty_like(x)
    assert np.isfinite(obj.objective(x, prob, fld, work, g))
    for tau in (-1e200, -1e30, 1e30, np.nan):
        bad = x.copy()
        bad[-1] = tau / sc
        g[:] = 1.0
        assert obj.objective(bad, prob, fld, work, g) == np.inf
        assert np.all(g == 0.0)


# a trial point of a line search (``bench hidden`` seed 30 with the pace floor at w_pace 1e4,
# 2026-12-01): waypoints km away and durations of 6e7 s and 2e-9 s side by side, each inside
# T_SANE's bounds, whose MINCO system has a zero pivot
SINGULAR_X = np.array([1.06335037e03, 6.78311137e01, 1.0, -2.18777799e04, 8.73786538e02, 1.0,
                       1.28084811e04, -1.20313913e04, 1.0,
                       1.10929139e04, -2.98557259e04, 3.05662088e04, -2.11663688e04])  # fmt: skip


def test_a_singular_minco_system_gives_an_infinite_cost_not_an_error() -> None:
    """Durations of absurd ratios inside the sanity bounds cancel a pivot of MINCO's band LU
    to zero: the compiled solve raised ZeroDivisionError out of the planner. Now the objective
    returns +inf with a zero gradient there, ``solve_coeffs`` says so (its coefficients NaN,
    which ``kernels.trajectory_from_x`` reads as not finite) and ``Minco`` refuses them."""
    T = T_from_tau(SINGULAR_X[9:])
    assert np.all((T >= obj.T_SANE_MIN_S) & (T <= obj.T_SANE_MAX_S))
    head = np.array([[5.1, 0.1, 1.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    tail = np.array([[11.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    q = SINGULAR_X[:9].reshape(3, 3).copy()
    band = np.zeros((24, BAND_COLS))
    c = np.zeros((24, 3))
    assert not solve_coeffs(head, tail, q, T, band, c)
    assert np.all(np.isnan(c))
    _, _, _, _, _, prob, fld = _setup(21, {"time": 5.0, "feasibility": 20.0})
    prob = (head, tail, *prob[2:])
    g = np.ones(SINGULAR_X.shape[0])
    assert obj.objective(SINGULAR_X.copy(), prob, fld, obj.workspace(4), g) == np.inf
    assert np.all(g == 0.0)
    m = Minco(4)
    m.set_conditions(head, tail)
    m.set_parameters(q, np.ones(4))
    before = m.c.copy()
    with pytest.raises(ValueError, match="singular"):
        m.set_parameters(q, T)
    np.testing.assert_array_equal(m.c, before)  # the state before the refusal stands
    np.testing.assert_array_equal(m.T, np.ones(4))
    # ordinary durations still solve
    assert solve_coeffs(head, tail, q, np.array([1.0, 2.0, 1.5, 0.8]), band, c)
    assert np.all(np.isfinite(c))


def test_unit_gradient_variant_does_not_match_its_cost() -> None:
    """The public code's variant, kept for comparison: its gradient is not the cost's."""
    M, head, tail, q, T, prob, fld = _setup(12, {"formation": 10.0}, mode="linear-unit")
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    c0 = m.c.copy()
    costs = np.zeros(obj.N_TERMS)
    gc = np.zeros_like(c0)
    obj.cost_c_T(c0, T, prob, fld, gc, np.zeros(M), costs)
    num_c = _num_grad(
        lambda cc: obj.cost_c_T(cc, T, prob, fld, np.zeros_like(c0), np.zeros(M), costs), c0, 1e-6
    )
    assert _rel_err(gc, num_c) > 1e-2


def test_altitude_term_is_active_below_and_above_the_band() -> None:
    """The gradient check of J_z above covers both sides: the set-up's trajectory leaves the
    band downwards and upwards, and each side alone gives a positive cost."""
    M, head, tail, q, T, prob, fld = _setup(11, {"altitude": 1e4})
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    costs = np.zeros(obj.N_TERMS)
    for lo, hi in ((1.05, 50.0), (-50.0, 1.12)):
        prm = prob[3].copy()
        prm[obj.P_Z_LO], prm[obj.P_Z_HI] = lo, hi
        prm.setflags(write=False)
        one_side = (*prob[:3], prm, *prob[4:])
        obj.cost_c_T(m.c, T, one_side, fld, np.zeros_like(m.c), np.zeros(M), costs)
        assert costs[obj.C_Z] > 0.0, (lo, hi)
    prm = prob[3].copy()
    prm[obj.P_Z_LO], prm[obj.P_Z_HI] = -50.0, 50.0
    prm.setflags(write=False)
    inside = (*prob[:3], prm, *prob[4:])
    obj.cost_c_T(m.c, T, inside, fld, np.zeros_like(m.c), np.zeros(M), costs)
    assert costs[obj.C_Z] == 0.0


def test_peer_speed_bounds_bound_the_sampled_speeds() -> None:
    rng = np.random.default_rng(5)
    peers = [_peer(rng, rng.normal(size=3), n) for n in (2, 3, 5)]
    pc, pT = _pack(peers, 6)  # padded: hovers at the end point, which stand still
    vb = peer_speed_bounds(pc, pT)
    for k, p in enumerate(peers):
        top = 0.0
        for i in range(p.M):
            t = np.linspace(0.0, p.T[i], 400)
            c = p.coeffs[i]
            v = sum(m * np.outer(t ** (m - 1), c[m]) for m in range(1, 6))
            top = max(top, float(np.max(np.linalg.norm(v, axis=1))))
        assert top <= vb[k] < 10.0 * top  # a bound, and not a useless one
    assert np.array_equal(peer_speed_bounds(pc[:, 5:], pT[:, 5:]), np.zeros(3))  # hovers


@pytest.mark.parametrize("seed", [31, 32, 33, 34])
@pytest.mark.parametrize("stride", [0, 1, 2])
def test_peers_skipped_where_no_term_reads_them_change_nothing(seed: int, stride: int) -> None:
    """The objective leaves a peer's position unevaluated at a point where J_f does not read it
    and J_r cannot reach it (from the peer's speed bound): with an infinite bound, every peer
    is evaluated everywhere, as before; costs and gradients must be the same to the bit, with
    J_r active near the peers."""
    # stride 0: no formation term, so that J_r alone decides at every point
    weights = {"swarm": 1e3, "formation": 10.0 if stride else 0.0, "obstacle": 1.0}
    M, head, tail, q, T, prob, fld = _setup(seed, weights, "linear", max(stride, 1))
    assert np.all(prob[10] > 0.0) and np.all(np.isfinite(prob[10]))
    every = (*prob[:10], np.full_like(prob[10], np.inf))
    m = Minco(M)
    m.set_conditions(head, tail)
    m.set_parameters(q, T)
    got = []
    for pr in (prob, every):
        costs = np.zeros(obj.N_TERMS)
        gc = np.zeros_like(m.c)
        gT = np.zeros(M)
        f = obj.cost_c_T(m.c.copy(), T, pr, fld, gc, gT, costs)
        got.append((f, gc, gT, costs))
    assert got[0][3][obj.C_R] > 0.0  # J_r active: peers within reach somewhere
    assert got[0][0] == got[1][0]
    for a, b in zip(got[0][1:], got[1][1:], strict=True):
        assert a.tobytes() == b.tobytes()
