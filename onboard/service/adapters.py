"""The real edges behind the service's ports: the autopilot link (``onboard.autopilot``), the
swarm bus (``onboard.comm``) and the depth sources (``onboard.sensors``)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from onboard.service.config import OnboardConfig
from onboard.service.ports import (
    CommandFailed,
    IncomingCommand,
    PeerInfo,
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


def link_config(cfg: OnboardConfig) -> Any:
    """The autopilot link's ``LinkConfig`` for this drone."""
    from onboard.autopilot import LinkConfig

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
        return float(st.rx_age_s)

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


__all__ = [
    "AutopilotAdapter",
    "IncomingCommand",
    "PeerInfo",
    "link_config",
    "open_autopilot",
    "quaternion_from_euler",
]
