"""Every module of the three packages imports on the interpreter running the suite.

`make test` runs the whole suite on Python 3.10 (the drone's) and a smoke selection on the
default interpreter (`.venv`, the one `make demo` uses); this test is part of both, so that a
module that does not import on either interpreter (syntax, a dependency built differently for
it) fails there, also when no other test of that run happens to load it.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("onboard", "gcs", "sitl_mock")


def _modules() -> list[str]:
    out: list[str] = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts.pop()
            out.append(".".join(parts))
    return out


MODULES = _modules()


def test_the_module_list_is_complete() -> None:
    # a package that moved or a glob that matches nothing would make the test below vacuous
    for pkg in PACKAGES:
        assert pkg in MODULES
    assert len(MODULES) > 60
    assert "onboard.service.service" in MODULES and "gcs.demo" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_module_imports(name: str) -> None:
    mod = importlib.import_module(name)
    assert mod.__name__ == name
    assert sys.version_info >= (3, 10)
