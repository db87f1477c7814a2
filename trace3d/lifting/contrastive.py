"""Contrastive lifting (paper Sec. 3.5; the ``lift`` step with ``method: contrastive``).

Every Gaussian gets a feature f_i in R^d (d = 16); with the geometry frozen, the rendered feature
map F is linear in the features. Each iteration samples labelled pixels U of one training view's
consistent instance map (label 0 = unlabelled, never sampled) and minimises

    L = -1/|U| sum_u log( sum_{u' in U+(u)} k(u, u') / sum_{u' in U} k(u, u') )

where U+(u) are the sampled pixels of u's instance. The kernel k and U+(u) are the preset's:

- ``official`` (the released code, ``utils/loss_utils.py``'s ``contrastive_loss``, after Contrastive
  Lift): k = exp(exp(-||F[u] - F[u']||^2 / tau)), tau = 100 between two pixels of the same instance
  and 1 otherwise; U+(u) leaves u itself out (its k = e stays in the denominator), and an anchor with
  no other pixel of its instance adds nothing (the mean still divides by |U|); 4,096 pixels per
  iteration, 20,000 iterations, Adam lr 0.005 on the features only.
- ``printed`` (the paper as printed): k = exp(sim), sim = exp(-tau ||f1 - f2||^2), tau = 0.01, lr 1e-5;
  U+(u) holds u itself (so a pixel alone in its instance contributes log of its own share).
- ``gaussian``: k = exp(-tau ||f1 - f2||^2) with one temperature (the printed similarity used directly
  as the kernel, i.e. without the outer exp); U+(u) holds u.

Undecided pairs (``undecided``, beyond the paper; docs/tracing.md). ``push`` (the paper): every pair of
pixels of two different patches is a negative. ``ignore``: two pixels of different patches that lie
under one common mask of their view (the patch step's hierarchy, ``<frame>.json`` beside the maps) are
neither pulled nor pushed: their pair leaves the denominator. The masks leave such pairs undecided (the
parts of one object, or two objects of one group); the other views' patches, through the shared
Gaussians, decide them. Works on the raw patches (``consistent_masks: false``), without a merge.
``undecided_weight`` softens instead of leaving out: an undecided pair keeps that weight in the
denominator (0: left out; 1: the paper's push).

Two levels (``coarse_depth``, beyond the paper; docs/lifting.md). A view's masks nest (a table holds its
top and legs, the room holds the table), and the patches are their finest overlap: trained on the patches
alone, the parts of an object that the masks split are pushed apart as far as two objects. With
``coarse_depth: k`` the lift trains a second block of ``dim`` features, with the same settings and
``undecided: push``, on the patches regrouped by the masks at most ``k`` deep in the view's nesting tree
(:func:`trace3d.masks.patches.coarser_patches`), and the features are the two blocks side by side
(2 x ``dim``): a distance between two Gaussians then counts both how the fine and how the coarse masks
cut them. Needs the patch step's hierarchy beside the maps (the raw patches, ``consistent_masks: false``).
A view's nesting tree is as deep as its masks make it: where the coarsest region of a view was too large to
be a mask (the source's ``max_area``), its other regions sit one level higher than in a view that kept it,
so one object lies at depth 0 in some views and depth 1 in others (the fern capture). ``coarse_depth: [1,
0]`` trains one coarse block per listed depth (3 x ``dim`` features): whichever depth holds the object in
a view, one block keeps it whole there.

The ``paper`` preset is the printed kernel with the released code's learning rate (0.005), counts and
pixels: at the printed lr 1e-5 the loss does not move in 1,500 iterations on a default room, at
0.005 it gave the best test-view query IoU of the forms we measured (docs/lifting.md).

Speed: the renders of the sampled pixels are sparse products with per-view blending weights computed
once (:mod:`trace3d.render.pixel_weights`), for a pool of ``pool_pixels`` random labelled pixels per
view, of which each iteration gathers only its sampled rows; ``path: raster`` renders with the
rasterizer instead (the twin, and the benchmark's baseline). The loss and its gradient come from one
fused numba kernel (:mod:`trace3d.lifting.kernels.contrastive`); ``fused: false`` uses the torch autograd form
(:func:`contrastive_loss`, its twin).
"""

from __future__ import annotations

import csv
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numba
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..tooling.compiling import track as track_compile_time
from ..errors import Trace3DError
from ..gaussians import GaussianModel
from ..scene import Camera
from ..training.kernels.adam import CpuAdam
from .kernels.contrastive import fused_contrastive_loss, kernel_constants, loss_and_grad

log = logging.getLogger(__name__)

PRESET_VALUES = {
    "official": {"kernel": "official", "temperature": 0.01, "temperature_pos": 100.0, "temperature_neg": 1.0,
                 "lr": 0.005, "iterations": 20000, "pixels": 4096},
    # the printed kernel (exp of exp(-0.01 d^2)) with the released code's lr and counts: the printed lr 1e-5
    # does not train (docs/lifting.md, measured on a default room)
    "paper": {"kernel": "printed", "temperature": 0.01, "temperature_pos": 100.0, "temperature_neg": 1.0,
              "lr": 0.005, "iterations": 20000, "pixels": 4096},
}


@dataclass
class ContrastiveParams:
    """Parameters of contrastive lifting (``None`` takes the preset's value; see the module docstring)."""

    method: Literal["contrastive"] = "contrastive"
    preset: Literal["paper", "official"] = "paper"
    dim: int = 16
    kernel: Literal["official", "printed", "gaussian"] | None = None
    temperature: float | None = None  # printed / gaussian kernels: exp(-temperature d^2)
    temperature_pos: float | None = None  # official kernel: exp(-d^2 / temperature_pos) within an instance
    temperature_neg: float | None = None  # official kernel: exp(-d^2 / temperature_neg) across instances
    lr: float | None = None
    iterations: int | None = None
    pixels: int | None = None  # labelled pixels sampled per iteration (from one view)
    pool_pixels: int = 8192  # labelled pixels per view whose blending weights are kept (sparse path)
    init_std: float = 0.1
    path: Literal["sparse", "raster"] = "sparse"
    fused: bool = True  # the fused CPU loss + gradient kernel (False: the torch autograd form, its twin)
    near: float = 0.01
    seed: int = 0
    pca_views: int = 3
    log_every: int = 10
    query: dict = field(default_factory=dict)  # QueryParams overrides, used when the lift is queried
    undecided: Literal["push", "ignore"] = "push"  # pairs of patches under one mask (module docstring)
    undecided_weight: float = 0.0  # under ``ignore``: the weight such a pair keeps in the denominator
    # a second block of ``dim`` features trained, with the same settings (``push``), on the patches regrouped by
    # their masks at most this deep (trace3d.masks.patches.coarser_patches; needs the patch step's hierarchy):
    # the features are the two blocks side by side. A list of depths: one such block per depth, in its order.
    # None: one block (the paper). Module docstring.
    coarse_depth: int | list[int] | None = None

    @property
    def coarse_depths(self) -> list[int]:
        """The depths of the coarse blocks, in their order ([] without ``coarse_depth``)."""
        if self.coarse_depth is None:
            return []
        return [self.coarse_depth] if isinstance(self.coarse_depth, int) else list(self.coarse_depth)

    def __post_init__(self) -> None:
        for key, value in PRESET_VALUES[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        if self.dim < 1 or self.iterations < 1 or self.pixels < 2 or self.pool_pixels < 2:
            raise ValueError(f"dim, iterations must be >= 1 and pixels, pool_pixels >= 2, got {self.dim}, "
                             f"{self.iterations}, {self.pixels}, {self.pool_pixels}")
        if self.undecided not in ("push", "ignore"):
            raise ValueError(f"undecided must be 'push' or 'ignore', got {self.undecided!r}")
        depths = self.coarse_depths
        if any(d < 0 for d in depths) or len(set(depths)) != len(depths) or self.coarse_depth == []:
            raise ValueError(f"coarse_depth must be a depth >= 0, a list of distinct such depths, or null, got "
                             f"{self.coarse_depth}")
        if not 0.0 <= self.undecided_weight <= 1.0:
            raise ValueError(f"undecided_weight must lie in [0, 1], got {self.undecided_weight}")
        if not (self.lr > 0 and self.temperature > 0 and self.temperature_pos > 0 and self.temperature_neg > 0):
            raise ValueError("lr and the temperatures must be > 0")


def _kernels(kernel: str, temperature: float, temperature_pos: float, temperature_neg: float):
    """(k_pos, k_neg): the kernel as a function of d^2 within an instance and across instances."""
    if kernel == "official":
        return (lambda d2: torch.exp(torch.exp(-d2 / temperature_pos))), (lambda d2: torch.exp(torch.exp(-d2 / temperature_neg)))
    if kernel == "gaussian":
        k = lambda d2: torch.exp(-temperature * d2)  # noqa: E731
        return k, k
    if kernel == "printed":
        k = lambda d2: torch.exp(torch.exp(-temperature * d2))  # noqa: E731
        return k, k
    raise Trace3DError(f"contrastive loss: unknown kernel {kernel!r}.")


def _sq_dist(a: Tensor, b: Tensor) -> Tensor:
    return ((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.t()).clamp_min(0.0)


def related_patches(hierarchy) -> np.ndarray:
    """[P + 1, P + 1] bool from one view's patch hierarchy: True where two different patches lie under a
    common mask of the view (the pairs ``undecided: ignore`` leaves out); row and column 0 (uncovered
    pixels) and the diagonal are False: the merge's co-membership (:func:`~trace3d.tracing.consistency.comembership`)
    without the patches' own pairs."""
    from ..tracing.consistency import comembership

    related = comembership(hierarchy, hierarchy.num_patches + 1) > 0
    np.fill_diagonal(related, False)
    return related


def _ignored(related: Tensor, rows: Tensor, cols: Tensor) -> Tensor:
    """[R, C] bool: the pairs of labels ``rows`` x ``cols`` that ``related`` ([L, L], by label value)
    leaves undecided (never two pixels of one label)."""
    return related[rows][:, cols] & (rows[:, None] != cols[None, :])


def contrastive_loss(features: Tensor, labels: Tensor, kernel: str = "official", temperature: float = 0.01,
                     temperature_pos: float = 100.0, temperature_neg: float = 1.0, chunk: int = 2048,
                     related: Tensor | None = None, undecided_weight: float = 0.0) -> Tensor:
    """The contrastive loss over P sampled pixels (module docstring).

    Cheap form: pixels are sorted by instance, so the positives of an anchor are one diagonal block.
    The denominator is the cross-instance kernel summed over the whole row (one [chunk, P] pass, no
    masks) plus, on the diagonal blocks only, (k_pos - k_neg); the numerator is k_pos summed over the
    block (``official``: without the anchor's own entry; anchors with no other pixel of their instance
    add nothing). Every kernel value is in (0, e], and the numerator is either empty (left out) or
    holds at least one value >= 1 for ``official`` (exp of a positive number) or the anchor's own
    k(0) >= 1, so no log-sum-exp shifting is needed.

    Args:
        features: [P, D] rendered features.
        labels: [P] int64 instance ids (all labelled).
        kernel: "official", "printed" or "gaussian".
        chunk: anchor rows per block of the full pass (bounds memory at chunk x P).
        related: optional [L, L] bool by label value (L > every label): pairs of two different labels
            marked True are left out of the denominator (``undecided: ignore``, :func:`related_patches`),
            or keep ``undecided_weight`` there.
    Returns:
        scalar loss (the anchors' sum over P).
    """
    p = features.shape[0]
    if p == 0:
        return features.sum() * 0.0
    k_pos, k_neg = _kernels(kernel, temperature, temperature_pos, temperature_neg)
    same_kernel = kernel != "official" or temperature_pos == temperature_neg
    without_self = kernel == "official"
    lab, order = torch.sort(labels, stable=True)
    f = features[order]
    if related is None:
        den = torch.cat([k_neg(_sq_dist(f[a:a + chunk], f)).sum(1) for a in range(0, p, chunk)])
    else:
        related = torch.as_tensor(related, dtype=torch.bool)
        rows = []
        for a in range(0, p, chunk):
            k = k_neg(_sq_dist(f[a:a + chunk], f))
            rows.append(torch.where(_ignored(related, lab[a:a + chunk], lab), k * undecided_weight, k).sum(1))
        den = torch.cat(rows)
    _, counts = torch.unique_consecutive(lab, return_counts=True)
    nums, fixes = [], []
    start = 0
    for n in counts.tolist():
        fb = f[start:start + n]
        d2 = _sq_dist(fb, fb)
        kp = k_pos(d2)
        nums.append((kp * (1.0 - torch.eye(n, dtype=kp.dtype)) if without_self else kp).sum(1))
        if not same_kernel:
            fixes.append((kp - k_neg(d2)).sum(1))
        start += n
    num = torch.cat(nums)
    if fixes:
        den = den + torch.cat(fixes)
    if not without_self:
        return (torch.log(den) - torch.log(num)).mean()
    counted = num > 0
    terms = torch.log(den) - torch.log(torch.where(counted, num, torch.ones_like(num)))
    return torch.where(counted, terms, torch.zeros_like(terms)).sum() / p


def contrastive_loss_reference(features: Tensor, labels: Tensor, **kwargs) -> Tensor:
    """Slow twin of :func:`contrastive_loss`: the formula anchor by anchor in float64."""
    f = features.double()
    kernel = kwargs.get("kernel", "official")
    related = kwargs.get("related")
    terms = []
    for u in range(f.shape[0]):
        d2 = ((f[u][None] - f) ** 2).sum(1)
        same = labels == labels[u]
        # the undecided pairs weigh undecided_weight (0: dropped from the anchor's row before any sum)
        weight = torch.ones_like(d2)
        if related is not None:
            undecided = torch.as_tensor(related)[int(labels[u])][labels] & ~same
            weight[undecided] = kwargs.get("undecided_weight", 0.0)
        kept = weight > 0
        d2, same, weight = d2[kept], same[kept], weight[kept]
        own = int(kept[:u].sum())  # the anchor's place in the kept row
        if kernel == "official":
            tau = torch.where(same, kwargs.get("temperature_pos", 100.0), kwargs.get("temperature_neg", 1.0))
            k = torch.exp(torch.exp(-d2 / tau.double())) * weight
            others = same.clone()
            others[own] = False
            if others.any():
                terms.append(-torch.log(k[others].sum() / k.sum()))
            continue
        if kernel == "gaussian":
            k = torch.exp(-kwargs.get("temperature", 0.01) * d2) * weight
        else:
            k = torch.exp(torch.exp(-kwargs.get("temperature", 0.01) * d2)) * weight
        terms.append(-torch.log(k[same].sum() / k.sum()))
    if not terms:
        return f.sum() * 0.0
    return torch.stack(terms).sum() / f.shape[0]


def loss_kwargs(p: ContrastiveParams) -> dict:
    return {"kernel": p.kernel, "temperature": p.temperature, "temperature_pos": p.temperature_pos,
            "temperature_neg": p.temperature_neg}


class PixelPools:
    """Per training view: a pool of labelled pixels, their labels and (sparse path) their blending weights."""

    def __init__(self, model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                 pool_pixels: int, rng: np.random.Generator, with_weights: bool, near: float = 0.01,
                 progress: bool = False, relations: Sequence[np.ndarray] | None = None):
        from ..render.pixel_weights import pixel_weights

        splats = model.splats()
        self.cameras: list[Camera] = []
        self.pixels: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.weights = []
        self.related: list[np.ndarray | None] = []  # per kept view: its undecided pairs, or None (push all)
        relations = list(relations) if relations is not None else [None] * len(label_maps)
        bar = tqdm(list(zip(cameras, label_maps, relations)), desc="pixel weights", disable=not progress, leave=False,
                   mininterval=0.5 if sys.stderr.isatty() else 30.0)
        for cam, lab, related in bar:
            flat = np.asarray(lab).reshape(-1)
            labelled = np.flatnonzero(flat > 0)
            if labelled.size < 2:
                continue
            pool = np.sort(rng.choice(labelled, size=min(pool_pixels, labelled.size), replace=False))
            self.cameras.append(cam)
            self.pixels.append(pool)
            self.labels.append(flat[pool].astype(np.int64))
            self.related.append(related)
            if with_weights:
                with torch.no_grad():
                    self.weights.append(pixel_weights(splats, cam, pool, near=near))
        if not self.cameras:
            raise Trace3DError("contrastive lifting: no training view has labelled pixels (every label map is 0).")

    @property
    def nnz(self) -> int:
        return sum(w.nnz for w in self.weights)

    @property
    def nbytes(self) -> int:
        return sum(w.nbytes for w in self.weights)


def render_pixels(model: GaussianModel, camera: Camera, features: Tensor, pixels: np.ndarray, near: float = 0.01) -> Tensor:
    """[P, D] features rendered by the rasterizer at flat pixel indices ``pixels`` (the twin of the sparse path)."""
    from ..render import render

    out = render(model.splats(), camera, features, near=near).features
    return out.reshape(-1, features.shape[1])[torch.from_numpy(np.asarray(pixels, np.int64))]


class ContrastiveTrainer:
    """Adam on the features only, one view's sampled pixels per iteration."""

    def __init__(self, model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                 params: ContrastiveParams, progress: bool = False, relations: Sequence[np.ndarray] | None = None):
        self.model = model.detached_copy()
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        gen = torch.Generator().manual_seed(params.seed)
        self.features = (torch.randn(len(model), params.dim, generator=gen) * params.init_std).requires_grad_(True)
        # one parallel numba pass over the [N, D] state that also clears the gradient buffer (torch's Adam,
        # tested against it; the for-each torch Adam took half of a sparse iteration on a room)
        self.optimizer = CpuAdam(self.features, lr=params.lr)
        start = time.perf_counter()
        self.pools = PixelPools(self.model, cameras, label_maps, params.pool_pixels, self.rng,
                                with_weights=params.path == "sparse", near=params.near, progress=progress,
                                relations=relations if params.undecided == "ignore" else None)
        self.precompute_seconds = time.perf_counter() - start
        self.kwargs = loss_kwargs(params)
        # the fast step (sparse path with the fused loss): no autograd graph, one reused gradient buffer
        self._grad = np.zeros(tuple(self.features.shape), np.float32)
        self._consts = kernel_constants(**self.kwargs)

    def sample(self) -> tuple[int, np.ndarray]:
        v = int(self.rng.integers(len(self.pools.cameras)))
        size = self.pools.pixels[v].size
        rows = np.sort(self.rng.choice(size, size=min(self.params.pixels, size), replace=False))
        return v, rows

    def loss_at(self, v: int, rows: np.ndarray, path: str | None = None) -> Tensor:
        path = path or self.params.path
        if path == "sparse":
            rendered = self.pools.weights[v].render_rows(self.features, rows)
        else:
            rendered = render_pixels(self.model, self.pools.cameras[v], self.features, self.pools.pixels[v][rows],
                                     self.params.near)
        loss = fused_contrastive_loss if self.params.fused else contrastive_loss
        return loss(rendered, torch.from_numpy(self.pools.labels[v][rows]), related=self.pools.related[v],
                    undecided_weight=self.params.undecided_weight, **self.kwargs)

    def step(self, path: str | None = None) -> float:
        if (path or self.params.path) == "sparse" and self.params.fused:
            return self.fast_step()
        return self.autograd_step(path)

    def fast_step(self) -> float:
        """One iteration of the sparse path by hand: gather the sampled rows' features, the fused loss
        and its gradient, scatter it into the reused gradient buffer, then Adam (which clears the
        buffer). The same arithmetic as :meth:`autograd_step` on the sparse path (its twin in the
        tests, equal bit for bit), without building a graph or a fresh N x D gradient every iteration."""
        from ..render.pixel_weights import _gather_rows, scatter_rows_add

        v, rows = self.sample()
        w = self.pools.weights[v]
        rendered = _gather_rows(w.indptr, w.indices, w.weights, rows, self.features.detach().numpy())
        loss, g_rendered = loss_and_grad(rendered, self.pools.labels[v][rows], self._consts,
                                         related=self.pools.related[v], undecided_weight=self.params.undecided_weight)
        scatter_rows_add(w.indptr, w.indices, w.weights, rows, g_rendered, self._grad, numba.get_num_threads())
        self.optimizer.step(self._grad)  # leaves the buffer zero
        return loss

    def autograd_step(self, path: str | None = None) -> float:
        """One iteration through autograd (either path, either loss form; the twin of :meth:`fast_step`)."""
        v, rows = self.sample()
        self.features.grad = None
        loss = self.loss_at(v, rows, path)
        loss.backward()
        self.optimizer.step(self.features.grad.numpy())
        self.features.grad = None
        return float(loss.detach())

    def train(self, iterations: int, progress: bool = False) -> list[tuple[int, float]]:
        history = []
        bar = tqdm(range(1, iterations + 1), desc="contrastive lifting", disable=not progress,
                   mininterval=0.5 if sys.stderr.isatty() else 30.0)
        track_compile_time(bar)  # the ETA leaves out a first run's kernel compilation
        running = None
        for it in bar:
            value = self.step()
            running = value if running is None else 0.98 * running + 0.02 * value
            if it % self.params.log_every == 0 or it == iterations:
                history.append((it, value))
                bar.set_postfix(loss=f"{running:.4f}", refresh=False)
            if it % max(1, iterations // 10) == 0:
                log.info("iteration %d/%d: loss %.4f (running %.4f)", it, iterations, value, running)
        return history


def lift_features(model: GaussianModel, cameras: Sequence[Camera], label_maps: Sequence[np.ndarray],
                  params: ContrastiveParams, progress: bool = False, relations: Sequence[np.ndarray] | None = None,
                  ) -> tuple[np.ndarray, list[tuple[int, float]], dict]:
    """Train the features; returns features [N, D] float32, the loss history and timings. ``relations``:
    per view its :func:`related_patches` (used when ``params.undecided`` is ``ignore``)."""
    start = time.perf_counter()
    trainer = ContrastiveTrainer(model, cameras, label_maps, params, progress=progress, relations=relations)
    history = trainer.train(params.iterations, progress=progress)
    info = {"precompute_seconds": trainer.precompute_seconds, "train_seconds": time.perf_counter() - start
            - trainer.precompute_seconds, "weights_nnz": trainer.pools.nnz, "weights_bytes": trainer.pools.nbytes,
            "views": len(trainer.pools.cameras)}
    return trainer.features.detach().numpy().astype(np.float32), history, info


# ----------------------------------------------------------------------------------------------
# Pictures
# ----------------------------------------------------------------------------------------------


def render_feature_map(model: GaussianModel, camera: Camera, features: np.ndarray | Tensor, near: float = 0.01) -> np.ndarray:
    """[H, W, D] rendered feature map (rasterizer, no gradient)."""
    from ..render import render

    with torch.no_grad():
        f = torch.as_tensor(np.asarray(features), dtype=torch.float32)
        return render(model.splats(), camera, f, near=near).features.numpy()


def pca_picture(path: Path, model: GaussianModel, cameras: Sequence[Camera], features: np.ndarray, scene=None,
                near: float = 0.01) -> None:
    """PCA (3 components, fitted over the pixels of all given views) of the rendered feature maps, beside RGB."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = [render_feature_map(model, c, features, near) for c in cameras]
    stack = np.concatenate([m.reshape(-1, m.shape[-1]) for m in maps])
    mean = stack.mean(0)
    _, _, vt = np.linalg.svd(stack - mean, full_matrices=False)
    proj = (stack - mean) @ vt[:3].T
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    fig, axes = plt.subplots(len(cameras), 2, figsize=(6, 2.4 * len(cameras)), squeeze=False)
    offset = 0
    for row, (cam, m) in enumerate(zip(cameras, maps)):
        n = m.shape[0] * m.shape[1]
        rgb = np.clip((proj[offset:offset + n] - lo) / np.maximum(hi - lo, 1e-8), 0, 1).reshape(m.shape[0], m.shape[1], 3)
        offset += n
        if scene is not None:
            axes[row, 0].imshow(scene.image(cam.name))
        axes[row, 0].set_title(cam.name, fontsize=8)
        axes[row, 1].imshow(rgb)
        axes[row, 1].set_title("feature PCA", fontsize=8)
        for ax in axes[row]:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def loss_picture(path: Path, history: list[tuple[int, float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = np.array([h[0] for h in history])
    vals = np.array([h[1] for h in history])
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.plot(its, vals, lw=0.6, alpha=0.5, label="loss")
    if vals.size >= 20:
        k = max(1, vals.size // 20)
        ax.plot(its[k - 1:], np.convolve(vals, np.ones(k) / k, mode="valid"), lw=1.5, label=f"mean of {k}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("contrastive loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_history(path: Path, history: list[tuple[int, float]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["iteration", "loss"])
        w.writerows([(i, f"{v:.6f}") for i, v in history])


def instance_map(model, camera, instance: np.ndarray, count: int, near: float = 0.01) -> np.ndarray:
    """[H, W] int: per pixel the instance (1..K) with the largest rendered blending weight (the one-hot
    [N, K] instance indicators rendered as features); 0 where no Gaussian covers the pixel."""
    if count == 0:
        return np.zeros((camera.height, camera.width), np.int64)
    onehot = np.zeros((instance.size, count), np.float32)
    hit = instance > 0
    onehot[np.flatnonzero(hit), instance[hit] - 1] = 1.0
    rendered = render_feature_map(model, camera, onehot, near)
    out = rendered.argmax(-1).astype(np.int64) + 1
    out[rendered.max(-1) <= 0] = 0
    return out
