"""``swarm-gcs bench demo``: how a run over seeds is judged, and a demo that fails is reported
(the flights themselves are benchmarks, not tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gcs.bench_demo import host_cpu_share, run_demo_seed, summarise
from gcs.demo import DEMO_LEAD_S


def _row(
    seed: int,
    ok: bool,
    reached: float | None,
    collisions: int = 0,
    after_switch: float | None = None,
) -> dict[str, Any]:
    side = {
        "success": ok,
        "collisions": collisions,
        "formation_change_reached_s": reached,
        "formation_change_reached_after_switch_s": reached
        if after_switch is None
        else after_switch,
    }
    return {"seed": seed, "demo": dict(side), "fastsim": dict(side)}


def test_every_seed_must_succeed() -> None:
    rows = [_row(1, True, None), _row(2, True, None)]
    s = summarise(rows, change=False)
    assert s["demo"] == {"flown": 2, "success": 2, "collisions": 0}
    assert s["demo_target_met"]
    rows.append(_row(3, False, None))
    s = summarise(rows, change=False)
    assert s["demo"]["success"] == 2 and not s["demo_target_met"]
    assert not summarise([], change=False)["demo_target_met"]


def test_a_change_must_reach_the_new_shape_within_10_s() -> None:
    ok = [_row(1, True, 6.0), _row(2, True, 10.0)]
    s = summarise(ok, change=True)
    assert s["demo"]["reached_within_10_s"] == 2 and s["demo_target_met"]
    for bad in (_row(3, True, 10.5), _row(3, True, None), _row(3, False, 4.0)):
        s = summarise([*ok, bad], change=True)
        assert s["demo"]["reached_within_10_s"] == 2 and not s["demo_target_met"], bad


def test_the_target_counts_from_the_command_not_from_the_switch() -> None:
    """The real stack's change switches the station's lead after the command: within 10 s of
    the switch is counted beside, but issue #10's target takes the command's clock."""
    rows = [_row(1, True, 6.0), _row(2, True, 11.0, after_switch=9.5)]
    s = summarise(rows, change=True)
    assert s["demo"]["reached_within_10_s"] == 1
    assert s["demo"]["reached_within_10_s_of_the_switch"] == 2
    assert not s["demo_target_met"]
    late = summarise([_row(1, True, 11.6, after_switch=10.1)], change=True)
    assert late["demo"]["reached_within_10_s_of_the_switch"] == 0


def test_a_failed_demo_is_reported_with_its_error(tmp_path: Path) -> None:
    r = run_demo_seed(1, ["--formation", "no-such-formation"], tmp_path / "f", 120.0)
    assert r["success"] is False and r["exit_code"] != 0
    assert "no-such-formation" in r["error"]
    assert r["min_obstacle_clearance_centre_m"] is None
    busy = r["host_cpu"]["busy"]  # the host's CPU over the run, a share of all cores
    assert busy is not None and 0.0 <= busy <= 1.0


def test_the_hosts_cpu_share_counts_idle_and_io_wait_as_free_and_steal_apart() -> None:
    """``host_cpu_share`` on two samples of the host's CPU times (psutil's fields, seconds over
    every core): 10 s of 40 idle or waiting for I/O -> 75 % busy, 4 s stolen -> 10 % (a guest's
    3 s are in ``user`` already); a platform without ``steal`` gives None for it; no time
    passed gives None for both."""
    from collections import namedtuple

    Times = namedtuple("Times", "user nice system idle iowait steal guest guest_nice")
    before = Times(100.0, 0.0, 20.0, 500.0, 5.0, 1.0, 0.0, 0.0)
    after = Times(120.0, 0.0, 26.0, 508.0, 7.0, 5.0, 3.0, 0.0)  # 20 + 6 + 8 + 2 + 4 = 40 s
    share = host_cpu_share(before, after)
    assert share["busy"] == pytest.approx(0.75) and share["steal"] == pytest.approx(0.10)
    Plain = namedtuple("Plain", "user system idle")
    share = host_cpu_share(Plain(1.0, 1.0, 1.0), Plain(2.0, 1.0, 4.0))
    assert share["busy"] == pytest.approx(0.25) and share["steal"] is None
    assert host_cpu_share(before, before) == {"busy": None, "steal": None}


def test_a_formation_of_another_size_is_refused_before_the_first_seed(tmp_path: Path) -> None:
    """The demo's own size check (``gcs.demo.demo_templates``), on the flight's formation and
    on the change's, before any process starts or any flight directory is made."""
    from click.testing import CliRunner

    from gcs.cli import main

    base = ["bench", "demo", "--seeds", "1", "--drones", "3", "--no-fastsim"]
    for extra, name in (
        (["--formation", "hexagon-7"], "hexagon-7"),
        (["--formation", "triangle-3", "--formation-change", "rectangle-7@8"], "rectangle-7"),
    ):
        out_dir = tmp_path / name
        res = CliRunner().invoke(main, [*base, *extra, "--out", str(out_dir)])
        assert res.exit_code == 1, res.output
        assert f"formation {name} has 7 points, not 3" in res.output
        assert not out_dir.exists() and "seed 1" not in res.output


def test_onboard_settings_reach_every_demo_and_the_fast_time_twin(
    tmp_path: Path, monkeypatch: Any
) -> None:
    """``--set-onboard`` goes to each seed's demo and, for the planner and the replan period,
    to its fast-time flight; a bad setting is refused before the first seed."""
    import json

    from click.testing import CliRunner

    import gcs.bench_demo as bd
    from gcs.cli import main

    seen: dict[str, Any] = {}

    def demo(seed: int, argv: list[str], out_dir: Path, timeout_s: float) -> dict[str, Any]:
        seen["argv"] = argv
        return {"success": True, "collisions": 0}

    def twin(*args: Any) -> dict[str, Any]:
        seen["planner"], seen["replan_s"], seen["occupancy"] = args[6], args[7], args[8]
        return {"success": True, "collisions": 0}

    monkeypatch.setattr(bd, "run_demo_seed", demo)
    monkeypatch.setattr(bd, "run_fastsim_seed", twin)
    base = ["bench", "demo", "--seeds", "1", "--drones", "3", "--formation", "triangle-3"]
    sets = ["--set-onboard", "planning.replan_period_s=0.5"]
    sets += ["--set-onboard", "planner.w_formation=2e5"]
    sets += ["--set-onboard", "mapping.occupancy.occluded_fill_m=0.2"]
    js = tmp_path / "b.json"
    res = CliRunner().invoke(main, [*base, *sets, "--out", str(tmp_path / "f"), "--json", str(js)])
    assert res.exit_code == 0, res.output
    argv = seen["argv"]
    assert argv[argv.index("planning.replan_period_s=0.5") - 1] == "--set-onboard"
    assert "planner.w_formation=2e5" in argv
    assert seen["replan_s"] == 0.5 and seen["planner"].w_formation == 2e5
    assert seen["occupancy"] == (("occluded_fill_m", 0.2),)  # the twins' maps too
    assert json.loads(js.read_text())["config"]["replan_period_s"] == 0.5
    # the demo's command-to-switch lead unless --lead says otherwise, recorded
    assert argv[argv.index("--lead") + 1] == str(DEMO_LEAD_S)
    assert json.loads(js.read_text())["config"]["lead_s"] == DEMO_LEAD_S
    lead = ["--lead", "1.5", "--no-fastsim", "--json", str(js)]
    res = CliRunner().invoke(main, [*base, *lead, "--out", str(tmp_path / "h")])
    assert res.exit_code == 0, res.output
    assert seen["argv"][seen["argv"].index("--lead") + 1] == "1.5"
    assert json.loads(js.read_text())["config"]["lead_s"] == 1.5
    too_fast = ["--set-onboard", "planning.replan_period_s=0.01"]
    bad = CliRunner().invoke(main, [*base, *too_fast, "--out", str(tmp_path / "g")])
    assert bad.exit_code == 1 and "replan_period_s" in bad.output
    assert not (tmp_path / "g").exists()


def test_fast_time_only_judges_no_real_stack() -> None:
    """Rows without a demo (``--fastsim-only``): the twins are counted, and issue #10's target
    (the real stack's) is neither met nor failed."""
    rows = [{"seed": k, "demo": None, "fastsim": _row(k, True, 12.0)["fastsim"]} for k in (1, 2)]
    s = summarise(rows, change=True)
    assert s["demo"]["flown"] == 0 and s["demo_target_met"] is None
    assert s["fastsim"] == {
        "flown": 2,
        "success": 2,
        "collisions": 0,
        "reached_within_10_s": 0,
        "reached_within_10_s_of_the_switch": 0,
    }


def test_fastsim_only_flies_no_demo(tmp_path: Path, monkeypatch: Any) -> None:
    """``--fastsim-only`` flies every seed's twin and no demo, makes no flight directory, and
    reports the twins' counts; ``--jobs`` over 1 needs it, and it excludes ``--no-fastsim``."""
    import json

    from click.testing import CliRunner

    import gcs.bench_demo as bd
    from gcs.cli import main

    flown: list[int] = []

    def demo(*args: Any) -> dict[str, Any]:
        raise AssertionError("a demo was started")

    def twin(seed: int, *args: Any) -> dict[str, Any]:
        flown.append(seed)
        reached = 6.0 if seed == 3 else 14.0
        return {
            "success": True,
            "collisions": 0,
            "formation_change_reached_s": reached,
            "formation_change_reached_after_switch_s": reached,
        }

    monkeypatch.setattr(bd, "run_demo_seed", demo)
    monkeypatch.setattr(bd, "run_fastsim_seed", twin)
    base = ["bench", "demo", "--seeds", "2", "--first-seed", "3", "--drones", "3"]
    base += ["--formation", "triangle-3", "--formation-change", "line-3@8"]
    out, js = tmp_path / "f", tmp_path / "b.json"
    res = CliRunner().invoke(main, [*base, "--fastsim-only", "--out", str(out), "--json", str(js)])
    assert res.exit_code == 0, res.output
    assert flown == [3, 4] and not out.exists()
    assert (
        "fast time: 2 of 2 seeds succeeded, 1 reached the new shape within 10 s "
        "(1 within 10 s of the switch)" in res.output
    )
    assert "real stack" not in res.output
    assert [ln.split()[1] for ln in res.output.splitlines() if "fast time" in ln][:2] == ["3", "4"]
    report = json.loads(js.read_text())
    assert report["config"]["real_stack"] is False and report["out_dir"] is None
    assert [r["demo"] for r in report["rows"]] == [None, None]
    assert report["summary"]["demo_target_met"] is None
    for bad, what in ((["--jobs", "2"], "--fastsim-only"),
                      (["--fastsim-only", "--no-fastsim"], "exclude each other")):  # fmt: skip
        res = CliRunner().invoke(main, [*base, *bad, "--out", str(out)])
        assert res.exit_code == 2 and what in res.output, res.output
    assert flown == [3, 4]


def test_twins_flown_in_worker_processes_are_the_twins_flown_here() -> None:
    """``fly_twins`` with two jobs (spawned workers: the arguments and results cross a process
    boundary) gives, in the seeds' order, the flights of one job: fast time is deterministic."""
    from gcs.bench_demo import fly_twins
    from gcs.fastsim import REFUSAL_KEYS
    from onboard.planner.params import PlannerParams

    planner = PlannerParams(z_limits_m=(0.4, 1.8))
    args = [(seed, "triangle-3", "forest-small", ("line-3", 6.0), 3.0, 3, planner, 1.0)
            for seed in (1, 2)]  # fmt: skip
    pooled = fly_twins(args, 2)
    here = fly_twins(args[1:], 1)  # the second seed: the order is kept
    for r in (*pooled, *here):
        for timing in ("sim_wall_s", "replan_ms_median"):
            r.pop(timing)
        assert r["success"] and r["collisions"] == 0
        assert set(r["refusals"]) == set(REFUSAL_KEYS)  # how many plans the check refused, why
    assert pooled[1] == here[0] and pooled[0] != pooled[1]
