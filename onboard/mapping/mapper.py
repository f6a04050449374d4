"""The on-board mapping pipeline of one drone: depth frames in, a signed distance field out.

``LocalMapper`` validates each frame (bad frames are refused or masked, never crash the map,
never mark unseen space free; pixels without a return clear free space only as far as the depths
around them and the map allow, see ``onboard.mapping.occupancy``), moves the rolling occupancy
window with the camera, ray casts the frame, and on request refreshes the ESDF (``EsdfField``,
a ``GridField``): ``field()`` the distance to the mapped surfaces, ``planning_field()`` the same
with the obstacles inflated by the drone's radius, which is what a planner should read.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.mapping.camera import DepthFrame, FrameRejected, validate_frame
from onboard.mapping.esdf import EsdfBuilder, EsdfField
from onboard.mapping.occupancy import IngestResult, OccupancyMap, OccupancyParams


class LocalMapper:
    """Occupancy window + ESDF of one drone."""

    def __init__(
        self,
        params: OccupancyParams | None = None,
        center: np.ndarray | None = None,
        surface_offset_m: float | None = None,
    ) -> None:
        self.params = params if params is not None else OccupancyParams()
        self.map = OccupancyMap(self.params, center)
        self._builder = EsdfBuilder(surface_offset_m)
        self._field: EsdfField | None = None
        self._planning: EsdfField | None = None
        self._dirty = True
        self.last_stamp_s = -math.inf
        self.rejected = 0
        self._next_no_return_s = -math.inf

    def recenter(self, center: np.ndarray) -> None:
        """Move the window to ``center`` (usually the drone's position)."""
        c = np.asarray(center, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(c)):
            return
        if self.map.recenter(c):
            self._dirty = True

    def ingest(
        self, frame: DepthFrame, step: int | None = None, recenter: bool = True
    ) -> IngestResult:
        """Validate a frame, centre the window on its camera (unless ``recenter`` is False;
        the camera must then lie inside the window) and ray cast it, every ``step``-th pixel
        of the camera's image (default ``params.skip_pixel``; of a decimated frame, every
        (step / decimation)-th of its own).

        Refused (``accepted`` False, map unchanged): wrong shape or dtype, non-finite time or
        pose, a time older than the last accepted frame. Masked (pixels ignored): NaN, inf,
        negative or below-minimum depths. 0 ("no return") clears free space along its ray as
        ``OccupancyParams.no_return_m`` says."""
        try:
            # not cleaned: the ray casting skips the invalid pixels itself (on its skip grid)
            depth = validate_frame(frame)
        except FrameRejected as e:
            self.rejected += 1
            return IngestResult(False, str(e))
        if frame.stamp_s < self.last_stamp_s:
            self.rejected += 1
            return IngestResult(False, "frame older than the last accepted one")
        cast = self.params.skip_pixel if step is None else int(step)
        dec = frame.decimation
        if cast % dec:
            self.rejected += 1
            return IngestResult(
                False,
                f"frame of every {dec}th pixel of the camera but cast every {cast}th: "
                f"the cast step (depth.step) must be a multiple of the decimation",
            )
        render = frame.render_step
        if render > 1 and (cast // dec) % render:
            # the pixels between the rendered ones read 0: cast, they would clear free space
            self.rejected += 1
            return IngestResult(
                False,
                f"frame rendered every {render}th pixel but cast every {cast}th: the cast "
                f"step (depth.step) must be a multiple of the render step",
            )
        if recenter:
            self.recenter(frame.position)
        # no-return rays at most every no_return_period_s (a fixed phase, as the ESDF refresh;
        # a frame a tenth of the period early counts, for stamps with jitter or rounding)
        t = float(frame.stamp_s)
        period = self.params.no_return_period_s
        no_return = t >= self._next_no_return_s - 0.1 * period
        res = self.map.ingest_depth(
            depth, frame.intrinsics, frame.position, frame.rotation, cast, no_return, dec
        )
        if res.accepted:
            self.last_stamp_s = t
            # a frame that changed nothing the ESDF reads (no cell changed between unknown,
            # free and occupied, no occupied cell was hit) leaves the field as it is: the
            # next field() is the same object, bit for bit what a refresh would give
            if res.esdf_changes:
                self._dirty = True
            if no_return:
                nxt = self._next_no_return_s + period
                self._next_no_return_s = nxt if t < nxt else t + period
        else:
            self.rejected += 1
        return res

    @property
    def esdf_new_buffer_sets(self) -> int:
        """Output buffer sets the ESDF refreshes allocated (pooled ones first; more means a
        refresh found every pooled set still held by some field)."""
        return self._builder.new_sets

    def field(self) -> EsdfField:
        """The ESDF of the current window (of its layers in ``params.esdf_z_m`` when set;
        recomputed only if the window moved or a frame changed what it reads since: see
        ``IngestResult.esdf_changes``)."""
        if self._dirty or self._field is None:
            # the planning field (inflated by the drone's radius) in the same pass
            self._field = self._builder.build(
                self.map, self.last_stamp_s, inflate_m=self.params.inflation_m
            )
            self._planning = None
            self._dirty = False
        return self._field

    def planning_field(self) -> EsdfField:
        """The field to plan on: the ESDF of the obstacles inflated by ``params.inflation_m``
        (the drone's radius; it also covers the map's error, about 0.09 m at the 95th
        percentile), so a planner tuned on exact distances keeps its margins."""
        f = self.field()
        if self._planning is None:
            self._planning = f.inflated(self.params.inflation_m)
        return self._planning
