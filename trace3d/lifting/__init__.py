"""Segmentation lifting: from consistent 2D instance maps to a scene that answers object queries.

The contract between the lifting step and the evaluation step (and the baselines) is small:

* a lift step writes a folder with ``lift.json`` whose ``"method"`` names how it lifted
  (e.g. ``"contrastive"``, ``"self_prompt"``, ``"labels"``), plus that method's own files;
* :func:`load_lifted` reads such a folder back, beside the Gaussians it was lifted on, as a
  :class:`LiftedScene`;
* evaluation only ever asks a :class:`LiftedScene` two questions about an :class:`ObjectQuery`
  (one reference view and a mask of the target on it): which Gaussians are the object
  (3D extraction, Table 2) and which pixels of other views are the object (novel-view 2D
  segmentation, Tables 3 and 4).

Methods register a loader with :func:`register_method`; the evaluation never imports a method.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable, Protocol, Sequence

import numpy as np

from ..errors import Trace3DError
from ..gaussians import GaussianModel
from ..scene import Camera, Scene


@dataclasses.dataclass(frozen=True)
class ObjectQuery:
    """One target object, given the way a user gives it: a mask on one reference view.

    reference: the frame name of the reference view (a training view of the scene).
    mask: [H, W] bool, the target's pixels on that view.
    object_id: the ground-truth id the query stands for (evaluation bookkeeping), or None.
    """

    reference: str
    mask: np.ndarray
    object_id: int | None = None


class LiftedScene(Protocol):
    """A fitted scene with lifted segmentation that answers object queries."""

    model: GaussianModel

    def object_gaussians(self, query: ObjectQuery) -> np.ndarray:
        """[N] bool: the Gaussians of the queried object."""

    def object_masks(self, query: ObjectQuery, cameras: Sequence[Camera]) -> list[np.ndarray]:
        """One [H, W] bool mask of the queried object per camera (any view, seen in training or not)."""


# loader(lift_dir, lift_json, model, scene, train_cameras) -> LiftedScene
Loader = Callable[[Path, dict, GaussianModel, Scene, Sequence[Camera]], LiftedScene]
_METHODS: dict[str, Loader] = {}
# the package's own methods, imported only when a lift folder names them (keeps this import cheap)
_BUILTIN = {"contrastive": ("trace3d.lifting.query", "load_feature_lifted"),
            "self_prompt": ("trace3d.lifting.self_prompt", "load_self_prompt")}


def register_method(name: str, loader: Loader) -> None:
    """Make ``lift.json``'s ``"method": name`` loadable by :func:`load_lifted`."""
    _METHODS[name] = loader


def load_lifted(lift_dir: str | Path, model: GaussianModel, scene: Scene,
                train_cameras: Sequence[Camera]) -> LiftedScene:
    """Read a lift step's folder back as a :class:`LiftedScene` over ``model``."""
    lift_dir = Path(lift_dir)
    path = lift_dir / "lift.json"
    if not path.is_file():
        raise Trace3DError(f"{path}: lift.json is missing; is {lift_dir} the output of a lift step?")
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise Trace3DError(f"{path}: not valid JSON ({exc}).") from exc
    method = info.get("method")
    if method not in _METHODS and method in _BUILTIN:
        import importlib

        module, name = _BUILTIN[method]
        register_method(method, getattr(importlib.import_module(module), name))
    if method not in _METHODS:
        known = ", ".join(sorted(set(_METHODS) | set(_BUILTIN))) or "none"
        raise Trace3DError(f"{path}: unknown lifting method {method!r} (known: {known}).")
    return _METHODS[method](lift_dir, info, model, scene, train_cameras)
