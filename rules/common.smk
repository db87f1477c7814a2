# Shared helpers: config validation, per-scene parameter merging, code-version hashes.
import hashlib
import json
import os
import shlex
from pathlib import Path

from snakemake.utils import validate


validate(config, schema="../workflow/schemas/config.schema.yaml")

RESULTS = config.get("results", "results")
SCENES = sorted(config["scenes"])
ENV = "../workflow/envs/trace3d.yaml"
PACKAGE = Path(workflow.basedir) / "trace3d"


wildcard_constraints:
    scene="|".join(SCENES),


def deep_merge(base, override):
    """Mapping ``override`` merged over ``base`` key by key (nested mappings merged too)."""
    out = dict(base)
    for key, value in (override or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def scene_config(scene):
    return config["scenes"][scene]


def step_params(scene, step):
    """The parameter mapping of ``step`` for ``scene``: defaults, then the scene's own entries."""
    merged = deep_merge(config.get("defaults", {}).get(step, {}), scene_config(scene).get(step, {}))
    return json.dumps(merged, sort_keys=True)


def code_version(*parts):
    """Hash of the library files a step runs, so that Snakemake reruns the step when they change."""
    digest = hashlib.sha1()
    for part in parts:
        path = PACKAGE / part
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for f in files:
            if f.is_file():
                digest.update(f.relative_to(PACKAGE).as_posix().encode())
                digest.update(f.read_bytes())
    return digest.hexdigest()[:12]


def scene_kind_args(wildcards):
    """The `trace3d scene` arguments for a scene: its kind, data source and parameters."""
    cfg = scene_config(wildcards.scene)
    kind = cfg["kind"]
    if kind == "synthetic":
        params = shlex.quote(step_params(wildcards.scene, "synthetic"))
        return f"synthetic --params {params}"
    params = shlex.quote(step_params(wildcards.scene, "importer"))
    source = os.path.join(config.get("data_root", "."), cfg["source"])
    return f"{kind} --source {shlex.quote(os.path.normpath(source))} --params {params}"


def mask_args(wildcards):
    """The `trace3d masks` arguments: the mask source and that source's parameters."""
    merged = json.loads(step_params(wildcards.scene, "masks"))
    source = merged.get("source", "simulated")
    params = shlex.quote(json.dumps(merged.get(source, {}), sort_keys=True))
    return f"--source {source} --params {params}"


def quoted_params(step):
    """A params function returning the step's parameters as one shell-quoted JSON word."""

    def inner(wildcards):
        return shlex.quote(step_params(wildcards.scene, step))

    return inner
