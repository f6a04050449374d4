"""The real edges behind the service's ports: the autopilot link (``onboard.autopilot``), the
swarm bus (``onboard.comm``) and the depth sources (``onboard.sensors``)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from onboard.comm.hearing import HearingReport, report_from_links
from onboard.comm.latency import BIN_KEY, LatencyFigures, LatencyRecorder
from onboard.service.config import OnboardConfig
from onboard.service.ports import (
    CommandFailed,
    IncomingCommand,
    PeerInfo,
    PeerState,
    Setpoint,
    SetpointSampler,
    VehicleSnapshot,
)

# PX4 mode names for the link's FlightMode values (what the service logs and publishes)
_MODE_NAMES = {
    "offboard": "OFFBOARD",
    "hold": "AUTO.LOITER",
    "posctl": "POSCTL",
    "altctl": "ALTCTL",
    "manual": "MANUAL",
    "takeoff": "AUTO.TAKEOFF",
    "land": "AUTO.LAND",
    "rtl": "AUTO.RTL",
    "mission": "AUTO.MISSION",
    "other": "OTHER",
    "unknown": "UNKNOWN",
}


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, ...]:
    """(w, x, y, z) of body (FLU) in ENU from roll, pitch, yaw (ENU, Z-Y-X)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def _finite3(v: Any) -> np.ndarray | None:
    """A finite ENU 3-vector as an array, else None."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        return None
    return a


def link_config(cfg: OnboardConfig) -> Any:
    """The autopilot link's ``LinkConfig`` for this drone."""
    from onboard.autopilot import LinkConfig
    from onboard.autopilot.config import DEFAULT_TELEMETRY_OFF

    ap = cfg.autopilot
    url = ap.endpoint(cfg.drone.id)
    if url.startswith("udp://"):
        url = "udpin://" + url[len("udp://") :]
    gf = cfg.geofence
    return LinkConfig(
        url=url,
        implementation=ap.implementation,
        baud=ap.baud,
        system_id=ap.target_system(cfg.drone.id),
        setpoint_rate_hz=ap.setpoint_rate_hz,
        link_timeout_s=ap.heartbeat_timeout_s,
        ack_timeout_s=min(0.5, ap.command_timeout_s),
        command_retries=ap.command_retries,
        # the link's final guard: the geofence with a margin (the planner keeps plans inside
        # the box itself; a vehicle standing on the ground reads a few cm below z = 0)
        geofence_min_enu_m=(gf.min_enu_m[0] - 1.0, gf.min_enu_m[1] - 1.0, gf.min_enu_m[2] - 1.0),
        geofence_max_enu_m=(gf.max_enu_m[0] + 1.0, gf.max_enu_m[1] + 1.0, gf.max_enu_m[2] + 1.0),
        max_speed_m_s=max(3.0, 2.0 * cfg.planner.v_max_m_s),
        max_accel_m_s2=max(5.0, 1.5 * cfg.planner.a_max_m_s2),
        signing_key_file=(
            ap.signing_key_file.replace("{id}", str(cfg.drone.id))
            if ap.signing_key_file is not None
            else None
        ),
        signing_required=ap.signing_required,
        local_origin_enu_m=ap.local_origin(cfg.drone.id),
        telemetry_off=DEFAULT_TELEMETRY_OFF if ap.trim_telemetry else (),
    )


class AutopilotAdapter:
    """``AutopilotPort`` over ``onboard.autopilot.AutopilotLink``."""

    def __init__(self, link: Any, clock: Callable[[], float] = time.time) -> None:
        self.link = link
        self.clock = clock
        self.healthy_timeout_s = 15.0

    def vehicle(self) -> VehicleSnapshot | None:
        st = self.link.state()
        if st.position_enu_m is None or st.velocity_enu_m_s is None:
            return None
        from onboard.autopilot import LandedState

        yaw = st.yaw_enu_rad if st.yaw_enu_rad is not None else 0.0
        q = quaternion_from_euler(st.roll_rad or 0.0, st.pitch_rad or 0.0, yaw)
        return VehicleSnapshot(
            t_s=self.clock() - (st.t_s - (st.position_t_s or st.t_s)),
            position_m=np.array(st.position_enu_m, dtype=np.float64),
            velocity_m_s=np.array(st.velocity_enu_m_s, dtype=np.float64),
            yaw_rad=yaw,
            attitude_wxyz=(q[0], q[1], q[2], q[3]),
            armed=st.armed,
            landed=st.landed_state == LandedState.ON_GROUND,
            mode=_MODE_NAMES.get(st.mode.value, st.mode.value.upper()),
            battery_v=st.battery_voltage_v,
        )

    def link_age_s(self) -> float:
        st = self.link.state()
        if not st.connected:
            return math.inf
        # the receive thread may stamp a message after the state's clock was read: a few ms
        # below zero, which the status wire format (rightly) refuses
        return max(0.0, float(st.rx_age_s))

    def stream(self, sampler: SetpointSampler | None) -> None:
        if sampler is None:
            self.link.stop_streaming()
            return
        from onboard.autopilot import Setpoint as LinkSetpoint

        def source(now_s: float) -> Any:
            sp: Setpoint | None = sampler(now_s)
            if sp is None:
                return None
            p, v, a = sp.position_m, sp.velocity_m_s, sp.acceleration_m_s2
            return LinkSetpoint(
                (float(p[0]), float(p[1]), float(p[2])),
                (float(v[0]), float(v[1]), float(v[2])),
                (float(a[0]), float(a[1]), float(a[2])),
                float(sp.yaw_rad),
            )

        self.link.start_streaming(source)

    @property
    def streaming(self) -> bool:
        return bool(self.link.streaming)

    def _call(self, name: str, fn: Callable[[], Any]) -> None:
        from onboard.autopilot import CommandError, LinkError

        try:
            fn()
        except (CommandError, LinkError, TimeoutError) as e:
            raise CommandFailed(f"{name}: {e}") from e

    def request_offboard(self) -> None:
        self._call("offboard", self.link.start_offboard)

    def arm(self) -> None:
        self._call("healthy", lambda: self.link.wait_healthy(self.healthy_timeout_s))
        self._call("arm", self.link.arm)

    def land(self) -> None:
        self._call("land", self.link.land)

    def counters(self) -> dict[str, int]:
        c = self.link.counters()
        return {
            f.name: int(getattr(c, f.name))
            for f in dataclasses.fields(c)
            if isinstance(getattr(c, f.name), int)
        }

    def close(self) -> None:
        self.link.close()


def open_autopilot(cfg: OnboardConfig, clock: Callable[[], float] = time.time) -> AutopilotAdapter:
    """Open and connect the configured autopilot link (``LinkError`` if PX4 is not heard)."""
    from onboard.autopilot import open_link

    link = open_link(link_config(cfg), sample_clock=clock)
    try:
        link.connect()
    except BaseException:
        link.close()
        raise
    return AutopilotAdapter(link, clock)


def command_from_wire(action: Any) -> Any:
    """A ground-station action (``onboard.comm.wire``) as a state-machine command."""
    from onboard.comm import wire
    from onboard.service import state

    if isinstance(action, wire.Takeoff):
        return state.Takeoff(float(action.altitude_m))
    if isinstance(action, wire.Land):
        return state.Land()
    if isinstance(action, wire.Abort):
        return state.Abort()
    if isinstance(action, wire.Resume):
        return state.Resume()
    if isinstance(action, wire.Goal):
        return state.Goal(
            tuple(float(v) for v in action.position_m),  # type: ignore[arg-type]
            float(action.effective_s),
        )
    if isinstance(action, wire.Waypoints):
        return state.Waypoints(
            tuple(tuple(float(v) for v in p) for p in action.points_m),  # type: ignore[misc]
            float(action.effective_s),
        )
    if isinstance(action, wire.FormationAssignment):
        c, s_ = math.cos(action.yaw_rad), math.sin(action.yaw_rad)
        pts = []
        for x, y, z in action.points_m:
            x, y, z = x * action.scale, y * action.scale, z * action.scale
            pts.append((c * x - s_ * y, s_ * x + c * y, z))
        return state.SetFormation(
            int(action.epoch),
            float(action.effective_s),
            tuple(sorted((int(d), int(k)) for d, k in action.slots.items())),
            tuple(pts),
        )
    raise ValueError(f"unknown action {type(action).__name__}")


class SwarmBusAdapter:
    """``SwarmBusPort`` over ``onboard.comm.zenoh_bus.SwarmNode`` (one drone's node).

    Its ``peers()`` is the inbox the planner reads (``onboard.service.planning.PortPeerBus``).
    Every peer trajectory that enters it is a latency sample: ``clock()`` right after the
    inbox was updated minus the sender's publish stamp (``onboard.comm.latency``, which says
    what the figure means across two clocks); the gate's refusals never get here.
    ``peer_latency()`` is the histogram so far; ``counters()`` carries it as
    ``peer_latency.*`` (the service's status and flight record add ``bus.``), the status only
    its summary (count, extremes, p50, p99), the flight record every bin too."""

    def __init__(self, node: Any, clock: Callable[[], float] = time.time) -> None:
        import threading

        self.node = node
        self.clock = clock
        self._lock = threading.Lock()
        self._peers: dict[int, PeerInfo] = {}
        self._latency = LatencyRecorder()
        self._states: dict[int, PeerState] = {}
        self._hearing: dict[int, HearingReport] = {}
        self._commands: list[IncomingCommand] = []
        self._last_cmd_s: float | None = None
        self._bad_commands = 0
        node.on_trajectory(self._on_traj)
        node.on_state(self._on_state)
        node.on_status(self._on_status)
        node.on_command(self._on_command)

    def _on_traj(self, env: Any, receive_s: float) -> None:
        from onboard.comm.messages import TrajectoryMsg

        m = TrajectoryMsg.from_envelope(env)
        info = PeerInfo(
            m.drone_id,
            m.slot,
            m.formation_epoch,
            m.trajectory,
            m.valid_until_s,
            receive_s,
            traj_id=m.traj_id,
            incarnation=int(env.incarnation),
        )
        stamp = float(env.stamp_s)
        with self._lock:
            self._peers[m.drone_id] = info
            self._latency.add(self.clock() - stamp)

    def _on_state(self, env: Any, receive_s: float) -> None:
        """A peer's 10 Hz state (the node subscribes to them: ``open_bus``): its newest by
        stamp is kept (the autopilot sample's time, at most the message's own stamp)."""
        body = env.body
        pid = int(env.sender)
        if pid == self.node.drone_id:
            return
        stamp = min(float(body.measured_s), float(env.stamp_s))
        st = PeerState(
            pid,
            stamp,
            _finite3(body.position_m),
            _finite3(body.velocity_m_s),
            str(body.flight_state),
            receive_s,
        )
        with self._lock:
            old = self._states.get(pid)
            if old is None or stamp > old.stamp_s:
                self._states[pid] = st

    def _on_status(self, env: Any, receive_s: float) -> None:
        """A peer's 1 Hz status: what it says about its link to us (``onboard.comm.hearing``);
        its newest by stamp is kept."""
        pid = int(env.sender)
        me = self.node.drone_id
        if pid == me or me is None:
            return
        links = [(str(x.name), bool(x.up), x.age_s) for x in env.body.links]
        rep = report_from_links(pid, float(env.stamp_s), me, links)
        with self._lock:
            old = self._hearing.get(pid)
            if old is None or rep.stamp_s > old.stamp_s:
                self._hearing[pid] = rep

    def _on_command(self, env: Any, receive_s: float) -> None:
        body = env.body
        try:
            cmd = command_from_wire(body.action)
        except ValueError as e:
            self.node.send_ack(body.cmd_id, False, str(e)[:200])
            with self._lock:
                self._bad_commands += 1
            return
        with self._lock:
            self._commands.append(IncomingCommand(int(body.cmd_id), cmd, int(env.sender)))
            self._last_cmd_s = receive_s

    # ---- SwarmBusPort ------------------------------------------------------------------------
    def publish_trajectory(
        self, traj_id: int, slot: int, epoch: int, trajectory: Any, valid_for_s: float
    ) -> None:
        from onboard.comm.messages import TrajectoryMsg

        now = self.clock()
        msg = TrajectoryMsg(
            self.node.drone_id, traj_id, slot, trajectory, max(epoch, 0), now + valid_for_s
        )
        self.node.publish_trajectory(msg, now)

    def publish_state(self, fields: dict[str, Any]) -> None:
        from onboard.comm.wire import StateBody

        f = dict(fields)
        f["formation_epoch"] = max(int(f["formation_epoch"]), 0)
        self.node.publish_state(StateBody(**f))

    def publish_status(self, fields: dict[str, Any]) -> None:
        from onboard.comm.wire import LinkHealth, StatusBody

        offsets = [abs(c.offset_s) for c in self.node.clock_report().values() if c is not None]
        links = [
            LinkHealth(name, bool(up), None if age is None or not math.isfinite(age) else age)
            for name, up, age in fields["links"]
        ]
        batt = fields.get("battery_v")
        self.node.publish_status(
            StatusBody(
                flight_state=fields["flight_state"],
                plan_status=fields["plan_status"],
                plan_stamp_s=fields["plan_stamp_s"],
                plan_ms_last=float(fields["plan_ms_last"]),
                plan_ms_max=float(fields["plan_ms_max"]),
                replans=int(fields["replans"]),
                links=links,
                battery_v=None if batt is None or not 0.0 <= batt <= 100.0 else float(batt),
                battery_remaining=None,
                clock_offset_max_s=max(offsets) if offsets else None,
                counters=_status_counters(fields["counters"]),
                message=str(fields.get("message", ""))[:200],
            )
        )

    def ack(self, cmd_id: int, accepted: bool, reason: str) -> None:
        self.node.send_ack(cmd_id, accepted, reason[:200])

    def peers(self) -> dict[int, PeerInfo]:
        with self._lock:
            return dict(self._peers)

    def peer_states(self) -> dict[int, PeerState]:
        with self._lock:
            return dict(self._states)

    def hearing_reports(self) -> dict[int, HearingReport]:
        with self._lock:
            return dict(self._hearing)

    def poll_commands(self) -> list[IncomingCommand]:
        with self._lock:
            out, self._commands = self._commands, []
        return out

    def gcs_last_heard_s(self) -> float | None:
        if self.node.gcs_alive():
            return self.clock()
        with self._lock:
            return self._last_cmd_s

    def clock_exceeded(self) -> dict[int, float]:
        return {k: c.offset_s for k, c in self.node.clock_report().items() if c.exceeded}

    def peer_latency(self) -> LatencyFigures:
        """``LatencyFigures``: every peer trajectory's publish -> inbox latency so far."""
        with self._lock:
            return self._latency.snapshot()

    def counters(self) -> dict[str, int]:
        out = {k: int(v) for k, v in self.node.counters().items()}
        out["commands_undecodable"] = self._bad_commands
        out.update(self.peer_latency().to_counters("peer_latency."))
        return out

    def close(self) -> None:
        self.node.close()


def _status_counters(counters: dict[str, Any], limit: int = 128) -> dict[str, int]:
    """The counters a status carries (at most ``limit``, the wire's bound): all but the
    latency histogram's bins (they go to the flight record only)."""
    kept = [(k, v) for k, v in counters.items() if f"peer_latency.{BIN_KEY}" not in k]
    return {k: max(int(v), 0) for k, v in kept[:limit]}


def open_bus(cfg: OnboardConfig, clock: Callable[[], float] = time.time) -> SwarmBusAdapter:
    from onboard.comm.zenoh_bus import BusConfig, SwarmNode

    node = SwarmNode(
        cfg.drone.swarm,
        cfg.drone.id,
        cfg.zenoh.endpoints(cfg.drone.id, cfg.drone.swarm),
        config=BusConfig(
            traj_valid_for_s=cfg.reactions.peer_lost.validity_s,
            clock_offset_bound_s=cfg.bus.clock_offset_bound_s,
            subscribe_states=True,  # the peers' states are their signs of life (peer_lost)
        ),
        clock=clock,
    )
    return SwarmBusAdapter(node, clock)


def open_depth(cfg: OnboardConfig, pose_at: Any = None) -> Any:
    """The configured depth source, or None ('none')."""
    d = cfg.depth
    if d.source == "none":
        return None
    if d.source == "realsense":
        from onboard.sensors.realsense import RealSenseSource

        if pose_at is None:
            raise ValueError("a RealSense source needs the vehicle's pose provider")
        return RealSenseSource(pose_at, d.realsense_bag, clock=time.time, fps=int(d.rate_hz))
    # zenoh-sim: the SITL mock's frames over Zenoh (each frame carries its camera pose)
    from onboard.comm.zenoh_session import ZenohEndpoints
    from onboard.sensors.zenoh_depth import open_depth_source

    return open_depth_source(
        cfg.autopilot.target_system(cfg.drone.id),
        d.sim_prefix,
        ZenohEndpoints(connect=d.sim_connect),
    )


__all__ = [
    "AutopilotAdapter",
    "SwarmBusAdapter",
    "command_from_wire",
    "open_bus",
    "open_depth",
    "IncomingCommand",
    "PeerInfo",
    "PeerState",
    "link_config",
    "open_autopilot",
    "quaternion_from_euler",
]
