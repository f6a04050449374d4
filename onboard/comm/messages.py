"""Messages drones exchange. Times are global (synchronised) seconds, positions ENU metres."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.comm.wire import Envelope, TrajectoryBody, coeff_array, trajectory_body
from onboard.planner.trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class TrajectoryMsg:
    """A drone's current trajectory, broadcast after every replan.

    drone_id: sender; traj_id: increases with every trajectory the sender publishes;
    slot: the sender's row in the formation template; trajectory: starts at ``trajectory.t0_s``;
    formation_epoch: the formation assignment the slot belongs to; valid_until_s: global time
    after which receivers stop using it (the sender promised a newer one before then; infinite
    on the in-memory bus, which never expires messages).
    """

    drone_id: int
    traj_id: int
    slot: int
    trajectory: Trajectory
    formation_epoch: int = 0
    valid_until_s: float = math.inf

    def to_body(self) -> TrajectoryBody:
        """The wire body of this message (validity goes in the envelope header)."""
        tr = self.trajectory
        return trajectory_body(
            self.traj_id, self.slot, self.formation_epoch, tr.t0_s, tr.durations_s, tr.coeffs
        )

    @staticmethod
    def from_envelope(env: Envelope) -> TrajectoryMsg:
        """The message carried by a checked trajectory envelope (``onboard.comm.wire.decode``)."""
        b = env.body
        if not isinstance(b, TrajectoryBody):
            raise TypeError(f"envelope carries {type(b).__name__}, not a trajectory")
        return TrajectoryMsg(
            drone_id=env.sender,
            traj_id=b.traj_id,
            slot=b.slot,
            trajectory=Trajectory(b.t0_s, coeff_array(b), np.asarray(b.durations_s)),
            formation_epoch=b.formation_epoch,
            valid_until_s=env.valid_until_s,
        )
