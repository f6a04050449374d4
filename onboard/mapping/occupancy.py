"""Probabilistic occupancy over a local window that rolls with the drone (a ring buffer).

Cells are cubes of ``resolution_m``; global cell (i, j, k) spans ``[i, i + 1) * res`` etc. The
window holds the cells ``lo + [0, n)`` per axis; cell g lives in storage slot ``g mod n``, so
moving the window only forgets the slabs that leave it (they become unknown) and keeps the rest
where it is.

Each depth frame is ray cast from the camera centre (every ``skip_pixel``-th row and column):
the cell of a measured surface point gets a hit, the cells the ray crossed before it a miss.
Every cell touched by a frame gets exactly one log-odds update for that frame (a hit wins over
misses), clamped to [l_min, l_max]; a cell is occupied at l >= l_occ. One ray is cast per end
cell and frame (rays that end in the same cell converge on the camera through the same cells):
on medium-forest frames this ran 4x faster than casting all 76 800 rays of a 640 x 480 frame at
skip 2 and left 0.7 % of their free cells unknown. (Also stopping a ray at the first cell
another ray crossed, as some implementations do, saved a further 20 % of the time but left
about 10 % unknown, so it is not done.)

A hit also adds the measured point (relative to its cell's centre) to the cell's surface
accumulator; the ESDF uses the mean as the sub-cell position of the surface. The accumulator is
halved when its count reaches 64 (it follows a moving surface) and cleared when the cell turns
more likely free than occupied.

Pixels that report 0, "no return", clear free space along their ray (``no_return_m``), as the
public reference's grid map does (it reads a 0 pixel, and a depth beyond its filter's range, as a
point just past its maximum ray length, so the whole ray turns free). Both the D435 and the
simulated camera report 0 for "nothing within range" (sky, far space) but also for holes,
dropout and surfaces too close to see, and a hole in front of a trunk must not carve free space
through it, so a no-return ray (every ``no_return_step``-th pixel) is cut three ways:

- the image: it stops ``no_return_margin_m`` in front of the nearest measured depth within
  ``no_return_radius_px`` pixels (more than the largest hole; invalid pixels nearby, NaN, inf,
  negative or below the minimum depth, stop it at the camera); a hole inside a trunk's image
  is surrounded by the trunk's own depths, so its ray ends in front of the trunk;
- the map: it stops at the first cell that is not more likely free than occupied (log-odds
  >= 0) or that a ray of this frame hit, so it never lowers an obstacle's cells, whatever the
  pixel really meant;
- the frame: none is cast when less than ``no_return_min_valid`` of the frame's pixels measured
  a depth (a covered lens, an obstacle too close to see filling the view).

The limit: an obstacle the map has never seen that returns nothing over more than the radius,
in a frame that measured enough elsewhere (a texture-less wall or glass for a real D435, a
surface closer than its minimum depth, the D435's invalid band at the left image edge unless
the source masks it as NaN), is cleared like the sky. On the mapping bench (forest-medium seed
1) the rays left the occupied cells and the free cells inside trunks exactly as they were,
made 3.5 times as many cells known, and cost about 0.5 ms of CPU per frame on average (about
1.3 ms on the frames that cast them, every third at 30 frames/s).

What else is never ray cast stays unknown: pixels without a measurement (NaN, inf, negative,
below the minimum depth) mark nothing, so a bad or partial frame can only leave space unknown.

Parameters (``OccupancyParams``) default to the public reference implementation's: 0.1 m cells,
p_hit 0.65, p_miss 0.35, p_min 0.12, p_max 0.90, p_occ 0.80 (log-odds 0.619, -0.619, -1.992,
2.197, 1.386), skip 2 pixels, inflation 0.1 m, depth 0.2-5 m; its rays were cut at 4.5 m, ours
at 5 m (the sensing horizon), and its local update range was 5.5, 5.5, 4.5 m where ours is a
window of 11 x 11 x 4 m, as the issue asks, centred on the drone in x and y and in z held from
0.5 m below the ground up while the drone flies below 2.5 m (``floor_z_m``). ``for_band``
fits the window's vertical extent to the planner's altitude band instead (the flight service
does: the band 0.3-3.1 m plus 0.4 m each side is 3.6 m, the same top, without the four layers
under the ground that hold nothing on flat ground) and has the ESDF computed only for the band's
layers (``esdf_z_m``). A cell starts unknown; its first update starts from probability 0.5
(log-odds 0), so a surface is occupied after 3 hits (three frames, 0.1 s at 30 Hz). A slower
camera gets a heavier hit (``OccupancyParams.for_frame_rate``: one hit at 10 frames/s or fewer),
so that what the drone saw for a tenth of a second is an obstacle at any frame rate.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from onboard.mapping.camera import CameraIntrinsics

UNKNOWN_LOGODDS = np.float32(-100.0)
"""Log-odds value that marks a never-observed cell (below any clamped value)."""
_UNKNOWN_BELOW = -50.0
_BIT_FREE = 1
_BIT_HIT = 2
_BIT_END = 4
_BIT_SHADOW = 8
_SURF_MAX_COUNT = 64.0


def logit(p: float) -> float:
    """log(p / (1 - p))."""
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class OccupancyParams:
    """Occupancy grid parameters (defaults: the reference's, see the module docstring)."""

    resolution_m: float = 0.1
    size_m: tuple[float, float, float] = (11.0, 11.0, 4.0)
    """Window extent (x, y, z): centred on the drone in x and y; in z see ``floor_z_m``."""
    floor_z_m: float | None = -0.5
    """Lowest z the window keeps while the drone flies low: the window's bottom is
    ``max(floor_z_m, z + headroom_m - size_z)``, so it holds the ground and everything on it
    until the drone climbs within ``headroom_m`` of its top, then rises with the drone (a drone
    that climbs and comes down again does not forget the trunks below it). A camera below the
    floor (a drone standing lower than the map's ground) takes the window down with it, a cell
    above its bottom. None: centred on the drone in z too. ``for_band`` sets this, the z
    extent and ``headroom_m`` from an altitude band."""
    headroom_m: float = 1.0
    """Space kept above the drone (with ``floor_z_m``)."""
    esdf_z_m: tuple[float, float] | None = None
    """(z_lo, z_hi): the ESDF covers only the window's layers a point of this z range
    interpolates from (their centres from the last at or below z_lo to the first at or above
    z_hi); the rest of the window still holds the obstacles whose distances they carry, and
    outside the field's box a planner reads unknown space. None: the whole window.
    ``for_band`` sets it to the band."""
    p_hit: float = 0.65
    p_miss: float = 0.35
    p_min: float = 0.12
    p_max: float = 0.90
    p_occ: float = 0.80
    occupied_after_s: float = 0.1
    """How long a surface must be seen to turn occupied: the reference's p_hit needs 3 hits,
    0.1 s at its 30 frames/s, but 1 s at 3 frames/s, and a trunk that enters the view at its
    edge or during a turn may be seen in one or two frames only (on the mapping bench at 3
    frames/s a trunk 1.9 m beside the drone was known, one hit, and free to the planner).
    ``for_frame_rate`` raises p_hit so that ``ceil(occupied_after_s * rate)`` hits (at least
    one) reach ``p_occ``; the misses that clear a cell stay as they are."""
    skip_pixel: int = 2
    """Use every skip_pixel-th row and column of a depth image."""
    max_ray_m: float = 5.0
    """Rays are cut at this length; a cut ray marks only free space (no hit)."""
    inflation_m: float = 0.1
    """Obstacles are inflated by this (the drone's radius) for the map's own collision check."""
    occluded_fill_m: float = 0.4
    """The ESDF counts as occupied never-observed cells within this distance (rounded to whole
    cells, Chebyshev in x and y) of an occupied cell of its layer: an obstacle goes on into the
    shadow behind what the camera saw of it (with ``occluded_fill_behind_hits``, only the cells
    a hit's ray marked). Without it the unseen side of a trunk the drone passes (its limb
    turned away from the camera, which leaves the view before that side faces it) is free
    space to the planner while the space in front of it is observed: on the mapping bench
    (forest-medium seed 1, 3 frames/s, ``bench mapping``'s ``near_overestimate``) 15 % of the
    points near trunks read more than the inflation too far, 0.7 % with the default fill.
    0: off."""
    occluded_fill_behind_hits: bool = True
    """Fill only the never-observed cells that a hit's ray went on into (up to
    ``occluded_fill_m`` behind the hit, at most ``occluded_fill_chord_m`` times the cosine of
    its incidence; one ray per end cell and frame): the hidden side of what was seen. False:
    every never-observed cell near an occupied one, the square rule, which also takes cells
    beside a trunk that no ray passed behind it and reads trunks up to 0.3 m wider where the
    drone flies past them. On the mapping bench (as above) the default reads 2.9 % of the near
    points more than 0.1 m too near against 5.1 % for the square rule at 0.2 m (0.67 against
    0.36 % more than the inflation too far), and the filled field's error is 0.086 against
    0.233 m p95; in mapped fast time (12 seeds, formation change) the shape held better (mean
    e_sim 0.033 against 0.050), re-formed sooner and kept the trunks further (closest 0.324
    against 0.315 m) (BENCHMARKS.md sections 4 and 8, 2026-11-30)."""
    occluded_fill_chord_m: float = 0.7
    """A depth pixel's fill behind its hit reaches at most this times the cosine of its ray's
    incidence on the surface (a cylinder of diameter D is D cos(i) deep along a ray at incidence
    i), so a ray grazing a trunk's limb fills nothing past it; nothing at an edge of the depth
    image (``_incidence_cos``). Point clouds (``ingest_points``) carry no incidence: their
    hits fill the whole ``occluded_fill_m``. 0: the whole length for depth pixels too."""
    no_return_m: float = 5.0
    """Pixels that report 0 ("no return") clear free space along their ray up to this length
    (cut as the module docstring says); 0: they mark nothing."""
    no_return_step: int = 8
    """Cast a no-return ray on every this-many-th pixel row and column (rounded up to a multiple
    of the skip step): at 5 m an 8-pixel step of the D435's 640 px over 87 degrees is 0.10 m,
    one cell (a 4-pixel step cost 60 % more time for the same known space)."""
    no_return_period_s: float = 0.1
    """``LocalMapper`` casts no-return rays on a frame at most this often (by the frames'
    stamps; 0: on every frame): the ESDF whose known mask reads this free space is refreshed at
    10 Hz, and a cell is as free as it gets after 3 misses anyway."""
    no_return_radius_px: int = 48
    """A no-return ray stops ``no_return_margin_m`` in front of the nearest depth measured
    within about this many pixels (searched in blocks of 8: 48 to 55 px). More than the largest
    hole of the simulated D435 (40 px)."""
    no_return_margin_m: float = 0.5
    """... this far in front of it (along the optical axis): more than a trunk's radius (a hole
    in the middle of a trunk's image is closer than the trunk's edges by up to its radius)."""
    no_return_min_valid: float = 0.1
    """No no-return ray is cast when less than this fraction of the frame's pixels (on the skip
    grid) measured a depth."""

    def __post_init__(self) -> None:
        if not self.resolution_m > 0.0:
            raise ValueError("resolution_m must be > 0")
        if len(self.size_m) != 3 or min(self.size_m) < 2 * self.resolution_m:
            raise ValueError("size_m must be 3 extents of at least two cells")
        if not 0.0 < self.p_min < self.p_miss < 0.5 < self.p_hit < 1.0:
            raise ValueError("need 0 < p_min < p_miss < 0.5 < p_hit < 1")
        if not self.p_min < self.p_occ < self.p_max < 1.0:
            raise ValueError("need p_min < p_occ < p_max < 1")
        if not (math.isfinite(self.occupied_after_s) and self.occupied_after_s >= 0.0):
            raise ValueError("occupied_after_s must be >= 0")
        if self.skip_pixel < 1:
            raise ValueError("skip_pixel must be >= 1")
        if not self.max_ray_m > 0.0 or self.inflation_m < 0.0:
            raise ValueError("max_ray_m must be > 0 and inflation_m >= 0")
        if not 0.0 <= self.occluded_fill_m <= 1.0:
            raise ValueError("occluded_fill_m must lie in [0, 1] m")
        if not 0.0 <= self.occluded_fill_chord_m <= 5.0:
            raise ValueError("occluded_fill_chord_m must lie in [0, 5] m")
        if self.floor_z_m is not None and not 0.0 < self.headroom_m < self.size_m[2]:
            raise ValueError("headroom_m must lie in (0, size_z)")
        if self.esdf_z_m is not None:
            lo, hi = self.esdf_z_m
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"esdf_z_m must be finite (low, high), low < high, got {lo}, {hi}")
        if not 0.0 <= self.no_return_m <= self.max_ray_m:
            raise ValueError("no_return_m must lie in [0, max_ray_m]")
        if not self.no_return_period_s >= 0.0:
            raise ValueError("no_return_period_s must be >= 0")
        if self.no_return_step < 1:
            raise ValueError("no_return_step must be >= 1")
        if self.no_return_radius_px < 0:
            raise ValueError("no_return_radius_px must be >= 0")
        if not self.no_return_margin_m >= 0.0:
            raise ValueError("no_return_margin_m must be >= 0")
        if not 0.0 <= self.no_return_min_valid <= 1.0:
            raise ValueError("no_return_min_valid must lie in [0, 1]")

    def for_band(self, z_lo: float, z_hi: float, margin_m: float) -> OccupancyParams:
        """These parameters with the window's vertical extent fitted to the altitude band
        [z_lo, z_hi] (the planner's ``z_limits_m``): from ``margin_m`` below the band to
        ``margin_m`` above it, rounded out to whole cells, held there while the camera flies in
        the band (``floor_z_m``, ``headroom_m`` and the z of ``size_m`` are replaced; above the
        band the window rises with the camera, below the floor it goes down with it, as
        ``floor_z_m`` says), and the ESDF computed only for the band (``esdf_z_m``: the layers
        in the margins only hold obstacles).

        Points of the band are then at least ``margin_m`` from anything outside the window,
        so a planner that only flies the band and only acts on distances below ``margin_m``
        (less half a cell for the interpolation between cell centres) sees what a taller
        window would show it; the field's cells in the band are bit for bit those of the
        window's whole ESDF."""
        if not (math.isfinite(z_lo) and math.isfinite(z_hi) and z_lo < z_hi):
            raise ValueError(f"for_band: need finite z_lo < z_hi, got {z_lo!r}, {z_hi!r}")
        if not (math.isfinite(margin_m) and margin_m > 0.0):
            raise ValueError(f"for_band: margin_m must be > 0, got {margin_m!r}")
        res = self.resolution_m
        bottom = math.floor((z_lo - margin_m) / res + 1e-9)
        top = math.ceil((z_hi + margin_m) / res - 1e-9)
        return dataclasses.replace(
            self,
            size_m=(self.size_m[0], self.size_m[1], (top - bottom) * res),
            floor_z_m=bottom * res,
            headroom_m=top * res - z_hi,
            esdf_z_m=(float(z_lo), float(z_hi)),
        )

    def for_frame_rate(self, rate_hz: float) -> OccupancyParams:
        """These parameters for a camera of ``rate_hz`` frames per second: p_hit raised (never
        lowered) so that ``ceil(occupied_after_s * rate_hz)`` hits, at least one, take a cell
        from unknown to occupied (with a 2 % margin over ``p_occ``, so that the stored float32
        reads occupied). At 30 frames/s the defaults are unchanged (3 hits); at 10 or fewer
        one hit is enough (p_hit 0.65 -> 0.804 at the default p_occ)."""
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"for_frame_rate: rate_hz must be > 0, got {rate_hz!r}")
        hits = max(1, math.ceil(self.occupied_after_s * rate_hz - 1e-9))
        need = 1.02 * self.l_occ / hits
        if self.l_hit >= need:
            return self
        return dataclasses.replace(self, p_hit=1.0 / (1.0 + math.exp(-need)))

    @property
    def occluded_fill_cells(self) -> int:
        """``occluded_fill_m`` in whole cells."""
        return int(round(self.occluded_fill_m / self.resolution_m))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Cells per axis."""
        n = [max(2, int(round(s / self.resolution_m))) for s in self.size_m]
        return n[0], n[1], n[2]

    @property
    def l_hit(self) -> float:
        return logit(self.p_hit)

    @property
    def l_miss(self) -> float:
        return logit(self.p_miss)

    @property
    def l_min(self) -> float:
        return logit(self.p_min)

    @property
    def l_max(self) -> float:
        return logit(self.p_max)

    @property
    def l_occ(self) -> float:
        return logit(self.p_occ)


@dataclass(frozen=True)
class IngestResult:
    """What one frame did to the map. ``accepted`` False: nothing was changed (``reason``)."""

    accepted: bool
    reason: str = ""
    rays: int = 0
    """Pixels ray cast (valid measurements, after skipping)."""
    masked: int = 0
    """Pixels on the skip grid without a valid measurement."""
    cells_updated: int = 0
    clear_rays: int = 0
    """No-return pixels cast as free space (see ``OccupancyParams.no_return_m``)."""
    esdf_changes: int = 0
    """Cells whose state as the ESDF reads it changed: unknown / free / occupied, or hit while
    occupied (its surface point; counted even when the same points again leave the mean as
    it was). 0: the ESDF of the window is what it was, bit for bit."""


@njit(cache=True, nogil=True)
def _wrap(g: int, n: int) -> int:
    s = g % n
    return s + n if s < 0 else s


@njit(cache=True, nogil=True)
def _slot(w: int, s0: int, n: int) -> int:
    """Storage slot of window index w in [0, n) on an axis of n cells whose window starts at
    slot s0 (lo mod n), without a modulo."""
    s = w + s0
    return s - n if s >= n else s


@njit(cache=True, nogil=True)
def _touch(
    touch: np.ndarray, touched: np.ndarray, n_touched: int, idx: int, bits: int
) -> tuple[int, int]:
    """Add bits to cell idx's mark of this frame (0: untouched so far); returns (its previous
    bits, n_touched)."""
    m = touch[idx]
    if m == 0:
        touched[n_touched] = idx
        n_touched += 1
        touch[idx] = bits
        return 0, n_touched
    touch[idx] = m | bits
    return m & 7, n_touched


@njit(cache=True, nogil=True)
def _add_point(
    surf: np.ndarray, idx: int, x: float, y: float, z: float, gx: int, gy: int, gz: int, res: float
) -> None:
    """Add point (x, y, z) of global cell (gx, gy, gz), relative to the cell's centre, to the
    cell's surface accumulator (row idx of surf: sum of offsets and count), halved first when
    its count has reached ``_SURF_MAX_COUNT`` (it forgets slowly: it follows a moving surface)."""
    if surf[idx, 3] >= _SURF_MAX_COUNT:
        for a in range(4):
            surf[idx, a] *= 0.5
    surf[idx, 0] += x - (gx + 0.5) * res
    surf[idx, 1] += y - (gy + 0.5) * res
    surf[idx, 2] += z - (gz + 0.5) * res
    surf[idx, 3] += 1.0


@njit(cache=True, nogil=True)
def _mark_shadow(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    lo: np.ndarray,
    lo_s: np.ndarray,
    res: float,
    o: np.ndarray,
    px: float,
    py: float,
    pz: float,
    length: float,
) -> None:
    """The points p + u * t, t = h, 2h, ... <= length (h half a cell, u the unit ray direction
    from o through p) that lie in the window, in never-observed cells this frame has not
    touched: added to their cells' surface accumulators as a hit's point is added to its cell's.
    A never-observed cell with points lies in the shadow right behind a surface that was hit
    (``OccupancyParams.occluded_fill_behind_hits``); its first hit forgets them, its first
    miss clears them with the rest of its accumulator."""
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    ux = px - o[0]
    uy = py - o[1]
    uz = pz - o[2]
    n = math.sqrt(ux * ux + uy * uy + uz * uz)
    if not n > 0.0:
        return
    ux /= n
    uy /= n
    uz /= n
    h = 0.5 * res
    steps = int(math.floor(length / h + 1e-9))
    for k in range(1, steps + 1):
        t = k * h
        qx = px + ux * t
        qy = py + uy * t
        qz = pz + uz * t
        gx = int(math.floor(qx / res))
        gy = int(math.floor(qy / res))
        gz = int(math.floor(qz / res))
        wx = gx - lo[0]
        wy = gy - lo[1]
        wz = gz - lo[2]
        if not (0 <= wx < nx and 0 <= wy < ny and 0 <= wz < nz):
            return
        sx = _slot(wx, lo_s[0], nx)
        sy = _slot(wy, lo_s[1], ny)
        sz = _slot(wz, lo_s[2], nz)
        idx = (sx * ny + sy) * nz + sz
        if logodds[sx, sy, sz] >= _UNKNOWN_BELOW or touch[idx] != 0:
            continue
        _add_point(surf, idx, qx, qy, qz, gx, gy, gz, res)


@njit(cache=True, nogil=True)
def _end_cell(
    shape: tuple[int, int, int],
    lo: np.ndarray,
    lo_s: np.ndarray,
    res: float,
    px: float,
    py: float,
    pz: float,
) -> tuple[int, int, int, int, int, int, int]:
    """The cell a ray ends in at (px, py, pz) (inside the window, clamped to it): its global
    grid index (gx, gy, gz), storage slots (sx, sy, sz) and flat storage index."""
    nx, ny, nz = shape
    gx = min(max(int(math.floor(px / res)), lo[0]), lo[0] + nx - 1)
    gy = min(max(int(math.floor(py / res)), lo[1]), lo[1] + ny - 1)
    gz = min(max(int(math.floor(pz / res)), lo[2]), lo[2] + nz - 1)
    sx = _slot(gx - lo[0], lo_s[0], nx)
    sy = _slot(gy - lo[1], lo_s[1], ny)
    sz = _slot(gz - lo[2], lo_s[2], nz)
    return gx, gy, gz, sx, sy, sz, (sx * ny + sy) * nz + sz


@njit(cache=True, nogil=True)
def _cast_ray(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    lo: np.ndarray,
    lo_s: np.ndarray,
    res: float,
    o: np.ndarray,
    px: float,
    py: float,
    pz: float,
    hit: bool,
    shadow_len: float,
) -> int:
    """One ray from camera centre o to end point p (both inside the window); returns
    n_touched. The end cell gets a hit (or a miss when ``hit`` is False), the cells between it
    and the camera a miss; nothing more when a ray of this frame already ended in the same
    cell. A hit adds the end point, relative to its cell's centre, to the cell's surface
    accumulator surf (N, 4): sum of offsets and count. A hit with ``shadow_len`` > 0 also marks
    the never-observed cells up to ``shadow_len`` behind it along the ray (``_mark_shadow``),
    unless a ray of this frame that ended in the same cell did."""
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    gx, gy, gz, sx, sy, sz, idx = _end_cell(logodds.shape, lo, lo_s, res, px, py, pz)
    if hit:
        if (touch[idx] & _BIT_HIT) == 0 and logodds[sx, sy, sz] < _UNKNOWN_BELOW:
            # a never-observed cell's first hit (a ray of this frame may have crossed it):
            # forget the shadow points it may hold
            for a in range(4):
                surf[idx, a] = 0.0
        _add_point(surf, idx, px, py, pz, gx, gy, gz, res)
    bits = _BIT_END | (_BIT_HIT if hit else _BIT_FREE)
    prev, n_touched = _touch(touch, touched, n_touched, idx, bits)
    if hit and shadow_len > 0.0 and not (touch[idx] & _BIT_SHADOW):
        # one shadow per end cell and frame, as one ray to the camera (the rays that end in a
        # cell have about the same direction; those at an edge, with none, leave it to others)
        touch[idx] |= _BIT_SHADOW
        _mark_shadow(logodds, surf, touch, lo, lo_s, res, o, px, py, pz, shadow_len)
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
        prev, n_touched = _touch(touch, touched, n_touched, idx, _BIT_FREE)
    return n_touched


@njit(cache=True, nogil=True)
def _cast_free_ray(
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
    l_min: float,
) -> tuple[int, bool]:
    """A no-return ray from camera centre o out to p (both inside the window): the cells it
    crosses get a miss, from the camera's cell on, until it reaches p's cell or a cell that is
    not more likely free than occupied (log-odds >= 0, unknown is -100) or that a ray of this
    frame hit (unless it was as free as a cell gets, ``l_min``: such cells are crossed without
    a look at this frame's marks, for speed); that cell and those behind it are left as they
    are. Nothing is cast when a ray of this frame already ended in p's cell. Returns
    (n_touched, cast)."""
    nx = logodds.shape[0]
    ny = logodds.shape[1]
    nz = logodds.shape[2]
    flat = logodds.reshape(-1)
    floor = l_min + 1e-4
    ex_g = min(max(int(math.floor(px / res)), lo[0]), lo[0] + nx - 1)
    ey_g = min(max(int(math.floor(py / res)), lo[1]), lo[1] + ny - 1)
    ez_g = min(max(int(math.floor(pz / res)), lo[2]), lo[2] + nz - 1)
    end = (_wrap(ex_g, nx) * ny + _wrap(ey_g, ny)) * nz + _wrap(ez_g, nz)
    m = touch[end]
    if m & _BIT_END:
        return n_touched, False
    gx = int(math.floor(o[0] / res))
    gy = int(math.floor(o[1] / res))
    gz = int(math.floor(o[2] / res))
    sx = _wrap(gx, nx)
    sy = _wrap(gy, ny)
    sz = _wrap(gz, nz)
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
            if m & _BIT_HIT:
                break
            bits = _BIT_FREE | (_BIT_END if last else 0)
            prev, n_touched = _touch(touch, touched, n_touched, idx, bits)
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


@njit(cache=True, nogil=True)
def _min_filter_blocks(block: np.ndarray, tmp: np.ndarray, out: np.ndarray, r: int) -> None:
    """out[i, j] = min of block over the (2 r + 1)^2 blocks around (i, j) (separable)."""
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


@njit(cache=True, nogil=True)
def _clip_to_window(
    o: np.ndarray, dx: float, dy: float, dz: float, box_lo: np.ndarray, box_hi: np.ndarray
) -> float:
    """Largest s in [0, 1] with o + s d inside the box (o is inside)."""
    s = 1.0
    d3 = (dx, dy, dz)
    for a in range(3):
        if d3[a] > 0.0:
            s = min(s, (box_hi[a] - o[a]) / d3[a])
        elif d3[a] < 0.0:
            s = min(s, (box_lo[a] - o[a]) / d3[a])
    return max(s, 0.0)


@njit(cache=True, nogil=True)
def _clip_ray(
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
    """Fraction s of the ray o + t (dx, dy, dz) to cast: cut at ``max_ray`` metres and just inside
    the window box; a cut ray ends in free space (no hit)."""
    s = 1.0
    if length > max_ray:
        s = max_ray / length
        hit = False
    # the usual ray ends well inside the window: no clipping to compute (1e-6 m is far more
    # than the rounding of o + d, so the box test below would give s_box > 1 >= s)
    ex = o[0] + dx
    ey = o[1] + dy
    ez = o[2] + dz
    m = 1e-6
    if (
        box_lo[0] + m < ex < box_hi[0] - m
        and box_lo[1] + m < ey < box_hi[1] - m
        and box_lo[2] + m < ez < box_hi[2] - m
    ):
        return s, hit
    s_box = _clip_to_window(o, dx, dy, dz, box_lo, box_hi)
    if s_box < s:
        s = max(s_box - eps / length, 0.0)
        hit = False
    return s, hit


@njit(cache=True, nogil=True)
def _apply_updates(
    logodds: np.ndarray,
    surf: np.ndarray,
    touch: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    l_occ: float,
) -> int:
    """One log-odds update per cell the frame touched (a hit wins over misses), and the
    cell's mark set back to 0 for the next frame. Returns the number of cells whose state as
    the ESDF reads it changed: unknown / free / occupied, or hit while occupied after the
    frame (its surface point; the ESDF reads the surface points of occupied cells only, and
    a cell that turns free forgets its own)."""
    flat = logodds.reshape(-1)
    changed = 0
    for i in range(n_touched):
        idx = touched[i]
        m = touch[idx]
        touch[idx] = 0
        v = flat[idx]
        was_known = v > _UNKNOWN_BELOW
        was_occ = v >= l_occ
        if v < _UNKNOWN_BELOW:
            v = 0.0
        v += l_hit if (m & _BIT_HIT) else l_miss
        v = min(max(v, l_min), l_max)
        flat[idx] = v
        if v < 0.0:  # more likely free than not: drop the surface estimate
            for a in range(4):
                surf[idx, a] = 0.0
        is_occ = flat[idx] >= l_occ  # as the ESDF will read it (the stored float32)
        if not was_known or is_occ != was_occ or (is_occ and (m & _BIT_HIT)):
            changed += 1
    return changed


@njit(cache=True, nogil=True)
def _incidence_cos(
    depth: np.ndarray, u: int, v: int, g: int, xn: np.ndarray, yn: np.ndarray
) -> float:
    """|cos| of the angle between pixel (v, u)'s ray and the surface's normal there, from the
    points of the pixels g to each side (central differences; one-sided at the image's edge);
    0 where a neighbour has no valid depth or lies more than 4 g pixels' width away in depth
    (an edge: the ray grazes the surface or passes beside it)."""
    h = depth.shape[0]
    w = depth.shape[1]
    z = depth[v, u]
    ua = max(u - g, 0)
    ub = min(u + g, w - 1)
    va = max(v - g, 0)
    vb = min(v + g, h - 1)
    if ua == ub or va == vb:
        return 0.0
    za = depth[v, ua]
    zb = depth[v, ub]
    zc = depth[va, u]
    zd = depth[vb, u]
    jump = 4.0 * g * (xn[1] - xn[0]) * z
    for q in (za, zb, zc, zd):
        if not (q > 0.0 and q < 1e30) or abs(q - z) > jump:
            return 0.0
    # tangents along the row and the column (camera frame)
    ax = xn[ub] * zb - xn[ua] * za
    ay = yn[v] * (zb - za)
    az = zb - za
    bx = xn[u] * (zd - zc)
    by = yn[vb] * zd - yn[va] * zc
    bz = zd - zc
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    rx = xn[u]
    ry = yn[v]
    rn = math.sqrt(rx * rx + ry * ry + 1.0)
    if not nn > 0.0:
        return 0.0
    return abs(nx * rx + ny * ry + nz) / (nn * rn)


@njit(cache=True, nogil=True)
def ingest_depth_kernel(
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
    l_occ: float,
    nr_len: float,
    nr_step: int,
    nr_margin: float,
    nr_min_valid: float,
    nr_block: int,
    nr_radius: int,
    blocks: np.ndarray,
    blocks_tmp: np.ndarray,
    blocks_near: np.ndarray,
    shadow_len: float,
    shadow_chord: float,
) -> tuple[int, int, int, int, int]:
    """Ray cast one depth image (height, width) float32 into the window; returns (rays,
    masked pixels, cells updated, no-return rays, cells changed for the ESDF: see
    ``_apply_updates``). Pixels with depth not in [min_depth, inf)
    are skipped; depths above max_depth and rays longer than max_ray mark free space only.

    No-return rays (``nr_len`` > 0; see the module docstring): pixels that are exactly 0, every
    ``nr_step``-th (a multiple of ``step``), cast free space up to ``nr_len`` metres, stopped
    ``nr_margin`` in front of the nearest depth measured within ``nr_radius`` blocks of
    ``nr_block`` pixels (arrays ``blocks*`` of shape (ceil(height / nr_block), ceil(width /
    nr_block)), scratch) and by the map (``_cast_free_ray``); none when fewer than
    ``nr_min_valid`` of the pixels measured a depth."""
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
    lo_s = np.empty(3, dtype=np.int64)
    lo_s[0] = _wrap(lo[0], nx)
    lo_s[1] = _wrap(lo[1], ny)
    lo_s[2] = _wrap(lo[2], nz)
    n_touched = 0
    rays = 0
    masked = 0
    track = nr_len > 0.0
    # block of each pixel column (no division per pixel)
    bu = np.zeros(depth.shape[1], dtype=np.int64)
    if track:
        blocks[:, :] = np.inf
        for u in range(depth.shape[1]):
            bu[u] = u // nr_block
    for v in range(0, depth.shape[0], step):
        bv = v // nr_block if track else 0
        for u in range(0, depth.shape[1], step):
            z = depth[v, u]
            if not (z >= min_depth) or z > 1e30:
                masked += 1
                if track and z != 0.0:  # an invalid value, not "no return": stop rays here
                    blocks[bv, bu[u]] = 0.0
                continue
            rays += 1
            if track and z < blocks[bv, bu[u]]:
                blocks[bv, bu[u]] = z
            xc = xn[u] * z
            yc = yn[v] * z
            dx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2] * z
            dy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2] * z
            dz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2] * z
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            hit = z <= max_depth
            s, hit = _clip_ray(o, dx, dy, dz, length, max_ray, box_lo, box_hi, eps, hit)
            px = o[0] + s * dx
            py = o[1] + s * dy
            pz = o[2] + s * dz
            sl = shadow_len
            if hit and sl > 0.0 and shadow_chord > 0.0:
                # the incidence cuts the shadow only of the ray that marks it, the first hit in
                # its end cell this frame (_cast_ray); the others would compute it for nothing
                end = _end_cell(logodds.shape, lo, lo_s, res, px, py, pz)[6]
                if not (touch[end] & _BIT_SHADOW):
                    sl = min(sl, shadow_chord * _incidence_cos(depth, u, v, 2 * step, xn, yn))
            n_touched = _cast_ray(
                logodds, surf, touch, touched, n_touched, lo, lo_s, res, o, px, py, pz, hit, sl
            )
    clear = 0
    if track and rays > 0 and rays >= nr_min_valid * (rays + masked):
        _min_filter_blocks(blocks, blocks_tmp, blocks_near, nr_radius)
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
                s = _clip_to_window(o, dx, dy, dz, box_lo, box_hi)
                if s < 1.0:
                    s = max(s - eps / (zc * norm), 0.0)
                n_touched, cast = _cast_free_ray(
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
                    l_min,
                )
                clear += 1 if cast else 0
    changed = _apply_updates(
        logodds, surf, touch, touched, n_touched, l_hit, l_miss, l_min, l_max, l_occ
    )
    return rays, masked, n_touched, clear, changed


@njit(cache=True, nogil=True)
def ingest_points_kernel(
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
    l_occ: float,
    shadow_len: float,
) -> tuple[int, int, int, int]:
    """Ray cast measured surface points (K, 3) seen from o; returns (rays, skipped, cells,
    cells changed for the ESDF: see ``_apply_updates``)."""
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
    lo_s = np.empty(3, dtype=np.int64)
    lo_s[0] = _wrap(lo[0], nx)
    lo_s[1] = _wrap(lo[1], ny)
    lo_s[2] = _wrap(lo[2], nz)
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
        s, hit = _clip_ray(o, dx, dy, dz, length, max_ray, box_lo, box_hi, eps, hit)
        n_touched = _cast_ray(
            logodds,
            surf,
            touch,
            touched,
            n_touched,
            lo,
            lo_s,
            res,
            o,
            o[0] + s * dx,
            o[1] + s * dy,
            o[2] + s * dz,
            hit,
            shadow_len,
        )
    changed = _apply_updates(
        logodds, surf, touch, touched, n_touched, l_hit, l_miss, l_min, l_max, l_occ
    )
    return rays, skipped, n_touched, changed


class OccupancyMap:
    """Log-odds occupancy over a rolling window (see the module docstring)."""

    def __init__(
        self, params: OccupancyParams | None = None, center: np.ndarray | None = None
    ) -> None:
        self.params = params if params is not None else OccupancyParams()
        self.shape = self.params.shape
        self.res = self.params.resolution_m
        self.logodds = np.full(self.shape, UNKNOWN_LOGODDS, dtype=np.float32)
        # per cell (flat storage order): sum of hit offsets from the cell centre (3) and count
        self.surf = np.zeros((int(np.prod(self.shape)), 4), dtype=np.float32)
        # per cell (flat storage order): what the frame being cast did to it (free / hit / end
        # bits, 0: nothing); the cells it touched are listed in _touched and set back to 0 as
        # the frame's updates are applied (one byte a cell: the marks stay in the caches)
        self._touch = np.zeros(int(np.prod(self.shape)), dtype=np.uint8)
        self._touched = np.empty(int(np.prod(self.shape)), dtype=np.int64)
        # how far behind a hit its ray marks never-observed cells (``_mark_shadow``; 0: not)
        fill_rays = self.params.occluded_fill_behind_hits and self.params.occluded_fill_m > 0.0
        self._shadow_len = float(self.params.occluded_fill_m) if fill_rays else 0.0
        self.frames = 0
        c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
        self.lo = self._lo_for(c)
        p = self.params
        self._l = (p.l_hit, p.l_miss, p.l_min, p.l_max)
        self._coords_of: CameraIntrinsics | None = None  # normalised pixel coordinates of it
        self._coords: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))
        empty = np.zeros((0, 0), dtype=np.float32)
        self._blocks: tuple[np.ndarray, ...] = (empty, empty, empty)  # no-return scratch

    # --- geometry ---------------------------------------------------------------------------

    def _lo_for(self, center: np.ndarray) -> np.ndarray:
        c = np.asarray(center, dtype=np.float64)
        g = np.floor(c / self.res).astype(np.int64)
        lo = g - np.array(self.shape, dtype=np.int64) // 2
        p = self.params
        if p.floor_z_m is not None:
            z = float(c[2])
            bottom = max(p.floor_z_m, z + p.headroom_m - self.shape[2] * self.res)
            # a camera below the floor: the window goes down with it (else every frame would
            # be refused as taken outside the window)
            bottom = min(bottom, z - self.res)
            lo[2] = int(math.floor(bottom / self.res + 1e-9))
        return lo

    @property
    def origin(self) -> np.ndarray:
        """Lower corner of the window (metres)."""
        return self.lo.astype(np.float64) * self.res

    @property
    def upper(self) -> np.ndarray:
        """Upper corner of the window (metres)."""
        return (self.lo + np.array(self.shape)).astype(np.float64) * self.res

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Bool (K,): inside the window box."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.all((p >= self.origin) & (p < self.upper), axis=1)

    def storage_index(self, g: np.ndarray) -> tuple[np.ndarray, ...]:
        """Storage slots of global cells g (K, 3) (they must be inside the window)."""
        g = np.asarray(g, dtype=np.int64).reshape(-1, 3)
        n = np.array(self.shape, dtype=np.int64)
        s = np.mod(g, n)
        return s[:, 0], s[:, 1], s[:, 2]

    def recenter(self, center: np.ndarray) -> int:
        """Move the window to be centred on ``center``; cells that leave it are forgotten.
        Returns the number of planes (x, y and z slabs one cell thick) cleared."""
        new = self._lo_for(center)
        cleared = 0
        for a in range(3):
            n = self.shape[a]
            shift = int(new[a] - self.lo[a])
            if shift == 0:
                continue
            if abs(shift) >= n:
                gone = np.arange(n)
            elif shift > 0:
                gone = np.mod(np.arange(self.lo[a], self.lo[a] + shift), n)
            else:
                gone = np.mod(np.arange(new[a] + n, self.lo[a] + n), n)
            idx: list[slice | np.ndarray] = [slice(None)] * 3
            idx[a] = gone
            self.logodds[tuple(idx)] = UNKNOWN_LOGODDS
            self.surf.reshape(*self.shape, 4)[tuple(idx)] = 0.0
            cleared += int(gone.shape[0])
        self.lo = new
        return cleared

    # --- updates ----------------------------------------------------------------------------

    def ingest_depth(
        self,
        depth: np.ndarray,
        intrinsics: CameraIntrinsics,
        position: np.ndarray,
        rotation: np.ndarray,
        step: int | None = None,
        no_return: bool = True,
        decimation: int = 1,
    ) -> IngestResult:
        """Ray cast a depth image (float32 metres along the optical axis) taken from the pose:
        0 is "no return" (free space along the ray, cut as the module docstring says, unless
        ``no_return`` is False); NaN, inf, negative and below-minimum values mark nothing.
        ``step`` and the parameters in pixels are the camera's: of an image of its every
        ``decimation``-th pixel (``intrinsics`` that image's), every (step / decimation)-th
        pixel is cast, so that it marks what the full image would (step a multiple of it).

        The camera centre must be inside the window (``recenter`` first); otherwise the frame
        is refused. See ``LocalMapper.ingest`` for frame validation."""
        o = np.ascontiguousarray(position, dtype=np.float64)
        if not bool(self.contains(o[None, :])[0]):
            return IngestResult(False, "camera outside the map window")
        d = np.ascontiguousarray(depth, dtype=np.float32)
        if self._coords_of != intrinsics:
            self._coords = intrinsics.normalized_coords()
            self._coords_of = intrinsics
        xn, yn = self._coords
        p = self.params
        k = p.skip_pixel if step is None else int(step)
        if k < 1:
            raise ValueError(f"step must be >= 1, got {k}")
        dec = int(decimation)
        if dec < 1 or k % dec:
            raise ValueError(f"step {k} must be a multiple of the decimation {dec}")
        # no-return rays and the depth blocks on the skip grid only (a simulated frame renders
        # nothing else), blocks of at least 8 pixels; in the camera's pixels, then this image's
        k_nr = k * -(-p.no_return_step // k)
        block = k * -(-8 // k)
        radius_blocks = -(-p.no_return_radius_px // block)
        k, k_nr, block = k // dec, k_nr // dec, block // dec
        shape = (-(-d.shape[0] // block), -(-d.shape[1] // block))
        if self._blocks[0].shape != shape:
            self._blocks = tuple(np.empty(shape, dtype=np.float32) for _ in range(3))
        rays, masked, cells, clear, changed = ingest_depth_kernel(
            self.logodds,
            self.surf,
            self._touch,
            self._touched,
            self.lo,
            self.res,
            d,
            k,
            xn,
            yn,
            np.ascontiguousarray(rotation, dtype=np.float64),
            o,
            intrinsics.min_depth_m,
            intrinsics.max_depth_m,
            p.max_ray_m,
            *self._l,
            p.l_occ,
            p.no_return_m if no_return else 0.0,
            k_nr,
            p.no_return_margin_m,
            p.no_return_min_valid,
            block,
            radius_blocks,
            *self._blocks,
            self._shadow_len,
            p.occluded_fill_chord_m,
        )
        self.frames += 1
        return IngestResult(True, "", int(rays), int(masked), int(cells), int(clear), int(changed))

    def ingest_points(self, origin: np.ndarray, points: np.ndarray) -> IngestResult:
        """Ray cast measured surface points (K, 3) (world frame) seen from ``origin``: e.g. a
        back-projected, downsampled cloud. Non-finite points are skipped."""
        o = np.ascontiguousarray(origin, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(o)):
            return IngestResult(False, "sensor origin is not finite")
        if not bool(self.contains(o[None, :])[0]):
            return IngestResult(False, "sensor origin outside the map window")
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            return IngestResult(False, f"points must have shape (K, 3), got {pts.shape}")
        rays, skipped, cells, changed = ingest_points_kernel(
            self.logodds,
            self.surf,
            self._touch,
            self._touched,
            self.lo,
            self.res,
            o,
            pts,
            self.params.max_ray_m,
            *self._l,
            self.params.l_occ,
            self._shadow_len,
        )
        self.frames += 1
        return IngestResult(True, "", int(rays), int(skipped), int(cells), 0, int(changed))

    # --- reading ----------------------------------------------------------------------------

    def window_logodds(self) -> np.ndarray:
        """Log-odds in window order (index 0 = cell ``lo``), a copy."""
        out = self.logodds
        for a in range(3):
            out = np.roll(out, -int(self.lo[a] % self.shape[a]), axis=a)
        return np.array(out, copy=True)

    def known(self) -> np.ndarray:
        """Bool grid in window order: observed at least once."""
        return self.window_logodds() > _UNKNOWN_BELOW

    def occupied(self) -> np.ndarray:
        """Bool grid in window order: log-odds >= l_occ."""
        return self.window_logodds() >= self.params.l_occ

    def cell_centres(self) -> np.ndarray:
        """Centres (nx, ny, nz, 3) of the window's cells in window order."""
        axes = [(self.lo[a] + np.arange(self.shape[a]) + 0.5) * self.res for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def surface_points(self) -> np.ndarray:
        """Occupied cells as points (K, 3): the mean measured surface point of each (its centre
        when it has none)."""
        n = np.array(self.shape, dtype=np.int64)
        s = np.argwhere(self.logodds >= self.params.l_occ)
        g = self.lo + np.mod(s - self.lo, n)  # global index of each storage slot in the window
        flat = np.ravel_multi_index((s[:, 0], s[:, 1], s[:, 2]), self.shape)
        acc = self.surf[flat].astype(np.float64)
        cnt = acc[:, 3:4]
        off = np.divide(acc[:, :3], cnt, out=np.zeros_like(acc[:, :3]), where=cnt > 0)
        return (g + 0.5) * self.res + off

    def state_at(self, points: np.ndarray) -> np.ndarray:
        """Per point (K,): -1 unknown or outside the window, 0 free, 1 occupied."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape[0], -1, dtype=np.int8)
        inside = self.contains(p)
        g = np.floor(p[inside] / self.res).astype(np.int64)
        v = self.logodds[self.storage_index(g)]
        st = np.where(v >= self.params.l_occ, 1, 0).astype(np.int8)
        st[v < _UNKNOWN_BELOW] = -1
        out[inside] = st
        return out
