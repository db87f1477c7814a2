"""``trace3d bench prompts``: how well each prompt source answers self-prompting's point prompts.

Measured on a scene with ground truth (a synthetic room), without a fitted model: for every view and
every evaluated ground-truth object (object level) covering at least ``min_pixels`` pixels, the
prompts are drawn as self-prompting draws them (:func:`trace3d.lifting.self_prompt.sample_prompts`:
the deepest pixel and random inner pixels) from a *cue* region, the source is asked with
``like=cue``, and the answer is scored by its IoU with the ground-truth object mask. Two cues:

* ``reference``: the ground-truth object mask itself (the user's query mask on the reference view);
* ``rendered``: the mask shifted by up to ``shift`` pixels and dilated or eroded by one pixel, a
  stand-in for the object's rendered indicator region on a later view;

plus ``points_only`` (the reference prompts without ``like``). ``rendered_cue_iou`` is the rendered
cue's own IoU with the object (what answering with the cue unchanged would score). The ground truth is read only to make
the cues and to score; the ``graph`` sources never see it (the ``simulated`` oracle does).
Every random choice comes from ``seed``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..errors import Trace3DError
from ..scene import Scene

log = logging.getLogger(__name__)

SOURCES = {  # name: (prompt source, its parameters: SimulateParams or GraphPromptParams overrides)
    "simulated_oracle": ("simulated", {}),
    "graph": ("graph", {}),
    "graph_points": ("graph", {"select": "points"}),
    "graph_grabcut": ("graph", {"refine": "grabcut"}),
    "graph_mask_hierarchy": ("graph", {"graph": {}}),
}


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def _rendered_cue(mask: np.ndarray, rng: np.random.Generator, shift: int) -> np.ndarray:
    from ..masks.simulate import morph_jitter

    dy, dx = rng.integers(-shift, shift + 1, size=2)
    moved = np.roll(mask, (int(dy), int(dx)), axis=(0, 1))
    out = morph_jitter(moved, int(rng.choice([-1, 1])))
    return out if out.sum() >= 4 else moved


def run_bench(room: Path, views: int = 16, points: int = 3, min_pixels: int = 100, shift: int = 2,
              seed: int = 0, sources: dict | None = None) -> dict:
    """Mean / median IoU of each prompt source's answers against the ground truth (module docstring).

    Args:
        room: a canonical scene folder with instances/ and objects.json, or a room's results folder
            holding one in scene/.
        views: the first ``views`` frames are used.
    """
    from ..lifting.self_prompt import sample_prompts
    from ..masks.prompts import make_segmenter

    root = Path(room)
    if (root / "scene" / "cameras.json").is_file():
        root = root / "scene"
    scene = Scene.read(root)
    if not scene.has_instances or scene.objects is None:
        raise Trace3DError(f"{root}: bench prompts needs a scene with ground truth (instances/ and objects.json).")
    sources = SOURCES if sources is None else sources
    segmenters = {name: make_segmenter(kind, scene, simulate=params if kind == "simulated" else None,
                                       graph=params if kind == "graph" else None)
                  for name, (kind, params) in sources.items()}
    lookup = scene.objects.lookup("object")
    evaluated = set(scene.objects.evaluated_ids())
    scores: dict[str, dict[str, list[float]]] = {n: {"reference": [], "rendered": [], "points_only": []}
                                                 for n in segmenters}
    cue_iou: list[float] = []
    seconds = {n: 0.0 for n in segmenters}
    count = 0
    for v, cam in enumerate(scene.cameras[:views]):
        leaf = scene.instances(cam.name)
        obj = lookup[np.minimum(leaf, len(lookup) - 1)]
        obj[leaf == 0] = 0
        for o in np.unique(obj):
            truth = obj == o
            if o == 0 or int(o) not in evaluated or truth.sum() < min_pixels:
                continue
            count += 1
            rng = np.random.default_rng([seed, v, int(o)])
            cue = _rendered_cue(truth, rng, shift)
            ref_points = sample_prompts(truth, points, rng)
            cue_points = sample_prompts(cue, points, rng)
            cue_iou.append(_iou(cue, truth))
            for name, seg in segmenters.items():
                t0 = time.perf_counter()
                ask_rng = np.random.default_rng([seed, v, int(o), 1])
                answers = {
                    "reference": seg.segment(cam.name, ref_points, ask_rng, like=truth),
                    "rendered": seg.segment(cam.name, cue_points, ask_rng, like=cue),
                    "points_only": seg.segment(cam.name, ref_points, ask_rng),
                }
                seconds[name] += time.perf_counter() - t0
                for cue_name, answer in answers.items():
                    scores[name][cue_name].append(_iou(answer, truth))
    if not count:
        raise Trace3DError(f"{root}: no evaluated object covers {min_pixels} pixels in the first {views} views.")
    log.info("bench prompts: %d object views", count)
    return {
        "scene": str(root), "views": min(views, len(scene.cameras)), "object_views": count, "points": points,
        "shift": shift, "seed": seed,
        "sources": {name: {"source": kind, "params": params} for name, (kind, params) in sources.items()},
        "iou": {name: {cue: {"mean": float(np.mean(vals)), "median": float(np.median(vals))}
                       for cue, vals in per.items()} for name, per in scores.items()},
        "rendered_cue_iou": {"mean": float(np.mean(cue_iou)), "median": float(np.median(cue_iou))},
        "seconds_per_object_view": {name: s / count for name, s in seconds.items()},
    }
