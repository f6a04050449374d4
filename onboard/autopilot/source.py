"""A setpoint source over the current immutable trajectory.

The service swaps the trajectory (one reference assignment, atomic in Python) whenever it has a
new plan; the streamer evaluates whichever trajectory is current at each tick. Nothing here
waits on the planner.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from onboard.autopilot.model import Setpoint


class _Trajectory(Protocol):
    def state(self, t_global: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


class TrajectorySource:
    """``source(now_s)`` samples the current trajectory (position, velocity, acceleration) at
    ``now_s`` (the trajectory's global time base). ``yaw_enu_rad``: a fixed heading, or None to
    leave the heading to the autopilot. Without a trajectory it returns None (the link holds).
    """

    def __init__(self, trajectory: _Trajectory | None = None, yaw_enu_rad: float | None = None):
        self._trajectory = trajectory
        self._yaw = yaw_enu_rad

    def set_trajectory(self, trajectory: _Trajectory | None) -> None:
        self._trajectory = trajectory

    def set_yaw(self, yaw_enu_rad: float | None) -> None:
        self._yaw = yaw_enu_rad

    @property
    def trajectory(self) -> _Trajectory | None:
        return self._trajectory

    def __call__(self, now_s: float) -> Setpoint | None:
        traj = self._trajectory
        if traj is None:
            return None
        p, v, a = traj.state(now_s)
        return Setpoint(
            (float(p[0]), float(p[1]), float(p[2])),
            (float(v[0]), float(v[1]), float(v[2])),
            (float(a[0]), float(a[1]), float(a[2])),
            self._yaw,
        )
