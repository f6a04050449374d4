"""Free ports on loopback for the local demo, benchmarks and tests, outside the kernel's
ephemeral range.

A port that the kernel reports free (``bind(0)``) comes from its ephemeral range, and so does
the source port of every outgoing TCP connection and of every UDP socket bound to port 0. A
port picked that way and released before its program binds it can be taken in between: on
2026-12-04 the demo's seed 20 failed to start because a mock vehicle's ephemeral UDP socket got
the port reserved for drone 4's MAVLink link (``Address already in use``). The ports here are
drawn at random outside that range, so no ephemeral allocation can take them; only a program
that binds the same port explicitly can, and each is checked free when drawn.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
EPHEMERAL_DEFAULT = (32768, 60999)
"""Linux's default ephemeral range (used where the file above cannot be read)."""
PORT_LO = 20000
"""The lowest port drawn: above PX4's (14540-14600), Zenoh's (7447) and Foxglove's (8765)."""
PORT_HI = 65535


def ephemeral_range(path: Path = EPHEMERAL_RANGE_FILE) -> tuple[int, int]:
    """The kernel's ephemeral port range (first, last), both included."""
    try:
        lo, hi = (int(v) for v in path.read_text(encoding="ascii").split())
    except (OSError, ValueError):
        return EPHEMERAL_DEFAULT
    if not 0 < lo <= hi <= 65535:
        return EPHEMERAL_DEFAULT
    return lo, hi


def candidate_bases(
    n: int,
    ephemeral: tuple[int, int] | None = None,
    lo: int = PORT_LO,
    hi: int = PORT_HI,
) -> list[tuple[int, int]]:
    """The ranges [first, last] of base ports whose ``n`` consecutive ports lie in [lo, hi] and
    outside ``ephemeral`` (default: the kernel's). Where the ephemeral range leaves no room, the
    whole of [lo, hi] (nothing better exists on such a host)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    e_lo, e_hi = ephemeral_range() if ephemeral is None else ephemeral
    out = []
    below, above = min(hi, e_lo - 1), max(lo, e_hi + 1)  # the last port below, first above
    if below - lo + 1 >= n:
        out.append((lo, below - n + 1))
    if hi - above + 1 >= n:
        out.append((above, hi - n + 1))
    if not out:
        if hi - lo + 1 < n:
            raise ValueError(f"no {n} consecutive ports in [{lo}, {hi}]")
        out.append((lo, hi - n + 1))
    return out


def _draw(rng: random.Random, ranges: list[tuple[int, int]]) -> int:
    sizes = [b - a + 1 for a, b in ranges]
    k = rng.randrange(sum(sizes))
    for (a, _), size in zip(ranges, sizes, strict=True):
        if k < size:
            return a + k
        k -= size
    raise AssertionError("unreachable")


def bind_consecutive(
    n: int, kind: int = socket.SOCK_DGRAM, host: str = "127.0.0.1", attempts: int = 200
) -> list[socket.socket]:
    """``n`` sockets of ``kind`` (``socket.SOCK_DGRAM`` or ``SOCK_STREAM``) bound to
    consecutive ports on ``host``, the base drawn at random outside the ephemeral range. They
    stay bound: close them just before the program that uses the ports binds them."""
    ranges = candidate_bases(n)
    rng = random.Random()
    for _ in range(attempts):
        base = _draw(rng, ranges)
        socks: list[socket.socket] = []
        try:
            for i in range(n):
                s = socket.socket(socket.AF_INET, kind)
                socks.append(s)
                s.bind((host, base + i))
            return socks
        except OSError:
            for s in socks:
                s.close()
    raise OSError(f"no {n} consecutive free ports on {host} outside the ephemeral range")


def free_port(kind: int = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """One port of ``kind`` on ``host``, free when drawn, outside the ephemeral range."""
    (s,) = bind_consecutive(1, kind, host)
    with s:
        return int(s.getsockname()[1])
