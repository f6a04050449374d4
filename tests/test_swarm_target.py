"""Swarm-consistent local target (``PlannerParams.swarm_target``, issue #11): the local target is
the formation's reference origin advanced along the shared path plus the drone's slot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gcs.fastsim import SimConfig, run_sim
from onboard.agent import DroneAgent, StaticMap
from onboard.comm import InMemoryBus
from onboard.config import (
    load_formation,
    load_planner_params,
    load_world_spec,
    parse_override,
)
from onboard.planner import objective as obj
from onboard.planner.field import AnalyticField
from onboard.planner.formation import similarity
from onboard.planner.params import PlannerParams, recover_params, reform_params
from onboard.planner.planner import FormationPlanner, PeerTrajectory, PlanStatus, _pack_peers
from onboard.planner.trajectory import Trajectory
from onboard.world import World

# a line across y, flying +x; slot 1 in the middle
LINE3 = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
ZERO = np.zeros(3)
EMPTY = AnalyticField(World.empty(0.0))
GOAL_ORIGIN = np.array([40.0, 0.0, 1.0])


def _peer(slot: int, p: list[float]) -> PeerTrajectory:
    return PeerTrajectory(slot, slot, Trajectory.hover(np.array(p), 0.0, 30.0))


def _target(mode: str, sp: np.ndarray, peers: list[PeerTrajectory], slot: int = 1) -> np.ndarray:
    """The local target of one replan of the drone in ``slot`` (its goal: the goal origin plus
    its slot)."""
    planner = FormationPlanner(PlannerParams(swarm_target=mode), LINE3, slot=slot)
    goal = GOAL_ORIGIN + LINE3[slot]
    problem = planner.prepare(0.0, sp, ZERO, ZERO, goal, peers, EMPTY)
    return np.asarray(problem.tail[0])


def test_the_option_is_validated_and_settable_like_every_planner_limit() -> None:
    assert PlannerParams().swarm_target == "centroid"  # the default since it was measured
    with pytest.raises(ValueError, match="swarm_target"):
        PlannerParams(swarm_target="nearest")
    assert load_planner_params(**parse_override("swarm_target=centroid")).swarm_target == (
        "centroid"
    )


def test_a_drone_off_its_slot_is_pulled_back_to_it() -> None:
    """The middle drone went round a trunk on the wrong side: 1 m to the left of its slot (its
    peers in theirs). 'own-goal' aims along its own line to the goal, keeping most of that 1 m; the
    swarm target aims at its slot, horizon_m ahead of the formation's origin."""
    h = PlannerParams().horizon_m
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [0.0, 1.5, 1.0])]
    sp = np.array([0.0, 1.0, 1.0])
    off = _target("own-goal", sp, peers)
    on = _target("centroid", sp, peers)
    assert off[1] > 0.7  # 1 m * (1 - 7.5 / 40) from its own line
    # the origin estimate (mean of p_j - F_j) is 1/3 m to the left; the target is its slot there
    np.testing.assert_allclose(on, [h * np.cos(np.arctan2(-1 / 3, 40)), 1 / 3 * (1 - h / 40), 1.0],
                               atol=1e-3)  # fmt: skip
    assert abs(on[1]) < abs(off[1]) / 2


def test_in_formation_the_targets_are_the_straight_line_ones_and_stay_a_formation() -> None:
    """Every drone in its slot (any subset of them: drones that dropped out of the formation
    change nothing): the swarm target is the one of 'own-goal', and the three targets are the
    formation translated."""
    x0 = 3.0
    pos = {s: np.array([x0, 0.0, 1.0]) + LINE3[s] for s in range(3)}
    targets = []
    for s in range(3):
        peers = [_peer(q, pos[q].tolist()) for q in range(3) if q != s]
        on = _target("centroid", pos[s], peers, slot=s)
        np.testing.assert_allclose(on, _target("own-goal", pos[s], peers, slot=s), atol=1e-9)
        np.testing.assert_allclose(_target("slowest", pos[s], peers, slot=s), on, atol=1e-9)
        targets.append(on)
    np.testing.assert_allclose(np.asarray(targets) - targets[1], LINE3, atol=1e-9)
    # one peer gone (dropped out): the same target from the remaining one
    on = _target("centroid", pos[1], [_peer(2, pos[2].tolist())])
    np.testing.assert_allclose(on, targets[1], atol=1e-9)


def test_slowest_waits_for_the_member_behind() -> None:
    """Peer 0 lags 3 m: 'centroid' moves the reference back by 1 m, 'slowest' by 3 m, so the
    target of the drone ahead comes that much closer; with ``lead_slowdown_m`` its lead is
    measured from that reference."""
    sp = np.array([3.0, 0.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [3.0, 1.5, 1.0])]
    off = _target("own-goal", sp, peers)
    cen = _target("centroid", sp, peers)
    slow = _target("slowest", sp, peers)
    h = PlannerParams().horizon_m
    assert off[0] == pytest.approx(sp[0] + h, abs=1e-6)
    assert cen[0] == pytest.approx(sp[0] + h - 1.0, abs=0.01)
    assert slow[0] == pytest.approx(sp[0] + h - 3.0, abs=0.01)
    # at the template's yaw (a line of three that lags at one end also reads as turned)
    params = PlannerParams(swarm_target="slowest", lead_slowdown_m=6.0, lead_turned=False)
    planner = FormationPlanner(params, LINE3, slot=1)
    goal = GOAL_ORIGIN + LINE3[1]
    _, _, lead = planner._swarm_setup(0.0, sp, goal, peers, _pack_peers(peers), True)
    assert lead == pytest.approx(3.0, abs=1e-3)


def test_near_the_goal_the_target_is_the_own_goal_and_a_far_leader_still_moves() -> None:
    peers = [_peer(0, [36.0, -1.5, 1.0]), _peer(2, [36.0, 1.5, 1.0])]
    sp = np.array([35.0, 0.0, 1.0])
    np.testing.assert_allclose(_target("centroid", sp, peers), GOAL_ORIGIN, atol=1e-12)
    # 12 m ahead of the slowest member: the reference's target lies behind it; it still aims
    # ahead, at least SWARM_TARGET_MIN_M away
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [0.0, 1.5, 1.0])]
    sp = np.array([12.0, 0.0, 1.0])
    t = _target("slowest", sp, peers)
    assert t[0] > sp[0] + 0.99


def test_the_target_avoids_a_trunk_on_it() -> None:
    """A trunk right on the swarm target: the target moves along the line to a clear point."""
    sp = np.array([0.0, 1.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [0.0, 1.5, 1.0])]
    on = _target("centroid", sp, peers)
    world = World(
        cylinders=np.array([[on[0], on[1], 0.4, 0.0, 3.0]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    field = AnalyticField(world)
    planner = FormationPlanner(PlannerParams(swarm_target="centroid"), LINE3, slot=1)
    problem = planner.prepare(0.0, sp, ZERO, ZERO, GOAL_ORIGIN + LINE3[1], peers, field)
    moved = np.asarray(problem.tail[0])
    assert float(field.distance(moved[None, :])[0][0]) >= PlannerParams().obstacle_clearance_m
    res = planner.plan(0.0, sp, ZERO, ZERO, GOAL_ORIGIN + LINE3[1], peers, field)
    assert res.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION)
    tr = res.trajectory
    pts = tr.sample(np.linspace(tr.t0_s, tr.t_end_s, 400))
    assert float(field.distance(pts)[0].min()) >= PlannerParams().check_obstacle_m


def _fly(
    agents: list[DroneAgent], t0: float, t_end: float, dt: float = 0.05
) -> tuple[np.ndarray, float]:
    """Perfect tracking of every agent's trajectory from t0 until t_end: (positions (K, N, 3),
    the smallest distance between two drones)."""
    track = []
    closest = np.inf
    for k in range(int(round((t_end - t0) / dt)) + 1):
        t = t0 + k * dt
        for ag in agents:
            if ag.due(t):
                ag.replan(t)
        p = np.array([ag.advance(t).sample(t) for ag in agents])
        d = np.linalg.norm(p[:, None] - p[None, :], axis=2)
        closest = min(closest, float(d[~np.eye(len(agents), dtype=bool)].min()))
        track.append(p)
    return np.asarray(track), closest


def test_agents_change_formation_mid_flight_and_lose_a_drone() -> None:
    """Three agents with the swarm target fly a line, switch to a triangle mid-flight (new
    template, slots, goals) and arrive in it; then one drops out (its peers told to ignore it)
    and the other two fly on in their slots of the template."""
    params = PlannerParams(v_max_m_s=1.0, swarm_target="centroid")
    assert params.lead_slowdown_m > 0.0 and params.lead_from_slowest
    bus = InMemoryBus(0.02)
    empty = StaticMap(EMPTY)
    start = np.array([0.0, 0.0, 1.0])
    agents = [
        DroneAgent(
            i,
            params,
            LINE3,
            i,
            Trajectory.hover(start + LINE3[i], 0.0),
            bus,
            empty,
            goal=np.array([30.0, 0.0, 1.0]) + LINE3[i],
            first_replan_s=i / 3,  # staggered, as the simulator and the swarm do
        )
        for i in range(3)
    ]
    for ag in agents:
        ag.announce(0.0)
    track, closest = _fly(agents, 0.0, 6.0)
    assert all(ag.last is not None and not ag.last.reforming for ag in agents)
    tri = np.array([[1.0, 0.0, 0.0], [-0.5, 1.3, 0.0], [-0.5, -1.3, 0.0]])
    goal_origin = np.array([14.0, 0.0, 1.0])
    for i, ag in enumerate(agents):
        ag.set_formation(tri, i, goal=goal_origin + tri[i])
    # the drone whose new slot is the front is the slowest member: with the lead slow-down
    # (the default) the others waited for it while their paths crossed (the triangle reached
    # after ~35 s); re-forming measures the lead from the centroid for reform_s
    _fly(agents, 6.05, 7.0)
    assert all(ag.last is not None and ag.last.reforming for ag in agents)
    track2, closest2 = _fly(agents, 7.05, 45.0)
    assert all(ag.last is not None and not ag.last.reforming for ag in agents)
    # the triangle's shape (any yaw, any size: the metric's) within 9 s of the change (6.7 s
    # measured with replans every reform_replan_period_s = 0.25 s while re-forming)
    shaped = np.array([similarity(p, tri)[0] for p in track2]) < 0.01
    assert shaped.any() and 1.0 + 0.05 * int(np.argmax(shaped)) < 9.0
    # ... and its slots. The triangle is entered at the yaw nearest the line's and turned to
    # the goals' on the way. When it arrives is chaotic: the starts moved by 1e-7 m (25 draws,
    # 2026-12-04) gave 24.3-40.3 s, median 29.6 s, both before and after the formation
    # metric's two-pass form (41fdc73); the unmoved flight's 26.6 s passed a 28 s bound only by
    # luck, and 41fdc73's 28.7 s failed it. The bound is over the spread measured
    reached = np.all(np.linalg.norm(track2 - (goal_origin + tri), axis=2) < 0.3, axis=1)
    assert reached.any() and 7.05 + 0.05 * int(np.argmax(reached)) < 43.0
    end = track2[-1]
    np.testing.assert_allclose(end, goal_origin + tri, atol=0.3)
    assert min(closest, closest2) >= params.check_drone_m
    # drone 2 drops out (stops where it is); the others ignore it and fly on in formation
    agents[2].set_goal(None)
    for ag in agents[:2]:
        ag.set_peer_roles(ignore=[2])
        ag.set_goal(np.array([14.0, 10.0, 1.0]) + tri[ag.slot])
    track3, _ = _fly(agents[:2], 45.05, 75.0)
    np.testing.assert_allclose(track3[-1], np.array([14.0, 10.0, 1.0]) + tri[:2], atol=0.3)
    for ag in agents[:2]:
        last = ag.last
        assert last is not None and last.status in (PlanStatus.OK, PlanStatus.KEPT_PREVIOUS)


@pytest.mark.parametrize("mode", ["centroid", "slowest"])
@pytest.mark.parametrize("kind", ["killed", "stuck"])
def test_a_drone_that_stops_does_not_hold_back_or_drag_the_others(mode: str, kind: str) -> None:
    """Drone 1 of the hexagon dies (or gets stuck) 4 s into the small forest. Its last position
    enters the others' reference origin until it leaves their formation term ('slowest' holds
    the reference at it): the healthy drones still all arrive, collide with nothing and keep
    the check's distance from it."""
    params = dataclasses.replace(load_planner_params(), v_max_m_s=1.0, swarm_target=mode)
    cfg = SimConfig(
        load_formation("hexagon-7"),
        load_world_spec("forest-small"),
        seed=1,
        planner=params,
        validity_s=3.0,
        peer_forget_s=10.0,
        fault_seed=1,
        kill_model="instant",
        **{f"{kind}_drones": {1: 4.0}},  # type: ignore[arg-type]
    )
    r = run_sim(cfg)
    healthy = [0, 2, 3, 4, 5, 6]
    assert r.collisions == 0, r.events
    assert not r.timed_out and bool(np.all(r.arrived[healthy])), r.arrived
    assert r.min_obstacle_clearance_m >= params.check_obstacle_m - 0.02
    d = np.linalg.norm(r.tracks.pos[:, healthy] - r.tracks.pos[:, [1]], axis=2)
    assert float(d.min()) >= params.check_drone_m - 0.02, float(d.min())


def test_lead_deadband_and_lead_from_the_slowest_member() -> None:
    """Peer 0 lags 3 m, the drone is 2 m ahead of its slot relative to peer 2: from the
    centroid its lead is 5/3 m, from the slowest member 3 m; a dead band of 1 m leaves 2/3 m
    and 2 m of it to slow down for, so the planned speed limit drops accordingly."""
    sp = np.array([3.0, 0.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [1.0, 1.5, 1.0])]
    goal = GOAL_ORIGIN + LINE3[1]
    base = PlannerParams(
        lead_slowdown_m=4.0, lead_deadband_m=1.0, lead_min_speed_frac=0.1, lead_turned=False
    )
    for slowest, lead in ((False, 5.0 / 3.0), (True, 3.0)):
        params = dataclasses.replace(base, lead_from_slowest=slowest)
        planner = FormationPlanner(params, LINE3, slot=1)
        problem = planner.prepare(0.0, sp, ZERO, ZERO, goal, peers, EMPTY)
        v = float(problem.prob[3][obj.P_V_MAX])
        assert v == pytest.approx(
            params.v_max_m_s * params.limit_margin * (1.0 - (lead - 1.0) / 4.0), rel=1e-9
        )
    with pytest.raises(ValueError, match="lead_deadband_m"):
        PlannerParams(lead_deadband_m=-1.0)


def test_with_the_lead_from_the_centroid_a_member_far_behind_is_still_waited_for() -> None:
    """The situation above, planned while recovering the shape (the lead from the centroid,
    5/3 m): with ``lead_slowest_beyond_m`` b the lead is the larger of that and the slowest
    member's 3 m less b (0: off). Without it a drone left behind is never waited for (the swarm
    cruises near the limit), and the shape stays broken. While re-forming the lead is the
    centroid's whatever b: a new shape forming turned reads as members behind."""
    sp = np.array([3.0, 0.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [1.0, 1.5, 1.0])]
    goal = GOAL_ORIGIN + LINE3[1]
    base = PlannerParams(lead_slowdown_m=4.0, lead_deadband_m=1.0, lead_min_speed_frac=0.1)
    full = base.v_max_m_s * base.limit_margin
    for beyond, lead in ((0.5, 2.5), (1.0, 2.0), (1.5, 5.0 / 3.0), (0.0, 5.0 / 3.0)):
        b = dataclasses.replace(base, lead_slowest_beyond_m=beyond)
        for params, want in ((recover_params(b), lead), (reform_params(b), 5.0 / 3.0)):
            assert not params.lead_from_slowest
            problem = FormationPlanner(params, LINE3, slot=1).prepare(
                0.0, sp, ZERO, ZERO, goal, peers, EMPTY
            )
            v = float(problem.prob[3][obj.P_V_MAX])
            assert v == pytest.approx(full * (1.0 - (want - 1.0) / 4.0), rel=1e-9), beyond
    # from the slowest member already (plain flight), the margin changes nothing
    plain = dataclasses.replace(base, lead_slowest_beyond_m=0.5)
    problem = FormationPlanner(plain, LINE3, slot=1).prepare(
        0.0, sp, ZERO, ZERO, goal, peers, EMPTY
    )
    assert float(problem.prob[3][obj.P_V_MAX]) == pytest.approx(full * (1.0 - 2.0 / 4.0))
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="lead_slowest_beyond_m"):
            PlannerParams(lead_slowest_beyond_m=bad)
    assert (
        load_planner_params(**parse_override("lead_slowest_beyond_m=0")).lead_slowest_beyond_m == 0
    )


@pytest.mark.parametrize("yaw_deg", [30.0, -20.0])
def test_a_formation_flown_turned_is_no_drone_ahead_of_another(yaw_deg: float) -> None:
    """The line flown turned by ``yaw_deg``, every drone in its turned slot: at the template's
    own yaw the end drone ahead reads a lead of 1.5 m (at 30 deg) over the other end and is
    slowed; measured against the template turned to the swarm's yaw (``lead_turned``, an
    option) it has none, as the formation term, e_sim and e_dist see it."""
    th = np.radians(yaw_deg)
    turn = np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0, 0, 1]])
    origin = np.array([3.0, 0.0, 1.0])
    at = origin + LINE3 @ turn.T
    front = int(np.argmax(at[:, 0]))
    peers = [_peer(k, list(at[k])) for k in range(3) if k != front]
    goal = GOAL_ORIGIN + LINE3[front]
    base = PlannerParams(lead_slowdown_m=4.0, lead_deadband_m=0.5, lead_min_speed_frac=0.1)
    assert base.lead_from_slowest and not base.lead_turned  # off by default
    full = base.v_max_m_s * base.limit_margin
    for turned in (True, False):
        params = dataclasses.replace(base, lead_turned=turned)
        problem = FormationPlanner(params, LINE3, slot=front).prepare(
            0.0, at[front], ZERO, ZERO, goal, peers, EMPTY
        )
        v = float(problem.prob[3][obj.P_V_MAX])
        if turned:
            assert v == pytest.approx(full, rel=1e-9)
        else:
            lead = 3.0 * abs(np.sin(th))
            assert v == pytest.approx(full * (1.0 - (lead - 0.5) / 4.0), rel=1e-6)


def test_while_reforming_the_lead_is_measured_from_the_centroid_and_the_shape_pulls_harder() -> (
    None
):
    """The situation above, planned as a drone does for ``reform_s`` after a formation change
    (``reform_params``): the lead from the centroid (5/3 m, not the slowest member's 3 m) and
    the formation weight scaled; with ``reform_lead_from_centroid`` off, no slow-down at all."""
    sp = np.array([3.0, 0.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [1.0, 1.5, 1.0])]
    goal = GOAL_ORIGIN + LINE3[1]
    base = PlannerParams(lead_slowdown_m=4.0, lead_deadband_m=1.0, lead_min_speed_frac=0.1)
    assert base.lead_from_slowest and base.reform_lead_from_centroid
    params = reform_params(base)
    assert params.w_formation == pytest.approx(base.w_formation * base.reform_formation_scale)
    assert base.reform_formation_scale > 1.0  # the default pulls harder
    problem = FormationPlanner(params, LINE3, slot=1).prepare(
        0.0, sp, ZERO, ZERO, goal, peers, EMPTY
    )
    v = float(problem.prob[3][obj.P_V_MAX])
    lead = 5.0 / 3.0
    assert v == pytest.approx(base.v_max_m_s * base.limit_margin * (1.0 - (lead - 1.0) / 4.0))
    off = reform_params(dataclasses.replace(base, reform_lead_from_centroid=False))
    problem = FormationPlanner(off, LINE3, slot=1).prepare(0.0, sp, ZERO, ZERO, goal, peers, EMPTY)
    assert float(problem.prob[3][obj.P_V_MAX]) == pytest.approx(base.v_max_m_s * base.limit_margin)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="reform_formation_scale"):
            PlannerParams(reform_formation_scale=bad)
    assert (
        load_planner_params(**parse_override("reform_formation_scale=2")).reform_formation_scale
        == 2.0
    )


def _prm_by_mode(base: PlannerParams) -> list[np.ndarray]:
    """The cost parameters (``prob[3]``) of one problem (the middle drone of LINE3, two peers)
    planned in normal flight, while re-forming and while recovering the shape, in that order."""
    sp = np.array([3.0, 0.0, 1.0])
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [1.0, 1.5, 1.0])]
    goal = GOAL_ORIGIN + LINE3[1]
    return [
        FormationPlanner(params, LINE3, slot=1)
        .prepare(0.0, sp, ZERO, ZERO, goal, peers, EMPTY)
        .prob[3]
        for params in (base, reform_params(base), recover_params(base))
    ]


def test_the_front_weight_is_the_re_formings_alone() -> None:
    """``reform_formation_front_gain`` reaches the problem while re-forming only: normal
    flight and shape recovery (which derives from the re-forming's parameters) keep the
    uniform weight; bad values are refused."""
    base = PlannerParams()
    assert base.formation_front_gain == 0.0 and base.reform_formation_front_gain > 0.0
    gains = (0.0, base.reform_formation_front_gain, 0.0)
    for prm, gain in zip(_prm_by_mode(base), gains, strict=True):
        assert float(prm[obj.P_FORM_FRONT]) == gain
        assert float(prm[obj.P_FORM_FRONT_S]) == base.formation_front_s
    for key, bad in (("formation_front_s", 0.0), ("reform_formation_front_gain", -1.0),
                     ("formation_front_gain", float("nan"))):  # fmt: skip
        with pytest.raises(ValueError, match=key):
            PlannerParams(**{key: bad})


def test_the_obstacle_weight_is_scaled_while_re_forming_alone() -> None:
    """``reform_obstacle_scale`` reaches the problem while re-forming only: normal flight and
    shape recovery (which derives from the re-forming's parameters) keep ``w_obstacle``; a
    scale below 1 or not finite is refused."""
    base = PlannerParams(reform_obstacle_scale=7.0)
    weights = (base.w_obstacle, 7.0 * base.w_obstacle, base.w_obstacle)
    for prm, w in zip(_prm_by_mode(base), weights, strict=True):
        assert float(prm[obj.P_W_OBS]) == pytest.approx(w)
    for bad in (0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="reform_obstacle_scale"):
            PlannerParams(reform_obstacle_scale=bad)
    key = "reform_obstacle_scale=3"
    assert load_planner_params(**parse_override(key)).reform_obstacle_scale == 3.0


def _crawling_peer(
    slot: int, start: np.ndarray, goal: np.ndarray, duration_s: float
) -> PeerTrajectory:
    """A peer flying straight from ``start`` to ``goal`` at a constant crawl over ``duration_s``."""
    c = np.zeros((1, 6, 3))
    c[0, 0] = start
    c[0, 1] = (goal - start) / duration_s
    return PeerTrajectory(slot, slot, Trajectory(0.0, c, np.array([duration_s])))


@pytest.mark.parametrize("pace", [0.0, 0.5])
def test_near_the_goal_a_drone_does_not_crawl_after_peers_that_crawl(pace: float) -> None:
    """The swarm 5.5 m short of its goals, in its shape, its two peers' plans crawling there
    over 40 s: each plan that follows its peers through the formation term keeps the shape all
    the way, and the drones settle on an ever later common arrival (``bench hidden``: plans of
    34 s for 6 m, drones backing away from their goals for 10 s). With the pace floor the plan
    to the own goal is no slower than ``pace_floor_frac`` of the speed limit, plus the slack."""
    params = PlannerParams(pace_floor_frac=pace)  # 0: off (the default is 0.5)
    planner = FormationPlanner(params, LINE3, slot=1)
    x0 = GOAL_ORIGIN[0] - 5.5
    peers = [
        _crawling_peer(s, np.array([x0, LINE3[s, 1], 1.0]), GOAL_ORIGIN + LINE3[s], 40.0)
        for s in (0, 2)
    ]
    sp = np.array([x0, 0.0, 1.0])
    res = planner.plan(0.0, sp, ZERO, ZERO, GOAL_ORIGIN.copy(), peers, EMPTY)
    assert res.status == PlanStatus.OK
    cap = 5.5 / (0.5 * params.v_max_m_s * params.limit_margin) + params.pace_slack_s
    if pace == 0.0:
        assert res.trajectory.duration_s > 35.0  # the crawl this guards against (39.4 s)
    else:
        # a soft floor: the formation term still holds it a little past the cap (27.4 s at
        # w_formation 1e5, 28.6 s at 1.5e5, the default since 2026-12-04), far from the crawl
        assert res.trajectory.duration_s < cap + 4.5
        np.testing.assert_allclose(res.trajectory.sample(res.trajectory.t_end_s), GOAL_ORIGIN,
                                   atol=1e-6)  # fmt: skip


def test_the_pace_floor_acts_only_where_the_local_target_is_the_own_goal() -> None:
    """Mid-flight (the goal beyond the horizon) the plan's end is passed at speed, and its
    pace is the formation's, as before: no cap in the problem."""
    params = PlannerParams()
    assert params.pace_floor_frac == 0.5
    planner = FormationPlanner(params, LINE3, slot=1)
    peers = [_peer(0, [0.0, -1.5, 1.0]), _peer(2, [0.0, 1.5, 1.0])]
    far = planner.prepare(0.0, np.array([0.0, 0.0, 1.0]), ZERO, ZERO, GOAL_ORIGIN, peers, EMPTY)
    assert far.prob[3][obj.P_W_PACE] == 0.0
    near_peers = [_peer(0, [37.0, -1.5, 1.0]), _peer(2, [37.0, 1.5, 1.0])]
    near = planner.prepare(
        0.0, np.array([37.0, 0.0, 1.0]), ZERO, ZERO, GOAL_ORIGIN, near_peers, EMPTY
    )
    assert near.prob[3][obj.P_W_PACE] == params.w_pace
    assert near.prob[3][obj.P_T_CAP] == pytest.approx(
        3.0 / (0.5 * params.v_max_m_s * params.limit_margin) + params.pace_slack_s
    )
    # without the formation term (nothing holds the plan back) or alone: none
    alone = planner.prepare(0.0, np.array([37.0, 0.0, 1.0]), ZERO, ZERO, GOAL_ORIGIN, [], EMPTY)
    assert alone.prob[3][obj.P_W_PACE] == 0.0
    free = planner.prepare(
        0.0, np.array([37.0, 0.0, 1.0]), ZERO, ZERO, GOAL_ORIGIN, near_peers, EMPTY,
        use_formation=False,
    )  # fmt: skip
    assert free.prob[3][obj.P_W_PACE] == 0.0
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="pace_floor_frac"):
            PlannerParams(pace_floor_frac=bad)
