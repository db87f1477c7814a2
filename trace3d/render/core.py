"""Public rendering API: :func:`render`, :func:`trace`, :func:`trace_argmax`.

Back ends: ``"numba"`` (CPU tile kernels with a hand-written backward, the default) and
``"reference"`` (dense pure torch, the oracle).  Both share :func:`~trace3d.render.projection.project`.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from ..errors import Trace3DError
from ..scene import Camera
from .projection import Projected, Splats, check_splats, project, visible_mask
from .reference import render_reference

log = logging.getLogger(__name__)

BACKENDS = ("numba", "reference")
_default_backend = "numba"


def set_default_backend(name: str) -> None:
    """Select the back end used when ``render``/``trace`` get ``backend=None``."""
    global _default_backend
    if name not in BACKENDS:
        raise Trace3DError(f"render: unknown backend {name!r} (expected one of {list(BACKENDS)}).")
    _default_backend = name


def _backend(name: Optional[str]) -> str:
    name = _default_backend if name is None else name
    if name not in BACKENDS:
        raise Trace3DError(f"render: unknown backend {name!r} (expected one of {list(BACKENDS)}).")
    return name


@dataclasses.dataclass
class RenderOutput:
    """What :func:`render` returns.

    Attributes:
        features: [H, W, C] blended features (colour when features are RGB), background added.
        alpha: [H, W] accumulated opacity, sum_k w_k.
        depth: [H, W] expected depth sum_k w_k z_k (not normalised by alpha).
        normal: [H, W, 3] sum_k w_k n_k, camera-space normals facing the camera.
        median_depth: [H, W] z of the splat at which the transmittance crosses 0.5 (0 where empty).
        distortion: [H, W] depth distortion sum_{i,j} w_i w_j (z_i - z_j)^2 (the squared form the
            official 2DGS CUDA code uses; order-independent, so exact in one pass), or None unless
            ``with_distortion``.
        means2d: [N, 2] projected centres; after ``backward`` its ``.grad`` is the screen-space
            positional gradient used by 3DGS/2DGS densification (None when nothing needed grad).
        visible: [N] bool, splats whose footprint touched the image.
        radii: [N] int32, half of the larger side of the footprint box in pixels (0 when culled).
        rows: None (``render`` itself); set by the training loop's compact gradients
            (:mod:`trace3d.training.sparse`) to the model rows [N] of the rendered splats, so that
            density control can file their statistics.
    """

    features: Tensor
    alpha: Tensor
    depth: Tensor
    normal: Tensor
    median_depth: Tensor
    distortion: Optional[Tensor]
    means2d: Tensor
    visible: Tensor
    radii: Tensor
    rows: Optional[Tensor] = None


def _check_features(features: Tensor, n: int, what: str) -> None:
    if not isinstance(features, Tensor) or features.dim() != 2 or features.shape[0] != n:
        got = tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__
        raise Trace3DError(f"render: {what} must have shape [N={n}, C], got {got}.")
    if features.shape[1] < 1:
        raise Trace3DError(f"render: {what} needs at least one channel.")


def render(splats: Splats, camera: Camera, features: Tensor | Callable[[Optional[Tensor]], Tensor],
           background: Optional[Tensor] = None, near: float = 0.01, with_distortion: bool = False,
           backend: Optional[str] = None) -> RenderOutput:
    """Render splats into ``camera``.

    Differentiable with respect to means, quats, scales, opacities, features and background.

    The numba back end rasterizes only the splats the view sees (``visible``): the kernels' inputs,
    outputs and the gradients' per-worker buffers are sized by them, not by N.

    Args:
        splats: N splats (activated scales and opacities).
        camera: the camera (its width, height, K, world_to_camera).
        features: [N, C] per-splat features (RGB colour, or C up to a few hundred); or a function
            ``rows -> [R, C]`` that computes the features of the splats ``rows`` ([R] int64,
            ascending; ``None`` for all N), so that a view pays only for the splats it sees (the
            training loop's SH colours).
        background: [C] added with the final transmittance, or None for zeros.
        near: near plane (camera z) for culling centres and ray-plane intersections.
        with_distortion: also compute ``distortion``.
        backend: "numba", "reference" or None for the default.
    Returns:
        a :class:`RenderOutput`.
    """
    n = check_splats(splats)
    name = _backend(backend)
    if not callable(features):
        _check_features(features, n, "features")
    proj = project(splats, camera, near)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    rows = None
    if name == "numba":
        rows = torch.nonzero(proj.visible).squeeze(1)
        if rows.numel() == n:
            rows = None  # everything visible: no selection needed
    if callable(features):
        features = features(rows)
        _check_features(features, n if rows is None else rows.numel(), "features(rows)")
    elif rows is not None:
        features = features.index_select(0, rows)
    c = features.shape[1]
    if background is None:
        background = torch.zeros(c, device=features.device, dtype=features.dtype)
    if background.shape != (c,):
        raise Trace3DError(f"render: background must have shape [{c}], got {tuple(background.shape)}.")
    if name == "reference":
        out = render_reference(proj, features, camera.width, camera.height, background, near)
    else:
        from .kernels.rasterize import rasterize

        out = rasterize(proj if rows is None else proj.select(rows), features, camera.width, camera.height,
                        background, near)
    distortion = None
    if with_distortion:
        # sum_{i,j} w_i w_j (z_i - z_j)^2 = 2 (W S2 - S1^2) with depths taken relative to depth_ref
        centred = out["depth"] - out["alpha"] * out["depth_ref"].detach()
        distortion = 2.0 * (out["alpha"] * out["depth2"] - centred * centred)
    boxes = torch.as_tensor(proj.boxes, device=proj.depths.device)
    half = torch.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]).clamp_min(0)
    radii = torch.where(proj.visible, (half + 1) // 2, torch.zeros_like(half)).to(torch.int32)
    return RenderOutput(
        features=out["features"], alpha=out["alpha"], depth=out["depth"], normal=out["normal"],
        median_depth=out["median_depth"], distortion=distortion, means2d=proj.means2d,
        visible=proj.visible, radii=radii,
    )


_LABEL_DTYPES = (torch.int64, torch.int32, torch.int16, torch.uint8, torch.uint16, torch.uint32)


def _check_labels(labels: Tensor, camera: Camera, num_labels: int) -> Tensor:
    """Validate a label map and return it as int64 (patch maps are uint16 PNGs)."""
    if not isinstance(labels, Tensor) or labels.shape != (camera.height, camera.width):
        got = tuple(labels.shape) if hasattr(labels, "shape") else type(labels).__name__
        raise Trace3DError(f"trace: labels for camera {camera.name!r} must have shape "
                           f"[{camera.height}, {camera.width}], got {got}.")
    if labels.dtype not in _LABEL_DTYPES:
        raise Trace3DError(f"trace: labels for camera {camera.name!r} must be integers, got {labels.dtype}.")
    if num_labels < 1:
        raise Trace3DError(f"trace: num_labels must be >= 1, got {num_labels}.")
    labels = labels.to(torch.int64)  # unsigned 16/32-bit tensors lack most torch reductions
    if labels.numel() and int(labels.max()) >= num_labels:
        raise Trace3DError(f"trace: labels for camera {camera.name!r} reach {int(labels.max())} "
                           f"but num_labels is {num_labels}.")
    return labels


def trace(splats: Splats, camera: Camera, labels: Tensor, num_labels: int, near: float = 0.01,
          backend: Optional[str] = None, count_pixels: bool = False) -> Tensor:
    """Gaussian Instance Tracing for one view.

    W[k, j] = sum over pixels x with labels[x] == j of w_k(x), the blending weight of splat k at x.
    Pixels with a negative label are ignored.  Summed over j (all labels, background included)
    a row is the splat's total visibility in the view, and summed over splats at one pixel it is
    that pixel's alpha.  It equals d/d f_k[j] of sum_x <onehot(labels[x]), F(x)> where F renders
    features f (a backward pass with one-hot upstream gradients), which the tests check.

    Args:
        splats: N splats.
        camera: the view.
        labels: [H, W] integer patch labels in 0..num_labels-1 (negative = ignored); any integer
            dtype, uint16 patch maps included.
        count_pixels: count the pixels of each label a splat contributes to (w_k(x) > 0) instead
            of summing its weights: the official Trace3D code's statistic (``numba`` back end only).
        num_labels: T (may be large, e.g. one label per pixel: memory is bounded by tracing the
            tiles in batches, plus the non-zero output).
    Returns:
        sparse COO tensor [N, T] (float32, coalesced, no gradient).
    """
    n = check_splats(splats)
    labels = _check_labels(labels, camera, num_labels)
    name = _backend(backend)
    if name == "reference":
        if count_pixels:
            raise Trace3DError("trace: count_pixels needs the numba back end.")
        with torch.no_grad():
            proj = project(splats, camera, near)
        dense = _trace_by_backward(proj, camera, labels, num_labels, near, "reference")
        return dense.to_sparse().coalesce()
    seen, rows, cols, w = traced_triplets(splats, camera, labels, near, count_pixels)
    return _coalesced_weights(seen, rows, cols, w, n, num_labels).to(splats.means.device)


def _coalesced_weights(seen: np.ndarray, rows: np.ndarray, cols: np.ndarray, w: np.ndarray, n: int,
                       num_labels: int) -> Tensor:
    """The trace kernel's triplets (rows: positions in ``seen``, the ascending splats the view sees)
    summed per (splat, label) into a coalesced sparse COO [n, num_labels] tensor (CPU)."""
    from .kernels.coalesce import coalesce_triplets

    rows, cols, w, _ = coalesce_triplets(rows, cols, w, seen.shape[0])
    idx = torch.from_numpy(np.stack([seen[rows], cols]))  # seen is ascending: still sorted
    return torch.sparse_coo_tensor(idx, torch.from_numpy(w), (n, num_labels), check_invariants=False,
                                   is_coalesced=True)


def traced_triplets(splats: Splats, camera: Camera, labels: Tensor, near: float = 0.01, count_pixels: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The numba trace kernel's output for one view (labels checked by the caller): ``seen`` [R] int64,
    the splats the view sees (ascending), and the triplets rows [E] (positions in ``seen``), cols [E]
    (labels), weights [E] float32 in tile order (:func:`~trace3d.render.kernels.trace_triplets`).

    Only the seen splats are projected and traced: the projection is row by row, so their values are
    those of the whole projection, and a view of a room sees about a fifth of it.
    """
    from .kernels.trace import trace_triplets

    with torch.no_grad():
        seen = torch.nonzero(visible_mask(splats, camera, near)).squeeze(1)
        proj = project(Splats(*(t.detach().index_select(0, seen) for t in splats)), camera, near)
        rows, cols, w = trace_triplets(proj, camera.width, camera.height, labels, near, count_pixels=count_pixels)
    return seen.cpu().numpy(), rows, cols, w


def trace_reduced(splats: Splats, camera: Camera, labels: Tensor, num_labels: int, near: float = 0.01,
                  backend: Optional[str] = None, count_pixels: bool = False,
                  out: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]] = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`trace_argmax` of :func:`trace` as numpy arrays (label [N] int32, probability [N] and
    total [N] float32), the per-view reduction GIT's statistics keep; written into ``out`` (three
    such arrays, strided views allowed: a column of an [N, views] table) when given.

    The numba back end reduces the kernel's coalesced triplets directly
    (:func:`~trace3d.render.kernels.reduce_into_rows`, bit for bit :func:`trace_argmax` of
    :func:`trace`, tested) instead of building the [N, T] sparse tensor and reducing it with torch.
    """
    n = check_splats(splats)
    name = _backend(backend)
    if out is None:
        out = (np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32))
    if any(a.shape != (n,) for a in out) or [a.dtype for a in out] != [np.int32, np.float32, np.float32]:
        raise Trace3DError(f"trace_reduced: out must be three [{n}] arrays (int32, float32, float32).")
    if name == "reference":
        reduced = trace_argmax(trace(splats, camera, labels, num_labels, near, name, count_pixels))
        for dst, src in zip(out, reduced):
            dst[:] = src.cpu().numpy()
        return out
    labels = _check_labels(labels, camera, num_labels)
    from .kernels.coalesce import coalesce_triplets, reduce_into_rows

    seen, rows, cols, w = traced_triplets(splats, camera, labels, near, count_pixels)
    _, cols, w, indptr = coalesce_triplets(rows, cols, w, seen.shape[0])
    reduce_into_rows(indptr, cols, w, seen, *out)
    return out


def trace_by_backward(splats: Splats, camera: Camera, labels: Tensor, num_labels: int, near: float = 0.01,
                      backend: Optional[str] = None) -> Tensor:
    """Dense W [N, T] computed as the gradient of sum_x <onehot(labels[x]), F(x)> w.r.t. features.

    The definition of GIT as one backward pass; :func:`trace` must agree with it (tested).
    """
    check_splats(splats)
    labels = _check_labels(labels, camera, num_labels)
    with torch.no_grad():
        proj = project(splats, camera, near)
    return _trace_by_backward(proj, camera, labels, num_labels, near, _backend(backend))


def _trace_by_backward(proj: Projected, camera: Camera, labels: Tensor, num_labels: int, near: float,
                       name: str) -> Tensor:
    n = proj.depths.shape[0]
    dev = proj.depths.device
    dt = proj.ray_transforms.dtype
    lab = labels.to(device=dev, dtype=torch.int64)
    onehot = torch.zeros(camera.height, camera.width, num_labels, device=dev, dtype=dt)
    valid = lab >= 0
    onehot[valid] = torch.nn.functional.one_hot(lab[valid], num_labels).to(dt)
    with torch.enable_grad():
        feats = torch.zeros(n, num_labels, device=dev, dtype=dt, requires_grad=True)
        bg = torch.zeros(num_labels, device=dev, dtype=dt)
        if name == "reference":
            out = render_reference(proj, feats, camera.width, camera.height, bg, near)
        else:
            from .kernels.rasterize import rasterize

            out = rasterize(proj, feats, camera.width, camera.height, bg, near)
        (grad,) = torch.autograd.grad((out["features"] * onehot).sum(), feats, allow_unused=True)
    if grad is None:
        grad = torch.zeros(n, num_labels, device=dev, dtype=dt)
    return grad


def trace_argmax(weights: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-view reduction of a trace (the paper's supplementary, "Scalability of GIT").

    Args:
        weights: [N, T] sparse COO or dense trace weights of one view.
    Returns:
        label [N] int64 (argmax over T; -1 where the splat has no weight in this view),
        probability [N] (max / total; 0 where total is 0), total [N] (sum over T).
    """
    if weights.dim() != 2:
        raise Trace3DError(f"trace_argmax: weights must be [N, T], got {tuple(weights.shape)}.")
    n = weights.shape[0]
    dev = weights.device
    if weights.is_sparse:
        w = weights.coalesce()
        rows, cols = w.indices()
        vals = w.values()
        total = torch.zeros(n, device=dev, dtype=vals.dtype).index_add_(0, rows, vals)
        best = torch.zeros(n, device=dev, dtype=vals.dtype).scatter_reduce_(0, rows, vals, "amax", include_self=True)
        # smallest column attaining the max (deterministic ties)
        is_best = (vals == best[rows]) & (vals > 0)
        big = torch.full((n,), weights.shape[1], device=dev, dtype=torch.int64)
        label = big.scatter_reduce(0, rows[is_best], cols[is_best], "amin", include_self=True)
    else:
        total = weights.sum(1)
        best, label = (weights.max(1) if weights.shape[1]
                       else (torch.zeros(n, device=dev), torch.zeros(n, device=dev, dtype=torch.int64)))
    has = (total > 0) & (best > 0)
    label = torch.where(has, label, torch.full_like(label, -1))
    prob = torch.where(has, best / total.clamp_min(1e-30), torch.zeros_like(total))
    return label, prob, total


class FrozenView:
    """One camera's projection of a frozen scene (no gradients) and its tile binning, built once.

    For a consumer that renders and traces the same view many times with other features or labels
    (self-prompting: every query renders and traces each training view), :meth:`render_features`
    and :meth:`trace` skip the projection and the binning and give the bits of :func:`render`'s
    ``features`` and of :func:`trace` (numba back end, CPU; tested), which build the same two from
    the same splats on every call. ``nbytes`` is what the view holds (its visible splats'
    projection and tile lists), for a caller that keeps views up to a memory budget.
    """

    def __init__(self, splats: Splats, camera: Camera, near: float = 0.01):
        from .kernels.binning import Binning

        n = check_splats(splats)
        with torch.no_grad():
            proj = project(splats, camera, near)
        rows = torch.nonzero(proj.visible).squeeze(1)
        self.num_splats, self.camera, self.near = n, camera, float(near)
        self.rows = None if rows.numel() == n else rows  # as render(): None when every splat is seen
        self.seen = rows.cpu().numpy()
        self.proj = proj if self.rows is None else proj.select(rows)
        self.binning = Binning(self.proj, camera.width, camera.height)
        tensors = (self.proj.ray_transforms, self.proj.coeffs, self.proj.means2d, self.proj.normals,
                   self.proj.depths, self.proj.opacities, self.proj.visible)
        arrays = (self.seen, self.proj.boxes, self.binning.boxes, self.binning.order, self.binning.offsets,
                  self.binning.lists, self.binning.entry_boxes)
        self.nbytes = sum(t.element_size() * t.numel() for t in tensors) + sum(a.nbytes for a in arrays)

    def render_features(self, features: Tensor) -> Tensor:
        """[H, W, C]: ``render(splats, camera, features, near=near).features`` (zero background)."""
        from .kernels.rasterize import rasterize

        _check_features(features, self.num_splats, "features")
        f = features if self.rows is None else features.index_select(0, self.rows)
        background = torch.zeros(f.shape[1], device=f.device, dtype=f.dtype)
        with torch.no_grad():
            out = rasterize(self.proj, f, self.camera.width, self.camera.height, background, self.near,
                            binning=self.binning)
        return out["features"]

    def trace(self, labels: Tensor, num_labels: int, count_pixels: bool = False) -> Tensor:
        """``trace(splats, camera, labels, num_labels, near)``: sparse COO [N, T], coalesced."""
        from .kernels.trace import trace_triplets

        labels = _check_labels(labels, self.camera, num_labels)
        with torch.no_grad():
            rows, cols, w = trace_triplets(self.proj, self.camera.width, self.camera.height, labels, self.near,
                                           count_pixels=count_pixels, binning=self.binning)
        return _coalesced_weights(self.seen, rows, cols, w, self.num_splats, num_labels)
