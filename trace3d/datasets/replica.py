"""Replica importer: the Semantic-NeRF renders of Replica, as Trace3D and EgoLifter load them.

Source layout (Semantic-NeRF's pre-rendered Replica release plus its separately released
``Replica_Instance_Segmentation.zip``)::

    <root>/<scene>/Sequence_1/
        traj_w_c.txt                              one camera-to-world 4x4 per line (16 numbers, row-major)
        rgb/rgb_<i>.png                           640x480 RGB
        depth/depth_<i>.png                       uint16 z-depth in millimetres
        semantic_instance/semantic_instance_<i>.png   uint16 instance ids (from the instance archive)
        semantic_class/semantic_class_<i>.png     optional, uint8 class ids (only used for categories)

``source`` may be ``<root>``, ``<root>/<scene>`` or ``<root>/<scene>/Sequence_1``.

Conventions, checked against the public loaders:

* ``traj_w_c.txt`` holds camera-to-world matrices in the OpenCV camera convention (Semantic-NeRF
  renders with ``convention: opencv``; its data generator converts Habitat's OpenGL camera with
  ``T_wc = T_wh @ T_hc @ opencv_to_opengl``; Trace3D/EgoLifter invert it directly into a 3DGS
  world-to-camera, which is OpenCV).  We store ``world_to_camera = inv(T_wc)``.
* Intrinsics: 90 degree horizontal field of view, fx = fy = W / 2 and principal point at the
  image centre.  Semantic-NeRF writes cx = (W - 1) / 2 = 319.5 because its pixel centres are
  integers; our cameras put pixel centres at +0.5, so the same camera has cx = W / 2 = 320 here.
* Instance ids: Replica id 0 is a real object (office_2 evaluates it), while our instance maps
  reserve 0 for "unlabelled".  Every id is therefore stored as ``replica_id + 1``
  (``meta.json: instance_id_offset = 1``); ``objects.json`` names each object ``replica_<id>``.
* Split (the official Trace3D / EgoLifter code): of the (strided) frame list, every 4th frame
  (positions 0, 4, 8, ...; frames 0, 4, ..., 896 at stride 1) is a test view, the rest train.
  office_1 frames 474-503 and office_4 frames 618-733 are dropped (after the split is made).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, ObjectTable, SceneObject, read_rgb, write_cameras, write_rgb, write_u16
from .common import downscale_depth, downscale_labels, downscale_rgb, rigid_inverse, scale_intrinsics

log = logging.getLogger(__name__)

#: Replica scene names of the paper -> folder names of the Semantic-NeRF release.
SCENE_FOLDERS = {
    "office0": "office_0",
    "office1": "office_1",
    "office2": "office_2",
    "office3": "office_3",
    "office4": "office_4",
    "room0": "room_0",
    "room1": "room_1",
    "room2": "room_2",
}

#: Evaluated objects of the 3D object extraction benchmark (paper supplementary, Table
#: "selected id lists"; identical to the official code's lists).  Ids are Replica instance ids.
#: office3 lists 86 twice in both the paper and the official code; the duplicate is dropped.
EVALUATED_IDS = {
    "office_0": [3, 4, 7, 9, 11, 12, 14, 15, 16, 17, 19, 21, 22, 23, 29, 30, 32, 34, 35, 36, 37, 40, 44,
                 48, 49, 57, 58, 61, 66],
    "office_1": [3, 8, 9, 11, 12, 13, 14, 17, 23, 24, 29, 30, 31, 32, 34, 35, 37, 43, 45],
    "office_2": [0, 2, 3, 4, 6, 8, 9, 12, 13, 14, 17, 23, 27, 34, 38, 39, 46, 49, 51, 54, 57, 58, 59, 63,
                 65, 68, 69, 70, 72, 73, 74, 75, 77, 78, 80, 84, 85, 86, 90, 92, 93],
    "office_3": [1, 2, 8, 11, 12, 15, 18, 21, 22, 25, 29, 32, 33, 42, 51, 54, 55, 56, 60, 61, 70, 82, 85,
                 86, 88, 97, 101, 102, 103, 110, 111],
    "office_4": [3, 4, 5, 6, 9, 13, 16, 18, 20, 23, 31, 34, 47, 48, 49, 51, 52, 56, 60, 61, 62, 65, 69,
                 70, 71],
    "room_0": [1, 2, 3, 4, 6, 7, 8, 11, 13, 15, 18, 19, 20, 21, 22, 24, 30, 32, 34, 35, 36, 39, 40, 41,
               43, 45, 47, 49, 50, 51, 54, 55, 58, 61, 63, 64, 68, 69, 70, 71, 72, 73, 74, 75, 78, 79, 83,
               85, 86, 87, 90, 92],
    "room_1": [3, 4, 6, 7, 8, 9, 11, 12, 13, 15, 17, 18, 19, 21, 22, 23, 24, 27, 30, 32, 33, 35, 37, 39,
               40, 43, 45, 46, 48, 50, 51, 52, 53, 54],
    "room_2": [2, 4, 5, 10, 14, 15, 17, 18, 19, 20, 22, 24, 26, 27, 28, 29, 31, 32, 34, 36, 38, 39, 40, 42,
               44, 46, 47, 48, 49, 52, 54, 55, 56, 57, 58, 59, 61],
}

#: Frames the official code drops (inclusive ranges of source frame indices).
REJECTED_FRAMES = {"office_1": (474, 503), "office_4": (618, 733)}

TEST_EVERY = 4
HFOV_DEG = 90.0
INSTANCE_ID_OFFSET = 1


@dataclasses.dataclass
class ReplicaParams:
    """Parameters of the Replica importer.

    Attributes:
        scene: ``office0`` .. ``office4``, ``room0`` .. ``room2`` (or the folder name ``office_0`` ...);
            empty: inferred from the source folder name.
        sequence: the Semantic-NeRF sequence folder.
        frame_stride: import every n-th frame (1 = all 900); the test split is taken on the strided list.
        max_frames: keep only the first n frames of the strided list (0 = all).
        downscale: integer image downscale (1 = 640x480) for CPU runs; intrinsics follow.
        init: which initial point cloud the 2DGS fit should use (recorded in meta.json).
        evaluated_ids: Replica instance ids to mark evaluated; ``None`` = the paper's list for the scene.
        occlusion_free_views: optional path to the official code's ``view_wo_occ_new.json``
            (per scene, per Replica id: source frame indices of test views where the object is not
            occluded); recorded in meta.json as ``evaluation_views``.
    """

    scene: str = ""
    sequence: str = "Sequence_1"
    frame_stride: int = 1
    max_frames: int = 0
    downscale: int = 1
    init: Literal["depth", "sfm"] = "depth"
    evaluated_ids: list[int] | None = None
    occlusion_free_views: str | None = None

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"frame_stride": ">= 1", "max_frames": ">= 0", "downscale": ">= 1"}

    def __post_init__(self) -> None:
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be >= 1, got {self.frame_stride}")
        if self.max_frames < 0:
            raise ValueError(f"max_frames must be >= 0, got {self.max_frames}")
        if self.downscale < 1:
            raise ValueError(f"downscale must be >= 1, got {self.downscale}")
        if self.scene and folder_name(self.scene) is None:
            raise ValueError(
                f"scene {self.scene!r} is not a Replica scene name; expected one of {sorted(SCENE_FOLDERS)}"
            )


def params_from(d: dict | None) -> ReplicaParams:
    """Typed :class:`ReplicaParams` from a config mapping (unknown keys and wrong types refused)."""
    return from_mapping(ReplicaParams, d, "replica params")


def folder_name(scene: str) -> str | None:
    """``office0`` / ``office_0`` -> ``office_0``; None for an unknown name."""
    if scene in SCENE_FOLDERS:
        return SCENE_FOLDERS[scene]
    if scene in SCENE_FOLDERS.values():
        return scene
    return None


def replica_intrinsics(width: int, height: int) -> np.ndarray:
    """[3, 3] K of the Semantic-NeRF Replica renders (90 degree HFOV, centred principal point)."""
    f = width / 2.0 / math.tan(math.radians(HFOV_DEG / 2.0))
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Source discovery and validation
# ----------------------------------------------------------------------------------------------


def resolve_sequence(source: Path, params: ReplicaParams) -> tuple[Path, str]:
    """The ``Sequence_1`` folder and the Replica folder name (``office_0`` ...) for ``source``."""
    source = Path(source)
    if not source.is_dir():
        raise Trace3DError(f"{source}: Replica source folder does not exist.")
    wanted = folder_name(params.scene) if params.scene else None
    if (source / "traj_w_c.txt").is_file() or source.name == params.sequence:
        seq, scene_dir = source, source.parent  # <root>/<scene>/Sequence_1
    elif (source / params.sequence).is_dir():
        seq, scene_dir = source / params.sequence, source  # <root>/<scene>
    else:  # <root>
        if wanted is None:
            found = sorted(p.name for p in source.iterdir() if p.is_dir() and (p / params.sequence).is_dir())
            raise Trace3DError(
                f"{source}: no {params.sequence}/ folder here and no `scene` parameter to pick one of the "
                f"scene folders {found or '(none found)'}."
            )
        scene_dir = source / wanted
        seq = scene_dir / params.sequence
        if not seq.is_dir():
            raise Trace3DError(
                f"{seq}: Replica sequence folder is missing (expected <root>/{wanted}/{params.sequence}/ "
                "from the Semantic-NeRF Replica release)."
            )
    inferred = folder_name(scene_dir.name)
    if wanted is not None and inferred is not None and inferred != wanted:
        raise Trace3DError(
            f"{seq}: the folder belongs to Replica scene {inferred!r} but the `scene` parameter says {wanted!r}."
        )
    name = wanted or inferred
    if name is None:
        name = scene_dir.name
        log.warning("%s: %r is not one of the paper's Replica scenes; no evaluated-object list applies", seq, name)
    return seq, name


def read_trajectory(path: Path) -> np.ndarray:
    """[N, 4, 4] camera-to-world matrices from ``traj_w_c.txt`` (one row-major 4x4 per line)."""
    if not path.is_file():
        raise Trace3DError(f"{path}: camera trajectory traj_w_c.txt is missing.")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError as exc:
            raise Trace3DError(f"{path}: line {lineno} has a non-numeric value.") from exc
        if len(values) != 16:
            raise Trace3DError(f"{path}: line {lineno} has {len(values)} numbers; expected 16 (a row-major 4x4).")
        rows.append(values)
    if not rows:
        raise Trace3DError(f"{path}: the trajectory file is empty.")
    poses = np.asarray(rows, dtype=np.float64).reshape(-1, 4, 4)
    if not np.isfinite(poses).all():
        raise Trace3DError(f"{path}: the trajectory contains non-finite numbers.")
    return poses


def select_frames(num_frames: int, scene_folder: str, params: ReplicaParams) -> list[tuple[int, str]]:
    """(source frame index, split) of the imported frames, in order.

    The split is made on the strided list (every 4th position is test), then the official
    rejected frames are dropped, then ``max_frames`` truncates.
    """
    strided = list(range(0, num_frames, params.frame_stride))
    frames = [(idx, "test" if pos % TEST_EVERY == 0 else "train") for pos, idx in enumerate(strided)]
    if scene_folder in REJECTED_FRAMES:
        lo, hi = REJECTED_FRAMES[scene_folder]
        frames = [(i, s) for i, s in frames if not lo <= i <= hi]
    if params.max_frames:
        frames = frames[: params.max_frames]
    return frames


def _frame_name(index: int) -> str:
    return f"rgb_{index:04d}"


def _read_u16_or_u8(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise Trace3DError(f"{path}: {what} file is missing.")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise Trace3DError(f"{path}: {what} file is corrupt or not an image.")
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise Trace3DError(
            f"{path}: {what} must be a single-channel 8- or 16-bit PNG, got dtype {img.dtype} shape {img.shape} "
            "(a colour visualisation is not an id map)."
        )
    return img


def _check_layout(seq: Path) -> None:
    for sub in ("rgb", "depth"):
        if not (seq / sub).is_dir():
            raise Trace3DError(f"{seq / sub}: folder is missing; this is not a Semantic-NeRF Replica sequence.")
    if not (seq / "semantic_instance").is_dir():
        raise Trace3DError(
            f"{seq / 'semantic_instance'}: instance maps are missing; unpack Semantic-NeRF's separately released "
            "Replica_Instance_Segmentation.zip into the sequence folder (semantic_class is not a substitute, "
            "and falling back to it silently is the known cause of unreproducible numbers)."
        )


def _check_frame_files(seq: Path, indices: list[int]) -> None:
    """Refuse up front (before any work) if a selected frame lacks one of its files."""
    for folder, pattern, what in (("rgb", "rgb_{}.png", "RGB image"), ("depth", "depth_{}.png", "depth map"),
                                  ("semantic_instance", "semantic_instance_{}.png", "instance map")):
        missing = [i for i in indices if not (seq / folder / pattern.format(i)).is_file()]
        if missing:
            raise Trace3DError(
                f"{seq / folder / pattern.format(missing[0])}: {what} is missing "
                f"({len(missing)} of the {len(indices)} selected frames lack one; the trajectory has more poses "
                "than the folder has files)."
            )


def _load_occlusion_free_views(path: str, scene_folder: str, names_by_index: dict[int, str]) -> dict[str, list[str]]:
    """{our object id (str): [test frame names]} from the official ``view_wo_occ_new.json``."""
    file = Path(path)
    if not file.is_file():
        raise Trace3DError(f"{file}: occlusion-free view list does not exist.")
    try:
        data = json.loads(file.read_text())
    except json.JSONDecodeError as exc:
        raise Trace3DError(f"{file}: not valid JSON ({exc}).") from exc
    if not isinstance(data, dict) or not isinstance(data.get(scene_folder), dict):
        raise Trace3DError(f"{file}: expected an object with a {scene_folder!r} entry mapping ids to frame lists.")
    out = {}
    for key, frames in data[scene_folder].items():
        if not re.fullmatch(r"\d+", str(key)) or not isinstance(frames, list):
            raise Trace3DError(f"{file}: entry {scene_folder}.{key} must map an integer id to a list of frames.")
        ours = int(key) + INSTANCE_ID_OFFSET
        out[str(ours)] = [names_by_index[int(i)] for i in frames if int(i) in names_by_index]
    return out


# ----------------------------------------------------------------------------------------------
# Import
# ----------------------------------------------------------------------------------------------


def import_replica(source: Path, out_dir: Path, params: ReplicaParams) -> None:
    """Write the canonical scene of one Replica sequence into the empty folder ``out_dir``.

    Writes images/, depth/ (mm), instances/ (Replica id + 1), cameras.json, objects.json, meta.json.
    """
    source, out_dir = Path(source), Path(out_dir)
    seq, scene_folder = resolve_sequence(source, params)
    _check_layout(seq)
    poses = read_trajectory(seq / "traj_w_c.txt")
    frames = select_frames(len(poses), scene_folder, params)
    if not frames:
        raise Trace3DError(f"{seq}: no frames left to import with these parameters.")
    _check_frame_files(seq, [index for index, _ in frames])
    have_class = (seq / "semantic_class").is_dir()
    log.info("importing Replica %s: %d of %d frames from %s", scene_folder, len(frames), len(poses), seq)

    cameras: list[Camera] = []
    pixel_counts: dict[int, int] = {}
    class_votes: dict[tuple[int, int], int] = {}
    size = None
    for index, split in tqdm(frames, desc=f"replica {scene_folder}", unit="frame"):
        rgb = read_rgb(seq / "rgb" / f"rgb_{index}.png")
        depth = _read_u16_or_u8(seq / "depth" / f"depth_{index}.png", "depth map")
        inst = _read_u16_or_u8(seq / "semantic_instance" / f"semantic_instance_{index}.png", "instance map")
        if depth.dtype != np.uint16:
            raise Trace3DError(f"{seq / 'depth' / f'depth_{index}.png'}: depth must be 16-bit millimetres, got 8-bit.")
        if size is None:
            size = rgb.shape[:2]
        for arr, path in ((rgb, seq / "rgb" / f"rgb_{index}.png"),
                          (depth, seq / "depth" / f"depth_{index}.png"),
                          (inst, seq / "semantic_instance" / f"semantic_instance_{index}.png")):
            if arr.shape[:2] != size:
                raise Trace3DError(
                    f"{path}: image is {arr.shape[1]}x{arr.shape[0]} but the sequence is {size[1]}x{size[0]}."
                )
        if int(inst.max()) + INSTANCE_ID_OFFSET > 65535:
            raise Trace3DError(f"{seq / 'semantic_instance'}: frame {index} has an instance id above 65534.")
        ids = inst.astype(np.int64) + INSTANCE_ID_OFFSET

        rgb = downscale_rgb(rgb, params.downscale)
        depth = downscale_depth(depth, params.downscale)
        ids = downscale_labels(ids, params.downscale)
        name = _frame_name(index)
        write_rgb(out_dir / "images" / f"{name}.png", rgb)
        write_u16(out_dir / "depth" / f"{name}.png", depth.astype(np.uint16))
        write_u16(out_dir / "instances" / f"{name}.png", ids.astype(np.uint16))

        counts = np.bincount(ids.ravel())  # bincount, not np.unique: no sort of 300k pixels per frame
        for u in np.flatnonzero(counts).tolist():
            pixel_counts[u] = pixel_counts.get(u, 0) + int(counts[u])
        if have_class:
            cls_path = seq / "semantic_class" / f"semantic_class_{index}.png"
            if cls_path.is_file():
                classes = downscale_labels(_read_u16_or_u8(cls_path, "class map"), params.downscale)
                if classes.shape == ids.shape:
                    present = np.flatnonzero(counts)
                    n_cls = int(classes.max()) + 1
                    # ids remapped to 0..len(present) - 1 so the pair histogram stays small
                    dense = np.searchsorted(present, ids.ravel()) * n_cls + classes.ravel().astype(np.int64)
                    pair_counts = np.bincount(dense)
                    for key in np.flatnonzero(pair_counts).tolist():
                        pair = (int(present[key // n_cls]), key % n_cls)
                        class_votes[pair] = class_votes.get(pair, 0) + int(pair_counts[key])

        w2c = rigid_inverse(poses[index], f"{seq / 'traj_w_c.txt'} (frame {index})")
        K = scale_intrinsics(replica_intrinsics(size[1], size[0]), 1.0 / params.downscale)
        cameras.append(Camera(name=name, split=split, width=rgb.shape[1], height=rgb.shape[0], K=K,
                              world_to_camera=w2c))

    write_cameras(out_dir, cameras)

    # objects.json: every id seen, evaluated per the paper's list.
    evaluated_src = params.evaluated_ids if params.evaluated_ids is not None else EVALUATED_IDS.get(scene_folder, [])
    evaluated = {int(i) + INSTANCE_ID_OFFSET for i in evaluated_src}
    best_class: dict[int, tuple[int, int]] = {}
    for (i, k), c in class_votes.items():
        if i not in best_class or c > best_class[i][1]:
            best_class[i] = (k, c)
    objects = [
        SceneObject(
            id=i,
            name=f"replica_{i - INSTANCE_ID_OFFSET}",
            level="object",
            parent=None,
            category=f"class_{best_class[i][0]}" if i in best_class else "",
            evaluated=i in evaluated,
        )
        for i in sorted(pixel_counts)
    ]
    write_json(out_dir / "objects.json", ObjectTable(objects).to_json())
    missing = sorted(i - INSTANCE_ID_OFFSET for i in evaluated - set(pixel_counts))
    if missing:
        log.warning("%s: evaluated Replica ids %s do not appear in the imported frames", scene_folder, missing)

    names_by_index = {idx: _frame_name(idx) for idx, split in frames if split == "test"}
    meta = {
        "importer": "replica",
        "source": str(seq.resolve()),
        "scene": scene_folder,
        "params": to_dict(params),
        "init": params.init,
        "instance_id_offset": INSTANCE_ID_OFFSET,
        "depth_units": "millimetres (z-depth)",
        "frame_index": {_frame_name(i): i for i, _ in frames},
        "rejected_frames": list(REJECTED_FRAMES.get(scene_folder, ())),
        "evaluated_replica_ids": sorted(int(i) for i in evaluated_src),
        "evaluated_ids_missing": missing,
        "has_semantic_class": have_class,
    }
    if params.occlusion_free_views:
        meta["evaluation_views"] = _load_occlusion_free_views(params.occlusion_free_views, scene_folder,
                                                              names_by_index)
    write_json(out_dir / "meta.json", meta)
    log.info("Replica %s: %d cameras (%d test), %d objects (%d evaluated)", scene_folder, len(cameras),
             sum(c.split == "test" for c in cameras), len(objects), sum(o.evaluated for o in objects))
