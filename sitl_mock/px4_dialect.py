"""The MAVLink dialect the mock speaks, and a fast MAVLink 2 framer for its telemetry.

PX4 v1.16 is built with MAVLink's ``development`` dialect (``common`` plus work-in-progress
messages such as CURRENT_MODE, which PX4 streams at 0.5 Hz). pymavlink 2.4.50 ships
``development`` (and ``all``), so the mock and its test client use ``development``; MAVSDK, which
knows these messages or drops what it does not know, is unaffected.

Two messages a real PX4 v1.16 sends are missing from pymavlink 2.4.50's dialect files:
PROTOCOL_VERSION (300, PX4 answers MAV_CMD_REQUEST_PROTOCOL_VERSION with it) and
LINK_NODE_STATUS (8, streamed at 1 Hz on the onboard link). They are defined here with the
field layout and CRC extra of the MAVLink definitions (a test derives the CRC extras from the
XML definitions with pymavlink's own parser) and registered in the development dialect's
decoder table, so that pymavlink decodes them too (only ids the dialect does not define are
added: importing this module never changes how a known message is decoded).

``MessageEncoder`` / ``frame`` build MAVLink 2 frames straight from field values, byte for byte
what pymavlink's ``encode(...).pack(mav)`` produces (a test compares them), without creating a
message object per frame: the mock sends ~400 frames per second per vehicle. ``MessageDecoder``
is the reverse for the one message a companion streams at tens of hertz
(SET_POSITION_TARGET_LOCAL_NED): a datagram holding exactly one unsigned frame of it is decoded
into the same message object pymavlink would make (a test compares them), anything else is
left to pymavlink's parser.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable, Sequence
from typing import Any

from pymavlink.dialects.v20 import development as mavlink

try:  # pymavlink uses fastcrc too when it is installed
    from fastcrc import crc16 as _fastcrc16

    _mcrf4xx: Callable[[bytes, int], int] | None = _fastcrc16.mcrf4xx
except ImportError:  # pragma: no cover - depends on the environment
    _mcrf4xx = None

MAVLINK_MSG_ID_LINK_NODE_STATUS = 8
MAVLINK_MSG_ID_PROTOCOL_VERSION = 300


class MAVLink_link_node_status_message(mavlink.MAVLink_message):  # noqa: N801 - pymavlink naming
    """LINK_NODE_STATUS (8): status of one MAVLink link (development.xml)."""

    id = MAVLINK_MSG_ID_LINK_NODE_STATUS
    msgname = "LINK_NODE_STATUS"
    fieldnames = [
        "timestamp",
        "tx_buf",
        "rx_buf",
        "tx_rate",
        "rx_rate",
        "rx_parse_err",
        "tx_overflows",
        "rx_overflows",
        "messages_sent",
        "messages_received",
        "messages_lost",
    ]
    ordered_fieldnames = [
        "timestamp",
        "tx_rate",
        "rx_rate",
        "messages_sent",
        "messages_received",
        "messages_lost",
        "rx_parse_err",
        "tx_overflows",
        "rx_overflows",
        "tx_buf",
        "rx_buf",
    ]
    fieldtypes = [
        "uint64_t",
        "uint8_t",
        "uint8_t",
        "uint32_t",
        "uint32_t",
        "uint16_t",
        "uint16_t",
        "uint16_t",
        "uint32_t",
        "uint32_t",
        "uint32_t",
    ]
    fielddisplays_by_name: dict[str, str] = {}
    fieldenums_by_name: dict[str, str] = {}
    fieldunits_by_name: dict[str, str] = {
        "timestamp": "ms",
        "tx_buf": "%",
        "rx_buf": "%",
        "tx_rate": "bytes/s",
        "rx_rate": "bytes/s",
        "rx_parse_err": "bytes",
        "tx_overflows": "bytes",
        "rx_overflows": "bytes",
    }
    native_format = bytearray(b"<QIIIIIHHHBB")
    orders = [0, 9, 10, 1, 2, 6, 7, 8, 3, 4, 5]
    lengths = [1] * 11
    array_lengths = [0] * 11
    crc_extra = 117
    unpacker = struct.Struct("<QIIIIIHHHBB")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        timestamp: int,
        tx_buf: int,
        rx_buf: int,
        tx_rate: int,
        rx_rate: int,
        rx_parse_err: int,
        tx_overflows: int,
        rx_overflows: int,
        messages_sent: int,
        messages_received: int,
        messages_lost: int,
    ) -> None:
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = self.instance_field
        self._instance_offset = self.instance_offset
        self.timestamp = timestamp
        self.tx_buf = tx_buf
        self.rx_buf = rx_buf
        self.tx_rate = tx_rate
        self.rx_rate = rx_rate
        self.rx_parse_err = rx_parse_err
        self.tx_overflows = tx_overflows
        self.rx_overflows = rx_overflows
        self.messages_sent = messages_sent
        self.messages_received = messages_received
        self.messages_lost = messages_lost

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        return bytes(
            self._pack(
                mav,
                self.crc_extra,
                self.unpacker.pack(
                    self.timestamp,
                    self.tx_rate,
                    self.rx_rate,
                    self.messages_sent,
                    self.messages_received,
                    self.messages_lost,
                    self.rx_parse_err,
                    self.tx_overflows,
                    self.rx_overflows,
                    self.tx_buf,
                    self.rx_buf,
                ),
                force_mavlink1=force_mavlink1,
            )
        )


class MAVLink_protocol_version_message(mavlink.MAVLink_message):  # noqa: N801 - pymavlink naming
    """PROTOCOL_VERSION (300): the MAVLink versions a component supports."""

    id = MAVLINK_MSG_ID_PROTOCOL_VERSION
    msgname = "PROTOCOL_VERSION"
    fieldnames = [
        "version",
        "min_version",
        "max_version",
        "spec_version_hash",
        "library_version_hash",
    ]
    ordered_fieldnames = list(fieldnames)
    fieldtypes = ["uint16_t", "uint16_t", "uint16_t", "uint8_t", "uint8_t"]
    fielddisplays_by_name: dict[str, str] = {}
    fieldenums_by_name: dict[str, str] = {}
    fieldunits_by_name: dict[str, str] = {}
    native_format = bytearray(b"<HHHBB")
    orders = [0, 1, 2, 3, 4]
    lengths = [1, 1, 1, 8, 8]
    array_lengths = [0, 0, 0, 8, 8]
    crc_extra = 217
    unpacker = struct.Struct("<HHH8B8B")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        version: int,
        min_version: int,
        max_version: int,
        spec_version_hash: Sequence[int],
        library_version_hash: Sequence[int],
    ) -> None:
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = self.instance_field
        self._instance_offset = self.instance_offset
        self.version = version
        self.min_version = min_version
        self.max_version = max_version
        self.spec_version_hash = list(spec_version_hash)
        self.library_version_hash = list(library_version_hash)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        return bytes(
            self._pack(
                mav,
                self.crc_extra,
                self.unpacker.pack(
                    self.version,
                    self.min_version,
                    self.max_version,
                    *self.spec_version_hash,
                    *self.library_version_hash,
                ),
                force_mavlink1=force_mavlink1,
            )
        )


EXTRA_MESSAGES: tuple[type[Any], ...] = (
    MAVLink_link_node_status_message,
    MAVLink_protocol_version_message,
)
for _cls in EXTRA_MESSAGES:
    if _cls.id not in mavlink.mavlink_map:
        mavlink.mavlink_map[_cls.id] = _cls
    setattr(mavlink, f"MAVLINK_MSG_ID_{_cls.msgname}", _cls.id)


def message_class(msg_id: int) -> type[Any]:
    """The pymavlink class of a message id (KeyError if the dialect lacks it)."""
    cls: type[Any] = mavlink.mavlink_map[msg_id]
    return cls


def message_id_by_name(name: str) -> int:
    """MAVLINK_MSG_ID of a message name such as ``"ATTITUDE"`` (ValueError if unknown)."""
    mid = getattr(mavlink, f"MAVLINK_MSG_ID_{name.upper()}", None)
    if mid is None:
        raise ValueError(f"unknown MAVLink message {name!r}")
    return int(mid)


def new_mavlink(system_id: int, component_id: int) -> Any:
    """A pymavlink MAVLink 2 endpoint object of the mock's dialect (no file: frames only)."""
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.robust_parsing = True
    return mav


_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")


class MessageEncoder:
    """Frames one message type from its field values given in declaration order (the order
    of pymavlink's ``<name>_encode`` arguments; arrays as sequences, ``char`` fields as bytes)."""

    __slots__ = ("cls", "msg_id", "name", "_crc_extra", "_pack", "_plan", "_getter", "_n")

    def __init__(self, cls: type[Any]) -> None:
        self.cls = cls
        self.msg_id = int(cls.id)
        self.name = str(cls.msgname)
        self._crc_extra = bytes([cls.crc_extra])
        self._pack = cls.unpacker.pack
        n = len(cls.fieldnames)
        self._n = n
        # declaration indices in wire order: orders[d] is the wire position of field d
        wire = sorted(range(n), key=lambda d: cls.orders[d])
        # array_lengths is indexed by wire position, fieldtypes by declaration index
        plan = tuple(
            (d, 0 if cls.fieldtypes[d] == "char" else int(cls.array_lengths[w]))
            for w, d in enumerate(wire)
        )
        self._plan = plan
        flat = all(length == 0 for _, length in plan)
        self._getter: Callable[[Sequence[Any]], Sequence[Any]] | None = None
        if flat:
            self._getter = operator.itemgetter(*wire) if n > 1 else (lambda a: (a[0],))

    def payload(self, args: Sequence[Any]) -> bytes:
        """The full (untrimmed) payload of the message with these field values."""
        if len(args) != self._n:
            raise ValueError(f"{self.name}: {self._n} fields expected, got {len(args)}")
        if self._getter is not None:
            return bytes(self._pack(*self._getter(args)))
        vals: list[Any] = []
        for d, length in self._plan:
            if length:
                v = args[d]
                if len(v) != length:
                    raise ValueError(f"{self.name}: field {d} needs {length} values")
                vals.extend(v)
            else:
                vals.append(args[d])
        return bytes(self._pack(*vals))


def frame(mav: Any, enc: MessageEncoder, args: Sequence[Any]) -> bytes:
    """One MAVLink 2 frame from ``mav`` (its ids, sequence and signing); advances the sequence.

    Signed links go through pymavlink's own packer (signatures, timestamps)."""
    if mav.signing.sign_outgoing or _mcrf4xx is None:
        buf = bytes(enc.cls(*args).pack(mav))
    else:
        payload = enc.payload(args).rstrip(b"\x00") or b"\x00"  # MAVLink 2 trims trailing zeros
        mid = enc.msg_id
        body = (
            _HEADER.pack(
                253,
                len(payload),
                0,
                0,
                mav.seq,
                mav.srcSystem,
                mav.srcComponent,
                mid & 0xFFFF,
                mid >> 16,
            )
            + payload
        )
        buf = body + _CRC.pack(_mcrf4xx(body[1:] + enc._crc_extra, 0xFFFF))
    mav.seq = (mav.seq + 1) % 256
    return buf


class MessageDecoder:
    """Decodes a datagram that holds exactly one unsigned MAVLink 2 frame of one message type
    (no arrays or strings), checking the CRC as pymavlink does; None for anything else."""

    __slots__ = ("cls", "msg_id", "_crc_extra", "_unpack", "_size", "_orders")

    def __init__(self, cls: type[Any]) -> None:
        if any(length != 1 for length in cls.lengths):
            raise ValueError(f"{cls.msgname}: arrays are not supported by the fast decoder")
        self.cls = cls
        self.msg_id = int(cls.id)
        self._crc_extra = bytes([cls.crc_extra])
        self._unpack = cls.unpacker.unpack
        self._size = int(cls.unpacker.size)
        self._orders = tuple(int(o) for o in cls.orders)

    def decode(self, data: bytes) -> Any | None:
        n = len(data)
        if n < 12 or data[0] != 253 or data[2] != 0 or n != data[1] + 12 or _mcrf4xx is None:
            return None  # not one unsigned MAVLink 2 frame
        if data[7] | (data[8] << 8) | (data[9] << 16) != self.msg_id:
            return None
        if _mcrf4xx(data[1:-2] + self._crc_extra, 0xFFFF) != data[-2] | (data[-1] << 8):
            return None  # let pymavlink's parser count it
        payload = data[10:-2]
        if len(payload) < self._size:
            payload += bytes(self._size - len(payload))  # MAVLink 2 trimmed trailing zeros
        t = self._unpack(payload[: self._size])
        msg = self.cls(*[t[o] for o in self._orders])
        msg._header = mavlink.MAVLink_header(
            self.msg_id, 0, data[3], data[1], data[4], data[5], data[6]
        )
        msg._msgbuf = bytearray(data)
        msg._payload = data[6:-2]
        msg._crc = data[-2] | (data[-1] << 8)
        msg._signed = False
        return msg
