"""The autopilot link over MAVSDK 4.x (the ``mavsdk`` wheel: a native library, no server).

MAVSDK runs on a ``raw://`` connection: this link owns the transport (the same UDP / serial
transports as the pymavlink link) and pumps bytes into MAVSDK and out of it. That is what lets
it keep the contract MAVSDK alone cannot:

- MAVSDK sends a heartbeat of its own from its own thread, forever; the link withholds those
  (outgoing HEARTBEATs whose type is not MAV_TYPE_ONBOARD_CONTROLLER) and sends its companion
  heartbeat from the streamer loop instead, so that a dead loop stops the heartbeat too.
- MAVSDK's Offboard plugin re-sends the last setpoint from its own thread at 20 Hz and its
  ``stop()`` commands Hold: a client whose logic died keeps streaming (PX4's offboard-loss
  failsafe never fires). The link does not use it: setpoints go out through MavlinkDirect from
  the streamer loop, one per tick.
- Action's results fold TEMPORARILY_REJECTED into COMMAND_DENIED; commands go through
  MavlinkDirect ``send_command`` instead (MAVSDK retransmits and handles IN_PROGRESS; the link
  sees the real MAV_RESULT and applies the same retry policy as the pymavlink link).

Telemetry comes from MAVSDK's Telemetry plugin (its own decoding, independent of pymavlink's);
mode, armed state and failsafe from the heartbeat (MavlinkDirect subscription).
Differences from the pymavlink link: ``decode_errors`` stays 0 (MAVSDK drops bad frames
silently); the per-transmission ack timeout and transmission count are MAVSDK's own;
``health_ok`` means MAVSDK's gyro/accelerometer/magnetometer calibration and local position
checks pass, ``prearm_ok`` its ``is_armable``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import px4
from onboard.autopilot.config import LinkConfig
from onboard.autopilot.frames import NedSetpoint
from onboard.autopilot.link import AutopilotLink
from onboard.autopilot.model import CommandResult, LinkError
from onboard.autopilot.transport import Address, Transport, open_transport

log = logging.getLogger("onboard.autopilot")
_mavsdk_log = logging.getLogger("onboard.autopilot.mavsdk")

_STX_V1, _STX_V2 = 0xFE, 0xFD
_MSG_ID_HEARTBEAT = 0


def split_frames(data: bytes) -> Iterator[tuple[int, int, int, int, int]]:
    """MAVLink v1/v2 frames in ``data`` as (start, end, system id, component id, message id);
    bytes between frames are skipped, a truncated last frame is not reported. No CRC check."""
    i, n = 0, len(data)
    while i < n:
        stx = data[i]
        if stx == _STX_V2 and i + 10 <= n:
            length = data[i + 1]
            signed = data[i + 2] & 0x01
            end = i + 10 + length + 2 + (13 if signed else 0)
            if end > n:
                return
            msgid = data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16)
            yield i, end, data[i + 5], data[i + 6], msgid
            i = end
        elif stx == _STX_V1 and i + 6 <= n:
            length = data[i + 1]
            end = i + 6 + length + 2
            if end > n:
                return
            yield i, end, data[i + 3], data[i + 4], data[i + 5]
            i = end
        elif stx in (_STX_V1, _STX_V2):
            return
        else:
            i += 1


def heartbeat_type(frame: bytes) -> int:
    """MAV_TYPE of a HEARTBEAT frame (payload byte 4; MAVLink 2 trims trailing zeros)."""
    header = 10 if frame[0] == _STX_V2 else 6
    length = frame[1]
    return frame[header + 4] if length > 4 else 0


def _json_fields(fields: dict[str, float | int]) -> str:
    """JSON for MavlinkDirect: NaN (which JSON cannot carry) is sent as null, which libmav
    turns back into NaN."""
    clean = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in fields.items()
    }
    return json.dumps(clean, separators=(",", ":"))


_LOG_LEVELS = {0: logging.DEBUG, 1: logging.DEBUG, 2: logging.WARNING, 3: logging.ERROR}
_log_hooked = False
_log_hook_lock = threading.Lock()


def _route_mavsdk_logs() -> None:
    """Send MAVSDK's console output to Python logging (once per process)."""
    global _log_hooked
    with _log_hook_lock:
        if _log_hooked:
            return
        from mavsdk import log_subscribe

        def hook(level: Any, message: str, file: str | None, line: int) -> bool:
            _mavsdk_log.log(_LOG_LEVELS.get(int(level), logging.INFO), "%s", message)
            return True

        log_subscribe(hook)
        _log_hooked = True


class MavsdkLink(AutopilotLink):
    """``AutopilotLink`` over MAVSDK 4.x on a raw connection (see the module docstring)."""

    implementation = "mavsdk"

    def __init__(
        self,
        config: LinkConfig,
        sample_clock: Callable[[], float] = time.time,
        name: str | None = None,
        transport: Transport | None = None,
    ) -> None:
        super().__init__(config, sample_clock=sample_clock, name=name)
        self._transport: Transport | None = transport
        self._mavsdk: Any = None
        self._system: Any = None
        self._direct: Any = None
        self._telemetry: Any = None
        self._remote: Address | None = None
        # before MAVSDK has found the autopilot the heartbeat is encoded here
        self._mav = mavlink.MAVLink(
            None, srcSystem=config.own_system_id, srcComponent=config.component_id
        )
        self._pending_cmd: int | None = None
        self._pending_final = False
        self._ack_lock = threading.Lock()

    @property
    def transport_description(self) -> str:
        t = self._transport
        return ("mavsdk raw over " + t.description) if t is not None else self.config.url

    # ---- lifecycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        from mavsdk import Configuration, ConnectionResult, Mavsdk

        _route_mavsdk_logs()
        if self._transport is None:
            self._transport = open_transport(self.config.endpoint)
        cfg = self.config
        conf = Configuration.create_manual(cfg.own_system_id, cfg.component_id, False)
        self._mavsdk = Mavsdk(conf)
        result = self._mavsdk.add_any_connection("raw://")
        if result != ConnectionResult.SUCCESS:
            self._mavsdk.destroy()
            self._mavsdk = None
            raise LinkError(f"{self.name}: MAVSDK raw connection failed: {result!r}")
        # nothing goes out before the autopilot is found, so subscribing after is lossless
        self._mavsdk.subscribe_raw_bytes_to_be_sent(self._on_outgoing)
        self._start_thread(self._pump_loop, "autopilot-pump")
        self._start_thread(self._discover, "autopilot-discover")

    def _shutdown(self) -> None:
        if self._mavsdk is not None:
            self._mavsdk.destroy()  # unsubscribes and waits for running callbacks
            self._mavsdk = None
        self._direct = self._telemetry = self._system = None
        if self._transport is not None:
            self._transport.close()

    def _discover(self) -> None:
        """Wait for MAVSDK to see the autopilot, then subscribe."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.telemetry import Telemetry

        cfg = self.config
        while not self._stop.is_set():
            md = self._mavsdk
            if md is None:
                return
            for s in md.get_systems():
                if s.get_system_id() == cfg.system_id and s.has_autopilot():
                    self._system = s
                    break
            if self._system is not None:
                break
            self._stop.wait(0.02)
        if self._system is None:
            return
        direct = MavlinkDirect(self._system)
        tel = Telemetry(self._system)
        direct.subscribe_message("HEARTBEAT", self._on_heartbeat_msg)
        direct.subscribe_message("COMMAND_ACK", self._on_ack_msg)
        tel.subscribe_position_velocity_ned(self._on_position_velocity)
        tel.subscribe_attitude_euler(self._on_attitude_euler)
        tel.subscribe_landed_state(self._on_landed_state)
        tel.subscribe_health(self._on_health)
        tel.subscribe_battery(self._on_battery)
        tel.subscribe_home(self._on_home)
        self._telemetry = tel
        self._direct = direct
        log.debug("%s: MAVSDK found system %d", self.name, cfg.system_id)

    # ---- bytes in and out --------------------------------------------------------------------
    def _pump_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        cfg = self.config
        while not self._stop.is_set():
            try:
                chunks = transport.read(0.1)
            except LinkError:
                time.sleep(0.1)
                continue
            md = self._mavsdk
            if md is None:
                return
            for data, addr in chunks:
                if addr is not None and addr != self._remote:
                    for _, _, sysid, compid, _ in split_frames(data):
                        if sysid == cfg.system_id and compid == cfg.autopilot_component_id:
                            self._remote = addr
                            transport.set_remote(addr)
                            break
                md.pass_received_raw_bytes(data)

    def _on_outgoing(self, data: bytes) -> None:
        """MAVSDK's outgoing bytes (on a MAVSDK thread): withhold its own heartbeats."""
        transport = self._transport
        if transport is None:
            return
        keep: list[bytes] = []
        dropped = False
        for start, end, _, _, msgid in split_frames(data):
            frame = data[start:end]
            if msgid == _MSG_ID_HEARTBEAT and heartbeat_type(frame) != (
                px4.MAV_TYPE_ONBOARD_CONTROLLER
            ):
                self._c["foreign_heartbeats_dropped"] += 1
                dropped = True
                continue
            keep.append(frame)
        if not dropped:
            transport.write(data)
        elif keep:
            transport.write(b"".join(keep))

    # ---- telemetry callbacks (MAVSDK threads) ------------------------------------------------
    def _on_heartbeat_msg(self, msg: Any, _user: Any) -> None:
        cfg = self.config
        if msg.system_id != cfg.system_id or msg.component_id != cfg.autopilot_component_id:
            return
        try:
            f = json.loads(msg.fields_json)
            custom, base, status = (
                int(f["custom_mode"]),
                int(f["base_mode"]),
                int(f["system_status"]),
            )
        except (ValueError, KeyError, TypeError):
            self._rx_decode_error()
            return
        now = time.monotonic()
        self._rx(now)
        self._rx_heartbeat(now, custom, base, status)

    def _on_ack_msg(self, msg: Any, _user: Any) -> None:
        cfg = self.config
        if msg.system_id != cfg.system_id or msg.component_id != cfg.autopilot_component_id:
            return
        try:
            f = json.loads(msg.fields_json)
            command, result = int(f["command"]), int(f["result"])
            target_sys, target_comp = (
                int(f.get("target_system", 0)),
                int(f.get("target_component", 0)),
            )
        except (ValueError, KeyError, TypeError):
            self._rx_decode_error()
            return
        if target_sys not in (0, cfg.own_system_id) or target_comp not in (0, cfg.component_id):
            return
        with self._ack_lock:
            matched = self._pending_cmd == command and not self._pending_final
            if matched and result != CommandResult.IN_PROGRESS.value:
                self._pending_final = True
        self._rx_ack(time.monotonic(), command, matched)

    def _on_position_velocity(self, pv: Any, _user: Any) -> None:
        now = time.monotonic()
        p, v = pv.position, pv.velocity
        self._rx(now)
        self._rx_local_position(
            now,
            (float(p.north_m), float(p.east_m), float(p.down_m)),
            (float(v.north_m_s), float(v.east_m_s), float(v.down_m_s)),
        )

    def _on_attitude_euler(self, e: Any, _user: Any) -> None:
        now = time.monotonic()
        self._rx(now)
        self._rx_attitude(
            now, math.radians(e.roll_deg), math.radians(e.pitch_deg), math.radians(e.yaw_deg)
        )

    def _on_landed_state(self, ls: Any, _user: Any) -> None:
        self._rx_landed_state(time.monotonic(), int(ls))

    def _on_health(self, h: Any, _user: Any) -> None:
        ok = bool(
            h.is_gyrometer_calibration_ok
            and h.is_accelerometer_calibration_ok
            and h.is_magnetometer_calibration_ok
            and h.is_local_position_ok
        )
        self._rx_health(time.monotonic(), ok, bool(h.is_armable))

    def _on_battery(self, b: Any, _user: Any) -> None:
        rem = float(b.remaining_percent)
        volt = float(b.voltage_v)
        self._rx_battery(
            time.monotonic(),
            rem / 100.0 if math.isfinite(rem) and rem >= 0 else None,
            volt if math.isfinite(volt) and volt > 0 else None,
        )

    def _on_home(self, home: Any, _user: Any) -> None:
        alt = float(home.absolute_altitude_m)
        if math.isfinite(alt):
            self._rx_home(time.monotonic(), alt)

    # ---- sending -----------------------------------------------------------------------------
    def _send_direct(self, name: str, fields: dict[str, float | int]) -> bool:
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        direct = self._direct
        if direct is None:
            return False
        cfg = self.config
        msg = MavlinkMessage(
            name,
            cfg.own_system_id,
            cfg.component_id,
            cfg.system_id,
            cfg.autopilot_component_id,
            _json_fields(fields),
        )
        try:
            direct.send_message(msg)
        except (MavlinkDirectError, RuntimeError):
            return False
        return True

    def _send_heartbeat(self) -> bool:
        fields: dict[str, float | int] = {
            "type": px4.MAV_TYPE_ONBOARD_CONTROLLER,
            "autopilot": px4.MAV_AUTOPILOT_INVALID,
            "base_mode": 0,
            "custom_mode": 0,
            "system_status": px4.MAV_STATE_ACTIVE,
            "mavlink_version": 3,
        }
        if self._direct is not None:
            return self._send_direct("HEARTBEAT", fields)
        # MAVSDK has not found the autopilot yet: send it ourselves (a udpout peer may wait
        # for a first message)
        t = self._transport
        if t is None:
            return False
        hb = self._mav.heartbeat_encode(
            px4.MAV_TYPE_ONBOARD_CONTROLLER, px4.MAV_AUTOPILOT_INVALID, 0, 0, px4.MAV_STATE_ACTIVE
        )
        buf = bytes(hb.pack(self._mav))
        self._mav.seq = (self._mav.seq + 1) % 256
        return t.write(buf)

    def _send_setpoint(self, sp: NedSetpoint) -> bool:
        cfg = self.config
        yaw = sp.yaw_ned_rad
        n, e, d = sp.position_ned_m
        vn, ve, vd = sp.velocity_ned_m_s
        an, ae, ad = sp.accel_ned_m_s2
        return self._send_direct(
            "SET_POSITION_TARGET_LOCAL_NED",
            {
                "time_boot_ms": 0,  # PX4 stamps the setpoint on receipt
                "target_system": cfg.system_id,
                "target_component": cfg.autopilot_component_id,
                "coordinate_frame": px4.MAV_FRAME_LOCAL_NED,
                "type_mask": px4.TYPE_MASK_PVA if yaw is None else px4.TYPE_MASK_PVA_YAW,
                "x": n,
                "y": e,
                "z": d,
                "vx": vn,
                "vy": ve,
                "vz": vd,
                "afx": an,
                "afy": ae,
                "afz": ad,
                "yaw": 0.0 if yaw is None else yaw,
                "yaw_rate": 0.0,
            },
        )

    def _command_once(self, command: int, params: tuple[float, ...]) -> CommandResult:
        from mavsdk.plugins.mavlink_direct import (
            MavlinkDirectError,
            MavlinkDirectResult,
            MavlinkMessage,
        )

        direct = self._direct
        if direct is None:
            return CommandResult.LINK_DOWN
        cfg = self.config
        fields: dict[str, float | int] = {
            "target_system": cfg.system_id,
            "target_component": cfg.autopilot_component_id,
            "command": command,
            "confirmation": 0,
        }
        for i, p in enumerate(params, start=1):
            fields[f"param{i}"] = p
        msg = MavlinkMessage(
            "COMMAND_LONG",
            cfg.own_system_id,
            cfg.component_id,
            cfg.system_id,
            cfg.autopilot_component_id,
            _json_fields(fields),
        )
        with self._ack_lock:
            self._pending_cmd = command
            self._pending_final = False
        self._c["commands_sent"] += 1
        try:
            ack = direct.send_command(msg)
        except MavlinkDirectError as e:
            if e.result == MavlinkDirectResult.TIMEOUT:
                return CommandResult.TIMEOUT
            return CommandResult.LINK_DOWN
        except RuntimeError:  # destroyed under us (closing)
            return CommandResult.LINK_DOWN
        try:
            result = int(json.loads(ack.fields_json)["result"])
        except (ValueError, KeyError, TypeError):
            return CommandResult.FAILED
        return CommandResult.from_mav_result(result)
