"""The ``poses`` stage: pycolmap structure-from-motion, or the data set's own cameras.

    params.py   :class:`PosesParams` (the step's parameters)
    step.py     :func:`run_poses` (the step) and the dataset mode
    colmap.py   the colmap mode: SIFT extraction, matching, incremental mapping; COLMAP models
    align.py    the Sim(3) into the scene's frame and the camera errors it leaves

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
