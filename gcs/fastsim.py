"""Fast-time swarm simulation: N onboard agents, an in-memory bus, perfect tracking.

Every drone is an ``onboard.agent.DroneAgent`` (the class the flight service runs), planning on
what it has sensed so far and on the latest
trajectories its peers broadcast (delivered with a delay). Drones track their trajectories
perfectly; the simulation checks collisions against the full world at ``dt_s`` (100 Hz) and
samples positions and the formation metric at 10 Hz. Simulated time runs as fast as the planner
allows; each plan call is timed with the wall clock.

Timeline of one replan of drone i at simulated time t (every ``replan_period_s``, drone i offset
by ``i * replan_period_s / N``): sense (obstacles with surface within ``sensing_radius_m`` join
the drone's own map), read peers from the bus, plan from the state of the trajectory in flight at
``t + plan_ahead_s``, publish at t; the new trajectory takes over at its start time (the
agent's cycle). What the simulator adds: the sensing (``SensedWorld`` or ``MappedView``), perfect
tracking of the trajectory in control, and the ``FlightMonitor`` that judges the flight.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from gcs.metrics import summary
from gcs.monitor import CollisionEvent, FlightMonitor, MonitorConfig, Tracks
from onboard.agent import (
    EPS_T,
    GHOST_WINDOW_S,
    MONITOR_BRAKE_WITHIN_S,
    MONITOR_REPLAN_AFTER_S,
    OFFBOARD_LOSS_S,
    PEER_DEVIATION_AHEAD_S,
    PLAN_AHEAD_S,
    PX4_POSITION_GAIN,
    REPLAN_PERIOD_S,
    RESEND_S,
    DroneAgent,
    MapSource,
    PlanInputs,
    peer_links,
    resend_delays,
)
from onboard.comm import InMemoryBus
from onboard.comm.faults import BusFaults, FaultyBus
from onboard.comm.hearing import HearingReport, not_hearing, report_from_links
from onboard.comm.messages import TrajectoryMsg
from onboard.config import Formation, WorldSpec, load_planner_params
from onboard.planner.field import AnalyticField, DistanceField
from onboard.planner.planner import APPROACH, LAST_RESORT
from onboard.planner.trajectory import Trajectory
from onboard.service.state import RETRY_AFTER_S
from onboard.world import World

if TYPE_CHECKING:
    from onboard.planner.params import PlannerParams
    from onboard.planner.planner import PeerTrajectory

PERCEPTIONS = ("ground-truth", "mapped")
KILL_MODELS = ("px4", "instant")


@dataclass(frozen=True)
class SimConfig:
    """One simulated flight. Lengths in metres, times in seconds (simulated)."""

    formation: Formation
    world: WorldSpec
    seed: int = 0
    v_max_m_s: float | None = None
    """Shorthand for ``planner.v_max_m_s``: the planner's parameters are the one owner of the
    speed limit. None takes the planner's; a value replaces the default planner's. Giving a
    ``planner`` and a different value here is an error. After construction both agree (use
    ``with_v_max`` to change the speed of a config)."""
    sensing_radius_m: float = 5.0
    replan_period_s: float = REPLAN_PERIOD_S
    plan_ahead_s: float = PLAN_AHEAD_S
    bus_delay_s: float = 0.05
    dt_s: float = 0.01
    """Step of motion and collision checks (100 Hz)."""
    sample_period_s: float = 0.1
    """Step of the recorded tracks and formation metrics (10 Hz)."""
    time_limit_s: float | None = None
    """None: 2 x (longest start-goal distance / v_max) + 30 s."""
    goal_tolerance_m: float = 0.5
    arrival_speed_m_s: float = 0.1
    collision_obstacle_m: float = 0.2
    """A drone collides when its centre is closer than this to an obstacle surface."""
    collision_drone_m: float = 0.4
    """Two drones collide when their centres are closer than this."""
    planner: PlannerParams | None = None
    """None: ``load_planner_params()`` (config/planner.yaml), with ``v_max_m_s`` if given. Always
    set after construction (``params``)."""
    silent_drones: tuple[int, ...] = ()
    """Drones whose broadcasts never reach anyone (a failed radio)."""
    radio_outages: dict[int, tuple[float, float]] = field(default_factory=dict)
    """Drone id -> (from, to) simulated seconds: nothing it sends in between (trajectories,
    states, statuses) reaches anyone; it still hears its peers (an uplink that fails for a
    while). Every drone's 1 Hz status tells the others whether it hears them
    (``onboard.comm.hearing``, as the flight service reads it; with ``bus_faults`` each copy is
    lost and delayed as a state would be): a drone that learns a peer does not hear it plans
    with ``PlannerParams.unheard_margin_m`` more."""
    formation_change: tuple[Formation, float] | None = None
    """(new template, simulated time): at that time every drone is given the new formation at
    once (the ground station's common effective time), its slot by minimum total distance from
    where the drones are (``gcs.formations.hungarian_slots`` over the template placed at their
    centroid, as the ground station assigns it) and its goal moved to the goal centre plus its
    new slot's offset; from then on the monitor scores e_sim, e_dist and arrival against the new
    shape. The result's ``formation_change`` says when the new shape was reached."""
    max_events: int = 20
    """Collision events kept in the result (all are counted)."""
    warmup: bool = True
    """Plan one small problem before the flight, untimed, so that replan_ms measures steady
    state rather than numba's compilation or cache loading (reported as ``warmup_s``)."""
    perception: str = "ground-truth"
    """'ground-truth': a drone's map is the exact distance to the obstacles it has come within
    sensing_radius_m of. 'mapped': each drone plans on the ESDF of its own occupancy map, built
    from simulated D435 depth frames taken along its flight (``onboard.sensors.simulated``)."""
    camera_rate_hz: float = 30.0
    """Depth frames per second per drone ('mapped')."""
    camera_skip_pixel: int = 2
    """Every n-th pixel row and column of a frame is rendered and ray cast ('mapped')."""
    occupancy_overrides: tuple[tuple[str, Any], ...] = ()
    """('mapped') ``OccupancyParams`` fields set on top of the drones' maps' defaults (field
    name, value), e.g. (("occluded_fill_m", 0.2),)."""
    bus_faults: BusFaults | None = None
    """Faults on every trajectory message (``onboard.comm.faults.FaultyBus`` around the bus,
    seeded with ``fault_seed``); receivers then keep the newest trajectory of each sender, as
    the Zenoh inbox does. None: the plain in-memory bus."""
    fault_seed: int = 0
    start_z_jitter_m: float = 0.0
    """Each drone starts up to this far (uniform, drawn from the seed) above or below its start
    altitude. A real vehicle never holds its altitude to the millimetre; started exactly level,
    a level formation flies exactly level (the formation term's vertical gradient is zero by
    symmetry), which hides a shape that tilts as soon as anything breaks the symmetry (issue
    #10: on the real stack, half a hexagon climbed to 3 m). 0: exact starts."""
    stuck_drones: dict[int, float] = field(default_factory=dict)
    """Drone id -> time: from then on its vehicle hovers where it is (a stuck airframe) and the
    drone keeps publishing that hover every ``replan_period_s``."""
    killed_drones: dict[int, float] = field(default_factory=dict)
    """Drone id -> time: its onboard process dies; it publishes nothing more and its vehicle
    fails safe as ``kill_model`` says."""
    kill_model: str = "px4"
    """How a killed drone's vehicle moves on. 'px4': as PX4 v1.16 does when the setpoint stream
    stops (REFERENCE_NOTES; the SITL mock does the same): its position controller keeps the
    last setpoint (position and velocity feed-forward) for ``offboard_loss_s`` (COM_OF_LOSS_T),
    so the vehicle carries on and slows (``p = p0 + v0 (1 - exp(-k t)) / k`` with ``k`` =
    ``px4_position_gain``, MPC_XY_P), then the failsafe brakes it to a hold. 'instant': it
    stops dead where it is (no vehicle can; the harshest case, kept for comparison)."""
    offboard_loss_s: float = OFFBOARD_LOSS_S
    """PX4's COM_OF_LOSS_T (v1.16 default 1.0 s), for ``kill_model`` 'px4'."""
    px4_position_gain: float = PX4_POSITION_GAIN
    """PX4's MPC_XY_P (v1.16 default 0.95 1/s), for ``kill_model`` 'px4'."""
    monitor_rate_hz: float = 0.0
    """The safety monitor of the flight service between replans (0: off): at this rate every
    flying drone checks the plan it will fly over ``monitor_horizon_s`` against its peers as it
    avoids them (``DroneAgent.peer_view``: their trajectories, ghosts, reported positions;
    refreshed every half state period, as the service does); a conflict closer than the
    planner's ``check_drone_m`` asks for a replan at once, and if it is still there within
    ``monitor_brake_after_s`` of a plan and less than ``monitor_brake_within_s`` ahead, the
    drone brakes (the service's conflict stop)."""
    monitor_horizon_s: float = 2.0
    monitor_brake_after_s: float = MONITOR_REPLAN_AFTER_S
    monitor_brake_within_s: float = MONITOR_BRAKE_WITHIN_S
    """A conflict further ahead than this that a fresh plan did not clear is left to the next
    replan (asked for ``monitor_brake_after_s`` after the last) instead of braking."""
    retry_after_s: float = RETRY_AFTER_S
    """The flight service's ``planning.retry_after_s``: a brake of the monitor is a failed plan
    to the service, which hovers this long before it replans, unless the stop itself is in a
    conflict (then at once, once per brake: ``FlightService.monitor_step``). 0: replans go on
    on their grid after a brake (the twin's rule before 2026-12-01)."""
    resend_s: tuple[float, ...] = RESEND_S
    """A braking stop or hover announced (every plan too with ``resend_plans``) goes out again
    this long after it unless a newer trajectory went out first (``DroneAgent.resend``; the
    flight service's ``planning.resend_s``); () once."""
    resend_plans: bool = False
    """True: plans are sent again too, not only braking stops and hovers (``DroneAgent``)."""
    validity_s: float = math.inf
    """Published trajectories are valid this long (``TrajectoryMsg.valid_until_s``); a peer
    past it leaves the formation term and is only avoided (``DroneAgent``)."""
    peer_forget_s: float = 10.0
    """An expired or silent peer is still avoided this long, then forgotten (``DroneAgent``)."""
    ghost_forget_s: float = 60.0
    """A silent peer's possible stop points (its vehicle holds there) are avoided this long
    after it fell silent; its last trajectory only ``peer_forget_s`` (``DroneAgent``)."""
    ghost_window_s: float = GHOST_WINDOW_S
    """A silent peer may have flown on this long after its newest message before it stopped
    (``DroneAgent``; ``onboard.agent.GHOST_WINDOW_S``: PX4's failsafe carries a killed drone's
    vehicle on for about 0.65 s worth of its speed, see ``kill_model``)."""
    peer_deviation_m: float = 0.3
    """A peer reported further than this from its trajectory (a stuck drone whose new hover is
    late) is also avoided where it reported itself (``DroneAgent``; tracking here is perfect)."""
    peer_deviation_ahead_s: float = PEER_DEVIATION_AHEAD_S
    """... and so is one that would be that far off it this long later if both went straight
    on at their velocities then (``DroneAgent``; 0: positions only)."""
    state_period_s: float = 0.1
    """Every drone whose process runs broadcasts its state (time, position) this often, over
    the bus's delay and ``bus_faults`` (drawn independently of the trajectories'); receivers
    pass the newest to ``DroneAgent.heard`` and call ``DroneAgent.watch``."""
    peer_silence_s: float = 0.5
    """A peer heard of nothing newer for this long is quiet (``DroneAgent``): avoided where it
    may have stopped, still in the formation; it is silent (out of the formation) once quiet
    longer than its link's recent quiet spells allow, at most ``DroneAgent``'s
    ``peer_silence_max_s`` (1.5 s). A follower close behind a drone that dies reaches it in
    under a second (0.8 s grazed one in bench faults seed 1000 trial 59). With 10 Hz states a
    live drone goes unheard this long with probability 3e-4 per look under 20 % loss, ~1 % with
    loss, 300 ms delays and reordering together (harmless: quiet, not silent). A peer whose
    ghosts lie in a drone's way is quiet for it already after ``DroneAgent``'s
    ``peer_silence_in_way_s`` (0.3 s) on a clean link (its longest recent quiet spell plus
    0.15 s, if longer)."""

    def __post_init__(self) -> None:
        positive = ("replan_period_s", "dt_s", "sample_period_s", "goal_tolerance_m")
        for name in positive:
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0")
        v = self.v_max_m_s
        if v is not None and not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"v_max_m_s must be > 0, got {v!r}")
        if self.planner is not None:
            params = self.planner
            if v is not None and v != params.v_max_m_s:
                raise ValueError(
                    f"v_max_m_s={v} differs from planner.v_max_m_s={params.v_max_m_s}: the "
                    "planner's parameters own the speed limit, give it once"
                )
        elif v is not None:
            params = load_planner_params(v_max_m_s=v)
        else:
            params = load_planner_params()
        object.__setattr__(self, "planner", params)
        object.__setattr__(self, "v_max_m_s", params.v_max_m_s)
        if self.plan_ahead_s < 0.0 or self.bus_delay_s < 0.0 or self.sensing_radius_m < 0.0:
            raise ValueError("plan_ahead_s, bus_delay_s and sensing_radius_m must be >= 0")
        if self.time_limit_s is not None and not self.time_limit_s > 0.0:
            raise ValueError("time_limit_s must be > 0")
        if not (math.isfinite(self.start_z_jitter_m) and 0.0 <= self.start_z_jitter_m <= 0.5):
            raise ValueError(f"start_z_jitter_m must be in [0, 0.5], got {self.start_z_jitter_m!r}")
        if self.perception not in PERCEPTIONS:
            raise ValueError(f"perception must be one of {PERCEPTIONS}, got {self.perception!r}")
        if not self.camera_rate_hz > 0.0 or self.camera_skip_pixel < 1:
            raise ValueError("camera_rate_hz must be > 0 and camera_skip_pixel >= 1")
        if self.bus_faults is not None and not isinstance(self.bus_faults, BusFaults):
            raise TypeError(f"bus_faults must be a BusFaults, got {type(self.bus_faults)}")
        if not self.validity_s > 0.0 or not self.peer_forget_s >= 0.0:
            raise ValueError("validity_s must be > 0 and peer_forget_s >= 0")
        if not (math.isfinite(self.state_period_s) and self.state_period_s > 0.0):
            raise ValueError(f"state_period_s must be > 0, got {self.state_period_s!r}")
        if not self.peer_silence_s > 0.0:
            raise ValueError(f"peer_silence_s must be > 0, got {self.peer_silence_s!r}")
        if not (math.isfinite(self.ghost_window_s) and self.ghost_window_s >= 0.0):
            raise ValueError(f"ghost_window_s must be >= 0, got {self.ghost_window_s!r}")
        if not self.peer_deviation_m > 0.0:
            raise ValueError(f"peer_deviation_m must be > 0, got {self.peer_deviation_m!r}")
        if not (math.isfinite(self.peer_deviation_ahead_s) and self.peer_deviation_ahead_s >= 0):
            raise ValueError(
                f"peer_deviation_ahead_s must be >= 0, got {self.peer_deviation_ahead_s!r}"
            )
        resend_delays(self.resend_s)
        if not self.ghost_forget_s >= 0.0:
            raise ValueError(f"ghost_forget_s must be >= 0, got {self.ghost_forget_s!r}")
        n = self.formation.n
        outages = {}
        for i, span in dict(self.radio_outages).items():
            if int(i) != i or not 0 <= int(i) < n:
                raise ValueError(f"radio_outages: drone {i!r} is not in the formation of {n}")
            a, b = (float(x) for x in span)
            if not (math.isfinite(a) and a >= 0.0 and b > a):
                raise ValueError(f"radio_outages[{i}]: expected 0 <= from < to, got {span!r}")
            outages[int(i)] = (a, b)
        object.__setattr__(self, "radio_outages", outages)
        for name in ("stuck_drones", "killed_drones"):
            faults = dict(getattr(self, name))
            for i, at in faults.items():
                if int(i) != i or not 0 <= int(i) < n:
                    raise ValueError(f"{name}: drone {i!r} is not in the formation of {n}")
                if not (math.isfinite(at) and at >= 0.0):
                    raise ValueError(f"{name}[{i}]: time must be finite and >= 0, got {at!r}")
            object.__setattr__(self, name, {int(i): float(t) for i, t in faults.items()})
        if self.kill_model not in KILL_MODELS:
            raise ValueError(f"kill_model must be one of {KILL_MODELS}, got {self.kill_model!r}")
        for name in ("offboard_loss_s", "px4_position_gain", "monitor_horizon_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        for name in (
            "monitor_rate_hz",
            "monitor_brake_after_s",
            "monitor_brake_within_s",
            "retry_after_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        if self.formation_change is not None:
            tpl, at = self.formation_change
            if not isinstance(tpl, Formation) or tpl.n != n:
                raise ValueError(
                    f"formation_change: expected a Formation of {n} points, got {tpl!r}"
                )
            if not (math.isfinite(at) and at >= 0.0):
                raise ValueError(f"formation_change: time must be finite and >= 0, got {at!r}")
            object.__setattr__(self, "formation_change", (tpl, float(at)))
        both = set(self.stuck_drones) & set(self.killed_drones)
        if both:
            raise ValueError(f"drones {sorted(both)} are both stuck_drones and killed_drones")

    @property
    def params(self) -> PlannerParams:
        """The planner parameters every drone flies with (speed limit included)."""
        assert self.planner is not None  # set by __post_init__
        return self.planner

    @property
    def speed_m_s(self) -> float:
        """The speed limit, ``params.v_max_m_s``."""
        return self.params.v_max_m_s

    def with_v_max(self, v_max_m_s: float) -> SimConfig:
        """This config with another speed limit (in the planner's parameters)."""
        return dataclasses.replace(
            self, planner=dataclasses.replace(self.params, v_max_m_s=v_max_m_s), v_max_m_s=None
        )


@dataclass(frozen=True, eq=False)
class PlanCall:
    """Everything one plan call received; enough to replay it (``gcs.cli bench planner``)."""

    drone_id: int
    slot: int
    t_start_s: float
    start_p: np.ndarray
    start_v: np.ndarray
    start_a: np.ndarray
    goal: np.ndarray
    peers: tuple[PeerTrajectory, ...]
    world: World
    previous: Trajectory | None
    mapped_field: DistanceField | None = None
    """The field the drone planned on when it was its own map (perception 'mapped': the
    ESDF, an immutable object of about 5 MB, so a recorder that keeps every call of a mapped
    flight keeps them all); None: the exact field of ``world``."""


@dataclass(frozen=True, eq=False)
class SimResult:
    """Outcome and metrics of one simulated flight."""

    success: bool
    """All drones arrived and no collision happened."""
    arrived: np.ndarray
    """(N,) bool: within goal tolerance and slower than the arrival speed at the end."""
    collisions: int
    obstacle_collisions: int
    drone_collisions: int
    events: tuple[CollisionEvent, ...]
    min_obstacle_clearance_m: float
    """Minimum over time and drones of the drone-centre-to-obstacle-surface distance."""
    min_obstacle_clearance_by_drone_m: np.ndarray
    """(N,) each drone's own minimum of ``min_obstacle_clearance_m``."""
    min_drone_distance_m: float
    max_speed_m_s: float
    """Highest drone speed at the 10 Hz sample instants."""
    e_sim_mean: float
    e_sim_max: float
    e_sim_mean_cluttered: float
    """Mean e_sim while the swarm's centroid is inside the cluttered x span."""
    e_dist_mean_cluttered: float
    """Mean e_dist over the same samples."""
    e_dist_mean: float
    e_dist_max: float
    flight_time_s: float
    timed_out: bool
    replan_ms: dict[str, float]
    iterations: dict[str, float]
    evaluations: dict[str, float]
    status_counts: dict[str, int]
    sim_wall_s: float
    warmup_s: float
    tracks: Tracks
    world: World
    starts: np.ndarray
    goals: np.ndarray
    formation_name: str
    world_name: str
    seed: int
    cluttered_x: tuple[float, float]
    config: dict[str, Any] = field(default_factory=dict)
    faults: dict[str, Any] = field(default_factory=dict)
    """The fault record: ``stale_formation_uses`` (formation peers whose message's validity had
    passed at the plan call: must be 0), ``expired_avoided_uses`` (expired peers only avoided,
    the designed reaction), ``peer_uses_audited``, ``killed`` / ``stuck`` (id -> time and
    position where the vehicle stopped), ``bus`` (the ``FaultyBus`` counters)."""

    formation_change: dict[str, Any] = field(default_factory=dict)
    """With ``SimConfig.formation_change``: ``name``, ``at_s`` (simulated time of the change),
    ``slots`` (drone id -> its slot in the new template) and ``reached_s`` (from the change to
    the first sample with e_sim below ``FORMATION_REACHED_E_SIM``; None if never). Empty
    without a change."""

    refusals: dict[str, int] = field(default_factory=dict)
    """Optimised attempts the safety check refused, over all replans (a replan that ends
    ok-no-formation, kept-previous or emergency refused one or more): ``attempts`` in all,
    ``unobserved`` of them because they entered unobserved map space, or came within
    ``check_known_margin_m`` of it, within ``check_known_s``, ``obstacle`` / ``drone`` /
    ``altitude`` for those reasons (from the plan reports' messages); ``approach`` /
    ``last_resort``: replans that flew a refused way toward a conflict far ahead
    (``APPROACH``), or one no closer than a stop
    (``count_refusals``)."""

    def to_json(self, include_tracks: bool = False) -> dict[str, Any]:
        """A JSON-serialisable summary (tracks only when asked: they are large)."""
        out: dict[str, Any] = {
            "success": bool(self.success),
            "arrived": [bool(a) for a in self.arrived],
            "n_arrived": int(np.sum(self.arrived)),
            "n_drones": int(self.arrived.shape[0]),
            "collisions": int(self.collisions),
            "obstacle_collisions": int(self.obstacle_collisions),
            "drone_collisions": int(self.drone_collisions),
            "events": [dataclasses.asdict(e) for e in self.events],
            "min_obstacle_clearance_m": _num(self.min_obstacle_clearance_m),
            "min_obstacle_clearance_by_drone_m": [
                _num(c) for c in self.min_obstacle_clearance_by_drone_m
            ],
            "min_drone_distance_m": _num(self.min_drone_distance_m),
            "max_speed_m_s": _num(self.max_speed_m_s),
            "e_sim_mean": _num(self.e_sim_mean),
            "e_sim_max": _num(self.e_sim_max),
            "e_sim_mean_cluttered": _num(self.e_sim_mean_cluttered),
            "e_dist_mean_cluttered": _num(self.e_dist_mean_cluttered),
            "e_dist_mean": _num(self.e_dist_mean),
            "e_dist_max": _num(self.e_dist_max),
            "flight_time_s": _num(self.flight_time_s),
            "timed_out": bool(self.timed_out),
            "replan_ms": {k: _num(v) for k, v in self.replan_ms.items()},
            "iterations": {k: _num(v) for k, v in self.iterations.items()},
            "evaluations": {k: _num(v) for k, v in self.evaluations.items()},
            "status_counts": dict(self.status_counts),
            "refusals": dict(self.refusals),
            "formation_change": dict(self.formation_change),
            "sim_wall_s": _num(self.sim_wall_s),
            "warmup_s": _num(self.warmup_s),
            "formation": self.formation_name,
            "world": self.world_name,
            "seed": int(self.seed),
            "cluttered_x": [float(x) for x in self.cluttered_x],
            "n_obstacles": {
                "cylinders": int(self.world.cylinders.shape[0]),
                "rings": int(self.world.rings.shape[0]),
                "boxes": int(self.world.boxes.shape[0]),
            },
            "starts": self.starts.tolist(),
            "goals": self.goals.tolist(),
            "config": self.config,
            "faults": self.faults,
        }
        if include_tracks:
            out["tracks"] = {
                "t": self.tracks.t.tolist(),
                "pos": self.tracks.pos.tolist(),
                "e_sim": self.tracks.e_sim.tolist(),
                "e_dist": self.tracks.e_dist.tolist(),
            }
        return out


REFUSAL_KEYS = (
    "attempts",
    "unobserved",
    "unobserved_near",
    "obstacle",
    "drone",
    "altitude",
    "other",
    "approach",
    "last_resort",
)
_ATTEMPT_PREFIXES = ("formation", "a* retry")


def count_refusals(message: str, counts: dict[str, int]) -> None:
    """Add the attempts a plan's message says the safety check refused to ``counts``
    (``REFUSAL_KEYS``): the planner joins one "<attempt>: <reason>" per refused attempt
    (``FormationPlanner.plan``) with "; ". ``approach`` and ``last_resort`` count the plans
    flown although every attempt was refused (the message ends with ``APPROACH`` or
    ``LAST_RESORT``); ``unobserved_near``, of the ``unobserved``, those refused for coming near
    unobserved space rather than entering it (``check_known_margin_m``)."""
    if message.endswith(APPROACH):
        counts["approach"] += 1
    elif message.endswith(LAST_RESORT):
        counts["last_resort"] += 1
    for part in message.split("; "):
        if not part.startswith(_ATTEMPT_PREFIXES) or ": " not in part:
            continue
        why = part.split(": ", 1)[1]
        counts["attempts"] += 1
        if why.startswith(("enters unobserved space", "unobserved space")):
            counts["unobserved"] += 1
            if why.startswith("unobserved space"):  # its neighbourhood, check_known_margin_m
                counts["unobserved_near"] += 1
        elif why.startswith("obstacle clearance"):
            counts["obstacle"] += 1
        elif why.startswith("drone "):
            counts["drone"] += 1
        elif why.startswith("altitude"):
            counts["altitude"] += 1
        else:
            counts["other"] += 1


def _num(x: float) -> float | int | None:
    """JSON has no NaN/inf: map them to null (integers stay integers)."""
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return int(x)
    x = float(x)
    return x if math.isfinite(x) else None


def default_time_limit_s(starts: np.ndarray, goals: np.ndarray, v_max_m_s: float) -> float:
    """2 x (longest start-goal distance / v_max) + 30 s."""
    return float(np.max(np.linalg.norm(goals - starts, axis=1))) / v_max_m_s * 2.0 + 30.0


def _config_summary(cfg: SimConfig, params: PlannerParams) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        if f.name in ("formation", "world", "planner"):
            continue
        v = getattr(cfg, f.name)
        if isinstance(v, BusFaults):
            v = dataclasses.asdict(v)
        elif f.name == "formation_change" and v is not None:
            v = {"name": v[0].name, "at_s": v[1], "points": np.asarray(v[0].points).tolist()}
        elif isinstance(v, dict):
            v = {str(k): x for k, x in v.items()}
        elif isinstance(v, float):
            v = _num(v)  # validity_s = inf
        out[f.name] = list(v) if isinstance(v, tuple) else v
    out["planner"] = _jsonable(dataclasses.asdict(params))
    return out


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return _num(float(x))
    if isinstance(x, np.integer):
        return int(x)
    if hasattr(x, "value") and not isinstance(x, (int, str, bool)):  # enums
        return _jsonable(x.value)
    return x


class PeerAudit:
    """The swarm bus as the agents see it in the simulator, instrumented.

    ``receive`` keeps, per receiver, the newest trajectory of each sender (by ``traj_id``: a
    late, reordered or duplicated copy never replaces a newer one, as the Zenoh inbox's gate
    does) and hands out every sender's latest, expired ones included (as the flight service's
    ``PortPeerBus`` does: the agent avoids them and leaves them out of the formation).
    ``check`` (called with every plan call's inputs) finds the message each peer trajectory
    came from and counts formation peers whose validity had passed at the plan call
    (``stale_formation_uses``: a fault), expired peers only avoided (``expired_avoided_uses``),
    trajectories that came from no delivered message (``unknown_uses``: a fault) and the silent
    peers' ghost hovers the agent added (``ghost_uses``).
    """

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self._latest: dict[int, dict[int, TrajectoryMsg]] = {}
        self._last: dict[int, tuple[float, dict[int, TrajectoryMsg]]] = {}
        self.counters = dict.fromkeys(
            (
                "peer_uses_audited",
                "stale_formation_uses",
                "expired_avoided_uses",
                "unknown_uses",
                "refused_older",
                "ghost_uses",
            ),
            0,
        )

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        self.inner.publish(msg, now_s)

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        seen = self._latest.setdefault(drone_id, {})
        for sender, m in self.inner.receive(drone_id, now_s).items():
            prev = seen.get(sender)
            if prev is not None and m.traj_id < prev.traj_id:
                self.counters["refused_older"] += 1
                continue
            seen[sender] = m
        out = dict(sorted(seen.items()))
        self._last[drone_id] = (now_s, out)
        return out

    def check(self, inputs: PlanInputs) -> None:
        """Audit the peers of one plan call (``DroneAgent``'s ``on_inputs``)."""
        now, msgs = self._last.get(inputs.drone_id, (math.nan, {}))
        n_form = int(inputs.formation.shape[0])
        if inputs.edge_mask is not None:  # avoided-only peers take the isolated extra rows
            n_form = int(np.count_nonzero(np.any(inputs.edge_mask != 0.0, axis=1)))
        c = self.counters
        n_real = len(inputs.peers) - inputs.n_ghosts
        c["ghost_uses"] += inputs.n_ghosts  # hovers where a silent peer may have stopped
        for p in inputs.peers[:n_real]:
            c["peer_uses_audited"] += 1
            m = msgs.get(p.drone_id)
            if m is None or m.trajectory is not p.trajectory:
                c["unknown_uses"] += 1
                continue
            if not now <= m.valid_until_s:
                if p.slot < n_form:
                    c["stale_formation_uses"] += 1
                else:
                    c["expired_avoided_uses"] += 1


@dataclass(frozen=True, eq=False)
class StateMsg:
    """A drone's 10 Hz state in the simulator: sender, stamp (its global time), position,
    velocity."""

    drone_id: int
    seq: int
    stamp_s: float
    position: np.ndarray
    velocity: np.ndarray | None = None


STATUS_PERIOD_S = 1.0
"""Every drone's status (what it says about its links to its peers) goes out this often, as
the flight service's does."""


def _radio_out(outages: dict[int, tuple[float, float]], drone: int, t: float) -> bool:
    """Is ``drone``'s uplink out at ``t`` (``SimConfig.radio_outages``)?"""
    span = outages.get(drone)
    return span is not None and span[0] <= t < span[1]


class _Uplinks:
    """The trajectory bus as the agents see it: what a drone publishes while its uplink is out
    (``SimConfig.radio_outages``) reaches nobody."""

    def __init__(self, inner: Any, outages: dict[int, tuple[float, float]]) -> None:
        self.inner = inner
        self.outages = outages
        self.dropped = 0

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        if _radio_out(self.outages, msg.drone_id, now_s):
            self.dropped += 1
            return
        self.inner.publish(msg, now_s)

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        out: dict[int, TrajectoryMsg] = self.inner.receive(drone_id, now_s)
        return out


class StateChannel:
    """Where the simulator's state messages travel: each becomes visible ``delay_s`` after it
    is handed over, and a receiver gets the newest (by stamp) of every sender that has arrived,
    as a subscriber that passes each state to ``DroneAgent.heard`` would keep it (a late copy
    never hides a newer state; a bus that keeps only the last delivered would). Senders in
    ``silent`` reach nobody."""

    def __init__(self, delay_s: float, silent: frozenset[int] = frozenset()) -> None:
        self.delay_s = float(delay_s)
        self.silent = silent
        self._pending: list[tuple[float, int, StateMsg]] = []
        self._n = 0
        self._newest: dict[int, StateMsg] = {}

    def publish(self, msg: StateMsg, now_s: float) -> None:
        heapq.heappush(self._pending, (float(now_s) + self.delay_s, self._n, msg))
        self._n += 1

    def receive(self, drone_id: int, now_s: float) -> dict[int, StateMsg]:
        while self._pending and self._pending[0][0] <= now_s:
            _, _, m = heapq.heappop(self._pending)
            old = self._newest.get(m.drone_id)
            if old is None or m.stamp_s > old.stamp_s:
                self._newest[m.drone_id] = m
        return {s: m for s, m in self._newest.items() if s != drone_id and s not in self.silent}


class SensedWorld:
    """A drone's map in the ground-truth perception: the exact distance to every obstacle whose
    surface has come within ``radius_m`` of the drone at one of its replans (a ``MapSource``)."""

    def __init__(self, world: World, radius_m: float) -> None:
        self.world = world
        self.radius_m = radius_m
        self.seen = World.empty(world.ground_z)
        self._field = AnalyticField(self.seen)

    def snapshot(self, now_s: float, position: np.ndarray) -> DistanceField:
        new = self.seen.merged(self.world.within(position, self.radius_m))
        if new.n_primitives != self.seen.n_primitives:
            self.seen = new
            self._field = AnalyticField(new)
        return self._field


class MappedView:
    """The 'mapped' perception: the drone senses like ``SensedWorld`` (kept for the plan-call
    records) but plans on the ESDF of its own simulated depth camera's map."""

    def __init__(self, sensed: SensedWorld, eyes: Any) -> None:
        self.sensed = sensed
        self.eyes = eyes

    def snapshot(self, now_s: float, position: np.ndarray) -> DistanceField:
        self.sensed.snapshot(now_s, position)
        field: DistanceField = self.eyes.field()
        return field


def _warm_up(planner: Any, starts: np.ndarray, peer_type: Any) -> float:
    """Plan a 3 m hop of drone 0 among its hovering peers in an empty world; returns seconds."""
    t0 = time.perf_counter()
    peers = [peer_type(i, i, Trajectory.hover(starts[i], 0.0, 30.0)) for i in range(1, len(starts))]
    z3 = np.zeros(3)
    goal = starts[0] + np.array([3.0, 0.0, 0.0])
    planner.plan(0.0, starts[0], z3, z3, goal, peers, AnalyticField(World.empty()), None)
    return time.perf_counter() - t0


def _piece(
    start: tuple[np.ndarray, np.ndarray, np.ndarray],
    end: tuple[np.ndarray, np.ndarray, np.ndarray],
    duration_s: float,
) -> np.ndarray:
    """The quintic from (p, v, a) ``start`` to ``end`` in ``duration_s``: coeffs (6, 3)."""
    from onboard.planner.minco import Minco

    m = Minco(1)
    m.set_conditions(np.stack(start), np.stack(end))
    m.set_parameters(np.zeros((0, 3)), np.array([duration_s]))
    return np.asarray(m.coeffs, dtype=np.float64).reshape(-1, 6, 3)[0]


def offboard_loss_trajectory(
    t0_s: float,
    p: np.ndarray,
    v: np.ndarray,
    a: np.ndarray,
    loss_s: float,
    gain: float,
    a_max_m_s2: float,
    hold_s: float,
) -> Trajectory:
    """How a PX4 vehicle moves on once its setpoint stream stops at ``t0_s`` in state
    (``p``, ``v``, ``a``): for ``loss_s`` its position controller keeps the last setpoint, a
    position with velocity feed-forward, so (velocity tracked, gain ``gain``) it carries on
    along ``p + v (1 - exp(-gain t)) / gain``, slowing; then the failsafe brakes it to rest
    (the service's braking stop, about a third of ``a_max_m_s2``) and it holds there for
    ``hold_s``. Each phase is one quintic matching position, velocity and acceleration at its
    ends (the first one starts with the vehicle's own acceleration: within ~2 cm of the
    exponential at 1 m/s, within millimetres when that acceleration is the loop's)."""
    from onboard.service.ports import braking_trajectory

    p, v, a = (np.asarray(x, dtype=np.float64).reshape(3) for x in (p, v, a))
    decay = math.exp(-gain * loss_s)
    p1 = p + v * (1.0 - decay) / gain
    v1 = v * decay
    a1 = -gain * v1
    first = _piece((p, v, a), (p1, v1, a1), loss_s)
    brake = braking_trajectory(t0_s + loss_s, p1, v1, a1, a_max_m_s2)
    rest = brake.sample(brake.t_end_s)
    hold = np.zeros((6, 3))
    hold[0] = rest
    coeffs = np.stack([first, brake.coeffs[0], hold])
    durations = np.array([loss_s, float(brake.durations_s[0]), max(hold_s, 1.0)])
    return Trajectory(t0_s, coeffs, durations)


class SafetyMonitor:
    """The flight service's monitor between replans, in fast time (``SimConfig.monitor_*``):
    one per drone; ``look`` checks the plan the drone will fly over the horizon against its
    peers as it avoids them and reacts as the service does (a replan at once; a braking stop
    if a plan made a moment ago did not clear it)."""

    def __init__(self, cfg: SimConfig, state_period_s: float) -> None:
        self.horizon_s = cfg.monitor_horizon_s
        self.brake_after_s = cfg.monitor_brake_after_s
        self.a_max = cfg.params.a_max_m_s2
        self.view_age_s = 0.5 * state_period_s
        self.view: Any = None
        self._key: tuple[Any, ...] = ()
        self._problem = ""
        self._at = math.inf
        self._helps = True
        self.no_better_stop = 0
        self.brake_within_s = cfg.monitor_brake_within_s
        self.last_plan_s = -math.inf
        self.asked_s = -math.inf
        self.brake_at_s = -math.inf
        self.retry_after_s = cfg.retry_after_s
        self.hold_until_s = -math.inf
        """No replan before this (the service's hover after a brake)."""
        self.replans = 0
        self.brakes = 0
        self.braking_retries = 0

    def look(self, agent: DroneAgent, t: float) -> str:
        """'' when clear, else what was done ('replan: ...' or 'brake: ...')."""
        from onboard.agent import (
            MONITOR_RETRY_S,
            monitor_action,
            monitor_step_index,
            monitor_times,
            peer_conflict,
            replan_asked_s,
        )
        from onboard.service.ports import braking_trajectory

        view = self.view
        if view is None or not 0.0 <= t - view.t_s < self.view_age_s - EPS_T:
            view = self.view = agent.peer_view(t)
        if not view.trajectories and not view.hover_ids:
            return ""
        # on a fixed grid: a look with the same view, plan and grid step finds what the
        # previous one found, so it is not computed again
        g = monitor_step_index(t)
        # the service's check distance and stop window: wider while a peer does not hear us
        key = (view, agent.plan_token, g, agent.unheard_by)
        last = self._key  # the same objects (not equal ones: views hold arrays), same step
        if not (
            last and last[0] is view and last[1] is key[1] and last[2] == g and last[3] == key[3]
        ):
            self._key = key
            ts = monitor_times(g, self.horizon_s)
            pp, vv, aa = agent.state(t)
            brake = braking_trajectory(t, pp, vv, aa, self.a_max, peak_fraction=1.0)
            self._problem, self._at, self._helps = peer_conflict(
                view, t, ts, agent.planned(ts), agent.check_drone_m, brake.sample(ts),
                agent.brake_reference_s,
            )  # fmt: skip
        problem = self._problem
        if not problem:
            return ""
        action = monitor_action(
            t,
            self._at,
            self.last_plan_s,
            self.brake_at_s,
            t >= self.hold_until_s,  # the service hovers after a brake: no replan, no watching
            self.brake_after_s,
            self.brake_within_s,
            self.asked_s,
        )
        if action == "replan":
            self.replans += 1
            self.asked_s = replan_asked_s(self.asked_s, self.last_plan_s, t)
            agent.request_replan()
        if action == "braking" and t < self.hold_until_s:
            # the stop after the brake is in a conflict itself: retry now (the service's rule)
            self.hold_until_s = t
            self.braking_retries += 1
            agent.request_replan()
        if action != "brake":
            return f"{action}: {problem}"
        if not self._helps:  # a braking stop would come as close (``service.monitor_step``)
            self.no_better_stop += 1
            if t - self.last_plan_s >= MONITOR_RETRY_S:
                agent.request_replan()
            return f"no better stop: {problem}"
        self.brake_at_s = t
        self.brakes += 1
        self.hold_until_s = t + self.retry_after_s
        pp, vv, aa = agent.state(t)
        agent.reset(braking_trajectory(t, pp, vv, aa, self.a_max, peak_fraction=1.0))
        agent.announce(t)
        return f"brake: {problem}"


def build_flight(cfg: SimConfig) -> tuple[World, np.ndarray, np.ndarray]:
    """(world, starts, goals) of ``cfg``'s flight: the world spec built from the seed, the
    starts moved by ``start_z_jitter_m`` (drawn from a stream of its own, so that the world
    and the goals are those of the same seed without jitter)."""
    world, starts, goals = cfg.world.build(cfg.seed, cfg.formation)
    if cfg.start_z_jitter_m > 0.0:
        rng = np.random.default_rng((cfg.seed, 0x7A))
        starts = starts.copy()
        starts[:, 2] += rng.uniform(-cfg.start_z_jitter_m, cfg.start_z_jitter_m, len(starts))
    return world, starts, goals


def run_sim(
    cfg: SimConfig,
    recorder: Callable[[PlanCall], None] | None = None,
    progress: Callable[[float, float], None] | None = None,
) -> SimResult:
    """Fly ``cfg.formation`` through ``cfg.world`` (seeded) and measure the flight.

    recorder: called with every plan call's inputs before the call. progress: called about once
    per simulated second with (t_s, time_limit_s).
    """
    from onboard.planner.planner import PeerTrajectory

    wall0 = time.perf_counter()
    world, starts, goals = build_flight(cfg)
    n = cfg.formation.n
    params = cfg.params
    t_limit = (
        cfg.time_limit_s
        if cfg.time_limit_s is not None
        else default_time_limit_s(starts, goals, params.v_max_m_s)
    )
    silent = frozenset(cfg.silent_drones)
    plain = InMemoryBus(cfg.bus_delay_s, drop=(lambda s, r: s in silent) if silent else None)
    faulty = (
        FaultyBus(plain, cfg.bus_faults, seed=cfg.fault_seed, gate=False)
        if cfg.bus_faults is not None
        else None
    )
    bus = PeerAudit(plain if faulty is None else faulty)
    outages = dict(cfg.radio_outages)
    uplinks = _Uplinks(bus, outages)
    # states travel the same way, their faults drawn from their own generator
    state_plain = StateChannel(cfg.bus_delay_s, silent)
    state_faulty = (
        FaultyBus(cast(Any, state_plain), cfg.bus_faults, seed=cfg.fault_seed + 7919, gate=False)
        if cfg.bus_faults is not None
        else None
    )
    state_bus: Any = state_plain if state_faulty is None else state_faulty
    sensed = [SensedWorld(world, cfg.sensing_radius_m) for _ in range(n)]
    eyes = _mapped_perception(cfg, world, starts, goals) if cfg.perception == "mapped" else None
    from onboard.sensors.simulated import look_velocity

    maps: list[MapSource] = (
        list(sensed) if eyes is None else [MappedView(sensed[i], eyes[i]) for i in range(n)]
    )

    def record(inputs: PlanInputs) -> None:
        bus.check(inputs)
        if recorder is None:
            return
        i = inputs.drone_id
        recorder(
            PlanCall(
                i,
                inputs.slot,
                inputs.t_start_s,
                inputs.start_p,
                inputs.start_v,
                inputs.start_a,
                inputs.goal,
                inputs.peers,
                sensed[i].seen,
                inputs.previous,
                inputs.field if eyes is not None else None,
            )
        )

    agents = [
        DroneAgent(
            i,
            params,
            cfg.formation.points,
            i,
            Trajectory.hover(starts[i], 0.0),
            uplinks,
            maps[i],
            goal=goals[i],
            replan_period_s=cfg.replan_period_s,
            plan_ahead_s=cfg.plan_ahead_s,
            first_replan_s=i * cfg.replan_period_s / n,
            validity_s=cfg.validity_s,
            peer_forget_s=cfg.peer_forget_s,
            peer_silence_s=cfg.peer_silence_s,
            ghost_forget_s=cfg.ghost_forget_s,
            ghost_window_s=cfg.ghost_window_s,
            peer_deviation_m=cfg.peer_deviation_m,
            peer_deviation_ahead_s=cfg.peer_deviation_ahead_s,
            on_inputs=record,
            resend_s=cfg.resend_s,
            resend_plans=cfg.resend_plans,
        )
        for i in range(n)
    ]
    monitors = (
        [SafetyMonitor(cfg, cfg.state_period_s) for _ in range(n)]
        if cfg.monitor_rate_hz > 0.0
        else []
    )
    monitor_every = max(1, round(1.0 / (cfg.monitor_rate_hz * cfg.dt_s))) if monitors else 1
    warmup_s = _warm_up(agents[0].planner, starts, PeerTrajectory) if cfg.warmup else 0.0
    for ag in agents:
        ag.announce(0.0)
    next_frame_s = 0.0
    next_state_s = 0.0
    state_seq = 0
    next_status_s = 0.0
    # what each drone's peers' statuses last said about their link to it
    hearing: list[dict[int, HearingReport]] = [{} for _ in range(n)]
    # statuses on their way: (arrival, seq, receiver, report)
    status_mail: list[tuple[float, int, int, HearingReport]] = []
    status_n = itertools.count()
    status_faults = cfg.bus_faults
    status_rng = np.random.default_rng(cfg.fault_seed + 104729)

    def status_lag() -> float | None:
        """How long a copy of a status takes to one receiver (None: lost): by the next look on
        a clean bus; with bus faults, lost and delayed as a state would be (its own
        generator, two draws a copy)."""
        f = status_faults
        if f is None:
            return cfg.state_period_s
        lost = status_rng.random() < f.loss
        lag = f.delay_min_s + (f.delay_max_s - f.delay_min_s) * status_rng.random()
        return None if lost else lag

    unheard_plans = 0

    replan_ms: list[float] = []
    iterations: list[float] = []
    evaluations: list[float] = []
    status_counts: dict[str, int] = {}
    refusals = dict.fromkeys(REFUSAL_KEYS, 0)

    def replan(ag: DroneAgent, t: float, p_now: np.ndarray) -> None:
        # the states that have arrived by now (a service's subscriber hands them over as they
        # come; between the 10 Hz looks a peer would seem up to 0.1 s quieter than it is)
        for sender, sm in state_bus.receive(ag.drone_id, t).items():
            ag.heard(sender, sm.stamp_s, sm.position, sm.velocity)
        nonlocal unheard_plans
        rep = ag.replan(t, p_now)
        unheard_plans += bool(rep.unheard_by)
        replan_ms.append(rep.plan_ms)
        iterations.append(float(rep.iterations))
        evaluations.append(float(rep.evaluations))
        key = str(rep.status.value)
        status_counts[key] = status_counts.get(key, 0) + 1
        count_refusals(rep.message, refusals)

    dt = cfg.dt_s
    mon = FlightMonitor(
        world,
        goals,
        cfg.formation.points,
        MonitorConfig(
            dt_s=dt,
            sample_period_s=cfg.sample_period_s,
            goal_tolerance_m=cfg.goal_tolerance_m,
            arrival_speed_m_s=cfg.arrival_speed_m_s,
            collision_obstacle_m=cfg.collision_obstacle_m,
            collision_drone_m=cfg.collision_drone_m,
            max_events=cfg.max_events,
        ),
    )
    progress_every = max(1, int(round(1.0 / dt)))
    n_steps_max = int(math.ceil(t_limit / dt))
    pos = np.empty((n, 3))
    vel = np.empty((n, 3))

    def velocities() -> np.ndarray:
        for i, ag in enumerate(agents):
            vel[i] = ag.current.sample(t, order=1)
        return vel

    killed = dict(cfg.killed_drones)
    stuck = dict(cfg.stuck_drones)
    stopped: dict[int, tuple[float, list[float]]] = {}  # drone -> (time, position) it stopped
    stuck_next: dict[int, float] = {}  # next publication of a stuck drone's hover
    healthy = np.array([i not in killed and i not in stuck for i in range(n)])
    change = cfg.formation_change
    change_record: dict[str, Any] | None = None
    timed_out = True
    t = 0.0
    for k in range(n_steps_max + 1):
        t = k * dt
        for i, ag in enumerate(agents):
            pos[i] = ag.advance(t).sample(t)
            at = killed.get(i, stuck.get(i, math.inf))
            if i not in stopped and t >= at - EPS_T:
                # queued plans are dropped with the process (or the stuck airframe's plans);
                # the vehicle stops dead (stuck; a killed one with kill_model 'instant') or
                # carries on along PX4's offboard-loss failsafe (killed, 'px4')
                if i in killed and cfg.kill_model == "px4":
                    p_k, v_k, a_k = ag.state(t)
                    ag.reset(
                        offboard_loss_trajectory(
                            t,
                            p_k,
                            v_k,
                            a_k,
                            cfg.offboard_loss_s,
                            cfg.px4_position_gain,
                            params.a_max_m_s2,
                            t_limit - t + 1.0,
                        )
                    )
                else:
                    ag.reset(Trajectory.hover(pos[i], t, t_limit - t + 1.0))
                stopped[i] = (t, pos[i].tolist())
                if i in stuck:
                    stuck_next[i] = t
        for i in sorted(stuck_next):
            if t >= stuck_next[i] - EPS_T:
                agents[i].announce(t)
                stuck_next[i] += cfg.replan_period_s
        if t >= next_state_s - EPS_T:
            v_now = velocities()
            for i in range(n):
                # a dead process sends nothing, nor does a radio that is out
                if (i not in killed or i not in stopped) and not _radio_out(outages, i, t):
                    msg = StateMsg(i, state_seq, t, pos[i].copy(), v_now[i].copy())
                    state_bus.publish(msg, t)
                    state_seq += 1
            for i, ag in enumerate(agents):
                if i in stopped and i not in stuck:
                    continue  # a dead process
                for sender, sm in state_bus.receive(i, t).items():
                    ag.heard(sender, sm.stamp_s, sm.position, sm.velocity)
                if i in stopped:
                    continue  # a stuck airframe: its service hears on (its statuses say so)
                # the statuses that have arrived (the newest of each peer by its stamp)
                heard_of = list(hearing[i].values())
                ag.set_unheard(not_hearing(heard_of, t, ag.first_published_s, ag.last_published_s))
                ag.watch(t)
            if t >= next_status_s - EPS_T:
                for j, ag in enumerate(agents):
                    if j in silent or (j in killed and j in stopped) or _radio_out(outages, j, t):
                        continue
                    links = peer_links(ag.peer_view(t), ag.heard_s, t)
                    for i in range(n):
                        if i == j:
                            continue
                        lag = status_lag()
                        if lag is None:
                            continue
                        report = report_from_links(j, t, i, links)
                        heapq.heappush(status_mail, (t + lag, next(status_n), i, report))
                next_status_s += STATUS_PERIOD_S
            # what arrives by the next look is read there
            while status_mail and status_mail[0][0] <= t + cfg.state_period_s + EPS_T:
                _, _, i, rep_ = heapq.heappop(status_mail)
                old = hearing[i].get(rep_.peer)
                if old is None or rep_.stamp_s > old.stamp_s:
                    hearing[i][rep_.peer] = rep_
            next_state_s += cfg.state_period_s
        if eyes is not None and t >= next_frame_s - EPS_T:
            for i, ag in enumerate(agents):
                eyes[i].observe(t, pos[i], look_velocity(ag.current, t, pos[i]), ag.goal)
            next_frame_s += 1.0 / cfg.camera_rate_hz
        if monitors and k % monitor_every == 0:
            for i, ag in enumerate(agents):
                if i not in stopped:
                    monitors[i].look(ag, t)
        if change is not None and change_record is None and t >= change[1] - EPS_T:
            change_record = _change_formation(change[0], t, pos, goals, agents, mon)
        for i, ag in sorted(enumerate(agents), key=lambda q: q[1].next_replan_s):
            if i not in stopped and ag.due(t) and not (monitors and t < monitors[i].hold_until_s):
                replan(ag, t, pos[i].copy())
                if monitors:
                    monitors[i].last_plan_s = t
                pos[i] = ag.advance(t).sample(t)
        for i, ag in enumerate(agents):
            if i not in killed or i not in stopped:  # a dead process sends nothing
                ag.resend(t)
        done = mon.step(k, t, pos, velocities)
        if (
            change_record is not None
            and change_record["reached_s"] is None
            and k % mon.sample_every == 0
            and mon.last_e_sim < FORMATION_REACHED_E_SIM
        ):
            change_record["reached_s"] = t - change_record["at_s"]
        if not done and stopped and k % mon.sample_every == 0:  # the healthy ones are enough
            done = bool(np.all(mon.arrived(pos, velocities())[healthy]))
        if done:
            timed_out = False
            break
        if progress is not None and k % progress_every == 0:
            progress(t, t_limit)

    if progress is not None:
        progress(t, t_limit)
    return result_from_monitor(
        cfg,
        mon,
        mon.arrived(pos, velocities()),
        world,
        starts,
        mon.goals,
        t,
        timed_out,
        replan_ms=replan_ms,
        iterations=iterations,
        evaluations=evaluations,
        status_counts=status_counts,
        refusals=refusals,
        wall_s=time.perf_counter() - wall0,
        warmup_s=warmup_s,
        config=_config_summary(cfg, params),
        faults={
            **bus.counters,
            "killed": {str(i): stopped[i] for i in sorted(killed) if i in stopped},
            "stuck": {str(i): stopped[i] for i in sorted(stuck) if i in stopped},
            "monitor_replans": sum(m.replans for m in monitors),
            "monitor_brakes": sum(m.brakes for m in monitors),
            "monitor_braking_retries": sum(m.braking_retries for m in monitors),
            "resent": sum(ag.resent for ag in agents),
            "monitor_no_better_stop": sum(m.no_better_stop for m in monitors),
            "radio_dropped": uplinks.dropped,
            "unheard_plans": unheard_plans,
            "bus": {} if faulty is None else dict(faulty.counters),
            "state_bus": {} if state_faulty is None else dict(state_faulty.counters),
            "agents": {
                k: int(sum(ag.counters()[k] for ag in agents))
                for k in ("silent", "refused_older", "avoided")
            },
        },
        formation_change=change_record,
    )


FORMATION_REACHED_E_SIM = 0.01
"""A new formation counts as reached once e_sim falls below this (issue #10's bar; the demo's
too)."""


def _change_formation(
    tpl: Formation,
    t: float,
    pos: np.ndarray,
    goals: np.ndarray,
    agents: Sequence[DroneAgent],
    mon: FlightMonitor,
) -> dict[str, Any]:
    """Give every drone its slot of ``tpl`` as the ground station assigns it
    (``FormationAssigner`` with the station's defaults: the template at the drones' centroid,
    turned the way nearest in total, slots by minimum total distance from ``pos``) and the goal
    centre plus that slot's offset; the monitor scores the new shape from now on. Returns the
    record of the change (``SimResult.formation_change``)."""
    from gcs.formations import FormationAssigner

    a = FormationAssigner(clock=lambda: t, lead_s=0.0).assign(
        tpl, dict(enumerate(pos)), yaw_rad=None
    )
    pts = a.offsets_m  # turned, as the wire carries them (``Assignment.to_wire``)
    slot_of = np.array([a.slots[i] for i in range(len(agents))])
    new_goals = goals.mean(axis=0) + pts[slot_of]
    for i, ag in enumerate(agents):
        ag.set_formation(pts, int(slot_of[i]), a.epoch, goal=new_goals[i])
    mon.retarget(new_goals, pts[slot_of])
    return {
        "name": tpl.name,
        "at_s": t,
        "slots": {str(i): int(s) for i, s in enumerate(slot_of)},
        "yaw_deg": math.degrees(a.yaw_rad),
        "reached_s": None,
    }


def result_from_monitor(
    cfg: SimConfig,
    mon: FlightMonitor,
    arrived: np.ndarray,
    world: World,
    starts: np.ndarray,
    goals: np.ndarray,
    t: float,
    timed_out: bool,
    *,
    replan_ms: Sequence[float],
    iterations: Sequence[float],
    evaluations: Sequence[float],
    status_counts: dict[str, int],
    refusals: dict[str, int] | None = None,
    wall_s: float,
    warmup_s: float,
    config: dict[str, Any],
    faults: dict[str, Any] | None = None,
    formation_change: dict[str, Any] | None = None,
) -> SimResult:
    """The result of a flight from what its monitor saw (shared by every way of flying)."""
    tracks = mon.tracks()
    e = tracks.e_sim
    ed = tracks.e_dist
    cx = tracks.pos[:, :, 0].mean(axis=1) if tracks.pos.shape[0] else np.zeros(0)
    lo, hi = cfg.world.cluttered_x
    inside = (cx >= lo) & (cx <= hi)
    return SimResult(
        success=bool(np.all(arrived) and mon.collisions == 0),
        arrived=arrived,
        collisions=mon.collisions,
        obstacle_collisions=mon.obstacle_events,
        drone_collisions=mon.drone_events,
        events=tuple(mon.events),
        min_obstacle_clearance_m=mon.min_clearance_m,
        min_obstacle_clearance_by_drone_m=mon.min_clearance_by_drone_m.copy(),
        min_drone_distance_m=mon.min_pair_m,
        max_speed_m_s=mon.max_speed_m_s,
        e_sim_mean=float(np.mean(e)) if e.size else math.nan,
        e_sim_max=float(np.max(e)) if e.size else math.nan,
        e_sim_mean_cluttered=float(np.mean(e[inside])) if np.any(inside) else math.nan,
        e_dist_mean_cluttered=float(np.mean(ed[inside])) if np.any(inside) else math.nan,
        e_dist_mean=float(np.mean(ed)) if ed.size else math.nan,
        e_dist_max=float(np.max(ed)) if ed.size else math.nan,
        flight_time_s=t,
        timed_out=timed_out,
        replan_ms=summary(replan_ms),
        iterations=summary(iterations),
        evaluations=summary(evaluations),
        status_counts=status_counts,
        sim_wall_s=wall_s,
        warmup_s=warmup_s,
        tracks=tracks,
        world=world,
        starts=starts,
        goals=goals,
        formation_name=cfg.formation.name,
        world_name=cfg.world.name,
        seed=cfg.seed,
        cluttered_x=(float(lo), float(hi)),
        config=config,
        faults={} if faults is None else faults,
        refusals={} if refusals is None else dict(refusals),
        formation_change={} if formation_change is None else dict(formation_change),
    )


def _mapped_perception(
    cfg: SimConfig, world: World, starts: np.ndarray, goals: np.ndarray
) -> list[Any]:
    """One simulated depth camera and local map per drone, facing its goal at the start."""
    from onboard.mapping.occupancy import OccupancyParams
    from onboard.sensors.simulated import SimulatedPerception

    occ = dataclasses.replace(
        OccupancyParams(skip_pixel=cfg.camera_skip_pixel), **dict(cfg.occupancy_overrides)
    )
    eyes = [
        SimulatedPerception(
            world,
            occupancy=occ,
            skip_pixel=cfg.camera_skip_pixel,
            seed=cfg.seed * 1000 + i,
            initial_yaw=math.atan2(goals[i, 1] - starts[i, 1], goals[i, 0] - starts[i, 0]),
            rate_hz=cfg.camera_rate_hz,
        )
        for i in range(starts.shape[0])
    ]
    for k in range(3, 0, -1):  # hovering at the start before t = 0: obstacles in view are mapped
        for i, e in enumerate(eyes):
            e.observe(-k / cfg.camera_rate_hz, starts[i], np.zeros(3), goals[i])
    return eyes


def replay_inputs(call: PlanCall) -> tuple[Any, ...]:
    """The positional arguments of ``FormationPlanner.plan`` / ``prepare`` for a recorded call
    (on the field the drone planned on: its map's ESDF when it had one, else the exact one)."""
    return (
        call.t_start_s,
        call.start_p,
        call.start_v,
        call.start_a,
        call.goal,
        list(call.peers),
        call.mapped_field if call.mapped_field is not None else AnalyticField(call.world),
        call.previous,
    )
