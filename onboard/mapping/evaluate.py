"""Ground truth for the mapping pipeline: ESDF error against the exact distance, in observed
space.

A cell of the map counts as "observed space" when it is known (observed free or occupied),
its exact distance to the world lies within a band (the distances the planner acts on), and the
nearest point of the world's surfaces to it was itself seen: it projects into one of the given
depth frames within the valid depth range, on a pixel the mapper used, whose depth agrees with it
to within ``tol_m``. Distances to surfaces no frame saw (hidden backs of trunks, space outside
the field of view) are not something the map can know, and are left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from onboard.mapping.camera import DepthFrame
from onboard.mapping.esdf import EsdfField
from onboard.world import World


def seen_in_frames(
    points: np.ndarray,
    frames: Sequence[DepthFrame],
    step: int,
    tol_m: float,
    max_range_m: float = np.inf,
) -> np.ndarray:
    """Bool (K,): the point was measured (within tol_m of the depth) by some frame, on its
    every-``step``-th pixel grid, within the frame's valid depth range and within
    ``max_range_m`` of the camera (the mapper's ray length)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    seen = np.zeros(p.shape[0], dtype=bool)
    for f in frames:
        intr = f.intrinsics
        q = (p - f.position) @ f.rotation  # camera coordinates, (K, 3)
        z = q[:, 2]
        ok = (z >= intr.min_depth_m) & (z <= intr.max_depth_m) & ~seen
        ok &= np.einsum("ij,ij->i", q, q) <= max_range_m**2
        if not np.any(ok):
            continue
        idx = np.flatnonzero(ok)
        u = np.rint((intr.fx * q[idx, 0] / z[idx] + intr.cx) / step).astype(np.int64) * step
        v = np.rint((intr.fy * q[idx, 1] / z[idx] + intr.cy) / step).astype(np.int64) * step
        inside = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        idx, u, v = idx[inside], u[inside], v[inside]
        d = f.depth_m[v, u].astype(np.float64)
        hit = np.isfinite(d) & (d >= intr.min_depth_m) & (np.abs(d - z[idx]) <= tol_m)
        seen[idx[hit]] = True
    return seen


@dataclass(frozen=True, eq=False)
class EsdfErrors:
    """Signed errors (estimate - exact) at the observed cells, split by the cell's state."""

    free: np.ndarray
    occupied: np.ndarray

    @property
    def all(self) -> np.ndarray:
        return np.concatenate([self.free, self.occupied])


def esdf_errors(
    field: EsdfField,
    world: World,
    frames: Sequence[DepthFrame],
    step: int,
    band_m: float = 2.0,
    tol_m: float | None = None,
    max_range_m: float = np.inf,
) -> EsdfErrors:
    """Errors of the field's cell-centre values against ``world.distance`` in observed space
    (see the module docstring); tol_m defaults to one cell, max_range_m should be the mapper's
    ray length."""
    tol = field.res if tol_m is None else tol_m
    centres = field.cell_centres().reshape(-1, 3)
    known = field.known.reshape(-1) if field.known is not None else np.ones(len(centres), bool)
    cand = np.flatnonzero(known)
    exact, grad = world.distance(centres[cand])
    near = np.abs(exact) <= band_m
    cand, exact, grad = cand[near], exact[near], grad[near]
    surface = centres[cand] - exact[:, None] * grad
    seen = seen_in_frames(surface, frames, step, tol, max_range_m)
    cand, exact = cand[seen], exact[seen]
    err = field.values.reshape(-1)[cand] - exact
    occ = field.occupied.reshape(-1)[cand]
    return EsdfErrors(err[~occ], err[occ])
