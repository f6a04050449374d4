"""Trajectory sharing between drones: message types and peer-bus transports."""

from onboard.comm.bus import InMemoryBus, PeerBus
from onboard.comm.messages import TrajectoryMsg

__all__ = ["InMemoryBus", "PeerBus", "TrajectoryMsg"]
