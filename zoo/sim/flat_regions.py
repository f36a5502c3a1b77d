"""A mesh's flat parts with the vertices they do not need removed: a pair's mesh at the SDF's resolution.

A simulation cuts a mesh's faces longer than its SDF's ``max_edge`` once, at build
(:func:`zoo.sim.contacts.refine_to_size`), so that every mesh looks alike to the SDF near it. A mesh tessellated
finer than that where it is flat (a CAD export's fans of slivers, a subdivided mesh) would otherwise put more faces
within the contact margin for the same surface: each costs the narrow phase a search, and the reduction keeps the
same contacts in the end. :func:`merge_flat_regions` removes, one at a time, each vertex whose fan of faces (all of
it, or the faces on one side of a line through it) lies in one plane, within ``ROUNDING`` of the mesh's largest
coordinate (the same surface up to float32 rounding), and cuts the fan's rim anew by ear clipping into fewer faces
over the same points (checked by their areas). Corners and curved parts stay. A mesh subdivided k times comes back
to the faces it was subdivided from. :class:`FaceCover` maps a point on a new face back to the input's face that
holds it, so contacts still name the faces of the mesh given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry import face_normals

# Points within this fraction of the mesh's largest coordinate of a plane (a line) lie in it: a model's meshes
# reach sdfzoo through MuJoCo as float32, rounded by up to 6e-8 of that, so a subdivided face's pieces are flat to
# about that, and no more.
ROUNDING = 2e-7
MAX_LINK = 12  # a vertex with more faces than this around it stays: its rim's ears would be long slivers
# A flat part is re-meshed only where that divides its faces by this much at least (a mesh cut finer than its shape
# needs, by a subdivision or more) and the pieces the refinement then cuts them into by half: re-cutting a coarse
# CAD tessellation into a few fewer, longer faces costs the narrow phase more than it saves (docs/sim-contacts.md).
MIN_GAIN = 4
# A mesh with more vertices between flat faces than this is left as it is: the pass removes them one at a time in
# Python, about 0.1 ms each, and a build should not wait seconds for it.
MAX_CANDIDATES = 50_000


@dataclass
class FaceCover:
    """The input's faces under each face of a mesh made from it (:func:`merge_flat_regions`), as compressed rows.

    Attributes:
        vertices (V, 3), faces (F, 3): the input mesh.
        start: (F' + 1,) int64, output face i's input faces are ``members[start[i]:start[i + 1]]``.
        members: (M,) int64 the input faces that may hold each output face's points.
    """

    vertices: np.ndarray
    faces: np.ndarray
    start: np.ndarray
    members: np.ndarray

    def __post_init__(self):
        self.one_each = len(self.members) == len(self.start) - 1  # each output face over one input face

    @classmethod
    def identity(cls, vertices: np.ndarray, faces: np.ndarray) -> FaceCover:
        """Each face over itself alone."""
        return cls(vertices, faces, np.arange(len(faces) + 1), np.arange(len(faces)))

    @classmethod
    def from_lists(cls, vertices: np.ndarray, faces: np.ndarray, lists: list) -> FaceCover:
        """From one list of input faces per output face."""
        counts = np.asarray([len(m) for m in lists], dtype=np.int64)
        members = np.concatenate([np.asarray(m, dtype=np.int64) for m in lists]) if lists else np.zeros(0, np.int64)
        return cls(vertices, faces, np.concatenate([[0], np.cumsum(counts)]), members)

    def take(self, rows: np.ndarray, triangles: np.ndarray) -> FaceCover:
        """The cover of pieces cut from the output faces ``rows`` (R,), their corners ``triangles`` (R, 3, 3): of the
        input faces under each piece's face, those whose boxes meet the piece's (grown by rounding's tolerance)."""
        rows = np.asarray(rows, dtype=np.int64)
        counts = self.start[rows + 1] - self.start[rows]
        members = self.members[_ranges(self.start[rows], counts)]
        owner = np.repeat(np.arange(len(rows)), counts)
        if len(members) > len(rows):  # something was merged: keep the input faces near each piece
            slack = _tolerance(self.vertices)
            corners = self.vertices[self.faces[members]]  # (N, 3, 3)
            meets = ((corners.min(axis=1) <= triangles[owner].max(axis=1) + slack)
                     & (corners.max(axis=1) >= triangles[owner].min(axis=1) - slack)).all(axis=1)
            members, owner = members[meets], owner[meets]
        counts = np.bincount(owner, minlength=len(rows))
        return FaceCover(self.vertices, self.faces, np.concatenate([[0], np.cumsum(counts)]), members)

    def under(self, faces: np.ndarray) -> np.ndarray:
        """(U,) the input faces under any of the output faces ``faces`` (N,), ascending."""
        faces = np.asarray(faces, dtype=np.int64)
        return np.unique(self.members[_ranges(self.start[faces], self.start[faces + 1] - self.start[faces])])

    def input_faces(self, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(K,) the input's face that holds each point ``points`` (K, 3) of the output faces ``faces`` (K,): of the
        faces under it, the one the point lies least outside of (barycentric coordinates, in its plane)."""
        faces = np.asarray(faces, dtype=np.int64)
        if self.one_each:
            return self.members[faces]
        counts = self.start[faces + 1] - self.start[faces]
        rows = _ranges(self.start[faces], counts)  # (N,) rows of members, contact after contact
        owner = np.repeat(np.arange(len(faces)), counts)
        score = _least_barycentric(self.vertices[self.faces[self.members[rows]]], np.asarray(points, np.float64)[owner])
        best = np.full(len(faces), -np.inf)
        np.maximum.at(best, owner, score)
        first = np.full(len(faces), len(rows))
        np.minimum.at(first, owner, np.where(score == best[owner], np.arange(len(rows)), len(rows)))
        return self.members[rows[first]]


def merge_flat_regions(vertices: np.ndarray, faces: np.ndarray, max_width: float = math.inf, pieces=None
                       ) -> tuple[np.ndarray, FaceCover]:
    """The mesh (vertices (V, 3), faces (F, 3)) with the vertices its flat parts do not need removed (see the
    module docstring), where the faces that replace a vertex's are no wider than ``max_width`` (m; a face's width:
    twice its area over its longest edge). A simulation passes half its reduction's cell: the reduction keeps at most
    one contact per cell, a face gives one at most, so faces that narrow leave a flat contact patch its contacts.
    A group of faces merged together keeps its merge only where that divides its faces by ``MIN_GAIN`` at least and
    their ``pieces`` by 2: (vertices, faces (N, 3)) -> (N,) the pieces a caller cuts each face into (a simulation's
    refinement to its SDF's size; None: one each).

    Returns:
        faces (F', 3) on the same vertices (orientation kept), and the :class:`FaceCover` of the input's faces
        under each.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tolerance = _tolerance(vertices)
    candidates = _vertices_between_flat_faces(vertices, faces, tolerance)
    if not len(candidates) or len(candidates) > MAX_CANDIDATES:  # none, or more than a build should loop over
        return faces, FaceCover.identity(vertices, faces)
    return _Decimation(vertices, faces, tolerance, max_width, pieces).run(candidates)


def _tolerance(vertices: np.ndarray) -> float:
    """m: how far from a plane or a line the mesh's points may lie and still count as in it (``ROUNDING``)."""
    return ROUNDING * max(float(np.abs(vertices).max(initial=0.0)), 1e-30)


class _Decimation:
    """Vertex removal where the mesh is flat, one vertex at a time (a build-time pass over its flat vertices).

    The faces around a vertex v, in order, make a fan (closed inside the mesh, open on its boundary). A run of them
    from rim vertex a to rim vertex b, where v lies on the segment ab (the whole fan, open, or one side of a line
    through v, closed) or the whole closed fan, whose corners lie within the tolerance of one plane, is replaced by
    an ear-clipping triangulation of its rim (a star-shaped polygon): one face fewer (two, closed), where the fan
    has at most ``MAX_LINK`` faces, the areas agree and no new face is wider than ``max_width``. The faces on the
    other side of the line keep v (a T-junction, which no collision query minds) until they can lose it too. The
    rim's vertices and v are then looked at again."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, tolerance: float, max_width: float, pieces):
        self.vertices, self.input, self.tolerance, self.max_width = vertices, faces, tolerance, max_width
        self.pieces = pieces or (lambda v, f: np.ones(len(f), dtype=np.int64))
        self.faces = [tuple(int(i) for i in face) for face in faces]
        self.cover = [[i] for i in range(len(faces))]
        self.alive = [True] * len(faces)
        self.incident = [set() for _ in range(len(vertices))]
        for index, face in enumerate(self.faces):
            for v in face:
                self.incident[v].add(index)

    def run(self, candidates: np.ndarray) -> tuple[np.ndarray, FaceCover]:
        pending = [int(v) for v in candidates[::-1]]
        queued = set(pending)
        while pending:
            v = pending.pop()
            queued.discard(v)
            for neighbour in self._remove(v):
                if neighbour not in queued:
                    queued.add(neighbour)
                    pending.append(neighbour)
        rows = [i for i, alive in enumerate(self.alive) if alive]
        faces, lists = self._worth_it([self.faces[i] for i in rows], [self.cover[i] for i in rows])
        if len(faces) == len(self.input):  # no merge was worth it: the mesh as given, in its order
            return self.input, FaceCover.identity(self.vertices, self.input)
        cover = FaceCover.from_lists(self.vertices, self.input, lists)
        return faces, cover.take(np.arange(len(faces)), self.vertices[faces])  # the faces merged into each, less those far

    def _worth_it(self, faces: list, lists: list) -> tuple[np.ndarray, list]:
        """The faces (F', 3) and their input faces' lists, where each group of input faces merged together
        (joined by sharing an output face) keeps its merge only if that divides its faces by ``MIN_GAIN`` and their
        ``pieces`` by 2 at least; the others get their input faces back."""
        n = len(self.input)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        pairs = np.asarray([(m[0], other) for m in lists for other in m[1:]], dtype=np.int64).reshape(-1, 2)
        group = _components(n, pairs[:, 0], pairs[:, 1])
        group_of_output = np.asarray([group[m[0]] for m in lists], dtype=np.int64)
        count_in, count_out = np.bincount(group, minlength=n), np.bincount(group_of_output, minlength=n)
        kept = (count_out * MIN_GAIN <= count_in) & (count_in > 1)  # the pieces are counted for these alone
        ins, outs = np.flatnonzero(kept[group]), np.flatnonzero(kept[group_of_output])
        if len(ins):
            inputs = np.bincount(group[ins], weights=self.pieces(self.vertices, self.input[ins]), minlength=n)
            outputs = np.bincount(group_of_output[outs], weights=self.pieces(self.vertices, faces[outs]), minlength=n)
            kept &= 2 * outputs <= inputs
        kept |= count_in == 1  # a face no merge touched stays
        keep = kept[group_of_output]
        restored = np.flatnonzero(~kept[group])
        faces = np.concatenate([faces[keep], self.input[restored]])
        return faces, [m for m, k in zip(lists, keep) if k] + [[int(i)] for i in restored]

    def _remove(self, v: int) -> list[int]:
        """Remove ``v`` from a flat run of its fan (see the class docstring); the vertices to look at again, or []."""
        fan = list(self.incident[v])
        if not 2 <= len(fan) <= MAX_LINK:
            return []
        rim = _rim(v, [self.faces[f] for f in fan])
        if rim is None:
            return []
        loop, closed, order = rim
        fan = [fan[k] for k in order]  # fan[m] spans loop[m] -> loop[m + 1]
        for first, last in self._runs(v, loop, closed):
            faces = [fan[m % len(fan)] for m in range(first, last)]
            polygon = [loop[m % len(loop)] for m in range(first, last + 1)]
            if closed and last - first == len(fan):  # the whole closed fan: its rim, once round
                polygon = polygon[:-1]
            if self._replace(v, faces, polygon):
                return polygon + [v]  # v may leave the rest of its fan too
        return []

    def _runs(self, v: int, loop: list, closed: bool) -> list[tuple[int, int]]:
        """(first, last): the runs of faces first .. last - 1 of the fan (cyclic where closed) that v may leave,
        the most faces first: a closed fan whole; the faces on one side of a line through v and two rim vertices
        (an open fan's ends, or any two)."""
        k = len(loop) if closed else len(loop) - 1  # the fan's faces
        direction = self.vertices[loop] - self.vertices[v]  # (L, 3)
        length = np.linalg.norm(direction, axis=1)
        across = np.linalg.norm(np.cross(direction[:, None], direction[None]), axis=2)  # (L, L) |d_i x d_j|
        opposite = (direction @ direction.T < 0) & (across <= self.tolerance * (length[:, None] + length[None]))
        runs = [(0, k)] if closed else []
        for i, j in zip(*np.nonzero(np.triu(opposite, 2))):  # a run of at least two faces
            runs.append((int(i), int(j)))
            if closed and k - (j - i) >= 2:
                runs.append((int(j), int(i) + k))
        return sorted(runs, key=lambda run: run[0] - run[1])

    def _replace(self, v: int, faces: list, polygon: list) -> bool:
        """Replace ``faces`` (v's, around it) by an ear-clipping triangulation of their rim ``polygon`` where they
        are flat and it covers their area; whether it did."""
        if len(polygon) < 3:
            return False
        old = self.vertices[[self.faces[f] for f in faces]]  # (k, 3, 3)
        basis = self._flat_basis(self.vertices[polygon + [v]], old)
        if basis is None:
            return False
        ears = _ear_clipping(self.vertices[polygon] @ basis.T, self.tolerance)
        if ears is None:
            return False
        new = np.asarray(polygon)[ears]
        rim, corners = self.vertices[polygon], self.vertices[new]
        perimeter = float(np.linalg.norm(rim - np.roll(rim, 1, axis=0), axis=1).sum())
        areas = _areas(corners)
        if abs(areas.sum() - _areas(old).sum()) > self.tolerance * perimeter:
            return False
        if (2 * areas > self.max_width * np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)).any():
            return False  # a face wider than max_width
        cover = sorted({i for f in faces for i in self.cover[f]})
        for f in faces:
            self.alive[f] = False
            for u in self.faces[f]:
                self.incident[u].discard(f)
        for face in new:
            self.faces.append(tuple(int(i) for i in face))
            self.cover.append(cover)
            self.alive.append(True)
            for u in face:
                self.incident[int(u)].add(len(self.faces) - 1)
        return True

    def _flat_basis(self, points: np.ndarray, fan: np.ndarray) -> np.ndarray | None:
        """(2, 3) an orthonormal basis (u, w) of the plane that fits ``points`` (N, 3) best, u x w along the fan's
        faces (k, 3, 3); None where a point lies farther than the tolerance from it."""
        centred = points - points.mean(axis=0)
        basis = np.linalg.svd(centred)[2]  # rows: the plane's directions, then its normal
        if np.abs(centred @ basis[2]).max() > self.tolerance:
            return None
        if np.cross(fan[:, 1] - fan[:, 0], fan[:, 2] - fan[:, 0]).sum(axis=0) @ np.cross(basis[0], basis[1]) < 0:
            basis[1] = -basis[1]
        return basis[:2]

    def _straight(self, before: int, v: int, after: int) -> bool:
        """Whether v lies on the segment from ``before`` to ``after`` (within the tolerance of the line)."""
        a, b = self.vertices[v] - self.vertices[before], self.vertices[after] - self.vertices[before]
        length = float(np.linalg.norm(b))
        return (length > 0 and float(np.linalg.norm(np.cross(a, b))) <= self.tolerance * length
                and 0 < float(a @ b) < length * length)


def _vertices_between_flat_faces(vertices: np.ndarray, faces: np.ndarray, tolerance: float) -> np.ndarray:
    """(N,) the vertices of an edge whose two faces lie in one plane, wound alike (an edge met once each way, by
    two faces only), ascending: the only vertices a flat run can lose."""
    n = len(faces)
    normal = face_normals(vertices[faces])
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)  # (3F, 2) corner k -> k + 1
    owner = np.repeat(np.arange(n), 3)
    key = np.minimum(directed[:, 0], directed[:, 1]) * (len(vertices) + 1) + np.maximum(directed[:, 0], directed[:, 1])
    order = np.argsort(key, kind="stable")
    key, directed, owner = key[order], directed[order], owner[order]
    uses = np.bincount(np.unique(key, return_inverse=True)[1]) if len(key) else np.zeros(0, dtype=np.int64)
    twice = np.flatnonzero((key[:-1] == key[1:]) & (np.repeat(uses, uses)[:-1] == 2))  # the first of each pair
    a, b = owner[twice], owner[twice + 1]
    opposite = directed[twice, 0] == directed[twice + 1, 1]  # wound alike: the edge runs each way once
    shared = directed[twice]  # (E, 2) the edge's ends
    quad = vertices[np.concatenate([shared, _third(faces[a], shared)[:, None], _third(faces[b], shared)[:, None]], axis=1)]
    centred = quad - quad.mean(axis=1, keepdims=True)  # (E, 4, 3)
    in_plane = np.linalg.svd(centred, compute_uv=False)[:, 2] <= tolerance if len(quad) else np.zeros(0, dtype=bool)
    facing = np.einsum("kc,kc->k", normal[a], normal[b]) > 0
    return np.unique(shared[opposite & in_plane & facing])


def _third(faces: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """(E,) the corner of each face (E, 3) not on its edge (E, 2)."""
    off = (faces != edge[:, :1]) & (faces != edge[:, 1:])
    return faces[np.arange(len(faces)), off.argmax(axis=1)]


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) the least node of each node's connected component, the edges a (E,) - b (E,)."""
    label = np.arange(n)
    while True:
        low = np.minimum(label[a], label[b])
        before = label.copy()
        np.minimum.at(label, a, low)
        np.minimum.at(label, b, low)
        label = label[label]  # pointer jumping: a chain's label reaches its root in a few rounds
        if np.array_equal(label, before):
            return label


def _ear_clipping(plane: np.ndarray, tolerance: float) -> np.ndarray | None:
    """A simple polygon's counter-clockwise points (L, 2) cut into L - 2 triangles (indices (L - 2, 3), counter-
    clockwise), each an ear: a corner convex by more than ``tolerance`` whose triangle holds no other corner. None
    where no ear is found."""
    left = list(range(len(plane)))
    ears = []
    while len(left) > 3:
        for i in range(len(left)):
            a, b, c = left[i - 1], left[i], left[(i + 1) % len(left)]
            if not _convex(plane[a], plane[b], plane[c], tolerance):
                continue  # a reflex or straight corner: its ear would be inside out or flat
            others = plane[[k for k in left if k not in (a, b, c)]]
            if len(others) and _inside_or_on(plane[a], plane[b], plane[c], others).any():
                continue
            ears.append((a, b, c))
            del left[i]
            break
        else:
            return None
    if not _convex(*plane[left], tolerance):
        return None
    ears.append(tuple(left))
    return np.asarray(ears, dtype=np.int64)


def _convex(a: np.ndarray, b: np.ndarray, c: np.ndarray, tolerance: float) -> bool:
    """Whether the 2-D corner abc turns counter-clockwise, b farther than ``tolerance`` from the line ac."""
    ab, ac = b - a, c - a
    return float(ab[0] * ac[1] - ab[1] * ac[0]) > tolerance * float(np.linalg.norm(ac))


def _inside_or_on(a: np.ndarray, b: np.ndarray, c: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) whether each 2-D point (N, 2) lies in the counter-clockwise triangle abc or on its edges."""
    def side(p, q):
        return (q[0] - p[0]) * (points[:, 1] - p[1]) - (q[1] - p[1]) * (points[:, 0] - p[0])

    return (side(a, b) >= 0) & (side(b, c) >= 0) & (side(c, a) >= 0)


def _areas(triangles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) -> (T,) areas."""
    return 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)


def _least_barycentric(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(...,) the least barycentric coordinate of each point (..., 3) projected into its triangle's (..., 3, 3) plane
    (negative: outside, by that much of the triangle); -inf for a degenerate triangle."""
    e1, e2 = triangles[..., 1, :] - triangles[..., 0, :], triangles[..., 2, :] - triangles[..., 0, :]
    d = points - triangles[..., 0, :]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    p1, p2 = (d * e1).sum(-1), (d * e2).sum(-1)
    det = d11 * d22 - d12 * d12
    ok = det > 0
    det = np.where(ok, det, 1.0)
    s, t = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
    return np.where(ok, np.minimum(np.minimum(s, t), 1 - s - t), -np.inf)


def _rim(v: int, fan: list) -> tuple[list, bool, list] | None:
    """The rim of ``v``'s fan of faces (each (3,), wound alike, all using v) in their winding: (its vertices, closed,
    the faces in that order: face order[m] spans rim vertex m to m + 1); None where the faces do not make one fan
    (a rim vertex met twice)."""
    following, face_from = {}, {}
    for index, face in enumerate(fan):
        k = face.index(v)
        x, y = face[(k + 1) % 3], face[(k + 2) % 3]
        if x in following:
            return None
        following[x], face_from[x] = y, index
    heads = set(following) - set(following.values())
    if len(heads) > 1:
        return None
    closed = not heads
    loop = [heads.pop() if heads else next(iter(following))]
    while loop[-1] in following and len(loop) <= len(fan):
        nxt = following[loop[-1]]
        if nxt == loop[0]:
            break
        loop.append(nxt)
    if len(loop) != len(fan) + (0 if closed else 1):
        return None
    return loop, closed, [face_from[x] for x in loop[:len(fan)]]


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(sum(counts),) the indices start_i, ..., start_i + count_i - 1 of every range, one after the other."""
    offsets = np.cumsum(counts) - counts
    return np.repeat(starts - offsets, counts) + np.arange(int(counts.sum()))
