"""``swarm-gcs`` end to end, headless, through click's CliRunner."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from gcs.cli import main

SMALL = ["--formation", "triangle-3", "--world", "forest-small", "--v-max", "1.0", "--seed", "1"]


def test_help_lists_commands() -> None:
    out = CliRunner().invoke(main, ["--help"])
    assert out.exit_code == 0
    assert "sim" in out.output and "bench" in out.output
    out = CliRunner().invoke(main, ["bench", "--help"])
    assert out.exit_code == 0 and "planner" in out.output


def test_sim_writes_json_and_plot(tmp_path: Path) -> None:
    js, png = tmp_path / "out" / "sim.json", tmp_path / "sim.png"
    out = CliRunner().invoke(
        main, ["sim", *SMALL, "--json", str(js), "--plot", str(png), "--check"]
    )
    assert out.exit_code == 0, out.output
    assert "success" in out.output and "replan ms" in out.output
    data = json.loads(js.read_text())
    assert data["success"] is True and data["collisions"] == 0
    for key in ("min_obstacle_clearance_m", "min_drone_distance_m", "e_sim_mean"):
        assert isinstance(data[key], float)
    assert {"median", "p90", "max"} <= set(data["replan_ms"])
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_sim_quiet_and_config_errors(tmp_path: Path) -> None:
    out = CliRunner().invoke(main, ["sim", *SMALL, "--quiet", "--set", "w_obstacle=x"])
    assert out.exit_code != 0
    assert "planner.w_obstacle: expected a number, got 'x'" in out.output
    out = CliRunner().invoke(main, ["sim", "--formation", "no-such-formation", "--quiet"])
    assert out.exit_code != 0 and "no file named 'no-such-formation'" in out.output
    out = CliRunner().invoke(main, ["sim", *SMALL, "--quiet", "--time-limit", "1"])
    assert out.exit_code == 0 and out.output == ""
    for bad, why in (
        ("1@5", "expected DRONE@FROM-TO"),
        ("x@1-2", "expected DRONE@FROM-TO"),
        ("7@1-2", "drone 7 is not in the formation of 3"),
        ("1@3-2", "expected 0 <= from < to"),
    ):
        out = CliRunner().invoke(main, ["sim", *SMALL, "-q", "--radio-outage", bad])
        assert out.exit_code != 0 and why in out.output, (bad, out.output)
    twice = ["--radio-outage", "1@1-2", "--radio-outage", "1@3-4"]
    out = CliRunner().invoke(main, ["sim", *SMALL, "-q", *twice])
    assert out.exit_code != 0 and "drone 1 is given two outages" in out.output


def test_one_owner_of_the_speed_limit(tmp_path: Path) -> None:
    """--set v_max_m_s takes effect; --v-max is its shorthand; both differently is an error."""
    base = ["sim", "--formation", "triangle-3", "--world", "forest-small", "--time-limit", "1"]
    seen = {}
    for name, extra in {
        "set": ["--set", "v_max_m_s=2"],
        "v-max": ["--v-max", "1.5"],
        "both, agreeing": ["--v-max", "2", "--set", "v_max_m_s=2.0"],
        "default": [],
    }.items():
        js = tmp_path / f"{name}.json"
        out = CliRunner().invoke(main, [*base, *extra, "--quiet", "--json", str(js)])
        assert out.exit_code == 0, (name, out.output)
        cfg = json.loads(js.read_text())["config"]
        assert cfg["v_max_m_s"] == cfg["planner"]["v_max_m_s"], name
        seen[name] = cfg["v_max_m_s"]
    assert seen == {"set": 2.0, "v-max": 1.5, "both, agreeing": 2.0, "default": 0.5}
    out = CliRunner().invoke(main, [*base, "--v-max", "1", "--set", "v_max_m_s=2", "--quiet"])
    assert out.exit_code != 0
    assert "--v-max 1.0 and --set v_max_m_s=2 disagree" in out.output
    out = CliRunner().invoke(main, [*base, "--v-max", "-1", "--quiet"])
    assert out.exit_code != 0 and "v_max_m_s must be a positive number" in out.output
    # the same rule in every command that flies
    for cmd in (["bench", "flights", "--seeds", "1"], ["bench", "planner"]):
        out = CliRunner().invoke(main, [*cmd, "--v-max", "1", "--set", "v_max_m_s=2", "-q"])
        assert out.exit_code != 0 and "disagree" in out.output, cmd
    out = CliRunner().invoke(
        main, ["bench", "table", "--trials", "1", "--v-max", "1", "--set", "v_max_m_s=2", "-q"]
    )
    assert out.exit_code != 0 and "disagree" in out.output


def test_scenario_speed_unless_given(tmp_path: Path) -> None:
    js = tmp_path / "s.json"
    base = ["sim", "--scenario", "tetrahedron-corridor", "--time-limit", "0.5", "-q"]
    for extra, want in (([], None), (["--set", "v_max_m_s=0.7"], 0.7), (["--v-max", "0.9"], 0.9)):
        out = CliRunner().invoke(main, [*base, *extra, "--json", str(js)])
        assert out.exit_code == 0, out.output
        got = json.loads(js.read_text())["config"]["v_max_m_s"]
        if want is None:
            from onboard.config import load_scenario

            want = load_scenario("tetrahedron-corridor").v_max_m_s
        assert got == want, extra


@pytest.mark.slow
def test_bench_planner_small(tmp_path: Path) -> None:
    js = tmp_path / "bench.json"
    args = [
        "bench", "planner", *SMALL, "--repeats", "1", "--max-problems", "4", "--skip-s", "2",
        "--eval-calls", "10", "--term-costs", "--json", str(js),
    ]  # fmt: skip
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert data["problems"] == 4
    by_term = data["eval_us_by_term"]  # --term-costs
    assert set(by_term) == {"all", "obstacle", "formation", "swarm", "feasibility", "uniformity",
                            "altitude", "base", "peers"}  # fmt: skip
    assert by_term["all"] > 0 and by_term["base"] > 0
    assert "one evaluation at the solution" in out.output
    for key in ("replan_ms", "iterations", "evaluations"):
        assert {"median", "p90", "max"} <= set(data[key])
    assert data["replan_ms"]["median"] > 0 and data["eval_us"] > 0
    assert set(data["breakdown"]) == {
        "setup_ms_median",
        "solve_ms_median",
        "cost_eval_ms_median",
        "solver_overhead_ms_median",
        "check_and_rest_ms_median",
    }
    assert data["solve_ms"]["median"] > 0.0
    assert sum(data["solver_status_counts"].values()) == data["problems"]
    assert data["pieces"]["median"] >= 1
    assert data["startup_s"] > 0 and data["startup"]["first_plan_status"]
    assert {"platform", "cpu", "python", "numpy", "numba"} <= set(data["machine"])
    # the fresh start's solve, timed alone where plan() makes one (a previous trajectory)
    assert 0.0 < data["fresh_share"] <= 1.0
    fresh = data["fresh_ms"]
    assert fresh["setup_median"] > 0 and fresh["solve"]["median"] > 0
    assert fresh["evaluations_median"] >= 1
    text = " ".join(out.output.split())  # the console wraps its lines
    assert "the fresh start, in" in text and "(side thread)" in text
    # what it buys: where its solution costs less than the warm one's, and by how much
    cheaper = data["fresh_cheaper"]
    assert 0.0 <= cheaper["share"] <= 1.0
    if cheaper["share"] > 0.0:
        gain = cheaper["gain_pct"]
        assert 0.0 < gain["median"] <= gain["p90"] <= gain["max"] < 100.0
        assert "costs less than the warm start's in" in out.output
    n_fresh = round(data["fresh_share"] * data["problems"])
    assert 0 <= cheaper["over_5pct"] <= round(cheaper["share"] * n_fresh)
    sets = ["--no-startup", "--set", "fresh_alternative=never", "--json", str(js)]
    out = CliRunner().invoke(main, [*args[:-3], *sets])
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert data["fresh_share"] == 0.0 and data["fresh_ms"]["solve"] is None
    assert data["fresh_cheaper"] == {"share": None, "gain_pct": None, "over_5pct": 0}
    assert "the fresh start, in" not in out.output


def test_bench_planner_replays_on_the_drones_maps(tmp_path: Path) -> None:
    """--perception mapped: a short mapped flight, its replans replayed on each drone's ESDF."""
    js = tmp_path / "bench.json"
    args = [
        "bench", "planner", *SMALL, "--perception", "mapped", "--camera-rate", "10",
        "--time-limit", "3", "--skip-s", "1.5", "--max-problems", "2", "--repeats", "1",
        "--eval-calls", "10", "--no-startup", "--json", str(js),
    ]  # fmt: skip
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    assert "on the ESDF" in out.output
    data = json.loads(js.read_text())
    assert data["scenario"]["perception"] == "mapped" and data["scenario"]["field"] == "esdf"
    assert data["problems"] == 2 and data["replan_ms"]["median"] > 0
    assert sum(data["plan_status_counts"].values()) == 2


def test_bench_flights_over_seeds(tmp_path: Path) -> None:
    js = tmp_path / "flights.json"
    args = ["bench", "flights", "--formation", "triangle-3", "--world", "forest-small"]
    out = CliRunner().invoke(main, [*args, "--v-max", "1.0", "--seeds", "2", "--json", str(js)])
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert data["seeds"] == 2 and len(data["flights"]) == 2
    assert data["collision_free_count"] == 2
    assert [f["seed"] for f in data["flights"]] == [1, 2]
    # the attempts the safety check refused, by reason, per flight
    for f in data["flights"]:
        assert f["refusals"]["attempts"] >= 0
        assert set(f["refusals"]) >= {"unobserved", "obstacle", "drone", "altitude"}
    # the second of them again, alone and in a worker process: the same flight
    js2 = tmp_path / "flights2.json"
    more = ["--seeds", "1", "--first-seed", "2", "--jobs", "2", "--json", str(js2)]
    out = CliRunner().invoke(main, [*args, "--v-max", "1.0", *more])
    assert out.exit_code == 0, out.output
    again = json.loads(js2.read_text())
    assert again["first_seed"] == 2 and again["jobs"] == 2

    def flown(f: dict[str, object]) -> dict[str, object]:  # without the planner's timing
        return {k: v for k, v in f.items() if k != "replan_ms"}

    assert [flown(f) for f in again["flights"]] == [flown(data["flights"][1])]


def test_onboard_warmup_and_sitl(tmp_path: Path) -> None:
    from onboard.cli import main as onboard_main
    from sitl_mock.cli import main as sitl_main
    from sitl_mock.client import MavClient, bind_consecutive_udp

    out = CliRunner().invoke(onboard_main, ["warmup"])
    assert out.exit_code == 0, out.output
    # the default config has a depth source: the mapping path is warmed too
    assert "planner ready" in out.output and "mapping path" in out.output
    out = CliRunner().invoke(sitl_main, ["--help"])
    assert out.exit_code == 0 and "--count" in out.output and "--speedup" in out.output
    # two vehicles in a world for half a second; their telemetry reaches the clients' ports
    socks = bind_consecutive_udp(2)
    clients = [MavClient(sock=s) for s in socks]
    js = tmp_path / "sitl.json"
    args = ["--count", "2", "--world", "forest-small", "--base-port", str(clients[0].port),
            "--local-port-offset", "-1", "--duration", "0.5", "--stats-json", str(js)]  # fmt: skip
    try:
        out = CliRunner().invoke(sitl_main, args)
        assert out.exit_code == 0, out.output
        assert "sysid 2" in out.output and "0 collision(s)" in out.output
        for i, c in enumerate(clients):
            assert c.wait("HEARTBEAT", timeout_s=2.0).get_srcSystem() == i + 1
    finally:
        for c in clients:
            c.close()
    data = json.loads(js.read_text())
    assert data["vehicles"] == 2 and data["ticks"] > 0 and data["collisions"] == []
    assert all(link["tx_messages"] > 0 for link in data["links"])
    out = CliRunner().invoke(sitl_main, ["--set", "autopilot.boot_time_s=x", "--duration", "0"])
    assert out.exit_code != 0
    assert "sitl.autopilot.boot_time_s: expected a number, got 'x'" in out.output


@pytest.mark.slow
def test_bench_table_small(tmp_path: Path) -> None:
    js, plots = tmp_path / "table.json", tmp_path / "plots"
    args = ["bench", "table", "--trials", "2", "--world", "forest-small"]
    args += [
        "--formation",
        "triangle-3",
        "--v-max",
        "1.0",
        "--json",
        str(js),
        "--plots",
        str(plots),
    ]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert len(data["trials"]) == 2 * 3
    assert {r["method"] for r in data["summary"]} == {"ours", "turpin", "zhou"}
    for row in data["summary"]:
        for key in (
            "density",
            "method",
            "trials",
            "success_rate",
            "e_dist",
            "e_sim",
            "min_obstacle_clearance_m",
            "min_drone_distance_m",
            "flight_time_s",
            "z_spread_max_m",
        ):
            assert key in row
        assert 0.0 <= row["success_rate"] <= 1.0 and row["trials"] == 2
    for t in data["trials"]:
        assert {"seed", "success", "e_dist_m", "e_dist_rms_m", "e_sim", "path_length_m"} <= set(t)
    assert [t["seed"] for t in data["trials"] if t["method"] == "ours"] == [1, 2]
    names = {p.name for p in plots.iterdir()}
    for m in ("ours", "turpin", "zhou"):
        assert f"top_forest-small_{m}.png" in names
        assert f"snapshots_forest-small_{m}.png" in names
    assert "esim_forest-small.png" in names


def test_sim_scenario_and_tracks_file(tmp_path: Path) -> None:
    import numpy as np

    npz = tmp_path / "tracks.npz"
    out = CliRunner().invoke(
        main, ["sim", "--scenario", "tetrahedron-corridor", "--tracks", str(npz), "--quiet"]
    )
    assert out.exit_code == 0, out.output
    data = np.load(npz)
    T = data["t"].shape[0]
    assert data["pos"].shape == (T, 4, 3)
    assert data["goals"].shape == (4, 3) and data["formation"].shape == (4, 3)


def test_world_export_round_trip(tmp_path: Path) -> None:
    import numpy as np

    from onboard.config import load_formation, load_world_spec

    for ext in ("yaml", "json"):
        out = tmp_path / f"w.{ext}"
        res = CliRunner().invoke(
            main, ["world", "export", "--world", "heart-forest", "--seed", "3", str(out)]
        )
        assert res.exit_code == 0, res.output
        form = load_formation("hexagon-7")
        a, sa, ga = load_world_spec("heart-forest").build(3, form)
        b, sb, gb = load_world_spec(out).build(0, form)
        for x, y in ((a.cylinders, b.cylinders), (a.rings, b.rings), (sa, sb), (ga, gb)):
            np.testing.assert_allclose(x, y, atol=1e-6)


def test_start_z_jitter_is_checked_and_flown() -> None:
    bad = CliRunner().invoke(main, ["sim", *SMALL, "--start-z-jitter", "0.6", "-q"])
    assert bad.exit_code == 2 and "--start-z-jitter" in bad.output
    out = CliRunner().invoke(main, ["sim", *SMALL, "--start-z-jitter", "0.05", "--time-limit", "3"])
    assert out.exit_code == 0, out.output
    # the starts are off 1 m by up to 5 cm, and the table says how far apart the drones flew
    line = next(x for x in out.output.splitlines() if "altitude" in x)
    lo, hi = (float(v) for v in line.split("│")[2].split("m")[0].split(" to "))
    assert 0.95 <= lo < hi <= 1.05


def test_replan_period_is_checked_and_flown(tmp_path: Path) -> None:
    bad = CliRunner().invoke(main, ["sim", *SMALL, "--replan-period", "0.05", "-q"])
    assert bad.exit_code == 2 and "--replan-period" in bad.output
    counts = {}
    for period in (1.0, 0.5):
        js = tmp_path / f"{period}.json"
        args = ["sim", *SMALL, "--time-limit", "6", "--replan-period", str(period), "-q"]
        # shape recovery off: its own period (0.1 s) would set the count where the shape is
        # off (on an AMD EPYC host these 6 s gave 37 replans at either period with it on)
        args += ["--set", "recover_e_sim=0"]
        out = CliRunner().invoke(main, [*args, "--json", str(js)])
        assert out.exit_code == 0, out.output
        data = json.loads(js.read_text())
        assert data["config"]["replan_period_s"] == period
        counts[period] = sum(data["status_counts"].values())
    # three drones over 6 s: about 18 replans at 1 s, twice as many at 0.5 s
    assert 1.8 <= counts[0.5] / counts[1.0] <= 2.2, counts
    js = tmp_path / "table.json"
    args = ["bench", "table", "--trials", "1", "--world", "forest-small", "--method", "ours"]
    args += ["--formation", "triangle-3", "--v-max", "1.0", "--replan-period", "0.5"]
    out = CliRunner().invoke(main, [*args, "--json", str(js), "-q"])
    assert out.exit_code == 0, out.output
    assert json.loads(js.read_text())["replan_period_s"] == 0.5


def test_bench_hidden_small(tmp_path: Path) -> None:
    js = tmp_path / "hidden.json"
    args = ["bench", "hidden", "--seeds", "1", "--jobs", "1", "--json", str(js), "-q"]
    out = CliRunner().invoke(main, [*args, "--set", "unheard_margin_m=0"])
    assert out.exit_code == 0, out.output
    assert "unheard_margin_m 0," in out.output and "success 1" in out.output
    data = json.loads(js.read_text())
    assert data["unheard_margin_m"] == 0.0 and len(data["flights"]) == 1
    assert data["total"]["collisions"] == 0 and data["total"]["unheard_plans"] > 0
    assert data["resend_s"] == [0.05, 0.15] and data["flights"][0]["resent"] > 0
    assert data["resend_plans"] is False and "(stops only)" in out.output
    out = CliRunner().invoke(main, [*args, "--resend-plans"])
    assert out.exit_code == 0 and "(stops only)" not in out.output, out.output
    plans = json.loads(js.read_text())
    assert plans["resend_plans"] is True
    assert plans["flights"][0]["resent"] > data["flights"][0]["resent"]
    # without the copies
    out = CliRunner().invoke(main, [*args, "--resend-s", "", "--deviation-ahead-s", "0"])
    assert out.exit_code == 0, out.output
    data = json.loads(js.read_text())
    assert data["resend_s"] == [] and data["deviation_ahead_s"] == 0.0
    assert data["flights"][0]["resent"] == 0
    for bad, hint in (
        (["--seeds", "0"], "--seeds"),
        (["--resend-s", "0.1,x"], "--resend-s"),
        (["--resend-s", "-0.1"], "--resend-s"),
        (["--deviation-ahead-s", "-1"], "--deviation-ahead-s"),
    ):
        out = CliRunner().invoke(main, ["bench", "hidden", *bad])
        assert out.exit_code != 0 and hint in out.output, out.output
