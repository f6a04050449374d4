"""Intel RealSense depth through Open3D (``open3d.t.io``): a live camera or a ``.bag`` replay.

Open3D delivers depth aligned to the colour camera (uint16, ``depth_scale`` units per metre)
with the colour camera's intrinsics in its metadata; frames are converted to metres (float32,
0 = no measurement) with those intrinsics. A RealSense frame carries no pose: the caller
provides one per timestamp (``PoseProvider``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from onboard.mapping.camera import CameraIntrinsics, DepthFrame
from onboard.sensors.source import PoseProvider


class RealSenseUnavailable(RuntimeError):
    """No camera, no readable recording, or no RealSense support in the installed Open3D."""


def _open3d_io() -> Any:
    try:
        import open3d as o3d
    except ImportError as e:  # pragma: no cover - open3d is a dependency
        raise RealSenseUnavailable(f"Open3D is not importable: {e}") from e
    io = getattr(o3d.t, "io", None)
    if io is None or not hasattr(io, "RealSenseSensor"):
        raise RealSenseUnavailable(
            "this Open3D build has no RealSense support (open3d.t.io.RealSenseSensor missing)"
        )
    return io


def _intrinsics_from_metadata(
    meta: Any, min_depth_m: float, max_depth_m: float
) -> CameraIntrinsics:
    k = np.asarray(meta.intrinsics.intrinsic_matrix, dtype=np.float64)
    return CameraIntrinsics(
        int(meta.width),
        int(meta.height),
        float(k[0, 0]),
        float(k[1, 1]),
        float(k[0, 2]),
        float(k[1, 2]),
        min_depth_m,
        max_depth_m,
    )


def depth_to_metres(raw: np.ndarray, depth_scale: float) -> np.ndarray:
    """A (H, W) or (H, W, 1) uint16 depth image in sensor units to float32 metres (0 stays 0)."""
    d = np.asarray(raw)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if not depth_scale > 0.0:
        raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
    return (d.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


class RealSenseSource:
    """A ``DepthSource`` over a live RealSense camera (``bag_path`` None) or a ``.bag`` file.

    Raises ``RealSenseUnavailable`` with the reason when the camera or file cannot be opened.
    clock: stamps frames on arrival (host time, what the pose provider understands); None
    uses the device / recording timestamp, made non-decreasing. Open3D plays a recording back
    in real time and drops frames the reader does not take in time (``read`` skips them).
    """

    def __init__(
        self,
        pose_at: PoseProvider,
        bag_path: str | Path | None = None,
        clock: Callable[[], float] | None = None,
        fps: int = 30,
        resolution: tuple[int, int] = (640, 480),
        min_depth_m: float = 0.2,
        max_depth_m: float = 5.0,
    ) -> None:
        self.pose_at = pose_at
        self.clock = clock
        self._io = _open3d_io()
        self._sensor: Any = None
        self._reader: Any = None
        self._last_stamp_s = -math.inf
        if bag_path is None:
            self._sensor = self._open_live(fps, resolution)
            meta = self._sensor.get_metadata()
        else:
            self._reader = self._open_bag(Path(bag_path))
            meta = self._reader.metadata
        self.depth_scale = float(meta.depth_scale)
        self._intrinsics = _intrinsics_from_metadata(meta, min_depth_m, max_depth_m)

    def _open_live(self, fps: int, resolution: tuple[int, int]) -> Any:
        io = self._io
        if not io.RealSenseSensor.list_devices():
            raise RealSenseUnavailable(
                "no RealSense camera found: connect a D435 to a USB 3 port (check `lsusb` and "
                "the udev rules of librealsense), or replay a recording with a .bag file"
            )
        w, h = resolution
        cfg = io.RealSenseSensorConfig(
            {
                "color_format": "RS2_FORMAT_RGB8",
                "color_resolution": f"{w},{h}",
                "depth_format": "RS2_FORMAT_Z16",
                "depth_resolution": f"{w},{h}",
                "fps": str(fps),
            }
        )
        sensor = io.RealSenseSensor()
        if not sensor.init_sensor(cfg, 0, ""):
            raise RealSenseUnavailable(
                f"the RealSense camera refused the configuration {w}x{h} at {fps} fps"
            )
        if not sensor.start_capture(False):
            raise RealSenseUnavailable("the RealSense camera did not start streaming")
        return sensor

    def _open_bag(self, path: Path) -> Any:
        if not path.is_file():
            raise RealSenseUnavailable(f"RealSense recording not found: {path}")
        if path.suffix.lower() != ".bag":
            raise RealSenseUnavailable(f"not a RealSense recording (.bag expected): {path}")
        reader = self._io.RSBagReader()
        if not reader.open(str(path)):
            raise RealSenseUnavailable(f"cannot open {path} as a RealSense recording")
        return reader

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    def read(self) -> DepthFrame | None:
        """The next frame (depth aligned to colour), or None at the end of a recording."""
        if self._reader is not None:
            rgbd = None
            while not self._reader.is_eof():  # playback is real-time: skip dropped frames
                rgbd = self._reader.next_frame()
                if not rgbd.is_empty():
                    break
            if rgbd is None:
                return None
            device_s = self._reader.get_timestamp() * 1e-6
        elif self._sensor is not None:
            rgbd = self._sensor.capture_frame(True, True)
            device_s = self._sensor.get_timestamp() * 1e-6
        else:
            return None
        if rgbd.is_empty():
            return None
        depth = depth_to_metres(rgbd.depth.as_tensor().numpy(), self.depth_scale)
        if self.clock is not None:
            stamp = float(self.clock())
        else:  # recording times from Open3D are coarse and may step back: keep them monotonic
            stamp = max(float(device_s), self._last_stamp_s)
        self._last_stamp_s = stamp
        position, rotation = self.pose_at(stamp)
        return DepthFrame(depth, stamp, position, rotation, self._intrinsics)

    def close(self) -> None:
        if self._sensor is not None:
            self._sensor.stop_capture()
            self._sensor = None
        if self._reader is not None:
            self._reader.close()
            self._reader = None


def host_clock() -> float:
    """Monotonic host time in seconds (a default ``clock`` for live capture)."""
    return time.monotonic()
