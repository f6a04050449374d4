"""Formation assignments made by the ground station: validation, slots, epochs, effective times.

A formation template (``config/formations/NAME.yaml`` or a user YAML/JSON file, ``points:
[[x, y, z], ...]``, slot k = row k) is *placed* at the swarm: centred on the centroid of the
drones' current positions, scaled by ``scale`` and turned by ``yaw`` about the up axis. Drones
get slots by the minimum total distance from their current positions to the placed points (the
Hungarian method, ``scipy.optimize.linear_sum_assignment``), which also holds mid-flight: a new
shape is taken with the least total travel and no two drones crossing needlessly. Without a
given yaw the turn is chosen too (:func:`best_yaw`): the one whose slots are nearest in total,
the template as written when no turn is nearer by more than a few centimetres a drone. The
shape metric (e_sim) and the planner's formation cost do not depend on the turn, so a swarm
re-shaping in flight should not travel for it: hexagon-7 to rectangle-7 as written is 8.25 m
of travel in all (1.58 m for one drone), turned by 30 (or 90) degrees 4.67 m (0.92 m).

Every assignment carries an *epoch* (strictly increasing; a drone accepts only epochs newer than
every one it knows, so it never flies two assignments at once) and an *effective time* (a common
global time in the near future at which every drone switches to it).

Validation happens before anything is sent: a bad formation raises :class:`FormationError`
naming the problem and no epoch is used up, so nothing changes in flight on an error.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from onboard.autopilot.frames import wrap_pi
from onboard.comm.wire import FormationAssignment
from onboard.config import ConfigError, Formation, load_formation

DEFAULT_MIN_SPACING_M = 0.8
"""Closest two placed formation points may be (after scale): about two drone diameters."""

YAW_GRID_STEP_DEG = 1.0
""":func:`best_yaw`'s grid over the full turn, before its refinement."""

YAW_TIE_M_PER_DRONE = 0.02
""":func:`best_yaw` takes totals within this many metres per drone of the least for a tie, and
of tied turns the one nearest to none: a symmetric shape fits as well at several turns, and
the drones' positions are known to centimetres (the demo's hexagon on the real stack fitted
0.01-0.1 m better turned by 60 degrees, the same points with the slots renamed)."""


class FormationError(ValueError):
    """A formation that cannot be assigned; the message names the problem."""


@dataclass(frozen=True, eq=False)
class Assignment:
    """One formation assignment, ready to send.

    name: the template's name; template: (N, 3) as in its file; scale, yaw_rad: how it was
    placed; center_m: where its centroid was placed (the swarm's centroid); points_m: (N, 3) the
    placed points (``center + Rz(yaw) * scale * (template - centroid(template))``), slot k = row
    k; slots: drone id -> slot; epoch; effective_s: common global switch time; cost_m: the total
    distance from the drones to their slots' placed points.
    """

    name: str
    template: np.ndarray
    scale: float
    yaw_rad: float
    center_m: np.ndarray
    points_m: np.ndarray
    slots: dict[int, int]
    epoch: int
    effective_s: float
    cost_m: float

    @property
    def offsets_m(self) -> np.ndarray:
        """(N, 3) the placed points minus their centroid (where each slot sits relative to the
        formation's centre; a goal is the centre)."""
        return self.points_m - self.points_m.mean(axis=0)

    def to_wire(self) -> FormationAssignment:
        """The wire action. The points go out already scaled and turned (about their centroid),
        with ``scale`` 1 and ``yaw_rad`` 0, so that every receiver flies the same shape whether
        or not it applies scale and yaw itself."""
        pts = self.offsets_m
        return FormationAssignment(
            points_m=[(float(p[0]), float(p[1]), float(p[2])) for p in pts],
            scale=1.0,
            yaw_rad=0.0,
            slots={int(d): int(s) for d, s in sorted(self.slots.items())},
            epoch=int(self.epoch),
            effective_s=float(self.effective_s),
        )

    def slot_positions(self) -> dict[int, np.ndarray]:
        """Drone id -> its placed point."""
        return {d: self.points_m[s] for d, s in self.slots.items()}


# --- templates -------------------------------------------------------------------------------


def load_template(name_or_path: str | Path) -> Formation:
    """A formation template by name (``config/formations``) or file; every failure (unknown
    name, unreadable file, bad content) is a :class:`FormationError` naming it."""
    try:
        return load_formation(name_or_path)
    except ConfigError as e:
        raise FormationError(f"formation {str(name_or_path)!r}: {e}") from e
    except (OSError, ValueError) as e:  # a directory, bad encoding, ...
        raise FormationError(f"formation {str(name_or_path)!r}: cannot read: {e}") from e


def rotation_z(yaw_rad: float) -> np.ndarray:
    """The rotation by ``yaw_rad`` about the up (z) axis, (3, 3)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def place(
    template: np.ndarray, center_m: Sequence[float] | np.ndarray, scale: float, yaw_rad: float
) -> np.ndarray:
    """(N, 3): the template's centroid moved to ``center_m``, scaled, turned by ``yaw_rad``."""
    t = np.asarray(template, dtype=np.float64)
    c = np.asarray(center_m, dtype=np.float64).reshape(3)
    return c + (scale * (t - t.mean(axis=0))) @ rotation_z(yaw_rad).T


def check_points(
    points: np.ndarray, n_drones: int | None, min_spacing_m: float, name: str = "formation"
) -> None:
    """Raise :class:`FormationError` unless ``points`` is (n_drones, 3), finite and no two
    points are closer than ``min_spacing_m``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise FormationError(f"{name}: points must be an (N, 3) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        rows = sorted({int(i) for i in np.argwhere(~np.isfinite(p))[:, 0]})
        raise FormationError(f"{name}: points {rows} are not finite (NaN or infinite)")
    n = p.shape[0]
    if n_drones is not None and n != n_drones:
        raise FormationError(
            f"{name}: has {n} points but {n_drones} drones are to fly it "
            "(pick the drones with --drones, or a formation of that size)"
        )
    if n < 2:
        raise FormationError(f"{name}: needs at least 2 points, got {n}")
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    d[np.diag_indices(n)] = np.inf
    k = int(np.argmin(d))
    i, j = divmod(k, n)
    if d[i, j] < min_spacing_m:
        what = "coincide" if d[i, j] < 1e-9 else f"are {d[i, j]:.3f} m apart"
        raise FormationError(
            f"{name}: points {min(i, j)} and {max(i, j)} {what}, closer than the drone spacing "
            f"{min_spacing_m:g} m (after scale)"
        )


# --- slots -----------------------------------------------------------------------------------


def distance_matrix(positions: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(N, M) Euclidean distances from each position to each target."""
    a = np.asarray(positions, dtype=np.float64)
    b = np.asarray(targets, dtype=np.float64)
    return np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)


def hungarian_slots(positions: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, float]:
    """The slot of each position (row i -> ``slots[i]``) that minimises the total distance, and
    that total. ``positions`` (N, 3), ``targets`` (N, 3)."""
    cost = distance_matrix(positions, targets)
    if cost.shape[0] != cost.shape[1]:
        raise FormationError(f"{cost.shape[0]} drones for {cost.shape[1]} slots")
    rows, cols = linear_sum_assignment(cost)
    slots = np.empty(cost.shape[0], dtype=np.int64)
    slots[rows] = cols
    return slots, float(cost[rows, cols].sum())


def best_yaw(
    template: np.ndarray,
    positions: np.ndarray,
    center_m: Sequence[float] | np.ndarray,
    scale: float,
) -> float:
    """The turn (rad, in (-pi, pi]) of ``template`` placed at ``center_m`` and scaled by
    ``scale`` (:func:`place`) whose slots are nearest ``positions`` (N, 3) in total distance
    (:func:`hungarian_slots`).

    Every whole degree is tried, the best refined to within about 1e-4 rad (the total is
    piecewise smooth in the turn: smooth while the slots stay the same). Of the grid's local
    minima about as near as the least (within ``YAW_TIE_M_PER_DRONE`` a drone: a symmetric
    shape has several) the one nearest to no turn is refined, so a swarm that already stands in
    the template as written keeps it (exactly, when it stands there exactly)."""
    from scipy.optimize import minimize_scalar

    pos = np.asarray(positions, dtype=np.float64)

    def total(yaw: float) -> float:
        return hungarian_slots(pos, place(template, center_m, scale, yaw))[1]

    n = int(round(360.0 / YAW_GRID_STEP_DEG))
    grid = [math.radians(k * YAW_GRID_STEP_DEG) for k in range(n)]
    totals = np.array([total(y) for y in grid])
    # the grid's local minima (on the circle), each the bottom of its own basin
    low = (totals <= np.roll(totals, 1)) & (totals <= np.roll(totals, -1))
    near = np.flatnonzero(low & (totals <= totals.min() + YAW_TIE_M_PER_DRONE * len(pos)))
    k = min(near, key=lambda j: (abs(wrap_pi(grid[j])), grid[j]))
    y0, f0 = grid[k], float(totals[k])
    h = math.radians(YAW_GRID_STEP_DEG)
    r = minimize_scalar(total, bounds=(y0 - h, y0 + h), method="bounded", options={"xatol": 1e-4})
    if bool(r.success) and float(r.fun) < f0 - 1e-9:
        return wrap_pi(float(r.x))
    return wrap_pi(y0)


def brute_force_slots(positions: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, float]:
    """The same as :func:`hungarian_slots` by trying every permutation (for tests, N <= 8)."""
    cost = distance_matrix(positions, targets)
    n = cost.shape[0]
    best: tuple[float, tuple[int, ...]] = (math.inf, ())
    for perm in itertools.permutations(range(n)):
        total = float(cost[np.arange(n), list(perm)].sum())
        if total < best[0]:
            best = (total, perm)
    return np.asarray(best[1], dtype=np.int64), best[0]


# --- the assigner ----------------------------------------------------------------------------


class FormationAssigner:
    """Makes validated assignments with strictly increasing epochs.

    clock: global time (s); lead_s: how far ahead of now the effective time lies (long enough
    for every drone to hear and acknowledge the command); min_spacing_m: see
    :func:`check_points`. Epochs start from the clock in milliseconds, so that a restarted ground
    station still issues epochs newer than the ones the drones know; :meth:`observe_epoch` lifts
    the counter above an epoch seen on the bus (drones report theirs in their state).
    """

    def __init__(
        self,
        clock: Callable[[], float] = time.time,
        lead_s: float = 1.5,
        min_spacing_m: float = DEFAULT_MIN_SPACING_M,
    ) -> None:
        if not (math.isfinite(lead_s) and lead_s >= 0.0):
            raise ValueError(f"lead_s must be >= 0, got {lead_s}")
        if not (math.isfinite(min_spacing_m) and min_spacing_m > 0.0):
            raise ValueError(f"min_spacing_m must be > 0, got {min_spacing_m}")
        self.clock = clock
        self.lead_s = float(lead_s)
        self.min_spacing_m = float(min_spacing_m)
        self._last_epoch = int(clock() * 1000.0)
        self.last: Assignment | None = None

    @property
    def last_epoch(self) -> int:
        return self._last_epoch

    def observe_epoch(self, epoch: int) -> None:
        """An epoch seen elsewhere (a drone's state, another ground station's command)."""
        self._last_epoch = max(self._last_epoch, int(epoch))

    def _next_epoch(self) -> int:
        self._last_epoch = max(self._last_epoch + 1, int(self.clock() * 1000.0))
        return self._last_epoch

    def assign(
        self,
        formation: Formation | str | Path,
        positions: Mapping[int, Sequence[float] | np.ndarray],
        *,
        scale: float = 1.0,
        yaw_rad: float | None = 0.0,
        drones: Sequence[int] | None = None,
        center_m: Sequence[float] | np.ndarray | None = None,
    ) -> Assignment:
        """Validate and assign ``formation`` to the drones at ``positions`` (drone id -> ENU
        position; every drone that is up). ``drones`` picks a subset (their number must equal
        the formation's); ``center_m`` places the formation elsewhere than at their centroid;
        ``yaw_rad`` None turns it the way that is nearest in total (:func:`best_yaw`).
        Raises :class:`FormationError` (no epoch used) on any problem."""
        tpl = formation if isinstance(formation, Formation) else load_template(formation)
        name = tpl.name
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0.0):
            raise FormationError(f"{name}: scale must be a positive finite number, got {scale}")
        if yaw_rad is not None and not math.isfinite(yaw_rad):
            raise FormationError(f"{name}: yaw must be finite, got {yaw_rad}")
        if drones is not None:
            ids = [int(d) for d in drones]
            if len(set(ids)) != len(ids):
                raise FormationError(f"{name}: --drones {ids} names a drone twice")
            unknown = sorted(set(ids) - set(positions))
            if unknown:
                raise FormationError(
                    f"{name}: drones {unknown} are not up (up: {sorted(positions)})"
                )
        else:
            ids = sorted(int(d) for d in positions)
        if not ids:
            raise FormationError(f"{name}: no drones to assign (none is up)")
        pos = np.array([np.asarray(positions[d], dtype=np.float64).reshape(3) for d in ids])
        bad = [d for d, p in zip(ids, pos, strict=True) if not np.all(np.isfinite(p))]
        if bad:
            raise FormationError(f"{name}: positions of drones {bad} are not finite")
        check_points(tpl.points, len(ids), 0.0, name)
        center = pos.mean(axis=0) if center_m is None else np.asarray(center_m, dtype=np.float64)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise FormationError(f"{name}: centre {center_m} is not a finite 3-vector")
        if yaw_rad is None:
            yaw_rad = best_yaw(tpl.points, pos, center, float(scale))
        placed = place(tpl.points, center, float(scale), float(yaw_rad))
        check_points(placed, len(ids), self.min_spacing_m, name)
        slot_of_row, cost = hungarian_slots(pos, placed)
        a = Assignment(
            name=name,
            template=np.array(tpl.points),
            scale=float(scale),
            yaw_rad=float(yaw_rad),
            center_m=center,
            points_m=placed,
            slots={d: int(s) for d, s in zip(ids, slot_of_row, strict=True)},
            epoch=self._next_epoch(),
            effective_s=float(self.clock()) + self.lead_s,
            cost_m=cost,
        )
        self.last = a
        return a


def formation_errors(
    positions: Mapping[int, Sequence[float] | np.ndarray],
    slots: Mapping[int, int],
    points: np.ndarray,
) -> tuple[float, float] | None:
    """(e_dist [m], e_sim) of the drones in ``slots`` (drone id -> row of ``points``) against the
    formation ``points``; None when fewer than 2 of them have a position."""
    from gcs.metrics import e_dist
    from onboard.planner.formation import similarity

    ids = [d for d in sorted(slots) if d in positions]
    if len(ids) < 2:
        return None
    cur = np.array([np.asarray(positions[d], dtype=np.float64).reshape(3) for d in ids])
    want = np.asarray(points, dtype=np.float64)[[slots[d] for d in ids]]
    if not np.all(np.isfinite(cur)):
        return None
    return e_dist(cur, want), float(similarity(cur, want)[0])


def per_drone_errors(
    positions: Mapping[int, Sequence[float] | np.ndarray],
    slots: Mapping[int, int],
    points: np.ndarray,
) -> dict[int, float]:
    """Each drone's distance [m] from its slot after the best Sim(3) alignment of the swarm onto
    the formation (the terms of e_dist); empty when fewer than 2 drones have a position."""
    from gcs.metrics import umeyama

    ids = [d for d in sorted(slots) if d in positions]
    if len(ids) < 2:
        return {}
    cur = np.array([np.asarray(positions[d], dtype=np.float64).reshape(3) for d in ids])
    if not np.all(np.isfinite(cur)):
        return {}
    want = np.asarray(points, dtype=np.float64)[[slots[d] for d in ids]]
    s, R, t = umeyama(cur, want)
    r = np.linalg.norm(want - (s * cur @ R.T + t), axis=1)
    return {d: float(x) for d, x in zip(ids, r, strict=True)}
