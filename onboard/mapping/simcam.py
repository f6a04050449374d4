"""Simulated Intel RealSense D435: depth frames of a ``World`` with optional noise and holes.

Pure computation: the caller passes the pose and the time; randomness comes from a seeded
``numpy.random.Generator`` owned by the camera.

Sensor model (a simplification of the real D435, documented so results can be judged):

- geometry: exact ray casting of the primitives (``onboard.mapping.render``), 640 x 480,
  fx = fy = 387.229, cx = 321.046, cy = 243.450 by default;
- range: surfaces closer than ``min_depth_m`` (0.2 m) or farther than ``far_m`` (default 10 m,
  the practical limit of the real sensor) give 0, "no return"; returns between
  ``max_depth_m`` (5 m) and ``far_m`` are reported as the real sensor reports them, and it is
  the mapper that uses them only as free space;
- noise: Gaussian with standard deviation ``noise_std_1m_m * z^2`` (stereo depth error grows
  with the square of the depth; about 1-2 mm at 1 m for a D435 in good light), off by default;
- holes: each valid pixel drops to 0 with probability ``dropout``, and ``hole_count`` random
  rectangles of up to ``hole_size_px`` pixels are cleared (texture-less or saturated patches).

Other drones are not rendered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.mapping.camera import CameraIntrinsics, DepthFrame
from onboard.mapping.render import render_depth
from onboard.world import World


@dataclass(frozen=True)
class SimCameraParams:
    """Noise and range of the simulated depth camera."""

    far_m: float = 10.0
    """Farthest surface that gives a return; farther (and the sky) give 0."""
    noise_std_1m_m: float = 0.0
    """Depth noise standard deviation at 1 m; it grows with depth squared."""
    dropout: float = 0.0
    """Probability that a valid pixel reports 0 (no measurement)."""
    hole_count: int = 0
    """Rectangular holes (value 0) per frame."""
    hole_size_px: int = 40
    """Largest side of a hole, pixels."""
    step: int = 1
    """Render only every step-th row and column (the rest is 0): pairs with the mapper's
    skip-pixel option to save time in simulation."""

    def __post_init__(self) -> None:
        if not self.far_m > 0.0:
            raise ValueError("far_m must be > 0")
        if self.noise_std_1m_m < 0.0 or not 0.0 <= self.dropout <= 1.0:
            raise ValueError("noise_std_1m_m must be >= 0 and dropout in [0, 1]")
        if self.hole_count < 0 or self.hole_size_px < 1 or self.step < 1:
            raise ValueError("hole_count >= 0, hole_size_px >= 1 and step >= 1 are required")


D435_TYPICAL = SimCameraParams(noise_std_1m_m=0.004, dropout=0.01, hole_count=2)
"""Noise and holes of a D435 in good conditions: 0.004 m at 1 m (0.08 px disparity noise, 50 mm
baseline, 387 px focal length: 0.1 m at 5 m), 1 % of pixels and two patches without depth."""


class SimulatedDepthCamera:
    """Renders depth frames of ``world`` from given poses (a simulated D435)."""

    def __init__(
        self,
        world: World,
        intrinsics: CameraIntrinsics | None = None,
        params: SimCameraParams | None = None,
        seed: int = 0,
        decimation: int = 1,
    ) -> None:
        if isinstance(decimation, bool) or not isinstance(decimation, int) or decimation < 1:
            raise ValueError(f"decimation must be an integer >= 1, got {decimation!r}")
        self.decimation = decimation
        """``intrinsics`` are those of every decimation-th pixel of the real camera (the
        frames say so: ``DepthFrame.decimation``)."""
        self.world = world
        self.intrinsics = intrinsics if intrinsics is not None else CameraIntrinsics()
        self.params = params if params is not None else SimCameraParams()
        self._rng = np.random.default_rng(seed)
        self._xn, self._yn = self.intrinsics.normalized_coords()

    def render(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """The noise-free depth image (height, width) float32 seen from the pose."""
        w = self.world
        i = self.intrinsics
        return render_depth(
            w.cylinders,
            w.rings,
            w.boxes,
            w.ground_z_or_nan,
            position,
            rotation,
            self._xn,
            self._yn,
            i.fx,
            i.fy,
            i.cx,
            i.cy,
            self.params.far_m,
            self.params.step,
        )

    def capture(self, position: np.ndarray, rotation: np.ndarray, stamp_s: float) -> DepthFrame:
        """A frame from the pose at time ``stamp_s``: rendered, then noise, range and holes."""
        p = self.params
        depth = self.render(position, rotation)
        flat = depth.reshape(-1)
        valid = np.flatnonzero(flat > 0.0)
        if p.noise_std_1m_m > 0.0:
            z = flat[valid]
            noise = self._rng.standard_normal(z.shape, dtype=np.float32)
            flat[valid] = z + noise * (np.float32(p.noise_std_1m_m) * z * z)
        if p.dropout > 0.0:
            flat[valid[self._rng.random(valid.shape, dtype=np.float32) < p.dropout]] = 0.0
        flat[valid[flat[valid] < self.intrinsics.min_depth_m]] = 0.0
        h, w = depth.shape
        for _ in range(p.hole_count):
            sh, sw = self._rng.integers(1, p.hole_size_px + 1, size=2)
            v0 = int(self._rng.integers(0, max(1, h - sh + 1)))
            u0 = int(self._rng.integers(0, max(1, w - sw + 1)))
            depth[v0 : v0 + sh, u0 : u0 + sw] = 0.0
        return DepthFrame(
            depth,
            float(stamp_s),
            np.array(position, dtype=np.float64),
            np.array(rotation, dtype=np.float64),
            self.intrinsics,
            render_step=int(p.step),
            decimation=self.decimation,
        )
