"""The mock's camera of every n-th pixel (``swarm-sitl --depth-step``): a smaller image through
the same rays (``CameraIntrinsics.decimated``), so that rendering, sending and decoding a
frame cost 1/n^2 of the full image's; the frames say so (``decimation``), and a mapper told to
cast every n-th pixel of the camera casts every pixel of them and builds the same map."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from onboard.mapping.camera import CameraIntrinsics, look_rotation
from onboard.mapping.mapper import LocalMapper
from onboard.mapping.simcam import SimCameraParams, SimulatedDepthCamera
from onboard.sensors.zenoh_depth import DecodeError, DepthImage
from onboard.world import World
from sitl_mock.truth import simulated_d435

WORLD = World(
    np.array([[2.5, 0.4, 0.3, 0.0, 2.5], [4.0, -1.2, 0.25, 0.0, 3.0], [6.0, 1.5, 0.4, 0.0, 2.0]]),
    np.zeros((0, 7)),
    np.zeros((0, 6)),
    0.0,
)
POSE = (np.array([0.0, 0.1, 1.0]), look_rotation(0.1))


@pytest.mark.parametrize("step", [1, 2, 3, 7])
def test_a_decimated_camera_looks_through_the_same_rays(step: int) -> None:
    full = CameraIntrinsics()
    small = full.decimated(step)
    assert small.shape == (-(-full.height // step), -(-full.width // step))
    xf, yf = full.normalized_coords()
    xs, ys = small.normalized_coords()
    np.testing.assert_allclose(xs, xf[::step], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ys, yf[::step], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="step"):
        full.decimated(0)


def test_the_mocks_camera_renders_the_full_cameras_grid() -> None:
    """``simulated_d435(step=3)`` renders what the full camera renders on its every 3rd pixel
    (to float32 rounding of the ray directions), in a 9-times smaller image."""
    small = simulated_d435(WORLD, 0, step=3).capture(*POSE, 1.0)
    full = SimulatedDepthCamera(WORLD, params=SimCameraParams(step=3)).capture(*POSE, 1.0)
    assert small.decimation == 3 and small.render_step == 1
    assert small.depth_m.shape == (160, 214) and full.depth_m.shape == (480, 640)
    grid = full.depth_m[::3, ::3]
    assert np.count_nonzero(grid) > 0.5 * grid.size  # ground and trunks
    np.testing.assert_allclose(small.depth_m, grid, rtol=0, atol=1e-5)


def test_a_mapper_casting_every_third_pixel_builds_the_same_map_from_either() -> None:
    small = simulated_d435(WORLD, 0, step=3).capture(*POSE, 1.0)
    full = SimulatedDepthCamera(WORLD, params=SimCameraParams(step=3)).capture(*POSE, 1.0)
    maps = []
    for frame in (small, full):
        m = LocalMapper()
        res = m.ingest(frame, step=3)
        assert res.accepted, res.reason
        maps.append(m)
    a, b = (m.map for m in maps)
    assert np.array_equal(a.known(), b.known())
    np.testing.assert_allclose(a.logodds, b.logodds, rtol=0, atol=1e-4)
    refused = LocalMapper().ingest(small, step=2)  # not a multiple of the decimation
    assert not refused.accepted and "multiple of the decimation" in refused.reason


def _header(data: bytes) -> dict[str, object]:
    (n,) = struct.unpack("<I", data[4:8])
    return dict(json.loads(data[8 : 8 + n]))


def test_the_decimation_travels_with_the_frame() -> None:
    frame = simulated_d435(WORLD, 0, step=3).capture(*POSE, 1.0)
    intr = frame.intrinsics
    keys = ("width", "height", "fx", "fy", "cx", "cy", "min_depth_m", "max_depth_m")
    img = DepthImage(
        4, 1.0, frame.depth_m, frame.position, frame.rotation,
        {k: float(getattr(intr, k)) for k in keys}, decimation=frame.decimation,
    )  # fmt: skip
    data = img.to_bytes()
    assert _header(data)["decimation"] == 3
    assert len(data) < 2 * 214 * 160 + 1000  # a ninth of the full image's bytes
    back = DepthImage.from_bytes(data).to_depth_frame()
    assert back.decimation == 3 and back.intrinsics == intr
    res = LocalMapper().ingest(back, step=3)
    assert res.accepted and res.rays > 0
    plain = DepthImage(4, 1.0, frame.depth_m, frame.position, frame.rotation, img.intrinsics)
    assert "decimation" not in _header(plain.to_bytes())  # a full camera's frames unchanged
    h = _header(data)
    h["decimation"] = 0
    raw = json.dumps(h).encode()
    body = data[8 + struct.unpack("<I", data[4:8])[0] :]
    with pytest.raises(DecodeError) as e:
        DepthImage.from_bytes(b"DPT1" + struct.pack("<I", len(raw)) + raw + body)
    assert e.value.reason == "malformed" and "decimation" in str(e.value)
