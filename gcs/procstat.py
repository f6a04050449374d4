"""CPU seconds from Linux ``/proc``: what the benchmarks and the demo read of their processes."""

from __future__ import annotations

import os


def _read_stat(path: str) -> tuple[str, float]:
    """(name, user + system CPU seconds) of a ``/proc`` stat file; OSError when unreadable."""
    with open(path) as f:
        text = f.read()
    fields = text.rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return text[text.index("(") + 1 : text.rindex(")")], cpu


def stat_cpu_s(path: str) -> float:
    """User + system CPU seconds in a ``/proc`` stat file (``/proc/<pid>/stat``: the process,
    all its threads). Raises OSError when the file cannot be read (the process has ended; no
    ``/proc``)."""
    return _read_stat(path)[1]


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds of the process ``pid``'s running threads by OS thread name (threads of one
    name summed; threads that ended are not counted, nor one that ends while this reads).
    Raises OSError when the process cannot be read."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            name, cpu = _read_stat(f"/proc/{pid}/task/{tid}/stat")
        except OSError:
            continue  # ended meanwhile
        out[name] = out.get(name, 0.0) + cpu
    return out
