"""The mock on the network, spoken to with pymavlink: acknowledgements as PX4 v1.16 gives them,
offboard entry / loss / return, status fields, several vehicles on one socket, garbage on the
port, STATUSTEXT routing, signing (an explicit v1.17+ option).

Every test binds its own free ports on 127.0.0.1, runs the fleet in a background thread at a
speed-up, and stops it (joining the thread) whatever happens. Every wait has a deadline. Every
test fails if a message handler of the mock raised (``handler_errors``) or the loop died.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
import zenoh  # noqa: F401 - a hard dependency: a broken install must fail, not skip

import onboard.mapping.simcam  # noqa: F401 - the perception work's simulated D435
from sitl_mock.autopilot import ARMING_DENIED_TEXT, AutopilotParams
from sitl_mock.client import MavClient, bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig, SigningSpec
from sitl_mock.mavlink_io import signing_timestamp_now
from sitl_mock.px4_dialect import mavlink

SPEEDUP = 4.0
HOLD, OFFBOARD, LAND, POSCTL, TAKEOFF = 0x03040000, 0x00060000, 0x06040000, 0x00030000, 0x02040000
ACCEPTED, TEMP_REJECTED, DENIED, UNSUPPORTED = 0, 1, 2, 3
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
KEY = bytes(range(32))


@contextmanager
def fleet_and_clients(
    count: int = 1, signing_keys: dict[int, bytes] | None = None, **kw: Any
) -> Iterator[tuple[Fleet, list[MavClient]]]:
    # At 4x speed COM_OF_LOSS_T = 1 s leaves 250 ms of wall clock between setpoints: a test
    # client starved by a loaded machine could miss it. It is raised to 2 s here (a PX4
    # parameter); test_sitl_autopilot checks the default in simulated time.
    ap: dict[str, Any] = {
        "boot_time_s": 0.5,
        "offboard_loss_timeout_s": 2.0,
        **kw.pop("autopilot", {}),
    }
    socks = bind_consecutive_udp(count)
    keys = signing_keys or {}
    clients = [MavClient(sock=s, signing_key=keys.get(i + 1)) for i, s in enumerate(socks)]
    cfg = FleetConfig(
        count=count,
        base_port=clients[0].port,
        local_port_offset=None,
        speedup=SPEEDUP,
        autopilot=AutopilotParams(**ap),
        **kw,
    )
    fleet = Fleet(cfg)
    try:
        fleet.start()
        for c in clients:
            c.connect(timeout_s=10.0)
        yield fleet, clients
    finally:
        fleet.stop()
        for c in clients:
            c.close()
    assert fleet._thread is None and fleet.loop_error is None
    assert [link.stats.handler_errors for link in fleet.links] == [0] * count


def stream(
    c: MavClient, sysid: int, pos_ned: tuple[float, float, float], wall_s: float, **kw: Any
) -> None:
    """Position setpoints at 25 Hz (wall) for ``wall_s``, reading telemetry in between."""
    end = time.monotonic() + wall_s
    while time.monotonic() < end:
        c.setpoint(sysid, pos_ned, **kw)
        c.poll(0.04)


def stream_until(
    c: MavClient,
    sysid: int,
    pos_ned: tuple[float, float, float],
    pred: Any,
    timeout_s: float = 10.0,
) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met while streaming")
        stream(c, sysid, pos_ned, 0.04)


def interval_round_trip(c: MavClient, interval_us: int, tries: int = 5) -> bool:
    """The vehicle processes commands: it stores a VIBRATION interval and reports it back
    (GET_MESSAGE_INTERVAL), a round trip whose answer depends on what was set."""
    vib = mavlink.MAVLINK_MSG_ID_VIBRATION
    for _ in range(tries):
        try:
            if c.command_long(511, (vib, float(interval_us)), timeout_s=1.0) != ACCEPTED:
                continue
            if c.command_long(510, (vib,), timeout_s=1.0) != ACCEPTED:
                continue
            got = c.wait("MESSAGE_INTERVAL", lambda m: m.message_id == vib, 1.0)
            return int(got.interval_us) == interval_us
        except TimeoutError:
            continue
    return False


def ready(c: MavClient) -> None:
    c.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & PREARM, 10.0)


def lpn(c: MavClient) -> Any:
    return c.latest.get("LOCAL_POSITION_NED")


def int_param(pv: Any) -> int:
    return int(struct.unpack("<i", struct.pack("<f", pv.param_value))[0])


def test_telemetry_requests_and_parameters() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        hb = c.latest["HEARTBEAT"]
        assert (hb.type, hb.autopilot, hb.custom_mode) == (2, 12, HOLD)
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
        ready(c)
        hb = c.wait("HEARTBEAT")
        assert (hb.base_mode, hb.system_status) == (29, 3)  # disarmed in Hold, ready
        st = c.latest["SYS_STATUS"]
        for bit in (
            mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO,
            mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
            mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG,
            mavlink.MAV_SYS_STATUS_SENSOR_GPS,
        ):
            assert st.onboard_control_sensors_present & bit
            assert st.onboard_control_sensors_health & bit
        # the pre-arm bit lives in the health field only
        assert not (st.onboard_control_sensors_present | st.onboard_control_sensors_enabled) & (
            PREARM
        )
        ess = c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == 1)
        assert ess.vtol_state == mavlink.MAV_VTOL_STATE_UNDEFINED  # a multicopter
        cm = c.wait("CURRENT_MODE", timeout_s=5.0)
        assert (cm.custom_mode, cm.intended_custom_mode) == (HOLD, HOLD)
        # REQUEST_MESSAGE: HOME_POSITION, AUTOPILOT_VERSION, PROTOCOL_VERSION; unknown: denied
        assert c.command_long(512, (mavlink.MAVLINK_MSG_ID_HOME_POSITION,)) == ACCEPTED
        home = c.wait("HOME_POSITION")
        assert home.latitude == pytest.approx(473977420, abs=200) and home.altitude == 488000
        assert c.command_long(512, (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)) == ACCEPTED
        ver = c.wait("AUTOPILOT_VERSION")
        assert ver.capabilities == 0xE8FF == 59647  # as a real PX4 v1.16 reports
        assert ver.flight_sw_version >> 16 == 0x0110  # 1.16
        assert c.command_long(519) == ACCEPTED  # MAV_CMD_REQUEST_PROTOCOL_VERSION
        pv = c.wait("PROTOCOL_VERSION")
        assert (pv.version, pv.min_version, pv.max_version) == (200, 100, 200)
        assert c.command_long(512, (300,)) == ACCEPTED
        c.wait("PROTOCOL_VERSION")
        assert c.command_long(512, (9999,)) == DENIED
        assert c.command_long(183, (1.0, 1500.0)) == UNSUPPORTED  # DO_SET_SERVO
        # TIMESYNC is answered with the request's ts1; PING requests are answered too
        c.send(c.mav.timesync_encode(0, 123456789))
        ts = c.wait("TIMESYNC", lambda m: m.ts1 == 123456789)
        assert ts.tc1 > 0
        c.send(c.mav.ping_encode(42, 7, 0, 0))
        pong = c.wait("PING", lambda m: m.seq == 7 and m.target_system == 245)
        assert pong.time_usec == 42 and pong.target_component == 190
        # SET_MESSAGE_INTERVAL: stop LOCAL_POSITION_NED, query, restore the default
        lpn_id = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
        assert c.command_long(511, (lpn_id, -1.0)) == ACCEPTED
        c.recorded.clear()
        c.record.add("LOCAL_POSITION_NED")
        assert c.command_long(510, (lpn_id,)) == ACCEPTED
        assert c.wait("MESSAGE_INTERVAL", lambda m: m.message_id == lpn_id).interval_us == -1
        c.wait("ATTITUDE")
        c.poll(0.3)
        assert not c.recorded  # none since the ACK
        assert c.command_long(511, (lpn_id, 0.0)) == ACCEPTED
        c.wait("LOCAL_POSITION_NED")
        assert c.command_long(511, (lpn_id, 200000.0)) == ACCEPTED  # 5 Hz
        assert c.command_long(511, (4242, 1000.0)) == DENIED
        # parameters: PX4 names, float and bytewise-int values, PX4's defaults
        c.send(c.mav.param_request_read_encode(1, 1, b"MIS_TAKEOFF_ALT", -1))
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == 2.5
        c.send(c.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, mavlink.MAV_PARAM_TYPE_REAL32))
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T").param_value == 0.5
        c.send(c.mav.param_request_read_encode(1, 1, b"COM_OBL_RC_ACT", -1))
        pv = c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")
        assert pv.param_type == mavlink.MAV_PARAM_TYPE_INT32 and int_param(pv) == 0
        # a supported code is applied (bytewise int, as MAVSDK and QGC send it)
        land = struct.unpack("<f", struct.pack("<i", 4))[0]
        c.send(c.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", land, mavlink.MAV_PARAM_TYPE_INT32))
        pv = c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")
        assert int_param(pv) == 4 and fleet.autopilots[0].params.offboard_loss_action == "land"
        # an unsupported one (2: Stabilized) is answered with an error and the value in force
        stab = struct.unpack("<f", struct.pack("<i", 2))[0]
        c.send(c.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", stab, mavlink.MAV_PARAM_TYPE_INT32))
        err = c.wait("PARAM_ERROR", lambda m: m.param_id == "COM_OBL_RC_ACT")
        assert err.error == mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE and err.target_system == 245
        assert int_param(c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")) == 4
        assert fleet.autopilots[0].params.offboard_loss_action == "land"
        # as is a NaN for a float parameter, and an unknown name
        c.send(c.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", math.nan, 9))
        c.wait("PARAM_ERROR", lambda m: m.param_id == "COM_OF_LOSS_T")
        assert fleet.autopilots[0].params.offboard_loss_timeout_s == 0.5
        c.send(c.mav.param_set_encode(1, 1, b"NO_SUCH_PARAM", 1.0, 9))
        err = c.wait("PARAM_ERROR", lambda m: m.param_id == "NO_SUCH_PARAM")
        assert err.error == mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST
        c.send(c.mav.param_request_list_encode(1, 1))
        c.wait_until(lambda: c.counts["PARAM_VALUE"] >= 6 + 11, 5.0)
        st = fleet.links[0].stats
        assert st.rx_malformed == 5 and st.rx_bad == 0  # 9999, 4242, Stabilized, NaN, unknown


@pytest.mark.slow
@pytest.mark.vehicle
def test_offboard_after_one_setpoint_failsafe_and_return() -> None:
    """PX4 v1.16 as observed: Offboard at once after one setpoint; stream lost -> Position
    mode, "Failsafe activated", system_status 5, CURRENT_MODE still naming Offboard; stream
    back -> Offboard by itself; after landing and the auto-disarm: Offboard, system_status 0,
    pre-arm bit clear; arming refused until another mode is chosen."""
    with fleet_and_clients() as (fleet, (c,)):
        c.send_heartbeat()  # a GCS: PX4 sends it STATUSTEXT
        ready(c)
        assert c.command_long(400, (2.0,)) == DENIED  # arm with a bad param1
        assert c.set_mode(1) == DENIED  # MANUAL: not in the mock
        assert c.command_long(176, (0.0, 4.0, 3.0)) == DENIED  # not a custom mode
        assert c.set_mode(3) == TEMP_REJECTED  # POSCTL without RC
        assert c.set_mode(6) == TEMP_REJECTED  # OFFBOARD without any setpoint
        assert c.command_long(400, (1.0,)) == ACCEPTED
        assert c.command_long(22, (math.nan,) * 7) == ACCEPTED  # takeoff, default altitude
        c.wait("HEARTBEAT", lambda m: m.custom_mode == TAKEOFF, 5.0)
        c.wait_until(lambda: lpn(c) is not None and lpn(c).z < -2.2, 15.0)
        c.wait("HEARTBEAT", lambda m: m.custom_mode == HOLD and m.base_mode == 157, 10.0)
        # one setpoint, then Offboard at once: accepted, acknowledged twice as PX4 does
        n_acks = c.counts["COMMAND_ACK"]
        c.setpoint(1, (0.0, 0.0, -2.5))
        assert c.set_mode(6) == ACCEPTED
        stream_until(
            c,
            1,
            (2.0, 0.0, -3.0),
            lambda: (
                c.counts["COMMAND_ACK"] >= n_acks + 2
                and c.latest["HEARTBEAT"].custom_mode == OFFBOARD
                and abs(lpn(c).x - 2.0) < 0.15
                and abs(lpn(c).z + 3.0) < 0.15
            ),
        )
        assert c.latest["HEARTBEAT"].base_mode == 145
        pt = c.latest["POSITION_TARGET_LOCAL_NED"]
        assert (pt.x, pt.z, pt.coordinate_frame) == pytest.approx((2.0, -3.0, 1), abs=1e-5)
        # the stream stops: Position mode (COM_OBL_RC_ACT 0), critical status, descending
        hb = c.wait("HEARTBEAT", lambda m: m.custom_mode == POSCTL, 10.0)
        assert hb.system_status == 5 and hb.base_mode & 128
        cm = c.wait("CURRENT_MODE", lambda m: m.custom_mode == POSCTL, 5.0)
        assert cm.intended_custom_mode == OFFBOARD
        assert cm.standard_mode == mavlink.MAV_STANDARD_MODE_POSITION_HOLD
        assert "Failsafe activated" in c.statustexts
        z0 = lpn(c).z
        c.poll(0.3)
        assert lpn(c).z > z0 + 0.2  # descending (without RC input)
        # setpoints again, still airborne: back to Offboard by itself
        stream_until(c, 1, (2.0, 0.0, -3.0), lambda: c.latest["HEARTBEAT"].custom_mode == OFFBOARD)
        stream(c, 1, (2.0, 0.0, -3.0), 0.4)  # a heartbeat or two later
        hb = c.latest["HEARTBEAT"]
        assert (hb.custom_mode, hb.system_status) == (OFFBOARD, 4)
        # land: lands, disarms, returns to the last user mode (Offboard)
        assert c.command_long(21) == ACCEPTED
        c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == 4, 5.0)
        hb = c.wait("HEARTBEAT", lambda m: not m.base_mode & 128, 20.0)
        assert (hb.base_mode, hb.custom_mode, hb.system_status) == (17, OFFBOARD, 0)
        c.discard_pending()
        for _ in range(5):  # the pre-arm bit stays clear
            st = c.wait("SYS_STATUS", timeout_s=2.0)
            assert not st.onboard_control_sensors_health & PREARM
        for text in ("Landing at current position", "Landing detected", "Disarmed by landing"):
            assert text in c.statustexts
        assert c.command_long(400, (1.0,)) == TEMP_REJECTED  # Offboard without a stream
        assert c.command_long(400, (1.0, 21196.0)) == TEMP_REJECTED  # forced: the same
        c.poll(0.1)
        assert c.statustexts.count(ARMING_DENIED_TEXT) == 2
        # the SET_MODE message works too (acknowledged as DO_SET_MODE)
        c.send(c.mav.set_mode_encode(1, 1, HOLD))
        assert c.wait("COMMAND_ACK", lambda m: m.command == 176).result == ACCEPTED
        c.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & PREARM, 3.0)
        assert c.command_long(400, (1.0,)) == ACCEPTED
        assert "Armed by external command" in c.statustexts
        assert c.command_long(400, (0.0,)) == ACCEPTED  # on the ground
        st = fleet.links[0].stats
        assert st.setpoints_malformed == 0 and st.rx_malformed == 1  # the bad arm param1


def test_failsafe_land_and_other_setpoint_types() -> None:
    ap = {"offboard_loss_action": "land"}
    with fleet_and_clients(autopilot=ap) as (fleet, (c,)):
        ready(c)
        c.setpoint(1, (0.0, 0.0, -2.0))
        assert c.set_mode(6) == ACCEPTED
        assert c.command_long(400, (1.0,)) == ACCEPTED  # armable in offboard with a setpoint
        stream_until(c, 1, (0.0, 0.0, -2.0), lambda: lpn(c) is not None and lpn(c).z < -1.9)
        # velocity north 1 m/s with altitude held by position, yaw to 1 rad
        mask = 1 | 2 | 32 | 64 | 128 | 256 | 2048
        end = time.monotonic() + 10.0
        while not (abs(lpn(c).vx - 1.0) < 0.05 and abs(c.latest["ATTITUDE"].yaw - 1.0) < 0.02):
            assert time.monotonic() < end
            c.setpoint(
                1, (0.0, 0.0, -2.0), velocity_ned=(1.0, 0.0, 0.0), yaw_rad=1.0, type_mask=mask
            )
            c.poll(0.04)
        assert abs(lpn(c).z + 2.0) < 0.1
        # yaw rate only (position hold)
        mask = 8 | 16 | 32 | 64 | 128 | 256 | 1024
        end = time.monotonic() + 5.0
        while not abs(c.latest["ATTITUDE"].yawspeed - 0.5) < 0.02:
            assert time.monotonic() < end
            c.setpoint(1, (2.0, 0.0, -2.0), yaw_rate_rad_s=0.5, type_mask=mask)
            c.poll(0.04)
        # frame 7 (LOCAL_OFFSET_NED) is ignored by PX4 v1.16: the stream counts as lost -> Land
        c.send_heartbeat()
        frame7 = 8 | 16 | 32 | 64 | 128 | 256 | 1024 | 2048
        end = time.monotonic() + 10.0
        while c.latest["HEARTBEAT"].custom_mode != LAND:
            assert time.monotonic() < end
            c.setpoint(1, (0.0, 0.0, 0.0), type_mask=frame7, frame=7)
            c.poll(0.04)
        assert "SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported" in c.statustexts
        c.wait("HEARTBEAT", lambda m: not m.base_mode & 128, 20.0)
        assert fleet.links[0].stats.setpoints_malformed >= 1


def test_vehicles_do_not_cross_talk_on_one_socket() -> None:
    """One client socket talks to three vehicles: each answers from its own system id, acts
    only on what is addressed to it, and ignores what is addressed to another vehicle."""
    with fleet_and_clients(3) as (fleet, clients):
        c = clients[0]  # vehicles 2 and 3 initially send to the other two sockets
        addrs = fleet.addresses()
        hb = c.pack(c.mav.heartbeat_encode(6, 8, 0, 0, 0, 3))
        c.record.update({"HEARTBEAT", "GLOBAL_POSITION_INT", "COMMAND_ACK"})
        for a in addrs:  # each vehicle takes this socket as its partner
            c.send_raw(hb, to=a)
        c.wait_until(lambda: {m.get_srcSystem() for _, m in c.recorded} == {1, 2, 3}, 5.0)

        def latest(kind: str, sysid: int) -> Any:
            ms = [m for _, m in c.recorded if m.get_type() == kind and m.get_srcSystem() == sysid]
            return ms[-1] if ms else None

        # each vehicle reports its own position: spawned 1.5 m apart along north
        c.wait_until(lambda: all(latest("GLOBAL_POSITION_INT", i) for i in (1, 2, 3)), 5.0)
        lats = [latest("GLOBAL_POSITION_INT", i).lat for i in (1, 2, 3)]
        assert lats[0] < lats[1] < lats[2]
        assert (lats[1] - lats[0]) * 1e-7 * math.pi / 180 * 6378137 == pytest.approx(1.5, abs=0.1)
        for i in (1, 2, 3):
            ready_deadline = time.monotonic() + 10.0
            while not fleet.autopilots[i - 1].ready(fleet.t_s):
                assert time.monotonic() < ready_deadline
                c.poll(0.05)

        def arm(target: int, via: int) -> None:
            msg = c.mav.command_long_encode(target, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
            c.send_raw(c.pack(msg), to=addrs[via - 1])

        # a command for vehicle 3 sent to vehicle 1's port: nobody acts, nobody answers
        c.recorded.clear()
        arm(3, via=1)
        c.poll(0.5)
        assert latest("COMMAND_ACK", 1) is None and latest("COMMAND_ACK", 3) is None
        assert [ap.armed for ap in fleet.autopilots] == [False, False, False]
        assert fleet.links[0].stats.rx_ignored >= 1
        # vehicle 2, addressed properly: only it arms, and only it acknowledges
        arm(2, via=2)
        c.wait_until(lambda: latest("COMMAND_ACK", 2) is not None, 3.0)
        ack = latest("COMMAND_ACK", 2)
        assert (ack.command, ack.result, ack.target_system, ack.target_component) == (
            400,
            ACCEPTED,
            245,
            190,
        )
        c.wait_until(lambda: bool(latest("HEARTBEAT", 2).base_mode & 128), 3.0)
        c.poll(1.0)  # a heartbeat from everybody
        assert [bool(latest("HEARTBEAT", i).base_mode & 128) for i in (1, 2, 3)] == [
            False,
            True,
            False,
        ]
        # a broadcast target (0) sent to vehicle 3: vehicle 3 only
        arm(0, via=3)
        c.wait_until(lambda: latest("COMMAND_ACK", 3) is not None, 3.0)
        assert latest("COMMAND_ACK", 1) is None
        assert [ap.armed for ap in fleet.autopilots] == [False, True, True]


def test_garbage_and_malformed_messages_do_not_crash_a_vehicle() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        ready(c)
        rng = np.random.default_rng(5)
        good = c.pack(c.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        junk: list[bytes] = [b"", bytes(60000), b"\xfd", b"\xfe\x09", b"\xfd\xff" + bytes(300)]
        junk += [
            rng.integers(0, 256, int(n), dtype=np.uint8).tobytes()
            for n in rng.integers(1, 400, 200)
        ]
        junk += [good[:k] for k in range(1, len(good))]  # truncated
        bad_crc = bytearray(good)
        bad_crc[-1] ^= 0xFF
        junk.append(bytes(bad_crc))
        junk.append(b"\xfd" + bytes([9, 0x80]) + good[3:])  # unknown incompat flag
        junk.append(bytes(rng.integers(0, 256, 50, dtype=np.uint8)) + good[:-1])
        for j in junk:
            c.send_raw(j)
        assert interval_round_trip(c, 123_000)
        assert not fleet.autopilots[0].armed  # no junk passed for the arm command
        # well-formed messages with hostile content
        mav = c.mav
        hostile = [
            mav.command_long_encode(1, 1, 400, 0, math.nan, math.nan, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 176, 0, math.inf, math.nan, -1e30, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 176, 0, 1.0, 1e30, -1e30, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 511, 0, math.nan, math.inf, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 512, 0, 1e30, 0, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 510, 0, -1e30, 0, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 22, 0, 0, 0, 0, 0, math.inf, -math.inf, 1e38),
            mav.command_int_encode(1, 1, 0, 400, 0, 0, 7.0, 0, 0, 0, 2**31 - 1, -(2**31), 0),
            mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0, *([math.nan] * 11)),
            mav.set_position_target_local_ned_encode(0, 1, 1, 99, 0, *([1.0] * 11)),
            mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0xFFFF, *([math.inf] * 11)),
            mav.set_position_target_local_ned_encode(0, 1, 1, 8, 0, *([math.inf] * 11)),
            mav.set_mode_encode(1, 255, 0xFFFFFFFF),
            mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", math.nan, 9),
            mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", 1e30, 6),
            mav.param_request_read_encode(1, 1, b"\xff\xfe", 32767),
            mav.timesync_encode(0, -1),
            mav.ping_encode(2**64 - 1, 2**32 - 1, 0, 0),
        ]
        for m in hostile:
            c.send(m)
        # the vehicle still lives: it processes commands, it streams, it counted the rubbish
        assert interval_round_trip(c, 456_000)
        assert c.command_long(400, (1.0,)) == ACCEPTED
        hb = c.wait("HEARTBEAT", lambda m: m.base_mode & 128, 5.0)
        assert hb.custom_mode == HOLD
        assert c.command_long(400, (0.0,)) == ACCEPTED
        assert fleet._thread is not None and fleet._thread.is_alive()
        st = fleet.links[0].stats
        assert st.rx_bad > 100 and st.setpoints == 0 and st.setpoints_malformed == 4
        # NaN / 7.0 arm, 511/512/510 out of range, 4 setpoints, 2 parameter values
        assert st.rx_malformed == 2 + 3 + 4 + 2
        assert st.handler_errors == 0
        assert fleet.autopilots[0].params.offboard_loss_timeout_s == 2.0  # NaN refused


def test_statustext_only_towards_a_gcs() -> None:
    """PX4 v1.16 sends STATUSTEXT only on a link where it hears a GCS heartbeat (observed)."""
    with fleet_and_clients() as (fleet, (c,)):
        ready(c)
        c.send_heartbeat(gcs=False)  # an onboard controller (MAV_TYPE_ONBOARD_CONTROLLER)
        assert c.command_long(400, (1.0,)) == ACCEPTED
        assert c.command_long(400, (0.0,)) == ACCEPTED
        c.poll(0.3)
        assert c.counts["STATUSTEXT"] == 0
        assert fleet.links[0].stats.statustexts_suppressed >= 2
        c.send_heartbeat(gcs=True)
        c.wait_until(lambda: fleet.links[0].gcs_seen, 3.0)
        assert c.command_long(400, (1.0,)) == ACCEPTED
        c.wait("STATUSTEXT", lambda m: m.text == "Armed by external command", 3.0)
        assert c.statustexts == ["Armed by external command"]


def test_signing_option_refuses_unsigned_commands() -> None:
    """The signing option (PX4 v1.17+ behaviour, off by default) on vehicle 2 only."""
    spec = (SigningSpec(KEY.hex(), require=True, system_id=2),)
    with fleet_and_clients(2, signing=spec) as (fleet, (c1, c2)):
        ready(c1)
        ready(c2)
        # vehicle 2 signs its telemetry; vehicle 1 does not
        assert (
            fleet.links[1].mav.signing.sign_outgoing
            and not fleet.links[0].mav.signing.sign_outgoing
        )
        signed = mavlink.MAVLINK_IFLAG_SIGNED
        assert c2.wait("HEARTBEAT").get_header().incompat_flags & signed
        assert not c1.wait("HEARTBEAT").get_header().incompat_flags & signed
        assert c1.command_long(400, (1.0,), target_system=1) == ACCEPTED  # unsigned, no key
        with pytest.raises(TimeoutError):
            c2.command_long(400, (1.0,), target_system=2, timeout_s=0.6)
        assert not c2.wait("HEARTBEAT").base_mode & 128
        # a wrong key is refused too
        c2.mav.signing.secret_key = bytes(32 * [7])
        c2.mav.signing.sign_outgoing = True
        c2.mav.signing.timestamp = 2**40
        with pytest.raises(TimeoutError):
            c2.command_long(400, (1.0,), target_system=2, timeout_s=0.6)
        # the right key: accepted (the forged timestamps above did not block the stream)
        c2.mav.signing.secret_key = KEY
        c2.mav.signing.timestamp = signing_timestamp_now()
        signed_arm = c2.pack(c2.mav.command_long_encode(2, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        c2.send_raw(signed_arm)
        assert c2.wait("COMMAND_ACK", lambda m: m.command == 400).result == ACCEPTED
        # a replay of the same signed bytes is refused
        assert c2.command_long(400, (0.0,), target_system=2) == ACCEPTED
        c2.send_raw(signed_arm)
        c2.poll(0.5)
        assert not fleet.autopilots[1].armed
        assert fleet.links[1].stats.rx_rejected_unsigned >= 3


def test_setup_signing_is_ignored_as_by_px4_v1_16() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        ready(c)
        c.send(c.mav.setup_signing_encode(1, 1, list(KEY), signing_timestamp_now()))
        assert interval_round_trip(c, 250_000)  # processed after SETUP_SIGNING
        assert fleet.links[0].signing is None
        assert c.command_long(400, (1.0,)) == ACCEPTED  # unsigned still works
        hb = c.wait("HEARTBEAT")  # nothing is signed
        assert not hb.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED
        assert fleet.links[0].stats.rx_ignored >= 1


def test_setup_signing_when_imitating_px4_v1_17() -> None:
    with fleet_and_clients(accept_setup_signing=True) as (fleet, (c,)):
        ready(c)
        c.send(c.mav.setup_signing_encode(1, 1, list(KEY), signing_timestamp_now()))
        c.wait_until(lambda: fleet.links[0].signing is not None, 5.0)
        with pytest.raises(TimeoutError):
            c.command_long(400, (1.0,), timeout_s=0.6)
        c.mav.signing.secret_key = KEY
        c.mav.signing.sign_outgoing = True
        c.mav.signing.timestamp = signing_timestamp_now()
        assert c.command_long(400, (1.0,)) == ACCEPTED


def test_ground_truth_and_depth_over_zenoh() -> None:
    from onboard.comm.zenoh_session import free_loopback_endpoint
    from onboard.mapping.camera import check_frame
    from onboard.world import World
    from sitl_mock.truth import ZenohTruth, ZenohTruthSubscriber, simulated_d435

    endpoint = free_loopback_endpoint()
    world = World(np.zeros((0, 5)), np.zeros((0, 7)), np.array([[-5, 3.0, 0, 5, 4.0, 5]]), 0.0)
    pub = ZenohTruth("test/sim", [endpoint])
    sub = ZenohTruthSubscriber("test/sim", connect=[endpoint])
    cfg = FleetConfig(count=2, local_port_offset=None)
    fleet = Fleet(cfg, world, [pub], {1: simulated_d435(world, step=4)})
    try:
        deadline = time.monotonic() + 30.0  # a deadline for a loaded machine, not a timing
        while sub.pose(1) is None or sub.pose(2) is None:
            assert time.monotonic() < deadline, "no poses over Zenoh"
            for _ in range(10):
                fleet.tick()
            time.sleep(0.02)
        assert fleet._depth is not None and fleet._depth.render_once() == 1
        source = sub.depth_source(1)
        deadline = time.monotonic() + 30.0
        frame = source.read()
        while frame is None:
            assert time.monotonic() < deadline, "no depth frame over Zenoh"
            time.sleep(0.02)
            frame = source.read()
        assert source.read() is None  # nothing new
    finally:
        sub.close()
        fleet.close()
    pose2 = sub.pose(2)
    assert pose2 is not None and pose2.position_m[1] == pytest.approx(0.75)
    depth = check_frame(frame)
    # vehicle 1 on the ground at y = -0.75 facing north: the box face at y = 3
    assert frame.decimation == 4 and depth.shape == (120, 160)  # every 4th pixel of 640 x 480
    assert depth[60, 80] == pytest.approx(3.0 - frame.position[1], abs=0.01)
    position, rotation = sub.pose_provider(1)(frame.stamp_s)
    np.testing.assert_allclose(position, frame.position, atol=1e-9)
    np.testing.assert_allclose(rotation, frame.rotation, atol=1e-9)
