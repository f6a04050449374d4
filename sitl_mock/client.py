"""A small MAVLink 2 client on one UDP socket: the stand-in companion / ground station that the
tests and the benchmark use to talk to the mock (or to a real PX4's API link).

It binds ``host:port`` (as MAVSDK's ``udpin://`` does), learns the vehicle's address from the
first valid message and sends there. Every wait has a deadline; nothing blocks forever. It speaks
the mock's dialect (``sitl_mock.px4_dialect``: ``development`` plus PROTOCOL_VERSION and
LINK_NODE_STATUS), so it decodes everything a PX4 v1.16 sends. It sends no heartbeat by itself:
``send_heartbeat()`` announces it (as a GCS by default, which PX4 needs to send STATUSTEXT).
"""

from __future__ import annotations

import math
import socket
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

from sitl_mock.mavlink_io import signing_timestamp_now
from sitl_mock.px4_dialect import mavlink, new_mavlink


class MavClient:
    """MAVLink 2 endpoint, system ``system_id`` component ``component_id`` (MAVSDK: 245/190)."""

    def __init__(
        self,
        port: int = 0,
        host: str = "127.0.0.1",
        sock: socket.socket | None = None,
        system_id: int = 245,
        component_id: int = 190,
        signing_key: bytes | None = None,
        record: tuple[str, ...] = (),
    ) -> None:
        if sock is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind((host, port))
        sock.setblocking(False)
        self.sock = sock
        self.port = sock.getsockname()[1]
        self.mav = new_mavlink(system_id, component_id)
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            self.mav.signing.timestamp = signing_timestamp_now()
        self.remote: tuple[str, int] | None = None
        self.latest: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()
        self.bad = 0
        self.record = set(record)
        self.recorded: list[tuple[float, Any]] = []  # (monotonic wall time, message)
        self.statustexts: list[str] = []  # whole texts (chunked ones reassembled)
        self._chunks: dict[int, list[str]] = {}
        self._pending: deque[Any] = deque(maxlen=20000)  # received, not yet passed by wait()

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> MavClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- receiving -----------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.0) -> list[Any]:
        """Read what arrives within ``timeout_s`` (at least what is already queued)."""
        out: list[Any] = []
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return out
                import select

                select.select([self.sock], [], [], remaining)
                continue
            out.extend(self._parse(data, addr))

    def _parse(self, data: bytes, addr: tuple[str, int]) -> list[Any]:
        mav = self.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        msgs = mav.parse_buffer(data) or []
        good = []
        now = time.monotonic()
        for m in msgs:
            t = m.get_type()
            if t == "BAD_DATA":
                self.bad += 1
                continue
            if self.remote is None:
                self.remote = addr
            self.latest[t] = m
            self.counts[t] += 1
            if t in self.record:
                self.recorded.append((now, m))
            if t == "STATUSTEXT":
                self._statustext(m)
            good.append(m)
        self._pending.extend(good)
        return good

    def _statustext(self, m: Any) -> None:
        txt = m.text if isinstance(m.text, str) else m.text.decode(errors="replace")
        if m.id == 0:
            self.statustexts.append(txt)
            return
        parts = self._chunks.setdefault(m.id, [])
        parts.append(txt)
        if len(txt) < 50:  # the last chunk of a long text is shorter than a whole one
            self.statustexts.append("".join(parts))
            del self._chunks[m.id]

    def discard_pending(self) -> None:
        """Forget what arrived so far: the next ``wait`` looks only at newer messages."""
        self.poll(0.0)
        self._pending.clear()

    def wait(
        self,
        msg_type: str,
        cond: Callable[[Any], bool] | None = None,
        timeout_s: float = 5.0,
    ) -> Any:
        """The next ``msg_type`` message for which ``cond`` holds; TimeoutError otherwise.

        "Next": the first such message received after the one the previous ``wait`` returned
        (messages passed over are dropped from the queue).
        """
        deadline = time.monotonic() + timeout_s
        pending = self._pending
        while True:
            while pending:
                m = pending.popleft()
                if m.get_type() == msg_type and (cond is None or cond(m)):
                    return m
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no {msg_type} within {timeout_s} s")
            self.poll(min(remaining, 0.05))

    def wait_until(self, pred: Callable[[], bool], timeout_s: float = 5.0) -> None:
        """Poll until ``pred()`` holds (it may read ``latest``); TimeoutError otherwise."""
        deadline = time.monotonic() + timeout_s
        while not pred():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"condition not met within {timeout_s} s")
            self.poll(min(remaining, 0.05))

    def connect(self, timeout_s: float = 5.0) -> Any:
        """Wait for the vehicle's heartbeat (learning its address); returns it."""
        return self.wait("HEARTBEAT", lambda m: m.get_srcComponent() == 1, timeout_s)

    # ---- sending -------------------------------------------------------------------------
    def send(self, msg: Any) -> None:
        if self.remote is None:
            raise RuntimeError("no vehicle address yet: call connect() first")
        self.send_raw(self.pack(msg))

    def pack(self, msg: Any) -> bytes:
        mav = self.mav
        if mav.signing.sign_outgoing:
            mav.signing.timestamp = max(mav.signing.timestamp, signing_timestamp_now())
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        return bytes(buf)

    def send_raw(self, data: bytes, to: tuple[str, int] | None = None) -> None:
        dest = to or self.remote
        if dest is None:
            raise RuntimeError("no vehicle address yet: call connect() first")
        self.sock.sendto(data, dest)

    def send_heartbeat(self, gcs: bool = True) -> None:
        """One HEARTBEAT: a ground station's (MAV_TYPE_GCS) or an onboard controller's."""
        kind = mavlink.MAV_TYPE_GCS if gcs else mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        self.send(self.mav.heartbeat_encode(kind, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))

    def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        target_system: int = 1,
        target_component: int = 1,
        wait_ack: bool = True,
        timeout_s: float = 3.0,
    ) -> int | None:
        """Send COMMAND_LONG; the MAV_RESULT of its COMMAND_ACK (None if not waited for)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.discard_pending()  # an older ACK of the same command must not be taken for this one
        self.send(self.mav.command_long_encode(target_system, target_component, command, 0, *p[:7]))
        if not wait_ack:
            return None
        ack = self.wait("COMMAND_ACK", lambda m: m.command == command, timeout_s)
        return int(ack.result)

    def set_mode(self, main: int, sub: int = 0, target_system: int = 1, **kw: Any) -> int | None:
        """DO_SET_MODE with a PX4 custom mode."""
        return self.command_long(176, (1.0, float(main), float(sub)), target_system, **kw)

    def setpoint(
        self,
        target_system: int = 1,
        position_ned: tuple[float, float, float] = (math.nan, math.nan, math.nan),
        velocity_ned: tuple[float, float, float] | None = None,
        acceleration_ned: tuple[float, float, float] | None = None,
        yaw_rad: float | None = None,
        yaw_rate_rad_s: float | None = None,
        type_mask: int | None = None,
        frame: int = 1,
    ) -> None:
        """SET_POSITION_TARGET_LOCAL_NED; the type mask follows from what is given."""
        vel = velocity_ned or (0.0, 0.0, 0.0)
        acc = acceleration_ned or (0.0, 0.0, 0.0)
        if type_mask is None:
            type_mask = 0
            if any(math.isnan(x) for x in position_ned):
                type_mask |= 1 | 2 | 4
            if velocity_ned is None:
                type_mask |= 8 | 16 | 32
            if acceleration_ned is None:
                type_mask |= 64 | 128 | 256
            if yaw_rad is None:
                type_mask |= 1024
            if yaw_rate_rad_s is None:
                type_mask |= 2048
        self.send(
            self.mav.set_position_target_local_ned_encode(
                int(time.monotonic() * 1000) & 0xFFFFFFFF,
                target_system,
                1,
                frame,
                type_mask,
                *position_ned,
                *vel,
                *acc,
                0.0 if yaw_rad is None else yaw_rad,
                0.0 if yaw_rate_rad_s is None else yaw_rate_rad_s,
            )
        )


def bind_consecutive_udp(
    n: int, host: str = "127.0.0.1", attempts: int = 200
) -> list[socket.socket]:
    """``n`` UDP sockets bound to consecutive free ports on ``host``, the base drawn at random
    outside the kernel's ephemeral range (``onboard.comm.loopback``: no socket bound to port 0
    and no outgoing connection can take them in between).

    The sockets stay bound, so nothing else can take the ports before the caller uses them
    (wrap them in ``MavClient(sock=...)``, or close them just before another program binds).
    """
    from onboard.comm.loopback import bind_consecutive

    return bind_consecutive(n, socket.SOCK_DGRAM, host, attempts)
