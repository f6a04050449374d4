"""DroneAgent: one drone's replan cycle with an injected clock, bus and map."""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np
import pytest

from onboard.agent import DroneAgent, PlanInputs, PlanReport, StaticMap, monitor_action
from onboard.comm import InMemoryBus, TrajectoryMsg
from onboard.planner.field import AnalyticField
from onboard.planner.formation import similarity
from onboard.planner.params import PlannerParams
from onboard.planner.planner import FormationPlanner, PeerTrajectory, PlanResult, PlanStatus
from onboard.planner.trajectory import Trajectory
from onboard.world import World

TRIANGLE = np.array([[0.0, 0.0, 0.0], [-1.0, 1.5, 0.0], [-1.0, -1.5, 0.0]])
PARAMS = PlannerParams(v_max_m_s=1.0)
EMPTY = StaticMap(AnalyticField(World.empty(0.0)))


def _agent(
    i: int,
    bus: InMemoryBus,
    start: np.ndarray,
    goal: np.ndarray | None,
    **kw: object,
) -> DroneAgent:
    return DroneAgent(
        i,
        PARAMS,
        TRIANGLE,
        i,
        Trajectory.hover(start, 0.0),
        bus,
        kw.pop("map_source", EMPTY),  # type: ignore[arg-type]
        goal=goal,
        **kw,  # type: ignore[arg-type]
    )


def _still_agent(params: PlannerParams, bus: InMemoryBus, p: np.ndarray) -> DroneAgent:
    """Drone 0 in slot 0 of TRIANGLE, hovering at ``p`` with its goal there (only its peers'
    plans move the shape), replanning from time 0."""
    return DroneAgent(
        0, params, TRIANGLE, 0, Trajectory.hover(p, 0.0), bus, EMPTY, goal=p, first_replan_s=0.0
    )


def _hover_msg(i: int, p: np.ndarray, slot: int, **kw: object) -> TrajectoryMsg:
    return TrajectoryMsg(i, 0, slot, Trajectory.hover(p, 0.0, 30.0), **kw)  # type: ignore[arg-type]


def test_replan_grid_and_demand() -> None:
    bus = InMemoryBus()
    a = _agent(0, bus, np.array([0.0, 0, 1]), np.array([3.0, 0, 1]), first_replan_s=0.25)
    assert not a.due(0.2) and a.due(0.25)
    assert a.step(0.2) is None
    rep = a.step(0.25)
    assert rep is not None and a.next_replan_s == pytest.approx(1.25)
    assert not a.due(1.0)
    a.request_replan(at_s=0.6)
    assert a.next_replan_s == 0.6 and a.due(0.6)
    a.request_replan()  # at once
    assert a.due(0.3)
    a.replan(0.4)
    # on demand between grid points: the grid stays (1.25), the request is used up
    assert a.next_replan_s == pytest.approx(1.25)
    # a stalled loop skips the grid points it missed instead of replanning in a burst
    a.replan(3.6)
    assert a.next_replan_s == pytest.approx(4.25)
    # no goal: never due, and replan refuses
    a.set_goal(None)
    assert not a.due(100.0)
    with pytest.raises(ValueError, match="no goal"):
        a.replan(5.0)


@pytest.mark.parametrize("period", [0.25, 0.0])
def test_replans_faster_while_reforming(period: float) -> None:
    """After a formation change in flight the agent replans every reform_replan_period_s
    (on top of its grid) for reform_s, then on its grid alone; 0: on the grid throughout."""
    params = PlannerParams(v_max_m_s=1.0, reform_s=2.0, reform_replan_period_s=period)
    bus = InMemoryBus()
    a = DroneAgent(
        0,
        params,
        TRIANGLE,
        0,
        Trajectory.hover(np.array([0.0, 0, 1]), 0.0),
        bus,
        EMPTY,
        goal=np.array([20.0, 0, 1]),
        first_replan_s=0.0,
    )
    rep = a.step(0.0)
    assert rep is not None and not rep.reforming and a.next_replan_s == pytest.approx(1.0)
    a.set_formation(TRIANGLE[[0, 2, 1]], 0, goal=np.array([20.0, 0, 1]))
    times = []
    t = 0.0
    while t < 6.0:
        t = round(t + 0.05, 2)
        rep = a.step(t)
        if rep is not None:
            times.append((t, rep.reforming))
    # the change is planned at once (0.05); reform_s from there to 2.05
    if period > 0:
        # every 0.25 s after the last replan, the grid's own points (1.0, 2.0) among them
        expect = [(t, True) for t in (0.05, 0.3, 0.55, 0.8, 1.0, 1.25, 1.5, 1.75, 2.0)]
        expect += [(2.25, False), (3.0, False), (4.0, False), (5.0, False), (6.0, False)]
    else:
        expect = [(0.05, True), (1.0, True), (2.0, True), (3.0, False), (4.0, False)]
        expect += [(5.0, False), (6.0, False)]
    assert times == expect, times


def test_recovers_the_shape_when_the_peers_plans_leave_it() -> None:
    """A replan that finds the swarm's shape (its start and its formation peers' broadcast
    plans, scored against their slots' template points) further than recover_e_sim from the
    template plans with the re-forming parameters at recover_formation_scale and replans every
    recover_replan_period_s (not re-forming's period), until recover_hold_s after the last such
    replan; in shape, or with recover_e_sim 0, on the grid with the plain parameters."""
    me = np.array([0.0, 0, 1])
    # the drone holds still: only the peers' plans move the shape

    def run(
        params: PlannerParams, peers: dict[int, np.ndarray], switch_s: float | None = None
    ) -> tuple[DroneAgent, list]:
        bus = InMemoryBus()
        for pid, p in peers.items():
            bus.publish(_hover_msg(pid, p, pid), 0.0)
        a = _still_agent(params, bus, me)
        times = []
        t = 0.0
        while t < 5.0:
            if switch_s is not None and t >= switch_s:  # the peers back in their slots
                for pid in peers:
                    bus.publish(_hover_msg(pid, me + TRIANGLE[pid], pid), t)
                switch_s = None
            rep = a.step(t)
            if rep is not None:
                times.append((t, rep.recovering))
            t = round(t + 0.05, 2)
        return a, times

    base = PlannerParams(
        v_max_m_s=1.0,
        recover_e_sim=0.005,
        recover_hold_s=1.0,
        recover_replan_period_s=0.25,
        reform_replan_period_s=0.4,
    )
    # the peers in a line with the drone: far from the triangle (e_sim about 0.2)
    line = {1: me + np.array([-1.0, 1.5, 0.0]) * 2.0, 2: me + np.array([-4.0, 0.0, 0.0])}
    assert similarity(np.vstack([me, line[1], line[2]]), TRIANGLE)[0] > 0.1
    a, times = run(base, line, switch_s=2.0)
    # off the shape until 2.0: every 0.25 s; the replan at 2.0 finds it in shape and the
    # recovery lasts until 1.0 s after the last replan that found it off (1.75 + 1.0)
    expect = [(t, True) for t in (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5)]
    expect += [(2.75, False), (3.0, False), (4.0, False)]  # then on the grid
    assert times == expect, times
    # the recovery's planner pulls the shape recover_formation_scale times harder, with the
    # lead measured from the centroid (reform_params); the plain one is the plain params
    weights = sorted(p.params.w_formation for p in a._planners.values())
    assert weights == [base.w_formation, base.w_formation * base.recover_formation_scale]
    assert base.recover_formation_scale != base.reform_formation_scale
    # ... and holds the altitude as much harder (the pull alone dipped a drone 0.19 m)
    holds = sorted(p.params.w_altitude_hold for p in a._planners.values())
    assert holds == [base.w_altitude_hold, base.w_altitude_hold * base.recover_formation_scale]
    # in shape: the grid alone; recovery off: the same with the peers off the shape
    _, times = run(base, {k: me + TRIANGLE[k] for k in (1, 2)})
    assert times == [(float(t), False) for t in range(5)]
    _, times = run(dataclasses.replace(base, recover_e_sim=0.0), line)
    assert times == [(float(t), False) for t in range(5)]
    with pytest.raises(ValueError, match="recover_e_sim"):
        PlannerParams(recover_e_sim=-0.1)
    with pytest.raises(ValueError, match="recover_formation_scale"):
        PlannerParams(recover_formation_scale=0.0)
    with pytest.raises(ValueError, match="recover_replan_period_s"):
        PlannerParams(recover_replan_period_s=-0.1)
    # 0: the grid alone, also while recovering
    _, times = run(dataclasses.replace(base, recover_replan_period_s=0.0), line)
    assert times == [(float(t), True) for t in range(5)]


def test_reforming_is_held_until_the_new_shape_is_seen() -> None:
    """With reform_hold_e_sim, re-forming goes on past reform_s while the shape the drone sees
    (its start and its formation peers' plans against the new template) is further than that,
    until the first replan that sees it reached or reform_hold_max_s after the change; it does
    not come back when the shape leaves again. Off (0): re-forming ends at reform_s."""
    me = np.array([0.0, 0, 1])
    narrow = np.array([[0.0, 0.0, 0.0], [-2.0, 0.5, 0.0], [-2.0, -0.5, 0.0]])
    old = {k: me + TRIANGLE[k] for k in (1, 2)}
    new = {k: me + narrow[k] for k in (1, 2)}
    assert similarity(np.vstack([me, old[1], old[2]]), narrow)[0] > 0.05

    def run(params: PlannerParams, moves: dict[float, dict[int, np.ndarray]]) -> list:
        """The drone holds still; the peers hover where ``moves`` puts them from each time on
        (``moves`` is used up); the new template is assigned after the first replan."""
        bus = InMemoryBus()
        a = _still_agent(params, bus, me)
        flags = []
        t = 0.0
        peers: dict[int, np.ndarray] = {}
        sent = 0
        while t < 5.0:
            peers.update(moves.pop(t, {}))
            sent += 1
            for pid, p in peers.items():  # broadcast as a swarm does (the new epoch after 0)
                hover = Trajectory.hover(p, t, 30.0)
                bus.publish(TrajectoryMsg(pid, sent, pid, hover, formation_epoch=int(t > 0)), t)
            rep = a.step(t)
            if rep is not None:
                flags.append((t, rep.reforming))
            if t == 0.0:
                a.set_formation(narrow, 0, goal=me)
            t = round(t + 0.05, 2)
        return flags

    base = PlannerParams(
        v_max_m_s=1.0,
        reform_s=1.0,
        reform_replan_period_s=0.25,
        reform_hold_e_sim=0.01,
        reform_hold_max_s=3.0,
        recover_e_sim=0.0,
    )
    # the change is planned at 0.05; re-forming every 0.25 s after the last replan
    during = [(0.0, False)] + [(t, True) for t in (0.05, 0.3, 0.55, 0.8, 1.0)]
    # the peers stay in the old shape: held until 3.05 (reform_hold_max_s), then the grid
    flags = run(base, {0.0: old})
    assert flags == during + [
        (t, True) for t in (1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75, 3.0)
    ] + [(3.25, False), (4.0, False)], flags  # fmt: skip
    # they take the new shape at 1.6: the replan at 1.75 sees it and the hold ends for good,
    # also when they leave it again at 2.5
    flags = run(base, {0.0: old, 1.6: new, 2.5: old})
    assert flags == during + [(1.25, True), (1.5, True), (1.75, False), (2.0, False)] + [
        (3.0, False), (4.0, False)
    ], flags  # fmt: skip
    # in the new shape by reform_s: re-forming ends there, as without the hold
    # (the replan at 1.25 was set by the last re-forming one)
    after = [(1.25, False), (2.0, False), (3.0, False), (4.0, False)]
    flags = run(base, {0.0: old, 0.6: new})
    assert flags == during + after, flags
    for off in (
        dataclasses.replace(base, reform_hold_e_sim=0.0),
        dataclasses.replace(base, reform_hold_max_s=0.5),  # at least reform_s
    ):
        flags = run(off, {0.0: old})
        assert flags == during + after, flags
    for bad in ({"reform_hold_e_sim": -0.01}, {"reform_hold_max_s": math.nan}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            PlannerParams(**bad)  # type: ignore[arg-type]


def test_trajectory_queue() -> None:
    bus = InMemoryBus()
    p0 = np.array([0.0, 0, 1])
    a = _agent(0, bus, p0, None)
    first = a.current
    t1 = Trajectory.hover(p0 + 1.0, 1.0, 5.0)
    t2 = Trajectory.hover(p0 + 2.0, 2.0, 5.0)
    t3 = Trajectory.hover(p0 + 3.0, 1.5, 5.0)
    a.schedule(t1)
    a.schedule(t2)
    assert a.queued == (t1, t2)
    assert a.flying(0.5) is first and a.flying(1.0) is t1 and a.flying(2.5) is t2
    a.schedule(t3)  # replaces what was queued from 1.5 on
    assert a.queued == (t1, t3)
    a.schedule(t3)  # scheduling the same object twice changes nothing
    assert a.queued == (t1, t3)
    assert a.advance(1.2) is t1 and a.queued == (t3,)
    np.testing.assert_allclose(a.state(2.0)[0], p0 + 3.0)
    a.reset(t2)
    assert a.current is t2 and a.queued == ()


def test_two_agents_plan_publish_and_see_each_other() -> None:
    bus = InMemoryBus(delay_s=0.05)
    starts = [np.array([0.0, 0, 1]), np.array([-1.0, 1.5, 1])]
    goals = [s + np.array([4.0, 0, 0]) for s in starts]
    inputs: list[PlanInputs] = []
    reports: list[PlanReport] = []
    agents = [
        _agent(
            i,
            bus,
            starts[i],
            goals[i],
            first_replan_s=0.5 * i,
            on_inputs=inputs.append,
            on_plan=reports.append,
        )
        for i in range(2)
    ]
    for ag in agents:
        ag.announce(0.0)
    for k in range(0, 1201):  # 12 s at 100 Hz, the clock passed in
        t = k * 0.01
        for ag in agents:
            ag.step(t)
    assert [r.drone_id for r in reports[:4]] == [0, 1, 0, 1]
    assert all(r.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION) for r in reports)
    # 50 ms bus delay: at t = 0 drone 0 sees nobody yet; at 0.5 s drone 1 sees drone 0
    assert reports[0].formation_peers == () and reports[1].formation_peers == (0,)
    assert all(r.avoided_peers == () for r in reports)
    assert [r.seq for r in reports if r.drone_id == 0][:3] == [1, 2, 3]  # 0 was the announce
    assert sum(agents[0].status_counts.values()) == len([r for r in reports if r.drone_id == 0])
    # every plan starts plan_ahead_s after its cycle, from the state of the trajectory in control
    for inp, rep in zip(inputs, reports, strict=True):
        assert inp.t_start_s == pytest.approx(rep.planned_at_s + 0.1)
        assert rep.plan_ms >= 0.0 and rep.cycle_ms >= rep.plan_ms
    # what the peer received is what the agent flies
    msg = bus.receive(1, 12.0)[0]
    assert msg.trajectory is agents[0].flying(msg.trajectory.t0_s)
    for ag, g in zip(agents, goals, strict=True):
        np.testing.assert_allclose(ag.state(12.0)[0], g, atol=0.05)
    assert agents[0].last is reports[-2] or agents[0].last is reports[-1]


def test_goal_and_formation_change_mid_flight() -> None:
    bus = InMemoryBus()
    a = _agent(0, bus, np.array([0.0, 0, 1]), np.array([5.0, 0, 1]))
    seen: list[PlanInputs] = []
    a.on_inputs = seen.append
    a.step(0.0)
    assert not a.due(0.3)
    a.set_goal([0.0, 4.0, 1.0])  # replans at once
    assert a.due(0.3)
    rep = a.step(0.3)
    assert rep is not None and np.array_equal(rep.goal, [0.0, 4.0, 1.0])
    np.testing.assert_array_equal(seen[-1].goal, [0.0, 4.0, 1.0])
    line = np.array([[0.0, 0, 0], [0.0, 1.0, 0], [0.0, 2.0, 0], [0.0, 3.0, 0]])
    a.set_formation(line, 2)  # new template and slot: epoch 0 -> 1
    assert a.formation_epoch == 1 and a.slot == 2 and a.due(0.4)
    rep = a.step(0.4)
    assert rep is not None and rep.slot == 2 and rep.formation_epoch == 1
    np.testing.assert_array_equal(seen[-1].formation, line)
    msg = bus.receive(9, 0.5)[0]
    assert (msg.slot, msg.formation_epoch) == (2, 1)
    a.set_slot(3, epoch=7)
    assert (a.slot, a.formation_epoch) == (3, 7)
    with pytest.raises(ValueError, match="slot 4"):
        a.set_slot(4)
    with pytest.raises(ValueError, match="goal"):
        a.set_goal([0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="formation"):
        a.set_formation(np.zeros((3, 2)), 0)


def test_peers_outside_the_formation_are_avoided_not_formed_with() -> None:
    bus = InMemoryBus()
    me = np.array([0.0, 0, 1])
    a = _agent(0, bus, me, me + np.array([6.0, 0, 0]), validity_s=2.0, peer_forget_s=3.0)
    a.set_formation(TRIANGLE, 0, epoch=5, replan=False)
    # 1 and 2 are fine; 3 claims our slot; 4 claims slot 2 too; 6 flies another epoch; 7 has
    # no slot; 8 (slot 1, like 1) is valid until 0.5 s
    cases = {
        1: (1, 5),
        2: (2, 5),
        3: (0, 5),
        4: (2, 5),
        6: (1, 4),
        7: (-1, 5),
    }
    for pid, (slot, epoch) in cases.items():
        p = me + np.array([3.0, 2.0 * pid - 8.0, 0.0])
        bus.publish(_hover_msg(pid, p, slot, formation_epoch=epoch), 0.0)
    late = _hover_msg(8, me + np.array([2.0, 1.0, 0]), 1, formation_epoch=5, valid_until_s=0.5)
    bus.publish(late, 0.0)
    a.set_peer_roles(avoid_only=[1])
    rep = a.replan(0.2)
    # 1 excluded by the service, 2 and 4 share slot 2; 8 is valid until 0.5 s
    assert rep.formation_peers == (8,)
    assert rep.avoided_peers == (1, 2, 3, 4, 6, 7)
    a.set_peer_roles()
    rep = a.replan(1.0)
    assert rep.formation_peers == (1,)  # 8 expired at 0.5; 2 and 4 still share slot 2
    assert rep.avoided_peers == (2, 3, 4, 6, 7, 8)
    a.set_peer_roles(ignore=[4])
    for pid, (slot, epoch) in cases.items():  # fresh plans (a peer re-announcing an old one
        p = me + np.array([3.0, 2.0 * pid - 8.0, 0.0])  # is not flying in formation, below)
        tr = Trajectory.hover(p, 3.9, 30.0)
        bus.publish(TrajectoryMsg(pid, 1, slot, tr, formation_epoch=epoch), 3.9)
    rep = a.replan(4.0)  # 8 forgotten 3 s after it expired
    assert rep.formation_peers == (1, 2) and rep.avoided_peers == (3, 6, 7)
    assert a.avoided_count == 3
    # messages still valid, but their plans started more than validity_s (2 s) ago: a peer
    # that stopped replanning (a stuck drone re-announcing its hover) leaves the formation
    rep = a.replan(5.8)
    assert rep.formation_peers == (1, 2)
    rep = a.replan(6.5)
    assert rep.formation_peers == () and rep.avoided_peers == (1, 2, 3, 6, 7)


def test_avoided_peer_adds_nothing_to_the_formation_term() -> None:
    """The isolated template row of an avoided peer leaves the formation cost unchanged."""
    me = np.array([0.0, 0, 1])
    peer1 = PeerTrajectory(1, 1, Trajectory.hover(me + np.array([-1.0, 1.7, 0]), 0.0, 30.0))
    intruder = Trajectory.hover(me + np.array([2.0, -0.3, 0]), 0.0, 30.0)
    field = AnalyticField(World.empty(0.0))
    goal = me + np.array([5.0, 0, 0])
    z = np.zeros(3)

    def terms(planner: FormationPlanner, peers: list[PeerTrajectory]) -> dict[str, float]:
        prob = planner.prepare(0.0, me, z, z, goal, peers, field)
        return prob.cost_terms(prob.x0)

    bus = InMemoryBus()
    a = _agent(0, bus, me, goal)
    ext = a._planner(a.formation, 0, 1)
    with_intruder = terms(ext, [peer1, PeerTrajectory(2, 3, intruder)])
    without = terms(a.planner, [peer1])
    assert with_intruder["formation"] == pytest.approx(without["formation"], rel=1e-12)
    assert with_intruder["formation"] > 0.0
    assert with_intruder["swarm"] > without["swarm"]  # the intruder is still avoided


def test_conflicting_peer_is_avoided_in_the_plan() -> None:
    bus = InMemoryBus()
    me = np.array([0.0, 0, 1])
    a = _agent(0, bus, me, me + np.array([6.0, 0, 0]))
    blocker = Trajectory.hover(me + np.array([3.0, 0.3, 0]), 0.0, 60.0)
    bus.publish(TrajectoryMsg(1, 0, 0, blocker), 0.0)  # claims our slot
    rep = a.replan(0.0)
    assert rep.avoided_peers == (1,) and rep.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION)
    assert [p.trajectory for p in rep.peers] == [blocker] and rep.peers[0].slot == 3
    assert a.planner.check(rep.trajectory, rep.t_start_s, EMPTY.field, rep.peers)[0]
    ts = np.linspace(rep.t_start_s, rep.trajectory.t_end_s, 400)
    gap = np.linalg.norm(rep.trajectory.sample(ts) - blocker.sample(ts), axis=1)
    assert gap.min() > PARAMS.check_drone_m


def test_emergency_is_reported_and_the_policy_hook_decides() -> None:
    """Walled in, closer to the walls than the check allows, with no way out: nothing is safe
    (not the hover either), the agent reports 'emergency', schedules the planner's braking
    stop, and the hook (the service's policy) asks for a retry."""
    h, t = 0.25, 0.2  # the room's half width (the walls 0.25 m away), the walls' thickness
    walls = np.array(
        [
            [-h - t, -h - t, 0.0, -h, h + t, 4.0],
            [h, -h - t, 0.0, h + t, h + t, 4.0],
            [-h, -h - t, 0.0, h, -h, 4.0],
            [-h, h, 0.0, h, h + t, 4.0],
        ]
    )
    wall = World(np.zeros((0, 5)), np.zeros((0, 7)), walls, 0.0)
    bus = InMemoryBus()
    decisions: list[str] = []

    def policy(rep: PlanReport) -> None:
        if rep.status in (PlanStatus.KEPT_PREVIOUS, PlanStatus.EMERGENCY):
            decisions.append(rep.status.value)
            a.request_replan(at_s=rep.planned_at_s + 0.2)

    a = _agent(
        0,
        bus,
        np.array([0.0, 0, 1]),
        np.array([5.0, 0, 1]),
        map_source=StaticMap(AnalyticField(wall)),
        on_plan=policy,
    )
    rep = a.step(0.0)
    assert rep is not None and rep.status is PlanStatus.EMERGENCY
    assert a.flying(rep.t_start_s) is rep.trajectory
    assert decisions == ["emergency"] and a.next_replan_s == pytest.approx(0.2)
    assert a.status_counts == {"emergency": 1}
    assert a.counters() == {
        "status.emergency": 1,
        "replans": 1,
        "avoided": 0,
        "silent": 0,
        "quiet": 0,
        "in_the_way": 0,
        "refused_older": 0,
        "seq": 1,
    }


def test_setpoint_reader_thread_sees_whole_trajectories() -> None:
    """A 'setpoint thread' reads while the planning thread schedules and advances."""
    bus = InMemoryBus()
    p0 = np.array([0.0, 0, 1])
    a = _agent(0, bus, p0, None)
    made = [Trajectory.hover(p0 + [0.01 * k, 0, 0], 0.001 * k, 1.0) for k in range(1, 2001)]
    allowed = {id(tr) for tr in made} | {id(a.current)}
    bad: list[str] = []
    stop = threading.Event()

    def reader() -> None:
        t = 0.0
        while not stop.is_set():
            tr = a.flying(t)
            p, v, _ = a.state(t)
            if id(tr) not in allowed or not np.all(np.isfinite(p)):
                bad.append(f"t={t}")
            t += 0.0005

    th = threading.Thread(target=reader)
    th.start()
    try:
        for k, tr in enumerate(made):
            a.schedule(tr)
            a.advance(0.001 * k)
    finally:
        stop.set()
        th.join(5.0)
    assert not th.is_alive() and bad == []
    assert a.advance(10.0) is made[-1]


def test_bad_construction() -> None:
    bus = InMemoryBus()
    hover = Trajectory.hover(np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="slot 3"):
        DroneAgent(0, PARAMS, TRIANGLE, 3, hover, bus, EMPTY)
    with pytest.raises(ValueError, match="replan_period_s"):
        DroneAgent(0, PARAMS, TRIANGLE, 0, hover, bus, EMPTY, replan_period_s=0.0)
    with pytest.raises(ValueError, match="goal"):
        DroneAgent(0, PARAMS, TRIANGLE, 0, hover, bus, EMPTY, goal=[1.0, 2.0])
    with pytest.raises(TypeError, match="initial"):
        DroneAgent(0, PARAMS, TRIANGLE, 0, np.zeros(3), bus, EMPTY)  # type: ignore[arg-type]


def _line(p0: np.ndarray, v: np.ndarray, t0: float, duration: float = 10.0) -> Trajectory:
    c = np.zeros((1, 6, 3))
    c[0, 0] = p0
    c[0, 1] = v
    return Trajectory(t0, c, np.array([duration]))


COAST_1 = 0.5 + (1.0 - math.exp(-0.95)) / 0.95 + 0.5 * math.exp(-0.95) * 0.5
"""Where PX4's failsafe brings a peer flying +x at 1 m/s to rest if it died at x = 0.5."""


def test_a_silent_peer_is_avoided_where_it_may_have_stopped() -> None:
    """Peer 1 flies +x at 1 m/s; its last state is stamped 0.3 s, then nothing: 0.5 s later it
    is silent (peer_silence_max_s = peer_silence_s: quiet is silent at once), a replan is due
    at once, it leaves the formation and is avoided at hovers at most 0.25 m apart from its
    last reported position along its trajectory to where it could have flown in
    ghost_window_s more, and on to where PX4's failsafe would carry it; an older copy of its
    trajectory never replaces the newer one."""
    bus = InMemoryBus()
    me = np.array([0.0, 0, 1])
    a = _agent(0, bus, me, me + np.array([6.0, 0, 0]), validity_s=3.0, peer_forget_s=2.0,
               ghost_forget_s=3.0, ghost_window_s=0.7, peer_silence_s=0.5,
               peer_silence_max_s=0.5)  # fmt: skip
    p0 = np.array([0.0, 3.0, 1.0])
    v = np.array([1.0, 0.0, 0.0])
    newer = _line(p0, v, 0.0)
    bus.publish(TrajectoryMsg(1, 7, 1, newer, valid_until_s=3.0), 0.0)
    rep = a.replan(0.0)
    assert rep.formation_peers == (1,) and rep.silent_peers == ()
    a.heard(1, 0.3, newer.sample(0.3))
    a.heard(1, 0.2, p0)  # a late state changes nothing
    assert a.heard_s(1) == pytest.approx(0.3)
    bus.publish(TrajectoryMsg(1, 6, 1, _line(p0 - 1.0, v, -1.0), valid_until_s=2.0), 0.5)
    assert a.watch(0.7) == () and not a.due(0.7)
    assert a.watch(0.85) == (1,) and a.due(0.85)
    assert a.watch(0.9) == ()  # flagged once per silence
    rep = a.replan(0.85)
    assert a.refused_older == 1  # the reordered traj_id 6 did not replace 7
    assert rep.silent_peers == (1,) and rep.formation_peers == () and rep.avoided_peers == (1,)
    own = [p for p in rep.peers if p.drone_id == 1]
    assert own[0].trajectory is newer  # still avoided where it would have flown on
    ghosts = np.array([p.trajectory.sample(5.0) for p in own[1:]])
    assert all(p.slot >= 3 for p in own) and len(ghosts) >= 3
    # from the last reported position (x = 0.3) to where it was at 0.85 s, and on to where
    # PX4's failsafe carries it had it died up to 0.2 s after it was last heard (from x = 0.5,
    # 0.742 m on at 1 m/s: 0.645 m slowing, then 0.097 m of braking; a point of it may give
    # way to a ghost within half a spacing): all on its line, at most 0.25 m apart
    np.testing.assert_allclose(ghosts[0], newer.sample(0.3))
    np.testing.assert_allclose(ghosts[:, 1:], np.tile(p0[1:], (len(ghosts), 1)), atol=1e-9)
    xs = np.sort(ghosts[:, 0])
    assert xs[0] == pytest.approx(0.3) and COAST_1 - 0.125 - 1e-3 <= xs[-1] <= COAST_1 + 1e-3
    assert np.any(np.isclose(xs, 0.85)) and np.max(np.diff(xs)) <= 0.25 + 1e-9
    assert np.min(np.diff(xs)) >= 0.125 - 1e-9  # no two hovers where one will do
    assert rep.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION)
    for g in ghosts:  # the new plan keeps clear of every place it may be
        d = np.linalg.norm(rep.trajectory.sample(np.arange(0.95, 8.0, 0.05)) - g, axis=1)
        assert d.min() >= PARAMS.check_drone_m
    # later, the ghosts reach to where it could have flown in ghost_window_s (0.7 s) after it
    # was last heard
    rep = a.replan(2.0)
    later = np.array([p.trajectory.sample(5.0) for p in rep.peers if p.drone_id == 1][1:])
    xs = np.sort(later[:, 0])
    np.testing.assert_allclose(later[0], newer.sample(0.3), atol=1e-9)
    assert np.any(np.isclose(xs, 1.0)) and COAST_1 - 0.125 - 1e-3 <= xs[-1] <= COAST_1 + 1e-3
    assert np.max(np.diff(xs)) <= 0.25 + 1e-9
    # silent since 0.3 + 0.5: its trajectory is forgotten after 2.8 s, its ghosts (where the
    # vehicle may hold) after 3.8 s
    rep = a.replan(2.85)
    assert rep.silent_peers == (1,) and rep.avoided_peers == ()
    mine = [p.trajectory for p in rep.peers if p.drone_id == 1]
    np.testing.assert_allclose([tr.sample(5.0) for tr in mine], later, atol=1e-12)
    rep = a.replan(3.85)
    assert 1 not in {p.drone_id for p in rep.peers} and rep.silent_peers == ()
    # it speaks again: back in the formation
    bus.publish(TrajectoryMsg(1, 8, 1, _line(newer.sample(4.0), v, 4.0), valid_until_s=7.0), 4.0)
    a.heard(1, 4.0, newer.sample(4.0))
    rep = a.replan(4.1)
    assert rep.formation_peers == (1,) and rep.silent_peers == ()


def test_silence_without_states_waits_one_replan_period_more() -> None:
    """A peer never heard through ``heard`` (its trajectories are its only sign of life) is
    silent only a replan period plus peer_silence_s after its last trajectory was sent."""
    bus = InMemoryBus()
    me = np.array([0.0, 0, 1])
    a = _agent(0, bus, me, me + np.array([6.0, 0, 0]), validity_s=3.0, peer_silence_s=0.5)
    bus.publish(_hover_msg(1, np.array([0.0, 3.0, 1.0]), 1, valid_until_s=3.0), 0.0)
    a.replan(0.0)
    assert a.watch(1.45) == ()
    assert a.watch(1.55) == (1,)
    with pytest.raises(ValueError, match="peer_silence_s"):
        _agent(0, bus, me, None, peer_silence_s=0.0)
    with pytest.raises(ValueError, match="ghost_spacing_m"):
        _agent(0, bus, me, None, ghost_spacing_m=float("nan"))
    with pytest.raises(ValueError, match="ghost_forget_s"):
        _agent(0, bus, me, None, ghost_forget_s=-1.0)
    with pytest.raises(ValueError, match="ghost_window_s"):
        _agent(0, bus, me, None, ghost_window_s=float("inf"))


def test_a_peer_reported_off_its_trajectory_is_avoided_where_it_reported() -> None:
    """Peer 1's trajectory flies on but its states say it stays at x = 0 (a stuck vehicle whose
    hover announcement is late): once more than peer_deviation_m off, a replan is due at once
    and it is also avoided as a hover where it reported itself, until its trajectory agrees."""
    bus = InMemoryBus()
    me = np.array([0.0, 0, 1])
    a = _agent(0, bus, me, me + np.array([6.0, 0, 0]), validity_s=3.0, peer_silence_s=0.5,
               peer_deviation_m=0.3)  # fmt: skip
    p0 = np.array([0.0, 3.0, 1.0])
    bus.publish(TrajectoryMsg(1, 1, 1, _line(p0, np.array([1.0, 0, 0]), 0.0), valid_until_s=3.0), 0)
    a.replan(0.0)
    a.heard(1, 0.2, p0)  # 0.2 m off: within the bound
    assert a.watch(0.25) == () and not a.due(0.25)
    a.heard(1, 0.4, p0)
    assert a.watch(0.45) == (1,) and a.due(0.45)
    assert a.watch(0.5) == ()  # flagged once
    rep = a.replan(0.45)
    assert rep.deviating_peers == (1,) and rep.silent_peers == () and rep.formation_peers == (1,)
    ghosts = [p for p in rep.peers if p.drone_id == 1][1:]
    assert len(ghosts) == 1 and ghosts[0].slot >= 3
    np.testing.assert_allclose(ghosts[0].trajectory.sample(9.0), p0)
    # its hover arrives: nothing more to avoid than that
    bus.publish(TrajectoryMsg(1, 2, 1, Trajectory.hover(p0, 0.5, 30.0), valid_until_s=3.5), 0.5)
    a.heard(1, 0.6, p0)
    rep = a.replan(0.7)
    assert rep.deviating_peers == () and [p.drone_id for p in rep.peers] == [1]
    assert a.watch(0.7) == ()
    with pytest.raises(ValueError, match="peer_deviation_m"):
        _agent(0, bus, me, None, peer_deviation_m=0.0)


def test_a_peer_whose_velocity_leaves_its_trajectory_is_avoided_before_its_position_does() -> None:
    """Peer 1's trajectory flies on at 1 m/s but it reports itself stopped (a brake whose
    copies were lost) 0.1 m short of where its trajectory has it: off by less than
    peer_deviation_m, but its velocity would take it 0.6 m off within peer_deviation_ahead_s.
    A velocity that agrees with the trajectory is no deviation; without the lookahead the
    stop is found only once its position is 0.3 m off."""
    me = np.array([0.0, 0, 1])
    p0 = np.array([0.0, 3.0, 1.0])
    line = _line(p0, np.array([1.0, 0, 0]), 0.0)
    for ahead, expect in ((0.5, (1,)), (0.0, ())):
        bus = InMemoryBus()
        a = _agent(0, bus, me, me + np.array([6.0, 0, 0]), validity_s=3.0, peer_silence_s=0.5,
                   peer_deviation_m=0.3, peer_deviation_ahead_s=ahead)  # fmt: skip
        bus.publish(TrajectoryMsg(1, 1, 1, line, valid_until_s=3.0), 0)
        a.replan(0.0)
        a.heard(1, 0.2, line.sample(0.2), line.sample(0.2, order=1))  # on it
        assert a.watch(0.25) == ()
        a.heard(1, 0.4, line.sample(0.3), np.zeros(3))  # stopped, 0.1 m short
        assert a.watch(0.45) == expect
        rep = a.replan(0.45)
        assert rep.deviating_peers == expect
    with pytest.raises(ValueError, match="peer_deviation_ahead_s"):
        _agent(0, bus, me, None, peer_deviation_ahead_s=-0.1)


@pytest.mark.parametrize(
    ("conflict_in_s", "asked_ago_s", "expected"),
    [
        (0.5, None, "replan"),  # nothing asked yet: a replan first
        (0.5, 0.1, "replan"),  # asked a moment ago: the replan may still clear it
        (0.5, 0.3, "brake"),  # the replan is late and the conflict is close
        (2.0, 0.3, "replan"),  # late, but far: ask again
        (2.0, 5.0, "replan"),
    ],
)
def test_the_monitor_brakes_when_the_replan_it_asked_for_is_late(
    conflict_in_s: float, asked_ago_s: float | None, expected: str
) -> None:
    now, last_plan = 100.0, 98.0  # the newest plan began 2 s ago (a starved planner)
    asked = -math.inf if asked_ago_s is None else now - asked_ago_s
    assert monitor_action(now, now + conflict_in_s, last_plan, -math.inf, True, asked_s=asked) == (
        expected
    )
    # a plan begun after the request came back: the usual rule (fresh plan, conflict close)
    assert monitor_action(now, now + conflict_in_s, now - 0.1, -math.inf, True, asked_s=asked) == (
        "brake" if conflict_in_s <= 1.0 else "watching"
    )


@pytest.mark.parametrize("plan_takes_s", [0.05, 2.0])
def test_a_plan_back_after_its_start_and_off_the_flown_one_is_not_flown(
    plan_takes_s: float,
) -> None:
    """With the flight's clock: a plan that comes back after its start, its setpoint then more
    than ``late_jump_m`` from the trajectory in control's, is neither flown nor published and
    a replan follows at once (a starved CPU); a plan a moment late, close to it, is flown."""
    now = {"t": 0.0}
    bus = InMemoryBus()
    start = np.array([0.0, 0.0, 1.0])

    def slow(_inputs: PlanInputs) -> None:  # the planner runs, the clock moves on
        now["t"] += 0.1 + plan_takes_s

    a = _agent(0, bus, start, np.array([6.0, 0, 1]), clock=lambda: now["t"], on_inputs=slow)
    hold = a.flying(0.0)
    rep = a.replan(0.0)
    done = now["t"]
    assert rep.t_start_s < done
    late = float(np.linalg.norm(rep.trajectory.sample(done) - hold.sample(done))) > 0.2
    assert late is (plan_takes_s > 1.0)
    if late:
        assert rep.status is PlanStatus.LATE and "after its start" in rep.message
        assert a.flying(done) is hold  # the trajectory in control flies on
        assert bus.receive(1, done + 1.0) == {}  # nothing published
        assert a.due(done)  # a replan at once
    else:
        assert rep.status is PlanStatus.OK
        assert a.flying(done) is rep.trajectory
        assert bus.receive(1, done + 1.0)[0].trajectory is rep.trajectory
    with pytest.raises(ValueError, match="late_jump_m"):
        _agent(0, bus, start, None, late_jump_m=0.0)


def test_the_plan_budget_is_measured_by_the_timer_and_an_over_budget_plan_flies_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``plan_budget_s``: the planner gets a ``give_up`` that turns true once the replan has
    taken that long by the agent's timer (none without a budget: the fast-time simulator's
    results must not depend on the host). An 'over-budget' result, the trajectory in control
    kept, is flown on and published, and a replan follows at once."""
    tm = {"t": 100.0}
    seen: list[object] = []
    real_plan = FormationPlanner.plan

    def plan(self: FormationPlanner, *args: object, **kw: object) -> PlanResult:
        give_up = args[8] if len(args) > 8 else kw.get("give_up")
        seen.append(give_up)
        if give_up is None:
            return real_plan(self, *args, **kw)  # type: ignore[arg-type]
        assert callable(give_up)
        assert give_up() is False
        tm["t"] += 0.29
        assert give_up() is False
        tm["t"] += 0.02
        assert give_up() is True
        previous = args[7]
        assert isinstance(previous, Trajectory)
        return PlanResult(PlanStatus.OVER_BUDGET, previous, message="formation: refused")

    monkeypatch.setattr(FormationPlanner, "plan", plan)
    bus = InMemoryBus()
    start = np.array([0.0, 0.0, 1.0])
    goal = np.array([6.0, 0, 1])
    free = _agent(0, bus, start, goal)
    assert free.replan(0.0).status is PlanStatus.OK and seen == [None]
    a = _agent(1, bus, start, goal, timer=lambda: tm["t"], plan_budget_s=0.3)
    hold = a.flying(0.1)
    rep = a.replan(0.0)
    assert rep.status is PlanStatus.OVER_BUDGET and rep.trajectory is hold
    assert a.flying(0.5) is hold
    assert bus.receive(0, 0.5)[1].trajectory is hold
    assert a.due(0.0)  # a replan at once
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="plan_budget_s"):
            _agent(0, bus, start, None, plan_budget_s=bad)


def test_the_replan_after_an_over_budget_one_starts_at_the_attempt_it_gave_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An 'over-budget' result's ``resume_at`` is the next replan's ``first_attempt`` (the
    attempts it gave up, from the newer start), and only that replan's: after any other
    result, and after a change of shape (what was given up was for the old one), the planner
    starts at its first attempt. The inputs handed to ``on_inputs`` carry it too."""
    tm = {"t": 100.0}
    firsts: list[int] = []
    outcome: list[PlanResult | None] = []
    real_plan = FormationPlanner.plan

    def plan(self: FormationPlanner, *args: object, **kw: object) -> PlanResult:
        first = args[9] if len(args) > 9 else kw.get("first_attempt", 0)
        assert isinstance(first, int)
        firsts.append(first)
        canned = outcome.pop(0)
        if canned is not None:
            previous = args[7]
            assert isinstance(previous, Trajectory)
            return dataclasses.replace(canned, trajectory=previous)
        return real_plan(self, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(FormationPlanner, "plan", plan)
    seen: list[PlanInputs] = []
    bus = InMemoryBus()
    start = np.array([0.0, 0.0, 1.0])
    a = _agent(
        1,
        bus,
        start,
        np.array([6.0, 0, 1]),
        timer=lambda: tm["t"],
        plan_budget_s=0.3,
        on_inputs=seen.append,
    )
    hold = Trajectory.hover(start, 0.0)
    over = [PlanResult(PlanStatus.OVER_BUDGET, hold, resume_at=k) for k in (1, 2)]
    outcome += [over[0], over[1], None, None, over[0], None]
    statuses = [a.replan(0.2 * k).status for k in range(4)]
    assert statuses[:2] == [PlanStatus.OVER_BUDGET] * 2
    assert PlanStatus.OVER_BUDGET not in statuses[2:]
    assert firsts == [0, 1, 2, 0]
    now = 0.8
    a.replan(now)  # over budget, resume at 1 ...
    a.set_formation(TRIANGLE[[0, 2, 1]], 1)  # ... but the shape changes
    a.replan(now + 0.2)
    assert firsts == [0, 1, 2, 0, 0, 0]
    assert [i.first_attempt for i in seen] == firsts


def test_the_plan_reports_its_cpu_apart_from_its_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    """``plan_cpu_ms`` is the planning thread's CPU within ``plan_ms``: a planner that waits
    (here a sleep, on a starved host a core or the interpreter lock) shows in ``plan_ms``
    only; one that computes shows in both."""
    real_plan = FormationPlanner.plan
    mode = {"wait": True}

    def plan(self: FormationPlanner, *args: object, **kw: object) -> PlanResult:
        if mode["wait"]:
            time.sleep(0.08)
        else:
            end = time.thread_time() + 0.03
            while time.thread_time() < end:
                pass
        return real_plan(self, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(FormationPlanner, "plan", plan)
    a = _agent(0, InMemoryBus(), np.array([0.0, 0.0, 1.0]), np.array([6.0, 0, 1]))
    waited = a.replan(0.0)
    assert waited.plan_ms >= 80.0
    assert 0.0 <= waited.plan_cpu_ms < waited.plan_ms - 60.0
    mode["wait"] = False
    busy = a.replan(1.0)
    assert busy.plan_cpu_ms >= 30.0
    assert busy.plan_cpu_ms <= busy.plan_ms + 1.0


def test_a_published_trajectory_goes_out_again_on_time_until_a_newer_one_does() -> None:
    bus = InMemoryBus(0.0)
    a = _agent(0, bus, np.zeros(3), None, resend_s=(0.05, 0.15))

    def newest() -> TrajectoryMsg:
        return bus.receive(1, 1e9)[0]

    assert not a.resend(0.0)  # nothing published yet
    a.announce(10.0)
    first = newest()
    assert not a.resend(10.04)
    assert a.resend(10.05)  # the first copy: a new number, the same trajectory
    copy = newest()
    assert copy.traj_id == first.traj_id + 1 and copy.trajectory is first.trajectory
    assert copy.slot == first.slot and copy.formation_epoch == first.formation_epoch
    assert not a.resend(10.06)
    assert a.resend(10.2) and not a.resend(10.5) and a.resent == 2  # a late look: one copy
    # a newer trajectory cancels the copies still due of the older one; only its own follow
    a.announce(20.0)
    a.reset(Trajectory.hover(np.ones(3), 20.01))
    a.announce(20.02)
    newer = newest()
    assert a.resend(20.07) and newest().trajectory is newer.trajectory
    assert not a.resend(20.1) and a.resend(20.17) and a.resent == 4
    assert newest().trajectory is newer.trajectory
    # resend_plans False: a plan goes out once, a braking stop or hover as before
    bus_c = InMemoryBus(0.0)
    c = _agent(0, bus_c, np.zeros(3), np.array([5.0, 0, 1]), resend_s=(0.05, 0.15),
               resend_plans=False)  # fmt: skip
    c.replan(0.0)
    assert not c.resend(0.05) and not c.resend(0.2) and c.resent == 0
    c.announce(1.0)
    assert c.resend(1.05) and c.resent == 1
    a.set_goal(np.array([5.0, 0, 1]))  # ... and with it True a plan goes out again too
    a.replan(30.0)
    assert not a.resend(30.04) and a.resend(30.05)
    # off by default
    b = _agent(1, InMemoryBus(0.0), np.zeros(3), None)
    b.announce(0.0)
    assert not b.resend(1.0) and b.resent == 0
    with pytest.raises(ValueError, match="resend_s"):
        _agent(2, InMemoryBus(0.0), np.zeros(3), None, resend_s=(0.05, -1.0))
    with pytest.raises(ValueError, match="resend_s"):
        _agent(2, InMemoryBus(0.0), np.zeros(3), None, resend_s=(math.nan,))
