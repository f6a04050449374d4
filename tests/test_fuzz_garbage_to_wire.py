"""Garbage driven into every layer above the autopilot link; nothing bad reaches the wire.

The pymavlink link runs its real threads over a capturing transport that plays the autopilot
(heartbeat and position telemetry, COMMAND_ACK for every command) and decodes every byte the
link writes. Garbage goes in at each layer:

- the autopilot's own telemetry (NaN / inf positions, so that no hold is built on them);
- the swarm bus: peer trajectories with NaN, zero durations, 10 km knots (the gate refuses them,
  so the planner never sees them);
- ground-station goals (gate, then the flight state machine and its geofence);
- the planner's output: trajectories that evaluate to NaN, inf, 1e300, 10 km away, 1 km/s,
  1e9 m/s^2; a source that raises, that returns no ``Setpoint``, a NaN yaw.

Every SET_POSITION_TARGET_LOCAL_NED on the wire is then finite, inside the geofence and within
the speed and acceleration limits, and the guard has refused (counted) every kind of garbage.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import LinkConfig, Setpoint, TrajectorySource
from onboard.autopilot.frames import ned_to_enu, position_ned_to_enu
from onboard.autopilot.pymavlink_link import PymavlinkLink
from onboard.autopilot.transport import Address, Transport
from onboard.comm.gate import MessageGate
from onboard.comm.wire import (
    GCS_ID,
    WIRE_VERSION,
    Command,
    Envelope,
    Goal,
    Rejected,
    TrajectoryBody,
)
from onboard.service.adapters import command_from_wire
from onboard.service.state import FlightStateMachine, SetFormation, Takeoff

NAN, INF = math.nan, math.inf
NOW = time.time()
GEOFENCE = ((-20.0, -20.0, 0.0), (20.0, 20.0, 6.0))
MAX_SPEED, MAX_ACCEL = 3.0, 5.0
AUTOPILOT = ("127.0.0.1", 14580)


class FakeAutopilot(Transport):
    """Plays PX4 at the other end of the link and decodes everything the link sends."""

    datagrams = True

    def __init__(self) -> None:
        self._mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self._parser = mavlink.MAVLink(None)
        self._lock = threading.Lock()
        self._inbox: list[bytes] = []
        self._closed = False
        self.position_ned = (1.0, 2.0, -1.5)
        self.garbage_positions: list[tuple[float, float, float]] = []
        self.setpoints: list[Any] = []

    def _frame(self, msg: Any) -> bytes:
        b = bytes(msg.pack(self._mav))
        self._mav.seq = (self._mav.seq + 1) % 256
        return b

    def read(self, timeout_s: float) -> list[tuple[bytes, Address | None]]:
        time.sleep(min(timeout_s, 0.01))
        if self._closed:
            return []
        with self._lock:
            out = self._inbox
            self._inbox = []
            garbage = self.garbage_positions
            self.garbage_positions = []
        m = self._mav
        n, e, d = self.position_ned
        out.append(self._frame(m.heartbeat_encode(2, 12, 129 | 28, 6 << 16, 4)))  # OFFBOARD
        out.append(self._frame(m.local_position_ned_encode(0, n, e, d, 0.0, 0.0, 0.0)))
        out.append(self._frame(m.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
        for g in garbage:
            out.append(self._frame(m.local_position_ned_encode(0, *g, NAN, INF, 0.0)))
        return [(b, AUTOPILOT) for b in out]

    def write(self, data: bytes) -> bool:
        if self._closed:
            return False
        p = self._parser
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        for msg in p.parse_buffer(data) or []:
            kind = msg.get_type()
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                with self._lock:
                    self.setpoints.append(msg)
            elif kind == "COMMAND_LONG":
                ack = self._mav.command_ack_encode(msg.command, 0, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent())  # fmt: skip
                with self._lock:
                    self._inbox.append(self._frame(ack))
        return True

    def close(self) -> None:
        self._closed = True

    def sent(self) -> list[Any]:
        with self._lock:
            return list(self.setpoints)


class Garbage:
    """A 'trajectory' (what ``TrajectorySource`` samples) returning fixed values."""

    def __init__(self, p: Any, v: Any = (0.0, 0.0, 0.0), a: Any = (0.0, 0.0, 0.0)) -> None:
        self.p, self.v, self.a = (np.asarray(x, dtype=float) for x in (p, v, a))

    def state(self, t_global: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.p, self.v, self.a


class Line:
    """A valid slow trajectory inside the geofence."""

    def state(self, t_global: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = 0.2 * math.sin(t_global)
        return np.array([2.0 + x, 1.0, 1.5]), np.array([0.2, 0.0, 0.0]), np.zeros(3)


def poll(pred: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.005)


def raw(body: Any, sender: int) -> bytes:
    return msgspec.msgpack.encode(Envelope(WIRE_VERSION, sender, 1, 0, NOW, 3.0, body))


def bus_garbage() -> list[bytes]:
    def tb(durations: list[float], c0: float) -> TrajectoryBody:
        coeffs = [c0] + [0.0] * (len(durations) * 18 - 1)
        return TrajectoryBody(1, 0, 1, NOW, durations, coeffs)

    return [
        raw(tb([1.0], NAN), 1),
        raw(tb([1.0], INF), 1),
        raw(tb([0.0], 1.0), 1),
        raw(tb([-1.0], 1.0), 1),
        raw(tb([1.0], 1e4 + 1.0), 1),
        raw(tb([1.0], 1e300), 1),
        raw(tb([0.5] * 10_000, 1.0), 1),
    ]


def goal_garbage() -> list[bytes]:
    goals = [(NAN, 0.0, 1.0), (INF, 0.0, 1.0), (1e300, 0.0, 1.0), (10_001.0, 0.0, 1.0)]
    return [raw(Command(1, [], NOW, Goal(g, None, NOW)), GCS_ID) for g in goals]


@pytest.mark.timeout(60)
def test_no_garbage_reaches_the_wire() -> None:
    cfg = LinkConfig(
        url="udpin://127.0.0.1:9",
        setpoint_rate_hz=200.0,
        geofence_min_enu_m=GEOFENCE[0],
        geofence_max_enu_m=GEOFENCE[1],
        max_speed_m_s=MAX_SPEED,
        max_accel_m_s2=MAX_ACCEL,
        ack_timeout_s=0.2,
    )
    ap = FakeAutopilot()
    link = PymavlinkLink(cfg, transport=ap)
    source = TrajectorySource(Line())
    logging.disable(logging.ERROR)
    try:
        link.connect(5.0)
        # telemetry garbage: never a position, never a hold built on it
        ap.garbage_positions = [(NAN, 0.0, 0.0), (INF, -INF, 0.0)]
        poll(lambda: link.counters().decode_errors >= 2, "garbage telemetry counted")
        st = link.state()
        assert st.position_enu_m is not None and all(map(math.isfinite, st.position_enu_m))

        link.start_streaming(source)
        poll(lambda: link.counters().setpoints_sent >= 5, "good setpoints")

        # the bus and the ground station: refused before any planner or state machine
        gate = MessageGate("swarm", own_id=0)
        for payload in bus_garbage():
            with pytest.raises(Rejected):
                gate.admit("swarm/drone/1/traj", payload, NOW)
        machine = airborne_machine()
        for payload in goal_garbage():
            try:
                env = gate.admit("swarm/cmd/goal", payload, NOW)
            except Rejected:
                continue
            assert isinstance(env.body, Command)  # (10 km is inside the wire's bound)
            r = machine.command(command_from_wire(env.body.action))
            assert not r.accepted and "geofence" in (r.reason or "")
        assert machine.goal is None

        # the planner's output and the source itself
        garbage: list[tuple[str, Callable[[float], Any]]] = [
            (n, TrajectorySource(g))
            for n, g in [
                ("nan position", Garbage((NAN, 0.0, 1.0))),
                ("inf velocity", Garbage((1.0, 1.0, 1.0), (INF, 0.0, 0.0))),
                ("nan accel", Garbage((1.0, 1.0, 1.0), a=(0.0, NAN, 0.0))),
                ("1e300", Garbage((1e300, 0.0, 1.0))),
                ("10 km away", Garbage((10_000.0, 0.0, 1.0))),
                ("under ground", Garbage((1.0, 1.0, -3.0))),
                ("1 km/s", Garbage((1.0, 1.0, 1.0), (1000.0, 0.0, 0.0))),
                ("1e9 m/s2", Garbage((1.0, 1.0, 1.0), a=(0.0, 0.0, 1e9))),
            ]
        ]
        garbage.append(("nan yaw", TrajectorySource(Line(), yaw_enu_rad=NAN)))
        garbage.append(("raises", _raises))
        garbage.append(("not a setpoint", lambda t: (1.0, 2.0, 3.0)))
        for name, bad in garbage:
            before = link.counters()
            link.set_source(bad)
            poll(
                lambda b=before: link.counters().setpoints_held >= b.setpoints_held + 3,  # type: ignore[misc]
                f"{name}: held",
            )
            after = link.counters()
            assert (
                after.setpoints_rejected > before.setpoints_rejected
                or after.source_errors > before.source_errors
            ), name
        link.set_source(source)
        n = link.counters().setpoints_sent
        poll(lambda: link.counters().setpoints_sent >= n + 5, "good setpoints again")
    finally:
        link.close()
        logging.disable(logging.NOTSET)

    sent = ap.sent()
    assert len(sent) >= 40
    for m in sent:
        p = position_ned_to_enu((m.x, m.y, m.z), cfg.local_origin_enu_m)
        v = ned_to_enu((m.vx, m.vy, m.vz))
        a = ned_to_enu((m.afx, m.afy, m.afz))
        assert all(math.isfinite(x) for x in (*p, *v, *a, m.yaw)), m
        assert all(GEOFENCE[0][k] <= p[k] <= GEOFENCE[1][k] for k in range(3)), p
        assert math.hypot(*v) <= MAX_SPEED and math.hypot(*a) <= MAX_ACCEL, (v, a)
    reasons = link.counters().rejected_by_reason
    assert {"non-finite", "outside-geofence", "speed-limit", "accel-limit"} <= set(reasons)
    assert link.counters().source_errors >= 2


def _raises(t: float) -> Setpoint:
    raise FloatingPointError("the planner blew up")


def airborne_machine() -> FlightStateMachine:
    def inside(p: Any) -> bool:
        return all(GEOFENCE[0][k] <= float(p[k]) <= GEOFENCE[1][k] for k in range(3))

    m = FlightStateMachine(0, lambda: NOW, inside_geofence=inside)
    m.command(SetFormation(1, 0.0, ((0, 0), (1, 1)), ((0.0, 0.0, 0.0), (1.5, 0.0, 0.0))))
    m.command(Takeoff(1.0))
    m.set_on_ground(False)
    m.takeoff_reached()
    return m
