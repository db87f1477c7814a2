"""The tracing table (``results/tracing.md``): what merging and GIT-guided refinement did per scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..io import atomic_file
from .summary import _read_json


PAIRS_NOTE = (
    " Pairs of patches in a view: a patch belongs to the ground-truth object holding most of its pixels (patches "
    "mostly on unlabelled pixels left out); a pair should merge when both belong to one object. Pair precision / "
    "recall: of the candidate pairs the merge compared, merged pairs that should merge / merged pairs, and merged "
    "should-merge pairs / should-merge candidate pairs; should-merge out of reach: share of all should-merge pairs "
    "that were never candidates; should-merge joined: share of them that ended in one instance (directly or "
    "through other merges).")


def tracing_row(merge_dir: Path, refine_dir: Path | None) -> dict:
    """One row from ``<merge_dir>/merge.json`` and (optionally) ``<refine_dir>/refine.json``; the scene
    is named after the folder that holds them."""
    merge = _read_json(Path(merge_dir) / "merge.json")
    row: dict = {"scene": Path(merge_dir).resolve().parent.name, "preset": merge["params"]["preset"],
                 "patches/view": merge["mean_patches"], "instances/view": merge["mean_instances"],
                 "merged pairs": merge["merged_pairs"], "merge s": merge["seconds"]}
    truth = merge.get("ground_truth")
    if truth:
        for key, name in (("ari", "ARI"), ("covered", "covered"), ("straddling", "straddling")):
            row[f"{name} before"] = truth["before"][key]
            row[f"{name} after"] = truth["after"][key]
        pairs = truth.get("pairs")
        if pairs:  # per-pair merge decisions against the ground truth (merge.py, PairQuality)
            for key, name in (("precision", "pair precision"), ("recall", "pair recall"),
                              ("out_of_reach_share", "should-merge out of reach"),
                              ("joined_recall", "should-merge joined")):
                row[name] = np.nan if pairs[key] is None else pairs[key]
    if refine_dir is not None:
        refine = _read_json(Path(refine_dir) / "refine.json")
        row.update({
            "ambiguous before": refine["ambiguous_before"], "split": refine["split"], "pruned": refine["pruned"],
            "ambiguous after": refine["ambiguous_after"],
            "PSNR before": refine["test_psnr_before"], "PSNR after": refine["test_psnr_after"],
        })
        boundary = refine.get("boundary")
        if boundary:
            row["ambiguous near boundary"] = boundary["ambiguous_near_boundary"]
            row["all near boundary"] = boundary["all_near_boundary"]
        row["refine min"] = refine["seconds"] / 60.0
    return row


def write_tracing_table(merge_dirs: list[Path], refine_dirs: list[Path] | None, out: Path,
                        plot: Path | None = None) -> pd.DataFrame:
    """Markdown table (CSV beside it) of the merge and refine figures, one row per scene plus the mean;
    ``plot``: bars of the quality figures before / after merging."""
    refine_dirs = refine_dirs or [None] * len(merge_dirs)
    table = pd.DataFrame([tracing_row(Path(m), Path(r) if r else None) for m, r in zip(merge_dirs, refine_dirs)])
    numeric = table.select_dtypes("number")
    mean = {c: numeric[c].mean() for c in numeric.columns}
    shown = pd.concat([table, pd.DataFrame([{"scene": "mean", "preset": "", **mean}])], ignore_index=True)
    text = ("# Consistent instance maps and GIT-guided refinement\n\n"
            "ARI: adjusted Rand index of the per-view maps against the ground-truth objects (labelled pixels); "
            "covered: fraction of objects (per view, >= 50 px) of which one instance holds >= 80 %; straddling: "
            "fraction of instances (>= 50 px) whose second object holds >= 20 % of them; near boundary: fraction "
            "of Gaussians whose footprint in their dominant view touches the 2-px band of a ground-truth object "
            "boundary." + (PAIRS_NOTE if "pair precision" in table else "") + "\n\n"
            + shown.to_markdown(index=False, floatfmt=".3f") + "\n")
    with atomic_file(out) as tmp:
        tmp.write_text(text)
    with atomic_file(Path(out).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    if plot is not None:  # without ground truth (e.g. a user's photos): patches and instances per view
        _plot(table, Path(plot))
    return table


def _plot(table: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if "ARI before" in table:
        names, before, after = ("ARI", "covered", "straddling"), "{} before", "{} after"
    else:
        names, before, after = ("segments per view",), "patches/view", "instances/view"
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    axes = axes[0]
    x = np.arange(len(table))
    for ax, name in zip(axes, names):
        ax.bar(x - 0.2, table[before.format(name)], 0.4, label="raw patches")
        ax.bar(x + 0.2, table[after.format(name)], 0.4, label="consistent maps")
        ax.set_xticks(x, table["scene"], rotation=30)
        ax.set_title(name)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
