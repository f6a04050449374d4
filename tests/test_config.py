"""Config loading: every shipped file loads; bad keys, types and shapes name their key path."""

from __future__ import annotations

import enum
import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
import yaml

from onboard.config import (
    ConfigError,
    config_dir,
    from_mapping,
    load_formation,
    load_planner_params,
    load_world_spec,
    parse_override,
    parse_overrides,
    world_file,
)
from onboard.planner.params import PlannerParams

FORMATIONS = sorted(p.stem for p in (config_dir() / "formations").glob("*.yaml"))
WORLDS = sorted(p.stem for p in (config_dir() / "worlds").glob("*.yaml"))


def test_shipped_files_exist() -> None:
    assert {"hexagon-7", "tetrahedron-4", "heart-10", "triangle-3"} <= set(FORMATIONS)
    assert {"forest-sparse", "forest-medium", "forest-dense", "forest-small"} <= set(WORLDS)
    assert (config_dir() / "planner.yaml").is_file()


@pytest.mark.parametrize("name", FORMATIONS)
def test_formation_loads(name: str) -> None:
    f = load_formation(name)
    n = int(name.rsplit("-", 1)[1])
    assert f.name == name and f.points.shape == (n, 3)
    assert not f.points.flags.writeable


def test_hexagon_is_regular() -> None:
    p = load_formation("hexagon-7").points
    assert np.allclose(p[0], 0.0)
    assert np.allclose(np.linalg.norm(p[1:], axis=1), 2.0, atol=1e-4)
    ring = np.linalg.norm(np.diff(np.vstack([p[1:], p[1:2]]), axis=0), axis=1)
    assert np.allclose(ring, 2.0, atol=1e-4)


@pytest.mark.parametrize("name", WORLDS)
def test_world_loads_and_builds(name: str) -> None:
    spec = load_world_spec(name)
    formation = load_formation("triangle-3" if name == "forest-small" else "hexagon-7")
    world, starts, goals = spec.build(3, formation)
    assert starts.shape == goals.shape == (formation.n, 3)
    assert np.allclose(starts.mean(axis=0), spec.start_center)
    assert np.allclose(goals - starts, np.asarray(spec.goal_center) - spec.start_center)
    assert world.cylinders.shape[0] == (spec.generator.n_cylinders if spec.generator else 0)
    # Cylinders are taller than the flight altitude, starts and goals are clear.
    assert np.all(world.cylinders[:, 4] >= 2.5)
    d, _ = world.distance(np.vstack([starts, goals]))
    assert np.all(d > 0.5)
    # Same seed, same world; another seed, another world.
    again, _, _ = spec.build(3, formation)
    other, _, _ = spec.build(4, formation)
    assert np.array_equal(again.cylinders, world.cylinders)
    if spec.generator is not None and spec.generator.n_cylinders > 0:
        assert not np.array_equal(other.cylinders, world.cylinders)
    else:  # an explicit world is the same whatever the seed
        assert np.array_equal(other.boxes, world.boxes)


def test_planner_yaml_loads() -> None:
    p = load_planner_params()
    assert isinstance(p, PlannerParams)
    assert load_planner_params(v_max_m_s=1.25).v_max_m_s == 1.25


def test_planner_overrides_and_nested_merge() -> None:
    p = load_planner_params(w_formation=3, lbfgs={"max_iterations": 7})
    assert p.w_formation == 3.0 and isinstance(p.w_formation, float)
    assert p.lbfgs.max_iterations == 7
    assert p.lbfgs.mem_size == PlannerParams().lbfgs.mem_size  # the rest kept
    assert parse_override("lbfgs.max_iterations=50") == {"lbfgs": {"max_iterations": 50}}
    assert parse_override("w_obstacle=1e4") == {"w_obstacle": 1e4}
    # several --set options: merged in order over a base, which is not changed
    base = {"lbfgs": {"mem_size": 8}, "kappa": 4}
    sets = ["lbfgs.max_iterations=50", "kappa=6", "lbfgs.max_iterations=60"]
    got = parse_overrides(sets, base)
    assert got == {"lbfgs": {"mem_size": 8, "max_iterations": 60}, "kappa": 6}
    assert base == {"lbfgs": {"mem_size": 8}, "kappa": 4} and parse_overrides([]) == {}


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"w_obstacle": "x"}, "planner.w_obstacle: expected a number, got 'x'"),
        ({"kappa": 2.5}, "planner.kappa: expected an integer"),
        ({"no_such_key": 1}, "planner.no_such_key: unknown key"),
        ({"lbfgs": {"bogus": 1}}, "planner.lbfgs.bogus: unknown key"),
        ({"lbfgs": {"mem_size": True}}, "planner.lbfgs.mem_size: expected an integer"),
        ({"z_limits_m": [1.0]}, "planner.z_limits_m: expected a list of 2 items"),
        ({"z_limits_m": [0.0, "a"]}, "planner.z_limits_m[1]: expected a number"),
        ({"v_max_m_s": -1.0}, "planner: v_max_m_s must be a positive number"),
        ({"w_time": float("nan")}, "planner.w_time: expected a finite number"),
    ],
)
def test_planner_errors_name_the_key(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_planner_params(**overrides)
    assert str(e.value).startswith(message), str(e.value)


def test_planner_file_errors(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text("w_swarm: 1.0e3\nkappa: 4\n")
    p = load_planner_params(f)
    assert p.w_swarm == 1e3 and p.kappa == 4
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="planner: expected a mapping"):
        load_planner_params(f)
    f.write_text("w_swarm: [1\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_planner_params(f)


def _write(tmp_path: Path, text: str, name: str = "f.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_formation_from_file_and_json(tmp_path: Path) -> None:
    f = load_formation(_write(tmp_path, "points: [[0, 0, 0], [1, 0, 0], [0, 1, 1]]\n"))
    assert f.name == "f" and f.points.shape == (3, 3)
    j = tmp_path / "line.json"
    j.write_text(json.dumps({"points": [[0, 0, 0], [2, 0, 0]]}))
    assert load_formation(str(j)).n == 2


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("points: [[0, 0, 0]]\n", "at least 2 points"),
        ("points: [[0, 0], [1, 1]]\n", "formation.points[0]: expected a list of 3 items"),
        ("points: [[0, 0, 0], [0, 0, x]]\n", "formation.points[1][2]: expected a number"),
        ("points: [[1, 1, 1], [1, 1, 1]]\n", "all points coincide"),
        ("points: [[0, 0, .nan], [1, 1, 1]]\n", "formation.points[0][2]: expected a finite"),
        ("pts: [[0, 0, 0], [1, 1, 1]]\n", "formation.pts: unknown key"),
        ("name: x\n", "formation.points: required key is missing"),
    ],
)
def test_bad_formations(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_formation(_write(tmp_path, text))


def test_unknown_names() -> None:
    with pytest.raises(ConfigError, match="no file named 'nope'"):
        load_formation("nope")
    with pytest.raises(ConfigError, match="no file named 'nope'"):
        load_world_spec("nope")


EXPLICIT = """
cylinders: [[5, 0, 0.3, 0, 3]]
rings: [{center: [8, 0, 1.5], yaw: 0.5, radius_horizontal: 0.8, radius_vertical: 0.8,
         tube_radius: 0.1}]
boxes: [[10, -1, 0, 11, 1, 2]]
cluttered_x: [0, 12]
start_center: [0, 0, 1]
goal_center: [15, 0, 1]
starts: [[0, 1, 1], [0, -1, 1]]
goals: [[15, 1, 1], [15, -1, 1]]
"""


def test_explicit_world(tmp_path: Path) -> None:
    spec = load_world_spec(_write(tmp_path, EXPLICIT, "explicit.yaml"))
    assert spec.name == "explicit"
    formation = load_formation(_write(tmp_path, "points: [[0, 0, 0], [1, 0, 0]]\n"))
    world, starts, goals = spec.build(0, formation)
    assert world.cylinders.shape == (1, 5) and world.rings.shape == (1, 7)
    assert world.boxes.shape == (1, 6)
    assert world.rings[0, 3] == 0.5
    assert np.array_equal(starts, [[0, 1, 1], [0, -1, 1]])
    assert np.array_equal(goals, [[15, 1, 1], [15, -1, 1]])
    with pytest.raises(ConfigError, match="starts: 2 given, formation has 3"):
        spec.build(0, load_formation("triangle-3"))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ("cylinders: [[5, 0, 0.3, 0]]", "world.cylinders[0]: expected a list of 5 items"),
        ("cylinders: [[5, 0, -0.3, 0, 3]]", "world: cylinders: bad row"),
        ("rings: [{center: [8, 0, 1.5]}]", "world.rings[0].radius_horizontal: required key"),
        ("rings: [{center: [8, 0], radius_horizontal: 1, radius_vertical: 1, tube_radius: 0}]",
         "world.rings[0].center: expected a list of 3 items"),
        ("boxes: [[1, 2, 3]]", "world.boxes[0]: expected a list of 6 items"),
        ("cluttered_x: 3", "world.cluttered_x: expected a list, got 3"),
        ("generator: {type: forest, n_cylinders: 5, x_range: [0, 1]}",
         "world.generator.y_range: required key is missing"),
        ("generator: {type: maze, n_cylinders: 5, x_range: [0, 1], y_range: [0, 1]}",
         "world.generator.type: expected one of ['forest']"),
        ("generator: {type: forest, n_cylinders: many, x_range: [0, 1], y_range: [0, 1]}",
         "world.generator.n_cylinders: expected an integer"),
        ("goals: [[15, 1, 1]]", "world: starts and goals must have the same length"),
        ("colour: red", "world.colour: unknown key"),
    ],
)  # fmt: skip
def test_bad_worlds(tmp_path: Path, edit: str, message: str) -> None:
    data = yaml.safe_load(EXPLICIT)
    data.update(yaml.safe_load(edit))
    with pytest.raises(ConfigError) as e:
        load_world_spec(_write(tmp_path, yaml.safe_dump(data)))
    assert str(e.value).startswith(message), str(e.value)


def test_world_errors_at_build(tmp_path: Path) -> None:
    crowded = (
        "generator: {type: forest, n_cylinders: 50, x_range: [0, 2], y_range: [0, 2]}\n"
        "cluttered_x: [0, 2]\nstart_center: [-3, 0, 1]\ngoal_center: [5, 0, 1]\n"
    )
    spec = load_world_spec(_write(tmp_path, crowded, "crowded.yaml"))
    with pytest.raises(ConfigError, match=r"^crowded\.generator: random_forest: could not place"):
        spec.build(0, load_formation("triangle-3"))
    data = yaml.safe_load(EXPLICIT)
    data["boxes"] = [[1, 1, 1, 0, 2, 2]]
    spec = load_world_spec(_write(tmp_path, yaml.safe_dump(data), "badbox.yaml"))
    pair = load_formation(_write(tmp_path, "points: [[0, 0, 0], [1, 0, 0]]\n"))
    with pytest.raises(ConfigError, match=r"^badbox: World\.boxes: min must be < max"):
        spec.build(0, pair)


@dataclass(frozen=True)
class _Inner:
    a: int = 1
    b: tuple[float, ...] = ()


@dataclass(frozen=True)
class _Outer:
    name: str
    inner: _Inner = _Inner()
    maybe: float | None = None
    flag: bool = False


def test_from_mapping_generic() -> None:
    o = from_mapping(_Outer, {"name": "x", "inner": {"b": [1, 2.5]}, "maybe": 2, "flag": True})
    assert o == _Outer("x", _Inner(1, (1.0, 2.5)), 2.0, True)
    assert from_mapping(_Outer, {"name": "y", "maybe": None}).maybe is None
    with pytest.raises(ConfigError, match=r"^cfg\.inner\.b\[1\]: expected a number, got 'q'"):
        from_mapping(_Outer, {"name": "x", "inner": {"b": [1, "q"]}}, "cfg")
    with pytest.raises(ConfigError, match=r"^cfg\.flag: expected true or false, got 1"):
        from_mapping(_Outer, {"name": "x", "flag": 1}, "cfg")
    with pytest.raises(ConfigError, match=r"^cfg\.name: expected a string"):
        from_mapping(_Outer, {"name": 3}, "cfg")
    with pytest.raises(ConfigError, match=r"^cfg: expected a mapping"):
        from_mapping(_Outer, [1, 2], "cfg")


def test_config_dir_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "formations").mkdir()
    (tmp_path / "formations" / "pair.yaml").write_text("points: [[0, 0, 0], [1, 0, 0]]\n")
    monkeypatch.setenv("SWARM_CONFIG_DIR", str(tmp_path))
    assert config_dir() == tmp_path
    assert load_formation("pair").n == 2
    assert load_planner_params() == PlannerParams()  # no planner.yaml there: defaults


def test_shipped_planner_file_equals_the_dataclass_defaults() -> None:
    """config/planner.yaml documents the defaults; retuning must change both."""
    from onboard.config import load_planner_params
    from onboard.planner.params import PlannerParams

    assert load_planner_params() == PlannerParams()


class _Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


class _Level(enum.IntEnum):
    LOW = 1
    HIGH = 2


@dataclass(frozen=True)
class _Service:
    """The kinds of fields a service config uses (nested, optional, enums, literals, dicts)."""

    colour: _Colour = _Colour.RED
    level: _Level = _Level.LOW
    mode: Literal["fast", "slow"] = "fast"
    port: int | str = 0
    timeouts_s: dict[str, float] = field(default_factory=dict)
    inners: dict[str, _Inner] = field(default_factory=dict)
    pair: tuple[float, float] = (0.0, 1.0)
    inner: _Inner = _Inner(a=5, b=(1.0,))
    maybe_inner: _Inner | None = None

    def __post_init__(self) -> None:
        if self.inner.a < 0:
            raise ValueError("inner.a must be >= 0")


def test_from_mapping_enums_literals_dicts_unions() -> None:
    s = from_mapping(
        _Service,
        {
            "colour": "BLUE",
            "level": 2,
            "mode": "slow",
            "port": "tty",
            "timeouts_s": {"gcs": 5, "peer": 0.5},
            "inners": {"x": {"a": 2}},
            "maybe_inner": {"b": [3]},
        },
    )
    assert s.colour is _Colour.BLUE and s.level is _Level.HIGH and s.mode == "slow"
    assert s.port == "tty" and s.timeouts_s == {"gcs": 5.0, "peer": 0.5}
    assert s.inners == {"x": _Inner(2, ())} and s.maybe_inner == _Inner(1, (3.0,))
    assert from_mapping(_Service, {"colour": "blue", "level": "HIGH", "port": 7}) == _Service(
        colour=_Colour.BLUE, level=_Level.HIGH, port=7
    )
    # numpy scalars and arrays are plain values
    assert from_mapping(_Service, {"pair": np.array([1, 2.5])}).pair == (1.0, 2.5)
    assert from_mapping(_Service, {"level": np.int64(2)}).level is _Level.HIGH


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"colour": "green"}, "svc.colour: expected one of ['red', 'blue'], got 'green'"),
        ({"level": 3}, "svc.level: expected one of [1, 2], got 3"),
        ({"level": True}, "svc.level: expected one of [1, 2], got True"),
        ({"mode": "medium"}, "svc.mode: expected one of ['fast', 'slow'], got 'medium'"),
        ({"port": 1.5}, "svc.port: expected an integer or a string, got 1.5"),
        ({"timeouts_s": {"gcs": "5"}}, "svc.timeouts_s.gcs: expected a number, got '5'"),
        ({"timeouts_s": [1]}, "svc.timeouts_s: expected a mapping, got [1]"),
        ({"inners": {"x": {"c": 1}}}, "svc.inners.x.c: unknown key (known: ['a', 'b'])"),
        ({"pair": [1, 2, 3]}, "svc.pair: expected a list of 2 items, got 3"),
        ({"pair": [1]}, "svc.pair: expected a list of 2 items, got 1"),
        ({"pair": [True, 1]}, "svc.pair[0]: expected a number, got True"),
        ({"pair": [1, float("inf")]}, "svc.pair[1]: expected a finite number, got inf"),
        ({"inner": None}, "svc.inner: expected a mapping, got None"),
        ({"inner": {"a": -1}}, "svc: inner.a must be >= 0"),
        ({"maybe_inner": {"a": "1"}}, "svc.maybe_inner.a: expected an integer, got '1'"),
        ({"maybe_inner": 3}, "svc.maybe_inner: expected a mapping, got 3"),
        ({"colour": b"red"}, "svc.colour: unsupported value b'red'"),
        ({"bogus": 1}, "svc.bogus: unknown key (known: ['colour', 'inner', 'inners', "),
    ],
)
def test_from_mapping_error_messages(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        from_mapping(_Service, data, "svc")
    assert str(e.value).startswith(message), str(e.value)


def test_from_mapping_reports_every_error_one_per_line() -> None:
    with pytest.raises(ConfigError) as e:
        from_mapping(_Service, {"mode": 1, "pair": [0, "x"], "nope": 2}, "svc")
    lines = str(e.value).splitlines()
    assert lines == [
        "svc.mode: expected one of ['fast', 'slow'], got 1",
        "svc.pair[1]: expected a number, got 'x'",
        "svc.nope: unknown key (known: ['colour', 'inner', 'inners', 'level', 'maybe_inner', "
        "'mode', 'pair', 'port', 'timeouts_s'])",
    ]


def test_from_mapping_partial_override_over_a_base() -> None:
    base = from_mapping(_Service, {"colour": "blue", "inner": {"a": 9}})
    assert base.inner == _Inner(9, (1.0,))  # filled in over the field's default, not _Inner()
    s = from_mapping(_Service, {"mode": "slow", "inner": {"b": [2]}}, base=base)
    assert s == _Service(colour=_Colour.BLUE, mode="slow", inner=_Inner(9, (2.0,)))
    assert from_mapping(_Service, {}, base=s) == s
    with pytest.raises(ConfigError, match=r"^svc\.inner\.a: expected an integer, got 1\.5"):
        from_mapping(_Service, {"inner": {"a": 1.5}}, "svc", base=s)


def test_from_mapping_accepts_no_booleans_or_strings_for_numbers() -> None:
    for bad in (True, "1", "1.5", None, [1]):
        with pytest.raises(ConfigError, match=r"^planner\.w_time: expected a number"):
            load_planner_params(w_time=bad)
    for bad in (2.0, "2", False):
        with pytest.raises(ConfigError, match=r"^planner\.kappa: expected an integer"):
            load_planner_params(kappa=bad)


def test_world_with_explicit_starts_needs_no_centres(tmp_path: Path) -> None:
    data = yaml.safe_load(EXPLICIT)
    del data["start_center"], data["goal_center"]
    spec = load_world_spec(_write(tmp_path, yaml.safe_dump(data), "bare.yaml"))
    assert spec.start_center == (0.0, 0.0, 1.0) and spec.goal_center == (15.0, 0.0, 1.0)
    pair = load_formation(_write(tmp_path, "points: [[0, 0, 0], [1, 0, 0]]\n"))
    world, starts, goals = spec.build(0, pair)
    assert np.array_equal(starts, [[0, 1, 1], [0, -1, 1]])
    # exported again, it loads to the same world
    again = load_world_spec(
        _write(tmp_path, yaml.safe_dump(world_file(world, spec, starts, goals)), "again.yaml")
    )
    world2, starts2, goals2 = again.build(1, pair)
    assert np.array_equal(world2.cylinders, world.cylinders)
    assert np.array_equal(starts2, starts) and np.array_equal(goals2, goals)
    del data["starts"], data["goals"]
    with pytest.raises(ConfigError) as e:
        load_world_spec(_write(tmp_path, yaml.safe_dump(data), "nothing.yaml"))
    assert str(e.value).startswith(
        "world: start_center and goal_center are required unless starts and goals are given"
    )


def test_config_loading_imports_no_numba_and_the_core_no_pydantic() -> None:
    def loaded(code: str) -> set[str]:
        out = subprocess.run(
            [sys.executable, "-c", f"import sys\n{code}\nprint(*sorted(sys.modules))"],
            capture_output=True,
            text=True,
            check=True,
        )
        return {m.split(".")[0] for m in out.stdout.split()}

    config = loaded(
        "from onboard.config import load_formation, load_world_spec, load_scenario\n"
        "load_formation('hexagon-7'); load_world_spec('forest-medium')\n"
        "load_scenario('tetrahedron-corridor')"
    )
    assert "pydantic" in config and "numba" not in config
    core = loaded("import onboard.planner.planner, onboard.planner.objective, onboard.world")
    assert "numba" in core and "pydantic" not in core


@dataclass(frozen=True)
class _Unions:
    count: Literal[1, 2] = 1
    colour_or_index: _Colour | int = 0
    inner_or_name: _Inner | str = ""


def test_from_mapping_unions_and_literals() -> None:
    assert from_mapping(_Unions, {"colour_or_index": "BLUE"}).colour_or_index is _Colour.BLUE
    assert from_mapping(_Unions, {"colour_or_index": 3}).colour_or_index == 3
    assert from_mapping(_Unions, {"inner_or_name": {"a": 2}}).inner_or_name == _Inner(2)
    cases = [
        ({"count": True}, "u.count: expected one of [1, 2], got True"),
        ({"count": 3}, "u.count: expected one of [1, 2], got 3"),
        (
            {"colour_or_index": "green"},
            "u.colour_or_index: expected one of ['red', 'blue'] or an integer, got 'green'",
        ),
        (
            {"inner_or_name": {"a": "x"}},
            "u.inner_or_name: expected _Inner (a: expected an integer, got 'x') or a string, "
            "got {'a': 'x'}",
        ),
    ]
    for data, message in cases:
        with pytest.raises(ConfigError) as e:
            from_mapping(_Unions, data, "u")
        assert str(e.value) == message
