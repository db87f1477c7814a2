"""LLFF forward-facing scenes and the NVOS benchmark (LLFF scenes + NVOS labels).

LLFF scene folder (the ``nerf_llff_data`` release)::

    <scene>/poses_bounds.npy        [N, 17]: a row-major 3x5 [R | t | hwf] per image, then near, far
    <scene>/images/                 full-resolution images (not needed)
    <scene>/images_<k>/             images downscaled by k (NeRF uses k = 4 or 8), sorted by name
                                    in the order of poses_bounds.npy rows

The 3x3 block of each pose is camera-to-world with the columns in LLFF's [down, right, back]
camera axes; we convert to OpenCV [right, down, forward] = [col1, col0, -col2] and invert.  hwf is
(height, width, focal) of the *full-resolution* images; the images_<k> size gives the scale that is
applied to the focal length.  The principal point is the image centre (W / 2, H / 2 with pixel
centres at +0.5, as LLFF/NeRF assume).  Positions stay in the COLMAP units of the release (no
recentring or bound rescaling); near/far bounds are kept in meta.json.

NVOS labels (Ren et al. 2022, as SA3D / OmniSeg3D / FlashSplat / Trace3D load them)::

    labels/llff/masks/<object>/<target>_mask.png          binary target mask (the test view)
    labels/llff/masks/<object>/<target>.JPG               the target image (not needed)
    labels/llff/reference_image/<object>/<reference>.JPG  the view the scribbles are drawn on
    labels/llff/scribbles/<object>/pos_0_<object>.png     positive scribbles on the reference view
    labels/llff/scribbles/<object>/neg_0_<object>.png     negative scribbles

with ``<object>`` one of fern, flower, fortress, horns_center, horns_left, leaves, orchids, trex
(both horns objects use the LLFF scene ``horns``; some copies name the horns scribbles
``pos_0_horns.png``, which is accepted too).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import Trace3DError
from ..io import atomic_file, write_json
from ..params import from_mapping, to_dict
from ..scene import Camera, read_rgb, write_cameras, write_rgb
from .common import IMAGE_EXTENSIONS, downscale_rgb, every_nth_split, list_images, rigid_inverse, scale_intrinsics

log = logging.getLogger(__name__)

#: NVOS object -> (LLFF scene, target view (test, has the mask), reference view (has the scribbles)).
NVOS_OBJECTS = {
    "fern": ("fern", "IMG_4027", "IMG_4038"),
    "flower": ("flower", "IMG_2962", "IMG_2983"),
    "fortress": ("fortress", "IMG_1800", "IMG_1821"),
    "horns_center": ("horns", "DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "horns_left": ("horns", "DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "leaves": ("leaves", "IMG_2997", "IMG_3011"),
    "orchids": ("orchids", "IMG_4480", "IMG_4479"),
    "trex": ("trex", "DJI_20200223_163619_411", "DJI_20200223_163607_906"),
}

@dataclasses.dataclass
class LLFFParams:
    """Parameters of the LLFF and NVOS importers.

    Attributes:
        scene: NVOS object name (``import_nvos``: fern, flower, fortress, horns_center, horns_left,
            leaves, orchids, trex; empty = inferred from the source folder name) or, for
            ``import_llff``, an optional sub-folder of the source holding the LLFF scene.
        images_factor: read ``images_<k>`` (1 = ``images``).  NVOS labels match k = 4 (1008x756).
        downscale: further integer downscale for CPU runs (block average); intrinsics follow.
        test_every: ``import_llff`` only: every n-th image (positions 0, n, 2n ...) is a test
            view (LLFF hold-out 8); 0 = all train.  NVOS always tests on its target view only.
        prompt_seed: seed of the scribble-to-point sampling.
        positive_fraction: share of the positive scribble's skeleton pixels kept as points
            (SA3D / SAGA keep 2 %).
        negative_fraction: the same for the negative scribble (0.5 %).
        scene_dir: NVOS: the LLFF scene folder, absolute or relative to the source (default: searched).
        labels_dir: NVOS: the folder holding masks/, reference_image/, scribbles/ (default: searched).
    """

    scene: str = ""
    images_factor: int = 4
    downscale: int = 1
    test_every: int = 8
    prompt_seed: int = 0
    positive_fraction: float = 0.02
    negative_fraction: float = 0.005
    scene_dir: str | None = None
    labels_dir: str | None = None

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"images_factor": ">= 1", "downscale": ">= 1", "test_every": ">= 0", "positive_fraction": "(0, 1]",
              "negative_fraction": "(0, 1]", "prompt_seed": ">= 0"}

    def __post_init__(self) -> None:
        if self.images_factor < 1:
            raise ValueError(f"images_factor must be >= 1, got {self.images_factor}")
        if self.downscale < 1:
            raise ValueError(f"downscale must be >= 1, got {self.downscale}")
        if self.test_every < 0:
            raise ValueError(f"test_every must be >= 0, got {self.test_every}")
        for name in ("positive_fraction", "negative_fraction"):
            value = getattr(self, name)
            if not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {value}")


def params_from(d: dict | None) -> LLFFParams:
    """Typed :class:`LLFFParams` from a config mapping (unknown keys and wrong types refused)."""
    return from_mapping(LLFFParams, d, "llff params")


# ----------------------------------------------------------------------------------------------
# LLFF scene
# ----------------------------------------------------------------------------------------------


def llff_to_opencv_c2w(pose: np.ndarray) -> np.ndarray:
    """[3, 4] LLFF camera-to-world ([down, right, back] columns, then position) -> [4, 4] OpenCV."""
    pose = np.asarray(pose, dtype=np.float64)
    c2w = np.eye(4)
    c2w[:3, 0] = pose[:, 1]  # right
    c2w[:3, 1] = pose[:, 0]  # down
    c2w[:3, 2] = -pose[:, 2]  # forward = -back
    c2w[:3, 3] = pose[:, 3]
    return c2w


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """poses [N, 3, 4] (LLFF axes), hwf [N, 3] and bounds [N, 2] from ``poses_bounds.npy``."""
    if not path.is_file():
        raise Trace3DError(f"{path}: poses_bounds.npy is missing; this is not an LLFF scene folder.")
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise Trace3DError(f"{path}: cannot be read as a numpy array ({exc}).") from exc
    if data.ndim != 2 or data.shape[1] != 17 or data.shape[0] == 0:
        raise Trace3DError(f"{path}: expected an [N, 17] array (3x5 pose + near, far per image), got {data.shape}.")
    data = data.astype(np.float64)
    if not np.isfinite(data).all():
        raise Trace3DError(f"{path}: contains non-finite values.")
    mats = data[:, :15].reshape(-1, 3, 5)
    return mats[:, :, :4], mats[:, :, 4], data[:, 15:17]


@dataclasses.dataclass
class _LLFFFrame:
    name: str
    path: Path
    c2w: np.ndarray  # [4, 4] OpenCV
    hwf: np.ndarray  # [3]
    bounds: np.ndarray  # [2]


def read_llff_scene(scene_dir: Path, params: LLFFParams) -> tuple[list[_LLFFFrame], Path]:
    """Frames of an LLFF scene folder (poses converted to OpenCV) and the image folder used."""
    poses, hwf, bounds = read_poses_bounds(scene_dir / "poses_bounds.npy")
    folder = scene_dir / ("images" if params.images_factor == 1 else f"images_{params.images_factor}")
    files = list_images(folder)
    if len(files) != len(poses):
        raise Trace3DError(
            f"{folder}: holds {len(files)} images but {scene_dir / 'poses_bounds.npy'} has {len(poses)} poses."
        )
    names = [p.stem for p in files]
    frames = []
    for k, path in enumerate(files):
        c2w = llff_to_opencv_c2w(poses[k])
        rigid_inverse(c2w, f"{scene_dir / 'poses_bounds.npy'} (row {k}, {path.name})")  # validates
        frames.append(_LLFFFrame(names[k], path, c2w, hwf[k], bounds[k]))
    return frames, folder


def _camera_for(frame: _LLFFFrame, rgb_shape: tuple[int, ...], params: LLFFParams, where: Path) -> tuple[Camera, float]:
    """Camera of one frame at the read image size, then scaled by 1 / downscale."""
    h_full, w_full, focal = frame.hwf
    height, width = rgb_shape[:2]
    scale = width / w_full
    if abs(h_full * scale - height) > 1.0:
        raise Trace3DError(
            f"{where}: image is {width}x{height} but poses_bounds.npy says {int(w_full)}x{int(h_full)}, "
            "a different aspect ratio."
        )
    K = np.array([[focal * scale, 0.0, width / 2.0], [0.0, focal * scale, height / 2.0], [0.0, 0.0, 1.0]])
    K = scale_intrinsics(K, 1.0 / params.downscale)
    w2c = rigid_inverse(frame.c2w, f"{where}")
    cam = Camera(name=frame.name, split="train", width=width // params.downscale,
                 height=height // params.downscale, K=K, world_to_camera=w2c)
    return cam, scale


def _write_llff_frames(frames: list[_LLFFFrame], splits: dict[str, str], out_dir: Path, params: LLFFParams,
                       desc: str) -> tuple[list[Camera], float]:
    cameras = []
    scale = 1.0
    size = None
    for frame in tqdm(frames, desc=desc, unit="frame"):
        rgb = read_rgb(frame.path)
        if size is None:
            size = rgb.shape[:2]
        elif rgb.shape[:2] != size:
            raise Trace3DError(
                f"{frame.path}: image is {rgb.shape[1]}x{rgb.shape[0]} but the scene's images are {size[1]}x{size[0]}."
            )
        cam, scale = _camera_for(frame, rgb.shape, params, frame.path)
        cam.split = splits[frame.name]
        write_rgb(out_dir / "images" / f"{frame.name}.png", downscale_rgb(rgb, params.downscale))
        cameras.append(cam)
    write_cameras(out_dir, cameras)
    return cameras, scale


def _llff_meta(frames: list[_LLFFFrame], scene_dir: Path, folder: Path, scale: float) -> dict:
    return {
        "scene_dir": str(scene_dir.resolve()),
        "images_folder": folder.name,
        "hwf_full_resolution": frames[0].hwf.tolist(),
        "focal_scale_from_hwf": scale,
        "bounds": {f.name: f.bounds.tolist() for f in frames},
        "pose_convention": "poses_bounds.npy [down, right, back] converted to OpenCV; COLMAP units",
    }


def import_llff(source: Path, out_dir: Path, params: LLFFParams) -> None:
    """Write the canonical scene of one plain LLFF scene (no labels) into ``out_dir``.

    ``source`` is the scene folder (with poses_bounds.npy), or its parent when ``params.scene``
    names the sub-folder.  Split: positions 0, n, 2n ... (n = ``test_every``) are test views.
    """
    source, out_dir = Path(source), Path(out_dir)
    if not source.is_dir():
        raise Trace3DError(f"{source}: LLFF source folder does not exist.")
    scene_dir = source
    if not (source / "poses_bounds.npy").is_file() and params.scene and (source / params.scene).is_dir():
        scene_dir = source / params.scene
    frames, folder = read_llff_scene(scene_dir, params)
    splits = every_nth_split([f.name for f in frames], params.test_every)
    cameras, scale = _write_llff_frames(frames, splits, out_dir, params, f"llff {scene_dir.name}")
    write_json(out_dir / "meta.json", {
        "importer": "llff",
        "source": str(scene_dir.resolve()),
        "scene": scene_dir.name,
        "params": to_dict(params),
        "init": "sfm",
        "llff": _llff_meta(frames, scene_dir, folder, scale),
    })
    log.info("LLFF %s: %d cameras (%d test)", scene_dir.name, len(cameras), sum(c.split == "test" for c in cameras))


# ----------------------------------------------------------------------------------------------
# NVOS
# ----------------------------------------------------------------------------------------------


def _resolve(source: Path, value: str) -> Path:
    path = Path(value)
    return path if path.is_absolute() else source / path


def resolve_nvos(source: Path, params: LLFFParams) -> tuple[str, Path, Path]:
    """(object name, LLFF scene folder, NVOS label folder) for an NVOS import."""
    source = Path(source)
    if not source.is_dir():
        raise Trace3DError(f"{source}: NVOS source folder does not exist.")
    obj = params.scene or source.name
    if obj not in NVOS_OBJECTS:
        raise Trace3DError(
            f"{source}: NVOS object {obj!r} is unknown (set the `scene` parameter to one of {sorted(NVOS_OBJECTS)})."
        )
    llff_scene = NVOS_OBJECTS[obj][0]

    if params.scene_dir:
        scene_candidates = [_resolve(source, params.scene_dir)]
    else:
        scene_candidates = [source / llff_scene, source / "nerf_llff_data" / llff_scene, source / "scenes" / llff_scene,
                            source.parent / llff_scene, source]
    scene_dir = next((p for p in scene_candidates if (p / "poses_bounds.npy").is_file()), None)
    if scene_dir is None:
        tried = ", ".join(str(p / "poses_bounds.npy") for p in scene_candidates)
        raise Trace3DError(f"{source}: no LLFF scene {llff_scene!r} found for NVOS object {obj!r} (tried {tried}).")

    if params.labels_dir:
        label_candidates = [_resolve(source, params.labels_dir)]
    else:
        label_candidates = [source / "labels" / "llff", source / "llff", source, source.parent / "labels" / "llff",
                            source.parent]
    labels = next((p for p in label_candidates if (p / "masks" / obj).is_dir()), None)
    if labels is None:
        tried = ", ".join(str(p / "masks" / obj) for p in label_candidates)
        raise Trace3DError(f"{source}: NVOS labels for {obj!r} are missing (no masks folder at {tried}).")
    return obj, scene_dir, labels


def _find_file(folder: Path, stems: list[str], what: str) -> Path:
    stems = list(dict.fromkeys(stems))
    if not folder.is_dir():
        raise Trace3DError(f"{folder}: NVOS {what} folder is missing.")
    for stem in stems:
        for path in sorted(folder.iterdir()):
            if path.is_file() and path.stem == stem and path.suffix.lower() in IMAGE_EXTENSIONS:
                return path
    present = sorted(p.name for p in folder.iterdir())
    raise Trace3DError(f"{folder}: NVOS {what} {' or '.join(stems)} is missing (found {present or 'nothing'}).")


def _read_binary(path: Path, what: str) -> np.ndarray:
    """[H, W] bool: non-zero pixels of a mask or scribble image (colour channels summed, alpha dropped)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise Trace3DError(f"{path}: NVOS {what} is corrupt or not an image.")
    if img.ndim == 3:
        img = img[..., :3].astype(np.int64).sum(-1)
    return img > (127 if what == "target mask" else 0)


def resize_binary(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """[h, w] bool -> [height, width] bool by area coverage >= 1/2 (centred, any ratio)."""
    if mask.shape == (height, width):
        return mask.copy()
    cover = cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    return cover >= 0.5


def scribble_points(
    scribble: np.ndarray, fraction: float, rng: np.random.Generator, scale_xy: tuple[float, float]
) -> np.ndarray:
    """Point prompts from a scribble, as SA3D / SAGA make them, but seeded.

    The scribble is thinned to its skeleton; each skeleton pixel is kept with probability
    ``fraction``; at least one point is kept (the middle skeleton pixel) if the scribble is not empty.

    Args:
        scribble: [h, w] bool at the label resolution.
        fraction: keep probability per skeleton pixel.
        rng: the seeded generator.
        scale_xy: (imported width / label width, imported height / label height).
    Returns:
        [P, 2] float (x, y) in imported-image pixel coordinates (pixel centres at +0.5).
    """
    from skimage.morphology import skeletonize

    skeleton = skeletonize(scribble)
    rows, cols = np.nonzero(skeleton)
    if rows.size == 0:
        return np.zeros((0, 2))
    keep = rng.random(rows.size) < fraction
    if not keep.any():
        keep[rows.size // 2] = True
    pts = np.stack([cols[keep] + 0.5, rows[keep] + 0.5], axis=1).astype(np.float64)
    return pts * np.asarray(scale_xy)[None, :]


def import_nvos(source: Path, out_dir: Path, params: LLFFParams) -> None:
    """Write the canonical scene of one NVOS object (its LLFF scene + labels) into ``out_dir``.

    ``source`` is the folder holding the LLFF scene and the NVOS labels (see the module docstring;
    ``scene_dir`` / ``labels_dir`` override the search).  Split: the target view is the only test
    view, every other view (the reference included) trains.  Writes images/, cameras.json,
    nvos/target_mask.png, nvos/positive_scribble.png, nvos/negative_scribble.png (8-bit 0/255 at the
    imported resolution) and meta.json with the point prompts.
    """
    source, out_dir = Path(source), Path(out_dir)
    obj, scene_dir, labels = resolve_nvos(source, params)
    llff_scene, target, reference = NVOS_OBJECTS[obj]
    mask_path = _find_file(labels / "masks" / obj, [f"{target}_mask"], "target mask")
    ref_path = _find_file(labels / "reference_image" / obj, [reference], "reference image")
    scribble_dir = labels / "scribbles" / obj
    pos_path = _find_file(scribble_dir, [f"pos_0_{obj}", f"pos_0_{llff_scene}"], "positive scribble")
    neg_path = _find_file(scribble_dir, [f"neg_0_{obj}", f"neg_0_{llff_scene}"], "negative scribble")

    frames, folder = read_llff_scene(scene_dir, params)
    names = [f.name for f in frames]
    for view, role in ((target, "target"), (reference, "reference")):
        if view not in names:
            raise Trace3DError(f"{folder}: the NVOS {role} view {view} of {obj!r} is not among the scene's images.")
    splits = {n: "test" if n == target else "train" for n in names}
    cameras, scale = _write_llff_frames(frames, splits, out_dir, params, f"nvos {obj}")
    cam_by_name = {c.name: c for c in cameras}
    tgt_cam, ref_cam = cam_by_name[target], cam_by_name[reference]

    target_mask = _read_binary(mask_path, "target mask")
    pos = _read_binary(pos_path, "positive scribble")
    neg = _read_binary(neg_path, "negative scribble")
    ref_h, ref_w = _reference_size(ref_path)
    for arr, path in ((pos, pos_path), (neg, neg_path)):
        if arr.shape != (ref_h, ref_w):
            raise Trace3DError(
                f"{path}: scribble is {arr.shape[1]}x{arr.shape[0]} but the reference image {ref_path.name} is "
                f"{ref_w}x{ref_h}."
            )
    for (h, w), path, cam in (((ref_h, ref_w), ref_path, ref_cam), (target_mask.shape, mask_path, tgt_cam)):
        if abs(w / h - cam.width / cam.height) > 0.02:
            raise Trace3DError(
                f"{path}: label is {w}x{h}, a different aspect ratio from the imported view {cam.width}x{cam.height}."
            )
    if not pos.any():
        raise Trace3DError(f"{pos_path}: the positive scribble is empty.")
    if not target_mask.any():
        raise Trace3DError(f"{mask_path}: the target mask is empty.")

    rng = np.random.default_rng(params.prompt_seed)
    scale_xy = (ref_cam.width / ref_w, ref_cam.height / ref_h)
    pos_points = scribble_points(pos, params.positive_fraction, rng, scale_xy)
    neg_points = scribble_points(neg, params.negative_fraction, rng, scale_xy)

    _write_mask(out_dir / "nvos" / "target_mask.png", resize_binary(target_mask, tgt_cam.width, tgt_cam.height))
    _write_mask(out_dir / "nvos" / "positive_scribble.png", resize_binary(pos, ref_cam.width, ref_cam.height))
    _write_mask(out_dir / "nvos" / "negative_scribble.png", resize_binary(neg, ref_cam.width, ref_cam.height))

    write_json(out_dir / "meta.json", {
        "importer": "nvos",
        "source": str(source.resolve()),
        "scene": obj,
        "params": to_dict(params),
        "init": "sfm",
        "llff": _llff_meta(frames, scene_dir, folder, scale),
        "nvos": {
            "object": obj,
            "llff_scene": llff_scene,
            "reference_frame": reference,
            "target_frame": target,
            "target_mask": "nvos/target_mask.png",
            "positive_scribble": "nvos/positive_scribble.png",
            "negative_scribble": "nvos/negative_scribble.png",
            "positive_points": pos_points.round(3).tolist(),
            "negative_points": neg_points.round(3).tolist(),
            "points_convention": "(x, y) pixel coordinates of the reference view at the imported resolution; "
                                 "pixel (col, row) spans [col, col + 1) x [row, row + 1), centre at +0.5",
            "label_size": [ref_w, ref_h],
            "target_mask_size": [int(target_mask.shape[1]), int(target_mask.shape[0])],
            "label_files": {"target_mask": str(mask_path), "reference_image": str(ref_path),
                            "positive_scribble": str(pos_path), "negative_scribble": str(neg_path)},
        },
    })
    log.info("NVOS %s: %d cameras, %d positive / %d negative prompt points", obj, len(cameras),
             len(pos_points), len(neg_points))


def _reference_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise Trace3DError(f"{path}: NVOS reference image is corrupt or not an image.")
    return int(img.shape[0]), int(img.shape[1])


def _write_mask(path: Path, mask: np.ndarray) -> None:
    """Write [H, W] bool as an 8-bit 0/255 PNG, atomically."""
    with atomic_file(path) as tmp:
        ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
        if not ok:
            raise Trace3DError(f"{path}: could not encode the mask.")
        tmp.write_bytes(buf.tobytes())


# ----------------------------------------------------------------------------------------------
# Reading an imported NVOS scene's labels back
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class NVOSLabels:
    """The NVOS labels of an imported scene (what ``import_nvos`` wrote).

    Attributes:
        object: NVOS object name.
        reference_frame, target_frame: frame names (reference trains, target is the test view).
        positive_points: [P, 2] (x, y) prompts on the reference view, pixel centres at +0.5.
        negative_points: [Q, 2] the same for the negative scribble.
        target_mask: [H, W] bool ground-truth mask of the target view.
    """

    object: str
    reference_frame: str
    target_frame: str
    positive_points: np.ndarray
    negative_points: np.ndarray
    target_mask: np.ndarray


def read_nvos_labels(scene) -> NVOSLabels:
    """:class:`NVOSLabels` of a canonical scene imported by :func:`import_nvos`."""
    where = scene.root / "meta.json"
    info = scene.meta.get("nvos") if isinstance(scene.meta, dict) else None
    if not isinstance(info, dict):
        raise Trace3DError(f"{where}: has no 'nvos' entry; the scene was not imported with `trace3d scene nvos`.")
    try:
        mask_path = scene.root / info["target_mask"]
        pos = np.asarray(info["positive_points"], dtype=np.float64).reshape(-1, 2)
        neg = np.asarray(info["negative_points"], dtype=np.float64).reshape(-1, 2)
        reference, target, obj = info["reference_frame"], info["target_frame"], info["object"]
    except (KeyError, TypeError, ValueError) as exc:
        raise Trace3DError(f"{where}: the 'nvos' entry is malformed ({exc}).") from exc
    mask = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
    if mask is None or mask.ndim != 2:
        raise Trace3DError(f"{mask_path}: NVOS target mask is missing or not a single-channel image.")
    cam = scene.camera(target)
    if mask.shape != (cam.height, cam.width):
        raise Trace3DError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]} but view {target} is "
                           f"{cam.width}x{cam.height}.")
    return NVOSLabels(obj, reference, target, pos, neg, mask > 0)
