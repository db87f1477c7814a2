"""The ``lift`` step: ``params.method`` picks contrastive lifting or self-prompting.

Outputs (in ``out_dir``):

- ``lift.json``: method, resolved params, seconds (and, for contrastive lifting, the final loss,
  the pixel-weight memory and timings);
- contrastive: ``features.npy`` [N, D] float32 in the Gaussians' PLY order, ``loss.csv``,
  ``loss.png``, ``pca.png`` (PCA of the rendered feature map on a few test views beside RGB);
- self_prompt: nothing else (self-prompting runs per query; lift.json names the mask source, which
  is checked here so that a missing SAM fails at this step, not at evaluation).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError

log = logging.getLogger(__name__)

METHODS = ("contrastive", "self_prompt", "labels")


def parse_lift_params(params: dict | None):
    """The method's parameter dataclass from the step's mapping (``method`` defaults to contrastive)."""
    from ..params import from_mapping

    params = dict(params or {})
    method = params.get("method", "contrastive")
    if method == "contrastive":
        from .contrastive import ContrastiveParams

        return from_mapping(ContrastiveParams, params, "lift params")
    if method == "self_prompt":
        from .self_prompt import SelfPromptParams

        return from_mapping(SelfPromptParams, params, "lift params")
    if method == "labels":
        from .labels import LabelsParams

        return from_mapping(LabelsParams, {k: v for k, v in params.items() if k not in ("method", "preset")},
                            "lift params (labels)")
    raise ConfigError(f"lift params.method: {method!r} is not one of {list(METHODS)}.")


def patch_hierarchies(labels_dir: Path, cameras, setting: str) -> list:
    """Per training view its patch map and the patch step's hierarchy beside it (for ``undecided: ignore`` and
    ``coarse_depth``, named by ``setting``); one sentence if the folder holds none (merged maps)."""
    from ..masks.patches import read_patches

    out = []
    for cam in cameras:
        path = labels_dir / f"{cam.name}.json"
        if not path.is_file():
            raise ConfigError(f"lift params.{setting} needs the patch step's hierarchy {path}; use it on "
                              f"the raw patches (consistent_masks: false), not on merged instance maps.")
        out.append(read_patches(labels_dir, cam.name))  # checks the map against it
    return out


def _final_loss(history: list) -> float | None:
    """The mean loss over the last twentieth of a training history ((iteration, loss) pairs); None if empty."""
    tail = [v for _, v in history[-max(1, len(history) // 20):]]
    return float(np.mean(tail)) if tail else None


def run_lift(scene, poses_dir: Path | None, gaussians_dir: Path, labels_dir: Path | None, out_dir: Path,
             params: dict, progress: bool = True) -> dict:
    """Run the lift step into ``out_dir``; returns the lift.json content."""
    from ..io import write_json
    from ..params import to_dict
    from ..tracing.git import load_fitted, load_label_maps

    p = parse_lift_params(params)
    if (params or {}).get("method") == "labels":  # closed-form assignment (FlashSplat-style), no training
        from .labels import run_labels_lift

        if labels_dir is None:
            raise ConfigError("lift params.method labels needs --labels (instance maps with ids consistent across views).")
        return run_labels_lift(scene, poses_dir, gaussians_dir, Path(labels_dir), Path(out_dir), to_dict(p))
    out_dir = Path(out_dir)
    start = time.perf_counter()
    model, cameras = load_fitted(scene, poses_dir, gaussians_dir)
    train = [c for c in cameras if c.split == "train"]
    if p.method == "self_prompt":
        from .self_prompt import make_prompt_segmenter

        segmenter = make_prompt_segmenter(scene, p)
        info = {"method": "self_prompt", "params": to_dict(p), "source": segmenter.settings(),
                "gaussians": len(model), "seconds": time.perf_counter() - start}
        write_json(out_dir / "lift.json", info)
        return info

    from .contrastive import lift_features, loss_picture, pca_picture, write_history

    if labels_dir is None:
        raise ConfigError("lift: contrastive lifting needs --labels (the consistent instance maps).")
    maps = load_label_maps(labels_dir, [c.name for c in train], "instance map", [(c.width, c.height) for c in train])
    relations = coarse_maps = None
    if p.undecided == "ignore" or p.coarse_depth is not None:  # read before any training: a bad folder stops at once
        from ..masks.patches import coarser_patches
        from .contrastive import related_patches

        read = patch_hierarchies(Path(labels_dir), train,
                                 "undecided: ignore" if p.undecided == "ignore" else "coarse_depth")
        if p.undecided == "ignore":
            relations = [related_patches(h) for _, h in read]
        if p.coarse_depth is not None:
            coarse_maps = [[coarser_patches(m, h, depth) for m, h in read] for depth in p.coarse_depths]
    labels_per_view = [int(np.unique(m[m > 0]).size) for m in maps]
    most = max(labels_per_view, default=0)
    warning = None
    if most < 2:  # the loss pulls one instance together and pushes nothing apart: it reaches 0 and says nothing
        warning = (f"no training view's instance map in {labels_dir} holds two instances (at most {most}); the "
                   f"contrastive loss has nothing to separate, so the features will not tell objects apart")
        log.warning("lift: %s; check the masks (or the merge) that made these maps", warning)
    features, history, timing = lift_features(model, train, maps, p, progress=progress, relations=relations)
    coarse_info = {}
    if coarse_maps is not None:
        import dataclasses

        single = isinstance(p.coarse_depth, int)  # one block: loss_coarse.csv and a dict; a list: per depth
        blocks, parts = [], [features]
        for depth, depth_maps in zip(p.coarse_depths, coarse_maps):
            counts = [int(np.unique(m[m > 0]).size) for m in depth_maps]
            log.info("lift: a coarse block on the patches regrouped by the masks at most %d deep: %.1f labels per "
                     "view (the patches: %.1f)", depth, float(np.mean(counts)), float(np.mean(labels_per_view)))
            coarse, coarse_history, coarse_timing = lift_features(
                model, train, depth_maps, dataclasses.replace(p, undecided="push"), progress=progress)
            parts.append(coarse)
            write_history(out_dir / ("loss_coarse.csv" if single else f"loss_coarse_{depth}.csv"), coarse_history)
            blocks.append({"depth": depth, "labels_per_view": float(np.mean(counts)),
                           "final_loss": _final_loss(coarse_history), "train_seconds": coarse_timing["train_seconds"]})
        features = np.concatenate(parts, axis=1)
        coarse_info = {"coarse": blocks[0] if single else blocks}
    np.save(out_dir / "features.npy", features)
    write_history(out_dir / "loss.csv", history)
    loss_picture(out_dir / "loss.png", history)
    test = [c for c in cameras if c.split == "test"] or train
    views = [test[i] for i in np.linspace(0, len(test) - 1, min(p.pca_views, len(test))).round().astype(int)]
    pca_picture(out_dir / "pca.png", model, views, features, scene, p.near)
    info = {"method": "contrastive", "params": to_dict(p), "gaussians": len(model), "dim": int(features.shape[1]),
            "seconds": time.perf_counter() - start, "final_loss": _final_loss(history),
            **timing, **coarse_info}
    if warning:
        info["warning"] = warning
    write_json(out_dir / "lift.json", info)
    log.info("contrastive lifting: %d Gaussians, %d iterations, final loss %.4f, %.1f s", len(model), p.iterations,
             info["final_loss"], info["seconds"])
    return info
