"""Grid A* for an initial path when the straight line from start to goal is blocked.

The path seeds the trajectory optimisation (the paper's planner starts from a collision-free
guide path when the straight line crosses obstacles); it is not itself the flown trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from onboard.planner.field import DistanceField

ASTAR_FOUND = 0
ASTAR_NO_PATH = 1
ASTAR_LIMIT = 2
_MAX_NODES = 50_000_000


@njit(cache=True, nogil=True)
def _heap_push(
    keys: np.ndarray, vals: np.ndarray, size: int, key: float, val: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """Push onto a binary min-heap stored in (keys, vals)[:size]; grows the arrays when full."""
    if size == keys.shape[0]:
        nk = np.empty(2 * size)
        nv = np.empty(2 * size, dtype=np.int64)
        nk[:size] = keys
        nv[:size] = vals
        keys = nk
        vals = nv
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if keys[parent] <= key:
            break
        keys[i] = keys[parent]
        vals[i] = vals[parent]
        i = parent
    keys[i] = key
    vals[i] = val
    return keys, vals, size + 1


@njit(cache=True, nogil=True)
def _heap_pop(keys: np.ndarray, vals: np.ndarray, size: int) -> tuple[int, int]:
    """Pop the minimum of a binary min-heap of ``size`` entries: (value, new size)."""
    top = vals[0]
    size -= 1
    key = keys[size]
    val = vals[size]
    i = 0
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        if child + 1 < size and keys[child + 1] < keys[child]:
            child += 1
        if keys[child] >= key:
            break
        keys[i] = keys[child]
        vals[i] = vals[child]
        i = child
    if size > 0:
        keys[i] = key
        vals[i] = val
    return top, size


_SQRT2 = math.sqrt(2.0)
_SQRT3 = math.sqrt(3.0)


@njit(cache=True, nogil=True)
def octile_distance(a: int, b: int, c: int) -> float:
    """Shortest 26-connected path length (in cells) over a free grid for offset (a, b, c).

    As many 3-D diagonal steps as the smallest |offset|, then 2-D diagonals, then straight
    steps. It never exceeds the true path cost on any grid (admissible) and is consistent.
    """
    a = abs(a)
    b = abs(b)
    c = abs(c)
    small = min(a, b, c)
    big = max(a, b, c)
    mid = a + b + c - small - big
    return (_SQRT3 - _SQRT2) * small + (_SQRT2 - 1.0) * mid + big


@njit(cache=True, nogil=True)
def astar_grid(
    occupied: np.ndarray, start: np.ndarray, goal: np.ndarray, max_expansions: int
) -> tuple[np.ndarray, int]:
    """A* on a 26-connected grid, step cost = Euclidean length of the step in cells.

    occupied: (nx, ny, nz) bool; start, goal: (3,) int64 free cells. Heuristic: the octile
    distance to the goal (the exact free-grid cost; tighter than the Euclidean distance, which
    it bounds from above, so about half as many nodes are expanded in a forest). Returns
    (cells (K, 3) int64 from start to goal, status ASTAR_FOUND / ASTAR_NO_PATH / ASTAR_LIMIT);
    cells is empty unless found.
    """
    nx, ny, nz = occupied.shape
    n = nx * ny * nz
    g = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    closed = np.zeros(n, dtype=np.bool_)
    offs = np.empty((26, 3), dtype=np.int64)
    cost = np.empty(26)
    m = 0
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                if a == 0 and b == 0 and c == 0:
                    continue
                offs[m, 0] = a
                offs[m, 1] = b
                offs[m, 2] = c
                cost[m] = math.sqrt(a * a + b * b + c * c)
                m += 1
    gx, gy, gz = goal[0], goal[1], goal[2]
    s = (start[0] * ny + start[1]) * nz + start[2]
    t = (gx * ny + gy) * nz + gz
    keys = np.empty(1024)
    vals = np.empty(1024, dtype=np.int64)
    g[s] = 0.0
    h0 = octile_distance(start[0] - gx, start[1] - gy, start[2] - gz)
    keys, vals, size = _heap_push(keys, vals, 0, h0, s)
    expansions = 0
    status = ASTAR_NO_PATH
    while size > 0:
        cur, size = _heap_pop(keys, vals, size)
        if closed[cur]:
            continue
        if cur == t:
            status = ASTAR_FOUND
            break
        closed[cur] = True
        expansions += 1
        if expansions > max_expansions:
            status = ASTAR_LIMIT
            break
        ci = cur // (ny * nz)
        cj = (cur // nz) % ny
        ck = cur % nz
        gc = g[cur]
        for m in range(26):
            i = ci + offs[m, 0]
            j = cj + offs[m, 1]
            k = ck + offs[m, 2]
            if i < 0 or i >= nx or j < 0 or j >= ny or k < 0 or k >= nz:
                continue
            if occupied[i, j, k]:
                continue
            nb = (i * ny + j) * nz + k
            if closed[nb]:
                continue
            ng = gc + cost[m]
            if ng < g[nb]:
                g[nb] = ng
                parent[nb] = cur
                h = octile_distance(i - gx, j - gy, k - gz)
                keys, vals, size = _heap_push(keys, vals, size, ng + h, nb)
    if status != ASTAR_FOUND:
        return np.empty((0, 3), dtype=np.int64), status
    count = 1
    cur = t
    while cur != s:
        cur = parent[cur]
        count += 1
    cells = np.empty((count, 3), dtype=np.int64)
    cur = t
    for q in range(count - 1, -1, -1):
        cells[q, 0] = cur // (ny * nz)
        cells[q, 1] = (cur // nz) % ny
        cells[q, 2] = cur % nz
        cur = parent[cur]
    return cells, ASTAR_FOUND


def segment_is_free(
    field: DistanceField, a: np.ndarray, b: np.ndarray, clearance_m: float, step_m: float = 0.05
) -> bool:
    """True when the field distance is >= clearance_m at samples every <= step_m along a-b.

    The samples include both ends; between samples the distance can dip by at most step_m / 2.
    """
    pa = np.asarray(a, dtype=np.float64).reshape(3)
    pb = np.asarray(b, dtype=np.float64).reshape(3)
    n = max(1, math.ceil(float(np.linalg.norm(pb - pa)) / step_m))
    s = np.linspace(0.0, 1.0, n + 1)[:, None]
    d, _ = field.distance(pa + s * (pb - pa))
    return bool(np.all(d >= clearance_m))


def _nearest_free(occupied: np.ndarray, f: np.ndarray) -> np.ndarray | None:
    """The free cell nearest (Euclidean, in cells) to continuous index f (3,), None if none."""
    n = np.array(occupied.shape)
    cell = np.clip(np.rint(f).astype(np.int64), 0, n - 1)
    if not occupied[tuple(cell)]:
        return cell
    free = np.argwhere(~occupied)
    if free.shape[0] == 0:
        return None
    return free[np.argmin(np.sum((free - f) ** 2, axis=1))].astype(np.int64)


def _drop_collinear(cells: np.ndarray) -> np.ndarray:
    """Keep the first and last cells and those where the step direction changes."""
    if cells.shape[0] <= 2:
        return cells
    steps = np.diff(cells, axis=0)
    turn = np.any(steps[1:] != steps[:-1], axis=1)
    keep = np.concatenate([[True], turn, [True]])
    return cells[keep]


def _shortcut(field: DistanceField, pts: np.ndarray, clearance_m: float) -> np.ndarray:
    """Greedy line-of-sight simplification: from each kept point jump to the last point of the
    run of points visible from it (segment_is_free), or to the next one when none is."""
    out = [pts[0]]
    i = 0
    n = pts.shape[0]
    while i < n - 1:
        j = i + 1
        while j + 1 < n and segment_is_free(field, pts[i], pts[j + 1], clearance_m):
            j += 1
        out.append(pts[j])
        i = j
    return np.array(out)


def astar_path(
    field: DistanceField,
    start: np.ndarray,
    goal: np.ndarray,
    clearance_m: float,
    resolution_m: float = 0.2,
    margin_m: float = 3.0,
    z_limits: tuple[float, float] | None = None,
    max_expansions: int = 200_000,
) -> np.ndarray | None:
    """A guide path from start to goal keeping about clearance_m from obstacles, or None.

    Grid nodes every resolution_m over the box spanned by start and goal grown by margin_m (its
    z range intersected with z_limits when given; z_limits alone if they do not overlap); a node
    is occupied where ``field.distance < clearance_m`` (unknown space counts as the field
    reports it). A* runs from the free node nearest the start to the free node nearest the goal.
    Returns (K, 3) points: the exact start, the turning nodes left after a greedy line-of-sight
    shortcut (``segment_is_free`` at clearance_m), the exact goal. Each segment either passes
    ``segment_is_free(clearance_m)`` or is a straight run of grid steps between free nodes, which
    keeps at least ``clearance_m - resolution_m * sqrt(3) / 2`` (1-Lipschitz distance; in
    practice a few millimetres below clearance_m where the run grazes a curved obstacle). The
    first/last segment starts inside the clearance zone if start/goal lie in it.
    start and goal at the same node: ``[start, goal]``. None: no path, or more than
    max_expansions nodes expanded.
    """
    return astar_path_levels(
        field, start, goal, (clearance_m,), resolution_m, margin_m, z_limits, max_expansions
    )[0]


def astar_path_levels(
    field: DistanceField,
    start: np.ndarray,
    goal: np.ndarray,
    clearances_m: Sequence[float],
    resolution_m: float = 0.2,
    margin_m: float = 3.0,
    z_limits: tuple[float, float] | None = None,
    max_expansions: int = 200_000,
) -> tuple[np.ndarray | None, float]:
    """``astar_path`` at each of ``clearances_m`` in turn until one finds a path (the field is
    sampled on the grid once): (path, the clearance it keeps), or (None, NaN) when none does.
    max_expansions bounds each search."""
    p0 = np.asarray(start, dtype=np.float64).reshape(3)
    p1 = np.asarray(goal, dtype=np.float64).reshape(3)
    if resolution_m <= 0.0 or margin_m < 0.0:
        raise ValueError("resolution_m must be > 0 and margin_m >= 0")
    lo = np.minimum(p0, p1) - margin_m
    hi = np.maximum(p0, p1) + margin_m
    if z_limits is not None:
        zl, zh = float(z_limits[0]), float(z_limits[1])
        if zh < zl:
            raise ValueError(f"z_limits must be increasing, got {z_limits}")
        if max(lo[2], zl) <= min(hi[2], zh):
            lo[2], hi[2] = max(lo[2], zl), min(hi[2], zh)
        else:
            lo[2], hi[2] = zl, zh
    shape = np.floor((hi - lo) / resolution_m + 1e-9).astype(np.int64) + 1
    if int(np.prod(shape)) > _MAX_NODES:
        raise ValueError(f"A* grid {tuple(shape)} too large; use a coarser resolution_m")
    axes = [lo[a] + np.arange(shape[a]) * resolution_m for a in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d, _ = field.distance(nodes)
    d = d.reshape(tuple(shape))
    for clearance_m in clearances_m:
        occupied = d < clearance_m
        s = _nearest_free(occupied, (p0 - lo) / resolution_m)
        t = _nearest_free(occupied, (p1 - lo) / resolution_m)
        if s is None or t is None:
            continue
        if np.array_equal(s, t):
            return np.stack([p0, p1]), float(clearance_m)
        cells, status = astar_grid(occupied, s, t, int(max_expansions))
        if status != ASTAR_FOUND:
            continue
        turning = lo + _drop_collinear(cells) * resolution_m
        pts = np.concatenate([p0[None], turning, p1[None]])
        return _shortcut(field, pts, clearance_m), float(clearance_m)
    return None, math.nan
