"""numpy reference for :mod:`zoo.sim.reduction`: the reduction to a manifold per patch as array expressions, for
tests only."""

from __future__ import annotations

import numpy as np

from zoo.sim.contacts import FLAT_COS, MAX_PER_PATCH, MERGE_CELL, PATCH_COS


def reduce_contacts(points: np.ndarray, depths: np.ndarray, normals: np.ndarray, faces: np.ndarray, merge_tol: float,
                    patch_cos: float = PATCH_COS, flat_cos: float = FLAT_COS, max_per_patch: int = MAX_PER_PATCH) -> np.ndarray:
    """:func:`zoo.sim.reduction.reduce_contacts` (the same arguments and result) as numpy array expressions."""
    if len(depths) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(depths, kind="stable")  # deepest first
    keys = np.floor(points[order] / (MERGE_CELL * merge_tol)).astype(np.int64)
    _, first = np.unique(_cell_index(keys), return_index=True)  # the deepest of each cell
    candidates = order[np.sort(first)]
    kept = []
    free = np.ones(len(candidates), dtype=bool)
    while free.any():
        seed = int(np.argmax(free))  # candidates are depth-ordered: the deepest unassigned
        same_face = np.abs(faces[candidates] @ faces[candidates[seed]]) >= patch_cos
        members = np.nonzero(free & (same_face | (np.arange(len(candidates)) == seed)))[0]
        free[members] = False
        flat = normals[candidates[members]] @ normals[candidates[seed]] >= flat_cos
        flat[0] = True  # the seed: members are ascending, the seed is first
        rows = np.nonzero(flat)[0]
        chosen = _manifold(points[candidates[members[rows]]], normals[candidates[seed]], max_per_patch, merge_tol)
        kept.extend(candidates[members[rows[chosen]]])
    return np.asarray(kept, dtype=np.int64)


def _cell_index(keys: np.ndarray) -> np.ndarray:
    """One int64 (K,) per integer cell (K, 3), equal where the cells are: their place in the cells' bounding grid
    (``np.unique(keys, axis=0)`` sorts rows of three; one key sorts several times faster)."""
    keys = keys - keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:  # a grid too large for one int64: rows, as numpy keys them
        return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)
    return (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]


def _manifold(points: np.ndarray, normal: np.ndarray, n: int, spread: float) -> list[int]:
    """Rows of ``points`` (P, 3) (row 0 the deepest) to keep: row 0, the farthest from it, then the
    points that most enlarge the area of the kept polygon projected on the patch's plane; a point
    within ``spread`` of a kept one is never kept."""
    if len(points) <= 1 or n <= 1:
        return [0]
    flat = points - np.outer(points @ normal, normal)
    chosen = [0]
    near = np.linalg.norm(flat - flat[0], axis=1)
    if near.max() <= spread:
        return chosen
    chosen.append(int(np.argmax(near)))
    near = np.minimum(near, np.linalg.norm(flat - flat[chosen[-1]], axis=1))
    while len(chosen) < min(n, len(points)):
        gain = _area_gain(flat, flat[chosen], normal)
        gain[near <= spread] = -1.0
        best = int(np.argmax(gain))
        if gain[best] <= 0:
            break
        chosen.append(best)
        near = np.minimum(near, np.linalg.norm(flat - flat[best], axis=1))
    return chosen


def _area_gain(flat: np.ndarray, polygon: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(P,) the area each point adds to the kept convex polygon (K, 3), all projected on the plane of ``normal``.

    The polygon's corners are put in counter-clockwise order about ``normal``; a point outside adds
    the triangles it makes with the edges it sees (those it lies outside of), a point inside adds nothing.
    """
    axes = tangent_frames(normal[None])[0, 3:9].reshape(2, 3)  # t1, t2: (t1, t2, normal) is right-handed
    centre = polygon.mean(axis=0)
    corners = (polygon - centre) @ axes.T  # (K, 2) in the plane
    points = (flat - centre) @ axes.T  # (P, 2)
    a = corners[np.argsort(np.arctan2(corners[:, 1], corners[:, 0]))]
    edge = np.roll(a, -1, axis=0) - a  # (K, 2)
    to_point = points[:, None] - a[None]  # (P, K, 2)
    signed = edge[None, :, 0] * to_point[..., 1] - edge[None, :, 1] * to_point[..., 0]  # (P, K): > 0 inside each edge
    return np.clip(-signed, 0.0, None).sum(axis=1) / 2


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals -> (K, 9) contact frames in numpy: the normal, then t1 = n x (x, or y where n is near x)
    made unit, then t2 = n x t1 (``zoo.sim.contacts.tangents``' reference)."""
    helper = np.zeros_like(normals)
    x_ok = np.abs(normals[:, 0]) < 0.9
    helper[x_ok, 0], helper[~x_ok, 1] = 1.0, 1.0
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.concatenate([normals, t1, np.cross(normals, t1)], axis=1)
