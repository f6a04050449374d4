"""``swarm-gcs demo --secure``: the set-up pieces, without flying (the secure flight is the
demo's test in tests/test_demo.py): fresh signing keys in 0600 files that both the mock and
the services load, certificates and the services' TLS + access-control configuration, and the
demo's checks that the swarm bus is secured in fact (TLS links, peers authenticated, intruders
refused) on real Zenoh sessions."""

from __future__ import annotations

import json
import os
import stat
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from gcs.demo import Demo, DemoConfig, DemoError, _refused, _session_links
from onboard.comm.security import SwarmAccessControl, TlsConfig
from onboard.comm.zenoh_session import ZenohEndpoints, open_session, peer_mesh
from onboard.config import from_mapping, read_yaml
from onboard.service.adapters import link_config
from onboard.service.config import load_onboard_config
from sitl_mock.fleet import FleetConfig


def _mode(p: Path) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def _secure_demo(tmp_path: Path) -> Demo:
    d = Demo(DemoConfig(drones=3, formation="triangle-3", world="forest-small", secure=True,
                        out_dir=tmp_path / "flight", swarm="securetest"))  # fmt: skip
    d.world_file = d._world_file()
    return d


def test_secure_setup_keys_config_and_certificates(tmp_path: Path) -> None:
    from gcs.demo import prepare_security

    d = _secure_demo(tmp_path)
    sec = prepare_security(d.out, 3, d.swarm)
    d.security = sec
    assert _mode(sec.secrets_dir) == 0o700
    keys = [p.read_text().strip() for p in sec.signing_keys]
    assert [p.name for p in sec.signing_keys] == [f"mavlink-{i}.key" for i in range(3)]
    assert all(_mode(p) == 0o600 for p in sec.signing_keys)
    assert all(len(k) == 64 and bytes.fromhex(k) for k in keys)
    assert len(set(keys)) == 3  # one fresh key per drone
    # the mock: the same key for system id = drone id + 1, unsigned input refused
    assert _mode(sec.sitl_config) == 0o600
    fleet = from_mapping(FleetConfig, {"count": 3, **read_yaml(sec.sitl_config)}, "sitl")
    assert {s.system_id: (s.key_hex, s.require) for s in fleet.signing} == {
        i + 1: (k, True) for i, k in enumerate(keys)
    }
    # the services: the config file validates; each link signs with its own key, required;
    # the bus is TLS with this drone's certificate and the swarm's access control
    conf = d.out / "onboard.yaml"
    conf.write_text(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
    text = conf.read_text()
    assert not [k for k in keys if k in text]  # the file names the keys, never holds them
    mesh = peer_mesh(4)
    for i in range(3):
        cfg = load_onboard_config(
            conf, drone_id=i, overrides={"zenoh": {"listen": list(mesh[i + 1].listen),
                                                   "connect": list(mesh[i + 1].connect)}},
        )  # fmt: skip
        lc = link_config(cfg)
        assert lc.signing_key_file == str(sec.signing_keys[i].resolve())
        assert lc.requires_signing
        assert not [k for k in keys if k in repr(lc)]
        ep = cfg.zenoh.endpoints(i, cfg.drone.swarm)
        assert ep.tls is not None and ep.tls.certificate.endswith(f"drone-{i}.pem")
        assert ep.access_control is not None and ep.access_control.drone_ids == (0, 1, 2)
        assert all(e.startswith("tls/") for e in (*ep.listen, *ep.connect))
    # the demo PKI: CA, three drones and the ground station, private keys 0600
    for name in ("ca", "gcs", "drone-0", "drone-1", "drone-2"):
        assert (sec.pki_dir / f"{name}.pem").is_file()
        assert _mode(sec.pki_dir / f"{name}.key") == 0o600
    assert isinstance(sec.gcs_tls(), TlsConfig)
    # never two runs' secrets in one directory
    with pytest.raises(DemoError, match="use a new flight directory"):
        prepare_security(d.out, 3, d.swarm)


def test_plain_demo_config_has_no_security(tmp_path: Path) -> None:
    d = Demo(DemoConfig(drones=3, formation="triangle-3", world="forest-small",
                        out_dir=tmp_path / "f"))  # fmt: skip
    d.world_file = d._world_file()
    data = json.loads(d._onboard_yaml(14540, "tcp/127.0.0.1:1", "x/sim"))
    # the drone's configuration below the demo's settings: its security keys are there, off
    assert data["autopilot"].get("signing_key_file") is None
    assert not data["autopilot"].get("signing_required")
    assert (data.get("zenoh") or {}).get("tls") is None
    assert (data.get("zenoh") or {}).get("access_control_drones") is None
    conf = tmp_path / "onboard.yaml"
    conf.write_text(json.dumps(data))
    svc = load_onboard_config(conf, drone_id=0)
    assert svc.autopilot.signing_key_file is None and svc.zenoh.tls is None
    assert not (d.out / "secrets").exists() and not (d.out / "pki").exists()


def test_bus_checks_tell_a_secured_mesh_from_a_plain_one(tmp_path: Path) -> None:
    """What ``--secure`` checks after start-up, on real sessions: a drone session with TLS and
    access control and a ground station session with its certificate are linked over tls/
    only and authenticated as drone-0; plain and certificate-less intruders are refused. The
    same checks on a plain mesh see tcp/ links, no identity, and an intruder let in."""
    from gcs.certs import make_demo_pki

    pki = tmp_path / "pki"
    make_demo_pki(pki, 1, days=2, swarm="t")

    def tls(name: str) -> TlsConfig:
        return TlsConfig(str(pki / "ca.pem"), str(pki / f"{name}.pem"), str(pki / f"{name}.key"))

    acl = SwarmAccessControl.for_count("t", 1)
    gcs_ep, drone_ep = peer_mesh(2)
    target = drone_ep.listen[0]
    ca_only = {"transport/link/tls/root_ca_certificate": json.dumps(str(pki / "ca.pem"))}
    with ExitStack() as stack:
        drone = open_session(drone_ep.secured(tls("drone-0"), acl))
        stack.callback(drone.close)
        gcs = open_session(gcs_ep.secured(tls("gcs"), acl))
        stack.callback(gcs.close)
        links = _wait_links(gcs)
        assert all(ln["src"].startswith("tls/") and ln["dst"].startswith("tls/") for ln in links)
        assert {ln["auth_identifier"] for ln in links} == {"drone-0"}
        assert _refused(ZenohEndpoints(connect=(target,)))
        assert _refused(ZenohEndpoints(connect=(target.replace("tcp/", "tls/"),), extra=ca_only))
        assert not _refused(ZenohEndpoints(connect=(target.replace("tcp/", "tls/"),),
                                           tls=tls("gcs")))  # fmt: skip
    gcs_ep, drone_ep = peer_mesh(2)
    with ExitStack() as stack:
        drone = open_session(drone_ep)
        stack.callback(drone.close)
        gcs = open_session(gcs_ep)
        stack.callback(gcs.close)
        links = _wait_links(gcs)
        assert all(ln["src"].startswith("tcp/") for ln in links)
        assert {ln["auth_identifier"] for ln in links} == {None}
        assert not _refused(ZenohEndpoints(connect=(drone_ep.listen[0],)))


def _wait_links(session: Any) -> list[dict[str, Any]]:
    import time

    deadline = time.monotonic() + 10.0
    while True:
        links = _session_links(session)
        if links or time.monotonic() > deadline:
            assert links, "no link within 10 s"
            return links
        time.sleep(0.05)
