"""Zenoh security of the swarm bus: TLS with mutual authentication and access control.

Identities are the common names of X.509 certificates issued by one swarm CA (``swarm-gcs
certs`` makes a demo one): ``drone-<id>`` for drone ``id`` and ``gcs`` for the ground station.
With mutual TLS every Zenoh link is authenticated at both ends by that CA, so a session without
a certificate, or with one from another CA, never gets a link at all. Access control (Zenoh 1.x
``access_control``) then decides per message, on the *receiving* side (ingress), what each
authenticated identity may publish:

- ``gcs``: ``<swarm>/cmd/**`` and its liveliness token ``<swarm>/alive/gcs``;
- ``drone-<id>``: ``<swarm>/drone/<id>/**`` (trajectory, state, status), ``<swarm>/ack/<id>``
  and its liveliness token ``<swarm>/alive/drone/<id>``;
- every identity: subscriptions and liveliness queries under ``<swarm>/**``;
- anything else (another swarm's keys, a drone's put on a command key or on another drone's
  keys): denied (``default_permission: deny``).

Every session of the swarm (each drone's and the ground station's) carries the same policy, so
each one refuses what a peer must not send it, whatever that peer's own configuration says.
In a routed deployment (``mode: client``) the router must carry it too: Zenoh applies access
control at the face a message arrives on, and the receiving clients then see the router.

Zenoh's key names (1.x) are those of ``transport/link/tls`` (``root_ca_certificate``,
``listen_certificate``, ``listen_private_key``, ``connect_certificate``,
``connect_private_key``, ``enable_mtls``, ``verify_name_on_connect``) and ``access_control``
(``enabled``, ``default_permission``, ``rules``, ``subjects``, ``policies``; subjects matched
on ``cert_common_names``).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from onboard.comm.keys import SwarmKeys
from onboard.comm.wire import MAX_DRONE_ID

GCS_COMMON_NAME = "gcs"

ACL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
"""The message kinds Zenoh 1.x access control knows."""

_READ_MESSAGES = (
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_query",
    "query",
    "reply",
)


def drone_common_name(drone_id: int) -> str:
    """The certificate common name of drone ``drone_id``: ``drone-<id>``."""
    if isinstance(drone_id, bool) or not isinstance(drone_id, int):
        raise ValueError(f"drone id must be an int, got {drone_id!r}")
    if not 0 <= drone_id <= MAX_DRONE_ID:
        raise ValueError(f"drone id {drone_id} not in [0, {MAX_DRONE_ID}]")
    return f"drone-{drone_id}"


def check_private_key_file(path: str, what: str = "private key") -> None:
    """Raise ``ValueError`` naming ``what`` unless ``path`` is a regular file readable by its
    owner only (no group or other permission bits: 0600 or 0400)."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise ValueError(f"{what}: cannot read {path!r}: {e.strerror or e}") from e
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{what}: {path!r} is not a regular file")
    if st.st_mode & 0o077:
        raise ValueError(
            f"{what}: {path!r} has permissions {stat.S_IMODE(st.st_mode):04o}; it must be "
            f"readable by its owner only (chmod 600 {path})"
        )


def _check_readable(path: str, what: str) -> None:
    if not isinstance(path, str) or not path:
        raise ValueError(f"{what}: expected a file path, got {path!r}")
    if not os.path.isfile(path):
        raise ValueError(f"{what}: no such file {path!r}")


@dataclass(frozen=True)
class TlsConfig:
    """TLS of one Zenoh session: the swarm CA, this node's certificate and its private key (PEM
    files; the key 0600). The same certificate serves both the links this node accepts and the
    ones it opens. ``enable_mtls``: require a certificate from the peer too (off only for
    experiments: access control by identity needs it). ``verify_name_on_connect``: check that
    the certificate of the node connected to names the host in the endpoint (its SAN).

    The files are checked when the object is built (``ValueError`` naming the field)."""

    root_ca_certificate: str
    certificate: str
    private_key: str
    enable_mtls: bool = True
    verify_name_on_connect: bool = True

    def __post_init__(self) -> None:
        _check_readable(self.root_ca_certificate, "tls.root_ca_certificate")
        _check_readable(self.certificate, "tls.certificate")
        _check_readable(self.private_key, "tls.private_key")
        check_private_key_file(self.private_key, "tls.private_key")

    def __repr__(self) -> str:
        return (
            f"TlsConfig(root_ca_certificate={self.root_ca_certificate!r}, "
            f"certificate={self.certificate!r}, private_key=<{self.private_key}>, "
            f"enable_mtls={self.enable_mtls})"
        )

    def zenoh_items(self) -> dict[str, str]:
        """Zenoh configuration keys (JSON5 values as text) for ``Config.insert_json5``."""
        tls = {
            "root_ca_certificate": self.root_ca_certificate,
            "listen_certificate": self.certificate,
            "listen_private_key": self.private_key,
            "connect_certificate": self.certificate,
            "connect_private_key": self.private_key,
            "enable_mtls": self.enable_mtls,
            "verify_name_on_connect": self.verify_name_on_connect,
        }
        return {f"transport/link/tls/{k}": json.dumps(v) for k, v in tls.items()}


@dataclass(frozen=True)
class SwarmAccessControl:
    """Who may publish what on one swarm's keys (see the module docstring).

    drone_ids: the drones of the swarm (an identity ``drone-<id>`` outside it may publish
    nothing); gcs_common_name: the ground station's certificate name; extra_rules: further
    ``(common name, key expression)`` pairs that identity may put on (e.g. a logger's keys).
    """

    swarm: str
    drone_ids: tuple[int, ...]
    gcs_common_name: str = GCS_COMMON_NAME
    extra_rules: tuple[tuple[str, str], ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        SwarmKeys(self.swarm)  # checks the name
        if not self.drone_ids:
            raise ValueError("access_control.drone_ids: at least one drone")
        for i in self.drone_ids:
            drone_common_name(i)
        if len(set(self.drone_ids)) != len(self.drone_ids):
            raise ValueError(f"access_control.drone_ids: repeated ids in {self.drone_ids}")
        if not self.gcs_common_name or self.gcs_common_name.startswith("drone-"):
            raise ValueError(
                f"access_control.gcs_common_name: {self.gcs_common_name!r} is empty or a "
                "drone's name"
            )

    def config(self) -> dict[str, Any]:
        """The ``access_control`` section of the Zenoh configuration."""
        k = SwarmKeys(self.swarm)
        s = self.swarm
        names = [self.gcs_common_name] + [drone_common_name(i) for i in self.drone_ids]
        rules: list[dict[str, Any]] = [
            _rule("read", _READ_MESSAGES, [f"{s}/**"], flows=("ingress",)),
            _rule("egress", ACL_MESSAGES, [f"{s}/**"], flows=("egress",)),
            _rule("gcs-cmd", ("put",), [f"{s}/cmd/**"]),
            _rule("gcs-alive", ("liveliness_token",), [k.alive_gcs]),
        ]
        subjects: list[dict[str, Any]] = [
            {"id": "swarm", "cert_common_names": names},
            {"id": "gcs", "cert_common_names": [self.gcs_common_name]},
        ]
        policies: list[dict[str, Any]] = [
            {"id": "swarm-read", "rules": ["read", "egress"], "subjects": ["swarm"]},
            {"id": "gcs", "rules": ["gcs-cmd", "gcs-alive"], "subjects": ["gcs"]},
        ]
        for i in sorted(self.drone_ids):
            rid = f"drone-{i}"
            rules.append(_rule(f"{rid}-put", ("put",), [f"{s}/drone/{i}/**", k.ack(i)]))
            rules.append(_rule(f"{rid}-alive", ("liveliness_token",), [k.alive_drone(i)]))
            subjects.append({"id": rid, "cert_common_names": [drone_common_name(i)]})
            policies.append({"id": rid, "rules": [f"{rid}-put", f"{rid}-alive"], "subjects": [rid]})
        for n, (cn, key) in enumerate(self.extra_rules):
            rules.append(_rule(f"extra-{n}", ("put",), [key]))
            subjects.append({"id": f"extra-{n}", "cert_common_names": [cn]})
            policies.append(
                {"id": f"extra-{n}", "rules": [f"extra-{n}"], "subjects": [f"extra-{n}"]}
            )
        return {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        }

    def zenoh_items(self) -> dict[str, str]:
        return {"access_control": json.dumps(self.config())}

    @classmethod
    def for_count(cls, swarm: str, n_drones: int, **kw: Any) -> SwarmAccessControl:
        """Drones ``0 .. n_drones-1`` (the ids ``swarm-gcs certs --drones N`` issues)."""
        if isinstance(n_drones, bool) or not isinstance(n_drones, int) or n_drones < 1:
            raise ValueError(f"access_control.drones: expected an integer >= 1, got {n_drones!r}")
        return cls(swarm, tuple(range(n_drones)), **kw)


def _rule(
    rid: str,
    messages: Iterable[str],
    key_exprs: list[str],
    flows: tuple[str, ...] = ("ingress",),
) -> dict[str, Any]:
    return {
        "id": rid,
        "messages": list(messages),
        "flows": list(flows),
        "permission": "allow",
        "key_exprs": key_exprs,
    }


def security_items(
    tls: TlsConfig | None, access_control: SwarmAccessControl | None
) -> Mapping[str, str]:
    """Zenoh configuration items for both (either may be None)."""
    out: dict[str, str] = {}
    if tls is not None:
        out.update(tls.zenoh_items())
    if access_control is not None:
        if tls is None or not tls.enable_mtls:
            raise ValueError(
                "access_control: needs tls with enable_mtls (identities are certificate names)"
            )
        out.update(access_control.zenoh_items())
    return out
