"""Key expressions of the swarm bus, all under one swarm name.

========================================  ==========================================
``<swarm>/drone/<id>/traj``               trajectory of drone ``id`` (after every replan)
``<swarm>/drone/<id>/state``              its state, 10 Hz
``<swarm>/drone/<id>/status``             its status, 1 Hz
``<swarm>/cmd/<action>``                  ground-station command (``takeoff``, ``land``,
                                          ``abort``, ``resume``, ``goal``, ``waypoints``,
                                          ``formation``); targets inside the message
``<swarm>/ack/<id>``                      drone ``id``'s acknowledgements
``<swarm>/alive/drone/<id>``              liveliness token of drone ``id``
``<swarm>/alive/gcs``                     liveliness token of the ground station
========================================  ==========================================

Commands carry their targets in the body (empty: all drones) rather than in the key, so that
one message addresses any subset and one access-control rule (``<swarm>/cmd/**``: ground
station only) covers every command. Every drone-published key contains the drone id, so an
access-control rule can bind an identity to its own keys.
"""

from __future__ import annotations

import re

from onboard.comm.wire import ACTIONS, MAX_DRONE_ID, Rejected

_SWARM_RE = re.compile(r"[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*")
DRONE_STREAMS = ("traj", "state", "status")


def check_swarm(name: str) -> str:
    """The swarm name, checked: chunks of ``A-Za-z0-9_-`` separated by ``/`` (no wildcards)."""
    if not isinstance(name, str) or _SWARM_RE.fullmatch(name) is None:
        raise ValueError(f"swarm name {name!r} must be chunks of A-Za-z0-9_- separated by '/'")
    return name


class SwarmKeys:
    """Builds and parses the key expressions of one swarm."""

    def __init__(self, swarm: str) -> None:
        self.swarm = check_swarm(swarm)
        s = self.swarm
        self.all_traj = f"{s}/drone/*/traj"
        self.all_state = f"{s}/drone/*/state"
        self.all_status = f"{s}/drone/*/status"
        self.all_cmd = f"{s}/cmd/*"
        self.all_ack = f"{s}/ack/*"
        self.all_alive = f"{s}/alive/**"
        self.alive_gcs = f"{s}/alive/gcs"

    def drone(self, drone_id: int, stream: str) -> str:
        if stream not in DRONE_STREAMS:
            raise ValueError(f"stream must be one of {DRONE_STREAMS}, got {stream!r}")
        return f"{self.swarm}/drone/{_check_id(drone_id)}/{stream}"

    def traj(self, drone_id: int) -> str:
        return self.drone(drone_id, "traj")

    def state(self, drone_id: int) -> str:
        return self.drone(drone_id, "state")

    def status(self, drone_id: int) -> str:
        return self.drone(drone_id, "status")

    def cmd(self, action: str) -> str:
        if action not in ACTIONS:
            raise ValueError(f"command action must be one of {ACTIONS}, got {action!r}")
        return f"{self.swarm}/cmd/{action}"

    def ack(self, drone_id: int) -> str:
        return f"{self.swarm}/ack/{_check_id(drone_id)}"

    def alive_drone(self, drone_id: int) -> str:
        return f"{self.swarm}/alive/drone/{_check_id(drone_id)}"

    def parse(self, key: str) -> tuple[str, int | str]:
        """``(stream, drone id)`` for drone and ack keys, ``("cmd", action)`` for commands;
        raises ``Rejected("bad_key")`` for anything else."""
        prefix = self.swarm + "/"
        if not key.startswith(prefix):
            raise Rejected("bad_key", f"{key!r} is not under {self.swarm!r}")
        parts = key[len(prefix) :].split("/")
        if len(parts) == 3 and parts[0] == "drone" and parts[2] in DRONE_STREAMS:
            return parts[2], _parse_id(parts[1], key)
        if len(parts) == 2 and parts[0] == "cmd" and parts[1] in ACTIONS:
            return "cmd", parts[1]
        if len(parts) == 2 and parts[0] == "ack":
            return "ack", _parse_id(parts[1], key)
        raise Rejected("bad_key", f"{key!r} is not a swarm bus key")

    def parse_alive(self, key: str) -> tuple[str, int | None] | None:
        """``("drone", id)`` or ``("gcs", None)`` for a liveliness key, None otherwise."""
        prefix = self.swarm + "/alive/"
        if not key.startswith(prefix):
            return None
        rest = key[len(prefix) :].split("/")
        if rest == ["gcs"]:
            return "gcs", None
        if len(rest) == 2 and rest[0] == "drone":
            try:
                return "drone", _parse_id(rest[1], key)
            except Rejected:
                return None
        return None


def _check_id(drone_id: int) -> int:
    if isinstance(drone_id, bool) or not isinstance(drone_id, int):
        raise ValueError(f"drone id must be an int, got {drone_id!r}")
    if not 0 <= drone_id <= MAX_DRONE_ID:
        raise ValueError(f"drone id {drone_id} not in [0, {MAX_DRONE_ID}]")
    return drone_id


def _parse_id(text: str, key: str) -> int:
    if (
        not (text.isascii() and text.isdigit())
        or len(text) > 4
        or (len(text) > 1 and text[0] == "0")
    ):
        raise Rejected("bad_key", f"{key!r}: {text!r} is not a drone id")
    value = int(text)
    if value > MAX_DRONE_ID:
        raise Rejected("bad_key", f"{key!r}: drone id {value} > {MAX_DRONE_ID}")
    return value
