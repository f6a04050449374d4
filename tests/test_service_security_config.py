"""Security settings of the flight service's config reach the autopilot link and the bus."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gcs.certs import make_demo_pki
from onboard.config import ConfigError
from onboard.service.adapters import link_config
from onboard.service.config import load_onboard_config


def _key(tmp_path: Path, mode: int) -> Path:
    p = tmp_path / "mavlink-0.key"
    p.write_text("ab" * 32)
    os.chmod(p, mode)
    return p


def test_signing_key_reaches_the_link(tmp_path: Path) -> None:
    key = _key(tmp_path, 0o600)
    cfg = load_onboard_config(
        drone_id=0,
        overrides={"autopilot": {"signing_key_file": str(tmp_path / "mavlink-{id}.key")}},
    )
    lc = link_config(cfg)
    assert lc.signing_key_file == str(key)
    assert "ab" * 32 not in repr(lc)


def test_a_readable_signing_key_is_refused(tmp_path: Path) -> None:
    _key(tmp_path, 0o644)
    cfg = load_onboard_config(
        drone_id=0,
        overrides={"autopilot": {"signing_key_file": str(tmp_path / "mavlink-{id}.key")}},
    )
    with pytest.raises(ValueError, match="signing_key_file"):
        link_config(cfg)


def test_mavsdk_cannot_sign(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="signing_key_file"):
        load_onboard_config(
            drone_id=0,
            overrides={
                "autopilot": {"implementation": "mavsdk", "signing_key_file": "/k"},
            },
        )


def test_access_control_needs_tls() -> None:
    with pytest.raises(ConfigError, match="access_control_drones"):
        load_onboard_config(drone_id=0, overrides={"zenoh": {"access_control_drones": 3}})


def test_tls_and_access_control_reach_the_bus_endpoints(tmp_path: Path) -> None:
    make_demo_pki(tmp_path / "pki", drones=2)
    pki = tmp_path / "pki"
    files = sorted(p.name for p in pki.iterdir())
    cert = next(n for n in files if n.startswith("drone-1") and n.endswith((".pem", ".crt")))
    key = next(n for n in files if n.startswith("drone-1") and n.endswith(".key"))
    ca = next(n for n in files if n.startswith("ca") and n.endswith((".pem", ".crt")))
    cfg = load_onboard_config(
        drone_id=1,
        overrides={
            "zenoh": {
                "listen": ["tcp/127.0.0.1:7450"],
                "tls": {
                    "root_ca_certificate": str(pki / ca),
                    "certificate": str(pki / cert.replace("drone-1", "drone-{id}")),
                    "private_key": str(pki / key.replace("drone-1", "drone-{id}")),
                },
                "access_control_drones": 2,
            }
        },
    )
    ep = cfg.zenoh.endpoints(cfg.drone.id, cfg.drone.swarm)
    assert ep.listen == ("tls/127.0.0.1:7450",)
    # endpoints already written as tls/ are taken as they are (they used to be refused)
    tls_cfg = load_onboard_config(
        drone_id=1,
        overrides={
            "zenoh": {
                "listen": ["tls/127.0.0.1:7450"],
                "connect": ["tls/127.0.0.1:7451"],
                "tls": dict(cfg.zenoh.tls.__dict__) if cfg.zenoh.tls is not None else None,
            }
        },
    )
    tls_ep = tls_cfg.zenoh.endpoints(1, cfg.drone.swarm)
    assert tls_ep.listen == ("tls/127.0.0.1:7450",) and tls_ep.connect == ("tls/127.0.0.1:7451",)
    assert ep.tls is not None and ep.tls.certificate.endswith(cert)
    assert ep.access_control is not None
    plain = load_onboard_config(drone_id=1).zenoh.endpoints(1, "s")
    assert plain.tls is None and plain.access_control is None
