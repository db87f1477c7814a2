"""``trace3d bench fit``: where a 2DGS training iteration spends its time, phase by phase.

For each frame size (a default room's 160x120 and an LLFF-sized 504x378) a synthetic room is generated
at that size, 80,000 Gaussians are initialised on its depth (surface-aligned disks, as a fit has
them), and the real training loop (:func:`trace3d.training.loop.fit`, default parameters) runs for a
warm-up and then ``iterations`` timed iterations from the default schedule's densification window
(``densify_from`` moved to the start, so that density control runs at its default interval and is
amortised as in a fit). The phases are measured by wrapping the functions the loop calls, so the
loop itself is the one the pipeline runs:

- ``projection``: :func:`trace3d.render.projection.project` (ray transforms, footprint boxes; with
  compact gradients both the visibility pass over all Gaussians and the seen rows' projection);
- ``binning``: tile binning of the footprint boxes (``Binning``);
- ``forward_kernel`` / ``backward_kernel``: the numba tile kernels;
- ``render_glue``: the rest of the render (SH colours, packing, conversions; with compact gradients
  the gather of the seen rows);
- ``loss``: L1 + D-SSIM and the regularisers (normal consistency, depth distortion terms);
- ``autograd_rest``: ``loss.backward()`` minus the backward kernel (projection and SH backward, loss
  backward, conversions);
- ``optimizer``: the Adam step (with compact gradients: and the gradients' scatter into Adam's
  buffers); ``density_control``: the strategy's hooks (amortised);
- ``other``: the iteration's remainder (sampling, logging, checks).

Reports ms per iteration for each, ``kernel_share`` = (forward + backward kernel) / iteration and
``iterations_per_s``; ``cores_busy`` per phase (process CPU time of all threads over wall time in the
same spans: about 1 for a phase that ran single-threaded, up to the core count) and for the whole
iteration. Wall-clock, so the machine's load counts: note it beside any figure.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import torch

log = logging.getLogger(__name__)

PHASES = ("projection", "binning", "forward_kernel", "render_glue", "loss", "backward_kernel", "autograd_rest",
          "optimizer", "density_control", "other")


class _Clock:
    def __init__(self):
        self.seconds = {k: 0.0 for k in ("projection", "binning", "forward_kernel", "render", "loss",
                                         "backward_kernel", "backward", "optimizer", "density_control")}
        self.cpu = dict.fromkeys(self.seconds, 0.0)  # process CPU time (all threads) in the same spans
        self.on = False
        self.active: set[str] = set()  # a span nested in one of its own key counts once

    def wrap(self, key, fn):
        def inner(*args, **kwargs):
            if not self.on or key in self.active:
                return fn(*args, **kwargs)
            start = time.perf_counter()
            cpu = time.process_time()
            self.active.add(key)
            try:
                return fn(*args, **kwargs)
            finally:
                self.active.discard(key)
                self.seconds[key] += time.perf_counter() - start
                self.cpu[key] += time.process_time() - cpu

        return inner


@contextlib.contextmanager
def _instrumented(clock: _Clock):
    """Wrap the functions the training loop calls (restored afterwards)."""
    from ..render import core
    from ..render.kernels import binning, rasterize
    from ..training import loop, optimizer, sparse, strategy

    # the kernels are wrapped where the autograd Function looks them up (render/kernels/rasterize.py)
    patches = [
        (core, "project", "projection"), (sparse, "visible_mask", "projection"),
        (rasterize, "forward_kernel", "forward_kernel"),
        (rasterize, "backward_kernel", "backward_kernel"), (loop, "render_view", "render"),
        # compact gradients: the visibility pass and the gather of the seen rows are part of the render,
        # the gradients' scatter into Adam's buffers part of the optimizer step
        (loop, "visible_rows", "render"), (loop, "CompactView", "render"),
        (optimizer.GaussianOptimizer, "sparse_step", "optimizer"),
        (loop, "photometric_terms", "loss"), (loop, "depth_normal_consistency", "loss"),
        (optimizer.GaussianOptimizer, "step", "optimizer"),
        (strategy.DefaultStrategy, "after_backward", "density_control"),
        (strategy.DefaultStrategy, "after_step", "density_control"),
        (torch.Tensor, "backward", "backward"),
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    binning_init = binning.Binning.__init__
    try:
        for obj, name, key in patches:
            setattr(obj, name, clock.wrap(key, getattr(obj, name)))
        binning.Binning.__init__ = clock.wrap("binning", binning_init)
        yield
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)
        binning.Binning.__init__ = binning_init


def _room(size: tuple[int, int], root: Path, views: int):
    from ..datasets import synthetic
    from ..scene import Scene

    out = root / f"room_{size[0]}x{size[1]}"
    synthetic.generate_scene(out, synthetic.params_from({"width": size[0], "height": size[1], "num_views": views,
                                                          "seed": 0}))
    return Scene.read(out)


def bench_size(size: tuple[int, int], gaussians: int, iterations: int, warmup: int, views: int, root: Path) -> dict:
    from ..gaussians import init_from_depth
    from ..params import from_mapping
    from ..training.loop import fit, scene_extent
    from ..training.params import TrainParams
    from ..training.step import load_images

    scene = _room(size, root, views)
    train = list(scene.train_cameras)
    images = load_images(scene, train)
    base = TrainParams()
    model = init_from_depth(scene, train, stride=1, max_points=gaussians, sh_degree=base.sh_degree,
                            opacity=base.init_opacity, seed=0)
    total = warmup + iterations
    # the default schedule from its densification window on: normal and distortion terms on, density
    # control at its default interval
    params = from_mapping(TrainParams, {"iterations": total, "schedule_scale": 1.0, "densify_from": 0,
                                        "densify_until": total + 1, "normal_from": 0, "distortion_from": 0,
                                        "initial_sh_degree": base.sh_degree, "log_interval": total,
                                        "checkpoint_interval": total}, "bench params")
    clock = _Clock()
    # warm-up (numba compile, caches) outside the clock, then the timed iterations
    warm = from_mapping(TrainParams, {**{k: getattr(params, k) for k in ("schedule_scale", "normal_from",
                                                                         "distortion_from", "initial_sh_degree")},
                                      "iterations": warmup, "densify_from": warmup + 1, "densify_until": warmup + 2,
                                      "log_interval": warmup, "checkpoint_interval": warmup}, "bench params")
    fit(model.detached_copy(), train, images, warm, extent=scene_extent(train), progress=False)
    with _instrumented(clock):
        clock.on = True
        start = time.perf_counter()
        cpu_start = time.process_time()
        result = fit(model.detached_copy(), train, images, params, extent=scene_extent(train), progress=False)
        wall = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
        clock.on = False
    it_ms = 1000.0 * wall / total
    phases = _phases({k: 1000.0 * v / total for k, v in clock.seconds.items()}, it_ms)
    phases_cpu = _phases({k: 1000.0 * v / total for k, v in clock.cpu.items()}, 1000.0 * cpu / total)
    channels = _channel_cost(model, train[len(train) // 2])
    return {
        "channels": channels,
        "width": size[0], "height": size[1], "views": len(train), "gaussians_start": len(model),
        "gaussians_end": len(result.model), "iterations": total, "wall_s": wall,
        "ms_per_iteration": it_ms, "iterations_per_s": 1000.0 / it_ms, "phases_ms": phases,
        "kernel_share": (phases["forward_kernel"] + phases["backward_kernel"]) / it_ms,
        # cores busy = process CPU time / wall time, per phase and for the whole iteration (2 = both
        # cores of a 2-core machine; a phase near 1 ran single-threaded)
        "cores_busy": {k: (phases_cpu[k] / phases[k] if phases[k] > 1e-3 else None) for k in PHASES},
        "cores_busy_iteration": cpu / wall,
    }


def _phases(per: dict, it_ms: float) -> dict:
    """The reported phases from the wrapped spans (ms per iteration; nested spans subtracted)."""
    phases = {
        "projection": per["projection"],
        "binning": per["binning"],
        "forward_kernel": per["forward_kernel"],
        "render_glue": per["render"] - per["projection"] - per["binning"] - per["forward_kernel"],
        "loss": per["loss"],
        "backward_kernel": per["backward_kernel"],
        "autograd_rest": per["backward"] - per["backward_kernel"],
        "optimizer": per["optimizer"],
        "density_control": per["density_control"],
    }
    phases["other"] = it_ms - sum(phases.values())
    return phases


def _channel_cost(model, camera, repeats: int = 7) -> dict:
    """Forward + backward time (ms, median) of one view's render with 3 and with 16 feature
    channels (plus the 3 normal channels the renderer always blends), and their ratio: what
    rendering lifting's 16-d features costs against colour.  ``fwd_bwd_ms_*`` and
    ``ratio_16_over_3`` differentiate the features only, with the geometry frozen as lifting has it
    (the values-only backward); the ``*_geometry`` figures differentiate the geometry as well (the
    backward of a fit)."""
    import numpy as np

    from ..render import Splats, render

    gen = torch.Generator().manual_seed(0)
    frozen = Splats(*(t.detach() for t in model.splats()))
    moving = Splats(*(t.detach().clone().requires_grad_() for t in frozen))
    out = {}
    for suffix, splats in (("", frozen), ("_geometry", moving)):
        for c in (3, 16):
            feats = torch.rand(len(model), c, generator=gen).requires_grad_()
            times = []
            for _ in range(repeats + 1):
                start = time.perf_counter()
                image = render(splats, camera, feats).features
                torch.autograd.grad(image.sum(), feats)
                times.append(time.perf_counter() - start)
            out[f"fwd_bwd_ms_{c}{suffix}"] = 1000.0 * float(np.median(times[1:]))
        out[f"ratio_16_over_3{suffix}"] = out[f"fwd_bwd_ms_16{suffix}"] / out[f"fwd_bwd_ms_3{suffix}"]
    return out


def run_bench(quick: bool = False, sizes: list[tuple[int, int]] | None = None,
              iterations: int | None = None) -> dict:
    """The phase table for each size (default: 160x120 and 504x378; ``quick``: fewer Gaussians and
    iterations, a smoke run)."""
    import numba

    from ..tooling.cputarget import describe
    from ..render.kernels.glue import fused_enabled

    gaussians = 5000 if quick else 80_000
    default_iterations, warmup = (10, 3) if quick else (200, 10)
    iterations = default_iterations if iterations is None else int(iterations)
    if iterations < 1:
        raise ValueError(f"bench fit: iterations must be >= 1, got {iterations}")
    views = 6 if quick else 24
    sizes = [(160, 120), (504, 378)] if sizes is None else list(sizes)
    from ..training.params import TrainParams

    # torch_threads: the process's; the fit itself runs torch with TrainParams.torch_threads
    out = {"torch_threads": torch.get_num_threads(), "fit_torch_threads": TrainParams().torch_threads,
           "numba_threads": numba.get_num_threads(),
           "gaussians": gaussians, "quick": quick, "fused_glue": fused_enabled(),
           "sparse_grad": TrainParams().sparse_grad, "cpu": describe(), "sizes": {}}
    with tempfile.TemporaryDirectory(prefix="trace3d-bench-fit-") as tmp:
        for size in sizes:
            log.info("bench fit: %dx%d, %d Gaussians, %d iterations", size[0], size[1], gaussians, iterations)
            out["sizes"][f"{size[0]}x{size[1]}"] = bench_size(size, gaussians, iterations, warmup, views, Path(tmp))
    out["load_average"] = [round(x, 2) for x in os.getloadavg()]
    return out


# ----------------------------------------------------------------------------------------------
# The other lever: the defaults (Gaussian budget x iterations)
# ----------------------------------------------------------------------------------------------


def run_sweep(rooms: list[Path], budgets: list[int], scales: list[float], out_plot: Path | None = None,
              base_params: dict | None = None) -> dict:
    """Fit each room at every (``max_gaussians``, ``schedule_scale``) pair with the ``gaussians``
    step itself and report test PSNR against fit minutes.

    Args:
        rooms: fitted rooms' results folders (their ``scene/`` and ``poses/`` are read).
        budgets: Gaussian budgets (``max_gaussians``); scales: schedule scales (0.1 = 3,000 iterations).
        out_plot: optional PNG, test PSNR against minutes, one line per budget and room.
        base_params: other ``gaussians`` parameters (default: the library defaults).
    Returns:
        {"rows": [{room, max_gaussians, schedule_scale, iterations, test_psnr, minutes, gaussians}],
         "load_average": [...]}.
    """
    from ..scene import Scene
    from ..training.step import run_gaussians

    rows = []
    for room in rooms:
        room = Path(room)
        scene = Scene.read(room / "scene")
        poses = room / "poses"
        for budget in budgets:
            for scale in scales:
                params = {**(base_params or {}), "max_gaussians": int(budget), "schedule_scale": float(scale)}
                log.info("fit sweep: %s, max_gaussians %d, schedule_scale %g", room.name, budget, scale)
                with tempfile.TemporaryDirectory(prefix="trace3d-fit-sweep-") as tmp:
                    run_gaussians(scene, poses if poses.is_dir() else None, Path(tmp), params)
                    metrics = json.loads((Path(tmp) / "metrics.json").read_text())
                rows.append({"room": room.name, "max_gaussians": int(budget), "schedule_scale": float(scale),
                             "iterations": metrics["iterations"], "test_psnr": metrics["test_psnr"],
                             "minutes": metrics["minutes"], "train_minutes": metrics["train_minutes"],
                             "gaussians": metrics["num_gaussians"]})
    result = {"rows": rows, "load_average": [round(x, 2) for x in os.getloadavg()]}
    if out_plot is not None:
        plot_sweep(rows, Path(out_plot))
    return result


def merge_sweeps(files: list[Path], out_plot: Path | None = None) -> dict:
    """The rows of several :func:`run_sweep` results (their JSON files, in order) as one result, with
    each file's load average kept per row; optionally plotted.  A sweep run in parts (more
    points added later) is plotted from its files, not retyped."""
    from ..errors import Trace3DError

    rows = []
    for f in files:
        try:
            part = json.loads(Path(f).read_text())
            part_rows = part["rows"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise Trace3DError(f"{f}: not a fit-sweep result (JSON with 'rows'): {err}") from err
        rows += [{**r, "load_average": part.get("load_average")} for r in part_rows]
    result = {"rows": rows, "merged_from": [str(f) for f in files]}
    if out_plot is not None:
        plot_sweep(rows, Path(out_plot))
    return result


def plot_sweep(rows: list[dict], path: Path) -> None:
    """Test PSNR against fit minutes: one line per (room, budget) through its iteration counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_file

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    rooms = sorted({r["room"] for r in rows})
    budgets = sorted({r["max_gaussians"] for r in rows})
    markers = "os^vD*"
    for ri, room in enumerate(rooms):
        for bi, budget in enumerate(budgets):
            pts = sorted((r["minutes"], r["test_psnr"], r["iterations"]) for r in rows
                         if r["room"] == room and r["max_gaussians"] == budget)
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=markers[ri % len(markers)],
                    color=f"C{bi}", linestyle="-" if ri == 0 else "--",
                    label=f"{room}, {budget // 1000}k Gaussians")
            for m, psnr, its in pts:
                ax.annotate(f"{its}", (m, psnr), textcoords="offset points", xytext=(3, -10), fontsize=7)
    ax.set_xlabel("gaussians step, minutes (fit + evaluation)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title("2DGS fit: Gaussian budget x iterations (labels: iterations)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def run_baseline(checkout: Path, sizes: list[tuple[int, int]] | None, iterations: int | None,
                 quick: bool) -> dict:
    """``trace3d bench fit`` of another checkout (e.g. a ``git worktree`` of the previous main), run
    in a subprocess with that checkout first on ``PYTHONPATH`` and its own numba cache, so that a
    change is measured side by side with what it replaces on the same machine in one run.

    Only options that checkout's benchmark knows are passed: ``--size``/``--iterations`` only when
    they differ from the defaults.
    """
    import subprocess
    import sys

    from ..tooling.cputarget import set_here

    checkout = Path(checkout).resolve()
    # trace3d/bench/fit.py, or trace3d/training/bench.py in checkouts from before the harnesses moved
    if not any((checkout / "trace3d" / sub).is_file() for sub in ("bench/fit.py", "training/bench.py")):
        raise FileNotFoundError(f"{checkout}: not a trace3d checkout with a fit benchmark (trace3d/bench/fit.py).")
    with tempfile.TemporaryDirectory(prefix="trace3d-bench-baseline-") as tmp:
        out = Path(tmp) / "baseline.json"
        cmd = [sys.executable, "-m", "trace3d.cli", "bench", "fit", "--out", str(out)]
        if quick:
            cmd.append("--quick")
        if sizes is not None and sizes != [(160, 120), (504, 378)]:
            for w, h in sizes:
                cmd += ["--size", f"{w}x{h}"]
        if iterations is not None:
            cmd += ["--iterations", str(iterations)]
        env = {**os.environ, "PYTHONPATH": str(checkout) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               "NUMBA_CACHE_DIR": str(Path(tmp) / "numba_cache")}
        # the CPU target this process's entry point chose is the current code's choice, not the
        # baseline's: its own entry point makes its own (a value the user set stays)
        if set_here() is not None and env.get("NUMBA_CPU_FEATURES") == set_here():
            del env["NUMBA_CPU_FEATURES"]
        log.info("bench fit: baseline %s", checkout)
        proc = subprocess.run(cmd, cwd=checkout, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"bench fit of the baseline {checkout} failed: {proc.stderr.strip()[-2000:]}")
        result = json.loads(out.read_text())
    head = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    result["checkout"] = str(checkout)
    result["commit"] = head.stdout.strip() if head.returncode == 0 else None
    return result


def compare(current: dict, baseline: dict) -> dict:
    """Per size: iterations/s of both and their ratio.  With rounds (:func:`median_round`), also the
    ratio of each round pair (``speedups``: baseline round r against current round r, run one after the
    other) and ``speedup`` is their median, not the ratio of the medians."""
    out = {}
    for size, row in current["sizes"].items():
        base = baseline["sizes"].get(size)
        if base:
            out[size] = {"iterations_per_s": row["iterations_per_s"],
                         "baseline_iterations_per_s": base["iterations_per_s"],
                         "speedup": row["iterations_per_s"] / base["iterations_per_s"]}
            cur_rounds, base_rounds = row.get("rounds_ms_per_iteration"), base.get("rounds_ms_per_iteration")
            if cur_rounds and base_rounds and len(cur_rounds) == len(base_rounds):
                speedups = [b / c for b, c in zip(base_rounds, cur_rounds)]
                out[size]["speedups"] = speedups
                out[size]["speedup"] = sorted(speedups)[(len(speedups) - 1) // 2]
    return out


def median_round(results: list[dict]) -> dict:
    """Several runs of the benchmark (rounds) as one result: per size, the round with the median
    ``ms_per_iteration`` (the lower one of the middle two for an even count; a real run, so its phases
    add up), plus every round's ``ms_per_iteration`` and ``kernel_share`` (``rounds_ms_per_iteration``,
    ``rounds_kernel_share``, in run order).  The machine drifts by several percent between runs minutes
    apart (docs/performance.md), more than many changes are worth: alternating rounds of the baseline
    and the current code and pairing them is how a small change is measured."""
    if not results:
        raise ValueError("median_round: no rounds")
    out = {k: v for k, v in results[0].items() if k != "sizes"}
    out["rounds"] = len(results)
    out["load_average"] = [r.get("load_average") for r in results]
    out["sizes"] = {}
    for size in results[0]["sizes"]:
        rows = [r["sizes"][size] for r in results]
        ms = [row["ms_per_iteration"] for row in rows]
        pick = sorted(range(len(rows)), key=lambda i: ms[i])[(len(rows) - 1) // 2]
        out["sizes"][size] = {**rows[pick], "round": pick, "rounds_ms_per_iteration": ms,
                              "rounds_kernel_share": [row["kernel_share"] for row in rows]}
    return out


def run_rounds(rounds: int, quick: bool = False, sizes: list[tuple[int, int]] | None = None,
               iterations: int | None = None, baseline: Path | None = None) -> dict:
    """``rounds`` runs of :func:`run_bench` (each after a run of ``baseline``'s benchmark when given:
    baseline, current, baseline, current, ...), summarised by :func:`median_round`; with a baseline,
    ``baseline`` (its rounds, summarised the same way) and ``compared`` (:func:`compare`) are added."""
    if rounds < 1:
        raise ValueError(f"bench fit: rounds must be >= 1, got {rounds}")
    currents, bases = [], []
    for r in range(rounds):
        if baseline is not None:
            log.info("bench fit: round %d of %d, baseline", r + 1, rounds)
            bases.append(run_baseline(baseline, sizes, iterations, quick))
        log.info("bench fit: round %d of %d, current code", r + 1, rounds)
        currents.append(run_bench(quick=quick, sizes=sizes, iterations=iterations))
    result = median_round(currents) if rounds > 1 else currents[0]
    if bases:
        base = median_round(bases) if rounds > 1 else bases[0]
        for key in ("checkout", "commit"):
            base[key] = bases[0].get(key)
        result = {**result, "baseline": base, "compared": compare(result, base)}
    return result
