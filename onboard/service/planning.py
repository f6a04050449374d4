"""What the service adds around the per-drone cycle (``onboard.agent.DroneAgent``, the class the
fast-time simulator runs too): the agent's bus over the service's bus port, the peers' states
handed to it as signs of life, the map source, the geofence check, and the warm-up before
READY."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from onboard.comm.messages import TrajectoryMsg
from onboard.mapping.occupancy import OccupancyParams
from onboard.planner.field import DistanceField
from onboard.planner.params import PlannerParams
from onboard.planner.trajectory import Trajectory
from onboard.service.config import GeofenceSection
from onboard.service.ports import PeerInfo, SwarmBusPort

if TYPE_CHECKING:
    from onboard.agent import DroneAgent


class PortPeerBus:
    """The agent's ``PeerBus`` over the service's ``SwarmBusPort``: ``publish`` sends the
    agent's trajectory message (its validity as ``valid_until_s - now``), ``receive`` gives the
    latest trajectory of every peer heard, expired ones included (the agent avoids a peer past
    its message's validity and forgets it ``peer_forget_s`` later).

    The ``traj_id`` handed to the agent is the sender's own sequence number (the agent never
    lets a trajectory replace one with a higher id: a late or duplicated copy). A restarted
    peer numbers its trajectories from 0 again under a new incarnation: the ids of each run
    (incarnation) seen are continued above every id seen from that peer before, so that the
    agent takes the new run's trajectories. (The bus's gate, ``onboard.comm.gate``, lets an
    older incarnation's message through again only after that sender was silent for a while,
    so a late copy of an old run does not come back as a new run.) Any thread."""

    def __init__(self, port: SwarmBusPort) -> None:
        self.port = port
        self._lock = threading.Lock()
        self._runs: dict[int, tuple[int, int, int]] = {}  # peer -> (incarnation, base, top id)

    def publish(self, msg: TrajectoryMsg, now_s: float) -> None:
        self.port.publish_trajectory(
            msg.traj_id,
            msg.slot,
            msg.formation_epoch,
            msg.trajectory,
            max(msg.valid_until_s - now_s, 1e-3),
        )

    def receive(self, drone_id: int, now_s: float) -> dict[int, TrajectoryMsg]:
        out = {}
        for pid, info in sorted(self.port.peers().items()):
            if pid == drone_id:
                continue
            out[pid] = TrajectoryMsg(
                pid,
                self.order(info),
                info.slot,
                info.trajectory,
                info.formation_epoch,
                info.valid_until_s,
            )
        return out

    def order(self, info: PeerInfo) -> int:
        """The id the agent orders ``info`` by: its ``traj_id`` within the sender's run (its
        incarnation), runs one after the other in the order they were seen."""
        pid = info.drone_id
        with self._lock:
            run = self._runs.get(pid)
            if run is None:
                base, top = 0, -1
            elif run[0] == info.incarnation:
                base, top = run[1], run[2]
            else:  # a new run of the sender: after everything of the previous ones
                base = run[2] + 1
                top = base - 1
            key = base + int(info.traj_id)
            self._runs[pid] = (info.incarnation, base, max(top, key))
        return key


class StateRelay:
    """Hands the peers' newest states from the bus port to the agent as signs of life
    (``DroneAgent.heard``: the sender's stamp, where its vehicle reported itself and its
    velocity), each one
    once. Any thread (the agent keeps the newest stamp)."""

    def __init__(self, port: SwarmBusPort, agent: DroneAgent) -> None:
        self.port = port
        self.agent = agent
        self._lock = threading.Lock()
        self._handed: dict[int, float] = {}

    def __call__(self) -> int:
        """Hand over what is new; the number of states handed."""
        n = 0
        for pid, st in sorted(self.port.peer_states().items()):
            with self._lock:
                if st.stamp_s <= self._handed.get(pid, -math.inf):
                    continue
                self._handed[pid] = st.stamp_s
            self.agent.heard(pid, st.stamp_s, st.position_m, st.velocity_m_s)
            n += 1
        return n


class FieldSource:
    """The agent's ``MapSource``: whatever field ``latest()`` gives (the mapping thread's latest
    ESDF snapshot, an immutable object replaced as a whole)."""

    def __init__(self, latest: Callable[[], Any]) -> None:
        self.latest = latest

    def snapshot(self, now_s: float, position: np.ndarray) -> DistanceField:
        f = self.latest()
        if f is None:
            raise RuntimeError("no map to plan on yet")
        return f


def inside_box(
    traj: Trajectory, t_from_s: float, box: GeofenceSection, step_s: float = 0.1
) -> bool:
    """Whether ``traj`` stays inside the geofence from ``t_from_s`` to its end."""
    t_end = max(traj.t_end_s, t_from_s)
    ts = np.append(np.arange(t_from_s, t_end, step_s), t_end)
    p = traj.sample(ts)
    lo = np.asarray(box.min_enu_m)
    hi = np.asarray(box.max_enu_m)
    return bool(np.all((p >= lo) & (p <= hi)))


def warm_up(params: PlannerParams) -> float:
    """Run every planning path once before READY, so that no kernel is loaded from numba's cache
    (or compiled) in flight, where loading holds the interpreter for a long time: one cycle of a
    ``DroneAgent`` (the class the service flies) on the mapped ESDF's field type (with its
    occupancy, which the check's neighbourhood test reads), a trunk on the straight line (A*
    guess) and an avoided-only peer (edge-masked template), then one on the exact ground field;
    then the objective alone on each field (a refined solution's cost), the safety monitor's
    conflict rule and the agent's shape test (the similarity metric).
    The flight service counts a kernel made after READY (``kernels_after_ready``). Seconds
    taken."""
    from onboard.agent import DroneAgent, StaticMap, obstacle_conflict
    from onboard.comm.bus import InMemoryBus
    from onboard.comm.messages import TrajectoryMsg
    from onboard.mapping.esdf import EsdfField
    from onboard.planner.field import AnalyticField
    from onboard.planner.formation import similarity
    from onboard.planner.planner import FormationPlanner, PeerTrajectory
    from onboard.world import World

    t0 = time.perf_counter()
    world = World(np.array([[2.0, 0.0, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    res = 0.2
    origin = np.array([-2.0, -3.0, -0.4])
    shape = (40, 30, 16)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    centres = origin + (idx.reshape(-1, 3) + 0.5) * res
    values = world.distance(centres)[0].reshape(shape)
    grid = EsdfField(values, origin, res, np.ones(shape, dtype=bool), values <= 0.0, 0.2)
    formation = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
    start = np.array([0.0, 0.0, 1.0])
    goal = np.array([4.0, 0.0, 1.0])
    zero = np.zeros(3)
    hovers = {k: Trajectory.hover(start + formation[k], 0.0, 5.0) for k in (0, 2)}
    for field in (grid, AnalyticField(World.empty(0.0))):
        bus = InMemoryBus()
        for k, epoch in ((0, 0), (2, 1)):  # drone 2 flies another epoch: avoided only
            bus.publish(TrajectoryMsg(k, 0, k, hovers[k], epoch), 0.0)
        agent = DroneAgent(
            1,
            params,
            formation,
            1,
            Trajectory.hover(start, 0.0, 1.0),
            bus,
            StaticMap(field),
            goal=goal,
        )
        agent.replan(0.0)
        # the objective outside the solver: a refined solution's cost (``Problem.cost`` of a
        # solve on ``refine_prob``'s stiffer problem, compared with the fresh start's)
        peers = [PeerTrajectory(0, 0, hovers[0])]
        problem = FormationPlanner(params, formation, 1).prepare(
            0.0, start, zero, zero, goal, peers, field
        )
        problem.objective(problem.x0)
    # the monitor's rule on distances that come inside the limit; the shape test as the agent
    # runs it (its points and the template's slots, fresh arrays)
    ts = np.linspace(0.0, 1.0, 11)
    obstacle_conflict(np.linspace(0.6, 0.1, 11), ts, 0.0, 0.3, np.linspace(0.6, 0.4, 11))
    similarity(formation + start, formation[[0, 1, 2]])
    return time.perf_counter() - t0


def warm_mapping(occupancy: OccupancyParams | None = None, step: int | None = None) -> float:
    """Run the mapping path once (a rendered depth frame ray cast into a ``LocalMapper``, its
    ESDF, the planning field sampled), so that its kernels are compiled into numba's cache (or
    loaded from it) before the depth thread needs them: compiling them there, cold, takes tens
    of seconds and would hold READY back. Seconds taken."""
    from onboard.mapping.camera import look_rotation
    from onboard.mapping.mapper import LocalMapper
    from onboard.mapping.simcam import D435_TYPICAL, SimulatedDepthCamera
    from onboard.world import World

    t0 = time.perf_counter()
    occ = occupancy if occupancy is not None else OccupancyParams()
    world = World(np.array([[2.5, 0.3, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    cam_step = step if step is not None else occ.skip_pixel
    camera = SimulatedDepthCamera(world, params=dataclasses.replace(D435_TYPICAL, step=cam_step))
    mapper = LocalMapper(occ)
    position = np.array([0.0, 0.0, 1.0])
    for k in range(2):
        frame = camera.capture(position, look_rotation(0.0), 0.1 * k)
        res = mapper.ingest(frame, step=step)
        if not res.accepted:
            raise RuntimeError(f"mapping warm-up: frame refused ({res.reason})")
    field = mapper.planning_field()
    field.distance(np.array([[2.0, 0.0, 1.0], [1.0, 0.5, 1.2]]))
    return time.perf_counter() - t0


class WarmUp:
    """``warm_up`` in a thread of its own, started early (while the process still connects to
    the autopilot and the bus, mostly waiting); ``wait`` joins it and returns its seconds, or
    raises what it raised."""

    def __init__(
        self,
        params: PlannerParams,
        mapping: OccupancyParams | None = None,
        depth_step: int | None = None,
    ) -> None:
        """``mapping``: also warm the mapping path with these map parameters (a service with a
        depth source), ray casting every ``depth_step``-th pixel."""
        import threading

        self.params = params
        self.mapping = mapping
        self.depth_step = depth_step
        self.seconds: float | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="svc-warm-up", daemon=True)

    def start(self) -> WarmUp:
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            seconds = warm_up(self.params)
            if self.mapping is not None:
                seconds += warm_mapping(self.mapping, self.depth_step)
            self.seconds = seconds
        except BaseException as e:  # handed to the caller of wait()
            self.error = e

    def running(self) -> bool:
        return self._thread.is_alive()

    def wait(self) -> float:
        self._thread.join()
        if self.error is not None:
            raise self.error
        assert self.seconds is not None
        return self.seconds
