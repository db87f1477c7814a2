"""A user's own photos: a folder of JPEG/PNG images -> a canonical scene with unknown poses.

Source: one folder of ``.jpg``/``.jpeg``/``.png`` files (not recursive), sorted by file name; the
frame name is the file name without its extension (so the stems must be unique).

* **Orientation.** The EXIF orientation tag (JPEG, or a PNG's eXIf chunk) is applied, so every image
  is stored upright as a viewer shows it (PIL's ``ImageOps.exif_transpose``; OpenCV's ``imread``
  applies it to JPEGs too, but not to PNGs, and the tag is lost once the image is re-encoded).
* **Size.** ``max_side > 0`` shrinks every image whose longer side exceeds it (area averaging, aspect
  kept, sizes rounded to whole pixels; the intrinsics follow per axis).  Images may differ in size
  (e.g. portrait and landscape shots); COLMAP then uses one camera per image.
* **Split.** Positions 0, n, 2n ... of the sorted list are test views (n = ``test_every``, default 8
  as LLFF's hold-out); 0 = all train.  Test views are registered by COLMAP like every other view.
* **Cameras (placeholders).** Poses are unknown: every camera gets the identity pose and meta.json
  says ``"poses": "unknown"``, so the ``poses`` step must run COLMAP (``mode: dataset`` is refused)
  and the steps that could fall back to the scene's cameras refuse to.  The intrinsics are a
  pinhole guess with the principal point at the image centre and a focal length (pixels), in order
  of preference:

  1. ``focal_px`` when given (the same for every image, at the imported size);
  2. EXIF ``FocalLengthIn35mmFilm`` (f35, mm): ``f = f35 / 43.27 * hypot(W, H)``, the 35 mm
     equivalent being defined on the diagonal (43.27 mm of the 36 x 24 mm frame);
  3. EXIF ``FocalLength`` (mm) with ``FocalPlaneXResolution`` / ``FocalPlaneResolutionUnit`` (the
     sensor's pixels per unit, scaled from the EXIF image width to the imported width);
  4. ``focal_guess * max(W, H)`` (default 1.2, COLMAP's own prior: about 45 degrees across the
     longer side).

  meta.json records, per frame, which one was used (``intrinsics``: ``params``, ``exif_35mm``,
  ``exif_focal_plane`` or ``guess``).  The ``poses`` step keeps such a focal length as the starting
  value and lets COLMAP refine it (see :func:`trace3d.poses.colmap.scene_intrinsics_are_guessed`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..io import write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, write_cameras, write_rgb
from .common import every_nth_split, list_images

log = logging.getLogger(__name__)

#: EXIF tags (the Exif sub-IFD 0x8769 holds the camera's).
EXIF_IFD = 0x8769
TAG_ORIENTATION = 0x0112
TAG_FOCAL_LENGTH = 0x920A
TAG_FOCAL_35MM = 0xA405
TAG_FOCAL_PLANE_X_RES = 0xA20E
TAG_FOCAL_PLANE_UNIT = 0xA210
TAG_PIXEL_X_DIMENSION = 0xA002
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm
#: FocalPlaneResolutionUnit -> millimetres per unit (2 = inch, 3 = cm, 4 = mm, 5 = um)
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclasses.dataclass
class ImagesParams:
    """Parameters of the ``images`` importer (a folder of a user's photos).

    Attributes:
        max_side: shrink images whose longer side exceeds this many pixels (0 = keep the size).
        test_every: every n-th image (positions 0, n, 2n ... in name order) is a test view; 0 = all train.
        focal_px: the focal length in pixels at the imported size, when known (overrides EXIF).
        use_exif_focal: take the focal length from EXIF when the photo has it.
        focal_guess: without EXIF, focal = ``focal_guess * max(W, H)``.
        min_images: fewer images than this is refused (SfM needs overlapping views).
    """

    max_side: int = 0
    test_every: int = 8
    focal_px: float | None = None
    use_exif_focal: bool = True
    focal_guess: float = 1.2
    min_images: int = 3

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"max_side": ">= 0", "test_every": "0 | >= 2", "focal_px": "> 0", "focal_guess": "> 0",
              "min_images": ">= 2"}

    def __post_init__(self) -> None:
        if self.max_side < 0:
            raise ValueError(f"max_side must be >= 0, got {self.max_side}")
        if self.test_every < 0 or self.test_every == 1:
            raise ValueError(f"test_every must be 0 (all train) or >= 2, got {self.test_every}")
        if self.focal_px is not None and not self.focal_px > 0:
            raise ValueError(f"focal_px must be > 0, got {self.focal_px}")
        if not self.focal_guess > 0:
            raise ValueError(f"focal_guess must be > 0, got {self.focal_guess}")
        if self.min_images < 2:
            raise ValueError(f"min_images must be >= 2, got {self.min_images}")


def params_from(d: dict | None) -> ImagesParams:
    """Typed :class:`ImagesParams` from a config mapping (unknown keys and wrong types refused)."""
    return from_mapping(ImagesParams, d, "images params")


@dataclasses.dataclass
class Photo:
    """One photo as read: upright RGB [H, W, 3] uint8 and what its EXIF says."""

    rgb: np.ndarray
    orientation: int  # EXIF orientation tag (1 = upright; 0 = none)
    focal_35mm: float | None  # FocalLengthIn35mmFilm, mm
    focal_plane_px: float | None  # focal length in pixels of the EXIF image width, from the focal plane


def _rational(value) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return out if math.isfinite(out) and out > 0 else None


def read_photo(path: Path) -> Photo:
    """Read ``path`` upright (EXIF orientation applied) with its focal-length EXIF tags."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            img.load()
            exif = img.getexif()
            upright = ImageOps.exif_transpose(img)
            rgb = np.asarray(upright.convert("RGB"), dtype=np.uint8)
    except Image.DecompressionBombError as exc:
        raise Trace3DError(f"{path}: photo is larger than PIL's safety limit ({exc}).") from exc
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise Trace3DError(f"{path}: photo is corrupt or not an image ({exc}).") from exc
    sub = exif.get_ifd(EXIF_IFD) if exif else {}
    orientation = int(exif.get(TAG_ORIENTATION, 0) or 0) if exif else 0
    focal_35 = _rational(sub.get(TAG_FOCAL_35MM))
    focal_plane_px = None
    focal_mm, res, unit = _rational(sub.get(TAG_FOCAL_LENGTH)), _rational(sub.get(TAG_FOCAL_PLANE_X_RES)), sub.get(
        TAG_FOCAL_PLANE_UNIT, 2)
    if focal_mm and res and unit in _UNIT_MM:
        focal_plane_px = focal_mm / _UNIT_MM[unit] * res  # pixels of the sensor's resolution (EXIF width)
        exif_width = _rational(sub.get(TAG_PIXEL_X_DIMENSION))
        stored_width = rgb.shape[0] if orientation in (5, 6, 7, 8) else rgb.shape[1]
        if exif_width:
            focal_plane_px *= stored_width / exif_width
    return Photo(rgb, orientation, focal_35, focal_plane_px)


def shrink_to_max_side(rgb: np.ndarray, max_side: int) -> tuple[np.ndarray, tuple[float, float]]:
    """[H, W, 3] -> the image with its longer side at most ``max_side`` (area averaging), and the
    (x, y) scale factors applied (new size / old size per axis; (1, 1) when unchanged)."""
    height, width = rgb.shape[:2]
    if max_side <= 0 or max(height, width) <= max_side:
        return rgb, (1.0, 1.0)
    scale = max_side / max(height, width)
    new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
    out = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_AREA)
    return out, (new_w / width, new_h / height)


def focal_for(photo: Photo, width: int, height: int, scale_x: float, params: ImagesParams) -> tuple[float, str]:
    """(focal length in pixels at the imported size ``width`` x ``height``, where it came from)."""
    if params.focal_px is not None:
        return float(params.focal_px), "params"
    if params.use_exif_focal and photo.focal_35mm:
        return photo.focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height), "exif_35mm"
    if params.use_exif_focal and photo.focal_plane_px:
        return photo.focal_plane_px * scale_x, "exif_focal_plane"
    return params.focal_guess * max(width, height), "guess"


def import_images(source: Path, out_dir: Path, params: ImagesParams) -> None:
    """Write the canonical scene of a folder of photos into ``out_dir`` (see the module docstring).

    Writes images/<name>.png (upright, shrunk to ``max_side``), cameras.json with identity poses and
    guessed pinhole intrinsics, meta.json (``"poses": "unknown"``, per-frame focal source and EXIF
    orientation) and no instances, depth or objects.
    """
    source, out_dir = Path(source), Path(out_dir)
    if not source.is_dir():
        raise Trace3DError(f"{source}: photo folder does not exist.")
    files = list_images(source)
    if len(files) < params.min_images:
        raise Trace3DError(
            f"{source}: holds {len(files)} photo(s), fewer than min_images {params.min_images} "
            "(structure-from-motion needs several overlapping views)."
        )
    splits = every_nth_split([p.stem for p in files], params.test_every)
    cameras, frames = [], {}
    for path in tqdm(files, desc=f"images {source.name}", unit="photo"):
        photo = read_photo(path)
        rgb, (sx, sy) = shrink_to_max_side(photo.rgb, params.max_side)
        height, width = rgb.shape[:2]
        focal, origin = focal_for(photo, width, height, sx, params)
        K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        write_rgb(out_dir / "images" / f"{path.stem}.png", rgb)
        cameras.append(Camera(path.stem, splits[path.stem], width, height, K, np.eye(4)))
        frames[path.stem] = {
            "file": path.name,
            "original_size": [int(photo.rgb.shape[1]), int(photo.rgb.shape[0])],
            "exif_orientation": photo.orientation,
            "scale": [sx, sy],
            "focal_px": focal,
            "intrinsics": origin,
        }
    write_cameras(out_dir, cameras)
    origins = sorted({f["intrinsics"] for f in frames.values()})
    write_json(out_dir / "meta.json", {
        "importer": "images",
        "source": str(source.resolve()),
        "scene": source.name,
        "params": to_dict(params),
        "poses": "unknown",
        "intrinsics": origins[0] if len(origins) == 1 else "mixed",
        "init": "sfm",
        "cameras_note": "identity poses and guessed pinhole intrinsics: placeholders until the poses step "
                        "(COLMAP) estimates both",
        "frames": frames,
    })
    log.info("images %s: %d photos (%d test), focal from %s", source.name, len(cameras),
             sum(c.split == "test" for c in cameras), ", ".join(origins))
