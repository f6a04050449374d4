"""The mock's depth streamer: one frame per vehicle with a new pose; with ``idle_rate_hz`` a
disarmed vehicle gets frames at that lower rate (a fleet waiting for its flight services costs
little rendering, yet each service gets the frames of its first map)."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.world import World
from sitl_mock.truth import DepthStreamer, InMemoryTruth, TruthSample, simulated_d435


def _sample(sid: int, t: float, armed: bool) -> TruthSample:
    return TruthSample(
        sid, t, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.0, armed, not armed,
        "OFFBOARD" if armed else "HOLD", 0,
    )  # fmt: skip


def test_disarmed_vehicles_get_frames_at_the_idle_rate() -> None:
    world = World(np.array([[3.0, 0.0, 0.3, 0.0, 3.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    cams = {1: simulated_d435(world, 0, step=8), 2: simulated_d435(world, 1, step=8)}
    poses = {1: _sample(1, 1.0, armed=True), 2: _sample(2, 1.0, armed=False)}
    with pytest.raises(ValueError, match="idle_rate_hz"):
        DepthStreamer(cams, lambda: dict(poses), [], rate_hz=10.0, idle_rate_hz=0.0)
    sink = InMemoryTruth()
    # an idle period far longer than this test: one frame of the disarmed vehicle, then none
    s = DepthStreamer(cams, lambda: dict(poses), [sink], rate_hz=10.0, idle_rate_hz=1e-4)
    assert s.render_once() == 2 and set(sink.depth) == {1, 2}
    assert s.render_once() == 0  # no new pose, no new frame
    for k in range(3):
        poses = {1: _sample(1, 2.0 + k, armed=True), 2: _sample(2, 2.0 + k, armed=False)}
        assert s.render_once() == 1  # the armed vehicle only
    assert sink.depth[2].stamp_s == pytest.approx(1.0) and sink.depth[1].stamp_s == 4.0
    poses[2] = _sample(2, 5.0, armed=True)  # vehicle 2 armed for take-off: full rate
    assert s.render_once() == 1 and sink.depth[2].stamp_s == pytest.approx(5.0)
    assert sink.depth[2].depth_m.shape == (60, 80)  # every 8th pixel of 640 x 480
    # without an idle rate every vehicle gets every frame
    every = DepthStreamer(cams, lambda: dict(poses), [InMemoryTruth()], rate_hz=10.0)
    poses = {1: _sample(1, 6.0, armed=False), 2: _sample(2, 6.0, armed=False)}
    assert every.render_once() == 2
    poses = {1: _sample(1, 7.0, armed=False), 2: _sample(2, 7.0, armed=False)}
    assert every.render_once() == 2
