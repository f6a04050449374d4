"""The mock's depth-frame and pose codecs (onboard.sensors.zenoh_depth): round trips, one test per
rejection reason, fuzzing, and the subscriber over a real Zenoh session on loopback."""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onboard.comm.zenoh_session import ZenohEndpoints, free_loopback_endpoint, open_session
from onboard.mapping.camera import look_rotation
from onboard.sensors.mount import CAMERA_OFFSET_BODY_M, R_BODY_CAM, camera_pose
from onboard.sensors.zenoh_depth import (
    REJECT_REASONS,
    CodecLimits,
    DecodeError,
    DepthImage,
    TruthDepthSource,
    TruthSample,
    ZenohTruthSubscriber,
    open_depth_source,
)
from sitl_mock.frames import matrix_from_quaternion

INTR = {"width": 8.0, "height": 6.0, "fx": 7.0, "fy": 7.0, "cx": 4.0, "cy": 3.0,
        "min_depth_m": 0.2, "max_depth_m": 5.0}  # fmt: skip


def _image(stamp: float = 1.5, sid: int = 2) -> DepthImage:
    depth = np.linspace(0.0, 6.0, 48, dtype=np.float32).reshape(6, 8)
    return DepthImage(sid, stamp, depth, np.array([1.0, 2.0, 1.1]), look_rotation(0.3), INTR)


def _frame(
    header: dict[str, Any], body: bytes | None = None, patch: tuple[bytes, bytes] = (b"", b"")
) -> bytes:
    """A frame with this header (its JSON text patched: ``old -> new``) and an image of zeros."""
    raw = json.dumps(header).encode().replace(*patch) if patch[0] else json.dumps(header).encode()
    if body is None:
        body = b"\0\0" * (header["shape"][0] * header["shape"][1])
    return b"DPT1" + struct.pack("<I", len(raw)) + raw + body


def _header(**changes: Any) -> dict[str, Any]:
    """The JSON header of ``_image()``, with changes."""
    good = _image().to_bytes()
    (n,) = struct.unpack("<I", good[4:8])
    h: dict[str, Any] = json.loads(good[8 : 8 + n])
    h.update(changes)
    return h


def _pose(**changes: Any) -> bytes:
    d = json.loads(_sample().to_bytes())
    d.update(changes)
    return json.dumps(d).encode()


def _sample(sid: int = 2, t: float = 3.0) -> TruthSample:
    q = (math.cos(0.2), 0.0, 0.0, math.sin(0.2))
    return TruthSample(sid, t, (1.0, 2.0, 3.0), (0.1, 0.0, 0.0), q, 0.4, True, False, "OFFB", 0)


def _reason(data: bytes, decode: Callable[[bytes], Any] = DepthImage.from_bytes) -> str:
    with pytest.raises(DecodeError) as e:
        decode(data)
    return e.value.reason


def test_depth_round_trip() -> None:
    img = _image()
    back = DepthImage.from_bytes(img.to_bytes())
    assert back.system_id == 2 and back.stamp_s == 1.5 and back.depth_m.dtype == np.float32
    np.testing.assert_allclose(back.depth_m, img.depth_m, atol=5e-4)
    np.testing.assert_array_equal(back.position, img.position)
    np.testing.assert_allclose(back.rotation, img.rotation, atol=1e-15)
    assert back.intrinsics == INTR
    frame = back.to_depth_frame()
    assert frame.intrinsics.shape == (6, 8) and frame.stamp_s == 1.5
    with pytest.raises(ValueError):  # the encoder refuses what the decoder would
        DepthImage(2, math.nan, img.depth_m, img.position, img.rotation, INTR).to_bytes()


def test_every_depth_rejection_reason() -> None:
    good = _image().to_bytes()
    small = CodecLimits(max_width=8, max_height=6, max_header_bytes=600)
    found: dict[str, str] = {}
    cases: dict[str, bytes] = {
        "empty": b"",
        "short": good[:7],
        "cut header": good[:40],
        "cut image": good[:-1],
        "trailing byte": good + b"\0",
        "magic": b"DPT2" + good[4:],
        "encoding": _frame(_header(encoding="z32_float")),
        "NaN literal": _frame(_header(), patch=(b'"stamp_s": 1.5', b'"stamp_s": NaN')),
        "huge number": _frame(_header(), patch=(b'"stamp_s": 1.5', b'"stamp_s": 1e999')),
        "huge int": _frame(_header(stamp_s=10**400)),
        "header length": good[:4] + struct.pack("<I", 10**6) + good[8:],
        "image size": _frame(_header(shape=[7, 8], intrinsics={**INTR, "height": 7.0})),
        "shape vs intrinsics": _frame(_header(intrinsics={**INTR, "width": 9.0})),
        "not json": b"DPT1" + struct.pack("<I", 3) + b"{{{" + b"\0" * 96,
        "missing key": _frame({k: v for k, v in _header().items() if k != "position"}),
        "unknown key": _frame(_header(extra=1)),
        "not a rotation": _frame(_header(rotation=[1, 0, 0, 0, 1, 0, 0, 0, -1])),
        "bool id": _frame(_header(system_id=True)),
        "negative fx": _frame(_header(intrinsics={**INTR, "fx": -1.0})),
        "depth range": _frame(_header(intrinsics={**INTR, "min_depth_m": 6.0})),
        "fractional width": _frame(_header(intrinsics={**INTR, "width": 8.5})),
        "shape type": _frame(_header(shape="6x8"), body=b""),
        "position length": _frame(_header(position=[1.0, 2.0])),
    }
    for name, data in cases.items():
        with pytest.raises(DecodeError) as e:
            DepthImage.from_bytes(data, small if name == "image size" else CodecLimits())
        found[name] = e.value.reason
    assert found == {
        "empty": "truncated",
        "short": "truncated",
        "cut header": "truncated",
        "cut image": "truncated",
        "trailing byte": "wrong-size",
        "magic": "wrong-version",
        "encoding": "wrong-version",
        "NaN literal": "non-finite",
        "huge number": "non-finite",
        "huge int": "non-finite",
        "header length": "oversized",
        "image size": "oversized",
        "shape vs intrinsics": "wrong-size",
        "not json": "malformed",
        "missing key": "malformed",
        "unknown key": "malformed",
        "not a rotation": "malformed",
        "bool id": "malformed",
        "negative fx": "malformed",
        "depth range": "malformed",
        "fractional width": "malformed",
        "shape type": "malformed",
        "position length": "malformed",
    }
    assert _reason(b"x" * (CodecLimits().max_frame_bytes + 1)) == "oversized"
    assert set(found.values()) == set(REJECT_REASONS) - {"wrong-sender"}


def test_pose_round_trip_and_rejections() -> None:
    s = _sample()
    assert TruthSample.from_bytes(s.to_bytes()) == s

    def pose(data: bytes) -> Any:
        return TruthSample.from_bytes(data)

    assert _reason(b"{" * 3000, pose) == "oversized"
    assert _reason(b"[1, 2", pose) == "malformed"
    assert _reason(b"[1, 2]", pose) == "malformed"
    assert _reason(_pose(t_s=float("inf")), pose) == "non-finite"
    assert _reason(_pose(quaternion_enu_flu=[1, 1, 0, 0]), pose) == "malformed"
    assert _reason(_pose(armed=1), pose) == "malformed"
    assert _reason(_pose(collisions=-1), pose) == "malformed"
    assert _reason(_pose(mode="x" * 65), pose) == "malformed"
    assert _reason(_pose(extra=0), pose) == "malformed"
    assert _reason(b"\xff\xfe", pose) == "malformed"  # not UTF-8


def test_camera_mount() -> None:
    """The camera looks along the body's x axis, 10 cm ahead; same as the mock's old formula."""
    q = (math.cos(0.35), 0.1, -0.05, math.sin(0.35))
    q = tuple(np.array(q) / np.linalg.norm(q))
    pos, rot = camera_pose((1.0, 2.0, 3.0), q)
    r_wb = matrix_from_quaternion(q)
    np.testing.assert_allclose(pos, np.array([1.0, 2.0, 3.0]) + r_wb @ CAMERA_OFFSET_BODY_M)
    np.testing.assert_allclose(rot, r_wb @ R_BODY_CAM)
    level = camera_pose((0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))[1]
    np.testing.assert_allclose(level, look_rotation(0.0), atol=1e-12)  # optical z = east
    with pytest.raises(ValueError):
        R_BODY_CAM[0, 0] = 1.0  # read-only


FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_GOOD = _image().to_bytes()


@FUZZ
@given(st.binary(max_size=400))
def test_fuzz_random_bytes_only_raise_decode_errors(data: bytes) -> None:
    for decode in (DepthImage.from_bytes, TruthSample.from_bytes):
        try:
            decode(data)
        except DecodeError as e:
            assert e.reason in REJECT_REASONS


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(_GOOD) - 1), st.integers(0, 255)), max_size=6),
       st.integers(0, len(_GOOD)))  # fmt: skip
def test_fuzz_mutated_frames_only_raise_decode_errors(
    edits: list[tuple[int, int]], cut: int
) -> None:
    data = bytearray(_GOOD)
    for i, b in edits:
        data[i] = b
    data = data[: max(cut, 0)] if cut < len(_GOOD) // 2 else data
    try:
        img = DepthImage.from_bytes(bytes(data))
    except DecodeError as e:
        assert e.reason in REJECT_REASONS
    else:
        assert np.all(np.isfinite(img.depth_m)) and np.all(np.isfinite(img.position))
        assert np.allclose(img.rotation.T @ img.rotation, np.eye(3), atol=1e-4)


def test_depth_source_reads_each_frame_once() -> None:
    holder: list[DepthImage | None] = [None]
    closed: list[bool] = []
    src = TruthDepthSource(lambda _after: holder[0], on_close=lambda: closed.append(True))
    assert src.read() is None and src.intrinsics.width == 640  # D435 before any frame
    assert src.newest_stamp_s() is None  # a source not told of arrivals cannot tell
    holder[0] = _image(stamp=2.0)
    f = src.read()
    assert f is not None and f.stamp_s == 2.0 and src.read() is None
    assert src.intrinsics.width == 8
    holder[0] = _image(stamp=1.0)  # older: not new
    assert src.read() is None
    src.close()
    src.close()
    assert closed == [True]


def _wait(cond: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


@pytest.fixture
def publisher() -> Iterator[tuple[Any, ZenohEndpoints]]:
    ep = free_loopback_endpoint()
    session = open_session(ZenohEndpoints(listen=(ep,)))
    try:
        yield session, ZenohEndpoints(connect=(ep,))
    finally:
        session.close()


def test_subscriber_counts_rejections_and_keeps_going(
    publisher: tuple[Any, ZenohEndpoints],
) -> None:
    pub, ep = publisher
    sub = ZenohTruthSubscriber("t/sim", endpoints=ep)
    try:
        # the subscription is up once a first good pose gets through
        def put_pose() -> bool:
            pub.put("t/sim/2/pose", _sample().to_bytes())
            time.sleep(0.02)
            return sub.pose(2) is not None

        _wait(put_pose, "the first pose")
        bad = {
            "truncated": _GOOD[:20],
            "oversized": b"DPT1" + struct.pack("<I", 10**6) + _GOOD[8:],
            "wrong-size": _GOOD + b"\0\0",
            "non-finite": _frame(_header(), patch=(b'"stamp_s": 1.5', b'"stamp_s": Infinity')),
            "malformed": b"DPT1\x02\0\0\0{}",
            "wrong-version": b"XXXX" + _GOOD[4:],
        }
        for payload in bad.values():
            pub.put("t/sim/2/depth", payload)
        pub.put("t/sim/3/depth", _GOOD)  # the frame says drone 2
        pub.put("t/sim/2/pose", b"\x00garbage")
        pub.put("t/sim/2/depth", _image(stamp=5.0).to_bytes())
        pub.put("t/sim/2/depth", _image(stamp=4.0).to_bytes())  # older than the one kept
        # poses and depth frames come through separate subscribers: one stream's callbacks may
        # run after the other's (seen in CI: the bad pose counted after the last frame)
        _wait(
            lambda: (
                sub.counters()["depth.out-of-order"] == 1 and sub.counters()["pose.malformed"] == 1
            ),
            "the last frame and the bad pose",
        )
        c = sub.counters()
        for reason in bad:
            assert c[f"depth.{reason}"] == 1, (reason, c)
        assert c["depth.wrong-sender"] == 1 and c["pose.malformed"] == 1
        assert c["depth.rx"] == 1 and c["error"] == 0
        assert sub.errors == len(bad) + 2
        img = sub.depth_image(2)
        assert img is not None and img.stamp_s == 5.0
        frame = sub.depth_source(2).read()
        assert frame is not None and frame.stamp_s == 5.0
        pos, rot = sub.pose_provider(2)(frame.stamp_s)
        np.testing.assert_allclose(pos, _sample().camera_pose()[0])
    finally:
        sub.close()


def test_depth_source_owning_its_subscriber_on_a_shared_session(
    publisher: tuple[Any, ZenohEndpoints],
) -> None:
    pub, ep = publisher
    session = open_session(ep)
    try:
        src = open_depth_source(7, prefix="t/own", session=session)
        try:
            assert src.newest_stamp_s() is None  # nothing arrived yet

            def got_frame() -> bool:
                pub.put("t/own/7/depth", _image(sid=7, stamp=time.monotonic()).to_bytes())
                time.sleep(0.02)
                return src.newest_stamp_s() is not None and src.read() is not None

            _wait(got_frame, "a frame")
        finally:
            src.close()
        # the shared session is still usable after the source closed its subscription
        session.put("t/own/7/pose", _sample(7).to_bytes())
    finally:
        session.close()


def test_subscriber_of_one_vehicle_never_receives_the_others_frames(
    publisher: tuple[Any, ZenohEndpoints],
) -> None:
    """A flight service subscribes to its own vehicle's streams: with N drones it would
    otherwise receive and decode N times the frames it uses."""
    pub, ep = publisher
    with pytest.raises(ValueError, match="system_id"):
        ZenohTruthSubscriber("t/one", endpoints=ep, system_id=0)
    sub = ZenohTruthSubscriber("t/one", endpoints=ep, system_id=7)
    try:
        # a frame of vehicle 3 before every frame of vehicle 7: once 7's last frame is kept,
        # all of 3's have been delivered (or not) already
        def put_frames() -> bool:
            pub.put("t/one/3/depth", _image(sid=3, stamp=time.monotonic()).to_bytes())
            pub.put("t/one/3/pose", _sample(3).to_bytes())
            pub.put("t/one/7/depth", _image(sid=7, stamp=time.monotonic()).to_bytes())
            time.sleep(0.02)
            return sub.depth_image(7) is not None

        _wait(put_frames, "a frame of vehicle 7")
        for _ in range(5):
            put_frames()
        c = sub.counters()
        assert sub.depth_image(3) is None and sub.pose(3) is None
        assert c["depth.rx"] >= 1 and sub.errors == 0
    finally:
        sub.close()


def test_a_depth_only_subscriber_never_decodes_poses(
    publisher: tuple[Any, ZenohEndpoints],
) -> None:
    """``poses=False`` (a flight service's depth source): the 50 Hz poses are not subscribed
    to; each is published before a frame, so once frames arrive a pose would have too."""
    pub, ep = publisher
    sub = ZenohTruthSubscriber("t/dp", endpoints=ep, system_id=4, poses=False)
    try:

        def put_both() -> bool:
            pub.put("t/dp/4/pose", _sample(4).to_bytes())
            pub.put("t/dp/4/depth", _image(sid=4, stamp=time.monotonic()).to_bytes())
            time.sleep(0.02)
            return sub.depth_image(4) is not None

        _wait(put_both, "a frame of vehicle 4")
        for _ in range(5):
            put_both()
        c = sub.counters()
        assert c["depth.rx"] >= 2 and c["pose.rx"] == 0 and sub.pose(4) is None
    finally:
        sub.close()


@pytest.mark.parametrize("queue_len", [4, 2])
def test_a_busy_reader_gets_the_frames_that_came_meanwhile_in_order(
    publisher: tuple[Any, ZenohEndpoints], queue_len: int
) -> None:
    """The mapping thread is busy for a while during an ESDF refresh: the frames that arrive
    meanwhile wait (up to the queue's length; beyond it the oldest go) instead of all but the
    newest being lost."""
    pub, ep = publisher
    with pytest.raises(ValueError, match="depth_queue"):
        ZenohTruthSubscriber("t/q", endpoints=ep, system_id=5, depth_queue=0)
    sub = ZenohTruthSubscriber("t/q", endpoints=ep, system_id=5, depth_queue=queue_len)
    try:
        src = sub.depth_source(5)

        def first() -> bool:
            pub.put("t/q/5/depth", _image(sid=5, stamp=1.0).to_bytes())
            time.sleep(0.02)
            return sub.depth_image(5) is not None

        _wait(first, "the first frame")
        assert src.newest_stamp_s() == 1.0
        f = src.read()
        assert f is not None and f.stamp_s == 1.0
        for stamp in (2.0, 3.0, 4.0):
            pub.put("t/q/5/depth", _image(sid=5, stamp=stamp).to_bytes())
        _wait(lambda: sub.counters()["depth.rx"] >= 4, "three more frames")
        # the newest arrival is told before it is read (the service's map-lag judgement)
        assert src.newest_stamp_s() == 4.0
        got = []
        while (f := src.read()) is not None:
            got.append(f.stamp_s)
        assert got == [2.0, 3.0, 4.0][-min(3, queue_len) :]
        assert src.read() is None
    finally:
        sub.close()
