"""The 2D Gaussian container, its initialisations and PLY read/write.

A :class:`GaussianModel` holds the *raw* (optimised) parameters of N 2D Gaussian disks:

    means           [N, 3]      centres, world coordinates
    quats           [N, 4]      rotation quaternions (w, x, y, z), unnormalised
    log_scales      [N, 2]      log of the two tangent scales s_u, s_v
    opacity_logits  [N]         logit of the opacity
    sh_dc           [N, 1, 3]   degree-0 spherical-harmonic colour coefficient
    sh_rest         [N, K, 3]   higher SH coefficients, K = (degree + 1)^2 - 1

and turns them into the renderer's activated :class:`~trace3d.render.Splats` (:meth:`splats`) and
view-dependent RGB (:meth:`colors`). Colours follow the 3DGS convention ``rgb = SH(d) + 0.5``,
clamped at 0.

Initialisations (all deterministic from a seed): :func:`init_from_points` (scales from the mean
distance to the 3 nearest neighbours, random rotations or rotations that align the disk normal
with given normals), :func:`init_from_depth` (back-projects ground-truth depth maps of the train
views) and :func:`init_random` (uniform in an axis-aligned box).

PLY layout (binary little endian, float32, one ``vertex`` element), as written by the 3DGS/2DGS
reference code so that common splat viewers open it::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3K-1} opacity scale_0 scale_1 rot_0 .. rot_3

``f_rest`` is channel-major (all K red coefficients, then green, then blue), ``opacity`` is the logit,
``scale_*`` are logs and ``rot_*`` the raw quaternion (w, x, y, z). ``nx ny nz`` hold the disk normal
(the reference code writes zeros there; readers ignore it).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .errors import SceneFormatError, Trace3DError
from .geometry import quat_to_rotmat
from .io import atomic_file
from .render.sh import MAX_SH_DEGREE, SH_C0, num_sh_rest
from .threads import torch_threads

if TYPE_CHECKING:  # pragma: no cover
    from .render import Splats
    from .scene import Scene

log = logging.getLogger(__name__)


def rgb_to_sh(rgb: torch.Tensor | np.ndarray) -> torch.Tensor:
    """DC coefficient that renders ``rgb`` (in [0, 1]): ``(rgb - 0.5) / C0``."""
    return (torch.as_tensor(rgb, dtype=torch.float32) - 0.5) / SH_C0


def sh_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_sh` (no clamping)."""
    return sh_dc * SH_C0 + 0.5


def quats_aligning_z_to(normals: torch.Tensor) -> torch.Tensor:
    """[N, 3] unit normals -> [N, 4] quaternions (w, x, y, z) whose rotation maps +z onto the normal.

    The disk normal of a 2D Gaussian is the third column of its rotation, so these quaternions make
    the disks perpendicular to ``normals``. For a normal equal to -z the rotation is 180 deg about x.
    """
    n = F.normalize(normals, dim=-1)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype, device=n.device).expand_as(n)
    # q = (1 + z.n, z x n), normalised: the shortest-arc rotation.
    w = 1.0 + n[:, 2]
    axis = torch.cross(z, n, dim=-1)
    quats = torch.cat([w[:, None], axis], dim=-1)
    opposite = w < 1e-6
    if opposite.any():
        quats[opposite] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=n.dtype, device=n.device)
    return F.normalize(quats, dim=-1)


def random_quats(count: int, generator: torch.Generator) -> torch.Tensor:
    """[count, 4] uniformly distributed unit quaternions (normalised Gaussian samples)."""
    q = torch.randn(count, 4, generator=generator)
    return F.normalize(q, dim=-1)


def nearest_neighbour_scales(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Root of the mean squared distance of every point to its ``k`` nearest other points.

    Uses a k-d tree (scipy, installed with scikit-image); :func:`_nearest_neighbour_scales_reference`
    is the brute-force twin.

    Args:
        points: [P, 3].
    Returns:
        [P] distances (clamped below at 1e-7; 1.0 for a single point).
    """
    from scipy.spatial import cKDTree

    count = points.shape[0]
    if count < 2:
        return torch.ones(count, dtype=points.dtype)
    k = min(k, count - 1)
    xyz = points.detach().cpu().double().numpy()
    distances, _ = cKDTree(xyz).query(xyz, k=k + 1)  # the first neighbour is the point itself
    mean_sq = (distances[:, 1:] ** 2).mean(axis=1)
    return torch.from_numpy(np.sqrt(np.maximum(mean_sq, 1e-14))).to(points.dtype)


def _nearest_neighbour_scales_reference(points: torch.Tensor, k: int = 3,
                                        chunk_elements: int = 1 << 24) -> torch.Tensor:
    """Brute-force twin of :func:`nearest_neighbour_scales` (all pairwise distances, in chunks)."""
    count = points.shape[0]
    if count < 2:
        return torch.ones(count, dtype=points.dtype)
    k = min(k, count - 1)
    rows = max(1, chunk_elements // count)
    out = torch.empty(count, dtype=points.dtype)
    for start in range(0, count, rows):
        block = points[start : start + rows]
        d2 = torch.cdist(block.double(), points.double()).pow(2)
        d2[torch.arange(block.shape[0]), torch.arange(start, start + block.shape[0])] = math.inf
        nearest = d2.topk(k, dim=1, largest=False).values
        out[start : start + rows] = nearest.mean(dim=1).clamp_min(1e-14).sqrt().to(points.dtype)
    return out


def all_finite(tensors) -> bool:
    """Whether every value of the tensors is finite: one sum each (a NaN or an infinity makes it
    non-finite, and so does an overflowing sum), no gradient."""
    with torch.no_grad():
        sums = [t.detach().float().sum() for t in tensors]
        return not sums or bool(torch.isfinite(torch.stack(sums).sum()))


@dataclass
class GaussianModel:
    """Raw parameters of N 2D Gaussians (see the module docstring for the shapes), plus any number
    of extra per-Gaussian attributes.

    The tensors are plain tensors; :class:`trace3d.training.GaussianOptimizer` wraps them as
    optimiser parameters. The maximum SH degree is implied by ``sh_rest`` (K = (degree + 1)^2 - 1).

    ``extras`` maps a name to a tensor [N] or [N, k] (e.g. lifting features [N, 16], tracing
    statistics, the split generation of the GIT-guided refinement). Extras follow every subset,
    split, prune and copy of the model, are written to the PLY as ``extra_<name>[_<i>]`` properties
    (viewers ignore unknown properties) and read back from it.
    """

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    log_scales: torch.Tensor  # [N, 2]
    opacity_logits: torch.Tensor  # [N]
    sh_dc: torch.Tensor  # [N, 1, 3]
    sh_rest: torch.Tensor  # [N, K, 3]
    extras: dict[str, torch.Tensor] = field(default_factory=dict)

    PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 2),
            "opacity_logits": (n,),
            "sh_dc": (n, 1, 3),
        }
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"GaussianModel.{name}: expected shape {shape}, "
                                 f"got {tuple(getattr(self, name).shape)}")
        rest = self.sh_rest
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or rest.shape[1] not in (0, 3, 8, 15):
            raise ValueError(f"GaussianModel.sh_rest: expected shape ({n}, K, 3) with K in (0, 3, 8, 15), "
                             f"got {tuple(rest.shape)}")
        self.extras = dict(self.extras)
        for name, value in self.extras.items():
            check_extra(name, value, n)

    # --- basic properties ----------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """Maximum SH degree the model stores."""
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def names(self) -> tuple[str, ...]:
        """Every per-Gaussian attribute: the core parameters, then the extras (insertion order)."""
        return self.PARAM_NAMES + tuple(self.extras)

    def get(self, name: str) -> torch.Tensor:
        """The attribute ``name`` (core or extra)."""
        return self.extras[name] if name in self.extras else getattr(self, name)

    def set(self, name: str, value: torch.Tensor) -> None:
        """Replace attribute ``name`` (core or extra; a new name adds an extra)."""
        if name in self.PARAM_NAMES:
            setattr(self, name, value)
        else:
            check_extra(name, value, len(self))
            self.extras[name] = value

    def tensors(self) -> dict[str, torch.Tensor]:
        """Every attribute by name, core then extras (same objects, not copies)."""
        return {name: self.get(name) for name in self.names}

    def map(self, fn) -> "GaussianModel":
        """A new model with ``fn`` applied to every tensor, extras included."""
        core = {name: fn(getattr(self, name)) for name in self.PARAM_NAMES}
        return GaussianModel(**core, extras={name: fn(t) for name, t in self.extras.items()})

    def detached_copy(self, device: str | torch.device | None = None) -> "GaussianModel":
        """A detached clone (optionally moved), e.g. a checkpoint."""
        return self.map(lambda t: t.detach().clone().to(device if device is not None else t.device))

    def to(self, device: str | torch.device) -> "GaussianModel":
        return self.map(lambda t: t.to(device))

    @classmethod
    def concat(cls, models: Sequence["GaussianModel"]) -> "GaussianModel":
        """The Gaussians of ``models`` one after another, detached (every model must carry the same
        extras)."""
        if not models:
            raise ValueError("GaussianModel.concat: no models.")
        names = set(models[0].extras)
        if any(set(m.extras) != names for m in models):
            raise ValueError("GaussianModel.concat: the models carry different extras.")
        core = {name: torch.cat([m.get(name).detach() for m in models]) for name in cls.PARAM_NAMES}
        return cls(**core, extras={name: torch.cat([m.extras[name].detach() for m in models])
                                   for name in models[0].extras})

    def subset(self, keep: torch.Tensor) -> "GaussianModel":
        """The Gaussians selected by ``keep`` ([N] bool or index tensor), detached."""
        return self.map(lambda t: t.detach()[keep])

    def is_finite(self) -> bool:
        """Whether every floating-point attribute is finite (one sum per tensor: a NaN or an infinity
        makes it non-finite, and so does an overflowing sum)."""
        return all_finite(t for t in self.tensors().values() if t.is_floating_point())

    # --- activations ---------------------------------------------------------------------------
    # The activations run on one torch thread: torch computes the last elements of each thread's share
    # with its scalar formula, the others with its vector one, and the two can differ in the last bit,
    # so with more threads a few values would change with the thread count (the fit runs them on one).
    @property
    def scales(self) -> torch.Tensor:
        """[N, 2] positive tangent scales."""
        with torch_threads(1):
            return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """[N] opacities in (0, 1)."""
        with torch_threads(1):
            return torch.sigmoid(self.opacity_logits)

    @property
    def rotations(self) -> torch.Tensor:
        """[N, 3, 3] rotations; columns t_u, t_v and the disk normal t_w."""
        return quat_to_rotmat(self.quats)

    @property
    def normals(self) -> torch.Tensor:
        """[N, 3] disk normals (world, unoriented)."""
        return self.rotations[:, :, 2]

    def splats(self) -> "Splats":
        """The activated Gaussians for :func:`trace3d.render.render` (differentiable).  The raw
        quaternions go in as they are: the projection normalises them (inside its fused kernel on the
        CPU), so a separate normalisation here would only add two passes and an autograd node."""
        from .render import Splats

        return Splats(
            means=self.means,
            quats=self.quats,
            scales=self.scales,
            opacities=self.opacities,
        )

    def colors(self, camera_center: torch.Tensor | np.ndarray, degree: int | None = None,
               rows: torch.Tensor | None = None) -> torch.Tensor:
        """View-dependent RGB of every Gaussian seen from ``camera_center``.

        Args:
            camera_center: [3] world position of the camera.
            degree: SH degree to evaluate (default: the model's maximum).
            rows: optional [R] distinct int64 indices: only those Gaussians (gradients zero for the
                others).
        Returns:
            [N, 3] colours (or [R, 3] for ``rows``), ``SH + 0.5`` clamped at 0 (the 3DGS convention).
        """
        degree = self.sh_degree if degree is None else min(int(degree), self.sh_degree)
        if degree == 0:
            dc = self.sh_dc[:, 0] if rows is None else self.sh_dc[rows, 0]
            return (SH_C0 * dc + 0.5).clamp_min(0.0)
        from .render.kernels.glue import sh_colors

        center = torch.as_tensor(np.asarray(camera_center) if not torch.is_tensor(camera_center) else camera_center)
        center = center.to(dtype=self.means.dtype, device=self.means.device)
        return sh_colors(self.means, self.sh_dc, self.sh_rest, center, degree, rows)

    # --- PLY -----------------------------------------------------------------------------------
    def ply_attribute_names(self) -> list[str]:
        k = self.sh_rest.shape[1]
        names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        names += [f"f_rest_{i}" for i in range(3 * k)]
        names += ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]
        for name, value in self.extras.items():
            names += extra_property_names(name, value)
        return names

    def write_ply(self, path: str | Path) -> None:
        """Write the model as a binary little-endian PLY (3DGS/2DGS layout, extras appended as
        ``extra_*`` float properties), atomically."""
        path = Path(path)
        with torch.no_grad():
            n = len(self)
            columns = [
                self.means,
                self.normals,
                self.sh_dc.reshape(n, 3),
                self.sh_rest.transpose(1, 2).reshape(n, 3 * self.sh_rest.shape[1]),  # channel-major
                self.opacity_logits[:, None],
                self.log_scales,
                self.quats,
            ]
            columns += [value.reshape(n, math.prod(value.shape[1:])) for value in self.extras.values()]
            data = torch.cat([c.detach().float().cpu() for c in columns], dim=1).numpy()
        names = self.ply_attribute_names()
        assert data.shape[1] == len(names)
        header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
        header += [f"property float {name}" for name in names]
        header += ["end_header"]
        with atomic_file(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(("\n".join(header) + "\n").encode("ascii"))
                fh.write(np.ascontiguousarray(data, dtype="<f4").tobytes())

    @classmethod
    def read_ply(cls, path: str | Path) -> "GaussianModel":
        """Read a PLY written by :meth:`write_ply` or by the 3DGS/2DGS reference code.

        Accepts ``scale_2`` (3DGS files) by dropping it with a warning. ``extra_<name>[_<i>]``
        properties become the extras (float32). Raises :class:`~trace3d.errors.SceneFormatError`
        naming the file for anything malformed.
        """
        path = Path(path)
        vertex_count, properties, data = _read_binary_ply_vertices(path)
        names = [name for name, _ in properties]
        required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                    "rot_0", "rot_1", "rot_2", "rot_3"]
        missing = [r for r in required if r not in names]
        if missing:
            raise SceneFormatError(f"{path}: Gaussian PLY lacks the vertex properties {missing}.")
        rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda s: int(s[7:]))
        if len(rest_names) % 3 or (len(rest_names) // 3) not in (0, 3, 8, 15):
            raise SceneFormatError(
                f"{path}: Gaussian PLY has {len(rest_names)} f_rest properties; expected 3 * K with K in (0, 3, 8, 15)."
            )
        if "scale_2" in names:
            log.warning("%s: dropping scale_2 (a 3D Gaussian file read as 2D disks)", path)

        def col(name: str) -> np.ndarray:
            return data[name].astype(np.float32)

        n = vertex_count
        k = len(rest_names) // 3
        rest = np.stack([col(r) for r in rest_names], axis=1) if k else np.zeros((n, 0), np.float32)
        extras = {}
        for name, columns in _extra_columns(names, path).items():
            values = np.stack([col(c) for c in columns], axis=1) if columns[0] != f"extra_{name}" else col(columns[0])
            extras[name] = torch.from_numpy(np.ascontiguousarray(values))
        model = cls(
            means=torch.from_numpy(np.stack([col("x"), col("y"), col("z")], axis=1)),
            quats=torch.from_numpy(np.stack([col(f"rot_{i}") for i in range(4)], axis=1)),
            log_scales=torch.from_numpy(np.stack([col("scale_0"), col("scale_1")], axis=1)),
            opacity_logits=torch.from_numpy(col("opacity")),
            sh_dc=torch.from_numpy(np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)).reshape(n, 1, 3),
            sh_rest=torch.from_numpy(rest.reshape(n, 3, k)).transpose(1, 2).contiguous(),
            extras=extras,
        )
        if not model.is_finite():
            raise SceneFormatError(f"{path}: Gaussian PLY contains non-finite values.")
        return model


def check_extra(name: str, value: torch.Tensor, n: int) -> None:
    """Refuse an extra attribute that is not a tensor [N] or [N, k] or that shadows a core name."""
    if name in GaussianModel.PARAM_NAMES or not name.isidentifier() or re.search(r"_\d+$", name):
        raise ValueError(f"GaussianModel extra {name!r}: the name must be an identifier not ending in _<digits> "
                         f"and other than {GaussianModel.PARAM_NAMES}.")
    if not isinstance(value, torch.Tensor) or value.ndim not in (1, 2) or value.shape[0] != n:
        got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"GaussianModel extra {name!r}: expected a tensor [N={n}] or [N={n}, k], got {got}.")


def extra_property_names(name: str, value: torch.Tensor) -> list[str]:
    """PLY property names of an extra: ``extra_<name>`` for [N], ``extra_<name>_<i>`` for [N, k]."""
    if value.ndim == 1:
        return [f"extra_{name}"]
    return [f"extra_{name}_{i}" for i in range(value.shape[1])]


def _extra_columns(names: list[str], path: Path) -> dict[str, list[str]]:
    """Group the ``extra_*`` property names of a PLY by attribute, columns in index order."""
    groups: dict[str, dict[int, str]] = {}
    for prop in names:
        if not prop.startswith("extra_"):
            continue
        match = re.fullmatch(r"extra_(\w+?)_(\d+)", prop)
        name, index = (match.group(1), int(match.group(2))) if match else (prop[6:], -1)
        groups.setdefault(name, {})[index] = prop
    out = {}
    for name, columns in groups.items():
        if -1 in columns:
            if len(columns) > 1:
                raise SceneFormatError(f"{path}: extra attribute {name!r} is both a scalar and a vector property.")
            out[name] = [columns[-1]]
            continue
        if sorted(columns) != list(range(len(columns))):
            raise SceneFormatError(f"{path}: extra attribute {name!r} has columns {sorted(columns)}, "
                                   f"expected 0..{len(columns) - 1}.")
        out[name] = [columns[i] for i in range(len(columns))]
    return out


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_binary_ply_vertices(path: Path) -> tuple[int, list[tuple[str, str]], np.ndarray]:
    """Parse a binary little-endian PLY whose first element is ``vertex`` with scalar properties.

    Returns:
        (vertex count, [(name, numpy dtype code)], structured array of the vertices).
    """
    if not path.is_file():
        raise SceneFormatError(f"{path}: Gaussian PLY file is missing.")
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise SceneFormatError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header').")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[end + len(b"end_header\n"):]
    if "format binary_little_endian 1.0" not in header:
        raise SceneFormatError(f"{path}: only binary little-endian PLY files are supported.")
    vertex_count = None
    properties: list[tuple[str, str]] = []
    in_vertex = False
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "element":
            if vertex_count is not None and in_vertex:
                break  # later elements (faces ...) are not needed
            in_vertex = len(parts) == 3 and parts[1] == "vertex"
            if in_vertex:
                vertex_count = int(parts[2])
            elif vertex_count is None:
                raise SceneFormatError(f"{path}: the first PLY element must be 'vertex', got {parts[1]!r}.")
        elif parts[0] == "property" and in_vertex:
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise SceneFormatError(f"{path}: unsupported vertex property declaration {line!r}.")
            properties.append((parts[2], _PLY_TYPES[parts[1]]))
    if vertex_count is None:
        raise SceneFormatError(f"{path}: PLY header declares no vertex element.")
    dtype = np.dtype([(name, "<" + code) for name, code in properties])
    needed = vertex_count * dtype.itemsize
    if len(body) < needed:
        raise SceneFormatError(
            f"{path}: PLY is truncated ({len(body)} bytes of vertex data, {needed} expected for "
            f"{vertex_count} vertices)."
        )
    data = np.frombuffer(body[:needed], dtype=dtype, count=vertex_count)
    return vertex_count, properties, data


# ----------------------------------------------------------------------------------------------
# Initialisation
# ----------------------------------------------------------------------------------------------


def init_from_points(
    points: torch.Tensor | np.ndarray,
    colors: torch.Tensor | np.ndarray,
    sh_degree: int = 3,
    normals: torch.Tensor | np.ndarray | None = None,
    opacity: float = 0.1,
    scale_factor: float = 1.0,
    seed: int = 0,
) -> GaussianModel:
    """Gaussians centred on ``points`` (the 3DGS/2DGS initialisation).

    Scales: both tangent scales equal ``scale_factor`` times the RMS distance to the 3 nearest
    neighbours. Rotations: aligned so that the disk normal is ``normals`` when given, otherwise
    uniformly random (seeded). Colours: the DC term reproduces ``colors``; higher SH terms are 0.

    Args:
        points: [P, 3] world positions.
        colors: [P, 3] RGB, uint8 (0..255) or float (0..1).
        sh_degree: maximum SH degree (0..3).
        normals: optional [P, 3] normals.
        opacity: initial opacity (2DGS: 0.1).
    Returns:
        a model with P Gaussians (float32, CPU).
    """
    points = torch.as_tensor(np.asarray(points) if not torch.is_tensor(points) else points).float().cpu()
    colors_t = torch.as_tensor(np.asarray(colors) if not torch.is_tensor(colors) else colors)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise Trace3DError(f"init_from_points: expected a non-empty [P, 3] point array, "
                           f"got shape {tuple(points.shape)}.")
    if colors_t.shape != points.shape:
        raise Trace3DError(f"init_from_points: colours have shape {tuple(colors_t.shape)}, "
                           f"points {tuple(points.shape)}.")
    if not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise Trace3DError(f"init_from_points: sh_degree must be in 0..{MAX_SH_DEGREE}, got {sh_degree}.")
    if not 0.0 < opacity < 1.0:
        raise Trace3DError(f"init_from_points: initial opacity must be in (0, 1), got {opacity}.")
    rgb = colors_t.float() / 255.0 if colors_t.dtype == torch.uint8 else colors_t.float()
    rgb = rgb.clamp(0.0, 1.0).cpu()
    count = points.shape[0]
    generator = torch.Generator().manual_seed(int(seed))
    distances = nearest_neighbour_scales(points) * scale_factor
    if normals is not None:
        normals_t = torch.as_tensor(np.asarray(normals) if not torch.is_tensor(normals) else normals).float().cpu()
        quats = quats_aligning_z_to(normals_t)
    else:
        quats = random_quats(count, generator)
    logit = math.log(opacity / (1.0 - opacity))
    # On one torch thread, like the model's activations: with two, torch's log of the 80,000 distances of
    # a default room gave the second thread's half other values (up to 170 ulps off) in 1 to 3 processes
    # in 100 on a 2-core machine (docs/history/performance.md, "Run to run"), so the same scene and
    # seed started the fit from other scales.
    with torch_threads(1):
        log_distances = torch.log(distances)
    return GaussianModel(
        means=points.clone(),
        quats=quats,
        log_scales=log_distances[:, None].repeat(1, 2),
        opacity_logits=torch.full((count,), logit),
        sh_dc=rgb_to_sh(rgb)[:, None, :],
        sh_rest=torch.zeros(count, num_sh_rest(sh_degree), 3),
    )


def init_from_depth(
    scene: "Scene",
    cameras=None,
    stride: int = 4,
    max_points: int | None = 100_000,
    sh_degree: int = 3,
    opacity: float = 0.1,
    use_normals: bool = True,
    seed: int = 0,
) -> GaussianModel:
    """Gaussians on the back-projected depth of the train views (see
    :func:`trace3d.datasets.depth_init.depth_points_and_normals`).

    With ``use_normals`` each disk starts perpendicular to the depth-map normal (random rotation
    where that normal is undefined).
    """
    from .datasets.depth_init import depth_points_and_normals

    points, colors, normals = depth_points_and_normals(scene, cameras, stride, max_points, seed)
    model = init_from_points(points, colors, sh_degree=sh_degree, opacity=opacity, seed=seed)
    if use_normals:
        valid = normals.norm(dim=-1) > 0.5
        model.quats[valid] = quats_aligning_z_to(normals[valid])
    return model


def init_random(
    count: int,
    bounds_min: np.ndarray | torch.Tensor,
    bounds_max: np.ndarray | torch.Tensor,
    sh_degree: int = 3,
    opacity: float = 0.1,
    seed: int = 0,
) -> GaussianModel:
    """``count`` Gaussians uniform in the box [bounds_min, bounds_max] with random colours and rotations."""
    if count < 1:
        raise Trace3DError(f"random init: the Gaussian count must be >= 1, got {count}.")
    lo = torch.as_tensor(np.asarray(bounds_min, dtype=np.float32))
    hi = torch.as_tensor(np.asarray(bounds_max, dtype=np.float32))
    if lo.shape != (3,) or hi.shape != (3,) or not bool((hi > lo).all()):
        raise Trace3DError(f"random init: bounds must be two 3-vectors with max > min, "
                           f"got {lo.tolist()} and {hi.tolist()}.")
    generator = torch.Generator().manual_seed(int(seed))
    points = lo + (hi - lo) * torch.rand(count, 3, generator=generator)
    colors = torch.rand(count, 3, generator=generator)
    return init_from_points(points, colors, sh_degree=sh_degree, opacity=opacity, seed=seed + 1)
