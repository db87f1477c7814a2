"""Camera poses: pycolmap structure-from-motion, or the data set's own cameras.

Entry point :func:`run_poses` (the ``poses`` pipeline step, ``trace3d poses``).  It writes into an
empty folder:

    sparse/0/       COLMAP binary model (cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin)
    cameras.json    our camera convention (:func:`trace3d.scene.write_cameras`), one entry per scene
                    frame with the scene's names and splits, test views included
    points3D.ply    x y z + red green blue (binary PLY), the trainer's initialisation
    sfm.json        registration, reprojection error, track length, points, pose error, timings,
                    the resolved parameters

``mode: colmap`` runs SIFT extraction, exhaustive or sequential matching and incremental mapping on
the CPU, with a shared PINHOLE camera when every frame has the same size and intrinsics (or when
``single_camera`` says so).  The scene's intrinsics are used as the camera's (fixed unless
``refine_intrinsics``) when ``known_intrinsics``; otherwise COLMAP estimates them.  Every scene
frame, train and test, must register (``min_registered_fraction = 1``); a failed or partial
reconstruction raises :class:`~trace3d.errors.Trace3DError` naming the frames that are missing.

Output frame.  When the scene has reference poses (its ``cameras.json``; see
:func:`scene_has_reference_poses`), the reconstruction is mapped by the Sim(3) that best aligns its
cameras with the reference cameras, so that every output (COLMAP model, cameras.json, points)
lives in the scene's frame and scale, and later steps can use the scene's depths and instances.
The default ``align_method: poses`` takes the rotation from the camera orientations and scale and
translation from the centres (least squares); ``centers`` is Umeyama on the centres alone, which
fixes the rotation poorly for a short camera loop (the default synthetic rooms and Replica capture
from a loop of ~1 m diameter).  The residual camera-centre error is reported relative to the
diameter of the reference camera centres (largest pairwise distance), with the rotation error in
degrees, for the alignment used and for the centres-only (Umeyama) alignment.  Without reference
poses COLMAP's own frame is kept.

Missing frames when ``min_registered_fraction < 1`` allows them: in the reference frame they are
written with the scene's reference pose and listed under ``filled_from_scene`` in sfm.json (later
steps need every frame); without reference poses they cannot be placed and are left out of
cameras.json, listed under ``missing``.

``mode: dataset`` copies the scene's cameras.  Its points (``dataset_points``) are back-projected
from a random subsample of depth pixels when the scene has ``depth/`` (the COLMAP model then holds
the cameras and track-less points), or else triangulated from SIFT matches with the scene's poses
and intrinsics held fixed (COLMAP's point triangulator; the model holds the tracks).  When no point
results, no ``points3D.ply`` is written (so the trainer's ``init: auto`` falls back to depth /
random) and sfm.json says why in its ``note``.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from .errors import ConfigError, Trace3DError
from .geometry import backproject_pixels
from .io import write_json
from .params import from_mapping, to_dict
from .pointcloud import align_cameras, rotation_angle_deg, write_points_ply
from .scene import Camera, Scene, write_cameras

log = logging.getLogger(__name__)

# after alignment, frames off the reference by more than this are listed as suspect (a warning, not a failure)
SUSPECT_CENTER_REL = 0.05  # of the camera diameter
SUSPECT_ROTATION_DEG = 2.0


@dataclasses.dataclass
class PosesParams:
    """Parameters of the ``poses`` step (COLMAP's defaults where COLMAP has one, except
    ``sift_peak_threshold``).

    Attributes:
        mode: "colmap" (run SfM) or "dataset" (use the scene's cameras; see ``dataset_points``).
        matcher: "exhaustive" (every pair; small scenes) or "sequential" (video-like captures, frames
            matched to their ``sequential_overlap`` successors in name order).
        sequential_overlap: number of following frames each frame is matched with (sequential).
        sequential_quadratic_overlap: also match frames 2^k apart (COLMAP's quadratic overlap).
        single_camera: one shared camera for all frames; None = decide from the scene (shared when
            every frame has the same size and, with known intrinsics, the same K).
        known_intrinsics: start from the scene's K (its cameras.json) instead of COLMAP's guess.
        refine_intrinsics: let bundle adjustment refine focal lengths and principal point (with
            known intrinsics; estimated intrinsics always refine the focal lengths).
        max_num_features: SIFT features per image.
        max_image_size: images larger than this are downscaled for extraction.
        sift_peak_threshold: SIFT detection threshold.  COLMAP's default is 0.02 / 3 = 0.0067, made
            for megapixel photos; 0.003 finds ~15 % more features in the small (160 x 120) benchmark
            images and removed the pose outliers measured on the default rooms (room 3: worst
            camera-centre error 17.8 % -> 2.1 % of the camera diameter, worst rotation 4.5 -> 0.6
            degrees).  On large images the ``max_num_features`` strongest are kept either way.
        domain_size_pooling: DSP-SIFT descriptors (more robust matching, slower extraction).
        guided_matching: re-match guided by the verified two-view geometry (more inliers, slower).
        init_min_num_inliers: verified matches needed by the initial image pair.
        min_num_matches: verified matches for a pair to enter the view graph.
        min_registered_fraction: fraction of the scene's frames that must register (1 = all).
        min_num_points: fewer triangulated points than this is a degenerate reconstruction.
        align_to_scene: map the reconstruction into the frame of the scene's poses; None = whenever
            the scene has reference poses.
        align_method: "poses" (rotation from the camera orientations, scale and translation from
            the centres) or "centers" (Umeyama on the centres alone); see
            :func:`trace3d.pointcloud.align_cameras`.
        dataset_points: (dataset mode) where points3D.ply comes from: "depth" (back-project the
            scene's depth maps), "triangulate" (SIFT matches triangulated with the scene's poses and
            intrinsics, poses kept fixed), "none"; "auto" = depth when the scene has depth/, else
            triangulate.
        depth_points: (dataset mode) total number of depth pixels back-projected into points.
        num_threads: CPU threads for pycolmap (-1 = all cores of ``trace3d --threads``). 1 by default:
            with more threads COLMAP's poses are not reproducible (two runs of the same room with 2
            threads gave cameras differing at about 1e-5 relative; with one, identical files), and
            every later step inherits the difference. More threads are faster on large captures at
            that price.
        seed: seed of pycolmap's random number generator (RANSAC, mapping) and of point sampling.
        colmap_log_level: verbosity of pycolmap's own log (written to stderr, the step log).
    """

    mode: Literal["colmap", "dataset"] = "colmap"
    matcher: Literal["exhaustive", "sequential"] = "exhaustive"
    sequential_overlap: int = 10
    sequential_quadratic_overlap: bool = True
    single_camera: bool | None = None
    known_intrinsics: bool = True
    refine_intrinsics: bool = False
    max_num_features: int = 8192
    max_image_size: int = 3200
    sift_peak_threshold: float = 0.003
    domain_size_pooling: bool = False
    guided_matching: bool = False
    init_min_num_inliers: int = 100
    min_num_matches: int = 15
    min_registered_fraction: float = 1.0
    min_num_points: int = 100
    align_to_scene: bool | None = None
    align_method: Literal["poses", "centers"] = "poses"
    dataset_points: Literal["auto", "depth", "triangulate", "none"] = "auto"
    depth_points: int = 100_000
    num_threads: int = 1
    seed: int = 0
    colmap_log_level: Literal["info", "warning", "error"] = "info"

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"min_registered_fraction": "(0, 1]", "sequential_overlap": ">= 1", "max_num_features": ">= 1",
              "max_image_size": ">= 1", "init_min_num_inliers": ">= 1", "min_num_matches": ">= 1",
              "sift_peak_threshold": "> 0", "min_num_points": ">= 0", "depth_points": ">= 0",
              "num_threads": "-1 | >= 1", "seed": ">= 0"}

    def __post_init__(self) -> None:
        if not 0.0 < self.min_registered_fraction <= 1.0:
            raise ValueError(f"min_registered_fraction must be in (0, 1], got {self.min_registered_fraction}")
        for name in ("sequential_overlap", "max_num_features", "max_image_size", "init_min_num_inliers",
                     "min_num_matches"):  # fmt: skip
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.sift_peak_threshold <= 0:
            raise ValueError(f"sift_peak_threshold must be > 0, got {self.sift_peak_threshold}")
        if self.min_num_points < 0 or self.depth_points < 0:
            raise ValueError("min_num_points and depth_points must be >= 0")
        if self.num_threads == 0 or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or >= 1, got {self.num_threads}")


def params_from(values: dict | None) -> PosesParams:
    """Parse a raw parameter mapping (config / ``--params``) into :class:`PosesParams`."""
    return from_mapping(PosesParams, values, "poses params")


# ----------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------


def run_poses(scene: Scene, out_dir: Path, params: dict) -> None:
    """The ``poses`` step: write sparse/0, cameras.json, points3D.ply and sfm.json into ``out_dir``."""
    from .threads import resolve_threads

    p = params_from(params)
    p = dataclasses.replace(p, num_threads=resolve_threads(p.num_threads))  # -1 = all of `trace3d --threads`
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if p.mode == "dataset":
        report = _run_dataset(scene, out_dir, p)
    else:
        report = _run_colmap(scene, out_dir, p)
    report["params"] = to_dict(p)
    write_json(out_dir / "sfm.json", report)
    log.info("poses: wrote %s", out_dir)


def scene_has_reference_poses(scene: Scene) -> bool:
    """Whether the scene's cameras.json poses are real (ground truth or the data set's own).

    An importer that does not know the poses writes identity poses and/or ``"poses": "unknown"``
    in meta.json; both are recognised.  Poses whose centres all coincide cannot anchor a Sim(3).
    """
    if str(scene.meta.get("poses", "")).lower() in ("unknown", "none", "identity"):
        return False
    centres = np.stack([c.center for c in scene.cameras])
    return len(centres) >= 3 and float(np.ptp(centres, axis=0).max()) > 1e-9


def scene_intrinsics_are_guessed(scene: Scene) -> bool:
    """Whether the scene's intrinsics are an importer's guess (``trace3d scene images``: meta.json
    ``intrinsics`` is ``guess``, ``exif_35mm``, ``exif_focal_plane`` or ``mixed``).

    COLMAP then starts from them but refines the focal length even when ``known_intrinsics`` (the
    principal point stays at the image centre unless ``refine_intrinsics``); only a plain ``guess``
    is not installed as a focal-length prior.
    """
    return str(scene.meta.get("intrinsics", "")) in ("guess", "exif_35mm", "exif_focal_plane", "mixed")


def camera_diameter(centres: np.ndarray) -> float:
    """Largest pairwise distance between camera centres [L, 3] (the scene extent used for errors)."""
    diff = centres[:, None, :] - centres[None, :, :]
    return float(np.sqrt((diff**2).sum(-1)).max())


# ----------------------------------------------------------------------------------------------
# dataset mode
# ----------------------------------------------------------------------------------------------


def _run_dataset(scene: Scene, out_dir: Path, p: PosesParams) -> dict:
    if not scene_has_reference_poses(scene):
        raise ConfigError(
            f"{scene.root / 'cameras.json'}: poses mode 'dataset' needs the scene's own poses, but they are "
            "unknown (identity poses or meta.json 'poses': 'unknown', as for `trace3d scene images`); "
            "use mode 'colmap'."
        )
    cameras = [dataclasses.replace(c) for c in scene.cameras]
    for cam in cameras:
        _check_pinhole(cam, str(scene.root / "cameras.json"))
    write_cameras(out_dir, cameras)
    source = p.dataset_points
    if source == "auto":
        source = "depth" if scene.has_depth else "triangulate"
    xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    report: dict = {"mode": "dataset", "images_registered": len(cameras), "images_total": len(scene.cameras),
                    "missing": [], "frame": "scene", "points_source": source}  # fmt: skip
    if source == "depth":
        if not scene.has_depth:
            raise ConfigError(f"{scene.root}: dataset_points is 'depth' but the scene has no depth/ folder.")
        if p.depth_points > 0:
            xyz, rgb = points_from_depth(scene, p.depth_points, p.seed)
        write_colmap_model(out_dir / "sparse" / "0", cameras, xyz, rgb)
        reason = "the depth maps have no valid pixel" if p.depth_points else "depth_points is 0"
        note = f"{len(xyz)} points back-projected from the scene's depth maps" if len(xyz) else reason
    elif source == "triangulate":
        rec, stats = _triangulate_known_poses(scene, p)
        report.update(stats)
        point_ids = sorted(rec.points3D)
        xyz = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
        (out_dir / "sparse" / "0").mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(out_dir / "sparse" / "0"))
        note = (f"{len(xyz)} points triangulated from SIFT matches with the scene's poses" if len(xyz)
                else "triangulation with the scene's poses found no points (too few verified matches)")
    else:
        write_colmap_model(out_dir / "sparse" / "0", cameras, xyz, rgb)
        note = "dataset_points is 'none'"
    if len(xyz):
        write_points_ply(out_dir / "points3D.ply", xyz, rgb)
    else:
        note = (f"no points3D.ply was written: {note}; the trainer must initialise the Gaussians another way "
                "(depth or random in the scene bounds)")
        log.warning("poses (dataset): %s", note)
    log.info("poses (dataset): %d cameras copied; %s", len(cameras), note)
    report.update({"num_points": int(len(xyz)), "points_file": "points3D.ply" if len(xyz) else None, "note": note})
    return report


def _triangulate_known_poses(scene: Scene, p: PosesParams):
    """Triangulate SIFT matches with the scene's own cameras (poses and intrinsics fixed).

    Returns the pycolmap Reconstruction (cameras, frames, images, points with tracks) and statistics.
    """
    import pycolmap

    _configure_colmap_log(p.colmap_log_level)
    pycolmap.set_random_seed(p.seed)
    single = _decide_single_camera(scene, p.single_camera, True)
    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="trace3d-tri-") as work:
        database = Path(work) / "database.db"
        num_keypoints, num_verified_pairs = _extract_and_match(scene, p, database, single, True, timings)
        t0 = time.perf_counter()
        with pycolmap.Database.open(str(database)) as db:
            db_cameras, rigs = db.read_all_cameras(), db.read_all_rigs()
            frames, images = db.read_all_frames(), db.read_all_images()
        rec = pycolmap.Reconstruction()
        for camera in db_cameras:  # _prepare_database installed the scene's K
            rec.add_camera(camera)
        for rig in rigs:
            rec.add_rig(rig)
        image_by_id = {image.image_id: image for image in images}
        for frame in frames:
            data_ids = list(frame.data_ids)
            if len(data_ids) != 1:
                raise Trace3DError(f"{scene.root}: pycolmap made a frame with {len(data_ids)} images; expected 1.")
            image = image_by_id[data_ids[0].id]
            frame.rig_from_world = pycolmap.Rigid3d(scene.camera(image.name[: -len(".png")]).world_to_camera[:3, :4])
            rec.add_frame(frame)
            image.frame_id = frame.frame_id
            rec.add_image(image)
        for frame in frames:
            rec.register_frame(frame.frame_id)
        log.info("poses (dataset): triangulating %d verified image pairs with the scene's poses ...",
                 num_verified_pairs)
        out = Path(work) / "triangulated"
        out.mkdir()
        options = _mapping_options(p, len(scene.cameras))
        if num_verified_pairs == 0:  # COLMAP refuses to triangulate without one verified pair
            log.warning("poses (dataset): no verified image pair in %s; no points to triangulate", scene.root)
        else:
            try:
                rec = pycolmap.triangulate_points(
                    rec, str(database), str(scene.root / "images"), str(out), clear_points=True, options=options,
                    refine_intrinsics=False,
                )  # fmt: skip
            except ValueError as exc:  # a failed COLMAP check: the points are optional, the poses are the scene's
                log.warning("poses (dataset): COLMAP triangulation with the scene's poses failed (%s); "
                            "continuing without points", str(exc).strip().splitlines()[-1])
                rec = pycolmap.Reconstruction(rec)
                for pid in list(rec.points3D):
                    rec.delete_point3D(pid)
        timings["triangulate_s"] = time.perf_counter() - t0
    stats = {
        "num_verified_pairs": num_verified_pairs,
        "mean_keypoints_per_image": num_keypoints / len(scene.cameras),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "single_camera": single,
        "timings": {k: round(v, 3) for k, v in timings.items()},
    }
    return rec, stats


def points_from_depth(scene: Scene, total: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a random subsample of valid depth pixels of every frame.

    Returns xyz [P, 3] in the scene frame and rgb [P, 3] uint8, P <= total (about total / L per frame).
    """
    rng = np.random.default_rng(seed)
    per_frame = max(1, total // len(scene.cameras))
    all_xyz, all_rgb = [], []
    for cam in tqdm(scene.cameras, desc="depth points", unit="frame", leave=False):
        depth = scene.depth(cam.name)
        valid = np.flatnonzero(depth.ravel() > 0)
        if len(valid) == 0:
            continue
        pick = rng.choice(valid, size=min(per_frame, len(valid)), replace=False)
        v, u = np.divmod(pick, cam.width)
        all_xyz.append(backproject_pixels(cam, v, u, depth.ravel()[pick]))
        all_rgb.append(scene.image(cam.name).reshape(-1, 3)[pick])
    if not all_xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    return np.concatenate(all_xyz), np.concatenate(all_rgb)


def write_colmap_model(path: Path, cameras: list[Camera], xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write known cameras (and track-less points [P, 3] / colours [P, 3]) as a COLMAP binary model."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, cam in enumerate(cameras, start=1):
        _check_pinhole(cam, "cameras.json")
        rec.add_camera(
            pycolmap.Camera(
                camera_id=i, model="PINHOLE", width=cam.width, height=cam.height,
                params=[cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]],
            )
        )  # fmt: skip
        rig = pycolmap.Rig(rig_id=i)
        rig.add_ref_sensor(rec.camera(i).sensor_id)
        rec.add_rig(rig)
        image = pycolmap.Image(name=f"{cam.name}.png", camera_id=i, image_id=i)
        frame = pycolmap.Frame(frame_id=i, rig_id=i)
        frame.add_data_id(image.data_id)
        frame.rig_from_world = pycolmap.Rigid3d(cam.world_to_camera[:3, :4])
        rec.add_frame(frame)
        image.frame_id = i
        rec.add_image(image)
        rec.register_frame(i)
    for point, colour in zip(xyz, rgb):
        rec.add_point3D(np.asarray(point, dtype=np.float64), pycolmap.Track(), np.asarray(colour, dtype=np.uint8))
    path.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(path))


def _check_pinhole(cam: Camera, where: str) -> None:
    if abs(cam.K[0, 1]) > 1e-9 or np.abs(cam.K[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-9:
        raise Trace3DError(
            f"{where}: frame {cam.name!r} has a K with skew or a non-standard last row, "
            "which a PINHOLE camera cannot represent."
        )


# ----------------------------------------------------------------------------------------------
# colmap mode
# ----------------------------------------------------------------------------------------------


def _configure_colmap_log(level: str) -> None:
    import pycolmap

    pycolmap.logging.logtostderr = True
    pycolmap.logging.minloglevel = {"info": 0, "warning": 1, "error": 2}[level]


def _decide_single_camera(scene: Scene, single_camera: bool | None, known_intrinsics: bool) -> bool:
    sizes = {(c.width, c.height) for c in scene.cameras}
    same_k = all(np.allclose(c.K, scene.cameras[0].K, rtol=0, atol=1e-6) for c in scene.cameras)
    if single_camera is None:
        return len(sizes) == 1 and (same_k or not known_intrinsics)
    if single_camera and len(sizes) > 1:
        raise ConfigError(
            f"{scene.root / 'cameras.json'}: single_camera is true but the frames have {len(sizes)} "
            f"different image sizes {sorted(sizes)}."
        )
    if single_camera and known_intrinsics and not same_k:
        raise ConfigError(
            f"{scene.root / 'cameras.json'}: single_camera and known_intrinsics are true but the frames' "
            "K differ; set single_camera to false or known_intrinsics to false."
        )
    return bool(single_camera)


def _extract_and_match(scene: Scene, p: PosesParams, database: Path, single: bool, known_intrinsics: bool,
                       timings: dict) -> tuple[int, int]:
    """SIFT extraction and matching of every scene frame into ``database``.

    Returns the total number of keypoints and the number of image pairs that passed geometric
    verification; adds ``extract_s`` and ``match_s`` to ``timings``.
    """
    import pycolmap

    image_dir = scene.root / "images"
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = p.num_threads
    extraction.max_image_size = p.max_image_size
    extraction.sift.max_num_features = p.max_num_features
    extraction.sift.peak_threshold = p.sift_peak_threshold
    extraction.sift.domain_size_pooling = p.domain_size_pooling
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    log.info("poses: extracting SIFT features of %d frames ...", len(scene.cameras))
    pycolmap.extract_features(
        str(database), str(image_dir), image_names=[f"{c.name}.png" for c in scene.cameras],
        camera_mode=pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE,
        camera_model="PINHOLE", reader_options=reader, extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )  # fmt: skip
    num_keypoints = _prepare_database(database, scene, known_intrinsics,
                                      prior=scene.meta.get("intrinsics") not in ("guess", "mixed"))
    timings["extract_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = p.num_threads
    matching.guided_matching = p.guided_matching
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = p.min_num_matches
    verification.ransac.random_seed = p.seed
    log.info("poses: %s matching ...", p.matcher)
    if p.matcher == "exhaustive":
        pycolmap.match_exhaustive(
            str(database), matching_options=matching, verification_options=verification,
            device=pycolmap.Device.cpu,
        )  # fmt: skip
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = p.sequential_overlap
        pairing.quadratic_overlap = p.sequential_quadratic_overlap
        pairing.num_threads = p.num_threads
        pycolmap.match_sequential(
            str(database), matching_options=matching, pairing_options=pairing,
            verification_options=verification, device=pycolmap.Device.cpu,
        )  # fmt: skip
    num_verified_pairs = _count_verified_pairs(database, p.min_num_matches)
    timings["match_s"] = time.perf_counter() - t0
    return num_keypoints, num_verified_pairs


def _run_colmap(scene: Scene, out_dir: Path, p: PosesParams) -> dict:
    import pycolmap

    _configure_colmap_log(p.colmap_log_level)
    pycolmap.set_random_seed(p.seed)
    names = [c.name for c in scene.cameras]
    single = _decide_single_camera(scene, p.single_camera, p.known_intrinsics)
    guessed = p.known_intrinsics and scene_intrinsics_are_guessed(scene)
    if p.known_intrinsics:
        for cam in scene.cameras:
            _check_pinhole(cam, str(scene.root / "cameras.json"))
    timings: dict[str, float] = {}
    log.info(
        "poses (colmap): %d frames, %s matching, %s camera, intrinsics %s",
        len(names), p.matcher, "one shared" if single else "one per image",
        ("known, refined" if p.refine_intrinsics else "guessed, focal refined" if guessed else "known, fixed")
        if p.known_intrinsics else "estimated",
    )  # fmt: skip

    with tempfile.TemporaryDirectory(prefix="trace3d-sfm-") as work:
        database = Path(work) / "database.db"
        num_keypoints, num_verified_pairs = _extract_and_match(scene, p, database, single, p.known_intrinsics, timings)
        t0 = time.perf_counter()
        mapping = _mapping_options(p, len(names), refine_focal=guessed)
        log.info("poses (colmap): incremental mapping (%d verified image pairs) ...", num_verified_pairs)
        models = pycolmap.incremental_mapping(
            str(database), str(scene.root / "images"), str(Path(work) / "sparse"), mapping
        )
        timings["map_s"] = time.perf_counter() - t0

    where = f"{scene.root}"
    if not models:
        raise Trace3DError(
            f"{where}: structure-from-motion built no model, so 0 of {len(names)} frames registered "
            f"({num_verified_pairs} image pairs passed geometric verification; the images may not overlap "
            f"or may lack texture); missing: {_name_list(names)}."
        )
    model_sizes = sorted((m.num_reg_images() for m in models.values()), reverse=True)
    rec = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))
    registered = {img.name[: -len(".png")]: img for img in rec.images.values() if img.has_pose}
    missing = [n for n in names if n not in registered]
    fraction = len(registered) / len(names)
    if missing and fraction < p.min_registered_fraction:
        several = f" (largest of {len(models)} models of sizes {model_sizes})" if len(models) > 1 else ""
        raise Trace3DError(
            f"{where}: only {len(registered)} of {len(names)} frames registered{several}, below "
            f"min_registered_fraction {p.min_registered_fraction:g}; missing: {_name_list(missing)}."
        )
    if rec.num_points3D() < max(p.min_num_points, 1):
        raise Trace3DError(
            f"{where}: degenerate reconstruction with {rec.num_points3D()} triangulated points "
            f"(fewer than min_num_points {p.min_num_points})."
        )
    if missing:
        log.warning("poses (colmap): %d frame(s) did not register: %s", len(missing), _name_list(missing))

    report: dict = {
        "mode": "colmap",
        "images_registered": len(registered),
        "images_total": len(names),
        "registered_fraction": fraction,
        "missing": missing,
        "num_models": len(models),
        "model_sizes": model_sizes,
        "num_verified_pairs": num_verified_pairs,
        "mean_keypoints_per_image": num_keypoints / len(names),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()),
        "num_points": int(rec.num_points3D()),
        "single_camera": single,
        "timings": {k: round(v, 3) for k, v in timings.items()},
    }

    align = scene_has_reference_poses(scene) if p.align_to_scene is None else p.align_to_scene
    if align and not scene_has_reference_poses(scene):
        raise ConfigError(f"{scene.root / 'cameras.json'}: align_to_scene is true but the scene has no usable poses.")
    filled: list[str] = []
    if align:
        report["alignment"] = _align_to_scene(rec, scene, registered, p.align_method)
        report["frame"] = "scene (SfM mapped by the Sim(3) in 'alignment')"
    else:
        report["frame"] = "colmap"

    cameras: list[Camera] = []
    for cam in scene.cameras:
        image = registered.get(cam.name)
        if image is None:
            if align:
                cameras.append(dataclasses.replace(cam))
                filled.append(cam.name)
            continue
        colmap_cam = image.camera
        fx, fy, cx, cy = (float(v) for v in colmap_cam.params)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        cameras.append(Camera(cam.name, cam.split, cam.width, cam.height, K, w2c))
    report["filled_from_scene"] = filled
    if guessed:
        report["intrinsics"] = {
            "initial": scene.meta.get("intrinsics"), "refined": "focal length",
            "focal_initial_px_mean": float(np.mean([scene.camera(c.name).K[0, 0] for c in cameras])),
            "focal_estimated_px_mean": float(np.mean([c.K[0, 0] for c in cameras])),
        }
    elif p.known_intrinsics is False or p.refine_intrinsics:
        report["intrinsics"] = _intrinsics_report([c for c in cameras if c.name in registered], scene)

    model_dir = out_dir / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(model_dir))
    write_cameras(out_dir, cameras)
    point_ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    write_points_ply(out_dir / "points3D.ply", xyz, rgb)
    log.info(
        "poses (colmap): %d/%d frames registered, %d points, reprojection error %.3f px, track length %.2f%s",
        len(registered), len(names), len(xyz), report["mean_reprojection_error_px"], report["mean_track_length"],
        (f", camera-centre error {report['alignment']['center_error_rel_mean']:.2%} mean / "
         f"{report['alignment']['center_error_rel_max']:.2%} max of the camera diameter") if align else "",
    )  # fmt: skip
    return report


def _name_list(names: list[str], limit: int = 30) -> str:
    if len(names) <= limit:
        return ", ".join(names)
    return ", ".join(names[:limit]) + f" and {len(names) - limit} more"


def _prepare_database(database: Path, scene: Scene, known_intrinsics: bool, prior: bool = True) -> int:
    """Install the scene's intrinsics as the cameras' (when known; flagged as a focal-length prior
    when ``prior``); return the total keypoint count."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        images = db.read_all_images()
        found = {img.name for img in images}
        absent = [c.name for c in scene.cameras if f"{c.name}.png" not in found]
        if absent:
            raise Trace3DError(
                f"{scene.root / 'images'}: pycolmap could not read the image(s) {_name_list(absent)}."
            )
        total = sum(int(db.num_keypoints_for_image(img.image_id)) for img in images)
        if known_intrinsics:
            by_name = {f"{c.name}.png": c for c in scene.cameras}
            for img in images:
                cam = by_name[img.name]
                colmap_cam = db.read_camera(img.camera_id)
                colmap_cam.params = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
                colmap_cam.has_prior_focal_length = prior
                db.update_camera(colmap_cam)
    return total


def _count_verified_pairs(database: Path, min_inliers: int) -> int:
    """Image pairs whose two-view geometry has at least ``min_inliers`` inlier matches."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        _, geometries = db.read_two_view_geometries()
    return sum(1 for g in geometries if len(g.inlier_matches) >= min_inliers)


def _mapping_options(p: PosesParams, num_images: int, refine_focal: bool = False):
    """COLMAP's incremental mapping options; ``refine_focal`` also refines known (guessed) focal lengths."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = p.num_threads
    opts.random_seed = p.seed
    opts.min_num_matches = p.min_num_matches
    opts.min_model_size = min(opts.min_model_size, max(2, num_images // 2))
    opts.extract_colors = True
    opts.multiple_models = True
    refine_focal = refine_focal or p.refine_intrinsics or not p.known_intrinsics
    opts.ba_refine_focal_length = refine_focal
    opts.ba_refine_principal_point = p.refine_intrinsics and p.known_intrinsics
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_extra_params = False
    opts.mapper.init_min_num_inliers = p.init_min_num_inliers
    opts.mapper.random_seed = p.seed
    opts.mapper.num_threads = p.num_threads
    opts.triangulation.random_seed = p.seed
    return opts


def _align_to_scene(rec, scene: Scene, registered: dict, method: str) -> dict:
    """Map ``rec`` (in place) by the Sim(3) aligning its cameras to the scene's; return the errors.

    ``method`` is :func:`trace3d.pointcloud.align_cameras`'s.  The errors after the alignment that
    uses the camera centres alone (Umeyama) are reported too, under ``centers_only``.
    """
    import pycolmap

    names = [c.name for c in scene.cameras if c.name in registered]
    if len(names) < 3:
        raise Trace3DError(
            f"{scene.root}: only {len(names)} frames registered, too few to align the reconstruction "
            "to the scene's poses (need 3)."
        )

    def sfm_poses() -> np.ndarray:
        out = np.tile(np.eye(4), (len(names), 1, 1))
        out[:, :3, :4] = [registered[n].cam_from_world().matrix() for n in names]
        return out

    reference = np.stack([scene.camera(n).world_to_camera for n in names])
    reference_centres = np.stack([scene.camera(n).center for n in names])
    diameter = camera_diameter(np.stack([c.center for c in scene.cameras]))

    def errors(poses: np.ndarray) -> dict:
        centres = -np.einsum("lji,lj->li", poses[:, :3, :3], poses[:, :3, 3])
        dist = np.linalg.norm(centres - reference_centres, axis=1)
        angles = np.array([rotation_angle_deg(a[:3, :3], b[:3, :3]) for a, b in zip(poses, reference)])
        suspect = [n for n, d, a in zip(names, dist, angles)
                   if d > SUSPECT_CENTER_REL * diameter or a > SUSPECT_ROTATION_DEG]
        return {
            "suspect_frames": suspect,
            "center_error_mean": float(dist.mean()),
            "center_error_max": float(dist.max()),
            "center_error_rel_mean": float(dist.mean() / diameter),
            "center_error_rel_max": float(dist.max() / diameter),
            "center_error_worst_frame": names[int(np.argmax(dist))],
            "rotation_error_deg_mean": float(angles.mean()),
            "rotation_error_deg_max": float(angles.max()),
        }

    before = sfm_poses()
    by_centres = align_cameras(before, reference, "centers")
    centres_only = errors(np.stack([by_centres.transform_world_to_camera(w) for w in before]))
    sim = align_cameras(before, reference, method)
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.rotation), sim.translation))
    after = errors(sfm_poses())
    if after["suspect_frames"]:
        log.warning(
            "poses (colmap): %d frame(s) are off the scene's poses by more than %.0f %% of the camera diameter "
            "or %.0f degrees after alignment: %s", len(after["suspect_frames"]), 100 * SUSPECT_CENTER_REL,
            SUSPECT_ROTATION_DEG, _name_list(after["suspect_frames"]),
        )  # fmt: skip
    return {
        "applied": True,
        "method": method,
        "sim3_scene_from_colmap": sim.to_json(),
        "extent": "diameter of the scene's camera centres (largest pairwise distance)",
        "extent_value": diameter,
        **after,
        "centers_only": centres_only,
    }


def _intrinsics_report(cameras: list[Camera], scene: Scene) -> dict:
    """Relative focal-length error of the estimated intrinsics against the scene's K."""
    rel = []
    for cam in cameras:
        ref = scene.camera(cam.name).K
        rel.append(abs(cam.K[0, 0] - ref[0, 0]) / ref[0, 0])
        rel.append(abs(cam.K[1, 1] - ref[1, 1]) / ref[1, 1])
    return {"focal_error_rel_mean": float(np.mean(rel)), "focal_error_rel_max": float(np.max(rel))}
