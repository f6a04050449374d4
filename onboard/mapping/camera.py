"""Depth camera model: intrinsics, pose, depth frames, frame validation, back-projection.

Frames (ENU world, SI units):

- camera optical frame: x right, y down, z forward (the image's u grows with x, v with y);
- a pose is the camera centre ``position`` (3,) and ``rotation`` (3, 3) = world_from_camera,
  whose columns are the camera's x, y, z axes in world coordinates;
- a depth image holds, per pixel, the z coordinate (metres along the optical axis) of the
  surface seen there; 0 means "no return" (what the D435 and the simulated camera report for
  nothing within range, but also for holes and for surfaces too close to see; the mapper clears
  free space along such pixels only where the depths around them and its map agree); NaN, inf,
  a negative value or one below the minimum depth means "no measurement" (nothing is marked).

The default intrinsics are those of the Intel RealSense D435 depth stream at 640 x 480.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

D435_WIDTH = 640
D435_HEIGHT = 480
D435_FX = 387.229
D435_FY = 387.229
D435_CX = 321.046
D435_CY = 243.450


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics and the valid depth range of a depth camera (D435 defaults)."""

    width: int = D435_WIDTH
    height: int = D435_HEIGHT
    fx: float = D435_FX
    fy: float = D435_FY
    cx: float = D435_CX
    cy: float = D435_CY
    min_depth_m: float = 0.2
    """Depths below this are not measurements (the D435 cannot see closer)."""
    max_depth_m: float = 5.0
    """Depths above this are not trusted as surfaces (the mapper still carves free space up to
    its ray length; see ``OccupancyParams.max_ray_m``)."""

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError("width and height must be >= 1")
        for name in ("fx", "fy"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise ValueError(f"{name} must be > 0")
        if not (0.0 < self.min_depth_m < self.max_depth_m):
            raise ValueError("need 0 < min_depth_m < max_depth_m")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (height, width) as numpy orders it."""
        return self.height, self.width

    def decimated(self, step: int) -> CameraIntrinsics:
        """The camera of every ``step``-th pixel row and column of this one (from pixel 0):
        pixel (u, v) of the result is pixel (step u, step v) here, through the same ray
        (pixel centres at integer coordinates, so fx, fy, cx and cy scale by 1 / step)."""
        if isinstance(step, bool) or not isinstance(step, int) or step < 1:
            raise ValueError(f"step must be an integer >= 1, got {step!r}")
        if step == 1:
            return self
        return CameraIntrinsics(
            -(-self.width // step),
            -(-self.height // step),
            self.fx / step,
            self.fy / step,
            self.cx / step,
            self.cy / step,
            self.min_depth_m,
            self.max_depth_m,
        )

    def normalized_coords(self) -> tuple[np.ndarray, np.ndarray]:
        """x_n (width,) = (u - cx) / fx and y_n (height,) = (v - cy) / fy of pixel centres."""
        u = np.arange(self.width, dtype=np.float64)
        v = np.arange(self.height, dtype=np.float64)
        return (u - self.cx) / self.fx, (v - self.cy) / self.fy


def look_rotation(yaw_rad: float, pitch_rad: float = 0.0) -> np.ndarray:
    """world_from_camera (3, 3) of a camera looking along ENU heading ``yaw_rad`` (0 = +x east,
    counter-clockwise) tilted up by ``pitch_rad``, with no roll (image rows horizontal)."""
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    z_axis = np.array([cy * cp, sy * cp, sp])  # forward
    x_axis = np.array([sy, -cy, 0.0])  # right
    y_axis = np.cross(z_axis, x_axis)  # down
    return np.stack([x_axis, y_axis, z_axis], axis=1)


@dataclass(frozen=True, eq=False)
class DepthFrame:
    """One depth image with its time and the camera pose it was taken from.

    depth_m (height, width): metres along the optical axis, float32 or float64; 0 is "no
    return", NaN, inf, negative or below-minimum values are "no measurement" (see the module
    docstring). stamp_s: seconds on the
    clock the poses come from. position (3,), rotation (3, 3): world_from_camera (ENU).
    """

    depth_m: np.ndarray
    stamp_s: float
    position: np.ndarray
    rotation: np.ndarray
    intrinsics: CameraIntrinsics
    render_step: int = 1
    """Only every render_step-th row and column holds a measurement (a simulated camera that
    renders a subset); the other pixels read 0 but are not "no return". A mapper casting a
    pixel grid that is not a subset of these refuses the frame."""
    decimation: int = 1
    """The image is every decimation-th pixel row and column of the camera's own
    (``intrinsics`` are those of the smaller image, ``CameraIntrinsics.decimated``): a mapper
    told to cast every n-th pixel of the camera casts every (n / decimation)-th of this one,
    and refuses the frame when n is not a multiple of it."""


class FrameRejected(ValueError):
    """A frame that cannot be used at all (wrong shape or dtype, bad pose or time)."""


def check_frame(frame: DepthFrame) -> np.ndarray:
    """A clean float32 depth image of ``frame``: 0 ("no return") stays 0, every other value
    that is not a measurement (non-finite, negative, outside [min_depth_m, inf)) becomes NaN
    ("no measurement"): the mapper reads both as ``validate_frame``'s raw image. Depths beyond
    ``max_depth_m`` are kept (free space up to the mapper's ray length is still seen). Raises
    FrameRejected for frames that cannot be used: wrong shape or dtype, non-finite time,
    non-finite position, non-orthonormal rotation."""
    out = np.array(validate_frame(frame), dtype=np.float32, copy=True)
    bad = ~np.isfinite(out) | (out < frame.intrinsics.min_depth_m)
    out[bad & (out != 0.0)] = np.nan
    return out


def validate_frame(frame: DepthFrame) -> np.ndarray:
    """``check_frame`` without the cleaning: the frame's depth image as a C-contiguous float32
    array (the frame's own array when it is one: no copy), invalid pixels as they came. For
    consumers that sort the pixels themselves (the mapper's ray casting reads exactly the same
    from both, on its skip grid only). Raises FrameRejected as
    ``check_frame`` does."""
    intr = frame.intrinsics
    d = frame.depth_m
    if not isinstance(d, np.ndarray):
        raise FrameRejected(f"depth must be a numpy array, got {type(d).__name__}")
    if d.dtype not in (np.float32, np.float64):
        raise FrameRejected(f"depth dtype must be float32 or float64 metres, got {d.dtype}")
    if d.shape != intr.shape:
        raise FrameRejected(f"depth shape {d.shape} differs from the camera's {intr.shape}")
    if not math.isfinite(float(frame.stamp_s)):
        raise FrameRejected("frame time is not finite")
    p = np.asarray(frame.position, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise FrameRejected(f"camera position must be 3 finite numbers, got {frame.position!r}")
    r = np.asarray(frame.rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise FrameRejected("camera rotation must be a finite 3 x 3 matrix")
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0.0:
        raise FrameRejected("camera rotation is not a proper rotation matrix")
    return np.ascontiguousarray(d, dtype=np.float32)


def backproject(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    position: np.ndarray,
    rotation: np.ndarray,
    step: int = 1,
    max_depth_m: float | None = None,
) -> np.ndarray:
    """World points (K, 3) of the valid pixels (every ``step``-th row and column) of a depth
    image: depth in [min_depth_m, max_depth_m] (default the camera's), finite."""
    intr = intrinsics
    hi = intr.max_depth_m if max_depth_m is None else max_depth_m
    xn, yn = intr.normalized_coords()
    d = np.asarray(depth_m)[::step, ::step].astype(np.float64)
    xs = xn[::step][None, :]
    ys = yn[::step][:, None]
    ok = np.isfinite(d) & (d >= intr.min_depth_m) & (d <= hi)
    z = d[ok]
    cam = np.stack([np.broadcast_to(xs, d.shape)[ok] * z, np.broadcast_to(ys, d.shape)[ok] * z, z])
    return (np.asarray(rotation, dtype=np.float64) @ cam).T + np.asarray(position, np.float64)
