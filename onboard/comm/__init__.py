"""Swarm bus: message schema (``wire``), key expressions (``keys``), the receiving gate
(``gate``), clock-offset estimates (``clock``), peer buses (in-memory, fault-injecting, Zenoh)."""

from onboard.comm.bus import InMemoryBus, PeerBus
from onboard.comm.messages import TrajectoryMsg

__all__ = ["InMemoryBus", "PeerBus", "TrajectoryMsg"]
