"""The A* fallback's clearance levels: ordinary replans use the two-step ladder (the optimiser's
clearance, then the check's); the intermediate levels only rescue a replan whose every attempt
was refused, before the previous trajectory would be kept."""

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from gcs.fastsim import REFUSAL_KEYS, count_refusals
from onboard.planner import planner as planner_module
from onboard.planner.astar import astar_path_levels
from onboard.planner.field import AnalyticField, DistanceField, GridField
from onboard.planner.lbfgs import LbfgsStatus
from onboard.planner.minco import Minco
from onboard.planner.params import PlannerParams
from onboard.planner.planner import (
    APPROACH,
    APPROACH_S,
    KEEP_MOVING_M,
    FormationPlanner,
    PeerTrajectory,
    PlanResult,
    PlanStatus,
    Problem,
)
from onboard.planner.trajectory import Trajectory
from onboard.world import World

LINE3 = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
ZERO = np.zeros(3)
# The scenarios below were built around the two-step ladder of the defaults before the twelfth
# session (the optimiser's clearance 0.6 m, the check's 0.22 m) and its rescue levels: their
# walls' gaps are sized for those, so they fly with them.
LADDER_SETUP = {
    "w_obstacle": 5e4,
    "obstacle_clearance_m": 0.6,
    "check_obstacle_m": 0.22,
    "astar_clearances_m": (0.5, 0.4, 0.3),
}
TWO_STEP = (0.6, 0.22)
RESCUE = (0.5, 0.4, 0.3)


def _params(**kw: Any) -> PlannerParams:
    return PlannerParams(**{**LADDER_SETUP, **kw})


def _wall(narrow_half_gap_m: float, trunk_ahead: bool) -> World:
    """A wall of 0.3 m trunks across x = 4 whose gaps are all narrower than the optimiser's
    0.6 m clearance needs: one 2 * ``narrow_half_gap_m`` wide on the straight way (y = 0), one
    0.95-1.0 m wide about 2.2 m aside, the rest 0.25-0.3 m; optionally a trunk on the straight
    way at x = 1.8."""
    c = narrow_half_gap_m + 0.3
    ys = [-c - 0.9 * k for k in range(11)] + [c, c + 0.85] + [3.0 + 0.9 * k for k in range(8)]
    cyl = [[4.0, y, 0.3, 0.0, 3.0] for y in ys]
    if trunk_ahead:
        cyl.append([1.8, 0.0, 0.25, 0.0, 3.0])
    return World(
        cylinders=np.array(cyl, dtype=float),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )


def _gap_unobserved(world: World) -> GridField:
    """The world's distances on a 0.1 m grid whose cells inside the narrow gap (and 0.35 m
    either side of the wall) were never observed: like a drone's own map, on which every plan
    through that gap is refused while A* at the check's distance still finds the way through
    it (mapped forest-medium seed 3, where the map's gap was narrower than the check needs)."""
    exact = AnalyticField(world)
    grid = GridField.from_function(exact.distance, [-1.0, -5.0, 0.0], [10.0, 6.0, 3.0], 0.1)
    c = grid.cell_centres()
    gap = (np.abs(c[..., 0] - 4.0) < 0.35) & (np.abs(c[..., 1]) < 0.3)
    return GridField(grid.values, grid.origin, grid.res, known=~gap)


@pytest.fixture
def ladders(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[tuple[tuple[float, ...], float]]]:
    """Every A* search of the planner: (the clearances it was given, the one that found)."""
    seen: list[tuple[tuple[float, ...], float]] = []

    def spy(
        field: DistanceField,
        start: np.ndarray,
        goal: np.ndarray,
        clearances_m: tuple[float, ...],
        **kw: Any,
    ) -> tuple[np.ndarray | None, float]:
        path, found = astar_path_levels(field, start, goal, clearances_m, **kw)
        seen.append((tuple(clearances_m), found))
        return path, found

    monkeypatch.setattr(planner_module, "astar_path_levels", spy)
    yield seen


def _crossing(res: PlanResult, world: World) -> tuple[float, float]:
    """(y where the plan crosses the wall at x = 4, closest approach of the whole plan to a
    trunk of the exact world); y is NaN when the plan does not reach the wall."""
    tr = res.trajectory
    pts = tr.sample(np.linspace(tr.t0_s, tr.t_end_s, 800))
    d = AnalyticField(world).distance(pts)[0]
    if pts[:, 0].max() < 4.0:
        return float("nan"), float(d.min())
    return float(pts[int(np.argmin(np.abs(pts[:, 0] - 4.0))), 1]), float(d.min())


def test_the_ladders_of_the_defaults_and_their_validation() -> None:
    # the defaults: the optimiser's clearance a little above the check's, the rescue above both
    p = PlannerParams()
    assert p.astar_ladder_m == (0.34, 0.3)
    assert p.astar_rescue_ladder_m == (0.5, 0.4)
    assert _params().astar_ladder_m == TWO_STEP and _params().astar_rescue_ladder_m == RESCUE
    assert PlannerParams(astar_clearances_m=()).astar_rescue_ladder_m == ()
    # levels at or under the check's distance are left out; the ordinary ladder never changes
    odd = _params(astar_clearances_m=(0.7, 0.45, 0.22, 0.1))
    assert odd.astar_rescue_ladder_m == (0.7, 0.45)
    assert odd.astar_ladder_m == TWO_STEP
    single = PlannerParams(obstacle_clearance_m=0.3)
    assert single.astar_ladder_m == (0.3,) and single.astar_rescue_ladder_m == (0.5, 0.4)
    with pytest.raises(ValueError, match="astar_clearances_m must hold positive"):
        PlannerParams(astar_clearances_m=(0.5, -0.1))
    with pytest.raises(ValueError, match="astar_clearances_m must hold positive"):
        PlannerParams(astar_clearances_m=(0.5, float("nan")))
    with pytest.raises(ValueError, match="astar_clearances_m must be strictly decreasing"):
        PlannerParams(astar_clearances_m=(0.3, 0.4))
    with pytest.raises(ValueError, match="astar_clearances_m must be strictly decreasing"):
        PlannerParams(astar_clearances_m=(0.4, 0.4))


def test_prepare_takes_a_ladder_and_says_which_clearance_its_path_keeps() -> None:
    field = _gap_unobserved(_wall(0.3, False))
    planner = FormationPlanner(_params(v_max_m_s=1.0), LINE3, slot=1)
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    two = planner.prepare(0.0, start, ZERO, ZERO, goal, [], field, force_astar=True)
    assert two.astar_clearance_m == 0.22  # no path at 0.6 m: the narrow gap at the check's
    rescue = planner.prepare(
        0.0, start, ZERO, ZERO, goal, [], field, force_astar=True, astar_ladder_m=RESCUE
    )
    assert rescue.astar_clearance_m == 0.4  # the wide gap
    straight = planner.prepare(0.0, np.array([0.0, 0, 1]), ZERO, ZERO, np.array([2.0, 0, 1]),
                               [], field)  # fmt: skip
    assert np.isnan(straight.astar_clearance_m)  # a free straight line: no A*
    for bad in ((), (0.5, -0.2), (float("inf"),)):
        with pytest.raises(ValueError, match="astar_ladder_m"):
            planner.prepare(0.0, start, ZERO, ZERO, goal, [], field, astar_ladder_m=bad)


def test_a_drone_in_front_of_a_refused_gap_is_rescued_by_the_way_around(
    ladders: list[tuple[tuple[float, ...], float]],
) -> None:
    """A hovering drone 0.15 m short of a gap it may not plan through (every plan enters the
    unobserved gap within the first second); A* at the check's distance only offers that gap.
    The old two-step fallback keeps the hover, replan after replan (158 kept hovers in mapped
    forest-medium seed 3); the rescue, tried before keeping it, flies the wide gap."""
    world = _wall(0.3, False)
    field = _gap_unobserved(world)
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    hover = Trajectory.hover(start, 0.0, 3.0)

    def plan(levels: tuple[float, ...], previous: Trajectory | None) -> PlanResult:
        params = _params(v_max_m_s=1.0, astar_clearances_m=levels)
        planner = FormationPlanner(params, LINE3, slot=1)
        res = planner.plan(0.0, start, ZERO, ZERO, goal, [], field, previous)
        if res.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION):
            assert planner.check(res.trajectory, 0.0, field, [])[0]
        return res

    res = plan(RESCUE, hover)
    assert res.status == PlanStatus.OK_NO_FORMATION, res.message
    # the formation attempt (from the hover) and the A* retry were refused for the gap; only
    # then the rescue searched the intermediate levels, and found the wide gap at 0.4 m
    assert res.message.count("enters unobserved space") == 2
    assert res.message.endswith("a* rescue: path at 0.40 m")
    counts = dict.fromkeys(REFUSAL_KEYS, 0)
    count_refusals(res.message, counts)
    assert counts["attempts"] == counts["unobserved"] == 2  # the accepted rescue is no refusal
    assert [ladder for ladder, _ in ladders] == [TWO_STEP, RESCUE]
    assert [found for _, found in ladders] == [0.22, 0.4]
    y, clearance = _crossing(res, world)
    assert y == pytest.approx(2.2, abs=0.25)  # through the wide gap
    assert clearance >= 0.35
    # the two-step fallback alone keeps the hover (the check accepts it), or stops without it
    ladders.clear()
    assert plan((), hover).status == PlanStatus.KEPT_PREVIOUS
    assert plan((), None).status == PlanStatus.EMERGENCY
    assert [ladder for ladder, _ in ladders] == [TWO_STEP, TWO_STEP]  # the two A* retries
    # without a previous trajectory the rescue still comes before the stop
    assert plan(RESCUE, None).status == PlanStatus.OK_NO_FORMATION


@pytest.mark.parametrize("approach", [False, True])
def test_a_refused_rescue_keeps_the_hover_and_counts_as_a_refusal(
    ladders: list[tuple[tuple[float, ...], float]], monkeypatch: Any, approach: bool
) -> None:
    """The narrow gap unobserved and a peer hovering in the wide one: the rescue's plan through
    the wide gap is refused too; the message names the three refused attempts, as the
    simulator counts them. The peer lies more than ``APPROACH_S`` ahead, so the drone flies
    the rescue's way toward it and looks again (``APPROACH``, no refusal more); were it nearer
    (``APPROACH_S`` longer than the way), the hover would be kept."""
    if not approach:
        monkeypatch.setattr(planner_module, "APPROACH_S", 1e3)
    field = _gap_unobserved(_wall(0.3, False))
    peers = [PeerTrajectory(7, 0, Trajectory.hover(np.array([4.0, 2.2, 1.0]), 0.0, 30.0))]
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    hover = Trajectory.hover(start, 0.0, 3.0)
    # the ladder alone: no A* retry with the formation term before the one without
    params = _params(v_max_m_s=1.0, astar_keeps_formation=False)
    planner = FormationPlanner(params, LINE3, slot=1)
    res = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, hover)
    if approach:
        assert res.status == PlanStatus.OK_NO_FORMATION, res.message
        assert res.message.endswith(APPROACH), res.message
        ok, why = planner.check(res.trajectory.until(APPROACH_S), 0.0, field, peers)
        assert ok and not why
        assert not planner.check(res.trajectory, 0.0, field, peers)[0]
    else:
        assert res.status == PlanStatus.KEPT_PREVIOUS, res.message
        assert res.trajectory is hover
    assert [ladder for ladder, _ in ladders] == [TWO_STEP, RESCUE]
    assert "a* retry at the rescue levels without formation: drone 7 at" in res.message
    counts = dict.fromkeys(REFUSAL_KEYS, 0)
    count_refusals(res.message, counts)
    assert (counts["attempts"], counts["unobserved"], counts["drone"]) == (3, 2, 1)


def _line(a: np.ndarray, b: np.ndarray, t0_s: float, duration_s: float) -> Trajectory:
    """One MINCO piece from rest at a to rest at b."""
    m = Minco(1)
    m.set_conditions(np.stack([a, ZERO, ZERO]), np.stack([b, ZERO, ZERO]))
    m.set_parameters(np.zeros((0, 3)), np.array([duration_s]))
    return Trajectory(t0_s, m.coeffs, np.array([duration_s]))


def test_a_previous_trajectory_that_still_moves_is_kept_before_the_rescue(
    ladders: list[tuple[tuple[float, ...], float]],
) -> None:
    """A peer hovers in the narrow gap (true distances): every plan through it is refused and
    A* at the check's distance only offers that gap. A safe previous trajectory that still
    takes the drone somewhere (1 m back) is kept, as before the rescue existed, and no rescue
    path is searched; a hover (or none) is not kept before the rescue, which flies the wide
    gap."""
    world = _wall(0.3, False)
    field = AnalyticField(world)
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    peers = [PeerTrajectory(7, 0, Trajectory.hover(np.array([4.3, 0.0, 1.0]), 0.0, 30.0))]
    back = _line(start, np.array([2.5, 0.0, 1.0]), 0.0, 4.0)
    assert np.linalg.norm(back.end_position - start) >= KEEP_MOVING_M
    # the default first retries from A* with the formation term (one more refused attempt,
    # the same search), then without it, and keeps the trajectory that still moves
    default = FormationPlanner(_params(v_max_m_s=1.0), LINE3, slot=1)
    res = default.plan(0.0, start, ZERO, ZERO, goal, peers, field, back)
    assert res.status == PlanStatus.KEPT_PREVIOUS and res.trajectory is back
    assert res.message.count("drone 7 at") == 3 and "rescue" not in res.message
    assert "a* retry: drone 7" in res.message and "a* retry without formation" in res.message
    ladders.clear()
    # the ladder alone
    params = _params(v_max_m_s=1.0, astar_keeps_formation=False)
    planner = FormationPlanner(params, LINE3, slot=1)
    res = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back)
    assert res.status == PlanStatus.KEPT_PREVIOUS
    assert res.trajectory is back
    assert res.message.count("drone 7 at") == 2 and "rescue" not in res.message
    assert ladders == [(TWO_STEP, 0.22)]
    for previous in (Trajectory.hover(start, 0.0, 3.0), None):
        ladders.clear()
        res = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, previous)
        assert res.status == PlanStatus.OK_NO_FORMATION, res.message
        assert [ladder for ladder, _ in ladders] == [TWO_STEP, RESCUE]
        assert planner.check(res.trajectory, 0.0, field, peers)[0]
        y, clearance = _crossing(res, world)
        assert y == pytest.approx(2.2, abs=0.25)
        assert clearance >= 0.35


def test_an_ordinary_replan_never_searches_the_intermediate_levels(
    ladders: list[tuple[tuple[float, ...], float]],
) -> None:
    """A trunk on the straight way, then the wall with a 0.5 m gap ahead (0.25 m from each
    trunk, the check allows 0.22 m) and a 1.0 m gap aside. A* at 0.6 m finds no way; at the
    check's distance it takes the narrow gap, and the plan through it is accepted: the
    intermediate levels (which would take the wide gap) are not searched, and the plan is bit
    for bit the one without them."""
    world = _wall(0.25, True)
    field = AnalyticField(world)
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([8.0, 0.0, 1.0])

    def plan(levels: tuple[float, ...]) -> PlanResult:
        params = _params(v_max_m_s=1.0, astar_clearances_m=levels)
        return FormationPlanner(params, LINE3, slot=1).plan(0.0, start, ZERO, ZERO, goal, [], field)

    res = plan(RESCUE)
    assert res.status == PlanStatus.OK, res.message
    assert ladders == [(TWO_STEP, 0.22)]  # the first attempt's A* guess (the line is blocked)
    y, clearance = _crossing(res, world)
    assert y == pytest.approx(0.0, abs=0.2)  # through the narrow gap
    assert 0.22 <= clearance < 0.3
    old = plan(())
    assert old.status == res.status
    np.testing.assert_array_equal(old.trajectory.coeffs, res.trajectory.coeffs)
    np.testing.assert_array_equal(old.trajectory.durations_s, res.trajectory.durations_s)
    assert (old.iterations, old.evaluations) == (res.iterations, res.evaluations)


def test_no_rescue_when_the_a_star_path_kept_the_optimisers_clearance(
    ladders: list[tuple[tuple[float, ...], float]],
) -> None:
    """Every plan is refused for unobserved space 0.1 m ahead, but the A* path keeps the full
    0.6 m (open space): the intermediate levels would offer nothing roomier, so no rescue."""
    exact = AnalyticField(World.empty(0.0))
    grid = GridField.from_function(exact.distance, [-2.0, -2.0, 0.0], [8.0, 2.0, 2.0], 0.1)
    field = GridField(grid.values, grid.origin, grid.res, known=grid.cell_centres()[..., 0] < 0.1)
    planner = FormationPlanner(_params(v_max_m_s=1.0), LINE3, slot=1)
    res = planner.plan(0.0, np.array([0.0, 0, 1]), ZERO, ZERO, np.array([6.0, 0, 1]), [], field)
    assert res.status == PlanStatus.EMERGENCY
    assert "rescue" not in res.message
    assert ladders == [(TWO_STEP, 0.6)]


def test_a_canceled_replan_makes_no_rescue_attempt(
    ladders: list[tuple[tuple[float, ...], float]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The rescue scenario with the A* retry's solve canceled (as ``cancel()`` from another
    thread does): the replan ends there, keeping the hover, and searches no rescue path."""
    field = _gap_unobserved(_wall(0.3, False))
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    solve = Problem.solve
    calls = [0]

    def cancel_second(
        self: Problem,
        x_start: np.ndarray | None = None,
        lb_prm: np.ndarray | None = None,
        prob: tuple | None = None,
    ) -> tuple[np.ndarray, LbfgsStatus]:
        calls[0] += 1
        if calls[0] == 3:  # 1: formation, 2: its refinement, 3: the A* retry
            self.cancel_flag[0] = 1
        return solve(self, x_start, lb_prm, prob)

    monkeypatch.setattr(Problem, "solve", cancel_second)
    planner = FormationPlanner(_params(v_max_m_s=1.0), LINE3, slot=1)
    hover = Trajectory.hover(start, 0.0, 3.0)
    res = planner.plan(0.0, start, ZERO, ZERO, goal, [], field, hover)
    assert res.status == PlanStatus.KEPT_PREVIOUS
    assert res.solver_status == LbfgsStatus.CANCELED
    assert res.message.endswith("canceled")
    assert calls[0] == 3
    assert [ladder for ladder, _ in ladders] == [TWO_STEP]


def _peer_in_the_gap() -> tuple[
    AnalyticField, np.ndarray, np.ndarray, list[PeerTrajectory], Trajectory, FormationPlanner
]:
    """The scenario of the budget tests: a peer hovers in the narrow gap of a wall, so every
    plan through it is refused; the previous trajectory backs away and still moves. (field,
    start, goal, peers, previous, planner)."""
    field = AnalyticField(_wall(0.3, False))
    start, goal = np.array([3.5, 0.0, 1.0]), np.array([9.0, 0.0, 1.0])
    peers = [PeerTrajectory(7, 0, Trajectory.hover(np.array([4.3, 0.0, 1.0]), 0.0, 30.0))]
    back = _line(start, np.array([2.5, 0.0, 1.0]), 0.0, 4.0)
    planner = FormationPlanner(_params(v_max_m_s=1.0), LINE3, slot=1)
    return field, start, goal, peers, back, planner


def test_a_replan_over_its_time_budget_keeps_the_safe_previous_and_tries_no_more(
    ladders: list[tuple[tuple[float, ...], float]],
) -> None:
    """The scenario above (a peer hovers in the narrow gap, every plan through it is refused).
    With ``give_up`` saying the budget is spent, the replan stops after its first attempt and
    keeps the previous trajectory that still moves (status 'over-budget'), without the A*
    retries; a previous that holds the drone where it is (or none) is no reason to stop, and the
    attempts go on to the rescue as without a budget. A budget never spent changes nothing."""
    field, start, goal, peers, back, planner = _peer_in_the_gap()
    full = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back)
    assert full.status == PlanStatus.KEPT_PREVIOUS and full.message.count("drone 7 at") == 3
    asked = [0]

    def spent() -> bool:
        asked[0] += 1
        return True

    ladders.clear()
    res = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back, give_up=spent)
    assert res.status == PlanStatus.OVER_BUDGET and res.trajectory is back
    assert res.message.count("drone 7 at") == 1 and "a* retry" not in res.message
    assert asked[0] == 1
    assert ladders == []  # the first attempt's guess is the straight line: no A* search
    assert 0 < res.evaluations < full.evaluations
    for previous in (Trajectory.hover(start, 0.0, 3.0), None):
        plain = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, previous)
        spent_res = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, previous, spent)
        assert plain.status == spent_res.status == PlanStatus.OK_NO_FORMATION
        np.testing.assert_array_equal(plain.trajectory.coeffs, spent_res.trajectory.coeffs)
    never = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back, lambda: False)
    assert (never.status, never.message, never.evaluations) == (
        full.status,
        full.message,
        full.evaluations,
    )


def test_the_replan_after_one_over_its_budget_goes_on_with_the_attempts_it_gave_up() -> None:
    """The scenario above. A replan that gave up at its budget says which attempt it gave up
    (``resume_at``); the next one, started there (``first_attempt``), runs that attempt first
    (its message says so) and not those already refused, which on a starved CPU would spend
    the budget again on the same refusals. Chained, the replans walk the whole sequence of
    attempts, each trying one; the last starts no budget question and goes on to the rescue.
    Started at 0, a replan is the usual one; past the end, at the last attempt."""
    field, start, goal, peers, back, planner = _peer_in_the_gap()
    full = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back)
    assert full.resume_at == 0
    labels = [part.split(":")[0] for part in full.message.split("; ") if "drone 7 at" in part]
    assert len(labels) >= 3  # every optimised attempt refused by the peer
    resumed: list[int] = []
    first = 0
    while True:
        res = planner.plan(
            0.0, start, ZERO, ZERO, goal, peers, field, back, lambda: True, first_attempt=first
        )
        if res.status is not PlanStatus.OVER_BUDGET:
            break
        assert res.trajectory is back
        assert res.message.count("drone 7 at") == 1  # one attempt, then the budget
        assert res.resume_at == first + 1
        if first > 0:
            assert res.message.startswith(f"resumed at {labels[first]}; {labels[first]}:")
        resumed.append(first)
        first = res.resume_at
    assert resumed == list(range(len(labels) - 1))
    # the last attempt asks no budget question: the rescue and the rest follow as without one
    assert res.status == full.status == PlanStatus.KEPT_PREVIOUS
    assert res.message.startswith(f"resumed at {labels[-1]}; {labels[-1]}:")
    assert res.message.endswith(full.message.split("; ", len(labels))[-1])
    assert res.resume_at == 0
    again = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back, first_attempt=0)
    assert (again.status, again.message) == (full.status, full.message)
    past = planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back, first_attempt=99)
    assert (past.status, past.message) == (res.status, res.message)
    for bad in (-1, 1.0, True, None):
        with pytest.raises(ValueError, match="first_attempt"):
            planner.plan(0.0, start, ZERO, ZERO, goal, peers, field, back, first_attempt=bad)


@pytest.mark.parametrize("see_still", [True, False])
def test_the_a_star_path_leads_around_peers_out_of_the_formation_that_hold_still(
    monkeypatch: Any, see_still: bool
) -> None:
    """Where a killed peer may have stopped (hovers 0.23 m apart along its last trajectory,
    avoided only), 0.6 m from a trunk: no way passes between them. The A* search used to lead
    straight through the hovers, which it does not know, and every plan was refused; a drone
    behind them held still for 35 s (bench faults seed 1000, trial 45). The hovers are
    obstacles to the search now, and the plan goes around them (``see_still`` False: the old
    search, which holds the drone)."""
    if not see_still:
        monkeypatch.setattr(planner_module, "_still_peers", lambda peers, t: np.zeros((0, 3)))
    world = World(
        cylinders=np.array([[15.65, -0.62, 0.32, 0.0, 3.0]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
        ground_z=0.0,
    )
    field = AnalyticField(world)
    ghosts = np.linspace([15.75, 0.29, 1.0], [16.66, 0.51, 1.0], 5)
    t0 = 28.7
    peers = [
        PeerTrajectory(0, 3 + k, Trajectory.hover(q, t0 - 0.1, 3600.0))
        for k, q in enumerate(ghosts)
    ]
    n = LINE3.shape[0]
    formation = np.vstack([LINE3, np.zeros((len(ghosts), 3))])
    mask = np.zeros((n + len(ghosts),) * 2)
    mask[:n, :n] = 1.0 - np.eye(n)
    params = PlannerParams(v_max_m_s=1.0)
    planner = FormationPlanner(params, formation, 1, edge_mask=mask)
    start = np.array([14.97, -0.1, 1.0])
    hover = Trajectory.hover(start, t0 - 1.0, 3.0)
    res = planner.plan(t0, start, ZERO, ZERO, np.array([24.4, -0.72, 1.0]), peers, field, hover)
    if not see_still:
        assert res.status == PlanStatus.KEPT_PREVIOUS, res.message
        return
    assert res.status in (PlanStatus.OK, PlanStatus.OK_NO_FORMATION), res.message
    assert planner.check(res.trajectory, t0, field, peers) == (True, "")
    # around the hovers or around the trunk, not between them
    pts = res.trajectory.sample(np.linspace(t0, res.trajectory.t_end_s, 400))
    beside = pts[(pts[:, 0] > 15.75) & (pts[:, 0] < 16.66)]
    above = beside[:, 1] > 0.29 + params.check_drone_m
    below = beside[:, 1] < -0.62 - 0.32 - params.check_obstacle_m
    assert beside.shape[0] and (np.all(above) or np.all(below))
