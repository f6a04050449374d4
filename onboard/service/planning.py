"""The planning side of the service: which peers count, the planner per formation slot, and the
checks the service adds to the planner's own (geofence, peers that went silent)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from onboard.planner.params import PlannerParams
from onboard.planner.planner import FormationPlanner, PeerTrajectory, PlanResult
from onboard.planner.trajectory import Trajectory
from onboard.service.config import GeofenceSection
from onboard.service.ports import PeerInfo


@dataclass(frozen=True)
class PeerSplit:
    """Peers sorted for one replan: ``formation`` (heard within their validity and flying the
    same formation epoch: kept in formation and avoided), ``avoid_only`` (silent past their
    validity, but not longer than the avoid time: avoided through their last trajectory),
    ``dropped`` (ids silent for longer: ignored)."""

    formation: tuple[PeerTrajectory, ...]
    avoid_only: tuple[PeerTrajectory, ...]
    dropped: tuple[int, ...]


def split_peers(
    peers: dict[int, PeerInfo],
    now_s: float,
    own_id: int,
    own_slot: int,
    epoch: int,
    n_slots: int,
    validity_s: float,
    avoid_for_s: float,
) -> PeerSplit:
    """Classify the peers (see ``PeerSplit``); a peer's validity ends at the earlier of its
    message's own ``valid_until_s`` and ``validity_s`` after it was received."""
    formation: list[PeerTrajectory] = []
    avoid: list[PeerTrajectory] = []
    dropped: list[int] = []
    taken = {own_slot}
    for pid in sorted(peers):
        if pid == own_id:
            continue
        info = peers[pid]
        until = min(info.valid_until_s, info.received_s + validity_s)
        if now_s <= until:
            pt = PeerTrajectory(pid, info.slot, info.trajectory)
            if (
                info.formation_epoch == epoch
                and 0 <= info.slot < n_slots
                and info.slot not in taken
            ):
                taken.add(info.slot)
                formation.append(pt)
            else:
                avoid.append(pt)
        elif now_s <= until + avoid_for_s:
            avoid.append(PeerTrajectory(pid, info.slot, info.trajectory))
        else:
            dropped.append(pid)
    return PeerSplit(tuple(formation), tuple(avoid), tuple(dropped))


def inside_box(
    traj: Trajectory, t_from_s: float, box: GeofenceSection, step_s: float = 0.1
) -> bool:
    """Whether ``traj`` stays inside the geofence from ``t_from_s`` to its end."""
    t_end = max(traj.t_end_s, t_from_s)
    ts = np.append(np.arange(t_from_s, t_end, step_s), t_end)
    p = traj.sample(ts)
    lo = np.asarray(box.min_enu_m)
    hi = np.asarray(box.max_enu_m)
    return bool(np.all((p >= lo) & (p <= hi)))


class Replanner:
    """One ``FormationPlanner`` per (formation template, slot), built when first needed."""

    def __init__(self, params: PlannerParams) -> None:
        self.params = params
        self._planners: dict[tuple[object, int], FormationPlanner] = {}

    def planner(self, points: Sequence[tuple[float, float, float]], slot: int) -> FormationPlanner:
        key = (tuple(tuple(float(x) for x in p) for p in points), int(slot))
        pl = self._planners.get(key)
        if pl is None:
            pl = FormationPlanner(self.params, np.array(key[0], dtype=np.float64), slot)
            self._planners = {key: pl}  # one formation at a time: drop the old ones
        return pl

    def plan(
        self,
        points: Sequence[tuple[float, float, float]],
        slot: int,
        t_start_s: float,
        start: tuple[np.ndarray, np.ndarray, np.ndarray],
        goal: np.ndarray,
        peers: Sequence[PeerTrajectory],
        field: object,
        previous: Trajectory | None,
    ) -> PlanResult:
        pl = self.planner(points, slot)
        p, v, a = start
        return pl.plan(t_start_s, p, v, a, goal, list(peers), field, previous)  # type: ignore[arg-type]


def warm_up(params: PlannerParams) -> float:
    """Plan a small formation problem once (numba's cache loaded, kernels hot); seconds taken."""
    import time

    from onboard.planner.field import AnalyticField
    from onboard.world import World

    t0 = time.perf_counter()
    formation = np.array([[0.0, -1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]])
    pl = FormationPlanner(params, formation, slot=1)
    start = np.array([0.0, 0.0, 1.0])
    peers = [PeerTrajectory(k, k, Trajectory.hover(start + formation[k], 0.0, 5.0)) for k in (0, 2)]
    z = np.zeros(3)
    pl.plan(0.0, start, z, z, np.array([3.0, 0.0, 1.0]), peers, AnalyticField(World.empty(0.0)))
    return time.perf_counter() - t0
