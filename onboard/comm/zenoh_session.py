"""The one place that opens Zenoh sessions (swarm bus, simulated sensors, ground station).

Peer mode with multicast scouting off and explicit endpoints by default, so that nothing on the
machine is discovered by accident and tests on loopback never see another test run's traffic.
A router (``mode="client"`` with ``connect`` naming it) is the option for field networks.
"""

from __future__ import annotations

import dataclasses
import json
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from onboard.comm.loopback import free_port
from onboard.comm.security import SwarmAccessControl, TlsConfig, security_items

MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class ZenohEndpoints:
    """How a process joins the Zenoh network.

    listen / connect: endpoints such as ``tcp/127.0.0.1:7447``; mode: 'peer' (default), 'client'
    (through a router) or 'router'; multicast_scouting: discover peers on the LAN (off: only the
    named endpoints are used); extra: further Zenoh configuration keys, JSON5 values as text
    (``{"transport/link/tls/root_ca_certificate": '"/etc/swarm/ca.pem"'}``); tls: TLS with
    mutual authentication (``tls/HOST:PORT`` endpoints need it); access_control: who may
    publish what (needs ``tls``). See ``onboard.comm.security``.
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    mode: str = "peer"
    multicast_scouting: bool = False
    extra: Mapping[str, str] = field(default_factory=dict)
    tls: TlsConfig | None = None
    access_control: SwarmAccessControl | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, got {self.mode!r}")
        for name in ("listen", "connect"):
            eps = getattr(self, name)
            if isinstance(eps, str):
                raise ValueError(f"zenoh {name} must be a list of endpoints, got a string")
            for ep in eps:
                if not isinstance(ep, str) or "/" not in ep:
                    raise ValueError(f"zenoh {name} endpoint {ep!r} is not like 'tcp/HOST:PORT'")
                if self.tls is not None and not ep.startswith("tls/"):
                    raise ValueError(
                        f"zenoh {name} endpoint {ep!r}: with tls every endpoint must be tls/..."
                    )
                if (
                    self.tls is None
                    and ep.startswith("tls/")
                    and not any(k.startswith("transport/link/tls") for k in self.extra)
                ):
                    raise ValueError(f"zenoh {name} endpoint {ep!r} needs the tls settings")
        security_items(self.tls, self.access_control)  # access control needs mutual TLS

    def config(self) -> Any:
        """The ``zenoh.Config`` for these settings."""
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        for key, value in {**security_items(self.tls, self.access_control), **self.extra}.items():
            cfg.insert_json5(key, value)
        return cfg

    def secured(
        self, tls: TlsConfig, access_control: SwarmAccessControl | None = None
    ) -> ZenohEndpoints:
        """These endpoints over TLS (``tcp/`` endpoints become ``tls/``) with ``tls`` and
        ``access_control``."""
        return dataclasses.replace(
            self,
            listen=tuple(as_tls_endpoint(ep) for ep in self.listen),
            connect=tuple(as_tls_endpoint(ep) for ep in self.connect),
            tls=tls,
            access_control=access_control,
        )


def as_tls_endpoint(endpoint: str) -> str:
    """``tcp/HOST:PORT`` as ``tls/HOST:PORT``; other endpoints unchanged."""
    proto, _, rest = endpoint.partition("/")
    return f"tls/{rest}" if proto in ("tcp", "tls") else endpoint


def open_session(endpoints: ZenohEndpoints | None = None, **kw: Any) -> Any:
    """Open a Zenoh session: ``open_session(ZenohEndpoints(...))`` or with its fields as keywords
    (``open_session(listen=["tcp/127.0.0.1:7447"])``). Raises ``RuntimeError`` naming the
    endpoints when Zenoh refuses (port taken, unreachable router, bad TLS files)."""
    import zenoh

    if endpoints is None:
        kw = {k: tuple(v) if k in ("listen", "connect") else v for k, v in kw.items()}
        endpoints = ZenohEndpoints(**kw)
    elif kw:
        raise TypeError("give either a ZenohEndpoints or keywords, not both")
    try:
        return zenoh.open(endpoints.config())
    except Exception as e:  # zenoh raises its own ZError; say which endpoints failed
        raise RuntimeError(
            f"cannot open Zenoh ({endpoints.mode}, listen={list(endpoints.listen)}, "
            f"connect={list(endpoints.connect)}): {e}"
        ) from e


def free_loopback_endpoint() -> str:
    """A TCP endpoint on 127.0.0.1 on a port free when drawn, outside the kernel's ephemeral
    range (``onboard.comm.loopback``; for tests and the local demo, so that two runs on one
    machine do not collide, and no outgoing connection's source port takes it before the
    listener binds it)."""
    return f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"


def loopback_endpoints(n: int) -> list[str]:
    """``n`` distinct free loopback endpoints."""
    out: list[str] = []
    while len(out) < n:
        ep = free_loopback_endpoint()
        if ep not in out:
            out.append(ep)
    return out


def peer_mesh(n: int) -> list[ZenohEndpoints]:
    """Endpoints for ``n`` peers on loopback: each listens on its own port and connects to all
    the others' (a full mesh that needs no scouting). ``.secured(tls, acl)`` turns one into
    TLS."""
    ports = loopback_endpoints(n)
    return [
        ZenohEndpoints(listen=(ports[i],), connect=tuple(p for j, p in enumerate(ports) if j != i))
        for i in range(n)
    ]


def declare_liveliness(session: Any, key: str) -> Any:
    """Announce ``key`` as alive while the returned token (or the session) lives."""
    return session.liveliness().declare_token(key)


def sequence_str(values: Sequence[str]) -> str:
    """Endpoints as one comma-separated string (for command lines)."""
    return ",".join(values)
