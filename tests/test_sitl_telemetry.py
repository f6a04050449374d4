"""What the mock sends, checked in simulated time (headless fleets, deterministic): the set of
streams and their rates against a real PX4 v1.16's, the frames byte for byte against pymavlink,
the two messages pymavlink lacks against their MAVLink definitions, the telemetry kernel
against the reference conversions, and HOME_POSITION's resets."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.generator import mavparse

from sitl_mock import dynamics as dyn
from sitl_mock import telemetry as tm
from sitl_mock.autopilot import AutopilotParams, Mode, Result
from sitl_mock.fleet import Fleet, FleetConfig
from sitl_mock.frames import (
    euler_zyx,
    geodetic_from_enu,
    quaternion_from_matrix,
    rotation_ned_frd,
)
from sitl_mock.px4_dialect import (
    MAVLink_link_node_status_message,
    MAVLink_protocol_version_message,
    MessageDecoder,
    mavlink,
    message_class,
    new_mavlink,
)

# What a real PX4 v1.16 (SITL, SIH quadrotor) sent on its API link while armed in Offboard
# (REFERENCE_NOTES section 5), Hz. Deliberately a copy: the mock's own table must match it.
OBSERVED_RATES_HZ = {
    "ATTITUDE": 100.0,
    "ATTITUDE_QUATERNION": 50.0,
    "HIGHRES_IMU": 50.0,
    "GLOBAL_POSITION_INT": 50.0,
    "LOCAL_POSITION_NED": 30.0,
    "ODOMETRY": 30.0,
    "TIMESYNC": 10.0,
    "ALTITUDE": 10.0,
    "DISTANCE_SENSOR": 10.0,
    "ATTITUDE_TARGET": 10.0,
    "POSITION_TARGET_LOCAL_NED": 10.0,
    "SERVO_OUTPUT_RAW": 10.0,
    "VFR_HUD": 10.0,
    "GPS_RAW_INT": 8.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "HEARTBEAT": 1.0,
    "MISSION_CURRENT": 1.0,
    "ESTIMATOR_STATUS": 1.0,
    "SYSTEM_TIME": 1.0,
    "PING": 1.0,
    "SCALED_PRESSURE": 1.0,
    "LINK_NODE_STATUS": 1.0,
    "BATTERY_STATUS": 0.5,
    "CURRENT_MODE": 0.5,
    "HOME_POSITION": 0.5,
    "VIBRATION": 0.5,
}
POS_ONLY = 8 | 16 | 32 | 64 | 128 | 256 | 2048
MAV = mavlink.MAVLink(None, 245, 190)


def make_fleet(**ap: Any) -> Fleet:
    cfg = FleetConfig(
        count=1, local_port_offset=None, autopilot=AutopilotParams(boot_time_s=0.5, **ap)
    )
    return Fleet(cfg)


def fly(f: Fleet, seconds: float, target: tuple[float, float, float] | None) -> None:
    """Tick ``seconds`` of simulated time, sending position setpoints at 20 Hz if ``target``."""
    every = int(round(0.05 / f.dt_s))
    for k in range(int(round(seconds / f.dt_s))):
        if target is not None and k % every == 0:
            f.links[0].handle(
                MAV.set_position_target_local_ned_encode(
                    0, 1, 1, 1, POS_ONLY, *target, 0, 0, 0, 0, 0, 0, 0, 0
                )
            )
        f.tick()


class Tap:
    """Decodes every frame a link emits (its socket need not exist), or only those of the
    message ids in ``only``."""

    def __init__(self, only: tuple[int, ...] = ()) -> None:
        self.mav = new_mavlink(245, 190)
        self.only = set(only)
        self.frames: list[bytes] = []
        self.msgs: list[Any] = []

    def __call__(self, buf: bytes) -> None:
        if self.only and buf[7] | (buf[8] << 8) | (buf[9] << 16) not in self.only:
            return
        self.frames.append(buf)
        self.mav.buf = bytearray()
        self.mav.buf_index = 0
        self.mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        got = self.mav.parse_buffer(buf)
        assert got is not None and len(got) == 1, buf
        assert got[0].get_type() != "BAD_DATA", got[0]
        self.msgs.append(got[0])

    def of(self, kind: str) -> list[Any]:
        return [m for m in self.msgs if m.get_type() == kind]


def test_stream_set_and_rates_match_a_real_px4() -> None:
    f = make_fleet()
    ap = f.autopilots[0]
    fly(f, 0.6, None)
    fly(f, 0.05, (0.0, 0.0, -2.0))
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    fly(f, 4.0, (0.0, 0.0, -2.0))
    assert not ap.landed and ap.mode is Mode.OFFBOARD
    before = Counter(f.links[0].stats.tx_by_message)
    window_s = 40.0
    fly(f, window_s, (0.0, 0.0, -2.0))
    sent = Counter(f.links[0].stats.tx_by_message) - before
    assert set(sent) == set(OBSERVED_RATES_HZ)  # every stream PX4 sends, and nothing else
    for name, px4_hz in OBSERVED_RATES_HZ.items():
        hz = sent[name] / window_s
        assert hz == pytest.approx(px4_hz, rel=0.10), name
    total = sum(sent.values()) / window_s
    assert total == pytest.approx(sum(OBSERVED_RATES_HZ.values()), rel=0.05)  # ~400 / s


def test_frames_are_what_pymavlink_packs_and_decode() -> None:
    """Every frame the fast framer built decodes with pymavlink, and re-packing the decoded
    message with pymavlink gives the same bytes (headers, trimmed payloads, CRCs)."""
    f = make_fleet()
    tap = Tap()
    f.links[0].tap = tap
    f.links[0].gcs_seen = True  # status texts too
    fly(f, 0.6, None)
    fly(f, 0.05, (0.0, 0.0, -2.0))
    f.links[0].handle(MAV.command_long_encode(1, 1, 176, 0, 1, 6, 0, 0, 0, 0, 0))
    f.links[0].handle(MAV.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    f.links[0].handle(MAV.command_long_encode(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0))
    f.links[0].handle(MAV.command_long_encode(1, 1, 519, 0, 0, 0, 0, 0, 0, 0, 0))
    f.links[0].handle(MAV.param_request_list_encode(1, 1))
    f.links[0].handle(MAV.param_set_encode(1, 1, b"COM_OBL_RC_ACT", 1e-45, 6))  # code 1: ok
    f.links[0].handle(MAV.param_set_encode(1, 1, b"COM_OBL_RC_ACT", 3e-45, 6))  # code 2: error
    f.links[0].handle(  # a long status text: chunked
        MAV.set_position_target_local_ned_encode(0, 1, 1, 9, POS_ONLY, *([0.0] * 11))
    )
    fly(f, 3.0, (0.0, 0.0, -2.0))
    kinds = Counter(m.get_type() for m in tap.msgs)
    for extra in ("COMMAND_ACK", "STATUSTEXT", "PARAM_VALUE", "PARAM_ERROR"):
        assert kinds[extra] > 0, extra
    assert kinds["AUTOPILOT_VERSION"] == 1 and kinds["PROTOCOL_VERSION"] == 1
    assert set(OBSERVED_RATES_HZ) <= set(kinds)
    ref = new_mavlink(1, 1)
    for buf, m in zip(tap.frames, tap.msgs, strict=True):
        ref.seq = buf[4]
        assert bytes(m.pack(ref)) == buf, m.get_type()
    chunks = [m for m in tap.of("STATUSTEXT") if m.id != 0]
    text = "".join(m.text for m in chunks)
    assert text == "SET_POSITION_TARGET_LOCAL_NED coordinate frame 9 unsupported"
    assert [m.chunk_seq for m in chunks] == [0, 1]


def test_field_values_are_consistent() -> None:
    f = make_fleet()
    tap = Tap()
    f.links[0].tap = tap
    fly(f, 0.6, None)
    fly(f, 0.05, (1.0, 2.0, -3.0))
    f.autopilots[0].command_set_mode(f.t_s, Mode.OFFBOARD)
    f.autopilots[0].command_arm(f.t_s, True)
    fly(f, 10.0, (1.0, 2.0, -3.0))
    last = {m.get_type(): m for m in tap.msgs}
    lpn = last["LOCAL_POSITION_NED"]
    assert (lpn.x, lpn.y, lpn.z) == pytest.approx((1.0, 2.0, -3.0), abs=0.1)
    gpi = last["GLOBAL_POSITION_INT"]
    assert gpi.relative_alt == pytest.approx(3000, abs=120)
    assert gpi.alt - last["HOME_POSITION"].altitude == pytest.approx(3000, abs=120)
    alt = last["ALTITUDE"]
    assert alt.altitude_relative == pytest.approx(3.0, abs=0.1)
    assert alt.bottom_clearance == pytest.approx(3.0, abs=0.1)
    assert last["DISTANCE_SENSOR"].current_distance == pytest.approx(300, abs=10)
    att, odo = last["ATTITUDE"], last["ODOMETRY"]
    w, x, y, z = odo.q
    yaw_q = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    assert att.yaw == pytest.approx(yaw_q, abs=0.02)
    assert att.yaw == pytest.approx(0.0, abs=0.05)  # spawned facing north
    hb = last["HEARTBEAT"]
    assert (hb.custom_mode, hb.base_mode, hb.system_status) == (0x60000, 145, 4)
    assert last["EXTENDED_SYS_STATE"].landed_state == 2
    assert last["SERVO_OUTPUT_RAW"].servo1_raw == pytest.approx(1500, abs=60)  # hover thrust
    gps = last["GPS_RAW_INT"]
    assert (gps.fix_type, gps.lat) == (3, pytest.approx(gpi.lat, abs=20))
    assert last["MISSION_CURRENT"].mission_state == mavlink.MISSION_STATE_NO_MISSION
    assert last["LINK_NODE_STATUS"].messages_sent > 0
    assert last["SCALED_PRESSURE"].press_abs == pytest.approx(955.0, abs=5.0)  # ~490 m AMSL


def test_home_position_reset_at_arming_and_after_takeoff() -> None:
    """HOME_POSITION every ~2 s; PX4 sets home at arming and again just after takeoff: a
    vehicle landed 3 m north of its first home and armed again reports home there."""
    f = make_fleet()
    ap = f.autopilots[0]
    tap = Tap(only=(mavlink.MAVLINK_MSG_ID_HOME_POSITION,))
    f.links[0].tap = tap
    fly(f, 5.0, None)
    homes = tap.of("HOME_POSITION")
    assert len(homes) == 3  # t = 0, 2, 4 s
    assert {(h.x, h.y, h.z) for h in homes} == {(0.0, 0.0, 0.0)}
    fly(f, 0.05, (3.0, 0.0, -2.0))
    ap.command_set_mode(f.t_s, Mode.OFFBOARD)
    ap.command_arm(f.t_s, True)
    assert ap.home_updates == 1
    fly(f, 1.2, (3.0, 0.0, -2.0))
    assert ap.home_updates == 2  # just after takeoff
    fly(f, 8.0, (3.0, 0.0, -2.0))
    assert ap.command_land(f.t_s) == Result.ACCEPTED
    fly(f, 8.0, None)
    assert not ap.armed and ap.landed
    assert ap.command_set_mode(f.t_s, Mode.HOLD) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    tap.msgs.clear()
    fly(f, 2.5, None)
    h = tap.of("HOME_POSITION")[-1]
    assert (h.x, h.y, h.z) == pytest.approx((3.0, 0.0, 0.0), abs=0.1)


def test_telemetry_kernel_matches_the_reference_conversions() -> None:
    rng = np.random.default_rng(3)
    n = 6
    state = dyn.initial_state(rng.normal(0, 20, (n, 3)), rng.uniform(-np.pi, np.pi, n))
    state[:, dyn.S_F : dyn.S_F + 3] = rng.normal(0, 3, (n, 3)) + [0, 0, 9.8]
    state[:, dyn.S_V : dyn.S_V + 3] = rng.normal(0, 2, (n, 3))
    state[:, dyn.S_E : dyn.S_E + 3] = rng.normal(0, 0.05, (n, 3))
    prm = dyn.DynamicsParams().as_array()
    att = np.zeros((n, dyn.NA))
    dyn.attitude_fleet(state, prm, np.zeros((n, 9)), 0.0, att)
    origin = rng.normal(0, 5, (n, 3))
    ground = rng.normal(0, 1, n)
    geo = np.array([47.397742, 8.545594, 488.0])
    out = np.zeros((n, tm.NT))
    tm.telemetry_fleet(state, att, origin, ground, geo, out)
    for i in range(n):
        est = state[i, dyn.S_P : dyn.S_P + 3] + state[i, dyn.S_E : dyn.S_E + 3]
        d = est - origin[i]
        np.testing.assert_allclose(out[i, tm.T_PN : tm.T_PN + 3], [d[1], d[0], -d[2]])
        r = rotation_ned_frd(att[i, dyn.A_R : dyn.A_R + 9].reshape(3, 3))
        np.testing.assert_allclose(out[i, tm.T_ROLL : tm.T_YAW + 1], euler_zyx(r), atol=1e-12)
        np.testing.assert_allclose(
            out[i, tm.T_Q : tm.T_Q + 4], quaternion_from_matrix(r), atol=1e-12
        )
        v = state[i, dyn.S_V : dyn.S_V + 3]
        v_ned = np.array([v[1], v[0], -v[2]])
        np.testing.assert_allclose(out[i, tm.T_VB : tm.T_VB + 3], r.T @ v_ned, atol=1e-12)
        lat, lon, alt = geodetic_from_enu(est, *geo)
        np.testing.assert_allclose(
            out[i, tm.T_LAT : tm.T_ALT + 1], [lat, lon, alt], rtol=0, atol=1e-9
        )
        assert out[i, tm.T_HAG] == pytest.approx(est[2] - ground[i])


_EXTRA_XML = """<?xml version="1.0"?>
<mavlink>
  <version>3</version>
  <dialect>0</dialect>
  <messages>
    <message id="8" name="LINK_NODE_STATUS">
      <description>Link status</description>
      <field type="uint64_t" name="timestamp" units="ms">t</field>
      <field type="uint8_t" name="tx_buf" units="%">t</field>
      <field type="uint8_t" name="rx_buf" units="%">t</field>
      <field type="uint32_t" name="tx_rate" units="bytes/s">t</field>
      <field type="uint32_t" name="rx_rate" units="bytes/s">t</field>
      <field type="uint16_t" name="rx_parse_err" units="bytes">t</field>
      <field type="uint16_t" name="tx_overflows" units="bytes">t</field>
      <field type="uint16_t" name="rx_overflows" units="bytes">t</field>
      <field type="uint32_t" name="messages_sent">t</field>
      <field type="uint32_t" name="messages_received">t</field>
      <field type="uint32_t" name="messages_lost">t</field>
    </message>
    <message id="300" name="PROTOCOL_VERSION">
      <description>Protocol version</description>
      <field type="uint16_t" name="version">t</field>
      <field type="uint16_t" name="min_version">t</field>
      <field type="uint16_t" name="max_version">t</field>
      <field type="uint8_t[8]" name="spec_version_hash">t</field>
      <field type="uint8_t[8]" name="library_version_hash">t</field>
    </message>
  </messages>
</mavlink>
"""


def test_messages_pymavlink_lacks_match_their_definitions(tmp_path: Path) -> None:
    """CRC extra and wire order of PROTOCOL_VERSION / LINK_NODE_STATUS as pymavlink's own
    generator derives them from the MAVLink definitions; both round-trip through pymavlink."""
    xml = tmp_path / "extra.xml"
    xml.write_text(_EXTRA_XML)
    parsed = {m.name: m for m in mavparse.MAVXML(str(xml), mavparse.PROTOCOL_2_0).message}
    for cls in (MAVLink_link_node_status_message, MAVLink_protocol_version_message):
        ref = parsed[cls.msgname]
        assert cls.id == ref.id and cls.crc_extra == ref.crc_extra, cls.msgname
        assert cls.fieldnames == ref.fieldnames
        assert cls.ordered_fieldnames == ref.ordered_fieldnames
    assert (
        MAVLink_link_node_status_message.crc_extra,
        MAVLink_protocol_version_message.crc_extra,
    ) == (
        117,
        217,
    )  # the C library's MAVLINK_MSG_ID_*_CRC
    tx, rx = new_mavlink(1, 1), new_mavlink(2, 2)
    msgs: list[Any] = [
        MAVLink_link_node_status_message(123, 90, 80, 1000, 2000, 3, 4, 5, 600, 700, 8),
        MAVLink_protocol_version_message(200, 100, 200, list(range(8)), list(range(8, 16))),
    ]
    for m in msgs:
        got = rx.parse_char(m.pack(tx))
        assert got.get_type() == m.msgname
        assert got.to_dict() == m.to_dict()


def test_fast_setpoint_decoder_matches_pymavlink() -> None:
    dec = MessageDecoder(message_class(mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED))
    rng = np.random.default_rng(9)
    tx = new_mavlink(77, 191)
    for k in range(200):
        vals = rng.normal(0, 10, 11)
        vals[rng.random(11) < 0.3] = 0.0  # zeros at the end are trimmed on the wire
        msg = tx.set_position_target_local_ned_encode(
            int(rng.integers(0, 2**32)),
            k % 3,
            1,
            int(rng.integers(0, 13)),
            int(rng.integers(0, 4096)),
            *vals,
        )
        buf = bytes(msg.pack(tx))
        tx.seq = (tx.seq + 1) % 256
        ref = new_mavlink(1, 1).parse_buffer(buf)[0]
        got = dec.decode(buf)
        assert got is not None and got.to_dict() == ref.to_dict()
        assert (got.get_srcSystem(), got.get_srcComponent(), got.get_seq()) == (77, 191, k % 256)
    good = bytes(tx.set_position_target_local_ned_encode(0, 1, 1, 1, 0, *([1.0] * 11)).pack(tx))
    bad_crc = good[:-1] + bytes([good[-1] ^ 1])
    other = bytes(tx.heartbeat_encode(6, 8, 0, 0, 0, 3).pack(tx))
    signer = new_mavlink(1, 1)
    signer.signing.secret_key = bytes(32)
    signer.signing.sign_outgoing = True
    signed = bytes(
        signer.set_position_target_local_ned_encode(0, 1, 1, 1, 0, *([1.0] * 11)).pack(signer)
    )
    for junk in (b"", good[:-1], good + good, bad_crc, other, signed, b"\xfe" + good[1:]):
        assert dec.decode(junk) is None
