"""Numba's on-disk cache of compiled functions, kept consistent with the sources.

Numba (0.61) checks a cached compiled function against its own source file only (that file's
modification time and size). A compiled function that calls one of another file has that
callee compiled into it: when only the callee's file changes (a ``git pull`` on a developer's
checkout or on a drone's editable install), the caller's cache still matches its own file and
keeps the old code. The planner's kernels call across files throughout (``objective`` ->
``trajectory``, ``minco``, ``field``, ...): after such a change a process would fly a mix of
old and new code. ``clear_stale`` hashes every source file that holds compiled code and, when
the hash differs from the one stamped beside the caches, deletes those files' cached
functions, so that they are compiled afresh (``swarm-onboard warmup`` does it before a flight).

The caches live either beside the sources (``__pycache__``, numba's default) or under
``NUMBA_CACHE_DIR`` (the systemd units set it); both are handled. A cache in numba's per-user
fallback directory (a read-only install without ``NUMBA_CACHE_DIR``) is not.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

STAMP = "swarm-jit-sources.sha256"
"""The file, in each cache location, holding the hash of the sources its caches were built
from (all of them: a change anywhere clears every location)."""

_COMPILED = re.compile(rb"^\s*@(?:numba\.|nb\.)?(?:njit|jit|vectorize|guvectorize)\b", re.M)

_PACKAGES = ("onboard", "sitl_mock")
"""The packages with compiled code, as siblings of this package's directory (the ones
present: the drone has no ``sitl_mock``). One hash covers them all, as the mock's kernels may
call the onboard ones."""


def default_roots() -> list[Path]:
    """The directories of the packages with compiled code that are present."""
    base = Path(__file__).resolve().parent.parent
    return [base / name for name in _PACKAGES if (base / name / "__init__.py").is_file()]


def jit_sources(roots: Iterable[Path]) -> list[Path]:
    """The Python files under ``roots`` with a numba decorator, sorted."""
    found: list[Path] = []
    for root in roots:
        for here, subdirs, names in os.walk(root):
            subdirs[:] = [d for d in subdirs if d != "__pycache__"]  # numba's own files
            for name in names:
                if not name.endswith(".py"):
                    continue
                path = Path(here) / name
                try:
                    if _COMPILED.search(path.read_bytes()):
                        found.append(path)
                except OSError:
                    continue
    return sorted(found)


def source_key(files: Sequence[Path]) -> str:
    """SHA-256 over the files' contents, each with its name (a rename counts as a change)."""
    h = hashlib.sha256()
    for path in files:
        h.update(path.name.encode() + b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def _user_cache_subdir(cache_dir: Path, source_dir: Path) -> Path:
    """Where numba's ``NUMBA_CACHE_DIR`` locator puts the caches of files in ``source_dir``:
    the directory's name and the SHA-1 of its absolute path."""
    path = os.path.abspath(source_dir)
    digest = hashlib.sha1(path.encode()).hexdigest()
    return cache_dir / f"{os.path.split(path)[-1]}_{digest}"


def cache_locations(files: Sequence[Path], cache_dir: str | None) -> list[Path]:
    """The directories that may hold cached compiled functions of ``files``: each file's
    directory's ``__pycache__`` and, with ``cache_dir``, numba's subdirectory of it for that
    directory. Each holds its own stamp (``STAMP``)."""
    dirs = sorted({f.parent for f in files})
    found = [d / "__pycache__" for d in dirs]
    if cache_dir:
        found += [_user_cache_subdir(Path(cache_dir), d) for d in dirs]
    return found


def clear_stale(roots: Iterable[Path] | None = None, cache_dir: str | None | bool = True) -> int:
    """Delete the cached compiled functions of ``roots`` (default ``default_roots()``) in
    every cache location whose stamp differs from the hash of all their compiled sources,
    then stamp it. Returns how many cache files were deleted. ``cache_dir``: numba's user
    cache directory (True: the ``NUMBA_CACHE_DIR`` environment variable; None or False:
    none). A location that cannot be created, read or written is left as it is (numba then
    compiles, or falls back, by itself)."""
    files = jit_sources(default_roots() if roots is None else roots)
    if not files:
        return 0
    key = source_key(files)
    user_dir = os.environ.get("NUMBA_CACHE_DIR") if cache_dir is True else cache_dir or None
    stems = {f.stem for f in files}
    removed = 0
    for d in cache_locations(files, user_dir):
        try:  # stamped before numba writes to it: its first caches are not taken as stale
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        stamp = d / STAMP
        try:
            if stamp.read_text().strip() == key:
                continue
        except OSError:
            pass
        removed += _remove_cached(d, stems)
        try:
            tmp = d / f"{STAMP}.{os.getpid()}.tmp"
            tmp.write_text(key + "\n")
            tmp.replace(stamp)
        except OSError:
            continue
    return removed


def _remove_cached(directory: Path, stems: set[str]) -> int:
    """Delete numba's index and data files of modules ``stems`` in ``directory``."""
    n = 0
    try:
        entries = list(directory.iterdir())
    except OSError:
        return 0
    for path in entries:
        if path.suffix not in (".nbi", ".nbc") or path.name.split(".", 1)[0] not in stems:
            continue
        try:
            path.unlink()
            n += 1
        except OSError:  # gone meanwhile (another process), or not ours to delete
            continue
    return n


def kernel_census(prefixes: Sequence[str] = ("onboard.",)) -> dict[str, int]:
    """How many compiled versions (signatures) each numba kernel of the loaded modules named
    ``prefixes`` holds now, by ``module.qualname``: compiled in this process or loaded from the
    cache. Two censuses taken before and after some work tell the kernels it compiled or
    loaded (``kernels_added``): the flight service takes one when it is READY, so that a kernel
    its warm-up missed shows in flight (where compiling one holds a planning thread for tens
    of seconds on a cold cache) rather than only as a late plan."""
    from numba.core.dispatcher import Dispatcher

    out: dict[str, int] = {}
    seen: set[int] = set()
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith(tuple(prefixes)):
            continue
        for value in list(vars(module).values()):
            if not isinstance(value, Dispatcher) or id(value) in seen:
                continue
            seen.add(id(value))
            fn = value.py_func
            out[f"{fn.__module__}.{fn.__qualname__}"] = len(value.overloads)
    return out


def kernels_added(before: Mapping[str, int], after: Mapping[str, int]) -> dict[str, int]:
    """The kernels of ``after`` with more compiled versions than in ``before`` (a kernel new
    to ``after`` counts all of its), and how many more."""
    return {k: n - before.get(k, 0) for k, n in sorted(after.items()) if n > before.get(k, 0)}
