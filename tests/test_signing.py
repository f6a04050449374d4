"""MAVLink 2 signing between the pymavlink link and the SITL mock (its signing option imitates
PX4 v1.17+; v1.16 has none), over real UDP on loopback.

- signed link + signing mock: commands acknowledged, telemetry verified, nothing refused;
- unsigned link + signing mock: the mock refuses every command (counted on its side);
- link requiring signing + non-signing mock (PX4 v1.16): refuses to connect, says which PX4
  versions sign; with another key: says the signatures do not verify;
- the key file: 0600 checked at load, never in repr, logs or errors; MAVSDK refused.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import CommandError, CommandResult, LinkConfig, LinkError, open_link
from onboard.autopilot.link import AutopilotLink
from onboard.autopilot.pymavlink_link import PymavlinkLink
from onboard.autopilot.signing import Verifier, load_signing_key, signing_timestamp_now
from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig, SigningSpec

KEY_HEX = "5a" * 16 + "c3" * 16
OTHER_HEX = "11" * 32


def key_file(tmp: Path, hex_key: str = KEY_HEX, mode: int = 0o600, name: str = "k") -> str:
    p = tmp / name
    p.write_text(hex_key + "\n")
    os.chmod(p, mode)
    return str(p)


def poll(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


@contextmanager
def mock_and_link(
    mock_key: str | None, connect_timeout_s: float = 3.0, **link_kw: Any
) -> Iterator[tuple[Fleet, AutopilotLink]]:
    """A one-vehicle mock (signing with ``mock_key`` when given, required) and a pymavlink
    link to it (not connected yet)."""
    vehicle_side, link_sock = bind_consecutive_udp(2)
    port = vehicle_side.getsockname()[1]
    link_port = link_sock.getsockname()[1]
    vehicle_side.close()
    link_sock.close()
    cfg = FleetConfig(
        count=1,
        base_port=port,
        local_port_offset=link_port - port,
        speedup=2.0,
        autopilot=AutopilotParams(boot_time_s=0.3),
        signing=(SigningSpec(mock_key, require=True),) if mock_key else (),
    )
    fleet = Fleet(cfg)
    link: AutopilotLink | None = None
    try:
        link = open_link(
            LinkConfig(
                url=f"udpin://127.0.0.1:{port}",
                connect_timeout_s=connect_timeout_s,
                ack_timeout_s=0.2,
                max_transmissions=2,
                **link_kw,
            )
        )
        fleet.start()
        yield fleet, link
    finally:
        if link is not None:
            link.close()
        fleet.stop()


def mock_stats(fleet: Fleet) -> Any:
    return fleet.links[0].stats


@pytest.mark.timeout(60)
def test_signed_link_with_signing_autopilot(tmp_path: Path) -> None:
    with mock_and_link(KEY_HEX, signing_key_file=key_file(tmp_path)) as (fleet, link):
        link.connect()
        assert set(link.telemetry_rate_results.values()) == {CommandResult.ACCEPTED}
        link.wait_healthy(20.0)
        link.arm()
        poll(lambda: link.state().armed, 5.0, "armed")
        link.disarm()
        c = link.counters()
        assert c.unsigned_rejected == 0 and c.bad_signatures == 0 and c.unsigned_accepted == 0
        assert c.messages_received > 50
        st = mock_stats(fleet)
        assert st.rx_rejected_unsigned == 0 and st.commands >= 4


@pytest.mark.timeout(60)
def test_signing_autopilot_refuses_an_unsigned_link() -> None:
    with mock_and_link(KEY_HEX) as (fleet, link):
        link.connect()  # its telemetry is signed; a link without a key reads it unverified
        assert set(link.telemetry_rate_results.values()) == {CommandResult.TIMEOUT}
        with pytest.raises(CommandError) as e:
            link.arm()
        assert e.value.result == CommandResult.TIMEOUT
        assert not link.state().armed
        assert mock_stats(fleet).rx_rejected_unsigned >= 6
        assert mock_stats(fleet).commands == 0


@pytest.mark.timeout(60)
def test_signing_required_against_px4_v1_16_refuses_to_start(tmp_path: Path) -> None:
    with mock_and_link(None, 1.5, signing_key_file=key_file(tmp_path)) as (fleet, link):
        with pytest.raises(LinkError, match=r"sends unsigned MAVLink .*PX4 v1\.17") as e:
            link.connect()
        assert "PX4 v1.16" in str(e.value)
        assert link.counters().unsigned_rejected > 0
        assert link.counters().messages_received == 0


@pytest.mark.timeout(60)
def test_signing_with_another_key_refuses_to_start(tmp_path: Path) -> None:
    with mock_and_link(OTHER_HEX, 1.5, signing_key_file=key_file(tmp_path)) as (fleet, link):
        with pytest.raises(LinkError, match="did not verify: another key"):
            link.connect()
        assert link.counters().bad_signatures > 0
        assert mock_stats(fleet).commands == 0


@pytest.mark.timeout(60)
def test_signing_not_required_accepts_unsigned_telemetry_counted(tmp_path: Path) -> None:
    kf = key_file(tmp_path)
    with mock_and_link(None, signing_key_file=kf, signing_required=False) as (fleet, link):
        link.connect()
        assert link.counters().unsigned_accepted > 0
        assert link.counters().unsigned_rejected == 0


def signed_frame(key: bytes, src: int = 1, stamp: int | None = None) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=src, srcComponent=1)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 0
    mav.signing.timestamp = signing_timestamp_now() if stamp is None else stamp
    return bytes(mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav))


def test_forged_and_replayed_frames_are_counted_not_accepted(tmp_path: Path) -> None:
    key = bytes.fromhex(KEY_HEX)
    link = PymavlinkLink(LinkConfig(signing_key_file=key_file(tmp_path)))
    good = signed_frame(key)
    link._on_chunk(good, ("127.0.0.1", 1), True)
    assert link.counters().heartbeats_received == 1
    link._on_chunk(good, ("127.0.0.1", 1), True)  # replayed
    link._on_chunk(signed_frame(bytes.fromhex(OTHER_HEX)), ("127.0.0.1", 1), True)
    unsigned = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    link._on_chunk(bytes(unsigned.heartbeat_encode(2, 12, 0, 0, 4).pack(unsigned)), None, True)
    c = link.counters()
    assert c.heartbeats_received == 1
    assert c.bad_signatures == 2 and c.unsigned_rejected == 1 and c.decode_errors == 0
    # a forged frame does not advance the stream: the next genuine frame still passes
    v = Verifier(key)
    t = signing_timestamp_now()
    assert not v.verify(signed_frame(bytes.fromhex(OTHER_HEX), stamp=t + 10**9), 1, 1)
    assert v.verify(signed_frame(key, stamp=t), 1, 1)


def test_key_file_checked_at_load_and_never_shown(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    loose = key_file(tmp_path, mode=0o644, name="loose")
    with pytest.raises(ValueError, match=r"signing_key_file: .* permissions 0644.*chmod 600"):
        LinkConfig(signing_key_file=loose)
    with pytest.raises(ValueError, match="signing_key_file: cannot open"):
        LinkConfig(signing_key_file=str(tmp_path / "missing"))
    short = key_file(tmp_path, hex_key="abcd", name="short")
    with pytest.raises(ValueError, match="32 raw bytes or 64 hexadecimal") as e:
        LinkConfig(signing_key_file=short)
    assert "abcd" not in str(e.value)
    with pytest.raises(ValueError, match="signing_key_file: the mavsdk implementation cannot"):
        LinkConfig(implementation="mavsdk", signing_key_file=key_file(tmp_path, name="m"))
    with pytest.raises(ValueError, match="signing_required: needs signing_key_file"):
        LinkConfig(signing_required=True)
    raw = tmp_path / "raw"
    raw.write_bytes(bytes.fromhex(KEY_HEX))
    os.chmod(raw, 0o600)
    assert load_signing_key(str(raw)) == bytes.fromhex(KEY_HEX)
    cfg = LinkConfig(signing_key_file=key_file(tmp_path))
    assert cfg.requires_signing
    caplog.set_level(logging.DEBUG)
    link = PymavlinkLink(cfg)
    shown = repr(cfg) + repr(link) + str(link.counters()) + str(vars(cfg))
    shown += caplog.text
    for secret in (KEY_HEX, KEY_HEX[:16], bytes.fromhex(KEY_HEX).hex()):
        assert secret not in shown
    assert "Verifier(newest" in repr(link._parser.check_signature.__self__)
    assert str(bytes.fromhex(KEY_HEX)) not in repr(link._parser.check_signature.__self__)
