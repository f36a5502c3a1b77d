"""A surface mesh of an SDF: its zero level set by marching cubes on a grid over its ``bounds``.

Used where MuJoCo or a pair needs triangles of an SDF body: the mesh drawn for it (its visual geom in
the models :class:`zoo.sim.Simulation` builds) and the surface an SDF body offers another SDF body in
:func:`zoo.sim.attach` (an SDF-SDF pair collides one side's SDF with the other's surface mesh). Each
(SDF, resolution) is extracted once per process and kept.
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError, require
from ..sdf import query_dtype

VISUAL_RESOLUTION = 48  # grid cells along the longest side: what a rendered body needs
CONTACT_RESOLUTION = 128  # for a surface another SDF collides with
_CACHE: dict[tuple[int, int], tuple[object, np.ndarray, np.ndarray]] = {}
CHUNK = 65536  # points per SDF query: bounded memory for a network SDF
COARSE = 4  # fine cells per coarse cell of the first, sparse sampling
LIPSCHITZ = 2.0  # a bound on |grad f| that holds for the learned SDFs too (zoo.collider.LEARNED_LIPSCHITZ)


def sdf_grid(sdf, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values (X, Y, Z), lower corner (3,), cell size (3,)) of ``sdf`` sampled on a grid over its bounds.

    The longest side gets ``resolution`` cells; the grid extends a cell beyond the bounds on every side,
    so the surface closes even where it touches them. Only nodes near the surface are queried: the SDF is
    first sampled every ``COARSE`` nodes, and a node whose trilinear estimate from that coarse grid is
    farther from zero than ``LIPSCHITZ`` times a coarse cell's diagonal keeps the estimate (its sign is
    right, and marching cubes reads nothing else there).
    """
    lo, hi = (np.asarray(torch.as_tensor(b).detach().cpu(), dtype=np.float64).reshape(3) for b in sdf.bounds)
    cell = float((hi - lo).max()) / resolution
    if not cell > 0:
        raise InputError("the SDF's bounds are empty; an SDF body needs a box that holds its surface")
    lo = lo - cell
    counts = np.maximum(2, np.ceil((hi + cell - lo) / cell).astype(int) + 1)
    counts = COARSE * np.ceil((counts - 1) / COARSE).astype(int) + 1  # whole coarse cells
    coarse_counts = (counts - 1) // COARSE + 1
    coarse = _values(sdf, lo, COARSE * cell, coarse_counts).reshape(*coarse_counts)
    axes = [np.arange(n) / COARSE for n in counts]  # fine nodes in coarse-cell units
    estimate = _trilinear(coarse, axes)
    near = np.abs(estimate) <= LIPSCHITZ * np.sqrt(3.0) * COARSE * cell
    index = np.argwhere(near)
    estimate[near] = _values_at(sdf, lo + index * cell)
    return estimate, lo, np.full(3, cell)


def _values(sdf, lo: np.ndarray, cell: float, counts: np.ndarray) -> np.ndarray:
    """``sdf`` at every node of the grid with corner ``lo``, spacing ``cell`` and ``counts`` (3,) nodes, flattened."""
    axes = [lo[i] + cell * np.arange(counts[i]) for i in range(3)]
    return _values_at(sdf, np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3))


def _values_at(sdf, points: np.ndarray) -> np.ndarray:
    """``sdf`` at ``points`` (N, 3), in chunks, as float64 (N,)."""
    values = np.empty(len(points))
    dtype = query_dtype(sdf)
    with torch.no_grad():
        for start in range(0, len(points), CHUNK):
            chunk = torch.as_tensor(points[start:start + CHUNK], dtype=dtype)
            values[start:start + CHUNK] = torch.as_tensor(sdf(chunk)).reshape(-1).double().cpu().numpy()
    return values


def _trilinear(grid: np.ndarray, axes: list[np.ndarray]) -> np.ndarray:
    """``grid`` (A, B, C) interpolated at the outer product of ``axes`` (fractional node coordinates per axis)."""
    out = grid
    for dim, x in enumerate(axes):
        i = np.clip(np.floor(x).astype(int), 0, grid.shape[dim] - 2)
        t = (x - i).reshape([-1 if d == dim else 1 for d in range(3)])
        out = np.take(out, i, axis=dim) * (1 - t) + np.take(out, i + 1, axis=dim) * t
    return out


def surface_mesh(sdf, resolution: int = CONTACT_RESOLUTION) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of ``sdf``'s zero level set, in its own frame.

    Faces are oriented outward (their normals follow the SDF's gradient). Kept for the process: the
    same SDF object and resolution extract once.
    """
    key = (id(sdf), int(resolution))
    if key in _CACHE and _CACHE[key][0] is sdf:
        return _CACHE[key][1], _CACHE[key][2]
    mcubes = require("mcubes", extra="sim")
    values, lo, cell = sdf_grid(sdf, resolution)
    if not (values < 0).any() or not (values > 0).any():
        raise InputError("the SDF has no zero crossing on a grid over its bounds: no surface to extract")
    vertices, faces = mcubes.marching_cubes(values, 0.0)
    vertices = lo + np.asarray(vertices, dtype=np.float64) * cell
    faces = np.asarray(faces, dtype=np.int64)
    faces = _outward(vertices, faces, sdf)
    _CACHE[key] = (sdf, vertices, faces)
    return vertices, faces


def _outward(vertices: np.ndarray, faces: np.ndarray, sdf) -> np.ndarray:
    """``faces`` (F, 3) reversed if their normals point into the SDF (marching cubes' convention varies)."""
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = tri.mean(axis=1)
    step = 1e-3 * float(np.ptp(vertices, axis=0).max())
    probe = torch.as_tensor(centre + step * normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30),
                            dtype=torch.float32)
    with torch.no_grad():
        outside = torch.as_tensor(sdf(probe[:CHUNK])).reshape(-1).cpu().numpy() > 0
    return faces if outside.mean() >= 0.5 else faces[:, ::-1].copy()
