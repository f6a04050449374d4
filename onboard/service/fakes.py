"""In-memory edges for the service: an autopilot that tracks setpoints perfectly, a bus, peers on
it (live, killed, stuck or lagging), a depth source. Driven by a clock passed in (tests,
benchmarks of the service's own logic)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from onboard.agent import REPLAN_PERIOD_S
from onboard.comm.hearing import HearingReport
from onboard.planner.trajectory import Trajectory
from onboard.service.ports import (
    CommandFailed,
    IncomingCommand,
    PeerInfo,
    PeerState,
    SetpointSampler,
    VehicleSnapshot,
)
from onboard.service.state import Command


class FakeAutopilot:
    """A PX4 stand-in. ``tick()`` advances it to ``clock()``: when armed in OFFBOARD with a
    stream, it is exactly where the last setpoint says; in AUTO.LAND it descends at
    ``land_speed_m_s`` and disarms on the ground. ``alive`` False silences its heartbeat."""

    def __init__(self, clock: Callable[[], float], start: tuple[float, float, float] = (0, 0, 0)):
        self.clock = clock
        self.position = np.array(start, dtype=np.float64)
        self.ground_z = float(start[2])
        self.velocity = np.zeros(3)
        self.yaw = 0.0
        self.armed = False
        self.mode = "AUTO.LOITER"
        self.alive = True
        self.last_heartbeat = clock()
        self.sampler: SetpointSampler | None = None
        self.setpoints: list[tuple[float, np.ndarray]] = []
        self.calls: list[str] = []
        self.deny: set[str] = set()
        self.land_speed_m_s = 0.7
        self._t = clock()

    # ---- AutopilotPort ---------------------------------------------------------------------
    def vehicle(self) -> VehicleSnapshot | None:
        return VehicleSnapshot(
            self._t,
            self.position.copy(),
            self.velocity.copy(),
            self.yaw,
            (math.cos(self.yaw / 2), 0.0, 0.0, math.sin(self.yaw / 2)),
            self.armed,
            self.landed,
            self.mode,
            15.8,
        )

    def link_age_s(self) -> float:
        return self.clock() - self.last_heartbeat

    def stream(self, sampler: SetpointSampler | None) -> None:
        self.calls.append("stream" if sampler is not None else "stop")
        self.sampler = sampler

    @property
    def streaming(self) -> bool:
        return self.sampler is not None

    def request_offboard(self) -> None:
        self.calls.append("offboard")
        if "offboard" in self.deny:
            raise CommandFailed("OFFBOARD denied")
        if self.sampler is None:
            raise CommandFailed("no setpoint stream")
        self.mode = "OFFBOARD"

    def arm(self) -> None:
        self.calls.append("arm")
        if "arm" in self.deny:
            raise CommandFailed("arming denied")
        self.armed = True

    def land(self) -> None:
        self.calls.append("land")
        self.mode = "AUTO.LAND"

    def counters(self) -> dict[str, int]:
        return {"setpoints": len(self.setpoints)}

    def close(self) -> None:
        self.sampler = None

    # ---- simulation --------------------------------------------------------------------------
    @property
    def landed(self) -> bool:
        return (
            self.position[2] <= self.ground_z + 0.05 and float(np.linalg.norm(self.velocity)) < 0.1
        )

    def tick(self) -> None:
        now = self.clock()
        dt = max(now - self._t, 0.0)
        self._t = now
        if self.alive:
            self.last_heartbeat = now
        if self.sampler is not None:
            sp = self.sampler(now)
            if sp is not None:
                self.setpoints.append((now, sp.position_m.copy()))
                if self.armed and self.mode == "OFFBOARD":
                    self.position = np.maximum(sp.position_m, [-1e9, -1e9, self.ground_z])
                    self.velocity = sp.velocity_m_s.copy()
                    self.yaw = sp.yaw_rad
        if self.mode == "AUTO.LAND" and self.armed:
            self.velocity = np.array([0.0, 0.0, -self.land_speed_m_s])
            self.position = self.position + self.velocity * dt
            if self.position[2] <= self.ground_z:
                self.position[2] = self.ground_z
                self.velocity = np.zeros(3)
                self.armed = False


class FakeBus:
    """The swarm bus in memory: what the service publishes is kept in lists; tests set
    ``peer_infos`` (trajectories), ``hearing_in`` (what the peers' statuses say about their
    link to us) and ``peer_states_in`` (states; or fly ``SimulatedPeer``s),
    queue ``commands`` and set ``gcs_heard``."""

    def __init__(self) -> None:
        self.trajectories: list[tuple[int, int, int, Trajectory, float]] = []
        self.states: list[dict[str, Any]] = []
        self.statuses: list[dict[str, Any]] = []
        self.acks: list[tuple[int, bool, str]] = []
        self.peer_infos: dict[int, PeerInfo] = {}
        self.peer_states_in: dict[int, PeerState] = {}
        self.hearing_in: dict[int, HearingReport] = {}
        self.commands: list[IncomingCommand] = []
        self.gcs_heard: float | None = None
        self.clock_offsets_exceeded: dict[int, float] = {}
        self._next_id = 1

    def send(self, command: Command, heard_s: float | None = None) -> int:
        cid = self._next_id
        self._next_id += 1
        self.commands.append(IncomingCommand(cid, command))
        if heard_s is not None:
            self.gcs_heard = heard_s
        return cid

    def resend(self, cmd_id: int, command: Command) -> None:
        """The ground station's resend of an unanswered command: the same id again."""
        self.commands.append(IncomingCommand(cmd_id, command))

    def ack_of(self, cmd_id: int) -> tuple[bool, str]:
        for c, ok, why in self.acks:
            if c == cmd_id:
                return ok, why
        raise KeyError(f"no ack for command {cmd_id}")

    # ---- SwarmBusPort ------------------------------------------------------------------------
    def publish_trajectory(
        self, traj_id: int, slot: int, epoch: int, trajectory: Trajectory, valid_for_s: float
    ) -> None:
        self.trajectories.append((traj_id, slot, epoch, trajectory, valid_for_s))

    def publish_state(self, fields: dict[str, Any]) -> None:
        self.states.append(fields)

    def publish_status(self, fields: dict[str, Any]) -> None:
        self.statuses.append(fields)

    def ack(self, cmd_id: int, accepted: bool, reason: str) -> None:
        self.acks.append((cmd_id, accepted, reason))

    def peers(self) -> dict[int, PeerInfo]:
        return dict(self.peer_infos)

    def peer_states(self) -> dict[int, PeerState]:
        return dict(self.peer_states_in)

    def hearing_reports(self) -> dict[int, HearingReport]:
        return dict(self.hearing_in)

    def poll_commands(self) -> list[IncomingCommand]:
        out, self.commands = self.commands, []
        return out

    def gcs_last_heard_s(self) -> float | None:
        return self.gcs_heard

    def clock_exceeded(self) -> dict[int, float]:
        return dict(self.clock_offsets_exceeded)

    def counters(self) -> dict[str, int]:
        return {"acks": len(self.acks)}

    def close(self) -> None:
        pass


class FakeDepth:
    """Depth frames of nothing (every pixel a far return) from the fake vehicle's pose while
    ``on``; ``read`` gives one new frame per call (``broken``: a frame the mapper refuses, its
    camera pose not finite). It does not tell when frames arrive (``FakeArrivingDepth`` does)."""

    def __init__(self, clock: Callable[[], float], vehicle: FakeAutopilot) -> None:
        from onboard.mapping.camera import CameraIntrinsics

        self.clock = clock
        self.vehicle = vehicle
        self.on = True
        self.broken = False
        self.intrinsics = CameraIntrinsics(32, 24, 16.0, 16.0, 16.0, 12.0, 0.2, 5.0)
        self._last = -math.inf

    def read(self) -> Any:
        from onboard.mapping.camera import DepthFrame, look_rotation

        now = self.clock()
        if not self.on or now <= self._last:
            return None
        self._last = now
        depth = np.zeros((24, 32), dtype=np.float32)  # no return: nothing mapped
        rot = look_rotation(self.vehicle.yaw)
        pos = self.vehicle.position + [0, 0, 0.05]
        if self.broken:
            pos = pos * math.nan
        return DepthFrame(depth, now, pos, rot, self.intrinsics)

    def close(self) -> None:
        pass


class FakeArrivingDepth(FakeDepth):
    """``FakeDepth`` that tells when frames arrive (``newest_stamp_s``, as the SITL mock's
    source does): a frame arrives at every clock time while ``on``, read or not."""

    def __init__(self, clock: Callable[[], float], vehicle: FakeAutopilot) -> None:
        super().__init__(clock, vehicle)
        self._newest: float | None = None

    def newest_stamp_s(self) -> float | None:
        if self.on:
            self._newest = self.clock()
        return self._newest


def straight_trajectory(
    a: np.ndarray, b: np.ndarray, t0_s: float, speed: float = 0.4
) -> Trajectory:
    """One quintic piece from rest at ``a`` to rest at ``b`` peaking at about ``speed`` (a
    simulated peer's trajectory)."""
    from onboard.planner.minco import Minco

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    T = max(float(np.linalg.norm(b - a)) * 1.875 / speed, 1.0)
    m = Minco(1)
    z = np.zeros(3)
    m.set_conditions(np.stack([a, z, z]), np.stack([b, z, z]))
    m.set_parameters(np.zeros((0, 3)), np.array([T]))
    return Trajectory(t0_s, m.coeffs, np.array([T]))


class SimulatedPeer:
    """A peer drone on a ``FakeBus``, driven by ``tick(now)`` on the test's clock: its vehicle
    flies ``path`` (a trajectory in global time; it hovers at its end after it) and its service
    re-announces the rest of the path every ``replan_period_s`` (new ``traj_id``, valid
    ``validity_s``) and sends its state every ``state_period_s``.

    Faults, each from time ``t`` on, the vehicle holding where it was then: ``kill(t)``: the
    process sends nothing more (PX4's offboard-loss failsafe holds the vehicle); ``stick(t)``:
    the process keeps sending states (where the vehicle holds) but no new trajectory (its last
    one goes stale); ``snag(t)``: the process keeps sending both, its trajectories flying on
    along the path while the vehicle stays behind (reported off its trajectory)."""

    def __init__(
        self,
        bus: FakeBus,
        drone_id: int,
        slot: int,
        epoch: int,
        path: Trajectory,
        *,
        validity_s: float = 3.0,
        replan_period_s: float = REPLAN_PERIOD_S,
        state_period_s: float = 0.1,
        incarnation: int = 1,
    ) -> None:
        self.bus = bus
        self.drone_id = drone_id
        self.slot = slot
        self.epoch = epoch
        self.path = path
        self.validity_s = validity_s
        self.replan_period_s = replan_period_s
        self.state_period_s = state_period_s
        self.incarnation = incarnation
        self.traj_id = -1
        self.killed_s = math.inf
        self.stuck_s = math.inf
        self.held: np.ndarray | None = None
        self._next_traj_s = -math.inf
        self._next_state_s = -math.inf

    def kill(self, t_s: float) -> None:
        self.killed_s = t_s
        self.held = self.position(t_s)

    def stick(self, t_s: float) -> None:
        self.stuck_s = t_s
        self.held = self.position(t_s)

    def snag(self, t_s: float) -> None:
        self.held = self.position(t_s)

    def position(self, t_s: float) -> np.ndarray:
        """Where the vehicle is at ``t_s``."""
        if self.held is not None:
            return self.held.copy()
        return self.path.sample(min(t_s, self.path.t_end_s))

    def announced(self, t_s: float) -> Trajectory:
        """The rest of the path from ``t_s`` (the same quintic pieces; a hover at its end)."""
        from onboard.planner.minco import Minco

        tr = self.path
        if t_s >= tr.t_end_s:
            return Trajectory.hover(tr.end_position, t_s, 1.0)
        p, v, a = tr.state(t_s)
        pe, ve, ae = tr.state(tr.t_end_s)
        m = Minco(1)  # one quintic from (p, v, a) to the end state: the path itself
        m.set_conditions(np.stack([p, v, a]), np.stack([pe, ve, ae]))
        m.set_parameters(np.zeros((0, 3)), np.array([tr.t_end_s - t_s]))
        return Trajectory(t_s, m.coeffs, np.array([tr.t_end_s - t_s]))

    def tick(self, now_s: float) -> None:
        """Send what is due at ``now_s``."""
        if now_s >= self.killed_s:
            return
        if now_s < self.stuck_s and now_s >= self._next_traj_s:
            self._next_traj_s = now_s + self.replan_period_s
            self.traj_id += 1
            self.bus.peer_infos[self.drone_id] = PeerInfo(
                self.drone_id,
                self.slot,
                self.epoch,
                self.announced(now_s),
                now_s + self.validity_s,
                now_s,
                traj_id=self.traj_id,
                incarnation=self.incarnation,
            )
        if now_s >= self._next_state_s:
            self._next_state_s = now_s + self.state_period_s
            self.bus.peer_states_in[self.drone_id] = PeerState(
                self.drone_id,
                now_s,
                self.position(now_s),
                (
                    np.zeros(3)
                    if self.held is not None
                    else self.path.sample(min(now_s, self.path.t_end_s), order=1)
                ),
                "formation-flight",
                now_s,
            )
