"""Consistent 2D instance maps by majority vote over co-visible views (paper Sec. 3.3; ``merge`` step).

For two patches P_a, P_b of a view v0, G_a and G_b are the Gaussians whose argmax patch in v0 is
P_a (P_b) — the supplementary's argmax reduction of W — and visible in v0. Over the other views v,
the co-visible triples are Omega = {(G_a, G_b, v) : both visible in v}, and

    sim(P_a, P_b) = 1/|Omega| sum_Omega [argmax_v(G_a) == argmax_v(G_b)],

the inner product of the two Gaussians' (one-hot, argmax-reduced) instance distributions in v.
Pairs with sim > theta (0.5; ``official`` 0.4) merge (union-find), considering only pairs inside a
common coarser mask (supplementary, "Scalability of patch merging").

**Cost.** The sum over Gaussian pairs factors per view into histograms of the two sets' labels:
with h_a[v, l] = |{i in G_a : visible in v, label_v(i) = l}| and n_a[v] = sum_l h_a[v, l],

    sum_Omega [same] = sum_v <h_a[v], h_b[v]>,   |Omega| = sum_v n_a[v] n_b[v],

so one source view costs one pass over its visible Gaussians and all views
(:func:`cooccurrence`, numba), instead of |G_a| |G_b| L. :func:`pair_similarity_bruteforce` is
the pair loop the tests compare against. The source view v0 itself is left out of the vote (in v0
the two sets disagree by construction).

**Ids across views** (beyond the paper, which merges within each view only): merged instances of
different views are linked when they hold each other's Gaussians by mutual majority (more than
``association_share`` of each one's Gaussians co-visible in the other view fall into the other);
links are joined strongest first, never joining two instances of the same view, so that every
instance map keeps its own segmentation and only its ids become global.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
from numba import njit, prange

from .git import GITStats

log = logging.getLogger(__name__)

PRESET_VALUES = {
    "paper": {"threshold": 0.5, "min_visibility": 0.0},
    "official": {"threshold": 0.4, "min_visibility": 25.0},
}


@dataclass
class MergeParams:
    """Parameters of the ``merge`` step (``None`` takes the preset's value).

    threshold: merge patch pairs whose similarity exceeds it (paper 0.5, official 0.4).
    min_visibility: a Gaussian sees a view when its GIT visibility exceeds this (paper: any weight,
        0.0; official: more than 25 pixels, with the pixel-count statistic).
    common_mask_only: consider only pairs of patches inside a common coarser mask (supplementary).
    association_share: the mutual-majority share that links instances across views.
    ground_truth_level: level of the ground-truth hierarchy the ``merge.json`` quality figures use.
    """

    preset: Literal["paper", "official"] = "paper"
    threshold: float | None = None
    min_visibility: float | None = None
    common_mask_only: bool = True
    association_share: float = 0.5
    ground_truth_level: Literal["part", "object", "group"] = "object"
    preview_views: int = 4

    def __post_init__(self) -> None:
        for key, value in PRESET_VALUES[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {self.threshold}")
        if not 0.0 < self.association_share < 1.0:
            raise ValueError(f"association_share must be in (0, 1), got {self.association_share}")


# ----------------------------------------------------------------------------------------------
# Similarity: factored (numba) and brute force (the twin)
# ----------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def cooccurrence(source: np.ndarray, labels: np.ndarray, visible: np.ndarray, num_source: int,
                 num_labels: int) -> np.ndarray:
    """hist[a, v, l] = |{i : source[i] == a, visible[i, v], labels[i, v] == l}|.

    Args:
        source: [n] int64 source label of each Gaussian (negative: skipped).
        labels: [n, L] int32 labels per view (negative: skipped).
        visible: [n, L] bool.
    Returns:
        [num_source, L, num_labels] int32 (views in parallel: each writes its own slice).
    """
    n, views = labels.shape
    hist = np.zeros((num_source, views, num_labels), np.int32)
    for v in prange(views):
        for i in range(n):
            a = source[i]
            if a < 0 or not visible[i, v]:
                continue
            lab = labels[i, v]
            if lab >= 0:
                hist[a, v, lab] += 1
    return hist


def pair_similarity(hist: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Similarities of patch ``pairs`` [K, 2] from one source view's histograms [A, L, T].

    Returns:
        sim [K] float64 (0 where Omega is empty) and |Omega| [K] int64.
    """
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    h = hist.astype(np.float64)
    ha, hb = h[pairs[:, 0]], h[pairs[:, 1]]
    same = (ha * hb).sum(axis=(1, 2))
    omega = (ha.sum(axis=2) * hb.sum(axis=2)).sum(axis=1)
    sim = np.where(omega > 0, same / np.maximum(omega, 1), 0.0)
    return sim, omega.astype(np.int64)


def pair_similarity_bruteforce(labels: np.ndarray, visible: np.ndarray, source_view: int, a: int,
                               b: int) -> tuple[float, int]:
    """The paper's definition as a loop over Gaussian pairs and views (the twin of the factored form).

    Args:
        labels: [N, L] argmax labels; visible: [N, L] bool; source_view: v0; a, b: patch ids in v0.
    Returns:
        (sim, |Omega|).
    """
    ga = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == a]
    gb = [i for i in range(labels.shape[0]) if visible[i, source_view] and labels[i, source_view] == b]
    same = total = 0
    for v in range(labels.shape[1]):
        if v == source_view:
            continue
        for i in ga:
            if not visible[i, v] or labels[i, v] < 0:
                continue
            for j in gb:
                if not visible[j, v] or labels[j, v] < 0:
                    continue
                total += 1
                same += int(labels[i, v] == labels[j, v])
    return (same / total if total else 0.0), total


def source_histograms(labels: np.ndarray, visible: np.ndarray, source_view: int, num_source: int,
                      num_labels: int) -> np.ndarray:
    """:func:`cooccurrence` of the Gaussians visible in ``source_view``, keyed by their label there,
    with the source view itself left out (its histogram slice is zero)."""
    rows = np.nonzero(visible[:, source_view] & (labels[:, source_view] >= 0))[0]
    source = labels[rows, source_view].astype(np.int64)
    vis = visible[rows].copy()
    vis[:, source_view] = False
    return cooccurrence(source, np.ascontiguousarray(labels[rows]), vis, int(num_source), int(num_labels))


@njit(cache=True)
def _all_source_histograms(labels, indptr, indices, first, count, num_source, num_labels):
    n, views = labels.shape
    hist = np.zeros((count, num_source, views, num_labels), np.int32)
    for i in range(n):  # every pair of views that sees Gaussian i (serial: the blocks overlap in i)
        lo, hi = indptr[i], indptr[i + 1]
        for k0 in range(lo, hi):
            v0 = indices[k0]
            if v0 < first or v0 >= first + count:
                continue
            a = labels[i, v0]
            for k in range(lo, hi):
                v = indices[k]
                if v != v0:
                    hist[v0 - first, a, v, labels[i, v]] += 1
    return hist


# Largest histogram block (int32 entries) computed at once: 64 M entries = 256 MB.
HISTOGRAM_BLOCK = 1 << 26


def all_source_histograms(labels: np.ndarray, visible: np.ndarray, num_source: int, num_labels: int):
    """:func:`source_histograms` of every source view, yielded in order as [num_source, L, num_labels].

    Each Gaussian contributes only over the views it is visible in (a per-Gaussian list), so the
    cost is the number of (Gaussian, source view, view) co-visibilities, sum_i k_i^2 for a Gaussian
    seen in k_i views, not N L^2. Source views come in blocks that bound the memory.
    """
    seen = visible & (labels >= 0)
    counts = seen.sum(axis=1)
    indptr = np.zeros(len(labels) + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    indices = np.nonzero(seen)[1].astype(np.int64)  # row-major: sorted views per Gaussian
    masked = np.ascontiguousarray(np.where(seen, labels, -1).astype(np.int32))
    views = labels.shape[1]
    per_view = max(1, int(num_source) * views * int(num_labels))
    block = max(1, min(views, HISTOGRAM_BLOCK // per_view))
    for start in range(0, views, block):
        count = min(block, views - start)
        yield from _all_source_histograms(masked, indptr, indices, start, count, int(num_source), int(num_labels))


# ----------------------------------------------------------------------------------------------
# Union-find merging per view
# ----------------------------------------------------------------------------------------------


class UnionFind:
    def __init__(self, count: int):
        self.parent = list(range(count))

    def find(self, x: int) -> int:
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


@dataclass
class ViewMerge:
    """The merge of one view: ``lut`` [P + 1] maps patch id -> merged instance (0 -> 0, 1..G)."""

    frame: str
    lut: np.ndarray
    pairs: np.ndarray  # [K, 2] candidate pairs
    sims: np.ndarray  # [K]
    omega: np.ndarray  # [K]
    merged: np.ndarray  # [K] bool

    @property
    def num_instances(self) -> int:
        return int(self.lut.max(initial=0))


def merge_view(stats: GITStats, view: int, num_patches: int, pairs: np.ndarray, threshold: float,
               min_visibility: float, hist: np.ndarray | None = None) -> ViewMerge:
    """Merge the patches of view ``view`` (ids 1..num_patches; 0 is uncovered and never merged).

    ``hist``: the view's [A, L, T] source histograms when already computed (:func:`all_source_histograms`).
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if hist is None:
        num_labels = int(stats.num_labels.max(initial=1))
        hist = source_histograms(stats.label, stats.visible(min_visibility), view,
                                 max(num_patches + 1, int(stats.num_labels[view])), num_labels)
    sims, omega = pair_similarity(hist, pairs)
    merged = sims > threshold
    uf = UnionFind(num_patches + 1)
    for (a, b), m in zip(pairs, merged):
        if m:
            uf.union(int(a), int(b))
    roots = np.array([uf.find(p) for p in range(num_patches + 1)])
    lut = np.zeros(num_patches + 1, np.int64)
    order = {r: k + 1 for k, r in enumerate(sorted(set(roots[1:].tolist())))}
    for p in range(1, num_patches + 1):
        lut[p] = order[roots[p]]
    return ViewMerge(stats.frames[view], lut, pairs, sims, omega, merged)


# ----------------------------------------------------------------------------------------------
# Ids across views
# ----------------------------------------------------------------------------------------------


def associate(stats: GITStats, merges: Sequence[ViewMerge], min_visibility: float,
              share: float = 0.5) -> list[np.ndarray]:
    """Global instance ids: for every view, [G_v + 1] lut from merged instance to a global id (0 -> 0).

    Instances (v, m) and (w, m') link when more than ``share`` of each one's Gaussians that are
    co-visible in the other view fall into the other; links are joined strongest first, never
    joining two instances of the same view.
    """
    views = len(merges)
    visible = stats.visible(min_visibility)
    merged_labels = np.full(stats.label.shape, -1, np.int32)
    for v, m in enumerate(merges):
        lab = stats.label[:, v]
        ok = (lab >= 0) & (lab < len(m.lut))
        merged_labels[ok, v] = m.lut[lab[ok]]
    counts = [m.num_instances for m in merges]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    width = int(max(counts, default=0)) + 1
    links = []
    for v, hist in enumerate(all_source_histograms(merged_labels, visible, width, width)):
        if counts[v] == 0:
            continue
        hist = hist.astype(np.float64)  # [G+1, L, G'+1]
        fwd_total = hist.sum(axis=2)  # [G+1, L]: Gaussians of (v, m) co-visible in w
        rev_total = hist.sum(axis=0)  # [L, G'+1]: Gaussians of (w, m') co-visible in v
        block = hist[1:, v + 1:, 1:]  # later views only: each pair of views once
        fwd = block / np.maximum(fwd_total[1:, v + 1:, None], 1)
        rev = block / np.maximum(rev_total[None, v + 1:, 1:], 1)
        strength = np.minimum(fwd, rev)
        m, w, mp = np.nonzero(strength > share)
        w_abs = w + v + 1
        mp_ok = mp < np.asarray(counts)[w_abs]
        for s_, a_, b_ in zip(strength[m, w, mp][mp_ok], offsets[v] + m[mp_ok], offsets[w_abs[mp_ok]] + mp[mp_ok]):
            links.append((float(s_), int(a_), int(b_)))
    total = int(offsets[-1])
    uf = UnionFind(total)
    view_of = np.repeat(np.arange(views), counts)
    masks = {i: 1 << int(view_of[i]) for i in range(total)}
    for strength, a, b in sorted(links, key=lambda t: (-t[0], t[1], t[2])):
        ra, rb = uf.find(int(a)), uf.find(int(b))
        if ra == rb or masks[ra] & masks[rb]:
            continue
        uf.union(ra, rb)
        root = uf.find(ra)
        masks[root] = masks[ra] | masks[rb]
    roots = [uf.find(i) for i in range(total)]
    ids = {r: k + 1 for k, r in enumerate(sorted(set(roots)))}
    luts = []
    for v in range(views):
        lut = np.zeros(counts[v] + 1, np.int64)
        lut[1:] = [ids[roots[offsets[v] + m]] for m in range(counts[v])]
        luts.append(lut)
    return luts


# ----------------------------------------------------------------------------------------------
# Quality against the ground truth (synthetic benchmark)
# ----------------------------------------------------------------------------------------------


def adjusted_rand_index(truth: np.ndarray, pred: np.ndarray) -> float:
    """Adjusted Rand index of two labelings of the same pixels (1 = identical partitions)."""
    truth = np.asarray(truth).ravel()
    pred = np.asarray(pred).ravel()
    n = truth.size
    if n < 2:
        return 1.0
    _, ti = np.unique(truth, return_inverse=True)
    _, pi = np.unique(pred, return_inverse=True)
    table = np.zeros((ti.max() + 1, pi.max() + 1), np.float64)
    np.add.at(table, (ti, pi), 1)

    def comb2(x):
        return (x * (x - 1) / 2.0).sum()

    index = comb2(table)
    a, b = comb2(table.sum(1)), comb2(table.sum(0))
    expected = a * b / (n * (n - 1) / 2.0)
    maximum = (a + b) / 2.0
    if maximum == expected:
        return 1.0
    return float((index - expected) / (maximum - expected))


@dataclass
class SegmentationQuality:
    """Quality figures of per-view instance maps against ground-truth object maps."""

    ari: float
    covered: float  # fraction of ground-truth objects (per view) with one instance holding >= cover of them
    straddling: float  # fraction of instances (per view) with >= straddle of their pixels on a second object
    objects: int = 0
    instances: int = 0
    params: dict = field(default_factory=dict)


def segmentation_quality(truths: Sequence[np.ndarray], preds: Sequence[np.ndarray], min_pixels: int = 50,
                         cover: float = 0.8, straddle: float = 0.2) -> SegmentationQuality:
    """ARI over the labelled ground-truth pixels, coverage and straddling (definitions in docs/tracing.md).

    Args:
        truths: per view, ground-truth ids [H, W] (0 unlabelled, excluded).
        preds: per view, instance ids [H, W] (0 = no instance; a cluster of its own for the ARI).
        min_pixels: objects and instances smaller than this in a view are not counted.
        cover: an object is covered when one instance holds at least this fraction of its pixels.
        straddle: an instance straddles when its second object holds at least this fraction of it.
    """
    aris, covered, n_obj, straddling, n_inst = [], 0, 0, 0, 0
    for truth, pred in zip(truths, preds):
        lab = truth > 0
        if not lab.any():
            continue
        t, p = truth[lab].astype(np.int64), pred[lab].astype(np.int64)
        aris.append(adjusted_rand_index(t, p))
        _, ti = np.unique(t, return_inverse=True)
        _, pi = np.unique(p, return_inverse=True)
        pid = np.unique(p)
        table = np.zeros((ti.max() + 1, pi.max() + 1), np.int64)
        np.add.at(table, (ti, pi), 1)
        real = pid > 0  # columns that are instances
        obj_size = table.sum(1)
        for row, size in zip(table, obj_size):
            if size < min_pixels:
                continue
            n_obj += 1
            covered += int(real.any() and row[real].max() >= cover * size)
        for col in np.nonzero(real)[0]:
            size = table[:, col].sum()
            if size < min_pixels:
                continue
            n_inst += 1
            second = np.sort(table[:, col])[-2] if table.shape[0] > 1 else 0
            straddling += int(second >= straddle * size)
    return SegmentationQuality(
        ari=float(np.mean(aris)) if aris else float("nan"),
        covered=covered / n_obj if n_obj else float("nan"),
        straddling=straddling / n_inst if n_inst else float("nan"),
        objects=n_obj, instances=n_inst,
        params={"min_pixels": min_pixels, "cover": cover, "straddle": straddle},
    )


# ----------------------------------------------------------------------------------------------
# The `merge` step
# ----------------------------------------------------------------------------------------------


def merge_all(stats: GITStats, hierarchies: Sequence, params: MergeParams) -> tuple[list[ViewMerge], list[np.ndarray]]:
    """Merge every traced view (``hierarchies``: the views' :class:`PatchHierarchy`, in stats order) and
    associate the results across views. Returns the per-view merges and global-id luts."""
    merges = []
    num_labels = int(stats.num_labels.max(initial=1))
    num_source = max(num_labels, max((h.num_patches + 1 for h in hierarchies), default=1))
    every = all_source_histograms(stats.label, stats.visible(params.min_visibility), num_source, num_labels)
    for v, (hierarchy, hist) in enumerate(zip(hierarchies, every)):
        if params.common_mask_only:
            pairs = hierarchy.candidate_pairs()
        else:
            a, b = np.triu_indices(hierarchy.num_patches + 1, k=1)
            keep = a > 0
            pairs = np.stack([a[keep], b[keep]], axis=1)
        merges.append(merge_view(stats, v, hierarchy.num_patches, pairs, params.threshold, params.min_visibility,
                                 hist=hist))
    luts = associate(stats, merges, params.min_visibility, params.association_share)
    return merges, luts


def run_merge(scene, git_dir: Path, patches_dir: Path, out_dir: Path, params: dict) -> dict:
    """The ``merge`` step: consistent instance maps ``instances/<frame>.png`` (16-bit, ids consistent
    across views, 0 = no instance), ``merge.json`` and ``preview.png`` in ``out_dir``."""
    from ..errors import SceneFormatError
    from ..io import write_json
    from ..masks.patches import read_patches
    from ..params import from_mapping, to_dict
    from ..scene import write_u16

    p = from_mapping(MergeParams, params, "merge params")
    stats = GITStats.load(Path(git_dir) / "git.npz")
    start = time.perf_counter()
    maps, hierarchies = [], []
    for frame in stats.frames:
        patch_map, hierarchy = read_patches(patches_dir, frame)
        maps.append(patch_map)
        hierarchies.append(hierarchy)
    for v, (frame, patch_map) in enumerate(zip(stats.frames, maps)):
        if int(patch_map.max(initial=0)) + 1 > int(stats.num_labels[v]) and int(patch_map.max(initial=0)) > 0:
            raise SceneFormatError(f"{Path(patches_dir) / (frame + '.png')}: the patch map has ids up to "
                                   f"{int(patch_map.max())} but the GIT trace saw {int(stats.num_labels[v])} labels; "
                                   f"the trace is stale (rerun the trace step).")
    merges, luts = merge_all(stats, hierarchies, p)
    seconds = time.perf_counter() - start
    out_dir = Path(out_dir)
    (out_dir / "instances").mkdir(parents=True, exist_ok=True)
    outputs = []
    for frame, patch_map, m, lut in zip(stats.frames, maps, merges, luts):
        instance_map = lut[m.lut[patch_map.astype(np.int64)]]
        if instance_map.max(initial=0) > 65535:
            raise ValueError(f"merge: {frame}: more than 65535 global instances.")
        write_u16(out_dir / "instances" / f"{frame}.png", instance_map.astype(np.uint16))
        outputs.append(instance_map)
    views = []
    for m in merges:
        views.append({
            "frame": m.frame, "patches": int(len(m.lut) - 1), "instances": m.num_instances,
            "pairs_considered": int(len(m.pairs)),
            "merged": [[int(a), int(b), round(float(s), 4)] for (a, b), s, ok in zip(m.pairs, m.sims, m.merged) if ok],
            "similarities": [[int(a), int(b), round(float(s), 4), int(o)] for (a, b), s, o in zip(m.pairs, m.sims, m.omega)],
        })
    report = {
        "params": to_dict(p), "seconds": seconds, "views": len(merges),
        "global_instances": int(max((int(l.max(initial=0)) for l in luts), default=0)),
        "mean_patches": float(np.mean([len(m.lut) - 1 for m in merges])) if merges else 0.0,
        "mean_instances": float(np.mean([m.num_instances for m in merges])) if merges else 0.0,
        "merged_pairs": int(sum(int(m.merged.sum()) for m in merges)),
        "pairs_considered": int(sum(len(m.pairs) for m in merges)),
    }
    if scene is not None and scene.has_instances and scene.objects is not None:
        table = scene.objects.lookup(p.ground_truth_level)
        truths = []
        for frame in stats.frames:
            leaf = scene.instances(frame).astype(np.int64)
            truths.append(table[np.clip(leaf, 0, len(table) - 1)])
        before = segmentation_quality(truths, maps)
        after = segmentation_quality(truths, outputs)
        report["ground_truth"] = {"level": p.ground_truth_level, "before": before.__dict__, "after": after.__dict__}
        log.info("merge vs ground truth: ARI %.3f -> %.3f, covered %.3f -> %.3f, straddling %.3f -> %.3f",
                 before.ari, after.ari, before.covered, after.covered, before.straddling, after.straddling)
        if p.preview_views > 0:
            write_merge_preview(scene, stats.frames, maps, outputs, truths, out_dir / "preview.png", p.preview_views)
    report["per_view"] = views
    write_json(out_dir / "merge.json", report)
    return report


def count_ids(label_map: np.ndarray) -> int:
    """Number of distinct non-zero ids in a label map."""
    ids = np.unique(label_map)
    return int((ids > 0).sum())


def write_merge_preview(scene, frames, patch_maps, instance_maps, truths, path: Path, count: int) -> None:
    """Rows of (image, raw patches, consistent instances, ground truth) for ``count`` views."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..masks.patches import label_overlay

    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    fig, axes = plt.subplots(len(picks), 4, figsize=(11, 2.3 * len(picks)), squeeze=False)
    for row, v in enumerate(picks):
        image = scene.image(frames[v])
        panels = [(image / 255.0, f"{frames[v]}"), (label_overlay(image, patch_maps[v]), f"patches ({count_ids(patch_maps[v])})"),
                  (label_overlay(image, instance_maps[v]), f"consistent ({count_ids(instance_maps[v])})"),
                  (label_overlay(image, truths[v]), "ground-truth objects")]
        for ax, (img, title) in zip(axes[row], panels):
            ax.imshow(np.clip(img, 0, 1))
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
