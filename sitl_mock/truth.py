"""Ground truth out of the mock: each vehicle's true pose and, when asked, simulated depth frames.

What a real drone gets from its camera driver, the mock gives from the simulation, so that the
onboard service can consume it through the same kind of interface:

- ``TruthSample``: true pose, velocity and status of one vehicle at one simulated time (ENU);
- ``DepthImage``: a depth image in metres with its time and camera pose (world_from_camera,
  optical frame x right, y down, z forward), rendered by the perception work's simulated D435
  (``onboard.mapping.SimulatedDepthCamera``) from the true pose;
- sinks: ``InMemoryTruth`` (same process: tests, demos) and ``ZenohTruth`` (other processes,
  key expressions ``<prefix>/<system_id>/pose`` and ``<prefix>/<system_id>/depth``);
- the consuming side: ``ZenohTruthSubscriber`` (or ``InMemoryTruth``) hands out, per vehicle,
  a depth source with the interface of ``onboard.sensors.DepthSource`` (``read()`` ->
  ``onboard.mapping.DepthFrame``) and a camera pose provider (``onboard.sensors.PoseProvider``);
- wire formats: a pose is a small JSON object; a depth frame is a JSON header plus the image as
  little-endian uint16 millimetres (the D435's Z16 format; 0 = no return).
"""

from __future__ import annotations

import json
import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from sitl_mock.frames import matrix_from_quaternion

# camera mounting: optical frame (x right, y down, z forward) in the FLU body frame
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAMERA_OFFSET_BODY_M = np.array([0.10, 0.0, 0.0])


@dataclass(frozen=True)
class TruthSample:
    """True state of one vehicle. ENU world, FLU body; quaternion (w, x, y, z) body -> world."""

    system_id: int
    t_s: float
    position_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]
    yaw_rad: float
    armed: bool
    landed: bool
    mode: str
    collisions: int

    def to_bytes(self) -> bytes:
        return json.dumps(
            {
                "system_id": self.system_id,
                "t_s": self.t_s,
                "position_enu_m": list(self.position_m),
                "velocity_enu_m_s": list(self.velocity_m_s),
                "quaternion_enu_flu": list(self.quaternion),
                "yaw_enu_rad": self.yaw_rad,
                "armed": self.armed,
                "landed": self.landed,
                "mode": self.mode,
                "collisions": self.collisions,
            },
            separators=(",", ":"),
        ).encode()

    @staticmethod
    def from_bytes(data: bytes) -> TruthSample:
        d = json.loads(data)
        return TruthSample(
            system_id=int(d["system_id"]),
            t_s=float(d["t_s"]),
            position_m=_vec3(d["position_enu_m"]),
            velocity_m_s=_vec3(d["velocity_enu_m_s"]),
            quaternion=(
                float(d["quaternion_enu_flu"][0]),
                float(d["quaternion_enu_flu"][1]),
                float(d["quaternion_enu_flu"][2]),
                float(d["quaternion_enu_flu"][3]),
            ),
            yaw_rad=float(d["yaw_enu_rad"]),
            armed=bool(d["armed"]),
            landed=bool(d["landed"]),
            mode=str(d["mode"]),
            collisions=int(d["collisions"]),
        )

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), world_from_camera (3, 3)) of the forward depth camera."""
        r_world_body = matrix_from_quaternion(self.quaternion)
        pos = np.asarray(self.position_m) + r_world_body @ CAMERA_OFFSET_BODY_M
        return pos, r_world_body @ R_BODY_CAM


def _vec3(v: Sequence[Any]) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


@dataclass(frozen=True, eq=False)
class DepthImage:
    """A depth image (height, width) float32 metres (0 = no return) from a camera pose.

    ``intrinsics``: width, height, fx, fy, cx, cy, min_depth_m, max_depth_m.
    """

    system_id: int
    stamp_s: float
    depth_m: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    intrinsics: dict[str, float]

    def to_bytes(self) -> bytes:
        header = json.dumps(
            {
                "system_id": self.system_id,
                "stamp_s": self.stamp_s,
                "position": [float(x) for x in self.position],
                "rotation": [float(x) for x in np.asarray(self.rotation).reshape(9)],
                "intrinsics": self.intrinsics,
                "shape": list(self.depth_m.shape),
                "encoding": "z16_mm",
            },
            separators=(",", ":"),
        ).encode()
        d = np.nan_to_num(np.asarray(self.depth_m, dtype=np.float64), nan=0.0, posinf=0.0)
        mm = np.clip(np.rint(d * 1000.0), 0, 65535).astype("<u2")
        return b"DPT1" + struct.pack("<I", len(header)) + header + mm.tobytes()

    @staticmethod
    def from_bytes(data: bytes) -> DepthImage:
        if data[:4] != b"DPT1":
            raise ValueError("not a depth frame")
        (n,) = struct.unpack("<I", data[4:8])
        h = json.loads(data[8 : 8 + n])
        shape = tuple(int(x) for x in h["shape"])
        mm = np.frombuffer(data[8 + n :], dtype="<u2")
        if mm.size != shape[0] * shape[1]:
            raise ValueError("depth frame size does not match its header")
        return DepthImage(
            system_id=int(h["system_id"]),
            stamp_s=float(h["stamp_s"]),
            depth_m=(mm.reshape(shape).astype(np.float32) / np.float32(1000.0)),
            position=np.array(h["position"], dtype=np.float64),
            rotation=np.array(h["rotation"], dtype=np.float64).reshape(3, 3),
            intrinsics={k: float(v) for k, v in h["intrinsics"].items()},
        )

    def to_depth_frame(self) -> Any:
        """This image as the perception work's ``onboard.mapping.DepthFrame``."""
        from onboard.mapping.camera import CameraIntrinsics, DepthFrame

        i = self.intrinsics
        intr = CameraIntrinsics(
            int(i["width"]),
            int(i["height"]),
            i["fx"],
            i["fy"],
            i["cx"],
            i["cy"],
            i.get("min_depth_m", 0.2),
            i.get("max_depth_m", 5.0),
        )
        return DepthFrame(self.depth_m, self.stamp_s, self.position, self.rotation, intr)


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

        def latest() -> DepthImage | None:
            with self._lock:
                return self.depth.get(system_id)

        return TruthDepthSource(latest)

    def pose_provider(self, system_id: int) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        """Camera pose of one vehicle, as ``onboard.sensors.PoseProvider``."""

        def latest() -> TruthSample | None:
            with self._lock:
                return self.latest.get(system_id)

        return pose_provider(latest)

    def close(self) -> None:
        pass


class ZenohTruth:
    """Publishes over Zenoh (peer mode, no multicast scouting, explicit endpoints only).

    ``listen`` / ``connect``: Zenoh endpoints such as ``tcp/127.0.0.1:7447``.
    """

    def __init__(
        self,
        prefix: str = "swarm/sim",
        listen: Sequence[str] = ("tcp/127.0.0.1:7447",),
        connect: Sequence[str] = (),
    ) -> None:
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        self.prefix = prefix.rstrip("/")
        self._session = zenoh.open(cfg)
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
    """The perception work's simulated D435 over ``world``.

    Raises RuntimeError when ``onboard.mapping`` does not provide it.
    """
    try:
        from onboard.mapping.simcam import SimCameraParams, SimulatedDepthCamera
    except ImportError as e:  # pragma: no cover - present in this tree
        raise RuntimeError(f"no simulated depth camera available: {e}") from e
    return SimulatedDepthCamera(world, params=SimCameraParams(step=step), seed=seed)


class DepthStreamer:
    """Renders depth frames for some vehicles at a fixed rate, in its own thread.

    ``poses()`` returns the latest truth samples (by system id); each period the streamer renders
    one frame per selected vehicle from the camera pose of its sample and hands it to the sinks.
    Rendering runs outside the simulation thread, so a slow renderer lowers the frame rate
    (frames are skipped, ``skipped`` counts them) but never the autopilot loop.
    """

    def __init__(
        self,
        cameras: dict[int, DepthCamera],
        poses: Callable[[], dict[int, TruthSample]],
        sinks: Sequence[TruthSink],
        rate_hz: float,
        speedup: float = 1.0,
    ) -> None:
        if not rate_hz > 0.0:
            raise ValueError("rate_hz must be > 0")
        self.cameras = cameras
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


# ---------------------------------------------------------------------------------------------
# The consuming side: what the onboard service reads instead of a camera driver


class TruthDepthSource:
    """One vehicle's simulated frames as a depth source (``onboard.sensors.DepthSource``):
    ``read`` returns the newest frame not returned before (an ``onboard.mapping.DepthFrame``),
    or None when there is no new one."""

    def __init__(self, latest: Callable[[], DepthImage | None]) -> None:
        self._latest = latest
        self._last_stamp = -math.inf
        self._intrinsics: Any = None

    @property
    def intrinsics(self) -> Any:
        if self._intrinsics is None:
            from onboard.mapping.camera import CameraIntrinsics

            return CameraIntrinsics()
        return self._intrinsics

    def read(self) -> Any:
        img = self._latest()
        if img is None or img.stamp_s <= self._last_stamp:
            return None
        self._last_stamp = img.stamp_s
        frame = img.to_depth_frame()
        self._intrinsics = frame.intrinsics
        return frame

    def close(self) -> None:
        return None


def pose_provider(
    latest: Callable[[], TruthSample | None],
) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
    """A pose provider (stamp -> camera position, world_from_camera) from the latest true pose
    (the stamp is not interpolated: the mock publishes poses faster than frames are taken)."""

    def at(_stamp_s: float) -> tuple[np.ndarray, np.ndarray]:
        s = latest()
        if s is None:
            raise LookupError("no pose received yet")
        return s.camera_pose()

    return at


class ZenohTruthSubscriber:
    """Subscribes to the poses and depth frames a ``ZenohTruth`` publishes; keeps the latest
    of each per vehicle."""

    def __init__(
        self,
        prefix: str = "swarm/sim",
        connect: Sequence[str] = ("tcp/127.0.0.1:7447",),
        listen: Sequence[str] = (),
    ) -> None:
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        self.prefix = prefix.rstrip("/")
        self._lock = threading.Lock()
        self._poses: dict[int, TruthSample] = {}
        self._depth: dict[int, DepthImage] = {}
        self.errors = 0
        self._session = zenoh.open(cfg)
        self._subs = [
            self._session.declare_subscriber(f"{self.prefix}/*/pose", self._on_pose),
            self._session.declare_subscriber(f"{self.prefix}/*/depth", self._on_depth),
        ]

    def _on_pose(self, sample: Any) -> None:
        try:
            s = TruthSample.from_bytes(sample.payload.to_bytes())
        except (ValueError, KeyError, TypeError):
            self.errors += 1
            return
        with self._lock:
            self._poses[s.system_id] = s

    def _on_depth(self, sample: Any) -> None:
        try:
            img = DepthImage.from_bytes(sample.payload.to_bytes())
        except (ValueError, KeyError, TypeError, struct.error):
            self.errors += 1
            return
        with self._lock:
            self._depth[img.system_id] = img

    def pose(self, system_id: int) -> TruthSample | None:
        with self._lock:
            return self._poses.get(system_id)

    def depth_image(self, system_id: int) -> DepthImage | None:
        with self._lock:
            return self._depth.get(system_id)

    def depth_source(self, system_id: int) -> TruthDepthSource:
        return TruthDepthSource(lambda: self.depth_image(system_id))

    def pose_provider(self, system_id: int) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        return pose_provider(lambda: self.pose(system_id))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
        self._session.close()
