"""On-board perception, pure computation: depth frames -> log-odds occupancy -> signed ESDF.

No files, sockets, clocks or printing here; depth sources (simulated D435, RealSense through
Open3D) and point-cloud I/O live in ``onboard.sensors``.
"""

from onboard.mapping.camera import (
    CameraIntrinsics,
    DepthFrame,
    FrameRejected,
    backproject,
    check_frame,
    look_rotation,
    validate_frame,
)
from onboard.mapping.esdf import EsdfBuilder, EsdfField
from onboard.mapping.mapper import LocalMapper
from onboard.mapping.occupancy import IngestResult, OccupancyMap, OccupancyParams
from onboard.mapping.simcam import SimCameraParams, SimulatedDepthCamera

__all__ = [
    "CameraIntrinsics",
    "DepthFrame",
    "EsdfBuilder",
    "EsdfField",
    "FrameRejected",
    "IngestResult",
    "LocalMapper",
    "OccupancyMap",
    "OccupancyParams",
    "SimCameraParams",
    "SimulatedDepthCamera",
    "backproject",
    "check_frame",
    "validate_frame",
    "look_rotation",
]
