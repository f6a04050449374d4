"""Byte transports under both link implementations: UDP (in/out) and a serial port.

- ``udpin``: bind ``host:port`` and send to the address the autopilot talks from (the link
  tells the transport once a valid message from the autopilot arrived: ``set_remote``), as
  MAVSDK's ``udpin://`` and PX4's API link (14540 + i) work.
- ``udpout``: send to ``host:port`` from an ephemeral port.
- ``serial``: a raw 8N1 tty (Xavier NX UART ``/dev/ttyTHS0``) opened with ``termios`` (no
  pyserial needed); reads return whatever bytes arrived (a stream: frames may be split).

``read`` waits at most ``timeout_s``; ``write`` never blocks for long (UDP datagrams; the tty in
non-blocking mode drops what does not fit and says so).
"""

from __future__ import annotations

import errno
import os
import select
import socket
import termios
import threading
import time
from abc import ABC, abstractmethod

from onboard.autopilot.config import Endpoint
from onboard.autopilot.model import LinkError

Address = tuple[str, int]


class Transport(ABC):
    """Bytes to and from the autopilot."""

    datagrams: bool
    """True: every chunk ``read`` returns holds whole frames (parse each on its own)."""

    drained: bool = True
    """Whether the last ``read`` left nothing behind that had arrived before it began (a read
    stops at a size limit; the link counts silence only up to a read that drained)."""

    @abstractmethod
    def read(self, timeout_s: float) -> list[tuple[bytes, Address | None]]:
        """Chunks received within ``timeout_s`` (empty on timeout or once closed)."""

    @abstractmethod
    def write(self, data: bytes) -> bool:
        """Send ``data``; False if there is nowhere to send yet or it could not be sent."""

    @abstractmethod
    def close(self) -> None: ...

    def set_remote(self, addr: Address | None) -> None:  # noqa: B027 - optional hook
        """(udpin) the autopilot's address, learned from a valid message."""

    @property
    def description(self) -> str:
        return type(self).__name__


class UdpTransport(Transport):
    datagrams = True

    def __init__(self, endpoint: Endpoint) -> None:
        if endpoint.kind not in ("udpin", "udpout"):
            raise ValueError(f"not a UDP endpoint: {endpoint}")
        self._kind = endpoint.kind
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            if endpoint.kind == "udpin":
                sock.bind((endpoint.host, endpoint.port))
                self._remote: Address | None = None
            else:
                sock.bind(("0.0.0.0", 0))
                self._remote = (endpoint.host, endpoint.port)
        except OSError as e:
            sock.close()
            where = f"{endpoint.host}:{endpoint.port}"
            raise LinkError(f"cannot open UDP {endpoint.kind} {where}: {e.strerror or e}") from e
        sock.setblocking(False)
        self._sock = sock
        self._closed = False
        self.local_address: Address = sock.getsockname()[:2]

    @property
    def description(self) -> str:
        return f"udp {self._kind} local {self.local_address[0]}:{self.local_address[1]}" + (
            f" remote {self._remote[0]}:{self._remote[1]}" if self._remote else ""
        )

    @property
    def remote(self) -> Address | None:
        return self._remote

    def set_remote(self, addr: Address | None) -> None:
        if self._kind == "udpin" and addr is not None:
            self._remote = addr

    def fileno(self) -> int:
        """The socket's descriptor (-1 once closed): the streamer's timed sender sends on it."""
        return -1 if self._closed else self._sock.fileno()

    def read(self, timeout_s: float) -> list[tuple[bytes, Address | None]]:
        if self._closed:
            return []
        out: list[tuple[bytes, Address | None]] = []
        try:
            ready, _, _ = select.select([self._sock], [], [], max(timeout_s, 0.0))
        except (OSError, ValueError):  # closed under us
            return out
        if not ready:
            self.drained = True  # nothing came for timeout_s
            return out
        self.drained = False
        while len(out) < 256:
            try:
                data, addr = self._sock.recvfrom(65535)
            except BlockingIOError:
                self.drained = True
                break
            except InterruptedError:
                break
            except OSError:  # an ICMP error surfacing, or closed
                break
            out.append((data, (addr[0], addr[1])))
        return out

    def write(self, data: bytes) -> bool:
        remote = self._remote
        if remote is None or self._closed:
            return False
        try:
            self._sock.sendto(data, remote)
        except OSError:  # e.g. ECONNREFUSED from an earlier datagram, buffer full
            return False
        return True

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()


def _baud_constant(baud: int) -> int:
    const = getattr(termios, f"B{baud}", None)
    if not isinstance(const, int):
        raise LinkError(f"baud: {baud} is not supported by this system's termios")
    return const


class SerialTransport(Transport):
    """A raw tty at ``baud``, 8 data bits, no parity, 1 stop bit, no flow control."""

    datagrams = False

    def __init__(self, endpoint: Endpoint) -> None:
        if endpoint.kind != "serial":
            raise ValueError(f"not a serial endpoint: {endpoint}")
        self.device = endpoint.device
        self.baud = endpoint.baud
        speed = _baud_constant(endpoint.baud)
        try:
            fd = os.open(endpoint.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as e:
            raise LinkError(
                f"cannot open serial device {endpoint.device}: {e.strerror or e}"
            ) from e
        try:
            attrs = termios.tcgetattr(fd)
            attrs[0] = 0  # iflag: no translation, no software flow control
            attrs[1] = 0  # oflag: raw output
            attrs[2] = termios.CS8 | termios.CREAD | termios.CLOCAL  # cflag: 8N1, no modem
            attrs[3] = 0  # lflag: no echo, no canonical mode, no signals
            attrs[4] = speed
            attrs[5] = speed
            attrs[6][termios.VMIN] = 0
            attrs[6][termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
            termios.tcflush(fd, termios.TCIOFLUSH)
        except (termios.error, OSError) as e:
            os.close(fd)
            raise LinkError(
                f"cannot configure serial device {endpoint.device} at {endpoint.baud} baud: {e}"
            ) from e
        self._fd = fd
        self._closed = False
        self._write_lock = threading.Lock()

    @property
    def description(self) -> str:
        return f"serial {self.device} {self.baud} baud"

    def read(self, timeout_s: float) -> list[tuple[bytes, Address | None]]:
        if self._closed:
            return []
        try:
            ready, _, _ = select.select([self._fd], [], [], max(timeout_s, 0.0))
        except (OSError, ValueError):
            return []
        if not ready:
            self.drained = True
            return []
        try:
            data = os.read(self._fd, 65536)
        except BlockingIOError:
            self.drained = True
            return []
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EINTR):
                return []
            raise LinkError(f"serial device {self.device}: {e.strerror or e}") from e
        self.drained = len(data) < 65536
        return [(data, None)] if data else []

    def write(self, data: bytes) -> bool:
        if self._closed:
            return False
        view = memoryview(data)
        deadline = time.monotonic() + 0.02
        with self._write_lock:  # frames from different threads must not interleave
            while view:
                try:
                    n = os.write(self._fd, view)
                except BlockingIOError:
                    n = 0
                except OSError:
                    return False
                view = view[n:]
                if view:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return False  # the tty is not draining: drop the rest of the frame
                    select.select([], [self._fd], [], remaining)
        return True

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            os.close(self._fd)


def open_transport(endpoint: Endpoint) -> Transport:
    if endpoint.kind == "serial":
        return SerialTransport(endpoint)
    return UdpTransport(endpoint)
