"""Layers point one way: read from the source (ast), so that no import path can hide a breach.

- ``onboard/`` imports neither ``gcs`` nor ``sitl_mock`` (the ground station and the mock import
  what they share from ``onboard``, never the other way);
- the pure core (``onboard/planner``, ``onboard/mapping``) imports no transport, device or
  concurrency module: no sockets, threads, Zenoh, MAVLink, MAVSDK or Open3D;
- the world model does not know the planner (``onboard/world.py`` imports nothing of
  ``onboard.planner``; the planner builds its exact field from a world).

Every import statement counts, also inside functions and ``if TYPE_CHECKING:`` blocks, and so do
``importlib.import_module("...")`` / ``__import__("...")`` calls with a literal name.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ONBOARD = ROOT / "onboard"

PURE_PACKAGES = ("planner", "mapping")
PURE_FORBIDDEN = ("zenoh", "pymavlink", "mavsdk", "open3d", "threading", "socket")

# Known exceptions, each with its reason; the tests fail when one is no longer needed, so that
# the list only shrinks. (path relative to the repository, imported top-level module or
# ``module@function``) -> reason.
EXCEPTIONS: dict[tuple[str, str], str] = {}


def _module_name(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, root: Path = ROOT) -> list[tuple[str, int, str]]:
    """(absolute module name, line, enclosing function or '') of every import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _module_name(path, root).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    out: list[tuple[str, int, str]] = []

    def visit(node: ast.AST, func: str) -> None:
        for child in ast.iter_child_nodes(node):
            name = func
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = child.name
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, func) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package[: len(package) - (child.level - 1)]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                out.append((mod, child.lineno, func))
            elif isinstance(child, ast.Call) and child.args:
                f = child.func
                called = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
                arg = child.args[0]
                if called in ("import_module", "__import__") and isinstance(arg, ast.Constant):
                    out.append((str(arg.value), child.lineno, func))
            visit(child, name)

    visit(tree, "")
    return out


def _sources(*parts: str) -> list[Path]:
    files = sorted((ONBOARD.joinpath(*parts)).rglob("*.py"))
    assert files, f"no sources under onboard/{'/'.join(parts)}"
    return files


def _top(module: str) -> str:
    return module.split(".")[0]


def _breaches(
    files: list[Path], forbidden: tuple[str, ...]
) -> tuple[list[str], set[tuple[str, str]]]:
    """Imports of a forbidden top-level module, and the exceptions that were used."""
    bad: list[str] = []
    used: set[tuple[str, str]] = set()
    for path in files:
        rel = str(path.relative_to(ROOT))
        for mod, line, _func in _imports(path):
            if _top(mod) not in forbidden:
                continue
            if (rel, _top(mod)) in EXCEPTIONS:
                used.add((rel, _top(mod)))
                continue
            bad.append(f"{rel}:{line} imports {mod}")
    return bad, used


def test_the_import_reader_sees_every_form(tmp_path: Path) -> None:
    """The checker itself: each form of import is found, relative ones resolved."""
    pkg = tmp_path / "onboard" / "planner"
    pkg.mkdir(parents=True)
    probe = pkg / "probe.py"
    probe.write_text(
        "import os, socket as s\n"
        "from . import field\n"
        "from ..comm import bus\n"
        "import typing\n"
        "if typing.TYPE_CHECKING:\n"
        "    from gcs.fastsim import run_sim\n"
        "def f():\n"
        "    import threading\n"
        "    import importlib\n"
        "    importlib.import_module('zenoh')\n"
        "    __import__('sitl_mock.truth')\n",
        encoding="utf-8",
    )
    found = {(m, fn) for m, _, fn in _imports(probe, tmp_path)}
    assert found >= {
        ("os", ""),
        ("socket", ""),
        ("onboard.planner", ""),
        ("onboard.comm", ""),
        ("gcs.fastsim", ""),
        ("threading", "f"),
        ("zenoh", "f"),
        ("sitl_mock.truth", "f"),
    }


def test_onboard_imports_neither_gcs_nor_sitl_mock() -> None:
    bad, _ = _breaches(_sources(), ("gcs", "sitl_mock"))
    assert bad == [], "onboard/ must not depend on the ground station or the mock:\n" + "\n".join(
        bad
    )


@pytest.mark.parametrize("package", PURE_PACKAGES)
def test_pure_core_imports_no_io_or_threads(package: str) -> None:
    bad, used = _breaches(_sources(package), PURE_FORBIDDEN)
    assert bad == [], f"onboard/{package} must stay pure:\n" + "\n".join(bad)
    stale = {
        k for k in EXCEPTIONS if k[0].startswith(f"onboard/{package}/") and "@" not in k[1]
    } - used
    assert not stale, f"exceptions no longer needed, remove them from EXCEPTIONS: {stale}"


def test_world_model_does_not_know_the_planner() -> None:
    path = ONBOARD / "world.py"
    bad: list[str] = []
    for mod, line, func in _imports(path):
        if not mod.startswith(("onboard.planner", "onboard.mapping")):
            continue
        bad.append(f"onboard/world.py:{line} imports {mod}" + (f" in {func}()" if func else ""))
    assert bad == [], "\n".join(bad)
