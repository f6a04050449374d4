"""A fleet of mock PX4 vehicles in one process: physics, autopilots, MAVLink links, ground truth.

One thread runs everything at ``tick_hz`` (wall clock): it reads every vehicle's socket while it
waits for the next tick, and at each tick advances simulated time by ``speedup / tick_hz``
(autopilot logic, one vectorised physics step for all vehicles, collision checks, telemetry,
ground truth). Commands are answered as soon as they arrive, not at the next tick.

Vehicle i: MAVLink system id i + 1, component 1, listens on ``host:base_port + local_port_offset
+ i`` (PX4: 14580 + i) and sends to ``host:base_port + i`` (PX4: 14540 + i).
"""

from __future__ import annotations

import logging
import math
import selectors
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from sitl_mock import dynamics as dyn
from sitl_mock import telemetry as tm
from sitl_mock.autopilot import Autopilot, AutopilotParams, Estimate, Severity
from sitl_mock.frames import quaternion_from_matrix
from sitl_mock.mavlink_io import SigningConfig, VehicleLink, VehicleView, message_id_by_name
from sitl_mock.truth import DepthCamera, DepthStreamer, TruthSample, TruthSink

log = logging.getLogger("sitl_mock")

_NOISE_BLOCK = 64  # ticks of random draws made at once

# PX4 SITL's default home (Zurich), used as the geodetic reference of the world origin
DEFAULT_LAT_DEG = 47.397742
DEFAULT_LON_DEG = 8.545594
DEFAULT_ALT_M = 488.0


@dataclass(frozen=True)
class SigningSpec:
    """Signing of one vehicle (``system_id``) or of all (None): 64 hex digits of key.

    PX4 v1.16 has no MAVLink signing; this option imitates PX4 v1.17+ and is off unless given.
    """

    key_hex: str
    require: bool = True
    system_id: int | None = None

    def __post_init__(self) -> None:
        try:
            key = bytes.fromhex(self.key_hex)
        except ValueError as e:
            raise ValueError("key_hex must be hexadecimal") from e
        if len(key) != 32:
            raise ValueError("key_hex must hold 32 bytes (64 hex digits)")

    @property
    def key(self) -> bytes:
        return bytes.fromhex(self.key_hex)


@dataclass(frozen=True)
class FleetConfig:
    """Everything about a fleet except its world (see ``Fleet``)."""

    count: int = 1
    host: str = "127.0.0.1"
    base_port: int = 14540
    local_port_offset: int | None = 40  # None: each vehicle binds an ephemeral port
    speedup: float = 1.0
    tick_hz: float = 200.0
    seed: int = 0
    spawn_enu_m: tuple[tuple[float, float, float], ...] | None = None
    spawn_center_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spawn_spacing_m: float = 1.5
    spawn_yaw_deg: float = 90.0  # ENU yaw of every vehicle at start (90 = facing north)
    home_lat_deg: float = DEFAULT_LAT_DEG
    home_lon_deg: float = DEFAULT_LON_DEG
    home_alt_m: float = DEFAULT_ALT_M
    local_origin: Literal["spawn", "world"] = "spawn"
    dynamics: dyn.DynamicsParams = field(default_factory=dyn.DynamicsParams)
    autopilot: AutopilotParams = field(default_factory=AutopilotParams)
    # MAVLink signing imitates PX4 v1.17+ (v1.16 has none): off unless keys are given here, and
    # SETUP_SIGNING is ignored, as by v1.16, unless accept_setup_signing
    signing: tuple[SigningSpec, ...] = ()
    accept_setup_signing: bool = False
    stream_rates_hz: tuple[tuple[str, float], ...] = ()  # (message name, Hz) overrides
    duplicate_mode_ack: bool = True
    batch_datagrams: bool = True
    body_radius_m: float = 0.2
    crash_speed_m_s: float = 3.0
    collision_action: Literal["report", "disarm"] = "report"
    truth_rate_hz: float = 50.0

    def __post_init__(self) -> None:
        if self.count < 1:
            raise ValueError("count must be >= 1")
        if not (self.speedup > 0.0 and math.isfinite(self.speedup)):
            raise ValueError("speedup must be a positive number")
        if not self.tick_hz > 0.0:
            raise ValueError("tick_hz must be > 0")
        if self.spawn_enu_m is not None and len(self.spawn_enu_m) != self.count:
            raise ValueError(f"spawn_enu_m has {len(self.spawn_enu_m)} rows for {self.count}")
        last = self.base_port + self.count - 1 + max(self.local_port_offset or 0, 0)
        if not (0 < self.base_port and last < 65536):
            raise ValueError("ports out of range")
        if self.body_radius_m <= 0.0 or self.crash_speed_m_s <= 0.0:
            raise ValueError("body_radius_m and crash_speed_m_s must be > 0")
        for name, rate in self.stream_rates_hz:
            message_id_by_name(name)
            if rate < 0.0:
                raise ValueError(f"stream rate of {name} must be >= 0")

    def spawn_positions(self) -> np.ndarray:
        """(N, 3) ENU spawn points: explicit, or a row along y (north) centred on the centre."""
        if self.spawn_enu_m is not None:
            return np.array(self.spawn_enu_m, dtype=np.float64).reshape(self.count, 3)
        c = np.asarray(self.spawn_center_enu_m, dtype=np.float64)
        off = (np.arange(self.count) - (self.count - 1) / 2.0) * self.spawn_spacing_m
        p = np.tile(c, (self.count, 1))
        p[:, 1] += off
        return p


@dataclass(frozen=True)
class CollisionEvent:
    """A collision starting at ``t_s``: ``kind`` obstacle | vehicle | ground; system ids."""

    t_s: float
    kind: str
    system_ids: tuple[int, ...]
    distance_m: float
    position_m: tuple[float, float, float]


@dataclass
class FleetStats:
    ticks: int = 0
    late_ticks: int = 0
    skipped_ticks: int = 0
    max_lateness_s: float = 0.0
    loop_cpu_s: float = 0.0
    wall_s: float = 0.0
    sim_s: float = 0.0
    sim_start_s: float = 0.0  # simulated time when these counters started


class Fleet:
    """N mock vehicles. ``world``: an ``onboard.world.World`` (obstacles and ground) or None.

    ``truth_sinks`` receive every vehicle's true pose at ``truth_rate_hz``; ``depth_cameras``
    (system id -> camera, e.g. ``truth.simulated_d435(world)``) get frames rendered at
    ``depth_rate_hz`` from the true poses, in a separate thread, to the same sinks (disarmed
    vehicles at ``depth_idle_rate_hz``).
    Use as a context manager, or ``start()`` / ``stop()``; ``run()`` runs in the caller's thread.
    """

    def __init__(
        self,
        config: FleetConfig,
        world: Any = None,
        truth_sinks: Sequence[TruthSink] = (),
        depth_cameras: dict[int, DepthCamera] | None = None,
        depth_rate_hz: float = 15.0,
        depth_idle_rate_hz: float | None = None,
    ) -> None:
        self.config = cfg = config
        self.world = world
        n = cfg.count
        spawns = cfg.spawn_positions()
        if world is not None and world.ground_z is not None:
            spawns[:, 2] = float(world.ground_z)
        self.ground_z = spawns[:, 2].copy()
        self._obstacles = None
        if world is not None and world.n_primitives > 0:
            from onboard.world import World

            self._obstacles = World(world.cylinders, world.rings, world.boxes, None, world.name)
        self.spawns = spawns
        yaw0 = math.radians(cfg.spawn_yaw_deg)
        self.state = dyn.initial_state(spawns, np.full(n, yaw0))
        self.cmd = dyn.idle_commands(n)
        self.att = np.zeros((n, dyn.NA))
        self._r_prev = np.zeros((n, 9))
        self._prm = cfg.dynamics.as_array()
        self._f_max = cfg.dynamics.f_max_m_s2
        dyn.attitude_fleet(self.state, self._prm, self._r_prev, 0.0, self.att)
        # compile (or load) the physics kernel now, not in the first tick of the real-time loop
        dyn.step_fleet(
            self.state.copy(),
            self.cmd,
            self._prm,
            self.ground_z,
            1e-3,
            np.zeros((n, 1, dyn.NOISE_PER_SUBSTEP)),
        )
        self._rngs = [np.random.default_rng([cfg.seed, i]) for i in range(n)]
        self._noise = np.zeros((0, n, 1, dyn.NOISE_PER_SUBSTEP))
        self._noise_k = _NOISE_BLOCK
        self._tel = np.zeros((n, tm.NT))
        self._geo = np.array([cfg.home_lat_deg, cfg.home_lon_deg, cfg.home_alt_m])
        self.t_s = 0.0
        self.dt_s = cfg.speedup / cfg.tick_hz
        self._nsub = dyn.substeps(self.dt_s, cfg.dynamics)
        geo_ref = (cfg.home_lat_deg, cfg.home_lon_deg, cfg.home_alt_m)
        overrides = {message_id_by_name(k): float(v) for k, v in cfg.stream_rates_hz}
        self.autopilots: list[Autopilot] = []
        self.links: list[VehicleLink] = []
        for i in range(n):
            sid = i + 1
            ap = Autopilot(
                cfg.autopilot,
                spawns[i],
                float(spawns[i, 2]),
                yaw0_rad=yaw0,
                hover_thrust=cfg.dynamics.hover_thrust,
            )
            origin = spawns[i] if cfg.local_origin == "spawn" else np.zeros(3)
            local_port = (
                0 if cfg.local_port_offset is None else (cfg.base_port + cfg.local_port_offset + i)
            )
            link = VehicleLink(
                sid,
                ap,
                cfg.host,
                cfg.base_port + i,
                local_port,
                origin,
                spawns[i],
                geo_ref,
                signing=self._signing_for(sid),
                accept_setup_signing=cfg.accept_setup_signing,
                stream_rates_hz=overrides,
                duplicate_mode_ack=cfg.duplicate_mode_ack,
                batch_datagrams=cfg.batch_datagrams,
            )
            self.autopilots.append(ap)
            self.links.append(link)
        self._origins = np.array([link.origin_enu for link in self.links]).reshape(n, 3)
        # compile (or load) the telemetry kernel now, not in the first tick
        tm.telemetry_fleet(self.state, self.att, self._origins, self.ground_z, self._geo, self._tel)
        self.loop_error: BaseException | None = None  # what stopped the background loop
        self._pairs = np.zeros((n * (n - 1) // 2, 2), dtype=np.int64)  # pairs in contact
        dyn.close_pairs(self.state[:, dyn.S_P : dyn.S_P + 3], 0.0, self._pairs)  # compile now
        self.collision_counts = np.zeros(n, dtype=np.int64)
        self.collisions: list[CollisionEvent] = []
        self._in_contact_obstacle = np.zeros(n, dtype=bool)
        self._in_contact_pair: set[tuple[int, int]] = set()
        self.min_obstacle_distance_m = math.inf
        self.min_vehicle_distance_m = math.inf
        self.truth_sinks = list(truth_sinks)
        self._truth_interval = 1.0 / cfg.truth_rate_hz if cfg.truth_rate_hz > 0 else math.inf
        self._next_truth = 0.0
        self._latest_truth: dict[int, TruthSample] = {}
        self._truth_snapshot: tuple[Any, ...] | None = None
        self.truth_sink_errors = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._reset_stats = False  # a plain flag: set from a signal handler, no lock
        self._thread: threading.Thread | None = None
        self._selector: selectors.BaseSelector | None = None
        self.stats = FleetStats()
        self._depth: DepthStreamer | None = None
        if depth_cameras:
            self._depth = DepthStreamer(
                depth_cameras,
                self.latest_truth,
                self.truth_sinks,
                depth_rate_hz,
                cfg.speedup,
                idle_rate_hz=depth_idle_rate_hz,
            )
        self._opened = False

    def _signing_for(self, system_id: int) -> SigningConfig | None:
        spec = None
        for s in self.config.signing:
            if s.system_id is None and spec is None:
                spec = s
            if s.system_id == system_id:
                spec = s
        return None if spec is None else SigningConfig(spec.key, spec.require)

    # ---- lifecycle -----------------------------------------------------------------------
    def open(self) -> None:
        """Bind every vehicle's socket (idempotent)."""
        if self._opened:
            return
        sel = selectors.DefaultSelector()
        try:
            for link in self.links:
                link.open()
                assert link.sock is not None
                sel.register(link.sock, selectors.EVENT_READ, link)
        except OSError:
            for link in self.links:
                link.close()
            sel.close()
            raise
        self._selector = sel
        self._opened = True
        for link in self.links:
            log.info(
                "vehicle %d: listening on %s:%d, sending to %s:%d",
                link.system_id,
                link.host,
                link.local_port,
                link.partner[0],
                link.partner[1],
            )

    def close(self) -> None:
        if self._selector is not None:
            self._selector.close()
            self._selector = None
        for link in self.links:
            link.close()
        for s in self.truth_sinks:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - closing must go on
                log.debug("closing a truth sink failed", exc_info=True)
        self._opened = False

    def start(self) -> Fleet:
        """Open the sockets and run the loop in a background thread."""
        self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run_guarded, name="sitl-fleet", daemon=True)
        self._thread.start()
        if self._depth is not None:
            self._depth.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the loop, join the threads, close the sockets."""
        self._stop.set()
        if self._depth is not None:
            self._depth.stop(timeout_s)
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.close()

    def request_stats_reset(self) -> None:
        """Restart the loop counters (ticks, lateness, CPU, wall and simulated time) at the
        next iteration: a benchmark's measurement window. Safe in a signal handler: it sets a
        flag and takes no lock (``Event.set`` does, and the loop's ``clear`` could hold it)."""
        self._reset_stats = True

    def request_stop(self) -> None:
        """Ask the loop to end (from another thread; a signal handler should not call it:
        ``Event.set`` takes a lock, see ``onboard/stopsignal.py``)."""
        self._stop.set()

    def __enter__(self) -> Fleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run_guarded(self) -> None:
        try:
            self.run()
        except Exception as e:  # logged and kept: the fleet is dead, tests check loop_error
            self.loop_error = e
            log.exception("SITL fleet loop failed")

    def run(self, duration_s: float | None = None) -> FleetStats:
        """Run the loop in this thread until ``request_stop`` or ``duration_s`` (wall)."""
        self.open()
        cfg = self.config
        period = 1.0 / cfg.tick_hz
        st = self.stats
        cpu0 = time.thread_time()
        wall0 = time.monotonic()
        next_tick = wall0 + period
        end = math.inf if duration_s is None else wall0 + duration_s
        sel = self._selector
        assert sel is not None
        while not self._stop.is_set():
            if self._reset_stats:
                self._reset_stats = False
                self.stats = st = FleetStats(sim_s=self.t_s, sim_start_s=self.t_s)
                cpu0 = time.thread_time()
                wall0 = time.monotonic()
            now = time.monotonic()
            if now >= end:
                break
            wait = next_tick - now
            if wait > 0:
                for key, _ in sel.select(min(wait, 0.05)):
                    key.data.receive()
                continue
            lateness = now - next_tick
            if lateness > 0.25:  # far behind: give up real time for these ticks
                missed = int(lateness / period)
                st.skipped_ticks += missed
                next_tick += missed * period
            elif lateness > period:
                st.late_ticks += 1
            st.max_lateness_s = max(st.max_lateness_s, lateness)
            for key, _ in sel.select(0):  # what arrived since the last wait
                key.data.receive()
            self.tick()
            next_tick += period
        st.loop_cpu_s += time.thread_time() - cpu0
        st.wall_s += time.monotonic() - wall0
        return st

    # ---- the tick ------------------------------------------------------------------------
    def tick(self) -> None:
        """Advance simulated time by one tick (logic, physics, collisions, telemetry, truth)."""
        t = self.t_s
        s = self.state
        est_p = s[:, dyn.S_P : dyn.S_P + 3] + s[:, dyn.S_E : dyn.S_E + 3]
        vel = s[:, dyn.S_V : dyn.S_V + 3].copy()
        yaw = s[:, dyn.S_YAW].tolist()
        ground = (s[:, dyn.S_GROUND] > 0.5).tolist()
        thrust = self.att[:, dyn.A_THRUST].tolist()
        for i, ap in enumerate(self.autopilots):
            est = Estimate(est_p[i], vel[i], yaw[i], ground[i], thrust[i])
            ap.update(t, est, self.cmd[i])
        dyn.step_fleet(s, self.cmd, self._prm, self.ground_z, self.dt_s, self._next_noise())
        dyn.attitude_fleet(s, self._prm, self._r_prev, self.dt_s, self.att)
        self.t_s = t = t + self.dt_s
        self._check_collisions(t)
        tm.telemetry_fleet(s, self.att, self._origins, self.ground_z, self._geo, self._tel)
        rows = self._tel.tolist()
        for i, link in enumerate(self.links):
            link.tick(
                VehicleView(
                    t,
                    s[i],
                    self.att[i],
                    self.cmd[i],
                    link.origin_enu,
                    link.home_enu,
                    link.geo_ref,
                    float(self.ground_z[i]),
                    self._f_max,
                    rows[i],
                )
            )
        if t + 1e-9 >= self._next_truth:
            self._publish_truth(t)
            self._next_truth = max(self._next_truth + self._truth_interval, t)
        st = self.stats
        st.ticks += 1
        st.sim_s = t

    def _next_noise(self) -> np.ndarray:
        """This tick's standard normals (N, substeps, NOISE_PER_SUBSTEP): each vehicle's own
        seeded generator, drawn ``_NOISE_BLOCK`` ticks at a time (the same numbers as drawing
        tick by tick)."""
        if self._noise_k >= _NOISE_BLOCK:
            shape = (_NOISE_BLOCK, self._nsub, dyn.NOISE_PER_SUBSTEP)
            draws = [r.standard_normal(shape) for r in self._rngs]
            self._noise = np.ascontiguousarray(np.stack(draws, axis=1))
            self._noise_k = 0
        k = self._noise_k
        self._noise_k += 1
        return self._noise[k]

    def _check_collisions(self, t: float) -> None:
        cfg = self.config
        s = self.state
        pos = s[:, dyn.S_P : dyn.S_P + 3]
        r = cfg.body_radius_m
        # ground impacts
        impact = s[:, dyn.S_IMPACT]
        if impact.max() > cfg.crash_speed_m_s:
            for i in np.flatnonzero(impact > cfg.crash_speed_m_s):
                self._collision(t, "ground", (int(i),), float(impact[i]), pos[i])
        impact[:] = 0.0
        # obstacles
        if self._obstacles is not None:
            d, _ = self._obstacles.distance(pos)
            self.min_obstacle_distance_m = min(self.min_obstacle_distance_m, float(np.min(d)) - r)
            touching = d < r
            for i in np.flatnonzero(touching & ~self._in_contact_obstacle):
                self._collision(t, "obstacle", (int(i),), float(d[i]) - r, pos[i])
            self._in_contact_obstacle = touching
        # vehicle pairs
        n = pos.shape[0]
        if n > 1:
            count, d_min = dyn.close_pairs(pos, 2.0 * r, self._pairs)
            self.min_vehicle_distance_m = min(self.min_vehicle_distance_m, d_min)
            if count or self._in_contact_pair:
                now_pairs = {(int(a), int(b)) for a, b in self._pairs[:count]}
                for a, b in sorted(now_pairs - self._in_contact_pair):
                    mid = 0.5 * (pos[a] + pos[b])
                    dist = float(np.linalg.norm(pos[a] - pos[b]))
                    self._collision(t, "vehicle", (a, b), dist, mid)
                self._in_contact_pair = now_pairs

    def _collision(
        self, t: float, kind: str, idx: tuple[int, ...], distance: float, where: np.ndarray
    ) -> None:
        ids = tuple(i + 1 for i in idx)
        ev = CollisionEvent(
            t, kind, ids, distance, (float(where[0]), float(where[1]), float(where[2]))
        )
        with self._lock:
            self.collisions.append(ev)
        log.warning(
            "collision t=%.2f s: %s, vehicles %s, at (%.2f, %.2f, %.2f) ENU, %.3f m",
            t,
            kind,
            list(ids),
            where[0],
            where[1],
            where[2],
            distance,
        )
        for i in idx:
            self.collision_counts[i] += 1
            text = f"Collision: {kind}" + (
                f" with vehicle {ids[1 - idx.index(i)]}" if kind == "vehicle" else ""
            )
            self.links[i].statustext(int(Severity.CRITICAL), text)
            if self.config.collision_action == "disarm" and self.autopilots[i].armed:
                self.autopilots[i].command_arm(t, False, force=True)

    def _publish_truth(self, t: float) -> None:
        """Snapshot the true state; build the samples now only if a sink wants them (else on
        demand, in ``latest_truth``)."""
        snap = (
            t,
            self.state.copy(),
            self.att.copy(),
            [(ap.armed, ap.landed, ap.mode.name) for ap in self.autopilots],
            self.collision_counts.copy(),
        )
        with self._lock:
            self._truth_snapshot = snap
            self._latest_truth = {}
        if not self.truth_sinks:
            return
        samples = self._truth_samples(snap)
        with self._lock:
            if self._truth_snapshot is snap:
                self._latest_truth = {x.system_id: x for x in samples}
        for sink in self.truth_sinks:
            try:
                sink.publish_poses(samples)
            except Exception:  # noqa: BLE001 - a broken sink must not stop the vehicles
                self.truth_sink_errors += 1  # counted and logged with its traceback
                log.exception("truth sink %r failed", sink)

    @staticmethod
    def _truth_samples(snap: tuple[Any, ...]) -> list[TruthSample]:
        t, s, att, status, collisions = snap
        samples = []
        for i, (armed, landed, mode) in enumerate(status):
            row = s[i]
            q = quaternion_from_matrix(att[i, dyn.A_R : dyn.A_R + 9].reshape(3, 3))
            samples.append(
                TruthSample(
                    system_id=i + 1,
                    t_s=t,
                    position_m=(float(row[0]), float(row[1]), float(row[2])),
                    velocity_m_s=(float(row[3]), float(row[4]), float(row[5])),
                    quaternion=q,
                    yaw_rad=float(row[dyn.S_YAW]),
                    armed=armed,
                    landed=landed,
                    mode=mode,
                    collisions=int(collisions[i]),
                )
            )
        return samples

    # ---- queries (any thread) ------------------------------------------------------------
    def latest_truth(self) -> dict[int, TruthSample]:
        """The last published true state of every vehicle, by system id."""
        with self._lock:
            snap = self._truth_snapshot
            latest = self._latest_truth
        if not latest and snap is not None:
            latest = {x.system_id: x for x in self._truth_samples(snap)}
            with self._lock:
                if self._truth_snapshot is snap:
                    self._latest_truth = latest
        return dict(latest)

    def collision_events(self) -> list[CollisionEvent]:
        with self._lock:
            return list(self.collisions)

    def addresses(self) -> list[tuple[str, int]]:
        """Where each vehicle listens (after ``open``/``start``)."""
        return [link.address for link in self.links]

    def summary(self) -> dict[str, Any]:
        """Counters for logs and benchmarks."""
        st = self.stats
        out: dict[str, Any] = {
            "vehicles": self.config.count,
            "sim_s": st.sim_s,
            "sim_start_s": st.sim_start_s,
            "wall_s": st.wall_s,
            "ticks": st.ticks,
            "late_ticks": st.late_ticks,
            "skipped_ticks": st.skipped_ticks,
            "max_lateness_ms": st.max_lateness_s * 1e3,
            "loop_cpu_s": st.loop_cpu_s,
            "loop_error": None if self.loop_error is None else repr(self.loop_error),
            "truth_sink_errors": self.truth_sink_errors,
            "collisions": [
                {
                    "t_s": c.t_s,
                    "kind": c.kind,
                    "system_ids": list(c.system_ids),
                    "distance_m": c.distance_m,
                    "position_enu_m": list(c.position_m),
                }
                for c in self.collision_events()
            ],
            "min_obstacle_distance_m": _finite_or_none(self.min_obstacle_distance_m),
            "min_vehicle_distance_m": _finite_or_none(self.min_vehicle_distance_m),
            "links": [dict(vars(link.stats), system_id=link.system_id) for link in self.links],
        }
        if self._depth is not None:
            rs = self._depth.render_s
            out["depth"] = {
                "frames": self._depth.frames,
                "skipped": self._depth.skipped,
                "render_ms_median": float(np.median(rs) * 1e3) if rs else None,
            }
        return out


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
