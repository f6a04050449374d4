"""Flight records: written in MCAP with JSON-schema channels, read back intact."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from onboard.record import (
    SCHEMAS,
    FlightRecorder,
    _jsonable,
    encode_record,
    flight_file_name,
    read_record,
)


def _write_flight(path: Path) -> None:
    with FlightRecorder(path, 3, metadata={"swarm": "alpha", "config": {"v_max": 0.5}}) as rec:
        for k in range(20):
            t = 1000.0 + 0.1 * k
            rec.state(
                t,
                flight_state="hover",
                position_enu_m=np.array([k * 0.1, 0.0, 1.0]),
                velocity_enu_m_s=[1.0, 0.0, 0.0],
                yaw_enu_rad=0.5,
                armed=True,
                landed=False,
                mode="OFFBOARD",
                battery_v=float("nan"),
            )
            rec.setpoint(t + 0.01, [k * 0.1, 0, 1], [1, 0, 0], [0, 0, 0], 0.5)
        rec.plan(
            1000.5,
            status="ok",
            traj_id=7,
            reason="period",
            plan_ms=12.5,
            iterations=30,
            evaluations=80,
            cycle_ms=14.0,
            n_peers=2,
            formation_peers=[1, 4],
            avoided_peers=[6],
            slot=3,
            formation_epoch=2,
            reforming=True,
            recovering=False,
            t0_s=1000.6,
            durations_s=np.array([1.0, 2.0]),
            coeffs=np.zeros((2, 6, 3)).ravel(),
            goal_enu_m=[5.0, 0, 1],
        )
        rec.map(
            1000.7,
            frames=21,
            occupied_cells=345,
            camera_enu_m=np.array([1.0, 0.0, 1.1]),
            nearest_obstacle_m=0.75,
            nearest_obstacle_enu_m=np.array([1.75, 0.0, 1.1]),
        )
        rec.counters(1001.0, {"traj_rx": 10, "traj_rejected_stale": 1})
        rec.transition(1000.2, "takeoff", "hover", "take-off altitude reached")
        rec.event(1000.3, "depth frames back", "warning")


def test_record_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "f.mcap"
    _write_flight(path)
    rec = read_record(path)
    assert "read_error" not in rec.metadata
    assert rec.drone_id == 3
    assert rec.metadata["swarm"] == "alpha"
    assert rec.metadata["config"] == {"v_max": 0.5}
    states = rec.messages("/state")
    assert len(states) == 20
    assert states[5]["position_enu_m"] == [0.5, 0.0, 1.0]
    assert states[0]["battery_v"] is None  # NaN is stored as null (JSON has no NaN)
    assert rec.times("/state")[1] == 1000.1
    assert len(rec.messages("/setpoint")) == 20
    assert len(rec.messages("/pose")) == 20
    plan = rec.messages("/plan")[0]
    assert plan["status"] == "ok" and plan["durations_s"] == [1.0, 2.0]
    assert len(plan["coeffs"]) == 36
    assert plan["formation_peers"] == [1, 4] and plan["avoided_peers"] == [6]
    assert (plan["slot"], plan["formation_epoch"], plan["reforming"]) == (3, 2, True)
    assert plan["recovering"] is False
    (m,) = rec.messages("/map")
    assert m["occupied_cells"] == 345 and m["nearest_obstacle_enu_m"] == [1.75, 0.0, 1.1]
    assert rec.messages("/counters")[0]["counters"]["traj_rx"] == 10
    assert rec.transitions() == [(1000.2, "takeoff", "hover", "take-off altitude reached")]
    assert rec.events() == [(1000.3, 3, "depth frames back")]


def test_channels_carry_foxglove_readable_json_schemas(tmp_path: Path) -> None:
    path = tmp_path / "f.mcap"
    _write_flight(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.id: s for s in summary.schemas.values()}
        for ch in summary.channels.values():
            schema = schemas[ch.schema_id]
            assert ch.message_encoding == "json"
            assert schema.encoding == "jsonschema"
            body = json.loads(schema.data)
            assert body["type"] == "object" and body["properties"]
            assert SCHEMAS[ch.topic][0] == schema.name
        for schema, channel, msg in reader.iter_messages():
            assert schema is not None
            props = json.loads(schema.data)["properties"]
            data = json.loads(msg.data)
            assert set(data) <= set(props), (channel.topic, set(data) - set(props))
    rec = read_record(path)
    assert rec.schemas["/pose"] == "foxglove.PoseInFrame"
    assert rec.schemas["/log"] == "foxglove.Log"


def test_producers_only_queue_until_flush(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path / "q.mcap", 0, max_queue=5)
    for k in range(8):
        rec.event(float(k), f"e{k}")
    assert rec.written == 0
    assert rec.dropped == 3
    assert rec.flush() == 5
    rec.close()
    assert [m for _, _, m in read_record(tmp_path / "q.mcap").events()] == [
        "e3",
        "e4",
        "e5",
        "e6",
        "e7",
    ]


def test_unknown_topic_is_an_error(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path / "x.mcap", 0)
    try:
        with pytest.raises(KeyError, match="/nope"):
            rec.put("/nope", 0.0, {})
    finally:
        rec.close()


def test_file_names_sort_by_time() -> None:
    a = flight_file_name(2, 1_700_000_000.0)
    b = flight_file_name(2, 1_700_000_100.0)
    assert a.startswith("drone2-") and a.endswith(".mcap") and a < b


_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4).map(np.array),
    st.floats(allow_nan=True, allow_infinity=True, width=32).map(np.float32),
    st.integers(min_value=-1000, max_value=1000).map(np.int64),
)
_payload = st.recursive(
    _leaf,
    lambda kids: st.one_of(
        st.lists(kids, max_size=4),
        st.tuples(kids, kids),
        st.dictionaries(st.one_of(st.text(max_size=6), st.integers(-5, 5)), kids, max_size=4),
    ),
    max_leaves=12,
)


@settings(max_examples=400, deadline=None)
@given(st.dictionaries(st.text(max_size=6), _payload, max_size=5))
def test_fast_encoding_is_the_json_path(payload: dict) -> None:
    """The records' encoder (msgspec) gives the value the plain json path gives: NaN and inf
    as null, numpy as lists and numbers, integer keys as strings; over 64-bit integers (which
    msgspec refuses) through the fallback."""
    fast = encode_record(payload)
    slow = json.dumps(_jsonable(payload), separators=(",", ":")).encode()
    assert json.loads(fast, parse_constant=_no_constant) == json.loads(slow)


def _no_constant(name: str) -> None:
    raise AssertionError(f"{name} in a record: not JSON")
