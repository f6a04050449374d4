"""Point clouds with Open3D: back-projection of depth frames, voxel downsampling, ``.ply`` files.

Back-projection here is Open3D's (``PointCloud.create_from_depth_image``); it gives the same
points as ``onboard.mapping.camera.backproject`` (a test checks it) and adds Open3D's voxel
downsampling, which ``ingest_cloud`` uses as an alternative way into the occupancy map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from onboard.mapping.camera import DepthFrame, check_frame
from onboard.mapping.occupancy import IngestResult, OccupancyMap


def _o3d() -> Any:
    import open3d as o3d

    return o3d


def frame_to_cloud(frame: DepthFrame, step: int = 1, voxel_m: float | None = None) -> Any:
    """The valid pixels of a frame (depth in [min, max] of its camera) as an Open3D
    ``PointCloud`` in world coordinates, every ``step``-th pixel, optionally voxel-downsampled
    (one point per ``voxel_m`` cube: the centroid of its points)."""
    o3d = _o3d()
    intr = frame.intrinsics
    depth = check_frame(frame)
    depth[depth > intr.max_depth_m] = 0.0
    pinhole = o3d.camera.PinholeCameraIntrinsic(
        intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy
    )
    extrinsic = np.eye(4)  # camera_from_world
    extrinsic[:3, :3] = frame.rotation.T
    extrinsic[:3, 3] = -frame.rotation.T @ frame.position
    cloud = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(np.ascontiguousarray(depth)),
        pinhole,
        extrinsic,
        depth_scale=1.0,
        depth_trunc=float(intr.max_depth_m) + 1e-6,
        stride=int(step),
    )
    if voxel_m is not None:
        cloud = cloud.voxel_down_sample(float(voxel_m))
    return cloud


def cloud_points(cloud: Any) -> np.ndarray:
    """Points (K, 3) float64 of an Open3D ``PointCloud``."""
    return np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)


def ingest_cloud(
    omap: OccupancyMap, frame: DepthFrame, step: int = 1, voxel_m: float | None = None
) -> IngestResult:
    """Back-project a frame with Open3D, downsample it and ray cast the points into ``omap``
    (the window must contain the camera). Pixels without a surface within the camera's range
    mark nothing (unlike ``OccupancyMap.ingest_depth``, which also carves free space up to the
    ray length for returns beyond it)."""
    cloud = frame_to_cloud(frame, step, voxel_m)
    return omap.ingest_points(frame.position, cloud_points(cloud))


def save_points_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write points (K, 3) (and optional colours (K, 3) in [0, 1]) as a ``.ply`` file."""
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_point_cloud(str(p), cloud):
        raise OSError(f"could not write {p}")


def height_colors(points: np.ndarray) -> np.ndarray:
    """Colours (K, 3) in [0, 1] from blue (lowest) to red (highest) by z."""
    z = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, 2]
    t = (z - z.min()) / max(float(np.ptp(z)), 1e-9) if z.size else z
    return np.stack([t, 0.3 * np.ones_like(t), 1.0 - t], axis=1)


def save_map_ply(path: str | Path, omap: OccupancyMap) -> int:
    """Write the occupied cells of a map (their measured surface points, coloured by height)
    as a ``.ply`` point cloud for inspection; returns the number of points."""
    pts = omap.surface_points()
    save_points_ply(path, pts, height_colors(pts))
    return int(pts.shape[0])


def load_points_ply(path: str | Path) -> np.ndarray:
    """Points (K, 3) of a ``.ply`` file."""
    o3d = _o3d()
    return cloud_points(o3d.io.read_point_cloud(str(path)))
