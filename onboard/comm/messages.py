"""Messages drones exchange. Times are global (synchronised) seconds, positions ENU metres."""

from __future__ import annotations

from dataclasses import dataclass

from onboard.planner.trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class TrajectoryMsg:
    """A drone's current trajectory, broadcast after every replan.

    drone_id: sender; traj_id: increases with every trajectory the sender publishes;
    slot: the sender's row in the formation template; trajectory: starts at ``trajectory.t0_s``.
    """

    drone_id: int
    traj_id: int
    slot: int
    trajectory: Trajectory
