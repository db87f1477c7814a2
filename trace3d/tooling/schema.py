"""The step parameters' one home, seen from outside: JSON schema and help text from the dataclasses.

Every step's parameters are a typed dataclass in the library (:mod:`trace3d.params`). This module
reads those dataclasses (field names, types, defaults and the one line of meaning their source gives
each field) and derives from them

- the JSON schema of the config's step sections, ``workflow/schemas/steps.schema.yaml`` (written
  as JSON, which is YAML too, for Snakemake's fast path: :func:`schema_text`), which
  ``config.schema.yaml`` refers to: every step mapping is closed (``additionalProperties: false``),
  so a misspelled key fails ``snakemake -n`` before anything runs, with the known keys listed;
- the parameter list that ``trace3d <step> --help`` prints.

``python -m trace3d.tooling.schema`` rewrites the schema file; ``tests/cli/test_bad_inputs.py`` fails when the
file and the dataclasses disagree (a field added, renamed or removed without regenerating it).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import json
import sys
import textwrap
import tokenize
import typing
from pathlib import Path
from typing import Any, Literal

SCHEMA_PATH = Path(__file__).resolve().parents[2] / "workflow" / "schemas" / "steps.schema.yaml"

def _registry() -> dict[str, list[type]]:
    """Config section -> the dataclasses whose fields it may hold (several: any one's keys), from the
    step registry (:data:`trace3d.steps.STEPS`; the masks' sources are :func:`mask_sources`)."""
    from ..steps import STEPS, load_class

    return {section: [load_class(ref) for ref in refs] for s in STEPS for section, refs in s.params.items()}


def mask_sources() -> dict[str, list[type]]:
    """Mask source name -> its parameter dataclasses (from :data:`trace3d.masks.SOURCES`; several where a
    ``model`` key picks the dataclass, as ``trace3d.masks.SIMULATED_MODELS`` does for the simulated source)."""
    from .. import masks

    out = {}
    for source in masks.SOURCES:
        classes = [type(masks.parse_params(source, None))]
        models = getattr(masks, f"{source.upper()}_MODELS", ())
        for model in models:
            cls = type(masks.parse_params(source, {"model": model}))
            if cls not in classes:
                classes.append(cls)
        out[source] = classes
    return out


def lift_classes() -> list[type]:
    from ..steps import LIFT_METHODS, load_class

    return [load_class(ref) for ref in LIFT_METHODS.values()]


def step_classes(step: str) -> list[tuple[str, type]]:
    """(when it applies, dataclass) of a CLI step (for ``--help``); empty where the step takes no parameters."""
    from ..steps import IMPORTERS, LIFT_METHODS, STEPS, load_class

    if step == "masks":
        return [(f"--source {source}", cls) for source, classes in mask_sources().items() for cls in classes]
    if step == "scene":
        kinds: dict[str, list[str]] = {}
        for kind, ref in IMPORTERS.items():
            kinds.setdefault(ref, []).append(kind)
        synthetic = [ref for s in STEPS if s.command == "scene" for ref in s.params["synthetic"]]
        return [("synthetic", load_class(synthetic[0]))] + [(", ".join(k), load_class(ref)) for ref, k in kinds.items()]
    if step == "lift":
        return [(f"method: {method}", load_class(ref)) for method, ref in LIFT_METHODS.items()]
    return [("", cls) for s in STEPS if s.command == step for refs in s.params.values() for ref in refs
            for cls in [load_class(ref)]]


def _nested() -> dict[tuple[type, str], type]:
    """Mapping fields that hold another dataclass's overrides."""
    from ..lifting.contrastive import ContrastiveParams
    from ..lifting.query import QueryParams
    from ..tracing.refine import RefineParams
    from ..training.params import TrainParams

    return {(RefineParams, "train"): TrainParams, (ContrastiveParams, "query"): QueryParams}


# Keys the workflow sets itself: refused in the config, where they would be overwritten.
WORKFLOW_SET = {"lift": ("method",)}


# ----------------------------------------------------------------------------------------------
# one line of meaning per field, from the dataclass's source
# ----------------------------------------------------------------------------------------------


def _comments(source: str) -> dict[int, str]:
    """Line number (1-based) -> the text of the comment on that line."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string.lstrip("#").strip()
    return out


def _first_sentence(text: str, limit: int = 140) -> str:
    """The first sentence of ``text`` on one line, cut at a word near ``limit`` characters."""
    text = " ".join(text.split())
    for i in range(len(text) - 1):
        if text[i] == "." and text[i + 1] == " " and text[:i].count("(") == text[:i].count(")"):
            text = text[: i + 1]
            break
    if len(text) > limit:
        text = text[:limit].rsplit(" ", 1)[0] + " ..."
    return text


def field_meanings(cls: type) -> dict[str, str]:
    """Field name -> one line of meaning: the class docstring's ``name: ...`` entry, else the comment on
    the field's line, else the comment block just above it; empty when the source says nothing."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    lines = source.splitlines()
    comments = _comments(source)
    doc = inspect.getdoc(cls) or ""
    documented: dict[str, str] = {}
    current = None
    for line in doc.splitlines():
        head = line.split(":", 1)
        if len(head) == 2 and head[0].strip().isidentifier() and not line.startswith(" "):
            current = head[0].strip()
            documented[current] = head[1].strip()
        elif current and line.startswith(" ") and line.strip():
            documented[current] += " " + line.strip()
        else:
            current = None
    out = {}
    tree = ast.parse(source)
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for node in body:
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        name = node.target.id
        if name in documented:
            out[name] = _first_sentence(documented[name])
            continue
        if node.lineno in comments:
            out[name] = _first_sentence(comments[node.lineno])
            continue
        block = []
        row = node.lineno - 1
        while row >= 1 and row in comments and lines[row - 1].strip().startswith("#"):
            text = comments[row]
            if text.startswith("---") or text.startswith("==="):
                break
            block.insert(0, text)
            row -= 1
        out[name] = _first_sentence(" ".join(block)) if block else ""
    return out


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return dataclasses.MISSING


def _type_text(annotation: Any) -> str:
    text = str(annotation) if not isinstance(annotation, type) else annotation.__name__
    return text.replace("typing.", "")


def describe(cls: type) -> list[dict]:
    """One row per field: name, type, default (JSON-able; None for null) and meaning."""
    hints = typing.get_type_hints(cls)
    meanings = field_meanings(cls)
    rows = []
    for f in dataclasses.fields(cls):
        default = _default(f)
        rows.append({"name": f.name, "type": _type_text(hints[f.name]),
                     "default": None if default is dataclasses.MISSING else json.loads(json.dumps(default)),
                     "meaning": meanings.get(f.name, "")})
    return rows


def help_text(step: str) -> str:
    """The parameter list of ``trace3d <step> --help`` (empty when the step takes none)."""
    parts = []
    for when, cls in step_classes(step):
        rows = describe(cls)
        if not rows:
            continue
        parts.append(f"{cls.__name__}" + (f" ({when})" if when else "") + ":")
        for row in rows:
            default = json.dumps(row["default"])
            line = f"  {row['name']} = {default}"
            if row["meaning"]:
                line += f"  -- {row['meaning']}"
            parts.append(line)
    return "\n".join(parts)


# ----------------------------------------------------------------------------------------------
# JSON schema
# ----------------------------------------------------------------------------------------------


def type_schema(annotation: Any) -> dict:
    """The JSON schema of one field's annotation (the types :func:`trace3d.params.from_mapping` accepts)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is Any:
        return {}
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        options = [a for a in args if a is not type(None)]
        nullable = len(options) < len(args)
        if len(options) == 1:
            inner = type_schema(options[0])
        else:
            inner = {"anyOf": [type_schema(a) for a in options]}
        if not nullable:
            return inner
        if "enum" in inner:
            return {"enum": list(inner["enum"]) + [None]}
        if isinstance(inner.get("type"), str) and len(inner) == 1:
            return {"type": [inner["type"], "null"]}
        return {"anyOf": [inner, {"type": "null"}]}
    if origin is Literal:
        return {"enum": list(args)}
    if origin in (list, tuple):
        if origin is tuple and args and args[-1] is not Ellipsis:
            items = {"prefixItems": [type_schema(a) for a in args], "minItems": len(args), "maxItems": len(args)}
            return {"type": "array", **items}
        return {"type": "array", "items": type_schema(args[0]) if args else {}}
    if origin is dict or annotation is dict:
        return {"type": "object"}
    if dataclasses.is_dataclass(annotation):
        return dataclass_schema([annotation])
    simple = {float: "number", int: "integer", bool: "boolean", str: "string"}
    if annotation in simple:
        return {"type": simple[annotation]}
    return {}


def _bounded(schema: dict, bounds: dict) -> dict:
    """``schema`` with a number's ``bounds`` on its numbers and on each item of its lists, through ``anyOf``
    alternatives (``int | list[int] | None``: the integer and every item of the list)."""
    if "anyOf" in schema:
        return {**schema, "anyOf": [_bounded(option, bounds) for option in schema["anyOf"]]}
    kinds = schema.get("type")
    kinds = [kinds] if isinstance(kinds, str) else list(kinds or ())
    if "array" in kinds:
        return {**schema, "items": {**schema.get("items", {}), **bounds}}
    if "integer" in kinds or "number" in kinds:
        return {**schema, **bounds}
    return schema


def dataclass_schema(classes: list[type], drop: tuple[str, ...] = ()) -> dict:
    """A closed object schema holding the fields of ``classes`` (a key of any one of them is allowed).

    No property carries a ``default``: a value the user did not write is the library's to choose
    (Snakemake's validate would write it into the config, and the rules would pass it on).

    ``propertyNames`` lists the known keys, so that a misspelled key's error message names them all.
    """
    from ..params import declared_ranges, range_schema

    nested = _nested()
    collected: dict[str, list[tuple[dict, str]]] = {}
    for cls in classes:
        hints = typing.get_type_hints(cls)
        meanings = field_meanings(cls)
        ranges = declared_ranges(cls)
        for f in dataclasses.fields(cls):
            if f.name in drop:
                continue
            if (cls, f.name) in nested:
                schema = dataclass_schema([nested[(cls, f.name)]])
            else:
                schema = type_schema(hints[f.name])
            if f.name in ranges:  # the range check_ranges applies (to each item of a list)
                schema = _bounded(schema, range_schema(ranges[f.name]))
            default = _default(f)
            text = meanings.get(f.name) or ""
            shown = "null (preset)" if default is None else json.dumps(default)
            collected.setdefault(f.name, []).append(
                (schema, f"{cls.__name__}.{f.name}, default {shown}" + (f": {text}" if text else "")))
    out = {}
    for name, entries in collected.items():
        schemas = []
        for schema, _ in entries:
            if schema not in schemas:
                schemas.append(schema)
        body = dict(schemas[0]) if len(schemas) == 1 else {"anyOf": schemas}
        body["description"] = "; ".join(text for _, text in entries)
        out[name] = body
    names = sorted(out)
    return {"type": "object", "propertyNames": {"enum": names}, "additionalProperties": False, "properties": out}


def step_schemas() -> dict:
    """The ``$defs`` of ``steps.schema.yaml``: one closed object schema per config step section."""
    defs = {}
    for step, classes in _registry().items():
        defs[step] = dataclass_schema(classes, drop=WORKFLOW_SET.get(step, ()))
        defs[step]["description"] = (f"parameters of the {step} step ({', '.join(c.__name__ for c in classes)}); "
                                     f"a key not listed here is refused")
    sources = mask_sources()
    masks = {"source": {"enum": list(sources), "description": "where the 2D masks come from"}}
    for source, classes in sources.items():
        masks[source] = dataclass_schema(classes)
        masks[source]["description"] = (f"parameters of the {source} mask source "
                                        f"({', '.join(c.__name__ for c in classes)})")
    defs["masks"] = {"type": "object", "description": "the 2D masks: the source and each source's parameters",
                     "propertyNames": {"enum": sorted(masks)}, "additionalProperties": False, "properties": masks}
    from ..steps import SCENE_KINDS, Variant

    defs["scene_kind"] = {"enum": list(SCENE_KINDS), "description": "how the canonical scene is made (generated, or "
                          "imported from a data set folder, a folder of photos or a transforms.json capture)"}
    defs["imported_kind"] = {"enum": [k for k in SCENE_KINDS if k != "synthetic"],
                             "description": "the scene kinds read from a `source` folder or file"}
    defs["variant"] = dataclass_schema([Variant])
    defs["variant"]["description"] = ("a variant: the settings of the paper's stages (trace3d.steps.Variant; a setting "
                                      "left out takes its default)")
    return defs


def schema_document() -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "description": "GENERATED by `python -m trace3d.tooling.schema` from the library's parameter dataclasses; "
                           "do not edit by hand (tests/cli/test_bad_inputs.py checks it is current).",
            "$defs": step_schemas()}


def schema_text() -> str:
    """The schema file's text: JSON (a subset of YAML, so YAML readers load it too).  Snakemake reads a
    schema file as JSON first and only then through its YAML templating (yte), which took ~0.4 s of CPU
    per read of this 60 kB file; a config validation reads it once per ``$ref`` (a dozen), so as YAML it
    cost ~5 s of CPU at every ``snakemake`` start, as JSON 0.1 s."""
    return json.dumps(schema_document(), indent=1, ensure_ascii=False) + "\n"


# ----------------------------------------------------------------------------------------------
# `trace3d describe --json`
# ----------------------------------------------------------------------------------------------


def _rows(ref: str) -> list[dict]:
    from ..steps import load_class

    return describe(load_class(ref))


def registry_document() -> dict:
    """The registry as data (imports every step's parameter dataclasses): steps with their flags,
    entry functions, rules and parameters (name, type, default, meaning), the lifting methods with the
    keys that apply to each, the variant settings with their defaults."""
    from ..steps import LIFT_METHODS, STEPS, Variant, default_inconsistency, lift_keys, variant_defaults

    steps = {}
    for s in STEPS:
        params = {section: {ref: _rows(ref) for ref in refs} for section, refs in s.params.items()}
        if s.command == "masks":
            params = {f"masks.{source}": {f"{c.__module__}:{c.__name__}": _rows(f"{c.__module__}:{c.__name__}")
                                          for c in classes} for source, classes in mask_sources().items()}
        steps[s.command] = {
            "help": s.help.replace("%%", "%"), "module": s.module, "entry": list(s.entry), "rules": list(s.rules),
            "kernels": s.kernels, "arguments": [{"flags": list(a.flags), **{k: v for k, v in a.kwargs.items()
                                                                           if k in ("required", "help", "nargs",
                                                                                    "choices", "default")}}
                                                for a in s.args],
            "params": params,
        }
    return {
        "steps": steps,
        "lift_methods": {m: {"params": ref, "keys": list(lift_keys()[m])} for m, ref in LIFT_METHODS.items()},
        "variant": {"defaults": variant_defaults(),
                    "keys": [f.name for f in dataclasses.fields(Variant)]},
        "simulated_default_inconsistency": default_inconsistency(),
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m trace3d.tooling.schema [PATH]``: write the steps' schema (default: the workflow's)."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m trace3d.tooling.schema",
        description="Write the steps' parameter schema, generated from the library's parameter dataclasses.")
    parser.add_argument("path", nargs="?", type=Path, default=SCHEMA_PATH,
                        help=f"the file to write (default: {SCHEMA_PATH.relative_to(SCHEMA_PATH.parents[2])})")
    target = parser.parse_args(sys.argv[1:] if argv is None else argv).path
    target.write_text(schema_text())
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
