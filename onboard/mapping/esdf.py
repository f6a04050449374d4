"""Signed Euclidean distance field (ESDF) of an occupancy window, as the planner's ``GridField``.

Exact Euclidean distance transform, separable (the lower envelope of parabolas of Felzenszwalb
and Huttenlocher, "Distance Transforms of Sampled Functions"): a linear scan along z, then the
envelope along y and along x. Two transforms per refresh: from every cell to the nearest occupied
cell (outside, carrying the index of that cell along: a feature transform) and from every
occupied cell to the nearest non-occupied cell (inside); signed distance = outside - inside.
Unknown cells count as free here, so the optimiser sees the distance to the nearest *known*
obstacle everywhere (unknown space is free for it); the field's ``known`` mask tells the
collision check which cells were observed. The exception is the shadow of an obstacle: unknown
cells within ``OccupancyParams.occluded_fill_m`` of an occupied cell of their layer, behind a
hit along its ray by default, count as occupied (``fill_occluded``; still unknown in
``known``), so that the side of a trunk the camera never faced is not free space right beside
the side it saw.

Values sit at cell centres and are refined below the cell size (``sub_cell``, the default):
every occupied cell remembers the mean of the measured surface points that fell into it, so a
free cell's value is its distance to the surface point of its nearest occupied cell, and a
surface cell's value is the signed offset of its centre from its own surface point along the
direction of its observed free neighbours (it may be positive: a cell can be occupied while its
centre lies just outside the surface). Deeper occupied cells, and every cell without
``sub_cell``, read occupied cells as solid cubes: centre distance minus ``surface_offset_m``
(half a cell by default). Values are capped at +-``UNKNOWN_DISTANCE``.

With ``OccupancyParams.esdf_z_m`` (the planner's altitude band) only the layers a point of
that range interpolates from get values (``esdf_layers``): the scan along z still runs over the
whole window, so obstacles in the layers above and below count, and the passes after it work
layer by layer, so each layer computed is bit for bit that of the whole window's transform.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import njit

from onboard.mapping.occupancy import OccupancyMap
from onboard.planner.field import UNKNOWN_DISTANCE, GridField

_BIG = np.float32(1e30)
_UNKNOWN_BELOW = -50.0


@njit(cache=True, nogil=True)
def _column_pass(
    logodds: np.ndarray,
    surf: np.ndarray,
    lo: np.ndarray,
    l_occ: float,
    res: float,
    f_out: np.ndarray,
    feat: np.ndarray,
    f_in: np.ndarray,
    occ: np.ndarray,
    known: np.ndarray,
    spt: np.ndarray,
) -> int:
    """Read the ring buffer in window order; per z column, the squared 1-D distance (cells) to
    the nearest occupied cell (f_out, whose number goes to feat) and to the nearest
    non-occupied cell (f_in). Occupied cells are numbered 0, 1, ... in window order; the m-th
    gets its surface point (mean of its hits, the centre when none), relative to the window
    origin, in spt[m] (spt: (at least the number of occupied cells, 3): a few hundred kB for
    a mapped window, where one slot per cell would spread them over megabytes). Returns the
    number of occupied cells. A column without an occupied cell (most: free and unknown space)
    gets f_out big and f_in 0 without the scans, and no feat (never read where f_out is big)."""
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    if spt.ndim != 2 or spt.shape[1] != 3 or spt.shape[0] < nx * ny * nz:
        raise ValueError("spt must have shape (at least the number of cells, 3)")
    big = np.float32(1e30)
    n_occ = 0
    sz_of = np.empty(nz, dtype=np.int64)
    for wk in range(nz):
        s = (lo[2] + wk) % nz
        sz_of[wk] = s + nz if s < 0 else s
    col = np.empty(nz, dtype=np.float32)
    ocol = np.empty(nz, dtype=np.bool_)
    dn = np.empty(nz, dtype=np.int64)
    num = np.empty(nz, dtype=np.int64)
    for wi in range(nx):
        si = (lo[0] + wi) % nx
        if si < 0:
            si += nx
        for wj in range(ny):
            sj = (lo[1] + wj) % ny
            if sj < 0:
                sj += ny
            base = (si * ny + sj) * nz
            any_occ = False
            for wk in range(nz):
                v = logodds[si, sj, sz_of[wk]]
                o = v >= l_occ
                ocol[wk] = o
                known[wi, wj, wk] = v > _UNKNOWN_BELOW
                any_occ |= o
            if not any_occ:
                for wk in range(nz):
                    occ[wi, wj, wk] = False
                    f_out[wi, wj, wk] = big
                    f_in[wi, wj, wk] = 0.0
                continue
            last_occ = -1
            last_free = -1
            for wk in range(nz):
                o = ocol[wk]
                occ[wi, wj, wk] = o
                if o:
                    m = n_occ
                    num[wk] = m
                    n_occ += 1
                    last_occ = wk
                    e = base + sz_of[wk]
                    c = surf[e, 3]
                    spt[m, 0] = (wi + 0.5) * res
                    spt[m, 1] = (wj + 0.5) * res
                    spt[m, 2] = (wk + 0.5) * res
                    if c > 0.0:
                        spt[m, 0] += surf[e, 0] / c
                        spt[m, 1] += surf[e, 1] / c
                        spt[m, 2] += surf[e, 2] / c
                else:
                    last_free = wk
                dn[wk] = last_occ
                col[wk] = (wk - last_free) if last_free >= 0 else big
            last_occ = -1
            last_free = -1
            for wk in range(nz - 1, -1, -1):
                if ocol[wk]:
                    last_occ = wk
                else:
                    last_free = wk
                lb = dn[wk]
                a = (wk - lb) if lb >= 0 else big
                if last_occ >= 0 and last_occ - wk < a:
                    a = last_occ - wk
                if last_occ >= 0 and last_occ - wk <= a:
                    feat[wi, wj, wk] = num[last_occ]
                elif lb >= 0:
                    feat[wi, wj, wk] = num[lb]
                b = col[wk]
                if last_free >= 0:
                    b = min(b, last_free - wk)
                f_out[wi, wj, wk] = a * a if a < big else big
                f_in[wi, wj, wk] = b * b if b < big else big
    return n_occ


@njit(cache=True, nogil=True)
def _envelope_line(
    f: np.ndarray,
    n: int,
    out: np.ndarray,
    v: np.ndarray,
    z: np.ndarray,
    big: float,
    feat: np.ndarray,
    feat_out: np.ndarray,
    with_feat: bool,
) -> None:
    """1-D squared distance transform of the samples f[0:n] (unit spacing) into out[0:n]; with
    with_feat, feat_out[q] = feat[p] of the sample p that gives out[q]."""
    k = -1
    for q in range(n):
        fq = f[q]
        if fq >= big:
            continue
        s = -math.inf
        while k >= 0:
            p = v[k]
            s = ((fq + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
            if s <= z[k]:
                k -= 1
                s = -math.inf
            else:
                break
        k += 1
        v[k] = q
        z[k] = s
        z[k + 1] = math.inf
    if k < 0:
        for q in range(n):
            out[q] = big
        return
    j = 0
    for q in range(n):
        while z[j + 1] < q:
            j += 1
        p = v[j]
        out[q] = (q - p) * (q - p) + f[p]
        if with_feat:
            feat_out[q] = feat[p]


@njit(cache=True, nogil=True)
def _envelope_pass(
    f: np.ndarray,
    axis: int,
    skip_value: float,
    feat: np.ndarray,
    with_feat: bool,
    k0: int = 0,
    k1: int = -1,
) -> None:
    """Squared distance transform of f (nx, ny, nz) along axis 0 or 1, in place, carrying the
    feature indices feat along when with_feat, on the layers k0 <= k < k1 (k1 < 0: nz; the
    others are left as they are: the passes after the one along z work layer by layer). Lines
    whose values all equal ``skip_value`` are left as they are (nothing to propagate)."""
    nx = f.shape[0]
    ny = f.shape[1]
    nz = k1 if k1 >= 0 else f.shape[2]
    n = nx if axis == 0 else ny
    line = np.empty(n)
    out = np.empty(n)
    v = np.empty(n, dtype=np.int64)
    z = np.empty(n + 1)
    fl = np.empty(n, dtype=np.int32)
    fo = np.empty(n, dtype=np.int32)
    big = 1e30
    if axis == 1:
        for i in range(nx):
            for k in range(k0, nz):
                same = True
                for j in range(ny):
                    x = f[i, j, k]
                    line[j] = x
                    if x != skip_value:
                        same = False
                if same:
                    continue
                if with_feat:
                    for j in range(ny):
                        fl[j] = feat[i, j, k]
                _envelope_line(line, ny, out, v, z, big, fl, fo, with_feat)
                for j in range(ny):
                    f[i, j, k] = out[j]
                if with_feat:
                    for j in range(ny):
                        feat[i, j, k] = fo[j]
    else:
        for j in range(ny):
            for k in range(k0, nz):
                same = True
                for i in range(nx):
                    x = f[i, j, k]
                    line[i] = x
                    if x != skip_value:
                        same = False
                if same:
                    continue
                if with_feat:
                    for i in range(nx):
                        fl[i] = feat[i, j, k]
                _envelope_line(line, nx, out, v, z, big, fl, fo, with_feat)
                for i in range(nx):
                    f[i, j, k] = out[i]
                if with_feat:
                    for i in range(nx):
                        feat[i, j, k] = fo[i]


@njit(cache=True, nogil=True)
def _envelope_pass_x(
    f: np.ndarray,
    skip_value: float,
    feat: np.ndarray,
    with_feat: bool,
    k0: int = 0,
    k1: int = -1,
) -> None:
    """``_envelope_pass`` along axis 0 (layers k0 <= k < k1, k1 < 0: nz), one (x, z) plane
    at a time through a transposed copy (the lines along x lie a plane apart in f)."""
    nx = f.shape[0]
    ny = f.shape[1]
    ka = k0
    nz = (k1 if k1 >= 0 else f.shape[2]) - ka
    F = np.empty((nz, nx))
    FT = np.zeros((nz, nx), dtype=np.int32)
    out = np.empty(nx)
    v = np.empty(nx, dtype=np.int64)
    z = np.empty(nx + 1)
    fo = np.empty(nx, dtype=np.int32)
    big = 1e30
    for j in range(ny):
        for i in range(nx):
            for k in range(nz):
                F[k, i] = f[i, j, ka + k]
        if with_feat:
            for i in range(nx):
                for k in range(nz):
                    FT[k, i] = feat[i, j, ka + k]
        for k in range(nz):
            line = F[k]
            same = True
            for i in range(nx):
                if line[i] != skip_value:
                    same = False
                    break
            if same:
                continue
            _envelope_line(line, nx, out, v, z, big, FT[k], fo, with_feat)
            for i in range(nx):
                line[i] = out[i]
            if with_feat:
                for i in range(nx):
                    FT[k, i] = fo[i]
        for i in range(nx):
            for k in range(nz):
                f[i, j, ka + k] = F[k, i]
        if with_feat:
            for i in range(nx):
                for k in range(nz):
                    feat[i, j, ka + k] = FT[k, i]


@njit(cache=True, nogil=True)
def _combine(
    f_out: np.ndarray,
    feat: np.ndarray,
    f_in: np.ndarray,
    occ: np.ndarray,
    known: np.ndarray,
    spt: np.ndarray,
    res: float,
    offset: float,
    sub_cell: bool,
    cap: float,
    values: np.ndarray,
    margin: float,
    inflated: np.ndarray,
    with_inflated: bool,
    k0: int = 0,
    k1: int = -1,
) -> int:
    """Signed distance per cell from the two squared transforms (see the module docstring);
    with ``with_inflated``, also ``inflated`` = the value minus ``margin`` within +-cap (what
    ``EsdfField.inflated(margin)`` computes, in the same pass). Only the layers k0 <= k < k1
    (k1 < 0: nz), into values[:, :, k - k0] (and inflated). Returns the number of
    non-finite values (none, unless an input was bad): the field's finiteness is checked here,
    not by another pass over the grid."""
    bad = 0
    nx = f_out.shape[0]
    ny = f_out.shape[1]
    nz = f_out.shape[2]
    kend = k1 if k1 >= 0 else nz
    big = 1e29
    sp = spt.reshape(-1)
    for i in range(nx):
        x = (i + 0.5) * res
        for j in range(ny):
            y = (j + 0.5) * res
            for k in range(k0, kend):
                z = (k + 0.5) * res
                if not occ[i, j, k]:
                    a = f_out[i, j, k]
                    if a >= big:
                        val = cap
                    else:
                        if sub_cell:
                            w = 3 * feat[i, j, k]
                            dx = x - sp[w]
                            dy = y - sp[w + 1]
                            dz = z - sp[w + 2]
                            d = math.sqrt(dx * dx + dy * dy + dz * dz)
                        else:
                            d = math.sqrt(a) * res - offset
                        val = min(max(d, 0.0), cap)
                else:
                    a = f_in[i, j, k]
                    if a >= big:
                        val = -cap
                    else:
                        d = -(math.sqrt(a) * res - offset)
                        if sub_cell and a <= 1.0:
                            # a surface cell: signed distance of its centre to its own surface
                            # point along the mean direction towards its observed free
                            # neighbours
                            gx = 0.0
                            gy = 0.0
                            gz = 0.0
                            if i > 0 and known[i - 1, j, k] and not occ[i - 1, j, k]:
                                gx -= 1.0
                            if i < nx - 1 and known[i + 1, j, k] and not occ[i + 1, j, k]:
                                gx += 1.0
                            if j > 0 and known[i, j - 1, k] and not occ[i, j - 1, k]:
                                gy -= 1.0
                            if j < ny - 1 and known[i, j + 1, k] and not occ[i, j + 1, k]:
                                gy += 1.0
                            if k > 0 and known[i, j, k - 1] and not occ[i, j, k - 1]:
                                gz -= 1.0
                            if k < nz - 1 and known[i, j, k + 1] and not occ[i, j, k + 1]:
                                gz += 1.0
                            gn = math.sqrt(gx * gx + gy * gy + gz * gz)
                            if gn > 0.0:
                                # an occupied cell is its own nearest: feat is its number
                                w = 3 * feat[i, j, k]
                                d = (
                                    (x - sp[w]) * gx + (y - sp[w + 1]) * gy + (z - sp[w + 2]) * gz
                                ) / gn
                        val = max(d, -cap)
                if not math.isfinite(val):
                    bad += 1
                values[i, j, k - k0] = val
                if with_inflated:
                    e = val - margin
                    inflated[i, j, k - k0] = -cap if e < -cap else (cap if e > cap else e)
    return bad


@njit(cache=True, nogil=True)
def _inside_local(
    occ: np.ndarray, f_in: np.ndarray, n_occ: int, r_max: int, k0: int = 0, k1: int = -1
) -> bool:
    """The inside transform (``f_in`` at occupied cells: squared distance, in cells, to the
    nearest non-occupied cell of the window) by a search around each occupied cell, in place
    of the two envelope passes over every line that holds an occupied cell.

    Mapped obstacles are shells (only their surfaces are observed; their inside stays unknown,
    which counts as non-occupied here), so nearly every occupied cell has a non-occupied face
    neighbour (distance 1, the least possible) and the others one a few cells away. ``f_in``
    enters with the column pass's values, the squared distance to the nearest non-occupied cell
    of the same column, an upper bound. Cells are searched in cubic shells of growing radius r;
    cells outside the shells searched so far are at least r^2 away, so the search ends as soon
    as the best found is at most that: the result is the exact minimum, as the envelope gives
    it (integers, exactly represented). Returns False, with ``f_in`` untouched, when some
    occupied cell has no non-occupied cell within ``r_max`` (large solid blocks): the caller
    then runs the envelope passes. Only the occupied cells of the layers k0 <= k < k1 (k1 < 0:
    nz) are searched for (their searches reach into every layer)."""
    nx = occ.shape[0]
    ny = occ.shape[1]
    nz = occ.shape[2]
    kend = k1 if k1 >= 0 else nz
    out = np.empty(n_occ, dtype=np.float32)
    at = np.empty(n_occ, dtype=np.int64)  # where each result goes
    m = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(k0, kend):
                if not occ[i, j, k]:
                    continue
                if (
                    (i > 0 and not occ[i - 1, j, k])
                    or (i < nx - 1 and not occ[i + 1, j, k])
                    or (j > 0 and not occ[i, j - 1, k])
                    or (j < ny - 1 and not occ[i, j + 1, k])
                    or (k > 0 and not occ[i, j, k - 1])
                    or (k < nz - 1 and not occ[i, j, k + 1])
                ):
                    out[m] = 1.0
                    at[m] = (i * ny + j) * nz + k
                    m += 1
                    continue
                best = f_in[i, j, k]  # the column's own (big when the column is all occupied)
                r = 1
                while True:
                    # every cell closer than shell r was searched; the rest are >= r^2 away
                    if best <= r * r:
                        break
                    if r > r_max:
                        return False
                    # shell r: cells with max(|di|, |dj|, |dk|) == r
                    for di in range(-r, r + 1):
                        a = i + di
                        if a < 0 or a >= nx:
                            continue
                        for dj in range(-r, r + 1):
                            b = j + dj
                            if b < 0 or b >= ny:
                                continue
                            edge = di == -r or di == r or dj == -r or dj == r
                            step = 1 if edge else 2 * r
                            for dk in range(-r, r + 1, step):
                                c = k + dk
                                if c < 0 or c >= nz or occ[a, b, c]:
                                    continue
                                d2 = di * di + dj * dj + dk * dk
                                if d2 < best:
                                    best = d2
                    r += 1
                out[m] = best
                at[m] = (i * ny + j) * nz + k
                m += 1
    flat = f_in.reshape(-1)
    for q in range(m):
        flat[at[q]] = out[q]
    return True


_INSIDE_SEARCH_CELLS = 8
"""Largest shell radius of ``_inside_local`` before it leaves the inside transform to the
envelope passes."""


@njit(cache=True, nogil=True)
def fill_occluded(
    logodds: np.ndarray,
    lo: np.ndarray,
    l_occ: float,
    cells: int,
    out: np.ndarray,
    queue: np.ndarray,
    surf: np.ndarray,
    behind_hits: bool,
) -> tuple[int, int]:
    """``out`` = ``logodds`` (the ring buffer, same storage order) with every never-observed
    cell within ``cells`` cells of an occupied cell in the same layer (Chebyshev distance in x
    and y, in the window: never across its edges) set to ``l_occ``: occupied for the ESDF
    (``OccupancyParams.occluded_fill_m``); with ``behind_hits``, only those whose row of
    ``surf`` (the map's surface accumulators) holds points, which in a never-observed cell are
    the points a hit's ray marked behind it (``OccupancyParams.occluded_fill_behind_hits``;
    their mean is then the filled cell's surface point for the ESDF). Only sideways: the
    shadows of a level camera lie behind what it saw, not above or below it, and each layer's
    fill depends on that layer alone (a band window's layers get what a taller window's get).
    ``queue`` (int64, at least one slot per cell) receives window-order flat indices
    ``(wi * ny + wj) * nz + wk``: the occupied cells, then the filled ones. Returns (occupied,
    occupied + filled): the filled cells are ``queue[occupied:occupied + filled]``."""
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    # storage slot of each window index per axis (no modulo in the loops below)
    sx = np.empty(nx, dtype=np.int64)
    sy = np.empty(ny, dtype=np.int64)
    sz = np.empty(nz, dtype=np.int64)
    for sa, na, la in ((sx, nx, lo[0]), (sy, ny, lo[1]), (sz, nz, lo[2])):
        r = la % na
        r = r + na if r < 0 else r
        for w in range(na):
            v = r + w
            sa[w] = v - na if v >= na else v
    out[...] = logodds
    m = 0
    for wi in range(nx):
        si = sx[wi]
        for wj in range(ny):
            sj = sy[wj]
            for wk in range(nz):
                if logodds[si, sj, sz[wk]] >= l_occ:
                    queue[m] = (wi * ny + wj) * nz + wk
                    m += 1
    n_occ = m
    for f in range(n_occ):
        w = queue[f]
        wk = w % nz
        wj = (w // nz) % ny
        wi = w // (nz * ny)
        sk = sz[wk]
        for ai in range(max(wi - cells, 0), min(wi + cells + 1, nx)):
            si = sx[ai]
            for aj in range(max(wj - cells, 0), min(wj + cells + 1, ny)):
                sj = sy[aj]
                if out[si, sj, sk] < _UNKNOWN_BELOW and (
                    not behind_hits or surf[(si * ny + sj) * nz + sk, 3] > 0.0
                ):
                    out[si, sj, sk] = l_occ
                    queue[m] = (ai * ny + aj) * nz + wk
                    m += 1
    return n_occ, m


@njit(cache=True, nogil=True)
def esdf_kernel(
    logodds: np.ndarray,
    surf: np.ndarray,
    lo: np.ndarray,
    l_occ: float,
    res: float,
    offset: float,
    sub_cell: bool,
    cap: float,
    f_out: np.ndarray,
    feat: np.ndarray,
    f_in: np.ndarray,
    occ: np.ndarray,
    known: np.ndarray,
    spt: np.ndarray,
    values: np.ndarray,
    margin: float = 0.0,
    inflated: np.ndarray | None = None,
    k0: int = 0,
    k1: int = -1,
) -> tuple[int, int]:
    """Signed distance of the ring-buffered window (see the module docstring) into values,
    occ and known (window order), and when ``inflated`` is given the values minus ``margin``
    (within +-cap) into it; returns the number of occupied cells and the number of
    non-finite values written (0 unless an input was bad). f_out, feat, f_in (nx, ny, nz) and
    spt (nx * ny * nz, 3) float32 are work buffers (feat: the number of each cell's nearest
    occupied cell, whose surface point is that row of spt).

    Only the window's layers k0 <= k < k1 (k1 < 0: nz) get values, into values (nx, ny,
    k1 - k0) (and inflated): the pass along z runs over the whole window, so every occupied
    cell counts, and the passes after it work layer by layer, so each of these layers gets, bit
    for bit, what it gets from the whole window's transform. occ and known cover the window."""
    n_occ = _column_pass(logodds, surf, lo, l_occ, res, f_out, feat, f_in, occ, known, spt)
    ka = k0
    kb = k1 if k1 >= 0 else logodds.shape[2]
    # the float32 the grids hold for "no occupied cell" (a float64 1e30 never equals it)
    big = np.float32(1e30)
    _envelope_pass(f_out, 1, big, feat, sub_cell, ka, kb)
    _envelope_pass_x(f_out, big, feat, sub_cell, ka, kb)
    if n_occ > 0 and not _inside_local(occ, f_in, n_occ, _INSIDE_SEARCH_CELLS, ka, kb):
        _envelope_pass(f_in, 1, np.float32(0.0), feat, False, ka, kb)
        _envelope_pass(f_in, 0, np.float32(0.0), feat, False, ka, kb)
    if inflated is None:
        bad = _combine(
            f_out,
            feat,
            f_in,
            occ,
            known,
            spt,
            res,
            offset,
            sub_cell,
            cap,
            values,
            0.0,
            values,
            False,
            ka,
            kb,
        )
    else:
        bad = _combine(
            f_out,
            feat,
            f_in,
            occ,
            known,
            spt,
            res,
            offset,
            sub_cell,
            cap,
            values,
            margin,
            inflated,
            True,
            ka,
            kb,
        )
    return n_occ, bad


class EsdfField(GridField):
    """The planner's ``GridField`` of a mapped window, plus the occupancy it came from.

    values: signed distance at cell centres (unknown cells: distance to the nearest known
    obstacle, so the optimiser treats them as free); ``known``: observed cells;
    ``occupied``: occupied cells; ``inflation_m``: the drone radius the map's own collision
    check inflates obstacles by. ``collision_free`` refuses unknown space.
    """

    def __init__(
        self,
        values: np.ndarray,
        origin: np.ndarray,
        res: float,
        known: np.ndarray,
        occupied: np.ndarray,
        inflation_m: float,
        stamp_s: float = math.nan,
        *,
        adopt: bool = False,
    ) -> None:
        """``adopt``: the arrays are read-only and valid (see ``GridField``), taken without a
        copy (the ESDF builder's)."""
        super().__init__(values, origin, res, known, adopt=adopt)
        if adopt and occupied.dtype == np.bool_ and not occupied.flags.writeable:
            occ = occupied
        else:
            occ = np.array(occupied, dtype=bool, copy=True)
            occ.setflags(write=False)
        self.occupied = occ
        self.inflation_m = float(inflation_m)
        self.stamp_s = float(stamp_s)
        self._inflated: tuple[float, EsdfField] | None = None  # computed with the field

    def collision_free(self, points: np.ndarray, clearance_m: float = 0.0) -> np.ndarray:
        """Bool (K,): the point lies in observed space, at least ``inflation_m + clearance_m``
        from every mapped obstacle. Unknown space and points outside the window are never
        free."""
        d, _ = self.distance(points)
        return self.is_known(points) & (d >= self.inflation_m + clearance_m)

    def inflated(self, margin_m: float) -> EsdfField:
        """The field of the obstacles grown by ``margin_m``: every value minus the margin
        (within +-``UNKNOWN_DISTANCE``); its own collision check adds the rest of
        ``inflation_m``, if any."""
        done = self._inflated
        if done is not None and done[0] == margin_m:
            return done[1]
        v = np.clip(self.values - margin_m, -UNKNOWN_DISTANCE, UNKNOWN_DISTANCE)
        return self._with_inflated_values(v, margin_m)

    def _with_inflated_values(self, v: np.ndarray, margin_m: float) -> EsdfField:
        """The field of the values ``v`` (within +-cap, finite: taken as they are) with this
        one's masks."""
        v.setflags(write=False)
        known = self.known if self.known is not None else np.ones(self.shape, dtype=bool)
        known.setflags(write=False)
        return EsdfField(
            v,
            self.origin,
            self.res,
            known,
            self.occupied,
            max(self.inflation_m - margin_m, 0.0),
            self.stamp_s,
            adopt=True,
        )

    def inflated_occupied(self) -> np.ndarray:
        """Bool grid: cells whose centre lies closer than ``inflation_m`` to an obstacle (the
        occupied cells dilated by the drone radius)."""
        return self.values < self.inflation_m


def esdf_layers(omap: OccupancyMap) -> tuple[int, int]:
    """The window layers k0 <= k < k1 (window order) the ESDF covers: with
    ``OccupancyParams.esdf_z_m`` = (z_lo, z_hi), those from the last cell centre at or below
    z_lo to the first at or above z_hi (every centre a point of [z_lo, z_hi] interpolates from),
    within the window (the whole window when fewer than two of them lie in it); else all."""
    nz = omap.shape[2]
    band = omap.params.esdf_z_m
    if band is None:
        return 0, nz
    res = omap.res
    lo = int(omap.lo[2])
    k0 = int(math.floor(band[0] / res - 0.5 - 1e-6)) - lo
    k1 = int(math.ceil(band[1] / res - 0.5 + 1e-6)) + 1 - lo
    k0, k1 = max(k0, 0), min(k1, nz)
    if k1 - k0 < 2:
        return 0, nz
    return k0, k1


_POOL_SETS = 3
"""Output buffer sets an ``EsdfBuilder`` keeps for reuse (the latest field, one a planner may
still hold, one spare)."""


def _refcounts(bufs: tuple[np.ndarray, ...]) -> list[int]:
    """``sys.getrefcount`` of each array of a buffer set, always through this same call path
    (the count includes the references of the path itself), so that a set's counts compare
    with those of a set nobody else holds."""
    return [sys.getrefcount(a) for a in bufs]


class _OutputPool:
    """Output arrays of ESDF refreshes (values, inflated values, known, occupied), reused once
    no field (nor any view of their arrays) is left: refreshing into fresh 4 MB arrays cost
    page faults worth a third of the kernel's own time (34 vs 26 ms of CPU per refresh, loaded
    machine). A buffer set is free when no object but the pool refers to any of its arrays
    (every numpy view holds a reference to the array that owns the memory, so a view kept
    anywhere keeps its set out of use)."""

    def __init__(self, shape: tuple[int, int, int], sets: int = _POOL_SETS) -> None:
        self.shape = shape
        self.sets: list[tuple[np.ndarray, ...]] = []
        self.max_sets = sets
        self._free_count = -1
        self.new_sets = 0
        """Buffer sets allocated (the pooled ones, then one per refresh that found none free:
        fresh arrays cost page faults)."""

    def _new_set(self) -> tuple[np.ndarray, ...]:
        sh = self.shape
        return (
            np.empty(sh, dtype=np.float64),
            np.empty(sh, dtype=np.float64),
            np.empty(sh, dtype=np.bool_),
            np.empty(sh, dtype=np.bool_),
        )

    def _is_free(self, bufs: tuple[np.ndarray, ...]) -> bool:
        return max(_refcounts(bufs)) <= self._free_count

    def take(self) -> tuple[np.ndarray, ...]:
        """A buffer set no one uses (pooled when the pool has room), its arrays writable."""
        if self._free_count < 0:
            probe = self._new_set()  # held by one tuple only, as a pooled set
            self._free_count = max(_refcounts(probe))
        for bufs in self.sets:
            if self._is_free(bufs):
                return bufs
        bufs = self._new_set()
        self.new_sets += 1
        if len(self.sets) < self.max_sets:
            self.sets.append(bufs)
        return bufs


def _read_only_view(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.setflags(write=False)
    return v


class EsdfBuilder:
    """Reusable buffers for ESDF refreshes of one ``OccupancyMap``: the work buffers, and the
    output arrays of fields no longer in use (see ``_OutputPool``)."""

    def __init__(self, surface_offset_m: float | None = None, sub_cell: bool = True) -> None:
        self.surface_offset_m = surface_offset_m
        self.sub_cell = sub_cell
        self._shape: tuple[int, int, int] | None = None
        self._bufs: tuple[np.ndarray, ...] = ()
        self._fill_bufs: tuple[np.ndarray, ...] = ()  # fill_occluded's output and work
        self._pool: _OutputPool | None = None
        self._masks: tuple[np.ndarray, ...] = ()
        self._new_sets_before = 0  # of pools replaced after a change of shape

    @property
    def new_sets(self) -> int:
        """Output buffer sets allocated so far (see ``_OutputPool.new_sets``)."""
        return self._new_sets_before + (self._pool.new_sets if self._pool is not None else 0)

    def build(
        self,
        omap: OccupancyMap,
        stamp_s: float = math.nan,
        inflate_m: float | None = None,
        fill_cells: int | None = None,
    ) -> EsdfField:
        """The signed distance field of the map's current window (of its layers that
        ``esdf_layers`` names: the field's box is those layers'); with ``inflate_m``, its
        ``inflated(inflate_m)`` is computed in the same pass (and returned by that call).
        ``fill_cells``: the shadow fill in cells (``fill_occluded``; None: the map's
        ``occluded_fill_m``; 0: the transform of what was observed alone)."""
        shape = omap.shape
        k0, k1 = esdf_layers(omap)
        partial = (k0, k1) != (0, shape[2])
        out_shape = (shape[0], shape[1], k1 - k0)
        if self._shape != shape or self._pool is None or self._pool.shape != out_shape:
            self._bufs = (
                np.empty(shape, dtype=np.float32),
                np.empty(shape, dtype=np.int32),
                np.empty(shape, dtype=np.float32),
                np.empty((int(np.prod(shape)), 3), dtype=np.float32),
            )
            self._fill_bufs = ()
            self._new_sets_before = self.new_sets
            self._pool = _OutputPool(out_shape)
            self._shape = shape
            # the whole window's masks, when the field covers only some of its layers
            self._masks = (
                (np.empty(shape, dtype=np.bool_), np.empty(shape, dtype=np.bool_))
                if partial
                else ()
            )
        f_out, feat, f_in, spt = self._bufs
        values, inflated, known_out, occ_out = self._pool.take()
        known, occ = self._masks if partial else (known_out, occ_out)
        res = omap.res
        offset = 0.5 * res if self.surface_offset_m is None else self.surface_offset_m
        logodds = omap.logodds
        fill = omap.params.occluded_fill_cells if fill_cells is None else int(fill_cells)
        if fill > 0:
            if not self._fill_bufs:
                self._fill_bufs = (
                    np.empty(shape, dtype=np.float32),
                    np.empty(int(np.prod(shape)), dtype=np.int64),
                )
            logodds, queue = self._fill_bufs
            n_occ, n_all = fill_occluded(
                omap.logodds,
                omap.lo,
                omap.params.l_occ,
                fill,
                logodds,
                queue,
                omap.surf,
                omap.params.occluded_fill_behind_hits,
            )
        _n_occ, bad = esdf_kernel(
            logodds,
            omap.surf,
            omap.lo,
            omap.params.l_occ,
            res,
            offset,
            self.sub_cell,
            UNKNOWN_DISTANCE,
            f_out,
            feat,
            f_in,
            occ,
            known,
            spt,
            values,
            0.0 if inflate_m is None else float(inflate_m),
            None if inflate_m is None else inflated,
            k0,
            k1,
        )
        if bad:
            raise ValueError(f"ESDF refresh produced {bad} non-finite values (a bad map input)")
        if fill > 0:
            # filled cells are occupied for the distances but still unobserved for the checks
            known.reshape(-1)[queue[n_occ:n_all]] = False
        if partial:
            known_out[...] = known[:, :, k0:k1]
            occ_out[...] = occ[:, :, k0:k1]
        known_v = _read_only_view(known_out)
        occ_v = _read_only_view(occ_out)
        origin = omap.origin
        if k0:
            origin = origin + np.array([0.0, 0.0, k0 * res])
        field = EsdfField(
            _read_only_view(values),
            origin,
            res,
            known_v,
            occ_v,
            omap.params.inflation_m,
            stamp_s,
            adopt=True,
        )
        if inflate_m is not None:
            field._inflated = (
                inflate_m,
                field._with_inflated_values(_read_only_view(inflated), inflate_m),
            )
        return field
