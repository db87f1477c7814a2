"""The robustness curve: object mIoU (and NVS mIoU) of several variants as the simulated masks'
inconsistency rises, on the same rooms and 2DGS fits (``rules/robustness.smk``).

Input: a spec, one entry per evaluated (room, level, variant)::

    {"runs": [{"scene": "room1", "level": 0.25, "variant": "full", "eval": "results/room1@inc0.25/full/eval"}, ...],
     "merges": [{"scene": "room1", "level": 0.25, "merge": "results/room1@inc0.25/merge-paper"}, ...]}

``merges`` (optional) adds the quality of the consistent instance maps per level (ARI, straddling before
and after merging, the merge's pair precision and recall against the ground truth) from each merge step's
``merge.json``. Where two variants of a stage pair are both run (``full`` and ``no_merge``: the merge's
own effect; ``no_merge`` and ``both_off``: density control's; ``full`` and ``both_off``: both), the table
gives their paired difference per level: mean over the rooms, 95 % Student-t interval and the rooms where
it is positive. Output: ``robustness.md`` / ``.csv`` (one row per run) and a plot of the curves with the
merge's paired effect.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import SceneFormatError, Trace3DError
from ..io import atomic_file
from .effects import t_interval
from .summary import _read_json

# (column, section, key); PQ^scene and the one-point NVS mIoU are read where the evaluation wrote them.
METRICS = (("object mIoU", "extraction", "mIoU"), ("NVS mIoU", "nvs", "mIoU"), ("PSNR", "extraction", "PSNR"),
           ("PQ scene", "panoptic", "PQ"), ("NVS mIoU 1pt", "single_point", "nvs"))
REQUIRED = ("extraction", "nvs")
# Paired stage effects per level: (label, variant, minus variant), reported where both are run.
PAIRS = (("merge: full - no_merge", "full", "no_merge"),
         ("density control: no_merge - both_off", "no_merge", "both_off"),
         ("both: full - both_off", "full", "both_off"))
EFFECT_METRICS = ("object mIoU", "NVS mIoU", "PQ scene")


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
        for section in REQUIRED:
            if not isinstance(data.get(section), dict):
                raise SceneFormatError(f"{path}: the '{section}' section is missing; is it an evaluate step's "
                                       f"metrics.json?")
        for name, section, key in METRICS:
            value = (data.get(section) or {}).get(key)
            if isinstance(value, dict):  # single_point.nvs holds the protocol's own section
                value = value.get("mIoU")
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
        pairs = truth.get("pairs") or {}
        for key in ("precision", "recall", "out_of_reach_share"):
            if pairs.get(key) is not None:
                row[f"merge {key.replace('_', ' ')}"] = float(pairs[key])
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


def paired_effects(runs: pd.DataFrame) -> pd.DataFrame:
    """Per level and stage pair of :data:`PAIRS` (both variants run): the difference's mean over the rooms
    (points), the half-width of its 95 % t interval, the rooms where it is positive and n."""
    out = []
    variants = set(runs["variant"])
    for label, a, b in PAIRS:
        if a not in variants or b not in variants:
            continue
        for level, group in runs.groupby("level", sort=True):
            left = group[group.variant == a].set_index("scene")
            right = group[group.variant == b].set_index("scene")
            common = left.index.intersection(right.index)
            if not len(common):
                continue
            row = {"effect": label, "level": level}
            for name in EFFECT_METRICS:
                diff = ((left.loc[common, name] - right.loc[common, name]) * 100.0).dropna()
                mean, half, n = t_interval(diff.to_numpy())
                row[name] = mean
                row[f"{name} ci"] = half
                row[f"{name} wins"] = f"{int((diff > 0).sum())}/{n}"
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
                  "= consistent instance maps; merge precision / recall: of the merged patch pairs, the share that "
                  "belong to one object / of the pairs that should merge, the share merged; out of reach: the "
                  "share of should-merge pairs the candidate rule never considers.", "", _md(mm, ".3f")]
    pq = summary.pivot(index="level", columns="variant", values="PQ scene")[variants]
    if pq.notna().any().any():
        pq.index = [f"{x:g}" for x in pq.index]
        pq.index.name = "level"
        lines += ["", "## PQ^scene (instances clustered from the lifted features alone, %)", "", _md(pq, ".1f")]
    effects = paired_effects(runs)
    if len(effects):
        lines += ["", "## Paired effects per level (points; mean over the rooms ± 95 % t interval, rooms where "
                  "positive)", ""]
        for label, group in effects.groupby("effect", sort=False):
            table = pd.DataFrame(index=[f"{x:g}" for x in group["level"]])
            table.index.name = "level"
            for name in EFFECT_METRICS:
                table[name] = [_pm(m, h, w) for m, h, w in
                               zip(group[name], group[f"{name} ci"], group[f"{name} wins"])]
            lines += [f"### {label}", "", table.to_markdown(disable_numparse=True,
                                                             colalign=["right"] * (len(table.columns) + 1)), ""]
    with atomic_file(out_md) as tmp:
        tmp.write_text("\n".join(lines).rstrip("\n") + "\n")
    table = runs.sort_values(["level", "variant", "scene"]).reset_index(drop=True)
    with atomic_file(Path(out_md).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    if plot is not None:
        _plot(summary, effects, variants, levels, scenes, plot)
    return summary


def _pm(mean: float, half: float, wins: str) -> str:
    if not np.isfinite(mean):
        return ""
    text = f"{mean:+.1f}" + (f" ± {half:.1f}" if np.isfinite(half) else "")
    return f"{text} ({wins})"


def _md(frame: pd.DataFrame, fmt: str) -> str:
    """Markdown of ``frame`` with its values formatted as ``fmt`` and its index (the levels) as written."""
    text = frame.apply(lambda col: col.map(lambda v: "" if pd.isna(v) else format(v, fmt)))
    return text.to_markdown(disable_numparse=True, colalign=["right"] * (len(frame.columns) + 1))


def _plot(summary: pd.DataFrame, effects: pd.DataFrame, variants: list[str], levels: list[float],
          scenes: list[str], plot: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    merge = effects[effects["effect"] == PAIRS[0][0]] if len(effects) else effects
    panels = 3 if len(merge) else 2
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 4), sharex=True)
    if len(merge):
        ax = axes[2]
        for i, name in enumerate(EFFECT_METRICS):
            if merge[name].notna().any():
                ax.errorbar(np.asarray(merge["level"]) + (i - 1) * 0.012, merge[name], yerr=merge[f"{name} ci"],
                            marker="o", capsize=3, label=name)
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xlabel("simulated mask inconsistency")
        ax.set_ylabel("full - no_merge (points, 95 % CI)")
        ax.set_title("the merge's paired effect", fontsize=9)
        ax.set_xticks(levels)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax, name in zip(axes[:2], ("object mIoU", "NVS mIoU")):
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
