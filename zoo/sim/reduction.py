"""A pair's contacts reduced to a manifold per patch, as MuJoCo's solver gets them (``zoo.sim.world``), compiled.

The reduction makes a manifold the way PhysX and MuJoCo do: coincident points merged (the deepest of each cell of
``MERGE_CELL`` times the merge distance kept), contacts grouped into patches of similar face normal, and each patch
kept as its deepest point plus up to three points that span the largest area (docs/sim-contacts.md). A step reduces
each pair's few dozen contacts; numpy's cost per call (a dozen calls a patch) was most of it, so the whole reduction
is one compiled pass (numba, ``cache=True``). tests/naive_reduction.py holds the numpy reference it is tested against.

numba is imported here: ``import zoo`` does not load it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..proxy_kernel import first_of_cell
from .contacts import FLAT_COS, MAX_PER_PATCH, MERGE_CELL, PATCH_COS, tangents


def reduce_contacts(points: np.ndarray, depths: np.ndarray, normals: np.ndarray, faces: np.ndarray, merge_tol: float,
                    patch_cos: float = PATCH_COS, flat_cos: float = FLAT_COS, max_per_patch: int = MAX_PER_PATCH) -> np.ndarray:
    """Indices of the contacts to keep: a manifold of at most ``max_per_patch`` points per patch.

    Args:
        points (K, 3), depths (K,), normals (K, 3): one pair's contacts (normals: the SDF's).
        faces: (K, 3) unit normals of the contacts' mesh faces (zeros where degenerate).
        merge_tol: points closer than this are one point (the deepest is kept): the copies
            triangles around a vertex give, which an iterative solver scatters by a fraction of
            their edge.
        patch_cos: a contact joins the patch of the deepest unassigned contact when their faces'
            normals are this close (either side): a plane is one patch however the SDF meets it.
        flat_cos: besides the deepest, a patch keeps only points whose SDF normal is this close to
            the deepest's: the flat part of the contact (a box's face: four corners), not the rim
            of a curved one (a sphere deep in a plane keeps one contact, as MuJoCo's own).

    Returns:
        (R,) int64 indices into the contacts, deepest patch first.
    """
    if len(depths) == 0:
        return np.zeros(0, dtype=np.int64)
    as_rows = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    return _reduce(as_rows(points), as_rows(depths), as_rows(normals), as_rows(faces), MERGE_CELL * float(merge_tol),
                   float(merge_tol), float(patch_cos), float(flat_cos), int(max_per_patch))


@njit(cache=True)
def _reduce(points, depths, normals, faces, cell, spread, patch_cos, flat_cos, max_per_patch):
    candidates = _deepest_per_cell(points, depths, cell)  # in depth order
    n = candidates.shape[0]
    free = np.ones(n, dtype=np.bool_)
    kept = np.empty(depths.shape[0], dtype=np.int64)
    n_kept = 0
    members = np.empty(n, dtype=np.int64)
    for seed in range(n):  # the deepest unassigned is the first free: candidates are depth-ordered
        if not free[seed]:
            continue
        s = candidates[seed]
        m = 0
        for i in range(seed, n):
            c = candidates[i]
            same_face = abs(faces[c, 0] * faces[s, 0] + faces[c, 1] * faces[s, 1] + faces[c, 2] * faces[s, 2]) >= patch_cos
            if free[i] and (same_face or i == seed):
                free[i] = False
                flat = normals[c, 0] * normals[s, 0] + normals[c, 1] * normals[s, 1] + normals[c, 2] * normals[s, 2] >= flat_cos
                if flat or i == seed:
                    members[m] = c
                    m += 1
        chosen = _manifold(points, members[:m], normals[s], max_per_patch, spread)
        for k in chosen:
            kept[n_kept] = members[k]
            n_kept += 1
    return kept[:n_kept]


@njit(cache=True)
def _deepest_per_cell(points, depths, cell):
    """The rows (C,) of the deepest contact of each cell of side ``cell`` (the first of equals), deepest first."""
    order = np.argsort(depths, kind="mergesort")
    cells = np.empty((order.shape[0], 3), dtype=np.int64)
    for i in range(order.shape[0]):
        for a in range(3):
            cells[i, a] = int(math.floor(points[order[i], a] / cell))
    first = first_of_cell(cells)  # in depth order: the first of a cell is its deepest
    rows = np.empty(order.shape[0], dtype=np.int64)
    m = 0
    for i in range(order.shape[0]):
        if first[i] == i:
            rows[m] = order[i]
            m += 1
    return rows[:m]


@njit(cache=True)
def _manifold(points, rows, normal, n, spread):
    """Of ``points[rows]`` (P of them, the first the deepest), the indices into ``rows`` to keep: the first, the
    farthest from it, then the points that most enlarge the area of the kept polygon projected on the plane of
    ``normal``; a point within ``spread`` of a kept one is never kept."""
    p = rows.shape[0]
    if p <= 1 or n <= 1:
        return [0]
    flat = np.empty((p, 3))
    for i in range(p):
        r = rows[i]
        along = points[r, 0] * normal[0] + points[r, 1] * normal[1] + points[r, 2] * normal[2]
        for a in range(3):
            flat[i, a] = points[r, a] - along * normal[a]
    chosen = [0]
    near = np.empty(p)
    for i in range(p):
        near[i] = _distance(flat, i, 0)
    if near.max() <= spread:
        return chosen
    chosen.append(int(np.argmax(near)))
    for i in range(p):
        near[i] = min(near[i], _distance(flat, i, chosen[-1]))
    t1, t2 = tangents(normal[0], normal[1], normal[2])
    while len(chosen) < min(n, p):
        gain = _area_gain(flat, chosen, t1, t2)
        for i in range(p):
            if near[i] <= spread:
                gain[i] = -1.0
        best = int(np.argmax(gain))
        if gain[best] <= 0:
            break
        chosen.append(best)
        for i in range(p):
            near[i] = min(near[i], _distance(flat, i, best))
    return chosen


@njit(cache=True, inline="always")
def _distance(flat, i, j):
    dx, dy, dz = flat[i, 0] - flat[j, 0], flat[i, 1] - flat[j, 1], flat[i, 2] - flat[j, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True)
def _area_gain(flat, chosen, t1, t2):
    """(P,) the area each point of ``flat`` (P, 3) adds to the convex polygon of its rows ``chosen``, in the plane of
    the tangents ``t1``, ``t2``: the polygon's corners in counter-clockwise order, a point outside adds the
    triangles it makes with the edges it sees, a point inside nothing."""
    k = len(chosen)
    centre = np.zeros(3)
    for c in chosen:
        for a in range(3):
            centre[a] += flat[c, a]
    centre /= k
    corners = np.empty((k, 2))
    angles = np.empty(k)
    for j in range(k):
        c = chosen[j]
        x = (flat[c, 0] - centre[0]) * t1[0] + (flat[c, 1] - centre[1]) * t1[1] + (flat[c, 2] - centre[2]) * t1[2]
        y = (flat[c, 0] - centre[0]) * t2[0] + (flat[c, 1] - centre[1]) * t2[1] + (flat[c, 2] - centre[2]) * t2[2]
        corners[j, 0], corners[j, 1], angles[j] = x, y, math.atan2(y, x)
    ring = corners[np.argsort(angles)]
    p = flat.shape[0]
    gain = np.zeros(p)
    for i in range(p):
        x = (flat[i, 0] - centre[0]) * t1[0] + (flat[i, 1] - centre[1]) * t1[1] + (flat[i, 2] - centre[2]) * t1[2]
        y = (flat[i, 0] - centre[0]) * t2[0] + (flat[i, 1] - centre[1]) * t2[1] + (flat[i, 2] - centre[2]) * t2[2]
        total = 0.0
        for j in range(k):
            ex, ey = ring[(j + 1) % k, 0] - ring[j, 0], ring[(j + 1) % k, 1] - ring[j, 1]
            signed = ex * (y - ring[j, 1]) - ey * (x - ring[j, 0])  # > 0 inside the edge
            total += max(-signed, 0.0)
        gain[i] = total / 2
    return gain
