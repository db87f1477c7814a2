"""The study table: every variant under every mask model, with 95 % confidence intervals, the paired
effect of each stage and the share of the raw-to-oracle gap each variant closes (``rules/effects.smk``).

Input: a spec, one entry per scored run::

    {"runs": [{"room": "room0", "masks": "default", "variant": "full", "seed": 0,
               "eval": "results/room0/full/eval"}, ...],
     "oracle": ["both_off"],     # the variants run on exact object masks (masks == "oracle")
     "raw": "both_off"}          # the lower end of the gap

A *sample* is one (room, fit seed, lift seed) (``fit`` 0 where a run names none).  For a mask model and
a variant, a metric's mean and its 95 % confidence interval (Student's t) are over the samples.  The
*paired effect* of a stage compares two
variants on the same samples (e.g. ``full - no_merge``: what merging adds with density control on);
its interval is the t interval of the paired differences, and ``wins`` counts the samples where the
difference is positive.  The *gap share* of a variant is ``mean(v - raw) / mean(oracle - raw)`` over the
rooms that have all three, each difference first averaged over the room's seeds (the oracle, the first
oracle variant on exact object masks, may have fewer seeds than the variant, each paired with the raw
patches of its own seed): 0 = no better than the raw patches, 1 = as good as exact masks; it is left out
("–") where that gap is under ``MIN_GAP`` points (a metric the masks' quality does not move).

Output: ``effects.md`` (Markdown), ``effects.csv`` (every number), a plot of the paired effects and one of
the raw variant under each mask model (``<plot>_masks.png``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import SceneFormatError, Trace3DError
from ..io import atomic_file
from .summary import _read_json

# (column, section path in metrics.json, scale): metrics read when present.
METRICS = (
    ("object mIoU", ("extraction", "mIoU"), 100.0),
    ("NVS mIoU", ("nvs", "mIoU"), 100.0),
    ("PQ scene", ("panoptic", "PQ"), 100.0),
    ("scene mIoU", ("panoptic", "mIoU"), 100.0),
    ("object mIoU 1pt", ("single_point", "extraction", "mIoU"), 100.0),
    ("NVS mIoU 1pt", ("single_point", "nvs", "mIoU"), 100.0),
    # without ground truth: the `segment` step's objects (PQ^scene of its clusters) and one click's object
    ("PQ segment", ("segment", "PQ"), 100.0),
    ("click IoU", ("click", "mIoU"), 100.0),
)
# A gap share is only reported where exact masks beat the raw patches by at least this many points: a
# metric that exact masks do not move (object mIoU on these rooms) has no gap to close.
MIN_GAP = 1.0
# Paired effects: (label, variant, minus variant).
EFFECTS = (
    ("merge (refine on): full - no_merge", "full", "no_merge"),
    ("merge (refine off): no_refine - both_off", "no_refine", "both_off"),
    ("refine (merge on): full - no_refine", "full", "no_refine"),
    ("refine (merge off): no_merge - both_off", "no_merge", "both_off"),
    ("both: full - both_off", "full", "both_off"),
    ("merge, all pairs (refine on): full_all - no_merge", "full_all", "no_merge"),
    ("all pairs vs coarser mask: full_all - full", "full_all", "full"),
    ("hierarchical merge (refine on): full_hier - no_merge", "full_hier", "no_merge"),
    ("hierarchical vs the paper's merge: full_hier - full", "full_hier", "full"),
    ("hierarchical merge (refine off): no_refine_hier - both_off", "no_refine_hier", "both_off"),
    ("hierarchical vs the paper's merge (refine off): no_refine_hier - no_refine", "no_refine_hier", "no_refine"),
    ("ignore relation, no merge (refine off): both_off_ignore - both_off", "both_off_ignore", "both_off"),
    ("ignore relation vs hierarchical merge (refine off): both_off_ignore - no_refine_hier", "both_off_ignore",
     "no_refine_hier"),
    ("released merge (refine on): full_released - no_merge", "full_released", "no_merge"),
    ("merge at theta 0.4 (refine on): full_t04 - no_merge", "full_t04", "no_merge"),
    ("theta 0.4 vs 0.5: full_t04 - full", "full_t04", "full"),
)


def _check_spec(spec: dict) -> None:
    runs = spec.get("runs")
    if not isinstance(runs, list) or not runs:
        raise Trace3DError("effects spec: 'runs' must be a non-empty list of {room, masks, variant, seed, eval}.")
    for run in runs:
        missing = [k for k in ("room", "masks", "variant", "seed", "eval") if k not in run]
        if missing:
            raise Trace3DError(f"effects spec: a run lacks {', '.join(missing)}: {run}.")


def _lookup(data: dict, path: tuple[str, ...]):
    for key in path:
        if not isinstance(data, dict) or key not in data:
            return None
        data = data[key]
    return data


def collect(spec: dict) -> pd.DataFrame:
    """One row per run: room, masks, variant, seed and every metric of its ``metrics.json`` (NaN where absent)."""
    _check_spec(spec)
    rows = []
    for run in spec["runs"]:
        path = Path(run["eval"]) / "metrics.json"
        data = _read_json(path)
        for section in ("extraction", "nvs"):
            if not isinstance(data.get(section), dict):
                raise SceneFormatError(f"{path}: the '{section}' section is missing; is it an evaluate step's "
                                       f"metrics.json?")
        row = {"room": str(run["room"]), "masks": str(run["masks"]), "variant": str(run["variant"]),
               "fit": int(run.get("fit", 0)), "seed": int(run["seed"])}
        for name, keys, scale in METRICS:
            value = _lookup(data, keys)
            row[name] = float(value) * scale if isinstance(value, (int, float)) and value is not None else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def t_interval(values) -> tuple[float, float, int]:
    """(mean, half-width of the two-sided 95 % Student-t interval, n) of the finite ``values``;
    the half-width is NaN for fewer than two values."""
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    n = len(v)
    if n == 0:
        return math.nan, math.nan, 0
    mean = float(v.mean())
    if n < 2:
        return mean, math.nan, n
    from scipy.stats import t

    half = float(t.ppf(0.975, n - 1) * v.std(ddof=1) / math.sqrt(n))
    return mean, half, n


def _paired(frame: pd.DataFrame, masks: str, a: str, b: str, metric: str,
            b_masks: str | None = None) -> pd.DataFrame:
    """Samples (room, fit, seed) with both ``a`` under ``masks`` and ``b`` under ``b_masks`` (default the same)."""
    keys = ["room", "fit", "seed"]
    left = frame[(frame.masks == masks) & (frame.variant == a)][keys + [metric]]
    right = frame[(frame.masks == (b_masks or masks)) & (frame.variant == b)][keys + [metric]]
    joined = left.merge(right, on=keys, suffixes=("_a", "_b"))
    return joined.dropna()


def summarize(frame: pd.DataFrame, oracle: list[str], raw: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per mask model and variant: mean, CI, n and gap share per metric; paired effects)."""
    metrics = [m for m, _, _ in METRICS if frame[m].notna().any()]
    oracle_variant = oracle[0] if oracle else None
    rows = []
    for (masks, name), group in sorted(frame.groupby(["masks", "variant"]), key=lambda kv: kv[0]):
        row = {"masks": masks, "variant": name}
        for m in metrics:
            mean, half, n = t_interval(group[m])
            row[f"{m} mean"], row[f"{m} ci95"], row[f"{m} n"] = mean, half, n
            share = share_half = math.nan
            if oracle_variant is not None and masks != "oracle":
                # per room: the variant's gain over the raw patches (mean over its seeds) and the oracle's
                # (mean over the oracle's seeds, which may be fewer: the oracle is often run on one seed)
                v_raw = _paired(frame, masks, name, raw, m)
                o_raw = _paired(frame, "oracle", oracle_variant, raw, m, b_masks=masks)
                gain = (v_raw[f"{m}_a"] - v_raw[f"{m}_b"]).groupby(v_raw["room"]).mean()
                room_gap = (o_raw[f"{m}_a"] - o_raw[f"{m}_b"]).groupby(o_raw["room"]).mean()
                rooms = gain.index.intersection(room_gap.index)
                gap = float(room_gap[rooms].mean()) if len(rooms) else math.nan
                if len(rooms) and gap >= MIN_GAP:
                    share = float(gain[rooms].mean()) / gap
                    share_half = t_interval(gain[rooms])[1] / gap
            row[f"{m} gap share"] = share
            row[f"{m} gap share ci95"] = share_half
        rows.append(row)
    summary = pd.DataFrame(rows)
    effects = []
    for masks in sorted(frame.masks.unique()):
        if masks == "oracle":
            continue
        for label, a, b in EFFECTS:
            for m in metrics:
                pairs = _paired(frame, masks, a, b, m)
                if pairs.empty:
                    continue
                diff = pairs[f"{m}_a"] - pairs[f"{m}_b"]
                mean, half, n = t_interval(diff)
                rooms = diff.groupby(pairs["room"]).mean()
                r_mean, r_half, r_n = t_interval(rooms)
                effects.append({"masks": masks, "effect": label, "metric": m, "mean": mean, "ci95": half, "n": n,
                                "wins": int((diff > 0).sum()), "rooms ci95": r_half, "rooms": r_n})
    return summary, pd.DataFrame(effects)


def _fmt(mean: float, half: float) -> str:
    if not np.isfinite(mean):
        return "–"
    return f"{mean:.1f}" if not np.isfinite(half) else f"{mean:.1f} ± {half:.1f}"


def _share(value: float, half: float = math.nan) -> str:
    if not np.isfinite(value):
        return "–"
    return f"{100 * value:.0f} %" if not np.isfinite(half) else f"{100 * value:.0f} ± {100 * half:.0f} %"


def markdown(summary: pd.DataFrame, effects: pd.DataFrame, frame: pd.DataFrame) -> str:
    metrics = [m for m, _, _ in METRICS if f"{m} mean" in summary]
    lines = ["**Variants under each mask model**: mean ± half-width of the 95 % confidence interval over "
             "rooms × lift seeds (n samples); *gap* = share of the raw-to-oracle gap the variant closes "
             "(raw patches without refinement = 0 %, the oracle on exact object masks = 100 %; ± the 95 % interval of "
             "the rooms' gains over the raw patches, over the mean gap; – where exact "
             f"masks gain less than {MIN_GAP:g} point over the raw patches: nothing to close).", ""]
    for masks in sorted(summary.masks.unique(), key=lambda m: (m == "oracle", m != "default", m)):
        part = summary[summary.masks == masks]
        rooms = sorted(frame[frame.masks == masks].room.unique())
        lines += [f"*Masks: {masks}* ({len(rooms)} rooms: {', '.join(rooms)})", ""]
        header = ["variant", "n"] + [c for m in metrics for c in (m, "gap")]
        lines += ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
        for _, r in part.iterrows():
            n = int(max(r[f"{m} n"] for m in metrics))
            cells = [r.variant, str(n)]
            for m in metrics:
                cells += [_fmt(r[f"{m} mean"], r[f"{m} ci95"]), _share(r[f"{m} gap share"], r[f"{m} gap share ci95"])]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    if not effects.empty:
        lines += ["**Paired effects** (same rooms and seeds): mean difference in points ± 95 % CI over rooms × "
                  "seeds, the CI over rooms alone (seed-averaged), and the samples where the first variant wins.", ""]
        header = ["masks", "effect", "metric", "difference", "CI over rooms", "wins"]
        lines += ["| " + " | ".join(header) + " |", "|---|---|---|---:|---:|---:|"]
        for _, e in effects.iterrows():
            lines.append(f"| {e.masks} | {e.effect} | {e.metric} | {_fmt(e['mean'], e['ci95'])} | "
                         f"± {e['rooms ci95']:.1f} ({e['rooms']} rooms) | {e.wins}/{e.n} |"
                         if np.isfinite(e["rooms ci95"]) else
                         f"| {e.masks} | {e.effect} | {e.metric} | {_fmt(e['mean'], e['ci95'])} | – | {e.wins}/{e.n} |")
        lines.append("")
    return "\n".join(lines)


def plot(effects: pd.DataFrame, path: Path) -> None:
    """The paired effects with their 95 % intervals (over rooms x seeds), one panel per metric, one
    colour per mask model: what each stage adds, and whether its interval includes 0."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m, _, _ in METRICS if not effects.empty and (effects.metric == m).any()][:4] or ["object mIoU"]
    labels = [label for label, _, _ in EFFECTS if not effects.empty and (effects.effect == label).any()]
    models = sorted(effects.masks.unique(), key=lambda m: (m != "default", m)) if not effects.empty else []
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.0 * len(metrics), 0.45 * max(len(labels), 1) + 1.6),
                             squeeze=False, sharey=True)
    for ax, m in zip(axes[0], metrics):
        for k, model in enumerate(models):
            part = effects[(effects.metric == m) & (effects.masks == model)].set_index("effect")
            ys = [i + (k - (len(models) - 1) / 2) * 0.25 for i, label in enumerate(labels) if label in part.index]
            xs = [part.loc[label, "mean"] for label in labels if label in part.index]
            es = [np.nan_to_num(part.loc[label, "ci95"]) for label in labels if label in part.index]
            ax.errorbar(xs, ys, xerr=es, fmt="o", capsize=3, label=f"{model} masks")
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_title(f"{m}: difference (points)")
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].set_yticks(range(len(labels)), [label.split(": ")[0] + "\n" + label.split(": ")[-1] for label in labels],
                          fontsize=7)
    axes[0][0].invert_yaxis()
    if models:
        axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.suptitle("Paired effect of each stage: mean and 95 % CI over rooms × lift seeds")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


# The mask models side by side (plot_masks): the metrics a user without ground truth cares about.
MASK_METRICS = ("NVS mIoU", "PQ scene", "PQ segment", "click IoU")


def masks_plot_path(plot_path: Path) -> Path:
    """Where :func:`write_effects` puts the mask models' plot beside the effects plot."""
    return Path(plot_path).with_name(Path(plot_path).stem + "_masks.png")


def plot_masks(summary: pd.DataFrame, variant: str, path: Path) -> None:
    """One variant (the raw patches) under every mask model: mean and 95 % interval of the metrics that
    need no ground truth at query time, one panel each; what the masks alone are worth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    part = summary[summary.variant == variant] if not summary.empty else summary
    metrics = [m for m in MASK_METRICS if f"{m} mean" in part and part[f"{m} mean"].notna().any()] or ["NVS mIoU"]
    models = sorted(part.masks.unique(), key=lambda m: (m == "oracle", m != "default", m)) if not part.empty else []
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.2 * len(metrics), 0.4 * max(len(models), 1) + 1.6),
                             squeeze=False, sharey=True)
    for ax, m in zip(axes[0], metrics):
        rows = [part[part.masks == model].iloc[0] for model in models]
        xs = [r[f"{m} mean"] if f"{m} mean" in r else np.nan for r in rows]
        es = [np.nan_to_num(r[f"{m} ci95"]) if f"{m} ci95" in r else 0.0 for r in rows]
        ax.barh(range(len(models)), np.nan_to_num(xs), xerr=es, capsize=3, color="tab:blue", alpha=0.7)
        for i, x in enumerate(xs):
            if np.isfinite(x):
                ax.text(1, i, f"{x:.1f}", va="center", fontsize=7, color="white")
        ax.set_xlim(0, 100)
        ax.set_title(m, fontsize=9)
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].set_yticks(range(len(models)), [f"{model} masks" for model in models], fontsize=8)
    axes[0][0].invert_yaxis()
    fig.suptitle(f"`{variant}` under each mask model: mean and 95 % CI over rooms × lift seeds", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def write_effects(spec: dict, out: Path, plot_path: Path | None = None) -> None:
    frame = collect(spec)
    summary, effects = summarize(frame, list(spec.get("oracle") or []), str(spec.get("raw", "both_off")))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        tmp.write_text(markdown(summary, effects, frame))
    csv = out.with_suffix(".csv")
    with atomic_file(csv) as tmp:
        text = summary.to_csv(index=False, float_format="%.6g")
        if not effects.empty:
            text += "\n" + effects.to_csv(index=False, float_format="%.6g")
        tmp.write_text(text)
    raw_csv = out.with_name(out.stem + "_runs.csv")
    with atomic_file(raw_csv) as tmp:
        tmp.write_text(frame.sort_values(["masks", "variant", "room", "seed"]).to_csv(index=False, float_format="%.6g"))
    if plot_path is not None:
        plot(effects, Path(plot_path))
        plot_masks(summary, str(spec.get("raw", "both_off")), masks_plot_path(Path(plot_path)))
