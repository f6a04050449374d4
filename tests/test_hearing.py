"""Whether the peers hear this drone (``onboard.comm.hearing``): the rules, the statuses that
carry it over Zenoh, and the planner's wider berth while a peer does not hear us."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.agent import DroneAgent, StaticMap
from onboard.comm import InMemoryBus, TrajectoryMsg
from onboard.comm.hearing import (
    REPORT_FRESH_S,
    UNHEARD_AGE_S,
    UNLISTED_GRACE_S,
    UNLISTED_RECENT_S,
    HearingReport,
    not_hearing,
    report_from_links,
)
from onboard.planner.field import AnalyticField
from onboard.planner.params import PlannerParams, unheard_params
from onboard.planner.planner import (
    EVADE,
    LAST_RESORT,
    FormationPlanner,
    PeerTrajectory,
    PlanResult,
    PlanStatus,
)
from onboard.planner.trajectory import Trajectory
from onboard.world import World

NOW = 1000.0


def test_the_rules_of_not_hearing() -> None:
    first, last = NOW - 60.0, NOW - 0.5  # we have published for a minute, the last just now
    up = HearingReport(0, NOW - 0.5, True, True, 0.2)
    assert not_hearing([up], NOW, first, last) == frozenset()
    # our link down (we are silent to it), or too long quiet, or never heard
    assert not_hearing([HearingReport(0, NOW, True, False, 0.3)], NOW, first, last) == {0}
    old = HearingReport(0, NOW, True, True, UNHEARD_AGE_S)
    assert not_hearing([old], NOW, first, last) == {0}
    assert not_hearing([HearingReport(0, NOW, True, True, None)], NOW, first, last) == {0}
    # not listed: it forgot us or never heard us, once we have published long enough and lately
    unlisted = HearingReport(3, NOW, False)
    assert not_hearing([unlisted], NOW, first, last) == {3}
    assert not_hearing([unlisted], NOW, NOW - UNLISTED_GRACE_S + 0.1, last) == frozenset()
    assert not_hearing([unlisted], NOW, math.inf, -math.inf) == frozenset()  # never published
    # landed: no trajectory for longer than UNLISTED_RECENT_S, forgotten, nothing wrong
    landed = NOW - UNLISTED_RECENT_S - 0.1
    assert not_hearing([unlisted], NOW, first, landed) == frozenset()
    # a stale report says nothing; the newest report of a peer wins, whatever the order
    stale = HearingReport(0, NOW - REPORT_FRESH_S - 0.01, True, False, 5.0)
    assert not_hearing([stale], NOW, first, last) == frozenset()
    down = HearingReport(0, NOW - 1.0, True, False, 1.2)
    assert not_hearing([up, down], NOW, first, last) == frozenset()
    assert not_hearing([down, up], NOW, first, last) == frozenset()
    assert not_hearing([down, unlisted, up], NOW, first, last) == {3}


def test_a_report_is_read_from_the_status_links() -> None:
    links = [("autopilot", True, 0.01), ("peer/2", True, 0.1), ("peer/12", False, 2.5)]
    assert report_from_links(4, NOW, 12, links) == HearingReport(4, NOW, True, False, 2.5)
    assert report_from_links(4, NOW, 2, links) == HearingReport(4, NOW, True, True, 0.1)
    assert report_from_links(4, NOW, 1, links) == HearingReport(4, NOW, False)
    inf = report_from_links(4, NOW, 2, [("peer/2", True, math.inf)])
    assert inf.listed and inf.age_s is None


def test_the_planner_keeps_a_wider_berth_from_peers_while_one_does_not_hear_us() -> None:
    """A peer hovers 0.6 m beside our goal: the plan goes there (the check's 0.5 m kept)
    while every peer hears us; once one does not, the plan flown keeps the check distance
    plus ``unheard_margin_m`` (0.8 m) from it."""
    params = PlannerParams(v_max_m_s=1.0)
    wide = unheard_params(params)
    assert wide.check_drone_m == pytest.approx(params.check_drone_m + params.unheard_margin_m)
    assert wide.swarm_clearance_m == pytest.approx(
        params.swarm_clearance_m + params.unheard_margin_m
    )
    assert wide.brake_reference_s == params.unheard_brake_reference_s > params.brake_reference_s
    assert unheard_params(PlannerParams(unheard_margin_m=0.0, unheard_brake_reference_s=1.0)) == (
        PlannerParams(unheard_margin_m=0.0, unheard_brake_reference_s=1.0)
    )
    with pytest.raises(ValueError, match="unheard_margin_m"):
        PlannerParams(unheard_margin_m=-0.1)
    me = np.array([0.0, 0.0, 1.0])
    goal = me + np.array([4.0, 0.0, 0.0])
    peer = Trajectory.hover(goal + np.array([0.0, 0.6, 0.0]), 0.0, 60.0)
    gaps = {}
    for deaf in (False, True):
        bus = InMemoryBus()
        agent = DroneAgent(
            0,
            params,
            np.zeros((1, 3)),
            0,
            Trajectory.hover(me, 0.0),
            bus,
            StaticMap(AnalyticField(World.empty(0.0))),
            goal=goal,
        )
        bus.publish(TrajectoryMsg(1, 0, 0, peer), 0.0)  # another slot claim: avoided only
        if deaf:
            agent.set_unheard([1, 0])  # our own id is never a peer
        assert agent.unheard_by == ({1} if deaf else set())
        assert agent.check_drone_m == pytest.approx(wide.check_drone_m if deaf else 0.5)
        assert agent.brake_reference_s == (3.0 if deaf else 1.0)
        flown = []
        reports = []
        for k in range(150):  # 15 s, replans on the agent's grid
            t = 0.1 * k
            rep = agent.step(t)
            if rep is not None:
                reports.append(rep)
            flown.append(agent.current.sample(t))
        assert {r.unheard_by for r in reports} == {(1,) if deaf else ()}
        ts = 0.1 * np.arange(150)
        gaps[deaf] = float(np.linalg.norm(np.array(flown) - peer.sample(ts), axis=1).min())
    assert params.check_drone_m <= gaps[False] < wide.check_drone_m
    assert gaps[True] >= wide.check_drone_m


@pytest.mark.parametrize("refine", [(1, 1.0), (2, 100.0)])
def test_an_unheard_drone_does_not_stop_where_a_peer_flies_through(
    refine: tuple[int, float],
) -> None:
    """CI's bus-faults flight (2026-12-01): a drone its peers did not hear refused every way
    (the closest 0.53 m from a peer, inside its widened 0.7 m check) and stopped, and the peer,
    which planned around its last heard trajectory, flew through the stop 1.6 s later (0.315 m
    apart). Here: our drone in a corridor of trunks, a peer on our line overtaking at 0.9 m/s.
    While the peer does not hear us the stop is judged over ``unheard_brake_reference_s``: it
    holds us where the peer passes, so a way that keeps more distance is flown (the one that
    keeps farthest of those the check accepts only as a last resort), not the stop. With the
    window of a heard peer (1 s) it stopped, and the peer flew through. ``refine``: the
    refused plans' second solve plain (as in the flight service) and stiffer (the defaults of
    ``refine_kappa_factor``, ``refine_penalty_scale``), whose stiffer obstacle term alone held
    the drone in the corridor's middle, 0.46 m from the peer, until the plain solve was
    compared with it."""
    xs = np.arange(-4.0, 8.0, 0.35)
    trunks = [[x, s * 1.0, 0.15, 0.0, 3.0] for x in xs for s in (-1.0, 1.0)]
    field = AnalyticField(World(np.array(trunks), np.zeros((0, 7)), np.zeros((0, 6)), 0.0))
    c = np.zeros((1, 6, 3))
    c[0, 0] = (-1.5, 0.0, 1.0)
    c[0, 1] = (0.9, 0.0, 0.0)
    peer = PeerTrajectory(0, 0, Trajectory(0.0, c, np.array([30.0])))
    line = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
    start = (0.0, np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.0, 0.0]), np.zeros(3))
    goal = np.array([10.0, 0.0, 1.0])
    ts = np.arange(0.0, 6.0, 0.02)

    def closest(res: PlanResult) -> float:  # held at its end after it (a stop holds)
        return float(
            np.linalg.norm(res.trajectory.sample(ts) - peer.trajectory.sample(ts), axis=1).min()
        )

    old = unheard_params(PlannerParams(unheard_brake_reference_s=1.0))
    stopped = FormationPlanner(old, line, slot=1).plan(*start, goal, [peer], field)
    assert stopped.status == PlanStatus.EMERGENCY, stopped.message
    assert closest(stopped) < 0.1
    kappa_factor, scale = refine
    wide = unheard_params(
        PlannerParams(refine_kappa_factor=kappa_factor, refine_penalty_scale=scale)
    )
    res = FormationPlanner(wide, line, slot=1).plan(*start, goal, [peer], field)
    assert res.status != PlanStatus.EMERGENCY, res.message
    assert res.message.endswith(LAST_RESORT), res.message
    assert closest(res) > 0.5  # the bodies (0.4 m) apart, with room
    # still clear of the trunks by the check's distance
    pts = res.trajectory.sample(np.linspace(res.trajectory.t0_s, res.trajectory.t_end_s, 2000))
    assert float(field.distance(pts)[0].min()) >= wide.check_obstacle_m


def test_an_unheard_drone_evades_a_peer_coming_at_it_when_no_optimised_way_keeps_clear() -> None:
    """A peer that does not hear us flies across our way at 0.5 m/s, 0.75 m off: every
    optimised way comes inside the check's distance (the optimiser starts from the way to
    the goal and stays near it), and the best of them kept 0.35 m. A move straight aside, as
    fast as the limits allow, keeps farther: it is flown (as a last resort: it too comes inside
    the widened 0.7 m here, but no closer than a stop would)."""
    field = AnalyticField(World.empty(0.0))
    line = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
    # the margin of the time (0.2 m; 0.3 since): at 0.3 the optimised ways keep 0.47 m here
    prm = unheard_params(PlannerParams(v_max_m_s=1.0, unheard_margin_m=0.2))
    c = np.zeros((1, 6, 3))
    c[0, 0] = (0.6, -0.45, 1.0)
    c[0, 1] = (0.0, 0.5, 0.0)
    peer = PeerTrajectory(0, 0, Trajectory(0.0, c, np.array([30.0])))
    start = (0.0, np.array([0.0, 0.0, 1.0]), np.array([0.8, 0.0, 0.0]), np.zeros(3))
    res = FormationPlanner(prm, line, slot=2).plan(
        *start, np.array([10.0, -1.0, 1.0]), [peer], field
    )
    assert res.status == PlanStatus.OK_NO_FORMATION, res.message
    assert f"; {EVADE} " in res.message and res.message.endswith(LAST_RESORT), res.message
    tr = res.trajectory
    ts = np.linspace(0.0, 6.0, 601)
    assert float(np.linalg.norm(tr.sample(ts) - peer.trajectory.sample(ts), axis=1).min()) > 0.4
    inside = np.linspace(tr.t0_s, tr.t_end_s, 400)
    assert np.linalg.norm(tr.sample(inside, 1), axis=1).max() <= prm.v_max_m_s + 1e-9
    assert np.linalg.norm(tr.sample(inside, 2), axis=1).max() <= prm.a_max_m_s2 + 1e-9
    np.testing.assert_allclose(tr.sample(tr.t0_s), start[1], atol=1e-12)
    np.testing.assert_allclose(tr.sample(tr.t0_s, 1), start[2], atol=1e-12)


def test_in_fast_time_a_drone_whose_uplink_fails_learns_it_and_keeps_clear() -> None:
    """``swarm-gcs bench hidden``'s flight (the bus-faults flight's swap in fast time): drone
    2's uplink is out for 7.5 s over the crossing; its peers' statuses tell it that they do not
    hear it, it plans with the wider berth, and the swap ends with every drone at its goal and
    the pair apart. On the same faulty bus with no outage, no drone is ever told that a peer
    does not hear it."""
    from gcs.bench_hidden import HiddenTrial, fly_hidden
    from onboard.config import load_planner_params

    params = load_planner_params(v_max_m_s=1.0)
    row = fly_hidden(HiddenTrial(1, 1.0, 7.5, params, 40.0))
    assert row["radio_dropped"] > 0 and row["unheard_plans"] > 0, row
    assert row["success"] and row["arrived"] == 3 and row["collisions"] == 0, row
    assert row["hidden_closest_m"] >= params.check_drone_m, row
    # the bench's time limit (80 s): with no outage 5-7 of 100 such swaps take over 40 s at
    # either replan period while the shape is off (bench hidden --outage-s 0 --time-limit 40,
    # 2026-12-01), seed 1 among them at 0.1 s (45.7 s)
    row = fly_hidden(HiddenTrial(1, 1.0, 0.0, params, 80.0))
    assert row["radio_dropped"] == 0 and row["unheard_plans"] == 0, row
    assert row["success"] and row["collisions"] == 0, row
    with pytest.raises(ValueError, match="radio_outages"):
        from gcs.fastsim import SimConfig
        from onboard.config import load_formation, load_world_spec

        SimConfig(
            load_formation("triangle-3"),
            load_world_spec("forest-small"),
            radio_outages={1: (5.0, 4.0)},
        )
