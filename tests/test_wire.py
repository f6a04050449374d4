"""Swarm bus wire schema: round trips, every rejection reason with its counter, fuzzed decoders."""

from __future__ import annotations

import math
import os
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onboard.comm.clock import ClockOffsets
from onboard.comm.gate import MessageGate
from onboard.comm.keys import SwarmKeys, check_swarm
from onboard.comm.messages import TrajectoryMsg
from onboard.comm.wire import (
    GCS_ID,
    REASONS,
    WIRE_VERSION,
    Abort,
    Ack,
    Command,
    Envelope,
    FormationAssignment,
    Goal,
    Land,
    LinkHealth,
    Rejected,
    Resume,
    StateBody,
    StatusBody,
    Takeoff,
    TrajectoryBody,
    Waypoints,
    WireLimits,
    decode,
    encode,
)
from onboard.planner.trajectory import Trajectory

NOW = 1_700_000_000.0
SWARM = "test/swarm"
KEYS = SwarmKeys(SWARM)


def traj_body(pieces: int = 6, seed: int = 0, t0: float = NOW) -> TrajectoryBody:
    rng = np.random.default_rng(seed)
    c = rng.normal(scale=0.2, size=(pieces, 6, 3))
    c[:, 0] += np.array([5.0, 2.0, 1.0])
    return TrajectoryMsg(
        1, 7, 1, Trajectory(t0, c, np.full(pieces, 1.1)), formation_epoch=2
    ).to_body()


def state_body() -> StateBody:
    return StateBody(
        flight_state="FORMATION_FLIGHT",
        measured_s=NOW - 0.01,
        position_m=(1.0, 2.0, 1.5),
        velocity_m_s=(0.5, 0.0, 0.0),
        attitude_wxyz=(1.0, 0.0, 0.0, 0.0),
        armed=True,
        autopilot_mode="OFFBOARD",
        slot=1,
        formation_epoch=2,
    )


def status_body() -> StatusBody:
    return StatusBody(
        flight_state="HOVER",
        plan_status="kept-previous",
        plan_stamp_s=NOW - 0.5,
        plan_ms_last=42.0,
        plan_ms_max=80.5,
        replans=17,
        links=[LinkHealth("autopilot", True, 0.02), LinkHealth("gcs", False, None)],
        battery_v=15.8,
        battery_remaining=None,
        clock_offset_max_s=0.003,
        counters={"reject.stale": 2, "rx.traj": 120},
        message="replanned after a predicted collision",
    )


ACTIONS_SAMPLE: list[Any] = [
    Takeoff(2.5),
    Land(),
    Abort(),
    Resume(),
    Goal((20.0, 0.0, 1.0), None, NOW + 1.0),
    Goal((20.0, 0.0, 1.0), 1.57, NOW + 1.0),
    Waypoints([(1.0, 0.0, 1.0), (5.0, 2.0, 1.0)], NOW),
    FormationAssignment(
        [(0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (1.0, 1.7, 0.0)],
        1.5,
        0.3,
        {0: 2, 1: 0, 4: 1},
        3,
        NOW + 2,
    ),
]


def env(
    body: Any,
    sender: int = 1,
    seq: int = 0,
    stamp: float = NOW,
    valid: float = 3.0,
    incarnation: int = 10,
    version: int = WIRE_VERSION,
) -> Envelope:
    if isinstance(body, Command) and sender == 1:
        sender = GCS_ID
    return Envelope(version, sender, incarnation, seq, stamp, valid, body)


def cmd(action: Any, targets: list[int] | None = None, cmd_id: int = 5) -> Command:
    return Command(cmd_id, targets if targets is not None else [], NOW - 0.1, action)


def all_samples() -> list[Envelope]:
    return [
        env(traj_body()),
        env(state_body()),
        env(status_body()),
        env(Ack(5, False, "goal outside the geofence")),
        *[env(cmd(a, [0, 3])) for a in ACTIONS_SAMPLE],
    ]


def key_of(e: Envelope) -> str:
    if isinstance(e.body, Command):
        return KEYS.cmd(type(e.body.action).__struct_config__.tag)  # type: ignore[arg-type]
    if isinstance(e.body, Ack):
        return KEYS.ack(e.sender)
    return KEYS.drone(e.sender, e.kind)


def raw(e: Envelope) -> bytes:
    """Encoded without the sender-side checks (to forge bad messages)."""
    return msgspec.msgpack.encode(e)


def walk_floats(obj: Any) -> list[float]:
    if isinstance(obj, float):
        return [obj]
    if isinstance(obj, msgspec.Struct):
        return [x for n in obj.__struct_fields__ for x in walk_floats(getattr(obj, n))]
    if isinstance(obj, (list, tuple)):
        return [x for v in obj for x in walk_floats(v)]
    if isinstance(obj, dict):
        return [x for v in obj.values() for x in walk_floats(v)]
    return []


# --- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("e", all_samples(), ids=lambda e: e.kind)
def test_round_trip_every_message(e: Envelope) -> None:
    data = encode(e)
    assert decode(data) == e
    gate = MessageGate(SWARM, own_id=0)
    assert gate.admit(key_of(e), data, NOW) == e
    assert gate.counters[f"rx.{e.kind}"] == 1


def test_trajectory_message_round_trip_and_compact() -> None:
    c = np.random.default_rng(1).normal(size=(6, 6, 3))
    msg = TrajectoryMsg(4, 9, 2, Trajectory(NOW, c, np.linspace(0.5, 1.5, 6)), formation_epoch=3)
    data = encode(env(msg.to_body(), sender=4, valid=2.5))
    assert len(data) < 1200  # 108 doubles + header: about 1 KB
    back = TrajectoryMsg.from_envelope(decode(data))
    assert (back.drone_id, back.traj_id, back.slot, back.formation_epoch) == (4, 9, 2, 3)
    assert back.valid_until_s == NOW + 2.5
    np.testing.assert_array_equal(back.trajectory.coeffs, msg.trajectory.coeffs)
    np.testing.assert_array_equal(back.trajectory.durations_s, msg.trajectory.durations_s)
    assert back.trajectory.t0_s == NOW


def test_trajectory_msg_keeps_constructor_order() -> None:
    tr = Trajectory.hover(np.zeros(3), 0.0)
    m = TrajectoryMsg(1, 2, 3, tr)
    assert (m.drone_id, m.traj_id, m.slot, m.trajectory) == (1, 2, 3, tr)
    assert m.formation_epoch == 0 and m.valid_until_s == math.inf


def test_wire_layout_is_positional_with_version_first() -> None:
    data = encode(env(Ack(5, True, "")))
    assert msgspec.msgpack.decode(data) == [WIRE_VERSION, 1, 10, 0, NOW, 3.0, ["ack", 5, True, ""]]


# --- every rejection reason, counted ----------------------------------------------------------


def forged(**kw: Any) -> tuple[str, bytes]:
    e = env(traj_body(), **kw)
    return key_of(e), raw(e)


def bad_cases() -> dict[str, tuple[str, bytes, float]]:
    """reason -> (key, payload, receive time)."""
    k_traj = KEYS.traj(1)
    good = raw(env(traj_body()))
    tb = traj_body()
    cases: dict[str, tuple[str, bytes, float]] = {
        "version": (*forged(version=WIRE_VERSION + 1), NOW),
        "truncated": (k_traj, good[:-5], NOW),
        "malformed": (k_traj, msgspec.msgpack.encode([WIRE_VERSION, "one", 2]), NOW),
        "oversized": (k_traj, good + b"\x00" * 20000, NOW),
        "non_finite": (
            k_traj,
            raw(env(msgspec.structs.replace(tb, coeffs=[*tb.coeffs[:-1], math.inf]))),
            NOW,
        ),
        "bad_duration": (
            k_traj,
            raw(env(msgspec.structs.replace(tb, durations_s=[1.0, 0.0, 1.0, 1.0, 1.0, 1.0]))),
            NOW,
        ),
        "too_many_pieces": (k_traj, raw(env(traj_body(pieces=65))), NOW),
        "bad_value": (k_traj, raw(env(msgspec.structs.replace(tb, slot=-5))), NOW),
        "bad_key": ("test/swarm/drone/01/traj", good, NOW),
        "kind_mismatch": (k_traj, raw(env(state_body())), NOW),
        "sender_mismatch": (KEYS.traj(2), good, NOW),
        "own_id": (KEYS.traj(0), raw(env(traj_body(), sender=0)), NOW),
        "future_stamp": (k_traj, raw(env(traj_body(), stamp=NOW + 5.0)), NOW),
        "stale": (k_traj, good, NOW + 3.5),
    }
    return cases


@pytest.mark.parametrize("reason", list(bad_cases()))
def test_each_rejection_reason_is_counted(reason: str) -> None:
    key, payload, t = bad_cases()[reason]
    gate = MessageGate(SWARM, own_id=0)
    with pytest.raises(Rejected) as info:
        gate.admit(key, payload, t)
    assert info.value.reason == reason
    assert gate.counters[f"reject.{reason}"] == 1
    assert sum(v for k, v in gate.counters.items() if k.startswith("reject.")) == 1
    assert gate.counters["rx.traj"] == 0


def test_every_reason_has_a_case() -> None:
    assert set(bad_cases()) | {"duplicate", "out_of_order"} == set(REASONS)


def test_duplicate_and_out_of_order_per_sender_and_stream() -> None:
    gate = MessageGate(SWARM, own_id=0)
    k = KEYS.traj(1)
    gate.admit(k, raw(env(traj_body(), seq=5)), NOW)
    with pytest.raises(Rejected, match="duplicate"):
        gate.admit(k, raw(env(traj_body(), seq=5)), NOW)
    with pytest.raises(Rejected, match="out_of_order"):
        gate.admit(k, raw(env(traj_body(), seq=4)), NOW)
    gate.admit(k, raw(env(traj_body(), seq=7)), NOW)  # gaps are fine (lost messages)
    # Other streams and senders have their own sequence.
    gate.admit(KEYS.state(1), raw(env(state_body(), seq=0)), NOW)
    gate.admit(KEYS.traj(2), raw(env(traj_body(), sender=2, seq=0)), NOW)
    assert gate.counters["reject.duplicate"] == 1
    assert gate.counters["reject.out_of_order"] == 1
    assert gate.counters["rx.traj"] == 3 and gate.counters["rx.state"] == 1


def test_restarted_sender_accepted_by_its_larger_incarnation() -> None:
    gate = MessageGate(SWARM, own_id=0, resync_after_s=5.0)
    k = KEYS.traj(1)
    gate.admit(k, raw(env(traj_body(), seq=100, incarnation=10)), NOW)
    gate.admit(k, raw(env(traj_body(), seq=0, incarnation=11)), NOW + 0.1)  # restarted
    with pytest.raises(Rejected, match="out_of_order"):  # a late message of the old process
        gate.admit(k, raw(env(traj_body(), seq=101, incarnation=10)), NOW + 0.2)
    # A restart whose clock stepped back: refused at first, accepted after a silence.
    late = NOW + 6.0
    gate.admit(k, raw(env(traj_body(), seq=0, incarnation=3, stamp=late)), late)
    assert gate.counters["resync"] == 1


def test_clock_sample_kept_even_for_stale_messages() -> None:
    gate = MessageGate(SWARM, own_id=0, clock=ClockOffsets(bound_s=0.05))
    with pytest.raises(Rejected, match="stale"):
        gate.admit(KEYS.traj(1), raw(env(traj_body(), stamp=NOW - 10.0)), NOW)
    assert gate.clock.offset(1) == pytest.approx(10.0)
    assert gate.clock.exceeded() == {1}


@pytest.mark.parametrize(
    "bad, reason, field",
    [
        (env(state_body(), sender=1000), "bad_value", "sender"),
        (
            env(msgspec.structs.replace(state_body(), position_m=(0.0, math.nan, 1.0))),
            "non_finite",
            "body.position_m[1]",
        ),
        (
            env(msgspec.structs.replace(state_body(), attitude_wxyz=(0.5, 0.0, 0.0, 0.0))),
            "bad_value",
            "attitude_wxyz",
        ),
        (
            env(msgspec.structs.replace(state_body(), flight_state="HOVER; rm -rf")),
            "bad_value",
            "flight_state",
        ),
        (env(state_body(), valid=0.0), "bad_duration", "valid_for_s"),
        (env(state_body(), valid=1e6), "bad_duration", "valid_for_s"),
        (env(traj_body(), stamp=math.inf), "non_finite", "stamp_s"),
        (env(msgspec.structs.replace(traj_body(), t0_s=NOW + 1e5)), "bad_value", "t0_s"),
        (
            env(msgspec.structs.replace(traj_body(7), durations_s=[599.0] * 7)),
            "bad_duration",
            "total",
        ),
        (
            env(msgspec.structs.replace(traj_body(), coeffs=traj_body().coeffs[:-1])),
            "malformed",
            "coeffs",
        ),
        (env(msgspec.structs.replace(traj_body(), coeffs=[1e6] * 108)), "bad_value", "coeffs"),
        (
            env(msgspec.structs.replace(traj_body(), coeffs=[*traj_body().coeffs[:-1], 1e300])),
            "bad_value",
            "beyond 1e+12",
        ),
        (
            env(msgspec.structs.replace(status_body(), battery_remaining=1.5)),
            "bad_value",
            "battery_remaining",
        ),
        (env(msgspec.structs.replace(status_body(), counters={"x": -1})), "bad_value", "counters"),
        (env(msgspec.structs.replace(status_body(), message="x" * 201)), "oversized", "message"),
        (env(Ack(0, True, "")), "bad_value", "cmd_id"),
        (env(cmd(Takeoff(0.0))), "bad_value", "altitude_m"),
        (env(cmd(Takeoff(1e4))), "bad_value", "altitude_m"),
        (env(cmd(Land(), targets=[1, 1])), "bad_value", "targets"),
        (env(cmd(Land(), targets=list(range(65)))), "oversized", "targets"),
        (env(cmd(Land()), sender=3), "bad_value", "ground station"),
        (env(cmd(Goal((2e4, 0.0, 1.0), None, NOW))), "bad_value", "goal position_m"),
        (env(cmd(Goal((2.0, 0.0, 1.0), math.nan, NOW))), "non_finite", "yaw_rad"),
        (env(cmd(Waypoints([], NOW))), "bad_value", "points_m is empty"),
        (env(cmd(Waypoints([(0.0, 0.0, 1.0)] * 257, NOW))), "oversized", "points_m"),
        (
            env(cmd(FormationAssignment([(0.0, 0.0, 0.0)] * 1000, 1.0, 0.0, {}, 1, NOW))),
            "oversized",
            "points_m",
        ),
        (
            env(cmd(FormationAssignment([(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)], 1.0, 0.0, {}, 1, NOW))),
            "bad_value",
            "coincide",
        ),
        (
            env(
                cmd(FormationAssignment([(0.0, 0, 0), (1.0, 0, 0)], 1.0, 0.0, {0: 0, 1: 0}, 1, NOW))
            ),
            "bad_value",
            "same slot",
        ),
        (
            env(cmd(FormationAssignment([(0.0, 0, 0), (1.0, 0, 0)], 1.0, 0.0, {0: 2}, 1, NOW))),
            "bad_value",
            "slots[0]",
        ),
        (
            env(cmd(FormationAssignment([(0.0, 0, 0), (1.0, 0, 0)], 0.0, 0.0, {0: 1}, 1, NOW))),
            "bad_value",
            "scale",
        ),
    ],
)
def test_encoder_and_decoder_refuse_bad_values_naming_the_field(
    bad: Envelope, reason: str, field: str
) -> None:
    with pytest.raises(Rejected) as sent:
        encode(bad)
    assert sent.value.reason == reason and field in str(sent.value)
    with pytest.raises(Rejected) as got:
        decode(raw(bad))
    assert got.value.reason == reason


def test_limits_are_configurable() -> None:
    tight = WireLimits(max_pieces=4)
    with pytest.raises(Rejected, match="too_many_pieces"):
        decode(encode(env(traj_body(pieces=6))), tight)
    with pytest.raises(ValueError, match="max_pieces"):
        WireLimits(max_pieces=0)


def test_keys() -> None:
    assert KEYS.traj(3) == "test/swarm/drone/3/traj"
    assert KEYS.cmd("goal") == "test/swarm/cmd/goal"
    assert KEYS.ack(3) == "test/swarm/ack/3"
    assert KEYS.alive_drone(3) == "test/swarm/alive/drone/3"
    assert KEYS.parse("test/swarm/drone/12/status") == ("status", 12)
    assert KEYS.parse("test/swarm/cmd/formation") == ("cmd", "formation")
    assert KEYS.parse_alive("test/swarm/alive/gcs") == ("gcs", None)
    assert KEYS.parse_alive("test/swarm/alive/drone/4") == ("drone", 4)
    for bad in (
        "test/swarm/drone/-1/traj",
        "test/swarm/cmd/fly",
        "other/drone/1/traj",
        "test/swarm/drone/1000/traj",
        "test/swarm/drone/1/traj/x",
    ):
        with pytest.raises(Rejected, match="bad_key"):
            KEYS.parse(bad)
    for name in ("", "a/*", "a//b", "a b", "x/**"):
        with pytest.raises(ValueError, match="swarm name"):
            check_swarm(name)
    with pytest.raises(ValueError, match="drone id"):
        KEYS.traj(1000)


# --- fuzzing: nothing but Rejected, never a non-finite value ---------------------------------

SAMPLES = [raw(e) for e in all_samples()]
SAMPLE_KEYS = [key_of(e) for e in all_samples()]
# SWARM_FUZZ_EXAMPLES=100000 for a long fuzzing run (the suite uses a few hundred per target).
N_FUZZ = int(os.environ.get("SWARM_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=N_FUZZ, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FUZZ_TREES = settings(FUZZ, max_examples=max(N_FUZZ // 3, 1))


def admit_or_reject(key: str, payload: bytes) -> None:
    gate = MessageGate(SWARM, own_id=0)
    try:
        e = gate.admit(key, payload, NOW)
    except Rejected as r:
        assert r.reason in REASONS
        assert gate.counters[f"reject.{r.reason}"] == 1
        return
    assert all(math.isfinite(x) for x in walk_floats(e))
    assert decode(encode(e)) == e  # whatever is accepted could have been sent


@FUZZ
@given(st.binary(max_size=2000), st.sampled_from(SAMPLE_KEYS))
def test_random_bytes_only_rejected(payload: bytes, key: str) -> None:
    admit_or_reject(key, payload)


@FUZZ
@given(
    st.integers(0, len(SAMPLES) - 1),
    st.lists(st.tuples(st.integers(0, 100_000), st.integers(0, 255)), min_size=1, max_size=8),
    st.integers(0, 3),
)
def test_mutated_valid_messages_only_rejected(
    which: int, edits: list[tuple[int, int]], mode: int
) -> None:
    data = bytearray(SAMPLES[which])
    for pos, byte in edits:
        i = pos % len(data)
        if mode == 0:
            data[i] = byte  # overwrite
        elif mode == 1:
            data[i] ^= 1 << (byte % 8)  # bit flip
        elif mode == 2:
            data.insert(i, byte)  # insertion
        else:
            del data[i:]  # truncation
            if not data:
                break
    admit_or_reject(SAMPLE_KEYS[which], bytes(data))


_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**64), 2**64),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=40),
    st.binary(max_size=20),
)
_tree = st.recursive(
    _leaf, lambda c: st.lists(c, max_size=8) | st.dictionaries(_leaf, c, max_size=4), max_leaves=60
)


@FUZZ_TREES
@given(st.integers(0, len(SAMPLES) - 1), st.lists(st.tuples(st.integers(0, 64), _tree), max_size=4))
def test_structurally_mutated_messages_only_rejected(
    which: int, edits: list[tuple[int, Any]]
) -> None:
    """Replace elements of the decoded array tree of a valid message with random values."""
    tree = msgspec.msgpack.decode(SAMPLES[which])
    for pos, value in edits:
        node = tree
        # walk down into nested arrays along pos's digits, then replace one element
        for step in range(3):
            idx = (pos >> (2 * step)) % max(len(node), 1)
            if isinstance(node[idx], list) and node[idx] and step < 2:
                node = node[idx]
            else:
                node[idx] = value
                break
    try:
        payload = msgspec.msgpack.encode(tree)
    except (TypeError, OverflowError):  # a tree msgpack cannot hold (e.g. a 2**64 int)
        return
    admit_or_reject(SAMPLE_KEYS[which], payload)
