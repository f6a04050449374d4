"""Compile numba's kernels into its on-disk cache before the suite (``make test``).

Not a test module: the Makefile runs ``python tests/warm_kernels.py planner`` and ``... rest``
side by side before pytest-xdist starts its workers. Without it every worker compiles the same
kernels at the same time when its first test needs them (measured on 6 planner and fast-time
test files, cold, 2 workers: 206 s of CPU; warmed first: 27 + 97 s). With a warm cache each
part takes a few seconds (loading).

- ``planner``: the flight service's own warm-up (a ``DroneAgent`` cycle on a grid field and on
  the exact field: the planner, A*, the checks);
- ``rest``: a simulated depth camera into the map and its ESDF (render, ray casting, ESDF), the
  exact world distances, and a few steps of the mock's vehicle dynamics and telemetry.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def planner() -> None:
    from onboard.planner.params import PlannerParams
    from onboard.service.planning import warm_up

    warm_up(PlannerParams())


def rest() -> None:
    from onboard.sensors.simulated import SimulatedPerception
    from onboard.world import World
    from sitl_mock.client import bind_consecutive_udp
    from sitl_mock.fleet import Fleet, FleetConfig

    world = World(
        np.array([[3.0, 0.0, 0.3, 0.0, 2.5]]),
        np.array([[6.0, 0.0, 1.5, 0.0, 0.8, 0.6, 0.1]]),
        np.array([[8.0, -1.0, 0.0, 9.0, 1.0, 2.0]]),
        0.0,
    )
    world.distance(np.zeros((4, 3)))
    eyes = SimulatedPerception(world, skip_pixel=4)
    for k in range(3):
        eyes.observe(k / 30, np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), None)
    eyes.field().distance(np.array([[2.0, 0.0, 1.0]]))

    socks = bind_consecutive_udp(2)
    port = socks[0].getsockname()[1]
    for s in socks:
        s.close()
    fleet = Fleet(FleetConfig(count=2, base_port=port, local_port_offset=None, speedup=20.0))
    fleet.start()
    try:
        time.sleep(1.0)
    finally:
        fleet.stop()


if __name__ == "__main__":
    parts = {"planner": planner, "rest": rest}
    if len(sys.argv) != 2 or sys.argv[1] not in parts:
        sys.exit(f"usage: {sys.argv[0]} {{{'|'.join(parts)}}}")
    t0 = time.perf_counter()
    parts[sys.argv[1]]()
    print(f"warm_kernels {sys.argv[1]}: {time.perf_counter() - t0:.1f} s")
