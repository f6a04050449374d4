"""Zenoh TLS with mutual authentication and access control, on real sessions over loopback.

A victim (drone 1's session, listening on ``tls/127.0.0.1:PORT`` with the swarm's access
control) subscribes to everything of the swarm; intruders connect to it. Refusals are shown
without timed waits: an intruder that cannot authenticate cannot open its session at all
(``connect/exit_on_failure``), and an authenticated one's forbidden puts are followed by an
allowed marker on the same link (one reliable, ordered link): once the marker is in, the
forbidden messages would have been before it.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
import zenoh

from gcs.certs import make_demo_pki
from onboard.comm.security import SwarmAccessControl, TlsConfig, drone_common_name
from onboard.comm.wire import Command, Land
from onboard.comm.zenoh_bus import SwarmNode
from onboard.comm.zenoh_session import (
    ZenohEndpoints,
    free_loopback_endpoint,
    open_session,
    peer_mesh,
)

SWARM = "tls-test"
DRONES = 3


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    good = tmp_path_factory.mktemp("pki")
    evil = tmp_path_factory.mktemp("evil-pki")
    make_demo_pki(good, DRONES, days=2)
    make_demo_pki(evil, 1, days=2)  # its own CA, the same names
    return {"good": good, "evil": evil}


def tls(d: Path, name: str, ca: Path | None = None) -> TlsConfig:
    return TlsConfig(str((ca or d) / "ca.pem"), str(d / f"{name}.pem"), str(d / f"{name}.key"))


def fail_fast() -> dict[str, str]:
    """Opening fails unless every connect endpoint is reached within 1.5 s (a good handshake
    on loopback takes milliseconds)."""
    return {"connect/timeout_ms": "1500", "connect/exit_on_failure": "true"}


class Victim:
    def __init__(self, session: Any, endpoint: str) -> None:
        self.session = session
        self.endpoint = endpoint
        self.got: list[str] = []
        self.alive: list[str] = []
        self._lock = threading.Lock()
        self._subs = [
            session.declare_subscriber(f"{SWARM}/**", self._on),
            session.liveliness().declare_subscriber(f"{SWARM}/alive/**", self._on_alive),
        ]

    def _on(self, sample: Any) -> None:
        with self._lock:
            self.got.append(str(sample.key_expr))

    def _on_alive(self, sample: Any) -> None:
        # Only appearances: a token undeclared at the end of a `with` block
        # also arrives, as a DELETE, and may land before the assertions.
        if sample.kind != zenoh.SampleKind.PUT:
            return
        with self._lock:
            self.alive.append(str(sample.key_expr))

    def keys(self) -> list[str]:
        with self._lock:
            return list(self.got)


def wait_for(pred: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


@pytest.fixture
def victim(pki: dict[str, Path]) -> Iterator[Victim]:
    ep = free_loopback_endpoint().replace("tcp/", "tls/")
    acl = SwarmAccessControl.for_count(SWARM, DRONES)
    s = open_session(
        ZenohEndpoints(listen=(ep,), tls=tls(pki["good"], "drone-1"), access_control=acl)
    )
    try:
        yield Victim(s, ep)
    finally:
        s.close()


def connect(victim: Victim, cfg: TlsConfig | None, **extra: str) -> Any:
    return open_session(
        ZenohEndpoints(connect=(victim.endpoint,), tls=cfg, extra={**fail_fast(), **extra})
    )


def put_until_seen(victim: Victim, session: Any, key: str) -> None:
    """Put ``key`` until the victim has it (routes established)."""
    n = len([k for k in victim.keys() if k == key])

    def seen() -> bool:
        session.put(key, b"marker")
        return len([k for k in victim.keys() if k == key]) > n

    wait_for(seen, f"{key} at the victim")


def test_legitimate_traffic_passes(victim: Victim, pki: dict[str, Path]) -> None:
    with ExitStack() as stack:
        gcs = connect(victim, tls(pki["good"], "gcs"))
        stack.callback(gcs.close)
        d0 = connect(victim, tls(pki["good"], drone_common_name(0)))
        stack.callback(d0.close)
        put_until_seen(victim, gcs, f"{SWARM}/cmd/land")
        for stream in ("traj", "state", "status"):
            put_until_seen(victim, d0, f"{SWARM}/drone/0/{stream}")
        put_until_seen(victim, d0, f"{SWARM}/ack/0")
        stack.enter_context(_token(d0, f"{SWARM}/alive/drone/0"))
        wait_for(lambda: f"{SWARM}/alive/drone/0" in victim.alive, "drone 0's token")


def _token(session: Any, key: str) -> Any:
    class _Ctx:
        def __enter__(self) -> Any:
            self.tok = session.liveliness().declare_token(key)
            return self.tok

        def __exit__(self, *exc: object) -> None:
            self.tok.undeclare()

    return _Ctx()


def test_a_session_without_a_certificate_is_refused(victim: Victim, pki: dict[str, Path]) -> None:
    ca_only = {"transport/link/tls/root_ca_certificate": json.dumps(str(pki["good"] / "ca.pem"))}
    with pytest.raises(RuntimeError, match="cannot open Zenoh"):
        connect(victim, None, **ca_only).close()
    # a plain TCP session to the TLS port gets nowhere either
    with pytest.raises(RuntimeError, match="cannot open Zenoh"):
        open_session(
            ZenohEndpoints(connect=(victim.endpoint.replace("tls/", "tcp/"),), extra=fail_fast())
        ).close()
    assert victim.keys() == []


def test_a_certificate_from_another_ca_is_refused(victim: Victim, pki: dict[str, Path]) -> None:
    # "gcs" signed by another CA; the intruder even trusts the swarm's CA
    with pytest.raises(RuntimeError, match="cannot open Zenoh"):
        connect(victim, tls(pki["evil"], "gcs", ca=pki["good"])).close()
    # and with its own CA only it does not accept the victim either
    with pytest.raises(RuntimeError, match="cannot open Zenoh"):
        connect(victim, tls(pki["evil"], "drone-0")).close()
    assert victim.keys() == []


def test_a_drone_may_not_command_nor_speak_for_another(
    victim: Victim, pki: dict[str, Path]
) -> None:
    d0 = connect(victim, tls(pki["good"], drone_common_name(0)))
    try:
        own = f"{SWARM}/drone/0/traj"
        put_until_seen(victim, d0, own)
        forbidden = [
            f"{SWARM}/cmd/land",
            f"{SWARM}/cmd/goal",
            f"{SWARM}/drone/2/traj",
            f"{SWARM}/drone/1/state",
            f"{SWARM}/drone/2/status",
            f"{SWARM}/ack/2",
            "other-swarm/cmd/land",
        ]
        for key in forbidden:
            d0.put(key, b"forged")
        with _token(d0, f"{SWARM}/alive/drone/2"), _token(d0, f"{SWARM}/alive/gcs"):
            d0.put(f"{SWARM}/drone/0/state", b"marker")
            wait_for(lambda: f"{SWARM}/drone/0/state" in victim.keys(), "the marker")
            with _token(d0, f"{SWARM}/alive/drone/0"):
                wait_for(lambda: f"{SWARM}/alive/drone/0" in victim.alive, "drone 0's own token")
        assert not set(forbidden) & set(victim.keys())
        assert victim.alive == [f"{SWARM}/alive/drone/0"]
    finally:
        d0.close()


def test_the_ground_station_may_not_speak_for_a_drone(victim: Victim, pki: dict[str, Path]) -> None:
    gcs = connect(victim, tls(pki["good"], "gcs"))
    try:
        put_until_seen(victim, gcs, f"{SWARM}/cmd/abort")
        gcs.put(f"{SWARM}/drone/0/traj", b"forged")
        gcs.put(f"{SWARM}/ack/0", b"forged")
        gcs.put(f"{SWARM}/cmd/land", b"marker")
        wait_for(lambda: f"{SWARM}/cmd/land" in victim.keys(), "the marker")
        assert set(victim.keys()) == {f"{SWARM}/cmd/abort", f"{SWARM}/cmd/land"}
    finally:
        gcs.close()


def test_tls_settings_are_checked(pki: dict[str, Path], tmp_path: Path) -> None:
    d = pki["good"]
    loose = tmp_path / "loose.key"
    loose.write_bytes((d / "gcs.key").read_bytes())
    os.chmod(loose, 0o644)
    with pytest.raises(ValueError, match=r"tls.private_key: .* permissions 0644"):
        TlsConfig(str(d / "ca.pem"), str(d / "gcs.pem"), str(loose))
    with pytest.raises(ValueError, match="tls.root_ca_certificate: no such file"):
        TlsConfig(str(d / "nope.pem"), str(d / "gcs.pem"), str(d / "gcs.key"))
    good = tls(d, "gcs")
    assert "BEGIN" not in repr(good)
    with pytest.raises(ValueError, match="must be tls/"):
        ZenohEndpoints(listen=("tcp/127.0.0.1:7447",), tls=good)
    with pytest.raises(ValueError, match="needs the tls settings"):
        ZenohEndpoints(listen=("tls/127.0.0.1:7447",))
    with pytest.raises(ValueError, match="access_control: needs tls"):
        ZenohEndpoints(access_control=SwarmAccessControl.for_count(SWARM, 2))
    with pytest.raises(ValueError, match="drone_ids"):
        SwarmAccessControl(SWARM, (1, 1))
    eps = ZenohEndpoints(listen=("tcp/127.0.0.1:7447",)).secured(good)
    assert eps.listen == ("tls/127.0.0.1:7447",) and eps.tls is good
    cfg = json.loads(eps.config().get_json("transport/link/tls"))
    assert cfg["enable_mtls"] is True and cfg["listen_private_key"].endswith("gcs.key")


def test_the_swarm_bus_over_tls_and_access_control(pki: dict[str, Path]) -> None:
    """SwarmNodes on a secured mesh: a command reaches the drones, their acks come back."""
    d = pki["good"]
    acl = SwarmAccessControl.for_count(SWARM, DRONES)
    eps = peer_mesh(3)
    names = ["gcs", "drone-0", "drone-1"]
    with ExitStack() as stack:
        nodes = [
            stack.enter_context(SwarmNode(SWARM, i, ep.secured(tls(d, n), acl)))
            for i, ep, n in zip([None, 0, 1], eps, names, strict=True)
        ]
        gcs, d0, d1 = nodes

        def answer(node: SwarmNode) -> Callable[[Any, float], None]:
            def cb(env: Any, _t: float) -> None:
                assert isinstance(env.body, Command)
                node.send_ack(env.body.cmd_id, True)

            return cb

        d0.on_command(answer(d0))
        d1.on_command(answer(d1))
        wait_for(lambda: gcs.alive_drones() == {0, 1}, "both drones up")
        wait_for(lambda: d0.gcs_alive() and d1.gcs_alive(), "the ground station seen")
        sent = gcs.send_command(Land())
        assert gcs.wait_acks(sent.cmd_id, [0, 1], timeout_s=10.0) == set()
