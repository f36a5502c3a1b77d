"""sdfzoo contacts into MuJoCo: large triangles refined near the SDF, contacts reduced to a manifold, d.contact filled.

``zoo.collide`` gives one contact per triangle. Two things make that set depend on the tessellation:

* triangles around a vertex or along an edge report the same point (a sphere over a vertex of a
  fine plane gets 6 copies of one contact, and N copies of a contact make it N times stiffer in
  MuJoCo's solver), and a flat patch reports one point per triangle under it;
* a triangle much larger than the SDF (a 2-triangle ground plane) reports one point for a whole
  face, too few to hold a box level.

:func:`refine_near` clips every triangle larger than a quarter of the SDF's median extent to
the SDF's bounds (grown by the margin; no point outside them can touch) and subdivides what is
left to that size, so every mesh looks alike to the SDF near it. :func:`reduce_contacts` then
makes a manifold the way PhysX and MuJoCo do: coincident points merged (the deepest kept), contacts grouped into
patches of similar normal, and each patch kept as its deepest point plus up to three points that
span the largest area. docs/sim-contacts.md has the measurements behind the choice.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from ..geometry import edge_lengths, faces_touching_box

PATCH_COS = math.cos(math.radians(20.0))  # faces within 20 degrees of a patch's deepest contact's face join it
FLAT_COS = math.cos(math.radians(5.0))  # a patch's extra points: SDF normals within 5 degrees of its deepest's
MAX_PER_PATCH = 4
MERGE_CELL = 0.5  # the reduction keeps the deepest contact per cell of this fraction of its merge distance
REFINE_CELLS = 4  # a refined triangle's edge is at most the SDF's median extent / REFINE_CELLS


@dataclass
class ContactRows:
    """Contacts of one (SDF body, mesh body) pair as MuJoCo wants them, world frame.

    Attributes:
        pos: (K, 3) midpoint between the mesh point and the SDF's surface.
        dist: (K,) signed distance, negative in penetration.
        frame: (K, 9) rows: the normal (from the SDF body to the mesh body), then two tangents.
        geom: (K, 2) int32 geoms: the SDF body's, then the other body's.
    """

    pos: np.ndarray
    dist: np.ndarray
    frame: np.ndarray
    geom: np.ndarray

    def __len__(self) -> int:
        return len(self.dist)


# -- large triangles ------------------------------------------------------------------------


def refine_near(vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_edge: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mesh equivalent to (vertices (V, 3), faces (F, 3)) inside the box [lo, hi] (same frame).

    Faces whose box misses [lo, hi] are dropped; faces with an edge longer than ``max_edge`` are
    clipped to the box and subdivided until no edge exceeds it; others are kept as they are.

    Returns:
        vertices (V', 3), faces (F', 3), origin (F',) the input face each output face comes from.
    """
    box = [torch.as_tensor(np.asarray(b, dtype=vertices.dtype)) for b in (lo, hi)]
    near = faces_touching_box(torch.as_tensor(vertices), torch.as_tensor(faces, dtype=torch.long), *box).numpy()
    tri = vertices[faces[near]]  # (N, 3, 3): only the faces near the box (a step's hot path on a large mesh)
    edge = _edge_lengths(tri).max(axis=1)
    small = near[edge <= max_edge]
    large = np.nonzero(edge > max_edge)[0]  # positions in ``near``
    if len(large) == 0:
        return vertices, faces[small], small
    parts_v, parts_f, parts_o = [vertices], [faces[small]], [small]
    offset = len(vertices)
    for position in large:  # few: the faces larger than the SDF that reach its box
        index = near[position]
        polygon = _clip_to_box(tri[position], lo, hi)
        if len(polygon) < 3:
            continue
        v, f = _subdivide(polygon, max_edge)
        if len(f) == 0:
            continue
        parts_v.append(v)
        parts_f.append(f + offset)
        parts_o.append(np.full(len(f), index))
        offset += len(v)
    return np.concatenate(parts_v), np.concatenate(parts_f), np.concatenate(parts_o)


def refine_to_size(vertices: np.ndarray, faces: np.ndarray, max_edge: float, max_faces: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The mesh (vertices (V, 3), faces (F, 3)) cut into faces with no edge longer than ``max_edge``.

    A sliver (shortest edge at most half of ``max_edge``) is cut into a ladder of strips across its
    length (:func:`_ladder`): pieces as wide as the sliver and nearly ``max_edge`` long. Every other
    face has its longest edge halved until no edge exceeds ``max_edge`` (longest-edge bisection, not
    subdivision of every edge). Bisection alone would cut a sliver lengthwise into needles, each
    nearly as long as ``max_edge``, so a contact across a finely tessellated cylinder would meet
    several needles per original face (docs/sim-bench.md). The result covers the same surface; a face
    cut where its neighbour is not leaves a T-junction, which no collision query minds. Done once
    when a simulation is built, so a body pair's mesh stays fixed from step to step (what
    :class:`zoo.CoherentCollider` needs), instead of :func:`refine_near` clipping and refining it at
    every step.

    Returns:
        vertices (V', 3), faces (F', 3) (orientation kept), origin (F',) the input face of each
        output face; None when the result would exceed ``max_faces`` faces.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    origin = np.arange(len(faces))
    if len(faces):
        laddered = _ladder(vertices, faces, max_edge, max_faces)
        if laddered is None:
            return None
        vertices, faces, origin = laddered
    while len(faces):
        tri = vertices[faces]
        lengths = _edge_lengths(tri)
        longest = lengths.argmax(axis=1)
        split = np.nonzero(lengths[np.arange(len(faces)), longest] > max_edge)[0]
        if len(split) == 0:
            break
        if len(faces) + len(split) > max_faces:
            return None
        k = longest[split]
        a, b, c = (faces[split, (k + shift) % 3] for shift in range(3))
        ends = np.sort(np.stack([a, b], axis=1), axis=1)
        edges, which = np.unique(ends, axis=0, return_inverse=True)  # a shared edge gets one midpoint
        middle = len(vertices) + which.reshape(-1)
        vertices = np.concatenate([vertices, vertices[edges].mean(axis=1)])
        keep = np.ones(len(faces), dtype=bool)
        keep[split] = False
        faces = np.concatenate([faces[keep], np.stack([a, middle, c], axis=1), np.stack([middle, b, c], axis=1)])
        origin = np.concatenate([origin[keep], origin[split], origin[split]])
    return vertices, faces, origin


def refined_pieces(max_edge: float):
    """(vertices (V, 3), faces (N, 3)) -> (N,): how many faces :func:`refine_to_size` cuts each face into at
    ``max_edge`` (what :func:`zoo.sim.flat_regions.merge_flat_regions` counts a merge's gain in)."""
    def pieces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        return np.bincount(refine_to_size(vertices, faces, max_edge, math.inf)[2], minlength=len(faces))

    return pieces


def _ladder(vertices: np.ndarray, faces: np.ndarray, max_edge: float, max_faces: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Every sliver of (vertices (V, 3), faces (F, 3)) longer than ``max_edge`` cut into strips across its length.

    A sliver's shortest edge AB (at most ``max_edge / 2``) faces its far corner C. Its long edges CA
    and CB are cut into n equal parts (P_i on AC, Q_i on BC, i = 0..n), with n the fewest for which
    every piece's edges, the diagonal P_i Q_i+1 included (at most |AB| + max(|CA|, |CB|) / n), stay
    within ``max_edge``. Strip i is the quad P_i Q_i Q_i+1 P_i+1 as two triangles; the last one is the
    triangle P_n-1 Q_n-1 C: the detector's cut of a needle (:func:`zoo.amortized.subdivision.strip_levels`),
    on the mesh. A cut point is shared by the faces on both sides of its edge when they cut it alike (a
    regularly tessellated cylinder's slivers do).

    Returns:
        vertices (V', 3) (the input's first), faces (F', 3) (orientation kept), origin (F',); None
        when the result would exceed ``max_faces`` faces.
    """
    tri = vertices[faces]
    lengths = _edge_lengths(tri)
    shortest = lengths.argmin(axis=1)
    short = lengths[np.arange(len(faces)), shortest]
    long = lengths.max(axis=1)
    sliver = np.nonzero((short <= 0.5 * max_edge) & (long > max_edge))[0]
    if len(sliver) == 0:
        return vertices, faces, np.arange(len(faces))
    strips = np.ceil(long[sliver] / (max_edge - short[sliver])).astype(np.int64)  # n per sliver
    if len(faces) - len(sliver) + int((2 * strips - 1).sum()) > max_faces:
        return None
    k = shortest[sliver]
    a, b, c = (faces[sliver, (k + shift) % 3] for shift in range(3))
    kept = np.setdiff1d(np.arange(len(faces)), sliver)
    parts_f, parts_o = [faces[kept]], [kept]
    points, keys = [], []
    for n in np.unique(strips):
        group = np.nonzero(strips == n)[0]
        fraction = np.arange(n + 1) / n  # (n + 1,) from the short edge (0) to the far corner (1)
        p = _cut_points(vertices, a[group], c[group], fraction, keys, points)  # (G, n + 1): P_0 = A .. P_n = C
        q = _cut_points(vertices, b[group], c[group], fraction, keys, points)  # (G, n + 1): Q_0 = B .. Q_n = C
        lower = np.stack([p[:, :-1], q[:, :-1], q[:, 1:]], axis=2)  # (G, n, 3): P_i Q_i Q_i+1, the last P_n-1 Q_n-1 C
        upper = np.stack([p[:, :-2], q[:, 1:-1], p[:, 1:-1]], axis=2)  # (G, n - 1, 3): P_i Q_i+1 P_i+1
        parts_f += [lower.reshape(-1, 3), upper.reshape(-1, 3)]
        parts_o += [np.repeat(sliver[group], n), np.repeat(sliver[group], n - 1)]
    faces_out = np.concatenate(parts_f)
    if not points:
        return vertices, faces_out, np.concatenate(parts_o)
    new_keys = np.concatenate(keys)  # (M, 4): edge ends (sorted), cuts, cut index from the first end
    _, first, inverse = np.unique(new_keys, axis=0, return_index=True, return_inverse=True)
    placeholder = faces_out >= len(vertices)  # cut points are numbered len(vertices) + their row in new_keys
    faces_out[placeholder] = len(vertices) + inverse.reshape(-1)[faces_out[placeholder] - len(vertices)]
    return np.concatenate([vertices, np.concatenate(points)[first]]), faces_out, np.concatenate(parts_o)


def _cut_points(vertices: np.ndarray, start: np.ndarray, end: np.ndarray, fraction: np.ndarray,
                keys: list, points: list) -> np.ndarray:
    """Vertex indices (G, T) of the points at ``fraction`` (T,) along the edges start (G,) -> end (G,).

    The ends (fraction 0 and 1) are the edges' own vertices. Interior points are appended to
    ``points`` (their positions) and ``keys`` (edge ends sorted, cut count, cut index counted from the
    lower-numbered end: the same point whichever face cuts the edge) and numbered after every vertex
    and every point appended before them (:func:`_ladder` merges equal keys).
    """
    cuts = len(fraction) - 1
    index = np.empty((len(start), len(fraction)), dtype=np.int64)
    index[:, 0], index[:, -1] = start, end
    inner = np.arange(1, cuts)
    if len(inner):
        offset = len(vertices) + sum(len(k) for k in keys)
        t = fraction[inner]
        positions = vertices[start][:, None] + t[None, :, None] * (vertices[end] - vertices[start])[:, None]
        forward = start[:, None] < end[:, None]
        from_low = np.where(forward, inner[None, :], cuts - inner[None, :])
        low, high = np.minimum(start, end), np.maximum(start, end)
        key = np.stack(np.broadcast_arrays(low[:, None], high[:, None], np.full_like(from_low, cuts), from_low), axis=-1)
        index[:, 1:-1] = offset + np.arange(len(start) * len(inner)).reshape(len(start), len(inner))
        points.append(positions.reshape(-1, 3))
        keys.append(key.reshape(-1, 4))
    return index


def _edge_lengths(triangles: np.ndarray) -> np.ndarray:
    """(F, 3, 3) -> (F, 3): edge k runs from corner k to k + 1 (:func:`zoo.geometry.edge_lengths` on numpy arrays)."""
    return edge_lengths(torch.from_numpy(np.ascontiguousarray(triangles))).numpy()


def _clip_to_box(triangle: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the convex polygon (P, 3) of ``triangle`` (3, 3) inside [lo, hi]."""
    polygon = list(triangle)
    for axis in range(3):
        for bound, sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            if not polygon:
                return np.zeros((0, 3))
            out = []
            for a, b in zip(polygon, polygon[1:] + polygon[:1]):
                da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
                if da >= 0:
                    out.append(a)
                if (da >= 0) != (db >= 0):
                    out.append(a + (b - a) * (da / (da - db)))
            polygon = out
    return np.asarray(polygon).reshape(-1, 3)


def _subdivide(polygon: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """A convex polygon (P, 3) fanned into triangles and subdivided until no edge exceeds ``max_edge``."""
    import trimesh

    fan = np.array([[0, i, i + 1] for i in range(1, len(polygon) - 1)])
    area = np.linalg.norm(np.cross(polygon[fan[:, 1]] - polygon[0], polygon[fan[:, 2]] - polygon[0]), axis=1)
    fan = fan[area > 1e-12 * max(float(np.ptp(polygon, axis=0).max()), 1e-30) ** 2]  # clipping through a corner repeats it
    if len(fan) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    v, f = trimesh.remesh.subdivide_to_size(polygon, fan, max_edge=max_edge, max_iter=12)
    return np.asarray(v), np.asarray(f)


# -- MuJoCo rows ----------------------------------------------------------------------------


@njit(cache=True)
def tangents(nx, ny, nz):
    """Two unit tangents (t1, t2) of the unit normal (nx, ny, nz), (t1, t2, normal) right-handed, as 3-tuples: t1 is
    the normal crossed with x, or with y where the normal is near x; t2 the normal crossed with t1."""
    hx, hy, hz = (1.0, 0.0, 0.0) if abs(nx) < 0.9 else (0.0, 1.0, 0.0)
    ax, ay, az = ny * hz - nz * hy, nz * hx - nx * hz, nx * hy - ny * hx
    length = math.sqrt(ax * ax + ay * ay + az * az)
    ax, ay, az = ax / length, ay / length, az / length
    return (ax, ay, az), (ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax)


@njit(cache=True)
def _positions_and_frames(points, depths, normals, keep):
    """:func:`contact_rows`' positions (K, 3) and frames (K, 9) at the rows ``keep`` (K,) of ``points`` (N, 3),
    ``depths`` (N,), ``normals`` (N, 3)."""
    k = keep.shape[0]
    pos = np.empty((k, 3))
    frame = np.empty((k, 9))
    for i in range(k):
        r = keep[i]
        nx, ny, nz = normals[r, 0], normals[r, 1], normals[r, 2]
        half = 0.5 * depths[r]
        pos[i, 0], pos[i, 1], pos[i, 2] = points[r, 0] - half * nx, points[r, 1] - half * ny, points[r, 2] - half * nz
        t1, t2 = tangents(nx, ny, nz)
        frame[i, 0], frame[i, 1], frame[i, 2] = nx, ny, nz
        frame[i, 3], frame[i, 4], frame[i, 5] = t1
        frame[i, 6], frame[i, 7], frame[i, 8] = t2
    return pos, frame


def contact_rows(contacts, keep: np.ndarray, geoms: tuple[int, int]) -> ContactRows:
    """MuJoCo rows of ``contacts`` (:class:`zoo.collision.ContactArrays`, world frame) at the indices ``keep``: the
    mesh point lies at depth d along the SDF's normal n from the SDF's surface, so the surface is at p - d n, and the
    row's position is their midpoint p - d n / 2."""
    keep = np.asarray(keep, dtype=np.int64)
    pos, frame = _positions_and_frames(contacts.points, contacts.depths, contacts.normals, keep)
    geom = np.empty((len(keep), 2), dtype=np.int32)
    geom[:] = geoms
    return ContactRows(pos=pos, dist=contacts.depths[keep], frame=frame, geom=geom)


def add_contacts(model, data, rows: ContactRows, params) -> int:
    """Append ``rows`` to ``data.contact`` (after MuJoCo's velocity stage) with one pair's mixed contact parameters
    (:class:`zoo.sim.geoms.ContactParameters`); returns how many were added (fewer when the buffer is full).

    One template contact (:func:`_template`) is appended per row by ``mj_addContact`` and the fields are then
    written as whole arrays, which costs a fraction of filling each contact on its own.
    """
    import mujoco

    k = len(rows)
    if k == 0:
        return 0
    template = _template(params)
    start = data.ncon
    added = 0
    for _ in range(k):
        if mujoco.mj_addContact(model, data, template):
            break  # buffer full: the caller reports the shortfall
        added += 1
    view = data.contact
    sl = slice(start, start + added)
    view.pos[sl] = rows.pos[:added]
    view.dist[sl] = rows.dist[:added]
    view.frame[sl] = rows.frame[:added]
    view.geom[sl] = rows.geom[:added]
    view.geom1[sl] = rows.geom[:added, 0]
    view.geom2[sl] = rows.geom[:added, 1]
    return added


@functools.cache
def _template(params) -> object:
    """The ``mujoco.MjContact`` :func:`add_contacts` appends for a pair's contact parameters
    (:class:`zoo.sim.geoms.ContactParameters`, frozen): made once per parameters, as ``mj_addContact`` copies it."""
    import mujoco

    template = mujoco.MjContact()
    # a contact with friction needs a friction coefficient: a 3-dim cone with zero friction makes MuJoCo's
    # acceleration non-finite
    template.dim = params.condim if params.friction[0] > 0 else 1
    template.includemargin = params.margin - params.gap
    template.friction = list(params.friction)
    template.mu = params.friction[0]
    template.solref = list(params.solref)
    template.solreffriction = [0.0, 0.0]
    template.solimp = list(params.solimp)
    template.exclude = 0
    template.efc_address = -1
    template.elem = [-1, -1]
    template.flex = [-1, -1]
    template.vert = [-1, -1]
    return template
