"""Depth rendering of a ``World`` (cylinders, rings, boxes, ground): a simulated depth camera.

Ray casting per pixel against the analytic primitives. A ray through pixel (u, v) is
``o + t * d`` with ``d = R @ (x_n, y_n, 1)`` (R world_from_camera), so the ray parameter t is
the depth itself. Cylinders, boxes and the ground have closed-form intersections; rings
(elliptical tubes, no closed form) are sphere-traced on their exact signed distance inside
their bounding sphere. Each primitive is drawn only over the image rectangle its bounding box
projects to (a z-buffer), so the cost grows with the image area the obstacles cover, not with
pixels x primitives.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from onboard.world import ring_distance

_NEAR_M = 0.02  # bounding boxes closer than this to the image plane cover the whole image
_SPHERE_TRACE_EPS_M = 1e-4
_SPHERE_TRACE_MAX_STEPS = 200


@njit(cache=True, nogil=True)
def _box_image_rect(
    lo: np.ndarray,
    hi: np.ndarray,
    o: np.ndarray,
    R: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    far: float,
) -> tuple[int, int, int, int]:
    """Pixel rectangle [u0, u1) x [v0, v1) covering the projection of the box lo-hi; empty
    (u0 >= u1) when the box is entirely behind the camera or farther than ``far``."""
    # nearest point of the box to the camera: farther than far -> nothing to draw
    dx = max(lo[0] - o[0], 0.0, o[0] - hi[0])
    dy = max(lo[1] - o[1], 0.0, o[1] - hi[1])
    dz = max(lo[2] - o[2], 0.0, o[2] - hi[2])
    if dx * dx + dy * dy + dz * dz > far * far:
        return 0, 0, 0, 0
    umin = math.inf
    umax = -math.inf
    vmin = math.inf
    vmax = -math.inf
    n_front = 0
    for c in range(8):
        px = hi[0] if c & 1 else lo[0]
        py = hi[1] if c & 2 else lo[1]
        pz = hi[2] if c & 4 else lo[2]
        qx = px - o[0]
        qy = py - o[1]
        qz = pz - o[2]
        # camera coordinates: R^T q
        xc = R[0, 0] * qx + R[1, 0] * qy + R[2, 0] * qz
        yc = R[0, 1] * qx + R[1, 1] * qy + R[2, 1] * qz
        zc = R[0, 2] * qx + R[1, 2] * qy + R[2, 2] * qz
        if zc < _NEAR_M:
            continue
        n_front += 1
        u = fx * xc / zc + cx
        v = fy * yc / zc + cy
        umin = min(umin, u)
        umax = max(umax, u)
        vmin = min(vmin, v)
        vmax = max(vmax, v)
    if n_front == 0:
        return 0, 0, 0, 0
    if n_front < 8:  # the box straddles the image plane: its projection is unbounded
        return 0, width, 0, height
    u0 = max(int(math.floor(umin)), 0)
    u1 = min(int(math.ceil(umax)) + 1, width)
    v0 = max(int(math.floor(vmin)), 0)
    v1 = min(int(math.ceil(vmax)) + 1, height)
    return u0, u1, v0, v1


@njit(cache=True, nogil=True)
def _cylinder_hit(
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    ccx: float,
    ccy: float,
    r: float,
    z0: float,
    z1: float,
) -> float:
    """Smallest t > 0 where o + t d enters the solid vertical cylinder; inf if none."""
    best = math.inf
    px = ox - ccx
    py = oy - ccy
    a = dx * dx + dy * dy
    c = px * px + py * py - r * r
    if a > 0.0:
        b = px * dx + py * dy
        disc = b * b - a * c
        if disc >= 0.0:
            t = (-b - math.sqrt(disc)) / a
            if t > 0.0:
                z = oz + t * dz
                if z0 <= z <= z1:
                    best = t
    if dz != 0.0:  # caps
        zc = z1 if oz > z1 else (z0 if oz < z0 else math.nan)
        if not math.isnan(zc):
            t = (zc - oz) / dz
            if 0.0 < t < best:
                qx = px + t * dx
                qy = py + t * dy
                if qx * qx + qy * qy <= r * r:
                    best = t
    return best


@njit(cache=True, nogil=True)
def _box_hit(
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    b: np.ndarray,
) -> float:
    """Smallest t > 0 where o + t d enters the axis-aligned box b = [lo(3), hi(3)]; inf if none."""
    t_near = -math.inf
    t_far = math.inf
    o3 = (ox, oy, oz)
    d3 = (dx, dy, dz)
    for a in range(3):
        if d3[a] == 0.0:
            if o3[a] < b[a] or o3[a] > b[a + 3]:
                return math.inf
            continue
        t1 = (b[a] - o3[a]) / d3[a]
        t2 = (b[a + 3] - o3[a]) / d3[a]
        if t1 > t2:
            t1, t2 = t2, t1
        t_near = max(t_near, t1)
        t_far = min(t_far, t2)
    if t_near <= t_far and t_near > 0.0:
        return t_near
    return math.inf


@njit(cache=True, nogil=True)
def _ring_hit(
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    g: np.ndarray,
    t_max: float,
) -> float:
    """Smallest t in (0, t_max) where o + t d meets ring g (sphere tracing); inf if none."""
    bound = max(g[4], g[5]) + g[6]
    px = ox - g[0]
    py = oy - g[1]
    pz = oz - g[2]
    a = dx * dx + dy * dy + dz * dz
    b = px * dx + py * dy + pz * dz
    c = px * px + py * py + pz * pz - bound * bound
    disc = b * b - a * c
    if disc < 0.0:
        return math.inf
    sq = math.sqrt(disc)
    t0 = max((-b - sq) / a, 0.0)
    t1 = min((-b + sq) / a, t_max)
    if t0 >= t1:
        return math.inf
    # the tube lies in the slab |(p - c) . n| <= tube around the ring's plane
    nx = math.cos(g[3])
    ny = math.sin(g[3])
    w0 = px * nx + py * ny
    wd = dx * nx + dy * ny
    if wd == 0.0:
        if abs(w0) > g[6]:
            return math.inf
    else:
        ta = (-g[6] - w0) / wd
        tb = (g[6] - w0) / wd
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
        if t0 >= t1:
            return math.inf
    inv_len = 1.0 / math.sqrt(a)
    t = t0
    for _ in range(_SPHERE_TRACE_MAX_STEPS):
        dist = ring_distance(
            g[0], g[1], g[2], g[3], g[4], g[5], g[6], ox + t * dx, oy + t * dy, oz + t * dz
        )[0]
        if dist < _SPHERE_TRACE_EPS_M:
            return t if t > 0.0 else math.inf
        t += dist * inv_len
        if t > t1:
            return math.inf
    return math.inf


@njit(cache=True, nogil=True)
def render_depth_kernel(
    cylinders: np.ndarray,
    rings: np.ndarray,
    boxes: np.ndarray,
    ground_z: float,
    o: np.ndarray,
    R: np.ndarray,
    xn: np.ndarray,
    yn: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    step: int,
    far: float,
    out: np.ndarray,
) -> None:
    """Fill out (height, width) float32 with the depth of the nearest surface per pixel, on
    every ``step``-th row and column; other pixels and rays with nothing within ``far`` get 0.

    cylinders (K, 5), rings (R, 7), boxes (B, 6), ground_z (NaN: none) as in ``onboard.world``;
    o (3,) camera centre, R (3, 3) world_from_camera, xn (width,), yn (height,) normalised pixel
    coordinates."""
    height = out.shape[0]
    width = out.shape[1]
    out[:, :] = math.inf
    lo = np.empty(3)
    hi = np.empty(3)
    # ground: every pixel whose ray points down
    if not math.isnan(ground_z):
        h = ground_z - o[2]
        for v in range(0, height, step):
            for u in range(0, width, step):
                dz = R[2, 0] * xn[u] + R[2, 1] * yn[v] + R[2, 2]
                if dz < 0.0 and h < 0.0:
                    t = h / dz
                    if t < out[v, u]:
                        out[v, u] = t
    for k in range(cylinders.shape[0]):
        ccx = cylinders[k, 0]
        ccy = cylinders[k, 1]
        r = cylinders[k, 2]
        lo[0] = ccx - r
        lo[1] = ccy - r
        lo[2] = cylinders[k, 3]
        hi[0] = ccx + r
        hi[1] = ccy + r
        hi[2] = cylinders[k, 4]
        u0, u1, v0, v1 = _box_image_rect(lo, hi, o, R, fx, fy, cx, cy, width, height, far)
        u0 = ((u0 + step - 1) // step) * step
        v0 = ((v0 + step - 1) // step) * step
        for v in range(v0, v1, step):
            for u in range(u0, u1, step):
                dx = R[0, 0] * xn[u] + R[0, 1] * yn[v] + R[0, 2]
                dy = R[1, 0] * xn[u] + R[1, 1] * yn[v] + R[1, 2]
                dz = R[2, 0] * xn[u] + R[2, 1] * yn[v] + R[2, 2]
                t = _cylinder_hit(o[0], o[1], o[2], dx, dy, dz, ccx, ccy, r, lo[2], hi[2])
                if t < out[v, u]:
                    out[v, u] = t
    for k in range(boxes.shape[0]):
        b = boxes[k]
        for a in range(3):
            lo[a] = b[a]
            hi[a] = b[a + 3]
        u0, u1, v0, v1 = _box_image_rect(lo, hi, o, R, fx, fy, cx, cy, width, height, far)
        u0 = ((u0 + step - 1) // step) * step
        v0 = ((v0 + step - 1) // step) * step
        for v in range(v0, v1, step):
            for u in range(u0, u1, step):
                dx = R[0, 0] * xn[u] + R[0, 1] * yn[v] + R[0, 2]
                dy = R[1, 0] * xn[u] + R[1, 1] * yn[v] + R[1, 2]
                dz = R[2, 0] * xn[u] + R[2, 1] * yn[v] + R[2, 2]
                t = _box_hit(o[0], o[1], o[2], dx, dy, dz, b)
                if t < out[v, u]:
                    out[v, u] = t
    for k in range(rings.shape[0]):
        g = rings[k]
        # axis-aligned box of the tube: semi-axes rh along u, rv along z, 0 along n, + tube
        ext_x = abs(math.sin(g[3])) * g[4] + g[6]
        ext_y = abs(math.cos(g[3])) * g[4] + g[6]
        ext_z = g[5] + g[6]
        lo[0] = g[0] - ext_x
        hi[0] = g[0] + ext_x
        lo[1] = g[1] - ext_y
        hi[1] = g[1] + ext_y
        lo[2] = g[2] - ext_z
        hi[2] = g[2] + ext_z
        u0, u1, v0, v1 = _box_image_rect(lo, hi, o, R, fx, fy, cx, cy, width, height, far)
        u0 = ((u0 + step - 1) // step) * step
        v0 = ((v0 + step - 1) // step) * step
        for v in range(v0, v1, step):
            for u in range(u0, u1, step):
                dx = R[0, 0] * xn[u] + R[0, 1] * yn[v] + R[0, 2]
                dy = R[1, 0] * xn[u] + R[1, 1] * yn[v] + R[1, 2]
                dz = R[2, 0] * xn[u] + R[2, 1] * yn[v] + R[2, 2]
                t_lim = min(out[v, u], far)
                t = _ring_hit(o[0], o[1], o[2], dx, dy, dz, g, t_lim)
                if t < out[v, u]:
                    out[v, u] = t
    for v in range(height):
        for u in range(width):
            t = out[v, u]
            if not (t <= far) or (v % step) != 0 or (u % step) != 0:
                out[v, u] = 0.0


def render_depth(
    cylinders: np.ndarray,
    rings: np.ndarray,
    boxes: np.ndarray,
    ground_z: float,
    position: np.ndarray,
    rotation: np.ndarray,
    xn: np.ndarray,
    yn: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    far_m: float,
    step: int = 1,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Depth image (height, width) float32 of the primitives seen from a camera pose; 0 where
    nothing lies within ``far_m`` and on pixels skipped by ``step``. See
    ``render_depth_kernel`` for the arguments."""
    if step < 1:
        raise ValueError("step must be >= 1")
    if out is None:
        out = np.empty((yn.shape[0], xn.shape[0]), dtype=np.float32)
    render_depth_kernel(
        np.ascontiguousarray(cylinders, dtype=np.float64),
        np.ascontiguousarray(rings, dtype=np.float64),
        np.ascontiguousarray(boxes, dtype=np.float64),
        float(ground_z),
        np.ascontiguousarray(position, dtype=np.float64),
        np.ascontiguousarray(rotation, dtype=np.float64),
        np.ascontiguousarray(xn, dtype=np.float64),
        np.ascontiguousarray(yn, dtype=np.float64),
        float(fx),
        float(fy),
        float(cx),
        float(cy),
        int(step),
        float(far_m),
        out,
    )
    return out
