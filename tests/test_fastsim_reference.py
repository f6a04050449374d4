"""Seeded fast-time flights must not change when the simulator's internals are reorganised.

``tests/data/fastsim_reference*.npz`` hold short seeded flights, each file recorded on one
platform with the code of the commit named in it: the flown tracks (10 Hz), the formation
metric, and the inputs of every plan call (which drone, when, from which state, how many
peers), plus the scalar metrics. The test flies them again and compares: integers and statuses
exactly, floats to 1e-9. They are equal to
the last bit only on the kind of machine that recorded them: numba compiles for the host CPU
(on an AVX-512 Cascade Lake the recording of an older host diverged within seconds: other plan
statuses, other tracks), so each file names the CPU, its vector instruction sets, Python, numpy
and numba it was recorded with; the test compares with the file of this platform, and where
there is none it is skipped, saying so. The CPU's name alone is not enough: the LLVM of numba
0.61 calls an AMD Zen 4 (AVX-512) "znver3" like a Zen 3 (none), and the two fly differently.

Regenerate (only when a change of results is intended, and say so in the commit; on every
platform that has a file, else the stale ones must go):
``.venv310/bin/python tests/test_fastsim_reference.py --write``
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.fastsim import PlanCall, SimConfig, run_sim
from onboard.config import load_formation, load_world_spec

DATA_DIR = Path(__file__).parent / "data"
# the instruction sets that change numba's code for these kernels (vector width, fused ops)
ISA = ("avx2", "fma", "avx512f", "avx512vl", "avx512bw", "avx512dq")

CASES: dict[str, dict[str, Any]] = {
    # a whole flight of three drones through the small forest
    "triangle_small_gt": {"formation": "triangle-3", "world": "forest-small", "seed": 1,
                          "v_max_m_s": 1.0},
    # the benchmark's hexagon through the medium forest, first 40 s
    "hexagon_medium_gt": {"formation": "hexagon-7", "world": "forest-medium", "seed": 1,
                          "v_max_m_s": 0.5, "time_limit_s": 40.0},
    # one drone's radio fails
    "triangle_silent": {"formation": "triangle-3", "world": "forest-small", "seed": 1,
                        "v_max_m_s": 1.0, "time_limit_s": 12.0, "silent_drones": (1,)},
    # every drone plans on its own map built from simulated depth frames
    "triangle_mapped_short": {"formation": "triangle-3", "world": "forest-small", "seed": 2,
                              "v_max_m_s": 1.0, "time_limit_s": 6.0, "perception": "mapped",
                              "camera_skip_pixel": 4},
}  # fmt: skip

SCALARS = (
    "success",
    "collisions",
    "min_obstacle_clearance_m",
    "min_drone_distance_m",
    "max_speed_m_s",
    "e_sim_mean",
    "e_dist_mean",
    "flight_time_s",
    "timed_out",
    "iterations",
    "evaluations",
    "status_counts",
    "arrived",
)


def fly(name: str) -> dict[str, Any]:
    """Fly one case; its tracks, plan-call inputs and scalar metrics."""
    spec = dict(CASES[name])
    cfg = SimConfig(
        load_formation(spec.pop("formation")), load_world_spec(spec.pop("world")), **spec
    )
    calls: list[PlanCall] = []
    r = run_sim(cfg, recorder=calls.append)
    d = r.to_json()
    return {
        "pos": r.tracks.pos,
        "e_sim": r.tracks.e_sim,
        "t": r.tracks.t,
        "call_t": np.array([c.t_start_s for c in calls]),
        "call_id": np.array([c.drone_id for c in calls]),
        "call_state": np.array([np.stack([c.start_p, c.start_v, c.start_a]) for c in calls]),
        "call_peers": np.array(
            [[p.drone_id for p in c.peers] + [-1] * (9 - len(c.peers)) for c in calls]
        ),
        "call_world": np.array([c.world.n_primitives for c in calls]),
        "scalars": {k: d[k] for k in SCALARS},
    }


def platform() -> dict[str, str]:
    """What the bits of a flight depend on besides the code: the CPU numba compiles for and the
    versions of the interpreter and the numerical libraries."""
    import llvmlite.binding
    import numba

    features = llvmlite.binding.get_host_cpu_features()
    return {
        "cpu": str(llvmlite.binding.get_host_cpu_name()),
        "isa": ",".join(f for f in ISA if features.get(f, False)),
        "python": f"{sys.version_info[0]}.{sys.version_info[1]}",
        "numpy": np.__version__,
        "numba": numba.__version__,
    }


def _recorded_on() -> dict[str, dict[str, str]]:
    """Each reference file's platform."""
    out = {}
    for path in sorted(DATA_DIR.glob("fastsim_reference*.npz")):
        with np.load(path, allow_pickle=False) as z:
            out[path.name] = json.loads(str(z["platform"]))
    return out


def _file_name(p: dict[str, str]) -> str:
    isa = "avx512" if "avx512f" in p["isa"].split(",") else p["isa"].replace(",", "-") or "base"
    return f"fastsim_reference_{p['cpu']}_{isa}_py{p['python']}.npz"


def _reference() -> dict[str, Any] | None:
    here = platform()
    for name, p in _recorded_on().items():
        if p == here:
            with np.load(DATA_DIR / name, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
    return None


def test_reference_files_name_distinct_platforms() -> None:
    recorded = _recorded_on()
    assert recorded, "no reference flight in tests/data"
    keys = [json.dumps(p, sort_keys=True) for p in recorded.values()]
    assert len(set(keys)) == len(keys), recorded
    for name, p in recorded.items():
        assert set(p) == {"cpu", "isa", "python", "numpy", "numba"}, (name, p)
        assert name == _file_name(p), (name, p)


@pytest.mark.parametrize("name", list(CASES))
def test_seeded_flight_is_unchanged(name: str) -> None:
    ref = _reference()
    if ref is None:
        pytest.skip(
            f"recorded on {list(_recorded_on().values())}, this is {platform()}: "
            "re-record here to compare"
        )
    got = fly(name)
    scalars = json.loads(str(ref[f"{name}/scalars"]))
    assert got["scalars"]["status_counts"] == scalars["status_counts"]
    for key in ("call_id", "call_peers", "call_world"):
        np.testing.assert_array_equal(got[key], ref[f"{name}/{key}"], err_msg=key)
    for key in ("t", "call_t", "call_state", "pos", "e_sim"):
        np.testing.assert_allclose(got[key], ref[f"{name}/{key}"], rtol=0, atol=1e-9, err_msg=key)
    for key, want in scalars.items():
        have = got["scalars"][key]
        if isinstance(want, float):
            assert have == pytest.approx(want, rel=0, abs=1e-9), key
        elif isinstance(want, dict):
            assert set(have) == set(want), key
            for k, v in want.items():
                if v is None:
                    assert have[k] is None, (key, k)
                else:
                    assert have[k] == pytest.approx(v, rel=0, abs=1e-9), (key, k)
        else:
            assert have == want, key


def _write() -> None:
    out: dict[str, Any] = {}
    for name in CASES:
        got = fly(name)
        for k, v in got.items():
            out[f"{name}/{k}"] = json.dumps(v) if k == "scalars" else v
        print(name, got["scalars"]["status_counts"], got["scalars"]["flight_time_s"])
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=DATA_DIR
    ).stdout.strip()
    out["commit"] = commit
    here = platform()
    out["platform"] = json.dumps(here)
    path = DATA_DIR / _file_name(here)
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    print(f"wrote {path} ({path.stat().st_size} bytes) at {commit}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        raise SystemExit("usage: python tests/test_fastsim_reference.py --write")
    _write()
