"""``trace3d bench evaluate``: where the seconds of one evaluation go.

Runs the ``evaluate`` step of one (scene, variant, protocol) of a results folder into a temporary
folder (``--out`` keeps it) and prints the wall and CPU seconds of each phase (:class:`~.step.Phases`:
load, ground_truth, object_gaussians, extraction, nvs, object_files, picture_renders, single_point,
panoptic, pictures, write), the total, and the seconds numba spent compiling (a cold cache).

The load of the machine changes wall seconds; ``cpu_s`` (the process's user + system time) is
steadier on a shared box, and the JSON records ``os.getloadavg()`` before and after.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import torch

from ..errors import Trace3DError


def run_bench(room: Path, variant: str = "full", params: dict | None = None, out: Path | None = None,
              repeats: int = 1) -> dict:
    """Evaluate ``room/variant/lift`` (``params``: the evaluate step's, default the standard protocol)
    ``repeats`` times; report every run's phases (the first may include numba compilation)."""
    from ..tooling import compiling
    from ..tooling.cputarget import describe
    from ..evaluation.step import Phases, run_evaluate

    room = Path(room)
    lift = room / variant / "lift"
    gaussians = _gaussians_dir(room, variant)
    poses = room / "poses" if (room / "poses").exists() else None  # None: the scene's own cameras
    for part in (room / "scene", lift / "lift.json", gaussians / "point_cloud.ply"):
        if not part.exists():
            raise Trace3DError(f"{part}: missing; run the pipeline for this room and variant first "
                               f"(e.g. `snakemake --cores 2 {lift}`) or pass --room / --variant.")
    params = dict(params or {"protocol": "standard"})
    runs = []
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="trace3d-bench-evaluate-") as tmp:
        for r in range(repeats):
            target = Path(out) / f"run{r}" if out is not None else Path(tmp) / f"run{r}"
            phases = Phases()
            compiled = compiling.compile_seconds() if hasattr(compiling, "compile_seconds") else None
            wall, cpu = time.perf_counter(), time.process_time()
            metrics = run_evaluate(room / "scene", poses, gaussians, lift, target / "eval", params,
                                   {"variant": variant}, target / "objects", phases=phases)
            run = {"wall_s": round(time.perf_counter() - wall, 3), "cpu_s": round(time.process_time() - cpu, 3),
                   "phases": phases.to_json(), "objects": len(metrics["objects"])}
            if compiled is not None:
                run["compile_s"] = round(compiling.compile_seconds() - compiled, 3)
            runs.append(run)
    return {"cpu": describe(), "room": str(room), "variant": variant, "gaussians_dir": str(gaussians), "params": params,
            "torch_threads": torch.get_num_threads(), "loadavg_before": load_before, "loadavg_after": os.getloadavg(),
            "runs": runs}


def _gaussians_dir(room: Path, variant: str) -> Path:
    """The Gaussians the variant's lift ran on: ``lift.json`` does not name them, so the refined
    folder whose Gaussian count matches, else ``gaussians``."""
    info = json.loads((room / variant / "lift" / "lift.json").read_text())
    count = info.get("gaussians")
    candidates = sorted(room.glob("refine-*")) + [room / "gaussians"]
    for folder in candidates:
        ply = folder / "point_cloud.ply"
        if ply.is_file() and count is not None and _ply_vertices(ply) == count:
            return folder
    return room / "gaussians"


def _ply_vertices(path: Path) -> int | None:
    with open(path, "rb") as fh:
        for _ in range(64):
            line = fh.readline()
            if line.startswith(b"element vertex"):
                return int(line.split()[-1])
            if line.strip() == b"end_header":
                break
    return None
