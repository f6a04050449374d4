"""The command protocol of both link implementations against a scripted autopilot: IN_PROGRESS,
retransmission, a late duplicate ACK, ACKs for someone else. The scripted autopilot is an
in-memory transport (MAVLink bytes both ways), so each case is exact and quick."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Literal

import pytest
from pymavlink.dialects.v20 import common as mavlink

from onboard.autopilot import CommandError, CommandResult, FlightMode, LinkConfig
from onboard.autopilot.link import AutopilotLink
from onboard.autopilot.mavsdk_link import MavsdkLink
from onboard.autopilot.pymavlink_link import PymavlinkLink
from onboard.autopilot.transport import Address, Transport

IMPLEMENTATIONS: list[Literal["pymavlink", "mavsdk"]] = ["pymavlink", "mavsdk"]
VEHICLE: Address = ("10.0.0.1", 14580)

# answer(command, confirmation) -> [(delay_s, MAV_RESULT, target_component), ...]
Script = Callable[[int, int], list[tuple[float, int, int]]]


class ScriptedAutopilot(Transport):
    """System 1 component 1: heartbeats and positions at 20 Hz, COMMAND_ACKs as scripted."""

    datagrams = True

    def __init__(self, script: Script) -> None:
        self.script = script
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.lock = threading.Lock()
        self.due: list[tuple[float, bytes]] = []
        self.next_tick = time.monotonic()
        self.commands: list[tuple[int, int]] = []  # (command, confirmation) received
        self.closed = False

    def _encode(self, msg: Any) -> bytes:
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def read(self, timeout_s: float) -> list[tuple[bytes, Address | None]]:
        end = time.monotonic() + timeout_s
        while not self.closed:
            now = time.monotonic()
            out: list[tuple[bytes, Address | None]] = []
            with self.lock:
                if now >= self.next_tick:
                    self.next_tick = now + 0.05
                    out.append(
                        (self._encode(self.mav.heartbeat_encode(2, 12, 29, 0x3040000, 3)), VEHICLE)
                    )
                    out.append(
                        (
                            self._encode(
                                self.mav.local_position_ned_encode(
                                    int(now * 1e3) & 0xFFFFFFFF, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0
                                )
                            ),
                            VEHICLE,
                        )
                    )
                ready = [d for d in self.due if d[0] <= now]
                self.due = [d for d in self.due if d[0] > now]
            out.extend((data, VEHICLE) for _, data in sorted(ready))
            if out:
                return out
            if now >= end:
                return []
            time.sleep(0.002)
        return []

    def write(self, data: bytes) -> bool:
        p = self.parser
        p.buf = bytearray()
        p.buf_index = 0
        p.expected_length = mavlink.HEADER_LEN_V1 + 2
        now = time.monotonic()
        for m in p.parse_buffer(data) or []:
            if m.get_type() != "COMMAND_LONG":
                continue
            cmd, conf = int(m.command), int(m.confirmation)
            with self.lock:
                self.commands.append((cmd, conf))
                for delay, result, comp in self.script(cmd, conf):
                    ack = self._encode(
                        self.mav.command_ack_encode(cmd, result, 0, 0, m.get_srcSystem(), comp)
                    )
                    self.due.append((now + delay, ack))
        return True

    def close(self) -> None:
        self.closed = True

    def of(self, command: int) -> list[int]:
        return [conf for cmd, conf in self.commands if cmd == command]


def make_link(impl: str, script: Script, **kw: Any) -> tuple[AutopilotLink, ScriptedAutopilot]:
    ap = ScriptedAutopilot(script)
    cfg = LinkConfig(
        url="udpin://127.0.0.1:0",
        implementation=impl,  # type: ignore[arg-type]
        telemetry_rates_hz=(),
        ack_timeout_s=0.3,
        in_progress_timeout_s=1.0,
        **kw,
    )
    cls = PymavlinkLink if impl == "pymavlink" else MavsdkLink
    link = cls(cfg, transport=ap)
    link.connect(10.0)
    return link, ap


ARM = 400


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_in_progress_then_accepted(implementation: str) -> None:
    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        if cmd == ARM:
            return [(0.01, 5, 191), (0.6, 5, 191), (0.9, 0, 191)]  # IN_PROGRESS ... ACCEPTED
        return [(0.01, 0, 191)]

    link, ap = make_link(implementation, script)
    try:
        link.arm()  # 0.9 s: longer than an ack timeout, accepted all the same
        assert ap.of(ARM) == [0]  # no retransmission after IN_PROGRESS
    finally:
        link.close()


@pytest.mark.timeout(60)
def test_in_progress_without_an_end_times_out() -> None:
    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        return [(0.01, 5, 191)] if cmd == ARM else [(0.01, 0, 191)]

    link, ap = make_link("pymavlink", script)
    try:
        t0 = time.monotonic()
        with pytest.raises(CommandError) as e:
            link.arm()
        assert e.value.result == CommandResult.TIMEOUT
        assert time.monotonic() - t0 >= link.config.in_progress_timeout_s
        assert ap.of(ARM) == [0]
    finally:
        link.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_retransmitted_until_answered(implementation: str) -> None:
    seen = {"n": 0}

    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        if cmd != ARM:
            return [(0.01, 0, 191)]
        seen["n"] += 1
        return [(0.01, 0, 191)] if seen["n"] >= 2 else []  # the first transmission is lost

    link, ap = make_link(implementation, script)
    try:
        link.arm()
        confs = ap.of(ARM)
        assert len(confs) == 2
        if implementation == "pymavlink":  # MAVSDK re-sends the message as given
            assert confs == [0, 1]
    finally:
        link.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_no_answer_is_a_timeout(implementation: str) -> None:
    link, ap = make_link(implementation, lambda cmd, conf: [])
    try:
        with pytest.raises(CommandError) as e:
            link.arm()
        assert e.value.result == CommandResult.TIMEOUT
        assert "MAV_CMD_COMPONENT_ARM_DISARM(arm)" in str(e.value)
        assert len(ap.of(ARM)) >= 2  # retransmitted before giving up
    finally:
        link.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_late_duplicate_ack_is_not_taken_for_the_next_command(implementation: str) -> None:
    answers = iter([[(0.01, 0, 191), (0.08, 0, 191)], [(0.15, 2, 191)]])

    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        # the first set-mode: accepted, and accepted again 80 ms later (as PX4 does);
        # the second: denied, 150 ms after it was sent
        return next(answers) if cmd == 176 else [(0.01, 0, 191)]

    link, ap = make_link(implementation, script)
    try:
        link.set_mode(FlightMode.HOLD)
        with pytest.raises(CommandError) as e:
            link.set_mode(FlightMode.OFFBOARD)
        assert e.value.result == CommandResult.DENIED
        assert link.counters().acks_unmatched >= 1
    finally:
        link.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_acks_for_someone_else_are_ignored(implementation: str) -> None:
    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        return [(0.01, 0, 190)]  # addressed to component 190, not this link (191)

    link, _ = make_link(implementation, script)
    try:
        with pytest.raises(CommandError) as e:
            link.arm()
        assert e.value.result == CommandResult.TIMEOUT
    finally:
        link.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_temporarily_rejected_is_retried(implementation: str) -> None:
    calls = {"n": 0}

    def script(cmd: int, conf: int) -> list[tuple[float, int, int]]:
        if cmd != ARM:
            return [(0.01, 0, 191)]
        calls["n"] += 1
        return [(0.01, 1 if calls["n"] < 3 else 0, 191)]

    link, _ = make_link(implementation, script, command_retries=3, retry_delay_s=0.05)
    try:
        link.arm()
        assert link.counters().command_retries == 2
    finally:
        link.close()
