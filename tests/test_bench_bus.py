"""`bench bus`: the latency benchmark runs end to end (tiny sizes) and writes its JSON."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from gcs.bench_bus import BusBenchConfig, bench_bus, run_bus_bench


def test_sessions_mode_counts_every_delivery() -> None:
    cfg = BusBenchConfig(drones=2, messages=10, rate_hz=50.0, warmup=2, mode="sessions")
    r = run_bus_bench(cfg)
    assert r["expected"] == 2 * 1 * 10
    assert r["received"] + r["lost"] == r["expected"] and r["lost"] == 0
    assert r["rejected_or_errors"] == 0
    s = r["latency_ms"]
    assert 0.0 < s["min"] <= s["median"] <= s["p99"] <= s["max"]
    assert set(r["per_receiver_ms"]) == {"0", "1"}
    assert 900 < r["message_bytes"] < 1300  # a 6-piece trajectory


def test_command_with_processes_writes_json(tmp_path: Path) -> None:
    out = tmp_path / "bus.json"
    res = CliRunner().invoke(
        bench_bus,
        ["--drones", "2", "--messages", "5", "--rate", "50", "--warmup", "1", "--json", str(out)],
    )
    assert res.exit_code == 0, res.output
    r = json.loads(out.read_text())
    assert r["config"]["mode"] == "processes" and r["received"] == 10 and r["lost"] == 0
    assert "median" in res.output and "p99" in res.output


def test_bad_config_refused() -> None:
    with pytest.raises(ValueError, match="drones"):
        BusBenchConfig(drones=1)
    with pytest.raises(ValueError, match="mode"):
        BusBenchConfig(mode="threads")
