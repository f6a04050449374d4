"""The measuring instruments of ``swarm-gcs bench service``: the MAVLink message-id scan, the UDP
tap that timestamps setpoints on their way to the autopilot, and the notify socket READY is
read from. Real sockets on loopback, real MAVLink frames (pymavlink)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from gcs.bench_service import (
    SET_POSITION_TARGET_LOCAL_NED,
    NotifySocket,
    SetpointTap,
    mavlink_msgids,
    poll_until,
    proc_cpu_s,
    proc_memory_kb,
)
from onboard.service.sdnotify import Notifier


def _encoder(signed: bool = False) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    if signed:
        mav.signing.secret_key = bytes(range(32))
        mav.signing.link_id = 0
        mav.signing.timestamp = 1
        mav.signing.sign_outgoing = True
    return mav


def _setpoint(mav: mavlink2.MAVLink) -> bytes:
    msg = mavlink2.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 1, 2048, 1.0, 2.0, -1.0, 0, 0, 0, 0, 0, 0, 0.5, 0
    )
    return bytes(msg.pack(mav))


def _heartbeat(mav: mavlink2.MAVLink) -> bytes:
    return bytes(mavlink2.MAVLink_heartbeat_message(18, 8, 0, 0, 0, 3).pack(mav))


@pytest.mark.parametrize("signed", [False, True])
def test_message_ids_of_every_frame_in_a_datagram(signed: bool) -> None:
    mav = _encoder(signed)
    data = _heartbeat(mav) + _setpoint(mav) + _heartbeat(mav)
    assert mavlink_msgids(data) == [0, SET_POSITION_TARGET_LOCAL_NED, 0]
    assert mavlink_msgids(b"") == []
    assert mavlink_msgids(b"\x00garbage") == []
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    hb1 = bytes(mavlink2.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3).pack(v1, force_mavlink1=True))
    assert hb1[0] == 0xFE and mavlink_msgids(hb1 + _setpoint(mav)) == [0, 84]


def test_tap_forwards_both_ways_and_timestamps_setpoints() -> None:
    service = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    service.bind(("127.0.0.1", 0))
    mock.bind(("127.0.0.1", 0))
    service.settimeout(2.0)
    mock.settimeout(2.0)
    mav = _encoder()
    try:
        with SetpointTap(service.getsockname()) as tap:
            # the mock talks first (its telemetry), the service answers whoever talked to it
            mock.sendto(_heartbeat(mav), ("127.0.0.1", tap.front_port))
            data, back = service.recvfrom(65535)
            assert mavlink_msgids(data) == [0]
            t0 = time.monotonic()
            for _ in range(5):
                service.sendto(_setpoint(mav), back)
                got, _ = mock.recvfrom(65535)
                assert mavlink_msgids(got) == [SET_POSITION_TARGET_LOCAL_NED]
            service.sendto(_heartbeat(mav), back)
            assert mavlink_msgids(mock.recvfrom(65535)[0]) == [0]
            t1 = time.monotonic()
            poll_until(lambda: tap.to_mock == 6, 2.0, "the last datagram")
            arrivals = tap.arrivals_between(t0, t1)
            assert len(arrivals) == 5  # the heartbeat is forwarded, not counted
            assert list(arrivals) == sorted(arrivals)
            # the kernel's receive stamps of the same datagrams: ordered, inside the window,
            # never after the tap thread's own stamp (1 ms for the clock conversion)
            kernel = tap.arrivals_between(t0, t1, kernel=True)
            assert len(kernel) == 5 and bool(np.all(np.isfinite(kernel)))
            assert list(kernel) == sorted(kernel)
            assert bool(np.all(kernel <= arrivals + 1e-3)) and kernel[0] >= t0 - 1e-3
            assert tap.to_service == 1 and tap.dropped == 0
    finally:
        service.close()
        mock.close()


def test_notify_socket_receives_what_the_service_notifier_sends() -> None:
    ns = NotifySocket()
    try:
        n = Notifier({"NOTIFY_SOCKET": ns.path})
        assert n.status("warming")
        t_sent = time.monotonic()
        assert n.ready("drone 3 ready")
        ns.poll(1.0)
        t_ready = ns.first("READY=1")
        assert t_ready is not None and t_ready >= t_sent
        assert ns.first("STATUS=warming") is not None
        assert ns.first("WATCHDOG=1") is None
    finally:
        ns.close()


def test_process_cpu_and_memory_are_read_from_proc() -> None:
    import os

    c0 = proc_cpu_s(os.getpid())
    x = 0
    t_end = time.process_time() + 0.05
    while time.process_time() < t_end:
        x += 1
    assert proc_cpu_s(os.getpid()) >= c0 + 0.03
    mem = proc_memory_kb(os.getpid())
    assert mem["VmHWM"] >= mem["VmRSS"] > 10_000


def test_service_config_is_the_drones_configuration_with_the_test_settings_on_top(
    tmp_path: Path,
) -> None:
    """The services the benchmarks and the process tests start fly ``config/onboard.yaml``
    with their loopback settings on top (a file given to the service replaces that one: built
    from scratch, they flew the planner's defaults, ``check_obstacle_horizon_s`` 0 instead of
    the drone's 4); ``extra`` wins; without a camera no depth key of the drone's file is kept."""
    import dataclasses

    import yaml

    from gcs.bench_service import service_config
    from onboard.service.config import load_onboard_config

    drone = load_onboard_config(None, drone_id=0)
    for depth in (None, {"source": "zenoh-sim", "rate_hz": 5.0}):
        cfg = service_config(
            swarm="t", autopilot_port=14600, zenoh_listen=["tcp/127.0.0.1:7000"],
            zenoh_connect=[], depth=depth, record_dir=tmp_path,
            extra={"planning": {"replan_period_s": 0.5}},
        )  # fmt: skip
        path = tmp_path / "onboard.yaml"
        path.write_text(yaml.safe_dump(cfg))
        got = load_onboard_config(path, drone_id=0)
        assert got.planner == drone.planner
        assert got.planner.check_obstacle_horizon_s > 0.0
        assert got.planning == dataclasses.replace(drone.planning, replan_period_s=0.5)
        assert got.mapping == drone.mapping and got.reactions == drone.reactions
        assert got.depth.source == ("none" if depth is None else "zenoh-sim")
        assert depth is None or got.depth.rate_hz == 5.0
        assert got.zenoh.listen == ("tcp/127.0.0.1:7000",)
