"""The flight service's configuration (``config/onboard.yaml``): frozen, typed, checked at load.

Loaded once at the edge with ``onboard.config.from_mapping``: an unknown key or a bad value is a
``ConfigError`` that names the key path and what was expected, e.g.
``autopilot: setpoint_rate_hz: expected a number in [10, 200], got 5.0``. Nothing reads the file
after start-up; every thread gets the frozen objects.

Drone ids are 0-based (the formation slot order of the ground station); the autopilot of drone
``i`` is MAVLink system ``i + 1`` on UDP port ``14540 + i`` (PX4's multi-vehicle convention).
Coordinates are ENU metres in the swarm's frame, shared by every drone and the ground station;
only the autopilot link converts to PX4's local NED frame, whose origin in the swarm frame is
``autopilot.local_origin_enu_m`` (per drone: ``autopilot.local_origins_enu_m``).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from onboard.agent import (
    GHOST_FORGET_S,
    GHOST_WINDOW_S,
    PEER_DEVIATION_AHEAD_S,
    PEER_DEVIATION_M,
    PEER_SILENCE_IN_WAY_S,
    PEER_SILENCE_MAX_S,
    PEER_SILENCE_S,
    PLAN_AHEAD_S,
    REPLAN_PERIOD_S,
    RESEND_S,
)
from onboard.config import (
    ConfigError,
    config_dir,
    from_mapping,
    load_planner_params,
    merge_mappings,
    read_yaml,
)
from onboard.mapping.occupancy import OccupancyParams
from onboard.planner.params import PlannerParams
from onboard.service.state import RETRY_AFTER_S

Vec3 = tuple[float, float, float]

_SWARM_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


def _in_range(name: str, value: float, lo: float, hi: float) -> None:
    if not (lo <= value <= hi):
        raise ValueError(f"{name}: expected a number in [{lo:g}, {hi:g}], got {value!r}")


def _positive(name: str, value: float) -> None:
    if not (value > 0.0 and math.isfinite(value)):
        raise ValueError(f"{name}: expected a number > 0, got {value!r}")


def _within_10_km(name: str, point: Vec3) -> None:
    if max(abs(v) for v in point) > 10_000.0:
        raise ValueError(f"{name}: must be within 10 km of the swarm origin, got {list(point)}")


@dataclass(frozen=True)
class DroneSection:
    """Who this process flies for. ``id`` is usually given on the command line (``--id``)."""

    id: int = 0
    swarm: str = "swarm"
    """The swarm name: the first part of every key expression on the bus."""

    def __post_init__(self) -> None:
        _in_range("id", self.id, 0, 253)
        if not _SWARM_NAME.match(self.swarm):
            raise ValueError(f"swarm: expected letters, digits, '_' or '-', got {self.swarm!r}")


@dataclass(frozen=True)
class AutopilotSection:
    """The MAVLink link to PX4.

    url: ``udp://HOST:PORT`` (the service binds HOST:PORT and answers whoever talks to it, like
    MAVSDK's ``udpin://``) or ``serial:///dev/ttyTHS0`` (with ``baud``). With
    ``port_plus_id`` the port is ``PORT + drone id`` (PX4 multi-vehicle: 14540 + i).
    system_id: the autopilot's MAVLink system id; None means drone id + 1.
    """

    implementation: Literal["pymavlink", "mavsdk"] = "pymavlink"
    url: str = "udp://127.0.0.1:14540"
    port_plus_id: bool = True
    baud: int = 921600
    system_id: int | None = None
    setpoint_rate_hz: float = 50.0
    heartbeat_timeout_s: float = 1.0
    """No autopilot HEARTBEAT for this long: the link is lost and the service stops commanding."""
    command_timeout_s: float = 1.5
    command_retries: int = 3
    signing_key_file: str | None = None
    """MAVLink 2 signing key file (32 raw bytes or 64 hex digits, mode 0600; ``{id}`` is replaced
    by the drone id). Needs an autopilot that signs (PX4 v1.17+); PX4 v1.16 has no signing, and
    the service then refuses to start while signing is required. pymavlink implementation only."""
    signing_required: bool | None = None
    """None: required when a key is given; false: unsigned telemetry accepted (and counted)."""
    trim_telemetry: bool = True
    """Turn off, at connect, the streams of PX4's onboard link the service never reads
    (``onboard.autopilot.config.DEFAULT_TELEMETRY_OFF``: ~265 of ~380 messages/s). False when
    another program reads them on the same MAVLink instance."""
    local_origin_enu_m: Vec3 = (0.0, 0.0, 0.0)
    """Where this PX4's local frame origin (its EKF origin: usually where it was powered up)
    lies in the swarm's ENU frame, the frame of the map, the plans, the geofence and the bus.
    Each PX4 of a swarm starts its own local frame, so drones differ here: give each one's in
    ``local_origins_enu_m``."""
    local_origins_enu_m: dict[str, Vec3] = field(default_factory=dict)
    """Per drone id (``"0"``, ``"1"``, ...): the local origin of that drone's autopilot, which
    overrides ``local_origin_enu_m``. One config file then serves the whole swarm."""

    def __post_init__(self) -> None:
        _within_10_km("local_origin_enu_m", self.local_origin_enu_m)
        for key, origin in self.local_origins_enu_m.items():
            if not (key.isdigit() and 0 <= int(key) <= 253):
                raise ValueError(
                    f"local_origins_enu_m: keys are drone ids in [0, 253], got {key!r}"
                )
            _within_10_km(f"local_origins_enu_m.{key}", origin)
        if self.signing_key_file is not None and self.implementation == "mavsdk":
            raise ValueError(
                "signing_key_file: the mavsdk implementation cannot sign (MAVSDK 4.x has no "
                "MAVLink signing API); use implementation: pymavlink"
            )
        if not re.match(r"^(udp://[^:/]*:\d{1,5}|serial://.+)$", self.url):
            raise ValueError(
                f"url: expected 'udp://HOST:PORT' or 'serial:///dev/DEVICE', got {self.url!r}"
            )
        _in_range("baud", self.baud, 9600, 4_000_000)
        if self.system_id is not None:
            _in_range("system_id", self.system_id, 1, 254)
        _in_range("setpoint_rate_hz", self.setpoint_rate_hz, 10.0, 200.0)
        _in_range("heartbeat_timeout_s", self.heartbeat_timeout_s, 0.2, 10.0)
        _in_range("command_timeout_s", self.command_timeout_s, 0.1, 30.0)
        _in_range("command_retries", self.command_retries, 0, 20)

    @property
    def is_serial(self) -> bool:
        return self.url.startswith("serial://")

    def endpoint(self, drone_id: int) -> str:
        """The url with the drone's port (``udp://127.0.0.1:14542`` for drone 2)."""
        if self.is_serial or not self.port_plus_id:
            return self.url
        host, port = self.url[len("udp://") :].rsplit(":", 1)
        p = int(port) + drone_id
        if not 0 < p < 65536:
            raise ConfigError(f"autopilot.url: port {p} for drone {drone_id} is out of range")
        return f"udp://{host}:{p}"

    def target_system(self, drone_id: int) -> int:
        return self.system_id if self.system_id is not None else drone_id + 1

    def local_origin(self, drone_id: int) -> Vec3:
        """The swarm-frame ENU position of drone ``drone_id``'s autopilot local origin."""
        return self.local_origins_enu_m.get(str(drone_id), self.local_origin_enu_m)


@dataclass(frozen=True)
class ZenohTlsSection:
    """Zenoh over TLS with mutual authentication (``onboard.comm.security.TlsConfig``): PEM
    files, ``{id}`` replaced by the drone id (``swarm-gcs certs`` names them ``drone-<id>``)."""

    root_ca_certificate: str
    certificate: str
    private_key: str
    enable_mtls: bool = True
    verify_name_on_connect: bool = True


@dataclass(frozen=True)
class ZenohSection:
    """How the swarm bus joins Zenoh (``onboard.comm.zenoh_session.ZenohEndpoints``).

    tls: null for plain TCP. access_control_drones: with TLS, the number of drones of the swarm
    (ids 0..N-1): every session then enforces that only the ground station publishes commands
    and each drone only under its own id (``onboard.comm.security.SwarmAccessControl``).
    """

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    tls: ZenohTlsSection | None = None
    access_control_drones: int | None = None

    def __post_init__(self) -> None:
        for name in ("listen", "connect"):
            for ep in getattr(self, name):
                if "/" not in ep:
                    raise ValueError(f"{name}: endpoint {ep!r} is not like 'tcp/HOST:PORT'")
        if self.access_control_drones is not None:
            if self.tls is None:
                raise ValueError(
                    "access_control_drones: needs tls (identities come from certificates)"
                )
            _in_range("access_control_drones", self.access_control_drones, 1, 999)

    def endpoints(self, drone_id: int | None = None, swarm: str | None = None) -> Any:
        """The endpoints of drone ``drone_id`` (TLS files and access control need the id and the
        swarm name; without TLS they are not used)."""
        from onboard.comm.zenoh_session import ZenohEndpoints, as_tls_endpoint

        if self.tls is None:
            return ZenohEndpoints(
                listen=self.listen,
                connect=self.connect,
                mode=self.mode,
                multicast_scouting=self.multicast_scouting,
            )
        if drone_id is None or swarm is None:
            raise ValueError("zenoh.tls: the drone id and swarm name are needed")
        from onboard.comm.security import SwarmAccessControl, TlsConfig

        t = self.tls
        tls = TlsConfig(
            root_ca_certificate=t.root_ca_certificate.replace("{id}", str(drone_id)),
            certificate=t.certificate.replace("{id}", str(drone_id)),
            private_key=t.private_key.replace("{id}", str(drone_id)),
            enable_mtls=t.enable_mtls,
            verify_name_on_connect=t.verify_name_on_connect,
        )
        acl = (
            SwarmAccessControl.for_count(swarm, self.access_control_drones)
            if self.access_control_drones is not None
            else None
        )
        # tcp/ endpoints become tls/; tls/ endpoints stay as given
        return ZenohEndpoints(
            listen=tuple(as_tls_endpoint(e) for e in self.listen),
            connect=tuple(as_tls_endpoint(e) for e in self.connect),
            mode=self.mode,
            multicast_scouting=self.multicast_scouting,
            tls=tls,
            access_control=acl,
        )


@dataclass(frozen=True)
class DepthSection:
    """Where depth frames come from.

    'zenoh-sim': frames the SITL mock renders and publishes under ``sim_prefix`` (its Zenoh
    session: ``sim_connect``); 'realsense': a D435 through Open3D (or ``realsense_bag`` replayed);
    'none': no camera (the planner sees only the ground; depth loss never fires).
    """

    source: Literal["zenoh-sim", "realsense", "none"] = "zenoh-sim"
    rate_hz: float = 30.0
    sim_prefix: str = "swarm/sim"
    sim_connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    realsense_bag: str | None = None
    step: int = 3
    """Ray cast every step-th pixel row and column of the camera's image (of a decimated
    frame, ``DepthFrame.decimation``, every (step / decimation)-th: ``swarm-sitl
    --depth-step`` 3 sends that grid, and a step that is not a multiple of it is refused).
    3 rather than 2: ingest CPU per frame -37 % (6.7 -> 4.2 ms at 30 frames/s), ESDF error
    p95 / p99 0.080 / 0.143 -> 0.073 / 0.130 m, 1.5 % fewer known and 10 % fewer occupied
    cells (``bench mapping``, forest-medium seed 1)."""

    def __post_init__(self) -> None:
        _in_range("rate_hz", self.rate_hz, 1.0, 90.0)
        _in_range("step", self.step, 1, 16)


@dataclass(frozen=True)
class MappingSection:
    """The rolling occupancy window and its ESDF."""

    esdf_rate_hz: float = 10.0
    """The planner's field is rebuilt at least this often while frames arrive."""
    occupancy: OccupancyParams = field(default_factory=OccupancyParams)
    window_band_margin_m: float | None = 0.45
    """The window's vertical extent follows the planner's altitude band (``planner.z_limits_m``
    after the geofence cut): from this far below the band to this far above it (whole cells),
    held there while the drone flies in the band, and the ESDF computed only for the layers
    the band interpolates from (``OccupancyParams.for_band``; the map the service uses is
    ``OnboardConfig.map_params``). The default band 0.3-3.1 m gives a window from -0.2 to
    3.6 m (38 layers of 0.1 m, two of them under the ground, which hold nothing; the 4 m
    window from 0.5 m below the ground, ``occupancy.floor_z_m``, has 40) and a
    field from 0.2 to 3.2 m (30 of the old 40 layers; outside it the planner reads unknown
    space, as beyond the window), whose cells are bit for bit the whole window's: with a
    0.4 m margin (window -0.1 to 3.5 m), 18 % less CPU per ESDF refresh (``bench mapping
    --compare-windows``, forest-medium: 26.7-26.9 -> 22.0-22.2 ms, pair ratio 0.82; the
    dropped layers alone gave 0.94); and a window that no longer rises off the ground when
    the drone climbs above 2.5 m. At least
    ``planner.check_obstacle_m + occupancy.inflation_m + occupancy.resolution_m / 2`` (0.45 m):
    no obstacle outside the window can then fail the safety check from inside the band.
    ``occupancy.size_m``'s z is then the most the window may take; ``occupancy.floor_z_m``,
    ``headroom_m`` and ``esdf_z_m`` must be left at their defaults. null: the window as
    ``occupancy`` places it."""
    thread_nice: int = 0
    """Niceness added to the mapping thread (Linux, per thread): when the CPU is short, the
    setpoint stream and the planner go first and frames are dropped instead (0: as the rest)."""

    def __post_init__(self) -> None:
        _in_range("esdf_rate_hz", self.esdf_rate_hz, 10.0, 100.0)
        _in_range("thread_nice", self.thread_nice, 0, 19)
        if self.window_band_margin_m is not None:
            _in_range("window_band_margin_m", self.window_band_margin_m, 0.05, 5.0)
            default = OccupancyParams()
            for key in ("floor_z_m", "headroom_m", "esdf_z_m"):
                if getattr(self.occupancy, key) != getattr(default, key):
                    raise ValueError(
                        f"occupancy.{key}: the window's vertical placement follows the "
                        "planner's altitude band while window_band_margin_m is set (null: "
                        "placed by occupancy.floor_z_m and headroom_m)"
                    )


@dataclass(frozen=True)
class PlanningSection:
    """The replan cycle and the safety monitor."""

    replan_period_s: float = REPLAN_PERIOD_S
    plan_ahead_s: float = PLAN_AHEAD_S
    """A replan starts from the current trajectory's state this far ahead (its computing time)."""
    plan_budget_s: float = 0.3
    """A replan that has taken this long starts no further attempt (A* retries, rescue) while
    the trajectory in control is safe and moves on: that one flies on (status 'over-budget')
    and a replan follows at once, from a newer start, starting with the attempts given up (not
    those just refused again: on a starved CPU they would spend the budget once more, and the
    drone flew its old plan replan after replan while its peers re-formed). On a starved CPU a
    refused first attempt and its retries took seconds, and such a plan comes back too late to
    be flown."""
    monitor_rate_hz: float = 100.0
    monitor_horizon_s: float = 2.0
    """The monitor checks the trajectory in flight this far ahead."""
    stream_guard_s: float = 1.0
    """The setpoint thread stops the drone along the trajectory in control (``stop_along``,
    the service's brake) when the safety monitor has not looked for this long (its thread
    starved or hung; 0: never). A plan is checked to its end only on the map of its time, and
    only its first second (``planner.check_known_s``) must lie in observed space: the replans
    and the monitor, which looks ``monitor_horizon_s`` ahead 100 times a second, are what keep
    the rest safe; the stream (a real-time thread) may go on flying while they stand still. A
    stop begun a second after the last look ends within the 2 s that look checked. (On an
    overloaded host, 2026-12-04, whole services stood still 5-6 s and three drones touched
    trunks: ``stream_gap_s`` is the guard for that case.)"""
    stream_gap_s: float = 0.5
    """A setpoint this long after the one before (the whole process stalled, the stream's
    real-time thread too; 0: never) does not jump ahead along the plan to where it is now, far
    from the vehicle, which PX4 would fly to in a straight line: a braking stop from the last
    setpoint sent takes control instead, and the next plan starts from it. The same seed-4
    flight: the stream paused 5.9 s, its next setpoint lay 1.8 m ahead of the vehicle, and the
    vehicle's straight way there touched a trunk. The stream's periods on the 7-drone demo stay
    under 0.25 s (``gcs.report.STREAM_GAP_S`` counts pauses above 0.5 s)."""
    monitor_obstacle_slack_m: float = 0.05
    """The monitor brakes for an obstacle only where the plan in flight comes closer than
    ``planner.check_obstacle_m`` less this; a plan that comes within the check's distance but
    not that close asks for a replan (when the last one is older than 0.3 s) and flies on.
    The planner accepts plans at the check's distance on the map of its time; the monitor judges
    them 100 times a second on the newest map, in which a trunk seen again sits a few
    millimetres nearer: with no slack a drone stopped dead (a braking stop, then a second's
    hover) for a plan 0.2995 m from a trunk on the inflated map, two to four times a flight of
    the demo (BENCHMARKS.md section 10, 2026-12-02). 0: brake at the check's distance."""
    resend_s: tuple[float, ...] = RESEND_S
    """A braking stop or hover announced (every plan too with ``resend_plans``) goes out again
    this long after it unless a newer trajectory went out first (``onboard.agent.RESEND_S``):
    one lost copy leaves the peers planning along a trajectory the drone no longer flies
    ([]: once)."""
    resend_plans: bool = False
    """true: the replans' plans go out again too, not only braking stops and hovers (three
    times the trajectory messages, and their cost to every peer: about a tenth more CPU for
    the 7-drone demo on 2 cores; no fewer contacts in fast time, BENCHMARKS 9b)."""
    retry_after_s: float = RETRY_AFTER_S
    """After an 'emergency' plan the drone hovers, then retries this late (after a
    'kept-previous' one the kept trajectory flies on and the next replan comes on its grid)."""
    max_failed_s: float = 15.0
    """Planning failing ('kept-previous' or 'emergency') for this long in a row: EMERGENCY
    (braking stop, hover, land)."""
    goal_tolerance_m: float = 0.3
    arrival_speed_m_s: float = 0.15
    warm_up: bool = True
    """Plan one small problem before READY, so the first real replan is at full speed."""
    side_thread: bool = True
    """Solve the fresh start of ``planner.fresh_alternative`` beside the warm start: the warm
    start's solve and check on a second thread, the fresh start's solve in the planning thread
    (the compiled solver releases the GIL). The same plans, sooner where a core is free
    (``bench planner`` median 1.6 ms against 2.1 ms one after the other; BENCHMARKS.md
    section 1). false: one after the other, in the planning thread."""

    def __post_init__(self) -> None:
        _in_range("replan_period_s", self.replan_period_s, 0.1, 10.0)
        _in_range("plan_ahead_s", self.plan_ahead_s, 0.0, 1.0)
        _in_range("plan_budget_s", self.plan_budget_s, 0.01, 60.0)
        _in_range("monitor_rate_hz", self.monitor_rate_hz, 10.0, 500.0)
        _in_range("monitor_horizon_s", self.monitor_horizon_s, 0.1, 10.0)
        _in_range("monitor_obstacle_slack_m", self.monitor_obstacle_slack_m, 0.0, 1.0)
        _in_range("stream_guard_s", self.stream_guard_s, 0.0, 10.0)
        _in_range("stream_gap_s", self.stream_gap_s, 0.0, 10.0)
        for i, after in enumerate(self.resend_s):
            _in_range(f"resend_s[{i}]", after, 0.01, 2.0)
        _in_range("retry_after_s", self.retry_after_s, 0.05, 30.0)
        _in_range("max_failed_s", self.max_failed_s, 1.0, 300.0)
        _in_range("goal_tolerance_m", self.goal_tolerance_m, 0.05, 5.0)
        _in_range("arrival_speed_m_s", self.arrival_speed_m_s, 0.01, 2.0)


@dataclass(frozen=True)
class GeofenceSection:
    """A box in the swarm's ENU frame: goals outside are refused; plans never leave it."""

    min_enu_m: Vec3 = (-50.0, -50.0, 0.0)
    max_enu_m: Vec3 = (50.0, 50.0, 5.0)

    def __post_init__(self) -> None:
        for name in ("min_enu_m", "max_enu_m"):
            _within_10_km(name, getattr(self, name))
        for k in range(3):
            if not self.min_enu_m[k] < self.max_enu_m[k]:
                raise ValueError(
                    f"min_enu_m/max_enu_m: min must be below max on every axis, got "
                    f"{list(self.min_enu_m)} / {list(self.max_enu_m)}"
                )

    def contains(self, p: Any, margin_m: float = 0.0) -> bool:
        return all(
            self.min_enu_m[k] + margin_m <= float(p[k]) <= self.max_enu_m[k] - margin_m
            for k in range(3)
        )


@dataclass(frozen=True)
class FlightSection:
    """Take-off, landing and emergencies."""

    takeoff_altitude_m: float = 1.0
    """Height above the take-off point the drone climbs to (ENU z up)."""
    takeoff_speed_m_s: float = 0.5
    emergency_hover_s: float = 5.0
    """EMERGENCY: braking stop, hover this long, then land."""

    def __post_init__(self) -> None:
        _in_range("takeoff_altitude_m", self.takeoff_altitude_m, 0.3, 20.0)
        _in_range("takeoff_speed_m_s", self.takeoff_speed_m_s, 0.1, 3.0)
        _in_range("emergency_hover_s", self.emergency_hover_s, 0.0, 120.0)


@dataclass(frozen=True)
class DepthLostReaction:
    """No depth frame for ``timeout_s``: stop and hover until frames return, and keep coming
    for ``recover_s`` (no gap above ``timeout_s`` meanwhile): a camera stuttering around the
    timeout holds the drone in hover instead of flipping its state at every frame.

    A source that tells when frames arrive (``newest_stamp_s``: the SITL mock's) separates a
    silent camera from a map that lags behind a live one (the mapping thread starved of CPU,
    frames waiting: unread, or read and not yet ingested): the camera is judged by its frames'
    arrival (``timeout_s``), the map by its last ingested frame against ``map_lag_s``, the same
    hold once either is over. A lagging map is a stale one, not a blind drone: the planner never
    accepts a plan that enters unobserved space in its first ``check_known_s``, so a drone whose
    map does not grow stops at the edge of what it has mapped. Recovery asks frames for
    ``recover_s`` and the map within ``timeout_s`` of them again. For a source that cannot tell,
    arrival is ingestion (``timeout_s`` alone)."""

    timeout_s: float = 0.5
    action: Literal["hover"] = "hover"
    recover_s: float = 0.5
    map_lag_s: float = 3.0

    def __post_init__(self) -> None:
        _in_range("timeout_s", self.timeout_s, 0.05, 10.0)
        _in_range("recover_s", self.recover_s, 0.0, 10.0)
        _in_range("map_lag_s", self.map_lag_s, 0.05, 30.0)
        if self.map_lag_s < self.timeout_s:
            raise ValueError(
                f"map_lag_s: expected at least timeout_s ({self.timeout_s:g} s), got "
                f"{self.map_lag_s!r}"
            )


@dataclass(frozen=True)
class PeerLostReaction:
    """Silent, stuck and lagging peers: the reaction of ``onboard.agent.DroneAgent``, the one
    the fast-time simulator flies (its defaults are the agent's ``PEER_SILENCE_S``,
    ``PEER_DEVIATION_M``, ``GHOST_WINDOW_S``, ``GHOST_FORGET_S``).

    A peer's last sign of life is its newest message of any kind (10 Hz states, trajectories).
    Heard of nothing newer for ``peer_silence_s`` it is *quiet*: still in the formation, but
    avoided as hovering ghosts where it may have stopped (along its last trajectory from where
    it was last heard to ``ghost_window_s`` later, and at its last reported position, for
    ``ghost_forget_s``), with a replan at once when those lie in our way. It is *silent*, out of
    the formation and avoided along its last trajectory (``avoid_for_s`` more), once quiet
    longer than its link's recent quiet spells allow (twice the longest of the last 30 s plus
    0.3 s), at most ``peer_silence_max_s``: so that a lossy, delayed bus does not take healthy
    peers for silent. A peer reported further than
    ``peer_deviation_m`` from its trajectory is also avoided where it reported itself. A peer
    whose newest trajectory is older than ``validity_s`` (a stuck drone) or past its message's
    own validity leaves the formation and is still avoided for ``avoid_for_s``.
    """

    validity_s: float = 3.0
    """Our trajectories are valid this long (a peer's, at most this long after it was sent)."""
    action: Literal["drop-from-formation"] = "drop-from-formation"
    avoid_for_s: float = 10.0
    """A silent or expired peer's last trajectory is still avoided this long."""
    peer_silence_s: float = PEER_SILENCE_S
    """Nothing heard from a peer for this long: it is quiet, avoided at its ghosts (more than 2
    state periods)."""
    peer_silence_in_way_s: float = PEER_SILENCE_IN_WAY_S
    """Nothing heard from a peer for this long and its ghosts in our way: quiet already (a
    peer dying as it crosses toward us comes on along PX4's failsafe coast); a value above
    ``peer_silence_s`` acts as ``peer_silence_s``."""
    peer_silence_max_s: float = PEER_SILENCE_MAX_S
    """Nothing heard from a peer for this long: it is silent, out of the formation, whatever its
    link's recent quiet spells (at least ``peer_silence_s``)."""
    peer_deviation_m: float = PEER_DEVIATION_M
    """A peer reported further than this from its trajectory is avoided where it reported
    itself (more than the vehicles' tracking error)."""
    peer_deviation_ahead_s: float = PEER_DEVIATION_AHEAD_S
    """... and so is one that would be that far off it this long later if it (its reported
    velocity) and its trajectory went straight on (it stopped or turned off it; 0: positions
    only)."""
    ghost_window_s: float = GHOST_WINDOW_S
    """A silent peer may have flown on this long after it was last heard before it stopped."""
    ghost_forget_s: float = GHOST_FORGET_S
    """A silent peer's ghosts are avoided this long after it fell silent."""

    def __post_init__(self) -> None:
        _in_range("validity_s", self.validity_s, 0.1, 60.0)
        _in_range("avoid_for_s", self.avoid_for_s, 0.0, 600.0)
        _in_range("peer_silence_s", self.peer_silence_s, 0.05, 60.0)
        _in_range("peer_silence_in_way_s", self.peer_silence_in_way_s, 0.05, 60.0)
        _in_range("peer_silence_max_s", self.peer_silence_max_s, 0.05, 60.0)
        if self.peer_silence_max_s < self.peer_silence_s:
            raise ValueError(
                f"peer_silence_max_s: expected at least peer_silence_s ({self.peer_silence_s:g}), "
                f"got {self.peer_silence_max_s:g}"
            )
        _in_range("peer_deviation_m", self.peer_deviation_m, 0.05, 10.0)
        _in_range("peer_deviation_ahead_s", self.peer_deviation_ahead_s, 0.0, 5.0)
        _in_range("ghost_window_s", self.ghost_window_s, 0.0, 10.0)
        _in_range("ghost_forget_s", self.ghost_forget_s, 0.0, 3600.0)


@dataclass(frozen=True)
class AutopilotLostReaction:
    """No autopilot heartbeat for ``autopilot.heartbeat_timeout_s``: stop commanding; after the
    link returns, stream nothing until a ground-station command says so."""

    action: Literal["stop-commanding"] = "stop-commanding"


@dataclass(frozen=True)
class GcsLostReaction:
    """Nothing from the ground station for ``timeout_s``: finish the current goal and hover
    ('hover'), or land there ('land')."""

    timeout_s: float = 5.0
    action: Literal["hover", "land"] = "hover"

    def __post_init__(self) -> None:
        _in_range("timeout_s", self.timeout_s, 0.5, 600.0)


@dataclass(frozen=True)
class PilotReaction:
    """The vehicle left OFFBOARD by someone else's decision: yield at once, never fight."""

    action: Literal["yield"] = "yield"


@dataclass(frozen=True)
class ReactionsSection:
    depth_lost: DepthLostReaction = field(default_factory=DepthLostReaction)
    peer_lost: PeerLostReaction = field(default_factory=PeerLostReaction)
    autopilot_lost: AutopilotLostReaction = field(default_factory=AutopilotLostReaction)
    gcs_lost: GcsLostReaction = field(default_factory=GcsLostReaction)
    pilot_took_over: PilotReaction = field(default_factory=PilotReaction)


@dataclass(frozen=True)
class BusSection:
    state_rate_hz: float = 10.0
    status_rate_hz: float = 1.0
    clock_offset_bound_s: float = 0.05
    """A peer whose clock seems further off than this is reported with a warning."""

    def __post_init__(self) -> None:
        _in_range("state_rate_hz", self.state_rate_hz, 1.0, 50.0)
        _in_range("status_rate_hz", self.status_rate_hz, 0.1, 10.0)
        _in_range("clock_offset_bound_s", self.clock_offset_bound_s, 0.001, 10.0)


@dataclass(frozen=True)
class LoggingSection:
    level: Literal["debug", "info", "warning", "error"] = "info"
    format: Literal["kv", "json"] = "kv"
    """One line per record: ``key=value`` pairs or a JSON object (both journald-friendly)."""


@dataclass(frozen=True)
class RecordSection:
    enabled: bool = True
    directory: str = "/var/lib/swarm-onboard/records"
    """One MCAP file per flight (take-off to landed) here; relative paths from the cwd."""


@dataclass(frozen=True)
class WatchdogSection:
    main_loop_hz: float = 20.0
    stall_s: float = 2.0
    """A thread (setpoints, planner, monitor, depth) that has not reported for this long marks
    the service unhealthy: the systemd watchdog is no longer fed."""

    def __post_init__(self) -> None:
        _in_range("main_loop_hz", self.main_loop_hz, 1.0, 200.0)
        _in_range("stall_s", self.stall_s, 0.2, 60.0)


@dataclass(frozen=True)
class OnboardConfig:
    """Everything ``swarm-onboard run`` reads (``config/onboard.yaml``)."""

    drone: DroneSection = field(default_factory=DroneSection)
    autopilot: AutopilotSection = field(default_factory=AutopilotSection)
    zenoh: ZenohSection = field(default_factory=ZenohSection)
    depth: DepthSection = field(default_factory=DepthSection)
    mapping: MappingSection = field(default_factory=MappingSection)
    planner: PlannerParams = field(default_factory=load_planner_params)
    """Planner parameters: ``config/planner.yaml`` with the keys given here overriding it."""
    planning: PlanningSection = field(default_factory=PlanningSection)
    geofence: GeofenceSection = field(default_factory=GeofenceSection)
    flight: FlightSection = field(default_factory=FlightSection)
    reactions: ReactionsSection = field(default_factory=ReactionsSection)
    bus: BusSection = field(default_factory=BusSection)
    logging: LoggingSection = field(default_factory=LoggingSection)
    record: RecordSection = field(default_factory=RecordSection)
    watchdog: WatchdogSection = field(default_factory=WatchdogSection)

    def __post_init__(self) -> None:
        g = self.geofence
        # plans never leave the geofence: the planner's altitude band is cut to its z range
        lo, hi = self.planner.z_limits_m
        band = (max(lo, g.min_enu_m[2]), min(hi, g.max_enu_m[2]))
        if band != (lo, hi):
            try:
                planner = dataclasses.replace(self.planner, z_limits_m=band)
            except ValueError as e:
                raise ValueError(
                    f"planner.z_limits_m: the planner's altitude band [{lo:g}, {hi:g}] cut to "
                    f"the geofence's z range [{g.min_enu_m[2]:g}, {g.max_enu_m[2]:g}] is "
                    f"too narrow ({e})"
                ) from None
            object.__setattr__(self, "planner", planner)
        self._check_map_window()
        slack = self.planning.monitor_obstacle_slack_m
        if not slack < self.planner.check_obstacle_m:
            raise ValueError(
                f"planning.monitor_obstacle_slack_m: {slack:g} m leaves nothing of the check's "
                f"distance (planner.check_obstacle_m {self.planner.check_obstacle_m:g} m): the "
                "monitor would never brake for an obstacle"
            )
        for key, taken in (("peer_silence_s", "silent"), ("peer_silence_in_way_s", "quiet")):
            limit = getattr(self.reactions.peer_lost, key)
            if not limit >= 2.0 / self.bus.state_rate_hz:
                raise ValueError(
                    f"reactions.peer_lost.{key}: {limit:g} s is less than two state periods "
                    f"(bus.state_rate_hz {self.bus.state_rate_hz:g}): live peers would be "
                    f"taken for {taken} between their states"
                )
        if not g.min_enu_m[2] + self.flight.takeoff_altitude_m <= g.max_enu_m[2]:
            raise ValueError(
                "flight.takeoff_altitude_m: the take-off altitude must lie inside the geofence "
                f"(max z {g.max_enu_m[2]:g})"
            )

    @property
    def map_params(self) -> OccupancyParams:
        """What the service maps with: ``mapping.occupancy`` for the camera's ``depth.rate_hz``
        (``OccupancyParams.for_frame_rate``), its window fitted to the planner's altitude band
        when ``mapping.window_band_margin_m`` is set."""
        m = self.mapping
        occ = m.occupancy.for_frame_rate(self.depth.rate_hz)
        if m.window_band_margin_m is None:
            return occ
        lo, hi = self.planner.z_limits_m
        return occ.for_band(lo, hi, m.window_band_margin_m)

    @property
    def camera_map_params(self) -> OccupancyParams | None:
        """``map_params`` when the service has a depth source to map, else None: whether (and
        with what) the service builds a map, and so whether the warm-up compiles the mapping
        path (``swarm-onboard run`` and ``warmup`` both ask here)."""
        return None if self.depth.source == "none" else self.map_params

    def _check_map_window(self) -> None:
        m = self.mapping
        margin = m.window_band_margin_m
        if margin is None:
            return
        occ = m.occupancy
        need = self.planner.check_obstacle_m + occ.inflation_m + occ.resolution_m / 2
        if margin < need - 1e-9:
            raise ValueError(
                f"mapping.window_band_margin_m: {margin:g} m is less than "
                f"planner.check_obstacle_m + mapping.occupancy.inflation_m + half a cell "
                f"({need:g} m): an obstacle just outside the map window could fail the safety "
                "check from inside the altitude band unseen"
            )
        tall = self.map_params.size_m[2]
        if tall > occ.size_m[2] + 1e-9:
            lo, hi = self.planner.z_limits_m
            raise ValueError(
                f"mapping.occupancy.size_m: the window fitted to the altitude band "
                f"[{lo:g}, {hi:g}] plus {margin:g} m each side is {tall:g} m tall, more than "
                f"size_m's z ({occ.size_m[2]:g} m), the most it may take"
            )


def default_config_path() -> Path:
    return config_dir() / "onboard.yaml"


def config_data(path: str | Path | None = None) -> dict[str, Any]:
    """The mapping in ``path`` (default ``config/onboard.yaml``, the drone's configuration),
    not yet validated: an empty file is an empty mapping. A file given to the service replaces
    the drone's, so whoever writes one for a service (the demo, the benchmarks, the tests)
    starts from this and merges its own settings on top."""
    p = Path(path) if path is not None else default_config_path()
    data = read_yaml(p)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"<root>: expected a mapping, got {type(data).__name__}")
    return data


def load_onboard_config(
    path: str | Path | None = None,
    drone_id: int | None = None,
    overrides: dict[str, Any] | None = None,
) -> OnboardConfig:
    """Read and validate ``path`` (default ``config/onboard.yaml``); ``drone_id`` (the
    ``--id`` option) and ``overrides`` (nested mappings) win over the file."""
    data = config_data(path)
    if overrides:
        data = merge_mappings(data, overrides)
    if drone_id is not None:
        data = merge_mappings(data, {"drone": {"id": drone_id}})
    return from_mapping(OnboardConfig, data)
