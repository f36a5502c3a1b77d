"""Triangle and point helpers shared by the solvers, the detector and collision.

Conventions: points are (..., 3); triangles are (M, 3, 3) (triangle, vertex, xyz);
barycentric coordinates are (M, 3), non-negative, rows summing to 1.
"""

from __future__ import annotations

import torch

from .errors import InputError

_FLOATS = (torch.float32, torch.float64)


def as_points(points, name: str = "points", dtype: torch.dtype | None = None) -> torch.Tensor:
    """Validate and convert ``points`` to a float tensor of shape (N, 3).

    float64 input is kept as float64; anything else becomes float32 unless ``dtype`` says.
    Raises :class:`InputError` for wrong shapes, empty input, NaN or Inf.
    """
    t = _as_float_tensor(points, name, dtype)
    if t.ndim != 2 or t.shape[-1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {tuple(t.shape)}; reshape with .reshape(-1, 3)")
    _check_finite(t, name)
    return t


def as_triangles(triangles, name: str = "triangles", dtype: torch.dtype | None = None) -> torch.Tensor:
    """Validate and convert ``triangles`` to a float tensor of shape (M, 3, 3)."""
    t = _as_float_tensor(triangles, name, dtype)
    if t.ndim == 2 and t.shape == (3, 3):
        t = t.unsqueeze(0)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise InputError(f"{name} must have shape (M, 3, 3) (triangle, vertex, xyz), got {tuple(t.shape)}")
    _check_finite(t, name)
    return t


def as_barycentric(bary, triangles: torch.Tensor, name: str = "bary") -> torch.Tensor:
    """Validate barycentric coordinates (M, 3) against triangles (M, 3, 3)."""
    b = _as_float_tensor(bary, name, triangles.dtype).to(triangles.device)
    if b.shape != triangles.shape[:2]:
        raise InputError(f"{name} must have shape {tuple(triangles.shape[:2])} to match the triangles, got {tuple(b.shape)}")
    _check_finite(b, name)
    return b


def _as_float_tensor(x, name: str, dtype: torch.dtype | None) -> torch.Tensor:
    try:
        t = torch.as_tensor(x)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name} must be array-like of numbers, got {type(x).__name__}") from exc
    if t.is_complex() or t.dtype == torch.bool:
        raise InputError(f"{name} must hold real numbers, got dtype {t.dtype}")
    if dtype is not None:
        t = t.to(dtype)
    elif t.dtype not in _FLOATS:
        t = t.to(torch.float32)
    if t.numel() == 0:
        raise InputError(f"{name} is empty (shape {tuple(t.shape)}); pass at least one element")
    return t


def _check_finite(t: torch.Tensor, name: str) -> None:
    if not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).any(dim=-1).sum()) if t.ndim > 1 else int((~torch.isfinite(t)).sum())
        raise InputError(f"{name} holds NaN or Inf in {bad} row(s); remove or fix them before calling")


def bary_to_points(triangles: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Points on triangles: (M, 3, 3), (M, 3) -> (M, 3)."""
    return torch.einsum("mv,mvc->mc", bary, triangles)


def edges(triangles: torch.Tensor) -> torch.Tensor:
    """Edge vectors v2-v1, v3-v2, v1-v3: (M, 3, 3) -> (M, 3, 3)."""
    return torch.roll(triangles, shifts=-1, dims=1) - triangles


def edge_lengths(triangles: torch.Tensor) -> torch.Tensor:
    """Lengths of the three edges (edge k from vertex k to k + 1, as :func:`edges`): (M, 3, 3) -> (M, 3)."""
    return edges(triangles).norm(dim=-1)


def perimeter(triangles: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) -> (M,)."""
    return edge_lengths(triangles).sum(dim=-1)


def mean_edge_length(triangles: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) -> (M,): the length scale NME divides by."""
    return edge_lengths(triangles).mean(dim=-1)


def area(triangles: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) -> (M,)."""
    e = edges(triangles)
    return 0.5 * torch.linalg.cross(e[:, 0], -e[:, 2]).norm(dim=-1)


def centroid(triangles: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) -> (M, 3)."""
    return triangles.mean(dim=1)


def bounding_radius(triangles: torch.Tensor) -> torch.Tensor:
    """Radius of the sphere about the centroid that holds the triangle: (M, 3, 3) -> (M,).

    With a 1-Lipschitz SDF, f(centroid) > radius + margin proves the whole triangle is
    farther than ``margin`` from the surface (PhysX's conservative cull).
    """
    return (triangles - centroid(triangles).unsqueeze(1)).norm(dim=-1).amax(dim=-1)


def as_pose(pose, dtype: torch.dtype = torch.float32, name: str = "pose") -> torch.Tensor:
    """Validate a 4x4 rigid transform (world-from-object); ``None`` is the identity."""
    if pose is None:
        return torch.eye(4, dtype=dtype)
    t = _as_float_tensor(pose, name, dtype)
    if t.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 homogeneous transform, got shape {tuple(t.shape)}")
    _check_finite(t, name)
    r = t[:3, :3].double()
    if not torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-4) or float(torch.det(r)) <= 0:
        raise InputError(f"{name}'s upper-left 3x3 block must be a rotation (orthonormal, det +1)")
    return t


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a 4x4 transform to points (..., 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def transform_vectors(pose: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Rotate vectors (..., 3) by a 4x4 transform's rotation."""
    return vectors @ pose[:3, :3].T


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid 4x4 transform."""
    inv = torch.eye(4, dtype=pose.dtype, device=pose.device)
    r = pose[:3, :3]
    inv[:3, :3] = r.T
    inv[:3, 3] = -(r.T @ pose[:3, 3])
    return inv
