"""The ``merge`` step's quality figures against the ground truth (synthetic benchmark; definitions in
docs/tracing.md): the adjusted Rand index, coverage and straddling of instance maps
(:func:`segmentation_quality`) and the per-pair merge decisions (:class:`PairQuality`,
:func:`view_pair_quality`). :func:`trace3d.tracing.merge.run_merge` writes them into merge.json."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:
    from .merge import ViewMerge


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


def patch_owners(truth: np.ndarray, patch_map: np.ndarray, num_patches: int) -> np.ndarray:
    """[P + 1] int64: the ground-truth object holding most of each patch's pixels (unlabelled pixels,
    id 0, count as an object of their own; ties go to the smaller id); 0 for a patch whose majority
    is unlabelled or that has no pixels. Entry 0 (uncovered pixels) is 0.

    Args:
        truth: [H, W] ground-truth ids (0 unlabelled); patch_map: [H, W] patch ids (0 uncovered).
    """
    p = patch_map.astype(np.int64).ravel()
    _, t = np.unique(truth.astype(np.int64).ravel(), return_inverse=True)
    ids = np.unique(truth)
    table = np.zeros((num_patches + 1, len(ids)), np.int64)
    np.add.at(table, (np.clip(p, 0, num_patches), t.ravel()), 1)
    owner = ids[table.argmax(axis=1)].astype(np.int64)
    owner[table.sum(axis=1) == 0] = 0
    owner[0] = 0
    return owner


@dataclass
class PairQuality:
    """Per-pair merge decisions against the ground truth, summed over views (docs/tracing.md).

    A patch *belongs* to the ground-truth object holding most of its pixels (:func:`patch_owners`);
    patches whose majority is unlabelled are left out, with every pair they are in. A pair *should
    merge* when both patches belong to the same object.
    """

    patches: int = 0  # patches counted (majority on a labelled object)
    excluded_patches: int = 0  # patches left out (majority unlabelled, or no pixels)
    candidates: int = 0  # candidate pairs of counted patches
    candidates_should_merge: int = 0
    merged: int = 0  # candidate pairs whose similarity exceeded the threshold
    merged_should_merge: int = 0
    unsupported: int = 0  # candidate pairs without the rule's minimum support (never merged)
    should_merge: int = 0  # all pairs of counted patches within a view that should merge
    out_of_reach: int = 0  # ... that were not candidates
    joined: int = 0  # pairs of counted patches that ended in one instance (transitively too)
    joined_should_merge: int = 0

    @staticmethod
    def _ratio(a: int, b: int) -> float | None:
        return a / b if b else None

    @property
    def precision(self) -> float | None:
        """Merged candidate pairs that should merge / merged candidate pairs."""
        return self._ratio(self.merged_should_merge, self.merged)

    @property
    def recall(self) -> float | None:
        """Should-merge candidate pairs that were merged / should-merge candidate pairs."""
        return self._ratio(self.merged_should_merge, self.candidates_should_merge)

    @property
    def out_of_reach_share(self) -> float | None:
        """Should-merge pairs that were never candidates / all should-merge pairs."""
        return self._ratio(self.out_of_reach, self.should_merge)

    @property
    def joined_precision(self) -> float | None:
        return self._ratio(self.joined_should_merge, self.joined)

    @property
    def joined_recall(self) -> float | None:
        """Should-merge pairs (candidates or not) that ended in one instance / all should-merge pairs."""
        return self._ratio(self.joined_should_merge, self.should_merge)

    def add(self, other: "PairQuality") -> None:
        for key in self.__dataclass_fields__:
            setattr(self, key, getattr(self, key) + getattr(other, key))

    def to_dict(self) -> dict:
        out = {key: int(getattr(self, key)) for key in self.__dataclass_fields__}
        for key in ("precision", "recall", "out_of_reach_share", "joined_precision", "joined_recall"):
            out[key] = getattr(self, key)
        return out


def view_pair_quality(truth: np.ndarray, patch_map: np.ndarray, merge: ViewMerge) -> tuple[PairQuality, list]:
    """:class:`PairQuality` of one view's merge, and the view's out-of-reach pairs [[a, b], ...].

    Args:
        truth: [H, W] ground-truth ids (0 unlabelled); patch_map: [H, W] patch ids; merge: the view's merge.
    """
    num_patches = len(merge.lut) - 1
    owner = patch_owners(truth, patch_map, num_patches)
    counted = owner > 0
    q = PairQuality(patches=int(counted[1:].sum()), excluded_patches=int((~counted[1:]).sum()))
    ids = np.nonzero(counted)[0]
    a, b = np.triu_indices(len(ids), k=1)
    a, b = ids[a], ids[b]
    should = owner[a] == owner[b]
    joined = merge.lut[a] == merge.lut[b]
    q.should_merge = int(should.sum())
    q.joined = int(joined.sum())
    q.joined_should_merge = int((should & joined).sum())
    pairs = merge.pairs.reshape(-1, 2)
    keep = counted[pairs[:, 0]] & counted[pairs[:, 1]]
    pairs, merged = pairs[keep], merge.merged[keep]
    supported = merge.supported[keep] if merge.supported is not None else np.ones(len(pairs), bool)
    cand_should = owner[pairs[:, 0]] == owner[pairs[:, 1]]
    q.candidates = int(len(pairs))
    q.candidates_should_merge = int(cand_should.sum())
    q.merged = int(merged.sum())
    q.merged_should_merge = int((merged & cand_should).sum())
    q.unsupported = int((~supported).sum())
    width = num_patches + 1
    candidate_keys = set((pairs[:, 0] * width + pairs[:, 1]).tolist())
    reach = [[int(x), int(y)] for x, y in zip(a[should], b[should]) if int(x) * width + int(y) not in candidate_keys]
    q.out_of_reach = len(reach)
    return q, reach
