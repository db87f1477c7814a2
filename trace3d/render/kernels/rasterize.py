"""The torch side of the tile kernels: :class:`_Rasterize`, the autograd Function that runs the forward
kernel and picks the full or the values-only backward, and :func:`rasterize`, what
:func:`trace3d.render.render` calls.  (Part of the former ``render/kernels.py``, moved unchanged.)"""

from __future__ import annotations

import contextlib
from typing import Iterator

import numpy as np
import torch
from torch import Tensor

from ..projection import Projected
from .backward import backward_kernel, fold_background_grad, sum_chunks
from .backward_values import backward_values_kernel, sum_value_chunks
from .binning import Binning
from .forward import forward_kernel
from .tiles import _f32, _geom_array, pack_geometry

# The backward deals the image's tiles to this many gradient buffers (tile t to buffer t mod n) and
# sums them in buffer order, one thread per buffer at a time: the gradients' bits depend on this
# number and never on how many threads run the kernel. 2 is what the earlier 2-thread runs used (the
# buffer count was then the thread count), so the published fits keep their bits.
GRADIENT_BUFFERS = 2
_gradient_buffers = GRADIENT_BUFFERS


def gradient_buffer_count() -> int:
    """The number of gradient buffers the rasterizer's backward deals its tiles to."""
    return _gradient_buffers


@contextlib.contextmanager
def gradient_buffers(count: int) -> Iterator[None]:
    """Run the block with the backward's tiles dealt to ``count`` gradient buffers (0: unchanged).

    More buffers let more threads share the backward (at most one thread per buffer) for another
    order of the gradient sums, hence other bits, as deterministic; memory grows by one
    [N, 15 + K] float32 array per buffer."""
    global _gradient_buffers
    previous = _gradient_buffers
    if count > 0:
        _gradient_buffers = int(count)
    try:
        yield
    finally:
        _gradient_buffers = previous

class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, geom15: Tensor, vals: Tensor, binning: Binning, near: float, split: int,
                background: Tensor | None, value_grad_cols: int | None = None):
        geom = _geom_array(geom15)
        vals_np = _f32(vals)
        egeom = binning.entry_geometry(geom)
        # the blended values as two outputs, columns [:split] and [split:] (features and normals), so
        # that the backward gets their gradients without two zero-filled slice gradients and their sum;
        # background: blended into the first part in the kernel (None: the caller blends it)
        ctx.split = split
        ctx.background = (np.zeros(split, np.float32) if background is None
                          else np.ascontiguousarray(background.detach().numpy()))
        ctx.fold = background is not None
        ctx.value_grad_cols = value_grad_cols  # with frozen geometry: gradients for vals[:, :value_grad_cols]
        head, tail, acc_z, acc_z2, final_t, median_z, depth_ref, last, median_at, pairs = forward_kernel(
            egeom, binning.entry_boxes, binning.lists, vals_np, binning.offsets, binning.width,
            binning.height, binning.tiles_x, float(near), split, ctx.background, ctx.fold)
        binning.pairs = pairs
        ctx.binning = binning
        ctx.near = near
        ctx.in_dtype = (geom15.dtype, vals.dtype, geom15.device)
        ctx.saved = (egeom, vals_np, final_t, depth_ref, last, median_at)
        dev, dt = vals.device, vals.dtype
        outs = [torch.from_numpy(a).to(device=dev, dtype=dt) for a in (head, tail, acc_z, acc_z2, final_t, median_z)]
        ref = torch.from_numpy(depth_ref).to(device=dev, dtype=dt)
        ctx.mark_non_differentiable(ref)
        return tuple(outs) + (ref,)

    @staticmethod
    def backward(ctx, v_head, v_tail, v_z, v_z2, v_final_t, v_median, v_ref):
        b = ctx.binning
        egeom, vals_np, final_t, depth_ref, last, median_at = ctx.saved
        h, w, k = b.height, b.width, vals_np.shape[1]

        def arr(t, shape):
            if t is None:
                return np.zeros(shape, np.float32)
            return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())

        g_head = arr(v_head, (h, w, ctx.split))
        n_chunks = _gradient_buffers
        gdt, vdt, dev = ctx.in_dtype
        if not ctx.needs_input_grad[0]:
            # frozen geometry: the value gradients alone, for the columns that need them (the depth,
            # transmittance and median outputs do not depend on the values)
            n_cols = k if ctx.value_grad_cols is None else ctx.value_grad_cols
            v_tail_np = arr(v_tail, (h, w, k - ctx.split)) if n_cols > ctx.split else np.zeros((h, w, 0), np.float32)
            grads = backward_values_kernel(egeom, b.entry_boxes, b.lists, vals_np.shape[0], b.offsets, b.width,
                                           b.height, b.tiles_x, float(ctx.near), n_chunks, final_t, last, g_head,
                                           v_tail_np, n_cols)
            g_vals = torch.from_numpy(sum_value_chunks(grads, k)).to(device=dev, dtype=vdt)
            return None, g_vals, None, None, None, None, None
        v_t = np.array(arr(v_final_t, (h, w)))  # a copy: the background's share is added in place
        if ctx.fold:
            fold_background_grad(g_head, v_t, ctx.background)
        grads = backward_kernel(egeom, b.entry_boxes, b.lists, vals_np, b.offsets, b.width, b.height, b.tiles_x,
                                float(ctx.near), n_chunks, final_t, depth_ref, last, median_at,
                                g_head, arr(v_tail, (h, w, k - ctx.split)), arr(v_z, (h, w)), arr(v_z2, (h, w)),
                                v_t, arr(v_median, (h, w)))
        g_geom_np, g_vals_np = sum_chunks(grads)
        g_geom = torch.from_numpy(g_geom_np).to(device=dev, dtype=gdt)
        g_vals = torch.from_numpy(g_vals_np).to(device=dev, dtype=vdt)
        return g_geom, g_vals, None, None, None, None, None


def rasterize(proj: Projected, features: Tensor, width: int, height: int, background: Tensor,
              near: float = 0.01, binning: Binning | None = None) -> dict[str, Tensor]:
    """Tile-kernel render of projected splats (same outputs as ``render_reference``).

    Args:
        proj: projection; features: [N, C]; background: [C].
    Returns:
        dict with features [H, W, C], alpha, depth, depth2 (sum w (z - depth_ref)^2), depth_ref,
        median_depth [H, W], normal [H, W, 3].
    """
    if binning is None:
        binning = Binning(proj, width, height)
    c = features.shape[1]
    vals = torch.cat([features, proj.normals.to(features.dtype)], dim=1)
    # a fixed background is blended inside: the same float32 operations as the torch line below, in
    # its order (tested) for three channels; for other channel counts only a zero background (then
    # every term is exact: the order cannot matter). A background to differentiate takes the torch line.
    fold = (vals.dtype == torch.float32 and background.dtype == torch.float32 and background.device.type == "cpu"
            and not background.requires_grad and (c == 3 or not bool(background.any())))
    feats, normal, acc_z, acc_z2, final_t, median_z, depth_ref = _Rasterize.apply(
        pack_geometry(proj), vals, binning, near, c, background.contiguous() if fold else None,
        None if proj.normals.requires_grad else c)
    return {
        "features": feats if fold else feats + final_t[..., None] * background,
        "alpha": 1.0 - final_t,
        "depth": acc_z,
        "depth2": acc_z2,
        "depth_ref": depth_ref,
        "normal": normal,
        "median_depth": median_z,
        "final_t": final_t,
        "pairs": binning.pairs,
    }
