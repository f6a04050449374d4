"""The ray casting's faster paths map bit for bit what the plain ones mapped.

The reference below is the ingest kernel as it was before they were cut (per-frame marks in an
int32 array instead of a byte reset after each frame, the storage slot of a ray's end cell by a
modulo, every ray's end clipped to the window box, the depth block of every pixel by a
division); docstrings left out. Both cast the same frames into copies of the same map: a flight
that rolls the window, with noise, holes, no-return pixels, every kind of invalid pixel, rays
that leave the window (trunks above its top, the camera near its edge), and cast points.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from onboard.mapping import (
    DepthFrame,
    OccupancyMap,
    OccupancyParams,
    SimCameraParams,
    SimulatedDepthCamera,
    look_rotation,
)
from onboard.world import World

_UNKNOWN_BELOW = -50.0
_BIT_FREE = 1
_BIT_HIT = 2
_BIT_END = 4
_SURF_MAX_COUNT = 64.0


@njit(cache=True)
def _ref_wrap(g: int, n: int) -> int:
    s = g % n
    return s + n if s < 0 else s


@njit(cache=True)
def _ref_touch(
    touch: np.ndarray, touched: np.ndarray, n_touched: int, idx: int, mark: int, bits: int
) -> tuple[int, int]:
    m = touch[idx]
    if (m >> 3) != mark:
        touched[n_touched] = idx
        n_touched += 1
        touch[idx] = (mark << 3) | bits
        return 0, n_touched
    touch[idx] = m | bits
    return m & 7, n_touched


@njit(cache=True)
def _ref_cast_ray(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    lo: np.ndarray,
    res: float,
    o: np.ndarray,
    px: float,
    py: float,
    pz: float,
    hit: bool,
    mark: int,
) -> int:
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    gx = int(math.floor(px / res))
    gy = int(math.floor(py / res))
    gz = int(math.floor(pz / res))
    gx = min(max(gx, lo[0]), lo[0] + nx - 1)
    gy = min(max(gy, lo[1]), lo[1] + ny - 1)
    gz = min(max(gz, lo[2]), lo[2] + nz - 1)
    sx = _ref_wrap(gx, nx)
    sy = _ref_wrap(gy, ny)
    sz = _ref_wrap(gz, nz)
    idx = (sx * ny + sy) * nz + sz
    if hit:
        if surf[idx, 3] >= _SURF_MAX_COUNT:  # forget slowly: keep following the surface
            for a in range(4):
                surf[idx, a] *= 0.5
        surf[idx, 0] += px - (gx + 0.5) * res
        surf[idx, 1] += py - (gy + 0.5) * res
        surf[idx, 2] += pz - (gz + 0.5) * res
        surf[idx, 3] += 1.0
    bits = _BIT_END | (_BIT_HIT if hit else _BIT_FREE)
    prev, n_touched = _ref_touch(touch, touched, n_touched, idx, mark, bits)
    if prev & _BIT_END:
        # a ray of this frame already ended in this cell: from here to the camera it crosses
        # the same cells (up to the neighbours of this one, which other rays end in)
        return n_touched
    ox_g = int(math.floor(o[0] / res))
    oy_g = int(math.floor(o[1] / res))
    oz_g = int(math.floor(o[2] / res))
    ex = o[0] - px
    ey = o[1] - py
    ez = o[2] - pz
    # Amanatides-Woo traversal in the ray parameter s in [0, 1] (p at 0, o at 1)
    inf = math.inf
    if ex > 0.0:
        stx = 1
        tmx = ((gx + 1) * res - px) / ex
        tdx = res / ex
    elif ex < 0.0:
        stx = -1
        tmx = (gx * res - px) / ex
        tdx = -res / ex
    else:
        stx = 0
        tmx = inf
        tdx = inf
    if ey > 0.0:
        sty = 1
        tmy = ((gy + 1) * res - py) / ey
        tdy = res / ey
    elif ey < 0.0:
        sty = -1
        tmy = (gy * res - py) / ey
        tdy = -res / ey
    else:
        sty = 0
        tmy = inf
        tdy = inf
    if ez > 0.0:
        stz = 1
        tmz = ((gz + 1) * res - pz) / ez
        tdz = res / ez
    elif ez < 0.0:
        stz = -1
        tmz = (gz * res - pz) / ez
        tdz = -res / ez
    else:
        stz = 0
        tmz = inf
        tdz = inf
    max_steps = nx + ny + nz + 3
    for _ in range(max_steps):
        if gx == ox_g and gy == oy_g and gz == oz_g:
            break
        if tmx <= tmy and tmx <= tmz:
            if tmx > 1.0:
                break
            gx += stx
            sx += stx
            if sx == nx:
                sx = 0
            elif sx < 0:
                sx = nx - 1
            tmx += tdx
        elif tmy <= tmz:
            if tmy > 1.0:
                break
            gy += sty
            sy += sty
            if sy == ny:
                sy = 0
            elif sy < 0:
                sy = ny - 1
            tmy += tdy
        else:
            if tmz > 1.0:
                break
            gz += stz
            sz += stz
            if sz == nz:
                sz = 0
            elif sz < 0:
                sz = nz - 1
            tmz += tdz
        if not (lo[0] <= gx < lo[0] + nx and lo[1] <= gy < lo[1] + ny and lo[2] <= gz < lo[2] + nz):
            break
        idx = (sx * ny + sy) * nz + sz
        prev, n_touched = _ref_touch(touch, touched, n_touched, idx, mark, _BIT_FREE)
    return n_touched


@njit(cache=True)
def _ref_cast_free_ray(
    logodds: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    lo: np.ndarray,
    res: float,
    o: np.ndarray,
    px: float,
    py: float,
    pz: float,
    mark: int,
    l_min: float,
) -> tuple[int, bool]:
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    flat = logodds.reshape(-1)
    floor = l_min + 1e-4
    ex_g = min(max(int(math.floor(px / res)), lo[0]), lo[0] + nx - 1)
    ey_g = min(max(int(math.floor(py / res)), lo[1]), lo[1] + ny - 1)
    ez_g = min(max(int(math.floor(pz / res)), lo[2]), lo[2] + nz - 1)
    end = (_ref_wrap(ex_g, nx) * ny + _ref_wrap(ey_g, ny)) * nz + _ref_wrap(ez_g, nz)
    m = touch[end]
    if (m >> 3) == mark and (m & _BIT_END):
        return n_touched, False
    gx = int(math.floor(o[0] / res))
    gy = int(math.floor(o[1] / res))
    gz = int(math.floor(o[2] / res))
    sx = _ref_wrap(gx, nx)
    sy = _ref_wrap(gy, ny)
    sz = _ref_wrap(gz, nz)
    ex = px - o[0]
    ey = py - o[1]
    ez = pz - o[2]
    # Amanatides-Woo traversal in the ray parameter s in [0, 1] (o at 0, p at 1)
    inf = math.inf
    if ex > 0.0:
        stx = 1
        tmx = ((gx + 1) * res - o[0]) / ex
        tdx = res / ex
    elif ex < 0.0:
        stx = -1
        tmx = (gx * res - o[0]) / ex
        tdx = -res / ex
    else:
        stx = 0
        tmx = inf
        tdx = inf
    if ey > 0.0:
        sty = 1
        tmy = ((gy + 1) * res - o[1]) / ey
        tdy = res / ey
    elif ey < 0.0:
        sty = -1
        tmy = (gy * res - o[1]) / ey
        tdy = -res / ey
    else:
        sty = 0
        tmy = inf
        tdy = inf
    if ez > 0.0:
        stz = 1
        tmz = ((gz + 1) * res - o[2]) / ez
        tdz = res / ez
    elif ez < 0.0:
        stz = -1
        tmz = (gz * res - o[2]) / ez
        tdz = -res / ez
    else:
        stz = 0
        tmz = inf
        tdz = inf
    max_steps = nx + ny + nz + 3
    for _ in range(max_steps):
        idx = (sx * ny + sy) * nz + sz
        v = flat[idx]
        if v >= 0.0:
            break
        last = idx == end or (tmx > 1.0 and tmy > 1.0 and tmz > 1.0)
        if v > floor or v < _UNKNOWN_BELOW or last:  # (a miss changes nothing at l_min)
            m = touch[idx]
            if (m >> 3) == mark and (m & _BIT_HIT):
                break
            bits = _BIT_FREE | (_BIT_END if last else 0)
            prev, n_touched = _ref_touch(touch, touched, n_touched, idx, mark, bits)
            if last:
                break
        if tmx <= tmy and tmx <= tmz:
            gx += stx
            sx += stx
            if sx == nx:
                sx = 0
            elif sx < 0:
                sx = nx - 1
            tmx += tdx
        elif tmy <= tmz:
            gy += sty
            sy += sty
            if sy == ny:
                sy = 0
            elif sy < 0:
                sy = ny - 1
            tmy += tdy
        else:
            gz += stz
            sz += stz
            if sz == nz:
                sz = 0
            elif sz < 0:
                sz = nz - 1
            tmz += tdz
        if not (lo[0] <= gx < lo[0] + nx and lo[1] <= gy < lo[1] + ny and lo[2] <= gz < lo[2] + nz):
            break
    return n_touched, True


@njit(cache=True)
def _ref_min_filter_blocks(block: np.ndarray, tmp: np.ndarray, out: np.ndarray, r: int) -> None:
    nb_v = block.shape[0]
    nb_u = block.shape[1]
    for i in range(nb_v):
        for j in range(nb_u):
            m = block[i, j]
            for jj in range(max(0, j - r), min(nb_u, j + r + 1)):
                if block[i, jj] < m:
                    m = block[i, jj]
            tmp[i, j] = m
    for i in range(nb_v):
        for j in range(nb_u):
            m = tmp[i, j]
            for ii in range(max(0, i - r), min(nb_v, i + r + 1)):
                if tmp[ii, j] < m:
                    m = tmp[ii, j]
            out[i, j] = m


@njit(cache=True)
def _ref_clip_to_window(
    o: np.ndarray, dx: float, dy: float, dz: float, box_lo: np.ndarray, box_hi: np.ndarray
) -> float:
    s = 1.0
    d3 = (dx, dy, dz)
    for a in range(3):
        if d3[a] > 0.0:
            s = min(s, (box_hi[a] - o[a]) / d3[a])
        elif d3[a] < 0.0:
            s = min(s, (box_lo[a] - o[a]) / d3[a])
    return max(s, 0.0)


@njit(cache=True)
def _ref_clip_ray(
    o: np.ndarray,
    dx: float,
    dy: float,
    dz: float,
    length: float,
    max_ray: float,
    box_lo: np.ndarray,
    box_hi: np.ndarray,
    eps: float,
    hit: bool,
) -> tuple[float, bool]:
    s = 1.0
    if length > max_ray:
        s = max_ray / length
        hit = False
    s_box = _ref_clip_to_window(o, dx, dy, dz, box_lo, box_hi)
    if s_box < s:
        s = max(s_box - eps / length, 0.0)
        hit = False
    return s, hit


@njit(cache=True)
def _ref_apply_updates(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
) -> None:
    flat = logodds.reshape(-1)
    for i in range(n_touched):
        idx = touched[i]
        m = touch[idx]
        v = flat[idx]
        if v < _UNKNOWN_BELOW:
            v = 0.0
        v += l_hit if (m & _BIT_HIT) else l_miss
        v = min(max(v, l_min), l_max)
        flat[idx] = v
        if v < 0.0:  # more likely free than not: drop the surface estimate
            for a in range(4):
                surf[idx, a] = 0.0


@njit(cache=True)
def _ref_ingest_depth_kernel(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    lo: np.ndarray,
    res: float,
    depth: np.ndarray,
    step: int,
    xn: np.ndarray,
    yn: np.ndarray,
    R: np.ndarray,
    o: np.ndarray,
    min_depth: float,
    max_depth: float,
    max_ray: float,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    mark: int,
    nr_len: float,
    nr_step: int,
    nr_margin: float,
    nr_min_valid: float,
    nr_block: int,
    nr_radius: int,
    blocks: np.ndarray,
    blocks_tmp: np.ndarray,
    blocks_near: np.ndarray,
) -> tuple[int, int, int, int]:
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    box_lo = np.empty(3)
    box_hi = np.empty(3)
    box_lo[0] = lo[0] * res
    box_lo[1] = lo[1] * res
    box_lo[2] = lo[2] * res
    box_hi[0] = (lo[0] + nx) * res
    box_hi[1] = (lo[1] + ny) * res
    box_hi[2] = (lo[2] + nz) * res
    eps = 1e-6 * res
    n_touched = 0
    rays = 0
    masked = 0
    track = nr_len > 0.0
    if track:
        blocks[:, :] = np.inf
    for v in range(0, depth.shape[0], step):
        for u in range(0, depth.shape[1], step):
            z = depth[v, u]
            if not (z >= min_depth) or z > 1e30:
                masked += 1
                if track and z != 0.0:  # an invalid value, not "no return": stop rays here
                    blocks[v // nr_block, u // nr_block] = 0.0
                continue
            rays += 1
            if track and z < blocks[v // nr_block, u // nr_block]:
                blocks[v // nr_block, u // nr_block] = z
            xc = xn[u] * z
            yc = yn[v] * z
            dx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2] * z
            dy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2] * z
            dz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2] * z
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            hit = z <= max_depth
            s, hit = _ref_clip_ray(o, dx, dy, dz, length, max_ray, box_lo, box_hi, eps, hit)
            n_touched = _ref_cast_ray(
                logodds,
                surf,
                touch,
                touched,
                n_touched,
                lo,
                res,
                o,
                o[0] + s * dx,
                o[1] + s * dy,
                o[2] + s * dz,
                hit,
                mark,
            )
    clear = 0
    if track and rays > 0 and rays >= nr_min_valid * (rays + masked):
        _ref_min_filter_blocks(blocks, blocks_tmp, blocks_near, nr_radius)
        for v in range(0, depth.shape[0], nr_step):
            for u in range(0, depth.shape[1], nr_step):
                if depth[v, u] != 0.0:
                    continue
                zc = blocks_near[v // nr_block, u // nr_block] - nr_margin
                norm = math.sqrt(xn[u] * xn[u] + yn[v] * yn[v] + 1.0)
                zc = min(zc, nr_len / norm)
                if zc < min_depth:
                    continue
                dx = (R[0, 0] * xn[u] + R[0, 1] * yn[v] + R[0, 2]) * zc
                dy = (R[1, 0] * xn[u] + R[1, 1] * yn[v] + R[1, 2]) * zc
                dz = (R[2, 0] * xn[u] + R[2, 1] * yn[v] + R[2, 2]) * zc
                s = _ref_clip_to_window(o, dx, dy, dz, box_lo, box_hi)
                if s < 1.0:
                    s = max(s - eps / (zc * norm), 0.0)
                n_touched, cast = _ref_cast_free_ray(
                    logodds,
                    touch,
                    touched,
                    n_touched,
                    lo,
                    res,
                    o,
                    o[0] + s * dx,
                    o[1] + s * dy,
                    o[2] + s * dz,
                    mark,
                    l_min,
                )
                clear += 1 if cast else 0
    _ref_apply_updates(logodds, surf, touch, touched, n_touched, l_hit, l_miss, l_min, l_max)
    return rays, masked, n_touched, clear


@njit(cache=True)
def _ref_ingest_points_kernel(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    lo: np.ndarray,
    res: float,
    o: np.ndarray,
    points: np.ndarray,
    max_ray: float,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    mark: int,
) -> tuple[int, int, int]:
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    box_lo = np.empty(3)
    box_hi = np.empty(3)
    box_lo[0] = lo[0] * res
    box_lo[1] = lo[1] * res
    box_lo[2] = lo[2] * res
    box_hi[0] = (lo[0] + nx) * res
    box_hi[1] = (lo[1] + ny) * res
    box_hi[2] = (lo[2] + nz) * res
    eps = 1e-6 * res
    n_touched = 0
    rays = 0
    skipped = 0
    for i in range(points.shape[0]):
        dx = points[i, 0] - o[0]
        dy = points[i, 1] - o[1]
        dz = points[i, 2] - o[2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not (length > 0.0 and length < 1e30):
            skipped += 1
            continue
        rays += 1
        hit = True
        s, hit = _ref_clip_ray(o, dx, dy, dz, length, max_ray, box_lo, box_hi, eps, hit)
        n_touched = _ref_cast_ray(
            logodds,
            surf,
            touch,
            touched,
            n_touched,
            lo,
            res,
            o,
            o[0] + s * dx,
            o[1] + s * dy,
            o[2] + s * dz,
            hit,
            mark,
        )
    _ref_apply_updates(logodds, surf, touch, touched, n_touched, l_hit, l_miss, l_min, l_max)
    return rays, skipped, n_touched


class _Reference:
    """A map state ray cast by the reference kernels (the mark bookkeeping of the old map)."""

    def __init__(self, om: OccupancyMap) -> None:
        self.om = om
        self.touch = np.zeros(om.logodds.size, dtype=np.int32)
        self.touched = np.empty(om.logodds.size, dtype=np.int64)
        self.mark = 0

    def _next_mark(self) -> int:
        self.mark += 1
        return self.mark

    def ingest_depth(self, f: DepthFrame, step: int, no_return: bool) -> tuple[int, ...]:
        om = self.om
        p = om.params
        xn, yn = f.intrinsics.normalized_coords()
        d = np.ascontiguousarray(f.depth_m, dtype=np.float32)
        k_nr = step * -(-p.no_return_step // step)
        block = step * -(-8 // step)
        shape = (-(-d.shape[0] // block), -(-d.shape[1] // block))
        blocks = tuple(np.empty(shape, dtype=np.float32) for _ in range(3))
        return tuple(
            _ref_ingest_depth_kernel(
                om.logodds,
                om.surf,
                self.touch,
                self.touched,
                om.lo,
                om.res,
                d,
                step,
                xn,
                yn,
                np.ascontiguousarray(f.rotation, dtype=np.float64),
                np.ascontiguousarray(f.position, dtype=np.float64),
                f.intrinsics.min_depth_m,
                f.intrinsics.max_depth_m,
                p.max_ray_m,
                p.l_hit,
                p.l_miss,
                p.l_min,
                p.l_max,
                self._next_mark(),
                p.no_return_m if no_return else 0.0,
                k_nr,
                p.no_return_margin_m,
                p.no_return_min_valid,
                block,
                -(-p.no_return_radius_px // block),
                *blocks,
            )
        )

    def ingest_points(self, origin: np.ndarray, points: np.ndarray) -> tuple[int, ...]:
        om = self.om
        p = om.params
        return tuple(
            _ref_ingest_points_kernel(
                om.logodds,
                om.surf,
                self.touch,
                self.touched,
                om.lo,
                om.res,
                np.ascontiguousarray(origin, dtype=np.float64),
                np.ascontiguousarray(points, dtype=np.float64),
                p.max_ray_m,
                p.l_hit,
                p.l_miss,
                p.l_min,
                p.l_max,
                self._next_mark(),
            )
        )


def _world() -> World:
    return World(
        cylinders=np.array(
            [
                [2.0, 0.4, 0.25, 0.0, 3.0],
                [3.5, -0.5, 0.2, 0.0, 3.0],
                [4.0, 1.6, 0.3, 0.0, 6.0],  # above the window's top
                [1.2, -1.4, 0.15, 0.0, 3.0],
            ]
        ),
        rings=np.zeros((0, 7)),
        boxes=np.array([[2.6, -2.0, 0.0, 3.2, -1.5, 1.2]]),
        ground_z=0.0,
    )


def _spoil(f: DepthFrame, rng: np.random.Generator) -> DepthFrame:
    d = np.array(f.depth_m, dtype=np.float32, copy=True)
    bad = [np.nan, np.inf, -np.inf, -1.0, 0.0, 0.1, 3e38, 9.0]
    idx = rng.integers(0, d.size, size=3000)
    d.reshape(-1)[idx] = np.array(bad, dtype=np.float32)[rng.integers(0, len(bad), idx.size)]
    return DepthFrame(d, f.stamp_s, f.position, f.rotation, f.intrinsics)


def _same(a: OccupancyMap, b: OccupancyMap) -> None:
    """Bit for bit, but for the points a hit's ray marks behind it in never-observed cells
    (``occluded_fill_behind_hits``), which the plain kernels do not mark: those change nothing
    else."""
    assert a.logodds.tobytes() == b.logodds.tobytes()
    if not a.params.occluded_fill_behind_hits:
        assert a.surf.tobytes() == b.surf.tobytes()
        return
    known = a.logodds.reshape(-1) > _UNKNOWN_BELOW
    assert a.surf[known].tobytes() == b.surf[known].tobytes()
    assert not b.surf[~known].any()


@pytest.mark.parametrize("behind_hits", [True, False])
@pytest.mark.parametrize("step", [2, 3])
def test_ray_casting_equals_the_plain_kernels_along_a_flight(step: int, behind_hits: bool) -> None:
    params = OccupancyParams(size_m=(5.0, 4.4, 2.6), occluded_fill_behind_hits=behind_hits)
    cam = SimulatedDepthCamera(
        _world(), params=SimCameraParams(noise_std_1m_m=0.004, dropout=0.02, hole_count=2), seed=4
    )
    rng = np.random.default_rng(9)
    new = OccupancyMap(params, center=np.array([0.0, 0.0, 1.0]))
    ref = _Reference(OccupancyMap(params, center=np.array([0.0, 0.0, 1.0])))
    casts = 0
    for k in range(30):
        pos = np.array([-0.6 + 0.12 * k, 0.3 * math.sin(0.4 * k), 1.0 + 0.3 * math.sin(0.3 * k)])
        yaw = 0.5 * math.sin(0.25 * k)
        f = cam.capture(pos, look_rotation(yaw, 0.2 * math.cos(0.5 * k)), k / 30.0)
        if k % 4 == 1:
            f = _spoil(f, rng)
        # the camera near the window's edge now and then (rays leave it through every side)
        centre = pos + (np.array([2.3, -2.0, 1.1]) if k % 5 == 2 else 0.0)
        new.recenter(centre)
        ref.om.recenter(centre)
        no_return = k % 3 != 2
        got = new.ingest_depth(f.depth_m, f.intrinsics, f.position, f.rotation, step, no_return)
        want = ref.ingest_depth(f, step, no_return)
        assert got.accepted
        assert (got.rays, got.masked, got.cells_updated, got.clear_rays) == want
        casts += got.clear_rays
        _same(new, ref.om)
        assert not new._touch.any()  # every mark set back for the next frame
    assert casts > 0
    assert np.count_nonzero(new.logodds >= params.l_occ) > 100
    shadowed = np.count_nonzero((new.logodds.reshape(-1) < _UNKNOWN_BELOW) & (new.surf[:, 3] > 0))
    assert (shadowed > 100) == behind_hits


@pytest.mark.parametrize("behind_hits", [True, False])
def test_point_casting_equals_the_plain_kernel(behind_hits: bool) -> None:
    params = OccupancyParams(
        size_m=(4.0, 4.0, 2.0), floor_z_m=None, occluded_fill_behind_hits=behind_hits
    )
    rng = np.random.default_rng(3)
    new = OccupancyMap(params, center=np.array([0.3, -0.2, 0.5]))
    ref = _Reference(OccupancyMap(params, center=np.array([0.3, -0.2, 0.5])))
    for _ in range(6):
        origin = rng.uniform(-1.0, 1.0, size=3) + np.array([0.3, -0.2, 0.5])
        pts = origin + rng.normal(scale=2.5, size=(3000, 3))
        # a wall seen again and again, some of it outside the window
        pts[:1500, 0] = 1.45
        pts[:1500, 1:] = rng.uniform(-2.5, 2.5, size=(1500, 2))
        pts[rng.integers(0, 3000, size=50)] = np.nan
        pts[rng.integers(0, 3000, size=20)] = origin  # zero length
        got = new.ingest_points(origin, pts)
        want = ref.ingest_points(origin, pts)
        assert (got.rays, got.masked, got.cells_updated) == want
        _same(new, ref.om)
    assert np.count_nonzero(new.logodds >= params.l_occ) > 0
