"""Depth sources behind one small interface (``DepthSource``), and Open3D point-cloud I/O.

- ``SimulatedD435Source``: frames of a ``World`` rendered at the pose a provider gives;
- ``RealSenseSource``: an Intel RealSense camera (live) or a recorded ``.bag`` file, through
  Open3D's RealSense support; ``RealSenseUnavailable`` with a clear message when neither works;
- ``onboard.sensors.cloud``: back-projection and voxel downsampling with Open3D, saving the map
  as a ``.ply`` point cloud.

Open3D is imported only when a RealSense source or a cloud function is used.
"""

from onboard.sensors.source import DepthSource, PoseProvider, SimulatedD435Source

__all__ = ["DepthSource", "PoseProvider", "SimulatedD435Source"]
