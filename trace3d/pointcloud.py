"""Coloured point clouds (PLY read/write) and similarity (Sim(3)) alignment.

``points3D.ply`` is the contract between the ``poses`` step and the Gaussian trainer: one vertex
element with ``x y z`` (float32) and ``red green blue`` (uchar), binary little-endian, so that
common viewers (MeshLab, CloudCompare, Blender) open it.  :func:`read_points_ply` also reads the
PLYs that COLMAP and other tools write (ASCII or binary, extra properties ignored).

A Sim(3) maps ``x -> scale * rotation @ x + translation``; :func:`umeyama` estimates the one that
best maps a set of points onto another in the least-squares sense (Umeyama 1991), which is how SfM
camera centres are brought into the frame of ground-truth poses.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .errors import Trace3DError
from .io import atomic_file

# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> None:
    """Write a coloured point cloud as a binary little-endian PLY, atomically.

    Args:
        path: output file.
        xyz: [P, 3] positions (stored as float32).
        rgb: [P, 3] uint8 colours; grey when None.  P may be 0 (a valid, empty cloud).
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be [P, 3], got {xyz.shape}")
    if rgb is None:
        rgb = np.full(xyz.shape, 128, dtype=np.uint8)
    rgb = np.asarray(rgb)
    if rgb.shape != xyz.shape:
        raise ValueError(f"rgb must be [P, 3] like xyz {xyz.shape}, got {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8, got {rgb.dtype}")
    if not np.isfinite(xyz).all():
        raise ValueError("xyz contains non-finite values")
    vertex = np.empty(
        len(xyz),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by trace3d\n"
        f"element vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with atomic_file(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(vertex.tobytes())


def _parse_ply_header(fh, path: Path) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], int]:
    """(format, elements [(name, count, [(property, numpy type)])], header byte length)."""
    first = fh.readline()
    if first.strip() != b"ply":
        raise Trace3DError(f"{path}: not a PLY file (the first line is not 'ply').")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        line = fh.readline()
        if not line:
            raise Trace3DError(f"{path}: PLY header has no 'end_header' line.")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append((words[1], int(words[2]), []))
            except ValueError as exc:
                raise Trace3DError(f"{path}: PLY element line {line!r} has a non-integer count.") from exc
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise Trace3DError(f"{path}: PLY header has an unsupported property line {line!r}.")
        else:
            raise Trace3DError(f"{path}: PLY header has an unexpected line {line!r}.")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise Trace3DError(f"{path}: PLY format {fmt!r} is not ascii or binary.")
    return fmt, elements, fh.tell()


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the vertices of a PLY point cloud.

    Returns:
        xyz [P, 3] float64 and rgb [P, 3] uint8 (grey 128 when the file has no colours).
    """
    path = Path(path)
    if not path.is_file():
        raise Trace3DError(f"{path}: point cloud file does not exist.")
    with open(path, "rb") as fh:
        fmt, elements, _ = _parse_ply_header(fh, path)
        if not elements or elements[0][0] != "vertex":
            raise Trace3DError(f"{path}: PLY file has no leading 'vertex' element.")
        _, count, props = elements[0]
        names = [p for p, _ in props]
        if any(t == "list" for _, t in props):
            raise Trace3DError(f"{path}: PLY vertex element has list properties, which point clouds do not use.")
        missing = [c for c in ("x", "y", "z") if c not in names]
        if missing:
            raise Trace3DError(f"{path}: PLY vertex element lacks the coordinate(s) {missing}.")
        if fmt == "ascii":
            rows = [fh.readline() for _ in range(count)]
            try:
                table = np.array([r.split() for r in rows], dtype=np.float64).reshape(count, len(props))
            except ValueError as exc:
                raise Trace3DError(f"{path}: PLY ascii vertex data is truncated or not numeric.") from exc
            column = {n: table[:, i] for i, n in enumerate(names)}
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            dtype = np.dtype([(n, order + t) for n, t in props])
            raw = fh.read(dtype.itemsize * count)
            if len(raw) < dtype.itemsize * count:
                raise Trace3DError(
                    f"{path}: PLY binary data is truncated ({len(raw)} of {dtype.itemsize * count} bytes)."
                )
            data = np.frombuffer(raw, dtype=dtype, count=count)
            column = {n: data[n] for n in names}
    xyz = np.stack([column["x"], column["y"], column["z"]], axis=1).astype(np.float64).reshape(count, 3)
    if all(c in column for c in ("red", "green", "blue")):
        rgb = np.stack([column["red"], column["green"], column["blue"]], axis=1)
        if rgb.dtype.kind == "f" and rgb.size and rgb.max() <= 1.0:
            rgb = rgb * 255.0
        rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8).reshape(count, 3)
    else:
        rgb = np.full((count, 3), 128, dtype=np.uint8)
    if not np.isfinite(xyz).all():
        raise Trace3DError(f"{path}: PLY vertex positions contain non-finite values.")
    return xyz, rgb


# ----------------------------------------------------------------------------------------------
# Sim(3)
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Sim3:
    """A similarity transform ``x -> scale * rotation @ x + translation``.

    Attributes:
        scale: positive scalar.
        rotation: [3, 3] proper rotation.
        translation: [3].
    """

    scale: float = 1.0
    rotation: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.scale = float(self.scale)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        self.translation = np.asarray(self.translation, dtype=np.float64).reshape(3)

    @property
    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points [P, 3] -> [P, 3]."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def inverse(self) -> "Sim3":
        rot_t = self.rotation.T
        return Sim3(1.0 / self.scale, rot_t, -rot_t @ self.translation / self.scale)

    def transform_world_to_camera(self, world_to_camera: np.ndarray) -> np.ndarray:
        """Re-express a camera pose [4, 4] when the world is mapped by this similarity.

        The camera sees the same image; its centre moves to ``apply(center)`` and its coordinates
        are scaled with the world, so depths grow by ``scale``.
        """
        w2c = np.asarray(world_to_camera, dtype=np.float64)
        out = np.eye(4)
        out[:3, :3] = w2c[:3, :3] @ self.rotation.T
        out[:3, 3] = self.scale * w2c[:3, 3] - out[:3, :3] @ self.translation
        return out

    def to_json(self) -> dict:
        return {
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
        }


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares similarity that maps ``source`` onto ``target`` (Umeyama 1991).

    Minimises ``sum_i |target_i - (s R source_i + t)|^2`` over proper rotations R (det +1), s > 0, t.

    Args:
        source: [P, 3] points, P >= 3 and not all collinear.
        target: [P, 3] corresponding points.
        with_scale: estimate the scale (else s = 1, a rigid fit).
    Raises:
        Trace3DError: when the correspondences are too few or degenerate.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"source and target must both be [P, 3], got {source.shape} and {target.shape}")
    if len(source) < 3:
        raise Trace3DError(f"Sim(3) alignment needs at least 3 point pairs, got {len(source)}.")
    mu_s = source.mean(axis=0)
    mu_t = target.mean(axis=0)
    src = source - mu_s
    tgt = target - mu_t
    var_s = (src**2).sum() / len(source)
    if var_s <= 1e-18:
        raise Trace3DError("Sim(3) alignment is degenerate: all source points coincide.")
    cov = tgt.T @ src / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    if d[1] <= 1e-12 * max(d[0], 1e-300):
        raise Trace3DError("Sim(3) alignment is degenerate: the source points are collinear.")
    scale = float(np.trace(np.diag(d) @ sign) / var_s) if with_scale else 1.0
    translation = mu_t - scale * rotation @ mu_s
    return Sim3(scale, rotation, translation)


def _project_to_rotation(matrix: np.ndarray) -> np.ndarray:
    """Nearest proper rotation [3, 3] to ``matrix`` [3, 3] in the Frobenius norm."""
    u, _, vt = np.linalg.svd(matrix)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ sign @ vt


def align_cameras(
    source_world_to_camera: np.ndarray,
    target_world_to_camera: np.ndarray,
    method: str = "poses",
) -> Sim3:
    """The similarity that maps the world of the source cameras onto the world of the target cameras.

    Args:
        source_world_to_camera: [L, 4, 4] poses of L cameras (e.g. from SfM).
        target_world_to_camera: [L, 4, 4] poses of the same cameras in the reference frame.
        method: ``"centers"``: Umeyama on the camera centres alone.  ``"poses"``: the rotation is
            the chordal mean of the per-camera rotations that bring each source orientation onto
            its target orientation (:meth:`Sim3.transform_world_to_camera` maps ``R_s`` to
            ``R_s @ R.T``), then scale and translation are the least-squares fit of the centres
            under that rotation.  Centres alone fix the rotation poorly when they span a small
            or nearly planar region (a short camera loop): the error is about centre noise /
            loop radius; the orientations fix it directly.
    Raises:
        Trace3DError: too few cameras or degenerate centres.
    """
    src = np.asarray(source_world_to_camera, dtype=np.float64)
    tgt = np.asarray(target_world_to_camera, dtype=np.float64)
    if src.shape != tgt.shape or src.ndim != 3 or src.shape[1:] != (4, 4):
        raise ValueError(f"camera poses must both be [L, 4, 4], got {src.shape} and {tgt.shape}")
    src_rot, tgt_rot = src[:, :3, :3], tgt[:, :3, :3]
    src_centres = -np.einsum("lji,lj->li", src_rot, src[:, :3, 3])
    tgt_centres = -np.einsum("lji,lj->li", tgt_rot, tgt[:, :3, 3])
    if method == "centers":
        return umeyama(src_centres, tgt_centres)
    if method != "poses":
        raise ValueError(f"unknown alignment method {method!r}")
    if len(src) < 2:
        raise Trace3DError(f"camera alignment needs at least 2 cameras, got {len(src)}.")
    rotation = _project_to_rotation(np.einsum("lji,ljk->ik", tgt_rot, src_rot))
    src_c = src_centres - src_centres.mean(axis=0)
    tgt_c = tgt_centres - tgt_centres.mean(axis=0)
    var = (src_c**2).sum()
    if var <= 1e-18:
        raise Trace3DError("camera alignment is degenerate: all source camera centres coincide.")
    scale = float((tgt_c * (src_c @ rotation.T)).sum() / var)
    if scale <= 0:
        raise Trace3DError("camera alignment is degenerate: the centres fit only with a negative scale.")
    translation = tgt_centres.mean(axis=0) - scale * rotation @ src_centres.mean(axis=0)
    return Sim3(scale, rotation, translation)


def rotation_angle_deg(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Angle in degrees of the relative rotation ``rotation_a @ rotation_b.T`` ([3, 3] each)."""
    rel = np.asarray(rotation_a) @ np.asarray(rotation_b).T
    cos = np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))
