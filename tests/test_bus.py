"""InMemoryBus: delivery delay, latest-only, silenced peers, own messages excluded."""

from __future__ import annotations

import numpy as np

from onboard.comm import InMemoryBus, TrajectoryMsg
from onboard.planner.trajectory import Trajectory


def _msg(drone: int, traj_id: int, t0: float = 0.0) -> TrajectoryMsg:
    return TrajectoryMsg(drone, traj_id, drone, Trajectory.hover(np.array([drone, 0.0, 1.0]), t0))


def test_message_visible_only_after_delay() -> None:
    bus = InMemoryBus(delay_s=0.05)
    bus.publish(_msg(1, 0), now_s=1.0)
    assert bus.receive(0, now_s=1.0) == {}
    assert bus.receive(0, now_s=1.04) == {}
    got = bus.receive(0, now_s=1.05)
    assert list(got) == [1] and got[1].traj_id == 0


def test_latest_visible_per_sender_only() -> None:
    bus = InMemoryBus(delay_s=0.1)
    bus.publish(_msg(1, 0), 0.0)
    bus.publish(_msg(1, 1), 0.5)
    bus.publish(_msg(2, 0), 0.5)
    bus.publish(_msg(1, 2), 1.0)
    got = bus.receive(0, 0.65)
    assert {k: m.traj_id for k, m in got.items()} == {1: 1, 2: 0}
    got = bus.receive(0, 2.0)
    assert {k: m.traj_id for k, m in got.items()} == {1: 2, 2: 0}
    # A receiver that first polls late sees the newest only.
    assert bus.receive(3, 2.0)[1].traj_id == 2


def test_own_messages_excluded() -> None:
    bus = InMemoryBus()
    bus.publish(_msg(0, 0), 0.0)
    bus.publish(_msg(1, 0), 0.0)
    assert set(bus.receive(0, 0.0)) == {1}
    assert set(bus.receive(1, 0.0)) == {0}


def test_silenced_peer_and_lossy_link_keep_previous() -> None:
    bus = InMemoryBus(delay_s=0.0, drop=lambda sender, receiver: sender == 2)
    for k in range(3):
        bus.publish(_msg(1, k), float(k))
        bus.publish(_msg(2, k), float(k))
    got = bus.receive(0, 5.0)
    assert set(got) == {1}

    # Drop only the newest message on one link: that receiver keeps the previous one.
    lost = {(1, 0, 1)}
    seen: list[tuple[int, int]] = []

    def drop(sender: int, receiver: int) -> bool:
        seen.append((sender, receiver))
        return (sender, receiver, len([s for s in seen if s == (sender, receiver)]) - 1) in lost

    bus2 = InMemoryBus(drop=drop)
    bus2.publish(_msg(1, 0), 0.0)
    assert bus2.receive(0, 0.0)[1].traj_id == 0
    bus2.publish(_msg(1, 1), 1.0)
    assert bus2.receive(0, 1.0)[1].traj_id == 0  # message 1 lost on link 1 -> 0
    assert bus2.receive(5, 1.0)[1].traj_id == 1  # another receiver got it
    bus2.publish(_msg(1, 2), 2.0)
    assert bus2.receive(0, 2.0)[1].traj_id == 2


def test_log_is_pruned() -> None:
    bus = InMemoryBus(delay_s=0.0)
    for k in range(100):
        bus.publish(_msg(1, k), float(k))
        bus.receive(0, float(k))
    assert len(bus._log[1]) <= 1
