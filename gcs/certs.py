"""``swarm-gcs certs OUTDIR --drones N``: a demo certificate authority for the swarm bus.

Makes, with the ``openssl`` command line (the ``cryptography`` package is not a dependency):

- ``ca.pem`` / ``ca.key``: a self-signed CA (``CN=<swarm>-demo-ca``);
- ``drone-<id>.pem`` / ``drone-<id>.key`` for ids ``0 .. N-1``: CN and SAN ``drone-<id>``;
- ``gcs.pem`` / ``gcs.key``: the ground station (CN and SAN ``gcs``).

Every certificate also names the hosts given with ``--host`` in its SAN (default 127.0.0.1 and
localhost: the loopback demo), since Zenoh checks the listener's name on connect. Keys are EC
P-256 (PKCS#8), written with mode 0600 in a directory of mode 0700; the CA key is needed only to
issue more certificates: keep it off the drones. A demo CA, not a production PKI: the keys are
unencrypted files.
"""

from __future__ import annotations

import ipaddress
import os
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

import click

from onboard.comm.security import GCS_COMMON_NAME, drone_common_name

DEFAULT_HOSTS = ("127.0.0.1", "localhost")


class CertError(RuntimeError):
    """openssl failed or is missing."""


def _openssl() -> str:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("the openssl command is needed to make certificates (apt install openssl)")
    return exe


def _run(args: Sequence[str], cwd: Path) -> None:
    # umask 077: key files never exist with wider permissions, even for an instant
    r = subprocess.run(
        [_openssl(), *args], cwd=cwd, capture_output=True, text=True, umask=0o077, check=False
    )
    if r.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {r.stderr.strip()[-500:]}")


def _san(name: str, hosts: Sequence[str]) -> str:
    items = [f"DNS:{name}"]
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            items.append(f"IP:{h}")
        except ValueError:
            items.append(f"DNS:{h}")
    return ",".join(items)


def _issue(out: Path, name: str, hosts: Sequence[str], days: int) -> None:
    key, csr, ext = f"{name}.key", f"{name}.csr", f"{name}.ext"
    _run(
        [
            "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-keyout", key, "-out", csr, "-subj", f"/CN={name}",
        ],
        out,
    )  # fmt: skip
    (out / ext).write_text(
        f"subjectAltName={_san(name, hosts)}\n"
        "basicConstraints=critical,CA:FALSE\n"
        "keyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=serverAuth,clientAuth\n"
    )
    try:
        _run(
            [
                "x509", "-req", "-in", csr, "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-out", f"{name}.pem", "-days", str(days),
                "-sha256", "-extfile", ext,
            ],
            out,
        )  # fmt: skip
    finally:
        (out / csr).unlink(missing_ok=True)
        (out / ext).unlink(missing_ok=True)
    os.chmod(out / key, 0o600)
    os.chmod(out / f"{name}.pem", 0o644)


def make_demo_pki(
    outdir: str | os.PathLike[str],
    drones: int,
    hosts: Sequence[str] = DEFAULT_HOSTS,
    days: int = 365,
    swarm: str = "swarm",
    gcs_name: str = GCS_COMMON_NAME,
) -> dict[str, Path]:
    """Make the CA and the certificates in ``outdir`` (created; existing files of the same
    names are refused). Returns ``{identity: certificate path}`` (``"ca"`` included)."""
    if isinstance(drones, bool) or not isinstance(drones, int) or drones < 1:
        raise ValueError(f"drones: expected an integer >= 1, got {drones!r}")
    if not 1 <= days <= 3650:
        raise ValueError(f"days: expected 1..3650, got {days!r}")
    names = [gcs_name] + [drone_common_name(i) for i in range(drones)]
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(out, 0o700)
    taken = [p.name for n in ["ca", *names] for p in (out / f"{n}.pem", out / f"{n}.key")]
    taken = [n for n in taken if (out / n).exists()]
    if taken:
        raise CertError(f"{out}: would overwrite {', '.join(sorted(taken)[:5])}")
    _run(
        [
            "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days), "-sha256",
            "-subj", f"/CN={swarm}-demo-ca",
            "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        ],
        out,
    )  # fmt: skip
    os.chmod(out / "ca.key", 0o600)
    os.chmod(out / "ca.pem", 0o644)
    paths = {"ca": out / "ca.pem"}
    for name in names:
        _issue(out, name, hosts, days)
        paths[name] = out / f"{name}.pem"
    (out / "ca.srl").unlink(missing_ok=True)
    return paths


@click.command("certs")
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--drones", "-n", type=int, default=3, show_default=True, help="Drones 0..N-1.")
@click.option(
    "--host",
    "hosts",
    multiple=True,
    help="Host name or IP every certificate is valid for (repeatable; default 127.0.0.1 and "
    "localhost).",
)
@click.option("--days", type=int, default=365, show_default=True)
@click.option("--swarm", default="swarm", show_default=True, help="Only names the CA.")
def certs_command(outdir: str, drones: int, hosts: tuple[str, ...], days: int, swarm: str) -> None:
    """Make a demo CA and one certificate per drone (drone-<id>) and for the ground station
    (gcs) in OUTDIR, keys 0600, for Zenoh TLS with mutual authentication."""
    try:
        paths = make_demo_pki(outdir, drones, hosts or DEFAULT_HOSTS, days, swarm)
    except (ValueError, CertError) as e:
        raise click.ClickException(str(e)) from e
    for name, path in paths.items():
        click.echo(
            f"{name:>10}  {path}" + ("" if name == "ca" else f"  {path.with_suffix('.key')}")
        )
