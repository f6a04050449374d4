"""Ground truth out of the mock: each vehicle's true pose and, when asked, simulated depth frames.

What a real drone gets from its camera driver, the mock gives from the simulation, so that the
onboard service can consume it through the same kind of interface:

- ``TruthSample``: true pose, velocity and status of one vehicle at one simulated time (ENU);
- ``DepthImage``: a depth image in metres with its time and camera pose (world_from_camera,
  optical frame x right, y down, z forward), rendered by the perception work's simulated D435
  (``onboard.mapping.SimulatedDepthCamera``) from the true pose;
- sinks: ``InMemoryTruth`` (same process: tests, demos) and ``ZenohTruth`` (other processes,
  key expressions ``<prefix>/<system_id>/pose`` and ``<prefix>/<system_id>/depth``);
- the consuming side, ``ZenohTruthSubscriber`` (or ``InMemoryTruth``), hands out per vehicle a
  depth source (``onboard.sensors.DepthSource``) and a camera pose provider; it and the wire
  formats (a pose is a small JSON object; a depth frame is a JSON header plus the image as
  little-endian uint16 millimetres, the D435's Z16 format) live in
  ``onboard.sensors.zenoh_depth``, the camera mount in ``onboard.sensors.mount``: the flight
  service reads them without importing the mock. They are re-exported here.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from onboard.comm.zenoh_session import ZenohEndpoints, open_session

# The consuming side and the wire formats live in onboard/ (the flight service reads them);
# re-exported here so that code importing them from the mock keeps working.
from onboard.sensors.mount import CAMERA_OFFSET_BODY_M, R_BODY_CAM
from onboard.sensors.zenoh_depth import (
    DecodeError,
    DepthImage,
    TruthDepthSource,
    TruthSample,
    ZenohTruthSubscriber,
    pose_provider,
)

__all__ = [
    "CAMERA_OFFSET_BODY_M",
    "R_BODY_CAM",
    "DecodeError",
    "DepthCamera",
    "DepthImage",
    "DepthStreamer",
    "InMemoryTruth",
    "TruthDepthSource",
    "TruthSample",
    "TruthSink",
    "ZenohTruth",
    "ZenohTruthSubscriber",
    "pose_provider",
    "simulated_d435",
]


class TruthSink(Protocol):
    """Where ground truth goes. Called from the simulation thread: must not block long."""

    def publish_poses(self, samples: Sequence[TruthSample]) -> None: ...

    def publish_depth(self, image: DepthImage) -> None: ...

    def close(self) -> None: ...


class InMemoryTruth:
    """Keeps the latest sample per vehicle, a bounded history, and the latest depth frames."""

    def __init__(self, history: int = 1000) -> None:
        self._lock = threading.Lock()
        self.latest: dict[int, TruthSample] = {}
        self.history: deque[TruthSample] = deque(maxlen=history)
        self.depth: dict[int, DepthImage] = {}
        self.depth_count = 0

    def publish_poses(self, samples: Sequence[TruthSample]) -> None:
        with self._lock:
            for s in samples:
                self.latest[s.system_id] = s
                self.history.append(s)

    def publish_depth(self, image: DepthImage) -> None:
        with self._lock:
            self.depth[image.system_id] = image
            self.depth_count += 1

    def snapshot(self) -> dict[int, TruthSample]:
        with self._lock:
            return dict(self.latest)

    def depth_source(self, system_id: int) -> TruthDepthSource:
        """Frames of one vehicle as an ``onboard.sensors.DepthSource``."""

        def after(stamp_s: float) -> DepthImage | None:
            with self._lock:
                img = self.depth.get(system_id)
            return img if img is not None and img.stamp_s > stamp_s else None

        def newest() -> float | None:
            with self._lock:
                img = self.depth.get(system_id)
            return None if img is None else img.stamp_s

        return TruthDepthSource(after, newest=newest)

    def pose_provider(self, system_id: int) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        """Camera pose of one vehicle, as ``onboard.sensors.PoseProvider``."""

        def latest() -> TruthSample | None:
            with self._lock:
                return self.latest.get(system_id)

        return pose_provider(latest)

    def close(self) -> None:
        pass


class ZenohTruth:
    """Publishes over Zenoh, on a session opened by ``onboard.comm.zenoh_session.open_session``
    (peer mode, no multicast scouting, explicit endpoints by default).

    ``listen`` / ``connect``: Zenoh endpoints such as ``tcp/127.0.0.1:7447``; or ``endpoints``
    (a ``ZenohEndpoints``, e.g. for a router).
    """

    def __init__(
        self,
        prefix: str = "swarm/sim",
        listen: Sequence[str] = ("tcp/127.0.0.1:7447",),
        connect: Sequence[str] = (),
        *,
        endpoints: ZenohEndpoints | None = None,
    ) -> None:
        self.prefix = prefix.rstrip("/")
        ep = endpoints or ZenohEndpoints(listen=tuple(listen), connect=tuple(connect))
        self._session = open_session(ep)
        self._pubs: dict[str, Any] = {}

    def _put(self, key: str, payload: bytes) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._session.declare_publisher(key)
            self._pubs[key] = pub
        pub.put(payload)

    def publish_poses(self, samples: Sequence[TruthSample]) -> None:
        for s in samples:
            self._put(f"{self.prefix}/{s.system_id}/pose", s.to_bytes())

    def publish_depth(self, image: DepthImage) -> None:
        self._put(f"{self.prefix}/{image.system_id}/depth", image.to_bytes())

    def close(self) -> None:
        for p in self._pubs.values():
            p.undeclare()
        self._pubs.clear()
        self._session.close()


class DepthCamera(Protocol):
    """A renderer of depth frames from a pose (``onboard.mapping.SimulatedDepthCamera``)."""

    def capture(self, position: np.ndarray, rotation: np.ndarray, stamp_s: float) -> Any: ...


def simulated_d435(world: Any, seed: int = 0, step: int = 1) -> DepthCamera:
    """The perception work's simulated D435 over ``world``; with ``step`` > 1, the camera of
    every ``step``-th pixel row and column of its image (``CameraIntrinsics.decimated``: the
    same rays, a ``step``-times smaller image). A flight service that would ray cast every
    ``step``-th pixel of the full image casts every pixel of this one: rendering, encoding,
    sending and decoding a frame cost about 1 / step^2 of the full image's, and the map gets
    the same rays.

    Raises RuntimeError when ``onboard.mapping`` does not provide it.
    """
    try:
        from onboard.mapping.camera import CameraIntrinsics
        from onboard.mapping.simcam import SimulatedDepthCamera
    except ImportError as e:  # pragma: no cover - present in this tree
        raise RuntimeError(f"no simulated depth camera available: {e}") from e
    return SimulatedDepthCamera(
        world, CameraIntrinsics().decimated(step), seed=seed, decimation=step
    )


class DepthStreamer:
    """Renders depth frames for some vehicles at a fixed rate, in its own thread.

    ``poses()`` returns the latest truth samples (by system id); each period the streamer renders
    one frame per selected vehicle from the camera pose of its sample and hands it to the sinks.
    Rendering runs outside the simulation thread, so a slow renderer lowers the frame rate
    (frames are skipped, ``skipped`` counts them) but never the autopilot loop.
    ``idle_rate_hz``: the frame rate of a disarmed vehicle (None: ``rate_hz``): a fleet
    waiting on the ground, e.g. while its flight services start and build their first map,
    costs little rendering.
    """

    def __init__(
        self,
        cameras: dict[int, DepthCamera],
        poses: Callable[[], dict[int, TruthSample]],
        sinks: Sequence[TruthSink],
        rate_hz: float,
        speedup: float = 1.0,
        idle_rate_hz: float | None = None,
    ) -> None:
        if not rate_hz > 0.0:
            raise ValueError("rate_hz must be > 0")
        if idle_rate_hz is not None and not idle_rate_hz > 0.0:
            raise ValueError("idle_rate_hz must be > 0")
        self.cameras = cameras
        self.idle_period_wall_s = (
            0.0 if idle_rate_hz is None else 1.0 / (idle_rate_hz * max(speedup, 1e-6))
        )
        self._last_wall: dict[int, float] = {}
        self.poses = poses
        self.sinks = list(sinks)
        self.period_wall_s = 1.0 / (rate_hz * max(speedup, 1e-6))
        self.frames = 0
        self.skipped = 0
        self.render_s: list[float] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_stamp: dict[int, float] = {}

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="sitl-depth", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def render_once(self) -> int:
        """Render and publish one frame per camera whose vehicle has a new pose."""
        n = 0
        latest = self.poses()
        for sid, cam in self.cameras.items():
            s = latest.get(sid)
            if s is None or self._last_stamp.get(sid) == s.t_s:
                continue
            now = time.monotonic()
            if not s.armed and now - self._last_wall.get(sid, -math.inf) < self.idle_period_wall_s:
                continue
            self._last_wall[sid] = now
            self._last_stamp[sid] = s.t_s
            pos, rot = s.camera_pose()
            t0 = time.perf_counter()
            frame = cam.capture(pos, rot, s.t_s)
            self.render_s.append(time.perf_counter() - t0)
            intr = frame.intrinsics
            img = DepthImage(
                sid,
                float(frame.stamp_s),
                np.asarray(frame.depth_m, dtype=np.float32),
                np.asarray(frame.position, dtype=np.float64),
                np.asarray(frame.rotation, dtype=np.float64),
                {
                    k: float(getattr(intr, k))
                    for k in (
                        "width",
                        "height",
                        "fx",
                        "fy",
                        "cx",
                        "cy",
                        "min_depth_m",
                        "max_depth_m",
                    )
                },
                render_step=frame.render_step,
                decimation=frame.decimation,
            )
            for sink in self.sinks:
                sink.publish_depth(img)
            n += 1
            self.frames += 1
        return n

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.render_once()
            next_t += self.period_wall_s
            delay = next_t - time.monotonic()
            if delay < 0:
                missed = int(-delay / self.period_wall_s)
                self.skipped += missed * max(len(self.cameras), 1)
                next_t += missed * self.period_wall_s
                delay = max(next_t - time.monotonic(), 0.0)
            if self._stop.wait(delay):
                break
