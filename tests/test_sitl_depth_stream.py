"""The mock's depth streamer: one frame per vehicle with a new pose, and with ``armed_only`` none
for a vehicle standing disarmed (a fleet waiting for its flight services renders nothing)."""

from __future__ import annotations

import numpy as np

from onboard.world import World
from sitl_mock.truth import DepthStreamer, InMemoryTruth, TruthSample, simulated_d435


def _sample(sid: int, t: float, armed: bool) -> TruthSample:
    return TruthSample(
        sid, t, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.0, armed, not armed,
        "OFFBOARD" if armed else "HOLD", 0,
    )  # fmt: skip


def test_armed_only_renders_for_armed_vehicles_only() -> None:
    world = World(np.array([[3.0, 0.0, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    cams = {1: simulated_d435(world, 0, step=8), 2: simulated_d435(world, 1, step=8)}
    poses = {1: _sample(1, 1.0, armed=True), 2: _sample(2, 1.0, armed=False)}
    sink = InMemoryTruth()
    every = DepthStreamer(cams, lambda: dict(poses), [sink], rate_hz=10.0)
    assert every.render_once() == 2 and set(sink.depth) == {1, 2}
    sink = InMemoryTruth()
    armed = DepthStreamer(cams, lambda: dict(poses), [sink], rate_hz=10.0, armed_only=True)
    assert armed.render_once() == 1 and set(sink.depth) == {1}
    assert armed.render_once() == 0  # no new pose, no new frame
    poses[2] = _sample(2, 1.1, armed=True)  # vehicle 2 armed for take-off
    assert armed.render_once() == 1 and set(sink.depth) == {1, 2}
    assert sink.depth[2].depth_m.shape == (480, 640)
