"""Meshes in, signed distances out: loading, the normalised frame, exact SDF samples.

This is runtime code (``m.fit_codes(path)`` needs it for an unseen mesh), so it imports only
numpy and trimesh at module level; libigl is imported lazily through
:func:`zoo.errors.require` by the functions that need it.

The normalised frame: the mesh is rotated so that its up axis is +z, centred at its
bounding-box centre, and scaled so that its largest extent is 1, i.e. it fills
[-0.5, 0.5]^3 along its longest side. :class:`Similarity` records that map.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DataError, InputError, require

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")

# Signed-distance sample defaults, in the normalised frame (largest extent 1).
# DeepSDF samples two Gaussian bands around the surface (variances 0.0025 and 0.00025 for a
# unit-sphere normalisation, i.e. sigma 0.05 and 0.016 for radius 1) plus ~8% uniform points;
# DCC-DIF (via DIF-Net) uses on-surface points plus uniform free space. Our shapes span 1, not 2,
# so the bands are sigma 0.005 (the fine band that pins the zero level set) and 0.05 (the
# shell the collision triangles live in: centroid SDF up to 0.1, see docs/paper-notes.md), with
# 20% uniform points so far field is learned too.
DEFAULT_N_POINTS = 250_000
DEFAULT_NEAR_SIGMAS = (0.005, 0.05)
DEFAULT_FRACTIONS = (0.4, 0.4, 0.2)  # fine band, coarse band, uniform in the padded cube
# Uniform points fill [-0.5 - pad, 0.5 + pad]^3: the detector queries the SDF up to about
# 0.1 + one triangle edge (0.08) outside the surface, and the surface touches the cube's faces.
DEFAULT_PADDING = 0.1


# --------------------------------------------------------------------------- loading


def load_mesh(path: str | os.PathLike):
    """Load a triangle mesh (.obj, .ply, .stl, .off, .glb, .gltf) as one ``trimesh.Trimesh``.

    Scenes are concatenated into one mesh; vertices split only by texture or normal seams are
    merged (so a closed scan reads as closed); degenerate, duplicate (double-sided) and
    unreferenced geometry is dropped, and face windings are made consistent between neighbours.
    Raises :class:`DataError` for a missing, unreadable or empty file.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DataError(f"mesh file {path} does not exist; check the path (or $ZOO_DATA)")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path} has suffix {path.suffix!r}; sdfzoo reads {', '.join(MESH_SUFFIXES)} meshes: convert it first")
    try:
        mesh = _load_any(trimesh, path)
    except DataError:
        raise
    except Exception as exc:  # trimesh raises many types for garbage input
        raise DataError(f"cannot read mesh {path}: {type(exc).__name__}: {exc}; is the file a valid {path.suffix} mesh?") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(getattr(mesh, "faces", ())) == 0:
        raise DataError(f"{path} holds no triangles; export the object as a triangle mesh")
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    # "Double-sided" exports list every face twice with opposite windings; their winding
    # numbers cancel to 0 everywhere, so nothing would be inside. Keep one of each pair...
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    # ...and make neighbouring faces agree on orientation (whichever copy was kept).
    trimesh.repair.fix_winding(mesh)
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise DataError(f"{path} has no valid triangles (all degenerate, or NaN/Inf vertices); repair or re-export it")
    return mesh


def _load_any(trimesh, path: Path):
    # Loaded unprocessed, then processed as trimesh.load would: its processing silently drops
    # NaN/Inf vertices with every face that uses them, so a mesh with a few bad vertices would
    # come back smaller but seemingly valid. They are refused here instead.
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (UnicodeDecodeError, ImportError):
        if path.suffix.lower() != ".obj":
            raise
        # A text OBJ with stray non-UTF-8 bytes (e.g. 0xa0 in a comment): trimesh would guess the
        # encoding with charset_normalizer, an optional dependency. Latin-1 decodes any byte, and
        # the geometry is ASCII anyway.
        text = path.read_bytes().decode("latin-1")
        mesh = trimesh.load(io.BytesIO(text.encode("utf-8")), file_type="obj", force="mesh", process=False)
    if isinstance(mesh, trimesh.Trimesh):
        bad = ~np.isfinite(np.asarray(mesh.vertices)).all(axis=-1)
        if bad.any():
            raise DataError(f"{path} has {int(bad.sum())} vertices with NaN or Inf coordinates (of {len(bad)}); "
                            "repair or re-export the mesh")
        mesh.process()
    return mesh


# --------------------------------------------------------------------------- the similarity


@dataclass(frozen=True)
class Similarity:
    """A similarity transform from a source mesh's frame to the normalised frame.

    ``p_norm = scale * rotation @ p_src + translation``, so signed distances scale too:
    ``d_norm = scale * d_src``. ``rotation`` is (3, 3) orthonormal with det +1; ``translation`` (3,).
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self):
        r = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.translation, dtype=np.float64).reshape(3)
        s = float(self.scale)
        if not (np.isfinite(s) and s > 0):
            raise InputError(f"Similarity scale must be a positive finite number, got {self.scale}")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
            raise InputError("Similarity rotation must be orthonormal with det +1 (a proper rotation)")
        if not np.isfinite(t).all():
            raise InputError("Similarity translation must be finite")
        object.__setattr__(self, "scale", s)
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def identity(cls) -> Similarity:
        return cls(1.0, np.eye(3), np.zeros(3))

    def to_normalised(self, points) -> np.ndarray:
        """Source-frame points (..., 3) -> normalised-frame points (..., 3)."""
        p = np.asarray(points)
        return (self.scale * (p @ self.rotation.T) + self.translation).astype(_float_dtype(p), copy=False)

    def to_source(self, points) -> np.ndarray:
        """Normalised-frame points (..., 3) -> source-frame points (..., 3)."""
        p = np.asarray(points)
        return (((p - self.translation) / self.scale) @ self.rotation).astype(_float_dtype(p), copy=False)

    def distance_to_source(self, d):
        """Normalised-frame distances (...) -> source-frame distances: ``d / scale``."""
        return np.asarray(d) / self.scale

    def distance_to_normalised(self, d):
        """Source-frame distances (...) -> normalised-frame distances: ``d * scale``."""
        return np.asarray(d) * self.scale

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix, normalised-from-source."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    @property
    def inverse_matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix, source-from-normalised."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.T / self.scale
        m[:3, 3] = -(self.rotation.T @ self.translation) / self.scale
        return m

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Similarity:
        try:
            return cls(d["scale"], d["rotation"], d["translation"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"not a similarity transform record: {d!r} ({exc}); re-run the normalise stage") from exc

    def to_json(self) -> str:
        # repr-exact floats: json writes the shortest string that round-trips a float64.
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> Similarity:
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, TypeError) as exc:
            raise DataError(f"similarity transform is not valid JSON ({exc}); re-run the normalise stage") from exc
        return cls.from_dict(d)

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Similarity)
            and self.scale == other.scale
            and np.array_equal(self.rotation, other.rotation)
            and np.array_equal(self.translation, other.translation)
        )

    __hash__ = None  # numpy fields: equal by value, not hashable


def _float_dtype(a: np.ndarray):
    return a.dtype if a.dtype in (np.float32, np.float64) else np.float64


# --------------------------------------------------------------------------- orientation and normalisation

_AXES = {"x": 0, "y": 1, "z": 2}


def up_rotation(up) -> np.ndarray:
    """Rotation (3, 3) that takes a source's up direction to +z.

    ``up`` is an axis name ("x", "y", "z", "-x", "-y", "-z") or a (3, 3) rotation matrix used
    as is. For an axis, the smallest rotation is used (for "y": +90 degrees about x, taking
    y to z and z to -y); only the up direction is standardised, not the azimuth.
    """
    if isinstance(up, str):
        name = up.strip().lower()
        sign = -1.0 if name.startswith("-") else 1.0
        axis = name.lstrip("+-")
        if axis not in _AXES:
            raise InputError(f"up axis must be one of x, y, z, -x, -y, -z or a 3x3 rotation, got {up!r}")
        u = np.zeros(3)
        u[_AXES[axis]] = sign
        return rotation_between(u, np.array([0.0, 0.0, 1.0]))
    r = np.asarray(up, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
        raise InputError(f"an orientation given as a matrix must be a (3, 3) proper rotation, got {np.asarray(up).tolist()}")
    return r


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a to unit vector b (180 degrees about x for a = -b along z)."""
    v = np.cross(a, b)
    c = float(a @ b)
    if np.isclose(c, 1.0):
        return np.eye(3)
    if np.isclose(c, -1.0):
        # any axis perpendicular to a works; pick the first basis axis not parallel to it
        k = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = np.cross(a, k)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def normalise(mesh, up_axis="z"):
    """Orient, centre and scale a mesh into the normalised frame.

    Returns ``(normalised_mesh, similarity)``: up becomes +z, the bounding-box centre goes to
    the origin, the largest extent becomes 1 (so the mesh lies in [-0.5, 0.5]^3), and
    ``similarity.to_normalised`` maps source points onto the normalised mesh.
    """
    rotation = np.round(up_rotation(up_axis), 15)
    rotated = np.asarray(mesh.vertices, dtype=np.float64) @ rotation.T
    lo, hi = rotated.min(axis=0), rotated.max(axis=0)
    extent = float((hi - lo).max())
    if not extent > 0:
        raise InputError("cannot normalise a mesh with zero extent (all vertices coincide)")
    scale = 1.0 / extent
    sim = Similarity(scale, rotation, -scale * (lo + hi) / 2.0)
    out = mesh.copy()
    out.vertices = sim.to_normalised(np.asarray(mesh.vertices, dtype=np.float64))
    return out, sim


# --------------------------------------------------------------------------- signed distance


SIGN_RULES = ("winding", "pseudonormal")


def signed_distance(mesh, points, sign: str = "winding") -> np.ndarray:
    """Exact signed distance from points to a mesh, negative inside: (N, 3) -> (N,).

    ``sign="winding"`` (the default, what the pipeline's samples use): the magnitude is the exact
    distance to the nearest boundary triangle (libigl's AABB tree; faces buried inside the solid are
    left out, see :func:`exterior_faces`), and the sign comes from the generalised winding number
    (libigl's fast winding number), which tolerates open scans, holes and triangle soups where ray
    parity fails: a point is inside where |w| > 0.5. The absolute value keeps a mesh whose faces all
    point inwards (a common export bug) right; a mesh with inconsistently oriented patches can still
    be signed wrongly near them. ``sign="pseudonormal"``: libigl's signed_distance over every face,
    signed by the angle-weighted pseudonormal at the closest point: exact for closed, consistently
    oriented meshes only. float32 points give float32 distances; anything else gives float64.
    """
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise InputError(f"points must have shape (N, 3), got {p.shape}; reshape with .reshape(-1, 3)")
    if len(p) == 0:
        return np.zeros(0, dtype=_float_dtype(p))
    q = np.ascontiguousarray(p, dtype=np.float64)
    if not np.isfinite(q).all():
        raise InputError("points hold NaN or Inf; remove them before calling signed_distance")
    d, _ = ExactMeshSDF(mesh, sign).distance_and_closest(q)
    return d.astype(_float_dtype(p), copy=False)


class ExactMeshSDF:
    """The exact signed distance of a mesh as an SDF (``sdf(points)``, ``value_and_grad``, ``bounds``).

    The sign rule is :func:`signed_distance`'s ``sign``. A query costs tens of microseconds per
    point (libigl's AABB tree): for references and for building grids (a VoxelSDF of it), not for a
    simulator's hot path. The gradient is the unit vector from the closest surface point, signed.
    """

    def __init__(self, mesh, sign: str = "winding"):
        if sign not in SIGN_RULES:
            raise InputError(f"unknown sign rule {sign!r}; use one of {', '.join(SIGN_RULES)}")
        self._igl = require("igl")
        self.sign = sign
        self.v, self.f = _igl_arrays(mesh)
        # distances to the outer surface only: a face buried inside the solid (where touching or
        # overlapping parts meet) is not on the boundary, and would add a false zero level set
        self.outer = self.f[exterior_faces(mesh)] if sign == "winding" else self.f
        self.lo, self.hi = self.v.min(axis=0), self.v.max(axis=0)

    @property
    def bounds(self):
        """Two (3,) float32 tensors: the corners of the mesh's bounding box."""
        import torch

        return torch.as_tensor(self.lo, dtype=torch.float32), torch.as_tensor(self.hi, dtype=torch.float32)

    def distance_and_closest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Float64 points (N, 3) -> signed distances (N,) and the closest surface points (N, 3)."""
        if self.sign == "pseudonormal":
            d, _, closest, _ = self._igl.signed_distance(q, self.v, self.f, sign_type=self._igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
            return d, closest
        sq, _, closest = self._igl.point_mesh_squared_distance(q, self.v, self.outer)
        winding = self._igl.fast_winding_number(self.v, self.f, q)
        d = np.sqrt(np.maximum(sq, 0.0))
        return np.where(np.abs(winding) > 0.5, -d, d), closest

    def _query(self, points):
        import torch

        p = torch.as_tensor(points)
        q = np.ascontiguousarray(p.detach().cpu().numpy(), dtype=np.float64).reshape(-1, 3)
        return p.dtype if p.is_floating_point() else torch.float32, q, self.distance_and_closest(q)

    def __call__(self, points):
        """(N, 3) -> (N,) signed distances, in the points' float dtype (float32 otherwise)."""
        import torch

        dtype, _, (d, _) = self._query(points)
        return torch.as_tensor(d, dtype=dtype)

    def value_and_grad(self, points):
        """(N, 3) -> distances (N,) and unit gradients (N, 3)."""
        import torch

        dtype, q, (d, closest) = self._query(points)
        g = (q - closest) * np.sign(d)[:, None]
        g = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-30)
        return torch.as_tensor(d, dtype=dtype), torch.as_tensor(g, dtype=dtype)


# A face is buried when the winding number exceeds this on both sides. Buried faces of touching
# parts see exactly 1 on both sides; 0.75 rather than 0.5 keeps the surface faces of a leaky
# open scan, whose outside can read 0.6 near a hole.
INTERIOR_WINDING = 0.75


def exterior_faces(mesh, offset: float = 1e-5) -> np.ndarray:
    """Which faces lie on the boundary of the solid: (F,) bool.

    Multi-part meshes (a bottle built from stacked closed bodies, a handle pushed into a mug's
    wall) carry faces that are inside the union. A face is interior when the generalised
    winding number is above ``INTERIOR_WINDING`` on both of its sides, probed at its centroid moved by
    ``offset`` x the bounding-box diagonal along and against its normal. Open sheets and thin
    walls have an outside on at least one side, so they are kept.
    """
    igl = require("igl")
    v, f = _igl_arrays(mesh)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    step = offset * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    centre = tri.mean(axis=1)
    probes = np.concatenate([centre + step * normal, centre - step * normal])
    w = np.abs(igl.fast_winding_number(v, f, probes)).reshape(2, -1)
    keep = ~((w[0] > INTERIOR_WINDING) & (w[1] > INTERIOR_WINDING))
    return keep if keep.any() else np.ones(len(f), dtype=bool)


def _igl_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise InputError("the mesh has no triangles; load it with zoo.meshes.load_mesh")
    return (
        np.ascontiguousarray(mesh.vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
    )


# --------------------------------------------------------------------------- samples


def sample_surface(mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """Area-uniform points on the surface, deterministic given ``rng``: -> (n, 3) float64."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    tri = v[np.asarray(mesh.faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    # uniform barycentrics by folding the unit square onto the triangle
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1.0
    u, w = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - w, w)
    t = tri[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


def sample_sdf(
    mesh,
    n_points: int = DEFAULT_N_POINTS,
    seed: int = 0,
    near_sigmas: tuple[float, float] = DEFAULT_NEAR_SIGMAS,
    fractions: tuple[float, float, float] = DEFAULT_FRACTIONS,
    padding: float = DEFAULT_PADDING,
) -> tuple[np.ndarray, np.ndarray]:
    """Signed-distance samples of a (normalised) mesh: -> points (N, 3) float32, sdf (N,) float32.

    ``fractions`` split ``n_points`` into: surface points plus Gaussian noise of
    ``near_sigmas[0]`` (fine band), the same with ``near_sigmas[1]`` (coarse band), and points
    uniform in [-0.5 - padding, 0.5 + padding]^3. The same mesh and seed give identical arrays.
    Units are the mesh's own: call it on the normalised mesh for the defaults to make sense.
    """
    n_points = int(n_points)
    if n_points <= 0:
        raise InputError(f"n_points must be positive, got {n_points}")
    if len(near_sigmas) != 2 or min(near_sigmas) <= 0:
        raise InputError(f"near_sigmas must be two positive numbers, got {near_sigmas}")
    frac = np.asarray(fractions, dtype=np.float64)
    if frac.shape != (3,) or (frac < 0).any() or not np.isclose(frac.sum(), 1.0):
        raise InputError(f"fractions must be three non-negative numbers summing to 1 (fine, coarse, uniform), got {fractions}")
    if padding < 0:
        raise InputError(f"padding must be >= 0, got {padding}")
    n_fine, n_coarse = int(round(frac[0] * n_points)), int(round(frac[1] * n_points))
    n_uniform = n_points - n_fine - n_coarse
    if n_uniform < 0:
        n_coarse += n_uniform
        n_uniform = 0
    rng = np.random.default_rng(seed)
    surface = sample_surface(mesh, n_fine + n_coarse, rng)
    sigma = np.repeat(np.asarray(near_sigmas, dtype=np.float64), [n_fine, n_coarse])
    near = surface + rng.normal(size=surface.shape) * sigma[:, None]
    half = 0.5 + float(padding)
    uniform = rng.uniform(-half, half, size=(n_uniform, 3))
    points = np.concatenate([near, uniform]).astype(np.float32)
    # distances of the float32 points themselves, so the stored pair is exactly consistent
    sdf = signed_distance(mesh, points.astype(np.float64)).astype(np.float32)
    return points, sdf
