"""Configuration, loaded once at the edge into frozen, validated objects.

Everything the numerical core needs arrives as plain values: planner parameters
(``PlannerParams``), formation templates (``Formation``) and world descriptions (``WorldSpec``).
Files are YAML (or JSON, which YAML reads too). Every unknown key and every wrongly typed value is
a ``ConfigError`` that names the key path, e.g. ``planner.w_obstacle: expected a number, got 'x'``.

Named files live under ``config_dir()``: ``formations/NAME.yaml``, ``worlds/NAME.yaml`` and
``planner.yaml``. ``SWARM_CONFIG_DIR`` overrides the directory.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar, Union

import numpy as np
import yaml

if TYPE_CHECKING:  # imported lazily at run time: config loading must not need numba
    from onboard.planner.params import PlannerParams
    from onboard.world import World

T = TypeVar("T")

ENV_CONFIG_DIR = "SWARM_CONFIG_DIR"


class ConfigError(ValueError):
    """A configuration file or mapping is invalid; the message starts with the key path."""


def config_dir() -> Path:
    """The configuration directory: ``$SWARM_CONFIG_DIR`` or the repository's ``config/``."""
    env = os.environ.get(ENV_CONFIG_DIR)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / "config"


# ---------------------------------------------------------------------------------------------
# YAML reading


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e4`` / ``5E-3`` as floats (YAML 1.1 wants a dot)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def read_yaml(path: Path | str) -> Any:
    """Parse a YAML or JSON file; a missing file or a syntax error is a ``ConfigError``."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{p}: cannot read ({e.strerror or e})") from e
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: invalid YAML: {e}") from e


def _resolve_file(name_or_path: str | Path, subdir: str) -> tuple[str, Path]:
    """A bare name is ``config_dir()/subdir/NAME.yaml``; anything path-like is a path."""
    s = str(name_or_path)
    p = Path(s)
    looks_like_path = (
        isinstance(name_or_path, Path)
        or os.sep in s
        or "/" in s
        or p.suffix.lower() in (".yaml", ".yml", ".json")
    )
    if looks_like_path or p.is_file():
        return p.stem, p
    candidates = [config_dir() / subdir / f"{s}{ext}" for ext in (".yaml", ".yml", ".json")]
    for c in candidates:
        if c.is_file():
            return s, c
    known = sorted(q.stem for q in (config_dir() / subdir).glob("*.y*ml"))
    raise ConfigError(f"{subdir}: no file named {s!r} in {config_dir() / subdir} (known: {known})")


# ---------------------------------------------------------------------------------------------
# Generic mapping -> frozen dataclass


def _where(path: str) -> str:
    return path if path else "<root>"


def _describe(value: Any) -> str:
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


def _convert(tp: Any, value: Any, path: str, base: Any = None) -> Any:
    """Check ``value`` against the type ``tp`` and convert it (lists become tuples).

    ``base``: for a nested dataclass, the instance whose values fill the keys not given.
    """
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    if tp is Any:
        return value
    if origin is Union or (hasattr(types, "UnionType") and isinstance(tp, types.UnionType)):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        errors = []
        for a in options:
            try:
                nested = base if isinstance(a, type) and isinstance(base, a) else None
                return _convert(a, value, path, nested)
            except ConfigError as e:
                errors.append(str(e))
        if len(options) == 1:
            raise ConfigError(errors[0])
        raise ConfigError(f"{_where(path)}: no accepted type matches {_describe(value)}")
    if origin is Literal:
        if value in args and not isinstance(value, bool):
            return value
        raise ConfigError(f"{_where(path)}: expected one of {list(args)}, got {_describe(value)}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{_where(path)}: expected true or false, got {_describe(value)}")
    if tp is int:
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            return int(value)
        raise ConfigError(f"{_where(path)}: expected an integer, got {_describe(value)}")
    if tp is float:
        if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
            v = float(value)
            if not math.isfinite(v):
                raise ConfigError(f"{_where(path)}: expected a finite number, got {value!r}")
            return v
        raise ConfigError(f"{_where(path)}: expected a number, got {_describe(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{_where(path)}: expected a string, got {_describe(value)}")
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value or value == member.name:
                return member
        choices = [m.value for m in tp]
        raise ConfigError(f"{_where(path)}: expected one of {choices}, got {_describe(value)}")
    if origin is tuple or tp is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{_where(path)}: expected a list, got {_describe(value)}")
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(
                f"{_where(path)}: expected a list of {len(args)} items, got {len(value)}"
            )
        return tuple(
            _convert(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, tp):
            return value
        return from_mapping(tp, value, path, base=base)
    raise ConfigError(f"{_where(path)}: unsupported field type {tp!r}")  # pragma: no cover


def from_mapping(cls: type[T], data: Any, path: str = "", base: T | None = None) -> T:
    """Build the frozen dataclass ``cls`` from a mapping, validating every key and value.

    Unknown keys, missing required keys and wrongly typed values raise ``ConfigError`` whose
    message starts with the dotted key path (``path`` is the prefix, e.g. ``"planner"``).
    Integers are accepted for float fields, lists for tuple fields; nested dataclasses recurse.
    A ``ValueError`` from the dataclass's own ``__post_init__`` becomes a ``ConfigError`` too.
    Keys not given keep the values of ``base`` if one is passed, else the field defaults; a
    nested dataclass field with a default is filled in over that default (partial override).
    """
    if not (dataclasses.is_dataclass(cls) and isinstance(cls, type)):
        raise TypeError(f"{cls!r} is not a dataclass type")
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{_where(path)}: expected a mapping, got {_describe(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    prefix = f"{path}." if path else ""
    for key in data:
        if not isinstance(key, str) or key not in fields:
            raise ConfigError(f"{prefix}{key}: unknown key (known: {sorted(fields)})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if base is not None:
            default: Any = getattr(base, name)
        elif f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        if name in data:
            nested_base = default if dataclasses.is_dataclass(default) else None
            kwargs[name] = _convert(hints[name], data[name], f"{prefix}{name}", nested_base)
        elif default is dataclasses.MISSING:
            raise ConfigError(f"{prefix}{name}: required key is missing")
        elif base is not None:
            kwargs[name] = default
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{_where(path)}: {e}") from e


# ---------------------------------------------------------------------------------------------
# Formations


@dataclass(frozen=True)
class _FormationFile:
    points: tuple[tuple[float, float, float], ...]
    name: str = ""
    description: str = ""


@dataclass(frozen=True, eq=False)
class Formation:
    """A desired formation: N template points (N, 3) in metres, slot i = row i."""

    name: str
    points: np.ndarray

    def __post_init__(self) -> None:
        p = np.array(self.points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ConfigError(f"{self.name}.points: expected shape (N, 3), got {p.shape}")
        if p.shape[0] < 2:
            raise ConfigError(f"{self.name}.points: expected at least 2 points, got {p.shape[0]}")
        if not np.all(np.isfinite(p)):
            raise ConfigError(f"{self.name}.points: values must be finite")
        if np.max(np.linalg.norm(p - p.mean(axis=0), axis=1)) < 1e-6:
            raise ConfigError(f"{self.name}.points: all points coincide")
        p.setflags(write=False)
        object.__setattr__(self, "points", p)

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    @property
    def centered(self) -> np.ndarray:
        """The points minus their centroid, (N, 3)."""
        return self.points - self.points.mean(axis=0)


def load_formation(name_or_path: str | Path) -> Formation:
    """A formation from ``config/formations/NAME.yaml`` or any file ``points: [[x, y, z], ...]``."""
    name, file = _resolve_file(name_or_path, "formations")
    parsed = from_mapping(_FormationFile, read_yaml(file), "formation")
    return Formation(parsed.name or name, np.asarray(parsed.points, dtype=np.float64))


# ---------------------------------------------------------------------------------------------
# Planner parameters


def load_planner_params(path: str | Path | None = None, **overrides: Any) -> PlannerParams:
    """``PlannerParams`` from ``config/planner.yaml`` (or ``path``), then keyword overrides.

    Overrides are validated like file values (``planner.<field>`` in error messages); a mapping
    given for a nested field (``lbfgs={"max_iterations": 50}``) is merged into the file's.
    """
    from onboard.planner.params import PlannerParams

    file = Path(path) if path is not None else config_dir() / "planner.yaml"
    data = read_yaml(file) if (path is not None or file.is_file()) else {}
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"planner: expected a mapping, got {_describe(data)}")
    return from_mapping(PlannerParams, merge_mappings(data, overrides), "planner")


# ---------------------------------------------------------------------------------------------
# Worlds

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ForestGenerator:
    """A random forest of vertical cylinders (and optionally rings), drawn from the run's seed.

    Diameters and heights are uniform in their ranges; cylinder centres at least
    ``min_spacing_m`` apart. Nothing is placed within ``keep_clear_m`` of any start or goal.
    """

    type: Literal["forest"]
    n_cylinders: int
    x_range: Vec2
    y_range: Vec2
    diameter_range: Vec2 = (0.25, 0.75)
    height_range: Vec2 = (2.5, 3.0)
    min_spacing_m: float = 0.8
    n_rings: int = 0
    ring_radius_range: Vec2 = (0.6, 1.0)
    ring_height_range: Vec2 = (1.0, 2.0)
    keep_clear_m: float = 1.0

    def __post_init__(self) -> None:
        if self.n_cylinders < 0 or self.n_rings < 0:
            raise ValueError("n_cylinders and n_rings must be >= 0")
        for key in ("x_range", "y_range", "diameter_range", "height_range", "ring_radius_range"):
            lo, hi = getattr(self, key)
            if hi < lo:
                raise ValueError(f"{key}: upper bound below lower bound")
        if self.diameter_range[0] <= 0.0:
            raise ValueError("diameter_range: diameters must be positive")
        if self.min_spacing_m < 0.0 or self.keep_clear_m < 0.0:
            raise ValueError("min_spacing_m and keep_clear_m must be >= 0")


@dataclass(frozen=True)
class RingSpec:
    """An upright elliptical ring (torus) that drones can fly through; ``yaw`` in radians."""

    center: Vec3
    radius_horizontal: float
    radius_vertical: float
    tube_radius: float
    yaw: float = 0.0

    def row(self) -> list[float]:
        """The World ring row ``[cx, cy, cz, yaw, r_h, r_v, tube]``."""
        return [
            *self.center,
            self.yaw,
            self.radius_horizontal,
            self.radius_vertical,
            self.tube_radius,
        ]


@dataclass(frozen=True)
class WorldSpec:
    """A scenario: obstacles (generated from the seed and/or explicit) plus start and goal areas.

    cylinders rows ``[x, y, r, z_min, z_max]``; boxes rows of 6 numbers as ``World`` takes them
    (``[x_min, y_min, z_min, x_max, y_max, z_max]``). ``starts``/``goals`` (per drone, optional)
    override ``start_center``/``goal_center`` + formation offsets.
    """

    cluttered_x: Vec2
    start_center: Vec3
    goal_center: Vec3
    name: str = ""
    description: str = ""
    generator: ForestGenerator | None = None
    cylinders: tuple[tuple[float, float, float, float, float], ...] = ()
    rings: tuple[RingSpec, ...] = ()
    boxes: tuple[tuple[float, float, float, float, float, float], ...] = ()
    ground_z: float | None = 0.0
    starts: tuple[Vec3, ...] | None = None
    goals: tuple[Vec3, ...] | None = None

    def __post_init__(self) -> None:
        if self.cluttered_x[1] < self.cluttered_x[0]:
            raise ValueError("cluttered_x: upper bound below lower bound")
        for r in self.cylinders:
            if r[2] <= 0.0 or r[4] < r[3]:
                raise ValueError(f"cylinders: bad row {list(r)} (need r > 0, z_max >= z_min)")
        if (self.starts is None) != (self.goals is None):
            raise ValueError("starts and goals must be given together")
        if self.starts is not None and self.goals is not None:
            if len(self.starts) != len(self.goals):
                raise ValueError("starts and goals must have the same length")

    def endpoints(self, formation: Formation) -> tuple[np.ndarray, np.ndarray]:
        """(starts (N, 3), goals (N, 3)) for ``formation``."""
        n = formation.n
        if self.starts is not None and self.goals is not None:
            if len(self.starts) != n:
                raise ConfigError(
                    f"{self.name}.starts: {len(self.starts)} given, formation has {n} drones"
                )
            return np.array(self.starts, dtype=np.float64), np.array(self.goals, dtype=np.float64)
        offs = formation.centered
        return np.asarray(self.start_center) + offs, np.asarray(self.goal_center) + offs

    def build(self, seed: int, formation: Formation) -> tuple[World, np.ndarray, np.ndarray]:
        """(World, starts (N, 3), goals (N, 3)); the generated part is drawn from ``seed``."""
        from onboard.world import World

        starts, goals = self.endpoints(formation)
        try:
            explicit = World(
                cylinders=np.array(self.cylinders, dtype=np.float64).reshape(-1, 5),
                rings=np.array([r.row() for r in self.rings], dtype=np.float64).reshape(-1, 7),
                boxes=np.array(self.boxes, dtype=np.float64).reshape(-1, 6),
                ground_z=self.ground_z,
                name=self.name,
            )
        except ValueError as e:
            raise ConfigError(f"{self.name or 'world'}: {e}") from e
        if self.generator is None:
            return explicit, starts, goals
        g = self.generator
        keep = [(p.copy(), g.keep_clear_m) for p in np.concatenate([starts, goals])]
        try:
            forest = self._forest(int(seed), keep)
        except ValueError as e:
            raise ConfigError(f"{self.name or 'world'}.generator: {e}") from e
        return forest.merged(explicit), starts, goals

    def _forest(self, seed: int, keep: list[tuple[np.ndarray, float]]) -> World:
        from onboard.world import random_forest

        g = self.generator
        assert g is not None
        return random_forest(
            seed,
            n_cylinders=g.n_cylinders,
            x_range=g.x_range,
            y_range=g.y_range,
            diameter_range=g.diameter_range,
            height_range=g.height_range,
            min_spacing_m=g.min_spacing_m,
            n_rings=g.n_rings,
            ring_radius_range=g.ring_radius_range,
            ring_height_range=g.ring_height_range,
            keep_clear=keep,
            ground_z=self.ground_z,
        )


def load_world_spec(name_or_path: str | Path) -> WorldSpec:
    """A world from ``config/worlds/NAME.yaml`` or any YAML/JSON file."""
    name, file = _resolve_file(name_or_path, "worlds")
    spec = from_mapping(WorldSpec, read_yaml(file), "world")
    return spec if spec.name else dataclasses.replace(spec, name=name)


def parse_override(text: str) -> dict[str, Any]:
    """``"a.b=VALUE"`` -> ``{"a": {"b": VALUE}}`` with VALUE read as YAML (``1e4``, ``[0, 1]``).

    For command-line overrides such as ``--set w_formation=1e6 --set lbfgs.max_iterations=50``.
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override {text!r}: expected KEY=VALUE")
    try:
        value = yaml.load(raw, Loader=_Loader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as e:
        raise ConfigError(f"{key}: invalid value {raw!r}: {e}") from e
    out: dict[str, Any] = {}
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def merge_mappings(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """Recursive merge: nested mappings are merged key by key, other values replaced."""
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge_mappings(out[k], v)
        else:
            out[k] = v
    return out


# ---------------------------------------------------------------------------------------------
# Named scenarios: a formation, a world and a speed that belong together


@dataclass(frozen=True)
class _ScenarioFile:
    formation: str
    world: str
    v_max_m_s: float = 0.5
    description: str = ""


@dataclass(frozen=True, eq=False)
class Scenario:
    """A named flight: formation and world loaded, and the speed limit to fly at."""

    name: str
    formation: Formation
    world: WorldSpec
    v_max_m_s: float


def load_scenario(name_or_path: str | Path) -> Scenario:
    """``config/scenarios/NAME.yaml`` or any file ``{formation, world, v_max_m_s}``; the formation
    and world are names or paths (relative paths: from the scenario file's folder)."""
    name, file = _resolve_file(name_or_path, "scenarios")
    parsed = from_mapping(_ScenarioFile, read_yaml(file), "scenario")
    if not (math.isfinite(parsed.v_max_m_s) and parsed.v_max_m_s > 0):
        raise ConfigError(f"scenario.v_max_m_s: must be positive, got {parsed.v_max_m_s}")

    def rel(ref: str) -> str | Path:
        p = Path(ref)
        return file.parent / p if (p.suffix and not p.is_absolute()) else ref

    return Scenario(
        name=name,
        formation=load_formation(rel(parsed.formation)),
        world=load_world_spec(rel(parsed.world)),
        v_max_m_s=parsed.v_max_m_s,
    )


def world_file(
    world: World, spec: WorldSpec, starts: np.ndarray, goals: np.ndarray, description: str = ""
) -> dict[str, Any]:
    """A built world as an explicit world file (the mapping ``load_world_spec`` reads): every
    obstacle listed, starts and goals per drone, so any tool can fly exactly this world."""

    def rows(a: np.ndarray) -> list[list[float]]:
        return [[round(float(v), 6) for v in r] for r in a]

    return {
        "description": description or spec.description,
        "cylinders": rows(world.cylinders),
        "rings": [
            {
                "center": [round(float(v), 6) for v in r[:3]],
                "yaw": round(float(r[3]), 6),
                "radius_horizontal": round(float(r[4]), 6),
                "radius_vertical": round(float(r[5]), 6),
                "tube_radius": round(float(r[6]), 6),
            }
            for r in world.rings
        ],
        "boxes": rows(world.boxes),
        "ground_z": world.ground_z,
        "cluttered_x": [float(v) for v in spec.cluttered_x],
        "start_center": [float(v) for v in spec.start_center],
        "goal_center": [float(v) for v in spec.goal_center],
        "starts": rows(starts),
        "goals": rows(goals),
    }
