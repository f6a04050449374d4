"""``swarm-gcs certs``: the demo CA and its certificates (openssl command line)."""

from __future__ import annotations

import json
import stat
import subprocess
from pathlib import Path

from click.testing import CliRunner

from gcs.bench_fuzz import fuzz_command
from gcs.certs import certs_command


def mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_certs_command_makes_a_ca_and_one_certificate_per_identity(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    r = CliRunner().invoke(certs_command, [str(out), "--drones", "2", "--host", "10.0.0.5"])
    assert r.exit_code == 0, r.output
    names = ["gcs", "drone-0", "drone-1"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["ca.pem", "ca.key"] + [f"{n}.{ext}" for n in names for ext in ("pem", "key")]
    )
    assert mode(out) == 0o700
    for key in out.glob("*.key"):
        assert mode(key) == 0o600, key
    for name in names:
        cert = out / f"{name}.pem"
        verify = subprocess.run(
            ["openssl", "verify", "-CAfile", str(out / "ca.pem"), str(cert)],
            capture_output=True,
            text=True,
            check=False,
        )
        assert verify.returncode == 0, verify.stderr
        text = subprocess.run(
            ["openssl", "x509", "-in", str(cert), "-noout", "-subject", "-ext", "subjectAltName"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        assert f"CN = {name}" in text or f"CN={name}" in text
        assert f"DNS:{name}" in text and "IP Address:10.0.0.5" in text
    # never overwrites, and refuses nonsense
    again = CliRunner().invoke(certs_command, [str(out), "--drones", "2"])
    assert again.exit_code != 0 and "would overwrite" in again.output
    bad = CliRunner().invoke(certs_command, [str(tmp_path / "x"), "--drones", "0"])
    assert bad.exit_code != 0 and "drones" in bad.output


def test_bench_fuzz_records_inputs_and_crashes(tmp_path: Path) -> None:
    js = tmp_path / "fuzz.json"
    r = CliRunner().invoke(
        fuzz_command, ["--target", "depth", "--inputs", "300", "--json", str(js)]
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(js.read_text())
    (res,) = doc["results"]
    assert res["target"] == "depth" and res["inputs"] == 300
    assert res["crashes"] == 0 and res["hangs"] == 0
    bad = CliRunner().invoke(fuzz_command, ["--target", "nope"])
    assert bad.exit_code != 0
