"""The live view: a stdlib WebSocket client speaks the Foxglove WebSocket protocol to the view's
server, subscribes, and decodes the scene messages (protobuf, field numbers read from the schema
the server advertises)."""

from __future__ import annotations

import base64
import json
import os
import signal
import socket
import struct
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from gcs.view import SWARM_TOPIC, WORLD_TOPIC, SceneInput, SwarmView
from onboard.planner.trajectory import Trajectory
from onboard.world import World

DEADLINE_S = 30.0

# --- a minimal WebSocket client (RFC 6455) -----------------------------------------------------


class WsClient:
    def __init__(self, port: int, protocol: str = "foxglove.sdk.v1") -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {protocol}\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, "connection closed during the handshake"
            head += chunk
        assert head.startswith(b"HTTP/1.1 101"), head
        assert protocol.encode() in head

    def _exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            assert chunk, "connection closed"
            buf += chunk
        return buf

    def recv(self) -> tuple[int, bytes]:
        """One message: (opcode, payload), continuation frames joined; pings answered."""
        opcode, data = None, b""
        while True:
            b0, b1 = self._exact(2)
            fin, op = b0 & 0x80, b0 & 0x0F
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._exact(8))[0]
            mask = self._exact(4) if b1 & 0x80 else None
            payload = self._exact(n)
            if mask:
                payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
            if op == 0x9:  # ping -> pong
                self._send(0xA, payload)
                continue
            if op != 0x0:
                opcode = op
            data += payload
            if fin:
                assert opcode is not None
                return opcode, data

    def _send(self, op: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | op])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        body = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
        self.sock.sendall(head + mask + body)

    def send_json(self, obj: Any) -> None:
        self._send(0x1, json.dumps(obj).encode())

    def close(self) -> None:
        self.sock.close()


# --- a minimal protobuf reader ------------------------------------------------------------------


def sigint_default() -> None:
    """In the child before exec: SIGINT back to its default, so that Python installs its Ctrl-C
    handler (a shell starting a job in the background, as CI runners may, leaves SIGINT
    ignored, and an ignored SIGINT stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def pb_fields(buf: bytes) -> dict[int, list[Any]]:
    """field number -> values (ints for varints, bytes for the rest)."""
    out: dict[int, list[Any]] = {}
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        v: Any
        if wt == 0:
            v, i = _varint(buf, i)
        elif wt == 1:
            v, i = buf[i : i + 8], i + 8
        elif wt == 2:
            n, i = _varint(buf, i)
            v, i = buf[i : i + n], i + n
        elif wt == 5:
            v, i = buf[i : i + 4], i + 4
        else:
            raise AssertionError(f"wire type {wt}")
        out.setdefault(num, []).append(v)
    return out


def field_numbers(descriptor_set: bytes) -> dict[str, dict[str, int]]:
    """message name -> field name -> number, from a FileDescriptorSet."""
    out: dict[str, dict[str, int]] = {}
    for file in pb_fields(descriptor_set).get(1, []):
        for msg in pb_fields(file).get(4, []):
            m = pb_fields(msg)
            name = m[1][0].decode()
            out[name] = {}
            for fd in m.get(2, []):
                f = pb_fields(fd)
                out[name][f[1][0].decode()] = f[3][0]
    return out


class Decoder:
    def __init__(self, schema_b64: str) -> None:
        self.n = field_numbers(base64.b64decode(schema_b64))

    def get(self, buf: bytes, msg: str, name: str) -> list[Any]:
        return pb_fields(buf).get(self.n[msg][name], [])

    def double(self, buf: bytes, msg: str, name: str) -> float:
        v = self.get(buf, msg, name)
        return struct.unpack("<d", v[0])[0] if v else 0.0

    def vec(self, buf: bytes, msg: str = "Vector3") -> np.ndarray:
        return np.array([self.double(buf, msg, k) for k in ("x", "y", "z")])


# --- the test ----------------------------------------------------------------------------------


@pytest.fixture
def client_of() -> Iterator[Any]:
    clients: list[WsClient] = []

    def make(port: int) -> WsClient:
        c = WsClient(port)
        clients.append(c)
        return c

    yield make
    for c in clients:
        c.close()


def test_view_serves_scene_updates(client_of: Any) -> None:
    now = 1.75e9
    c = np.zeros((2, 6, 3))
    c[:, 0] = [[0.0, 1.0, 1.5], [2.0, 1.0, 1.5]]
    c[:, 1] = [1.0, 0.0, 0.0]  # 1 m/s along x for 2 s
    traj = Trajectory(now - 0.5, c, np.array([2.0, 2.0]))
    offsets = np.array([[1.0, 0.0, 0.0], [-0.5, 0.8, 0.0], [-0.5, -0.8, 0.0]])
    positions = {0: np.array([1.0, 0.0, 1.5]), 1: np.array([0.5, 1.0, 1.5]),
                 2: np.array([0.0, -1.0, 1.5])}  # fmt: skip
    scene = SceneInput(now, positions, {0: "hover", 1: "formation-flight", 2: "hover"},
                       {1: traj}, (offsets, {0: 0, 1: 1, 2: 2}))  # fmt: skip
    world = World(
        cylinders=np.array([[3.0, 0.0, 0.25, 0.0, 3.0], [6.0, 2.0, 0.4, 0.0, 2.5]]),
        rings=np.zeros((0, 7)),
        boxes=np.zeros((0, 6)),
    )
    with SwarmView(lambda: scene, world, port=0, rate_hz=20.0) as view:
        assert view.port > 0 and view.url == f"ws://127.0.0.1:{view.port}"
        view.start()
        ws = client_of(view.port)
        channels: dict[str, dict[str, Any]] = {}
        end = time.monotonic() + DEADLINE_S
        while {SWARM_TOPIC, WORLD_TOPIC} - set(channels) and time.monotonic() < end:
            op, data = ws.recv()
            if op == 0x1:
                msg = json.loads(data)
                if msg.get("op") == "advertise":
                    channels.update({ch["topic"]: ch for ch in msg["channels"]})
        assert {SWARM_TOPIC, WORLD_TOPIC} <= set(channels)
        ch = channels[SWARM_TOPIC]
        assert ch["encoding"] == "protobuf" and ch["schemaName"] == "foxglove.SceneUpdate"
        subs = {1: SWARM_TOPIC, 2: WORLD_TOPIC}
        ws.send_json({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": channels[t]["id"]} for k, t in subs.items()]})  # fmt: skip
        got: dict[str, bytes] = {}
        while len(got) < 2 and time.monotonic() < end:
            op, data = ws.recv()
            if op == 0x2 and data[0] == 0x01:  # message data
                sub, _ts = struct.unpack_from("<IQ", data, 1)
                got.setdefault(subs[sub], data[13:])
        assert set(got) == {SWARM_TOPIC, WORLD_TOPIC}
        dec = Decoder(ch["schema"])
        # the swarm: one entity per drone, the plan of drone 1, the formation target
        entities = {
            dec.get(e, "SceneEntity", "id")[0].decode(): e
            for e in dec.get(got[SWARM_TOPIC], "SceneUpdate", "entities")
        }
        assert set(entities) == {"drone/0", "drone/1", "drone/2", "plan/1", "formation"}
        e1 = entities["drone/1"]
        assert dec.get(e1, "SceneEntity", "frame_id")[0] == b"enu"
        (sphere,) = dec.get(e1, "SceneEntity", "spheres")
        (pose,) = dec.get(sphere, "SpherePrimitive", "pose")
        (pos,) = dec.get(pose, "Pose", "position")
        np.testing.assert_allclose(dec.vec(pos), positions[1])
        (text,) = dec.get(e1, "SceneEntity", "texts")
        assert dec.get(text, "TextPrimitive", "text")[0].decode() == "1 formation-flight"
        (line,) = dec.get(entities["plan/1"], "SceneEntity", "lines")
        pts = [dec.vec(p, "Point3") for p in dec.get(line, "LinePrimitive", "points")]
        np.testing.assert_allclose(pts[0], traj.sample(now))  # from now ...
        np.testing.assert_allclose(pts[-1], traj.sample(traj.t_end_s))  # ... to its end
        assert len(pts) == 1 + int(np.ceil((traj.t_end_s - now) / 0.2 - 1e-9))
        form = entities["formation"]
        centre = np.mean(list(positions.values()), axis=0)
        targets = [
            dec.vec(dec.get(dec.get(s, "SpherePrimitive", "pose")[0], "Pose", "position")[0])
            for s in dec.get(form, "SceneEntity", "spheres")
        ]
        np.testing.assert_allclose(np.array(targets), centre + offsets)
        # the world: both trunks as cylinders of the right size
        wdec = Decoder(channels[WORLD_TOPIC]["schema"])
        (obst,) = wdec.get(got[WORLD_TOPIC], "SceneUpdate", "entities")
        cyl = wdec.get(obst, "SceneEntity", "cylinders")
        assert len(cyl) == 2
        size = wdec.vec(wdec.get(cyl[1], "CylinderPrimitive", "size")[0])
        np.testing.assert_allclose(size, [0.8, 0.8, 2.5])
        assert view.errors == 0 and view.published >= 1


def test_view_survives_a_bad_snapshot(client_of: Any) -> None:
    calls = {"n": 0}

    def flaky() -> SceneInput:
        calls["n"] += 1
        if calls["n"] == 1:
            raise ValueError("bad snapshot")
        return SceneInput(1.75e9, {0: np.zeros(3)})

    with SwarmView(flaky, None, port=0, rate_hz=50.0) as view:
        view.start()
        end = time.monotonic() + DEADLINE_S
        while view.published < 2 and time.monotonic() < end:
            time.sleep(0.01)
        assert view.errors == 1 and view.published >= 2
    with pytest.raises(ValueError, match="rate_hz"):
        SwarmView(flaky, None, port=0, rate_hz=0.0)


def test_view_command_end_to_end(client_of: Any) -> None:
    """``swarm-gcs view`` as a process: it serves on a free port, a client gets the world's
    obstacles, and Ctrl-C ends it cleanly."""
    import signal
    import subprocess
    import sys

    from onboard.comm.zenoh_session import free_loopback_endpoint

    code = "from gcs.commands import view; view(prog_name='swarm-gcs view')"
    args = ["--listen", free_loopback_endpoint(), "--wait", "0", "--port", "0",
            "--world", "forest-small", "--seed", "2", "--count", "3"]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=sigint_default)  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stderr is not None
        line = proc.stdout.readline()  # blocks until the server is up (or the process ends)
        assert "Foxglove view on ws://127.0.0.1:" in line, line + proc.stderr.read()
        port = int(line.split("ws://127.0.0.1:")[1].split()[0])
        ws = client_of(port)
        end = time.monotonic() + DEADLINE_S
        world_ch = None
        while world_ch is None and time.monotonic() < end:
            op, data = ws.recv()
            msg = json.loads(data) if op == 0x1 else {}
            for ch in msg.get("channels", []) if msg.get("op") == "advertise" else []:
                if ch["topic"] == WORLD_TOPIC:
                    world_ch = ch
        assert world_ch is not None
        ws.send_json({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": world_ch["id"]}]})
        while time.monotonic() < end:
            op, data = ws.recv()
            if op == 0x2 and data[0] == 0x01:
                break
        dec = Decoder(world_ch["schema"])
        (obst,) = dec.get(data[13:], "SceneUpdate", "entities")
        assert len(dec.get(obst, "SceneEntity", "cylinders")) == 8  # forest-small's trunks
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=DEADLINE_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for f in (proc.stdout, proc.stderr):
            if f is not None:
                f.close()
