"""The swarm bus wire format: versioned msgpack messages (msgspec), their limits and decoder.

Every message is one msgpack array, an :class:`Envelope`::

    [version, sender, incarnation, seq, stamp_s, valid_for_s, body]

``body`` is a tagged array whose first element names its kind: ``["traj", ...]``,
``["state", ...]``, ``["status", ...]``, ``["cmd", ...]`` or ``["ack", ...]``; a command's
action is tagged the same way (``["goal", ...]``). Field order is the order of the class
attributes below; every field is required (``None`` where a type says ``| None``).

Units and frames are in the field names: ENU metres, seconds of *global* time (the system clock,
kept in sync by chrony), radians. Floats are IEEE doubles; trajectory coefficients are a flat
list in row-major order of the ``(pieces, 6, 3)`` array of ``onboard.planner.trajectory``.

Header semantics:

- ``sender``: drone id (0..``MAX_DRONE_ID``) or a ground-station id (>= ``GCS_ID``);
- ``incarnation``: chosen once per sender process, larger after a restart (the process's start
  time in microseconds of global time), so that receivers accept a restarted sender whose
  ``seq`` starts again from 0 and refuse messages of an older incarnation;
- ``seq``: per sender and stream (``traj``, ``state``, ``status``, ``cmd``, ``ack``), +1 per
  message; receivers refuse duplicates and anything older than what they accepted;
- ``stamp_s``: the sender's clock when it sent the message (used for staleness and for the
  receiver's estimate of the sender's clock offset);
- ``valid_for_s``: the message is stale after ``stamp_s + valid_for_s``; for a trajectory it is
  the sender's promise to publish again before then (after it, peers treat the drone as silent).

:func:`decode` runs the stateless checks (size, version, structure, finite numbers, durations,
piece count, value ranges) and raises :class:`Rejected` with one of :data:`REASONS`;
:class:`onboard.comm.gate.MessageGate` adds the checks that need the key expression and the
history (sender, staleness, sequence). :func:`encode` runs the same checks, so that nothing a
receiver would refuse is ever sent.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

WIRE_VERSION = 1
"""Version of this schema; receivers refuse any other."""

MAX_DRONE_ID = 999
"""Drone ids are 0..MAX_DRONE_ID."""
GCS_ID = 1000
"""The default ground-station sender id; ground-station ids are >= GCS_ID."""
MAX_INT = 2**63 - 1

N_COEFFS = 6  # quintic pieces, as onboard.planner.trajectory
COEFFS_PER_PIECE = N_COEFFS * 3

STREAMS = ("traj", "state", "status", "cmd", "ack")
"""Message kinds (the body tags), one sequence counter per sender and stream."""

REASONS = (
    "version",  # not WIRE_VERSION
    "truncated",  # the msgpack data ends early
    "malformed",  # not msgpack, or not this schema (wrong types, missing or extra fields)
    "oversized",  # payload larger than its kind's bound, or a list longer than its bound
    "non_finite",  # a NaN or infinite number anywhere
    "bad_duration",  # piece durations or validity non-positive or absurdly long
    "too_many_pieces",  # more trajectory pieces than the bound
    "bad_value",  # a value out of its range (ids, coordinates, speeds, names, ...)
    "bad_key",  # a key expression outside the schema
    "kind_mismatch",  # the body kind (or command action) does not match the key expression
    "sender_mismatch",  # the sender id does not match the key expression
    "own_id",  # a message under this node's own id from another session (duplicate ids)
    "future_stamp",  # stamped further in the future than the clock tolerance
    "stale",  # received after stamp_s + valid_for_s
    "duplicate",  # the same (incarnation, seq) again
    "out_of_order",  # older than a message already accepted from that sender and stream
)
"""Every reason a message can be refused for (each has its own counter)."""


class Rejected(ValueError):
    """A message refused by a decoder or the encoder: ``reason`` (one of :data:`REASONS`) and
    ``detail`` naming the field."""

    def __init__(self, reason: str, detail: str) -> None:
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class WireLimits:
    """Bounds every decoder enforces (sizes in bytes of the whole payload)."""

    max_traj_bytes: int = 16384
    max_state_bytes: int = 1024
    max_status_bytes: int = 16384
    max_cmd_bytes: int = 16384
    max_ack_bytes: int = 1024
    max_pieces: int = 64
    min_piece_s: float = 1e-3
    max_piece_s: float = 600.0
    max_total_s: float = 3600.0
    """Longest trajectory; also the furthest its start may lie from its stamp."""
    max_valid_for_s: float = 600.0
    max_abs_coord_m: float = 10000.0
    """Largest ENU coordinate anywhere (positions, goals, formation points, trajectory knots)."""
    max_speed_m_s: float = 50.0
    max_altitude_m: float = 500.0
    max_formation_points: int = 64
    max_waypoints: int = 256
    max_targets: int = 64
    max_links: int = 64
    max_counters: int = 128
    max_text: int = 200
    max_future_s: float = 1.0
    """Stamps further ahead of the receiver's clock than this are refused (``future_stamp``)."""

    def __post_init__(self) -> None:
        for name, value in self.__dict__.items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"WireLimits.{name} must be a positive finite number, got {value}")

    def max_bytes(self, kind: str | None) -> int:
        """The payload bound of a kind (the largest of all when the kind is unknown)."""
        sizes = {
            "traj": self.max_traj_bytes,
            "state": self.max_state_bytes,
            "status": self.max_status_bytes,
            "cmd": self.max_cmd_bytes,
            "ack": self.max_ack_bytes,
        }
        return sizes[kind] if kind is not None else max(sizes.values())


DEFAULT_LIMITS = WireLimits()

Vec3 = tuple[float, float, float]


class _Wire(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """Base of every wire struct: positional msgpack array, no unknown trailing fields."""


# --- bodies ----------------------------------------------------------------------------------


class TrajectoryBody(_Wire, frozen=True, tag="traj"):
    """A drone's current trajectory (key ``<swarm>/drone/<id>/traj``), published after every
    replan. ``coeffs`` is the flat row-major ``(len(durations_s), 6, 3)`` array; ``slot`` is the
    sender's row in the formation of ``formation_epoch`` (-1: none)."""

    traj_id: int
    slot: int
    formation_epoch: int
    t0_s: float
    durations_s: list[float]
    coeffs: list[float]


class StateBody(_Wire, frozen=True, tag="state"):
    """A drone's state at 10 Hz (key ``<swarm>/drone/<id>/state``).

    measured_s: global time of the autopilot sample; attitude_wxyz: unit quaternion of the body
    (FLU) in ENU; autopilot_mode: PX4 mode name (e.g. ``OFFBOARD``, ``AUTO.LOITER``)."""

    flight_state: str
    measured_s: float
    position_m: Vec3
    velocity_m_s: Vec3
    attitude_wxyz: tuple[float, float, float, float]
    armed: bool
    autopilot_mode: str
    slot: int
    formation_epoch: int


class LinkHealth(_Wire, frozen=True):
    """One link of a drone: ``name`` (``autopilot``, ``gcs``, ``depth``, ``peer/3``...), whether
    it is up, and the age of its last message (None: never heard)."""

    name: str
    up: bool
    age_s: float | None


class StatusBody(_Wire, frozen=True, tag="status"):
    """A drone's status at 1 Hz (key ``<swarm>/drone/<id>/status``).

    plan_status: last planner status name ('' before the first plan); plan_stamp_s: global time
    of the last plan; plan_ms_last / plan_ms_max: its duration and the longest since the last
    status; replans: plans so far; links: link health; battery_v / battery_remaining (0..1):
    None when unknown; clock_offset_max_s: largest estimated |offset| to a peer (None: no
    estimate); counters: bus and service counters; message: last event, free text."""

    flight_state: str
    plan_status: str
    plan_stamp_s: float | None
    plan_ms_last: float
    plan_ms_max: float
    replans: int
    links: list[LinkHealth]
    battery_v: float | None
    battery_remaining: float | None
    clock_offset_max_s: float | None
    counters: dict[str, int]
    message: str


# --- ground-station commands (key <swarm>/cmd/<action>) ----------------------------------------


class Takeoff(_Wire, frozen=True, tag="takeoff"):
    altitude_m: float


class Land(_Wire, frozen=True, tag="land"):
    pass


class Abort(_Wire, frozen=True, tag="abort"):
    """Every addressed drone stops and hovers, then lands."""


class Resume(_Wire, frozen=True, tag="resume"):
    pass


class Goal(_Wire, frozen=True, tag="goal"):
    """Fly the formation to ``position_m`` (ENU), optional final yaw; takes effect at the global
    time ``effective_s`` on every drone (a time in the past: at once)."""

    position_m: Vec3
    yaw_rad: float | None
    effective_s: float


class Waypoints(_Wire, frozen=True, tag="waypoints"):
    points_m: list[Vec3]
    effective_s: float


class FormationAssignment(_Wire, frozen=True, tag="formation"):
    """A formation: template ``points_m`` (scaled by ``scale``, rotated by ``yaw_rad`` about
    up), ``slots`` mapping drone id -> template row, its ``epoch`` (increases with every
    assignment; a drone never flies two epochs at once) and the common global time
    ``effective_s`` at which every drone switches to it."""

    points_m: list[Vec3]
    scale: float
    yaw_rad: float
    slots: dict[int, int]
    epoch: int
    effective_s: float


Action = Takeoff | Land | Abort | Resume | Goal | Waypoints | FormationAssignment
ACTIONS = ("takeoff", "land", "abort", "resume", "goal", "waypoints", "formation")


class Command(_Wire, frozen=True, tag="cmd"):
    """A ground-station command: ``cmd_id`` (unique per ground station, >= 1), ``targets``
    (drone ids; empty: every drone), ``issued_s`` (global time the operator issued it; a
    resend keeps it) and the ``action``."""

    cmd_id: int
    targets: list[int]
    issued_s: float
    action: Action


class Ack(_Wire, frozen=True, tag="ack"):
    """A drone's answer to a command (key ``<swarm>/ack/<drone id>``)."""

    cmd_id: int
    accepted: bool
    reason: str


Body = TrajectoryBody | StateBody | StatusBody | Command | Ack


class Envelope(_Wire, frozen=True):
    """One wire message: the header (see the module docstring) and a body."""

    version: int
    sender: int
    incarnation: int
    seq: int
    stamp_s: float
    valid_for_s: float
    body: Body

    @property
    def kind(self) -> str:
        """The body's kind, one of :data:`STREAMS`."""
        return kind_of(self.body)

    @property
    def valid_until_s(self) -> float:
        return self.stamp_s + self.valid_for_s


def kind_of(body: Any) -> str:
    tag = type(body).__struct_config__.tag
    assert isinstance(tag, str)
    return tag


class _Probe(msgspec.Struct, array_like=True):
    version: int


_probe_decoder = msgspec.msgpack.Decoder(_Probe)
_decoder = msgspec.msgpack.Decoder(Envelope)
_encoder = msgspec.msgpack.Encoder()


# --- encode / decode -------------------------------------------------------------------------


def encode(env: Envelope, limits: WireLimits = DEFAULT_LIMITS) -> bytes:
    """The msgpack bytes of ``env`` after the same checks a receiver makes (raises
    :class:`Rejected` naming the field, so a bad message is refused where it is made)."""
    validate(env, limits)
    data = _encoder.encode(env)
    bound = limits.max_bytes(env.kind)
    if len(data) > bound:
        raise Rejected("oversized", f"{env.kind} message of {len(data)} bytes > {bound}")
    return data


def decode(
    payload: bytes | bytearray | memoryview,
    limits: WireLimits = DEFAULT_LIMITS,
    kind: str | None = None,
) -> Envelope:
    """Decode and check one message (``kind``: the kind its key expression promises, for the
    size bound). Returns the envelope, or raises :class:`Rejected`; never anything else."""
    bound = limits.max_bytes(kind)
    if len(payload) > bound:
        raise Rejected("oversized", f"payload of {len(payload)} bytes > {bound}")
    try:
        version = _probe_decoder.decode(payload).version
    except _DECODE_ERRORS as e:
        raise _decode_rejection(e) from None
    if version != WIRE_VERSION:
        raise Rejected("version", f"version {version}, this node speaks {WIRE_VERSION}")
    try:
        env = _decoder.decode(payload)
    except _DECODE_ERRORS as e:
        raise _decode_rejection(e) from None
    validate(env, limits)
    return env


# What msgspec raises on bad input: DecodeError (ValidationError is one) and, for strings that
# are not UTF-8, UnicodeDecodeError.
_DECODE_ERRORS = (msgspec.DecodeError, UnicodeDecodeError)


def _decode_rejection(e: Exception) -> Rejected:
    text = str(e)
    if "truncated" in text:
        return Rejected("truncated", text)
    return Rejected("malformed", text)


# --- checks ----------------------------------------------------------------------------------

_NAME_RE = re.compile(r"[A-Za-z0-9_.:/\-]*")


def validate(env: Envelope, limits: WireLimits = DEFAULT_LIMITS) -> None:
    """Every stateless check of one message; raises :class:`Rejected` naming the field."""
    if env.version != WIRE_VERSION:
        raise Rejected("version", f"version {env.version}, this node speaks {WIRE_VERSION}")
    _check_finite(env, "")
    _int_range("sender", env.sender, 0, MAX_INT)
    _int_range("incarnation", env.incarnation, 0, MAX_INT)
    _int_range("seq", env.seq, 0, MAX_INT)
    if not 0.0 < env.stamp_s < 2.0**33:
        raise Rejected("bad_value", f"stamp_s {env.stamp_s} is not a global time in seconds")
    if not 0.0 < env.valid_for_s <= limits.max_valid_for_s:
        raise Rejected(
            "bad_duration", f"valid_for_s {env.valid_for_s} not in (0, {limits.max_valid_for_s}]"
        )
    body = env.body
    if isinstance(body, TrajectoryBody):
        _check_trajectory(body, env.stamp_s, limits)
    elif isinstance(body, StateBody):
        _check_state(body, limits)
    elif isinstance(body, StatusBody):
        _check_status(body, limits)
    elif isinstance(body, Command):
        _check_command(body, env.stamp_s, limits)
    elif isinstance(body, Ack):
        _int_range("body.cmd_id", body.cmd_id, 1, MAX_INT)
        _text("body.reason", body.reason, limits)
    else:  # pragma: no cover - the decoder only builds the types above
        raise Rejected("malformed", f"unknown body type {type(body).__name__}")
    if kind_of(body) in ("traj", "state", "status", "ack"):
        _int_range("sender", env.sender, 0, MAX_DRONE_ID)
    elif env.sender < GCS_ID:
        raise Rejected("bad_value", f"sender {env.sender} of a command is not a ground station")


def _check_finite(obj: Any, path: str) -> None:
    """Raise ``non_finite`` at the first NaN or infinity anywhere inside ``obj``."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise Rejected("non_finite", f"{path or 'value'} is {obj}")
    elif isinstance(obj, msgspec.Struct):
        for name in obj.__struct_fields__:
            _check_finite(getattr(obj, name), f"{path}.{name}" if path else name)
    elif isinstance(obj, (list, tuple)):
        # Fast path for long float lists (coefficients): a sum is non-finite if any term is
        # (or if it overflows; then the scan below finds nothing and the list passes).
        if len(obj) > 8 and all(type(x) is float for x in obj) and math.isfinite(sum(obj)):
            return
        for i, x in enumerate(obj):
            _check_finite(x, f"{path}[{i}]")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_finite(v, f"{path}[{k!r}]")


def _int_range(name: str, value: int, lo: int, hi: int) -> None:
    if not lo <= value <= hi:
        raise Rejected("bad_value", f"{name} {value} not in [{lo}, {hi}]")


def _count(name: str, n: int, bound: int, reason: str = "oversized") -> None:
    if n > bound:
        raise Rejected(reason, f"{name} has {n} entries > {bound}")


def _text(name: str, s: str, limits: WireLimits) -> None:
    if len(s) > limits.max_text:
        raise Rejected("oversized", f"{name} is {len(s)} characters > {limits.max_text}")
    if not s.isprintable():
        raise Rejected("bad_value", f"{name} has non-printable characters")


def _name(field: str, s: str, limits: WireLimits, max_len: int = 32) -> None:
    if len(s) > max_len or _NAME_RE.fullmatch(s) is None:
        raise Rejected(
            "bad_value", f"{field} {s[:40]!r} is not a name (<= {max_len} of A-Za-z0-9_.:/-)"
        )


def _coord(field: str, p: Sequence[float], limits: WireLimits) -> None:
    if max(abs(x) for x in p) > limits.max_abs_coord_m:
        raise Rejected("bad_value", f"{field} {tuple(p)} beyond {limits.max_abs_coord_m} m")


def _check_trajectory(b: TrajectoryBody, stamp_s: float, limits: WireLimits) -> None:
    m = len(b.durations_s)
    if m == 0:
        raise Rejected("bad_duration", "durations_s is empty")
    _count("body.durations_s", m, limits.max_pieces, "too_many_pieces")
    if len(b.coeffs) != m * COEFFS_PER_PIECE:
        raise Rejected(
            "malformed", f"body.coeffs has {len(b.coeffs)} values, {m} pieces need {m * 18}"
        )
    _int_range("body.traj_id", b.traj_id, 0, MAX_INT)
    _int_range("body.slot", b.slot, -1, limits.max_formation_points - 1)
    _int_range("body.formation_epoch", b.formation_epoch, 0, MAX_INT)
    lo, hi, total = min(b.durations_s), max(b.durations_s), sum(b.durations_s)
    if lo < limits.min_piece_s or hi > limits.max_piece_s:
        raise Rejected(
            "bad_duration",
            f"body.durations_s range [{lo}, {hi}] outside "
            f"[{limits.min_piece_s}, {limits.max_piece_s}]",
        )
    if total > limits.max_total_s:
        raise Rejected("bad_duration", f"body.durations_s total {total} > {limits.max_total_s}")
    if abs(b.t0_s - stamp_s) > limits.max_total_s:
        raise Rejected("bad_value", f"body.t0_s {b.t0_s} is {b.t0_s - stamp_s:.0f} s from stamp")
    # Knots (the start and end of every piece) and their velocities, by Horner's rule in
    # plain Python (faster than numpy for a few pieces).
    co = b.coeffs
    if max(map(abs, co)) > MAX_COEFF:
        raise Rejected("bad_value", f"body.coeffs has a coefficient beyond {MAX_COEFF:g}")
    far = limits.max_abs_coord_m
    v2max = limits.max_speed_m_s**2
    for i, T in enumerate(b.durations_s):
        o = i * COEFFS_PER_PIECE
        v0 = v1 = 0.0
        for d in range(3):
            c0, c1, c2, c3, c4, c5 = co[o + d : o + COEFFS_PER_PIECE : 3]
            p1 = ((((c5 * T + c4) * T + c3) * T + c2) * T + c1) * T + c0
            dp1 = (((5 * c5 * T + 4 * c4) * T + 3 * c3) * T + 2 * c2) * T + c1
            if abs(c0) > far or abs(p1) > far:
                raise Rejected("bad_value", f"body.coeffs piece {i} reaches beyond {far} m")
            v0 += c1 * c1
            v1 += dp1 * dp1
        if max(v0, v1) > v2max:
            speed = math.sqrt(max(v0, v1))
            raise Rejected(
                "bad_value", f"body.coeffs piece {i} speed {speed:.1f} m/s > {limits.max_speed_m_s}"
            )


MAX_COEFF = 1e12
"""Largest |coefficient|: with pieces of at most 600 s no knot overflows a double."""


def _check_state(b: StateBody, limits: WireLimits) -> None:
    _name("body.flight_state", b.flight_state, limits)
    _name("body.autopilot_mode", b.autopilot_mode, limits)
    if not 0.0 < b.measured_s < 2.0**33:
        raise Rejected("bad_value", f"body.measured_s {b.measured_s} is not a global time")
    _coord("body.position_m", b.position_m, limits)
    if math.hypot(*b.velocity_m_s) > limits.max_speed_m_s:
        raise Rejected("bad_value", f"body.velocity_m_s {b.velocity_m_s} too fast")
    norm = math.sqrt(sum(q * q for q in b.attitude_wxyz))
    if abs(norm - 1.0) > 1e-2:
        raise Rejected("bad_value", f"body.attitude_wxyz has norm {norm:.4f}, not 1")
    _int_range("body.slot", b.slot, -1, limits.max_formation_points - 1)
    _int_range("body.formation_epoch", b.formation_epoch, 0, MAX_INT)


def _nonneg(field: str, x: float | None, hi: float) -> None:
    if x is not None and not 0.0 <= x <= hi:
        raise Rejected("bad_value", f"{field} {x} not in [0, {hi}]")


def _check_status(b: StatusBody, limits: WireLimits) -> None:
    _name("body.flight_state", b.flight_state, limits)
    _name("body.plan_status", b.plan_status, limits)
    if b.plan_stamp_s is not None and not 0.0 < b.plan_stamp_s < 2.0**33:
        raise Rejected("bad_value", f"body.plan_stamp_s {b.plan_stamp_s} is not a global time")
    _nonneg("body.plan_ms_last", b.plan_ms_last, 1e7)
    _nonneg("body.plan_ms_max", b.plan_ms_max, 1e7)
    _int_range("body.replans", b.replans, 0, MAX_INT)
    _count("body.links", len(b.links), limits.max_links)
    for i, link in enumerate(b.links):
        _name(f"body.links[{i}].name", link.name, limits)
        _nonneg(f"body.links[{i}].age_s", link.age_s, 1e9)
    _nonneg("body.battery_v", b.battery_v, 100.0)
    _nonneg("body.battery_remaining", b.battery_remaining, 1.0)
    _nonneg("body.clock_offset_max_s", b.clock_offset_max_s, 1e9)
    _count("body.counters", len(b.counters), limits.max_counters)
    for k, v in b.counters.items():
        _name("body.counters key", k, limits, max_len=64)
        _int_range(f"body.counters[{k!r}]", v, 0, MAX_INT)
    _text("body.message", b.message, limits)


def _points(field: str, pts: Sequence[Sequence[float]], bound: int, limits: WireLimits) -> None:
    if len(pts) == 0:
        raise Rejected("bad_value", f"{field} is empty")
    _count(field, len(pts), bound)
    for i, p in enumerate(pts):
        _coord(f"{field}[{i}]", p, limits)


def _effective(field: str, t: float, stamp_s: float, limits: WireLimits) -> None:
    if abs(t - stamp_s) > limits.max_total_s:
        raise Rejected("bad_value", f"{field} {t} is {t - stamp_s:.0f} s from the stamp")


def _check_command(b: Command, stamp_s: float, limits: WireLimits) -> None:
    _int_range("body.cmd_id", b.cmd_id, 1, MAX_INT)
    _count("body.targets", len(b.targets), limits.max_targets)
    for t in b.targets:
        _int_range("body.targets[]", t, 0, MAX_DRONE_ID)
    if len(set(b.targets)) != len(b.targets):
        raise Rejected("bad_value", f"body.targets {b.targets} has duplicates")
    if not 0.0 < b.issued_s < 2.0**33:
        raise Rejected("bad_value", f"body.issued_s {b.issued_s} is not a global time")
    a = b.action
    if isinstance(a, Takeoff):
        if not 0.0 < a.altitude_m <= limits.max_altitude_m:
            raise Rejected(
                "bad_value",
                f"takeoff altitude_m {a.altitude_m} not in (0, {limits.max_altitude_m}]",
            )
    elif isinstance(a, Goal):
        _coord("goal position_m", a.position_m, limits)
        if a.yaw_rad is not None and abs(a.yaw_rad) > 4 * math.pi:
            raise Rejected("bad_value", f"goal yaw_rad {a.yaw_rad} not in [-4 pi, 4 pi]")
        _effective("goal effective_s", a.effective_s, stamp_s, limits)
    elif isinstance(a, Waypoints):
        _points("waypoints points_m", a.points_m, limits.max_waypoints, limits)
        _effective("waypoints effective_s", a.effective_s, stamp_s, limits)
    elif isinstance(a, FormationAssignment):
        _check_formation(a, stamp_s, limits)


def _check_formation(a: FormationAssignment, stamp_s: float, limits: WireLimits) -> None:
    n = len(a.points_m)
    _points("formation points_m", a.points_m, limits.max_formation_points, limits)
    if not 0.0 < a.scale <= 1000.0:
        raise Rejected("bad_value", f"formation scale {a.scale} not in (0, 1000]")
    if abs(a.yaw_rad) > 4 * math.pi:
        raise Rejected("bad_value", f"formation yaw_rad {a.yaw_rad} not in [-4 pi, 4 pi]")
    P = np.asarray(a.points_m, dtype=np.float64) * a.scale
    if np.abs(P).max() > limits.max_abs_coord_m:
        raise Rejected("bad_value", "formation points_m * scale beyond the coordinate bound")
    if n > 1:
        d = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=-1)
        d[np.diag_indices(n)] = np.inf
        if d.min() < 1e-3:
            i, j = np.unravel_index(int(np.argmin(d)), d.shape)
            raise Rejected("bad_value", f"formation points_m[{i}] and [{j}] coincide")
    _count("formation slots", len(a.slots), limits.max_formation_points)
    for drone, slot in a.slots.items():
        _int_range("formation slots key (drone id)", drone, 0, MAX_DRONE_ID)
        _int_range(f"formation slots[{drone}]", slot, 0, n - 1)
    if len(set(a.slots.values())) != len(a.slots):
        raise Rejected("bad_value", "formation slots gives two drones the same slot")
    _int_range("formation epoch", a.epoch, 0, MAX_INT)
    _effective("formation effective_s", a.effective_s, stamp_s, limits)


# --- conversions -----------------------------------------------------------------------------


def trajectory_body(
    traj_id: int,
    slot: int,
    formation_epoch: int,
    t0_s: float,
    durations_s: Iterable[float],
    coeffs: np.ndarray,
) -> TrajectoryBody:
    """A trajectory body from arrays (``coeffs`` of shape (M, 6, 3))."""
    c = np.asarray(coeffs, dtype=np.float64)
    return TrajectoryBody(
        traj_id=int(traj_id),
        slot=int(slot),
        formation_epoch=int(formation_epoch),
        t0_s=float(t0_s),
        durations_s=[float(x) for x in durations_s],
        coeffs=c.reshape(-1).tolist(),
    )


def coeff_array(b: TrajectoryBody) -> np.ndarray:
    """The ``(M, 6, 3)`` coefficient array of a trajectory body."""
    return np.asarray(b.coeffs, dtype=np.float64).reshape(len(b.durations_s), N_COEFFS, 3)
