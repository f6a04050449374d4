"""Flight records: one MCAP file per flight, JSON-schema channels that Foxglove opens as they are.

Topics (log time = global time of the event, nanoseconds):

- ``/state``      the vehicle and flight state (10 Hz): position, velocity, yaw, mode, armed ...
- ``/pose``       the same pose as ``foxglove.PoseInFrame`` (frame ``enu``) for the 3D panel
- ``/setpoint``   every setpoint streamed to the autopilot: position, velocity, acceleration, yaw
- ``/plan``       every replan: status, timing (ms, iterations, evaluations), the peers in the
                  formation and only avoided, slot and epoch, the trajectory
- ``/map``        what the map holds (2 Hz while frames arrive): occupied cells, the nearest
                  mapped surface to the camera and where it is
- ``/counters``   bus and link counters (1 Hz)
- ``/transition`` flight state machine transitions
- ``/log``        events and reactions as ``foxglove.Log``

Writers in time-critical threads (the setpoint stream) only append to a queue;
``FlightRecorder.flush()`` (the service's main loop) encodes and writes. ``read_record`` loads a
file back (the ground station's flight report uses it).
"""

from __future__ import annotations

import json
import math
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

_NUM = {"type": "number"}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}


def _obj(title: str, props: Mapping[str, Any], description: str = "") -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object", "properties": props}


SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    "/state": (
        "swarm.VehicleState",
        _obj(
            "swarm.VehicleState",
            {
                "t_s": _NUM,
                "drone_id": {"type": "integer"},
                "flight_state": {"type": "string"},
                "position_enu_m": _VEC3,
                "velocity_enu_m_s": _VEC3,
                "yaw_enu_rad": _NUM,
                "armed": {"type": "boolean"},
                "landed": {"type": "boolean"},
                "mode": {"type": "string"},
                "battery_v": _NUM,
            },
            "Vehicle state (ENU, local frame of the autopilot) and flight state",
        ),
    ),
    "/pose": (
        "foxglove.PoseInFrame",
        _obj(
            "foxglove.PoseInFrame",
            {
                "timestamp": _TIME,
                "frame_id": {"type": "string"},
                "pose": _obj(
                    "foxglove.Pose",
                    {
                        "position": _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM}),
                        "orientation": _obj(
                            "foxglove.Quaternion",
                            {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM},
                        ),
                    },
                ),
            },
            "A timestamped pose for an object or reference frame in 3D space",
        ),
    ),
    "/setpoint": (
        "swarm.Setpoint",
        _obj(
            "swarm.Setpoint",
            {
                "t_s": _NUM,
                "position_enu_m": _VEC3,
                "velocity_enu_m_s": _VEC3,
                "acceleration_enu_m_s2": _VEC3,
                "yaw_enu_rad": _NUM,
            },
            "A setpoint sent to the autopilot (ENU; converted to NED on the link)",
        ),
    ),
    "/plan": (
        "swarm.Plan",
        _obj(
            "swarm.Plan",
            {
                "t_s": _NUM,
                "status": {"type": "string"},
                "traj_id": {"type": "integer"},
                "reason": {"type": "string"},
                "plan_ms": _NUM,
                "plan_cpu_ms": {
                    "type": "number",
                    "description": "the planning thread's CPU time within plan_ms (no waiting)",
                },
                "iterations": {"type": "integer"},
                "evaluations": {"type": "integer"},
                "cycle_ms": _NUM,
                "n_peers": {"type": "integer", "description": "peers in the formation term"},
                "formation_peers": {"type": "array", "items": {"type": "integer"}},
                "avoided_peers": {
                    "type": "array",
                    "items": {"type": "integer"},
                    "description": "peers only avoided (silent, other epoch, slot conflict)",
                },
                "silent_peers": {
                    "type": "array",
                    "items": {"type": "integer"},
                    "description": "peers silent past peer_silence_s (avoided, also as ghosts)",
                },
                "deviating_peers": {
                    "type": "array",
                    "items": {"type": "integer"},
                    "description": "peers reported off their trajectory (avoided where they are)",
                },
                "slot": {"type": "integer"},
                "formation_epoch": {"type": "integer"},
                "reforming": {
                    "type": "boolean",
                    "description": "within reform_s of a formation change (with reform_params)",
                },
                "recovering": {
                    "type": "boolean",
                    "description": "recovering the shape (recover_e_sim; with recover_params)",
                },
                "unheard_by": {
                    "type": "array",
                    "items": {"type": "integer"},
                    "description": "peers that reported they did not hear this drone "
                    "(planned with unheard_params: unheard_margin_m more from every peer)",
                },
                "t0_s": _NUM,
                "durations_s": {"type": "array", "items": _NUM},
                "coeffs": {
                    "type": "array",
                    "items": _NUM,
                    "description": "(M, 6, 3) row-major: piece, power of t, ENU axis",
                },
                "goal_enu_m": _VEC3,
            },
            "One replan: outcome, timing and the trajectory it produced",
        ),
    ),
    "/map": (
        "swarm.Map",
        _obj(
            "swarm.Map",
            {
                "t_s": _NUM,
                "frames": {"type": "integer"},
                "occupied_cells": {"type": "integer"},
                "camera_enu_m": _VEC3,
                "nearest_obstacle_m": _NUM,
                "nearest_obstacle_enu_m": _VEC3,
            },
            "The rolling map: occupied cells, the nearest mapped surface to the camera (ENU)",
        ),
    ),
    "/counters": (
        "swarm.Counters",
        _obj(
            "swarm.Counters",
            {"t_s": _NUM, "counters": {"type": "object", "additionalProperties": _NUM}},
            "Bus, link and mapping counters",
        ),
    ),
    "/transition": (
        "swarm.Transition",
        _obj(
            "swarm.Transition",
            {
                "t_s": _NUM,
                "source": {"type": "string"},
                "target": {"type": "string"},
                "reason": {"type": "string"},
            },
            "A flight state machine transition",
        ),
    ),
    "/log": (
        "foxglove.Log",
        _obj(
            "foxglove.Log",
            {
                "timestamp": _TIME,
                "level": {"type": "integer", "description": "1 debug 2 info 3 warning 4 error"},
                "message": {"type": "string"},
                "name": {"type": "string"},
                "file": {"type": "string"},
                "line": {"type": "integer"},
            },
            "A log message",
        ),
    ),
}

LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def _stamp(t_s: float) -> dict[str, int]:
    ns = _ns(t_s)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _jsonable(x: Any) -> Any:
    """Numbers, lists and mappings as JSON values (numpy arrays too; NaN and inf as null)."""
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return _jsonable(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return x


def _enc_hook(x: Any) -> Any:
    """What msgspec cannot encode itself: numpy arrays and scalars as lists and numbers, other
    mappings as dicts."""
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, Mapping):
        return dict(x)
    raise TypeError(f"cannot record a {type(x).__name__}")


_ENCODER = msgspec.json.Encoder(enc_hook=_enc_hook)


def encode_record(payload: Mapping[str, Any]) -> bytes:
    """A record's payload as compact JSON, the value of ``json.dumps(_jsonable(payload),
    separators=(",", ":"))`` (NaN and inf as null, numpy as lists and numbers, keys as
    strings), about five times faster (msgspec; the flight service records ~70 messages a
    second, the setpoints at 50 Hz among them). What msgspec refuses takes the json path."""
    try:
        return _ENCODER.encode(payload)
    except (TypeError, msgspec.EncodeError):  # keys msgspec refuses (tuples), ints over 64 bits
        return json.dumps(_jsonable(payload), separators=(",", ":")).encode()


def flight_file_name(drone_id: int, t_s: float) -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(t_s))
    return f"drone{drone_id}-{stamp}.mcap"


class FlightRecorder:
    """Writes one flight to ``path`` (MCAP, zstd chunks). Thread-safe producers (``put`` only
    appends to a bounded queue; when full, the oldest entries go and ``dropped`` counts them);
    the owner calls ``flush()`` regularly and ``close()`` at the end."""

    def __init__(
        self,
        path: str | Path,
        drone_id: int,
        metadata: Mapping[str, Any] | None = None,
        max_queue: int = 20000,
    ) -> None:
        from mcap.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.drone_id = drone_id
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=256 * 1024)
        self._writer.start(profile="", library="swarm-onboard")
        self._channels: dict[str, int] = {}
        for topic, (name, schema) in SCHEMAS.items():
            sid = self._writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        meta = {"drone_id": str(drone_id)}
        for k, v in (metadata or {}).items():
            meta[str(k)] = v if isinstance(v, str) else json.dumps(_jsonable(v))
        self._writer.add_metadata("flight", meta)
        self._queue: deque[tuple[str, float, dict[str, Any]]] = deque(maxlen=max_queue)
        self._max_queue = max_queue
        self._seq: dict[str, int] = {}
        self.dropped = 0
        self.written = 0
        self.closed = False

    # ---- producers (any thread) -------------------------------------------------------------
    def put(self, topic: str, t_s: float, payload: Mapping[str, Any]) -> None:
        if topic not in self._channels:
            raise KeyError(f"unknown record topic {topic!r}")
        if len(self._queue) >= self._max_queue:
            self.dropped += 1
        self._queue.append((topic, float(t_s), dict(payload)))

    def state(self, t_s: float, **fields: Any) -> None:
        self.put("/state", t_s, {"t_s": t_s, "drone_id": self.drone_id, **fields})
        p = fields.get("position_enu_m")
        q = fields.get("quaternion_wxyz")
        if p is not None:
            w, x, y, z = q if q is not None else (1.0, 0.0, 0.0, 0.0)
            self.put(
                "/pose",
                t_s,
                {
                    "timestamp": _stamp(t_s),
                    "frame_id": "enu",
                    "pose": {
                        "position": {"x": p[0], "y": p[1], "z": p[2]},
                        "orientation": {"x": x, "y": y, "z": z, "w": w},
                    },
                },
            )

    def setpoint(
        self,
        t_s: float,
        position: Sequence[float] | np.ndarray,
        velocity: Sequence[float] | np.ndarray,
        acceleration: Sequence[float] | np.ndarray,
        yaw_rad: float,
    ) -> None:
        self.put(
            "/setpoint",
            t_s,
            {
                "t_s": t_s,
                "position_enu_m": position,
                "velocity_enu_m_s": velocity,
                "acceleration_enu_m_s2": acceleration,
                "yaw_enu_rad": yaw_rad,
            },
        )

    def plan(self, t_s: float, **fields: Any) -> None:
        self.put("/plan", t_s, {"t_s": t_s, **fields})

    def map(self, t_s: float, **fields: Any) -> None:
        self.put("/map", t_s, {"t_s": t_s, **fields})

    def counters(self, t_s: float, counters: Mapping[str, float]) -> None:
        self.put("/counters", t_s, {"t_s": t_s, "counters": dict(counters)})

    def transition(self, t_s: float, source: str, target: str, reason: str) -> None:
        self.put(
            "/transition", t_s, {"t_s": t_s, "source": source, "target": target, "reason": reason}
        )

    def event(self, t_s: float, message: str, level: str = "info", name: str = "") -> None:
        self.put(
            "/log",
            t_s,
            {
                "timestamp": _stamp(t_s),
                "level": LEVELS.get(level, 2),
                "message": message,
                "name": name or f"drone{self.drone_id}",
                "file": "",
                "line": 0,
            },
        )

    # ---- the owner --------------------------------------------------------------------------
    def flush(self) -> int:
        """Write what is queued; returns the number of messages written."""
        n = 0
        while self._queue and not self.closed:
            topic, t_s, payload = self._queue.popleft()
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            data = encode_record(payload)
            ns = _ns(t_s)
            self._writer.add_message(self._channels[topic], ns, data, ns, seq)
            n += 1
        self.written += n
        return n

    def close(self) -> None:
        if self.closed:
            return
        self.flush()
        self.closed = True
        self._writer.finish()
        self._file.close()

    def __enter__(self) -> FlightRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class FlightRecord:
    """A flight record loaded back: metadata and, per topic, (time, message) in time order."""

    path: Path
    metadata: dict[str, Any] = field(default_factory=dict)
    topics: dict[str, list[tuple[float, dict[str, Any]]]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)

    def messages(self, topic: str) -> list[dict[str, Any]]:
        return [m for _, m in self.topics.get(topic, [])]

    def times(self, topic: str) -> list[float]:
        return [t for t, _ in self.topics.get(topic, [])]

    @property
    def drone_id(self) -> int:
        return int(self.metadata.get("drone_id", -1))

    def transitions(self) -> list[tuple[float, str, str, str]]:
        return [
            (m["t_s"], m["source"], m["target"], m["reason"]) for m in self.messages("/transition")
        ]

    def events(self) -> list[tuple[float, int, str]]:
        out = []
        for t, m in self.topics.get("/log", []):
            out.append((t, int(m["level"]), str(m["message"])))
        return out


def read_record(path: str | Path) -> FlightRecord:
    """Load a flight record (a complete file, or one cut short by a crash: what was written in
    whole chunks is returned)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    p = Path(path)
    rec = FlightRecord(p)
    with open(p, "rb") as f:
        reader = make_reader(f)
        try:
            for m in reader.iter_metadata():
                if m.name == "flight":
                    for k, v in m.metadata.items():
                        try:
                            rec.metadata[k] = json.loads(v)
                        except ValueError:
                            rec.metadata[k] = v
            for schema, channel, msg in reader.iter_messages(log_time_order=True):
                topic = channel.topic
                if schema is not None:
                    rec.schemas[topic] = schema.name
                rec.topics.setdefault(topic, []).append((msg.log_time / 1e9, json.loads(msg.data)))
        except (McapError, EOFError, ValueError) as e:
            rec.metadata.setdefault("read_error", str(e))
    return rec
