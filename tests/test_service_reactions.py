"""The flight service's logic with in-memory edges and a clock passed in: a nominal flight, and
every reaction, each tested by cutting its input."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from onboard.agent import DroneAgent, PlanReport
from onboard.config import merge_mappings
from onboard.planner.trajectory import Trajectory
from onboard.record import read_record
from onboard.service.config import default_config_path, load_onboard_config
from onboard.service.fakes import FakeAutopilot, FakeBus, FakeDepth, straight_trajectory
from onboard.service.planning import PortPeerBus, inside_box, peer_roles
from onboard.service.ports import PeerInfo
from onboard.service.sdnotify import Notifier
from onboard.service.service import FlightService
from onboard.service.state import FlightState, Goal, Land, Resume, SetFormation, Takeoff

S = FlightState
T0 = 1_700_000_000.0
POINTS = ((0.0, -1.5, 0.0), (0.0, 0.0, 0.0), (0.0, 1.5, 0.0))


class Clock:
    def __init__(self) -> None:
        self.t = T0

    def __call__(self) -> float:
        return self.t


moving = straight_trajectory


class Harness:
    """One service, its fake edges, and a loop that steps them all on the same clock."""

    def __init__(self, tmp_path: Path, depth: bool = True, **overrides: Any) -> None:
        self.clock = Clock()
        data = merge_mappings(
            {"record": {"directory": str(tmp_path)}, "planning": {"warm_up": False}},
            overrides,
        )
        self.cfg = load_onboard_config(default_config_path(), 1, overrides=data)
        self.ap = FakeAutopilot(self.clock)
        self.bus = FakeBus()
        self.bus.gcs_heard = self.clock.t
        self.depth = FakeDepth(self.clock, self.ap) if depth else None
        self.svc = FlightService(
            self.cfg, self.ap, self.bus, self.depth, clock=self.clock, notifier=Notifier({})
        )
        self.gcs = True
        self.monitor_results: list[str] = []
        self.reports: list[PlanReport] = []

    @property
    def state(self) -> FlightState:
        return self.svc.machine.state

    def step(self, n: int = 1, dt: float = 0.05) -> None:
        svc = self.svc
        for _ in range(n):
            self.clock.t += dt
            if self.gcs:
                self.bus.gcs_heard = self.clock.t
            self.ap.tick()
            if self.depth is not None:
                svc.depth_step()
            svc.main_step()
            while svc.actions_step(0.0):
                pass
            r = svc.monitor_step()
            if r:
                self.monitor_results.append(r)
            rep = svc.plan_step()  # the agent replans when due on its grid or when asked
            if rep is not None:
                self.reports.append(rep)

    def until(self, cond: Callable[[], bool], max_s: float, what: str) -> None:
        t_end = self.clock.t + max_s
        while not cond():
            assert self.clock.t < t_end, f"{what} not within {max_s} s (state {self.state})"
            self.step()

    def command(self, cmd: Any) -> tuple[bool, str]:
        cid = self.bus.send(cmd)
        self.step()
        return self.bus.ack_of(cid)

    def formation(self, epoch: int = 1) -> None:
        ok, why = self.command(SetFormation(epoch, self.clock.t, ((0, 0), (1, 1), (2, 2)), POINTS))
        assert ok, why

    def airborne(self) -> None:
        self.formation()
        ok, why = self.command(Takeoff())
        assert ok, why
        self.until(lambda: self.state is S.HOVER, 10.0, "hover after take-off")

    def fly_to(self, x: float, z: float = 1.0) -> np.ndarray:
        """Peers flying their slots alongside (``peers_along``), then the goal ``(x, 0, z)``,
        which must be accepted; returns the goal."""
        goal = np.array([x, 0.0, z])
        self.peers_along(goal)
        ok, why = self.command(Goal(tuple(goal)))
        assert ok, why
        return goal

    def peers_along(self, goal_center: np.ndarray, valid_for_s: float = 60.0) -> None:
        """Two peers flying their slots from the start formation to the goal formation."""
        start_center = np.array([0.0, 0.0, 1.0])
        c = np.mean(POINTS, axis=0)
        for pid in (0, 2):
            off = np.array(POINTS[pid]) - c
            traj = moving(start_center + off, goal_center + off, self.clock.t)
            self.bus.peer_infos[pid] = PeerInfo(
                pid, pid, 1, traj, self.clock.t + valid_for_s, self.clock.t
            )


def test_nominal_flight_takeoff_formation_goal_land_with_a_record(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    assert h.svc.link_up() and not h.ap.streaming
    h.airborne()
    assert h.ap.calls[:3] == ["stream", "offboard", "arm"]
    assert h.ap.position[2] == pytest.approx(1.0, abs=0.05)
    goal = h.fly_to(4.0)
    assert h.state is S.FORMATION_FLIGHT
    h.until(lambda: h.state is S.HOVER, 30.0, "arrival")
    assert np.linalg.norm(h.ap.position - goal) < h.cfg.planning.goal_tolerance_m
    assert h.bus.trajectories, "no trajectory published"
    assert all(slot == 1 and epoch == 1 for _, slot, epoch, _, _ in h.bus.trajectories)
    ok, why = h.command(Land())
    assert ok, why
    h.until(lambda: h.state is S.LANDED, 10.0, "landed")
    assert not h.ap.armed and not h.ap.streaming
    assert h.bus.states and h.bus.statuses
    assert h.bus.statuses[-1]["counters"]["service.replans"] >= 1
    files = list(tmp_path.glob("drone1-*.mcap"))
    assert len(files) == 1
    rec = read_record(files[0])
    targets = [t for _, _, t, _ in rec.transitions()]
    assert targets == ["takeoff", "hover", "formation-flight", "hover", "landing", "landed"]
    assert rec.messages("/setpoint") and rec.messages("/plan") and rec.messages("/state")
    assert {m["status"] for m in rec.messages("/plan")} <= {"ok", "ok-no-formation"}


def test_goal_outside_the_geofence_is_refused(tmp_path: Path) -> None:
    h = Harness(tmp_path, geofence={"min_enu_m": [-5, -5, 0], "max_enu_m": [5, 5, 3]})
    h.airborne()
    ok, why = h.command(Goal((4.9, 0.0, 1.0)))
    assert ok, why  # this drone's own goal (slot 1, the centre) is inside
    ok, why = h.command(Goal((0.0, 4.0, 1.0)))  # slot offset 0: inside; but checked per drone
    assert ok, why
    ok, why = h.command(Goal((6.0, 0.0, 1.0)))
    assert not ok and "geofence" in why


def test_plans_never_leave_the_geofence() -> None:
    from onboard.service.config import GeofenceSection

    box = GeofenceSection((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))
    inside = moving(np.array([0.0, 0, 1]), np.array([0.9, 0, 1]), 0.0)
    outside = moving(np.array([0.0, 0, 1]), np.array([1.5, 0, 1]), 0.0)
    assert inside_box(inside, 0.0, box)
    assert not inside_box(outside, 0.0, box)


def test_depth_lost_stops_and_hovers_then_continues(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.airborne()
    goal = h.fly_to(6.0)
    h.step(20)
    assert h.state is S.FORMATION_FLIGHT
    h.depth.on = False  # type: ignore[union-attr]
    t_cut = h.clock.t
    h.until(lambda: h.state is S.HOVER, 1.0, "hover after the depth cut")
    assert h.clock.t - t_cut == pytest.approx(0.5, abs=0.11)
    h.step(40)  # two seconds later: stopped where the braking ended
    x_stop = h.ap.position.copy()
    h.step(10)
    assert np.linalg.norm(h.ap.position - x_stop) < 1e-6
    assert h.state is S.HOVER and h.ap.streaming
    h.depth.on = True  # type: ignore[union-attr]
    h.until(lambda: h.state is S.FORMATION_FLIGHT, 1.0, "flight resumed")
    h.until(lambda: h.state is S.HOVER, 40.0, "arrival after the depth came back")
    assert np.linalg.norm(h.ap.position - goal) < h.cfg.planning.goal_tolerance_m


def test_a_stuttering_camera_holds_the_drone_instead_of_flipping_its_state(
    tmp_path: Path,
) -> None:
    """Frames with gaps just above the timeout: one stop, then hover (no flip at every frame)
    until frames come steadily for ``recover_s``; the stop itself stays bounded."""
    h = Harness(tmp_path)
    h.airborne()
    h.fly_to(6.0)
    h.step(20)
    assert h.state is S.FORMATION_FLIGHT
    states = []
    for _ in range(6):  # 0.1 s of frames, 0.6 s without: 6 gaps above the 0.5 s timeout
        h.depth.on = True  # type: ignore[union-attr]
        h.step(2)
        states.append(h.state)
        h.depth.on = False  # type: ignore[union-attr]
        for _ in range(12):
            h.step()
            states.append(h.state)
    assert states[-1] is S.HOVER
    first_hover = states.index(S.HOVER)
    assert first_hover * 0.05 <= 0.5 + 0.1 + 0.11  # stopped within the timeout of a gap
    assert all(s is S.HOVER for s in states[first_hover:]), "state flipped with the frames"
    h.depth.on = True  # type: ignore[union-attr,unused-ignore]
    t_back = h.clock.t
    h.until(lambda: h.state is S.FORMATION_FLIGHT, 2.0, "flight resumed")
    rc = h.cfg.reactions.depth_lost.recover_s
    assert h.clock.t - t_back == pytest.approx(rc, abs=0.16)


def test_autopilot_heartbeat_lost_stops_commanding_and_never_resumes_by_itself(
    tmp_path: Path,
) -> None:
    h = Harness(tmp_path, depth=False)
    h.airborne()
    h.ap.alive = False
    t_cut = h.clock.t
    h.until(lambda: h.state is S.LINK_LOST, 2.0, "link lost")
    assert h.clock.t - t_cut == pytest.approx(1.0, abs=0.11)
    assert not h.ap.streaming
    h.ap.alive = True
    h.step(40)
    assert h.state is S.LINK_LOST and not h.ap.streaming  # link back: still silent
    n_offboard = h.ap.calls.count("offboard")
    ok, why = h.command(Resume())
    assert ok, why
    assert h.state is S.HOVER and h.ap.streaming
    assert h.ap.calls.count("offboard") == n_offboard + 1


def test_pilot_switching_out_of_offboard_is_obeyed_at_once(tmp_path: Path) -> None:
    h = Harness(tmp_path, depth=False)
    h.airborne()
    h.fly_to(4.0)
    h.step(10)
    h.ap.mode = "POSCTL"  # the pilot's switch
    h.step(1)
    assert h.state is S.PILOT
    assert not h.ap.streaming
    n = len(h.ap.calls)
    h.step(40)
    assert h.ap.calls[n:] == []  # no stream, no mode request: the pilot keeps the vehicle
    ok, why = h.command(Land())
    assert not ok and "pilot" in why


@pytest.mark.parametrize("action", ["hover", "land"])
def test_gcs_lost_finishes_the_goal_then_hovers_or_lands(tmp_path: Path, action: str) -> None:
    h = Harness(tmp_path, depth=False, reactions={"gcs_lost": {"timeout_s": 1.0, "action": action}})
    h.airborne()
    goal = h.fly_to(3.0)
    h.gcs = False
    h.step(30)
    assert not h.svc.machine.gcs_ok
    assert h.state is S.FORMATION_FLIGHT  # the current goal is finished
    h.until(lambda: h.state is not S.FORMATION_FLIGHT, 30.0, "arrival")
    assert np.linalg.norm(h.ap.position - goal) < h.cfg.planning.goal_tolerance_m
    if action == "land":
        assert h.state is S.LANDING
        h.until(lambda: h.state is S.LANDED, 10.0, "landed")
    else:
        h.step(40)
        assert h.state is S.HOVER


def test_a_restarted_service_finds_its_vehicle_airborne_and_waits_for_resume(
    tmp_path: Path,
) -> None:
    """systemd restarted the service mid-flight: PX4's failsafe holds the vehicle. The service
    neither streams nor flies an old plan; resume takes it over where it is, then it rejoins."""
    h = Harness(tmp_path, depth=False)
    h.ap.armed, h.ap.mode = True, "AUTO.LOITER"
    h.ap.position[:] = (2.0, 1.0, 1.2)
    h.step(10)
    assert h.state is S.PILOT and "resume" in h.svc.machine.history[-1].reason
    assert not h.ap.streaming and "offboard" not in h.ap.calls
    h.formation()
    ok, why = h.command(Goal((5.0, 0.0, 1.0)))
    assert not ok and "resume" in why
    ok, why = h.command(Resume())
    assert ok, why
    h.step(10)
    assert h.state is S.HOVER and h.ap.streaming and h.ap.mode == "OFFBOARD"
    assert np.linalg.norm(h.ap.position - (2.0, 1.0, 1.2)) < 0.05  # held where it was
    h.fly_to(5.0, 1.2)
    h.until(lambda: h.state is S.FORMATION_FLIGHT, 5.0, "rejoined")


def test_a_clock_beyond_the_bound_stops_formation_flight_and_says_why(tmp_path: Path) -> None:
    """Offsets up to the bound are flown with; beyond it the drone hovers, refuses goals with
    the reason, and flies on once the clocks agree again."""
    h = Harness(tmp_path, depth=False)
    h.airborne()
    goal = h.fly_to(3.0)
    h.step(10)
    assert h.state is S.FORMATION_FLIGHT
    h.bus.clock_offsets_exceeded = {2: 0.12}
    h.step()
    assert h.state is S.HOVER
    assert h.svc.machine.history[-1].reason.startswith("refusing formation flight")
    ok, why = h.command(Goal(tuple(goal)))
    assert not ok and "clock offset to drone 2 is +0.120 s" in why and "0.050" in why
    h.step(20)
    assert h.state is S.HOVER and not h.ap.position[0] > 3.0
    assert "clock offset" in h.bus.statuses[-1]["message"]
    h.bus.clock_offsets_exceeded = {}
    h.step()
    assert h.state is S.FORMATION_FLIGHT  # the goal it had is flown on
    h.until(lambda: h.state is not S.FORMATION_FLIGHT, 30.0, "arrival")
    assert np.linalg.norm(h.ap.position - goal) < h.cfg.planning.goal_tolerance_m


def test_peer_silent_past_validity_leaves_the_formation_but_is_avoided_for_a_while() -> None:
    """The service's roles for silent peers, applied by the agent's cycle (the one the
    simulator runs): judged on the peers each plan was made against."""
    from onboard.planner.field import AnalyticField
    from onboard.world import World

    traj = Trajectory.hover(np.array([0.0, 1.5, 1.0]), T0, 100.0)
    bus = FakeBus()
    bus.peer_infos = {
        0: PeerInfo(0, 0, 1, traj, T0 + 2.0, T0),  # valid until T0 + 2
        2: PeerInfo(2, 2, 1, traj, T0 + 50.0, T0),
        3: PeerInfo(3, 1, 1, traj, T0 + 50.0, T0),  # claims our slot: avoided, not in formation
    }
    cfg = load_onboard_config(default_config_path(), 1)
    agent = DroneAgent(
        1,
        cfg.planner,
        POINTS,
        1,
        Trajectory.hover(np.array([0.0, 0.0, 1.0]), T0, 1.0),
        PortPeerBus(bus),
        lambda_map(AnalyticField(World.empty(0.0))),
        goal=(3.0, 0.0, 1.0),
        formation_epoch=1,
        validity_s=3.0,
        peer_forget_s=10.0,
    )

    def split(now: float) -> tuple[list[int], list[int], list[int]]:
        roles = peer_roles(bus.peers(), now, 1, validity_s=3.0, avoid_for_s=10.0)
        agent.set_peer_roles(roles.avoid_only, roles.ignore)
        rep = agent.replan(now)
        seen = {*rep.formation_peers, *rep.avoided_peers}
        assert {p.drone_id for p in rep.peers} == seen  # the plan was made against exactly these
        return (
            list(rep.formation_peers),
            list(rep.avoided_peers),
            sorted(set(bus.peer_infos) - seen),
        )

    assert split(T0 + 1.0) == ([0, 2], [3], [])
    assert split(T0 + 2.5) == ([2], [0, 3], [])  # 0 past its message's validity
    assert split(T0 + 3.5) == ([], [0, 2, 3], [])  # 2 silent past validity_s
    assert split(T0 + 13.5) == ([], [], [0, 2, 3])  # avoided no longer
    # what the agent published went out through the service's bus port, with its validity
    _, slot, epoch, _, valid_for = bus.trajectories[-1]
    assert (slot, epoch) == (1, 1) and valid_for == pytest.approx(3.0)


def lambda_map(field: Any) -> Any:
    from onboard.agent import StaticMap

    return StaticMap(field)


def test_silent_peer_drops_out_of_the_plans_formation(tmp_path: Path) -> None:
    h = Harness(tmp_path, depth=False, reactions={"peer_lost": {"validity_s": 1.0}})
    h.airborne()
    goal = np.array([4.0, 0.0, 1.0])
    h.peers_along(goal, valid_for_s=1.0)
    assert h.command(Goal(tuple(goal)))[0]
    h.step(5)
    rec = h.svc.recorder
    assert rec is not None
    rec.flush()
    h.step(40)  # the peers said nothing more: after 1 s they leave the formation
    h.svc._close_record()
    plans = read_record(next(tmp_path.glob("*.mcap"))).messages("/plan")
    assert plans[0]["n_peers"] == 2
    assert plans[-1]["n_peers"] == 0


def test_monitor_brakes_when_a_peer_will_cross_the_path(tmp_path: Path) -> None:
    h = Harness(tmp_path, depth=False)
    h.airborne()
    goal = np.array([8.0, 0.0, 1.0])
    assert h.command(Goal(tuple(goal)))[0]
    h.step(40)  # cruising
    flying = h.svc.flying(h.clock.t)
    assert flying is not None
    # a peer of another epoch flies across the path, through where this drone will be in 1.9 s
    cross = flying.sample(h.clock.t + 1.9)
    a, b = cross + [0.0, -3.0, 0.0], cross + [0.0, 3.0, 0.0]
    T = 6.0 * 1.875 / 4.0
    intruder = moving(a, b, h.clock.t + 1.9 - T / 2, speed=4.0)
    h.bus.peer_infos[7] = PeerInfo(7, 0, 9, intruder, h.clock.t + 30, h.clock.t)
    h.step(2)
    assert h.monitor_results, "the monitor saw nothing"
    assert h.monitor_results[0].startswith("replan")
    h.until(lambda: h.state is S.HOVER or h.svc.counters["monitor_brakes"] > 0, 3.0, "reaction")
    ts = np.arange(h.clock.t - 0.1, h.clock.t + 3.0, 0.05)
    d_before = np.linalg.norm(flying.sample(ts) - intruder.sample(ts), axis=1)
    assert d_before.min() < h.cfg.planner.check_drone_m  # without a reaction: a collision
    flown = h.svc.flying(h.clock.t)
    assert flown is not None
    d = np.linalg.norm(flown.sample(ts) - intruder.sample(ts), axis=1)
    assert d.min() > h.cfg.planner.check_drone_m


def test_takeoff_denied_returns_to_idle_and_stops_streaming(tmp_path: Path) -> None:
    h = Harness(tmp_path, depth=False)
    h.formation()
    h.ap.deny.add("arm")
    ok, _ = h.command(Takeoff())
    assert ok  # accepted; the autopilot then refuses to arm
    h.step(2)
    assert h.state is S.IDLE
    assert not h.ap.streaming
    assert "arming denied" in h.svc.machine.history[-1].reason


def test_goal_and_formation_take_effect_at_their_common_time_in_the_agent(
    tmp_path: Path,
) -> None:
    h = Harness(tmp_path, depth=False)
    h.airborne()
    assert h.svc.agent.formation_epoch == 1 and h.svc.agent.slot == 1
    # a new formation (this drone moves to slot 0) and a goal, both at common times ahead
    t_form = h.clock.t + 1.0
    ok, why = h.command(SetFormation(2, t_form, ((0, 1), (1, 0), (2, 2)), POINTS))
    assert ok, why
    t_goal = h.clock.t + 1.5
    ok, why = h.command(Goal((4.0, 0.0, 1.0), t_goal))
    assert ok, why
    n_reports = len(h.reports)
    h.until(lambda: h.clock.t >= t_form - 0.06, 2.0, "just before the formation time")
    assert h.svc.agent.formation_epoch == 1 and h.svc.agent.goal is None
    h.until(lambda: h.svc.agent.formation_epoch == 2, 0.2, "the formation at its time")
    assert h.svc.agent.slot == 0 and h.clock.t >= t_form
    assert h.state is S.HOVER and len(h.reports) == n_reports  # no goal yet: no replan
    h.until(lambda: h.state is S.FORMATION_FLIGHT, 1.0, "the goal at its time")
    assert h.clock.t >= t_goal
    h.step()
    first = h.reports[n_reports]
    assert first.planned_at_s >= t_goal  # the first plan to it is made at its time, not before
    assert (first.slot, first.formation_epoch) == (0, 2)
    # this drone's goal: the formation goal plus its slot's offset (slot 0: y - 1.5)
    assert np.allclose(first.goal, [4.0, -1.5, 1.0])
    h.until(lambda: h.state is S.HOVER, 30.0, "arrival")
    assert np.linalg.norm(h.ap.position - [4.0, -1.5, 1.0]) < h.cfg.planning.goal_tolerance_m
    # every trajectory message went out with the epoch in force when it was made
    epochs = [epoch for _, _, epoch, _, _ in h.bus.trajectories]
    assert epochs == sorted(epochs) and epochs[-1] == 2


def test_a_plan_made_while_the_service_overrides_never_replaces_the_override(
    tmp_path: Path,
) -> None:
    """The race between a replan (planner thread) and a braking stop (main loop), made
    deterministic: the override happens inside the agent's cycle, while it plans."""
    h = Harness(tmp_path, depth=False)
    h.airborne()
    assert h.command(Goal((6.0, 0.0, 1.0)))[0]
    h.step(20)
    assert h.state is S.FORMATION_FLIGHT
    svc = h.svc
    inner = svc.agent.map_source
    braked: list[Trajectory] = []

    class Interrupting:
        def snapshot(self, now_s: float, position: np.ndarray) -> Any:
            if not braked:
                svc._brake(now_s, None)  # what the main loop does on a hold, meanwhile
                braked.append(svc.agent.current)
            return inner.snapshot(now_s, position)

    svc.agent.map_source = Interrupting()  # type: ignore[assignment]
    svc.agent.request_replan()
    rep = svc.plan_step()
    assert rep is not None and braked
    assert svc.agent.current is braked[0] and not svc.agent.queued
    assert svc.flying(h.clock.t + 1.0) is braked[0]  # the new plan did not take over
    assert svc.counters["announcements"] >= 1
    _, _, _, announced, _ = h.bus.trajectories[-1]
    assert announced is braked[0]  # peers heard the braking stop last, not the plan
    svc.main_step()
    assert svc.counters["plans_superseded"] == 1


def test_hovering_drone_keeps_announcing_its_trajectory(tmp_path: Path) -> None:
    h = Harness(tmp_path, depth=False)
    h.airborne()
    h.step(2)
    n = len(h.bus.trajectories)
    h.step(100)  # 5 s of hover without a goal: no replan, but peers must keep seeing it
    assert not h.reports
    sent = h.bus.trajectories[n:]
    period = h.cfg.planning.replan_period_s
    assert len(sent) == pytest.approx(5.0 / period, abs=1)
    for _, slot, epoch, traj, valid_for in sent:
        assert (slot, epoch) == (1, 1)
        assert valid_for == pytest.approx(h.cfg.reactions.peer_lost.validity_s)
        assert np.allclose(traj.sample(h.clock.t), h.ap.position, atol=1e-6)


def test_a_plan_leaving_the_geofence_is_replaced_by_a_braking_stop(tmp_path: Path) -> None:
    """A trunk on the straight line and a geofence too narrow to pass it: the planner's detour
    would leave the box, so the service brakes and hovers instead."""
    from onboard.planner.field import AnalyticField
    from onboard.world import World

    box = {"min_enu_m": [-2.0, -0.35, 0.0], "max_enu_m": [8.0, 0.35, 3.0]}
    h = Harness(tmp_path, depth=False, geofence=box)
    world = World(np.array([[3.0, 0.0, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    h.svc._ground_field = AnalyticField(world)
    h.airborne()
    assert h.command(Goal((6.0, 0.0, 1.0)))[0]
    h.until(lambda: h.svc.counters["plans_failed"] > 0, 20.0, "a refused plan")
    assert h.state is S.HOVER  # hover, retry later
    lo, hi = np.array(box["min_enu_m"]), np.array(box["max_enu_m"])
    for _ in range(60):
        h.step()
        traj = h.svc.flying(h.clock.t)
        assert traj is not None
        p = traj.sample(np.linspace(h.clock.t, traj.t_end_s + 1.0, 50))
        assert np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9)
    h.svc._close_record()
    plans = read_record(next(tmp_path.glob("*.mcap"))).messages("/plan")
    assert any(m["status"] == "emergency" and "geofence" in m["reason"] for m in plans)
    assert np.all(h.ap.position >= lo) and np.all(h.ap.position <= hi)


def test_link_age_is_never_negative() -> None:
    """The link's receive thread can stamp a message just after its state read the clock: the
    age handed to the status message (which refuses a negative age) is clamped at 0."""
    from types import SimpleNamespace

    from onboard.service.adapters import AutopilotAdapter

    state = SimpleNamespace(connected=True, rx_age_s=-0.007)
    ap = AutopilotAdapter(SimpleNamespace(state=lambda: state))
    assert ap.link_age_s() == 0.0
    state.rx_age_s = 0.25
    assert ap.link_age_s() == 0.25
    state.connected = False
    assert ap.link_age_s() == math.inf
