"""Configuration, loaded once at the edge into frozen, validated objects.

Everything the numerical core needs arrives as plain values: planner parameters
(``PlannerParams``), formation templates (``Formation``) and world descriptions (``WorldSpec``).
Files are YAML (or JSON, which YAML reads too). Every unknown key and every wrongly typed value is
a ``ConfigError`` that names the key path, e.g. ``planner.w_obstacle: expected a number, got 'x'``.
``from_mapping`` builds any frozen dataclass this way (pydantic checks the values against the
dataclass's type hints; the dataclasses themselves stay plain, so the core never imports pydantic).

Named files live under ``config_dir()``: ``formations/NAME.yaml``, ``worlds/NAME.yaml`` and
``planner.yaml``. ``SWARM_CONFIG_DIR`` overrides the directory.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import datetime
import enum
import functools
import json
import math
import os
import re
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar, Union

import numpy as np
import pydantic
import yaml
from pydantic import ConfigDict

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


# Bounds that keep a file from asking for what no flight can use (and no loader should build).
MAX_COORDINATE_M = 10_000.0
"""No template point, start, goal or centre farther than this from the origin (10 km)."""
MAX_FORMATION_POINTS = 64
"""Largest formation (the swarm bus carries at most this many points)."""
MAX_GENERATED_OBSTACLES = 100_000
MAX_SPACING_M = 1_000.0


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e4`` / ``5E-3`` as floats (YAML 1.1 wants a dot), and
    refuses aliases: a few nested aliases expand into gigabytes (a "billion laughs" file took
    minutes to load) and a self-referencing one builds a recursive structure."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                f"aliases (*{event.anchor}) are not accepted in configuration files",
                event.start_mark,
            )
        return super().compose_node(parent, index)


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
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not UTF-8 text (byte {e.start})") from e
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
# Generic mapping -> frozen dataclass, validated by pydantic
#
# The config dataclasses stay plain frozen stdlib dataclasses (the numerical core does not import
# pydantic); pydantic validates them from their type hints. The mapping is handed to pydantic as
# JSON text in strict mode, which gives exactly the rules a config file should follow on every
# Python version: integers are accepted for floats but booleans and strings are not numbers,
# lists become tuples, objects become dataclasses or dicts, nothing is coerced from a string.
# pydantic's errors (a location and a type code) are then worded here, with the dotted key path.

_PYDANTIC_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False)
_WRAPPER_FIELD = "value"
_MAX_ENUM_PASSES = 64


def _where(path: str) -> str:
    return path if path else "<root>"


def _describe(value: Any) -> str:
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


@functools.cache
def _validator(cls: type) -> type[pydantic.BaseModel]:
    """A pydantic model with the single field ``value: cls`` (the wrapper carries the config that
    stdlib dataclasses cannot carry themselves: unknown keys are errors, floats are finite)."""
    return pydantic.create_model(
        f"_{cls.__name__}Validator",
        __config__=_PYDANTIC_CONFIG,
        value=(cls, ...),
    )


def _plain(value: Any, path: str) -> Any:
    """``value`` as JSON-compatible data: mappings -> dicts with string keys, sequences -> lists,
    numpy scalars and arrays -> Python numbers and lists, enum members -> their values, dataclass
    instances -> dicts of their fields."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, enum.Enum):
        return _plain(value.value, path)
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{path}.{k}" if path else str(k)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), path)
    if isinstance(value, np.generic):
        return _plain(value.item(), path)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: _plain(getattr(value, f.name), f"{path}.{f.name}" if path else f.name)
            for f in dataclasses.fields(value)
            if f.init
        }
    if isinstance(value, (datetime.date, datetime.time)):  # YAML reads unquoted timestamps
        return value.isoformat()
    raise ConfigError(f"{_where(path)}: unsupported value {_describe(value)}")


def _field_default(f: dataclasses.Field, base: Any) -> Any:
    if base is not None:
        return getattr(base, f.name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _fill(cls: type, data: dict[str, Any], base: Any, path: str) -> dict[str, Any]:
    """``data`` completed from ``base`` (keys not given keep its values) and, for a nested
    dataclass given as a mapping, from that field's current value (partial override)."""
    out = dict(data)
    hints: dict[str, Any] | None = None
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        sub = f"{path}.{f.name}" if path else f.name
        if f.name in data:
            value = data[f.name]
            default = _field_default(f, base) if isinstance(value, dict) else None
            if dataclasses.is_dataclass(default) and not isinstance(default, type):
                # only where the field holds one dataclass type (``A`` or ``A | None``): the
                # mapping of ``A | B`` may be meant for ``B``
                hints = hints if hints is not None else typing.get_type_hints(cls)
                if _members(hints[f.name]) == [type(default)]:
                    out[f.name] = _fill(type(default), value, default, sub)
        elif base is not None:
            out[f.name] = _plain(getattr(base, f.name), sub)
    return out


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) is Union or isinstance(tp, types.UnionType)


def _members(tp: Any) -> list[Any]:
    """The types a union accepts besides None (``[tp]`` for anything else)."""
    if _is_union(tp):
        return [a for a in typing.get_args(tp) if a is not type(None)]
    return [tp]


def _tag(tp: Any) -> str:
    """How pydantic names a union member in an error location (without spaces)."""
    if tp is Ellipsis:
        return "..."
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return f"enum[{tp.__name__}]"
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return f"literal[{','.join(repr(a) for a in args)}]"
    if origin is not None and args:
        name = getattr(origin, "__name__", str(origin))
        return f"{name}[{','.join(_tag(a) for a in args)}]"
    return str(getattr(tp, "__name__", tp)).replace(" ", "")


@dataclass(frozen=True)
class _Located:
    """What a pydantic error location points at: ``tp`` the type there (None if unknown), ``keys``
    the location without union tags (it indexes the data), ``union_at`` where the first union
    with several accepted types starts in ``keys`` (None if none), ``member`` its tag."""

    tp: Any
    keys: tuple[str | int, ...]
    union_at: int | None = None
    member: str = ""


def _locate(cls: type, loc: tuple[str | int, ...]) -> _Located:
    """Follow a pydantic error location through the type hints of ``cls``."""
    tp: Any = cls
    keys: list[str | int] = []
    union_at: int | None = None
    member = ""
    for key in loc:
        options = _members(tp)
        if len(options) > 1:  # a union: pydantic names the member it tried
            if union_at is None:
                union_at, member = len(keys), str(key)
            match = [m for m in options if _tag(m) == str(key).replace(" ", "")]
            tp = match[0] if len(match) == 1 else None
            if tp is None:
                return _Located(None, tuple(keys), union_at, member)
            continue
        tp = options[0]
        keys.append(key)
        origin, args = typing.get_origin(tp), typing.get_args(tp)
        if dataclasses.is_dataclass(tp) and isinstance(tp, type) and isinstance(key, str):
            tp = typing.get_type_hints(tp).get(key)
        elif origin is tuple and isinstance(key, int) and args:
            if len(args) == 2 and args[1] is Ellipsis:
                tp = args[0]
            else:
                tp = args[key] if key < len(args) else None
        elif origin in (list, collections.abc.Sequence) and isinstance(key, int) and args:
            tp = args[0]
        elif origin in (dict, collections.abc.Mapping) and len(args) == 2:
            tp = args[1]
        else:
            tp = None
        if tp is None:
            return _Located(None, tuple(keys), union_at, member)
    options = _members(tp)
    return _Located(options[0] if len(options) == 1 else tp, tuple(keys), union_at, member)


def _dotted(path: str, keys: tuple[str | int, ...]) -> str:
    out = path
    for k in keys:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else str(k))
    return out


def _expected(kind: str, tp: Any, error: Any) -> str | None:
    """``expected ...`` for one pydantic error type (None: not a type error)."""
    ctx = error.get("ctx") or {}
    if kind in ("float_type", "float_parsing"):
        return "a number"
    if kind == "finite_number":
        return "a finite number"
    if kind in ("int_type", "int_parsing", "int_from_float"):
        return "an integer"
    if kind in ("bool_type", "bool_parsing"):
        return "true or false"
    if kind in ("string_type", "string_unicode"):
        return "a string"
    if kind in ("tuple_type", "list_type", "set_type", "frozen_set_type"):
        return "a list"
    if kind in ("dict_type", "dataclass_type", "dataclass_args_type", "model_type"):
        return "a mapping"
    if kind == "none_required":
        return "null"
    if kind == "enum":
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            return f"one of {[m.value for m in tp]}"
        return f"one of {ctx.get('expected', '?')}"
    if kind == "literal_error":
        if typing.get_origin(tp) is Literal:
            return f"one of {list(typing.get_args(tp))}"
        return f"one of {ctx.get('expected', '?')}"
    return None


def _tuple_length(tp: Any) -> int | None:
    """The fixed length of ``tuple[A, B, ...]`` (None for ``tuple[A, ...]`` or another type)."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is not tuple or not args or (len(args) == 2 and args[1] is Ellipsis):
        return None
    return len(args)


def _error_message(cls: type, error: Any, path: str) -> tuple[str, str]:
    """(dotted key path, what is wrong) for one pydantic error."""
    loc = tuple(error["loc"][1:])  # without the wrapper's field
    kind = error["type"]
    value = error.get("input")
    at = _locate(cls, loc)
    where = _dotted(path, at.keys)
    if kind == "missing" and at.keys and isinstance(at.keys[-1], int):
        # an item missing from a fixed-length tuple: say so at the list's key
        parent = _locate(cls, loc[:-1])
        n = _tuple_length(parent.tp)
        have = len(value) if isinstance(value, list) else "fewer"
        want = f"a list of {n} items" if n is not None else "more items"
        return _dotted(path, parent.keys), f"expected {want}, got {have}"
    if kind == "missing":
        return where, "required key is missing"
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        parent = _locate(cls, loc[:-1]).tp
        if dataclasses.is_dataclass(parent) and isinstance(parent, type):
            known = sorted(f.name for f in dataclasses.fields(parent) if f.init)
            return where, f"unknown key (known: {known})"
        return where, "unknown key"
    if kind in ("too_long", "too_short"):
        n = _tuple_length(at.tp)
        got = (error.get("ctx") or {}).get("actual_length")
        if n is not None:
            return where, f"expected a list of {n} items, got {got}"
    if kind in ("value_error", "assertion_error"):
        cause = (error.get("ctx") or {}).get("error")
        return _where(where), str(cause) if cause is not None else error["msg"]
    expected = _expected(kind, at.tp, error)
    if expected is not None:
        return where, f"expected {expected}, got {_describe(value)}"
    msg = str(error["msg"])
    return where, f"{msg[:1].lower()}{msg[1:]}, got {_describe(value)}"


def _config_error(cls: type, errors: list[Any], path: str) -> ConfigError:
    """One ``ConfigError`` for all of pydantic's errors, one line each, in pydantic's order.

    The errors of the members of a union are folded into one line: ``expected an integer or
    a string, got 1.5``.
    """
    lines: dict[Any, str | list[tuple[str, str, str]]] = {}
    for error in errors:
        at = _locate(cls, tuple(error["loc"][1:]))
        where, what = _error_message(cls, error, path)
        if at.union_at is None:
            lines.setdefault(("line", where, what), f"{_where(where)}: {what}")
        else:
            tried = lines.setdefault(("union", at.keys[: at.union_at]), [])
            assert isinstance(tried, list)
            tried.append((at.member, where, what))
    out = []
    for key, line in lines.items():
        if isinstance(line, list):
            out.append(_union_line(_dotted(path, key[1]), line))
        else:
            out.append(line)
    return ConfigError("\n".join(out))


def _union_line(where: str, tried: list[tuple[str, str, str]]) -> str:
    """``where: expected A or B, got V`` from the errors of each member of a union."""
    alternatives: list[str] = []
    got = ""
    for member, sub_where, what in tried:
        if sub_where == where and what.startswith("expected ") and ", got " in what:
            text, got = what[len("expected ") :].rsplit(", got ", 1)
        else:
            inner = sub_where[len(where) :].lstrip(".")
            text = f"{member} ({inner}: {what})" if inner else f"{member} ({what})"
        if text not in alternatives:
            alternatives.append(text)
    tail = f", got {got}" if got else ""
    return f"{_where(where)}: expected {' or '.join(alternatives)}{tail}"


def _enum_names_to_values(cls: type, errors: list[Any], data: Any) -> bool:
    """Where pydantic refused an enum member's name, put its value in ``data``; True if any."""
    changed = False
    for error in errors:
        if error["type"] != "enum" or not isinstance(error.get("input"), str):
            continue
        at = _locate(cls, tuple(error["loc"][1:]))
        if not (isinstance(at.tp, type) and issubclass(at.tp, enum.Enum)):
            continue
        member = at.tp.__members__.get(error["input"])
        if member is None or not at.keys:
            continue
        node = data
        for k in at.keys[:-1]:
            node = node[k]
        node[at.keys[-1]] = _plain(member.value, "")
        changed = True
    return changed


def _bools_taken_as_numbers(
    plain: Any, obj: Any, keys: tuple[str | int, ...] = ()
) -> list[tuple[tuple[str | int, ...], bool]]:
    """Where a boolean of the input became a number or an enum member in the result (pydantic
    matches ``true`` against ``IntEnum`` and ``Literal[1]``, since ``True == 1`` in Python)."""
    if isinstance(plain, bool):
        return [] if isinstance(obj, bool) else [(keys, plain)]
    out: list[tuple[tuple[str | int, ...], bool]] = []
    if isinstance(plain, dict):
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            for k, v in plain.items():
                out += _bools_taken_as_numbers(v, getattr(obj, k, None), (*keys, k))
        elif isinstance(obj, Mapping):
            for k, v in plain.items():
                out += _bools_taken_as_numbers(v, obj.get(k), (*keys, k))
    elif isinstance(plain, list) and isinstance(obj, (list, tuple)) and len(obj) == len(plain):
        for i, (v, o) in enumerate(zip(plain, obj, strict=True)):
            out += _bools_taken_as_numbers(v, o, (*keys, i))
    return out


def from_mapping(cls: type[T], data: Any, path: str = "", base: T | None = None) -> T:
    """Build the frozen dataclass ``cls`` from a mapping, validating every key and value.

    Unknown keys, missing required keys and wrongly typed values raise ``ConfigError`` whose
    message starts with the dotted key path (``path`` is the prefix, e.g. ``"planner"``), one
    line per error. Integers are accepted for float fields (never booleans or strings), lists for
    tuple fields, an enum member's value or name for an enum field; floats must be finite.
    Nested dataclasses, ``X | None``, unions, ``Literal``, tuples and ``dict[str, X]`` are
    validated (by pydantic, from the type hints). A ``ValueError`` from a dataclass's own
    ``__post_init__`` becomes a ``ConfigError`` at that dataclass's path. Keys not given keep the
    values of ``base`` if one is passed, else the field defaults; a nested dataclass given as a
    mapping is filled in over the field's value (partial override).
    """
    if not (dataclasses.is_dataclass(cls) and isinstance(cls, type)):
        raise TypeError(f"{cls!r} is not a dataclass type")
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{_where(path)}: expected a mapping, got {_describe(data)}")
    plain = _fill(cls, _plain(data, path), base, path)
    model = _validator(cls)
    for _ in range(_MAX_ENUM_PASSES):
        try:
            checked = model.model_validate_json(json.dumps({_WRAPPER_FIELD: plain}), strict=True)
        except pydantic.ValidationError as e:
            errors = e.errors()
            if _enum_names_to_values(cls, errors, plain):
                continue
            raise _config_error(cls, errors, path) from None
        result = getattr(checked, _WRAPPER_FIELD)
        wrong = _bools_taken_as_numbers(plain, result)
        if wrong:
            lines = []
            for keys, value in wrong:
                tp = _locate(cls, keys).tp
                if isinstance(tp, type) and issubclass(tp, enum.Enum):
                    expected = _expected("enum", tp, {})
                elif typing.get_origin(tp) is Literal:
                    expected = _expected("literal_error", tp, {})
                else:
                    expected = "a number"
                lines.append(f"{_dotted(path, keys)}: expected {expected}, got {value!r}")
            raise ConfigError("\n".join(lines))
        return typing.cast(T, result)
    raise ConfigError(f"{_where(path)}: too many enum names")  # pragma: no cover


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
        if p.shape[0] > MAX_FORMATION_POINTS:
            raise ConfigError(
                f"{self.name}.points: at most {MAX_FORMATION_POINTS} points, got {p.shape[0]}"
            )
        if not np.all(np.isfinite(p)):
            raise ConfigError(f"{self.name}.points: values must be finite")
        if np.max(np.abs(p)) > MAX_COORDINATE_M:
            raise ConfigError(
                f"{self.name}.points: coordinates must be within {MAX_COORDINATE_M:.0f} m"
            )
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
        for key in ("n_cylinders", "n_rings"):
            n = getattr(self, key)
            if not 0 <= n <= MAX_GENERATED_OBSTACLES:
                raise ValueError(f"{key}: expected 0 to {MAX_GENERATED_OBSTACLES}, got {n}")
        for key in ("x_range", "y_range"):
            if max(abs(v) for v in getattr(self, key)) > MAX_COORDINATE_M:
                raise ValueError(f"{key}: must be within {MAX_COORDINATE_M:.0f} m")
        for key in ("x_range", "y_range", "diameter_range", "height_range", "ring_radius_range"):
            lo, hi = getattr(self, key)
            if hi < lo:
                raise ValueError(f"{key}: upper bound below lower bound")
        if self.diameter_range[0] <= 0.0:
            raise ValueError("diameter_range: diameters must be positive")
        for key in ("min_spacing_m", "keep_clear_m"):
            v = getattr(self, key)
            if not 0.0 <= v <= MAX_SPACING_M:
                raise ValueError(f"{key}: expected 0 to {MAX_SPACING_M:.0f} m, got {v}")


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
    override ``start_center``/``goal_center`` + formation offsets. With ``starts`` and ``goals``
    the centres may be left out: they are then the centroids of the starts and of the goals, so
    that after construction ``start_center`` and ``goal_center`` are never None.
    """

    cluttered_x: Vec2
    start_center: Vec3 | None = None
    goal_center: Vec3 | None = None
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
            if len(self.starts) == 0:
                raise ValueError("starts and goals: at least one drone")
            for key, rows in (("start_center", self.starts), ("goal_center", self.goals)):
                if getattr(self, key) is None:
                    c = np.mean(np.asarray(rows, dtype=np.float64), axis=0)
                    object.__setattr__(self, key, (float(c[0]), float(c[1]), float(c[2])))
        elif self.start_center is None or self.goal_center is None:
            raise ValueError(
                "start_center and goal_center are required unless starts and goals are given"
            )
        for key in ("start_center", "goal_center", "starts", "goals"):
            v = getattr(self, key)
            if v is not None and np.max(np.abs(np.asarray(v, dtype=np.float64))) > MAX_COORDINATE_M:
                raise ValueError(f"{key}: coordinates must be within {MAX_COORDINATE_M:.0f} m")

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
        assert self.start_center is not None and self.goal_center is not None  # __post_init__
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


def parse_overrides(texts: Iterable[str], base: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``base`` (default empty) with every ``"a.b=VALUE"`` of ``texts`` merged in, in order
    (``parse_override``, ``merge_mappings``): the ``--set`` options of the command lines."""
    out: dict[str, Any] = dict(base) if base is not None else {}
    for text in texts:
        out = merge_mappings(out, parse_override(text))
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
        "start_center": [float(v) for v in spec.start_center or starts.mean(axis=0)],
        "goal_center": [float(v) for v in spec.goal_center or goals.mean(axis=0)],
        "starts": rows(starts),
        "goals": rows(goals),
    }
