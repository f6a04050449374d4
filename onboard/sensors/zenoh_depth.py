"""Depth frames and true poses from the simulator over Zenoh: the codecs and the subscriber.

The SITL mock (``sitl_mock.truth``) publishes, per vehicle ``<prefix>/<system_id>/pose`` and
``<prefix>/<system_id>/depth``. A flight service that flies against the mock reads them here,
in place of a camera driver:

- ``TruthSample``: the true pose, velocity and status of one vehicle (a small JSON object);
- ``DepthImage``: one depth image with its stamp and camera pose; on the wire ``b"DPT1"``, the
  header length (uint32 little-endian), a JSON header, then the image as little-endian uint16
  millimetres (the D435's Z16 format; 0 = no return);
- ``ZenohTruthSubscriber``: keeps the latest pose and frame per vehicle and hands out a depth
  source (``onboard.sensors.DepthSource``) and a camera pose provider per vehicle.

Decoders are strict: every malformed payload raises ``DecodeError`` with one of
``REJECT_REASONS`` (never another exception), and the subscriber counts rejections per stream
and reason instead of crashing its callback thread.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from onboard.comm.zenoh_session import ZenohEndpoints, open_session
from onboard.mapping.camera import CameraIntrinsics, DepthFrame
from onboard.sensors.mount import camera_pose
from onboard.threadname import name_callback_thread

log = logging.getLogger(__name__)

DEPTH_MAGIC = b"DPT1"
DEPTH_ENCODING = "z16_mm"
REJECT_REASONS = (
    "wrong-version",  # not a DPT1 frame, or an unknown image encoding
    "truncated",  # shorter than its header says
    "oversized",  # larger than the limits (bytes, header, image size)
    "wrong-size",  # trailing bytes, or the intrinsics disagree with the image shape
    "non-finite",  # NaN, infinity or an out-of-range number in the header
    "malformed",  # not JSON, missing or unknown keys, wrong types, not a rotation, bad values
    "wrong-sender",  # the id in the payload differs from the one in the key expression
)
_INTRINSICS_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "min_depth_m", "max_depth_m")
_HEADER_KEYS = {"system_id", "stamp_s", "position", "rotation", "intrinsics", "shape", "encoding"}
_OPTIONAL_HEADER_KEYS = frozenset({"render_step", "decimation"})
_POSE_KEYS = {
    "system_id",
    "t_s",
    "position_enu_m",
    "velocity_enu_m_s",
    "quaternion_enu_flu",
    "yaw_enu_rad",
    "armed",
    "landed",
    "mode",
    "collisions",
}
_MAX_ID = 2**31 - 1


class DecodeError(ValueError):
    """A payload the decoder refused; ``reason`` is one of ``REJECT_REASONS``."""

    def __init__(self, reason: str, detail: str) -> None:
        assert reason in REJECT_REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class CodecLimits:
    """Largest payloads the decoders accept."""

    max_width: int = 1920
    max_height: int = 1200
    max_header_bytes: int = 8192
    max_pose_bytes: int = 2048

    @property
    def max_frame_bytes(self) -> int:
        return 8 + self.max_header_bytes + 2 * self.max_width * self.max_height


DEFAULT_LIMITS = CodecLimits()


# --- strict field readers -----------------------------------------------------------------------


def _reject_constant(name: str) -> Any:
    raise DecodeError("non-finite", f"{name} in JSON")


def _json(data: bytes, what: str) -> dict[str, Any]:
    try:
        obj = json.loads(data, parse_constant=_reject_constant)
    except DecodeError:
        raise
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError
        raise DecodeError("malformed", f"{what} is not JSON ({type(e).__name__})") from None
    if not isinstance(obj, dict):
        raise DecodeError("malformed", f"{what} is not a JSON object")
    return obj


def _keys(
    obj: dict[str, Any], want: set[str], what: str, optional: frozenset = frozenset()
) -> None:
    missing = want - set(obj) - optional
    extra = set(obj) - want
    if missing or extra:
        raise DecodeError(
            "malformed", f"{what}: missing {sorted(missing)}, unknown {sorted(extra)}"
        )


def _number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DecodeError("malformed", f"{name} must be a number, got {type(v).__name__}")
    try:
        f = float(v)
    except OverflowError:
        raise DecodeError("non-finite", f"{name} is out of range") from None
    if not math.isfinite(f):
        raise DecodeError("non-finite", f"{name} is {f}")
    return f


def _integer(name: str, v: Any, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise DecodeError("malformed", f"{name} must be an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise DecodeError("malformed", f"{name} = {v} is outside [{lo}, {hi}]")
    return int(v)


def _vector(name: str, v: Any, n: int) -> list[float]:
    if not isinstance(v, list) or len(v) != n:
        raise DecodeError("malformed", f"{name} must be a list of {n} numbers")
    return [_number(f"{name}[{i}]", x) for i, x in enumerate(v)]


def _flag(name: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise DecodeError("malformed", f"{name} must be true or false")
    return v


# --- the pose sample ----------------------------------------------------------------------------


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
            allow_nan=False,
        ).encode()

    @staticmethod
    def from_bytes(data: bytes, limits: CodecLimits = DEFAULT_LIMITS) -> TruthSample:
        """Decode a pose; raises ``DecodeError`` for anything but a well-formed sample."""
        if len(data) > limits.max_pose_bytes:
            raise DecodeError("oversized", f"pose of {len(data)} bytes")
        d = _json(bytes(data), "pose")
        _keys(d, _POSE_KEYS, "pose")
        q = _vector("quaternion_enu_flu", d["quaternion_enu_flu"], 4)
        if abs(math.sqrt(sum(c * c for c in q)) - 1.0) > 1e-3:
            raise DecodeError("malformed", "quaternion_enu_flu is not a unit quaternion")
        mode = d["mode"]
        if not isinstance(mode, str) or len(mode) > 64:
            raise DecodeError("malformed", "mode must be a string of at most 64 characters")
        p = _vector("position_enu_m", d["position_enu_m"], 3)
        v = _vector("velocity_enu_m_s", d["velocity_enu_m_s"], 3)
        return TruthSample(
            system_id=_integer("system_id", d["system_id"], 0, _MAX_ID),
            t_s=_number("t_s", d["t_s"]),
            position_m=(p[0], p[1], p[2]),
            velocity_m_s=(v[0], v[1], v[2]),
            quaternion=(q[0], q[1], q[2], q[3]),
            yaw_rad=_number("yaw_enu_rad", d["yaw_enu_rad"]),
            armed=_flag("armed", d["armed"]),
            landed=_flag("landed", d["landed"]),
            mode=mode,
            collisions=_integer("collisions", d["collisions"], 0, _MAX_ID),
        )

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), world_from_camera (3, 3)) of the forward depth camera."""
        return camera_pose(self.position_m, self.quaternion)


# --- the depth frame ----------------------------------------------------------------------------


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
    render_step: int = 1
    """Only every render_step-th row and column was rendered (the rest reads 0); on the wire
    only when above 1."""
    decimation: int = 1
    """The image is every decimation-th pixel of the camera's (``DepthFrame.decimation``;
    ``intrinsics`` are the smaller image's); on the wire only when above 1."""

    def to_bytes(self) -> bytes:
        """The wire form (raises ValueError for a non-finite stamp, pose or intrinsics)."""
        header = json.dumps(
            {
                "system_id": self.system_id,
                "stamp_s": self.stamp_s,
                "position": [float(x) for x in self.position],
                "rotation": [float(x) for x in np.asarray(self.rotation).reshape(9)],
                "intrinsics": self.intrinsics,
                "shape": list(self.depth_m.shape),
                "encoding": DEPTH_ENCODING,
                **({"render_step": int(self.render_step)} if self.render_step != 1 else {}),
                **({"decimation": int(self.decimation)} if self.decimation != 1 else {}),
            },
            separators=(",", ":"),
            allow_nan=False,
        ).encode()
        d = np.nan_to_num(np.asarray(self.depth_m, dtype=np.float64), nan=0.0, posinf=0.0)
        mm = np.clip(np.rint(d * 1000.0), 0, 65535).astype("<u2")
        return DEPTH_MAGIC + struct.pack("<I", len(header)) + header + mm.tobytes()

    @staticmethod
    def from_bytes(data: bytes, limits: CodecLimits = DEFAULT_LIMITS) -> DepthImage:
        """Decode a frame; raises ``DecodeError`` for anything but a well-formed frame."""
        data = bytes(data)
        if len(data) > limits.max_frame_bytes:
            raise DecodeError("oversized", f"frame of {len(data)} bytes")
        if len(data) < 8:
            raise DecodeError("truncated", f"{len(data)} bytes, no header")
        if data[:4] != DEPTH_MAGIC:
            raise DecodeError("wrong-version", f"magic {data[:4]!r}, expected {DEPTH_MAGIC!r}")
        (n,) = struct.unpack("<I", data[4:8])
        if n > limits.max_header_bytes:
            raise DecodeError("oversized", f"header of {n} bytes")
        if 8 + n > len(data):
            raise DecodeError("truncated", f"header of {n} bytes, {len(data) - 8} left")
        h = _json(data[8 : 8 + n], "depth header")
        _keys(h, _HEADER_KEYS | _OPTIONAL_HEADER_KEYS, "depth header", _OPTIONAL_HEADER_KEYS)
        if h["encoding"] != DEPTH_ENCODING:
            raise DecodeError("wrong-version", f"encoding {h['encoding']!r}")
        shape = h["shape"]
        if not isinstance(shape, list) or len(shape) != 2:
            raise DecodeError("malformed", "shape must be [height, width]")
        height = _integer("shape[0]", shape[0], 1, _MAX_ID)
        width = _integer("shape[1]", shape[1], 1, _MAX_ID)
        if height > limits.max_height or width > limits.max_width:
            raise DecodeError("oversized", f"image of {height} x {width}")
        body = len(data) - 8 - n
        if body < 2 * height * width:
            raise DecodeError("truncated", f"{body} image bytes, {2 * height * width} expected")
        if body > 2 * height * width:
            raise DecodeError("wrong-size", f"{body} image bytes, {2 * height * width} expected")
        intr = _intrinsics(h["intrinsics"])
        ih, iw = int(intr["height"]), int(intr["width"])
        if (ih, iw) != (height, width):
            raise DecodeError("wrong-size", f"intrinsics {ih} x {iw}, image {height} x {width}")
        rot = np.array(_vector("rotation", h["rotation"], 9)).reshape(3, 3)
        if not (np.allclose(rot.T @ rot, np.eye(3), atol=1e-4) and np.linalg.det(rot) > 0.0):
            raise DecodeError("malformed", "rotation is not a proper rotation matrix")
        mm = np.frombuffer(data, dtype="<u2", count=height * width, offset=8 + n)
        return DepthImage(
            system_id=_integer("system_id", h["system_id"], 0, _MAX_ID),
            stamp_s=_number("stamp_s", h["stamp_s"]),
            # one pass (uint16 -> float32, then the float32 division, as astype + divide)
            depth_m=np.divide(mm.reshape(height, width), np.float32(1000.0), dtype=np.float32),
            position=np.array(_vector("position", h["position"], 3)),
            rotation=rot,
            intrinsics=intr,
            render_step=_integer("render_step", h.get("render_step", 1), 1, 64),
            decimation=_integer("decimation", h.get("decimation", 1), 1, 64),
        )

    def to_depth_frame(self) -> DepthFrame:
        """This image as the mapping pipeline's ``DepthFrame``."""
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
        return DepthFrame(
            self.depth_m,
            self.stamp_s,
            self.position,
            self.rotation,
            intr,
            self.render_step,
            self.decimation,
        )


def _intrinsics(v: Any) -> dict[str, float]:
    if not isinstance(v, dict):
        raise DecodeError("malformed", "intrinsics must be an object")
    _keys(v, set(_INTRINSICS_KEYS), "intrinsics", frozenset({"min_depth_m", "max_depth_m"}))
    out: dict[str, float] = {}
    for k in ("width", "height"):  # the mock writes every intrinsic as a float
        x = _number(f"intrinsics.{k}", v[k])
        if not (x.is_integer() and 1 <= x <= _MAX_ID):
            raise DecodeError("malformed", f"intrinsics.{k} = {x} is not a pixel count")
        out[k] = x
    for k in ("fx", "fy", "cx", "cy"):
        out[k] = _number(f"intrinsics.{k}", v[k])
    out["min_depth_m"] = _number("intrinsics.min_depth_m", v.get("min_depth_m", 0.2))
    out["max_depth_m"] = _number("intrinsics.max_depth_m", v.get("max_depth_m", 5.0))
    if not (out["fx"] > 0.0 and out["fy"] > 0.0):
        raise DecodeError("malformed", "intrinsics.fx and fy must be > 0")
    if not 0.0 < out["min_depth_m"] < out["max_depth_m"]:
        raise DecodeError("malformed", "intrinsics need 0 < min_depth_m < max_depth_m")
    return out


# --- consumers ----------------------------------------------------------------------------------


class TruthDepthSource:
    """One vehicle's simulated frames as a depth source (``onboard.sensors.DepthSource``):
    ``read`` returns the oldest frame newer than the last one returned (a ``DepthFrame``), or
    None when there is none. ``next_after(stamp_s)`` gives that frame: a subscriber that keeps a
    few recent frames hands them out in order, so a reader busy for a while (an ESDF refresh)
    catches up instead of losing the frames that came meanwhile. ``on_close``: called by
    ``close`` (e.g. to close a subscriber it owns). ``newest``: the stamp of the newest frame
    received, read or not (None before the first; ``newest_stamp_s``): whether the camera is
    alive, apart from whether its reader keeps up."""

    def __init__(
        self,
        next_after: Callable[[float], DepthImage | None],
        on_close: Callable[[], None] | None = None,
        newest: Callable[[], float | None] | None = None,
    ) -> None:
        self._next_after = next_after
        self._on_close = on_close
        self._newest = newest
        self._last_stamp = -math.inf
        self._intrinsics: CameraIntrinsics | None = None

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The intrinsics of the last frame read (D435 defaults before the first)."""
        return self._intrinsics if self._intrinsics is not None else CameraIntrinsics()

    def newest_stamp_s(self) -> float | None:
        """The stamp of the newest frame that has arrived, read or not (None: none yet, or a
        source that cannot tell): frames still come when it moves on, even while ``read`` is
        not called (a starved mapping thread)."""
        return None if self._newest is None else self._newest()

    def read(self) -> DepthFrame | None:
        img = self._next_after(self._last_stamp)
        if img is None or img.stamp_s <= self._last_stamp:
            return None
        self._last_stamp = img.stamp_s
        frame = img.to_depth_frame()
        self._intrinsics = frame.intrinsics
        return frame

    def close(self) -> None:
        if self._on_close is not None:
            cb, self._on_close = self._on_close, None
            cb()


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


def _sender(key: str, prefix: str) -> int | None:
    """The system id in ``<prefix>/<id>/<stream>``, or None when it is not a number."""
    rest = key[len(prefix) + 1 :] if key.startswith(prefix + "/") else key
    head = rest.split("/", 1)[0]
    return int(head) if head.isdigit() else None


DEPTH_QUEUE = 4
"""Depth frames a ``ZenohTruthSubscriber`` keeps per vehicle (133 ms at 30 frames/s): a reader
busy for up to that long still gets every frame."""


class ZenohTruthSubscriber:
    """Subscribes to the poses and depth frames the mock publishes; keeps the latest pose and
    the ``depth_queue`` newest depth frames per vehicle (a frame older than the newest kept is
    dropped; when the queue is full the oldest goes).

    The session comes from ``session`` (shared, left open by ``close``), else is opened with
    ``endpoints`` (``ZenohEndpoints``), else with ``connect`` / ``listen`` endpoint lists.
    ``counters()``: ``pose.rx``, ``depth.rx``, ``depth.out-of-order``, ``<stream>.<reason>`` per
    rejection reason, and ``error`` (an unexpected exception in a callback, logged).
    ``system_id``: subscribe to that vehicle's streams only (a flight service: the other
    vehicles' frames are neither sent to it nor decoded), else to every vehicle's.
    ``poses``: also subscribe to the poses (False: depth frames only; a flight service has its
    autopilot's estimate, and the 50 Hz poses would only be decoded and dropped).
    """

    def __init__(
        self,
        prefix: str = "swarm/sim",
        connect: Sequence[str] = ("tcp/127.0.0.1:7447",),
        listen: Sequence[str] = (),
        *,
        endpoints: ZenohEndpoints | None = None,
        session: Any = None,
        limits: CodecLimits = DEFAULT_LIMITS,
        system_id: int | None = None,
        depth_queue: int = DEPTH_QUEUE,
        poses: bool = True,
    ) -> None:
        if system_id is not None and (isinstance(system_id, bool) or not 0 < system_id < 256):
            raise ValueError(f"system_id must be a MAVLink system id 1..255, got {system_id!r}")
        if isinstance(depth_queue, bool) or not 1 <= depth_queue <= 64:
            raise ValueError(f"depth_queue must be 1..64 frames, got {depth_queue!r}")
        self._queue_len = int(depth_queue)
        self.prefix = prefix.rstrip("/")
        self.limits = limits
        self._lock = threading.Lock()
        self._poses: dict[int, TruthSample] = {}
        self._depth: dict[int, deque[DepthImage]] = {}
        self._counts: dict[str, int] = {"pose.rx": 0, "depth.rx": 0, "depth.out-of-order": 0}
        for stream in ("pose", "depth"):
            self._counts.update({f"{stream}.{r}": 0 for r in REJECT_REASONS})
        self._counts["error"] = 0
        self._own_session = session is None
        if session is None:
            ep = endpoints or ZenohEndpoints(listen=tuple(listen), connect=tuple(connect))
            session = open_session(ep)
        self._session = session
        self._subs: list[Any] = []
        try:
            who = "*" if system_id is None else str(int(system_id))
            if poses:
                self._subs.append(
                    session.declare_subscriber(f"{self.prefix}/{who}/pose", self._on_pose)
                )
            self._subs.append(
                session.declare_subscriber(f"{self.prefix}/{who}/depth", self._on_depth)
            )
        except Exception:
            self.close()
            raise

    def __enter__(self) -> ZenohTruthSubscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _count(self, key: str) -> None:
        with self._lock:
            self._counts[key] += 1

    def _admit(self, sample: Any, stream: str, parse: Callable[[bytes, Any], Any]) -> Any:
        """The decoded message of ``sample`` (its sender checked against its key), or None with
        the rejection counted as ``<stream>.<reason>``; a bug is logged and counted as
        ``error``, and the subscription lives on."""
        try:
            msg = parse(sample.payload.to_bytes(), self.limits)
            if _sender(str(sample.key_expr), self.prefix) != msg.system_id:
                raise DecodeError("wrong-sender", f"{msg.system_id} under {sample.key_expr}")
        except DecodeError as e:
            self._count(f"{stream}.{e.reason}")
            return None
        except Exception:
            log.exception("%s callback failed", stream)
            self._count("error")
            return None
        return msg

    def _on_pose(self, sample: Any) -> None:
        name_callback_thread("truth-pose-rx")
        s = self._admit(sample, "pose", TruthSample.from_bytes)
        if s is None:
            return
        with self._lock:
            self._poses[s.system_id] = s
            self._counts["pose.rx"] += 1

    def _on_depth(self, sample: Any) -> None:
        name_callback_thread("depth-rx")
        img = self._admit(sample, "depth", DepthImage.from_bytes)
        if img is None:
            return
        with self._lock:
            q = self._depth.get(img.system_id)
            if q is None:
                q = self._depth[img.system_id] = deque(maxlen=self._queue_len)
            elif q and img.stamp_s < q[-1].stamp_s:
                self._counts["depth.out-of-order"] += 1
                return
            q.append(img)
            self._counts["depth.rx"] += 1

    def counters(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    @property
    def errors(self) -> int:
        """Payloads refused or failed, all streams and reasons together."""
        c = self.counters()
        return sum(v for k, v in c.items() if not k.endswith((".rx", ".out-of-order")))

    def pose(self, system_id: int) -> TruthSample | None:
        with self._lock:
            return self._poses.get(system_id)

    def depth_image(self, system_id: int) -> DepthImage | None:
        """The newest depth frame of a vehicle."""
        with self._lock:
            q = self._depth.get(system_id)
            return q[-1] if q else None

    def depth_after(self, system_id: int, stamp_s: float) -> DepthImage | None:
        """The oldest kept depth frame of a vehicle newer than ``stamp_s``."""
        with self._lock:
            for img in self._depth.get(system_id, ()):
                if img.stamp_s > stamp_s:
                    return img
        return None

    def depth_newest_stamp(self, system_id: int) -> float | None:
        """The stamp of the newest depth frame kept of a vehicle (None: none yet)."""
        with self._lock:
            q = self._depth.get(system_id)
            return q[-1].stamp_s if q else None

    def depth_source(
        self, system_id: int, on_close: Callable[[], None] | None = None
    ) -> TruthDepthSource:
        """The frames of one vehicle (closing the source calls ``on_close``, if given, and
        leaves the subscriber open otherwise)."""
        return TruthDepthSource(
            lambda after: self.depth_after(system_id, after),
            on_close=on_close,
            newest=lambda: self.depth_newest_stamp(system_id),
        )

    def pose_provider(self, system_id: int) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        return pose_provider(lambda: self.pose(system_id))

    def close(self) -> None:
        subs, self._subs = self._subs, []
        for sub in subs:
            sub.undeclare()
        if self._own_session and self._session is not None:
            session, self._session = self._session, None
            session.close()


def open_depth_source(
    system_id: int,
    prefix: str = "swarm/sim",
    endpoints: ZenohEndpoints | None = None,
    session: Any = None,
) -> TruthDepthSource:
    """A depth source of one vehicle's frames from the mock that owns its subscriber (closing
    the source closes the subscription, and the session unless ``session`` was given)."""
    sub = ZenohTruthSubscriber(
        prefix,
        endpoints=endpoints or ZenohEndpoints(),
        session=session,
        system_id=system_id,
        poses=False,
    )
    return sub.depth_source(system_id, on_close=sub.close)
