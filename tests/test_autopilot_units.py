"""The autopilot link's pure parts: frames, PX4 modes, the final guard, link health, mode
tracking, the command retry policy, config checks, transports, MAVLink framing for MAVSDK."""

from __future__ import annotations

import math
import os
import socket
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import px4
from onboard.autopilot.config import LinkConfig, parse_url
from onboard.autopilot.frames import (
    attitude_ned_to_enu,
    enu_to_ned,
    ned_to_enu,
    position_ned_to_enu,
    setpoint_enu_to_ned,
    wrap_pi,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)
from onboard.autopilot.guard import GuardLimits, guard_setpoint, setpoint_problem
from onboard.autopilot.link import LinkHealth, ModeTracker, run_command
from onboard.autopilot.mavsdk_link import _json_fields, heartbeat_type, split_frames
from onboard.autopilot.model import (
    CommandError,
    CommandResult,
    FlightMode,
    LinkError,
    PeriodStats,
    Setpoint,
)
from onboard.autopilot.pymavlink_link import sys_status_health
from onboard.autopilot.source import TrajectorySource
from onboard.autopilot.transport import SerialTransport, UdpTransport
from onboard.planner.trajectory import Trajectory

finite = st.floats(-1e4, 1e4, allow_nan=False)
angles = st.floats(-20.0, 20.0, allow_nan=False)

# ---- frames ------------------------------------------------------------------------------


def test_enu_to_ned_axes() -> None:
    assert enu_to_ned((1.0, 0.0, 0.0)) == (0.0, 1.0, -0.0)  # east
    assert enu_to_ned((0.0, 1.0, 0.0)) == (1.0, 0.0, -0.0)  # north
    assert enu_to_ned((0.0, 0.0, 1.0)) == (0.0, 0.0, -1.0)  # up is minus down
    assert enu_to_ned((1.0, 2.0, 3.0)) == (2.0, 1.0, -3.0)


@given(finite, finite, finite)
def test_ned_to_enu_inverts_enu_to_ned(x: float, y: float, z: float) -> None:
    assert ned_to_enu(enu_to_ned((x, y, z))) == (x, y, z)


def test_yaw_conversion() -> None:
    assert yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)  # facing east
    assert yaw_enu_to_ned(math.pi / 2) == pytest.approx(0.0)  # facing north
    assert yaw_enu_to_ned(math.pi) == pytest.approx(-math.pi / 2)  # facing west
    assert abs(yaw_enu_to_ned(-math.pi / 2)) == pytest.approx(math.pi)  # facing south
    assert math.isnan(yaw_enu_to_ned(math.nan))


@given(angles)
def test_yaw_conversion_is_wrapped_and_inverse(yaw: float) -> None:
    ned = yaw_enu_to_ned(yaw)
    assert -math.pi < ned <= math.pi
    back = yaw_ned_to_enu(ned)
    assert math.isclose(math.cos(back), math.cos(yaw), abs_tol=1e-9)
    assert math.isclose(math.sin(back), math.sin(yaw), abs_tol=1e-9)
    # the NED heading is clockwise from north: its unit vector, in ENU, is (sin, cos)
    assert math.isclose(math.sin(ned), math.cos(yaw), abs_tol=1e-9)
    assert math.isclose(math.cos(ned), math.sin(yaw), abs_tol=1e-9)


def test_wrap_pi_range() -> None:
    assert wrap_pi(-math.pi) == math.pi
    assert wrap_pi(3 * math.pi) == pytest.approx(math.pi)
    assert wrap_pi(0.5) == 0.5


def test_setpoint_enu_to_ned_with_origin() -> None:
    ned = setpoint_enu_to_ned(
        (13.0, 22.0, 3.0), (1.0, 2.0, 0.5), (0.1, -0.2, 0.3), 0.0, origin_enu_m=(10.0, 20.0, 1.0)
    )
    assert ned.position_ned_m == (2.0, 3.0, -2.0)
    assert ned.velocity_ned_m_s == (2.0, 1.0, -0.5)
    assert ned.accel_ned_m_s2 == (-0.2, 0.1, -0.3)
    assert ned.yaw_ned_rad == pytest.approx(math.pi / 2)
    assert setpoint_enu_to_ned((0, 0, 0), (0, 0, 0), (0, 0, 0), None).yaw_ned_rad is None
    back = position_ned_to_enu(ned.position_ned_m, (10.0, 20.0, 1.0))
    assert back == (13.0, 22.0, 3.0)


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@given(st.floats(-3.0, 3.0), st.floats(-1.4, 1.4), st.floats(-3.1, 3.1))
def test_attitude_ned_to_enu_matches_rotation_matrices(
    roll: float, pitch: float, yaw: float
) -> None:
    r_ned_frd = _rz(yaw) @ _ry(pitch) @ _rx(roll)
    t_enu_ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t_frd_flu = np.diag([1.0, -1.0, -1.0])
    r_enu_flu = t_enu_ned @ r_ned_frd @ t_frd_flu
    r2, p2, y2 = attitude_ned_to_enu(roll, pitch, yaw)
    assert np.allclose(_rz(y2) @ _ry(p2) @ _rx(r2), r_enu_flu, atol=1e-9)


# ---- PX4 modes ---------------------------------------------------------------------------


def test_px4_modes_as_observed_on_v1_16() -> None:
    assert px4.mode_from_custom_mode(0x03040000) == FlightMode.HOLD
    assert px4.mode_from_custom_mode(0x02040000) == FlightMode.TAKEOFF
    assert px4.mode_from_custom_mode(0x00060000) == FlightMode.OFFBOARD
    assert px4.mode_from_custom_mode(393216) == FlightMode.OFFBOARD
    assert px4.mode_from_custom_mode(0x06040000) == FlightMode.LAND
    assert px4.mode_from_custom_mode(196608) == FlightMode.POSCTL
    assert px4.mode_from_custom_mode(0x05040000) == FlightMode.RTL
    assert px4.mode_from_custom_mode(0x00070000) == FlightMode.MANUAL
    assert px4.mode_from_custom_mode(0) == FlightMode.OTHER


@pytest.mark.parametrize(
    "mode",
    [m for m in FlightMode if m not in (FlightMode.UNKNOWN, FlightMode.OTHER)],
)
def test_px4_mode_round_trip(mode: FlightMode) -> None:
    assert px4.mode_from_custom_mode(px4.custom_mode_of(mode)) == mode
    p = px4.set_mode_params(mode)
    assert p[0] == 1.0 and len(p) == 7
    assert px4.command_name(px4.CMD_DO_SET_MODE, p) == f"MAV_CMD_DO_SET_MODE({mode.name})"


def test_px4_mode_not_selectable() -> None:
    with pytest.raises(ValueError, match="OTHER"):
        px4.set_mode_params(FlightMode.OTHER)


def test_px4_command_params() -> None:
    assert px4.custom_mode_of(FlightMode.OFFBOARD) == 0x60000
    assert px4.custom_mode_of(FlightMode.HOLD) == 0x3040000
    assert px4.custom_mode_of(FlightMode.LAND) == 0x6040000
    assert px4.arm_params(True)[:2] == (1.0, 0.0)
    assert px4.arm_params(False, force=True)[:2] == (0.0, 21196.0)
    tk = px4.takeoff_params(500.0)
    assert tk[6] == 500.0 and math.isnan(tk[4]) and math.isnan(tk[5])  # never lat/lon 0
    assert math.isnan(px4.takeoff_params(None)[6])
    assert all(math.isnan(v) for v in px4.land_params()[4:6])
    assert px4.command_name(400, px4.arm_params(True)) == "MAV_CMD_COMPONENT_ARM_DISARM(arm)"


# ---- the final guard ---------------------------------------------------------------------

LIMITS = GuardLimits((-10.0, -10.0, 0.0), (10.0, 10.0, 5.0), 2.0, 4.0)
GOOD = Setpoint((1.0, 2.0, 1.5), (0.5, 0.0, 0.1), (0.2, 0.0, 0.0), 0.3)


def test_guard_passes_a_good_setpoint() -> None:
    v = guard_setpoint(GOOD, None, LIMITS)
    assert v.setpoint is GOOD and v.reason is None
    edge = Setpoint((10.0, -10.0, 0.0), (2.0, 0.0, 0.0), (0.0, 4.0, 0.0))
    assert setpoint_problem(edge, LIMITS) is None  # the box and the limits are inclusive


BAD = [
    (Setpoint((math.nan, 0.0, 1.0)), "non-finite"),
    (Setpoint((0.0, 0.0, 1.0), (0.0, math.inf, 0.0)), "non-finite"),
    (Setpoint((0.0, 0.0, 1.0), accel_enu_m_s2=(0.0, 0.0, -math.nan)), "non-finite"),
    (Setpoint((0.0, 0.0, 1.0), yaw_enu_rad=math.nan), "non-finite"),
    (Setpoint((0.0, 0.0, 1.0), yaw_enu_rad=math.inf), "non-finite"),
    (Setpoint((10.01, 0.0, 1.0)), "outside-geofence"),
    (Setpoint((0.0, -10.5, 1.0)), "outside-geofence"),
    (Setpoint((0.0, 0.0, -0.01)), "outside-geofence"),
    (Setpoint((0.0, 0.0, 5.2)), "outside-geofence"),
    (Setpoint((0.0, 0.0, 1.0), (1.5, 1.5, 0.0)), "speed-limit"),
    (Setpoint((0.0, 0.0, 1.0), accel_enu_m_s2=(0.0, 3.0, 3.0)), "accel-limit"),
]


@pytest.mark.parametrize(("sp", "reason"), BAD)
def test_guard_replaces_a_bad_setpoint_by_holding(sp: Setpoint, reason: str) -> None:
    v = guard_setpoint(sp, GOOD, LIMITS)
    assert v.reason == reason
    assert v.setpoint is not None and v.setpoint is not sp
    assert v.setpoint.position_enu_m == GOOD.position_enu_m
    assert v.setpoint.velocity_enu_m_s == (0.0, 0.0, 0.0)
    assert v.setpoint.accel_enu_m_s2 == (0.0, 0.0, 0.0)
    assert v.setpoint.yaw_enu_rad == GOOD.yaw_enu_rad
    assert setpoint_problem(v.setpoint, LIMITS) is None
    # without a good setpoint to hold, nothing is sent
    assert guard_setpoint(sp, None, LIMITS).setpoint is None


def test_guard_holds_when_the_source_has_nothing() -> None:
    v = guard_setpoint(None, GOOD, LIMITS)
    assert v.reason is None and v.setpoint is not None
    assert v.setpoint.position_enu_m == GOOD.position_enu_m
    assert guard_setpoint(None, None, LIMITS).setpoint is None


def test_setpoint_rejects_wrong_shapes() -> None:
    with pytest.raises(ValueError, match="position_enu_m"):
        Setpoint((1.0, 2.0))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="velocity_enu_m_s"):
        Setpoint((1.0, 2.0, 3.0), 5.0)  # type: ignore[arg-type]
    sp = Setpoint(np.array([1.0, 2.0, 3.0]))  # type: ignore[arg-type]
    assert sp.position_enu_m == (1.0, 2.0, 3.0) and isinstance(sp.position_enu_m, tuple)


# ---- link health, mode tracking, command policy ------------------------------------------


def test_link_health_transitions() -> None:
    h = LinkHealth(link_timeout_s=1.0, heartbeat_timeout_s=3.0)
    assert h.update(0.0, None, None) is None and not h.connected
    assert h.update(0.1, 0.05, 0.05) == "connected"
    assert h.update(1.04, 1.0, 0.05) is None  # telemetry flows, heartbeat 1 s old: fine
    assert h.update(2.0, 1.0, 1.05) is None  # exactly 1.0 s of silence: not yet
    assert h.update(2.01, 1.0, 1.05) == "lost" and h.lost and h.lost_since == 2.01
    assert h.update(2.5, 1.0, 1.05) is None  # still lost, reported once
    assert h.update(3.0, 2.99, 1.05) == "regained" and not h.lost
    # a missing heartbeat alone also counts (3 s: PX4's heartbeat is 1 Hz)
    assert h.update(4.25, 4.2, 1.25) is None  # exactly 3 s
    assert h.update(4.3, 4.29, 1.25) == "lost"


def test_link_health_counts_silence_up_to_the_receivers_last_look() -> None:
    """A receiving thread that did not run leaves messages waiting in the socket: the silence
    it has not looked at is not the link's (a loaded CI host: "lost" at 1.0 s, "back" 0.02 s
    later). A receiver that looked after the deadline and found nothing loses the link; one that
    has not looked for ``receiver_stall_s`` (hung, dead) no longer holds the verdict back."""
    h = LinkHealth(link_timeout_s=1.0, heartbeat_timeout_s=3.0, receiver_stall_s=3.0)
    assert h.update(0.1, 0.05, 0.05, looked=0.1) == "connected"
    # the receiver last looked at 0.5 (all handled by then); at 1.6 the checker wakes first
    assert h.update(1.6, 0.5, 0.5, looked=0.5) is None and not h.lost
    # it runs, drains the waiting messages and looks again: nothing lost
    assert h.update(1.62, 1.61, 1.2, looked=1.6) is None and not h.lost
    # a receiver that looked after the deadline and found nothing: lost
    assert h.update(2.7, 1.61, 1.2, looked=2.65) == "lost"
    assert h.update(2.8, 2.75, 2.75, looked=2.79) == "regained"
    # a receiver that stopped looking (hung): the verdict runs up to now once it is stale
    assert h.update(5.0, 2.75, 2.75, looked=2.79) is None  # 2.21 s without a look
    assert h.update(5.8, 2.75, 2.75, looked=2.79) == "lost"  # 3.01 s without a look


def test_mode_tracker_tells_commanded_from_uncommanded() -> None:
    m = ModeTracker(window_s=5.0)
    assert m.observe(FlightMode.HOLD, 0.0).change is None  # first heartbeat: no change
    m.expect(FlightMode.OFFBOARD, 1.0)
    o = m.observe(FlightMode.OFFBOARD, 1.5)
    assert o.change == (FlightMode.HOLD, FlightMode.OFFBOARD, True) and not o.offboard_lost
    # a pilot (or PX4's failsafe) switches to Position: not asked for
    o = m.observe(FlightMode.POSCTL, 20.0)
    assert o.change == (FlightMode.OFFBOARD, FlightMode.POSCTL, False) and o.offboard_lost
    # asked for Land: not a loss
    m.observe(FlightMode.OFFBOARD, 21.0)
    m.expect(FlightMode.LAND, 30.0)
    assert not m.observe(FlightMode.LAND, 30.2).offboard_lost
    # an old request does not excuse a later change
    m.observe(FlightMode.OFFBOARD, 31.0)
    assert m.observe(FlightMode.LAND, 40.0).offboard_lost
    # takeoff: PX4 goes to Hold by itself
    m.expect(FlightMode.TAKEOFF, 50.0)
    m.observe(FlightMode.TAKEOFF, 50.1)
    assert m.observe(FlightMode.HOLD, 52.0).change == (FlightMode.TAKEOFF, FlightMode.HOLD, True)
    # a request excuses one change only: HOLD -> OFFBOARD (asked), OFFBOARD -> HOLD (not)
    m.expect(FlightMode.OFFBOARD, 52.5)
    assert not m.observe(FlightMode.OFFBOARD, 53.0).offboard_lost
    assert m.observe(FlightMode.HOLD, 54.0).offboard_lost
    # only the latest request counts
    m.observe(FlightMode.OFFBOARD, 55.0)
    m.expect(FlightMode.LAND, 55.0)
    m.expect(FlightMode.OFFBOARD, 55.5)
    assert m.observe(FlightMode.LAND, 56.0).offboard_lost


def test_run_command_policy() -> None:
    sleeps: list[float] = []

    def script(*results: CommandResult):  # type: ignore[no-untyped-def]
        it = iter(results)
        return lambda: next(it)

    assert run_command("x", script(CommandResult.ACCEPTED), 3, 0.5, sleeps.append) == 1
    assert sleeps == []
    t = CommandResult.TEMPORARILY_REJECTED
    assert run_command("x", script(t, t, CommandResult.ACCEPTED), 3, 0.5, sleeps.append) == 3
    assert sleeps == [0.5, 0.5]
    with pytest.raises(CommandError) as e:
        run_command("MAV_CMD_X(arm)", script(t, t, t), 2, 0.1, lambda _: None)
    assert e.value.result == t and e.value.attempts == 3
    assert "MAV_CMD_X(arm)" in str(e.value) and "TEMPORARILY_REJECTED" in str(e.value)
    for r in (CommandResult.DENIED, CommandResult.FAILED, CommandResult.TIMEOUT):
        with pytest.raises(CommandError) as e:
            run_command("cmd", script(r, CommandResult.ACCEPTED), 5, 0.0, lambda _: None)
        assert e.value.result == r and e.value.attempts == 1


def test_command_result_from_mav_result() -> None:
    assert CommandResult.from_mav_result(0) == CommandResult.ACCEPTED
    assert CommandResult.from_mav_result(1) == CommandResult.TEMPORARILY_REJECTED
    assert CommandResult.from_mav_result(2) == CommandResult.DENIED
    assert CommandResult.from_mav_result(5) == CommandResult.IN_PROGRESS
    assert CommandResult.from_mav_result(99) == CommandResult.FAILED


def test_period_stats() -> None:
    s = PeriodStats.of([0.02] * 98 + [0.03, 0.05])
    assert s.count == 100 and s.p50_ms == pytest.approx(20.0)
    assert s.p99_ms == pytest.approx(30.0) and s.max_ms == pytest.approx(50.0)
    assert PeriodStats.of([]).count == 0


def test_sys_status_health() -> None:
    gyro, gps = 1, 32
    prearm = px4.SENSOR_PREARM_CHECK
    assert sys_status_health(gyro | gps | prearm, gyro | gps | prearm, gyro | gps | prearm) == (
        True,
        True,
    )
    assert sys_status_health(gyro | gps | prearm, gyro | gps | prearm, gyro) == (False, False)
    # after a landing PX4 clears the pre-arm bit; the sensors are still fine
    assert sys_status_health(gyro | prearm, gyro | prearm, gyro) == (True, False)


# ---- config --------------------------------------------------------------------------------


def test_parse_url() -> None:
    e = parse_url("udpin://127.0.0.1:14540")
    assert (e.kind, e.host, e.port) == ("udpin", "127.0.0.1", 14540)
    assert parse_url("udp://:14541").kind == "udpin"
    assert parse_url("udp://:14541").host == "0.0.0.0"
    e = parse_url("udpout://10.0.0.2:14580")
    assert (e.kind, e.host, e.port) == ("udpout", "10.0.0.2", 14580)
    e = parse_url("serial:///dev/ttyTHS0", baud=921600)
    assert (e.kind, e.device, e.baud) == ("serial", "/dev/ttyTHS0", 921600)
    e = parse_url("serial:///dev/ttyTHS0:57600")
    assert (e.device, e.baud) == ("/dev/ttyTHS0", 57600)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"url": "tcp://1.2.3.4:5"}, "url"),
        ({"url": "udpin://127.0.0.1"}, "url"),
        ({"url": "udpout://127.0.0.1:0"}, "url"),
        ({"url": "serial://ttyTHS0"}, "url"),
        ({"url": "serial:///dev/ttyTHS0:1234"}, "baud"),
        ({"baud": 12345}, "baud"),
        ({"implementation": "grpc"}, "implementation"),
        ({"system_id": 0}, "system_id"),
        ({"component_id": 1}, "component_id"),
        ({"setpoint_rate_hz": 1.0}, "setpoint_rate_hz"),
        ({"link_timeout_s": 0.0}, "link_timeout_s"),
        ({"max_speed_m_s": math.nan}, "max_speed_m_s"),
        ({"command_retries": -1}, "command_retries"),
        ({"telemetry_rates_hz": (("LOCAL_POSITION_NEDX", 10.0),)}, "telemetry_rates_hz"),
        ({"telemetry_rates_hz": (("ATTITUDE", -1.0),)}, "telemetry_rates_hz"),
        ({"telemetry_off": ("VFR_HUDX",)}, "telemetry_off"),
        ({"telemetry_off": ("HEARTBEAT",)}, "telemetry_off"),
        ({"telemetry_off": ("VFR_HUD", "LOCAL_POSITION_NED")}, r"telemetry_off\[1\]"),
        (
            {"telemetry_rates_hz": (("VFR_HUD", 5.0),), "telemetry_off": ("VFR_HUD",)},
            "telemetry_off",
        ),
        (
            {"geofence_min_enu_m": (0.0, 0.0, 5.0), "geofence_max_enu_m": (1.0, 1.0, 5.0)},
            "geofence_max_enu_m",
        ),
        ({"local_origin_enu_m": (0.0, math.inf, 0.0)}, "local_origin_enu_m"),
    ],
)
def test_link_config_errors_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        LinkConfig(**kwargs)


def test_link_config_defaults() -> None:
    c = LinkConfig()
    assert c.own_system_id == 1 and c.component_id == 191 and c.setpoint_period_s == 0.02
    assert LinkConfig(system_id=3).own_system_id == 3  # PX4 wants the vehicle's system id
    assert LinkConfig(system_id=3, source_system_id=200).own_system_id == 200


# ---- transports ----------------------------------------------------------------------------


def test_bad_serial_device_is_a_clear_error() -> None:
    with pytest.raises(LinkError, match="/dev/does-not-exist-ttyTHS9"):
        SerialTransport(parse_url("serial:///dev/does-not-exist-ttyTHS9:921600"))


def test_serial_transport_over_a_pty() -> None:
    master, slave = os.openpty()
    try:
        t = SerialTransport(parse_url(f"serial://{os.ttyname(slave)}:921600"))
        try:
            frame = bytes(range(200)) * 3
            assert t.write(frame)
            got = b""
            deadline = time.monotonic() + 5.0
            while len(got) < len(frame) and time.monotonic() < deadline:
                got += os.read(master, 4096)
            assert got == frame  # raw: no byte translated
            os.write(master, b"\xfd\x01\x02\r\n\x11")
            chunks = t.read(2.0)
            assert b"".join(c for c, _ in chunks) == b"\xfd\x01\x02\r\n\x11"
            assert all(addr is None for _, addr in chunks)
        finally:
            t.close()
        assert t.read(0.0) == [] and not t.write(b"x")
    finally:
        os.close(master)
        os.close(slave)


def test_udp_transport_learns_its_remote() -> None:
    t = UdpTransport(parse_url("udpin://127.0.0.1:0"))
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        peer.bind(("127.0.0.1", 0))
        assert not t.write(b"nobody yet")
        peer.sendto(b"hello", t.local_address)
        chunks = t.read(2.0)
        assert chunks == [(b"hello", peer.getsockname())]
        t.set_remote(chunks[0][1])
        assert t.write(b"back")
        peer.settimeout(2.0)
        assert peer.recvfrom(100)[0] == b"back"
        with pytest.raises(LinkError, match="cannot open UDP udpin"):
            UdpTransport(parse_url(f"udpin://127.0.0.1:{t.local_address[1]}"))
    finally:
        peer.close()
        t.close()


# ---- MAVLink framing (MAVSDK's outgoing bytes) ----------------------------------------------


def test_split_frames_and_heartbeat_type() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    hb_ours = bytes(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav))
    hb_mavsdk = bytes(mav.heartbeat_encode(0, 8, 0, 0, 0).pack(mav))
    sp = bytes(mav.set_position_target_local_ned_encode(0, 1, 1, 1, 2048, *[0.0] * 11).pack(mav))
    data = b"\x00garbage" + hb_ours + sp + hb_mavsdk
    frames = list(split_frames(data))
    assert [f[4] for f in frames] == [0, 84, 0]
    assert all((f[2], f[3]) == (1, 191) for f in frames)
    assert heartbeat_type(data[frames[0][0] : frames[0][1]]) == 18
    assert heartbeat_type(data[frames[2][0] : frames[2][1]]) == 0
    assert data[frames[1][0] : frames[1][1]] == sp
    assert list(split_frames(sp[:-3])) == []  # truncated
    mav1 = mavlink.MAVLink(None, srcSystem=2, srcComponent=1)
    mav1.WIRE_PROTOCOL_VERSION = "1.0"
    v1 = bytes(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3).pack(mav1, force_mavlink1=True))
    assert list(split_frames(v1))[0][2:] == (2, 1, 0)


def test_json_fields_send_nan_as_null() -> None:
    assert _json_fields({"a": 1, "b": math.nan, "c": 2.5}) == '{"a":1,"b":null,"c":2.5}'


# ---- trajectory source ---------------------------------------------------------------------


def test_trajectory_source_samples_the_current_trajectory() -> None:
    src = TrajectorySource(yaw_enu_rad=0.5)
    assert src(10.0) is None
    c = np.zeros((1, 6, 3))
    c[0, 0] = (1.0, 2.0, 3.0)
    c[0, 1] = (0.5, 0.0, 0.0)  # 0.5 m/s east
    src.set_trajectory(Trajectory(100.0, c, np.array([4.0])))
    sp = src(102.0)
    assert sp is not None
    assert sp.position_enu_m == pytest.approx((2.0, 2.0, 3.0))
    assert sp.velocity_enu_m_s == pytest.approx((0.5, 0.0, 0.0))
    assert sp.yaw_enu_rad == 0.5
    src.set_trajectory(Trajectory.hover(np.array([0.0, 0.0, 1.0]), 0.0))
    sp = src(1e6)
    assert sp is not None and sp.position_enu_m == (0.0, 0.0, 1.0)
