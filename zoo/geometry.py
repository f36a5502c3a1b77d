"""Triangle, point and pose geometry shared by the solvers, the detector and collision.

Conventions: points are (..., 3); triangles are (M, 3, 3) (triangle, vertex, xyz);
barycentric coordinates are (M, 3), non-negative, rows summing to 1. Checking and converting
arguments is :mod:`zoo.validation`'s job; these functions take validated tensors.
"""

from __future__ import annotations

import numpy as np
import torch


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


def unique_rows(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distinct rows of ``points`` (N, 3) and where each row went: (U, 3), inverse (N,) with ``unique[inverse] == points``.

    Exact (rows equal in every coordinate are merged), by three stable sorts: far cheaper than
    ``torch.unique(dim=0)``.
    """
    n = points.shape[0]
    order = torch.argsort(points[:, 2], stable=True)
    for col in (1, 0):
        order = order[torch.argsort(points[order, col], stable=True)]
    s = points[order]
    new = torch.ones(n, dtype=torch.bool, device=points.device)
    new[1:] = (s[1:] != s[:-1]).any(dim=-1)
    inverse = torch.empty(n, dtype=torch.int64, device=points.device)
    inverse[order] = torch.cumsum(new, 0) - 1
    return s[new], inverse


def barycentric_grid(resolution: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """All (i, j, k) / resolution with i + j + k = resolution: (G, 3), G = (r+1)(r+2)/2.

    Rows run over i, then j (row order matters: the detector's soft-argmax head sums in it). Includes
    the three vertices exactly (rows of the identity) and points on every edge; symmetric under
    every vertex permutation. Computed in float64, then cast.
    """
    r = int(resolution)
    i, j = torch.meshgrid(torch.arange(r + 1), torch.arange(r + 1), indexing="ij")
    keep = (i + j) <= r
    ijk = torch.stack([i[keep], j[keep], r - i[keep] - j[keep]], dim=-1)
    return (ijk.to(torch.float64) / r).to(dtype=dtype, device=device)


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a 4x4 transform to points (..., 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def transform_vectors(pose: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Rotate vectors (..., 3) by a 4x4 transform's rotation."""
    return vectors @ pose[:3, :3].T


def faces_touching_box(vertices: torch.Tensor, faces: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Indices (N,) of the faces (F, 3) whose AABB touches the box [lo, hi] ((3,) each).

    Without building the (F, 3, 3) triangles: each vertex (V, 3) gets six bits (below the box on
    x, y, z; above it on x, y, z), and a face's box misses the box exactly when its three vertices
    share a bit.
    """
    weights = torch.tensor([1, 2, 4], dtype=torch.uint8, device=vertices.device)
    below = ((vertices < lo).to(torch.uint8) * weights).sum(dim=-1, dtype=torch.uint8)
    above = ((vertices > hi).to(torch.uint8) * weights).sum(dim=-1, dtype=torch.uint8)
    code = below | (above << 3)  # (V,) uint8
    per_face = code[faces]  # (F, 3)
    shared = per_face[:, 0] & per_face[:, 1] & per_face[:, 2]
    return (shared == 0).nonzero().squeeze(-1)


def invert_pose(pose):
    """Inverse of a rigid 4x4 transform, a torch tensor or a numpy array (the same kind back)."""
    if isinstance(pose, np.ndarray):
        inv = np.eye(4, dtype=pose.dtype)
        inv[:3, :3] = pose[:3, :3].T
        inv[:3, 3] = -(pose[:3, :3].T @ pose[:3, 3])
        return inv
    inv = torch.eye(4, dtype=pose.dtype, device=pose.device)
    r = pose[:3, :3]
    inv[:3, :3] = r.T
    inv[:3, 3] = -(r.T @ pose[:3, 3])
    return inv


def row_norms(v: np.ndarray) -> np.ndarray:
    """(..., n) -> (...): each row's Euclidean length (numpy; ``np.linalg.norm``'s checks cost more than a few rows'
    arithmetic)."""
    return np.sqrt((v * v).sum(axis=-1))


def unit_rows(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3): each vector over its length (numpy), zeros left zero."""
    length = row_norms(v)[..., None]
    return v / np.where(length > 0, length, 1.0)


def face_normals(triangles: np.ndarray) -> np.ndarray:
    """(K, 3, 3) -> (K, 3) unit normals (numpy); zeros for degenerate (zero-area) triangles."""
    face = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    length = np.linalg.norm(face, axis=1, keepdims=True)
    return face / np.where(length > 0, length, 1.0)
