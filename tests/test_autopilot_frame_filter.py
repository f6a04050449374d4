"""The pymavlink link skips, undecoded, the frames of message types it does not use: what it
keeps decodes exactly as the wanted frames of the whole datagram would, and whatever does not
look like a whole frame still reaches the decoder (which counts it as bad data)."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot.pymavlink_link import select_frames

WANTED = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED})


def _frames(kinds: list[int], signed: bool = False, v1: bool = False) -> list[bytes]:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    if v1:
        mav.WIRE_PROTOCOL_VERSION = "1.0"
    if signed:
        mav.signing.secret_key = bytes(range(32))
        mav.signing.sign_outgoing = True
    out = []
    for i, k in enumerate(kinds):
        if k == 0:
            m = mav.heartbeat_encode(2, 12, 0, 0, 4)
        elif k == 1:
            m = mav.local_position_ned_encode(i, 1.0 * i, 2.0, -3.0, 0.1, 0.2, 0.3)
        elif k == 2:
            m = mav.attitude_encode(i, 0.1, 0.2, 0.3 * i, 0.0, 0.0, 0.0)
        else:
            m = mav.highres_imu_encode(i, *([0.5] * 13), 7, 0)
        out.append(m.pack(mav))
    return out


def _decode(data: bytes) -> list[tuple[str, tuple[object, ...]]]:
    p = mavlink.MAVLink(None)
    p.robust_parsing = True
    return [(m.get_type(), tuple(m.to_dict().items())) for m in (p.parse_buffer(data) or [])]


@settings(max_examples=100, deadline=None)
@given(
    kinds=st.lists(st.integers(0, 3), min_size=0, max_size=10),
    signed=st.booleans(),
    v1=st.booleans(),
    tail=st.binary(max_size=20),
)
def test_the_kept_frames_decode_as_the_wanted_ones_of_the_whole_datagram(
    kinds: list[int], signed: bool, v1: bool, tail: bytes
) -> None:
    frames = _frames(kinds, signed=signed and not v1, v1=v1)
    data = b"".join(frames)
    kept, left_out = select_frames(data, WANTED)
    unwanted = [f for f, k in zip(frames, kinds, strict=True) if k >= 2]
    assert left_out == len(unwanted)
    assert kept == b"".join(f for f, k in zip(frames, kinds, strict=True) if k < 2)
    whole = _decode(data)
    assert len(whole) == len(frames)
    assert _decode(kept) == [m for m in whole if m[0] in ("HEARTBEAT", "LOCAL_POSITION_NED")]
    # bytes after the frames: the frames are filtered as before, and the tail is passed on
    # (less any whole unwanted-looking frame in it), never anything else
    kept_t, left_out_t = select_frames(data + tail, WANTED)
    assert kept_t.startswith(kept) and left_out_t >= left_out
    assert len(kept_t) - len(kept) <= len(tail)
    if not tail or tail[0] not in (0xFD, 0xFE):
        assert kept_t == kept + tail and left_out_t == left_out


def test_garbage_and_cut_frames_reach_the_decoder_unchanged() -> None:
    hb, att = _frames([0, 2])
    assert select_frames(b"\x00\x01garbage" + att, WANTED) == (b"\x00\x01garbage" + att, 0)
    cut = att + hb[:-3]  # the last frame cut short: kept for the decoder to reject
    kept, left_out = select_frames(cut, WANTED)
    assert (kept, left_out) == (hb[:-3], 1)
    only_unwanted = att + att
    assert select_frames(only_unwanted, WANTED) == (b"", 2)
    assert select_frames(hb, WANTED) == (hb, 0)
