"""Property-based fuzzing of every decoder target of ``bench fuzz`` (``gcs/bench_fuzz.py``).

Each target may only refuse an input with its layer's error (a counted ``Rejected``, a
``ConfigError`` naming the key, a ``DecodeError`` with a reason, a counted MAVLink decode
error); an accepted value must be finite (goals also inside the geofence). Hypothesis drives
random input and the harness's own mutations of valid seeds. ``SWARM_FUZZ_EXAMPLES`` sets the
examples per test (a few hundred in the suite; the benchmark runs 100 000 per target).
"""

from __future__ import annotations

import os
import random
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcs.bench_fuzz import TARGETS, FuzzTarget, OneInput, mutate, run_mutation
from onboard.config import ConfigError, load_formation, load_world_spec

N_FUZZ = int(os.environ.get("SWARM_FUZZ_EXAMPLES", "300"))
FAST = settings(max_examples=N_FUZZ, deadline=None, suppress_health_check=list(HealthCheck))
# file targets write a file and parse YAML per input: a third of the examples
FILES = settings(FAST, max_examples=max(N_FUZZ // 3, 1))

BINARY = ["traj", "state", "command", "mavlink", "depth"]
TEXT = ["formation", "world", "config"]

_ONE: dict[str, OneInput] = {}
_SEEDS: dict[str, list[bytes]] = {}


def one(name: str) -> OneInput:
    if name not in _ONE:
        _ONE[name] = TARGETS[name].make()
        _SEEDS[name] = TARGETS[name].seeds()
    return _ONE[name]


def seeds(name: str) -> list[bytes]:
    one(name)
    return _SEEDS[name]


@pytest.mark.parametrize("name", BINARY + TEXT)
def test_every_seed_is_accepted_whole(name: str) -> None:
    """The seeds are valid inputs (a target that refused everything would prove nothing)."""
    t: FuzzTarget = TARGETS[name]
    assert t.seeds(), name
    for s in seeds(name):
        one(name)(s)


@pytest.mark.parametrize("name", BINARY)
def test_random_bytes(name: str) -> None:
    f = one(name)

    @FAST
    @given(st.binary(max_size=3000))
    def run(data: bytes) -> None:
        f(data)

    run()


@pytest.mark.parametrize("name", BINARY)
def test_mutated_seeds(name: str) -> None:
    f = one(name)
    pool = seeds(name)

    @FAST
    @given(st.integers(0, len(pool) - 1), st.randoms(use_true_random=False))
    def run(which: int, rng: random.Random) -> None:
        f(mutate(pool[which], rng, pool, False))

    run()


@pytest.mark.parametrize("name", TEXT)
def test_mutated_files(name: str) -> None:
    f = one(name)
    pool = seeds(name)

    @FILES
    @given(st.integers(0, len(pool) - 1), st.randoms(use_true_random=False))
    def run(which: int, rng: random.Random) -> None:
        data = mutate(pool[which], rng, pool, True)
        f(data.decode("utf-8", "replace").encode("utf-8"))

    run()


@pytest.mark.parametrize("name", TEXT)
def test_random_text_files(name: str) -> None:
    f = one(name)

    @FILES
    @given(st.text(max_size=400))
    def run(text: str) -> None:
        f(text.encode("utf-8"))

    run()


def test_a_file_that_is_not_utf8_is_a_config_error(tmp_path: Path) -> None:
    p = tmp_path / "f.yaml"
    p.write_bytes(b"points: [[0, 0, 0], [1, 0, 0]]\n# \xff\xfe\n")
    with pytest.raises(ConfigError, match="f.yaml"):
        load_formation(p)


@pytest.mark.parametrize(
    "text",
    [
        "points: &a [*a, [0, 0, 0]]\n",
        "cluttered_x: &a [*a, 1]\nstart_center: [0, 0, 0]\ngoal_center: [1, 1, 1]\n",
    ],
)
def test_a_recursive_yaml_alias_is_a_config_error(tmp_path: Path, text: str) -> None:
    p = tmp_path / "f.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError):
        (load_formation if text.startswith("points") else load_world_spec)(p)


def test_the_harness_counts_a_crash() -> None:
    """The engine itself can fail: a target that raises is counted, with its input kept."""

    def boom() -> Callable[[bytes], None]:
        def f(data: bytes) -> None:
            if len(data) > 3:
                raise KeyError("boom")

        return f

    t = FuzzTarget("boom", "test", lambda: [b"ab", b"abcdef"], boom)
    r = run_mutation(t, 50, seed=1)
    assert r.inputs == 50 and r.crashes > 0 and r.examples
    assert "KeyError" in r.examples[0]["error"]


@pytest.mark.parametrize("name", TEXT)
def test_file_target_leaves_no_directory(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file target's scratch directory goes with it (runs used to leave them in /tmp)."""
    import gc
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # this test's own: no other worker's
    f = TARGETS[name].make()
    f(TARGETS[name].seeds()[0])
    made = list(tmp_path.glob("swarm-fuzz-*"))
    assert len(made) == 1 and (made[0] / "input.yaml").is_file()
    del f
    gc.collect()
    assert not made[0].exists()
