"""Live 3-D view of the swarm in Foxglove, through the ``foxglove-sdk`` WebSocket server.

Open Foxglove (app or desktop), "Open connection" -> Foxglove WebSocket -> the URL printed by
``swarm-gcs view`` (``ws://127.0.0.1:8765`` by default), then add a 3D panel: frame ``enu``.

Topics (``foxglove.SceneUpdate``, protobuf):

- ``/swarm/world``: the obstacles (vertical cylinders as cylinders, boxes as cubes), re-sent
  every ``world_period_s`` so that a viewer that connects late gets them;
- ``/swarm/drones``: one entity per drone (``drone/<id>``: a sphere and a label with its id and
  flight state), its planned trajectory (``plan/<id>``: the trajectory sampled as a polyline
  from now to its end) and the formation target (``formation``: where each slot should be,
  placed at the swarm's centroid, with a thin line from each drone to its slot).

:func:`scene_update` builds the messages from a :class:`SceneInput` (pure, no I/O);
:class:`SwarmView` serves them, fed by a callable that returns the current input (a ground
station's view of the bus: :func:`station_input`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gcs.station import GroundStation
    from onboard.planner.trajectory import Trajectory
    from onboard.world import World

log = logging.getLogger(__name__)

FRAME = "enu"
WORLD_TOPIC = "/swarm/world"
SWARM_TOPIC = "/swarm/drones"
DRONE_DIAMETER_M = 0.3


@dataclass(frozen=True)
class SceneInput:
    """One snapshot of what to draw (global time ``t_s``, ENU metres).

    positions: drone id -> position; states: drone id -> flight state name; trajectories: drone
    id -> its current plan; formation: (offsets of the slots from the formation's centre (N, 3),
    drone id -> slot) or None."""

    t_s: float
    positions: Mapping[int, np.ndarray] = field(default_factory=dict)
    states: Mapping[int, str] = field(default_factory=dict)
    trajectories: Mapping[int, Trajectory] = field(default_factory=dict)
    formation: tuple[np.ndarray, Mapping[int, int]] | None = None


def _palette(i: int) -> tuple[float, float, float]:
    """tab10-like colours, by drone id."""
    colors = [
        (0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
        (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5),
        (0.74, 0.74, 0.13), (0.09, 0.75, 0.81),
    ]  # fmt: skip
    return colors[i % len(colors)]


def _stamp(t_s: float) -> Any:
    from foxglove.messages import Timestamp

    ns = int(round(t_s * 1e9))
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _pose(p: np.ndarray | tuple[float, float, float]) -> Any:
    from foxglove.messages import Pose, Quaternion, Vector3

    return Pose(
        position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
    )


def world_update(world: World, t_s: float) -> Any:
    """The obstacles of ``world`` as one ``SceneUpdate`` (entity ``obstacles``)."""
    from foxglove.messages import (
        Color,
        CubePrimitive,
        CylinderPrimitive,
        SceneEntity,
        SceneUpdate,
        Vector3,
    )

    trunk = Color(r=0.45, g=0.35, b=0.25, a=1.0)
    cylinders = [
        CylinderPrimitive(
            pose=_pose((c[0], c[1], 0.5 * (c[3] + c[4]))),
            size=Vector3(x=2.0 * c[2], y=2.0 * c[2], z=c[4] - c[3]),
            bottom_scale=1.0,
            top_scale=1.0,
            color=trunk,
        )
        for c in np.asarray(world.cylinders, dtype=np.float64)
    ]
    cubes = [
        CubePrimitive(
            pose=_pose(0.5 * (b[:3] + b[3:])),
            size=Vector3(x=b[3] - b[0], y=b[4] - b[1], z=b[5] - b[2]),
            color=Color(r=0.5, g=0.5, b=0.55, a=1.0),
        )
        for b in np.asarray(world.boxes, dtype=np.float64)
    ]
    entity = SceneEntity(
        timestamp=_stamp(t_s),
        frame_id=FRAME,
        id="obstacles",
        cylinders=cylinders,
        cubes=cubes,
    )
    return SceneUpdate(entities=[entity])


def scene_update(s: SceneInput, plan_step_s: float = 0.2, max_plan_s: float = 20.0) -> Any:
    """The drones, their plans and the formation target as one ``SceneUpdate``."""
    from foxglove.messages import (
        Color,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TextPrimitive,
        Vector3,
    )

    stamp = _stamp(s.t_s)
    entities = []
    size = Vector3(x=DRONE_DIAMETER_M, y=DRONE_DIAMETER_M, z=DRONE_DIAMETER_M)
    for d, p in sorted(s.positions.items()):
        r, g, b = _palette(d)
        label = f"{d} {s.states.get(d, '')}".strip()
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=FRAME,
                id=f"drone/{d}",
                spheres=[
                    SpherePrimitive(pose=_pose(p), size=size, color=Color(r=r, g=g, b=b, a=1))
                ],
                texts=[
                    TextPrimitive(
                        pose=_pose((p[0], p[1], p[2] + 0.35)),
                        billboard=True,
                        font_size=14.0,
                        scale_invariant=True,
                        color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                        text=label,
                    )
                ],
            )
        )
    for d, tr in sorted(s.trajectories.items()):
        t0 = max(s.t_s, tr.t0_s)
        t1 = min(tr.t_end_s, t0 + max_plan_s)
        if t1 <= t0:
            continue
        ts = np.append(np.arange(t0, t1, plan_step_s), t1)
        pts = tr.sample(ts)
        r, g, b = _palette(d)
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=FRAME,
                id=f"plan/{d}",
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineStrip,
                        thickness=2.0,
                        scale_invariant=True,
                        points=[Point3(x=float(q[0]), y=float(q[1]), z=float(q[2])) for q in pts],
                        color=Color(r=r, g=g, b=b, a=0.8),
                    )
                ],
            )
        )
    if s.formation is not None:
        offsets, slots = s.formation
        have = [d for d in slots if d in s.positions]
        if have:
            center = np.mean([s.positions[d] for d in have], axis=0)
            target = center + np.asarray(offsets, dtype=np.float64)
            ghost = Color(r=0.2, g=0.9, b=0.3, a=0.35)
            spheres = [SpherePrimitive(pose=_pose(q), size=size, color=ghost) for q in target]
            segs = []
            for d in have:
                segs += [_p3(s.positions[d]), _p3(target[slots[d]])]
            lines = [
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    thickness=1.0,
                    scale_invariant=True,
                    points=segs,
                    color=Color(r=0.2, g=0.9, b=0.3, a=0.6),
                )
            ]
            entities.append(
                SceneEntity(
                    timestamp=stamp, frame_id=FRAME, id="formation", spheres=spheres, lines=lines
                )
            )
    return SceneUpdate(entities=entities)


def _p3(p: np.ndarray) -> Any:
    from foxglove.messages import Point3

    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def station_input(gs: GroundStation) -> Callable[[], SceneInput]:
    """A snapshot source from a ground station: positions and states of the drones up, their
    valid trajectories, the newest known formation."""

    def snapshot() -> SceneInput:
        now = float(gs.clock())
        views = gs.views()
        positions = {
            d: np.asarray(v.position_m) for d, v in views.items() if v.position_m is not None
        }
        states = {d: v.flight_state or "" for d, v in views.items()}
        trajs = {d: m.trajectory for d, m in gs.node.receive(-1, now).items()}
        known = gs.known_formation()
        formation = None
        if known is not None:
            wire = known[1]
            formation = (np.asarray(wire.points_m, dtype=np.float64), dict(wire.slots))
        return SceneInput(now, positions, states, trajs, formation)

    return snapshot


class SwarmView:
    """Serves the swarm to Foxglove: ``source()`` is asked for a :class:`SceneInput` at
    ``rate_hz``; ``world`` (optional) is sent every ``world_period_s``. ``port`` 0 picks a free
    port (read :attr:`port`). Use as a context manager or call :meth:`close`."""

    def __init__(
        self,
        source: Callable[[], SceneInput],
        world: World | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        rate_hz: float = 5.0,
        world_period_s: float = 2.0,
        name: str = "swarm-gcs",
    ) -> None:
        import foxglove
        from foxglove.channels import SceneUpdateChannel

        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"view rate_hz must be > 0, got {rate_hz}")
        self.source = source
        self.world = world
        self.period_s = 1.0 / rate_hz
        self.world_period_s = float(world_period_s)
        self.published = 0
        self.errors = 0
        self._ctx = foxglove.Context()
        self._world_ch = SceneUpdateChannel(WORLD_TOPIC, context=self._ctx)
        self._swarm_ch = SceneUpdateChannel(SWARM_TOPIC, context=self._ctx)
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._ctx)
        except Exception as e:  # the SDK raises its own error type: name the address
            raise RuntimeError(f"cannot serve the Foxglove view on {host}:{port}: {e}") from e
        self.host = host
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_world = -math.inf

    @property
    def port(self) -> int:
        return int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def publish_once(self) -> None:
        """Ask the source and publish (the world too when it is due)."""
        s = self.source()
        now = time.monotonic()
        if self.world is not None and now - self._last_world >= self.world_period_s:
            self._world_ch.log(world_update(self.world, s.t_s), log_time=int(s.t_s * 1e9))
            self._last_world = now
        self._swarm_ch.log(scene_update(s), log_time=int(s.t_s * 1e9))
        self.published += 1

    def start(self) -> SwarmView:
        """Publish in a background thread until :meth:`close`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="swarm-view", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.publish_once()
            except Exception:  # a bad snapshot must not end the view: log it, count it
                self.errors += 1
                log.exception("view: cannot publish a scene")
            self._stop.wait(self.period_s)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._server.stop()

    def __enter__(self) -> SwarmView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
