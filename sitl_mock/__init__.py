"""A pure-Python PX4-like autopilot fleet that real MAVLink 2 clients (MAVSDK, pymavlink) fly.

What it imitates is PX4 v1.16 as a companion computer sees it; ``sitl_mock/README.md`` lists
each observable behaviour, its source (observation of a real PX4 v1.16 or PX4's code), the test
that checks it and the differences that remain.

- ``sitl_mock.fleet``: ``Fleet`` / ``FleetConfig``: N vehicles in one process and one loop;
- ``sitl_mock.autopilot``: the PX4-like flight logic (modes, arming, offboard, failsafe);
- ``sitl_mock.dynamics``: the quadrotor model and PX4-like position controller (numba);
- ``sitl_mock.mavlink_io``: the API link of one vehicle (UDP, streams, commands, signing);
- ``sitl_mock.px4_dialect``: the MAVLink dialect (development + two messages) and fast framer;
- ``sitl_mock.telemetry``: the fleet-wide kernel computing what the streams report (NED, FRD);
- ``sitl_mock.frames``: ENU <-> NED, attitudes, geodetic positions;
- ``sitl_mock.truth``: ground-truth poses and simulated depth frames, in-memory or over Zenoh;
- ``sitl_mock.client``: a small MAVLink client for tests and benchmarks;
- ``sitl_mock.cli``: the ``swarm-sitl`` command.
"""

# the mock's kernels are cached by numba like the onboard ones: stale caches cleared first
import onboard  # noqa: E402,F401  (onboard/__init__ clears both packages' stale caches)
