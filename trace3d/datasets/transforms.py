"""A ``transforms.json`` capture (instant-ngp / nerfstudio / Blender NeRF-synthetic) -> a canonical scene.

Source: a folder holding ``transforms.json`` (instant-ngp's ``colmap2nerf.py``, nerfstudio's
``ns-process-data``), or ``transforms_train.json`` / ``transforms_val.json`` / ``transforms_test.json``
(Blender NeRF-synthetic), or one ``.json`` file given directly.  ``file_path`` of every frame is
relative to the JSON's folder (absolute paths are kept).

* **Intrinsics**, per frame, each key taken from the frame when it has it, else from the top level:
  ``fl_x`` / ``fl_y`` (pixels) or ``camera_angle_x`` / ``camera_angle_y`` (radians; focal
  ``0.5 w / tan(angle / 2)``; a missing y focal equals the x focal), ``cx`` / ``cy`` (default the image
  centre), ``w`` / ``h`` (default the image's size; a different image size is refused).  The file's
  principal point is in continuous pixel coordinates (nerfstudio and instant-ngp cast the ray of pixel
  (i, j) through (i + 0.5, j + 0.5); COLMAP's cx, which colmap2nerf copies, has the same origin), which
  is the project's convention, so K is copied as it is.  Images of different sizes need per-frame
  intrinsics (``fl_x`` or ``camera_angle_x`` in each frame); otherwise they are refused.
* **Distortion** (``k1 k2 k3 k4 p1 p2``; nerfstudio's ``camera_model`` ``OPENCV`` or
  ``OPENCV_FISHEYE``, instant-ngp's ``is_fisheye``): with ``distortion: undistort`` (default) every
  image is resampled into a pinhole image of the same size (OpenCV's remap, bilinear) whose K keeps only
  valid pixels (``getOptimalNewCameraMatrix`` with alpha 0, or the fisheye twin with balance 0), so no
  black corners enter the fit; with ``distortion: refuse`` a non-zero coefficient is refused.  Other
  models (``EQUIRECTANGULAR``, ``FULL_OPENCV`` with k5/k6 ...) are refused.
* **Poses**: ``transform_matrix`` is camera-to-world with OpenGL camera axes (x right, y up, z back).
  The project's cameras are OpenCV (x right, y down, z forward): the y and z columns are negated, then
  inverted into ``world_to_camera`` (the rotation re-orthonormalised by SVD; a 3x3 block further than
  1e-2 from a rotation, a reflection, or a last row other than (0, 0, 0, 1) is refused).  The world
  frame is the file's (instant-ngp's / nerfstudio's re-centred, re-scaled world is kept, and
  ``aabb_scale``, ``scale``, ``offset``, ``applied_transform``, ``applied_scale`` are recorded in
  meta.json).  ``poses: unknown`` writes identity placeholders instead (``"poses": "unknown"``), so
  that the ``poses`` step recovers them with COLMAP, starting from the file's intrinsics.
* **Splits**: Blender's train file -> train, test file -> test (the val file is not imported, as
  in NeRF practice); nerfstudio's ``train_filenames`` / ``test_filenames`` (``val_filenames`` when there
  is no test list) when the file has them; otherwise positions 0, n, 2n ... are test views
  (n = ``test_every``).  ``frame_stride`` keeps every k-th frame of each split file.
* **Missing images**: a frame whose image file does not exist is skipped (published captures often
  list more frames than they ship), with one warning naming how many and the first three; the import
  is refused only when fewer than ``min_images`` frames keep an image. Test positions count the kept
  frames.
* **Images**: RGBA (Blender) is composited over ``background`` (white by default, the NeRF-synthetic
  convention); images are shrunk to ``max_side`` (area averaging, the intrinsics per axis).  Frame names
  are the file stems, or the relative paths with ``/`` -> ``_`` when stems repeat (Blender's
  ``train/r_0`` and ``test/r_0``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, write_cameras, write_rgb
from .common import every_nth_split, rigid_inverse
from .images import shrink_to_max_side

log = logging.getLogger(__name__)

#: OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward), right-multiplied
#: onto a camera-to-world matrix.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
BLENDER_FILES = {"train": "transforms_train.json", "val": "transforms_val.json", "test": "transforms_test.json"}
TRY_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PIXEL_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
RECORDED_KEYS = ("aabb_scale", "scale", "offset", "applied_transform", "applied_scale", "camera_model",
                 "orientation_override", "up")


@dataclasses.dataclass
class TransformsParams:
    """Parameters of the ``transforms`` importer.

    Attributes:
        max_side: shrink images whose longer side exceeds this many pixels (0 = keep the size).
        poses: "known" (the file's poses) or "unknown" (identity placeholders: the poses step runs COLMAP).
        distortion: "undistort" (resample into a pinhole image) or "refuse" (non-zero coefficients are an error).
        background: colour that RGBA images are composited over: "white" or "black".
        test_every: without a split in the file, every n-th frame (positions 0, n, 2n ...) is a test
            view; 0 = all train.
        frame_stride: keep every k-th frame of each split file (1 = all).
        min_images: fewer frames than this (listed, or with an existing image) is refused.
    """

    max_side: int = 0
    poses: Literal["known", "unknown"] = "known"
    distortion: Literal["undistort", "refuse"] = "undistort"
    background: Literal["white", "black"] = "white"
    test_every: int = 8
    frame_stride: int = 1
    min_images: int = 2

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"max_side": ">= 0", "test_every": "0 | >= 2", "frame_stride": ">= 1", "min_images": ">= 1"}

    def __post_init__(self) -> None:
        if self.max_side < 0:
            raise ValueError(f"max_side must be >= 0, got {self.max_side}")
        if self.test_every < 0 or self.test_every == 1:
            raise ValueError(f"test_every must be 0 (all train) or >= 2, got {self.test_every}")
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be >= 1, got {self.frame_stride}")
        if self.min_images < 1:
            raise ValueError(f"min_images must be >= 1, got {self.min_images}")


def params_from(d: dict | None) -> TransformsParams:
    """Typed :class:`TransformsParams` from a config mapping (unknown keys and wrong types refused)."""
    return from_mapping(TransformsParams, d, "transforms params")


# ----------------------------------------------------------------------------------------------
# reading the JSON files
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class RawFrame:
    """One frame entry as read: the file's dict, the top-level dict it inherits from, the JSON's path,
    its position, and the split the file assigns (None = decided later)."""

    entry: dict
    top: dict
    json_path: Path
    index: int
    split: str | None


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark (Windows editors) is skipped
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise Trace3DError(f"{path}: not valid JSON ({exc}).") from exc
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise Trace3DError(f"{path}: expected a JSON object with a 'frames' list (a NeRF transforms file).")
    if not data["frames"]:
        raise Trace3DError(f"{path}: the 'frames' list is empty.")
    return data


def read_frames(source: Path, params: TransformsParams) -> tuple[list[RawFrame], str, list[Path]]:
    """The frames of ``source`` (a folder or a .json file), the convention's name and the files read."""
    source = Path(source)
    if source.is_file():
        files = {"all": source}
    elif source.is_dir():
        if (source / "transforms.json").is_file():
            files = {"all": source / "transforms.json"}
        elif (source / BLENDER_FILES["train"]).is_file():
            files = {split: source / name for split, name in BLENDER_FILES.items()
                     if split != "val" and (source / name).is_file()}
        else:
            raise Trace3DError(f"{source}: holds neither transforms.json nor transforms_train.json (give the "
                               "capture's folder or the .json file itself).")
    else:
        raise Trace3DError(f"{source}: transforms source does not exist.")
    frames: list[RawFrame] = []
    convention = "blender" if "train" in files else "transforms"
    for split, path in files.items():
        data = _load_json(path)
        top = {k: v for k, v in data.items() if k != "frames"}
        if convention != "blender":
            convention = "nerfstudio" if "camera_model" in top else "instant-ngp"
        lists = _split_lists(data, path)
        for k, entry in enumerate(data["frames"][:: params.frame_stride]):
            if not isinstance(entry, dict):
                raise Trace3DError(f"{path}: frame {k * params.frame_stride} is not a JSON object.")
            assigned = split if split != "all" else None
            if lists is not None:
                assigned = lists.get(_normalised(entry.get("file_path", "")))
                if assigned is None:
                    continue  # in no split list (nerfstudio drops such frames too)
            frames.append(RawFrame(entry, top, path, k * params.frame_stride, assigned))
    return frames, convention, list(files.values())


def _normalised(file_path) -> str:
    text = str(file_path).replace("\\", "/")
    while text.startswith("./"):
        text = text[2:]
    return text


def _split_lists(data: dict, path: Path) -> dict[str, str] | None:
    """nerfstudio's ``train_filenames`` / ``test_filenames`` (or ``val_filenames``): file path -> split."""
    if "train_filenames" not in data:
        return None
    test_key = "test_filenames" if "test_filenames" in data else "val_filenames"
    out = {}
    for key, split in (("train_filenames", "train"), (test_key, "test")):
        names = data.get(key, [])
        if not isinstance(names, list):
            raise Trace3DError(f"{path}: '{key}' must be a list of file paths.")
        for name in names:
            out[_normalised(name)] = split
    return out


class MissingImage(Trace3DError):
    """A frame's image file does not exist (:func:`existing_images` skips such frames)."""


def resolve_image(frame: RawFrame) -> Path:
    """The image file of a frame: ``file_path`` relative to its JSON (an extension is tried when absent)."""
    where = f"{frame.json_path}: frame {frame.index}"
    file_path = frame.entry.get("file_path")
    if not isinstance(file_path, str) or not file_path:
        raise Trace3DError(f"{where} has no 'file_path'.")
    path = Path(file_path.replace("\\", "/"))  # a path written on Windows (images\\0001.png) names the same file
    if not path.is_absolute():
        path = frame.json_path.parent / path
    if path.is_file():
        return path
    for ext in TRY_EXTENSIONS:
        candidate = path.with_name(path.name + ext)
        if candidate.is_file():
            return candidate
    raise MissingImage(f"{where}: image {file_path!r} is missing (looked for {path} with and without "
                       f"{'/'.join(TRY_EXTENSIONS[:3])}).")


def existing_images(frames: list[RawFrame], json_path: Path, min_images: int) -> tuple[list[RawFrame], list[Path]]:
    """The frames whose image file exists, and those files; the others are skipped, named in one log line.

    Published captures often list more frames than they ship images for. Refused (one sentence) when fewer
    than ``min_images`` frames keep an image; a frame without a ``file_path`` is refused as malformed.
    """
    kept, paths, missing = [], [], []
    for frame in frames:
        try:
            paths.append(resolve_image(frame))
            kept.append(frame)
        except MissingImage:
            missing.append(str(frame.entry["file_path"]))
    if len(kept) < min_images:
        raise Trace3DError(
            f"{json_path}: only {len(kept)} of its {len(frames)} frames have an image file (missing: "
            f"{', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}), fewer than min_images {min_images}; "
            "check the file paths or the images folder.")
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        log.warning("%s: skipped %d of %d frames whose image is missing: %s%s", json_path, len(missing), len(frames),
                    ", ".join(missing[:3]), more)
    return kept, paths


def _number(frame: RawFrame, key: str, per_frame_only: bool = False):
    """The frame's value of ``key``, else the top level's (None when neither has it)."""
    value = frame.entry.get(key)
    if value is None and not per_frame_only:
        value = frame.top.get(key)
    if value is None:
        return None
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise Trace3DError(f"{frame.json_path}: frame {frame.index}: '{key}' is {value!r}, not a number.") from exc
    if not math.isfinite(out):
        raise Trace3DError(f"{frame.json_path}: frame {frame.index}: '{key}' is not finite.")
    return out


def camera_to_world(frame: RawFrame) -> np.ndarray:
    """[4, 4] camera-to-world, OpenCV axes, of a frame's OpenGL ``transform_matrix``."""
    where = f"{frame.json_path}: frame {frame.index} ({frame.entry.get('file_path')})"
    matrix = frame.entry.get("transform_matrix")
    if matrix is None:
        raise Trace3DError(f"{where} has no 'transform_matrix' (no pose); remove the frame or use poses: unknown.")
    try:
        pose = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise Trace3DError(f"{where}: 'transform_matrix' is not a numeric matrix.") from exc
    if pose.shape == (3, 4):
        pose = np.vstack([pose, [0.0, 0.0, 0.0, 1.0]])
    if pose.shape != (4, 4):
        raise Trace3DError(f"{where}: 'transform_matrix' has shape {pose.shape}; expected 4x4 (or 3x4).")
    return pose @ OPENGL_TO_OPENCV


def intrinsics(frame: RawFrame, width: int, height: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(K [3, 3], distortion coefficients [k1 k2 k3 k4 p1 p2], model "pinhole" | "opencv" | "fisheye") of a
    frame whose image is ``width`` x ``height``."""
    where = f"{frame.json_path}: frame {frame.index} ({frame.entry.get('file_path')})"
    w, h = _number(frame, "w"), _number(frame, "h")
    if (w is not None and int(round(w)) != width) or (h is not None and int(round(h)) != height):
        raise Trace3DError(f"{where}: the image is {width}x{height} but the file says w x h = "
                           f"{w if w is None else int(w)}x{h if h is None else int(h)}.")
    fx, fy = _number(frame, "fl_x"), _number(frame, "fl_y")
    angle_x, angle_y = _number(frame, "camera_angle_x"), _number(frame, "camera_angle_y")
    if fx is None and angle_x is not None:
        if not 0 < angle_x < math.pi:
            raise Trace3DError(f"{where}: camera_angle_x {angle_x} is not an angle in (0, pi) radians.")
        fx = 0.5 * width / math.tan(0.5 * angle_x)
    if fy is None and angle_y is not None:
        if not 0 < angle_y < math.pi:
            raise Trace3DError(f"{where}: camera_angle_y {angle_y} is not an angle in (0, pi) radians.")
        fy = 0.5 * height / math.tan(0.5 * angle_y)
    if fx is None and fy is None:
        raise Trace3DError(f"{where}: no focal length (give fl_x or camera_angle_x, per frame or at the top level).")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    if not (fx > 0 and fy > 0):
        raise Trace3DError(f"{where}: focal lengths must be > 0, got fl_x {fx}, fl_y {fy}.")
    cx, cy = _number(frame, "cx"), _number(frame, "cy")
    cx = width / 2.0 if cx is None else cx
    cy = height / 2.0 if cy is None else cy
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    coeffs = np.array([_number(frame, k) or 0.0 for k in DISTORTION_KEYS])
    model = str(frame.entry.get("camera_model", frame.top.get("camera_model", "OPENCV"))).upper()
    fisheye = model == "OPENCV_FISHEYE" or bool(frame.entry.get("is_fisheye", frame.top.get("is_fisheye", False)))
    if model not in ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE"):
        raise Trace3DError(f"{where}: camera_model {model!r} is not supported (PINHOLE, OPENCV, OPENCV_FISHEYE); "
                           "convert the capture to perspective images first.")
    for extra in ("k5", "k6"):
        if _number(frame, extra):
            raise Trace3DError(f"{where}: distortion coefficient {extra} is not supported (k1-k4, p1, p2 only).")
    if not coeffs.any():
        return K, coeffs, "pinhole"
    if fisheye and (coeffs[4] or coeffs[5]):
        raise Trace3DError(f"{where}: a fisheye camera with tangential coefficients p1/p2 is not a model OpenCV knows.")
    return K, coeffs, "fisheye" if fisheye else "opencv"


# ----------------------------------------------------------------------------------------------
# images
# ----------------------------------------------------------------------------------------------


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return int(image.size[0]), int(image.size[1])
    except Exception as exc:  # PIL raises several types for bad files
        raise Trace3DError(f"{path}: image file is corrupt or not an image ({exc}).") from exc


def read_image(path: Path, background: str) -> np.ndarray:
    """[H, W, 3] uint8 RGB of an 8- or 16-bit image file; RGBA is composited over ``background``."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise Trace3DError(f"{path}: image file is corrupt or not an image.")
    if image.dtype == np.uint16:
        image = (image.astype(np.float64) / 257.0).round().astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.shape[2] == 4:
        bgr = image[..., :3].astype(np.float64)
        alpha = image[..., 3:].astype(np.float64) / 255.0
        back = 255.0 if background == "white" else 0.0
        image = (bgr * alpha + back * (1.0 - alpha)).round().clip(0, 255).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_BGR2RGB)


def undistort(rgb: np.ndarray, K: np.ndarray, coeffs: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """A distorted [H, W, 3] image -> (the pinhole image of the same size, its K [3, 3]).

    The new K keeps only pixels that the distorted image covers (alpha / balance 0).  OpenCV puts
    pixel centres at integers, the project at +0.5: K is shifted by half a pixel on the way in and out.
    """
    height, width = rgb.shape[:2]
    shift = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    K_cv = shift @ K
    k1, k2, k3, k4, p1, p2 = coeffs
    if model == "fisheye":
        D = np.array([k1, k2, k3, k4], dtype=np.float64)
        new_cv = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K_cv, D, (width, height), np.eye(3),
                                                                        balance=0.0)
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K_cv, D, np.eye(3), new_cv, (width, height), cv2.CV_32FC1)
    else:
        if k4:
            raise Trace3DError("undistort: k4 belongs to the fisheye model; set camera_model OPENCV_FISHEYE.")
        D = np.array([k1, k2, p1, p2, k3], dtype=np.float64)
        new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, D, (width, height), 0.0, (width, height))
        map_x, map_y = cv2.initUndistortRectifyMap(K_cv, D, None, new_cv, (width, height), cv2.CV_32FC1)
    out = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out, np.linalg.inv(shift) @ new_cv


def _frame_names(paths: list[Path], roots: list[Path]) -> list[str]:
    """File stems, or relative paths with separators -> ``_`` when stems repeat."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    names = []
    for path, root in zip(paths, roots):
        try:
            rel = path.relative_to(root)
        except ValueError:
            rel = Path(*path.parts[-2:])
        names.append("_".join(rel.with_suffix("").parts))
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise Trace3DError(f"{roots[0]}: frames name the same image more than once ({', '.join(dup[:5])}).")
    return names


# ----------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------


def import_transforms(source: Path, out_dir: Path, params: TransformsParams) -> None:
    """Write the canonical scene of a transforms.json capture into ``out_dir`` (module docstring)."""
    source, out_dir = Path(source), Path(out_dir)
    frames, convention, files = read_frames(source, params)
    if len(frames) < params.min_images:
        raise Trace3DError(f"{files[0]}: holds {len(frames)} frame(s), fewer than min_images {params.min_images}.")
    frames, paths = existing_images(frames, files[0], params.min_images)
    names = _frame_names(paths, [f.json_path.parent for f in frames])
    world_to_cameras = []  # every pose is checked before any image is read
    for frame in frames:
        if params.poses == "unknown":
            world_to_cameras.append(np.eye(4))
            continue
        where = f"{frame.json_path}: frame {frame.index} ({frame.entry.get('file_path')}) transform_matrix"
        world_to_cameras.append(rigid_inverse(camera_to_world(frame), where))
    if any(f.split is None for f in frames):
        fallback = every_nth_split(names, params.test_every)
        splits = [f.split or fallback[n] for f, n in zip(frames, names)]
    else:
        splits = [f.split for f in frames]
    sizes = {path: image_size(path) for path in paths}
    if len(set(sizes.values())) > 1:
        lacking = [f for f in frames if _number(f, "fl_x", True) is None and _number(f, "camera_angle_x", True) is None]
        common = max(set(sizes.values()), key=list(sizes.values()).count)  # name a frame of an odd size first
        lacking.sort(key=lambda f: sizes[paths[frames.index(f)]] == common)
        if lacking:
            shown = sorted({f"{w}x{h}" for w, h in sizes.values()})
            raise Trace3DError(
                f"{lacking[0].json_path}: the images have different sizes ({', '.join(shown[:4])}) but frame "
                f"{lacking[0].index} ({lacking[0].entry.get('file_path')}) has no intrinsics of its own (fl_x or "
                "camera_angle_x per frame); give every frame its own intrinsics or resize the images alike.")
    lenses = [intrinsics(frame, *sizes[path]) for frame, path in zip(frames, paths)]  # all checked first
    for frame, (_, coeffs, model) in zip(frames, lenses):
        if model != "pinhole" and params.distortion == "refuse":
            raise Trace3DError(
                f"{frame.json_path}: frame {frame.index} ({frame.entry.get('file_path')}) has distortion "
                f"coefficients {dict(zip(DISTORTION_KEYS, coeffs.tolist()))}; set distortion: undistort or "
                "give undistorted images.")
    cameras, meta_frames, models = [], {}, set()
    rows = list(zip(frames, paths, names, splits, world_to_cameras, lenses))
    for frame, path, name, split, w2c, (K, coeffs, model) in tqdm(rows, desc=f"transforms {source.name}",
                                                                   unit="frame"):
        width, height = sizes[path]
        rgb = read_image(path, params.background)
        if model != "pinhole":
            rgb, K = undistort(rgb, K, coeffs, model)
        models.add(model)
        rgb, (sx, sy) = shrink_to_max_side(rgb, params.max_side)
        K = K.copy()
        K[0] *= sx
        K[1] *= sy
        out_h, out_w = rgb.shape[:2]
        write_rgb(out_dir / "images" / f"{name}.png", rgb)
        cameras.append(Camera(name, split, out_w, out_h, K, w2c))
        meta_frames[name] = {"file": str(path), "json": frame.json_path.name, "index": frame.index,
                             "original_size": [width, height], "scale": [sx, sy], "camera_model": model}
    write_cameras(out_dir, cameras)
    recorded = {}
    for path in files:
        top = {k: v for k, v in _load_json(path).items() if k in RECORDED_KEYS}
        recorded.update(top)
    meta = {
        "importer": "transforms",
        "convention": convention,
        "source": str(source.resolve()),
        "scene": source.stem if source.is_file() else source.name,
        "files": [p.name for p in files],
        "params": to_dict(params),
        "poses": "unknown" if params.poses == "unknown" else "transforms",
        "intrinsics": "transforms",
        "undistorted": sorted(models - {"pinhole"}),
        "init": "sfm",
        **{key: recorded[key] for key in RECORDED_KEYS if key in recorded},
        "frames": meta_frames,
    }
    if params.poses == "unknown":
        meta["cameras_note"] = ("identity poses (placeholders until the poses step's COLMAP estimates them); "
                                "the intrinsics are the file's")
    write_json(out_dir / "meta.json", meta)
    log.info("transforms %s (%s): %d frames (%d test)%s", source.name, convention, len(cameras),
             sum(c.split == "test" for c in cameras), ", undistorted" if meta["undistorted"] else "")
