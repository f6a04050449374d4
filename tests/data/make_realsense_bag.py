"""Write ``realsense_wall.bag``: a tiny RealSense recording for the .bag replay test.

Not part of the test run. It needs ``pyrealsense2`` 2.55 (later versions write ROS 2 ``.db3``
files, which Open3D's reader does not open) and ``libusb-1.0-0``; use a throw-away venv:

    python3 -m venv /tmp/rs && /tmp/rs/bin/pip install pyrealsense2==2.55.1.6486 numpy
    /tmp/rs/bin/python tests/data/make_realsense_bag.py tests/data/realsense_wall.bag

The recording: a software D435 (depth Z16 and colour RGB8, 640 x 480 at 30 fps, the D435 depth
intrinsics for both streams, identity extrinsics, depth unit 1 mm), 12 frames of a flat wall
2.0 m in front of the camera with a 0.5 m closer square (1.5 m) in the middle, a band of
missing depth (0) along the top rows. (Open3D plays a recording back in real time and may drop
frames; 12 frames make it very likely that several arrive.)
"""

from __future__ import annotations

import sys

import numpy as np
import pyrealsense2 as rs

W, H, FPS, N_FRAMES = 640, 480, 30, 12


def intrinsics() -> rs.intrinsics:
    i = rs.intrinsics()
    i.width, i.height = W, H
    i.fx = i.fy = 387.229
    i.ppx, i.ppy = 321.046, 243.450
    i.model = rs.distortion.none
    i.coeffs = [0.0] * 5
    return i


def stream(kind: rs.stream, uid: int, fmt: rs.format, bpp: int) -> rs.video_stream:
    s = rs.video_stream()
    s.type, s.index, s.uid = kind, 0, uid
    s.width, s.height, s.fps, s.bpp, s.fmt = W, H, FPS, bpp, fmt
    s.intrinsics = intrinsics()
    return s


def main(out: str) -> None:
    dev = rs.software_device()
    for key, val in (
        (rs.camera_info.name, "Intel RealSense D435 (software)"),
        (rs.camera_info.serial_number, "000000000001"),
        (rs.camera_info.firmware_version, "5.13.0.50"),
        (rs.camera_info.product_id, "0B07"),
        (rs.camera_info.product_line, "D400"),
    ):
        dev.register_info(key, val)
    depth_sensor = dev.add_sensor("Stereo Module")
    color_sensor = dev.add_sensor("RGB Camera")
    dprof = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, rs.format.z16, 2))
    cprof = color_sensor.add_video_stream(stream(rs.stream.color, 1, rs.format.rgb8, 3))
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    cprof.register_extrinsics_to(dprof, rs.extrinsics())
    recorder = rs.recorder(out, dev)
    depth_sensor.open(dprof)
    color_sensor.open(cprof)
    depth_sensor.start(lambda f: None)
    color_sensor.start(lambda f: None)
    depth = np.full((H, W), 2000, np.uint16)
    c = (H // 2, W // 2)
    half = int(0.25 * 387.229 / 1.5)  # a 0.5 m square at 1.5 m
    depth[c[0] - half : c[0] + half, c[1] - half : c[1] + half] = 1500
    depth[:12] = 0
    color = np.full((H, W, 3), 128, np.uint8)
    for k in range(N_FRAMES):
        t_ms = 1000.0 + k * 1000.0 / FPS
        for sensor, prof, pixels, bpp in (
            (depth_sensor, dprof, depth, 2),
            (color_sensor, cprof, color, 3),
        ):
            f = rs.software_video_frame()
            f.pixels = pixels.copy()
            f.stride, f.bpp = W * bpp, bpp
            f.timestamp, f.domain = t_ms, rs.timestamp_domain.hardware_clock
            f.frame_number = k
            f.profile = prof.as_video_stream_profile()
            sensor.on_video_frame(f)
    for sensor in (depth_sensor, color_sensor):
        sensor.stop()
        sensor.close()
    del recorder


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "realsense_wall.bag")
