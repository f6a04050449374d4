"""One drone's replan cycle: the same class in the fast-time simulator and in the flight service.

A ``DroneAgent`` owns one drone's planner, its current and queued trajectories, its goal, its
formation template and slot, and the replan timing. One cycle at time ``now`` (``replan``):

1. map: ``map_source.snapshot(now, position)`` gives the distance field to plan on;
2. state: the trajectory in control at ``t_start = now + plan_ahead_s`` and its (p, v, a) there;
3. peers: the latest message of each peer from the bus (``PeerBus.receive``), sorted by id,
   split into formation peers and peers that are only avoided (see below);
4. plan: ``FormationPlanner.plan`` from that state, timed with ``timer`` (wall clock);
5. publish the result on the bus at ``now``, then schedule it to take control at ``t_start``;
6. the next replan is due one period later on the drone's own grid (or earlier on demand).

Time is always passed in (global seconds): the simulator passes its simulated clock, the flight
service the synchronised system clock. Nothing here sleeps or starts a thread.

Peers are *avoided* by the planner in every case; they are also in the *formation* term unless
the service excluded them (``set_peer_roles``), their message has expired (``valid_until_s``
passed; they are forgotten ``peer_forget_s`` later), they fly another formation epoch, their
slot lies outside the template, equals ours, or is claimed twice. Avoided-only peers take extra
template rows whose formation-graph edges are masked out (an isolated vertex adds nothing to
the similarity metric), so the formation among the others is unchanged.

Quiet and silent peers. A peer is *heard* at the sender's time of its newest message of any
kind: a new trajectory (``valid_until_s - validity_s``; the receive time when validity is
infinite) or a state message the owner passes to ``heard`` (10 Hz in the service and the
simulator). It is *quiet* when nothing newer was heard for ``peer_silence_s`` (plus one replan
period for a peer never heard through ``heard``, whose trajectories are its only sign of life),
or already for ``peer_silence_in_way_s`` (as much more; on a link whose quiet spells are
longer, their longest plus ``IN_WAY_SPELL_MARGIN_S``) when ``watch`` then finds its ghosts
(below) in our way, until it is heard again: a peer that dies as it crosses toward us comes on
along PX4's failsafe coast, and the 0.2 s gained are the room to evade it.
A quiet peer may have died (its autopilot then holds where it was: PX4's offboard-loss
failsafe) anywhere along its last trajectory after it was last heard: besides its last
trajectory, it is avoided as hovers ("ghosts") at points ``ghost_spacing_m`` apart along that
trajectory from where it was last heard to where it could have flown in ``ghost_window_s`` more
(its messages in between lost), at its last reported position, and along the straight line
PX4's failsafe carries a vehicle on from where it died (``_coast``: along the velocity it had,
which a turning trajectory leaves); ``watch`` asks for a replan
at once only if the trajectory we fly comes closer than ``check_drone_m`` to a ghost (it is in
our way). A quiet peer stays in the formation term until it is *silent*: quiet for longer than
its silence limit, the longest *quiet spell* it had in the last ``spell_window_s`` (the age of
its newest message at the last look before something newer arrived; looks: ``watch``, a replan,
``peer_view``) times ``spell_factor`` plus ``spell_margin_s``, at least the quiet limit and at
most ``peer_silence_max_s``. On a clean link (states and looks every 0.1 s: spells of 0.1 s)
quiet and silent coincide; under loss and delay a healthy peer's newest state is often older
than ``peer_silence_s`` (20 % loss and up to 300 ms delay: 1-3 % of looks), which then costs at
most ghosts avoided for a moment, while silence waits for what this link's spells say is
improbable. A killed peer is thus avoided where it may have stopped ``peer_silence_s`` after
its last message was sent and out of the formation at most ``peer_silence_max_s`` after it
(both one look later at most; one replan period more without states).

A peer whose last reported position is further than ``peer_deviation_m`` from its trajectory
(stuck or lagging, its new trajectory late), or would be ``peer_deviation_ahead_s`` later if
it and its trajectory went straight on at their velocities (it stopped or turned off it: a
brake or a plan whose copies were lost; a report from before its trajectory's start is
compared at that start, carried there, by position only), is also avoided as a hover there; with
``avoid_reported``, so is a peer heard through states without a trajectory considered.
``watch`` (called at the state rate) asks for a replan at once when a peer falls silent, falls
quiet in our way or leaves its trajectory; ``peer_view`` gives what a plan made now would avoid
(for a safety monitor between replans). A peer whose newest trajectory started more than
``validity_s`` ago (a stuck drone re-announcing its hover) leaves the formation term too. A
quiet peer's last trajectory is forgotten ``peer_forget_s`` after it fell quiet (or after its
message's validity, if earlier); its ghosts, where its vehicle may still hold,
``ghost_forget_s`` after it fell quiet. A trajectory with a lower ``traj_id`` than one already
received from the same peer (a late, reordered or duplicated copy) never replaces it.

Threads (flight service): ``flying``, ``state``, ``current``, ``queued`` and ``last`` read
immutable snapshots without locking and may be called from any thread (the 50 Hz setpoint
loop); ``advance``, ``schedule`` and ``reset`` lock; the setters (goal, formation, slot, peer
roles), ``heard``, ``watch``, ``peer_view``, ``request_replan`` and ``cancel`` may be called
from any thread; ``replan`` and ``step`` run one at a time (a second caller waits).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from onboard.comm.bus import PeerBus
from onboard.comm.messages import TrajectoryMsg
from onboard.planner.field import DistanceField
from onboard.planner.formation import complete_mask, similarity
from onboard.planner.kernels import BAND_MARGINAL, BAND_OK, band_state
from onboard.planner.params import (
    BRAKE_REFERENCE_S,
    PlannerParams,
    recover_params,
    reform_params,
    unheard_params,
)
from onboard.planner.planner import (
    FormationPlanner,
    PeerTrajectory,
    PlanStatus,
    SideExecutor,
)
from onboard.planner.trajectory import Trajectory, braking_distance_m

EPS_T = 1e-9
"""Times closer than this count as equal (a trajectory starting at t is in control at t)."""

REPLAN_PERIOD_S = 1.0
"""Seconds between a drone's replans, the paper's once a second: the default of the agent, of
the flight service (``planning.replan_period_s``) and of fast time (``SimConfig``)."""
PLAN_AHEAD_S = 0.1
"""A new plan starts this long after the replan that made it (its computing time): the same
three defaults."""

# The silent and stuck peer reaction as flown: the flight service's defaults
# (``reactions.peer_lost``) and the values of the fast-time fault trials (BENCHMARKS 9b). The
# agent's own arguments leave silence and deviation off (inf) unless they are passed.
PEER_SILENCE_S = 0.5
"""A peer heard of nothing newer for this long is quiet: avoided where it may have stopped."""
PEER_SILENCE_IN_WAY_S = 0.3
"""A peer heard of nothing newer for this long (but less than ``PEER_SILENCE_S``) is quiet
already if its ghosts lie in our way, on a link whose quiet spells allow it (``IN_WAY_SPELL_
MARGIN_S``): three state periods. A peer that dies while it crosses toward us comes on along
PX4's failsafe coast; at 0.9 m/s from 0.85 m the quiet limit's 0.2 s are the margin between
evading it and touching it (``bench faults --seed 1000``, trial 61)."""
IN_WAY_SPELL_MARGIN_S = 0.15
"""... but at least its longest recent quiet spell plus this: on a clean link (spells of one
look period plus the bus's delay, 0.15 s in fast time) the in-the-way limit holds; on a
delayed or lossy one (spells of 0.45-0.55 s with up to 300 ms of delay) a healthy peer in a
formation lane would be taken for quiet again and again, and the limit is the quiet one."""
PEER_SILENCE_MAX_S = 1.5
"""A quiet peer is silent (out of the formation) at the latest this long after its newest
message was sent (10 Hz states with 28 % of them missing: 12 in a row with p = 2e-7)."""
SPELL_FACTOR = 2.0
SPELL_MARGIN_S = 0.3
"""A peer is silent once quiet longer than ``SPELL_FACTOR`` times its longest recent quiet
spell plus ``SPELL_MARGIN_S`` (spells of one 0.1 s look period on a clean link: silent when
quiet, at ``PEER_SILENCE_S``; the factor because the longest of a few hundred spells
underestimates a lossy link's tail: with 20 % loss, k states in a row are lost with 0.2^k)."""
SPELL_WINDOW_S = 30.0
"""How far back a peer's quiet spells (how long it went unheard before it was heard again)
count."""
PEER_DEVIATION_M = 0.3
"""A peer reported further than this from its trajectory is also avoided where it reported."""
PEER_DEVIATION_AHEAD_S = 0.5
"""... and so is a peer that would be further than ``PEER_DEVIATION_M`` off its trajectory this
long later if both went straight on at their velocities (the reported one, the trajectory's):
a peer that stops off its plan from 0.5 m/s is found at once instead of 0.6 s later, when its
position has drifted 0.3 m from the plan (two drones 0.30 m apart, ``bench hidden
--outage-from 3`` seed 87: a brake whose three copies were lost, the peer behind closing at
0.8 m/s)."""
GHOST_WINDOW_S = 1.0
"""A quiet peer may have flown on this long after its newest message before it stopped: a
state period or two before it died, then PX4's offboard-loss failsafe, which keeps the last
setpoint for COM_OF_LOSS_T (1 s) and so carries the vehicle on about 0.65 s worth of its speed
(position gain MPC_XY_P 0.95: ``v (1 - exp(-0.95)) / 0.95``) before it brakes to a hold."""
OFFBOARD_LOSS_S = 1.0
"""PX4's COM_OF_LOSS_T (v1.16 default): how long its position controller keeps the last
setpoint (position and velocity feed-forward) once the stream stops, before the failsafe."""
PX4_POSITION_GAIN = 0.95
"""PX4's MPC_XY_P (v1.16 default, 1/s): over ``OFFBOARD_LOSS_S`` the vehicle carries on in a
straight line along the velocity it had, slowing: ``p + v (1 - exp(-k t)) / k``."""
COAST_DEATH_S = 0.2
"""A quiet peer may have died this long after its newest message (two state periods); it
carries on in a straight line from where its trajectory had it then (``_coast``)."""
GHOST_FORGET_S = 60.0
"""A quiet peer's ghosts (where its vehicle may hold) are avoided this long."""
MONITOR_REPLAN_AFTER_S = 0.3
"""A safety monitor asks for a replan for a conflict only when the last plan is older than
this (a younger one that still meets it leads to a brake or to waiting, see below)."""
MONITOR_BRAKE_WITHIN_S = 1.0
"""A safety monitor brakes for a conflict a fresh plan did not clear only when it lies less
than this far ahead (a braking stop from 1 m/s takes 0.5 s, plus the look and the autopilot's
reaction); further ahead it asks for another replan instead (a brake for a conflict 1.6 s
ahead broke up a formation in bench faults seed 0 trial 7)."""
LATE_JUMP_M = 0.2
"""A plan that comes back after its start time is flown only if its setpoint then lies within
this of the trajectory in control's (replans of 1-4 s on a starved CPU moved setpoints by up to
2.2 m: bench demo seeds 2 and 4 of 2026-11-28)."""
MONITOR_RETRY_S = 0.1
"""A safety monitor whose plan comes inside the check's distance where a braking stop would
come as close (``monitor_action``'s 'brake' with no better stop: a last resort in flight, a
peer that does not hear us coming on) asks for a new plan at most this often: each look
(100 Hz) asking again replanned, and broadcast, a hundred times a second while such a plan
was flown."""
MONITOR_PLAN_WAIT_S = 0.2
"""A safety monitor that asked for a replan for a conflict less than ``MONITOR_BRAKE_WITHIN_S``
ahead brakes if no plan begun after the request has come back within this time (replans take
milliseconds; on a starved CPU they took 1-2 s, and a drone flew into a hovering peer while
its monitor asked for replan after replan: bench demo seed 3, 2026-11-28)."""
HOVER_S = 3600.0
"""Duration of the hovers a plan avoids where a peer may hold (ghosts, reported positions)."""
RESEND_S = (0.05, 0.15)
"""A braking stop or hover a drone announces (and, with ``resend_plans``, every plan) goes out
again this long after it, unless a newer trajectory went out first (``DroneAgent.resend``; the
flight service's and fast time's default). On a bus that loses messages one lost copy left the
peers planning along a trajectory the drone no longer flew until its next publication: two
drones 0.33 m apart (``bench hidden --outage-from 3`` seed 7, a brake lost; seed 271, 0.07 m,
a plan that slowed lost). Copies of plans too triple the trajectory messages for no fewer
contacts over 800 flights (BENCHMARKS 9b), so the defaults send stops and hovers again only."""


def resend_delays(delays: Iterable[float]) -> tuple[float, ...]:
    """``delays`` as the tuple ``DroneAgent(resend_s=...)`` keeps; ValueError unless each is a
    finite number > 0."""
    out = tuple(float(d) for d in delays)
    if any(not (math.isfinite(d) and d > 0.0) for d in out):
        raise ValueError(f"resend_s must hold delays > 0, got {out!r}")
    return out


class MapSource(Protocol):
    """Where the agent's distance field comes from (a sensed world, a mapping thread's ESDF)."""

    def snapshot(self, now_s: float, position: np.ndarray) -> DistanceField:
        """The field to plan on at ``now_s`` with the drone at ``position`` (ENU m); a source
        that senses around the drone may update its map first. Must not be mutated later by
        the source (hand out a new object when the map changes)."""
        ...


class StaticMap:
    """A map that never changes (a known world, tests)."""

    def __init__(self, field: DistanceField) -> None:
        self.field = field

    def snapshot(self, now_s: float, position: np.ndarray) -> DistanceField:
        return self.field


@dataclass(frozen=True, eq=False)
class PlanInputs:
    """Everything one plan call receives, in ``FormationPlanner(params, formation, slot,
    edge_mask).plan(t_start_s, start_p, start_v, start_a, goal, peers, field, previous)``."""

    drone_id: int
    slot: int
    t_start_s: float
    start_p: np.ndarray
    start_v: np.ndarray
    start_a: np.ndarray
    goal: np.ndarray
    peers: tuple[PeerTrajectory, ...]
    field: DistanceField
    previous: Trajectory
    formation: np.ndarray
    """The template the planner used: the formation, plus one row per avoided-only peer."""
    edge_mask: np.ndarray | None
    """None: the complete graph; else the mask that isolates the avoided-only rows."""
    n_ghosts: int = 0
    """The last ``n_ghosts`` of ``peers`` are hovers where quiet peers (silent ones included)
    may have stopped, or where deviating peers reported themselves."""
    first_attempt: int = 0
    """The plan call's ``first_attempt`` (after a replan that gave up at its time budget)."""


@dataclass(frozen=True, eq=False)
class PlanReport:
    """The outcome of one replan, as the service publishes it (status, timings, peers)."""

    drone_id: int
    seq: int
    """Sequence number of the published trajectory message."""
    planned_at_s: float
    """Global time of the cycle (``now``); the message was published then."""
    t_start_s: float
    """Global time the new trajectory takes control."""
    status: PlanStatus
    message: str
    trajectory: Trajectory
    iterations: int
    evaluations: int
    plan_ms: float
    """Wall time of the planner call alone."""
    cycle_ms: float
    """Wall time of the whole cycle (map snapshot, bus, planner, publish)."""
    slot: int
    formation_epoch: int
    goal: np.ndarray
    formation_peers: tuple[int, ...]
    """Peers in the formation term, by drone id."""
    avoided_peers: tuple[int, ...]
    """Peers only avoided (excluded, expired, other epoch, bad or conflicting slot)."""
    peers: tuple[PeerTrajectory, ...]
    """The peers' trajectories the plan was made against (formation peers first, the quiet
    peers' ghost hovers last), e.g. for a safety monitor's
    ``agent.planner.check(trajectory, t, field, peers)``."""
    silent_peers: tuple[int, ...] = ()
    """Peers judged silent: only avoided, along their last trajectory and at their ghosts."""
    deviating_peers: tuple[int, ...] = ()
    """Peers heard alive but reported off their trajectory: also avoided where they reported
    (with ``avoid_reported``, also peers heard without a trajectory considered)."""
    quiet_peers: tuple[int, ...] = ()
    """Peers quiet but not (yet) silent: avoided at their ghosts too, still in the formation."""
    reforming: bool = False
    """Planned within ``PlannerParams.reform_s`` of a formation change: with
    ``params.reform_params`` (the lead slow-down from the centroid, a stronger formation term)."""
    recovering: bool = False
    """Planned while recovering the shape (``PlannerParams.recover_e_sim``): with
    ``params.recover_params``."""
    unheard_by: tuple[int, ...] = ()
    """Peers that reported they did not hear us (``DroneAgent.set_unheard``): planned with
    ``params.unheard_params`` (a wider berth to every peer)."""
    plan_cpu_ms: float = math.nan
    """CPU time of the planner call in the planning thread (NaN: not measured). Against
    ``plan_ms`` it tells computing from waiting for a core or the interpreter lock (the warm
    start's part, where a side executor takes it, runs in another thread: not counted)."""


@dataclass(frozen=True, eq=False)
class PeerView:
    """The peers as a plan made at ``t_s`` would avoid them (``DroneAgent.peer_view``): what a
    safety monitor checks the trajectory in control against between replans."""

    t_s: float
    trajectories: tuple[PeerTrajectory, ...]
    """Every peer trajectory still considered (in the formation or only avoided), by id."""
    hover_ids: tuple[int, ...]
    """The drone of each row of ``hover_points``."""
    hover_points: np.ndarray
    """(K, 3) ENU m, read-only: the quiet and silent peers' ghosts (where each may have
    stopped), then
    where the deviating peers reported themselves: the hovers a plan avoids besides the
    trajectories."""
    silent: tuple[int, ...]
    """Peers judged silent (out of the formation, avoided at their ghosts too)."""
    deviating: tuple[int, ...]
    """Peers avoided where they reported themselves (``PlanReport.deviating_peers``)."""
    quiet: tuple[int, ...] = ()
    """Peers quiet but not (yet) silent: avoided at their ghosts too, still in the formation
    (``PlanReport.quiet_peers``)."""


_REFORM = "reform"
"""``DroneAgent._planner``'s mode within ``reform_s`` of a formation change."""
_RECOVER = "recover"
"""... and while recovering the shape (``PlannerParams.recover_e_sim``)."""


def _shape_error(
    start_p: np.ndarray, a: _Assignment, formed: Sequence[TrajectoryMsg], t_s: float
) -> float:
    """The swarm's shape as a drone sees it at a replan: the similarity metric (e_sim) of its
    own start ``start_p`` and its formation peers' broadcast plans at ``t_s`` against their
    slots' points of the template."""
    pts = np.empty((len(formed) + 1, 3))
    pts[0] = start_p
    slots = [a.slot]
    for k, m in enumerate(formed):
        pts[k + 1] = m.trajectory.sample(t_s)
        slots.append(m.slot)
    return similarity(pts, a.formation[slots])[0]


def same_peers(a: PeerView, b: PeerView) -> bool:
    """Do two views hold the same peers: the same trajectory objects in the same slots, the
    same hovers and the same quiet, silent and deviating peers (whatever their times)?"""
    return (
        len(a.trajectories) == len(b.trajectories)
        and all(
            p.drone_id == q.drone_id and p.slot == q.slot and p.trajectory is q.trajectory
            for p, q in zip(a.trajectories, b.trajectories, strict=True)
        )
        and a.hover_ids == b.hover_ids
        and a.silent == b.silent
        and a.deviating == b.deviating
        and a.quiet == b.quiet
        and np.array_equal(a.hover_points, b.hover_points)
    )


def _first_conflict(
    d: np.ndarray, limit_m: float, brake_d: np.ndarray | None, closer_marginal: bool = False
) -> tuple[int, bool]:
    """(the index of the first sample of the distances ``d`` (K,) that is a conflict with a
    limit of ``limit_m``, -1 when none; whether braking instead would help), by the planner's
    rule (``kernels._band``, the safety check's): a plan that starts inside the limit, never
    comes closer than its start (or than the braking stop instead would: ``brake_d``, that
    stop's distances on the first samples, those within its window (``brake_reference_s``,
    ``_brake_samples``); None: the
    start) and leaves the limit is the way out, not a conflict (braking there would hold the
    drone inside for good: every retry's plan backs out and every brake undoes it); a plan
    that starts outside and comes inside, but no closer than the stop, is a conflict that a
    brake does not help (a replan may); with ``closer_marginal`` (peers, the planner's rule for
    them), so is a start inside that comes closer before it backs out."""
    close = d < limit_m
    if not close.any():
        return -1, True
    floor = math.inf if brake_d is None else float(brake_d.min())
    band = band_state(d, limit_m, floor, closer_marginal)
    if band == BAND_OK:
        return -1, True
    return int(np.argmax(close)), band != BAND_MARGINAL


def _brake_samples(ts: np.ndarray, ref_s: float) -> int:
    """How many of the samples ``ts`` lie within ``ref_s`` of the first."""
    return max(1, int(np.searchsorted(ts, ts[0] + ref_s + 1e-9, side="right")))


def peer_links(
    view: PeerView, heard_s: Callable[[int], float], now_s: float, limit: int = 60
) -> list[tuple[str, bool, float | None]]:
    """A drone's ``peer/<id>`` links as its status reports them: one per peer in ``view``
    (flown, silent or deviating), up unless silent, with the age of its newest sign of life
    (``heard_s``; None: never heard); at most ``limit`` (the status's bound). What the peers
    read to know whether this drone hears them (``onboard.comm.hearing``)."""
    ids = sorted({pt.drone_id for pt in view.trajectories} | set(view.silent) | set(view.deviating))
    out: list[tuple[str, bool, float | None]] = []
    for pid in ids[:limit]:
        age = now_s - heard_s(pid)
        out.append(
            (f"peer/{pid}", pid not in view.silent, max(age, 0.0) if math.isfinite(age) else None)
        )
    return out


def peer_conflict(
    view: PeerView,
    now_s: float,
    ts: np.ndarray,
    pos: np.ndarray,
    limit_m: float,
    brake: np.ndarray | None = None,
    ref_s: float = BRAKE_REFERENCE_S,
) -> tuple[str, float, bool]:
    """The earliest conflict of ``pos`` (our positions at the increasing times ``ts``, (K, 3))
    with ``view``: a peer trajectory (sampled at the same times), a quiet or silent peer's
    ghost or where a deviating peer reported itself (hovers) closer than ``limit_m``, as (what,
    the time of the first sample too close, whether a brake would help); ('', inf, True) when
    none. Judged by the planner's rule (``_first_conflict``) against ``brake``: the braking
    stop the monitor would fly instead, at ``ts`` (None: a start inside the limit against the
    start), over its first ``ref_s`` (``DroneAgent.brake_reference_s``). What a safety monitor
    checks between replans (the flight service's and the fast-time one)."""
    first = math.inf
    problem = ""
    helps = True
    ref = None if brake is None else brake[: _brake_samples(ts, ref_s)]
    for pt in view.trajectories:
        peer = pt.trajectory.sample(ts)
        dd = np.linalg.norm(pos - peer, axis=1)
        ref_d = None if ref is None else np.linalg.norm(ref - peer[: len(ref)], axis=1)
        k, k_helps = _first_conflict(dd, limit_m, ref_d, True)
        if k >= 0 and ts[k] < first:
            first, helps = float(ts[k]), k_helps
            problem = f"drone {pt.drone_id} {float(dd.min()):.2f} m in {ts[k] - now_s:.1f} s"
    for j, pid in enumerate(view.hover_ids):
        point = view.hover_points[j]
        d = np.linalg.norm(pos - point, axis=1)
        ref_d = None if ref is None else np.linalg.norm(ref - point, axis=1)
        k, k_helps = _first_conflict(d, limit_m, ref_d, True)
        if k >= 0 and ts[k] < first:
            if pid in view.silent:
                what = "a ghost of silent"
            elif pid in view.quiet:
                what = "a ghost of quiet"
            else:
                what = "where it reported itself:"
            first, helps = float(ts[k]), k_helps
            problem = f"{what} drone {pid} {float(d.min()):.2f} m in {ts[k] - now_s:.1f} s"
    return problem, first, helps


def obstacle_conflict(
    d: np.ndarray,
    ts: np.ndarray,
    now_s: float,
    limit_m: float,
    brake_d: np.ndarray | None = None,
    ref_s: float = BRAKE_REFERENCE_S,
) -> tuple[str, float, bool]:
    """The first sample closer than ``limit_m`` to an obstacle, from the distances ``d`` (K,)
    of our positions at the increasing times ``ts`` (d[0] where we are), as (what, its time,
    whether a brake would help); ('', inf, True) when none. Judged by the planner's rule
    (``_first_conflict``) against ``brake_d``: the distances of the braking stop the monitor
    would fly instead, at ``ts`` (None: a start inside the limit against the start), over its
    first ``ref_s``."""
    ref = None if brake_d is None else brake_d[: _brake_samples(ts, ref_s)]
    k, helps = _first_conflict(d, limit_m, ref)
    if k < 0:
        return "", math.inf, True
    return f"obstacle {float(d.min()):.2f} m in {ts[k] - now_s:.1f} s", float(ts[k]), helps


MONITOR_STEP_S = 0.1
"""A safety monitor samples the plan on a fixed grid of this step (``monitor_times``)."""


def monitor_step_index(now_s: float) -> int:
    """The index of the first ``MONITOR_STEP_S`` grid step at or after ``now_s``: a safety
    monitor samples the plan on that fixed grid (``monitor_times``), so that looks with the
    same inputs and step index find the same thing (and may reuse it)."""
    return math.ceil(now_s / MONITOR_STEP_S - 1e-6)


def monitor_times(step_index: int, horizon_s: float) -> np.ndarray:
    """The grid times from step ``step_index`` over ``horizon_s``."""
    n = round(horizon_s / MONITOR_STEP_S) + 1
    return np.arange(step_index, step_index + n) * MONITOR_STEP_S


def monitor_action(
    now_s: float,
    conflict_s: float,
    last_plan_s: float,
    last_brake_s: float,
    may_replan: bool,
    replan_after_s: float = MONITOR_REPLAN_AFTER_S,
    brake_within_s: float = MONITOR_BRAKE_WITHIN_S,
    asked_s: float = -math.inf,
    plan_wait_s: float = MONITOR_PLAN_WAIT_S,
) -> str:
    """What a safety monitor does about a conflict first met at ``conflict_s``: 'replan' (the
    last plan is older than ``replan_after_s``), 'watching' (a fresh plan still meets it, but
    more than ``brake_within_s`` ahead: the next replan may clear it), 'braking' (a brake less
    than a second ago is still on) or 'brake'. ``may_replan`` False (not in formation flight):
    never 'replan' nor 'watching'. ``asked_s``: when the monitor asked for the replan still
    awaited (-inf: none; ``last_plan_s``, the start of the newest plan, is before it): a
    conflict within ``brake_within_s`` brakes once the wait exceeds ``plan_wait_s``."""
    if may_replan and now_s - last_plan_s > replan_after_s:
        late = asked_s > last_plan_s and now_s - asked_s > plan_wait_s
        if not (late and conflict_s - now_s <= brake_within_s):
            return "replan"
    if may_replan and conflict_s - now_s > brake_within_s:
        return "watching"
    if now_s - last_brake_s < 1.0:
        return "braking"
    return "brake"


def replan_asked_s(asked_s: float, last_plan_s: float, now_s: float) -> float:
    """``monitor_action``'s ``asked_s`` after the monitor asks for a replan at ``now_s``: the
    time of the first request still awaited (a plan begun after ``asked_s`` answers it)."""
    return now_s if asked_s <= last_plan_s else asked_s


@dataclass(frozen=True)
class _Plan:
    """The trajectory in control and the ones queued after it (increasing start times)."""

    current: Trajectory
    queue: tuple[Trajectory, ...] = ()


@dataclass(frozen=True, eq=False)
class _Assignment:
    """What the drone is asked to do: goal, template, slot, epoch, peer roles."""

    goal: np.ndarray | None
    formation: np.ndarray
    slot: int
    epoch: int
    avoid_only: frozenset[int]
    ignore: frozenset[int]


@dataclass(frozen=True, eq=False)
class _Seen:
    """A peer's newest trajectory message and the sender's time it was sent (estimated)."""

    msg: TrajectoryMsg
    sent_s: float


@dataclass(frozen=True, eq=False)
class _Heard:
    """A peer's newest state message: the sender's stamp, the position and velocity it
    reported."""

    stamp_s: float
    position: np.ndarray | None
    velocity: np.ndarray | None = None


def _vec3(name: str, v: Sequence[float] | np.ndarray) -> np.ndarray:
    a = np.array(v, dtype=np.float64, copy=True)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    a.setflags(write=False)
    return a


def _template(formation: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    F = np.array(formation, dtype=np.float64, copy=True)
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] < 1 or not np.all(np.isfinite(F)):
        raise ValueError(f"formation must be a finite (N, 3) array, got shape {F.shape}")
    F.setflags(write=False)
    return F


def _spaced(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points along the polyline ``points`` (K, 3): its ends and as few between as keep
    consecutive ones at most ``spacing`` apart (along the line)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = int(math.ceil(s[-1] / spacing - 1e-9)) if s[-1] > 0.0 else 0
    if n == 0:
        return points[:1].copy()
    targets = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(targets, s, points[:, d]) for d in range(3)], axis=1)


class DroneAgent:
    """One drone: planner, trajectories, goal, formation slot and replan timing.

    drone_id: the drone's id on the bus; params: planner limits and weights (the one owner);
    formation: template (N, 3) ENU m; slot: this drone's row; initial: the trajectory in
    control at the start (e.g. ``Trajectory.hover(p, t0)``); bus: where trajectories are
    published and peers read (``PeerBus``); map_source: the distance field (``MapSource``).

    goal: ENU m, None = no replans until one is set; replan_period_s: the replan grid;
    plan_ahead_s: a new plan starts this long after the cycle that made it; first_replan_s:
    the first grid point (None: the initial trajectory's start; the simulator staggers drones);
    formation_epoch: the assignment the slot belongs to (peers of another epoch are avoided,
    not formed with); validity_s: published messages are valid this long after publication
    (inf: forever, the in-memory bus); peer_forget_s: an expired or silent peer is still
    avoided this long; ghost_forget_s: a quiet peer's ghosts are avoided this long after it
    fell quiet (at least as long as its trajectory); ghost_window_s: how long after its newest
    message a quiet peer may have flown on before it stopped (its messages in between lost;
    one replan period more for a peer heard only through trajectories); peer_silence_s: a
    peer heard of nothing newer for this long is quiet (see the module docstring; inf:
    never; flown with ``PEER_SILENCE_S``); peer_silence_max_s: a quiet peer is silent at the
    latest this long after it was last heard (or at the quiet limit, if that is longer;
    ``peer_silence_s`` here makes quiet and silent one); spell_factor, spell_margin_s,
    spell_window_s: a quiet peer is silent once quiet longer than ``spell_factor`` times its
    longest quiet spell of the last ``spell_window_s`` plus ``spell_margin_s``;
    peer_deviation_m: a peer whose reported position is
    further than this from its trajectory (a stuck or lagging vehicle) is also avoided as a
    hover where it reported itself (inf: never; more than the vehicles' tracking error; flown
    with ``PEER_DEVIATION_M``); peer_deviation_ahead_s: ... or would be this long later if
    it (its reported velocity, ``heard``) and its trajectory went straight on (0: positions
    only; flown with ``PEER_DEVIATION_AHEAD_S``); ghost_spacing_m:
    spacing of a quiet peer's ghost hovers (at most 2 * sqrt(check_drone_m^2 - collision
    distance^2): a plan clear of the ghosts by check_drone_m is clear of any point between
    them by that distance); avoid_reported: a peer heard through ``heard`` with a position but
    no trajectory considered (none received, or forgotten: one flown by hand, or stuck long
    after its last trajectory) is avoided as a hover where it last reported itself, until
    ``ghost_forget_s`` after it fell silent (the flight service; off in the simulator, whose
    seeded results it could change);
    on_inputs: called with every plan call's inputs before the call (records, replays);
    on_plan: called with every ``PlanReport`` after the new trajectory is scheduled — the
    service's status policy (hover, retry via ``request_replan``, land) hangs here; the agent
    itself only reports. It runs inside the cycle: it may call anything but ``replan`` and
    ``step`` (which would wait for the cycle it is in); timer: wall clock for the timings
    (seconds, monotonic); clock and late_jump_m: see ``_late``; plan_budget_s: once a replan
    has taken this long by ``timer`` (the flight service; inf: no budget, the fast-time
    simulator, whose results must not depend on the host's speed), it starts no further
    attempt while the trajectory in control is safe and moves on (``PlanStatus.OVER_BUDGET``:
    that trajectory flies on and a replan follows at once, starting at the attempt given up,
    ``PlanResult.resume_at``, unless the shape changed meanwhile); resend_s: each published
    trajectory goes out again this long after it unless a newer one went out first, as
    ``resend`` is called (``RESEND_S`` in the flight service and fast time; () none);
    resend_plans: False: only what ``announce`` publishes (braking stops, hovers) is sent
    again, not the replans' plans; side: where each planner solves its fresh start beside the
    warm one (``FormationPlanner``'s ``side``; None: one after the other).
    """

    def __init__(
        self,
        drone_id: int,
        params: PlannerParams,
        formation: np.ndarray | Sequence[Sequence[float]],
        slot: int,
        initial: Trajectory,
        bus: PeerBus,
        map_source: MapSource,
        *,
        goal: np.ndarray | Sequence[float] | None = None,
        replan_period_s: float = REPLAN_PERIOD_S,
        plan_ahead_s: float = PLAN_AHEAD_S,
        first_replan_s: float | None = None,
        formation_epoch: int = 0,
        validity_s: float = math.inf,
        peer_forget_s: float = 5.0,
        peer_silence_s: float = math.inf,
        peer_silence_in_way_s: float = PEER_SILENCE_IN_WAY_S,
        peer_silence_max_s: float = PEER_SILENCE_MAX_S,
        spell_factor: float = SPELL_FACTOR,
        spell_margin_s: float = SPELL_MARGIN_S,
        spell_window_s: float = SPELL_WINDOW_S,
        ghost_forget_s: float = GHOST_FORGET_S,
        ghost_window_s: float = GHOST_WINDOW_S,
        peer_deviation_m: float = math.inf,
        peer_deviation_ahead_s: float = 0.0,
        ghost_spacing_m: float = 0.25,
        avoid_reported: bool = False,
        on_inputs: Callable[[PlanInputs], None] | None = None,
        on_plan: Callable[[PlanReport], None] | None = None,
        timer: Callable[[], float] = time.perf_counter,
        clock: Callable[[], float] | None = None,
        late_jump_m: float = LATE_JUMP_M,
        plan_budget_s: float = math.inf,
        resend_s: Sequence[float] = (),
        resend_plans: bool = True,
        side: SideExecutor | None = None,
    ) -> None:
        self._side = side
        self.resend_s = resend_delays(resend_s)
        self.resend_plans = bool(resend_plans)
        if not (math.isfinite(replan_period_s) and replan_period_s > 0.0):
            raise ValueError(f"replan_period_s must be > 0, got {replan_period_s!r}")
        if not (math.isfinite(plan_ahead_s) and plan_ahead_s >= 0.0):
            raise ValueError(f"plan_ahead_s must be >= 0, got {plan_ahead_s!r}")
        if not validity_s > 0.0:
            raise ValueError(f"validity_s must be > 0, got {validity_s!r}")
        if not peer_forget_s >= 0.0:
            raise ValueError(f"peer_forget_s must be >= 0, got {peer_forget_s!r}")
        if not peer_silence_s > 0.0:
            raise ValueError(f"peer_silence_s must be > 0, got {peer_silence_s!r}")
        if not peer_silence_in_way_s > 0.0:
            raise ValueError(f"peer_silence_in_way_s must be > 0, got {peer_silence_in_way_s!r}")
        if not peer_silence_max_s > 0.0:
            raise ValueError(f"peer_silence_max_s must be > 0, got {peer_silence_max_s!r}")
        if not (math.isfinite(spell_factor) and spell_factor >= 1.0):
            raise ValueError(f"spell_factor must be >= 1, got {spell_factor!r}")
        if not (math.isfinite(spell_margin_s) and spell_margin_s >= 0.0):
            raise ValueError(f"spell_margin_s must be >= 0, got {spell_margin_s!r}")
        if not (math.isfinite(spell_window_s) and spell_window_s > 0.0):
            raise ValueError(f"spell_window_s must be > 0, got {spell_window_s!r}")
        if not (math.isfinite(ghost_window_s) and ghost_window_s >= 0.0):
            raise ValueError(f"ghost_window_s must be >= 0, got {ghost_window_s!r}")
        if not peer_deviation_m > 0.0:
            raise ValueError(f"peer_deviation_m must be > 0, got {peer_deviation_m!r}")
        if not (math.isfinite(peer_deviation_ahead_s) and 0.0 <= peer_deviation_ahead_s <= 5.0):
            raise ValueError(
                f"peer_deviation_ahead_s must be in [0, 5], got {peer_deviation_ahead_s!r}"
            )
        if not ghost_forget_s >= 0.0:
            raise ValueError(f"ghost_forget_s must be >= 0, got {ghost_forget_s!r}")
        if not (math.isfinite(ghost_spacing_m) and ghost_spacing_m > 0.0):
            raise ValueError(f"ghost_spacing_m must be > 0, got {ghost_spacing_m!r}")
        if not (math.isfinite(late_jump_m) and late_jump_m > 0.0):
            raise ValueError(f"late_jump_m must be > 0, got {late_jump_m!r}")
        if not plan_budget_s > 0.0:
            raise ValueError(f"plan_budget_s must be > 0, got {plan_budget_s!r}")
        if not isinstance(initial, Trajectory):
            raise TypeError(f"initial must be a Trajectory, got {type(initial).__name__}")
        self.drone_id = int(drone_id)
        self.params = params
        self._unheard_params = unheard_params(params)  # while a peer does not hear us
        self.bus = bus
        self.map_source = map_source
        self.replan_period_s = float(replan_period_s)
        self.plan_ahead_s = float(plan_ahead_s)
        self.validity_s = float(validity_s)
        self.peer_forget_s = float(peer_forget_s)
        self.peer_silence_s = float(peer_silence_s)
        self.peer_silence_in_way_s = min(float(peer_silence_in_way_s), self.peer_silence_s)
        self.peer_silence_max_s = float(peer_silence_max_s)
        self.spell_factor = float(spell_factor)
        self.spell_margin_s = float(spell_margin_s)
        self.spell_window_s = float(spell_window_s)
        self.ghost_spacing_m = float(ghost_spacing_m)
        self.ghost_forget_s = float(ghost_forget_s)
        self.ghost_window_s = float(ghost_window_s)
        self.peer_deviation_m = float(peer_deviation_m)
        self.peer_deviation_ahead_s = float(peer_deviation_ahead_s)
        self.avoid_reported = bool(avoid_reported)
        self._deviant: set[int] = set()  # peers off their trajectory at the last ``watch``
        self.on_inputs = on_inputs
        self.on_plan = on_plan
        self.timer = timer
        self.clock = clock
        self.late_jump_m = float(late_jump_m)
        self.plan_budget_s = float(plan_budget_s)
        self._traj_lock = threading.Lock()
        self._cfg_lock = threading.Lock()
        self._cycle_lock = threading.Lock()
        self._plan = _Plan(initial)
        F = _template(formation)
        self._assign = _Assignment(
            None if goal is None else _vec3("goal", goal),
            F,
            self._check_slot(slot, F),
            self._check_epoch(formation_epoch),
            frozenset(),
            frozenset(),
        )
        self._planners: dict[tuple[int, bytes, int, str, bool], FormationPlanner] = {}
        # peers that report they do not hear us (``set_unheard``)
        self._unheard: frozenset[int] = frozenset()
        self.first_published_s = math.inf
        """When this agent published its first trajectory (inf: not yet)."""
        self.last_published_s = -math.inf
        """When this agent published its newest trajectory (-inf: not yet)."""
        # (epoch, slot, template) of the last replan, and when the re-forming after a change
        # ends (``PlannerParams.reform_s``)
        self._shape_seen: tuple[int, int, bytes] | None = None
        self._reform_until_s = -math.inf
        # ... and goes on until then while the shape is not reached (``reform_hold_e_sim``)
        self._reform_hold_until_s = -math.inf
        # shape recovery (``PlannerParams.recover_e_sim``) lasts until then
        self._recover_until_s = -math.inf
        self._active: FormationPlanner | None = None
        # where the next replan starts the planner's attempts: those the last one gave up at
        # its time budget (``PlanResult.resume_at``), else the first
        self._resume_at = 0
        self._next_replan_s = float(initial.t0_s if first_replan_s is None else first_replan_s)
        if not math.isfinite(self._next_replan_s):
            raise ValueError("first_replan_s must be finite")
        self._demand_s = math.inf
        self._seq = 0
        self._pub_lock = threading.Lock()
        # the last trajectory published (and its assignment), and when to send it again
        self._last_sent: tuple[Trajectory, _Assignment] | None = None
        self._resend_at: tuple[float, ...] = ()  # replaced, never changed: read unlocked
        self.resent = 0
        """Copies sent by ``resend``."""
        self._last: PlanReport | None = None
        self.status_counts: dict[str, int] = {}
        """Replans by plan status value (``PlanStatus.value``); other threads: ``counters()``."""
        self.avoided_count = 0
        """Replans in which at least one peer was only avoided."""
        self._peer_lock = threading.Lock()
        self._seen: dict[int, _Seen] = {}  # newest trajectory per peer (the cycle writes)
        self._heard: dict[int, _Heard] = {}  # newest state per peer (``heard`` writes)
        self._flagged: dict[int, float] = {}  # peer -> heard time its silence was flagged at
        self._in_way: dict[int, float] = {}  # peer -> heard time its quiet ghosts were in the way
        self._looked: dict[int, float] = {}  # peer -> its newest heard time at the last look
        # what ``_ghosts`` and ``_deviation`` last computed per peer, with what it came from
        # (``peer_view`` runs 20-40 times a second, a peer's messages change at 10 Hz)
        self._ghost_cache: dict[int, tuple[tuple[Any, ...], np.ndarray]] = {}
        self._deviation_cache: dict[int, tuple[_Heard, _Seen, np.ndarray | None]] = {}
        self._spells: dict[int, deque[tuple[float, float]]] = {}  # peer -> (look, spell)
        self._spell_max: dict[int, float] = {}  # peer -> longest spell kept (None: recompute)
        self._spell_stale: set[int] = set()  # peers whose longest spell left the window
        self._look_s = -math.inf  # the latest look's time
        self._refused: dict[int, TrajectoryMsg] = {}  # peer -> the last message refused
        self.refused_older = 0
        """Trajectories refused because a newer one of the same peer had been received."""
        self.silent_count = 0
        """Replans in which at least one peer was silent (out of the formation, avoided at its
        ghosts)."""
        self.quiet_count = 0
        """Replans in which at least one peer was quiet but not silent (avoided at its ghosts,
        still in the formation)."""
        self.in_the_way_count = 0
        """Times ``watch`` found a quiet peer's ghosts on our path (each asks for a replan)."""

    # --- trajectories (any thread) ----------------------------------------------------------

    @property
    def current(self) -> Trajectory:
        """The trajectory in control since the last ``advance``."""
        return self._plan.current

    @property
    def queued(self) -> tuple[Trajectory, ...]:
        """Published trajectories that have not taken control yet (increasing start times)."""
        return self._plan.queue

    def flying(self, t_s: float) -> Trajectory:
        """The trajectory that will be in control at ``t_s`` (at or after the last advance)."""
        plan = self._plan  # one immutable snapshot
        out = plan.current
        for q in plan.queue:
            if t_s >= q.t0_s - EPS_T:
                out = q
        return out

    @property
    def plan_token(self) -> object:
        """An object that changes whenever the trajectory in control or the queue does (for
        callers that cache what they computed from ``planned``)."""
        return self._plan

    def planned(self, ts: np.ndarray) -> np.ndarray:
        """Where the drone will be commanded at the increasing times ``ts`` (at or after the
        last advance), (K, 3): the trajectory in control, then each queued one from its start
        (a plan made a moment ago takes control ``plan_ahead_s`` later; a monitor that sampled
        only the trajectory in control would judge the plan it replaces)."""
        ts = np.asarray(ts, dtype=np.float64).reshape(-1)
        plan = self._plan  # one immutable snapshot
        out = plan.current.sample(ts)
        for q in plan.queue:
            k = int(np.searchsorted(ts, q.t0_s - EPS_T))
            if k < ts.shape[0]:
                out[k:] = q.sample(ts[k:])
        return out

    def state(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, velocity, acceleration) commanded at ``t_s``: the setpoint."""
        return self.flying(t_s).state(t_s)

    def advance(self, t_s: float) -> Trajectory:
        """Hand control to every queued trajectory whose start time has come; the current."""
        with self._traj_lock:
            plan = self._plan
            k = 0
            while k < len(plan.queue) and t_s >= plan.queue[k].t0_s - EPS_T:
                k += 1
            if k:
                plan = _Plan(plan.queue[k - 1], plan.queue[k:])
                self._plan = plan
            return plan.current

    def schedule(self, new: Trajectory) -> None:
        """``new`` takes control at its start time, replacing what was queued from then on."""
        with self._traj_lock:
            plan = self._plan
            if new is plan.current or any(new is q for q in plan.queue):
                return
            keep = tuple(q for q in plan.queue if q.t0_s < new.t0_s - EPS_T)
            self._plan = _Plan(plan.current, (*keep, new))

    def reset(self, trajectory: Trajectory) -> None:
        """``trajectory`` is in control now; everything queued is dropped (e.g. taking over
        from the autopilot's own takeoff at the vehicle's position)."""
        with self._traj_lock:
            self._plan = _Plan(trajectory)

    # --- assignment (any thread) ------------------------------------------------------------

    @property
    def goal(self) -> np.ndarray | None:
        return self._assign.goal

    @property
    def formation(self) -> np.ndarray:
        """The formation template (N, 3), read-only."""
        return self._assign.formation

    @property
    def slot(self) -> int:
        return self._assign.slot

    @property
    def formation_epoch(self) -> int:
        return self._assign.epoch

    def set_goal(self, goal: np.ndarray | Sequence[float] | None, replan: bool = True) -> None:
        """A new goal (ENU m; None: stop replanning and keep the current trajectory); by
        default the next ``due`` is at once."""
        g = None if goal is None else _vec3("goal", goal)
        with self._cfg_lock:
            self._assign = dataclasses.replace(self._assign, goal=g)
            if replan and g is not None:
                self._demand_s = -math.inf

    def set_formation(
        self,
        formation: np.ndarray | Sequence[Sequence[float]],
        slot: int,
        epoch: int | None = None,
        goal: np.ndarray | Sequence[float] | None = None,
        replan: bool = True,
    ) -> None:
        """A new template and slot (and epoch; None: the current one + 1), optionally with a
        new goal; takes effect at the next replan (at once by default)."""
        F = _template(formation)
        s = self._check_slot(slot, F)
        g = None if goal is None else _vec3("goal", goal)
        with self._cfg_lock:
            e = self._assign.epoch + 1 if epoch is None else self._check_epoch(epoch)
            self._assign = dataclasses.replace(
                self._assign,
                formation=F,
                slot=s,
                epoch=e,
                goal=self._assign.goal if g is None else g,
            )
            if replan:
                self._demand_s = -math.inf

    def set_slot(self, slot: int, epoch: int | None = None, replan: bool = True) -> None:
        """A new slot in the same template (and epoch; None: the current one + 1)."""
        self.set_formation(self._assign.formation, slot, epoch, replan=replan)

    def set_peer_roles(self, avoid_only: Iterable[int] = (), ignore: Iterable[int] = ()) -> None:
        """Peers (drone ids) kept out of the formation term but still avoided, and peers not
        considered at all. Replaces the previous sets."""
        with self._cfg_lock:
            self._assign = dataclasses.replace(
                self._assign,
                avoid_only=frozenset(int(i) for i in avoid_only),
                ignore=frozenset(int(i) for i in ignore),
            )

    def set_unheard(self, peers: Iterable[int]) -> None:
        """Peers (drone ids) that report they do not hear us (the flight service reads it from
        their statuses). While any does, plans keep ``PlannerParams.unheard_margin_m`` more from
        every peer (``unheard_params``; ``check_drone_m`` says what the safety monitor should
        keep). Replaces the previous set."""
        got = frozenset(int(i) for i in peers)
        with self._cfg_lock:
            self._unheard = got - {self.drone_id}

    @property
    def unheard_by(self) -> frozenset[int]:
        """The peers that last reported they do not hear us (``set_unheard``)."""
        return self._unheard

    @property
    def brake_reference_s(self) -> float:
        """The window of the safety check's braking stop now: ``PlannerParams.brake_reference_s``,
        longer while a peer does not hear us (``unheard_params``, as the planner's)."""
        return (self._unheard_params if self._unheard else self.params).brake_reference_s

    @property
    def check_drone_m(self) -> float:
        """The distance to peers a plan keeps now: ``PlannerParams.check_drone_m``, plus
        ``unheard_margin_m`` while a peer does not hear us (``unheard_params``, as the
        planner's)."""
        return (self._unheard_params if self._unheard else self.params).check_drone_m

    @staticmethod
    def _check_slot(slot: int, formation: np.ndarray) -> int:
        if int(slot) != slot or not 0 <= int(slot) < formation.shape[0]:
            raise ValueError(f"slot {slot!r} is outside the formation of {formation.shape[0]}")
        return int(slot)

    @staticmethod
    def _check_epoch(epoch: int) -> int:
        if int(epoch) != epoch or epoch < 0:
            raise ValueError(f"formation_epoch must be an integer >= 0, got {epoch!r}")
        return int(epoch)

    # --- timing -----------------------------------------------------------------------------

    @property
    def next_replan_s(self) -> float:
        """The next replan time: the grid point or an earlier request."""
        return min(self._next_replan_s, self._demand_s)

    def due(self, now_s: float) -> bool:
        """Is a replan due at ``now_s``? (Never while there is no goal.)"""
        return self._assign.goal is not None and now_s >= self.next_replan_s - EPS_T

    def request_replan(self, at_s: float | None = None) -> None:
        """Replan at once (None) or by ``at_s``, whichever of it and the grid comes first."""
        with self._cfg_lock:
            self._demand_s = min(self._demand_s, -math.inf if at_s is None else float(at_s))

    def cancel(self) -> None:
        """Ask a running planner call (in another thread) to stop at its next evaluation; the
        planner then keeps the previous trajectory if safe, else stops."""
        p = self._active
        if p is not None:
            p.cancel()

    # --- peers' signs of life (any thread) -----------------------------------------------

    def heard(
        self,
        drone_id: int,
        stamp_s: float,
        position: np.ndarray | None = None,
        velocity: np.ndarray | None = None,
    ) -> None:
        """A message of any kind other than a trajectory (a state message) from ``drone_id``,
        sent at the sender's global time ``stamp_s``, optionally reporting its position (ENU
        m) and velocity (ENU m/s; only with a position). Only the newest counts: an older
        stamp (a late, reordered copy) changes nothing."""
        pid = int(drone_id)
        t = float(stamp_s)
        if pid == self.drone_id or not math.isfinite(t):
            return
        p = None if position is None else _vec3("position", position)
        v = None if velocity is None or p is None else _vec3("velocity", velocity)
        with self._peer_lock:
            h = self._heard.get(pid)
            if h is None or t > h.stamp_s:
                self._heard[pid] = _Heard(t, p, v)

    def heard_s(self, drone_id: int) -> float:
        """The sender's time of the newest message heard from ``drone_id`` (-inf: none)."""
        with self._peer_lock:
            return self._heard_s(int(drone_id))

    def _heard_s(self, pid: int) -> float:
        h = self._heard.get(pid)
        s = self._seen.get(pid)
        return max(-math.inf if h is None else h.stamp_s, -math.inf if s is None else s.sent_s)

    def _silence_limit(self, pid: int) -> float:
        """How long ``pid`` may be heard of nothing newer before it is quiet."""
        if pid in self._heard:
            return self.peer_silence_s
        return self.peer_silence_s + self.replan_period_s

    def _in_way_limit(self, pid: int) -> float:
        """How long ``pid`` may be heard of nothing newer before it is quiet if its ghosts lie
        in our way (``watch`` looks): ``peer_silence_in_way_s`` (one replan period more
        without states), but at least its longest recent quiet spell plus
        ``IN_WAY_SPELL_MARGIN_S`` and at most its quiet limit. Under ``_peer_lock``."""
        quiet = self._silence_limit(pid)
        if not math.isfinite(quiet):
            return math.inf
        base = self.peer_silence_in_way_s + (quiet - self.peer_silence_s)
        return min(quiet, max(base, self._longest_spell(pid) + IN_WAY_SPELL_MARGIN_S))

    def _is_quiet(self, pid: int, h: float, now: float) -> bool:
        """Quiet: heard of nothing newer than ``h`` for longer than its quiet limit, or found
        in our way by ``watch`` (past its in-the-way limit) and not heard since."""
        return now - h > self._silence_limit(pid) or self._in_way.get(pid) == h

    def silence_limit(self, drone_id: int) -> float:
        """How long ``drone_id`` may now be heard of nothing newer before it is silent:
        ``spell_factor`` times its longest quiet spell of the last ``spell_window_s`` plus
        ``spell_margin_s``, at least
        the quiet limit (``peer_silence_s``; one replan period more without states) and at
        most ``peer_silence_max_s`` (or the quiet limit, if larger)."""
        with self._peer_lock:
            return self._silent_limit(int(drone_id))

    def _silent_limit(self, pid: int) -> float:
        base = self._silence_limit(pid)
        longest = self._longest_spell(pid)
        longest = self.spell_factor * longest + self.spell_margin_s
        return max(base, min(self.peer_silence_max_s, longest))

    def _note(self, now: float) -> None:
        """A look at ``now``: a peer heard of something newer since the last look ended a
        quiet spell as long as the age of its newest message at the last look (the longest
        age a look saw before it was heard again; kept for ``spell_window_s``). Under
        ``_peer_lock``."""
        last = self._look_s
        if now > last:
            self._look_s = now
        cut = self._look_s - self.spell_window_s
        for pid in set(self._seen) | set(self._heard):
            h = self._heard_s(pid)
            prev = self._looked.get(pid)
            self._looked[pid] = h
            spells = self._spells.get(pid)
            if prev is not None and h > prev and math.isfinite(prev) and last >= prev:
                if spells is None:
                    spells = self._spells[pid] = deque(maxlen=1024)
                spell = min(last, now) - prev
                if len(spells) == spells.maxlen:
                    self._drop_spell(pid, spells[0][1])  # append evicts the oldest
                spells.append((now, spell))
                if pid not in self._spell_stale:
                    self._spell_max[pid] = max(self._spell_max.get(pid, spell), spell)
            while spells and spells[0][0] < cut:
                self._drop_spell(pid, spells.popleft()[1])

    def _drop_spell(self, pid: int, spell: float) -> None:
        """A spell left ``pid``'s window: if it may have been the longest, recompute that
        when next asked (``_longest_spell``). Under ``_peer_lock``."""
        if spell >= self._spell_max.get(pid, -math.inf):
            self._spell_stale.add(pid)

    def _longest_spell(self, pid: int) -> float:
        """The longest quiet spell kept for ``pid`` (0 if none): the max over its window,
        kept up to date as spells come and go. Under ``_peer_lock``."""
        spells = self._spells.get(pid)
        if not spells:
            return 0.0
        if pid in self._spell_stale or pid not in self._spell_max:
            self._spell_max[pid] = max(d for _, d in spells)
            self._spell_stale.discard(pid)
        return self._spell_max[pid]

    def watch(self, now_s: float) -> tuple[int, ...]:
        """Peers that fell silent, fell quiet with a ghost on our path (the trajectory we fly
        comes closer than ``check_drone_m`` to a place where it may have stopped), or whose
        reported position left their trajectory, since the last call (see the module
        docstring); a replan is requested at once when there is one. Call at the rate of the
        state messages (each call is a look that measures the peers' quiet spells); with
        ``peer_deviation_m`` or ``peer_silence_s`` set it reads the bus first (states are
        compared with the newest trajectories, ghosts lie along them)."""
        out = []
        quiet = []  # (peer, heard time) to look at: in our way, it is quiet
        now = float(now_s)
        fresh = None
        if math.isfinite(self.peer_deviation_m) or math.isfinite(self.peer_silence_s):
            fresh = self.bus.receive(self.drone_id, now)  # states vs the newest trajectories
        with self._peer_lock:
            if fresh is not None:
                self._take(fresh, now)
            self._note(now)
            for pid in sorted(set(self._seen) | set(self._heard)):
                h = self._heard_s(pid)
                if now - h > self._silent_limit(pid):
                    if self._flagged.get(pid) != h:
                        self._flagged[pid] = h
                        out.append(pid)
                else:
                    # past the in-the-way limit (at most the quiet limit): quiet if in our way
                    if (
                        now - h > self._in_way_limit(pid)
                        and pid in self._seen
                        and self._in_way.get(pid) != h
                    ):
                        quiet.append((pid, h))
                    if now - h > self._silence_limit(pid):
                        continue  # quiet: no deviation to judge
                    if self._deviation(pid) is not None:
                        if pid not in self._deviant:
                            self._deviant.add(pid)
                            out.append(pid)
                    else:
                        self._deviant.discard(pid)
        for pid, h in quiet:  # outside the lock: sampling trajectories
            if self._in_the_way(pid, now):
                with self._peer_lock:
                    self._in_way[pid] = h  # quiet from now on, until heard again
                with self._cfg_lock:
                    self.in_the_way_count += 1
                out.append(pid)
        if out and self._assign.goal is not None:
            self.request_replan()
        return tuple(sorted(out))

    def _in_the_way(self, pid: int, now: float) -> bool:
        """Does the trajectory we fly from ``now`` (the one in control, then the queued ones)
        come closer than ``check_drone_m`` to one of quiet peer ``pid``'s ghosts?"""
        ghosts = self._ghosts({pid}, now)
        if not ghosts:
            return False
        g = np.array([p for _, p in ghosts], dtype=np.float64)
        plan = self._plan
        trs = (plan.current, *plan.queue)
        starts = [max(now, trs[0].t0_s)] + [q.t0_s for q in trs[1:]]
        ends = [q.t0_s for q in trs[1:]] + [max(trs[-1].t_end_s, now)]
        limit = self.params.check_drone_m
        for tr, t_a, t_b in zip(trs, starts, ends, strict=True):
            if t_b < now:
                continue
            ts = np.append(np.arange(max(t_a, now), t_b, 0.05), t_b)
            pts = tr.sample(ts)
            d = np.linalg.norm(pts[:, None, :] - g[None, :, :], axis=2)
            if float(d.min()) < limit:
                return True
        return False

    def _deviation(self, pid: int) -> np.ndarray | None:
        """Where ``pid`` last reported itself if that is further than ``peer_deviation_m``
        from its newest trajectory at the report's time, or would be ``peer_deviation_ahead_s``
        later if both went straight on (``_off_by``), else None. A report older than the
        trajectory's start is compared at that start, carried there at its velocity (until
        2026-12-01 it was not compared: a peer whose vehicle holds while its process
        announces plans along its path was, between each announcement and its next report,
        neither off its trajectory nor avoided where it holds). Under ``_peer_lock``."""
        if not math.isfinite(self.peer_deviation_m):
            return None
        st = self._heard.get(pid)
        seen = self._seen.get(pid)
        if st is None or st.position is None or seen is None:
            return None
        cached = self._deviation_cache.get(pid)
        if cached is not None and cached[0] is st and cached[1] is seen:
            return cached[2]
        out: np.ndarray | None = st.position
        tr = seen.msg.trajectory
        if self._off_by(st, tr) <= self.peer_deviation_m:
            out = None
        self._deviation_cache[pid] = (st, seen, out)
        return out

    def _off_by(self, st: _Heard, tr: Trajectory) -> float:
        """How far ``st`` is off ``tr``: at its stamp, and ``peer_deviation_ahead_s`` later if
        both went on at the velocity they have then (the larger). Both straight on: a peer that
        follows a turn or a braking of its trajectory is not off it. A report from before
        ``tr``'s start: at that start, the report carried there at its velocity, by position
        only (a new plan may turn from its start on)."""
        assert st.position is not None
        if tr.t0_s > st.stamp_s:  # a report from before the trajectory's start
            pos = st.position
            if st.velocity is not None:
                pos = pos + (tr.t0_s - st.stamp_s) * st.velocity
            return float(np.linalg.norm(pos - tr.sample(tr.t0_s)))
        gap = st.position - tr.sample(st.stamp_s)
        off = float(np.linalg.norm(gap))
        ahead = self.peer_deviation_ahead_s
        if st.velocity is None or ahead <= 0.0:
            return off
        dv = st.velocity - tr.sample(st.stamp_s, order=1)
        return max(off, float(np.linalg.norm(gap + ahead * dv)))

    # --- the cycle --------------------------------------------------------------------------

    def counters(self) -> dict[str, int]:
        """A snapshot: ``replans``, ``status.<value>`` per plan status, ``avoided`` (replans
        with some peer only avoided), ``silent`` (replans with some peer silent), ``quiet``
        (replans with some peer quiet, not silent), ``in_the_way`` (quiet peers whose ghosts
        ``watch`` found on our path),
        ``refused_older`` (older trajectories refused), ``seq`` (messages published)."""
        with self._cfg_lock:
            out = {f"status.{k}": v for k, v in self.status_counts.items()}
            out["replans"] = sum(self.status_counts.values())
            out["avoided"] = self.avoided_count
            out["silent"] = self.silent_count
            out["quiet"] = self.quiet_count
            out["in_the_way"] = self.in_the_way_count
            out["refused_older"] = self.refused_older
        out["seq"] = self._seq
        return out

    @property
    def last(self) -> PlanReport | None:
        """The latest replan's report."""
        return self._last

    @property
    def planner(self) -> FormationPlanner:
        """The planner of the current template and slot (all peers in the formation)."""
        a = self._assign
        return self._planner(a.formation, a.slot, 0)

    def announce(self, now_s: float) -> None:
        """Publish the trajectory in control (e.g. the initial hover) at ``now_s``."""
        a = self._assign
        self._publish(self.flying(now_s), a, now_s)

    def step(self, now_s: float, position: np.ndarray | None = None) -> PlanReport | None:
        """Advance to ``now_s`` and replan if due; the report, or None when not due."""
        self.advance(now_s)
        self.watch(now_s)
        if not self.due(now_s):
            return None
        return self.replan(now_s, position)

    def replan(self, now_s: float, position: np.ndarray | None = None) -> PlanReport:
        """One cycle at ``now_s`` (see the module docstring), due or not.

        position: where the drone is (ENU m), for map sources that sense around it; None: the
        commanded position ``flying(now_s)`` at ``now_s``. Raises ValueError without a goal.
        """
        with self._cycle_lock:
            return self._replan(float(now_s), position)

    def _replan(self, now: float, position: np.ndarray | None) -> PlanReport:
        c0 = self.timer()
        with self._cfg_lock:
            a = self._assign
            self._demand_s = math.inf
        if a.goal is None:
            raise ValueError(f"drone {self.drone_id}: no goal to plan to")
        p_now = self.flying(now).sample(now) if position is None else position
        field = self.map_source.snapshot(now, p_now)
        t_start = now + self.plan_ahead_s
        flying = self.flying(t_start)
        sp, sv, sa = flying.state(t_start)
        msgs, quiet, silent = self._peers_now(self.bus.receive(self.drone_id, now), a, now)
        formed, avoided = self._split_peers(msgs, a, now, silent)
        ghosts = [(pid, Trajectory.hover(p, now, HOVER_S)) for pid, p in self._ghosts(quiet, now)]
        deviating = self._deviating(msgs, quiet, a, now)
        ghosts += [(pid, Trajectory.hover(p, now, HOVER_S)) for pid, p in sorted(deviating.items())]
        n_form = a.formation.shape[0]
        n_av = len(avoided)
        peers = (
            tuple(PeerTrajectory(m.drone_id, m.slot, m.trajectory) for m in formed)
            + tuple(
                PeerTrajectory(m.drone_id, n_form + k, m.trajectory) for k, m in enumerate(avoided)
            )
            + tuple(PeerTrajectory(pid, n_form + n_av + k, g) for k, (pid, g) in enumerate(ghosts))
        )
        shape = (a.epoch, a.slot, a.formation.tobytes())
        if self._shape_seen is not None and shape != self._shape_seen:
            self._resume_at = 0  # what was given up was for the old shape
            self._reform_until_s = now + self.params.reform_s
            self._reform_hold_until_s = now + max(
                self.params.reform_s, self.params.reform_hold_max_s
            )
        self._shape_seen = shape
        reforming = self._reforming(now, sp, a, formed, t_start)
        recovering = False
        if not reforming and self.params.recover_e_sim > 0.0 and self.params.lead_slowdown_m > 0.0:
            if len(formed) >= 2 and (
                _shape_error(sp, a, formed, t_start) > self.params.recover_e_sim
            ):
                self._recover_until_s = now + self.params.recover_hold_s
            recovering = now < self._recover_until_s
        mode = _REFORM if reforming else _RECOVER if recovering else ""
        unheard = self._unheard
        planner = self._planner(a.formation, a.slot, n_av + len(ghosts), mode, bool(unheard))
        if self.on_inputs is not None:
            self.on_inputs(
                PlanInputs(
                    self.drone_id,
                    a.slot,
                    t_start,
                    sp,
                    sv,
                    sa,
                    a.goal,
                    peers,
                    field,
                    flying,
                    planner.formation,
                    None if not (avoided or ghosts) else planner.mask,
                    len(ghosts),
                    self._resume_at,
                )
            )
        self._active = planner
        p0 = self.timer()
        q0 = time.thread_time()
        give_up: Callable[[], bool] | None = None
        if math.isfinite(self.plan_budget_s):
            budget_end = p0 + self.plan_budget_s

            def give_up() -> bool:
                return self.timer() >= budget_end

        try:
            res = planner.plan(
                t_start, sp, sv, sa, a.goal, peers, field, flying, give_up, self._resume_at
            )
        finally:
            self._active = None
        self._resume_at = res.resume_at if res.status is PlanStatus.OVER_BUDGET else 0
        plan_ms = (self.timer() - p0) * 1e3
        plan_cpu_ms = (time.thread_time() - q0) * 1e3
        new = res.trajectory
        late = self._late(new, t_start)
        if late:
            # not flown: a plan that comes back after its start would move the setpoint
            # away from the trajectory in control, which has been flown since
            why = f"{late}; was {res.status.value}" + (f": {res.message}" if res.message else "")
            res = dataclasses.replace(res, status=PlanStatus.LATE, message=why)
            seq = -1
            self.request_replan()
        else:
            seq = self._publish(new, a, now, copies=self.resend_plans)
            self.schedule(new)
            if res.status is PlanStatus.OVER_BUDGET:
                self.request_replan()  # the attempts it gave up, from a newer start
        while self._next_replan_s <= now + EPS_T:
            self._next_replan_s += self.replan_period_s
        period = (
            self.params.reform_replan_period_s
            if reforming
            else self.params.recover_replan_period_s
            if recovering
            else 0.0
        )
        if period > 0.0:
            # the peers' re-shaping moves, each the answer to the others' last plans,
            # converge in replans, not in seconds
            self.request_replan(now + period)
        key = str(res.status.value)
        with self._cfg_lock:
            self.status_counts[key] = self.status_counts.get(key, 0) + 1
            if avoided:
                self.avoided_count += 1
            if silent:
                self.silent_count += 1
            if quiet - silent:
                self.quiet_count += 1
        report = PlanReport(
            drone_id=self.drone_id,
            seq=seq,
            planned_at_s=now,
            t_start_s=t_start,
            status=res.status,
            message=res.message,
            trajectory=new,
            iterations=int(res.iterations),
            evaluations=int(res.evaluations),
            plan_ms=plan_ms,
            cycle_ms=(self.timer() - c0) * 1e3,
            slot=a.slot,
            formation_epoch=a.epoch,
            goal=a.goal,
            formation_peers=tuple(m.drone_id for m in formed),
            avoided_peers=tuple(m.drone_id for m in avoided),
            peers=peers,
            silent_peers=tuple(sorted(silent)),
            deviating_peers=tuple(sorted(deviating)),
            quiet_peers=tuple(sorted(quiet - silent)),
            reforming=reforming,
            recovering=recovering,
            unheard_by=tuple(sorted(unheard)),
            plan_cpu_ms=plan_cpu_ms,
        )
        self._last = report
        if self.on_plan is not None:
            self.on_plan(report)
        return report

    def _late(self, new: Trajectory, t_start: float) -> str:
        """Why the plan ``new`` for ``t_start`` is not to be flown ('' to fly it): with a
        ``clock`` (the flight's; the fast-time simulator has none, its plans take no time),
        it came back after its start and would move the setpoint more than ``late_jump_m``
        from the trajectory in control."""
        if self.clock is None:
            return ""
        done = float(self.clock())
        if done <= t_start:
            return ""
        jump = float(np.linalg.norm(new.sample(done) - self.flying(done).sample(done)))
        if jump <= self.late_jump_m:
            return ""
        return f"done {done - t_start:.2f} s after its start, {jump:.2f} m off the flown one"

    def _publish(self, traj: Trajectory, a: _Assignment, now: float, copies: bool = True) -> int:
        """Any thread (a flight service announces its brakes from the thread that made them):
        the numbers go out in the order they are taken. Copies follow ``resend_s`` later
        (``copies``; either way, none of an older trajectory goes out after this one)."""
        with self._pub_lock:
            self._last_sent = (traj, a)
            self._resend_at = tuple(sorted(now + d for d in self.resend_s)) if copies else ()
            return self._send(traj, a, now)

    def _send(self, traj: Trajectory, a: _Assignment, now: float) -> int:
        """Under ``_pub_lock``."""
        seq = self._seq
        self._seq += 1
        if seq == 0:
            self.first_published_s = now
        self.last_published_s = now
        msg = TrajectoryMsg(
            self.drone_id,
            seq,
            a.slot,
            traj,
            formation_epoch=a.epoch,
            valid_until_s=now + self.validity_s,
        )
        self.bus.publish(msg, now)
        return seq

    def resend(self, now_s: float) -> bool:
        """Any thread, called often (a flight service's monitor, fast time's every step): when
        a copy of the last published trajectory is due (``resend_s`` after it; none once a
        newer one went out), send it (a new number, the same trajectory and assignment).
        Whether one went out: a look that comes late sends one copy for all that are due."""
        at = self._resend_at
        if not at or now_s < at[0] - EPS_T:
            return False
        with self._pub_lock:
            at = self._resend_at
            last = self._last_sent
            if not at or now_s < at[0] - EPS_T or last is None:
                return False
            self._resend_at = tuple(d for d in at if now_s < d - EPS_T)
            self._send(last[0], last[1], now_s)
            self.resent += 1
        return True

    def _take(self, msgs: dict[int, TrajectoryMsg], now: float) -> None:
        """Keep the newest trajectory of each peer from ``msgs``: an older one (lower
        ``traj_id``, or the same with an earlier start) never replaces a newer one. Under
        ``_peer_lock``."""
        for pid, m in msgs.items():
            if pid == self.drone_id:
                continue
            old = self._seen.get(pid)
            if old is not None:
                o = old.msg
                if m is o or (m.trajectory is o.trajectory and m.valid_until_s == o.valid_until_s):
                    continue  # the same message again
                if m.traj_id < o.traj_id or (
                    m.traj_id == o.traj_id and m.trajectory.t0_s < o.trajectory.t0_s - EPS_T
                ):
                    if self._refused.get(pid) is not m:  # each message counted once
                        self._refused[pid] = m
                        self.refused_older += 1
                    continue
            if math.isfinite(self.validity_s) and math.isfinite(m.valid_until_s):
                sent = m.valid_until_s - self.validity_s
            else:
                sent = now  # no better bound: when it was first seen
            if old is not None:
                sent = max(sent, old.sent_s)
            self._seen[pid] = _Seen(m, sent)

    def _reforming(
        self,
        now: float,
        sp: np.ndarray,
        a: _Assignment,
        formed: Sequence[TrajectoryMsg],
        t_s: float,
    ) -> bool:
        """Whether this replan re-forms (``reform_params``): within ``reform_s`` of the last
        formation change, and after it while the shape this drone sees (``_shape_error``) is
        further than ``reform_hold_e_sim`` from the template, up to ``reform_hold_max_s``. The
        hold ends for good at the first replan that sees the shape reached (or too few formation
        peers to judge it); shape recovery looks after it from then on."""
        p = self.params
        if p.lead_slowdown_m <= 0.0:
            return False
        if now < self._reform_until_s:
            return True
        if p.reform_hold_e_sim <= 0.0 or now >= self._reform_hold_until_s:
            return False
        if len(formed) >= 2 and _shape_error(sp, a, formed, t_s) > p.reform_hold_e_sim:
            return True
        self._reform_hold_until_s = -math.inf
        return False

    def _peers_now(
        self, msgs: dict[int, TrajectoryMsg], a: _Assignment, now: float
    ) -> tuple[dict[int, TrajectoryMsg], set[int], set[int]]:
        """Take the newest trajectory of each peer from ``msgs`` (an older one never replaces
        a newer one) and look at the peers (``_note``); the peers whose trajectory to consider
        (not ignored, not forgotten), the quiet peers whose ghosts to avoid (not ignored,
        ghosts not forgotten; the silent ones included) and the silent ones among them."""
        with self._peer_lock:
            self._take(msgs, now)
            self._note(now)
            out: dict[int, TrajectoryMsg] = {}
            quiet: set[int] = set()
            silent: set[int] = set()
            for pid in sorted(self._seen):
                if pid in a.ignore:
                    continue
                m = self._seen[pid].msg
                lim = self._silence_limit(pid)
                h = self._heard_s(pid)
                if self._is_quiet(pid, h, now) and now <= h + lim + max(
                    self.ghost_forget_s, self.peer_forget_s
                ):
                    quiet.add(pid)
                    if now - h > self._silent_limit(pid):
                        silent.add(pid)
                if now > min(m.valid_until_s, h + lim) + self.peer_forget_s:
                    continue  # its trajectory is forgotten
                out[pid] = m
        return out, quiet, silent

    def _deviating(
        self, msgs: dict[int, TrajectoryMsg], silent: set[int], a: _Assignment, now: float
    ) -> dict[int, np.ndarray]:
        """Where each peer of ``msgs`` that is not silent reported itself, if off its
        trajectory (``_deviation``); with ``avoid_reported``, also where each peer heard
        through states without a trajectory in ``msgs`` (never received, or forgotten) and not
        avoided at its ghosts reported itself last, until ``ghost_forget_s`` after it fell
        silent."""
        with self._peer_lock:
            out = {
                pid: p
                for pid in msgs
                if pid not in silent and (p := self._deviation(pid)) is not None
            }
            if self.avoid_reported:
                for pid in sorted(self._heard):
                    st = self._heard[pid]
                    if pid in msgs or pid in silent or pid in a.ignore or st.position is None:
                        continue  # avoided along its trajectory or at its ghosts, or not at all
                    if now - st.stamp_s <= self.peer_silence_s + self.ghost_forget_s:
                        out[pid] = st.position
            return out

    def peer_view(self, now_s: float) -> PeerView:
        """The peers as a plan made at ``now_s`` would see them: their trajectories still
        considered, the quiet peers' ghosts and the deviating peers' reported positions
        (module docstring). Reads the bus (newer trajectories are taken as a cycle takes
        them); changes nothing else. Any thread."""
        now = float(now_s)
        a = self._assign
        msgs, quiet, silent = self._peers_now(self.bus.receive(self.drone_id, now), a, now)
        hovers = self._ghosts(quiet, now)
        deviating = self._deviating(msgs, quiet, a, now)
        hovers += sorted(deviating.items())
        points = np.array([p for _, p in hovers], dtype=np.float64).reshape(-1, 3)
        points.setflags(write=False)
        return PeerView(
            t_s=now,
            trajectories=tuple(
                PeerTrajectory(pid, m.slot, m.trajectory) for pid, m in msgs.items()
            ),
            hover_ids=tuple(pid for pid, _ in hovers),
            hover_points=points,
            silent=tuple(sorted(silent)),
            deviating=tuple(sorted(deviating)),
            quiet=tuple(sorted(quiet - silent)),
        )

    def _ghosts(self, quiet: set[int], now: float) -> list[tuple[int, np.ndarray]]:
        """Where each quiet peer may have stopped (its ghosts, avoided as hovers): points
        ``ghost_spacing_m`` apart along its last reported position and its last trajectory
        from when it was last heard to ``ghost_window_s`` later (one replan period more without
        states; at most now), and along the straight lines PX4's failsafe would carry it on
        had it died up to ``COAST_DEATH_S`` after it was last heard (``_coast``)."""
        out: list[tuple[int, np.ndarray]] = []
        for pid in sorted(quiet):
            with self._peer_lock:
                seen = self._seen[pid]
                state = self._heard.get(pid)
                h = self._heard_s(pid)
                lim = self._silence_limit(pid)
            tr = seen.msg.trajectory
            t_a = max(h, tr.t0_s)
            t_b = max(t_a, min(now, h + lim - self.peer_silence_s + self.ghost_window_s))
            # the same messages and the same end: the same ghosts (once ``now`` is past the
            # window's end, every look until the peer is heard again)
            cached = self._ghost_cache.get(pid)
            if cached is not None:
                c_seen, c_state, c_a, c_b = cached[0]
                if c_seen is seen and c_state is state and c_a == t_a and c_b == t_b:
                    out.extend((pid, p) for p in cached[1])
                    continue
            ts = np.append(np.arange(t_a, t_b, 0.02), t_b)
            pts = tr.sample(ts)
            if state is not None and state.position is not None and state.stamp_s >= h - EPS_T:
                pts = np.vstack([state.position, pts])
            # the coasts from moments it may have died, 0.1 s apart (a state period; the
            # rest points of two such moments lie up to ~0.3 m apart at 1 m/s and 3 m/s^2),
            # each point kept only if no ghost is within half a spacing: every hover is a peer
            # the planner avoids
            t_d = min(t_b, t_a + lim - self.peer_silence_s + COAST_DEATH_S)
            ghosts = _spaced(pts, self.ghost_spacing_m)
            for t in np.linspace(t_a, t_d, 1 + int(math.ceil((t_d - t_a) / 0.1 - 1e-9))):
                for q in _spaced(self._coast(tr, t), self.ghost_spacing_m):
                    if np.min(np.linalg.norm(ghosts - q, axis=1)) >= 0.5 * self.ghost_spacing_m:
                        ghosts = np.vstack([ghosts, q])
            ghosts.setflags(write=False)
            self._ghost_cache[pid] = ((seen, state, t_a, t_b), ghosts)
            out.extend((pid, p) for p in ghosts)
        return out

    def _coast(self, tr: Trajectory, t: float) -> np.ndarray:
        """(2, 3): where a peer flying ``tr`` whose setpoints stop at ``t`` comes to rest,
        from where it was then: PX4's offboard-loss failsafe keeps the last setpoint for
        ``OFFBOARD_LOSS_S``, so the vehicle carries on in a straight line along the velocity it
        had (its trajectory may have turned away: a peer crossing toward us to pass behind us
        comes on toward us), slowing with gain ``PX4_POSITION_GAIN``, then brakes to a hold
        (half an ``a_max`` stop, as the flight service's ``braking_trajectory``)."""
        p, v, _ = tr.state(t)
        speed = float(np.linalg.norm(v))
        if speed < 1e-6:
            return np.stack([p, p])
        decay = math.exp(-PX4_POSITION_GAIN * OFFBOARD_LOSS_S)
        carry = speed * (1.0 - decay) / PX4_POSITION_GAIN
        v1 = speed * decay
        brake = braking_distance_m(v1, self.params.a_max_m_s2)
        return np.stack([p, p + v * ((carry + brake) / speed)])

    def _split_peers(
        self, msgs: dict[int, TrajectoryMsg], a: _Assignment, now: float, silent: set[int]
    ) -> tuple[list[TrajectoryMsg], list[TrajectoryMsg]]:
        """(formation peers, avoided-only peers), each by increasing drone id."""
        formed: list[TrajectoryMsg] = []
        avoided: list[TrajectoryMsg] = []
        n = a.formation.shape[0]
        for pid in sorted(msgs):
            m = msgs[pid]
            if pid in a.ignore or pid == self.drone_id:
                continue
            if (
                pid in a.avoid_only
                or pid in silent
                or now > m.valid_until_s
                or now - m.trajectory.t0_s > self.validity_s
                or m.formation_epoch != a.epoch
                or not 0 <= m.slot < n
                or m.slot == a.slot
            ):
                avoided.append(m)
            else:
                formed.append(m)
        claims = Counter(m.slot for m in formed)
        if any(c > 1 for c in claims.values()):
            avoided = sorted(
                avoided + [m for m in formed if claims[m.slot] > 1], key=lambda m: m.drone_id
            )
            formed = [m for m in formed if claims[m.slot] == 1]
        return formed, avoided

    def _planner(
        self,
        formation: np.ndarray,
        slot: int,
        n_avoided: int,
        mode: str = "",
        unheard: bool = False,
    ) -> FormationPlanner:
        """The planner of a template and slot with ``n_avoided`` isolated extra rows (cached);
        ``mode`` ``_REFORM``: with ``reform_params`` (``PlannerParams.reform_s``);
        ``_RECOVER``: with ``recover_params`` (``PlannerParams.recover_e_sim``); ``unheard``:
        with ``unheard_params`` on top (a peer does not hear us)."""
        key = (slot, formation.tobytes(), n_avoided, mode, unheard)
        hit = self._planners.get(key)
        if hit is not None:
            return hit
        if len(self._planners) > 16:
            self._planners.clear()
        params = self.params
        if mode == _REFORM:
            params = reform_params(params)
        elif mode == _RECOVER:
            params = recover_params(params)
        if unheard:
            params = unheard_params(params)
        if n_avoided == 0:
            planner = FormationPlanner(params, formation, slot, side=self._side)
        else:
            n = formation.shape[0]
            F = np.vstack([formation, np.zeros((n_avoided, 3))])
            mask = np.zeros((n + n_avoided, n + n_avoided))
            mask[:n, :n] = complete_mask(n)
            if params.formation_penalty == "relative":
                # fixed offsets ignore the edge mask: no formation term while some are avoided
                params = dataclasses.replace(params, w_formation=0.0)
            planner = FormationPlanner(params, F, slot, edge_mask=mask, side=self._side)
        self._planners[key] = planner
        return planner
