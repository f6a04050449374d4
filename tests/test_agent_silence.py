"""DroneAgent's quiet and silent peers (issue #12): a healthy peer under bus faults is at most
quiet (avoided at its ghosts for a moment, still in the formation), never silent; a killed one
is quiet ``peer_silence_s`` and silent at most ``peer_silence_max_s`` after its last message;
a quiet peer asks for a replan only when its ghosts lie on our path."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from onboard.agent import (
    PEER_SILENCE_IN_WAY_S,
    PEER_SILENCE_MAX_S,
    SPELL_FACTOR,
    SPELL_MARGIN_S,
    DroneAgent,
    StaticMap,
    same_peers,
)
from onboard.comm import InMemoryBus, TrajectoryMsg
from onboard.comm.faults import BusFaults, FaultyBus
from onboard.planner.field import AnalyticField
from onboard.planner.params import PlannerParams
from onboard.planner.trajectory import Trajectory
from onboard.world import World

TRIANGLE = np.array([[0.0, 0.0, 0.0], [-1.0, 1.5, 0.0], [-1.0, -1.5, 0.0]])
PARAMS = PlannerParams(v_max_m_s=1.0)
EMPTY = StaticMap(AnalyticField(World.empty(0.0)))
PERIOD = 0.1  # states and looks, as in the simulator and the service


def _agent(bus: InMemoryBus, goal: np.ndarray | None, **kw: object) -> DroneAgent:
    return DroneAgent(
        0,
        PARAMS,
        TRIANGLE,
        0,
        Trajectory.hover(np.array([0.0, 0.0, 1.0]), 0.0),
        bus,
        EMPTY,
        goal=goal,
        validity_s=3.0,
        peer_silence_s=0.5,
        **kw,  # type: ignore[arg-type]
    )


def _line(p0: np.ndarray, v: np.ndarray, t0: float, duration: float = 600.0) -> Trajectory:
    c = np.zeros((1, 6, 3))
    c[0, 0] = p0
    c[0, 1] = v
    return Trajectory(t0, c, np.array([duration]))


@dataclass(frozen=True)
class _State:
    drone_id: int
    stamp_s: float
    position: np.ndarray


class _StateChannel:
    """The inner bus of the states: each receiver gets every sender's newest state by stamp."""

    def __init__(self) -> None:
        self.newest: dict[int, _State] = {}

    def publish(self, msg: _State, now_s: float) -> None:
        old = self.newest.get(msg.drone_id)
        if old is None or msg.stamp_s > old.stamp_s:
            self.newest[msg.drone_id] = msg

    def receive(self, drone_id: int, now_s: float) -> dict[int, _State]:
        return {s: m for s, m in self.newest.items() if s != drone_id}


def test_a_live_peer_under_bus_faults_is_never_silent_a_dead_one_is_within_the_bound() -> None:
    """Peer 1 sends its state every 0.1 s through 20 % loss, delays up to 300 ms, 20 %
    duplication and 10 % held back 1.5 s; we look every 0.1 s. For 400 s it is often older
    than peer_silence_s (the old rule's silence; here quiet) but never silent. Then it dies:
    quiet peer_silence_s after its last state was sent, silent at most peer_silence_max_s
    after it (one look later at most)."""
    bus = InMemoryBus()
    a = _agent(bus, None)
    v = np.array([1.0, 0.0, 0.0])
    traj = _line(np.array([0.0, 3.0, 1.0]), v, 0.0)
    bus.publish(TrajectoryMsg(1, 0, 1, traj, valid_until_s=math.inf), 0.0)
    faults = BusFaults(loss=0.2, delay_max_s=0.3, duplicate=0.2, reorder=0.1)
    states: Any = FaultyBus(_StateChannel(), faults, seed=3, gate=False)  # type: ignore[arg-type]
    t_kill = 400.0
    quiet_looks = silent_looks = 0
    last_sent = -math.inf
    first_quiet = first_silent = math.inf
    for k in range(int((t_kill + 3.0) / PERIOD)):
        t = round(k * PERIOD, 9)
        if t <= t_kill:
            states.publish(_State(1, t, traj.sample(t)), t)
            last_sent = t
        for pid, st in states.receive(0, t).items():
            a.heard(pid, st.stamp_s, st.position)
        view = a.peer_view(t)
        if t <= t_kill:
            quiet_looks += 1 in view.quiet
            silent_looks += 1 in view.silent
        else:
            if 1 in view.quiet or 1 in view.silent:
                first_quiet = min(first_quiet, t)
            if 1 in view.silent:
                first_silent = min(first_silent, t)
    assert silent_looks == 0
    assert quiet_looks > 20  # the faults bite: the 0.5 s rule alone would have fired
    assert t_kill < first_quiet <= last_sent + 0.5 + PERIOD + 1e-9
    assert first_quiet < first_silent <= last_sent + PEER_SILENCE_MAX_S + PERIOD + 1e-9
    assert a.counters()["silent"] == 0


def test_the_silence_limit_follows_the_links_quiet_spells_within_its_bounds() -> None:
    """On a clean link the silence limit is peer_silence_s; after a look saw a peer's newest
    message 0.5 s old before it was heard again, spell_factor times that plus spell_margin_s
    (1.3 s); after a 5 s outage
    peer_silence_max_s; it falls back once the long spells are older than spell_window_s."""
    bus = InMemoryBus()
    a = _agent(bus, None, spell_window_s=10.0)
    p = np.array([0.0, 3.0, 1.0])
    bus.publish(TrajectoryMsg(1, 0, 1, Trajectory.hover(p, 0.0, 600.0), valid_until_s=3.0), 0.0)

    def talk(t0: float, t1: float) -> None:
        for k in range(int(round((t1 - t0) / PERIOD)) + 1):
            t = t0 + k * PERIOD
            a.heard(1, t, p)
            a.peer_view(t)

    talk(0.0, 2.0)
    assert a.silence_limit(1) == pytest.approx(0.5)
    a.peer_view(2.3)
    a.peer_view(2.5)  # its newest message is 0.5 s old
    talk(2.6, 4.0)  # heard again: a 0.5 s spell
    assert a.silence_limit(1) == pytest.approx(SPELL_FACTOR * 0.5 + SPELL_MARGIN_S)
    lim = a.silence_limit(1)
    for k in range(1, 50):  # unheard 5 s: silent once quiet longer than the limit
        view = a.peer_view(4.0 + k * PERIOD)
        assert (1 in view.silent) == (k * PERIOD > lim + 1e-9)
        assert (1 in view.quiet) == (0.5 + 1e-9 < k * PERIOD <= lim + 1e-9)
    talk(9.0, 10.0)
    assert a.silence_limit(1) == pytest.approx(PEER_SILENCE_MAX_S)
    talk(10.1, 19.0)
    assert a.silence_limit(1) == pytest.approx(PEER_SILENCE_MAX_S)
    talk(19.1, 20.5)  # the long spells (seen at 2.6 and 9.0) left the 10 s window
    assert a.silence_limit(1) == pytest.approx(0.5)
    # peer_silence_max_s = peer_silence_s: one fixed limit
    b = _agent(bus, None, peer_silence_max_s=0.5)
    b.heard(1, 0.0, p)
    b.peer_view(0.0)
    b.heard(1, 5.0, p)
    b.peer_view(5.0)
    assert b.silence_limit(1) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="peer_silence_max_s"):
        _agent(bus, None, peer_silence_max_s=0.0)
    with pytest.raises(ValueError, match="spell_factor"):
        _agent(bus, None, spell_factor=0.5)
    with pytest.raises(ValueError, match="spell_margin_s"):
        _agent(bus, None, spell_margin_s=-0.1)
    with pytest.raises(ValueError, match="spell_window_s"):
        _agent(bus, None, spell_window_s=math.inf)


def test_a_quiet_peer_stays_in_the_formation_and_asks_for_a_replan_only_in_our_way() -> None:
    """Peers 1 (3 m ahead in our lane) and 2 (3 m to the side) fly +x at 1 m/s like us and
    have had a 0.4 s quiet spell (peer 1, in our way, was quiet in it from 0.35 s on, when the
    link had had none); both go quiet after 0.7 s. Quiet (0.5 s later): only peer 1's
    ghosts lie on our path, so only it asks for a replan; the plan avoids both at their ghosts
    and keeps both in the formation. On this link (quiet spells of 0.4 s) a peer in our way is
    quiet no sooner than any other (0.4 + 0.15 s is past the quiet limit). Silent (limit
    1 * 0.4 + 0.4 = 0.8 s): both leave the formation and ask for a replan."""
    bus = InMemoryBus()
    me = np.array([0.0, 0.0, 1.0])
    v = np.array([1.0, 0.0, 0.0])
    a = _agent(
        bus,
        me + np.array([8.0, 0.0, 0.0]),
        spell_factor=1.0,
        spell_margin_s=0.4,
        peer_silence_in_way_s=0.35,  # off the looks' grid
    )
    a.reset(_line(me, v, 0.0, 8.0))
    p1 = np.array([3.0, 0.0, 1.0])
    p2 = np.array([-1.0, 3.0, 1.0])
    tr1, tr2 = _line(p1, v, 0.0), _line(p2, v, 0.0)
    bus.publish(TrajectoryMsg(1, 0, 1, tr1, valid_until_s=3.0), 0.0)
    bus.publish(TrajectoryMsg(2, 0, 2, tr2, valid_until_s=3.0), 0.0)
    a.request_replan(math.inf)  # the reset already counts as the current plan
    for k in range(8):
        t = round(k * PERIOD, 9)
        if k not in (2, 3, 4, 5):  # heard at 0.0, 0.1, 0.6, 0.7: seen 0.4 s old at 0.5
            a.heard(1, t, tr1.sample(t))
            a.heard(2, t, tr2.sample(t))
        if k == 5:  # the first long spell: peer 1 in our way is quiet at the in-the-way limit
            assert a.watch(t) == (1,) and a.replan(t).quiet_peers == (1,)
        else:
            assert a.watch(t) == ()
    assert a.silence_limit(1) == pytest.approx(0.8) and a.silence_limit(2) == pytest.approx(0.8)
    assert a.watch(1.2) == ()  # 0.5 s: not yet quiet
    assert a.watch(1.3) == (1,) and a.due(1.3)  # quiet, and in our way
    assert a.watch(1.4) == ()  # once per quiet spell
    rep = a.replan(1.3)
    assert rep.quiet_peers == (1, 2) and rep.silent_peers == ()
    assert rep.formation_peers == (1, 2) and rep.avoided_peers == ()
    ghosts = [q for q in rep.peers if q.slot >= 3]
    assert {q.drone_id for q in ghosts} == {1, 2} and rep.status.value.startswith("ok"), rep.message
    ts = np.arange(1.4, rep.trajectory.t_end_s, 0.05)
    for g in ghosts:
        d = np.linalg.norm(rep.trajectory.sample(ts) - g.trajectory.sample(5.0), axis=1)
        assert d.min() >= PARAMS.check_drone_m - 1e-6
    assert a.watch(1.5) == ()  # 0.8 s: not yet silent
    assert a.watch(1.6) == (1, 2)  # silent: out of the formation
    rep = a.replan(1.6)
    assert rep.silent_peers == (1, 2) and rep.quiet_peers == () and rep.formation_peers == ()
    c = a.counters()
    assert c["quiet"] == 2 and c["silent"] == 1 and c["in_the_way"] == 2


def test_a_peer_in_our_way_is_quiet_sooner_on_a_clean_link() -> None:
    """Peer 1 (3 m ahead in our lane, +x at 1 m/s) heard every 0.1 s (looks 0.05 s after each
    state) falls quiet in our way at the in-the-way limit (0.3 s), not the quiet limit
    (0.5 s), and asks for a replan once; peer 2 beside us (not in our way) is quiet only at the
    quiet limit (where, on a clean link, it is silent as well). Heard again, peer 1 is not
    quiet; its link has now had a 0.35 s spell, so the next spell in our way is quiet only at
    0.35 + 0.15 s, the quiet limit."""
    bus = InMemoryBus()
    me = np.array([0.0, 0.0, 1.0])
    v = np.array([1.0, 0.0, 0.0])
    a = _agent(bus, me + np.array([8.0, 0.0, 0.0]))
    a.reset(_line(me, v, 0.0, 8.0))
    tr1 = _line(np.array([3.0, 0.0, 1.0]), v, 0.0)
    tr2 = _line(np.array([0.0, 3.0, 1.0]), v, 0.0)
    bus.publish(TrajectoryMsg(1, 0, 1, tr1, valid_until_s=3.0), 0.0)
    bus.publish(TrajectoryMsg(2, 0, 2, tr2, valid_until_s=3.0), 0.0)
    a.request_replan(math.inf)
    for k in range(11):  # states at 0.0 ... 1.0, looks 0.05 s later
        t = round(k * PERIOD, 9)
        a.heard(1, t, tr1.sample(t))
        a.heard(2, t, tr2.sample(t))
        assert a.watch(t + 0.05) == ()
    a.reset(_line(me + 1.05 * v, v, 1.05, 6.95))
    assert PEER_SILENCE_IN_WAY_S == pytest.approx(0.3)
    assert a.watch(1.25) == ()  # 0.25 s
    assert a.watch(1.35) == (1,) and a.due(1.35)  # 0.35 s, in our way: quiet
    rep = a.replan(1.35)
    assert rep.quiet_peers == (1,) and rep.formation_peers == (1, 2)
    assert a.watch(1.45) == ()  # once per quiet spell
    assert a.replan(1.55).silent_peers == (1, 2)  # 0.55 s: both (on a clean link, silent)
    a.heard(1, 1.6, tr1.sample(1.6))
    a.heard(2, 1.6, tr2.sample(1.6))
    assert a.watch(1.65) == ()
    assert a.replan(1.65).quiet_peers == ()  # heard again
    a.reset(_line(me + 1.65 * v, v, 1.65, 6.35))  # back in the peer's lane
    assert a.watch(2.05) == ()  # 0.45 s, in our way, after a 0.35 s spell: not quiet yet
    assert a.watch(2.15) == (1,)  # 0.55 s: quiet


def _one_peer_ahead() -> tuple[InMemoryBus, DroneAgent, Trajectory]:
    """An agent (deviation limit 0.3 m) and peer 1, 3 m ahead flying +x at 1 m/s, whose
    trajectory (sent at 0) and state at 0 it has."""
    bus = InMemoryBus()
    a = _agent(bus, None, peer_deviation_m=0.3)
    tr1 = _line(np.array([3.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.0)
    bus.publish(TrajectoryMsg(1, 0, 1, tr1, valid_until_s=3.0), 0.0)
    a.heard(1, 0.0, tr1.sample(0.0))
    return bus, a, tr1


def test_the_peer_view_cache_never_serves_old_ghosts_or_positions() -> None:
    """``peer_view`` keeps each quiet peer's ghosts and each peer's deviation check while the
    messages they come from and the ghosts' time span stay the same. Through a quiet spell
    (the window still growing, then past its end), a peer heard again at another place, a new
    trajectory and a report off it, every view equals one computed without the caches."""
    bus, a, tr1 = _one_peer_ahead()
    v = np.array([1.0, 0.0, 0.0])
    looks = []
    for k in range(1, 70):
        t = round(k * 0.05, 9)
        if k == 20:  # heard again, 0.5 m off its trajectory
            a.heard(1, t, tr1.sample(t) + np.array([0.0, 0.5, 0.0]))
        if k == 30:  # a new trajectory from where it is
            tr2 = _line(tr1.sample(t) + np.array([0.0, 0.5, 0.0]), -v, t)
            bus.publish(TrajectoryMsg(1, 1, 1, tr2, valid_until_s=t + 3.0), t)
        if k == 35:  # heard off the new one
            a.heard(1, t, tr2.sample(t) + np.array([0.0, 0.0, 0.4]))
        view = a.peer_view(t)
        again = a.peer_view(t)  # from the caches
        a._ghost_cache.clear()
        a._deviation_cache.clear()
        fresh = a.peer_view(t)
        for got in (view, again):
            assert got.hover_ids == fresh.hover_ids and got.quiet == fresh.quiet
            np.testing.assert_array_equal(got.hover_points, fresh.hover_points)
        looks.append((view.quiet + view.silent, len(view.hover_ids), view.deviating))
    assert (1,) in {q for q, _, _ in looks} and (1,) in {d for _, _, d in looks}
    sizes = [n for q, n, _ in looks if q]
    assert len(set(sizes)) > 1  # the ghosts grew with the window, then stayed


def test_views_of_the_same_peers_are_told_apart_from_changed_ones() -> None:
    """``same_peers`` (the service keeps its view object while it holds): the same
    trajectories and hovers at another time are the same peers; a new trajectory, a peer
    fallen quiet (its ghosts) or off its trajectory are not."""
    bus, a, tr1 = _one_peer_ahead()
    v = np.array([1.0, 0.0, 0.0])
    v0 = a.peer_view(0.0)
    a.heard(1, 0.1, tr1.sample(0.1))  # on its trajectory: nothing changes
    v1 = a.peer_view(0.1)
    assert v1 is not v0 and same_peers(v0, v1) and same_peers(v1, v0)
    quiet = a.peer_view(0.7)  # nothing heard for 0.6 s: ghosts
    assert quiet.hover_ids and not same_peers(v1, quiet)
    a.heard(1, 0.8, tr1.sample(0.8) + np.array([0.0, 0.5, 0.0]))  # heard, off its path
    off = a.peer_view(0.8)
    assert off.deviating == (1,) and not same_peers(v1, off) and not same_peers(quiet, off)
    tr2 = _line(tr1.sample(0.9), v, 0.9)
    bus.publish(TrajectoryMsg(1, 1, 1, tr2, valid_until_s=3.9), 0.9)
    a.heard(1, 0.9, tr2.sample(0.9))
    new = a.peer_view(0.9)
    assert new.deviating == () and new.hover_ids == () and not same_peers(v1, new)


def test_a_quiet_peer_is_avoided_where_px4s_failsafe_carries_it_not_only_along_its_path() -> None:
    """Peer 1 flies toward us (+y at 1 m/s) on a path that turns away (4 m/s^2 along +x). If
    it died after its last message, PX4's offboard-loss failsafe carries it on in a straight
    line along the velocity it had, not along the turn (bench faults seed 1000 trial 61: a
    killed drone coasted into the drone whose path it was about to leave). Its ghosts must
    hold where the simulator's model of that failsafe brings it to rest, for a death up to
    two state periods after the last message (at 0.1 s steps); its path alone passes 0.3 m or
    more from there."""
    from gcs.fastsim import offboard_loss_trajectory

    bus = InMemoryBus()
    a = _agent(bus, None)
    c = np.zeros((1, 6, 3))
    c[0, 0] = [0.0, -2.0, 1.0]
    c[0, 1] = [0.0, 1.0, 0.0]
    c[0, 2] = [2.0, 0.0, 0.0]  # x = 2 t^2
    tr = Trajectory(0.0, c, np.array([600.0]))
    bus.publish(TrajectoryMsg(1, 0, 1, tr, valid_until_s=3.0), 0.0)
    a.heard(1, 0.0, tr.sample(0.0))
    first = a.peer_view(0.4)
    assert first.quiet + first.silent == () and first.hover_points.size == 0
    view = a.peer_view(0.6)
    assert view.quiet + view.silent == (1,)  # silent too: no quiet spells heard
    path = tr.sample(np.arange(0.0, 1.5, 0.01))
    for died in (0.0, 0.1, 0.2):
        fs = offboard_loss_trajectory(died, *tr.state(died), 1.0, 0.95, PARAMS.a_max_m_s2, 10.0)
        rest = fs.sample(fs.t_end_s)
        assert np.linalg.norm(fs.sample(fs.t_end_s - 5.0) - rest) < 1e-9  # at rest by then
        assert np.min(np.linalg.norm(path - rest, axis=1)) >= 0.3
        assert np.min(np.linalg.norm(view.hover_points - rest, axis=1)) < 0.05, died
