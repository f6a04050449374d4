"""The mock on the network, spoken to with pymavlink: acknowledgements as PX4 gives them,
offboard rules, failsafe, several vehicles, garbage on the port, signing.

Every test binds its own free ports on 127.0.0.1, runs the fleet in a background thread at a
speed-up, and stops it (joining the thread) whatever happens. Every wait has a deadline.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import MavClient, bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig, SigningSpec

SPEEDUP = 4.0
HOLD, OFFBOARD, LAND = 0x03040000, 0x00060000, 0x06040000
ACCEPTED, TEMP_REJECTED, DENIED, UNSUPPORTED = 0, 1, 2, 3
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
KEY = bytes(range(32))


@contextmanager
def fleet_and_clients(
    count: int = 1, signing_keys: dict[int, bytes] | None = None, **kw: Any
) -> Iterator[tuple[Fleet, list[MavClient]]]:
    # At 4x speed PX4's 2 Hz / 1 s offboard rules leave 125 / 250 ms of wall clock between
    # setpoints: a test client starved by a loaded machine could miss them. The rules are
    # relaxed here (1 Hz, 2 s); test_sitl_autopilot checks the defaults in simulated time.
    ap: dict[str, Any] = {
        "boot_time_s": 0.5,
        "offboard_min_rate_hz": 1.0,
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
    assert fleet._thread is None


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


def answers(c: MavClient, tries: int = 5) -> bool:
    """The vehicle acknowledges a harmless command (retried, as a ground station would):
    REQUEST_AUTOPILOT_CAPABILITIES, which nothing else in these tests sends."""
    for _ in range(tries):
        try:
            if c.command_long(520, (1.0,), timeout_s=1.0) == 0:
                return True
        except TimeoutError:
            continue
    return False


def ready(c: MavClient) -> None:
    c.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & PREARM, 10.0)


def lpn(c: MavClient) -> Any:
    return c.latest.get("LOCAL_POSITION_NED")


def test_telemetry_requests_and_parameters() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        hb = c.latest["HEARTBEAT"]
        assert (hb.type, hb.autopilot, hb.base_mode, hb.custom_mode) == (2, 12, 29, HOLD)
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1 and hb.system_status == 3
        ready(c)
        st = c.latest["SYS_STATUS"]
        for bit in (
            mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO,
            mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
            mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG,
            mavlink.MAV_SYS_STATUS_SENSOR_GPS,
        ):
            assert st.onboard_control_sensors_present & bit
            assert st.onboard_control_sensors_health & bit
        c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == 1)
        # REQUEST_MESSAGE: HOME_POSITION and AUTOPILOT_VERSION, an unknown id is denied
        assert c.command_long(512, (mavlink.MAVLINK_MSG_ID_HOME_POSITION,)) == ACCEPTED
        home = c.wait("HOME_POSITION")
        assert home.latitude == pytest.approx(473977420, abs=200) and home.altitude == 488000
        assert c.command_long(512, (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)) == ACCEPTED
        ver = c.wait("AUTOPILOT_VERSION")
        assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert c.command_long(512, (9999,)) == DENIED
        # TIMESYNC is answered with the request's ts1
        c.send(c.mav.timesync_encode(0, 123456789))
        ts = c.wait("TIMESYNC", lambda m: m.ts1 == 123456789)
        assert ts.tc1 > 0
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
        # parameters: PX4 names, float and bytewise-int values
        c.send(c.mav.param_request_read_encode(1, 1, b"MIS_TAKEOFF_ALT", -1))
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == 2.5
        c.send(c.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.5, mavlink.MAV_PARAM_TYPE_REAL32))
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T").param_value == 0.5
        c.send(c.mav.param_request_read_encode(1, 1, b"COM_OBL_RC_ACT", -1))
        pv = c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")
        assert pv.param_type == mavlink.MAV_PARAM_TYPE_INT32
        assert np.frombuffer(np.float32(pv.param_value).tobytes(), np.int32)[0] == 5
        c.send(c.mav.param_request_list_encode(1, 1))
        c.wait_until(lambda: c.counts["PARAM_VALUE"] >= 13, 5.0)
        assert fleet.autopilots[0].params.offboard_loss_timeout_s == 0.5


def test_command_acks_offboard_rules_and_failsafe() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        ready(c)
        assert c.command_long(183, (1.0, 1500.0)) == UNSUPPORTED  # DO_SET_SERVO
        assert c.command_long(400, (2.0,)) == DENIED  # arm with a bad param1
        assert c.set_mode(1) == DENIED  # MANUAL: not in the mock
        assert c.command_long(176, (0.0, 4.0, 3.0)) == DENIED  # not a custom mode
        assert c.set_mode(3) == TEMP_REJECTED  # POSCTL without RC
        assert c.set_mode(6) == TEMP_REJECTED  # OFFBOARD without a setpoint stream
        assert "Switching to Offboard is currently not possible" in c.statustexts
        assert c.command_long(400, (1.0,)) == ACCEPTED
        assert c.command_long(22, (math.nan,) * 7) == ACCEPTED  # takeoff, default altitude
        c.wait_until(lambda: lpn(c) is not None and lpn(c).z < -2.2, 15.0)
        c.wait("HEARTBEAT", lambda m: m.custom_mode == HOLD and m.base_mode == 157, 10.0)
        assert c.command_long(400, (0.0,)) == TEMP_REJECTED  # disarm in the air
        # a setpoint stream, then offboard: accepted, acknowledged twice as PX4 does
        stream(c, 1, (0.0, 0.0, -2.5), 0.4)
        n_acks = c.counts["COMMAND_ACK"]
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
        assert (pt.x, pt.z) == pytest.approx((2.0, -3.0), abs=1e-5)
        # the stream stops: the failsafe holds the position
        hb = c.wait("HEARTBEAT", lambda m: m.custom_mode == HOLD, 10.0)
        assert hb.system_status == 5  # critical while the failsafe is active
        assert any("offboard signal lost" in t for t in c.statustexts)
        # land: lands, disarms, returns to the last user mode (offboard)
        assert c.command_long(21) == ACCEPTED
        c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == 4, 5.0)
        hb = c.wait("HEARTBEAT", lambda m: not m.base_mode & 128, 20.0)
        assert (hb.base_mode, hb.custom_mode) == (17, OFFBOARD)
        assert c.command_long(400, (1.0,)) == TEMP_REJECTED  # offboard without a stream
        # the SET_MODE message works too (acknowledged as DO_SET_MODE)
        c.send(c.mav.set_mode_encode(1, 1, HOLD))
        assert c.wait("COMMAND_ACK", lambda m: m.command == 176).result == ACCEPTED
        assert c.command_long(400, (1.0,)) == ACCEPTED
        assert c.command_long(400, (0.0,)) == ACCEPTED  # on the ground
        assert fleet.links[0].stats.setpoints_malformed == 0


def test_failsafe_land_and_other_setpoint_types() -> None:
    ap = {"offboard_loss_action": "land"}
    with fleet_and_clients(autopilot=ap) as (fleet, (c,)):
        ready(c)
        stream(c, 1, (0.0, 0.0, -2.0), 0.4)
        assert c.set_mode(6) == ACCEPTED
        assert c.command_long(400, (1.0,)) == ACCEPTED  # armable in offboard with a stream
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
        # stream lost: land
        c.wait("HEARTBEAT", lambda m: m.custom_mode == LAND, 10.0)
        c.wait("HEARTBEAT", lambda m: not m.base_mode & 128, 20.0)


def test_vehicles_do_not_cross_talk() -> None:
    with fleet_and_clients(3) as (fleet, clients):
        for c in clients:
            ready(c)
        for i, c in enumerate(clients):
            c.poll(0.2)
            assert c.latest["HEARTBEAT"].get_srcSystem() == i + 1
            assert {m.get_srcSystem() for m in [c.latest[k] for k in c.latest]} == {i + 1}
        # arm vehicle 2 only
        assert clients[1].command_long(400, (1.0,), target_system=2) == ACCEPTED
        clients[1].wait("HEARTBEAT", lambda m: m.base_mode & 128)
        for c in (clients[0], clients[2]):
            assert not c.wait("HEARTBEAT").base_mode & 128
        # a command for vehicle 3 sent to vehicle 1 is ignored (no ACK, nothing happens)
        with pytest.raises(TimeoutError):
            clients[0].command_long(400, (1.0,), target_system=3, timeout_s=0.5)
        assert not clients[2].wait("HEARTBEAT").base_mode & 128
        assert [ap.armed for ap in fleet.autopilots] == [False, True, False]
        assert fleet.links[0].stats.rx_ignored >= 1


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
        alive_after = answers(c)
        # well-formed messages with hostile content
        mav = c.mav
        hostile = [
            mav.command_long_encode(1, 1, 400, 0, math.nan, math.nan, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 176, 0, math.inf, math.nan, -1e30, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 511, 0, math.nan, math.inf, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 512, 0, 1e30, 0, 0, 0, 0, 0, 0),
            mav.command_long_encode(1, 1, 22, 0, 0, 0, 0, 0, math.inf, -math.inf, 1e38),
            mav.command_int_encode(1, 1, 0, 400, 0, 0, 7.0, 0, 0, 0, 2**31 - 1, -(2**31), 0),
            mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0, *([math.nan] * 11)),
            mav.set_position_target_local_ned_encode(0, 1, 1, 99, 0, *([1.0] * 11)),
            mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0xFFFF, *([math.inf] * 11)),
            mav.set_mode_encode(1, 255, 0xFFFFFFFF),
            mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", math.nan, 9),
            mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", 1e30, 6),
            mav.param_request_read_encode(1, 1, b"\xff\xfe", 32767),
            mav.timesync_encode(0, -1),
        ]
        for m in hostile:
            c.send(m)
        # the vehicle still lives: it answers, it streams, and counted the rubbish
        assert alive_after and answers(c)
        assert c.command_long(400, (1.0,)) == ACCEPTED
        hb = c.wait("HEARTBEAT", lambda m: m.base_mode & 128, 5.0)
        assert hb.custom_mode == HOLD
        assert c.command_long(400, (0.0,)) == ACCEPTED
        assert fleet._thread is not None and fleet._thread.is_alive()
        st = fleet.links[0].stats
        assert st.rx_bad > 100 and st.setpoints == 0 and st.setpoints_malformed == 3
        assert fleet.autopilots[0].params.offboard_loss_timeout_s == 2.0  # NaN refused


def test_signing_required_refuses_unsigned_commands() -> None:
    spec = (SigningSpec(KEY.hex(), require=True, system_id=2),)
    with fleet_and_clients(2, signing=spec) as (fleet, (c1, c2)):
        ready(c1)
        ready(c2)
        # vehicle 2 signs its telemetry; vehicle 1 does not
        assert (
            fleet.links[1].mav.signing.sign_outgoing
            and not fleet.links[0].mav.signing.sign_outgoing
        )
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
        from sitl_mock.mavlink_io import signing_timestamp_now

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


def test_setup_signing_switches_signing_on() -> None:
    with fleet_and_clients() as (fleet, (c,)):
        ready(c)
        from sitl_mock.mavlink_io import signing_timestamp_now

        c.send(c.mav.setup_signing_encode(1, 1, list(KEY), signing_timestamp_now()))
        c.wait_until(lambda: fleet.links[0].signing is not None, 5.0)
        with pytest.raises(TimeoutError):
            c.command_long(400, (1.0,), timeout_s=0.6)
        c.mav.signing.secret_key = KEY
        c.mav.signing.sign_outgoing = True
        c.mav.signing.timestamp = signing_timestamp_now()
        assert c.command_long(400, (1.0,)) == ACCEPTED


def test_ground_truth_and_depth_over_zenoh() -> None:
    pytest.importorskip("zenoh")
    pytest.importorskip("onboard.mapping.simcam")  # the perception work's simulated D435
    from onboard.mapping.camera import check_frame
    from onboard.world import World
    from sitl_mock.truth import ZenohTruth, ZenohTruthSubscriber, simulated_d435

    port = bind_consecutive_udp(1)[0]
    tcp_port = port.getsockname()[1]  # a free UDP number is very likely a free TCP number too
    port.close()
    endpoint = f"tcp/127.0.0.1:{tcp_port}"
    world = World(np.zeros((0, 5)), np.zeros((0, 7)), np.array([[-5, 3.0, 0, 5, 4.0, 5]]), 0.0)
    pub = ZenohTruth("test/sim", [endpoint])
    sub = ZenohTruthSubscriber("test/sim", connect=[endpoint])
    cfg = FleetConfig(count=2, local_port_offset=None)
    fleet = Fleet(cfg, world, [pub], {1: simulated_d435(world, step=4)})
    try:
        deadline = time.monotonic() + 10.0
        while sub.pose(1) is None or sub.pose(2) is None:
            assert time.monotonic() < deadline, "no poses over Zenoh"
            for _ in range(10):
                fleet.tick()
            time.sleep(0.02)
        assert fleet._depth is not None and fleet._depth.render_once() == 1
        source = sub.depth_source(1)
        deadline = time.monotonic() + 10.0
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
    assert depth[240, 320] == pytest.approx(3.0 - frame.position[1], abs=0.01)
    position, rotation = sub.pose_provider(1)(frame.stamp_s)
    np.testing.assert_allclose(position, frame.position, atol=1e-9)
    np.testing.assert_allclose(rotation, frame.rotation, atol=1e-9)
