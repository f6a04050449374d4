"""The streamer's timed sender (``onboard.autopilot.timed_send``): a datagram leaves at its
deadline, never before it, from native code without the interpreter lock; a cancel ends the
wait without sending; the pymavlink link streams through it against the SITL mock over UDP and
sends nothing once ``stop_streaming`` returned."""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Callable

import pytest

from onboard.autopilot import LinkConfig, Setpoint, open_link, timed_send
from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig

SO_TIMESTAMPNS = 35  # Linux (Python's socket module does not name it)
pytestmark = pytest.mark.skipif(not timed_send.available, reason="Linux 64-bit only")


def _ready() -> None:
    assert timed_send.wait_compiled(120.0), timed_send._kernel_error


def _receiver() -> socket.socket:
    r = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    r.bind(("127.0.0.1", 0))
    r.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    r.settimeout(5.0)
    return r


def _kernel_stamp_monotonic(r: socket.socket) -> tuple[bytes, float]:
    """A datagram and the kernel's receive stamp of it, on the monotonic clock."""
    offset = time.time() - time.monotonic()
    data, anc, _, _ = r.recvmsg(256, 64)
    for level, kind, raw in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("@qq", raw[:16])
            return data, sec + nsec * 1e-9 - offset
    raise AssertionError("no receive stamp")


def test_a_datagram_leaves_at_its_deadline_never_before() -> None:
    _ready()
    r = _receiver()
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ts = timed_send.TimedSender()
    try:
        dest = r.getsockname()
        for k in range(5):
            deadline = time.monotonic() + 0.02 + 0.01 * k
            n = ts.send_at(deadline, s.fileno(), b"sp%d" % k, dest)
            assert n == 3
            data, stamp = _kernel_stamp_monotonic(r)
            assert data == b"sp%d" % k
            assert stamp >= deadline - 2e-4  # the clock conversion's error, not earlier
        # a deadline in the past: at once
        assert ts.send_at(time.monotonic() - 1.0, s.fileno(), b"late", dest) == 4
        assert r.recv(16) == b"late"
        # a send error (closed socket) is reported, not raised
        bad = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        fd = bad.fileno()
        bad.close()
        assert ts.send_at(time.monotonic(), fd, b"x", dest) == -1
    finally:
        ts.close()
        s.close()
        r.close()


def test_cancel_ends_the_wait_and_nothing_is_sent() -> None:
    _ready()
    r = _receiver()
    r.settimeout(0.2)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ts = timed_send.TimedSender()
    try:
        threading.Timer(0.05, ts.cancel).start()
        t0 = time.monotonic()
        n = ts.send_at(t0 + 30.0, s.fileno(), b"never", r.getsockname())
        assert n == timed_send.CANCELLED and time.monotonic() - t0 < 25.0
        with pytest.raises(socket.timeout):
            r.recv(16)
        # a cancel before the call counts too, unless cleared
        ts.cancel()
        assert ts.send_at(time.monotonic() + 30.0, s.fileno(), b"x", r.getsockname()) == -2
        ts.cancel()
        ts.clear()
        assert ts.send_at(time.monotonic() + 0.01, s.fileno(), b"y", r.getsockname()) == 1
        assert r.recv(16) == b"y"
    finally:
        ts.close()
        s.close()
        r.close()


def _poll(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("timed", [True, False])
def test_pymavlink_link_streams_through_the_timed_sender(timed: bool) -> None:
    _ready()
    socks = bind_consecutive_udp(1)
    port = socks[0].getsockname()[1]
    socks[0].close()
    spawn = (3.0, -2.0, 0.0)
    fleet = Fleet(
        FleetConfig(
            count=1,
            base_port=port,
            local_port_offset=None,
            speedup=1.0,
            spawn_enu_m=(spawn,),
            autopilot=AutopilotParams(boot_time_s=0.5),
        )
    )
    link = open_link(
        LinkConfig(
            url=f"udpin://127.0.0.1:{port}", implementation="pymavlink", local_origin_enu_m=spawn
        )
    )
    link.timed_setpoints = timed  # False: from Python, as serial and MAVSDK links do
    calls: list[tuple[float, float]] = []  # (sample time asked for, wall clock at the call)

    def source(t: float) -> Setpoint:
        calls.append((t, time.time()))
        return Setpoint.hold((spawn[0] + 0.5, spawn[1], 0.0), 0.0)

    try:
        fleet.start()
        link.connect(10.0)
        link.wait_healthy(10.0)
        link.start_streaming(source)
        _poll(lambda: link.counters().setpoints_sent >= 25, 10.0, "setpoints")
        sp = fleet.autopilots[0].offboard_setpoint
        assert sp is not None and math.dist(sp.position_m, (spawn[0] + 0.5, spawn[1], 0.0)) < 1e-4
        if timed:
            # all of them (the kernel was compiled before connecting; read in this order, the
            # two counters may differ by the setpoint being counted at that instant)
            timed_n = link.timed_setpoints_sent
            assert timed_n >= link.counters().setpoints_sent - 1 >= 24
            # each tick is prepared ahead and sampled at the time it will be sent
            assert any(t > wall + 1e-3 for t, wall in calls)
        else:
            assert link.timed_setpoints_sent == 0
        assert all(b[0] > a[0] for a, b in zip(calls, calls[1:], strict=False))
        link.stop_streaming()
        sent = link.counters().setpoints_sent
        time.sleep(0.1)  # what left before the return has arrived by now
        got = fleet.links[0].stats.setpoints
        time.sleep(0.2)  # ten periods: nothing more may leave, nothing more arrive
        assert link.counters().setpoints_sent == sent
        assert fleet.links[0].stats.setpoints == got
        assert link.counters().heartbeats_sent >= 1
    finally:
        link.close()
        fleet.stop()


def test_the_kernel_is_compiled_once_for_the_types_it_is_called_with() -> None:
    # a second specialisation would be compiled in the streamer's first tick, holding the GIL
    _ready()
    r = _receiver()
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ts = timed_send.TimedSender()
    try:
        assert (
            ts.send_at(time.monotonic(), s.fileno(), bytes(bytearray(b"ab")), r.getsockname()) == 2
        )
        assert ts.send_at(time.monotonic(), s.fileno(), b"abc", r.getsockname()) == 3
        assert len(timed_send._kernel.signatures) == 1
    finally:
        ts.close()
        s.close()
        r.close()


def test_realtime_request_is_the_callers_alone_and_not_inherited() -> None:
    import os

    out: dict[str, object] = {}

    def child() -> None:
        out["child"] = os.sched_getscheduler(threading.get_native_id())

    def streamer() -> None:
        tid = threading.get_native_id()
        before = os.sched_getscheduler(tid)
        out["granted"] = timed_send.request_realtime()
        out["policy"] = os.sched_getscheduler(tid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        out["before"] = before
        t = threading.Thread(target=child)
        t.start()
        t.join()

    t = threading.Thread(target=streamer)
    t.start()
    t.join()
    if out["granted"]:
        assert out["policy"] == os.SCHED_FIFO
    else:  # no privilege: nothing changed
        assert out["policy"] == out["before"]
    assert out["child"] == os.SCHED_OTHER  # a thread it starts runs normally
    assert os.sched_getscheduler(threading.get_native_id()) == os.SCHED_OTHER


@pytest.mark.timeout(60)
def test_a_source_with_nothing_to_send_does_not_spin_the_streamer() -> None:
    # nothing to send and nothing to hold: the timed streamer must still keep its 50 Hz pace
    # (it once looped without waiting, at real-time priority where permitted)
    _ready()
    socks = bind_consecutive_udp(1)
    port = socks[0].getsockname()[1]
    socks[0].close()
    fleet = Fleet(
        FleetConfig(
            count=1,
            base_port=port,
            local_port_offset=None,
            speedup=1.0,
            autopilot=AutopilotParams(boot_time_s=0.5),
        )
    )
    link = open_link(LinkConfig(url=f"udpin://127.0.0.1:{port}", implementation="pymavlink"))
    calls: list[float] = []

    def nothing(t: float) -> None:
        calls.append(time.monotonic())
        return None

    try:
        fleet.start()
        link.connect(10.0)
        link._last_good = None
        link.start_streaming(nothing)
        link._last_good = None  # no hold position either: every tick sends nothing
        t0 = time.monotonic()
        time.sleep(0.5)
        n = sum(1 for c in calls if c >= t0)
        assert n <= 0.5 * 50 + 3, n  # one call per 20 ms tick at most
        # (a tick may have held the position start_streaming set before it was cleared)
        assert link.counters().setpoints_sent <= 2
    finally:
        link.close()
        fleet.stop()
