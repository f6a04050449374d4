"""The depth-source interface and the simulated D435 behind it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from onboard.mapping.camera import CameraIntrinsics, DepthFrame
from onboard.mapping.simcam import SimulatedDepthCamera

PoseProvider = Callable[[float], tuple[np.ndarray, np.ndarray]]
"""Camera pose at a time: stamp_s -> (position (3,), rotation (3, 3) world_from_camera), ENU.
On a drone: the autopilot's odometry at that time composed with the camera's mounting."""


class DepthSource(Protocol):
    """Where depth frames come from: metres, a timestamp and the camera pose per frame."""

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the frames ``read`` returns."""
        ...

    def read(self) -> DepthFrame | None:
        """The next frame, or None when there is none (end of a recording, no new frame)."""
        ...

    def close(self) -> None:
        """Release the device or file."""
        ...


class SimulatedD435Source:
    """A ``DepthSource`` that renders ``camera``'s world at the pose ``pose_at(clock())``."""

    def __init__(
        self, camera: SimulatedDepthCamera, pose_at: PoseProvider, clock: Callable[[], float]
    ) -> None:
        self.camera = camera
        self.pose_at = pose_at
        self.clock = clock

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.camera.intrinsics

    def read(self) -> DepthFrame:
        stamp = float(self.clock())
        position, rotation = self.pose_at(stamp)
        return self.camera.capture(position, rotation, stamp)

    def close(self) -> None:
        return None
