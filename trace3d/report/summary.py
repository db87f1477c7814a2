"""The per-scene summary table (``results/scenes.md``)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..io import atomic_file
from ..scene import Scene


def scene_row(scene_dir: Path) -> dict:
    """One table row describing the canonical scene in ``scene_dir``."""
    scene = Scene.read(scene_dir, check_files=False)
    sizes = sorted({(c.width, c.height) for c in scene.cameras})
    objects = scene.objects
    return {
        "scene": scene_dir.parent.name if scene_dir.name == "scene" else scene_dir.name,
        "source": scene.meta.get("source", "unknown"),
        "views": len(scene.cameras),
        "train": len(scene.train_cameras),
        "test": len(scene.test_cameras),
        "objects": sum(1 for o in objects if o.level == "object") if objects is not None else 0,
        "evaluated": len(objects.evaluated_ids()) if objects is not None else 0,
        "resolution": ", ".join(f"{w}x{h}" for w, h in sizes),
    }


def write_scene_table(scene_dirs: list[Path], out: Path) -> pd.DataFrame:
    """Write a Markdown table (and a CSV beside it) with one row per scene."""
    table = pd.DataFrame([scene_row(Path(d)) for d in scene_dirs])
    with atomic_file(out) as tmp:
        tmp.write_text("# Scenes\n\n" + table.to_markdown(index=False) + "\n")
    with atomic_file(Path(out).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    return table


def _read_json(path: Path) -> dict:
    import json

    from ..errors import Trace3DError

    if not path.is_file():
        raise Trace3DError(f"{path}: result file is missing (did the step run?).")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise Trace3DError(f"{path}: not valid JSON ({exc}).") from exc


def reconstruction_row(poses_dir: Path, gaussians_dir: Path) -> dict:
    """One row of the reconstruction table from ``<poses_dir>/sfm.json`` and ``<gaussians_dir>/metrics.json``;
    the scene is named after the folder that holds both."""
    scene = Path(gaussians_dir).resolve().parent.name
    sfm = _read_json(Path(poses_dir) / "sfm.json")
    metrics = _read_json(Path(gaussians_dir) / "metrics.json")
    alignment = sfm.get("alignment") or {}
    row = {
        "scene": scene,
        "poses": sfm.get("mode", "?"),
        "registered": f"{sfm.get('images_registered', '?')}/{sfm.get('images_total', '?')}",
        "pose error (% extent)": (
            round(100.0 * alignment["center_error_rel_mean"], 3) if "center_error_rel_mean" in alignment else None
        ),
        "rotation error (deg)": (
            round(alignment["rotation_error_deg_mean"], 3) if "rotation_error_deg_mean" in alignment else None
        ),
        "gaussians": metrics.get("num_gaussians"),
        "PSNR": round(metrics["test_psnr"], 2) if metrics.get("test_psnr") is not None else None,
        "SSIM": round(metrics["test_ssim"], 4) if metrics.get("test_ssim") is not None else None,
        "train PSNR": round(metrics["train_psnr"], 2) if metrics.get("train_psnr") is not None else None,
        "minutes": round(metrics.get("minutes", float("nan")), 2),
    }
    return row


def write_reconstruction_table(
    poses_dirs: list[Path], gaussians_dirs: list[Path], out: Path, plot: Path | None = None
) -> pd.DataFrame:
    """Write the reconstruction table (Markdown + CSV) and, optionally, a bar plot of test PSNR and minutes.

    ``poses_dirs`` and ``gaussians_dirs`` are paired by position, one pair per scene.
    """
    from ..errors import Trace3DError

    if len(poses_dirs) != len(gaussians_dirs):
        raise Trace3DError(
            f"reconstruction table: {len(poses_dirs)} poses folders but {len(gaussians_dirs)} gaussians folders."
        )
    table = pd.DataFrame([reconstruction_row(Path(p), Path(g)) for p, g in zip(poses_dirs, gaussians_dirs)])
    mean = {"scene": "mean", "poses": "", "registered": ""}
    for col in ("pose error (% extent)", "rotation error (deg)", "gaussians", "PSNR", "SSIM", "train PSNR", "minutes"):
        values = pd.to_numeric(table[col], errors="coerce")
        mean[col] = round(float(values.mean()), 3) if values.notna().any() else None
    shown = pd.concat([table, pd.DataFrame([mean])], ignore_index=True)
    with atomic_file(out) as tmp:
        tmp.write_text(
            "# Reconstruction\n\nPoses (views registered, camera-centre error after Sim(3) alignment relative to the "
            "diameter of the ground-truth camera centres) and the 2DGS fit (test-view PSNR / SSIM, Gaussians, "
            "minutes of the `gaussians` step).\n\n" + shown.to_markdown(index=False) + "\n"
        )
    with atomic_file(Path(out).with_suffix(".csv")) as tmp:
        table.to_csv(tmp, index=False)
    if plot is not None:
        _plot_psnr(table, plot)
    return table


def _plot_psnr(table: pd.DataFrame, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    psnr = pd.to_numeric(table["PSNR"], errors="coerce").fillna(0.0)
    axes[0].bar(table["scene"], psnr, color="tab:blue")
    axes[0].axhline(27.0, color="tab:red", linestyle="--", label="goal 27 dB")
    axes[0].set_ylabel("test PSNR (dB)")
    axes[0].set_title("2DGS fit, test views")
    axes[0].legend(loc="lower right")
    axes[1].bar(table["scene"], pd.to_numeric(table["minutes"], errors="coerce").fillna(0.0), color="tab:gray")
    axes[1].axhline(10.0, color="tab:red", linestyle="--", label="budget 10 min")
    axes[1].set_ylabel("minutes")
    axes[1].set_title("`gaussians` step time")
    axes[1].legend(loc="lower right")
    for ax in axes:
        ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
