"""``swarm-gcs demo``: the real stack (mock fleet, one flight service per drone, the ground
station) through a small forest, headless; and no process left behind after Ctrl-C."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.demo import (
    DEMO_LEAD_S,
    Demo,
    DemoConfig,
    DemoError,
    parse_change,
    result_text,
    run_demo,
)
from gcs.report import DroneFlight
from gcs.station import StationConfig
from onboard.comm.latency import LatencyFigures, LatencyRecorder
from onboard.record import FlightRecorder, read_record

DEMO = "import sys; from gcs.demo import demo; sys.argv[0] = 'swarm-gcs demo'; demo()"


def sigint_default() -> None:
    """In the child before exec: SIGINT back to its default, so that Python installs its Ctrl-C
    handler (a shell starting a job in the background, as CI runners may, leaves SIGINT
    ignored, and an ignored SIGINT stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is not running (its parent, the demo, has not reaped it)
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except OSError:
        return False


def _group_members(pgid: int) -> list[str]:
    """The processes of process group ``pgid`` that still run (zombies not: their parent has
    not reaped them yet), as "pid state cmdline" for an assertion's message."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return []
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().split(") ", 1)[1].split()
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError):
            continue  # ended meanwhile
        # after the comm: state, ppid, pgrp
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(f"{d} {fields[0]} {cmd[:200]}")
    return out


def _group_alive(pgid: int) -> bool:
    return bool(_group_members(pgid))


def _wait_for(cond: Any, timeout_s: float, what: str, proc: subprocess.Popen[str]) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"the demo ended ({proc.returncode}) before {what}")
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def test_parse_change_and_config_errors(tmp_path: Path) -> None:
    assert parse_change("arrow-7@20") == ("arrow-7", 20.0)
    assert parse_change("my@shape.yaml@2.5") == ("my@shape.yaml", 2.5)
    assert parse_change(None) is None
    for bad in ("arrow-7", "@3", "arrow-7@x", "arrow-7@-1"):
        with pytest.raises(ValueError, match="NAME@SECONDS"):
            parse_change(bad)
    with pytest.raises(DemoError, match="has 7 points, not 3"):
        Demo(DemoConfig(drones=3, formation="hexagon-7", out_dir=tmp_path / "a"))
    with pytest.raises(DemoError, match="no file named 'nope'"):
        Demo(DemoConfig(drones=3, formation="triangle-3", formation_change=("nope", 1.0),
                        out_dir=tmp_path / "b"))  # fmt: skip
    # a change to a shape of another size is refused before anything starts
    with pytest.raises(DemoError, match="rectangle-7 has 7 points, not 3"):
        Demo(DemoConfig(drones=3, formation="triangle-3", formation_change=("rectangle-7", 8.0),
                        out_dir=tmp_path / "c"))  # fmt: skip
    assert not (tmp_path / "c").exists()
    for lead in (-0.1, math.nan, 11.0):  # the command-to-switch lead
        with pytest.raises(DemoError, match="lead_s must lie in"):
            Demo(DemoConfig(drones=3, formation="triangle-3", lead_s=lead, out_dir=tmp_path / "d"))


def test_depth_rate_by_fleet_size_and_the_services_depth_timeout(tmp_path: Path) -> None:
    """A 2-core machine maps 3 x 10 frames/s but not 7 x 10 (nor 7 x 5): 3 above 4 drones;
    the services' depth-lost timeout follows the rate (4 frame periods, at least 0.5 s)."""
    for n, formation, rate, timeout in ((3, "triangle-3", 10.0, 0.5), (7, "hexagon-7", 3.0, 4 / 3)):
        d = Demo(DemoConfig(drones=n, formation=formation, out_dir=tmp_path / formation))
        d.world_file = d._world_file()  # the services' local origins come from its starts
        assert d.depth_rate_hz == rate
        onboard = json.loads(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
        assert onboard["depth"]["rate_hz"] == rate
        assert onboard["reactions"]["depth_lost"]["timeout_s"] == pytest.approx(timeout)
    d = Demo(
        DemoConfig(drones=3, formation="triangle-3", depth_rate_hz=2.0, out_dir=tmp_path / "c")
    )
    d.world_file = d._world_file()
    onboard = json.loads(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
    assert onboard["reactions"]["depth_lost"]["timeout_s"] == pytest.approx(2.0)
    with pytest.raises(DemoError, match="depth_rate_hz"):
        Demo(DemoConfig(drones=3, formation="triangle-3", depth_rate_hz=0.5, out_dir=tmp_path))


def test_the_altitude_band_by_fleet_size(tmp_path: Path) -> None:
    """Above 4 drones the planner's band narrows around the cruise altitude (0.6 below, 0.8
    above: 0.4-1.8 m at the forests' 1 m), which the services' map windows and ESDFs follow
    (each service's own config check); (0, 0) keeps the onboard config's band; a band that is
    not two positive distances is refused before anything starts."""
    from onboard.service.config import load_onboard_config

    cases = (
        (3, "triangle-3", None, None),
        (7, "hexagon-7", None, [0.4, 1.8]),
        (7, "hexagon-7", (0.0, 0.0), None),
        (3, "triangle-3", (0.5, 1.0), [0.5, 2.0]),
    )
    for k, (n, formation, band, z_limits) in enumerate(cases):
        d = Demo(DemoConfig(drones=n, formation=formation, altitude_band_m=band,
                            out_dir=tmp_path / str(k)))  # fmt: skip
        d.world_file = d._world_file()
        onboard = json.loads(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
        assert onboard["planner"].get("z_limits_m") == z_limits
        if z_limits is not None:
            conf = tmp_path / f"{k}.yaml"
            conf.write_text(json.dumps(onboard))
            svc = load_onboard_config(conf, drone_id=0)
            assert svc.planner.z_limits_m == tuple(z_limits)
            lo, hi = svc.map_params.esdf_z_m
            assert lo <= z_limits[0] and hi >= z_limits[1] and hi - lo < 2.5
    for bad in ((-0.1, 0.8), (0.6, float("nan")), (0.0, 1.0)):
        with pytest.raises(DemoError, match="altitude band"):
            Demo(DemoConfig(drones=7, altitude_band_m=bad, out_dir=tmp_path / "bad"))


def test_the_services_fly_the_drones_own_configuration(tmp_path: Path) -> None:
    """The demo's service file is config/onboard.yaml with the demo's settings on top: a file
    given to the service replaces that one, and the services once flew another planner than
    the drone's (``check_obstacle_horizon_s`` 0 instead of 4) and than the fast-time twin."""
    import dataclasses

    from onboard.service.config import load_onboard_config

    d = Demo(DemoConfig(drones=7, out_dir=tmp_path / "d"))
    d.world_file = d._world_file()
    conf = tmp_path / "onboard.yaml"
    conf.write_text(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
    demo, drone = load_onboard_config(conf, drone_id=0), load_onboard_config(None, drone_id=0)
    assert drone.planner.check_obstacle_horizon_s > 0.0  # what the services lacked
    set_by_demo = {"planner": {"z_limits_m"}, "mapping": {"thread_nice"},
                   "depth": {"rate_hz", "sim_prefix", "sim_connect"}, "reactions": {"depth_lost"},
                   "record": {"directory"}, "autopilot": {"url", "local_origins_enu_m"},
                   "drone": {"swarm"}}  # fmt: skip
    for section in ("planner", "planning", "mapping", "depth", "bus", "reactions", "zenoh",
                    "record", "autopilot", "drone", "geofence", "flight", "watchdog"):  # fmt: skip
        got, want = (
            dataclasses.asdict(getattr(demo, section)),
            dataclasses.asdict(getattr(drone, section)),
        )
        differ = {k for k in want if got[k] != want[k]}
        assert differ <= set_by_demo.get(section, set()), (section, differ)


def test_the_mapping_thread_yields_above_4_drones(tmp_path: Path) -> None:
    """Above 4 drones (7 services on this machine's 2 cores) every service's mapping thread
    runs at ``MAPPING_NICE``, which the service's config accepts and its depth thread applies;
    up to 4 drones it stays at the services' default; an explicit value wins; out of range is
    refused before anything starts."""
    from gcs.demo import MAPPING_NICE
    from onboard.service.config import load_onboard_config

    cases = ((3, "triangle-3", None, 0), (7, "hexagon-7", None, MAPPING_NICE),
             (7, "hexagon-7", 0, 0), (3, "triangle-3", 5, 5))  # fmt: skip
    for k, (n, formation, nice, want) in enumerate(cases):
        d = Demo(DemoConfig(drones=n, formation=formation, mapping_nice=nice,
                            out_dir=tmp_path / str(k)))  # fmt: skip
        d.world_file = d._world_file()
        onboard = json.loads(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
        assert onboard["mapping"]["thread_nice"] == want
        conf = tmp_path / f"{k}.yaml"
        conf.write_text(json.dumps(onboard))
        assert load_onboard_config(conf, drone_id=0).mapping.thread_nice == want
    for bad in (-1, 20):
        with pytest.raises(DemoError, match="mapping_nice"):
            Demo(DemoConfig(drones=7, mapping_nice=bad, out_dir=tmp_path / "bad"))


def test_peer_latency_from_the_services_records(tmp_path: Path) -> None:
    """The target's figure (peer trajectory, publish -> the planner's inbox) as the demo reads
    it after a flight: each service's cumulative histogram in the 1 Hz ``/counters`` of its
    record, cut to take-off .. landing command and merged over the services, against numpy on
    the samples of that window; the printed result says which figure is the target's."""
    rng = np.random.default_rng(7)
    demo = Demo(DemoConfig(drones=3, formation="triangle-3", out_dir=tmp_path / "f"))
    t_off, t_land = 1000.0, 1020.0
    demo.t_takeoff, demo.t_land_cmd = t_off, t_land
    kept: list[float] = []
    for drone in range(3):
        lat = LatencyRecorder()
        with FlightRecorder(demo.out / f"drone{drone}-x.mcap", drone) as rec:
            for t in np.arange(t_off + 0.5, t_land + 3.0, 1.0):  # take-off to after landing
                for s in rng.lognormal(np.log(3e-3), 0.7, 6):
                    lat.add(float(s))
                    if t <= t_land + 0.5:  # up to the first snapshot at/after landing
                        kept.append(float(s) * 1e3)
                c = {f"bus.{k}": v for k, v in lat.snapshot().to_counters().items()}
                rec.counters(float(t), {"bus.rx.traj": lat.count, **c})
                rec.flush()
    got = demo.peer_latency()
    want = np.asarray(kept)
    assert got["count"] == want.size and got["per_drone"] == {"0": 126, "1": 126, "2": 126}
    for q, key in ((50, "median"), (90, "p90"), (99, "p99")):
        assert got[key] == pytest.approx(np.percentile(want, q), rel=0.017, abs=1e-3)
    # the maximum is exact (nothing before take-off), the extremes of the truncated samples
    assert got["max"] == pytest.approx(want.max(), abs=1e-3) and got["max_exact"]
    assert got["meets_target"] == bool(got["median"] < 5.0 and got["p99"] < 20.0)
    assert "planner's inbox" in got["definition"]
    text = result_text(
        {
            "success": True, "arrived": True, "collisions": 0, "e_dist_m": 0.1, "e_sim": 0.01,
            "min_obstacle_clearance_m": 0.3, "min_drone_distance_m": 1.0, "flight_time_s": 40.0,
            "crossing_time_s": 30.0, "setpoint_period_ms": {}, "peer_latency_ms": got,
            "bus_latency_ms": demo.bus_latency(), "security": {}, "flight_dir": "x",
        }
    )  # fmt: skip
    assert f"the target's definition: publish -> each planner's inbox, {want.size} " in text
    assert "ground station latency (drone trajectory -> ground station inbox, not the " in text
    # the flight report's figure: each record's last snapshot (the whole record)
    flight = DroneFlight.from_record(demo.records()[0])
    assert flight.peer_latency() == LatencyFigures.from_counters(
        {k[4:]: v for k, v in flight.counters.items() if k.startswith("bus.")}
    )
    assert flight.peer_latency().count == 23 * 6  # type: ignore[union-attr]
    # no take-off: no figure
    idle = Demo(DemoConfig(drones=3, formation="triangle-3", out_dir=tmp_path / "g"))
    assert idle.peer_latency()["count"] == 0 and idle.peer_latency()["meets_target"] is None


def _force_stop(info: dict[str, Any]) -> None:
    """SIGKILL what the demo had started (its process group and every pid it recorded)."""
    pgid = info.get("pgid")
    if pgid and int(pgid) != os.getpgrp():  # the demo's own group, never the test's
        try:
            os.killpg(int(pgid), signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass  # already gone
    for pid in info.get("pids", {}).values():
        try:
            os.kill(int(pid), signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass  # already gone


@pytest.mark.timeout(330)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_no_process_left_after_an_interrupt(tmp_path: Path, signum: int) -> None:
    """Ctrl-C and SIGTERM: the demo stops its processes and exits 130. SIGKILL (no cleanup
    possible in the demo): its children get SIGTERM from the kernel and end too."""
    out = tmp_path / "flight"
    args = ["--drones", "3", "--formation", "triangle-3", "--world", "forest-small",
            "--out", str(out), "-q"]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", DEMO, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=sigint_default)  # fmt: skip
    info: dict[str, Any] = {}
    try:
        pfile = out / "logs" / "processes.json"

        def all_started() -> bool:
            if not pfile.is_file():
                return False
            try:
                info.update(json.loads(pfile.read_text()))
            except ValueError:  # being written
                return False
            return len(info.get("pids", {})) == 4  # the mock and three services

        _wait_for(all_started, 120.0, "every process to start", proc)
        pids = list(info["pids"].values())
        assert all(_alive(p) for p in pids)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=150.0)
        if signum == signal.SIGKILL:
            assert proc.returncode == -signal.SIGKILL
        else:
            assert proc.returncode == 130, err
            assert "interrupted: every process stopped" in err
    except BaseException:
        _force_stop(info)  # the test failed: leave nothing behind (only then, or it could not fail)
        raise
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    # orphans take a moment to stop after their SIGTERM, and so may a process of the group
    # that is not one of the four (one was seen alive once, right after them; CI, 2026-11-30)
    # (the mock once stayed for good after a SIGKILL, its handler deadlocked: a failure here
    # names who is left, and stops it, or it would outlive the test)
    pgid = int(info["pgid"])
    group = signum != signal.SIGKILL
    end = time.monotonic() + 30.0
    while ([p for p in pids if _alive(p)] or (group and _group_alive(pgid))) and (
        time.monotonic() < end
    ):
        time.sleep(0.1)
    try:
        assert not {n: p for n, p in info["pids"].items() if _alive(p)}
        if group:
            left = _group_members(pgid)
            assert not left, left
    except BaseException:
        _force_stop(info)
        raise


@pytest.mark.slow
@pytest.mark.fleet
@pytest.mark.timeout(600)
def test_demo_flies_three_drones_through_a_small_forest(tmp_path: Path) -> None:
    """The whole stack, headless, in-process ground station: take off, form a triangle, cross
    forest-small, change to a line in flight, land; no collision; report written; nothing left
    running. It flies ``--secure`` (the suite's one demo flight; the plain demo's configuration
    is checked in tests/test_demo_secure.py, and the plain bus and links fly in the other
    `fleet` tests): every MAVLink frame accepted at either end was signed, the bus links are
    TLS, intruders were refused, and no key appears in the logs, records or result."""
    out = tmp_path / "flight"
    line = tmp_path / "line-3.yaml"  # a user file: three in a line, 1.5 m apart
    line.write_text("points: [[0, -1.5, 0], [0, 0, 0], [0, 1.5, 0]]\n")
    cfg = DemoConfig(
        drones=3,
        formation="triangle-3",
        world="forest-small",
        seed=2,
        formation_change=(str(line), 8.0),
        out_dir=out,
        secure=True,
        startup_timeout_s=150.0,
        flight_timeout_s=300.0,  # a loaded machine plans slowly; a quiet one crosses in ~40 s
    )
    result = run_demo(cfg)
    procs = json.loads((out / "logs" / "processes.json").read_text())
    assert not [p for p in procs["pids"].values() if _alive(p)]
    assert not _group_alive(int(procs["pgid"]))
    assert result["success"], json.dumps(result, indent=1, default=str)
    assert result["arrived"] and result["collisions"] == 0
    # the mock's truth: body clearance to obstacles, distance between centres (2 radii: 0.4 m)
    assert result["min_obstacle_clearance_m"] > 0.0 and result["min_drone_distance_m"] > 0.4
    assert all(rc == 0 for rc in result["exit_codes"].values())
    mission = json.loads((out / "mission.json").read_text())
    assert [c["ok"] for c in mission["commands"]] == [True] * len(mission["commands"])
    assert [a["name"] for a in mission["assignments"]] == ["triangle-3", "line-3"]
    e1, e2 = (a["epoch"] for a in mission["assignments"])
    assert e2 > e1
    # the new shape's time from the command, and from the common switch time it carries
    reached = result["formation_change_reached_s"]
    after = result["formation_change_reached_after_switch_s"]
    assert (reached is None) == (after is None)
    # the switch: the demo's lead after the command was sent (the station's for loopback)
    assert mission["lead_s"] == cfg.lead_s == DEMO_LEAD_S < StationConfig().lead_s
    if reached is not None:
        assert cfg.lead_s <= reached - after < cfg.lead_s + 1.0
    records = sorted(out.glob("drone*.mcap"))
    assert len(records) == 3
    for rec_path in records:
        rec = read_record(rec_path)
        # each drone planned on its own map, built from the mock's depth frames ...
        assert max(m["occupied_cells"] for m in rec.messages("/map")) > 100, rec_path
        # ... and flew with its peers: some plans had both others in the formation
        assert max(p["n_peers"] for p in rec.messages("/plan")) == 2, rec_path
        # ... on a healthy bus: no peer ever reported that it did not hear this drone
        last = rec.messages("/counters")[-1]["counters"]
        assert last["service.peers_stopped_hearing_us"] == 0, rec_path
        # ... and in formation flight no peer was taken for one off its trajectory (by its
        # position, or its velocity within peer_deviation_ahead_s): the vehicles' tracking
        # errors are no deviation. (Climbing to the take-off altitude and landing, the vehicle
        # is under the autopilot's control, off the hover it announces: those count.)
        spans, since = [], None
        for t, tr in rec.topics["/transition"]:
            if tr["target"] == "formation-flight":
                since = t
            elif since is not None and tr["source"] == "formation-flight":
                spans.append((since, t))
                since = None
        assert spans, rec_path
        off = [
            (t, m["message"])
            for t, m in rec.topics["/log"]
            if "off its trajectory" in m["message"] and any(a <= t <= b for a, b in spans)
        ]
        assert not off, (rec_path, off)
        assert not [p for p in rec.messages("/plan") if p["unheard_by"]], rec_path
    for name in ("top_view.png", "formation_error.png", "summary.json"):
        assert (out / "report" / name).is_file()
    summary = json.loads((out / "report" / "summary.json").read_text())
    assert summary["n_drones"] == 3 and summary["arrived"]
    assert summary["setpoint_period_ms"]["count"] > 1000
    # the target's latency figure: every service heard its peers' trajectories
    peer = result["peer_latency_ms"]
    assert sorted(peer["per_drone"]) == ["0", "1", "2"], peer
    assert all(n > 0 for n in peer["per_drone"].values()) and peer["median"] > 0.0
    assert sum(d["peer_latency_ms"]["count"] for d in summary["drones"]) >= peer["count"]
    # the security, checked by the demo on the processes and links it ran
    sec = result["security"]
    assert sec["signing"] and sec["zenoh_tls"] and sec["signing_checks"]["signed_only"]
    assert sec["bus_checks"]["link_locators_tls_only"]
    assert sec["bus_checks"]["every_drone_authenticated"]
    assert result["bus_latency_ms"]["count"] > 0
    # where the CPU went, by OS thread: the services' own threads and the bus's callback
    # threads by name (threads that ended, as the warm-up, count in the totals only)
    threads = result["cpu_threads_s"]["services"]
    for name in ("svc-depth", "svc-planner", "svc-monitor", "bus-rx", "depth-rx"):
        assert threads.get(name, 0.0) > 0.0, threads
    total = sum(v for k, v in result["cpu_s"].items() if k.startswith("drone"))
    assert 0.0 < sum(threads.values()) <= total + 0.05 * len(records)
    assert result["cpu_threads_s"]["sitl"] and "CPU over the run (" in result_text(result)
    # the safety monitors' stops and replans, summed from the records' counters
    assert result["monitor"] == summary["monitor"]
    assert set(result["monitor"]) == {"brakes", "replans", "shallow_replans"}
    assert "safety monitors: " in result_text(result)
    # the holds for lost depth, with the map's lags behind a live camera
    assert result["depth_holds"] == summary["depth_holds"]
    assert set(result["depth_holds"]) == {
        "holds",
        "map_lag_holds",
        "map_lag_rides",
        "frames_missed",
    }
    assert "holds for lost depth" in result_text(result)
    # every kernel the flight ran was compiled or loaded by the warm-up, before READY: one
    # made in flight holds a planning thread (on a cold cache, a 7-drone demo's first plans
    # took 65 s when the check met a mask type the warm-up had not)
    assert result["kernels_after_ready"] == summary["kernels_after_ready"] == 0, [
        line
        for p in sorted((out / "logs").glob("drone*.log"))
        for line in p.read_text().splitlines()
        if "kernels_after_ready" in line
    ]
    keys = [p.read_text().strip() for p in sorted((out / "secrets").glob("mavlink-*.key"))]
    assert len(keys) == 3
    for p in out.rglob("*"):
        if p.is_file() and "secrets" not in p.parts:
            data = p.read_bytes()
            assert not [k for k in keys if k.encode() in data or bytes.fromhex(k) in data], p
