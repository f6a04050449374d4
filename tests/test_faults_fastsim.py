"""Fault survival in fast time (issue #12): killed and stuck drones, swarm bus faults, and the
audit that no trajectory past its validity is used in the formation term."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gcs.bench_faults import (
    ReactionLog,
    bench_faults,
    draw_trial,
    run_bench,
    summarise,
    trial_config,
)
from gcs.fastsim import PeerAudit, PlanCall, SimConfig, SimResult, run_sim
from onboard.agent import HOVER_S, PlanInputs
from onboard.comm import InMemoryBus
from onboard.comm.faults import BusFaults
from onboard.comm.messages import TrajectoryMsg
from onboard.config import load_formation, load_planner_params, load_world_spec
from onboard.planner.field import AnalyticField
from onboard.planner.planner import PeerTrajectory
from onboard.planner.trajectory import Trajectory
from onboard.world import World


def _config(formation: str, **kw: object) -> SimConfig:
    """A killed drone stops dead here (``kill_model`` 'instant', the harshest case: no vehicle
    can, PX4's failsafe carries it on, see the px4 tests below), unless a test says otherwise."""
    kw.setdefault("kill_model", "instant")
    return SimConfig(
        load_formation(formation),
        load_world_spec("forest-small"),
        seed=1,
        v_max_m_s=1.0,
        validity_s=3.0,
        peer_forget_s=10.0,
        fault_seed=1,
        **kw,  # type: ignore[arg-type]
    )


def _assert_safe(cfg: SimConfig, r: SimResult) -> None:
    """No collision at all (the hovering faulty drones included) and clearances above the
    monitor's collision thresholds."""
    assert r.collisions == 0, r.events
    assert r.min_obstacle_clearance_m >= cfg.collision_obstacle_m
    assert r.min_obstacle_clearance_by_drone_m.shape == (cfg.formation.n,)
    assert r.min_obstacle_clearance_m == float(np.min(r.min_obstacle_clearance_by_drone_m))
    assert r.min_drone_distance_m >= cfg.collision_drone_m


def test_killed_and_stuck_drones_the_others_arrive_safely() -> None:
    calls: list[PlanCall] = []
    cfg = _config("pyramid-5", killed_drones={1: 2.0}, stuck_drones={3: 3.0})
    r = run_sim(cfg, recorder=calls.append)
    _assert_safe(cfg, r)
    healthy = [0, 2, 4]
    assert not r.timed_out
    assert bool(np.all(r.arrived[healthy])), r.arrived
    assert not r.arrived[1] and not r.arrived[3]  # they stopped on the way
    # both vehicles hold where they stopped until the end
    t_kill, p_kill = r.faults["killed"]["1"]
    t_stuck, p_stuck = r.faults["stuck"]["3"]
    assert (t_kill, t_stuck) == pytest.approx((2.0, 3.0))
    late = r.tracks.t >= 3.0
    np.testing.assert_allclose(r.tracks.pos[late, 1], np.broadcast_to(p_kill, (late.sum(), 3)))
    np.testing.assert_allclose(r.tracks.pos[late, 3], np.broadcast_to(p_stuck, (late.sum(), 3)))
    # the killed drone plans (and publishes) nothing after its death, nor does the stuck one
    assert max(c.t_start_s for c in calls if c.drone_id == 1) < t_kill + cfg.plan_ahead_s
    assert max(c.t_start_s for c in calls if c.drone_id == 3) < t_stuck + cfg.plan_ahead_s
    # the stuck drone keeps publishing its hover: the others plan against it to the end
    last = [c for c in calls if c.drone_id in healthy and c.t_start_s > r.flight_time_s - 2.0]
    assert last
    for c in last:
        peer3 = [p for p in c.peers if p.drone_id == 3]
        assert len(peer3) == 1
        np.testing.assert_allclose(peer3[0].trajectory.sample(c.t_start_s), p_stuck)
    # the killed drone left the formation once its validity passed and was still avoided
    assert r.faults["expired_avoided_uses"] > 0
    assert r.faults["stale_formation_uses"] == 0
    assert r.faults["unknown_uses"] == 0


def test_a_killed_drone_is_avoided_where_it_holds() -> None:
    """bench faults seed 0 trial 49: drone 2 dies at 7.68 s and holds; its last trajectory flies
    on. Its peers hear nothing newer for peer_silence_s, replan at once and keep clear of where
    it may have stopped (before: a follower hit it 2.4 s after the kill)."""
    calls: list[PlanCall] = []
    cfg = dataclasses.replace(
        _config("hexagon-7", killed_drones={2: 7.68}),
        world=load_world_spec("forest-medium"),
        seed=49,
        time_limit_s=12.0,
    )
    r = run_sim(cfg, recorder=calls.append)
    _assert_safe(cfg, r)
    t_kill, p_kill = r.faults["killed"]["2"]
    # every healthy drone planned against it as silent within silence + one state period +
    # plan_ahead after the kill (its last state may be up to a state period older)
    bound = t_kill + cfg.peer_silence_s + 2 * cfg.state_period_s + cfg.plan_ahead_s + 1e-6
    for i in (0, 1, 3, 4, 5, 6):
        first = min(
            c.t_start_s for c in calls if c.drone_id == i and _ghost_near(c, 2, p_kill, 0.25)
        )
        assert t_kill < first <= bound, (i, first)
    assert r.faults["ghost_uses"] > 0 and r.faults["unknown_uses"] == 0


def _hover(q: PeerTrajectory) -> bool:
    tr = q.trajectory
    return tr.n_pieces == 1 and not np.any(tr.coeffs[0, 1:])


def _ghost_near(c: PlanCall, pid: int, p: list[float], within_m: float) -> bool:
    """Whether plan call ``c`` avoided a hover of peer ``pid`` within ``within_m`` of ``p``."""
    for q in c.peers:
        if q.drone_id == pid and _hover(q):
            if np.linalg.norm(q.trajectory.coeffs[0, 0] - np.asarray(p)) <= within_m:
                return True
    return False


@pytest.mark.parametrize("kind", ["killed", "stuck"])
def test_healthy_drones_keep_clear_of_a_faulty_one_and_arrive(kind: str) -> None:
    """Drone 1 of the hexagon dies (or gets stuck) 4 s into the small forest, right in front of
    a follower: without the silence reaction a healthy drone flew into the killed one (0.04 m).
    The healthy drones keep the planner's clearance from it, all arrive, and after a bounded
    time fly without it in the formation term while still avoiding it."""
    calls: list[PlanCall] = []
    fault = {f"{kind}_drones": {1: 4.0}}
    cfg = _config("hexagon-7", **fault)
    r = run_sim(cfg, recorder=calls.append)
    _assert_safe(cfg, r)
    healthy = [0, 2, 3, 4, 5, 6]
    assert not r.timed_out and bool(np.all(r.arrived[healthy])), r.arrived
    t_stop, p_stop = r.faults[kind]["1"]
    d = np.linalg.norm(r.tracks.pos[:, healthy] - r.tracks.pos[:, [1]], axis=2)
    assert float(d.min()) >= cfg.params.check_drone_m - 0.02, float(d.min())
    np.testing.assert_allclose(r.tracks.pos[r.tracks.t >= t_stop + 0.1, 1], [p_stop] * int(
        np.sum(r.tracks.t >= t_stop + 0.1)))  # fmt: skip
    # dropped from the formation term: a killed one once silent, a stuck one (re-announcing
    # its hover, heard alive) once its plan is older than validity_s; still avoided to the end
    # (a killed one: its last trajectory for peer_forget_s, where it holds for ghost_forget_s)
    drop = t_stop + (cfg.peer_silence_s + 0.3 if kind == "killed" else cfg.validity_s + 1.2)
    n_form = cfg.formation.n
    late = [c for c in calls if c.drone_id in healthy and c.t_start_s > drop]
    assert late and r.flight_time_s < t_stop + cfg.ghost_forget_s
    for c in late:
        mine = [q for q in c.peers if q.drone_id == 1]
        assert mine and all(q.slot >= n_form for q in mine), (c.drone_id, c.t_start_s)
    if kind == "killed":
        assert all(_ghost_near(c, 1, p_stop, 0.2) for c in late)
        moving = [c for c in late if any(q.drone_id == 1 and not _hover(q) for q in c.peers)]
        assert moving and max(c.t_start_s for c in moving) <= t_stop + 1.0 + cfg.peer_forget_s
    assert r.faults["stale_formation_uses"] == 0 and r.faults["unknown_uses"] == 0


def test_bus_faults_loss_delay_duplication_reordering_no_collision() -> None:
    faults = BusFaults(loss=0.2, delay_max_s=0.3, duplicate=0.2, reorder=0.1)
    cfg = _config("triangle-3", bus_faults=faults)
    r = run_sim(cfg)
    _assert_safe(cfg, r)
    assert bool(np.all(r.arrived)) and not r.timed_out
    bus = r.faults["bus"]
    # the faults did happen
    assert bus["lost"] > 0 and bus["duplicated"] > 0 and bus["held_back"] > 0
    assert r.faults["refused_older"] > 0  # late copies never replaced a newer trajectory
    assert r.faults["stale_formation_uses"] == 0
    assert r.faults["unknown_uses"] == 0
    assert r.faults["resent"] > 0  # every trajectory goes out again (RESEND_S)
    # no healthy drone taken for silent (dropped from the formation): the quiet ones are only
    # avoided where they may have stopped (a fixed 0.5 s silence: 12 replans with one silent)
    assert r.faults["agents"]["silent"] == 0


def test_default_config_has_no_faults() -> None:
    cfg = SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"))
    assert cfg.bus_faults is None and not cfg.killed_drones and not cfg.stuck_drones
    assert cfg.validity_s == float("inf")


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"killed_drones": {5: 1.0}}, "killed_drones"),
        ({"stuck_drones": {0: -1.0}}, "stuck_drones"),
        ({"killed_drones": {0: 1.0}, "stuck_drones": {0: 2.0}}, "both"),
        ({"validity_s": 0.0}, "validity_s"),
    ],
)
def test_bad_fault_fields_are_refused(kw: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SimConfig(load_formation("triangle-3"), load_world_spec("forest-small"), **kw)  # type: ignore[arg-type]


def _inputs(peers: tuple[PeerTrajectory, ...], n_form: int, n_avoided: int) -> PlanInputs:
    n = n_form + n_avoided
    mask = None
    if n_avoided:
        mask = np.zeros((n, n))
        mask[:n_form, :n_form] = 1.0 - np.eye(n_form)
    z = np.zeros(3)
    return PlanInputs(
        0, 0, 2.1, z, z, z, z, peers, AnalyticField(World.empty()), Trajectory.hover(z, 0.0),
        np.zeros((n, 3)), mask,
    )  # fmt: skip


def test_audit_counts_a_stale_trajectory_in_the_formation() -> None:
    """The instrument can fail: a formation peer from an expired message is counted."""
    audit = PeerAudit(InMemoryBus())
    tr = Trajectory.hover(np.ones(3), 0.0)
    audit.publish(TrajectoryMsg(1, 0, 1, tr, valid_until_s=1.0), 0.0)
    got = audit.receive(0, 2.0)
    assert got[1].trajectory is tr  # expired messages are still handed out (to be avoided)
    audit.check(_inputs((PeerTrajectory(1, 1, tr),), 3, 0))
    assert audit.counters["stale_formation_uses"] == 1
    audit.check(_inputs((PeerTrajectory(1, 3, tr),), 3, 1))  # avoided only: the design
    assert audit.counters["expired_avoided_uses"] == 1
    audit.check(_inputs((PeerTrajectory(1, 1, Trajectory.hover(np.ones(3), 0.0)),), 3, 0))
    assert audit.counters["unknown_uses"] == 1


def test_audit_never_goes_back_to_an_older_trajectory() -> None:
    audit = PeerAudit(InMemoryBus())
    new = TrajectoryMsg(1, 5, 1, Trajectory.hover(np.ones(3), 0.0))
    old = TrajectoryMsg(1, 4, 1, Trajectory.hover(np.zeros(3), 0.0))
    audit.publish(new, 0.0)
    assert audit.receive(0, 0.1)[1] is new
    audit.publish(old, 0.2)  # a held-back copy arrives late
    assert audit.receive(0, 0.3)[1] is new
    assert audit.counters["refused_older"] == 1


def test_draw_trial_is_seeded_and_covers_every_fault() -> None:
    a = [draw_trial(7, k, 7, (3.0, 25.0)) for k in range(60)]
    b = [draw_trial(7, k, 7, (3.0, 25.0)) for k in range(60)]
    assert [t.to_json() for t in a] == [t.to_json() for t in b]
    kinds = {k for t in a for k in t.kinds()}
    assert kinds == {"killed", "stuck", "loss", "delay", "duplicate", "reorder"}
    for t in a:
        assert t.kinds()
        assert not set(t.killed) & set(t.stuck)
        for at in (*t.killed.values(), *t.stuck.values()):
            assert 3.0 <= at <= 25.0


def test_bench_faults_command_writes_the_report(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    res = CliRunner().invoke(
        bench_faults,
        ["--trials", "1", "--jobs", "1", "--seed", "3", "--time-limit", "4", "--json", str(out)],
    )
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["n_trials"] == 1 and len(rep["trials"]) == 1
    row = rep["trials"][0]
    assert row["kinds"] and row["collisions"] == 0 and row["stale_formation_uses"] == 0
    assert row["peer_uses_audited"] > 0 and row["replans"] > 0
    assert rep["collisions"] == 0
    # the healthy drones' own minimum: never below every drone's, and the run's is the trials'
    assert row["healthy_min_obstacle_clearance_m"] >= row["min_obstacle_clearance_m"]
    assert rep["healthy_min_obstacle_clearance_m"] == row["healthy_min_obstacle_clearance_m"]
    # a trial with no healthy drone (NaN) does not hide the others' minimum, wherever it stands
    healthy_min = row["healthy_min_obstacle_clearance_m"]
    none_left = {**row, "healthy_min_obstacle_clearance_m": math.nan}
    for rows in ([row, none_left], [none_left, row]):
        assert summarise(rows)["healthy_min_obstacle_clearance_m"] == healthy_min
    assert math.isnan(summarise([none_left])["healthy_min_obstacle_clearance_m"])
    for key in ("silent_replans_no_kill", "healthy_hover_plans", "healthy_dropped_plans"):
        assert isinstance(rep[key], int)
    assert set(rep["reaction_killed"]) == {
        "hover_s",
        "hover_s_never",
        "dropped_s",
        "dropped_s_never",
    }


def test_reaction_log_times_the_reaction_and_counts_false_alarms() -> None:
    """Drone 2 is killed at 1.0 s at p: drone 0 keeps it in the formation along its moving
    trajectory at 1.3 s and avoids it as a hover near p, out of the formation, at 1.6 s; a plan
    that avoids healthy drone 1 at an added hover, out of the formation, is a false alarm."""
    log = ReactionLog(3, 0.1, [2])
    p = np.array([1.0, 2.0, 1.0])
    z = np.zeros(3)
    moving = Trajectory(0.0, np.array([[p, [1.0, 0, 0], z, z, z, z]]), np.array([5.0]))
    one = Trajectory.hover(np.ones(3), 0.0, 30.0)

    def call(t: float, *peers: PeerTrajectory) -> PlanCall:
        return PlanCall(0, 0, t + 0.1, z, z, z, z, peers, World.empty(), None)

    log(call(1.3, PeerTrajectory(1, 1, one), PeerTrajectory(2, 2, moving)))
    log(call(1.6, PeerTrajectory(1, 1, one), PeerTrajectory(2, 3, moving),
             PeerTrajectory(2, 4, Trajectory.hover(p + 0.1, 1.6, HOVER_S))))  # fmt: skip
    assert log.healthy_hover_plans == 0 and log.healthy_dropped_plans == 0
    log(call(2.0, PeerTrajectory(1, 3, one), PeerTrajectory(1, 4, Trajectory.hover(
        np.ones(3), 2.0, HOVER_S))))  # fmt: skip
    assert log.healthy_hover_plans == 1 and log.healthy_dropped_plans == 1
    r = log.reactions({2: (1.0, p.tolist())})
    assert r == {"2": {"0": {"hover_s": pytest.approx(0.6), "dropped_s": pytest.approx(0.6)}}}
    # never seen where it stopped: None
    assert log.reactions({2: (1.0, (p + 5.0).tolist())})["2"]["0"]["hover_s"] is None


def test_run_bench_refuses_bad_arguments() -> None:
    with pytest.raises(ValueError, match="trials"):
        run_bench(0, 1, 0)
    with pytest.raises(ValueError, match="jobs"):
        run_bench(1, 0, 0)


def test_a_trial_flies_the_planner_and_the_silence_it_is_given() -> None:
    trial = draw_trial(5, 0, 7, (3.0, 25.0))
    default = trial_config(trial, 1.0, 60.0)
    assert default.params.lead_turned is False and default.peer_silence_s == 0.5
    p = load_planner_params(lead_turned=True, v_max_m_s=0.5)
    cfg = trial_config(trial, 1.0, 60.0, planner=p, peer_silence_s=0.3)
    # the trial's speed limit wins over the parameters' own
    assert cfg.params.lead_turned is True and cfg.params.v_max_m_s == 1.0
    assert cfg.peer_silence_s == 0.3
    assert dataclasses.replace(cfg.params, lead_turned=False) == default.params


def test_bench_faults_command_takes_planner_settings(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    args = ["--trials", "1", "--jobs", "1", "--seed", "3", "--time-limit", "2", "-q"]
    res = CliRunner().invoke(
        bench_faults,
        [*args, "--set", "lead_turned=true", "--peer-silence", "0.3", "--json", str(out)],
    )
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    # flown, not only written down
    row = rep["trials"][0]
    assert row["planner_changes"] == {"lead_turned": True} and row["peer_silence_s"] == 0.3
    settings = rep["settings"]
    assert settings == {
        "planner_file": None,
        "set": ["lead_turned=true"],
        "v_max_m_s": 1.0,
        "peer_silence_s": 0.3,
    }
    res = CliRunner().invoke(bench_faults, [*args, "--set", "v_max_m_s=0.5", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["settings"]["v_max_m_s"] == 0.5 and rep["trials"][0]["v_max_m_s"] == 0.5
    assert rep["trials"][0]["planner_changes"] == {} and rep["trials"][0]["peer_silence_s"] == 0.5
    for bad, what in (
        (["--set", "no_such_key=1"], "no_such_key"),
        (["--set", "v_max_m_s=0.5", "--v-max", "1.0"], "disagree"),
        (["--peer-silence", "0"], "--peer-silence"),
    ):
        res = CliRunner().invoke(bench_faults, [*args, *bad])
        assert res.exit_code != 0 and what in res.output, (bad, res.output)


def _children(pid: int) -> set[int]:
    out = set()
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    rest = f.read().rsplit(") ", 1)[1].split()
            except OSError:
                continue
            if int(rest[1]) == pid and rest[0] != "Z":
                out.add(int(d))
    return out


def test_a_terminated_bench_leaves_no_worker_flying() -> None:
    """SIGTERM to ``bench faults`` on two workers: it ends and so do its pool's workers (they
    went on flying the trials queued to them before)."""
    cmd = "from gcs.cli import main; main()"
    args = ["bench", "faults", "--trials", "8", "--jobs", "2", "--seed", "3", "-q"]
    proc = subprocess.Popen([sys.executable, "-c", cmd, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    kids: set[int] = set()
    try:
        end = time.monotonic() + 60.0
        while len(kids) < 3 and time.monotonic() < end:  # two workers and the resource tracker
            assert proc.poll() is None, proc.communicate()
            kids |= _children(proc.pid)
            time.sleep(0.2)
        assert len(kids) >= 3, kids
        time.sleep(2.0)  # the workers at their trials
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30.0)  # not its output: orphaned workers would hold its pipes open
        # at once: a worker left alone would first finish its trial (several seconds)
        end = time.monotonic() + 3.0
        while {k for k in kids if os.path.exists(f"/proc/{k}")} and time.monotonic() < end:
            time.sleep(0.1)
        assert not {k for k in kids if os.path.exists(f"/proc/{k}")}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        for k in kids:
            if os.path.exists(f"/proc/{k}"):
                os.kill(k, signal.SIGKILL)
