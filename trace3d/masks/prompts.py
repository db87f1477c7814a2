"""Promptable mask sources: point prompts on one view in, that view's mask of the prompted object out.

Used by self-prompting (:mod:`trace3d.lifting.self_prompt`). Three sources share one method,
``segment(frame, points, rng) -> [H, W] bool`` with ``points`` [K, 2] pixel (x, y) coordinates:

- :class:`SamPromptSegmenter`: SAM's ``SamPredictor`` (the ``segment_anything`` package and a
  checkpoint), all K points as positive prompts, the best-scored of SAM's three masks.
- :class:`trace3d.masks.graph.GraphPromptSegmenter` (``graph``): the image's nested multi-scale graph
  segmentation, the candidate closest to the rendered region (optionally GrabCut-refined); reads no
  ground truth, so it runs on any scene.
- :class:`SimulatedPromptSegmenter`: an **oracle** — it reads the scene's ground-truth instance maps
  and answers with SAM-like imperfections (:class:`trace3d.masks.simulate.SimulatedPromptSegmenter` answers each point: the
  object, sometimes its part or its group, jittered boundaries); the K answers are combined by a
  per-pixel majority (at least half of them), which is how extra positive points steady SAM.
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Mapping, Protocol

import numpy as np

from ..errors import Trace3DError
from ..scene import Scene


class PromptSegmenter(Protocol):
    def segment(self, frame: str, points: np.ndarray, rng: np.random.Generator,
                like: np.ndarray | None = None) -> np.ndarray:
        """[H, W] bool mask of the object under the positive point prompts ``points`` [K, 2] (x, y).

        ``like`` ([H, W] bool, optional): a mask the answer should resemble (the user's mask on the
        reference view): among the source's candidate granularities, the one closest to it (IoU) is
        taken, as a user picks one of SAM's three answers."""

    def settings(self) -> dict:
        """The source's settings (written to lift.json)."""


def frame_seed(seed: int, frame: str) -> np.random.Generator:
    """A generator that depends only on the seed and the frame name (not on the order views are visited)."""
    return np.random.default_rng([int(seed), zlib.crc32(frame.encode())])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def _check_points(points: np.ndarray, frame: str) -> np.ndarray:
    points = np.asarray(points, np.float64).reshape(-1, 2)
    if points.shape[0] == 0:
        raise Trace3DError(f"prompt segmenter: no point prompts for frame {frame!r}.")
    return points


class SimulatedPromptSegmenter:
    """Point prompts answered from ground truth (see the module docstring); deterministic given the rng."""

    def __init__(self, scene: Scene, params: Mapping | None = None):
        from .simulate import SimulatedPromptSegmenter as _Single

        self._single = _Single(scene, params)
        self.params = self._single.params

    def segment(self, frame: str, points: np.ndarray, rng: np.random.Generator,
                like: np.ndarray | None = None) -> np.ndarray:
        points = _check_points(points, frame)
        votes = None
        for x, y in points:
            if like is None:
                m = self._single.segment(frame, (float(x), float(y)), rng)
            else:
                m = self._closest(frame, (float(x), float(y)), rng, np.asarray(like, bool))
            m = m.astype(np.int32)
            votes = m if votes is None else votes + m
        return 2 * votes >= points.shape[0]

    def _closest(self, frame: str, point: tuple[float, float], rng: np.random.Generator, like: np.ndarray) -> np.ndarray:
        from .simulate import morph_jitter

        cands = self._single.candidates(frame, point)
        best = max(sorted(cands), key=lambda k: _iou(cands[k], like))
        mask = cands[best]
        radius = int(round(self.params.inconsistency * self.params.jitter_pixels))
        if radius > 0:
            jittered = morph_jitter(mask, int(rng.integers(-radius, radius + 1)))
            if jittered[int(point[1]), int(point[0])]:
                mask = jittered
        return mask.copy()

    def settings(self) -> dict:
        from ..params import to_dict

        return {"source": "simulated", "simulate": to_dict(self.params)}


def sam_problems(checkpoint: str | None) -> list[str]:
    problems = []
    try:
        import segment_anything  # noqa: F401
    except ImportError:
        problems.append("the `segment_anything` package is not installed "
                        "(pip install git+https://github.com/facebookresearch/segment-anything.git)")
    if checkpoint is None:
        problems.append("no SAM checkpoint is configured (set lift params `sam_checkpoint`, e.g. sam_vit_h_4b8939.pth)")
    elif not Path(checkpoint).is_file():
        problems.append(f"the SAM checkpoint file {checkpoint} does not exist")
    return problems


class SamPromptSegmenter:
    """SAM's point-prompted predictor on the scene's images."""

    def __init__(self, scene: Scene, checkpoint: str | None, model_type: str = "vit_h", device: str = "cpu"):
        problems = sam_problems(checkpoint)
        if problems:
            raise Trace3DError(f"the `sam` prompt source cannot run: {' and '.join(problems)}; use "
                               f"`prompt_source: graph` (graph segmentation of the images) or `prompt_source: simulated` "
                               f"(an oracle: prompts answered from ground truth) instead.")
        from segment_anything import SamPredictor, sam_model_registry

        self.scene = scene
        self.checkpoint, self.model_type, self.device = checkpoint, model_type, device
        model = sam_model_registry[model_type](checkpoint=checkpoint)
        model.to(device=device)
        self.predictor = SamPredictor(model)
        self._frame = None

    def segment(self, frame: str, points: np.ndarray, rng: np.random.Generator,
                like: np.ndarray | None = None) -> np.ndarray:
        points = _check_points(points, frame)
        if self._frame != frame:
            self.predictor.set_image(self.scene.image(frame))
            self._frame = frame
        masks, scores, _ = self.predictor.predict(point_coords=points.astype(np.float32),
                                                  point_labels=np.ones(points.shape[0], np.int64),
                                                  multimask_output=True)
        if like is not None:
            return np.asarray(max(masks, key=lambda m: _iou(np.asarray(m, bool), like)), bool)
        return np.asarray(masks[int(np.argmax(scores))], bool)

    def settings(self) -> dict:
        return {"source": "sam", "checkpoint": self.checkpoint, "model_type": self.model_type, "device": self.device}


def make_segmenter(source: str, scene: Scene, simulate: Mapping | None = None, sam_checkpoint: str | None = None,
                   sam_model_type: str = "vit_h", sam_device: str = "cpu",
                   graph: Mapping | None = None) -> PromptSegmenter:
    if source == "graph":
        from .graph import GraphPromptSegmenter

        return GraphPromptSegmenter(scene, graph)
    if source == "simulated":
        return SimulatedPromptSegmenter(scene, simulate)
    if source == "sam":
        return SamPromptSegmenter(scene, sam_checkpoint, sam_model_type, sam_device)
    raise Trace3DError(f"unknown prompt source {source!r} (expected simulated, sam or graph).")
