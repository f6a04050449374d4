"""One simulated drone's perception: a D435 on the drone, looking where it flies, feeding its
own ``LocalMapper``. Used by the fast-time simulation (``SimConfig.perception = 'mapped'``).

The camera is mounted level, looking forward; the drone's yaw follows the direction to where its
trajectory takes it in ``LOOK_AHEAD_S`` (while it holds still short of its goal, towards the
goal and swinging either side of it, ``SWEEP_RAD``; unchanged once there). The simulation passes
time and state in; the object only adds up its own render and ingest times (``perf_counter``)
for reports.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from onboard.mapping.camera import look_rotation
from onboard.mapping.esdf import EsdfField
from onboard.mapping.mapper import LocalMapper
from onboard.mapping.occupancy import OccupancyParams
from onboard.mapping.simcam import D435_TYPICAL, SimCameraParams, SimulatedDepthCamera
from onboard.planner.trajectory import Trajectory
from onboard.world import World

_MOVING_M_S = 0.1
_GOAL_NEAR_M = 0.3
LOOK_AHEAD_S = 1.0
"""The camera looks where the drone will be this long ahead on its trajectory (the planner's
``check_known_s``, the part of a plan that must lie in observed space), not along its velocity
of the moment: in a turn the camera, whose yaw lags the setpoint, then sees the space the
drone turns into before the next replan asks for it to be observed."""


def look_velocity(trajectory: Trajectory, t_s: float, position: np.ndarray) -> np.ndarray:
    """The mean velocity of the next ``LOOK_AHEAD_S`` on ``trajectory`` from ``position`` at
    ``t_s`` (what ``heading_yaw`` turns the camera along)."""
    ahead = trajectory.sample(t_s + LOOK_AHEAD_S)
    return np.subtract(ahead, position, dtype=np.float64) / LOOK_AHEAD_S


SWEEP_RAD = math.radians(50.0)
"""A drone that holds still short of its goal (``heading_yaw`` with a time) swings its camera
this far either side of the goal's direction: with the D435's 87 deg field of view it then sees
the sides (+-93 deg), where the ways around whatever stopped it lie. Plans must not enter
unobserved space (the planner's ``check_known_s``); facing only the goal, a drone stopped by a
trunk had every way round refused as "enters unobserved space" until it gave up (the 7-drone
demo, forest-medium seeds 2 and 5, BENCHMARKS.md section 10)."""
SWEEP_PERIOD_S = 6.0
"""One swing left, right and back: at most 52 deg/s (the mock's yaw-rate limit, after PX4's
MC_YAWRATE_MAX, is 200 deg/s), and 30 frames a swing at the 7-drone demo's 5 frames/s."""


def heading_yaw(
    velocity: np.ndarray,
    position: np.ndarray,
    goal: np.ndarray | None,
    previous: float,
    t_s: float | None = None,
) -> float:
    """Yaw (rad, ENU) the drone faces: along its horizontal velocity when moving, else towards
    its goal when not there (swinging ``SWEEP_RAD`` either side of it over ``SWEEP_PERIOD_S``
    when the time ``t_s`` is given), else ``previous``."""
    v = np.asarray(velocity, dtype=np.float64)
    if math.hypot(v[0], v[1]) > _MOVING_M_S:
        return math.atan2(v[1], v[0])
    if goal is not None:
        d = np.asarray(goal, dtype=np.float64) - np.asarray(position, dtype=np.float64)
        if math.hypot(d[0], d[1]) > _GOAL_NEAR_M:
            yaw = math.atan2(d[1], d[0])
            if t_s is not None:
                swing = SWEEP_RAD * math.sin(2.0 * math.pi * t_s / SWEEP_PERIOD_S)
                yaw = math.remainder(yaw + swing, 2.0 * math.pi)  # in [-pi, pi]
            return yaw
    return previous


class SimulatedPerception:
    """Simulated depth camera (``D435_TYPICAL`` noise and holes unless ``camera`` is given;
    only the skip grid is rendered) + local map of one drone, for a camera of ``rate_hz``
    frames per second (``OccupancyParams.for_frame_rate``)."""

    def __init__(
        self,
        world: World,
        skip_pixel: int = 2,
        seed: int = 0,
        camera: SimCameraParams | None = None,
        occupancy: OccupancyParams | None = None,
        initial_yaw: float = 0.0,
        rate_hz: float = 30.0,
    ) -> None:
        cam = dataclasses.replace(camera if camera is not None else D435_TYPICAL, step=skip_pixel)
        occ = occupancy if occupancy is not None else OccupancyParams(skip_pixel=skip_pixel)
        occ = occ.for_frame_rate(rate_hz)
        self.camera = SimulatedDepthCamera(world, params=cam, seed=seed)
        self.mapper = LocalMapper(occ)
        self.yaw = float(initial_yaw)
        self.frames = 0
        self.ingest_s = 0.0
        self.render_s = 0.0

    def observe(
        self, t_s: float, position: np.ndarray, velocity: np.ndarray, goal: np.ndarray | None
    ) -> None:
        """Take one frame at time t_s from the drone's state and add it to the map."""
        self.yaw = heading_yaw(velocity, position, goal, self.yaw, t_s)
        t0 = time.perf_counter()
        frame = self.camera.capture(position, look_rotation(self.yaw), t_s)
        t1 = time.perf_counter()
        self.mapper.ingest(frame)
        t2 = time.perf_counter()
        self.frames += 1
        self.render_s += t1 - t0
        self.ingest_s += t2 - t1

    def field(self) -> EsdfField:
        """The field the drone plans on now: its map's ESDF with the obstacles inflated by the
        drone's radius (``LocalMapper.planning_field``)."""
        return self.mapper.planning_field()
