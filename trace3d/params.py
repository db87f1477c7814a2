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
        params = cls(**kwargs)
        check_ranges(params)
        return params
    except (TypeError, ValueError) as exc:
        text = str(exc)
        raise ConfigError(f"{where}: {text}" + ("" if text.endswith((".", "?")) else ".")) from exc


def yaml_problem(exc: Exception) -> str:
    """A YAML parse error on one line: what is wrong and where (PyYAML's own text spans several lines)."""
    problem = getattr(exc, "problem", None) or str(exc)
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return " ".join(f"{problem}{where}".split())


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing a key given twice in one mapping (it would keep the last silently),
    as the workflow refuses one in a config file (rules/common.smk)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} appears twice in one mapping; keep one", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


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
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as exc:
        if "appears twice" in str(getattr(exc, "problem", "")):
            raise ConfigError(f"{source}: {yaml_problem(exc)}.") from exc
        raise ConfigError(f"{source}: not valid JSON/YAML ({yaml_problem(exc)}); check the brackets and "
                          f"quotes.") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of parameters, got {type(data).__name__}.")
    return data


def to_dict(params: Any) -> dict:
    """The dataclass as a plain dict (saved beside outputs as the resolved config)."""
    return json.loads(json.dumps(dataclasses.asdict(params)))


# ----------------------------------------------------------------------------------------------
# ranges: declared once per field, checked here and written into the config schema (trace3d.tooling.schema)
# ----------------------------------------------------------------------------------------------
#
# A parameter dataclass declares the range of each numeric field in ``RANGES: ClassVar[dict]``: field ->
# ``">= 0"``, ``"> 0"``, ``"<= 1"``, ``"< 1"``, an interval ``"[0, 1]"``, ``"(0, 1]"``, ``"[0, 1)"``,
# ``"(0, 1)"``, or alternatives joined by ``|`` (``"0 | >= 2"``: 0, or 2 and more); a list field's range
# holds for each item, and null (an optional field left to its preset) is always allowed.
# :func:`from_mapping` refuses a value outside it (the step's one sentence) and :mod:`trace3d.tooling.schema`
# writes it as JSON-schema bounds (the dry run's refusal), so the two cannot disagree.  Checks that
# relate two fields (``initial_sh_degree <= sh_degree``) stay in the dataclass's ``__post_init__``.
# A dataclass whose file is not this project's to change here declares its ranges in
# :data:`DECLARED_RANGES` (by ``module:Class``), with the same effect.

DECLARED_RANGES: dict[str, dict[str, str]] = {
    "trace3d.tracing.merge:MergeParams": {
        "threshold": "[0, 1]", "association_share": "(0, 1)", "min_view_share": "[0, 1)", "mask_weight": "[0, 1]",
        "min_gaussians": ">= 0", "min_views": ">= 0", "min_gaussian_views": ">= 0"},
    "trace3d.segment:SegmentParams": {
        "neighbours": ">= 1", "feature_threshold": "> 0", "samples": ">= 2", "min_share": "(0, 1)",
        "min_size": "[0, 1)", "flat_ratio": "(0, 1)", "stuff_size": "(0, 1]", "seed": ">= 0",
        "min_gaussians": ">= 1", "min_pixels": ">= 1", "turntable_views": ">= 1", "turntable_size": ">= 8"},
    "trace3d.masks.geometry:GeometryParams": {
        "superpixel_scale": "> 0", "depth_edge": "> 0", "crease_cut": "> 0", "near": "> 0", "sigma": ">= 0",
        "colour_weight": ">= 0", "depth_weight": ">= 0", "concave_weight": ">= 0", "convex_weight": ">= 0",
        "normal_smooth": ">= 0", "crease_reach": ">= 0", "depth_reach": ">= 0", "colour_sigma": ">= 0",
        "plane_tolerance": ">= 0", "plane_weight": ">= 0", "plane_discount": ">= 0", "max_planes": ">= 0",
        "plane_iterations": ">= 0", "small_area": "[0, 1)", "min_area": "[0, 1)", "min_alpha": "[0, 1)",
        "plane_min_share": "[0, 1)", "plane_member": "[0, 1)", "max_area": "(0, 1]", "reference_pixels": ">= 1",
        "finest_level": ">= 0"},
    "trace3d.lifting.contrastive:ContrastiveParams": {
        "dim": ">= 1", "iterations": ">= 1", "pixels": ">= 2", "pool_pixels": ">= 2", "lr": "> 0",
        "temperature": "> 0", "temperature_pos": "> 0", "temperature_neg": "> 0", "seed": ">= 0",
        "undecided_weight": "[0, 1]", "coarse_depth": ">= 0"},
}


def _bound(text: str) -> dict:
    """One alternative of a range as JSON-schema keywords."""
    text = text.strip()
    for op, key in ((">=", "minimum"), ("<=", "maximum"), (">", "exclusiveMinimum"), ("<", "exclusiveMaximum")):
        if text.startswith(op):
            return {key: _number(text[len(op):])}
    if text[:1] in "[(" and text[-1:] in "])":
        low, high = (part.strip() for part in text[1:-1].split(","))
        return {("minimum" if text[0] == "[" else "exclusiveMinimum"): _number(low),
                ("maximum" if text[-1] == "]" else "exclusiveMaximum"): _number(high)}
    return {"const": _number(text)}


def _number(text: str) -> int | float:
    value = float(text)
    return int(value) if value.is_integer() and "." not in text else value


def range_schema(spec: str) -> dict:
    """The JSON-schema keywords of a declared range (``"(0, 1]"`` -> exclusiveMinimum 0, maximum 1)."""
    alternatives = [_bound(part) for part in spec.split("|")]
    return alternatives[0] if len(alternatives) == 1 else {"anyOf": alternatives}


def _inside(value: float, bound: dict) -> bool:
    checks = {"minimum": lambda b: value >= b, "maximum": lambda b: value <= b,
              "exclusiveMinimum": lambda b: value > b, "exclusiveMaximum": lambda b: value < b,
              "const": lambda b: value == b}
    return all(checks[key](b) for key, b in bound.items())


def declared_ranges(cls: type) -> dict[str, str]:
    """Field -> declared range of the parameter dataclass ``cls`` (its ``RANGES`` and :data:`DECLARED_RANGES`)."""
    out = dict(DECLARED_RANGES.get(f"{cls.__module__}:{cls.__name__}", {}))
    out.update(getattr(cls, "RANGES", {}) or {})
    return out


def check_ranges(params: Any) -> None:
    """Refuse a field of the parameter dataclass ``params`` outside its declared range (``ValueError``
    naming the field, the range and the value)."""
    for name, spec in declared_ranges(type(params)).items():
        value = getattr(params, name)
        items = value if isinstance(value, (list, tuple)) else [value]
        for item in items:
            if item is None or isinstance(item, bool) or not isinstance(item, (int, float)):
                continue
            schema = range_schema(spec)
            if not any(_inside(item, bound) for bound in schema.get("anyOf", [schema])):
                shown = " or ".join(part.strip() if part.strip()[:1] in "[(<>" else f"= {part.strip()}"
                                    for part in spec.split("|"))
                shown = shown if shown[:1] in "<>=" else f"in {shown}"
                raise ValueError(f"{name} must be {shown}, got {item}")
