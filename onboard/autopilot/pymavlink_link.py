"""The autopilot link over pymavlink's MAVLink 2 codec (the default implementation).

One receiver thread reads the transport, decodes with pymavlink (each UDP datagram on its own,
so garbage cannot swallow the next datagram; a serial stream through one persistent parser),
keeps what the state needs and routes COMMAND_ACKs to the one pending command.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import px4
from onboard.autopilot.config import LinkConfig
from onboard.autopilot.frames import NedSetpoint
from onboard.autopilot.link import AutopilotLink
from onboard.autopilot.model import CommandResult, LinkError, VehicleState
from onboard.autopilot.signing import (
    SIGNING_VERSIONS,
    Verifier,
    frame_origin,
    load_signing_key,
    signing_timestamp_now,
)
from onboard.autopilot.streamlock import YIELD_BEFORE_DEADLINE_S, StreamLock
from onboard.autopilot.timed_send import CANCELLED
from onboard.autopilot.transport import Address, Transport, UdpTransport, open_transport

_UINT16_MAX = 65535
_STX_V2 = 0xFD
_STX_V1 = 0xFE


def select_frames(data: bytes, wanted: frozenset[int]) -> tuple[bytes, int]:
    """The frames of one datagram whose message id is in ``wanted``, and how many were left
    out. A PX4 streams some 25 message types on its onboard link (about 380 per second, most
    of them not used here), and pymavlink's pure-Python decoding of each costs about as much as
    everything else the receiver does; the header says the id and the length, so the unused
    ones are skipped unread. Nothing that does not look like a whole frame is dropped: from the
    first byte that does not start a frame, or a frame the datagram cuts short, the rest goes
    to the decoder as it is (which counts it as bad data, as before)."""
    n = len(data)
    i = 0
    keep: list[bytes] = []
    left_out = 0
    start = 0  # the kept run of frames starts here
    while i < n:
        stx = data[i]
        if stx == _STX_V2:
            if i + 10 > n:
                break
            length = 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)
            msg_id = data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16)
        elif stx == _STX_V1:
            if i + 6 > n:
                break
            length = 8 + data[i + 1]
            msg_id = data[i + 5]
        else:
            break
        if i + length > n:
            break
        if msg_id not in wanted:
            if start < i:
                keep.append(data[start:i])
            left_out += 1
            start = i + length
        i += length
    if left_out == 0:
        return data, 0
    keep.append(data[start:])
    return b"".join(keep), left_out


class _Pending:
    """The command waiting for its acknowledgement."""

    def __init__(self, command: int) -> None:
        self.command = command
        self.result: CommandResult | None = None
        self.progress_t: float | None = None


def sys_status_health(present: int, enabled: int, health: int) -> tuple[bool, bool]:
    """(no present and enabled sensor reports a fault, PX4's pre-arm checks pass) from
    SYS_STATUS. The pre-arm bit lives in the health field only, so it is left out of the
    fault check."""
    sensors = present & enabled & ~px4.SENSOR_PREARM_CHECK
    return (sensors & ~health) == 0, bool(health & px4.SENSOR_PREARM_CHECK)


class PymavlinkLink(AutopilotLink):
    """``AutopilotLink`` over pymavlink. ``transport``: an already open transport (tests);
    None opens the one ``config.url`` names."""

    implementation = "pymavlink"
    timed_setpoints = True  # over UDP (see _timed_ready)

    def __init__(
        self,
        config: LinkConfig,
        sample_clock: Callable[[], float] = time.time,
        name: str | None = None,
        transport: Transport | None = None,
    ) -> None:
        super().__init__(config, sample_clock=sample_clock, name=name)
        self._transport: Transport | None = transport
        self._mav = mavlink.MAVLink(
            None, srcSystem=config.own_system_id, srcComponent=config.component_id
        )
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._signing = config.signing_key_file is not None
        self._autopilot_unsigned = 0
        self._autopilot_badsig = 0
        if config.signing_key_file is not None:
            self._setup_signing(load_signing_key(config.signing_key_file))
        self._tx_lock = StreamLock()  # the streamer holds it while a timed setpoint waits
        self._ack_cond = threading.Condition()
        self._pending: _Pending | None = None
        self._remote: Address | None = None
        self._handlers: dict[str, Callable[[float, Any], None]] = {
            "HEARTBEAT": self._on_heartbeat,
            "LOCAL_POSITION_NED": self._on_local_position,
            "ATTITUDE": self._on_attitude,
            "EXTENDED_SYS_STATE": self._on_extended_sys_state,
            "SYS_STATUS": self._on_sys_status,
            "HOME_POSITION": self._on_home_position,
            "COMMAND_ACK": self._on_command_ack,
        }
        self._wanted_ids = frozenset(
            getattr(mavlink, f"MAVLINK_MSG_ID_{name}") for name in self._handlers
        )

    def _setup_signing(self, key: bytes) -> None:
        """Sign everything sent; verify what arrives (the key stays in the codecs only)."""
        out = self._mav.signing
        out.secret_key = key
        out.sign_outgoing = True
        out.link_id = self.config.signing_link_id
        out.timestamp = signing_timestamp_now()
        inp = self._parser.signing
        inp.secret_key = key
        self._parser.check_signature = Verifier(key).verify
        if not self.config.requires_signing:
            inp.allow_unsigned_callback = lambda _mav, _msg_id: True

    def connect(self, timeout_s: float | None = None) -> VehicleState:
        """As ``AutopilotLink.connect``; with signing required, an autopilot that sends only
        unsigned frames (PX4 v1.16) or frames signed with another key is named as such."""
        try:
            return super().connect(timeout_s)
        except LinkError as e:
            cfg = self.config
            who = f"{self.name}: the autopilot (system {cfg.system_id})"
            if cfg.requires_signing and self._autopilot_unsigned:
                raise LinkError(
                    f"{who} sends unsigned MAVLink ({self._autopilot_unsigned} frames refused) "
                    f"and signing_required is set: MAVLink signing needs {SIGNING_VERSIONS}, "
                    "with the same key"
                ) from e
            if self._autopilot_badsig:
                raise LinkError(
                    f"{who} signs, but {self._autopilot_badsig} frames did not verify: another "
                    "key (or replayed frames)"
                ) from e
            raise

    @property
    def transport_description(self) -> str:
        t = self._transport
        return t.description if t is not None else self.config.url

    # ---- lifecycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        if self._transport is None:
            self._transport = open_transport(self.config.endpoint)
        self._start_thread(self._recv_loop, "autopilot-recv")

    def _shutdown(self) -> None:
        if self._transport is not None:
            self._transport.close()
        with self._ack_cond:
            self._ack_cond.notify_all()

    # ---- receiving ---------------------------------------------------------------------------
    def _recv_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        while not self._stop.is_set():
            began = time.monotonic()
            try:
                chunks = transport.read(0.1)
            except LinkError:
                self._rx_decode_error()
                time.sleep(0.1)
                continue
            for data, addr in chunks:
                self._on_chunk(data, addr, transport.datagrams)
            if transport.drained:  # all that had arrived when the read began is handled
                self._rx_looked_at(began)

    def _on_chunk(self, data: bytes, addr: Address | None, datagram: bool) -> None:
        p = self._parser
        if datagram:  # each datagram on its own
            data, left_out = select_frames(data, self._wanted_ids)
            if left_out:
                self._c["frames_ignored"] += left_out
                if not data:
                    return
            p.buf = bytearray()
            p.buf_index = 0
            p.expected_length = mavlink.HEADER_LEN_V1 + 2
        unsigned_before = p.signing.unsigned_count
        try:
            msgs = p.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - malformed input must never stop the receiver
            self._rx_decode_error()
            return
        if p.signing.unsigned_count != unsigned_before:
            self._c["unsigned_accepted"] += p.signing.unsigned_count - unsigned_before
        now = time.monotonic()
        cfg = self.config
        for m in msgs:
            kind = m.get_type()
            if kind == "BAD_DATA":
                if self._signing and "signature" in str(getattr(m, "reason", "")):
                    self._rx_signing_reject(m.data)
                else:
                    self._rx_decode_error()
                continue
            if m.get_srcSystem() != cfg.system_id:
                continue
            if m.get_srcComponent() != cfg.autopilot_component_id:
                continue
            if addr is not None and addr != self._remote:
                self._remote = addr
                if self._transport is not None:
                    self._transport.set_remote(addr)
            self._rx(now)
            handler = self._handlers.get(kind)
            if handler is not None:
                try:
                    handler(now, m)
                except Exception:  # noqa: BLE001 - a malformed field: count, go on
                    self._rx_decode_error()

    def _rx_signing_reject(self, frame: Any) -> None:
        origin = frame_origin(bytes(frame))
        signed = origin is not None and origin[2]
        self._c["bad_signatures" if signed else "unsigned_rejected"] += 1
        cfg = self.config
        if origin is not None and origin[:2] == (cfg.system_id, cfg.autopilot_component_id):
            if signed:
                self._autopilot_badsig += 1
            else:
                self._autopilot_unsigned += 1

    def _on_heartbeat(self, now: float, m: Any) -> None:
        self._rx_heartbeat(now, int(m.custom_mode), int(m.base_mode), int(m.system_status))

    def _on_local_position(self, now: float, m: Any) -> None:
        self._rx_local_position(
            now, (float(m.x), float(m.y), float(m.z)), (float(m.vx), float(m.vy), float(m.vz))
        )

    def _on_attitude(self, now: float, m: Any) -> None:
        self._rx_attitude(now, float(m.roll), float(m.pitch), float(m.yaw))

    def _on_extended_sys_state(self, now: float, m: Any) -> None:
        self._rx_landed_state(now, int(m.landed_state))

    def _on_sys_status(self, now: float, m: Any) -> None:
        ok, prearm = sys_status_health(
            int(m.onboard_control_sensors_present),
            int(m.onboard_control_sensors_enabled),
            int(m.onboard_control_sensors_health),
        )
        self._rx_health(now, ok, prearm)
        rem = int(m.battery_remaining)
        volt = int(m.voltage_battery)
        self._rx_battery(
            now,
            None if rem < 0 else rem / 100.0,
            None if volt == _UINT16_MAX else volt / 1000.0,
        )

    def _on_home_position(self, now: float, m: Any) -> None:
        self._rx_home(now, int(m.altitude) / 1000.0)

    def _on_command_ack(self, now: float, m: Any) -> None:
        cfg = self.config
        if int(m.target_system) not in (0, cfg.own_system_id):
            return
        if int(m.target_component) not in (0, cfg.component_id):
            return
        command = int(m.command)
        result = int(m.result)
        matched = False
        with self._ack_cond:
            pend = self._pending
            if pend is not None and pend.command == command and pend.result is None:
                matched = True
                if result == CommandResult.IN_PROGRESS.value:
                    pend.progress_t = now
                else:
                    pend.result = CommandResult.from_mav_result(result)
                self._ack_cond.notify_all()
        self._rx_ack(now, command, matched)

    # ---- sending -----------------------------------------------------------------------------
    def _send(self, msg: Any) -> bool:
        t = self._transport
        if t is None:
            return False
        with self._tx_lock:
            mav = self._mav
            if self._signing:  # never behind the wall clock (a restarted link stays fresh)
                mav.signing.timestamp = max(mav.signing.timestamp, signing_timestamp_now())
            buf = bytes(msg.pack(mav))
            mav.seq = (mav.seq + 1) % 256
            return t.write(buf)

    def _timed_capable(self) -> bool:
        return self.timed_setpoints and isinstance(self._transport, UdpTransport)

    def _timed_ready(self) -> bool:
        t = self._transport
        return (
            self._timed is not None
            and self._timed.ready
            and isinstance(t, UdpTransport)
            and t.remote is not None
        )

    def _send_setpoint_at(self, sp: NedSetpoint, deadline_s: float) -> bool | None:
        """Encode now, send at ``deadline_s`` from the timed sender (see ``timed_send``);
        ``_tx_lock`` is held until it left, so that nothing sent by another thread (a command)
        overtakes it: its sequence number and signing timestamp stay in order; a thread waiting
        to send goes first. None: cancelled (nothing sent)."""
        t = self._transport
        timed = self._timed
        if not isinstance(t, UdpTransport) or timed is None:
            return self._send_setpoint(sp)
        msg = self._setpoint_message(sp)
        with self._tx_lock.after_waiters(deadline_s - YIELD_BEFORE_DEADLINE_S):
            mav = self._mav
            if self._signing:
                mav.signing.timestamp = max(mav.signing.timestamp, signing_timestamp_now())
            remote = t.remote
            fd = t.fileno()
            if remote is None or fd < 0:
                return False
            buf = bytes(msg.pack(mav))
            mav.seq = (mav.seq + 1) % 256
            n = timed.send_at(deadline_s, fd, buf, remote)
        if n == CANCELLED:
            return None
        return n == len(buf)

    def _send_heartbeat(self) -> bool:
        return self._send(
            self._mav.heartbeat_encode(
                px4.MAV_TYPE_ONBOARD_CONTROLLER,
                px4.MAV_AUTOPILOT_INVALID,
                0,
                0,
                px4.MAV_STATE_ACTIVE,
            )
        )

    def _send_setpoint(self, sp: NedSetpoint) -> bool:
        return self._send(self._setpoint_message(sp))

    def _setpoint_message(self, sp: NedSetpoint) -> Any:
        cfg = self.config
        yaw = sp.yaw_ned_rad
        return self._mav.set_position_target_local_ned_encode(
            0,  # time_boot_ms: PX4 stamps the setpoint on receipt
            cfg.system_id,
            cfg.autopilot_component_id,
            px4.MAV_FRAME_LOCAL_NED,
            px4.TYPE_MASK_PVA if yaw is None else px4.TYPE_MASK_PVA_YAW,
            *sp.position_ned_m,
            *sp.velocity_ned_m_s,
            *sp.accel_ned_m_s2,
            0.0 if yaw is None else yaw,
            0.0,
        )

    def _command_once(self, command: int, params: tuple[float, ...]) -> CommandResult:
        cfg = self.config
        pend = _Pending(command)
        with self._ack_cond:
            self._pending = pend
        try:
            for transmission in range(cfg.max_transmissions):
                if pend.progress_t is not None:
                    break  # IN_PROGRESS: no retransmission, wait below
                msg = self._mav.command_long_encode(
                    cfg.system_id,
                    cfg.autopilot_component_id,
                    command,
                    transmission,  # confirmation: 0 first, then 1, 2, ...
                    *params,
                )
                if not self._send(msg):
                    return CommandResult.LINK_DOWN
                self._c["commands_sent"] += 1
                result = self._wait_ack(pend, time.monotonic() + cfg.ack_timeout_s)
                if result is not None:
                    return result
            if pend.progress_t is not None:
                result = self._wait_ack(pend, None)
                if result is not None:
                    return result
            return CommandResult.TIMEOUT
        finally:
            with self._ack_cond:
                if self._pending is pend:
                    self._pending = None

    def _wait_ack(self, pend: _Pending, deadline: float | None) -> CommandResult | None:
        """The final result, or None at ``deadline`` (None: only the IN_PROGRESS deadline)."""
        with self._ack_cond:
            while pend.result is None and not self._closed:
                limit = deadline
                if pend.progress_t is not None:
                    limit = pend.progress_t + self.config.in_progress_timeout_s
                assert limit is not None
                remaining = limit - time.monotonic()
                if remaining <= 0:
                    return None
                self._ack_cond.wait(remaining)
            return pend.result if pend.result is not None else CommandResult.LINK_DOWN
