"""`trace3d scale-table` (trace3d.report.scale): benchmark files of two scene sizes -> ratios and exponents."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from trace3d.errors import Trace3DError
from trace3d.report.scale import Bench, SceneSize, read_benchmark, scale_rows, scene_size, write_scale_table
from trace3d.scene import Camera, write_cameras

HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def bench(path, rows):
    """A Snakemake benchmark TSV with ``rows`` of (s, max_rss, cpu_time)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER + "".join(f"{s}\t0:00:00\t{rss}\t1.0\t1.0\t1.0\t0.0\t0.0\t50.0\t{cpu}\n"
                                     for s, rss, cpu in rows))


def scene(folder, views, width, height):
    folder.mkdir(parents=True, exist_ok=True)
    K = [[width, 0, width / 2], [0, width, height / 2], [0, 0, 1]]
    write_cameras(folder, [Camera(f"view_{i:03d}", "train", width, height, K, np.eye(4)) for i in range(views)])


def results(root):
    """Small: 10 views of 40x30 (12,000 view-pixels); large: 25 views of 80x60 (120,000): w = 10."""
    scene(root / "a" / "scene", 10, 40, 30)
    scene(root / "b" / "scene", 25, 80, 60)
    bench(root / "benchmarks" / "a" / "scene.tsv", [(2.0, 100.0, 4.0)])
    bench(root / "benchmarks" / "b" / "scene.tsv", [(30.0, 900.0, 40.0)])           # linear: 10x
    bench(root / "benchmarks" / "a" / "trace-paper.tsv", [(1.0, 200.0, 3.0)])
    bench(root / "benchmarks" / "b" / "trace-paper.tsv", [(50.0, 400.0, 300.0)])    # quadratic: 100x
    bench(root / "benchmarks" / "a" / "full" / "lift.tsv", [(5.0, 300.0, 10.0), (7.0, 310.0, 14.0)])  # 2 runs
    bench(root / "benchmarks" / "b" / "full" / "lift.tsv", [(6.0, 320.0, 12.0)])
    bench(root / "benchmarks" / "b" / "gaussians.tsv", [(9.0, 999.0, 18.0)])        # large only


def test_rows_ratios_and_exponents(tmp_path):
    results(tmp_path)
    rows = write_scale_table(tmp_path, "a", "b", tmp_path / "out" / "scale.md")
    by = {r["step"]: r for r in rows}
    assert list(by) == ["full/lift", "scene", "trace-paper", "gaussians"]
    assert all(r["work_ratio"] == pytest.approx(10.0) for r in rows)
    assert by["scene"]["cpu_ratio"] == pytest.approx(10.0) and by["scene"]["cpu_exponent"] == pytest.approx(1.0)
    assert by["scene"]["rss_ratio"] == pytest.approx(9.0)
    assert by["trace-paper"]["cpu_exponent"] == pytest.approx(2.0)
    # two rows: mean seconds and CPU seconds, largest peak
    assert by["full/lift"]["cpu_small"] == pytest.approx(12.0) and by["full/lift"]["s_small"] == pytest.approx(6.0)
    assert by["full/lift"]["rss_small_mb"] == pytest.approx(310.0)
    assert by["full/lift"]["cpu_exponent"] == pytest.approx(0.0)
    assert by["gaussians"]["cpu_small"] is None and by["gaussians"]["cpu_exponent"] is None
    assert by["gaussians"]["cpu_large"] == pytest.approx(18.0)
    text = (tmp_path / "out" / "scale.md").read_text()
    assert "10 views of 1,200 pixels = 0.01 M view-pixels" in text and "work ratio w = 10.00" in text
    assert "| trace-paper | 3.0 | 300.0 | 1.0 | 50.0 | 200 | 400 | 100.00 | 2.00 | 2.00 |" in text
    assert "| gaussians | — | 18.0 |" in text
    with open(tmp_path / "out" / "scale.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert [r["step"] for r in table] == list(by)
    assert float(table[2]["cpu_exponent"]) == pytest.approx(2.0)


def test_exponent_against_a_power_law():
    """cost = c (views x pixels)^b at two sizes gives b back, whatever the sizes."""
    small, large = SceneSize(7, 5000, 35_000), SceneSize(31, 20_000, 620_000)
    for b in (0.5, 1.0, 1.3):
        rows = scale_rows({"x": Bench(1.0, 10.0, 2.0 * 35_000 ** b)}, {"x": Bench(1.0, 10.0, 2.0 * 620_000 ** b)},
                          small, large)
        assert rows[0]["cpu_exponent"] == pytest.approx(b)
        assert rows[0]["cpu_ratio"] == pytest.approx((620_000 / 35_000) ** b)
        assert math.isclose(rows[0]["work_ratio"], 620_000 / 35_000)


def test_bad_inputs(tmp_path):
    from trace3d.cli import main

    bench(tmp_path / "empty.tsv", [])
    with pytest.raises(Trace3DError, match="no rows"):
        read_benchmark(tmp_path / "empty.tsv")
    (tmp_path / "other.tsv").write_text("s\tmax_rss\n1\t2\n")
    with pytest.raises(Trace3DError, match="cpu_time"):
        read_benchmark(tmp_path / "other.tsv")
    with pytest.raises(Trace3DError, match="cameras.json"):
        scene_size(tmp_path)
    results(tmp_path / "r")
    assert main(["scale-table", "--results", str(tmp_path / "r"), "--small", "a", "--large", "zz",
                 "--out", str(tmp_path / "o.md")]) == 2
    assert main(["scale-table", "--results", str(tmp_path / "r"), "--small", "a", "--large", "b",
                 "--out", str(tmp_path / "o.md")]) == 0
    assert (tmp_path / "o.csv").is_file()
