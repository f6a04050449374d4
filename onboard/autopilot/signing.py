"""MAVLink 2 message signing between the companion link and the autopilot.

Which autopilots sign: PX4 v1.16 and older have no MAVLink signing (their receiver ignores
SETUP_SIGNING); PX4 v1.17 brings it (PX4-Autopilot PR #25284), ArduPilot has had it for years.
MAVSDK 4.x has no signing API, so only the pymavlink implementation can sign.

The key is a 32-byte secret in a file readable by its owner only (mode 0600 or 0400): either the
32 raw bytes or 64 hexadecimal digits (the form the SITL mock's ``--signing-key`` and PX4's
parameters take). It is read when the link is built, is never logged, and appears in no
``repr``, record or error message.

Verification (``verify``): a frame's signature is the first 6 bytes of SHA-256(key || frame up
to and including the timestamp); its 48-bit timestamp (10 us units since 2015-01-01) must
advance per stream (link id, system, component), and a stream not seen before must not be more
than a minute older than the newest timestamp seen. Unlike pymavlink's own check, a stream's
timestamp advances only once the signature verified, so forged frames cannot lock the autopilot
out.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import struct
import time
from dataclasses import dataclass, field

SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01T00:00:00Z
NEW_STREAM_MAX_AGE = 60 * 100_000  # one minute in 10 us units
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01

SIGNING_VERSIONS = (
    "PX4 v1.17 or newer (PX4 v1.16 and older have no MAVLink signing: they ignore "
    "SETUP_SIGNING and never sign), or ArduPilot"
)


class SigningKeyError(ValueError):
    """The key file is missing, readable by others or malformed (never shows the key)."""


def signing_timestamp_now(now_unix_s: float | None = None) -> int:
    """MAVLink signing timestamp: 10 us units since 2015-01-01."""
    t = time.time() if now_unix_s is None else now_unix_s
    return int((t - SIGNING_EPOCH_UNIX_S) * 100_000)


def load_signing_key(path: str, field_name: str = "signing_key_file") -> bytes:
    """The 32-byte key in ``path``; ``SigningKeyError`` naming ``field_name`` if the file is
    missing, not a regular file, readable or writable by group or others, or not 32 raw bytes
    nor 64 hexadecimal digits."""
    if not isinstance(path, str) or not path:
        raise SigningKeyError(f"{field_name}: expected a file path, got {path!r}")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError as e:
        raise SigningKeyError(f"{field_name}: cannot open {path!r}: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SigningKeyError(f"{field_name}: {path!r} is not a regular file")
        if st.st_mode & 0o077:
            raise SigningKeyError(
                f"{field_name}: {path!r} has permissions {stat.S_IMODE(st.st_mode):04o}; a "
                f"signing key must be readable by its owner only (chmod 600 {path})"
            )
        data = os.read(fd, 200)
    finally:
        os.close(fd)
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(
        f"{field_name}: {path!r} must hold the 32-byte key as 32 raw bytes or 64 hexadecimal "
        f"digits ({len(data)} bytes found)"
    )


@dataclass
class Verifier:
    """Checks signatures of incoming frames (see the module docstring). Not thread-safe: one
    receiving thread. ``key`` is kept out of ``repr``."""

    key: bytes = field(repr=False)
    newest: int = 0
    streams: dict[tuple[int, int, int], int] = field(default_factory=dict)

    def verify(self, frame: bytes | bytearray, src_system: int, src_component: int) -> bool:
        """True if ``frame`` (a whole signed MAVLink 2 frame) is signed with the key and its
        timestamp is fresh for its stream."""
        if len(frame) < SIGNATURE_LEN + 12:
            return False
        digest = hashlib.sha256(self.key + bytes(frame[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(frame[-6:])):
            return False
        link_id = frame[-SIGNATURE_LEN]
        lo, hi = struct.unpack("<IH", bytes(frame[-12:-6]))
        stamp = lo + (hi << 32)
        stream = (link_id, src_system, src_component)
        last = self.streams.get(stream)
        if last is not None and stamp <= last:
            return False  # a replay, or an old frame
        if last is None and stamp + NEW_STREAM_MAX_AGE < self.newest:
            return False
        self.streams[stream] = stamp
        self.newest = max(self.newest, stamp)
        return True


def frame_origin(frame: bytes | bytearray) -> tuple[int, int, bool] | None:
    """``(system, component, signed)`` from a MAVLink 2 frame's header, None for anything else
    (a MAVLink 1 frame has no signature)."""
    if len(frame) < 10 or frame[0] != 0xFD:
        return None
    return int(frame[5]), int(frame[6]), bool(frame[2] & IFLAG_SIGNED)
