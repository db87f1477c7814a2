"""The robustness curve: object mIoU (and NVS mIoU) of several variants as the simulated masks'
inconsistency rises, on the same rooms and 2DGS fits (``rules/robustness.smk``).

Input: a spec, one entry per evaluated (room, level, variant)::

    {"runs": [{"scene": "room1", "level": 0.25, "variant": "full", "eval": "results/room1@inc0.25/full/eval"}, ...],
     "merges": [{"scene": "room1", "level": 0.25, "merge": "results/room1@inc0.25/merge-paper"}, ...]}

``merges`` (optional) adds the quality of the consistent instance maps per level (ARI, straddling before
and after merging) from each merge step's ``merge.json``. Output: ``robustness.md`` / ``.csv`` (one row
per level and variant, mean over the rooms) and a plot of the curves.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import SceneFormatError, Trace3DError
from ..io import atomic_file
from .summary import _read_json

METRICS = (("object mIoU", "extraction", "mIoU"), ("NVS mIoU", "nvs", "mIoU"), ("PSNR", "extraction", "PSNR"))


def _check_spec(spec: dict) -> None:
    runs = spec.get("runs")
    if not isinstance(runs, list) or not runs:
        raise Trace3DError("robustness spec: 'runs' must be a non-empty list of {scene, level, variant, eval}.")
    for run in runs:
        missing = [k for k in ("scene", "level", "variant", "eval") if k not in run]
        if missing:
            raise Trace3DError(f"robustness spec: a run lacks {', '.join(missing)}: {run}.")


def collect_runs(spec: dict) -> pd.DataFrame:
    """One row per run: scene, level, variant and the metrics of its ``metrics.json``."""
    _check_spec(spec)
    rows = []
    for run in spec["runs"]:
        path = Path(run["eval"]) / "metrics.json"
        data = _read_json(path)
        row = {"scene": str(run["scene"]), "level": float(run["level"]), "variant": str(run["variant"]),
               "protocol": data.get("protocol", "?")}
        for name, section, key in METRICS:
            if not isinstance(data.get(section), dict):
                raise SceneFormatError(f"{path}: the '{section}' section is missing; is it an evaluate step's "
                                       f"metrics.json?")
            value = data[section].get(key)
            row[name] = float(value) if value is not None else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def collect_merges(spec: dict) -> pd.DataFrame:
    """One row per (scene, level) merge: ground-truth quality of the patches and the merged maps."""
    rows = []
    for entry in spec.get("merges") or []:
        data = _read_json(Path(entry["merge"]) / "merge.json")
        truth = data.get("ground_truth") or {}
        row = {"scene": str(entry["scene"]), "level": float(entry["level"])}
        for when in ("before", "after"):
            for key in ("ari", "straddling"):
                value = (truth.get(when) or {}).get(key)
                row[f"{key} {when}"] = float(value) if value is not None else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def summarise(runs: pd.DataFrame) -> pd.DataFrame:
    """Mean and std over scenes per (level, variant), metrics in percent (PSNR in dB)."""
    out = []
    for (level, variant), group in runs.groupby(["level", "variant"], sort=True):
        row = {"level": level, "variant": variant, "rooms": len(group)}
        for name, _, _ in METRICS:
            scale = 1.0 if name == "PSNR" else 100.0
            values = group[name].dropna() * scale
            row[name] = float(values.mean()) if len(values) else np.nan
            row[f"{name} std"] = float(values.std(ddof=0)) if len(values) else np.nan
        out.append(row)
    return pd.DataFrame(out)


def write_robustness(spec: dict, out_md: Path, plot: Path | None = None) -> pd.DataFrame:
    """Write ``out_md`` (Markdown), the CSV beside it and, if asked, the plot; returns the summary."""
    runs = collect_runs(spec)
    summary = summarise(runs)
    merges = collect_merges(spec)
    variants = list(dict.fromkeys(r["variant"] for r in spec["runs"]))
    scenes = sorted(runs["scene"].unique())
    levels = sorted(summary["level"].unique())

    wide = summary.pivot(index="level", columns="variant", values="object mIoU")[variants]
    nvs = summary.pivot(index="level", columns="variant", values="NVS mIoU")[variants]
    for frame in (wide, nvs):  # levels as written (0.25, not 0.2)
        frame.index = [f"{x:g}" for x in frame.index]
        frame.index.name = "level"
    lines = [
        "# Robustness to mask inconsistency",
        "",
        f"Rooms: {', '.join(scenes)} (same scene, poses and 2DGS fit at every level; protocol "
        f"{', '.join(sorted(runs['protocol'].unique()))}). Level = the simulated masks' `inconsistency` "
        f"(0: exact object masks; 1: every granularity switch, miss, split and boundary jitter at full rate).",
        "",
        "## Object mIoU (3D extraction, %)",
        "",
        _md(wide, ".1f"),
        "",
        "## NVS mIoU (novel-view 2D segmentation, %)",
        "",
        _md(nvs, ".1f"),
    ]
    if len(merges):
        mm = merges.groupby("level").mean(numeric_only=True)
        mm.index = [f"{x:g}" for x in mm.index]
        mm.index.name = "level"
        lines += ["", "## The masks at each level (mean over rooms)", "",
                  "ARI: adjusted Rand index of the per-view maps against the ground-truth objects; straddling: "
                  "fraction of instances whose second object holds >= 20 % of them; before = raw patches, after "
                  "= consistent instance maps.", "", _md(mm, ".3f")]
    with atomic_file(out_md) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    table = runs.sort_values(["level", "variant", "scene"]).reset_index(drop=True)
    with atomic_file(Path(out_md).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    if plot is not None:
        _plot(summary, variants, levels, scenes, plot)
    return summary


def _md(frame: pd.DataFrame, fmt: str) -> str:
    """Markdown of ``frame`` with its values formatted as ``fmt`` and its index (the levels) as written."""
    text = frame.apply(lambda col: col.map(lambda v: "" if pd.isna(v) else format(v, fmt)))
    return text.to_markdown(disable_numparse=True, colalign=["right"] * (len(frame.columns) + 1))


def _plot(summary: pd.DataFrame, variants: list[str], levels: list[float], scenes: list[str], plot: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharex=True)
    for ax, name in zip(axes, ("object mIoU", "NVS mIoU")):
        for variant in variants:
            rows = summary[summary["variant"] == variant].sort_values("level")
            ax.errorbar(rows["level"], rows[name], yerr=rows[f"{name} std"] if len(scenes) > 1 else None,
                        marker="o", capsize=3, label=variant)
        ax.set_xlabel("simulated mask inconsistency")
        ax.set_ylabel(f"{name} (%)")
        ax.set_xticks(levels)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Robustness to mask inconsistency ({', '.join(scenes)})")
    fig.tight_layout()
    with atomic_file(plot) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
