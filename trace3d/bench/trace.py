"""``trace3d bench trace``: the cost of GIT, merging and ambiguity detection on a fitted default room.

Figures (one JSON object):

- ``trace_over_render``: tracing every training view's patch map / rendering every training view
  (colour, no gradient) — GIT is meant to cost about one render.
- ``merge_share``: merge seconds (best of 3) / (trace + merge + one refine detection) seconds (goal <= 0.10).
- ``hierarchical_over_paper``: the hierarchical merge's seconds (``merge: {method: hierarchical}``, best
  of 3) / the paper merge's (goal <= 2).
- ``sweep``: trace + merge seconds over random subsets of the Gaussians and of the views, and
  ``scaling_slope``, the least-squares slope of log(time) against log(Gaussians x views) (goal <= 1.1:
  linear), with the slopes along each axis alone.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import Trace3DError

log = logging.getLogger(__name__)


def _timed(fn, repeats: int = 1) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def run_bench(room: Path, quick: bool = False) -> dict:
    """Benchmark on ``room`` (a results folder with scene/, poses/, gaussians/, patches/)."""
    from ..masks.patches import read_patches
    from ..scene import Scene
    from ..training import render_view
    from ..tracing.git import load_fitted, trace_views
    from ..tracing.merge import MergeParams, merge_all
    from ..tracing.refine import find_ambiguous

    room = Path(room)
    for part in ("scene", "poses", "gaussians/point_cloud.ply", "patches"):
        if not (room / part).exists():
            raise Trace3DError(f"{room / part}: missing; fit a room first (e.g. `snakemake --cores 2 "
                               f"{room}/patches {room}/gaussians`) or pass --room.")
    scene = Scene.read(room / "scene")
    model, cameras = load_fitted(scene, room / "poses", room / "gaussians")
    train = [c for c in cameras if c.split == "train"]
    if quick:
        train = train[:12]
    patches = [read_patches(room / "patches", c.name) for c in train]
    maps = [p[0].astype(np.int64) for p in patches]
    hierarchies = [p[1] for p in patches]
    params = MergeParams()
    torch.set_grad_enabled(False)
    warm = trace_views(model, train[:2], maps[:2])  # compile / warm up the kernels
    merge_all(warm, hierarchies[:2], params)
    render_s, _ = _timed(lambda: [render_view(model, c, model.sh_degree, None) for c in train])
    trace_s, stats = _timed(lambda: trace_views(model, train, maps))
    merge_s, (merges, luts) = _timed(lambda: merge_all(stats, hierarchies, params), repeats=3)
    hier_s, _ = _timed(lambda: merge_all(stats, hierarchies, MergeParams(method="hierarchical")), repeats=3)
    consistent = [lut[m.lut[x]] for x, m, lut in zip(maps, merges, luts)]

    def detection():
        refined = trace_views(model, train, consistent)
        return find_ambiguous(refined, 0.8, 0.5, 0.0)

    detect_s, _ = _timed(detection)
    result = {
        "room": str(room), "gaussians": len(model), "views": len(train),
        "width": train[0].width, "height": train[0].height,
        "render_s": render_s, "trace_s": trace_s, "merge_s": merge_s, "detect_s": detect_s,
        "trace_over_render": trace_s / render_s,
        "merge_share": merge_s / (trace_s + merge_s + detect_s),
        "hierarchical_merge_s": hier_s, "hierarchical_over_paper": hier_s / merge_s,
    }
    rng = np.random.default_rng(0)
    fractions = (0.25, 0.5, 1.0) if not quick else (0.5, 1.0)
    rows = []
    for fg in fractions:
        keep = np.sort(rng.permutation(len(model))[: max(1, int(fg * len(model)))])
        sub = model.subset(torch.from_numpy(keep))
        for fv in fractions:
            count = max(2, int(round(fv * len(train))))
            views = np.sort(rng.permutation(len(train))[:count])
            cams = [train[i] for i in views]
            sub_maps = [maps[i] for i in views]
            sub_h = [hierarchies[i] for i in views]
            t_s, sub_stats = _timed(lambda: trace_views(sub, cams, sub_maps))
            m_s, _ = _timed(lambda: merge_all(sub_stats, sub_h, params), repeats=3)
            rows.append({"gaussians": len(sub), "views": count, "trace_s": t_s, "merge_s": m_s,
                         "total_s": t_s + m_s})
    size = np.log([r["gaussians"] * r["views"] for r in rows])
    total = np.log([r["total_s"] for r in rows])
    result["sweep"] = rows
    result["scaling_slope"] = float(np.polyfit(size, total, 1)[0])
    full_g = [r for r in rows if r["gaussians"] == max(x["gaussians"] for x in rows)]
    full_v = [r for r in rows if r["views"] == max(x["views"] for x in rows)]
    result["slope_views"] = float(np.polyfit(np.log([r["views"] for r in full_g]),
                                             np.log([r["total_s"] for r in full_g]), 1)[0])
    result["slope_gaussians"] = float(np.polyfit(np.log([r["gaussians"] for r in full_v]),
                                                 np.log([r["total_s"] for r in full_v]), 1)[0])
    return result
