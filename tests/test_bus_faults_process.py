"""Swarm bus faults between drones on the real Zenoh path (issue #12), on the real processes.

Three ``swarm-onboard run`` processes fly three mock vehicles (``swarm-sitl``, its own process).
Their swarm bus is a star: a Zenoh router opened by the test, and each service in
``zenoh.mode: client`` connected *only* to its own UDP fault proxy (``gcs.faultproxy``), which
forwards to the router's ``udp/`` endpoint; the ground-station client of the test connects
straight to the router over TCP. Every message between two drones therefore crosses two proxies
(the sender's uplink, the receiver's downlink); the test first shows that this is the only path
(downlinks at 100 % loss: the services hear no trajectory while the ground station still hears
theirs).

Faults per proxy and direction, seeded: 10.6 % loss (20 % over the two hops), a delay up to
150 ms (300 ms over two hops, in order), 10 % duplication and 5 % of datagrams held back 50 ms
so that later ones overtake them; and, in flight, drone 2's uplink held for 7.5 s and then
released in order (an outage that buffers), which delivers its trajectories after their
validity. Zenoh over UDP is best effort: its receiving transport drops a duplicated or
overtaken frame, so those two faults reach the services as loss (the proxies count what they
did; the services count what they received).

Judged on the mock's ground truth and the services' own records: every drone arrives at its
slot, no collision, the drones keep clear of each other; the trajectories that came after their
validity were refused by the receiving gate; while drone 2's newest trajectory was past its
validity the others planned with drone 2 avoided but not in the formation term, and took it back
afterwards.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from gcs.bench_service import (
    MockProcess,
    ServiceProcess,
    poll_until,
    service_config,
    swarm_summary,
    write_world,
)
from gcs.faultproxy import CLEAN, RCVBUF_BYTES, FaultyStar, LinkFaults, UdpFaultProxy
from gcs.station import GroundStation, StationConfig
from onboard.comm import wire
from onboard.comm.zenoh_session import free_loopback_endpoint, open_session
from onboard.record import read_record
from sitl_mock.client import bind_consecutive_udp

BODY_RADIUS_M = 0.2  # the mock's default
N = 3
# a line across the direction of flight; drones 0 and 2 swap ends on the way (their paths
# cross), so they must avoid each other through the trajectories the faulty bus carries
POINTS = [(0.0, -1.5, 0.0), (0.0, 0.0, 0.0), (0.0, 1.5, 0.0)]
SLOTS = {0: 2, 1: 1, 2: 0}
SPAWNS = [(0.0, -2.0, 0.0), (-1.5, 0.0, 0.0), (0.0, 2.0, 0.0)]
GOAL_CENTRE = np.array([11.0, 0.0, 1.0])
VALIDITY_S = 3.0  # reactions.peer_lost.validity_s: a trajectory's validity
# drone 2's uplink outage: > VALIDITY_S, so that what it buffered arrives stale. Drone 2 sends
# a trajectory a second, so the outage holds HOLD_S - VALIDITY_S of them past their validity,
# and each reaches drones 0 and 1 through two faulty hops (about 85 % each). At 6 s that was
# three, none of which reached either drone about once in 200 runs (a clean clone failed
# once so, 2026-11-29); at 7.5 s it is four or five (once in 1 000 to 10 000). It stays under
# Zenoh's 10 s lease, past which the router would drop drone 2's session.
HOLD_S = 7.5
# per proxy and direction: two hops make 1 - (1 - 0.106)^2 = 20 % loss and up to 300 ms
HOP_FAULTS = LinkFaults(
    loss=0.106,
    delay_min_s=0.0,
    delay_max_s=0.150,
    keep_order=True,
    duplicate=0.10,
    duplicate_lag_s=0.01,
    reorder=0.05,
    reorder_hold_s=0.05,
)


def _ok(outcome: Any) -> None:
    assert outcome.ok, outcome.describe()


def _states(gs: GroundStation) -> dict[int, str]:
    return {d: str(v.flight_state or "") for d, v in gs.views().items()}


def _status(gs: GroundStation, d: int) -> tuple[float, dict[str, int]]:
    """Stamp and counters of drone ``d``'s newest status (stamp -inf before the first)."""
    st = gs.node.latest_statuses().get(d)
    if st is None:
        return -np.inf, {}
    env = st[0]
    assert isinstance(env.body, wire.StatusBody)
    return float(env.stamp_s), dict(env.body.counters)


def _status_after(gs: GroundStation, d: int, t: float, timeout_s: float) -> dict[str, int]:
    """Counters of drone ``d``'s first status stamped after ``t`` (its sender's clock)."""
    poll_until(lambda: _status(gs, d)[0] > t, timeout_s, f"a status of drone {d} after {t:.1f}")
    return _status(gs, d)[1]


def _hears_again(gs: GroundStation, d: int, t: float, rx: int) -> Callable[[], bool]:
    """True once drone ``d`` reports, after ``t``, more peer trajectories than ``rx``."""

    def cond() -> bool:
        stamp, counters = _status(gs, d)
        return stamp > t and counters["bus.rx.traj"] > rx

    return cond


def _slot_goals() -> np.ndarray:
    pts = np.array(POINTS)
    centred = pts - pts.mean(axis=0)
    return np.array([GOAL_CENTRE + centred[SLOTS[d]] for d in range(N)])


# --- the proxy on its own (quick) -------------------------------------------------------------
class _Receiver:
    """A UDP socket on 127.0.0.1 whose thread collects datagrams (4-byte big-endian indices)
    from the start, so that none is lost in a full receive buffer."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.addr = self.sock.getsockname()
        self.got: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.got.append(int.from_bytes(self.sock.recv(100)[:4], "big"))
            except TimeoutError:
                continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


def _send_through(
    faults: LinkFaults, n: int = 400, seed: int = 3, hold_s: float = 0.0
) -> tuple[list[int], dict[str, int]]:
    """Send datagrams 0..n-1 up through a proxy with ``faults``; what arrived, in arrival
    order, and the proxy's counters once everything it kept was sent."""
    rx = _Receiver()
    try:
        with UdpFaultProxy(rx.addr, up=faults, down=CLEAN, seed=seed) as proxy:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                if hold_s:
                    proxy.hold(hold_s, "up")
                for i in range(n):
                    tx.sendto(i.to_bytes(4, "big"), ("127.0.0.1", proxy.port))
                    if i % 10 == 9:
                        time.sleep(0.001)  # the proxy's thread shares this interpreter
                deadline = time.monotonic() + 10.0
                while time.monotonic() < deadline:
                    counters = proxy.counters("up")
                    if counters["received"] == n and proxy.pending() == 0:
                        if len(rx.got) == counters["sent"]:
                            break
                    time.sleep(0.02)
                assert counters["received"] == n, counters
                assert len(rx.got) == counters["sent"], (len(rx.got), counters)
        return list(rx.got), counters
    finally:
        rx.close()


def test_the_proxy_loses_and_duplicates_as_counted_and_a_seed_repeats_it() -> None:
    faults = LinkFaults(loss=0.2, duplicate=0.1)
    got, c = _send_through(faults)
    assert c["received"] == 400 and c["send_errors"] == 0
    assert len(got) == c["sent"] == 400 - c["dropped"] + c["duplicated"]
    assert 40 <= c["dropped"] <= 120 and 15 <= c["duplicated"] <= 70, c
    assert len(got) - len(set(got)) == c["duplicated"]
    again, c2 = _send_through(faults)
    assert sorted(again) == sorted(got) and c2 == c  # same seed, same datagrams, same faults
    other, _ = _send_through(faults, seed=4)
    assert sorted(other) != sorted(got)


def test_delays_keep_the_order_unless_a_datagram_is_held_back() -> None:
    got, c = _send_through(LinkFaults(delay_min_s=0.01, delay_max_s=0.05))
    assert got == list(range(400)) and c["delayed"] == 400 and c["reordered"] == 0
    got, c = _send_through(LinkFaults(reorder=0.1, reorder_hold_s=0.02))
    assert sorted(got) == list(range(400))
    # every datagram that arrived after a later one is one the proxy counted as reordered
    late = sum(1 for k, i in enumerate(got) if i < max(got[:k], default=-1))
    assert late == c["reordered"] > 0 and c["held_back"] >= c["reordered"], c


def test_a_hold_releases_everything_in_order_afterwards() -> None:
    got, c = _send_through(LinkFaults(), n=100, hold_s=0.3)
    assert got == list(range(100)) and c["held"] == 100 and c["delayed"] == 100


def test_faults_are_checked_naming_the_field() -> None:
    with pytest.raises(ValueError, match="faults.loss"):
        LinkFaults(loss=1.5)
    with pytest.raises(ValueError, match="faults.delay_max_s"):
        LinkFaults(delay_min_s=0.2, delay_max_s=0.1)
    with pytest.raises(ValueError, match="faults.reorder_hold_s"):
        LinkFaults(reorder_hold_s=float("nan"))
    with UdpFaultProxy(("127.0.0.1", 9)) as proxy, pytest.raises(ValueError, match="direction"):
        proxy.set_faults(CLEAN, "sideways")


def test_zenoh_clients_behind_proxies_hear_each_other_only_through_them() -> None:
    """Two client sessions, each connected only to its own proxy, and a third straight to the
    router: with client 1's downlink at 100 % loss, client 1 hears nothing of client 0 while
    the direct session hears everything; open again, it hears client 0 again."""
    with ExitStack() as stack:
        star = stack.enter_context(FaultyStar(2, seed=5))
        a = open_session(star.client_endpoints(0))
        stack.callback(a.close)
        b = open_session(star.client_endpoints(1))
        stack.callback(b.close)
        g = open_session(star.direct_endpoints())
        stack.callback(g.close)
        heard: dict[str, list[int]] = {"b": [], "g": []}
        for name, session in (("b", b), ("g", g)):
            sub = session.declare_subscriber(
                "fp/**", lambda s, name=name: heard[name].append(int(s.payload.to_bytes()))
            )
            stack.callback(sub.undeclare)
        # BLOCK: under CPU load a session's queue may fill and Drop would lose messages there
        pub = a.declare_publisher("fp/x", congestion_control=zenoh.CongestionControl.BLOCK)
        stack.callback(pub.undeclare)

        def burst(first: int, n: int = 20) -> None:
            for i in range(first, first + n):
                pub.put(str(i).encode())
            poll_until(lambda: first + n - 1 in heard["g"], 5.0, "the direct session's copy")

        # the declarations travel once: probe until the router forwards to client 1 and to the
        # direct session (a probe put before a subscriber's declaration reached the router is
        # lost for that subscriber: waiting for each probe's copy failed CI once)
        probes: list[int] = []

        def both_hear() -> bool:
            probes.append(1000 + len(probes))
            pub.put(str(probes[-1]).encode())
            return bool(heard["b"]) and bool(heard["g"])

        poll_until(both_hear, 10.0, "client 1 and the direct session hear client 0", period_s=0.1)
        # a probe sent after the first one heard may still be in the proxy: the link keeps the
        # order, so once the last probe is heard nothing more of them is on its way
        poll_until(
            lambda: probes[-1] in heard["b"] and probes[-1] in heard["g"],
            5.0,
            "client 1 and the direct session hear the last probe",
        )
        star.proxies[1].set_faults(LinkFaults(loss=1.0), "down")
        heard["b"].clear()
        burst(0)
        time.sleep(0.3)  # anything still on its way through the proxy
        assert heard["b"] == [] and star.proxies[1].counters("down")["dropped"] > 0
        assert set(range(20)) <= set(heard["g"])
        star.proxies[1].set_faults(CLEAN)
        burst(100)
        poll_until(lambda: 119 in heard["b"], 5.0, "client 1 hears client 0 again")
        assert star.proxies[0].counters("up")["sent"] > 0  # client 0 sends through its proxy


def test_zenoh_over_udp_turns_duplicated_and_overtaken_datagrams_into_loss() -> None:
    """What the services can see of the proxies' duplication and reordering: Zenoh's receiving
    transport drops a frame whose sequence number does not come after the last one accepted,
    so a duplicated datagram is delivered once and an overtaken one not at all; what arrives
    arrives in order (measured on eclipse-zenoh 1.10; if this changes, the gate's duplicate and
    out-of-order refusals become reachable from the network)."""
    with ExitStack() as stack:
        star = stack.enter_context(FaultyStar(2, seed=9))
        a = open_session(star.client_endpoints(0))
        stack.callback(a.close)
        b = open_session(star.client_endpoints(1))
        stack.callback(b.close)
        heard: list[int] = []
        sub = b.declare_subscriber("fz/**", lambda s: heard.append(int(s.payload.to_bytes())))
        stack.callback(sub.undeclare)
        pub = a.declare_publisher(  # express: one message per datagram
            "fz/x", express=True, congestion_control=zenoh.CongestionControl.BLOCK
        )
        stack.callback(pub.undeclare)

        def b_hears() -> bool:
            pub.put(b"-1")
            return bool(heard)

        poll_until(b_hears, 10.0, "client 1 hears client 0", period_s=0.1)
        proxy = star.proxies[0]

        def send(first: int, n: int) -> list[int]:
            heard.clear()
            for i in range(first, first + n):
                pub.put(str(i).encode())
                time.sleep(0.002)
            proxy.set_faults(CLEAN, "up")
            time.sleep(0.05)  # past the longest hold: the marker comes after everything
            pub.put(b"-2")
            poll_until(lambda: -2 in heard, 5.0, "the marker")
            return [i for i in heard if i >= 0]

        proxy.set_faults(LinkFaults(duplicate=0.5), "up")
        got = send(0, 100)
        # each delivered once, in order (the first copies are not faulted, but a loaded machine
        # may still lose one: loopback UDP is not reliable either)
        assert got == sorted(set(got)) and len(got) >= 90
        assert proxy.counters("up")["duplicated"] > 20
        proxy.set_faults(LinkFaults(reorder=0.3, reorder_hold_s=0.01), "up")
        got = send(1000, 100)
        reordered = proxy.counters("up")["reordered"]
        assert reordered > 5 and got == sorted(set(got)) and len(got) <= 100 - reordered


@pytest.mark.slow
@pytest.mark.fleet
@pytest.mark.timeout(300)
def test_bus_faults_between_drones_on_the_real_zenoh_path(tmp_path: Path) -> None:
    swarm = f"bf{os.getpid()}"
    world = write_world(tmp_path / "world.yaml", [], SPAWNS, SPAWNS)
    socks = bind_consecutive_udp(N)
    port = socks[0].getsockname()[1]
    for sock in socks:
        sock.close()
    goals = _slot_goals()
    with ExitStack() as stack:
        star = stack.enter_context(FaultyStar(N, CLEAN, seed=1200))
        mock = stack.enter_context(
            MockProcess(world, N, port, free_loopback_endpoint(), f"{swarm}/sim", tmp_path / "mock")
        )
        assert mock.proc is not None
        _raise_priority(mock.proc.pid)  # its main thread, before it starts the others
        services = []
        for d in range(N):
            cfg = service_config(
                swarm=swarm,
                autopilot_port=port,
                port_plus_id=True,
                zenoh_listen=[],
                zenoh_connect=[],
                record_dir=tmp_path / f"d{d}" / "records",
                extra={
                    "zenoh": star.client_zenoh(d),
                    "planner": {"v_max_m_s": 1.0},
                    "flight": {"takeoff_speed_m_s": 1.0},
                    "geofence": {"min_enu_m": [-5.0, -6.0, 0.0], "max_enu_m": [16.0, 6.0, 3.0]},
                    "reactions": {"peer_lost": {"validity_s": VALIDITY_S}},
                    # one-way stamps cannot tell latency from clock offset: the estimate is the
                    # smallest latency seen (for the ground station, over a handful of
                    # commands), so with the default 50 ms bound a 150-300 ms bus delay reads
                    # as a clock problem and the drone refuses formation flight; the bound here
                    # is above the largest delay the proxies add
                    "bus": {"clock_offset_bound_s": 0.5},
                },
            )
            services.append(stack.enter_context(ServiceProcess(d, cfg, tmp_path / f"d{d}")))
        gs = stack.enter_context(
            GroundStation(
                swarm,
                star.direct_endpoints(),
                config=StationConfig(lead_s=1.0, ack_timeout_s=8.0),
            )
        )
        t_start = time.monotonic()
        for s in services:
            s.wait_ready(90.0)
        _raise_priority(mock.proc.pid)  # and every thread it started
        print(f"services ready in {time.monotonic() - t_start:.1f} s")

        def all_alive() -> bool:
            return mock.alive() and all(s.alive() for s in services)

        assert gs.wait_for_drones(ids=range(N), timeout_s=20.0, with_state=True) == set(range(N))
        _ok(gs.send(wire.FormationAssignment(POINTS, 1.0, 0.0, SLOTS, 1, time.time())))
        _ok(gs.takeoff(1.0, list(range(N))))
        poll_until(
            lambda: set(_states(gs).values()) == {"hover"},
            40.0,
            "hover",
            all_alive,
            describe=lambda: swarm_summary(gs),
        )

        # --- the topology: the proxies are the only path between the drones ----------------
        # hovering drones announce their trajectory every replan period; with every downlink
        # at 100 % loss no service hears a peer's trajectory, while the ground station (a
        # direct TCP client of the router) still hears all of them through the uplinks
        # (first, every drone hears its peers: a status with a peer trajectory counted; the
        # statuses come once a second, and a drone that has just reached its hover may report
        # before the first of its peers' announcements in hover has reached it)
        t_hover = time.time()
        for d in range(N):
            poll_until(_hears_again(gs, d, t_hover, 0), 10.0, f"drone {d} hears its peers")
        star.set_faults(LinkFaults(loss=1.0), "down")
        t_cut = time.time()
        gs_rx0 = gs.node.counters()["rx.traj"]
        # statuses go up through the uplinks; the first one 0.5 s after the cut may still count
        # a trajectory that was on its way
        cut_a = {d: _status_after(gs, d, t_cut + 0.5, 5.0) for d in range(N)}
        t_a = time.time()
        cut_b = {d: _status_after(gs, d, t_a + 2.0, 6.0) for d in range(N)}
        gs_rx1 = gs.node.counters()["rx.traj"]
        for d in range(N):
            assert cut_b[d]["bus.rx.traj"] == cut_a[d]["bus.rx.traj"], (d, cut_a[d], cut_b[d])
            assert cut_b[d]["bus.tx.traj"] > cut_a[d]["bus.tx.traj"], (d, cut_a[d], cut_b[d])
        assert gs_rx1 - gs_rx0 >= N * 2, (gs_rx0, gs_rx1)
        assert star.counters("down")["dropped"] > 0
        star.set_faults(CLEAN)
        t_open = time.time()
        for d in range(N):
            poll_until(
                _hears_again(gs, d, t_open, cut_b[d]["bus.rx.traj"]),
                8.0,
                f"drone {d} hears its peers again through its proxy",
                all_alive,
            )

        # --- the flight through the faults ------------------------------------------------
        print(f"topology checked at {time.monotonic() - t_start:.1f} s")
        star.set_faults(HOP_FAULTS)
        faults_on = time.time()
        c_on = {d: _status_after(gs, d, faults_on, 8.0) for d in range(N)}
        _ok(gs.goal(tuple(GOAL_CENTRE), targets=list(range(N))))
        poll_until(
            lambda: set(_states(gs).values()) == {"formation-flight"}, 10.0, "flying", all_alive
        )
        poll_until(
            lambda: min(t.position_m[0] for t in mock.latest_truth().values()) > 1.0,
            20.0,
            "the swarm under way",
            all_alive,
        )
        star.proxies[2].hold(HOLD_S, "up")
        t_hold = time.time()

        def arrived() -> bool:
            truth = mock.latest_truth()
            states = _states(gs)
            return all(
                np.linalg.norm(np.array(truth[d + 1].position_m) - goals[d]) < 0.4
                and states.get(d) == "hover"
                for d in range(N)
            )

        poll_until(arrived, 60.0, "every drone at its slot goal", all_alive)
        assert time.time() > t_hold + HOLD_S + 1.0, "the flight ended before the outage did"
        faults_off = time.time()
        t_arrived = time.monotonic() - t_start
        print(f"arrived at {t_arrived:.1f} s, faults for {faults_off - faults_on:.1f} s")
        c_off = {d: _status_after(gs, d, faults_off, 8.0) for d in range(N)}
        star.set_faults(CLEAN)
        injected = star.counters()
        stats = star.stats()
        truth = mock.latest_truth()
        slot_error = [float(np.linalg.norm(truth[d + 1].position_m - goals[d])) for d in range(N)]
        final = {d: _status_after(gs, d, time.time(), 5.0) for d in range(N)}
        # landing closes every flight record, so that they do not depend on the services'
        # SIGTERM handling (seen once: a service whose handler never finished, its record
        # left open)
        _ok(gs.land(list(range(N))))
        poll_until(lambda: set(_states(gs).values()) == {"landed"}, 30.0, "landed", all_alive)
        for s in services:
            s.stop()
        sitl = mock.stop()

    # --- the faults were applied on the path ------------------------------------------------
    print("proxies:", stats)
    for k in ("dropped", "delayed", "duplicated", "held_back", "reordered", "held"):
        assert injected[k] > 0, (k, injected)
    assert injected["send_errors"] == 0, injected
    # what the services saw: trajectories of the peers received while the faults were on,
    # against those the peers sent (loss, stale refusals and Zenoh's drops of duplicated and
    # overtaken frames together)
    sent = {d: c_off[d]["bus.tx.traj"] - c_on[d]["bus.tx.traj"] for d in range(N)}
    got = {d: c_off[d]["bus.rx.traj"] - c_on[d]["bus.rx.traj"] for d in range(N)}
    lost = {d: 1.0 - got[d] / sum(sent[j] for j in range(N) if j != d) for d in range(N)}
    print("trajectories sent", sent, "received", got, "lost fraction", lost)
    print("rejects", {d: {k: v for k, v in final[d].items() if "reject" in k} for d in range(N)})
    # two hops at 10.6 % each lose ~20 % (more with Zenoh's drops of duplicates); each drone
    # hears ~50 peer trajectories in the window, so a per-drone bound near 20 % fails a few
    # runs in a hundred (CI saw 5 of 54 lost): each drone must see a loss, and the swarm as a
    # whole (~150 trajectories) a fraction that random draws miss about once in 10^4 runs
    assert all(lost[d] > 0.02 for d in range(N)), lost
    total_sent = sum(sent[j] for d in range(N) for j in range(N) if j != d)
    lost_all = 1.0 - sum(got.values()) / total_sent
    assert lost_all > 0.08, (lost_all, lost)
    for d in range(N):
        assert final[d]["bus.error.internal"] == 0 and final[d]["bus.error.callback"] == 0

    # --- safety on the ground truth ----------------------------------------------------------
    print("mock:", {k: sitl.get(k) for k in ("collisions", "min_vehicle_distance_m")})
    print("distance to the slot goals at the arrival, m:", slot_error)
    assert sitl.get("collisions") == [], sitl.get("collisions")
    # contact is 2 body radii between centres; the planner accepts no plan closer than
    # check_drone_m (0.5 m) to a peer's trajectory
    assert sitl["min_vehicle_distance_m"] > 2 * BODY_RADIUS_M + 0.05, sitl

    # --- stale trajectories: refused at the gate, never in the formation term ---------------
    stale_logged = [
        d
        for d in (0, 1)
        if _log_lines(services[d], f"rejected message on {swarm}/drone/2/traj: stale")
    ]
    assert stale_logged, "no stale trajectory of drone 2 reached drones 0 and 1"
    for d in stale_logged:
        assert final[d]["bus.reject.stale"] > 0
    for d in (0, 1):
        plans = _plans(tmp_path / f"d{d}" / "records")
        during = [p for t, p in plans if t_hold + VALIDITY_S + 0.3 < t < t_hold + HOLD_S - 0.1]
        after = [p for t, p in plans if t > t_hold + HOLD_S + 0.2]  # released, heard again
        assert during, f"drone {d} made no plan while drone 2's trajectory was past its validity"
        for p in during:
            assert 2 not in p["formation_peers"], (d, p["formation_peers"])
            assert 2 in p["avoided_peers"], (d, p["avoided_peers"])
        assert any(2 in p["formation_peers"] for p in after), f"drone {d} never took 2 back"
    # --- drone 2, hidden: it learns from its peers' statuses that they do not hear it ------
    # (their links to it down or quiet for a second: onboard.comm.hearing) and plans with the
    # wider berth (unheard_margin_m) until they hear it again
    plans2 = _plans(tmp_path / "d2" / "records")
    late = [p for t, p in plans2 if t_hold + VALIDITY_S < t < t_hold + HOLD_S - 0.1]
    assert late, "drone 2 made no plan in the second half of its outage"
    assert all(p["unheard_by"] for p in late), [(p["t_s"], p["unheard_by"]) for p in late]
    logs2 = [
        (t, m["message"])
        for f in sorted((tmp_path / "d2" / "records").glob("*.mcap"))
        for t, m in read_record(f).topics.get("/log", [])
    ]
    for peer in (0, 1):
        said = [t for t, m in logs2 if m.startswith(f"drone {peer} reports it does not hear us")]
        again = [t for t, m in logs2 if m == f"drone {peer} hears us again"]
        assert any(t_hold < t < t_hold + HOLD_S for t in said), (peer, logs2)
        assert any(t > t_hold + HOLD_S for t in again), (peer, logs2)
    # how the formation degraded: plans made under the faults in which a peer was only avoided
    for d in range(N):
        made = [p for t, p in _plans(tmp_path / f"d{d}" / "records") if faults_on < t < faults_off]
        partial = sum(1 for p in made if len(p["formation_peers"]) < N - 1)
        print(f"drone {d}: {len(made)} plans under the faults, {partial} without every peer")


def _plans(directory: Path) -> list[tuple[float, dict[str, Any]]]:
    out: list[tuple[float, dict[str, Any]]] = []
    for f in sorted(directory.glob("*.mcap")):
        out.extend(read_record(f).topics.get("/plan", []))
    return sorted(out, key=lambda tp: tp[0])


def _raise_priority(pid: int, nice: int = -5) -> None:
    """Every thread of process ``pid`` at niceness ``nice``, as the demo runs the mock: it stands
    for the autopilots' own hardware, whose clock and heartbeats must not starve behind three
    services on a loaded 2-core machine (a starved mock stops its heartbeats, every service
    declares its autopilot lost and PX4's failsafe lands the swarm). Without the privilege the
    mock keeps its niceness."""
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            os.setpriority(os.PRIO_PROCESS, int(task), nice)
        except PermissionError:
            return
        except ProcessLookupError:  # a thread that ended meanwhile
            continue


def _log_lines(svc: ServiceProcess, text: str) -> list[str]:
    """The service's log lines that contain ``text``."""
    return [line for line in svc.log_path.read_text(errors="replace").splitlines() if text in line]
