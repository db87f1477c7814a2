"""Rasterizer benchmark: ``trace3d bench render`` prints the JSON object that :func:`run_bench` returns.

Scenes are seeded and synthetic: splats scattered through the camera frustum (depths 2..6), tangent
scales log-uniform so that footprints span about 1 to 12 pixels, random orientations and opacities,
RGB features; trace labels are 32 Voronoi patches.  Times are wall-clock medians over repeats
after a warm-up (numba compilation excluded, reported separately; the dense reference runs once,
without warm-up).  ``render`` and ``trace`` are timed end to end (projection, binning, kernels,
autograd); ``kernel_forward_ms`` is the forward kernel alone.  The headline figures sit at the top
level of the JSON:

* ``speedup_fwd_bwd``: reference / kernel time of forward+backward, 5,000 splats at 128x96.
* ``trace_over_forward``: trace time / forward time, 50,000 splats at 320x240.
* ``pair_evals_per_s``: pixel-splat pairs evaluated per second by the forward kernel on the
  50,000-splat scene: every pair its inner loop touches, skipped or not.  The kernel evaluates a
  whole 16-pixel tile row per splat row (vectorised), so this counts 16 pairs per (splat, tile row);
  ``footprint_pairs`` counts only the pixels inside each splat's footprint box, for comparison.

The machine is shared: the load average at start and end is part of the result, and
``kernel_forward_process_cpu_ms`` (CPU time of the process) shows how much of the wall time was
spent computing rather than waiting for a core.
"""

from __future__ import annotations

import logging
import os
import statistics
import time
from typing import Callable

import numba
import numpy as np
import torch

from ..tooling.cputarget import describe
from ..render.core import render, trace
from ..render.kernels.binning import Binning
from ..render.kernels.forward import forward_kernel
from ..render.kernels.tiles import _geom_array, pack_geometry
from ..render.projection import Splats, project
from ..scene import Camera

log = logging.getLogger(__name__)


def make_scene(n: int, width: int, height: int, seed: int = 0,
               scale_range: tuple[float, float] = (0.004, 0.04)) -> tuple[Splats, Camera, torch.Tensor]:
    """A seeded random scene.

    Returns:
        splats (N), a camera looking down +z from the origin (focal 0.9 * width), features [N, 3].
    """
    gen = torch.Generator().manual_seed(seed)
    focal = 0.9 * width
    z = 2.0 + 4.0 * torch.rand(n, generator=gen)
    x = (torch.rand(n, generator=gen) - 0.5) * 1.1 * width / focal * z
    y = (torch.rand(n, generator=gen) - 0.5) * 1.1 * height / focal * z
    means = torch.stack([x, y, z], dim=1)
    quats = torch.randn(n, 4, generator=gen)
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 2, generator=gen))
    opacities = 0.05 + 0.9 * torch.rand(n, generator=gen)
    features = torch.rand(n, 3, generator=gen)
    K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
    camera = Camera("bench", "train", width, height, K, np.eye(4))
    return Splats(means, quats, scales, opacities), camera, features


def _time(fn: Callable[[], object], repeats: int, warmup: bool = True) -> float:
    """Median wall time of ``fn`` in milliseconds (after one warm-up call unless ``warmup`` is False)."""
    if warmup:
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)


def _with_grad(splats: Splats, features: torch.Tensor) -> tuple[Splats, torch.Tensor]:
    return Splats(*(t.detach().clone().requires_grad_() for t in splats)), features.detach().clone().requires_grad_()


def patch_labels(width: int, height: int, num_labels: int = 32, seed: int = 2) -> torch.Tensor:
    """[H, W] int64 piecewise-constant labels (Voronoi cells of random sites), like a patch map."""
    rng = np.random.default_rng(seed)
    sites = rng.random((num_labels, 2)) * [width, height]
    ys, xs = np.mgrid[0:height, 0:width]
    d = (xs[..., None] + 0.5 - sites[:, 0]) ** 2 + (ys[..., None] + 0.5 - sites[:, 1]) ** 2
    return torch.from_numpy(d.argmin(-1).astype(np.int64))


def _measure(splats: Splats, camera: Camera, features: torch.Tensor, backend: str, repeats: int,
             with_trace: bool, warmup: bool = True) -> dict:
    sp, feats = _with_grad(splats, features)
    gen = torch.Generator().manual_seed(1)
    up = torch.rand(camera.height, camera.width, 3, generator=gen)

    def fwd():
        with torch.no_grad():
            render(splats, camera, features, backend=backend)

    def fwd_bwd():
        out = render(sp, camera, feats, backend=backend)
        ((out.features * up).sum() + out.depth.sum() + out.normal.sum()).backward()

    res = {"forward_ms": _time(fwd, repeats, warmup), "forward_backward_ms": _time(fwd_bwd, repeats, warmup)}
    if with_trace:
        labels = patch_labels(camera.width, camera.height)
        res["trace_ms"] = _time(lambda: trace(splats, camera, labels, 32, backend=backend), repeats, warmup)
    return res


def _pairs_per_second(splats: Splats, camera: Camera, features: torch.Tensor, repeats: int) -> dict:
    """Time the forward kernel alone and count the pairs it visits."""
    with torch.no_grad():
        proj = project(splats, camera)
        binning = Binning(proj, camera.width, camera.height)
        geom = _geom_array(pack_geometry(proj))
        vals = np.ascontiguousarray(torch.cat([features, proj.normals], 1).numpy().astype(np.float32))
    # every channel to the head, nothing folded in (the kernel's plain blend)
    args = (binning.entry_geometry(geom), binning.entry_boxes, binning.lists, vals, binning.offsets,
            binning.width, binning.height, binning.tiles_x, 0.01, vals.shape[1], np.zeros(vals.shape[1], np.float32),
            False)
    pairs = int(forward_kernel(*args)[-1].sum())
    ms = _time(lambda: forward_kernel(*args), repeats)
    cpu0 = time.process_time()
    forward_kernel(*args)
    cpu_ms = (time.process_time() - cpu0) * 1000.0
    # pixels of each entry's footprint box inside its tile (what a scalar loop over the box visits)
    tile = np.repeat(np.arange(binning.offsets.shape[0] - 1), np.diff(binning.offsets))
    tx, ty = (tile % binning.tiles_x) * 16, (tile // binning.tiles_x) * 16
    box = binning.entry_boxes
    footprint = (np.clip(np.minimum(box[:, 2], tx + 16) - np.maximum(box[:, 0], tx), 0, None)
                 * np.clip(np.minimum(box[:, 3], ty + 16) - np.maximum(box[:, 1], ty), 0, None)).sum()
    return {"kernel_forward_ms": ms, "kernel_forward_process_cpu_ms": cpu_ms, "pairs": pairs,
            "pair_evals_per_s": pairs / (ms / 1000.0), "footprint_pairs": int(footprint),
            "tile_entries": int(binning.lists.shape[0]), "visible": int(proj.visible.sum())}


def run_bench(quick: bool = False) -> dict:
    """Run the rasterizer benchmark; return a JSON-serialisable dict (see the module docstring)."""
    repeats = 2 if quick else 5
    t0 = time.perf_counter()
    warm, cam, feats = make_scene(200, 64, 48)
    _measure(warm, cam, feats, "numba", 1, with_trace=True)  # compile (or load cached) kernels
    compile_s = time.perf_counter() - t0

    result: dict = {
        "threads": {"numba": numba.get_num_threads(), "torch": torch.get_num_threads(),
                    "cpu_count": os.cpu_count(), "numba_threading_layer": numba.config.THREADING_LAYER},
        "cpu": describe(),
        "load_average_at_start": list(os.getloadavg()),
        "warmup_and_compile_s": compile_s,
    }
    small_n, small_w, small_h = (2000, 128, 96) if quick else (5000, 128, 96)
    splats, camera, features = make_scene(small_n, small_w, small_h)
    kernel = _measure(splats, camera, features, "numba", repeats, with_trace=True)
    reference = _measure(splats, camera, features, "reference", 1, with_trace=False, warmup=False)
    result["small"] = {"n": small_n, "width": small_w, "height": small_h, "kernel": kernel, "reference": reference}
    result["speedup_forward"] = reference["forward_ms"] / kernel["forward_ms"]
    result["speedup_fwd_bwd"] = reference["forward_backward_ms"] / kernel["forward_backward_ms"]

    large_n, large_w, large_h = (20000, 160, 120) if quick else (50000, 320, 240)
    splats, camera, features = make_scene(large_n, large_w, large_h)
    kernel = _measure(splats, camera, features, "numba", repeats, with_trace=True)
    kernel.update(_pairs_per_second(splats, camera, features, repeats))
    result["large"] = {"n": large_n, "width": large_w, "height": large_h, "kernel": kernel,
                       "reference": "skipped: the dense reference needs N x H x W memory"}
    result["trace_over_forward"] = kernel["trace_ms"] / kernel["forward_ms"]
    result["pair_evals_per_s"] = kernel["pair_evals_per_s"]

    sweep = []
    counts = (5000, 20000) if quick else (10000, 25000, 50000, 100000)
    sizes = ((160, 120),) if quick else ((160, 120), (320, 240), (640, 480))
    for n in counts:
        for w, h in sizes:
            sp, cam, ft = make_scene(n, w, h)
            row = {"n": n, "width": w, "height": h}
            row.update(_measure(sp, cam, ft, "numba", 1 if quick else 3, with_trace=False))
            row.update(_pairs_per_second(sp, cam, ft, 1 if quick else 3))
            row["forward_backward_ns_per_pair"] = row["forward_backward_ms"] * 1e6 / max(row["pairs"], 1)
            sweep.append(row)
            log.info("sweep %s", row)
    result["sweep"] = sweep
    result["load_average_at_end"] = list(os.getloadavg())
    result["total_s"] = time.perf_counter() - t0
    return result
