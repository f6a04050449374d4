"""Where the depth camera sits on the drone, and the camera pose that follows from the body's.

Frames: world ENU, body FLU (x forward, y left, z up), camera optical (x right, y down,
z forward). The forward depth camera looks along the body's x axis, level, ``CAMERA_OFFSET_BODY_M``
ahead of the body origin.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation optical camera frame -> FLU body frame (columns: the camera axes in the body)."""
R_BODY_CAM.setflags(write=False)

CAMERA_OFFSET_BODY_M = np.array([0.10, 0.0, 0.0])
"""Camera centre in the body frame [m]."""
CAMERA_OFFSET_BODY_M.setflags(write=False)


def rotation_from_quaternion(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = (float(c) for c in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def camera_pose(
    position_m: Sequence[float] | np.ndarray, quaternion_wxyz: Sequence[float] | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(camera position (3,), world_from_camera (3, 3)) of the forward depth camera, from the
    body's ENU position and its FLU-body -> ENU-world attitude quaternion (w, x, y, z)."""
    r_world_body = rotation_from_quaternion(quaternion_wxyz)
    pos = np.asarray(position_m, dtype=np.float64).reshape(3) + r_world_body @ CAMERA_OFFSET_BODY_M
    return pos, r_world_body @ R_BODY_CAM
