"""The planner benchmark's replay on the drones' own maps: which replans keep their field."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.bench import FieldKeeper
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
