"""World model: solid primitives in ENU metres and their exact signed distance.

Primitives (all float64, one row each):

- cylinders (K, 5): ``[x, y, radius, z_min, z_max]``, vertical finite solid cylinders;
- rings (R, 7): ``[cx, cy, cz, yaw, radius_horizontal, radius_vertical, tube_radius]``, an
  elliptical tube in the vertical plane whose normal is ``n = (cos yaw, sin yaw, 0)``; the ellipse
  has semi-axis ``radius_horizontal`` along ``u = (-sin yaw, cos yaw, 0)`` and ``radius_vertical``
  along ``z``; the signed distance is the 3-D distance to the ellipse curve minus ``tube_radius``;
- boxes (B, 6): ``[x_min, y_min, z_min, x_max, y_max, z_max]``, axis-aligned solid boxes;
- ground: the half-space ``z < ground_z`` is solid (distance ``z - ground_z``) unless absent.

Signed distances are negative inside a solid; the gradient is the unit vector of steepest ascent.
This is the ground truth the obstacle cost J_o of the paper (Sec. IV) is evaluated against when
no mapped ESDF is used.

The world model knows nothing of the planner: the planner's exact field of a world is
``onboard.planner.field.AnalyticField(world)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

FAR_DISTANCE_M = 1.0e6  # distance reported when there is nothing at all in the world
CYLINDER_COLS = 5
RING_COLS = 7
BOX_COLS = 6
_NEWTON_MAX_ITERS = 100


# --------------------------------------------------------------------------------------------
# Per-primitive signed distances (value and unit gradient)
# --------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def cylinder_distance(
    cx: float, cy: float, radius: float, z_min: float, z_max: float, x: float, y: float, z: float
) -> tuple[float, float, float, float]:
    """Exact signed distance and gradient of a vertical finite solid cylinder."""
    dx = x - cx
    dy = y - cy
    r = math.sqrt(dx * dx + dy * dy)
    if r > 0.0:
        ux = dx / r
        uy = dy / r
    else:  # on the axis: every horizontal direction is steepest, take +x
        ux = 1.0
        uy = 0.0
    dr = r - radius
    below = z_min - z
    above = z - z_max
    if above >= below:
        dz = above
        sz = 1.0
    else:
        dz = below
        sz = -1.0
    if dr > 0.0 and dz > 0.0:  # nearest point on a rim
        d = math.sqrt(dr * dr + dz * dz)
        return d, dr * ux / d, dr * uy / d, dz * sz / d
    if dr >= dz:  # side is nearest (outside beside it, or inside closer to the side)
        return dr, ux, uy, 0.0
    return dz, 0.0, 0.0, sz


@njit(cache=True, nogil=True)
def box_distance(
    lo_x: float,
    lo_y: float,
    lo_z: float,
    hi_x: float,
    hi_y: float,
    hi_z: float,
    x: float,
    y: float,
    z: float,
) -> tuple[float, float, float, float]:
    """Exact signed distance and gradient of an axis-aligned solid box."""
    # per axis: signed distance to the slab and the outward direction of the nearer face
    qx = max(lo_x - x, x - hi_x)
    sx = -1.0 if lo_x - x > x - hi_x else 1.0
    qy = max(lo_y - y, y - hi_y)
    sy = -1.0 if lo_y - y > y - hi_y else 1.0
    qz = max(lo_z - z, z - hi_z)
    sz = -1.0 if lo_z - z > z - hi_z else 1.0
    if qx > 0.0 or qy > 0.0 or qz > 0.0:
        px = max(qx, 0.0)
        py = max(qy, 0.0)
        pz = max(qz, 0.0)
        d = math.sqrt(px * px + py * py + pz * pz)
        return d, px * sx / d, py * sy / d, pz * sz / d
    if qx >= qy and qx >= qz:
        return qx, sx, 0.0, 0.0
    if qy >= qz:
        return qy, 0.0, sy, 0.0
    return qz, 0.0, 0.0, sz


@njit(cache=True, nogil=True)
def ellipse_closest_point(e0: float, e1: float, y0: float, y1: float) -> tuple[float, float]:
    """Closest point ``(x0, x1)`` on the ellipse ``(x0/e0)^2 + (x1/e1)^2 = 1`` to ``(y0, y1)``.

    Requires ``e0 >= e1 > 0`` and ``y0, y1 >= 0`` (first quadrant; callers reflect).
    Method of Eberly ("Distance from a point to an ellipse"): the closest point is
    ``x0 = r0 y0 / (u + r0 - 1)``, ``x1 = y1 / u`` with ``r0 = (e0/e1)^2`` and ``u > 0`` the root of
    ``F(u) = (r0 z0 / (u + r0 - 1))^2 + (z1 / u)^2 - 1`` (``z = y / e``). F is convex and
    decreasing, so Newton's method started left of the root (where F >= 0) increases
    monotonically to it without overshoot. The parameter ``u = s + 1`` of Eberly's ``s`` keeps
    full relative precision near the major axis.
    """
    if y1 > 0.0:
        if y0 > 0.0:
            z0 = y0 / e0
            z1 = y1 / e1
            r0 = (e0 / e1) * (e0 / e1)
            rm1 = (e0 - e1) * (e0 + e1) / (e1 * e1)  # r0 - 1 without cancellation
            n0 = r0 * z0
            # each term of F alone reaches 1 at these u; F >= 0 at the larger one (left of root)
            u = max(z1, n0 - rm1)
            for _ in range(_NEWTON_MAX_ITERS):
                a = n0 / (u + rm1)
                b = z1 / u
                f = a * a + b * b - 1.0
                if f <= 0.0:
                    break
                slope = 2.0 * (a * a / (u + rm1) + b * b / u)  # -F'(u) > 0
                u_new = u + f / slope
                if u_new == u:
                    break
                u = u_new
            return r0 * y0 / (u + rm1), y1 / u
        return 0.0, e1  # on the minor axis
    # on the major axis (y1 == 0): the closest point leaves the axis when y0 is small enough
    numer = e0 * y0
    denom = (e0 - e1) * (e0 + e1)
    if numer < denom:
        xde0 = numer / denom
        return e0 * xde0, e1 * math.sqrt(max(1.0 - xde0 * xde0, 0.0))
    return e0, 0.0


@njit(cache=True, nogil=True)
def ring_distance(
    cx: float,
    cy: float,
    cz: float,
    yaw: float,
    radius_h: float,
    radius_v: float,
    tube: float,
    x: float,
    y: float,
    z: float,
) -> tuple[float, float, float, float]:
    """Signed distance and gradient of an elliptical tube in a vertical plane.

    d = sqrt(dist_inplane^2 + n_component^2) - tube where dist_inplane is the 2-D distance from the
    point's projection on the ring plane to the ellipse curve.
    """
    nx = math.cos(yaw)
    ny = math.sin(yaw)
    px = x - cx
    py = y - cy
    pz = z - cz
    a = -ny * px + nx * py  # along u = (-sin yaw, cos yaw, 0)
    b = pz  # along z
    w = nx * px + ny * py  # along the plane normal
    ya = abs(a)
    yb = abs(b)
    if radius_h == radius_v:
        rho = math.sqrt(ya * ya + yb * yb)
        if rho > 0.0:
            qa = radius_h * ya / rho
            qb = radius_h * yb / rho
        else:
            qa = 0.0
            qb = radius_h
    elif radius_h > radius_v:
        qa, qb = ellipse_closest_point(radius_h, radius_v, ya, yb)
    else:
        qb, qa = ellipse_closest_point(radius_v, radius_h, yb, ya)
    # vector from the closest curve point (reflected back to the point's quadrant; a point on
    # an axis takes the + side) to the point, in (u, z, n) coordinates
    va = ya - qa if a >= 0.0 else qa - ya
    vb = yb - qb if b >= 0.0 else qb - yb
    dist = math.sqrt(va * va + vb * vb + w * w)
    if dist > 0.0:
        ga = va / dist
        gb = vb / dist
        gw = w / dist
    else:  # on the curve itself: any unit vector, take the plane normal
        ga = 0.0
        gb = 0.0
        gw = 1.0
    gx = -ny * ga + nx * gw
    gy = nx * ga + ny * gw
    return dist - tube, gx, gy, gb


@njit(cache=True, nogil=True)
def primitives_distance(
    cylinders: np.ndarray,
    rings: np.ndarray,
    boxes: np.ndarray,
    ground_z: float,
    x: float,
    y: float,
    z: float,
) -> tuple[float, float, float, float]:
    """Signed distance ``d`` and unit gradient ``(gx, gy, gz)`` of the union of all primitives.

    cylinders (K, 5), rings (R, 7), boxes (B, 6) as in the module docstring; ``ground_z`` NaN
    means no ground. The union's distance is the minimum over primitives (exact outside the
    solids and inside a single solid). Nothing at all: ``(FAR_DISTANCE_M, 0, 0, 0)``.
    Only the nearest primitive's gradient is computed; primitives that cannot beat the current
    minimum are rejected by a cheap lower bound.
    """
    best = FAR_DISTANCE_M
    kind = -1  # 0 ground, 1 cylinder, 2 ring, 3 box
    index = 0
    if not math.isnan(ground_z):
        best = z - ground_z
        kind = 0
    for k in range(cylinders.shape[0]):
        dx = x - cylinders[k, 0]
        dy = y - cylinders[k, 1]
        r2 = dx * dx + dy * dy
        rad = cylinders[k, 2]
        # lower bound r - radius >= best: cannot be nearer (only valid when best + rad > 0)
        lim = best + rad
        if lim > 0.0 and r2 >= lim * lim:
            continue
        d = cylinder_distance(
            cylinders[k, 0], cylinders[k, 1], rad, cylinders[k, 3], cylinders[k, 4], x, y, z
        )[0]
        if d < best:
            best = d
            kind = 1
            index = k
    for k in range(rings.shape[0]):
        dx = x - rings[k, 0]
        dy = y - rings[k, 1]
        dz = z - rings[k, 2]
        # every curve point is within max(radii) of the centre
        lim = best + rings[k, 6] + max(rings[k, 4], rings[k, 5])
        if lim > 0.0 and dx * dx + dy * dy + dz * dz >= lim * lim:
            continue
        d = ring_distance(
            rings[k, 0],
            rings[k, 1],
            rings[k, 2],
            rings[k, 3],
            rings[k, 4],
            rings[k, 5],
            rings[k, 6],
            x,
            y,
            z,
        )[0]
        if d < best:
            best = d
            kind = 2
            index = k
    for k in range(boxes.shape[0]):
        d = box_distance(
            boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3], boxes[k, 4], boxes[k, 5], x, y, z
        )[0]
        if d < best:
            best = d
            kind = 3
            index = k
    if kind == 0:
        return best, 0.0, 0.0, 1.0
    if kind == 1:
        c = cylinders[index]
        return cylinder_distance(c[0], c[1], c[2], c[3], c[4], x, y, z)
    if kind == 2:
        g = rings[index]
        return ring_distance(g[0], g[1], g[2], g[3], g[4], g[5], g[6], x, y, z)
    if kind == 3:
        b = boxes[index]
        return box_distance(b[0], b[1], b[2], b[3], b[4], b[5], x, y, z)
    return best, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def primitives_distance_many(
    cylinders: np.ndarray, rings: np.ndarray, boxes: np.ndarray, ground_z: float, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``primitives_distance`` at each row of points (K, 3): d (K,), grad (K, 3)."""
    n = points.shape[0]
    d = np.empty(n)
    g = np.empty((n, 3))
    for i in range(n):
        d[i], g[i, 0], g[i, 1], g[i, 2] = primitives_distance(
            cylinders, rings, boxes, ground_z, points[i, 0], points[i, 1], points[i, 2]
        )
    return d, g


@njit(cache=True, nogil=True)
def _each_primitive_distance(
    cylinders: np.ndarray, rings: np.ndarray, boxes: np.ndarray, x: float, y: float, z: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of one point to every primitive separately: (K,), (R,), (B,)."""
    dc = np.empty(cylinders.shape[0])
    for k in range(cylinders.shape[0]):
        c = cylinders[k]
        dc[k] = cylinder_distance(c[0], c[1], c[2], c[3], c[4], x, y, z)[0]
    dr = np.empty(rings.shape[0])
    for k in range(rings.shape[0]):
        g = rings[k]
        dr[k] = ring_distance(g[0], g[1], g[2], g[3], g[4], g[5], g[6], x, y, z)[0]
    db = np.empty(boxes.shape[0])
    for k in range(boxes.shape[0]):
        b = boxes[k]
        db[k] = box_distance(b[0], b[1], b[2], b[3], b[4], b[5], x, y, z)[0]
    return dc, dr, db


# --------------------------------------------------------------------------------------------
# World
# --------------------------------------------------------------------------------------------


def _as_rows(name: str, value: object, cols: int) -> np.ndarray:
    arr = np.array(value, dtype=np.float64, copy=True)
    if arr.size == 0:
        arr = arr.reshape(0, cols)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise ValueError(f"World.{name} must have shape (N, {cols}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"World.{name} contains non-finite values")
    arr = np.ascontiguousarray(arr)
    arr.setflags(write=False)
    return arr


def _union_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of a then b, without exact duplicates, first occurrence order kept."""
    c = np.concatenate([a, b], axis=0)
    if c.shape[0] == 0:
        return c
    _, first = np.unique(c, axis=0, return_index=True)
    return c[np.sort(first)]


@dataclass(frozen=True, eq=False)
class World:
    """Solid primitives in ENU metres (see the module docstring for the row layouts).

    cylinders (K, 5), rings (R, 7), boxes (B, 6): float64, stored read-only and C-contiguous.
    ground_z: height of the solid ground plane, None for no ground.
    """

    cylinders: np.ndarray
    rings: np.ndarray
    boxes: np.ndarray
    ground_z: float | None = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        cyl = _as_rows("cylinders", self.cylinders, CYLINDER_COLS)
        rings = _as_rows("rings", self.rings, RING_COLS)
        boxes = _as_rows("boxes", self.boxes, BOX_COLS)
        bad = np.flatnonzero(cyl[:, 2] <= 0.0)
        if bad.size:
            raise ValueError(f"World.cylinders: radius must be > 0 (rows {bad.tolist()})")
        bad = np.flatnonzero(cyl[:, 3] >= cyl[:, 4])
        if bad.size:
            raise ValueError(f"World.cylinders: z_min must be < z_max (rows {bad.tolist()})")
        bad = np.flatnonzero((rings[:, 4] <= 0.0) | (rings[:, 5] <= 0.0))
        if bad.size:
            raise ValueError(f"World.rings: ellipse radii must be > 0 (rows {bad.tolist()})")
        bad = np.flatnonzero(rings[:, 6] < 0.0)
        if bad.size:
            raise ValueError(f"World.rings: tube radius must be >= 0 (rows {bad.tolist()})")
        bad = np.flatnonzero(np.any(boxes[:, :3] >= boxes[:, 3:], axis=1))
        if bad.size:
            raise ValueError(f"World.boxes: min must be < max on every axis (rows {bad.tolist()})")
        gz = self.ground_z
        if gz is not None:
            gz = float(gz)
            if not math.isfinite(gz):
                raise ValueError("World.ground_z must be finite or None")
        object.__setattr__(self, "cylinders", cyl)
        object.__setattr__(self, "rings", rings)
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "ground_z", gz)
        object.__setattr__(self, "name", str(self.name))

    @property
    def ground_z_or_nan(self) -> float:
        """ground_z in the kernels' convention: NaN when there is no ground."""
        return math.nan if self.ground_z is None else self.ground_z

    @property
    def n_primitives(self) -> int:
        """Number of cylinders, rings and boxes (the ground not counted)."""
        return int(self.cylinders.shape[0] + self.rings.shape[0] + self.boxes.shape[0])

    def distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact signed distance (K,) and unit gradient (K, 3) at points (K, 3)."""
        p = np.ascontiguousarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (K, 3), got {p.shape}")
        d, g = primitives_distance_many(
            self.cylinders, self.rings, self.boxes, self.ground_z_or_nan, p
        )
        return d, g

    def without_ground(self) -> World:
        """The same primitives with no ground plane (clearances to obstacles alone)."""
        return World(self.cylinders, self.rings, self.boxes, ground_z=None, name=self.name)

    def within(self, center: np.ndarray, radius: float) -> World:
        """The primitives with some solid point within ``radius`` of ``center`` (ground kept).

        Selection by the exact signed distance of ``center`` to each primitive (``d <= radius``),
        so the distance field of the result equals this world's at every point p where the
        true distance is below ``radius - |p - center|``.
        """
        c = np.asarray(center, dtype=np.float64).reshape(3)
        dc, dr, db = _each_primitive_distance(
            self.cylinders, self.rings, self.boxes, float(c[0]), float(c[1]), float(c[2])
        )
        return World(
            self.cylinders[dc <= radius],
            self.rings[dr <= radius],
            self.boxes[db <= radius],
            self.ground_z,
            self.name,
        )

    def merged(self, other: World) -> World:
        """Union of both worlds' primitives, identical rows kept once.

        The ground is taken from whichever has one; two different ground heights are an error.
        """
        if self.ground_z is None:
            gz = other.ground_z
        elif other.ground_z is None or other.ground_z == self.ground_z:
            gz = self.ground_z
        else:
            raise ValueError(
                f"cannot merge worlds with ground at {self.ground_z} and {other.ground_z}"
            )
        return World(
            _union_rows(self.cylinders, other.cylinders),
            _union_rows(self.rings, other.rings),
            _union_rows(self.boxes, other.boxes),
            gz,
            self.name or other.name,
        )

    @staticmethod
    def empty(ground_z: float | None = 0.0) -> World:
        """A world with no primitives (only the ground, unless None)."""
        return World(
            np.zeros((0, CYLINDER_COLS)),
            np.zeros((0, RING_COLS)),
            np.zeros((0, BOX_COLS)),
            ground_z,
        )


# --------------------------------------------------------------------------------------------
# Random forest
# --------------------------------------------------------------------------------------------

RING_TUBE_RADIUS_M = 0.1
_TRIES_PER_OBJECT = 5000


def _dist_point_segment_xy(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Horizontal distance from points p (N, 2) to the segment a-b (2,)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _dist_to_segments_xy(
    p: np.ndarray, a: np.ndarray, ab: np.ndarray, ab2: np.ndarray
) -> np.ndarray:
    """Horizontal distance from one point p (2,) to K segments a-(a + ab), (K, 2) each;
    ``ab2`` (K,) the squared segment lengths."""
    pa = p - a
    t = np.clip((pa[:, 0] * ab[:, 0] + pa[:, 1] * ab[:, 1]) / ab2, 0.0, 1.0)
    d = pa - t[:, None] * ab
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def random_forest(
    rng_seed: int,
    n_cylinders: int,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    diameter_range: tuple[float, float] = (0.25, 0.75),
    height_range: tuple[float, float] = (2.0, 3.0),
    min_spacing_m: float = 0.8,
    n_rings: int = 0,
    ring_radius_range: tuple[float, float] = (0.6, 1.0),
    ring_height_range: tuple[float, float] = (1.0, 2.0),
    keep_clear: Sequence[tuple[np.ndarray, float]] = (),
    ground_z: float | None = 0.0,
) -> World:
    """A seeded random forest of vertical cylinders and (optionally) vertical elliptical rings.

    Cylinders stand on the ground (z from ``ground_z``, 0 when None, to that plus a height drawn
    from ``height_range``), diameters from ``diameter_range``; centres lie in the x/y ranges and are
    at least ``min_spacing_m`` apart (centre to centre). Rings are placed first: random yaw, each
    semi-axis drawn from ``ring_radius_range``, tube radius ``RING_TUBE_RADIUS_M``, centre height
    from ``ring_height_range`` (raised if needed so the ring clears the ground); a ring's
    footprint keeps ``min_spacing_m`` from other rings and ``min_spacing_m / 2`` from cylinder
    surfaces. ``keep_clear``: (centre xyz, radius) horizontal discs that no primitive enters.
    Rejection sampling, at most ``_TRIES_PER_OBJECT`` tries per object; ValueError when an
    object cannot be placed.
    """
    if n_cylinders < 0 or n_rings < 0:
        raise ValueError("object counts must be >= 0")
    if x_range[1] <= x_range[0] or y_range[1] <= y_range[0]:
        raise ValueError("x_range and y_range must be increasing")
    if not 0.0 < diameter_range[0] <= diameter_range[1]:
        raise ValueError("diameter_range must be positive and increasing")
    if not 0.0 < height_range[0] <= height_range[1]:
        raise ValueError("height_range must be positive and increasing")
    if not 0.0 < ring_radius_range[0] <= ring_radius_range[1]:
        raise ValueError("ring_radius_range must be positive and increasing")
    rng = np.random.default_rng(rng_seed)
    base_z = 0.0 if ground_z is None else float(ground_z)
    clear_xy = np.array([np.asarray(c, dtype=np.float64)[:2] for c, _ in keep_clear]).reshape(-1, 2)
    clear_r = np.array([float(r) for _, r in keep_clear])
    tube = RING_TUBE_RADIUS_M

    rings: list[np.ndarray] = []
    ring_ends: list[tuple[np.ndarray, np.ndarray]] = []  # footprint segments in xy
    for i in range(n_rings):
        for _ in range(_TRIES_PER_OBJECT):
            c = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
            yaw = rng.uniform(-math.pi, math.pi)
            rh = rng.uniform(*ring_radius_range)
            rv = rng.uniform(*ring_radius_range)
            cz = max(rng.uniform(*ring_height_range), base_z + rv + tube)
            u = np.array([-math.sin(yaw), math.cos(yaw)])
            a, b = c - rh * u, c + rh * u
            if clear_xy.shape[0] and np.any(
                _dist_point_segment_xy(clear_xy, a, b) - tube < clear_r
            ):
                continue
            if any(
                np.linalg.norm(c - 0.5 * (a2 + b2))
                < rh + 0.5 * np.linalg.norm(b2 - a2) + 2 * tube + min_spacing_m
                for a2, b2 in ring_ends
            ):
                continue
            rings.append(np.array([c[0], c[1], cz, yaw, rh, rv, tube]))
            ring_ends.append((a, b))
            break
        else:
            raise ValueError(f"random_forest: could not place ring {i + 1} of {n_rings}")

    # the rings' footprint segments as arrays: one vectorised distance per candidate cylinder
    ring_a = np.array([a for a, _ in ring_ends]).reshape(-1, 2)
    ring_ab = np.array([b - a for a, b in ring_ends]).reshape(-1, 2)
    ring_ab2 = np.einsum("ij,ij->i", ring_ab, ring_ab)
    cyl = np.zeros((n_cylinders, CYLINDER_COLS))
    for i in range(n_cylinders):
        for _ in range(_TRIES_PER_OBJECT):
            p = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
            radius = 0.5 * rng.uniform(*diameter_range)
            height = rng.uniform(*height_range)
            if i and np.any(np.sum((cyl[:i, :2] - p) ** 2, axis=1) < min_spacing_m**2):
                continue
            if clear_xy.shape[0] and np.any(
                np.linalg.norm(clear_xy - p, axis=1) - radius < clear_r
            ):
                continue
            if ring_ends and np.any(
                _dist_to_segments_xy(p, ring_a, ring_ab, ring_ab2)
                < radius + tube + 0.5 * min_spacing_m
            ):
                continue
            cyl[i] = (p[0], p[1], radius, base_z, base_z + height)
            break
        else:
            raise ValueError(
                f"random_forest: could not place cylinder {i + 1} of {n_cylinders} "
                f"with spacing {min_spacing_m} m in x {x_range}, y {y_range}"
            )
    return World(
        cyl,
        np.array(rings).reshape(-1, RING_COLS),
        np.zeros((0, BOX_COLS)),
        ground_z,
        f"forest(seed={rng_seed}, n={n_cylinders}, rings={n_rings})",
    )
