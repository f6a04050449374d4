"""The planner benchmark's replay on the drones' own maps: which replans keep their field."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.bench import FieldKeeper, _fresh_cheaper
from gcs.fastsim import PlanCall, replay_inputs
from onboard.planner.field import AnalyticField, GridField
from onboard.world import World


def _call(t_s: float, n_peers: int, field: GridField | None) -> PlanCall:
    z3 = np.zeros(3)
    peers: tuple = tuple(object() for _ in range(n_peers))  # only counted here
    return PlanCall(0, 0, t_s, z3, z3, z3, z3, peers, World.empty(0.0), None, field)


def _grid() -> GridField:
    return GridField(np.ones((2, 2, 2)), np.zeros(3), 0.1)


def test_field_keeper_keeps_an_even_subset_of_the_chosen_replans() -> None:
    keeper = FieldKeeper(n_drones=3, skip_s=2.0, cap=4)
    fields = {}
    for k in range(40):
        t = 0.5 * k
        f = _grid()
        fields[t] = f
        keeper(_call(t, 2 if k % 10 else 1, f))  # every 10th misses a peer
    assert len(keeper.calls) == 40 and all(c.mapped_field is None for c in keeper.calls)
    kept_t = [c.t_start_s for c in keeper.kept]
    eligible = [0.5 * k for k in range(40) if 0.5 * k >= 2.0 and k % 10]
    assert 2 <= len(kept_t) <= 4
    assert kept_t == eligible[:: keeper.stride][: len(kept_t)]  # every stride-th, in order
    assert all(c.mapped_field is fields[c.t_start_s] for c in keeper.kept)
    with pytest.raises(ValueError, match="cap"):
        FieldKeeper(3, 0.0, 0)


def test_replay_uses_the_recorded_map_when_there_is_one() -> None:
    g = _grid()
    assert replay_inputs(_call(1.0, 2, g))[6] is g
    assert isinstance(replay_inputs(_call(1.0, 2, None))[6], AnalyticField)


def test_fresh_cheaper_counts_only_the_problems_where_the_fresh_start_wins() -> None:
    """``fresh_cheaper``: the share of the fresh start's problems where it costs less, and the
    gain there in percent; a tie or a dearer fresh start is no gain."""
    got = _fresh_cheaper([0.10, -0.20, 0.01, 0.0, 0.06])
    assert got["share"] == pytest.approx(0.6)
    assert got["gain_pct"]["median"] == pytest.approx(6.0)
    assert got["gain_pct"]["max"] == pytest.approx(10.0)
    assert got["over_5pct"] == 2
    assert _fresh_cheaper([-0.1, 0.0]) == {"share": 0.0, "gain_pct": None, "over_5pct": 0}
    assert _fresh_cheaper([]) == {"share": None, "gain_pct": None, "over_5pct": 0}
