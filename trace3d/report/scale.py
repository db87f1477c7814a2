"""How each step's cost grows with the scene: the ``scale-table`` command (issue 36, docs/scale.md).

Snakemake's ``benchmark:`` files (``<results>/benchmarks/<scene>/<step>.tsv``, one per job) hold the
job's wall seconds ``s``, its peak resident memory ``max_rss`` (MB) and its CPU seconds ``cpu_time``.
For two scenes of one room at two sizes (config/scale.yaml: 320x240 x 100 views and 640x480 x 250
views) :func:`scale_rows` pairs the steps that ran on both and gives, per step,

    work ratio   w = (views x pixels of the large scene) / (views x pixels of the small one)
    cpu ratio    c = cpu_time(large) / cpu_time(small)        (likewise for s and max_rss)
    exponent     b = log c / log w        cost ~ (views x pixels)^b: 1 = linear, 2 = quadratic

where views x pixels is summed over the scene's cameras (``cameras.json``: every view's width x
height). CPU seconds, not wall seconds, are the cost to compare on a shared machine: a job waiting for
a core adds wall time, not CPU time; peak memory does not depend on the load at all.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

from ..errors import Trace3DError
from ..io import atomic_file

COLUMNS = ("s", "max_rss", "cpu_time")


@dataclass(frozen=True)
class Bench:
    """One step's benchmark: wall seconds, peak RSS (MB), CPU seconds (means over the file's rows;
    the peak is the largest)."""

    seconds: float
    max_rss_mb: float
    cpu_seconds: float


def read_benchmark(path: Path) -> Bench:
    """The :class:`Bench` of one Snakemake benchmark TSV (header ``s h:m:s max_rss ... cpu_time``)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    if not rows:
        raise Trace3DError(f"{path}: benchmark file has no rows (was the job benchmarked to the end?).")
    missing = [c for c in COLUMNS if c not in rows[0]]
    if missing:
        raise Trace3DError(f"{path}: benchmark file lacks the column(s) {', '.join(missing)}; expected a "
                           f"Snakemake benchmark TSV (s, max_rss, cpu_time, ...).")
    try:
        values = {c: [float(r[c]) for r in rows] for c in COLUMNS}
    except (TypeError, ValueError) as exc:
        raise Trace3DError(f"{path}: a benchmark value is not a number ({exc}).") from exc
    return Bench(seconds=sum(values["s"]) / len(rows), max_rss_mb=max(values["max_rss"]),
                 cpu_seconds=sum(values["cpu_time"]) / len(rows))


def read_benchmarks(folder: Path) -> dict[str, Bench]:
    """Every benchmark under ``folder`` (one scene's), keyed by its path without ``.tsv``
    (``scene``, ``trace-paper``, ``full/lift``, ...)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise Trace3DError(f"{folder}: no benchmark folder (run the scene's steps with Snakemake first).")
    return {p.relative_to(folder).with_suffix("").as_posix(): read_benchmark(p)
            for p in sorted(folder.rglob("*.tsv"))}


@dataclass(frozen=True)
class SceneSize:
    """A scene's size: views, pixels of one view (the largest), and views x pixels summed over views."""

    views: int
    pixels: int
    view_pixels: int


def scene_size(scene_dir: Path) -> SceneSize:
    """The :class:`SceneSize` of the canonical scene folder ``scene_dir`` (its cameras.json)."""
    from ..scene import Scene

    scene = Scene.read(Path(scene_dir), check_files=False)
    sizes = [c.width * c.height for c in scene.cameras]
    if not sizes:
        raise Trace3DError(f"{scene_dir}: the scene has no cameras.")
    return SceneSize(views=len(sizes), pixels=max(sizes), view_pixels=sum(sizes))


def _ratio(large: float, small: float) -> float | None:
    return large / small if small > 0 and large > 0 else None


def _exponent(ratio: float | None, work: float) -> float | None:
    return math.log(ratio) / math.log(work) if ratio is not None and work > 0 and work != 1.0 else None


def scale_rows(small: dict[str, Bench], large: dict[str, Bench], small_size: SceneSize,
               large_size: SceneSize) -> list[dict]:
    """One row per step that ran at both sizes (in the order of ``small``): both sizes' seconds, CPU
    seconds and peak RSS, the ratios large / small, the work ratio and the CPU exponent (module
    docstring). Steps that ran at one size only get a row with that size's values and no ratios."""
    work = large_size.view_pixels / small_size.view_pixels
    rows = []
    for step in list(small) + [s for s in large if s not in small]:
        a, b = small.get(step), large.get(step)
        row = {"step": step,
               "s_small": a.seconds if a else None, "s_large": b.seconds if b else None,
               "cpu_small": a.cpu_seconds if a else None, "cpu_large": b.cpu_seconds if b else None,
               "rss_small_mb": a.max_rss_mb if a else None, "rss_large_mb": b.max_rss_mb if b else None,
               "work_ratio": work, "cpu_ratio": None, "rss_ratio": None, "cpu_exponent": None}
        if a and b:
            row["cpu_ratio"] = _ratio(b.cpu_seconds, a.cpu_seconds)
            row["rss_ratio"] = _ratio(b.max_rss_mb, a.max_rss_mb)
            row["cpu_exponent"] = _exponent(row["cpu_ratio"], work)
        rows.append(row)
    return rows


def _cell(value, digits: int) -> str:
    return "—" if value is None else f"{value:,.{digits}f}"


def scale_markdown(rows: list[dict], small_name: str, large_name: str, small_size: SceneSize,
                   large_size: SceneSize) -> str:
    """The rows of :func:`scale_rows` as a Markdown document (title, sizes, table)."""
    def size(name: str, s: SceneSize) -> str:
        return f"`{name}`: {s.views} views of {s.pixels:,} pixels = {s.view_pixels / 1e6:.2f} M view-pixels"

    work = rows[0]["work_ratio"] if rows else large_size.view_pixels / small_size.view_pixels
    lines = [
        "# Step cost at two scene sizes",
        "",
        f"{size(small_name, small_size)}; {size(large_name, large_size)}; work ratio w = {work:.2f}.",
        "cpu = CPU seconds (user + system), s = wall seconds, RSS = peak resident memory (MB), from the",
        "Snakemake benchmark files; ratio = large / small; exponent b = log(cpu ratio) / log(w)",
        "(cost ~ (views x pixels)^b: 1 = linear). `trace3d scale-table` writes this file (docs/scale.md).",
        "",
        f"| step | cpu {small_name} | cpu {large_name} | s {small_name} | s {large_name} | "
        f"RSS {small_name} | RSS {large_name} | cpu ratio | exponent b | RSS ratio |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['step']} | {_cell(r['cpu_small'], 1)} | {_cell(r['cpu_large'], 1)} | {_cell(r['s_small'], 1)} | "
            f"{_cell(r['s_large'], 1)} | {_cell(r['rss_small_mb'], 0)} | {_cell(r['rss_large_mb'], 0)} | "
            f"{_cell(r['cpu_ratio'], 2)} | {_cell(r['cpu_exponent'], 2)} | {_cell(r['rss_ratio'], 2)} |")
    return "\n".join(lines) + "\n"


def write_scale_table(results: Path, small: str, large: str, out: Path) -> list[dict]:
    """Read ``<results>/benchmarks/<small|large>/`` and ``<results>/<small|large>/scene/``; write the
    Markdown table to ``out`` and a CSV beside it (same stem). Returns the rows."""
    results = Path(results)
    sizes = {name: scene_size(results / name / "scene") for name in (small, large)}
    rows = scale_rows(read_benchmarks(results / "benchmarks" / small), read_benchmarks(results / "benchmarks" / large),
                      sizes[small], sizes[large])
    if not rows:
        raise Trace3DError(f"{results}/benchmarks: no benchmark files for {small} or {large}.")
    with atomic_file(out) as tmp:
        tmp.write_text(scale_markdown(rows, small, large, sizes[small], sizes[large]))
    with atomic_file(Path(out).with_suffix(".csv")) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return rows
