"""Typed parameter sets.

Every step's parameters live in one dataclass in the library, with the paper's values as defaults.
The pipeline config overrides them; :func:`from_mapping` refuses unknown keys and wrong types with a
message that names the offending key.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

import yaml

from .errors import ConfigError

T = TypeVar("T")


def _check_type(value: Any, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is Any:
        return value
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        errors = []
        for arg in args:
            try:
                return _check_type(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: {value!r} matches none of {annotation}.")
    if annotation is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected null, got {value!r}.")
    if origin is typing.Literal:
        if value in args:
            return value
        raise ConfigError(f"{where}: {value!r} is not one of {list(args)}.")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}.")
        inner = args[0] if args else Any
        items = [_check_type(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}.")
        return dict(value)
    if dataclasses.is_dataclass(annotation):
        return from_mapping(annotation, value, where)
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}.")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}.")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}.")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}.")
        return value
    return value


def from_mapping(cls: type[T], values: Mapping[str, Any] | None, where: str = "params") -> T:
    """Build dataclass ``cls`` from ``values``, refusing unknown keys and wrong types."""
    if values is None:
        return cls()
    if not isinstance(values, Mapping):
        raise ConfigError(f"{where}: expected a mapping of parameters, got {values!r}.")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ConfigError(
            f"{where}: unknown parameter(s) {unknown}; known parameters are {sorted(fields)}."
        )
    kwargs = {k: _check_type(v, hints[k], f"{where}.{k}") for k, v in values.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        text = str(exc)
        raise ConfigError(f"{where}: {text}" + ("" if text.endswith((".", "?")) else ".")) from exc


def yaml_problem(exc: Exception) -> str:
    """A YAML parse error on one line: what is wrong and where (PyYAML's own text spans several lines)."""
    problem = getattr(exc, "problem", None) or str(exc)
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return " ".join(f"{problem}{where}".split())


def load_params_arg(text: str | None) -> dict:
    """Parse a ``--params`` CLI value: inline JSON/YAML, or ``@path`` to a JSON/YAML file."""
    if not text:
        return {}
    source = "--params"
    if text.startswith("@"):
        path = Path(text[1:])
        if not path.is_file():
            raise ConfigError(f"{path}: parameter file does not exist.")
        source = str(path)
        text = path.read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: not valid JSON/YAML ({yaml_problem(exc)}); "
                          f"check the brackets and quotes.") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of parameters, got {type(data).__name__}.")
    return data


def to_dict(params: Any) -> dict:
    """The dataclass as a plain dict (saved beside outputs as the resolved config)."""
    return json.loads(json.dumps(dataclasses.asdict(params)))


def check_ranges(params: Any, unit: tuple[str, ...] = (), nonnegative: tuple[str, ...] = (),
                 at_least: Mapping[str, float] | None = None) -> None:
    """Refuse out-of-range fields of a parameter dataclass (``ValueError`` naming the field): ``unit``
    fields must lie in [0, 1], ``nonnegative`` ones be >= 0, and ``at_least`` maps a field to its
    smallest allowed value."""
    for name in unit:
        value = getattr(params, name)
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {value}")
    for name in nonnegative:
        if getattr(params, name) < 0:
            raise ValueError(f"{name} must be >= 0, got {getattr(params, name)}")
    for name, low in (at_least or {}).items():
        if getattr(params, name) < low:
            raise ValueError(f"{name} must be >= {low:g}, got {getattr(params, name)}")
