"""Ports on loopback drawn outside the kernel's ephemeral range (``onboard.comm.loopback``)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from onboard.comm.loopback import (
    EPHEMERAL_DEFAULT,
    bind_consecutive,
    candidate_bases,
    ephemeral_range,
    free_port,
)
from onboard.comm.zenoh_session import free_loopback_endpoint, loopback_endpoints
from sitl_mock.client import bind_consecutive_udp


def _outside(port: int) -> bool:
    lo, hi = ephemeral_range()
    return not lo <= port <= hi


def test_the_kernel_hands_out_ports_inside_the_range_read() -> None:
    """The premise: a socket bound to port 0 gets a port of ``ephemeral_range()``."""
    lo, hi = ephemeral_range()
    for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
        socks = []
        try:
            for _ in range(20):
                s = socket.socket(socket.AF_INET, kind)
                socks.append(s)
                s.bind(("127.0.0.1", 0))
                assert lo <= s.getsockname()[1] <= hi
        finally:
            for s in socks:
                s.close()


def test_ephemeral_range_file(tmp_path: Path) -> None:
    f = tmp_path / "range"
    f.write_text("40000\t50000\n", encoding="ascii")
    assert ephemeral_range(f) == (40000, 50000)
    for bad in ("", "1 2 3", "x 5", "50000 40000", "0 100"):
        f.write_text(bad, encoding="ascii")
        assert ephemeral_range(f) == EPHEMERAL_DEFAULT
    assert ephemeral_range(tmp_path / "missing") == EPHEMERAL_DEFAULT


def test_candidate_bases() -> None:
    assert candidate_bases(7, (32768, 60999)) == [(20000, 32761), (61000, 65529)]
    assert candidate_bases(1, (32768, 60999), lo=20000, hi=40000) == [(20000, 32767)]
    assert candidate_bases(3, (1024, 65535)) == [(20000, 65533)]  # no room outside: anywhere
    with pytest.raises(ValueError, match="n must be"):
        candidate_bases(0)
    with pytest.raises(ValueError, match="consecutive"):
        candidate_bases(10, (1024, 65535), lo=100, hi=105)


@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM])
def test_bound_ports_are_consecutive_and_outside_the_range(kind: int) -> None:
    socks = bind_consecutive(7, kind)
    try:
        ports = [s.getsockname()[1] for s in socks]
        assert ports == list(range(ports[0], ports[0] + 7))
        assert all(_outside(p) for p in ports)
        assert all(s.type == kind for s in socks)
    finally:
        for s in socks:
            s.close()


def test_the_helpers_draw_outside_the_range() -> None:
    socks = bind_consecutive_udp(3)
    try:
        assert all(_outside(s.getsockname()[1]) for s in socks)
    finally:
        for s in socks:
            s.close()
    eps = loopback_endpoints(4)
    assert len(set(eps)) == 4
    for ep in eps:
        assert ep.startswith("tcp/127.0.0.1:") and _outside(int(ep.rsplit(":", 1)[1]))
    assert _outside(int(free_loopback_endpoint().rsplit(":", 1)[1]))
    port = free_port(socket.SOCK_DGRAM)  # the fault proxy's UDP port
    assert _outside(port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))  # free when drawn, and released
