"""The flight state machine: every transition, every rejection, with a clock passed in."""

from __future__ import annotations

import pytest

from onboard.service.state import (
    Abort,
    CommandResult,
    FlightState,
    FlightStateMachine,
    Goal,
    Land,
    MachineParams,
    Resume,
    SetFormation,
    Takeoff,
    Transition,
    Waypoints,
)

S = FlightState
POINTS = ((0.0, 0.0, 0.0), (0.0, 1.5, 0.0), (0.0, -1.5, 0.0))


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def formation(
    epoch: int = 1, at: float = 0.0, slots: tuple = ((0, 1), (1, 0), (2, 2))
) -> SetFormation:
    return SetFormation(epoch, at, slots, POINTS)


def make(**kw: object) -> tuple[FlightStateMachine, Clock, list[Transition]]:
    clock = Clock()
    seen: list[Transition] = []
    params = MachineParams(**kw)  # type: ignore[arg-type]
    m = FlightStateMachine(
        0,
        clock,
        params,
        inside_geofence=lambda p: abs(p[0]) <= 10 and abs(p[1]) <= 10 and 0 <= p[2] <= 3,
        listener=seen.append,
    )
    return m, clock, seen


def ok(r: CommandResult) -> None:
    assert r.accepted, r.reason


def rejected(r: CommandResult, words: str) -> None:
    assert not r.accepted
    assert words in r.reason


def airborne(m: FlightStateMachine) -> None:
    ok(m.command(formation()))
    ok(m.command(Takeoff()))
    m.set_on_ground(False)
    m.takeoff_reached()


def test_nominal_flight_and_every_transition_reported() -> None:
    m, clock, seen = make()
    assert m.state is S.IDLE and not m.commanding
    ok(m.command(formation()))
    assert m.slot() == 1
    ok(m.command(Takeoff(1.2)))
    assert m.state is S.TAKEOFF and m.commanding and m.takeoff_altitude_m == 1.2
    m.set_on_ground(False)
    m.takeoff_reached()
    assert m.state is S.HOVER
    ok(m.command(Goal((5.0, 0.0, 1.0))))
    assert m.state is S.FORMATION_FLIGHT and m.goal == (5.0, 0.0, 1.0)
    m.goal_reached()
    assert m.state is S.HOVER and m.goal is None
    ok(m.command(Land()))
    assert m.state is S.LANDING and not m.commanding
    clock.t += 3
    m.set_on_ground(True)
    assert m.state is S.LANDED
    path = [(t.source, t.target) for t in seen]
    assert path == [
        (S.IDLE, S.TAKEOFF),
        (S.TAKEOFF, S.HOVER),
        (S.HOVER, S.FORMATION_FLIGHT),
        (S.FORMATION_FLIGHT, S.HOVER),
        (S.HOVER, S.LANDING),
        (S.LANDING, S.LANDED),
    ]
    assert seen == m.history
    assert seen[-1].t_s == clock.t
    ok(m.command(Takeoff()))  # a second flight from LANDED


def test_waypoints_are_flown_in_order() -> None:
    m, _, _ = make()
    airborne(m)
    ok(m.command(Waypoints(((1.0, 0, 1), (2.0, 0, 1), (3.0, 0, 1)))))
    assert m.goal == (1.0, 0, 1)
    m.goal_reached()
    assert m.state is S.FORMATION_FLIGHT and m.goal == (2.0, 0, 1)
    m.goal_reached()
    m.goal_reached()
    assert m.state is S.HOVER and m.goal is None


@pytest.mark.parametrize(
    ("setup", "cmd", "words"),
    [
        ("idle", Goal((1.0, 0, 1)), "on the ground"),
        ("idle", Land(), "already on the ground"),
        ("idle", Abort(), "nothing to abort"),
        ("idle", Resume(), "nothing to resume"),
        ("takeoff", Takeoff(), "cannot take off"),
        ("takeoff", Goal((1.0, 0, 1)), "cannot take a goal in state takeoff"),
        ("hover", Goal((50.0, 0, 1)), "outside the geofence"),
        ("hover", Goal((float("nan"), 0, 1)), "finite"),
        ("hover", Waypoints(((1.0, 0, 1), (1.0, 0, 9))), "outside the geofence"),
        ("hover", Waypoints(()), "no waypoint"),
        ("landing", Land(), "already landing"),
        ("landing", Goal((1.0, 0, 1)), "cannot take a goal"),
        ("pilot", Land(), "pilot has control"),
        ("pilot", Goal((1.0, 0, 1)), "pilot has control"),
        ("pilot", Abort(), "pilot has control"),
        ("emergency", Abort(), "already in emergency"),
        ("emergency", Goal((1.0, 0, 1)), "cannot take a goal"),
    ],
)
def test_invalid_commands_are_rejected_with_a_reason(setup: str, cmd: object, words: str) -> None:
    m, _, _ = make()
    if setup != "idle":
        ok(m.command(formation()))
        ok(m.command(Takeoff()))
        m.set_on_ground(False)
    if setup in ("hover", "landing", "pilot", "emergency"):
        m.takeoff_reached()
    if setup == "landing":
        ok(m.command(Land()))
    if setup == "pilot":
        m.pilot_took_over("POSCTL")
    if setup == "emergency":
        ok(m.command(Abort()))
    before = m.state
    rejected(m.command(cmd), words)  # type: ignore[arg-type]
    assert m.state is before


def test_goal_needs_a_formation() -> None:
    m, _, _ = make()
    ok(m.command(Takeoff()))
    m.set_on_ground(False)
    m.takeoff_reached()
    rejected(m.command(Goal((1.0, 0, 1))), "no formation")


def test_formation_epochs_slots_and_effective_time() -> None:
    m, clock, _ = make()
    rejected(m.command(formation(slots=((1, 0), (2, 1)))), "has no slot")
    rejected(m.command(formation(slots=((0, 0), (1, 0)))), "slot is assigned twice")
    rejected(m.command(formation(slots=((0, 0), (0, 1)))), "drone is assigned twice")
    rejected(m.command(formation(slots=((0, 5),))), "out of range")
    ok(m.command(formation(epoch=3, at=clock.t + 2.0, slots=((0, 2), (1, 0)))))
    assert m.assignment is None and m.slot() is None  # not yet in force
    rejected(m.command(formation(epoch=3)), "stale formation epoch 3")
    rejected(m.command(formation(epoch=2)), "stale")
    clock.t += 2.0
    m.tick()
    assert m.assignment is not None and m.assignment.epoch == 3 and m.slot() == 2
    assert m.assignment.drone_of_slot() == {2: 0, 0: 1}
    ok(m.command(formation(epoch=4, slots=((0, 0), (1, 1)))))
    assert m.slot() == 0  # effective time in the past: at once


def test_goal_and_waypoints_take_effect_at_their_common_time() -> None:
    m, clock, seen = make()
    airborne(m)
    n = len(seen)
    ok(m.command(Goal((5.0, 0, 1), clock.t + 1.5)))  # checked and acknowledged now
    rejected(m.command(Goal((50.0, 0, 1), clock.t + 1.5)), "outside the geofence")
    rejected(m.command(Goal((1.0, 0, 1), float("nan"))), "effective time")
    assert m.state is S.HOVER and m.goal is None and len(seen) == n
    clock.t += 1.49
    m.tick()
    assert m.state is S.HOVER and m.goal is None  # not before its time
    clock.t += 0.01
    m.tick()
    assert m.state is S.FORMATION_FLIGHT and m.goal == (5.0, 0, 1)
    assert seen[-1].reason == "goal at its effective time" and seen[-1].t_s == clock.t
    # a later goal while flying: the current one is flown until the new one's time
    ok(m.command(Waypoints(((6.0, 0, 1), (7.0, 0, 1)), clock.t + 2.0)))
    assert m.goal == (5.0, 0, 1)
    m.goal_reached()  # arrival at the current goal keeps the pending one
    assert m.state is S.HOVER and m.pending_goals is not None
    clock.t += 2.0
    m.tick()
    assert m.state is S.FORMATION_FLIGHT and m.goal == (6.0, 0, 1)
    assert m.waypoints == [(7.0, 0, 1)]


@pytest.mark.parametrize("cut", ["land", "abort", "pilot", "link"])
def test_a_pending_goal_goes_with_the_current_one(cut: str) -> None:
    m, clock, _ = make()
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1), clock.t + 1.0)))
    if cut == "land":
        ok(m.command(Land()))
    elif cut == "abort":
        ok(m.command(Abort()))
    elif cut == "pilot":
        m.pilot_took_over("POSCTL")
    else:
        m.link_lost()
    state = m.state
    clock.t += 2.0
    m.tick()
    assert m.state is state and m.goal is None and m.pending_goals is None


def test_a_goal_pending_during_a_depth_hold_waits_for_the_frames() -> None:
    m, clock, _ = make()
    airborne(m)
    m.depth_lost()
    ok(m.command(Goal((5.0, 0, 1), clock.t + 1.0)))
    clock.t += 1.0
    m.tick()
    assert m.state is S.HOVER and m.paused and m.goal == (5.0, 0, 1)
    m.depth_restored()
    assert m.state is S.FORMATION_FLIGHT


def test_depth_loss_pauses_the_flight_until_frames_return() -> None:
    m, _, seen = make()
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    m.depth_lost()
    assert m.state is S.HOVER and m.paused and m.goal == (5.0, 0, 1)
    assert seen[-1].reason == "no depth frames"
    ok(m.command(Goal((6.0, 0, 1))))  # a new goal waits for the frames too
    assert m.state is S.HOVER and m.goal == (6.0, 0, 1)
    m.depth_restored()
    assert m.state is S.FORMATION_FLIGHT


def test_depth_loss_in_hover_keeps_a_new_goal_waiting() -> None:
    m, _, _ = make()
    airborne(m)
    m.depth_lost()
    ok(m.command(Goal((5.0, 0, 1))))
    assert m.state is S.HOVER
    m.depth_restored()
    assert m.state is S.FORMATION_FLIGHT


def test_kept_plans_fly_on_but_run_the_failure_clock() -> None:
    """A 'kept-previous' plan holds nothing (the kept trajectory flies on); kept plans for
    ``max_failed_s`` in a row are an EMERGENCY all the same, and a success resets the clock."""
    m, clock, _ = make(retry_after_s=1.0, max_failed_s=5.0)
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    m.plan_failed("kept-previous", hover=False)
    assert m.state is S.FORMATION_FLIGHT and not m.paused
    clock.t += 4.0
    m.plan_ok()
    m.plan_failed("kept-previous", hover=False)  # the first after the success starts the clock
    for _ in range(5):  # 4.995 s failing
        clock.t += 0.999
        m.plan_failed("kept-previous", hover=False)
        assert m.state is S.FORMATION_FLIGHT
    clock.t += 0.01
    m.plan_failed("kept-previous", hover=False)
    assert m.state is S.EMERGENCY and m.goal is None


def test_failed_plans_hover_then_retry_then_emergency_then_land() -> None:
    m, clock, _ = make(retry_after_s=1.0, max_failed_s=5.0, emergency_hover_s=4.0)
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    m.plan_failed("emergency")
    assert m.state is S.HOVER and m.paused
    clock.t += 0.5
    m.tick()
    assert m.state is S.HOVER
    clock.t += 0.6
    m.tick()
    assert m.state is S.FORMATION_FLIGHT  # retry
    m.plan_ok()  # a success resets the failure clock
    clock.t += 10.0
    m.plan_failed("emergency")
    assert m.state is S.HOVER
    for _ in range(5):
        clock.t += 1.01
        m.tick()
        assert m.state is S.FORMATION_FLIGHT
        m.plan_failed("emergency")
    assert m.state is S.EMERGENCY and m.commanding
    clock.t += 3.9
    m.tick()
    assert m.state is S.EMERGENCY
    clock.t += 0.2
    m.tick()
    assert m.state is S.LANDING
    m.set_on_ground(True)
    assert m.state is S.LANDED


def test_a_failed_plans_hover_is_cut_short_when_asked() -> None:
    """``retry_now`` (the monitor: a peer comes at the hover) retries a failed plan at once,
    not ``retry_after_s`` later; the failure clock runs on; no other hover is cut short."""
    m, clock, _ = make(retry_after_s=1.0, max_failed_s=5.0)
    airborne(m)
    assert not m.retry_now("nothing failed")  # the hover after take-off: no goal, no hold
    ok(m.command(Goal((5.0, 0, 1))))
    m.plan_failed("emergency")
    assert m.state is S.HOVER
    clock.t += 0.1
    assert m.retry_now("a peer comes at the hover")
    assert m.state is S.FORMATION_FLIGHT
    assert not m.retry_now("again")  # nothing held any more
    clock.t += 4.95  # 5.05 s failing in a row: the clock ran on through the early retry
    m.plan_failed("emergency")
    assert m.state is S.EMERGENCY
    assert not m.retry_now("an emergency is not a failed plan's hover")
    assert m.state is S.EMERGENCY


def test_abort_is_an_emergency_and_resume_clears_it() -> None:
    m, _, _ = make()
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    ok(m.command(Abort()))
    assert m.state is S.EMERGENCY and m.goal is None
    ok(m.command(Resume()))
    assert m.state is S.HOVER


def test_pilot_takeover_yields_at_once_and_only_resume_returns() -> None:
    m, _, _ = make()
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    m.pilot_took_over("POSCTL")
    assert m.state is S.PILOT and not m.commanding and m.goal is None
    m.tick()
    m.depth_restored()
    m.goal_reached()
    assert m.state is S.PILOT  # nothing but a command brings the service back
    ok(m.command(Resume()))
    assert m.state is S.HOVER and m.commanding


def test_pilot_landed_then_resume_waits_on_the_ground() -> None:
    m, _, _ = make()
    airborne(m)
    m.pilot_took_over()
    m.set_on_ground(True)
    assert m.state is S.PILOT
    ok(m.command(Resume()))
    assert m.state is S.IDLE


def test_pilot_takeover_on_the_ground_changes_nothing() -> None:
    m, _, seen = make()
    m.pilot_took_over()
    assert m.state is S.IDLE and not seen


def test_link_loss_stops_commanding_and_return_needs_a_command() -> None:
    m, _, _ = make()
    airborne(m)
    ok(m.command(Goal((5.0, 0, 1))))
    m.link_lost()
    assert m.state is S.LINK_LOST and not m.commanding
    rejected(m.command(Resume()), "link is down")
    rejected(m.command(Land()), "link lost")
    m.link_restored()
    m.tick()
    assert m.state is S.LINK_LOST and not m.commanding  # never re-enters by itself
    ok(m.command(Land()))
    assert m.state is S.LANDING


def test_link_loss_on_the_ground_blocks_takeoff() -> None:
    m, _, _ = make()
    m.link_lost()
    assert m.state is S.IDLE
    rejected(m.command(Takeoff()), "link is down")
    m.link_restored()
    ok(m.command(Takeoff()))


def test_takeoff_failure_returns_to_idle() -> None:
    m, _, _ = make()
    ok(m.command(Takeoff()))
    m.takeoff_failed("arming denied")
    assert m.state is S.IDLE and "arming denied" in m.history[-1].reason


@pytest.mark.parametrize("action", ["hover", "land"])
def test_gcs_loss_finishes_the_current_goal_then_hovers_or_lands(action: str) -> None:
    m, _, _ = make(gcs_lost_action=action)
    airborne(m)
    ok(m.command(Waypoints(((1.0, 0, 1), (2.0, 0, 1)))))
    m.gcs_lost()
    assert m.state is S.FORMATION_FLIGHT and m.goal == (1.0, 0, 1)  # current goal kept
    m.goal_reached()  # the next waypoint is dropped
    assert m.state is (S.HOVER if action == "hover" else S.LANDING)


def test_gcs_loss_while_hovering_with_land_policy_lands() -> None:
    m, _, _ = make(gcs_lost_action="land")
    airborne(m)
    m.gcs_lost()
    assert m.state is S.LANDING


def test_gcs_loss_with_hover_policy_keeps_hovering() -> None:
    m, clock, _ = make(gcs_lost_action="hover")
    airborne(m)
    m.gcs_lost()
    clock.t += 100
    m.tick()
    assert m.state is S.HOVER
    m.gcs_restored()
    ok(m.command(Goal((1.0, 0, 1))))


def test_bad_params_are_refused() -> None:
    with pytest.raises(ValueError, match="gcs_lost_action"):
        FlightStateMachine(0, Clock(), MachineParams(gcs_lost_action="rtl"))
