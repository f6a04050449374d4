"""A pure-Python PX4-like autopilot fleet that real MAVLink 2 clients (MAVSDK, pymavlink) fly.

- ``sitl_mock.fleet``: ``Fleet`` / ``FleetConfig``: N vehicles in one process and one loop;
- ``sitl_mock.autopilot``: the PX4-like flight logic (modes, arming, offboard, failsafe);
- ``sitl_mock.dynamics``: the quadrotor model and PX4-like position controller (numba);
- ``sitl_mock.mavlink_io``: the API link of one vehicle (UDP, streams, commands, signing);
- ``sitl_mock.frames``: ENU <-> NED, attitudes, geodetic positions;
- ``sitl_mock.truth``: ground-truth poses and simulated depth frames, in-memory or over Zenoh;
- ``sitl_mock.client``: a small MAVLink client for tests and benchmarks;
- ``sitl_mock.cli``: the ``swarm-sitl`` command.
"""
