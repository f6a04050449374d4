"""A simulated camera renders only every n-th pixel row and column (the rest reads 0, which a
mapper would take for "no return" and clear free space along): the frames say so, and a mapper
casting pixels that were not rendered refuses the frame instead of carving the map."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from onboard.mapping.camera import look_rotation
from onboard.mapping.mapper import LocalMapper
from onboard.mapping.simcam import SimCameraParams, SimulatedDepthCamera
from onboard.sensors.zenoh_depth import DecodeError, DepthImage
from onboard.world import World

INTR = {"width": 8.0, "height": 6.0, "fx": 7.0, "fy": 7.0, "cx": 4.0, "cy": 3.0,
        "min_depth_m": 0.2, "max_depth_m": 5.0}  # fmt: skip


def _image(render_step: int = 1) -> DepthImage:
    depth = np.linspace(0.0, 6.0, 48, dtype=np.float32).reshape(6, 8)
    return DepthImage(
        2, 1.5, depth, np.array([1.0, 2.0, 1.1]), look_rotation(0.3), INTR, render_step
    )


def _header(data: bytes) -> dict[str, object]:
    (n,) = struct.unpack("<I", data[4:8])
    return dict(json.loads(data[8 : 8 + n]))


def test_the_render_step_travels_with_the_frame() -> None:
    plain = _image().to_bytes()
    assert "render_step" not in _header(plain)  # frames of a full camera are unchanged
    assert DepthImage.from_bytes(plain).render_step == 1
    three = DepthImage.from_bytes(_image(3).to_bytes())
    assert three.render_step == 3
    assert three.to_depth_frame().render_step == 3


@pytest.mark.parametrize("bad", [0, 65, 2.5, "2", True])
def test_a_bad_render_step_is_refused(bad: object) -> None:
    data = _image(2).to_bytes()
    h = _header(data)
    h["render_step"] = bad
    raw = json.dumps(h).encode()
    body = data[8 + struct.unpack("<I", data[4:8])[0] :]
    with pytest.raises(DecodeError) as e:
        DepthImage.from_bytes(b"DPT1" + struct.pack("<I", len(raw)) + raw + body)
    assert e.value.reason == "malformed" and "render_step" in str(e.value)


def test_the_mapper_refuses_pixels_that_were_not_rendered() -> None:
    world = World(np.array([[3.0, 0.0, 0.3, 0.0, 2.5]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    cam = SimulatedDepthCamera(world, params=SimCameraParams(step=2), seed=0)
    frame = cam.capture(np.array([0.0, 0.0, 1.0]), look_rotation(0.0), 0.1)
    assert frame.render_step == 2
    rendered = frame.depth_m[::2, ::2]
    assert np.all(frame.depth_m[1::2, :] == 0.0) and np.any(rendered > 0.0)

    mapper = LocalMapper()
    refused = mapper.ingest(frame, step=3)  # every 3rd pixel: odd rows read 0
    assert not refused.accepted
    assert "multiple of the render step" in refused.reason
    assert mapper.rejected == 1 and not np.any(mapper.map.known())  # the map is untouched

    for step in (2, 4):
        res = LocalMapper().ingest(frame, step=step)
        assert res.accepted and res.rays > 0
