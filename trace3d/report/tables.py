"""The paper's result tables from the evaluate step's ``metrics.json`` files.

Reads every ``<results>/<scene>/<variant>/eval/metrics.json`` and writes, each as ``.md``, ``.csv``
and ``.tex`` into the output folder (variants as rows, the paper's layout):

    table2        3D object extraction (paper Table 2): object mIoU per scene, mean mIoU, mean PSNR
    table2_psnr   the same PSNR per scene (the supplementary's PSNR table)
    table3        novel-view 2D segmentation (paper Table 3): NVS mIoU per scene, mean mIoU, mean mAcc
    table5        ablation (paper Table 5): consistent 2D masks x ambiguous-Gaussian (density) control,
                  NVS mIoU, object mIoU, PSNR; rows come from the variant settings saved in each
                  metrics.json; combinations no variant covers are left out

mIoU and mAcc are in percent, PSNR in dB; means are over scenes, "mean ± std" with the population
standard deviation over scenes. A variant missing a scene shows "–" there and its mean is over the
scenes it has. Output is deterministic (sorted inputs, fixed formatting).
"""

from __future__ import annotations

import csv
import io
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SceneFormatError, Trace3DError
from ..io import atomic_file

log = logging.getLogger(__name__)

GRID_KEYS = ("consistent_masks", "density_control")
# Variant settings that joined later: a metrics.json written before a key existed had its default.
SETTING_DEFAULTS = {"preset": "paper", "lifting": "contrastive", "overlay": False}
DASH = "–"
SELF_PROMPT = "self_prompt"


@dataclass
class Row:
    """One variant's figures over the scenes."""

    name: str
    settings: dict
    method: str
    protocols: set = field(default_factory=set)
    object_miou: dict = field(default_factory=dict)  # scene -> fraction
    psnr: dict = field(default_factory=dict)  # scene -> dB
    nvs_miou: dict = field(default_factory=dict)
    nvs_macc: dict = field(default_factory=dict)


def collect(results: Path, evals: list[Path] | None = None) -> tuple[list[str], list[Row]]:
    """Scenes (sorted) and one :class:`Row` per variant (sorted by name) from ``results`` (every
    ``*/*/eval/metrics.json``), or from exactly the ``evals`` folders (``<scene>/<variant>/eval``)."""
    results = Path(results)
    if not results.is_dir():
        raise Trace3DError(f"{results}: results folder does not exist.")
    if evals is None:
        paths = sorted(results.glob("*/*/eval/metrics.json"))
    else:
        paths = sorted(Path(e) / "metrics.json" for e in evals)
        missing = [p for p in paths if not p.is_file()]
        if missing:
            raise SceneFormatError(f"{missing[0]}: metrics.json is missing; is it an evaluate step's folder?")
    rows: dict[str, Row] = {}
    scenes: set[str] = set()
    for path in paths:
        scene, variant_dir = path.parts[-4], path.parts[-3]
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise SceneFormatError(f"{path}: not valid JSON ({exc}).") from exc
        for key in ("extraction", "nvs"):
            if not isinstance(data.get(key), dict):
                raise SceneFormatError(f"{path}: the '{key}' section is missing; "
                                       f"is it an evaluate step's metrics.json?")
        settings = dict(data.get("variant") or {})
        name = str(settings.pop("variant", variant_dir))
        row = rows.get(name)
        if row is None:
            row = rows[name] = Row(name, settings, str((data.get("lift") or {}).get("method", "?")))
        scenes.add(scene)
        row.protocols.add(str(data.get("protocol", "?")))
        for store, section, key in ((row.object_miou, "extraction", "mIoU"), (row.psnr, "extraction", "PSNR"),
                                    (row.nvs_miou, "nvs", "mIoU"), (row.nvs_macc, "nvs", "mAcc")):
            value = data[section].get(key)
            if value is not None:
                store[scene] = float(value)
    return sorted(scenes), [rows[k] for k in sorted(rows)]


def _stats(values: dict) -> tuple[float | None, float | None]:
    v = list(values.values())
    return (float(np.mean(v)), float(np.std(v))) if v else (None, None)


def _num(value: float | None, scale: float) -> str:
    return DASH if value is None else f"{value * scale:.1f}"


def _pm(values: dict, scale: float) -> tuple[str, str]:
    """("mean ± std" text, LaTeX text)."""
    mean, std = _stats(values)
    if mean is None:
        return DASH, "--"
    return f"{mean * scale:.1f} ± {std * scale:.1f}", f"{mean * scale:.1f} $\\pm$ {std * scale:.1f}"


@dataclass
class Table:
    """A table as text cells; ``csv_rows`` carry plain numbers (means and stds in separate columns)."""

    name: str
    caption: str
    header: list[str]
    rows: list[list[str]]
    tex_rows: list[list[str]]
    csv_header: list[str]
    csv_rows: list[list]
    notes: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        lines = [f"**{self.caption}**", "", "| " + " | ".join(self.header) + " |",
                 "|" + "|".join(["---"] + ["---:"] * (len(self.header) - 1)) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in self.rows]
        lines += [""] + [f"{n}" for n in self.notes]
        return "\n".join(lines).rstrip() + "\n"

    def csv(self) -> str:
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(self.csv_header)
        for r in self.csv_rows:
            writer.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in r])
        return buf.getvalue()

    def latex(self) -> str:
        def esc(text: str) -> str:
            return text.replace("_", "\\_").replace("%", "\\%").replace("&", "\\&").replace("±", "$\\pm$")

        spec = "l" + "c" * (len(self.header) - 1)
        lines = ["\\begin{table}[ht]", "\\centering", "\\small", f"\\caption{{{esc(self.caption)}}}",
                 f"\\begin{{tabular}}{{{spec}}}", "\\toprule", " & ".join(esc(h) for h in self.header) + " \\\\",
                 "\\midrule"]
        lines += [" & ".join(esc(c) if "$" not in c else c for c in r) + " \\\\" for r in self.tex_rows]
        lines += ["\\bottomrule", "\\end{tabular}", f"\\label{{tab:{self.name}}}", "\\end{table}"]
        return "\n".join(lines) + "\n"


def _protocol_note(rows: list[Row]) -> list[str]:
    protocols = sorted({p for r in rows for p in r.protocols})
    return [f"Evaluation protocol: {', '.join(protocols)} (docs/evaluation.md)."] if protocols else []


def _per_scene_table(name: str, caption: str, scenes: list[str], rows: list[Row], per_scene: str,
                     means: list[tuple[str, str, float]]) -> Table:
    """Variants as rows, one column per scene of ``per_scene`` (attribute), then ``means``
    (header, attribute, scale) as mean ± std."""
    scale = {"object_miou": 100.0, "nvs_miou": 100.0, "nvs_macc": 100.0, "psnr": 1.0}
    header = ["Method"] + scenes + [h for h, _, _ in means]
    csv_header = ["method"] + scenes
    for _h, attr, _ in means:
        csv_header += [f"{attr}_mean", f"{attr}_std"]
    text, tex, plain = [], [], []
    for r in rows:
        values = getattr(r, per_scene)
        cells = [_num(values.get(s), scale[per_scene]) for s in scenes]
        mean_cells = [_pm(getattr(r, attr), s) for _, attr, s in means]
        text.append([r.name] + cells + [m[0] for m in mean_cells])
        tex.append([r.name] + [c if c != DASH else "--" for c in cells] + [m[1] for m in mean_cells])
        numbers: list = [r.name] + [None if values.get(s) is None else values[s] * scale[per_scene] for s in scenes]
        for _, attr, s in means:
            mean, std = _stats(getattr(r, attr))
            numbers += [None if mean is None else mean * s, None if std is None else std * s]
        plain.append(numbers)
    return Table(name, caption, header, text, tex, csv_header, plain, _protocol_note(rows))


def _grid_group(rows: list[Row]) -> list[Row]:
    """The variants that differ only in the two ablation switches: the group of ``full`` (else the
    largest group; ties: the group of the first variant by name). Beside ``full``'s lifting method,
    the group takes the self-prompting variants of the same settings, as the paper's Table 5 has an
    "SP." row; other methods (the closed-form baseline) stay out of the grid."""
    def other(r: Row, method: bool = True) -> str:
        settings = {**SETTING_DEFAULTS, **r.settings}
        kept = {k: v for k, v in settings.items()
                if k not in GRID_KEYS + ("seed",) and (method or k not in ("lifting", "lift"))}
        return json.dumps(kept | ({"method": r.method} if method else {}), sort_keys=True)

    eligible = [r for r in rows if all(isinstance(r.settings.get(k), bool) for k in GRID_KEYS)]
    if not eligible:
        return []
    full = next((r for r in eligible if r.name == "full"), None)
    if full is not None:
        return [r for r in eligible if other(r, method=False) == other(full, method=False)
                and r.method in (full.method, SELF_PROMPT)]
    groups: dict[str, list[Row]] = {}
    for r in eligible:
        groups.setdefault(other(r), []).append(r)
    return max(groups.values(), key=lambda g: (len(g), [-ord(c) for c in g[0].name]))


def table5(rows: list[Row]) -> Table:
    """The ablation grid (paper Table 5): one row per (consistent masks, density control) present."""
    group = _grid_group(rows)
    by_combo: dict[tuple[bool, bool, bool], Row] = {}  # (consistent masks, density control, contrastive)
    for r in sorted(group, key=lambda r: r.name):
        by_combo.setdefault((r.settings["consistent_masks"], r.settings["density_control"],
                             r.method != SELF_PROMPT), r)
    header = ["Variant", "Lifting", "Consistent 2D Mask", "Amb. Gauss. Control", "NVS mIoU", "Object mIoU", "PSNR"]
    csv_header = ["variant", "lifting", "consistent_masks", "density_control", "nvs_miou_mean", "nvs_miou_std",
                  "object_miou_mean", "object_miou_std", "psnr_mean", "psnr_std"]
    text, tex, plain = [], [], []
    # the paper's row order; a self-prompting row goes above its contrastive twin
    for combo in [(m, d, c) for m, d in ((False, False), (False, True), (True, False), (True, True))
                  for c in (False, True)]:
        r = by_combo.get(combo)
        if r is None:
            continue
        combo = combo[:2]
        marks = ["✓" if c else "×" for c in combo]
        tex_marks = ["$\\checkmark$" if c else "$\\times$" for c in combo]
        pms = [_pm(r.nvs_miou, 100.0), _pm(r.object_miou, 100.0), _pm(r.psnr, 1.0)]
        text.append([r.name, r.method] + marks + [p[0] for p in pms])
        tex.append([r.name, r.method] + tex_marks + [p[1] for p in pms])
        numbers: list = [r.name, r.method, combo[0], combo[1]]
        for values, s in ((r.nvs_miou, 100.0), (r.object_miou, 100.0), (r.psnr, 1.0)):
            mean, std = _stats(values)
            numbers += [None if mean is None else mean * s, None if std is None else std * s]
        plain.append(numbers)
    caption = ("Ablation (paper Table 5): consistent 2D masks and GIT-guided ambiguous-Gaussian control; "
               "NVS mIoU, object mIoU (%) and PSNR (dB), mean ± std over scenes")
    return Table("table5", caption, header, text, tex, csv_header, plain, _protocol_note(group))


def build_tables(results: Path, evals: list[Path] | None = None) -> list[Table]:
    scenes, rows = collect(results, evals)
    if not rows:
        raise Trace3DError(f"{results}: no */*/eval/metrics.json found; run the evaluate step first.")
    t2 = _per_scene_table("table2", "3D object extraction (paper Table 2): object mIoU (%) per scene, "
                          "mean ± std over scenes of mIoU (%) and PSNR (dB)", scenes, rows, "object_miou",
                          [("mIoU", "object_miou", 100.0), ("PSNR", "psnr", 1.0)])
    t2p = _per_scene_table("table2_psnr", "3D object extraction: PSNR (dB) per scene inside the ground-truth "
                           "box grown by 10 px (the supplementary's PSNR table)", scenes, rows, "psnr",
                           [("PSNR", "psnr", 1.0)])
    if all(r.protocols == {"nvos"} for r in rows):  # NVOS: one target mask per scene, Table 4 only
        return [_per_scene_table("table4", "NVOS (paper Table 4): target-view mIoU (%) per scene from the "
                                 "reference view's scribbles, mean ± std over scenes of mIoU and mAcc (%)", scenes,
                                 rows, "nvs_miou", [("mIoU", "nvs_miou", 100.0), ("mAcc", "nvs_macc", 100.0)])]
    if any("nvos" in r.protocols for r in rows):
        raise Trace3DError(f"{results}: NVOS evaluations (Table 4) and Replica / synthetic ones (Tables 2, 3, 5) "
                           f"cannot share one set of tables; pass them separately.")
    t3 = _per_scene_table("table3", "Novel-view 2D segmentation (paper Table 3): mIoU (%) per scene, "
                          "mean ± std over scenes of mIoU and mAcc (%)", scenes, rows, "nvs_miou",
                          [("mIoU", "nvs_miou", 100.0), ("mAcc", "nvs_macc", 100.0)])
    return [t2, t2p, t3, table5(rows)]


def write_tables(results: Path, out_dir: Path, evals: list[Path] | None = None) -> list[Path]:
    """Write every table as .md, .csv and .tex into ``out_dir``; returns the paths written.
    ``evals`` restricts the input to those evaluate folders (the workflow passes its own)."""
    out_dir = Path(out_dir)
    tables = build_tables(results, evals)  # before the folder is made: a refused input leaves no empty --out
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for table in tables:
        for ext, text in (("md", table.markdown()), ("csv", table.csv()), ("tex", table.latex())):
            path = out_dir / f"{table.name}.{ext}"
            with atomic_file(path) as tmp:
                tmp.write_text(text)
            written.append(path)
    log.info("tables: wrote %d files into %s", len(written), out_dir)
    return written
