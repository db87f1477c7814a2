"""``trace3d bench synthetic``: the time to generate and write the default room."""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numba

from ..datasets.synthetic.cameras import camera_trajectory
from ..datasets.synthetic.params import SyntheticParams
from ..datasets.synthetic.raycast import render_view
from ..datasets.synthetic.room import build_room
from ..datasets.synthetic.writer import generate_scene


def run_bench(quick: bool = False) -> dict:
    """Time generating the default room (``quick``: 8 views) including PNG writing.

    Returns views, resolution, compile_s (first-call numba compile / cache load), total_s and
    ms_per_view (wall clock: rendering + writing, after compilation), cpu_s (process CPU time),
    numba_threads and the 1-minute load average (the machine may be shared).
    """
    params = SyntheticParams(num_views=8) if quick else SyntheticParams()
    start = time.perf_counter()
    tiny = dataclasses.replace(SyntheticParams(), width=16, height=12)
    render_view(build_room(tiny).packed(), camera_trajectory(tiny)[0], 1)
    compile_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        cpu_start = time.process_time()
        generate_scene(Path(tmp) / "scene", params)
        total = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
    return {
        "views": params.num_views,
        "resolution": [params.width, params.height],
        "supersample": params.supersample,
        "compile_s": round(compile_s, 3),
        "total_s": round(total, 3),
        "ms_per_view": round(1000 * total / params.num_views, 2),
        "cpu_s": round(cpu, 3),  # all threads of this process; on a busy machine total_s >> cpu_s / cores
        "numba_threads": int(numba.get_num_threads()),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
