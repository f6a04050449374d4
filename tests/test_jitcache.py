"""Numba's on-disk cache is cleared when a file that compiled code calls changes
(``onboard.jitcache``): numba itself checks a cached function against its own file only."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from onboard import jitcache
from onboard.jitcache import STAMP, cache_locations, clear_stale, jit_sources, source_key

CALLER = """
from numba import njit
from pkg.callee import g

@njit(cache=True)
def f():
    return g() + 10
"""
CALLEE = """
from numba import njit

@njit(cache=True)
def g():
    return {value}
"""


def _package(root: Path, value: int) -> Path:
    pkg = root / "pkg"
    pkg.mkdir(exist_ok=True)
    if not (pkg / "caller.py").exists():  # written once: only the callee changes
        (pkg / "__init__.py").write_text("")
        (pkg / "caller.py").write_text(textwrap.dedent(CALLER))
    callee = pkg / "callee.py"
    callee.write_text(textwrap.dedent(CALLEE.format(value=value)))
    st = callee.stat()  # a distinct modification time even on a coarse clock
    os.utime(callee, ns=(st.st_atime_ns, st.st_mtime_ns + value * 10**9))
    return pkg


def _run(root: Path, clear: bool, env: dict[str, str]) -> int:
    """f() in a fresh process, after ``clear_stale`` on the package when ``clear``."""
    code = "import sys; from pathlib import Path; from onboard.jitcache import clear_stale\n"
    if clear:
        code += "clear_stale([Path(sys.argv[1]) / 'pkg'])\n"
    code += "from pkg.caller import f; print(f())"
    out = subprocess.run(
        [sys.executable, "-c", code, str(root)],
        cwd=root,
        env={**env, "PYTHONPATH": os.pathsep.join([str(root), str(Path.cwd())])},
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return int(out.stdout.split()[-1])


def test_a_changed_callee_is_compiled_afresh_where_numba_would_keep_the_old_one(
    tmp_path: Path,
) -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    for where, extra in (("in-tree", {}), ("user", {"NUMBA_CACHE_DIR": str(tmp_path / "nc")})):
        root = tmp_path / where
        root.mkdir()
        e = {**env, **extra}
        _package(root, 1)
        assert _run(root, True, e) == 11  # compiled and cached
        _package(root, 2)  # only the callee's file changes
        assert _run(root, False, e) == 11  # numba alone: the caller's cache holds the old g
        assert _run(root, True, e) == 12  # cleared: compiled afresh
        assert _run(root, True, e) == 12  # and cached again under the new stamp


def test_the_stamps_the_locations_and_what_is_deleted(tmp_path: Path) -> None:
    pkg = _package(tmp_path, 1)
    (pkg / "plain.py").write_text("x = 1\n")
    files = jit_sources([pkg])
    assert [f.name for f in files] == ["callee.py", "caller.py"]
    user = tmp_path / "nc"
    locs = cache_locations(files, str(user))
    assert locs[0] == pkg / "__pycache__" and len(locs) == 2
    assert locs[1].parent == user and locs[1].name.startswith("pkg_")
    for d in locs:
        d.mkdir(parents=True, exist_ok=True)
        for name in ("caller.f-5.py311.nbi", "caller.f-5.py311.1.nbc", "other.h-1.py311.nbi"):
            (d / name).write_bytes(b"x")
        (d / "caller.cpython-311.pyc").write_bytes(b"x")
    assert clear_stale([pkg], str(user)) == 4  # our modules' index and data, both places
    for d in locs:
        assert sorted(p.name for p in d.iterdir() if p.name != STAMP) == [
            "caller.cpython-311.pyc",
            "other.h-1.py311.nbi",
        ]
        assert (d / STAMP).read_text().strip() == source_key(files)
    (locs[0] / "caller.f-5.py311.nbi").write_bytes(b"x")
    assert clear_stale([pkg], str(user)) == 0  # the stamps match: nothing deleted
    (pkg / "plain.py").write_text("x = 2\n")  # no compiled code in it: no change
    assert clear_stale([pkg], str(user)) == 0
    _package(tmp_path, 3)
    assert clear_stale([pkg], None) == 1  # in-tree only without a user directory
    assert (locs[1] / STAMP).read_text().strip() != source_key(jit_sources([pkg]))
    fresh = tmp_path / "fresh"
    assert clear_stale([pkg], str(fresh)) == 0  # created and stamped before numba writes
    assert (cache_locations(files, str(fresh))[1] / STAMP).is_file()


def test_an_unwritable_location_is_left_alone(tmp_path: Path) -> None:
    pkg = _package(tmp_path, 1)
    blocked = tmp_path / "file"
    blocked.write_text("")  # a 'cache directory' that is a file: mkdir fails
    assert clear_stale([pkg], str(blocked)) == 0
    assert (pkg / "__pycache__" / STAMP).is_file()  # the other location is still stamped


def test_the_onboard_packages_are_covered() -> None:
    names = {f"{f.parent.name}/{f.name}" for f in jit_sources(jitcache.default_roots())}
    assert {"planner/objective.py", "planner/trajectory.py", "mapping/esdf.py"} <= names
    assert "sitl_mock/dynamics.py" in names


def test_the_census_counts_each_kernels_compiled_versions(monkeypatch) -> None:
    """``kernel_census`` counts the compiled versions of the kernels in the modules it is
    asked for, once for a kernel a module imported from another; ``kernels_added`` names
    those that gained one (the flight service's count of kernels made after READY)."""
    import types

    from onboard.jitcache import kernel_census, kernels_added

    main = types.ModuleType("census_probe")
    source = "from numba import njit\n@njit\ndef kernel(x):\n    return x + 1\n"
    source += "@njit\ndef caller(x):\n    return kernel(x) * 2\n"
    exec(compile(source, "census_probe.py", "exec"), main.__dict__)
    other = types.ModuleType("census_probe_b")
    other.kernel = main.kernel  # imported elsewhere too: counted once
    monkeypatch.setitem(sys.modules, "census_probe", main)
    monkeypatch.setitem(sys.modules, "census_probe_b", other)
    name, caller = "census_probe.kernel", "census_probe.caller"
    before = kernel_census(("census_probe",))
    assert before == {name: 0, caller: 0}
    assert main.kernel(1) == 2
    assert kernels_added(before, kernel_census(("census_probe",))) == {name: 1}
    assert main.kernel(1) == 2  # the same signature: nothing new
    mid = kernel_census(("census_probe",))
    assert kernels_added(before, mid) == {name: 1}
    assert main.caller(1.5) == 5.0  # compiles the caller, and the kernel for a float
    assert kernels_added(mid, kernel_census(("census_probe",))) == {name: 1, caller: 1}
    assert kernels_added({}, mid) == {name: 1}  # new to the second census: all its versions
    assert kernel_census(("no_such_module",)) == {}
