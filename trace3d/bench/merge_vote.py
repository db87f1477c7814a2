"""``trace3d bench merge-vote``: what a multi-view vote can see, pair by pair, on a room with ground truth.

For every pair of patches of every traced view, the votes the merges read are computed from the
room's GIT trace and patches (:mod:`trace3d.tracing.consistency`, every pair of the view):

- ``same_patch``: the paper's vote (the two patches' Gaussians fall into one patch of the other views;
  the hierarchical merge with ``mask_weight`` 0);
- ``common_mask``: they fall under one common mask there (``mask_weight`` 1);
- ``mask_jaccard``: the Jaccard index of the two patches' mask sets there (the masks that contain each),
  1 for the same patch;

and each pair is labelled from the ground truth: *should merge* (both patches belong to one object),
*group-mates* (two objects of one ground-truth group) or *unrelated*.

Figures (one JSON object, per room and pooled over the rooms):

- each vote's median per class;
- for each score, the largest pair recall at a pair precision of at least 0.95, 0.90 and 0.80 over all
  thresholds, and the area under its precision-recall curve. Scores: the three votes, the hierarchical
  merge's mixes ``(1 - w) same_patch + w common_mask``, and ``binned_bayes``, the share of should-merge
  pairs in the pair's cell of a 10 x 10 grid over (same_patch, common_mask) measured on the same pairs:
  an optimistic (in-sample) bound on any rule that reads only those two votes.

Pair figures come before any grouping (average linkage or union-find): they say what the vote separates,
not what a merge does with it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import Trace3DError
from ..tracing.consistency import patch_pair_matrix

log = logging.getLogger(__name__)

PRECISIONS = (0.95, 0.90, 0.80)
MIXES = (0.1, 0.25, 0.5)


def _jaccard_comembership(hierarchy, num_labels: int) -> np.ndarray:
    """[T, T] Jaccard index of the mask sets of each pair of patches (1 on the diagonal, 0 for label 0)."""
    member = hierarchy.membership().astype(np.int64)
    inter = member @ member.T
    sizes = member.sum(axis=1)
    union = sizes[:, None] + sizes[None, :] - inter
    return patch_pair_matrix(np.where(union > 0, inter / np.maximum(union, 1), 0.0), num_labels)


def recall_at_precision(score: np.ndarray, positive: np.ndarray) -> dict:
    """Largest recall at precision >= each of PRECISIONS over every threshold of ``score`` (pairs scored
    higher are merged first; ties enter together), and the area under the precision-recall curve."""
    total = int(positive.sum())
    if total == 0 or len(score) == 0:
        return {f"recall_at_{p:g}": None for p in PRECISIONS} | {"pr_auc": None}
    order = np.argsort(-score, kind="stable")
    s, pos = score[order], positive[order].astype(np.int64)
    tp, n = np.cumsum(pos), np.arange(1, len(s) + 1)
    last = np.r_[s[1:] != s[:-1], True]  # a threshold sits after the last pair of each tie
    tp, n = tp[last], n[last]
    precision, recall = tp / n, tp / total
    out = {}
    for p in PRECISIONS:
        ok = precision >= p
        out[f"recall_at_{p:g}"] = float(recall[ok].max()) if ok.any() else 0.0
    steps = np.diff(np.r_[0.0, recall])
    out["pr_auc"] = float((precision * steps).sum())
    return out


def binned_bayes(same: np.ndarray, common: np.ndarray, positive: np.ndarray, bins: int = 10) -> np.ndarray:
    """Each pair's score: the share of positives among the pairs of its (same, common) grid cell."""
    i = np.clip((same * bins).astype(np.int64), 0, bins - 1)
    j = np.clip((common * bins).astype(np.int64), 0, bins - 1)
    cell = i * bins + j
    count = np.bincount(cell, minlength=bins * bins)
    hits = np.bincount(cell, weights=positive.astype(np.float64), minlength=bins * bins)
    return (hits / np.maximum(count, 1))[cell]


def room_pairs(room: Path) -> dict[str, np.ndarray]:
    """Every compared pair of the room's views: votes, class labels."""
    from ..masks.patches import read_patches
    from ..scene import Scene
    from ..tracing.consistency import comembership, mask_vote, stack_comembership
    from ..tracing.git import GITVisible
    from ..tracing.merge import all_source_histograms, candidate_pairs
    from ..tracing.merge_quality import patch_owners

    room = Path(room)
    git = room / "trace-paper" / "git.npz"
    for need in (room / "scene", git, room / "patches"):
        if not need.exists():
            raise Trace3DError(f"bench merge-vote: {need} is missing; run the room's trace first "
                               f"(snakemake ... {room / 'trace-paper'}).")
    scene = Scene.read(room / "scene")
    if not (scene.has_instances and scene.objects is not None):
        raise Trace3DError(f"bench merge-vote: {room / 'scene'} has no ground truth (it needs a synthetic room).")
    stats = GITVisible.load(git, 0.0)
    hierarchies, maps = [], []
    for frame in stats.frames:
        patch_map, hierarchy = read_patches(room / "patches", frame)
        maps.append(patch_map)
        hierarchies.append(hierarchy)
    num_labels = int(stats.num_labels.max(initial=1))
    num_source = max(num_labels, max((h.num_patches + 1 for h in hierarchies), default=1))
    visible = stats.visible(0.0)
    stacks = {
        "same_patch": stack_comembership([comembership(h, num_labels, 0.0) for h in hierarchies], num_labels),
        "common_mask": stack_comembership([comembership(h, num_labels, 1.0) for h in hierarchies], num_labels),
        "mask_jaccard": stack_comembership([_jaccard_comembership(h, num_labels) for h in hierarchies], num_labels),
    }
    objects, groups = scene.objects.lookup("object"), scene.objects.lookup("group")
    cols: dict[str, list] = {k: [] for k in (*stacks, "omega", "should", "group_mates")}
    every = all_source_histograms(stats.label, visible, num_source, num_labels)
    for v, (hierarchy, hist) in enumerate(zip(hierarchies, every)):
        pairs = candidate_pairs(hierarchy, "all_pairs")
        if len(pairs) == 0:
            continue
        leaf = scene.instances(stats.frames[v]).astype(np.int64)
        truth = objects[np.clip(leaf, 0, len(objects) - 1)]
        owner = patch_owners(truth, maps[v], hierarchy.num_patches)
        a, b = owner[pairs[:, 0]], owner[pairs[:, 1]]
        counted = (a > 0) & (b > 0)
        sims = {}
        for name, stack in stacks.items():
            sims[name], omega = mask_vote(hist, pairs, stack, v)
        keep = counted & (omega > 0)
        for name in stacks:
            cols[name].append(sims[name][keep])
        cols["omega"].append(omega[keep])
        cols["should"].append((a == b)[keep])
        ga, gb = groups[np.clip(a, 0, len(groups) - 1)], groups[np.clip(b, 0, len(groups) - 1)]
        cols["group_mates"].append(((a != b) & (ga == gb) & (ga > 0))[keep])
    every.close()
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}


def _figures(pairs: dict[str, np.ndarray]) -> dict:
    should = pairs["should"].astype(bool)
    mates = pairs["group_mates"].astype(bool)
    unrelated = ~should & ~mates
    out = {"pairs": int(len(should)), "should_merge": int(should.sum()), "group_mates": int(mates.sum()),
           "unrelated": int(unrelated.sum()), "medians": {}, "scores": {}}
    for name in ("same_patch", "common_mask", "mask_jaccard"):
        x = pairs[name]
        out["medians"][name] = {cls: (float(np.median(x[m])) if m.any() else None)
                                for cls, m in (("should_merge", should), ("group_mates", mates),
                                               ("unrelated", unrelated))}
    scores = {name: pairs[name] for name in ("same_patch", "common_mask", "mask_jaccard")}
    for w in MIXES:
        scores[f"mix_w{w:g}"] = (1 - w) * pairs["same_patch"] + w * pairs["common_mask"]
    scores["binned_bayes"] = binned_bayes(pairs["same_patch"], pairs["common_mask"], should)
    for name, score in scores.items():
        out["scores"][name] = recall_at_precision(score, should)
    return out


def run_bench(rooms: list[Path]) -> dict:
    """Pair figures of each room and of all rooms pooled."""
    if not rooms:
        raise Trace3DError("bench merge-vote: name at least one room folder (--room results/dev/d200).")
    per_room, pooled = {}, None
    for room in rooms:
        log.info("merge-vote: %s", room)
        pairs = room_pairs(Path(room))
        per_room[Path(room).name] = _figures(pairs)
        pooled = pairs if pooled is None else {k: np.concatenate([pooled[k], pairs[k]]) for k in pairs}
    return {"what": __doc__.split("\n\n")[0].strip(), "rooms": per_room, "pooled": _figures(pooled)}
