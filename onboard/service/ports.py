"""What the service needs from its edges, as small interfaces: the autopilot link, the swarm bus,
the depth source and the replanner. The process wires real implementations
(``onboard.service.adapters``); the tests wire in-memory fakes (``tests/service_fakes.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from onboard.comm.hearing import HearingReport
from onboard.planner.trajectory import Trajectory
from onboard.service.state import Command


@dataclass(frozen=True, eq=False)
class VehicleSnapshot:
    """The autopilot's latest telemetry, ENU. ``t_s``: global time of the sample; ``mode``: PX4
    mode name (``OFFBOARD``, ``AUTO.LAND``, ``AUTO.LOITER``, ``POSCTL`` ...); ``landed``: the
    landed state says on the ground."""

    t_s: float
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    yaw_rad: float
    attitude_wxyz: tuple[float, float, float, float]
    armed: bool
    landed: bool
    mode: str
    battery_v: float | None = None

    @property
    def on_ground(self) -> bool:
        return self.landed and not self.armed


@dataclass(frozen=True, eq=False)
class Setpoint:
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    yaw_rad: float


SetpointSampler = Callable[[float], "Setpoint | None"]
"""Global time -> the setpoint to send now (None: send nothing this period)."""


class CommandFailed(RuntimeError):
    """An autopilot command was denied, failed or timed out (the message says which)."""


class AutopilotPort(Protocol):
    def vehicle(self) -> VehicleSnapshot | None:
        """The latest telemetry (None before the first)."""
        ...

    def link_age_s(self) -> float:
        """Seconds since the autopilot was last heard (inf before the first message). The real
        link counts every valid message (PX4 sends hundreds a second; its 1 Hz heartbeat alone
        would make a 1 s timeout fire on every late heartbeat); the service declares the link
        lost after ``autopilot.heartbeat_timeout_s``."""
        ...

    def stream(self, sampler: SetpointSampler | None) -> None:
        """Start streaming setpoints from ``sampler`` at the configured rate (with the companion
        heartbeat), or stop at once (None)."""
        ...

    @property
    def streaming(self) -> bool: ...

    def request_offboard(self) -> None:
        """Switch to OFFBOARD (setpoints must already flow); raises ``CommandFailed``."""
        ...

    def arm(self) -> None: ...

    def land(self) -> None: ...

    def counters(self) -> dict[str, int]: ...

    def close(self) -> None: ...


@dataclass(frozen=True, eq=False)
class PeerInfo:
    """A peer's latest trajectory as the bus delivered it."""

    drone_id: int
    slot: int
    formation_epoch: int
    trajectory: Trajectory
    valid_until_s: float
    received_s: float
    traj_id: int = 0
    """The sender's sequence number of this trajectory (increases with every one it sends)."""
    incarnation: int = 0
    """The sender process's incarnation (``onboard.comm.wire``): a restarted process numbers
    its trajectories from 0 again under a new one."""


@dataclass(frozen=True, eq=False)
class PeerState:
    """A peer's newest state message (10 Hz, ``<swarm>/drone/<id>/state``): its sign of life.

    stamp_s: the sender's global time of the state (its autopilot sample, never later than
    the message's own stamp); position_m / velocity_m_s: ENU, where its vehicle reported itself
    (None if not finite); flight_state: its service's state name; received_s: our clock when
    it arrived."""

    drone_id: int
    stamp_s: float
    position_m: np.ndarray | None
    velocity_m_s: np.ndarray | None
    flight_state: str
    received_s: float


@dataclass(frozen=True)
class IncomingCommand:
    """A ground-station command as it arrived. A resend (no answer heard in time) arrives again
    with the same ``sender`` (the ground station's node id) and ``cmd_id``."""

    cmd_id: int
    command: Command
    sender: int = 0


class SwarmBusPort(Protocol):
    def publish_trajectory(
        self, traj_id: int, slot: int, epoch: int, trajectory: Trajectory, valid_for_s: float
    ) -> None: ...

    def publish_state(self, fields: dict[str, Any]) -> None: ...

    def publish_status(self, fields: dict[str, Any]) -> None: ...

    def ack(self, cmd_id: int, accepted: bool, reason: str) -> None: ...

    def peers(self) -> dict[int, PeerInfo]:
        """The latest accepted trajectory of every peer heard."""
        ...

    def peer_states(self) -> dict[int, PeerState]:
        """The newest state (by its stamp) of every peer heard."""
        ...

    def hearing_reports(self) -> dict[int, HearingReport]:
        """The newest (by its stamp) of what each peer's status says about its link to us
        (``onboard.comm.hearing``)."""
        ...

    def poll_commands(self) -> list[IncomingCommand]:
        """Commands addressed to this drone since the last call (decoded and checked)."""
        ...

    def gcs_last_heard_s(self) -> float | None:
        """Global time the ground station was last heard (command or liveliness)."""
        ...

    def clock_exceeded(self) -> dict[int, float]:
        """Senders (drone ids; ground stations >= ``onboard.comm.wire.GCS_ID``) whose estimated
        clock offset is beyond the configured bound, with that offset in seconds."""
        ...

    def counters(self) -> dict[str, int]: ...

    def close(self) -> None: ...


braking_trajectory = Trajectory.braking
"""One quintic piece from (p, v, a) to rest, then hovering there: the service's brakes
(``peak_fraction`` 1.0, the hardest stop within the limit, for a collision ahead)."""


def climb_trajectory(
    t0_s: float, start: np.ndarray, height_m: float, speed_m_s: float
) -> Trajectory:
    """A vertical climb of ``height_m`` from rest to rest at about ``speed_m_s``: the one
    minimum-jerk piece, in closed form (``Trajectory.to_rest``; a ``Minco`` here ran a
    kernel that the warm-up does not, made at take-off in the actions thread)."""
    s = np.asarray(start, dtype=np.float64).reshape(3)
    T = max(1.0, 1.875 * abs(height_m) / max(speed_m_s, 1e-3))  # peak speed of a rest-to-rest
    z = np.zeros(3)
    return Trajectory.to_rest(t0_s, s, z, z, s + np.array([0.0, 0.0, height_m]), T)
