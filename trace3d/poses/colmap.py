"""The ``poses`` step's COLMAP side (:mod:`trace3d.poses`): the colmap mode (SIFT extraction,
matching, incremental mapping, the reconstruction's checks and report), the dataset mode's
triangulation with known poses, and COLMAP models written from known cameras."""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError, Trace3DError
from ..pointcloud import write_points_ply
from ..scene import Camera, Scene, write_cameras
from .align import _align_to_scene, _name_list, scene_has_reference_poses

if TYPE_CHECKING:
    from .params import PosesParams

log = logging.getLogger(__name__)


def scene_intrinsics_are_guessed(scene: Scene) -> bool:
    """Whether the scene's intrinsics are an importer's guess (``trace3d scene images``: meta.json
    ``intrinsics`` is ``guess``, ``exif_35mm``, ``exif_focal_plane`` or ``mixed``).

    COLMAP then starts from them but refines the focal length even when ``known_intrinsics`` (the
    principal point stays at the image centre unless ``refine_intrinsics``); only a plain ``guess``
    is not installed as a focal-length prior.
    """
    return str(scene.meta.get("intrinsics", "")) in ("guess", "exif_35mm", "exif_focal_plane", "mixed")


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


def _intrinsics_report(cameras: list[Camera], scene: Scene) -> dict:
    """Relative focal-length error of the estimated intrinsics against the scene's K."""
    rel = []
    for cam in cameras:
        ref = scene.camera(cam.name).K
        rel.append(abs(cam.K[0, 0] - ref[0, 0]) / ref[0, 0])
        rel.append(abs(cam.K[1, 1] - ref[1, 1]) / ref[1, 1])
    return {"focal_error_rel_mean": float(np.mean(rel)), "focal_error_rel_max": float(np.max(rel))}
