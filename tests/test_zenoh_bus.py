"""The swarm bus over real Zenoh sessions on loopback: trajectories, validity, liveliness,
commands and acks, bad payloads, callback errors, clock offsets."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from functools import partial
from typing import Any

import msgspec
import numpy as np
import pytest
import zenoh

from onboard.comm import PeerBus, TrajectoryMsg
from onboard.comm.wire import (
    WIRE_VERSION,
    Ack,
    Command,
    Envelope,
    Goal,
    Land,
    StateBody,
    StatusBody,
    Takeoff,
)
from onboard.comm.zenoh_bus import BusConfig, SwarmNode, ZenohBus
from onboard.comm.zenoh_session import open_session, peer_mesh
from onboard.planner.trajectory import Trajectory
from onboard.service.adapters import SwarmBusAdapter, _status_counters

SWARM = "t/swarm"
DEADLINE_S = 30.0  # a deadline on a loaded machine, not a timed assert


def wait_for(cond: Callable[[], Any], what: str, timeout_s: float = DEADLINE_S) -> Any:
    """Poll ``cond`` until it returns something truthy (a deadline, not a timed assert)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = cond()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def mesh() -> Iterator[Callable[..., list[SwarmNode]]]:
    """Factory of nodes on one loopback mesh; every node and raw session is closed after."""
    with ExitStack() as stack:

        def make(ids: list[int | None], **kw: Any) -> list[SwarmNode]:
            eps = peer_mesh(len(ids))
            nodes = []
            for i, ep in zip(ids, eps, strict=True):
                node = SwarmNode(SWARM, i, ep, **kw.get(str(i), {}))
                stack.callback(node.close)
                nodes.append(node)
            drones = {i for i in ids if i is not None}
            for n in nodes:
                wait_for(partial(_sees, n, drones), "every drone alive")
            if len(nodes) > 1:  # the subscriptions too, not only the liveliness tokens
                for n in nodes:
                    if n.drone_id is not None:
                        wait_for(n.heard_by_someone, "a subscriber of the trajectories")
            return nodes

        yield make


def _sees(node: SwarmNode, drones: set[int]) -> bool:
    return node.alive_drones() == drones


def traj(drone: int, t0: float, traj_id: int = 0, pieces: int = 6) -> TrajectoryMsg:
    c = np.zeros((pieces, 6, 3))
    c[:, 0] = [drone, 0.0, 1.0]
    c[:, 1] = [0.5, 0.0, 0.0]
    return TrajectoryMsg(drone, traj_id, drone, Trajectory(t0, c, np.full(pieces, 1.0)), 1)


def state(x: float = 0.0) -> StateBody:
    return StateBody(
        "HOVER", time.time(), (x, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0, 0, 0), True, "OFFBOARD", 0, 1
    )


def test_peers_exchange_trajectories_latest_only(mesh: Callable[..., list[SwarmNode]]) -> None:
    a, b = mesh([0, 1])
    bus: PeerBus = a  # the planner's interface
    assert ZenohBus is SwarmNode
    now = time.time()
    # One at a time: the trajectory publisher drops under congestion (Zenoh's queue holds two
    # express batches and waits 1 ms before dropping), so three puts back to back on a loaded
    # machine can lose the third. Each is awaited; the receiver keeps only the latest.
    for k in range(3):
        bus.publish(traj(0, now, traj_id=k), time.time())
        got = wait_for(
            lambda k=k: (r := b.receive(1, time.time())) and r[0].traj_id == k and r, f"traj {k}"
        )
        assert set(got) == {0}
    b.publish(traj(1, now), time.time())
    m = got[0]
    assert set(got) == {0} and m.drone_id == 0 and m.slot == 0 and m.formation_epoch == 1
    np.testing.assert_array_equal(m.trajectory.coeffs, traj(0, now).trajectory.coeffs)
    assert m.trajectory.t0_s == now
    assert set(wait_for(lambda: a.receive(0, time.time()), "a hears b")) == {1}  # own excluded
    assert set(b.trajectories(time.time())) == {0}
    c = b.counters()
    assert c["rx.traj"] == 3 and a.counters()["tx.traj"] == 3
    assert sum(v for k, v in c.items() if k.startswith(("reject.", "error."))) == 0


def test_callbacks_run_in_threads_named_for_the_bus(
    mesh: Callable[..., list[SwarmNode]],
) -> None:
    """Zenoh runs a subscriber's callbacks in a thread of its own; the node names it (``bus-rx``)
    so that its CPU is told apart from the process's main thread in ``/proc``."""
    a, b = mesh([0, 1])
    names: list[str] = []

    def on_traj(env: Envelope, now: float) -> None:
        tid = threading.get_native_id()
        with open(f"/proc/self/task/{tid}/comm") as f:
            names.append(f.read().strip())

    b.on_trajectory(on_traj)
    a.publish(traj(0, time.time()), time.time())
    wait_for(lambda: names, "the callback")
    assert names[0] == "bus-rx"


def test_trajectory_dropped_after_its_validity(mesh: Callable[..., list[SwarmNode]]) -> None:
    a, b = mesh([0, 1])
    now = time.time()
    msg = traj(0, now)
    a.publish_trajectory(TrajectoryMsg(0, 0, 0, msg.trajectory, 1, valid_until_s=now + 0.5), now)
    got = wait_for(lambda: b.receive(1, time.time()), "trajectory")
    until = got[0].valid_until_s
    assert until == pytest.approx(now + 0.5)
    assert b.receive(1, until) != {}  # valid up to and including its end of validity
    assert b.receive(1, until + 1e-3) == {}
    assert set(b.expired(until + 1e-3, keep_s=2.0)) == {0}  # still avoidable for a while
    assert b.expired(until + 2.5, keep_s=2.0) == {}
    # Default validity from the config when the message has none.
    a.publish_trajectory(traj(0, now, traj_id=1))
    m = wait_for(lambda: (r := b.receive(1, time.time())) and r[0].traj_id == 1 and r, "t1")[0]
    assert m.valid_until_s == pytest.approx(time.time() + 3.0, abs=0.5)


def test_liveliness_appears_and_disappears(mesh: Callable[..., list[SwarmNode]]) -> None:
    gcs, d0, d1 = mesh([None, 0, 1])
    events: list[tuple[str, int | None, bool]] = []
    gcs.on_alive(lambda kind, i, up: events.append((kind, i, up)))
    assert gcs.alive_drones() == {0, 1} and d0.alive_drones() == {0, 1}
    assert wait_for(d0.gcs_alive, "gcs seen")
    drones, gcs_up = gcs.query_alive(timeout_s=2.0)
    assert drones == {0, 1} and gcs_up
    d1.close()
    wait_for(lambda: gcs.alive_drones() == {0}, "drone 1 gone")
    wait_for(lambda: d0.alive_drones() == {0}, "drone 1 gone for its peer")
    assert ("drone", 1, False) in events
    gcs.close()
    wait_for(lambda: not d0.gcs_alive(), "gcs gone")


def test_commands_and_acks(mesh: Callable[..., list[SwarmNode]]) -> None:
    gcs, d0, d1 = mesh([None, 0, 1])
    got: dict[int, list[Envelope]] = {0: [], 1: []}

    def answer(node: SwarmNode, reply: bool) -> Callable[[Envelope, float], None]:
        def cb(env: Envelope, _rx: float) -> None:
            assert node.drone_id is not None
            got[node.drone_id].append(env)
            assert isinstance(env.body, Command)
            if reply:
                node.send_ack(env.body.cmd_id, isinstance(env.body.action, Takeoff), "not now")

        return cb

    d0.on_command(answer(d0, True))
    d1.on_command(answer(d1, False))
    acks: list[Envelope] = []
    gcs.on_ack(lambda env, _rx: acks.append(env))

    sent = gcs.send_command(Takeoff(2.0))  # every drone
    assert gcs.wait_acks(sent.cmd_id, [0], timeout_s=DEADLINE_S) == set()
    assert gcs.acks(sent.cmd_id) == {0: Ack(sent.cmd_id, True, "not now")}
    wait_for(lambda: got[1], "drone 1 got the takeoff")
    assert got[0][0].body == got[1][0].body == sent and got[0][0].sender == 1000

    goal = gcs.send_command(Goal((5.0, 1.0, 1.0), None, time.time() + 1.0), targets=[0])
    assert gcs.wait_acks(goal.cmd_id, [0], DEADLINE_S) == set()
    assert gcs.acks(goal.cmd_id)[0].accepted is False
    wait_for(lambda: d1.counters()["cmd.not_addressed"] == 1, "not addressed counted")
    assert len(got[1]) == 1

    # A command nobody answers in time is reported with the ids that did not answer.
    land = gcs.send_command(Land(), targets=[0, 1])
    assert gcs.wait_acks(land.cmd_id, [0, 1], timeout_s=0.5) == {1}
    # A resend keeps the command id and issue time.
    again = gcs.send_command(Land(), targets=[1], cmd_id=land.cmd_id, issued_s=land.issued_s)
    wait_for(lambda: len(got[1]) == 3, "resend")
    assert got[1][-1].body == again and again.cmd_id == land.cmd_id
    assert acks and all(e.sender == 0 for e in acks)
    with pytest.raises(RuntimeError, match="ground-station"):
        d0.send_command(Land())
    with pytest.raises(RuntimeError, match="ground-station"):
        gcs.publish_state(state())


def test_states_and_statuses_reach_the_ground_station(
    mesh: Callable[..., list[SwarmNode]],
) -> None:
    gcs, d0 = mesh([None, 0])
    d0.publish_state(state(3.0))
    st = StatusBody("HOVER", "ok", None, 12.0, 30.0, 4, [], 15.9, 0.8, None, {"rx.traj": 3}, "")
    d0.publish_status(st)
    s = wait_for(lambda: gcs.latest_states().get(0), "state")[0]
    assert isinstance(s.body, StateBody) and s.body.position_m == (3.0, 0.0, 1.0)
    assert wait_for(lambda: gcs.latest_statuses().get(0), "status")[0].body == st
    assert d0.latest_states() == {}  # drones do not subscribe to states by default


def test_bad_payloads_never_reach_the_inbox() -> None:
    eps = peer_mesh(2)
    with SwarmNode(SWARM, 1, eps[0]) as victim, ExitStack() as stack:
        attacker = open_session(eps[1])
        stack.callback(attacker.close)
        wait_for(lambda: victim.alive_drones() == {1}, "victim up")
        # The victim declares its subscribers before its liveliness token: once the attacker
        # sees the token, its puts are routed to the victim.
        wait_for(
            lambda: list(attacker.liveliness().get(f"{SWARM}/alive/drone/1", timeout=0.5)),
            "the victim's token seen by the attacker",
        )
        now = time.time()
        good = traj(0, now).to_body()
        key = f"{SWARM}/drone/0/traj"

        def env(**kw: Any) -> bytes:
            base = dict(
                version=WIRE_VERSION,
                sender=0,
                incarnation=1,
                seq=0,
                stamp_s=now,
                valid_for_s=3.0,
                body=good,
            )
            base.update(kw)
            return msgspec.msgpack.encode(Envelope(**base))  # type: ignore[arg-type]

        bad = [
            b"",
            b"\xff" * 50,
            env(version=99),
            env()[:-3],
            env(body=msgspec.structs.replace(good, t0_s=float("nan"))),
            env(sender=2),
            env(stamp_s=now - 60.0),
            b"\x00" * 70000,
        ]
        block = zenoh.CongestionControl.BLOCK  # never dropped by the sender's queue
        for payload in bad:
            attacker.put(key, payload, congestion_control=block)
        # a good one after all of them
        attacker.put(key, env(seq=5, stamp_s=time.time()), congestion_control=block)
        wait_for(lambda: victim.receive(1, time.time()), f"the good one {victim.counters()}")
        c = victim.counters()
        rejected = {k: v for k, v in c.items() if k.startswith("reject.") and v}
        assert sum(rejected.values()) == len(bad), rejected
        for reason in (
            "version",
            "truncated",
            "non_finite",
            "sender_mismatch",
            "stale",
            "oversized",
            "malformed",
        ):
            assert rejected.get(f"reject.{reason}", 0) >= 1, (reason, rejected)
        assert c["error.internal"] == 0 and c["rx.traj"] == 1
        assert victim.receive(1, time.time())[0].trajectory.t0_s == now
        assert c["reject.truncated"] == 2 and c["reject.malformed"] == 1


def test_callback_errors_are_logged_and_counted(
    mesh: Callable[..., list[SwarmNode]], caplog: pytest.LogCaptureFixture
) -> None:
    a, b = mesh([0, 1])
    seen: list[int] = []

    def broken(env: Envelope, _rx: float) -> None:
        raise ZeroDivisionError("bug in a callback")

    b.on_trajectory(broken)
    b.on_trajectory(lambda env, _rx: seen.append(env.seq))
    with caplog.at_level(logging.ERROR, logger="onboard.comm.zenoh_bus"):
        a.publish(traj(0, time.time()), time.time())
        wait_for(lambda: seen, "the second callback still runs")
    assert b.counters()["error.callback"] == 1 and b.counters()["error.internal"] == 0
    assert any("ZeroDivisionError" in (r.exc_text or "") for r in caplog.records)
    assert b.receive(1, time.time())  # the inbox was updated all the same


def test_clock_offset_estimated_and_warned(
    mesh: Callable[..., list[SwarmNode]], caplog: pytest.LogCaptureFixture
) -> None:
    ahead = 0.3
    cfg = BusConfig(clock_offset_bound_s=0.05, subscribe_states=True)
    a, b = mesh([0, 1], **{"0": {"clock": lambda: time.time() + ahead}, "1": {"config": cfg}})
    # b subscribes to states: put nothing before Zenoh matched it (a state put earlier reaches
    # nobody)
    wait_for(lambda: a.heard_by_someone("state"), "a subscriber of the states")
    with caplog.at_level(logging.WARNING, logger="onboard.comm.clock"):
        for k in range(5):  # one at a time: the state publisher drops under congestion
            a.publish_state(state(float(k)))
            wait_for(lambda k=k: b.counters()["rx.state"] == k + 1, f"state {k}")
    report = b.clock_report()[0]
    # our clock minus theirs (-0.3) plus the smallest loopback latency (small, positive)
    assert -ahead <= report.offset_s < -ahead + 0.1
    assert report.exceeded and report.samples == 5
    assert b.clock_exceeded() == {0}
    # what the flight service reads to refuse formation flight (onboard.service.ports)
    assert SwarmBusAdapter(b).clock_exceeded() == {0: report.offset_s}
    assert b.counters()["clock.warnings"] == 1
    assert any("clock offset to sender 0" in r.getMessage() for r in caplog.records)
    # Seen from the other side the same offset has the other sign.
    b.publish_trajectory(traj(1, time.time()))
    wait_for(lambda: 1 in a.clock_report(), "a hears b")
    assert ahead <= a.clock_report()[1].offset_s < ahead + 0.1


def test_sender_refuses_bad_messages_naming_the_field(
    mesh: Callable[..., list[SwarmNode]],
) -> None:
    (a,) = mesh([0])
    with pytest.raises(ValueError, match="altitude_m|position_m"):
        a.publish_state(msgspec.structs.replace(state(), position_m=(1e9, 0.0, 0.0)))
    with pytest.raises(ValueError, match="published by"):
        a.publish(traj(3, time.time()), time.time())
    assert a.counters()["tx.state"] == 0
    a.close()
    with pytest.raises(RuntimeError, match="closed"):
        a.publish(traj(0, time.time()), time.time())
    a.close()  # idempotent


def test_planner_thread_reads_whole_messages_while_they_arrive(
    mesh: Callable[..., list[SwarmNode]],
) -> None:
    a, b = mesh([0, 1])
    n = 200
    stop = threading.Event()
    torn: list[str] = []
    reads = [0]

    def planner() -> None:
        while not stop.is_set():
            m = b.receive(1, time.time()).get(0)
            reads[0] += 1
            if m is not None and m.trajectory.coeffs[0, 0, 0] != m.traj_id:
                torn.append(f"traj {m.traj_id} with the coefficients of another")

    reader = threading.Thread(target=planner)
    reader.start()
    now = time.time()
    sent = 0
    last_sent = time.monotonic()

    def publish_next() -> None:
        nonlocal sent, last_sent
        m = traj(0, now, traj_id=sent)
        c = m.trajectory.coeffs.copy()
        c[0, 0, 0] = sent
        a.publish(TrajectoryMsg(0, sent, 0, Trajectory(now, c, m.trajectory.durations_s)), now)
        sent += 1
        last_sent = time.monotonic()

    def burst_ended() -> bool:
        """The burst's last or a newer one arrived. Trajectories are published with Zenoh's
        DROP congestion control (a late one is worth less than the next), so under CPU load
        the burst may lose its last messages: then newer ones follow, one every 0.2 s."""
        r = b.receive(1, time.time())
        if r and r[0].traj_id >= n - 1:
            return True
        if time.monotonic() - last_sent > 0.2:
            publish_next()
        return False

    try:
        for _ in range(n):
            publish_next()
        wait_for(burst_ended, "the burst's last one or a newer one")
    finally:
        stop.set()
        reader.join()
    assert not torn and reads[0] > 0
    cnt = b.counters()
    assert cnt["error.internal"] == 0 and cnt["error.callback"] == 0
    # Received in order or refused as out of order: never an older one after a newer one.
    assert cnt["rx.traj"] + cnt["reject.out_of_order"] + cnt["reject.duplicate"] <= sent


def test_peer_trajectories_entering_the_inbox_are_latency_samples(
    mesh: Callable[..., list[SwarmNode]],
) -> None:
    """The flight service's inbox (``SwarmBusAdapter.peers()``, what the planner reads) takes a
    latency sample per peer trajectory: its clock after the update minus the sender's stamp. A
    trajectory the gate refuses (stale) is no sample. The service's clock is injected here so
    that each sample is known to the microsecond."""
    a, b = mesh([0, 1])
    stamp = time.time()
    inbox_time = stamp + 0.0123
    port = SwarmBusAdapter(b, clock=lambda: inbox_time)
    assert port.peer_latency().count == 0
    a.publish_trajectory(traj(0, stamp, traj_id=0), stamp)
    wait_for(lambda: 0 in port.peers(), "the first trajectory in the inbox")
    first = port.peer_latency()
    assert first.count == 1 and abs(first.max_us - 12300) <= 1 and first.below_zero == 0
    # refused by the gate (stale: stamped 60 s ago, valid 3 s), then a good one
    a.publish_trajectory(traj(0, stamp, traj_id=1), time.time() - 60.0)
    a.publish_trajectory(traj(0, stamp, traj_id=2), inbox_time - 0.0045)
    wait_for(lambda: port.peers()[0].traj_id == 2, "the good trajectory after the stale one")
    assert b.counters()["reject.stale"] == 1 and b.counters()["rx.traj"] == 2
    fig = port.peer_latency()
    assert fig.count == 2 and fig.below_zero == 0
    assert abs(fig.min_us - 4500) <= 1 and abs(fig.max_us - 12300) <= 1
    # in the counters (the flight record's /counters; the status gets the summary only)
    c = port.counters()
    assert c["peer_latency.count"] == 2 and c["rx.traj"] == 2
    bins = {k: v for k, v in c.items() if k.startswith("peer_latency.bin_us.")}
    assert sum(bins.values()) == 2
    status = _status_counters({f"bus.{k}": v for k, v in c.items()})
    assert status["bus.peer_latency.count"] == 2 and status["bus.peer_latency.p99_us"] > 0
    assert not [k for k in status if ".bin_us." in k] and len(status) <= 128
