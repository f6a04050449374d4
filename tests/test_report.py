"""The flight report: records written with onboard/record.py, read back into plots and a summary
whose figures are checked against what the synthetic flight was built to contain."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gcs.fastsim import REFUSAL_KEYS
from gcs.formations import load_template, place
from gcs.report import (
    PLOTS,
    ReportError,
    analyse,
    find_records,
    load_flights,
    mission_world,
    report,
    write_report,
)
from onboard.planner.planner import APPROACH
from onboard.record import FlightRecorder

T0 = 1.75e9
IDS = [0, 1, 2]
SPEED = 0.5  # m/s along x
CRUISE_Z = 1.0
TRIANGLE = load_template("triangle-3").points
SETPOINT_OFFSET = {
    0: np.array([0.05, 0.0, 0.0]),
    1: np.array([0.0, 0.1, 0.0]),
    2: np.array([0.0, 0.0, -0.15]),
}
"""Each drone's commanded position is its true one plus this: its tracking error."""


def _true_positions(t: float) -> dict[int, np.ndarray]:
    """The synthetic flight: a triangle-3 at 1 m climbs for 2 s from t=1, crosses x from -3 at
    0.5 m/s from t=3 to t=33, and lands from t=33 to t=35; drone 2 swerves 1.7 m towards
    drone 1 around t = 20 (a near miss inside 0.4 m)."""
    tpl = TRIANGLE
    z = CRUISE_Z * float(np.clip(t - 1.0, 0.0, 2.0) / 2.0)
    if t > 33.0:
        z = CRUISE_Z * float(np.clip(35.0 - t, 0.0, 2.0) / 2.0)
    x = -3.0 + SPEED * float(np.clip(t - 3.0, 0.0, 30.0))
    p = place(tpl, (x, 0.0, z), 1.0, 0.0)
    out = {d: p[d].copy() for d in IDS}
    bump = max(0.0, 1.0 - abs(t - 20.0))  # 0..1..0 over t in [19, 21]
    out[2] += bump * (p[1] - p[2]) * 0.9  # to within 10 % of the 2 m side: 0.2 m
    return out


def _state_of(t: float) -> str:
    if t < 1.0:
        return "idle"
    if t < 3.0:
        return "takeoff"
    if t < 33.0:
        return "formation-flight"
    if t < 35.0:
        return "landing"
    return "landed"


def write_flight(d: Path) -> dict[str, object]:
    """Three drones' records (10 Hz states; 50 Hz setpoints from take-off to landed, each
    ``SETPOINT_OFFSET`` from the true position, with one 45 ms hiccup; 1 Hz plans) and the
    mission file; returns the mission."""
    tpl = load_template("triangle-3").points
    placed = place(tpl, (-3.0, 0.0, CRUISE_Z), 1.0, 0.0)
    mission = {
        "world": "forest-small",
        "seed": 3,
        "count": 3,
        "spacing_m": 1.5,
        "goal_m": [12.0, 0.0, CRUISE_Z],
        "assignments": [
            {
                "name": "triangle-3",
                "epoch": 5,
                "effective_s": T0 + 2.0,
                "points_m": (placed - placed.mean(axis=0)).tolist(),
                "slots": {"0": 0, "1": 1, "2": 2},
            }
        ],
        "sitl": {"collisions": 0},
    }
    (d / "mission.json").write_text(json.dumps(mission))
    for i in IDS:
        with FlightRecorder(d / f"drone{i}.mcap", i, {"swarm": "t"}) as rec:
            prev = None
            for k in range(0, 361):
                t = k * 0.1
                p = _true_positions(t)[i]
                st = _state_of(t)
                if st != prev:
                    rec.transition(T0 + t, prev or "idle", st, "test")
                    prev = st
                rec.state(T0 + t, flight_state=st, position_enu_m=p, velocity_enu_m_s=[SPEED, 0, 0])
            ts = T0 + 1.0 + np.arange(0, 34.0, 0.02)
            ts[300:] += 0.025  # one period of 45 ms
            for t in ts:
                want = _true_positions(float(t) - T0)[i] + SETPOINT_OFFSET[i]
                rec.setpoint(float(t), want, [0, 0, 0], [0, 0, 0], 0.0)
            for j in range(30):
                # drone 2's service records no CPU time (an older one): NaN, left out
                cpu = {"plan_cpu_ms": 2.0 + i + 0.1 * j} if i < 2 else {}
                status, reason = REFUSED.get((i, j), ("ok", ""))
                rec.plan(T0 + 3.0 + j, status=status, plan_ms=40.0 + i + j, traj_id=j,
                         goal_enu_m=[12.0, 0.0, 1.0], reason=reason, **cpu)  # fmt: skip
            rec.event(T0 + 20.0, "near miss", level="warning")
            # the safety monitors' counters: the last snapshot counts (drone 2's service is
            # older: no shallow replans)
            mon = {"service.monitor_brakes": i, "service.monitor_replans": 10 + i,
                   "service.depth_holds": 2 * i, "service.frames_missed": 5,
                   "service.stream_guard_stops": int(i == 2)}  # fmt: skip
            rec.counters(T0 + 10.0, {k: 0 for k in mon})
            if i < 2:
                mon["service.monitor_shallow_replans"] = 3
                mon["service.map_lag_holds"] = i
                mon["service.map_lag_rides"] = 4
            rec.counters(T0 + 30.0, mon)
    return mission


REFUSED = {
    (1, 5): (
        "ok-no-formation",
        "formation: obstacle clearance 0.20 m at t=1.00 s; "
        "a* retry: unobserved space 0.25 m away at t=0.50 s (from 0.45 m)",
    ),
    (1, 6): (
        "ok-no-formation",
        "formation: drone 2 at 0.30 m at t=2.00 s; a* retry without formation: enters "
        "unobserved space at t=0.40 s; previous: obstacle clearance 0.10 m at t=0.30 s; "
        + APPROACH,
    ),
}
"""Drone 1's plans (drone, plan) with refused attempts, as the planner writes their messages
(the kept previous plan's own refusal is no attempt)."""


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, object]]:
    """The synthetic flight, written once for the module (tests work on copies)."""
    d = tmp_path_factory.mktemp("recorded")
    return d, write_flight(d)


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_report_figures(tmp_path: Path, recorded: tuple[Path, dict[str, object]]) -> None:
    flight = _copy(recorded[0], tmp_path / "flight")
    mission = recorded[1]
    s, out = write_report([flight])
    assert out == flight / "report"
    for name in PLOTS:  # every plot is a PNG with something in it
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name
    assert json.loads((out / "summary.json").read_text())["n_drones"] == 3
    assert "flight of 3 drone(s) in forest-small" in (out / "summary.txt").read_text()
    assert s["world"] == "forest-small" and s["seed"] == 3 and s["n_drones"] == 3
    # setpoints: 1700 per drone at 20 ms, one 45 ms period each
    sp = s["setpoint_period_ms"]
    assert sp["count"] == 3 * 1699 and sp["median"] == pytest.approx(20.0, abs=1e-3)
    assert sp["max"] == pytest.approx(45.0, abs=1e-3)
    assert all(d["setpoint_pauses"] == 0 for d in s["drones"])
    # plans: 30 per drone, 40 + id + j ms
    assert s["plan_ms"]["count"] == 90 and s["plan_ms"]["max"] == pytest.approx(71.0)
    assert s["plan_cpu_ms"]["count"] == 60 and s["plan_cpu_ms"]["max"] == pytest.approx(5.9)
    assert s["drones"][2]["plan_cpu_ms"]["count"] == 0
    assert "the planning thread's CPU: median" in (out / "summary.txt").read_text()
    assert s["drones"][2]["plan_statuses"] == {"ok": 30}
    assert s["stream_guard_stops"] == {"stream_guard_stops": 1, "stream_gap_stops": 0}
    assert s["kernels_after_ready"] == 0
    # the refused attempts by why, from the plans' messages: drone 1's two plans
    want = {**dict.fromkeys(REFUSAL_KEYS, 0), "attempts": 4, "obstacle": 1, "drone": 1}
    want.update(unobserved=2, unobserved_near=1, approach=1)
    assert s["plan_refusals"] == s["drones"][1]["plan_refusals"] == want
    assert s["drones"][0]["plan_refusals"] == dict.fromkeys(REFUSAL_KEYS, 0)
    assert s["drones"][1]["plan_statuses"] == {"ok": 28, "ok-no-formation": 2}
    assert (
        "refused plan attempts: 4 (1 for an obstacle, 1 for a peer, 2 for unobserved space, "
        "1 of them for its neighbourhood" in (out / "summary.txt").read_text()
    )
    assert s["monitor"] == {"brakes": 0 + 1 + 2, "replans": 33, "shallow_replans": 6}
    assert s["depth_holds"] == {
        "holds": 0 + 2 + 4,
        "map_lag_holds": 1,
        "map_lag_rides": 8,
        "frames_missed": 15,
    }
    # flight time: take-off transition at t=1 to landed at t=35
    assert s["flight_time_s"] == pytest.approx(34.0, abs=1e-6)
    # the near miss: drone 2 comes to 0.2 m of drone 1 (one drone-collision start)
    assert s["min_drone_distance_m"] == pytest.approx(0.2, abs=0.02)
    assert s["collisions_from_records"]["drone"] == 1
    assert s["collisions_reported_by_mock"] == 0
    # formation error: zero while the triangle is intact, > 0 in the swerve
    a = analyse(load_flights(find_records([flight])), mission_world(mission), mission)
    rel = a.t - T0
    intact = (rel > 4.0) & (rel < 15.0)
    assert np.nanmax(a.e_sim[intact]) < 1e-9 and np.nanmax(a.e_dist[intact]) < 1e-6
    assert np.nanmax(a.e_dist) > 0.5 and s["e_dist_m"]["max"] == pytest.approx(np.nanmax(a.e_dist))
    assert np.isnan(a.e_dist[rel < 1.5]).all()  # on the ground: not flying the formation
    # in the cluttered span (x 0..10 of forest-small: t = 9..29 s) the swerve is included
    cl = s["cluttered"]
    assert cl["x_span_m"] == [0.0, 10.0] and cl["e_dist_m"]["max"] == s["e_dist_m"]["max"]
    assert cl["e_dist_m"]["count"] == pytest.approx(201, abs=2)
    # obstacle clearance: the minimum over airborne samples of the mock's world
    w = mission_world(mission)
    assert w is not None and w.cylinders.shape[0] == 8
    air = (rel >= 1.0) & (rel < 35.0)
    from onboard.world import World

    solid = World(w.cylinders, w.rings, w.boxes, ground_z=None)
    pts = np.array([list(_true_positions(float(t)).values()) for t in rel[air]])
    direct = float(solid.distance(pts.reshape(-1, 3))[0].min())
    assert s["min_obstacle_clearance_m"] == pytest.approx(direct, abs=1e-6)
    assert (s["collisions_from_records"]["obstacle"] > 0) == (direct < 0.2)
    # per drone, the closest approach on the grid, the commanded position's clearance then and
    # the tracking error (the offset); the worst of them is the flight's
    for i in IDS:
        d = s["drones"][i]
        own = np.array([_true_positions(float(t))[i] for t in rel[air]])
        dist = solid.distance(own)[0]
        k = int(np.argmin(dist))
        c = d["closest_obstacle"]
        assert c["clearance_m"] == pytest.approx(dist[k], abs=1e-6)
        assert c["t_s"] == pytest.approx(T0 + rel[air][k], abs=1e-6)
        sp_at = own[k] + SETPOINT_OFFSET[i]
        assert c["setpoint_clearance_m"] == pytest.approx(
            float(solid.distance(sp_at.reshape(1, 3))[0][0]), abs=2e-3
        )
        off = float(np.linalg.norm(SETPOINT_OFFSET[i]))
        assert c["tracking_error_m"] == pytest.approx(off, abs=2e-3)
        # in formation flight (t = 3..33 s, 10 Hz): the offset at every sample
        te = d["tracking_error_m"]
        assert te["count"] == pytest.approx(300, abs=2)
        assert te["median"] == pytest.approx(off, abs=1e-3) and te["max"] == pytest.approx(
            off, abs=5e-3
        )
    worst = min(IDS, key=lambda i: s["drones"][i]["closest_obstacle"]["clearance_m"])
    assert s["closest_obstacle"]["id"] == worst
    assert s["closest_obstacle"]["clearance_m"] == pytest.approx(direct, abs=1e-6)
    assert s["tracking_error_m"]["max"] == pytest.approx(0.15, abs=5e-3)
    text = (out / "summary.txt").read_text()
    assert "tracking (position - setpoint): median 0.100 m" in text
    assert f"closest to an obstacle: drone {worst}," in text
    # arrival: the goal is 12 m east; the swarm stops at x = 12 - offset: every drone arrived
    assert s["arrived"] and all(d["arrived"] for d in s["drones"])


def test_report_cli_and_errors(tmp_path: Path, recorded: tuple[Path, dict[str, object]]) -> None:
    flight = _copy(recorded[0], tmp_path / "f")
    out = tmp_path / "out"
    r = CliRunner().invoke(report, [str(flight / "drone0.mcap"), str(flight / "drone1.mcap"),
                                    "--out", str(out), "--json", "--no-plots"])  # fmt: skip
    assert r.exit_code == 0, r.output
    s = json.loads(r.output)
    assert s["n_drones"] == 2 and (out / "summary.json").is_file() and s["plots"] == []
    r = CliRunner().invoke(report, [str(flight), "--out", str(out), "--no-plots"])
    assert r.exit_code == 0 and "flight of 3 drone(s) in forest-small (seed 3)" in r.output
    r = CliRunner().invoke(report, [str(tmp_path / "nothing")])
    assert r.exit_code == 1 and "no such file" in r.output
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ReportError, match="no flight record"):
        write_report([empty])
    (flight / "mission.json").write_text("{not json")
    with pytest.raises(ReportError, match="mission file"):
        write_report([flight])


def test_report_of_a_record_cut_short(tmp_path: Path) -> None:
    """A record cut by a crash (no summary section) still reports the whole chunks it holds."""
    flight = tmp_path / "f"
    flight.mkdir()
    path = flight / "drone-cut.mcap"
    with FlightRecorder(path, 4) as rec:
        for k in range(3000):  # several 256 kB chunks: states and setpoints interleaved
            t = T0 + k * 0.02
            if k % 5 == 0:
                rec.state(t, flight_state="formation-flight", position_enu_m=[k * 0.01, 0, 1],
                          velocity_enu_m_s=[0.5, 0, 0], noise=list(range(k % 7, 40)))  # fmt: skip
            rec.setpoint(t, [k * 0.01, 0.1, 1.0], [0.5, 0, 0], [0, 0, 0], 1.0 / (k + 1))
            if k % 200 == 0:
                rec.flush()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    s, _ = write_report([flight], world="forest-small", seed=3, plots=False)
    (d,) = s["drones"]
    assert d["id"] == 4 and d["read_error"]
    assert 0 < d["states"] < 600 and 0 < d["setpoints"] < 3000
    assert d["setpoint_period_ms"]["max"] == pytest.approx(20.0, abs=1e-3)
    assert s["min_obstacle_clearance_m"] is not None and s["e_dist_m"]["count"] == 0


def test_setpoint_at_skips_pauses_and_the_ends() -> None:
    """The commanded position is interpolated inside the stream only: NaN before its first and
    after its last setpoint and inside a pause longer than STREAM_GAP_S."""
    from gcs.report import STREAM_GAP_S, DroneFlight

    ts = np.array([0.0, 0.02, 0.04, 0.04 + STREAM_GAP_S + 0.01, 0.06 + STREAM_GAP_S + 0.01])
    pos = np.column_stack([ts, np.zeros(5), np.ones(5)])
    f = DroneFlight(
        drone_id=0, path=Path("x"), t=ts, pos=pos, vel=np.zeros((5, 3)),
        flight_state=("formation-flight",) * 5, setpoint_t=ts, plan_t=np.zeros(0),
        plan_ms=np.zeros(0), plan_status=(), plan_goal=np.zeros((0, 3)), transitions=(),
        events=(), counters={}, setpoint_pos=pos + [0.0, 0.3, 0.0],
    )  # fmt: skip
    got = f.setpoint_at(np.array([-0.01, 0.03, 0.3, ts[-1] - 0.01, ts[-1] + 0.01]))
    assert np.isnan(got[[0, 2, 4]]).all()
    assert got[1] == pytest.approx([0.03, 0.3, 1.0]) and np.isfinite(got[3]).all()
    assert f.tracking_error_m() == pytest.approx([0.3] * 5)
