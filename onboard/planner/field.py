"""Distance fields for the planner's obstacle cost J_o (paper Sec. IV, the ESDF term).

The compiled objective needs one numba kernel for every kind of field, so a field hands the
objective its "kernel data" (``FieldData``) and the objective calls ``field_eval`` with it:

- ``FIELD_GRID``: a signed-distance grid (an ESDF from the mapping pipeline, or a sampled
  function), values at cell centres ``origin + (i + 0.5) * res``, trilinearly interpolated;
- ``FIELD_PRIMITIVES``: the exact distance to a ``World``'s primitives (ground truth).

All arrays in a ``FieldData`` are C-contiguous, read-only float64 with fixed ndim, so the
objective compiles one specialisation for both kinds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from onboard.world import World, primitives_distance

FIELD_GRID = 0
FIELD_PRIMITIVES = 1
UNKNOWN_DISTANCE = 10.0  # metres reported outside a grid: unknown space is free for the optimiser


@njit(cache=True, nogil=True)
def _axis_weights(f: float, n: int) -> tuple[int, int, float, float]:
    """Interpolation along one axis at continuous centre index f: (i0, i1, t, dt/df).

    Between the first and last cell centres: linear; in the outer half cells: clamped to the
    boundary value (derivative 0).
    """
    if n == 1:
        return 0, 0, 0.0, 0.0
    if f <= 0.0:
        return 0, 1, 0.0, 0.0
    if f >= n - 1:
        return n - 2, n - 1, 1.0, 0.0
    i0 = int(math.floor(f))
    if i0 > n - 2:
        i0 = n - 2
    return i0, i0 + 1, f - i0, 1.0


@njit(cache=True, nogil=True)
def grid_eval(
    grid: np.ndarray, origin: np.ndarray, res: float, x: float, y: float, z: float
) -> tuple[float, float, float, float]:
    """Trilinear interpolation of grid (nx, ny, nz) and the exact gradient of the interpolant.

    Cell (i, j, k) holds the signed distance at ``origin + ((i, j, k) + 0.5) * res``. Points
    outside the grid box ``[origin, origin + n * res]`` give ``(UNKNOWN_DISTANCE, 0, 0, 0)``.
    """
    nx = grid.shape[0]
    ny = grid.shape[1]
    nz = grid.shape[2]
    fx = (x - origin[0]) / res
    fy = (y - origin[1]) / res
    fz = (z - origin[2]) / res
    if not (0.0 <= fx <= nx and 0.0 <= fy <= ny and 0.0 <= fz <= nz):
        return UNKNOWN_DISTANCE, 0.0, 0.0, 0.0
    i0, i1, tx, sx = _axis_weights(fx - 0.5, nx)
    j0, j1, ty, sy = _axis_weights(fy - 0.5, ny)
    k0, k1, tz, sz = _axis_weights(fz - 0.5, nz)
    c000 = grid[i0, j0, k0]
    c100 = grid[i1, j0, k0]
    c010 = grid[i0, j1, k0]
    c110 = grid[i1, j1, k0]
    c001 = grid[i0, j0, k1]
    c101 = grid[i1, j0, k1]
    c011 = grid[i0, j1, k1]
    c111 = grid[i1, j1, k1]
    # interpolate along x, then y, then z
    c00 = c000 + tx * (c100 - c000)
    c10 = c010 + tx * (c110 - c010)
    c01 = c001 + tx * (c101 - c001)
    c11 = c011 + tx * (c111 - c011)
    c0 = c00 + ty * (c10 - c00)
    c1 = c01 + ty * (c11 - c01)
    d = c0 + tz * (c1 - c0)
    # derivatives of the interpolant with respect to tx, ty, tz
    dx0 = (c100 - c000) + ty * ((c110 - c010) - (c100 - c000))
    dx1 = (c101 - c001) + ty * ((c111 - c011) - (c101 - c001))
    ddx = dx0 + tz * (dx1 - dx0)
    ddy = (c10 - c00) + tz * ((c11 - c01) - (c10 - c00))
    ddz = c1 - c0
    inv = 1.0 / res
    return d, ddx * sx * inv, ddy * sy * inv, ddz * sz * inv


@njit(cache=True, nogil=True)
def field_eval(
    kind: int,
    grid: np.ndarray,
    origin: np.ndarray,
    res: float,
    cylinders: np.ndarray,
    rings: np.ndarray,
    boxes: np.ndarray,
    ground_z: float,
    x: float,
    y: float,
    z: float,
) -> tuple[float, float, float, float]:
    """Signed distance d and its gradient (gx, gy, gz) at (x, y, z): the d of J_o.

    kind FIELD_GRID: ``grid_eval(grid (nx, ny, nz), origin (3,), res)``; kind FIELD_PRIMITIVES:
    ``primitives_distance(cylinders (K, 5), rings (R, 7), boxes (B, 6), ground_z)`` (NaN: no
    ground). The members of the other kind are ignored.
    """
    if kind == FIELD_GRID:
        return grid_eval(grid, origin, res, x, y, z)
    return primitives_distance(cylinders, rings, boxes, ground_z, x, y, z)


@njit(cache=True, nogil=True)
def field_eval_many(
    kind: int,
    grid: np.ndarray,
    origin: np.ndarray,
    res: float,
    cylinders: np.ndarray,
    rings: np.ndarray,
    boxes: np.ndarray,
    ground_z: float,
    points: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``field_eval`` at each row of points (K, 3): d (K,), grad (K, 3)."""
    n = points.shape[0]
    d = np.empty(n)
    g = np.empty((n, 3))
    for i in range(n):
        d[i], g[i, 0], g[i, 1], g[i, 2] = field_eval(
            kind,
            grid,
            origin,
            res,
            cylinders,
            rings,
            boxes,
            ground_z,
            points[i, 0],
            points[i, 1],
            points[i, 2],
        )
    return d, g


def _frozen(a: np.ndarray) -> np.ndarray:
    """A read-only C-contiguous float64 array with a's values (a itself if it is one)."""
    if a.dtype == np.float64 and a.flags.c_contiguous and not a.flags.writeable:
        return a
    out = np.array(a, dtype=np.float64, order="C", copy=True)
    out.setflags(write=False)
    return out


_NO_GRID = _frozen(np.zeros((1, 1, 1)))
_NO_ORIGIN = _frozen(np.zeros(3))
_NO_CYLINDERS = _frozen(np.zeros((0, 5)))
_NO_RINGS = _frozen(np.zeros((0, 7)))
_NO_BOXES = _frozen(np.zeros((0, 6)))


class FieldData(NamedTuple):
    """Arguments of ``field_eval`` after x, y, z, in order; unused members are small empties.

    grid (nx, ny, nz), origin (3,), res (m), cylinders (K, 5), rings (R, 7), boxes (B, 6),
    ground_z (NaN when absent). Arrays are C-contiguous read-only float64.
    """

    kind: int
    grid: np.ndarray
    origin: np.ndarray
    res: float
    cylinders: np.ndarray
    rings: np.ndarray
    boxes: np.ndarray
    ground_z: float


def _check_points(points: np.ndarray) -> np.ndarray:
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (K, 3), got {p.shape}")
    return p


def eval_field_data(data: FieldData, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``field_eval`` of kernel data at points (K, 3): d (K,), grad (K, 3)."""
    return field_eval_many(*data, _check_points(points))


class DistanceField(Protocol):
    """What the planner needs from an obstacle map."""

    def distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (K,) and gradient (K, 3) at points (K, 3)."""
        ...

    def kernel_data(self) -> FieldData:
        """Arguments for ``field_eval`` in the compiled objective."""
        ...

    def is_known(self, points: np.ndarray) -> np.ndarray:
        """Bool (K,): False where the field has no information."""
        ...


class AnalyticField:
    """The exact distance field of a ``World`` (ground truth); known everywhere."""

    def __init__(self, world: World) -> None:
        self.world = world
        self._data = FieldData(
            FIELD_PRIMITIVES,
            _NO_GRID,
            _NO_ORIGIN,
            1.0,
            _frozen(world.cylinders),
            _frozen(world.rings),
            _frozen(world.boxes),
            world.ground_z_or_nan,
        )

    def distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return eval_field_data(self._data, points)

    def kernel_data(self) -> FieldData:
        return self._data

    def is_known(self, points: np.ndarray) -> np.ndarray:
        return np.ones(_check_points(points).shape[0], dtype=bool)


class GridField:
    """A signed-distance grid: values (nx, ny, nz) at cell centres ``origin + (i + 0.5) * res``.

    known: optional bool mask of the same shape (False: unobserved cell). Values of unknown
    cells are used as they are by the kernel, so a producer should fill them with something
    the optimiser may treat as free (e.g. ``UNKNOWN_DISTANCE``). Outside the grid box the field
    is ``UNKNOWN_DISTANCE`` with zero gradient and unknown.
    """

    def __init__(
        self,
        values: np.ndarray,
        origin: np.ndarray,
        res: float,
        known: np.ndarray | None = None,
        *,
        adopt: bool = False,
    ) -> None:
        """``adopt``: (for producers that guarantee it, e.g. the ESDF builder) the values are a
        finite read-only float64 C-contiguous array and ``known`` a read-only bool array of
        the same shape, taken as they are: no copy, no finiteness pass."""
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 3 or min(v.shape) < 1:
            raise ValueError(f"GridField values must have shape (nx, ny, nz), got {v.shape}")
        if adopt:
            if v.flags.writeable or not v.flags.c_contiguous:
                raise ValueError("adopted GridField values must be read-only and C-contiguous")
        elif not np.all(np.isfinite(v)):
            raise ValueError("GridField values must be finite")
        o = np.asarray(origin, dtype=np.float64).reshape(-1)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise ValueError(f"GridField origin must be 3 finite numbers, got {origin!r}")
        if not (math.isfinite(res) and res > 0.0):
            raise ValueError(f"GridField res must be > 0, got {res}")
        if known is not None:
            if adopt and known.dtype == np.bool_ and not known.flags.writeable:
                k = known
            else:
                k = np.array(known, dtype=bool, copy=True)
            if k.shape != v.shape:
                raise ValueError(f"known mask shape {k.shape} differs from values {v.shape}")
            k.setflags(write=False)
        else:
            k = None
        self.values = _frozen(v)
        self.origin = _frozen(o)
        self.res = float(res)
        self.known = k
        self._data = FieldData(
            FIELD_GRID,
            self.values,
            self.origin,
            self.res,
            _NO_CYLINDERS,
            _NO_RINGS,
            _NO_BOXES,
            math.nan,
        )

    @property
    def shape(self) -> tuple[int, int, int]:
        nx, ny, nz = self.values.shape
        return int(nx), int(ny), int(nz)

    @property
    def upper(self) -> np.ndarray:
        """Upper corner of the grid box, ``origin + shape * res``."""
        return self.origin + np.array(self.shape) * self.res

    def cell_centres(self) -> np.ndarray:
        """Centres of all cells, (nx, ny, nz, 3)."""
        axes = [self.origin[a] + (np.arange(n) + 0.5) * self.res for a, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return eval_field_data(self._data, points)

    def kernel_data(self) -> FieldData:
        return self._data

    def is_known(self, points: np.ndarray) -> np.ndarray:
        p = _check_points(points)
        f = (p - self.origin) / self.res
        n = np.array(self.shape)
        inside = np.all((f >= 0.0) & (f <= n), axis=1)
        if self.known is None:
            return inside
        idx = np.clip(np.floor(f[inside]).astype(np.int64), 0, n - 1)
        out = inside.copy()
        out[inside] = self.known[idx[:, 0], idx[:, 1], idx[:, 2]]
        return out

    @staticmethod
    def from_function(
        fn: Callable[[np.ndarray], np.ndarray | tuple[np.ndarray, np.ndarray]],
        lo: ArrayLike,
        hi: ArrayLike,
        res: float,
    ) -> GridField:
        """Sample ``fn`` (points (K, 3) -> d (K,) or (d, grad)) at the cell centres of a grid.

        The grid starts at ``lo`` and has ``ceil((hi - lo) / res)`` cells per axis (at least 1),
        so its box covers ``[lo, hi]``.
        """
        lo_a = np.asarray(lo, dtype=np.float64).reshape(3)
        hi_a = np.asarray(hi, dtype=np.float64).reshape(3)
        if not np.all(hi_a > lo_a):
            raise ValueError("from_function: hi must exceed lo on every axis")
        shape = np.maximum(np.ceil((hi_a - lo_a) / res - 1e-9).astype(np.int64), 1)
        axes = [lo_a[a] + (np.arange(shape[a]) + 0.5) * res for a in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        out = fn(pts)
        d = out[0] if isinstance(out, tuple) else out
        return GridField(np.asarray(d, dtype=np.float64).reshape(tuple(shape)), lo_a, res)
