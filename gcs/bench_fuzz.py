"""``bench fuzz``: every decoder of the system fed random and mutated input.

Targets (each a function of one byte string that may only *refuse* the input with its layer's
error type; anything else escaping it, or an accepted value that breaks a property, is a crash):

=============  ===============================================================================
traj           trajectory messages through the swarm bus gate (``MessageGate.admit``)
state          state messages through the gate
command        ground-station commands through the gate, then the service's conversion
               (``command_from_wire``) and an airborne flight state machine with a geofence:
               an accepted goal is finite and inside the geofence
formation      formation files (``onboard.config.load_formation``)
world          world files (``load_world_spec``, then ``build`` of small worlds)
config         onboard.yaml (``onboard.service.config.load_onboard_config``)
mavlink        the pymavlink link's receive path (``_on_chunk``, datagrams and a serial stream):
               only counted decode errors, the vehicle state stays finite
depth          depth frames and truth poses (``DepthImage.from_bytes``, ``TruthSample``)
=============  ===============================================================================

Engines: ``mutate`` (default; seeded random mutation of valid seeds: bit flips, byte edits,
insertions, deletions, splices, and for text targets numbers swapped for absurd ones such as
``.nan``, ``-1e308`` or ``100000``) and ``atheris`` (coverage-guided libFuzzer, when the
``atheris`` package is installed; each target in its own process, libFuzzer's own ``-runs`` and
``-timeout``). An input running longer than ``--hang-s`` counts as a hang.

``swarm-gcs bench fuzz --target all --inputs 100000 --json fuzz.json``
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click

NOW = 1_700_000_000.0
SWARM = "fuzz/swarm"
GEOFENCE_MIN = (-50.0, -50.0, 0.0)
GEOFENCE_MAX = (50.0, 50.0, 5.0)

OneInput = Callable[[bytes], None]


class PropertyViolation(AssertionError):
    """An input was accepted but the accepted value breaks a safety property."""


def _check(cond: bool, what: str) -> None:
    if not cond:
        raise PropertyViolation(what)


def _floats(obj: Any) -> Iterator[float]:
    if isinstance(obj, float):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _floats(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _floats(v)


def _all_finite(obj: Any) -> bool:
    return all(math.isfinite(x) for x in _floats(obj))


@dataclass
class FuzzTarget:
    name: str
    description: str
    seeds: Callable[[], list[bytes]]
    make: Callable[[], OneInput]
    """Builds the one-input function (once per run: temp files, parsers)."""
    text: bool = False
    """YAML text: mutations also swap numbers and tokens."""
    tokens: tuple[bytes, ...] = ()


# --------------------------------------------------------------------------------------------
# the swarm bus


def _envelope(body: Any, sender: int, seq: int = 0, valid_for_s: float = 3.0) -> bytes:
    from onboard.comm.wire import WIRE_VERSION, Envelope, encode

    return encode(Envelope(WIRE_VERSION, sender, 1, seq, NOW, valid_for_s, body))


def _traj_seeds() -> list[bytes]:
    import numpy as np

    from onboard.comm.messages import TrajectoryMsg
    from onboard.planner.trajectory import Trajectory

    out = []
    for pieces in (1, 3, 8):
        rng = np.random.default_rng(pieces)
        c = rng.normal(scale=0.2, size=(pieces, 6, 3))
        c[:, 0] += np.array([5.0, 2.0, 1.0])
        tr = Trajectory(NOW, c, np.full(pieces, 0.8))
        out.append(_envelope(TrajectoryMsg(1, 7, 1, tr, formation_epoch=2).to_body(), 1))
    return out


def _state_seeds() -> list[bytes]:
    from onboard.comm.wire import StateBody

    b = StateBody(
        "FORMATION_FLIGHT",
        NOW - 0.01,
        (1.0, 2.0, 1.5),
        (0.5, 0.0, 0.0),
        (1.0, 0.0, 0.0, 0.0),
        True,
        "OFFBOARD",
        1,
        2,
    )
    return [_envelope(b, 1, valid_for_s=1.0)]


def _gate_target(kind: str) -> Callable[[], OneInput]:
    def make() -> OneInput:
        from onboard.comm.gate import MessageGate
        from onboard.comm.wire import REASONS, Rejected, decode, encode

        key = f"{SWARM}/drone/1/{kind}"

        def one(data: bytes) -> None:
            gate = MessageGate(SWARM, own_id=0)
            try:
                env = gate.admit(key, data, NOW)
            except Rejected as r:
                _check(r.reason in REASONS, f"unknown reason {r.reason}")
                return
            import msgspec

            _check(_all_finite(msgspec.to_builtins(env)), "a non-finite value accepted")
            _check(decode(encode(env)) == env, "accepted message does not round-trip")

        return one

    return make


def _command_seeds() -> list[bytes]:
    from onboard.comm.wire import (
        ACTIONS,
        GCS_ID,
        Abort,
        Action,
        Command,
        FormationAssignment,
        Goal,
        Land,
        Resume,
        Takeoff,
        Waypoints,
    )

    actions: list[Action] = [
        Takeoff(1.5),
        Land(),
        Abort(),
        Resume(),
        Goal((10.0, 5.0, 2.0), 0.5, NOW - 1.0),
        Waypoints([(1.0, 1.0, 1.0), (20.0, -3.0, 2.5), (40.0, 0.0, 3.0)], NOW - 1.0),
        FormationAssignment(
            [(0.0, 0.0, 0.0), (1.5, 0.0, 0.0), (0.0, 1.5, 0.0)], 1.0, 0.0, {0: 0, 1: 1}, 3, NOW
        ),
    ]
    out = []
    for i, a in enumerate(actions):
        cmd = Command(cmd_id=i + 1, targets=[0] if i % 2 else [], issued_s=NOW, action=a)
        tag = type(a).__struct_config__.tag
        out.append(bytes([ACTIONS.index(str(tag))]) + _envelope(cmd, GCS_ID, seq=i))
    return out


def _command_make() -> OneInput:
    from onboard.comm.gate import MessageGate
    from onboard.comm.wire import ACTIONS, Command, Rejected
    from onboard.service.adapters import command_from_wire
    from onboard.service.state import FlightStateMachine, SetFormation, Takeoff

    points = ((0.0, 0.0, 0.0), (1.5, 0.0, 0.0), (0.0, 1.5, 0.0))

    def inside(p: Any) -> bool:
        return all(GEOFENCE_MIN[k] <= float(p[k]) <= GEOFENCE_MAX[k] for k in range(3))

    def airborne() -> FlightStateMachine:
        m = FlightStateMachine(0, lambda: NOW, inside_geofence=inside)
        m.command(SetFormation(1, 0.0, ((0, 0), (1, 1)), points))
        m.command(Takeoff(1.0))
        m.set_on_ground(False)
        m.takeoff_reached()
        return m

    def one(data: bytes) -> None:
        if not data:
            return
        key = f"{SWARM}/cmd/{ACTIONS[data[0] % len(ACTIONS)]}"
        gate = MessageGate(SWARM, own_id=0)
        try:
            env = gate.admit(key, data[1:], NOW)
        except Rejected:
            return
        assert isinstance(env.body, Command)
        cmd = command_from_wire(env.body.action)
        m = airborne()
        before = (m.goal, list(m.waypoints), m.assignment)
        result = m.command(cmd)
        if not result.accepted:
            _check(bool(result.reason), "a refusal without a reason")
            _check((m.goal, list(m.waypoints), m.assignment) == before, "refused but changed")
            return
        for p in ([m.goal] if m.goal is not None else []) + list(m.waypoints):
            _check(_all_finite(list(p)) and inside(p), f"goal {p} accepted outside the box")
        if m.pending_goals is not None:
            for p in m.pending_goals[0]:
                _check(_all_finite(list(p)) and inside(p), f"pending goal {p} outside the box")
        for a in (m.assignment, m.pending):
            if a is not None:
                _check(_all_finite([list(p) for p in a.points]), "non-finite formation")
                _check(len(a.points) <= 64, "a formation beyond the wire bound")

    return one


# --------------------------------------------------------------------------------------------
# files


def _config_seeds(sub: str, names: tuple[str, ...]) -> Callable[[], list[bytes]]:
    def seeds() -> list[bytes]:
        from onboard.config import config_dir

        d = config_dir() / sub if sub else config_dir()
        return [(d / n).read_bytes() for n in names if (d / n).is_file()]

    return seeds


def _file_target(
    load: Callable[[Path], Any], check: Callable[[Any], None]
) -> Callable[[], OneInput]:
    def make() -> OneInput:
        from onboard.config import ConfigError

        tmp = Path(tempfile.mkdtemp(prefix="swarm-fuzz-"))
        path = tmp / "input.yaml"

        def one(data: bytes) -> None:
            path.write_bytes(data)
            try:
                value = load(path)
            except ConfigError as e:
                _check(bool(str(e)), "an error without a message")
                return
            check(value)

        # the directory goes with the target (a test run made three and left them in /tmp)
        weakref.finalize(one, shutil.rmtree, tmp, ignore_errors=True)
        return one

    return make


def _load_formation(p: Path) -> Any:
    from onboard.config import load_formation

    return load_formation(p)


def _check_formation(f: Any) -> None:
    import numpy as np

    _check(bool(np.all(np.isfinite(f.points))), "non-finite formation points")
    _check(f.n >= 2, "a formation of fewer than 2 points")


def _load_world(p: Path) -> Any:
    from onboard.config import ConfigError, Formation, load_world_spec

    spec = load_world_spec(p)
    g = spec.generator
    if g is not None and g.n_cylinders + g.n_rings > 50:
        return spec  # building thousands of random obstacles is a benchmark, not a decoder
    import numpy as np

    f = Formation("fuzz", np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 1.5, 0.0]]))
    try:
        return spec.build(0, f)
    except ConfigError:
        raise
    except ValueError as e:  # the World's own checks: a refusal, re-raised as a config error
        raise ConfigError(f"world: {e}") from e


def _check_world(w: Any) -> None:
    if isinstance(w, tuple):
        world, starts, goals = w
        import numpy as np

        _check(bool(np.all(np.isfinite(starts)) and np.all(np.isfinite(goals))), "non-finite")
        for name in ("cylinders", "boxes", "rings"):
            arr = getattr(world, name, None)
            if arr is not None:
                _check(bool(np.all(np.isfinite(np.asarray(arr)))), f"non-finite {name}")


def _load_onboard(p: Path) -> Any:
    from onboard.service.config import load_onboard_config

    return load_onboard_config(p)


def _check_onboard(cfg: Any) -> None:
    _check(_all_finite(_plain(cfg)), "non-finite value in the loaded config")


def _plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    return obj


# --------------------------------------------------------------------------------------------
# MAVLink input of the autopilot link


def _mavlink_seeds() -> list[bytes]:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    msgs = [
        mav.heartbeat_encode(2, 12, 157, 393216, 4),
        mav.local_position_ned_encode(1000, 1.0, -2.0, -3.0, 0.1, 0.2, -0.3),
        mav.attitude_encode(1000, 0.01, -0.02, 1.5, 0.0, 0.0, 0.0),
        mav.extended_sys_state_encode(0, 2),
        mav.sys_status_encode(
            0x3FFFFFFF, 0x3FFFFFFF, 0x3FFFFFFF, 500, 12000, -1, 80, 0, 0, 0, 0, 0, 0
        ),
        mav.home_position_encode(473977420, 85455940, 488000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0),
        mav.command_ack_encode(511, 0, 0, 0, 1, 191),
        mav.command_ack_encode(176, 5, 0, 0, 1, 191),
    ]
    out = []
    for m in msgs:
        buf = bytes(m.pack(mav))
        mav.seq = (mav.seq + 1) % 256
        out.append(buf)
    out.append(b"".join(out))  # several frames in one datagram
    return out


_PHYSICAL = (
    "position_enu_m",
    "velocity_enu_m_s",
    "roll_rad",
    "pitch_rad",
    "yaw_enu_rad",
    "home_altitude_amsl_m",
    "battery_remaining",
    "battery_voltage_v",
)


def _mavlink_make() -> OneInput:
    from onboard.autopilot.config import LinkConfig
    from onboard.autopilot.pymavlink_link import PymavlinkLink

    cfg = LinkConfig(url="udpin://127.0.0.1:9")
    stream = PymavlinkLink(cfg)  # one persistent parser: the serial path

    def one(data: bytes) -> None:
        link = PymavlinkLink(cfg)
        before = link.counters()
        link._on_chunk(data, ("127.0.0.1", 14580), True)
        stream._on_chunk(data, None, False)
        for lk in (link, stream):
            st = lk.state()
            physical = [getattr(st, f) for f in _PHYSICAL if getattr(st, f, None) is not None]
            _check(_all_finite(physical), f"non-finite vehicle state {st}")
        c = link.counters()
        _check(c.messages_received >= before.messages_received, "counters went back")

    return one


# --------------------------------------------------------------------------------------------
# depth frames


def _depth_seeds() -> list[bytes]:
    import numpy as np

    from onboard.sensors.zenoh_depth import DepthImage, TruthSample

    pose = TruthSample(
        1, NOW, (1.0, 2.0, 3.0), (0.1, 0.0, -0.2), (1.0, 0.0, 0.0, 0.0), 0.3, True, False,
        "OFFBOARD", 0,
    )  # fmt: skip
    out = [pose.to_bytes()]
    rng = np.random.default_rng(0)
    for h, w in ((4, 6), (12, 16)):
        depth = rng.uniform(0.2, 8.0, size=(h, w)).astype(np.float32)
        depth[0, 0] = 0.0  # no return
        intr = {"width": w, "height": h, "fx": 10.0, "fy": 10.0, "cx": w / 2, "cy": h / 2,
                "min_depth_m": 0.1, "max_depth_m": 10.0}  # fmt: skip
        img = DepthImage(1, NOW, depth, np.array([0.0, 0.0, 1.0]), np.eye(3), intr)
        out.append(img.to_bytes())
    return out


def _depth_make() -> OneInput:
    import numpy as np

    from onboard.sensors.zenoh_depth import DecodeError, DepthImage, TruthSample

    def one(data: bytes) -> None:
        for decoder in (DepthImage.from_bytes, TruthSample.from_bytes):
            try:
                v = decoder(data)
            except DecodeError as e:
                _check(bool(e.reason), "a refusal without a reason")
                continue
            for name, val in vars(v).items():
                if isinstance(val, np.ndarray) and val.dtype.kind == "f":
                    d = val[np.isfinite(val)] if name.startswith("depth") else val
                    _check(bool(np.all(np.isfinite(d))), f"non-finite {name}")
                elif isinstance(val, (float, tuple, list, dict)):
                    _check(_all_finite(val), f"non-finite {name}")

    return one


# --------------------------------------------------------------------------------------------

TARGETS: dict[str, FuzzTarget] = {
    t.name: t
    for t in [
        FuzzTarget("traj", "trajectory messages via the gate", _traj_seeds, _gate_target("traj")),
        FuzzTarget("state", "state messages via the gate", _state_seeds, _gate_target("state")),
        FuzzTarget(
            "command",
            "ground-station commands: gate, conversion, flight state machine",
            _command_seeds,
            _command_make,
        ),
        FuzzTarget(
            "formation",
            "formation files",
            _config_seeds("formations", ("triangle-3.yaml", "heart-10.yaml", "line-7.yaml")),
            _file_target(_load_formation, _check_formation),
            text=True,
        ),
        FuzzTarget(
            "world",
            "world files",
            _config_seeds("worlds", ("corridor.yaml", "forest-small.yaml", "heart-forest.yaml")),
            _file_target(_load_world, _check_world),
            text=True,
        ),
        FuzzTarget(
            "config",
            "onboard.yaml",
            _config_seeds("", ("onboard.yaml",)),
            _file_target(_load_onboard, _check_onboard),
            text=True,
        ),
        FuzzTarget("mavlink", "the pymavlink link's receive path", _mavlink_seeds, _mavlink_make),
        FuzzTarget("depth", "depth frames and truth poses", _depth_seeds, _depth_make),
    ]
}

# --------------------------------------------------------------------------------------------
# the mutation engine

_ABSURD = [
    b".nan", b".inf", b"-.inf", b"-1", b"0", b"-0.0", b"1e308", b"-1e308", b"100000",
    b"10000", b"1000", b"2147483648", b"18446744073709551616", b"null", b"true", b"[]",
    b"{}", b"''", b"1e-320", b"0x7fffffff", b"[1, 2]", b"[.nan, 0, 0]", b"&a [*a]",
]  # fmt: skip
_NUMBER = re.compile(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?")


def mutate(data: bytes, rng: random.Random, pool: list[bytes], text: bool) -> bytes:
    """One mutated input from ``data`` (1 to 4 edits)."""
    b = bytearray(data)
    for _ in range(1 + rng.randrange(4)):
        op = rng.randrange(12 if text else 9)
        n = len(b)
        if op == 0 and n:
            i = rng.randrange(n)
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and n:
            b[rng.randrange(n)] = rng.choice((0, 0xFF, 0x7F, 0x80, rng.randrange(256)))
        elif op == 2:
            i = rng.randrange(n + 1)
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 9)))
        elif op == 3 and n:
            i = rng.randrange(n)
            del b[i : i + rng.randrange(1, 17)]
        elif op == 4 and n:
            del b[rng.randrange(n) :]
        elif op == 5 and n:
            i = rng.randrange(n)
            j = min(n, i + rng.randrange(1, 65))
            k = rng.randrange(n + 1)
            b[k:k] = b[i:j]
        elif op == 6 and pool:
            other = rng.choice(pool)
            i = rng.randrange(len(b) + 1)
            j = rng.randrange(len(other) + 1)
            b = b[:i] + bytearray(other[j:])
        elif op == 7 and n >= 8:  # an interesting 32/64-bit pattern over 4 or 8 bytes
            i = rng.randrange(n - 7)
            w = rng.choice((4, 8))
            pat = rng.choice([b"\xff" * 8, b"\x00" * 8, b"\x00\x00\xc0\x7f" * 2, b"\x7f" * 8])
            b[i : i + w] = pat[:w]
        elif op == 8:
            b = bytearray(rng.randbytes(rng.randrange(0, 200)))
        elif op >= 9 and n:  # text: swap a number or insert an absurd token
            nums = list(_NUMBER.finditer(bytes(b)))
            if nums and op != 11:
                m = rng.choice(nums)
                rep = rng.choice(_ABSURD) if op == 9 else str(rng.uniform(-1e5, 1e5)).encode()
                b[m.start() : m.end()] = rep
            else:
                i = rng.randrange(n + 1)
                b[i:i] = rng.choice(_ABSURD + [b"\n", b": ", b"- ", b"{", b"["])
    return bytes(b)


@dataclass
class FuzzResult:
    target: str
    engine: str
    inputs: int
    crashes: int
    hangs: int
    seconds: float
    inputs_per_s: float
    max_input_ms: float
    examples: list[dict[str, str]] = field(default_factory=list)
    note: str = ""
    slowest_input_hex: str = ""


def run_mutation(
    target: FuzzTarget, n: int, seed: int = 0, hang_s: float = 1.0, keep: int = 5
) -> FuzzResult:
    """Run ``target`` on its seeds, then ``n`` mutated (and some random) inputs in this
    process. Crashes are counted and up to ``keep`` kept (input and traceback)."""
    rng = random.Random(seed)
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)  # every refusal is logged by its layer: not measured here
    try:
        return _run_mutation(target, n, rng, hang_s, keep)
    finally:
        logging.disable(previous)


def _run_mutation(
    target: FuzzTarget, n: int, rng: random.Random, hang_s: float, keep: int
) -> FuzzResult:
    seeds = target.seeds()
    if not seeds:
        raise RuntimeError(f"{target.name}: no seed inputs")
    one = target.make()
    pool = list(seeds)
    crashes = hangs = 0
    examples: list[dict[str, str]] = []
    seen_kinds: set[str] = set()
    worst = 0.0
    slowest = b""
    t_start = time.perf_counter()
    for k in range(n):
        if k < len(seeds):
            data = seeds[k]
        elif rng.random() < 0.03:
            data = rng.randbytes(rng.randrange(0, 300))
        else:
            data = mutate(rng.choice(pool), rng, pool, target.text)
            if target.text and rng.random() < 0.9:  # mostly text: reach past the UTF-8 check
                data = data.decode("utf-8", "replace").encode("utf-8")
        t0 = time.perf_counter()
        try:
            one(data)
        except Exception as e:  # noqa: BLE001 - a crash is what this counts and reports
            crashes += 1
            tb = traceback.extract_tb(e.__traceback__)
            kind = f"{type(e).__name__} at {tb[-1].filename}:{tb[-1].lineno}" if tb else repr(e)
            if len(examples) < keep and kind not in seen_kinds:
                seen_kinds.add(kind)
                examples.append(
                    {
                        "input_hex": data[:400].hex(),
                        "error": f"{type(e).__name__}: {e}"[:500],
                        "traceback": "".join(traceback.format_exc(limit=6))[-1500:],
                    }
                )
        dt = time.perf_counter() - t0
        if dt > worst:
            worst = dt
            slowest = data
        if dt > hang_s:
            hangs += 1
        if k >= len(seeds) and rng.random() < 0.002 and len(pool) < 200:
            pool.append(data)  # keep a few mutants as parents: deeper mutations
    secs = time.perf_counter() - t_start
    return FuzzResult(
        target.name,
        "mutate",
        n,
        crashes,
        hangs,
        round(secs, 2),
        round(n / secs, 1) if secs > 0 else 0.0,
        round(worst * 1000, 2),
        examples,
        slowest_input_hex=slowest[:400].hex(),
    )


def atheris_available() -> bool:
    try:
        import atheris  # noqa: F401
    except ImportError:
        return False
    return True


def run_atheris(target: FuzzTarget, n: int, hang_s: float = 1.0) -> FuzzResult:
    """Coverage-guided run of ``target`` in a child process (libFuzzer exits at the end)."""
    work = Path(tempfile.mkdtemp(prefix=f"swarm-atheris-{target.name}-"))
    corpus = work / "corpus"
    corpus.mkdir()
    for i, s in enumerate(target.seeds()):
        (corpus / f"seed{i}").write_bytes(s)
    args = [
        sys.executable, "-m", "gcs.bench_fuzz", "--atheris-worker", target.name,
        str(corpus), f"-runs={n}", f"-timeout={max(1, math.ceil(hang_s))}",
        f"-artifact_prefix={work}/", "-max_len=4096", "-print_final_stats=1",
    ]  # fmt: skip
    t0 = time.perf_counter()
    r = subprocess.run(args, capture_output=True, text=True, check=False, cwd=_repo_root())
    secs = time.perf_counter() - t0
    out = r.stdout + r.stderr
    m = re.search(r"Done (\d+) runs", out)
    runs = int(m.group(1)) if m else 0
    if not m:
        m2 = re.findall(r"#(\d+)\s", out)
        runs = int(m2[-1]) if m2 else 0
    crash_files = sorted(p.name for p in work.glob("crash-*"))
    hang_files = sorted(p.name for p in work.glob("timeout-*"))
    examples = []
    if r.returncode != 0 and not hang_files:
        tail = out[-1500:]
        examples.append({"error": tail, "artifacts": ", ".join(crash_files)})
    cov = re.findall(r"cov: (\d+)", out)
    return FuzzResult(
        target.name,
        "atheris",
        runs,
        len(crash_files) or (1 if r.returncode != 0 and not hang_files else 0),
        len(hang_files),
        round(secs, 2),
        round(runs / secs, 1) if secs > 0 else 0.0,
        float("nan"),
        examples,
        note=f"coverage edges {cov[-1] if cov else '?'}; artifacts in {work}",
    )


def _repo_root() -> str:
    return str(Path(__file__).resolve().parent.parent)


def _atheris_worker(argv: list[str]) -> None:
    import atheris

    name = argv[0]
    with atheris.instrument_imports(include=["onboard", "pymavlink", "msgspec", "yaml"]):
        target = TARGETS[name]
        one = target.make()
        target.seeds()

    def test_one(data: bytes) -> None:
        one(bytes(data))

    atheris.Setup([sys.argv[0], *argv[1:]], test_one)
    atheris.Fuzz()


@click.command("fuzz")
@click.option(
    "--target",
    "target_name",
    default="all",
    show_default=True,
    help=f"One of {', '.join(TARGETS)} or 'all'.",
)
@click.option("--inputs", "-n", type=int, default=100_000, show_default=True)
@click.option(
    "--engine",
    type=click.Choice(["mutate", "atheris"]),
    default="mutate",
    show_default=True,
    help="atheris: coverage-guided (needs the atheris package).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--hang-s", type=float, default=1.0, show_default=True)
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None)
def fuzz_command(
    target_name: str, inputs: int, engine: str, seed: int, hang_s: float, json_path: str | None
) -> None:
    """Fuzz the decoders (see ``gcs/bench_fuzz.py``): inputs tried, crashes and hangs per
    target."""
    if target_name != "all" and target_name not in TARGETS:
        raise click.BadParameter(f"one of {', '.join(TARGETS)} or all", param_hint="--target")
    if inputs < 1:
        raise click.BadParameter("at least 1", param_hint="--inputs")
    if engine == "atheris" and not atheris_available():
        raise click.ClickException("atheris is not installed (pip install atheris)")
    names = list(TARGETS) if target_name == "all" else [target_name]
    results = []
    click.echo(f"{'target':<10} {'engine':<8} {'inputs':>9} {'crashes':>8} {'hangs':>6} "
               f"{'s':>8} {'inputs/s':>9} {'max ms':>8}")  # fmt: skip
    for name in names:
        t = TARGETS[name]
        res = (
            run_mutation(t, inputs, seed, hang_s)
            if engine == "mutate"
            else run_atheris(t, inputs, hang_s)
        )
        results.append(res)
        click.echo(
            f"{res.target:<10} {res.engine:<8} {res.inputs:>9} {res.crashes:>8} {res.hangs:>6} "
            f"{res.seconds:>8.1f} {res.inputs_per_s:>9.0f} {res.max_input_ms:>8.1f}"
        )
        for ex in res.examples[:2]:
            click.echo(f"   crash: {ex.get('error', '')[:300]}")
    if json_path:
        doc = {
            "benchmark": "fuzz",
            "engine": engine,
            "seed": seed,
            "hang_s": hang_s,
            "python": sys.version.split()[0],
            "machine_cpus": os.cpu_count(),
            "results": [dataclasses.asdict(r) for r in results],
        }
        Path(json_path).write_text(json.dumps(doc, indent=2, default=str))
        click.echo(f"wrote {json_path}")
    if any(r.crashes or r.hangs for r in results):
        raise SystemExit(1)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--atheris-worker":
        _atheris_worker(sys.argv[2:])
    else:
        fuzz_command()
