"""The ground-station client over real Zenoh sessions on loopback, against fake drones: one that
answers, one that refuses some commands, one that loses the first copy of every command, one
that never answers."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.formations import FormationError, best_yaw, hungarian_slots, load_template, place
from gcs.station import GroundStation, StationConfig, StationError
from onboard.comm.wire import (
    Command,
    Envelope,
    FormationAssignment,
    Goal,
    LinkHealth,
    StateBody,
    StatusBody,
    Takeoff,
)
from onboard.comm.zenoh_bus import SwarmNode
from onboard.comm.zenoh_session import peer_mesh

SWARM = "t/gcs"
DEADLINE_S = 30.0  # a deadline on a loaded machine, not a timed assert


def wait_for(cond: Callable[[], Any], what: str, timeout_s: float = DEADLINE_S) -> Any:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = cond()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@dataclass
class FakeDrone:
    """A drone on the bus that answers commands by a policy and publishes a state."""

    node: SwarmNode
    mode: str = "answer"  # 'answer' | 'silent' | 'lossy' (ignores the first copy)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    received: list[Command] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self.node.on_command(self._on_command)

    def _on_command(self, env: Envelope, _rx: float) -> None:
        cmd = env.body
        assert isinstance(cmd, Command)
        with self.lock:
            first = all(c.cmd_id != cmd.cmd_id for c in self.received)
            self.received.append(cmd)
        if self.mode == "silent" or (self.mode == "lossy" and first):
            return
        a = cmd.action
        if isinstance(a, Goal) and a.position_m[0] > 100.0:
            self.node.send_ack(cmd.cmd_id, False, "goal outside the geofence")
        else:
            self.node.send_ack(cmd.cmd_id, True, "")

    def publish_state(self, epoch: int = 0) -> None:
        assert self.node.drone_id is not None
        self.node.publish_state(
            StateBody(
                "hover",
                time.time(),
                self.position,
                (0.3, 0.4, 0.0),
                (1.0, 0.0, 0.0, 0.0),
                True,
                "OFFBOARD",
                -1,
                epoch,
            )  # fmt: skip
        )

    def publish_states(self, stop: threading.Event, period_s: float = 0.1) -> threading.Thread:
        """Publish the state every ``period_s`` until ``stop`` is set (as a drone does)."""

        def run() -> None:
            while not stop.wait(period_s):
                self.publish_state()

        th = threading.Thread(target=run, daemon=True)
        th.start()
        return th

    def commands(self) -> list[Command]:
        with self.lock:
            return list(self.received)


@pytest.fixture
def swarm() -> Iterator[Callable[..., tuple[GroundStation, dict[int, FakeDrone]]]]:
    """``make({id: mode}, **station config)``: a station and fake drones on one loopback mesh,
    every drone up and seen by the station; everything closed after the test."""
    with ExitStack() as stack:

        def make(modes: dict[int, str], **cfg: Any) -> tuple[GroundStation, dict[int, FakeDrone]]:
            eps = peer_mesh(len(modes) + 1)
            gs = GroundStation(SWARM, eps[0], config=StationConfig(**cfg))
            stack.callback(gs.close)
            drones = {}
            for (i, mode), ep in zip(modes.items(), eps[1:], strict=True):
                node = SwarmNode(SWARM, i, ep)
                stack.callback(node.close)
                drones[i] = FakeDrone(node, mode)
            assert gs.wait_for_drones(ids=list(modes), timeout_s=DEADLINE_S) == set(modes)
            for d in drones.values():  # every drone sees the station (so the mesh is complete)
                wait_for(d.node.gcs_alive, "drone sees the station")
            return gs, drones

        yield make


def test_acks_collected_and_silent_drone_reported(
    swarm: Callable[..., tuple[GroundStation, dict[int, FakeDrone]]],
) -> None:
    gs, drones = swarm({0: "answer", 1: "answer", 2: "silent"}, ack_timeout_s=1.0)
    out = gs.takeoff(2.5)
    assert out.addressed == (0, 1, 2)
    assert out.accepted == (0, 1) and out.missing == (2,) and not out.rejected
    assert not out.ok and "NO ANSWER from [2]" in out.describe()
    assert out.sends >= 2  # the silent drone got the command again
    # every copy is the same command (id, issue time, action); the first went to everybody
    got = drones[2].commands()
    assert len(got) == out.sends
    assert {(c.cmd_id, c.issued_s) for c in got} == {(out.cmd_id, got[0].issued_s)}
    assert got[0].targets == [] and all(c.targets == [2] for c in got[1:])
    assert all(isinstance(c.action, Takeoff) and c.action.altitude_m == 2.5 for c in got)
    assert len(drones[0].commands()) == 1  # it answered: no resend
    # a subset: the silent drone is not addressed, everything accepted
    sub = gs.land(targets=[1, 0])
    assert sub.ok and sub.addressed == (0, 1) and sub.sends == 1
    assert drones[0].commands()[-1].targets == [0, 1]
    wait_for(lambda: drones[2].node.counters()["cmd.not_addressed"] >= 1, "not addressed")


def test_lost_command_is_resent_with_the_same_id(
    swarm: Callable[..., tuple[GroundStation, dict[int, FakeDrone]]],
) -> None:
    gs, drones = swarm({4: "lossy", 5: "answer"}, ack_timeout_s=DEADLINE_S, resend_every_s=0.2)
    out = gs.resume()
    assert out.ok and out.sends == 2
    assert [c.cmd_id for c in drones[4].commands()] == [out.cmd_id, out.cmd_id]


def test_rejections_carry_reasons_and_goal_has_one_effective_time(
    swarm: Callable[..., tuple[GroundStation, dict[int, FakeDrone]]],
) -> None:
    gs, drones = swarm({0: "answer", 1: "answer"}, lead_s=2.0)
    t0 = time.time()
    ok = gs.goal((20.0, 0.0, 1.5), yaw_rad=0.5)
    assert ok.ok and ok.effective_s is not None and ok.effective_s >= t0 + 2.0
    goals = [d.commands()[-1].action for d in drones.values()]
    assert all(isinstance(g, Goal) for g in goals)
    assert {g.effective_s for g in goals if isinstance(g, Goal)} == {ok.effective_s}
    bad = gs.goal((500.0, 0.0, 1.5))
    assert bad.rejected == {0: "goal outside the geofence", 1: "goal outside the geofence"}
    assert "REFUSED by 0: goal outside the geofence" in bad.describe()
    assert bad.to_json()["ok"] is False and gs.outcomes[-1] is bad
    with pytest.raises(StationError, match="not finite"):
        gs.goal((math.nan, 0.0, 1.0))
    with pytest.raises(StationError, match="3 coordinates"):
        gs.goal((1.0, 2.0))
    w = gs.waypoints([(5.0, 0.0, 1.5), (10.0, 2.0, 1.5)])
    assert w.ok and w.effective_s is not None


def test_formation_assigned_from_reported_positions(
    swarm: Callable[..., tuple[GroundStation, dict[int, FakeDrone]]],
) -> None:
    ids = [2, 5, 7, 9]
    gs, drones = swarm(dict.fromkeys(ids, "answer"))
    # the drones sit on a rectangle-4, shuffled
    truth = place(load_template("rectangle-4").points, (3.0, 1.0, 1.5), 1.0, 0.0)
    order = [2, 0, 3, 1]
    for d, k in zip(ids, order, strict=True):
        drones[d].position = tuple(float(x) for x in truth[k])  # type: ignore[assignment]
        drones[d].publish_state(epoch=0)
    wait_for(lambda: len(gs.positions()) == 4, "positions")
    # nothing is sent on an error: wrong count, unknown drone, too close
    n_before = [len(d.commands()) for d in drones.values()]
    with pytest.raises(FormationError, match="has 7 points but 4 drones"):
        gs.formation("hexagon-7")
    with pytest.raises(FormationError, match=r"drones \[42\] are not up"):
        gs.formation("triangle-3", drones=[2, 5, 42])
    with pytest.raises(FormationError, match="closer than the drone spacing"):
        gs.formation("rectangle-4", scale=0.2)
    assert [len(d.commands()) for d in drones.values()] == n_before
    a, out = gs.formation("rectangle-4")
    assert out.ok and out.action == "formation"
    assert {d: a.slots[d] for d in ids} == dict(zip(ids, order, strict=True))
    sent = [d.commands()[-1].action for d in drones.values()]
    assert all(isinstance(s, FormationAssignment) for s in sent)
    assert len({(s.epoch, s.effective_s) for s in sent if isinstance(s, FormationAssignment)}) == 1
    err = gs.formation_error()
    assert err is not None and err[0] == pytest.approx(0.0, abs=1e-6)
    # a second assignment has a newer epoch; a drone reporting a far newer epoch lifts it
    drones[2].publish_state(epoch=a.epoch + 500)
    wait_for(lambda: gs.assigner.last_epoch >= a.epoch + 500, "epoch observed")
    a2, out2 = gs.formation("line-4", yaw_rad=math.pi / 2)
    assert out2.ok and a2.epoch > a.epoch + 500
    # another station sees the assignment without sending it
    known = gs.known_formation()
    assert known is not None and known[1].epoch == a2.epoch and known[0] == "line-4"


def test_views_merge_state_and_status(
    swarm: Callable[..., tuple[GroundStation, dict[int, FakeDrone]]],
) -> None:
    gs, drones = swarm({3: "answer"})
    drones[3].position = (1.0, 2.0, 3.0)
    drones[3].publish_state()
    links = [LinkHealth("autopilot", True, 0.01), LinkHealth("depth", False, 0.9)]
    drones[3].node.publish_status(
        StatusBody(
            "hover",
            "ok",
            time.time(),
            40.0,
            80.0,
            12,
            links,
            15.2,
            0.7,
            0.002,
            {"tx.traj": 5, "rx.traj": 7, "reject.stale": 1},
            "took off",
        )  # fmt: skip
    )
    v = wait_for(lambda: (x := gs.views().get(3)) and x.plan_status and x, "view")
    assert v.alive and v.flight_state == "hover" and v.position_m == (1.0, 2.0, 3.0)
    assert v.speed_m_s == pytest.approx(0.5)
    assert v.links_text() == "down: depth" and v.bus_text() == "tx 5 rx 7 rej 1"
    assert v.battery_remaining == 0.7 and v.replans == 12 and v.message == "took off"
    j = v.to_json()
    assert j["id"] == 3 and j["links"][1] == {"name": "depth", "up": False, "age_s": 0.9}


def test_no_drone_up_is_an_error() -> None:
    (ep,) = peer_mesh(1)
    with GroundStation(SWARM, ep) as gs:
        assert gs.wait_for_drones(count=1, timeout_s=0.2) == set()
        with pytest.raises(StationError, match="no drone is up"):
            gs.land()
        with pytest.raises(StationError, match="empty list"):
            gs.land(targets=[])


# --- the operator commands (gcs/commands.py), in-process against fake drones ------------------


@pytest.fixture
def drones_only() -> Iterator[Callable[[dict[int, str]], tuple[dict[int, FakeDrone], str]]]:
    """``make({id: mode})``: fake drones on a loopback mesh and the --connect value that reaches
    all of them."""
    with ExitStack() as stack:

        def make(modes: dict[int, str]) -> tuple[dict[int, FakeDrone], str]:
            eps = peer_mesh(len(modes))
            drones = {}
            for (i, mode), ep in zip(modes.items(), eps, strict=True):
                node = SwarmNode(SWARM, i, ep)
                stack.callback(node.close)
                drones[i] = FakeDrone(node, mode)
            for d in drones.values():
                wait_for(partial(_sees, d.node, set(modes)), "mesh up")
            stop = threading.Event()
            for d in drones.values():
                stack.callback(d.publish_states(stop).join)
            stack.callback(stop.set)  # runs first (the stack unwinds last in, first out)
            return drones, ",".join(ep.listen[0] for ep in eps)

        yield make


def _sees(node: SwarmNode, ids: set[int]) -> bool:
    return node.alive_drones() == ids


def _run(args: list[str]) -> Any:
    from click.testing import CliRunner

    from gcs.commands import COMMANDS

    cmds = {c.name: c for c in COMMANDS}
    return CliRunner().invoke(cmds[args[0]], args[1:], catch_exceptions=False)


@pytest.mark.slow
def test_cli_commands_report_acks(
    drones_only: Callable[[dict[int, str]], tuple[dict[int, FakeDrone], str]],
    tmp_path: Any,
) -> None:

    drones, connect = drones_only({0: "answer", 1: "answer", 2: "silent"})
    for i, d in drones.items():
        d.position = (float(i) * 2.0, 0.0, 1.0)
    bus = ["--swarm", SWARM, "--connect", connect, "--timeout", "0.6", "--expect", "3"]
    r = _run(["takeoff", "--altitude", "2", *bus])
    assert (
        r.exit_code == 1 and "NO ANSWER from [2]" in r.output and "accepted by [0, 1]" in r.output
    )
    r = _run(["land", "--drones", "0,1", "--json", *bus])
    out = json.loads(r.output)
    assert r.exit_code == 0 and out["ok"] and out["addressed"] == [0, 1]
    r = _run(["goal", "5", "1", "1.5", "--yaw", "90", "--drones", "0-1", *bus])
    assert r.exit_code == 0, r.output
    g = drones[0].commands()[-1].action
    assert isinstance(g, Goal) and g.position_m == (5.0, 1.0, 1.5)
    assert g.yaw_rad == pytest.approx(math.pi / 2)
    wp = tmp_path / "wp.yaml"
    wp.write_text("points: [[1, 0, 1.5], [2, 1, 1.5]]\n")
    assert _run(["waypoints", str(wp), "--drones", "1", *bus]).exit_code == 0
    bad = tmp_path / "bad.yaml"
    bad.write_text("points: [[1, 0], [2, 1, 1.5]]\n")
    r = _run(["waypoints", str(bad), *bus])
    assert r.exit_code == 2 and "points[0]" in r.output
    # a bad formation is refused before anything is sent
    n_before = {i: len(d.commands()) for i, d in drones.items()}
    r = _run(["formation", "hexagon-7", *bus])
    assert r.exit_code == 1 and "has 7 points but 3 drones" in r.output
    assert "nothing sent" in r.output
    r = _run(["formation", "no-such-shape", *bus])
    assert r.exit_code == 1 and "no file named 'no-such-shape'" in r.output
    assert {i: len(d.commands()) for i, d in drones.items()} == n_before
    r = _run(["formation", "line-4", "--drones", "0,1,2,7", *bus, "--wait", "0.5"])
    assert r.exit_code == 1 and "drones [7] are not up" in r.output
    r = _run(["formation", "triangle-3", "--scale", "1.5", "--json", *bus])
    out = json.loads(r.output)
    assert r.exit_code == 1 and out["missing"] == [2] and out["formation"] == "triangle-3"
    assert sorted(out["slots"].values()) == [0, 1, 2]
    # without --yaw the turn of least travel, with it the turn given
    line = np.array([d.position for d in drones.values()], dtype=np.float64)
    tri = load_template("triangle-3").points
    auto = best_yaw(tri, line, line.mean(axis=0), 1.5)
    assert out["yaw_deg"] == pytest.approx(math.degrees(auto))
    assert out["cost_m"] < hungarian_slots(line, place(tri, line.mean(axis=0), 1.5, 0.0))[1]
    r = _run(["formation", "triangle-3", "--yaw", "30", *bus])
    assert "yaw 30.0 deg," in r.output and "least travel" not in r.output
    sent = drones[0].commands()[-1].action
    assert isinstance(sent, FormationAssignment)
    turned = place(tri, (0.0, 0.0, 0.0), 1.0, math.radians(30.0))
    assert np.allclose(np.asarray(sent.points_m), turned)
    r = _run(["formation", "line-4", "--drones", "0,1", "--scale", "0.5", *bus])
    assert r.exit_code == 1 and "has 4 points but 2 drones" in r.output


def test_cli_status_and_usage_errors(
    drones_only: Callable[[dict[int, str]], tuple[dict[int, FakeDrone], str]],
) -> None:

    drones, connect = drones_only({0: "answer", 1: "answer"})
    for i, d in drones.items():
        d.position = (float(i) * 2.0, 0.0, 1.0)
    bus = ["--swarm", SWARM, "--connect", connect, "--expect", "2"]
    r = _run(["status", "--once", "--json", *bus])
    assert r.exit_code == 0, r.output
    data = json.loads(r.output)
    assert [d["id"] for d in data["drones"]] == [0, 1]
    assert data["drones"][1]["position_m"] == [2.0, 0.0, 1.0]
    assert data["drones"][1]["flight_state"] == "hover" and data["formation"] is None
    r = _run(["status", "--once", *bus])
    assert r.exit_code == 0 and "2 drone(s) up" in r.output and "(2.0, 0.0, 1.0)" in r.output
    r = _run(["land", "--swarm", SWARM])
    assert r.exit_code == 2 and "--connect" in r.output
    r = _run(["land", "--drones", "1,x", *bus])
    assert r.exit_code == 2 and "drone ids" in r.output
    r = _run(["land", "--swarm", "bad swarm*", "--connect", connect])
    assert r.exit_code == 2 and "swarm name" in r.output


def test_cli_over_mutual_tls(tmp_path: Path) -> None:
    """The same command over TLS with the station's certificate; refused without it."""
    from gcs.certs import make_demo_pki
    from onboard.comm.security import TlsConfig

    pki = make_demo_pki(tmp_path / "pki", 1, days=2)
    d = pki["ca"].parent
    (ep,) = peer_mesh(1)
    tls = TlsConfig(str(d / "ca.pem"), str(d / "drone-0.pem"), str(d / "drone-0.key"))
    with SwarmNode(SWARM, 0, ep.secured(tls)) as node:
        drone = FakeDrone(node, "answer")
        connect = ep.listen[0]
        ca, cert, key = (str(d / n) for n in ("ca.pem", "gcs.pem", "gcs.key"))
        r = _run(["land", "--swarm", SWARM, "--connect", connect, "--tls-ca", ca,
                  "--tls-cert", cert, "--tls-key", key, "--expect", "1", "--json"])  # fmt: skip
        assert r.exit_code == 0, r.output
        assert json.loads(r.output)["accepted"] == [0] and len(drone.commands()) == 1
        r = _run(["land", "--swarm", SWARM, "--connect", connect, "--tls-ca", ca, "--wait", "1"])
        assert r.exit_code == 2 and "needs all three" in r.output
        r = _run(["land", "--swarm", SWARM, "--connect", connect, "--wait", "1"])  # plain TCP
        assert r.exit_code == 1 and "no drone is up" in r.output
