"""The canonical scene directory: what every importer writes and every later step reads.

Layout (one folder per scene)::

    images/<frame>.png        RGB, 8-bit
    cameras.json              {"frames": [{name, split, width, height, K (3x3),
                                          world_to_camera (4x4, OpenCV: x right, y down, z forward)}]}
    instances/<frame>.png     optional ground-truth instance ids, 16-bit, 0 = unlabelled
    depth/<frame>.png         optional ground-truth depth along the optical axis (z), 16-bit,
                              millimetres, 0 = invalid (the Replica convention)
    objects.json              optional: {"objects": [{id, name, level, parent, category, evaluated}]}
    masks/<frame>.npz         optional precomputed 2D masks: "masks" bool [M, H, W], "scores" [M]
    meta.json                 optional free-form metadata of the importer (source, seed, prompts ...)

Instance maps carry the *finest* ids (parts when an object has parts).  ``objects.json`` gives the
hierarchy part -> object -> group through ``parent``; ``level`` is one of ``part``, ``object``,
``group``; ``evaluated`` marks the objects that the benchmark scores.

Reading validates the directory and raises :class:`~trace3d.errors.SceneFormatError` with one
sentence naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Iterable, Literal, Sequence

import cv2
import numpy as np
from PIL import Image

from .errors import SceneFormatError
from .io import atomic_file, write_json

log = logging.getLogger(__name__)

SPLITS = ("train", "test")
LEVELS = ("part", "object", "group")
DEPTH_SCALE = 1000.0  # depth PNG units per metre


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Camera:
    """A pinhole camera, OpenCV convention (x right, y down, z forward; pixel centres at +0.5).

    Attributes:
        name: frame name; the image is ``images/<name>.png``.
        split: ``"train"`` or ``"test"``.
        width, height: image size in pixels.
        K: [3, 3] intrinsics.
        world_to_camera: [4, 4] rigid transform from world to camera coordinates.
    """

    name: str
    split: Literal["train", "test"]
    width: int
    height: int
    K: np.ndarray
    world_to_camera: np.ndarray

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.world_to_camera = np.asarray(self.world_to_camera, dtype=np.float64).reshape(4, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def rotation(self) -> np.ndarray:
        """[3, 3] world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        """[3] world-to-camera translation."""
        return self.world_to_camera[:3, 3]

    @property
    def camera_to_world(self) -> np.ndarray:
        """[4, 4] inverse of ``world_to_camera``."""
        out = np.eye(4)
        out[:3, :3] = self.rotation.T
        out[:3, 3] = -self.rotation.T @ self.translation
        return out

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return -self.rotation.T @ self.translation

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Args:
            points_world: [P, 3].
        Returns:
            pixels [P, 2] (x, y in pixel units, centres at +0.5) and depths [P] (camera z).
        """
        cam = points_world @ self.rotation.T + self.translation
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[:, :2] / z[:, None]
        return uv, z

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "split": self.split,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
        }


def validate_rotation(rotation: np.ndarray, where: str, tol: float = 1e-4) -> None:
    """Raise if ``rotation`` [3, 3] is not a proper rotation (orthonormal, det +1)."""
    err = np.abs(rotation @ rotation.T - np.eye(3)).max()
    det = np.linalg.det(rotation)
    if not np.isfinite(err) or err > tol or abs(det - 1.0) > tol:
        raise SceneFormatError(
            f"{where}: world_to_camera rotation is not orthonormal with det +1 "
            f"(max |R R^T - I| = {err:.2e}, det = {det:.4f})."
        )


def camera_from_json(entry: dict, where: str) -> Camera:
    """Parse and validate one ``cameras.json`` frame entry."""
    if not isinstance(entry, dict):
        raise SceneFormatError(f"{where}: expected an object per frame, got {type(entry).__name__}.")
    missing = [k for k in ("name", "split", "width", "height", "K", "world_to_camera") if k not in entry]
    if missing:
        raise SceneFormatError(f"{where}: frame entry is missing the key(s) {missing}.")
    name = entry["name"]
    if entry["split"] not in SPLITS:
        raise SceneFormatError(
            f"{where}: frame {name!r} has unknown split {entry['split']!r} (expected one of {list(SPLITS)})."
        )
    try:
        K = np.asarray(entry["K"], dtype=np.float64)
        w2c = np.asarray(entry["world_to_camera"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(f"{where}: frame {name!r} has a non-numeric K or world_to_camera.") from exc
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise SceneFormatError(
            f"{where}: frame {name!r} needs K of shape 3x3 and world_to_camera of shape 4x4, "
            f"got {K.shape} and {w2c.shape}."
        )
    if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
        raise SceneFormatError(f"{where}: frame {name!r} has non-finite camera values.")
    if np.abs(w2c[3] - np.array([0, 0, 0, 1])).max() > 1e-6:
        raise SceneFormatError(f"{where}: frame {name!r} world_to_camera last row is not (0, 0, 0, 1).")
    validate_rotation(w2c[:3, :3], f"{where} (frame {name!r})")
    width, height = entry["width"], entry["height"]
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise SceneFormatError(f"{where}: frame {name!r} has invalid width/height {width!r}x{height!r}.")
    return Camera(name=str(name), split=entry["split"], width=width, height=height, K=K, world_to_camera=w2c)


# ----------------------------------------------------------------------------------------------
# Objects
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class SceneObject:
    """One entry of the ground-truth hierarchy.

    Attributes:
        id: positive integer; leaves appear with this id in ``instances/``.
        name: human-readable name (``"table_3/leg_1"``).
        level: ``"part"``, ``"object"`` or ``"group"``.
        parent: id of the enclosing object/group, or None.
        category: semantic kind (``"wall"``, ``"table"`` ...), free text.
        evaluated: whether the benchmark scores this object.
    """

    id: int
    name: str
    level: Literal["part", "object", "group"] = "object"
    parent: int | None = None
    category: str = ""
    evaluated: bool = False

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


class ObjectTable:
    """The ground-truth hierarchy with lookups between levels."""

    def __init__(self, objects: Sequence[SceneObject]):
        self.objects = list(objects)
        self.by_id = {o.id: o for o in self.objects}

    def __len__(self) -> int:
        return len(self.objects)

    def __iter__(self):
        return iter(self.objects)

    def ancestor(self, object_id: int, level: str) -> int:
        """Id of ``object_id``'s ancestor at ``level`` (itself if already there or higher).

        Walking up stops at the first entry whose level is ``level`` or coarser; an entry with no
        parent at that level maps to itself (a stand-alone object is its own group).
        """
        rank = LEVELS.index(level)
        current = self.by_id[object_id]
        while LEVELS.index(current.level) < rank and current.parent is not None:
            current = self.by_id[current.parent]
        return current.id

    def lookup(self, level: str) -> np.ndarray:
        """[max_id + 1] int array mapping every leaf id to its ancestor at ``level`` (0 -> 0)."""
        max_id = max((o.id for o in self.objects), default=0)
        table = np.zeros(max_id + 1, dtype=np.int64)
        for o in self.objects:
            table[o.id] = self.ancestor(o.id, level)
        return table

    def evaluated_ids(self) -> list[int]:
        return [o.id for o in self.objects if o.evaluated]

    def to_json(self) -> dict:
        return {"objects": [o.to_json() for o in self.objects]}


def objects_from_json(data: dict, where: str) -> ObjectTable:
    if not isinstance(data, dict) or not isinstance(data.get("objects"), list):
        raise SceneFormatError(f"{where}: expected an object with an 'objects' list.")
    objects = []
    for i, entry in enumerate(data["objects"]):
        try:
            obj = SceneObject(**entry)
        except TypeError as exc:
            raise SceneFormatError(f"{where}: entry {i} is malformed ({exc}).") from exc
        if not isinstance(obj.id, int) or obj.id <= 0 or obj.id > 65535:
            raise SceneFormatError(f"{where}: entry {i} has id {obj.id!r}; ids must be integers in 1..65535.")
        if obj.level not in LEVELS:
            raise SceneFormatError(f"{where}: object {obj.id} has unknown level {obj.level!r}.")
        objects.append(obj)
    ids = [o.id for o in objects]
    if len(set(ids)) != len(ids):
        raise SceneFormatError(f"{where}: object ids are not unique.")
    table = ObjectTable(objects)
    for o in objects:
        if o.parent is not None and o.parent not in table.by_id:
            raise SceneFormatError(f"{where}: object {o.id} names parent {o.parent}, which is not listed.")
    return table


# ----------------------------------------------------------------------------------------------
# Image I/O
# ----------------------------------------------------------------------------------------------


def read_rgb(path: str | Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB image; raises SceneFormatError naming the file if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: image file is missing.")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SceneFormatError(f"{path}: image file is corrupt or not an image.")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write [H, W, 3] uint8 RGB as PNG (atomically)."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_rgb expects [H, W, 3] uint8, got {rgb.shape} {rgb.dtype}")
    with atomic_file(path) as tmp:
        ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        tmp.write_bytes(buf.tobytes())


def scene_name(scene_dir: str | Path, meta: dict | None = None) -> str:
    """A scene's name for reports: ``meta.json``'s ``name`` when it has one, else the folder's name, or its
    parent's when the folder is the pipeline's ``results/<scene>/scene`` (never a parent such as ``data``)."""
    if meta and isinstance(meta.get("name"), str) and meta["name"]:
        return meta["name"]
    folder = Path(scene_dir).resolve()
    return folder.parent.name if folder.name == "scene" else folder.name


def read_u16(path: str | Path, what: str = "16-bit map", size: tuple[int, int] | None = None) -> np.ndarray:
    """[H, W] uint16 PNG; raises SceneFormatError if missing, corrupt, not 16-bit single channel or (with
    ``size`` = (width, height), the camera's) not the camera's size."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: {what} file is missing.")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneFormatError(f"{path}: {what} file is corrupt or not an image.")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise SceneFormatError(
            f"{path}: {what} must be a single-channel 16-bit PNG, got dtype {img.dtype} with shape {img.shape}."
        )
    if size is not None and img.shape != (size[1], size[0]):
        raise SceneFormatError(
            f"{path}: {what} is {img.shape[1]}x{img.shape[0]} but its view's image is {size[0]}x{size[1]}; "
            f"make it at the image size (or point at the folder made for this scene)."
        )
    return img


def write_u16(path: str | Path, array: np.ndarray) -> None:
    """Write [H, W] uint16 as a 16-bit PNG (atomically)."""
    array = np.asarray(array)
    if array.dtype != np.uint16 or array.ndim != 2:
        raise ValueError(f"write_u16 expects [H, W] uint16, got {array.shape} {array.dtype}")
    with atomic_file(path) as tmp:
        ok, buf = cv2.imencode(".png", array)
        assert ok
        tmp.write_bytes(buf.tobytes())


def _png_header(path: Path, what: str) -> tuple[int, int, str]:
    """(width, height, PIL mode) of an image file, reading only its header."""
    if not path.is_file():
        raise SceneFormatError(f"{path}: {what} file is missing.")
    try:
        with Image.open(path) as im:
            return im.size[0], im.size[1], im.mode
    except Exception as exc:  # PIL raises several types for bad files
        raise SceneFormatError(f"{path}: {what} file is corrupt or not an image ({exc}).") from exc


# ----------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Scene:
    """A canonical scene directory, loaded (cameras and objects in memory; images on demand)."""

    root: Path
    cameras: list[Camera]
    objects: ObjectTable | None = None
    meta: dict = dataclasses.field(default_factory=dict)

    # --- lookups -------------------------------------------------------------------------------
    def camera(self, name: str) -> Camera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    def split(self, split: str) -> list[Camera]:
        return [c for c in self.cameras if c.split == split]

    @property
    def train_cameras(self) -> list[Camera]:
        return self.split("train")

    @property
    def test_cameras(self) -> list[Camera]:
        return self.split("test")

    # --- paths ---------------------------------------------------------------------------------
    def image_path(self, name: str) -> Path:
        return self.root / "images" / f"{name}.png"

    def instances_path(self, name: str) -> Path:
        return self.root / "instances" / f"{name}.png"

    def depth_path(self, name: str) -> Path:
        return self.root / "depth" / f"{name}.png"

    def masks_path(self, name: str) -> Path:
        return self.root / "masks" / f"{name}.npz"

    @property
    def has_instances(self) -> bool:
        return (self.root / "instances").is_dir()

    @property
    def has_depth(self) -> bool:
        return (self.root / "depth").is_dir()

    @property
    def has_masks(self) -> bool:
        return (self.root / "masks").is_dir()

    # --- data ----------------------------------------------------------------------------------
    def image(self, name: str) -> np.ndarray:
        """[H, W, 3] uint8 RGB."""
        return read_rgb(self.image_path(name))

    def instances(self, name: str) -> np.ndarray:
        """[H, W] uint16 ground-truth instance ids (leaf level)."""
        cam = next((c for c in self.cameras if c.name == name), None)
        size = (cam.width, cam.height) if cam is not None else None  # a map at the wrong pixels is refused
        return read_u16(self.instances_path(name), "instance map", size)

    def depth(self, name: str) -> np.ndarray:
        """[H, W] float32 depth along the optical axis in scene units; 0 where invalid."""
        return read_u16(self.depth_path(name), "depth map").astype(np.float32) / DEPTH_SCALE

    # --- I/O -----------------------------------------------------------------------------------
    @classmethod
    def read(cls, root: str | Path, check_files: bool = True) -> "Scene":
        """Load and validate the scene directory at ``root``."""
        root = Path(root)
        if not root.is_dir():
            raise SceneFormatError(f"{root}: scene directory does not exist.")
        cams_path = root / "cameras.json"
        if not cams_path.is_file():
            raise SceneFormatError(f"{cams_path}: cameras.json is missing.")
        cameras = read_cameras(cams_path)
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            raise SceneFormatError(f"{cams_path}: frame names are not unique.")

        objects = None
        obj_path = root / "objects.json"
        if obj_path.is_file():
            try:
                objects = objects_from_json(json.loads(obj_path.read_text()), str(obj_path))
            except json.JSONDecodeError as exc:
                raise SceneFormatError(f"{obj_path}: not valid JSON ({exc}).") from exc
        meta = {}
        meta_path = root / "meta.json"
        if meta_path.is_file():
            try:
                meta = json.loads(meta_path.read_text())
            except json.JSONDecodeError as exc:
                raise SceneFormatError(f"{meta_path}: not valid JSON ({exc}).") from exc

        scene = cls(root=root, cameras=cameras, objects=objects, meta=meta)
        if check_files:
            scene.validate_files()
        return scene

    def validate_files(self) -> None:
        """Check that every image (and instance / depth map, if present) exists with the right size."""
        for cam in self.cameras:
            path = self.image_path(cam.name)
            w, h, mode = _png_header(path, "image")
            if (w, h) != (cam.width, cam.height):
                raise SceneFormatError(
                    f"{path}: image is {w}x{h} but cameras.json says {cam.width}x{cam.height}."
                )
            for folder, what in (("instances", "instance map"), ("depth", "depth map")):
                if not (self.root / folder).is_dir():
                    continue
                p = self.root / folder / f"{cam.name}.png"
                w, h, mode = _png_header(p, what)
                if (w, h) != (cam.width, cam.height):
                    raise SceneFormatError(
                        f"{p}: {what} is {w}x{h} but the image is {cam.width}x{cam.height}."
                    )
                if not mode.startswith("I;16"):
                    raise SceneFormatError(f"{p}: {what} must be a 16-bit single-channel PNG, got mode {mode}.")

    def write_metadata(self) -> None:
        """Write cameras.json, objects.json and meta.json into ``root`` (images are written per frame)."""
        write_cameras(self.root, self.cameras)
        if self.objects is not None:
            write_json(self.root / "objects.json", self.objects.to_json())
        if self.meta:
            write_json(self.root / "meta.json", self.meta)


def read_cameras(path: str | Path) -> list[Camera]:
    """Parse and validate a ``cameras.json`` file (the scene's, or a poses step's)."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: cameras.json is missing.")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneFormatError(f"{path}: not valid JSON ({exc}).") from exc
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise SceneFormatError(f"{path}: expected a non-empty 'frames' list.")
    return [camera_from_json(f, str(path)) for f in frames]


def write_cameras(root: str | Path, cameras: Iterable[Camera]) -> None:
    write_json(Path(root) / "cameras.json", {"frames": [c.to_json() for c in cameras]})


def write_frame(
    root: str | Path,
    name: str,
    rgb: np.ndarray,
    instances: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> None:
    """Write one frame's image [H, W, 3] uint8, optional instance ids [H, W] and depth [H, W] (float, metres)."""
    root = Path(root)
    write_rgb(root / "images" / f"{name}.png", rgb)
    if instances is not None:
        if instances.max(initial=0) > 65535 or instances.min(initial=0) < 0:
            raise ValueError("instance ids must fit in 16 bits")
        write_u16(root / "instances" / f"{name}.png", instances.astype(np.uint16))
    if depth is not None:
        mm = np.clip(np.round(np.asarray(depth, dtype=np.float64) * DEPTH_SCALE), 0, 65535)
        mm[~np.isfinite(np.asarray(depth, dtype=np.float64))] = 0
        write_u16(root / "depth" / f"{name}.png", mm.astype(np.uint16))


def require_known_poses(scene: Scene, step: str) -> None:
    """Refuse to use the scene's own cameras when its poses are placeholders (meta.json ``"poses":
    "unknown"``, as ``trace3d scene images`` writes): ``step`` must take the ``poses`` step's folder."""
    if str(scene.meta.get("poses", "")).lower() in ("unknown", "none", "identity"):
        raise SceneFormatError(
            f"{scene.root / 'meta.json'}: the scene's poses are unknown (placeholders), so `{step}` needs the "
            "poses step's folder (--poses) with the cameras COLMAP estimated."
        )


def read_pose_cameras(poses_dir: Path, scene: "Scene") -> list[Camera]:
    """The cameras of ``poses_dir/cameras.json`` for the scene's frames, in the scene's frame order.

    Raises if a test view is missing (the poses step must not drop evaluation views); train views
    that SfM did not register are skipped with a warning.
    """
    path = poses_dir / "cameras.json"
    if not path.is_file():
        raise SceneFormatError(f"{path}: poses cameras.json is missing.")
    by_name = {cam.name: cam for cam in read_cameras(path)}
    unknown = sorted(set(by_name) - {c.name for c in scene.cameras})
    if unknown:
        raise SceneFormatError(f"{path}: frames {unknown[:5]} are not in the scene {scene.root}.")
    missing_test = [c.name for c in scene.test_cameras if c.name not in by_name]
    if missing_test:
        raise SceneFormatError(f"{path}: test views {missing_test[:5]} have no pose ({len(missing_test)} missing).")
    missing_train = [c.name for c in scene.train_cameras if c.name not in by_name]
    if missing_train:
        log.warning("%s: %d train views have no pose and are skipped: %s", path, len(missing_train), missing_train[:5])
    cameras = []
    for scene_cam in scene.cameras:
        cam = by_name.get(scene_cam.name)
        if cam is None:
            continue
        if (cam.width, cam.height) != (scene_cam.width, scene_cam.height):
            raise SceneFormatError(
                f"{path}: frame {cam.name!r} is {cam.width}x{cam.height} but its image is "
                f"{scene_cam.width}x{scene_cam.height}."
            )
        cam.split = scene_cam.split  # the scene owns the split
        cameras.append(cam)
    return cameras
