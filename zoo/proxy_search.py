"""The search on a proxy that :class:`zoo.proxy_collider.ProxyCollider` runs at a call: what it takes and gives, and its
numpy reference.

A call's search is one compiled loop (:func:`zoo.proxy_kernel.search_faces`, what runs); :func:`numpy_search` is the
same algorithm as a fixed handful of vectorised numpy passes, each with one proxy read for all the faces
(``ProxyCollider(kernel="numpy")``), the reference the compiled loop is tested against. Both take the same records:

* :class:`SearchMesh`: the mesh as the search reads it, made once per collider;
* :class:`SearchCall`: the pose and what the search stops at, per call;
* :class:`FaceMemory`: what crosses calls (each face's last answer; the held bounds, which only the compiled loop
  keeps and applies);

and give :class:`ProxyAnswers`. The steps (clusters, faces, the search inside) are described in
:mod:`zoo.proxy_collider`'s docstring.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .collider import CoherenceStats
from .proxy import IN_BAND
from .simplex import descent_segment, frank_wolfe_gap, on_simplex


class SearchMesh(NamedTuple):
    """A collider's mesh as a search reads it, in the mesh's frame, made once."""

    faces: np.ndarray  # (F, 3) int64
    vertices: np.ndarray  # (V, 3)
    reach: np.ndarray  # (F, 3) zoo.bounds.triangle_reach: how far each corner reaches over the face
    ball: np.ndarray  # (F,) the radius about the lowest corner that holds the face
    clusters: np.ndarray  # (C, K) int64 faces of each cluster (-1 padding)
    cluster_centre: np.ndarray  # (C, 3)
    cluster_radius: np.ndarray  # (C,)
    line_apex: np.ndarray  # (F,) int64 the corner a long face's line of starts runs from (line_starts)
    line_count: np.ndarray  # (F,) int64 the starts on that line (0: a face shorter than LINE_START_CELLS cells)


class SearchCall(NamedTuple):
    """One call of a search: the pose and what the search stops at."""

    rotation: np.ndarray  # (3, 3) the mesh's rotation in the SDF's frame
    shift: np.ndarray  # (3,) its translation
    search: float  # m: the search margin (a face whose proxy minimum may be at most this is searched)
    net: float  # m: a face whose answer is at most this is given
    stop: float  # the Frank-Wolfe gap below which a search stops
    search_steps: int  # the descents a cold face takes at most
    warm_steps: int  # and a warm one
    n_clusters: int  # the first clusters searched (the rest passed over)
    bounds_lo: np.ndarray  # (3,) the SDF's bounds
    bounds_hi: np.ndarray  # (3,)
    pattern: np.ndarray  # (P, 3) a cold face's starting barycentrics
    hold: bool  # whether faces are passed over on their held bounds (FaceMemory)
    stamp: int  # this call's stamp (zoo.proxy_kernel.KernelBuffers.vertex_stamp)


class FaceMemory(NamedTuple):
    """What crosses calls: each face's last answer, the warm start, and the bounds that pass faces over (``hold``).
    A face (a cluster) whose key, less L times its cluster's motion now, exceeds the search margin cannot hold a
    contact and is passed over with no read; the compiled loop updates the keys."""

    last_bary: np.ndarray  # (F, 3) each face's last answer (NaN: none)
    cluster_motion: np.ndarray  # (C,) m: how far each cluster's points have moved relative to the SDF, in all
    cluster_key: np.ndarray  # (C,) the least of its faces' keys
    face_key: np.ndarray  # (F,) its bound on the proxy's minimum when last answered, plus L times its cluster's
    #                       motion then (-inf: none)


@dataclass
class ProxyAnswers:
    """The proxy's minima over faces, as a search leaves them: ``faces`` (N,) (the collider's order), their corners
    ``tri`` (N, 3, 3) in the SDF's frame, the minimisers ``bary`` (N, 3), the proxy's ``values`` (N,), ``grads``
    (N, 3) and ``status`` (N,) there."""

    faces: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    values: np.ndarray
    grads: np.ndarray
    status: np.ndarray

    def take(self, rows: np.ndarray) -> ProxyAnswers:
        """The answers at ``rows`` (K,), in that order."""
        return ProxyAnswers(self.faces[rows], self.tri[rows], self.bary[rows], self.values[rows], self.grads[rows],
                            self.status[rows])

    def with_values(self, rows: np.ndarray, values: np.ndarray, grads: np.ndarray) -> ProxyAnswers:
        """A copy whose rows ``rows`` (K,) hold the ``values`` (K,) and ``grads`` (K, 3) given (the SDF's, where the
        proxy's were only a bound); this one is left as it is."""
        out = ProxyAnswers(self.faces, self.tri, self.bary, self.values.copy(), self.grads.copy(), self.status)
        out.values[rows], out.grads[rows] = values, grads
        return out


LINE_START_CELLS = 4  # a long face's cold search also starts every this many proxy cells along its length


def line_starts(corners: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a cold search starts along a long face, besides the pattern: on the line from the corner opposite its
    shortest edge to that edge's midpoint (a sliver's length), every ``LINE_START_CELLS`` cells of ``spacing``. A
    sliver 100 cells long (a gear's flank: 10 mm by 0.25) meets an SDF that varies along it, with minima the
    pattern's seven starts miss. ``corners`` (F, 3, 3) -> apex (F,) int64 (the corner), count (F,) int64 (the
    starts, at s = 1 .. count over count + 1 of the way, :func:`line_points`)."""
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)  # (F, 3): edge i joins corners i-1 and i
    shortest = edges.argmin(axis=1)
    apex = (shortest + 1) % 3
    rows = np.arange(len(corners))
    ends = corners[rows, shortest] + corners[rows, (shortest + 2) % 3]
    length = np.linalg.norm(corners[rows, apex] - ends / 2, axis=1)
    count = np.floor(length / (LINE_START_CELLS * spacing)).astype(np.int64)
    return apex.astype(np.int64), count


def line_points(apex: np.ndarray, count: int) -> np.ndarray:
    """The barycentrics (W, count, 3) of :func:`line_starts`' points on faces whose line runs from corner ``apex``
    (W,): (1 - s) at the apex, s / 2 at the others, s = 1 .. count over count + 1."""
    s = np.arange(1, count + 1) / (count + 1)
    points = np.empty((len(apex), count, 3))
    points[:] = (s / 2)[None, :, None]
    points[np.arange(len(apex)), :, apex] = 1 - s
    return points


def numpy_search(call: SearchCall, mesh: SearchMesh, proxy, memory: FaceMemory, stats: CoherenceStats) -> ProxyAnswers:
    """The faces whose proxy minimum is at most ``call.net``, with the proxy (a ``zoo.proxy.ProxySDF``) at their
    minima; ``memory.last_bary`` is read and updated (the held bounds are not used); ``stats`` counted."""
    faces, values, grads, status, tri = _near_faces(call, mesh, proxy, stats)
    bary, values, grads, status = _search(call, proxy, memory, faces, tri, values, grads, status, stats,
                                          mesh.line_apex[faces], mesh.line_count[faces])
    return ProxyAnswers(faces, tri, bary, values, grads, status).take(np.flatnonzero(values <= call.net))


# -- culling ---------------------------------------------------------------------------------------------------------


def _near_faces(call: SearchCall, mesh: SearchMesh, proxy, stats: CoherenceStats):
    """The faces (N,) that may come within the search margin of the SDF, and the proxy at their vertices: (faces,
    values (N, 3), gradients (N, 3, 3), status (N, 3), vertices (N, 3, 3) in the SDF's frame): clusters first, then
    each face on its vertices' values."""
    rotation, shift, search = call.rotation, call.shift, call.search
    centres = mesh.cluster_centre[:call.n_clusters] @ rotation.T + shift
    kept = _may_touch(call, proxy, centres, mesh.cluster_radius[:call.n_clusters], stats)
    faces = mesh.clusters[:call.n_clusters][kept].reshape(-1)
    faces = faces[faces >= 0]
    stats.faces_near = int(faces.size)
    corner_ids = mesh.faces[faces]  # (N, 3)
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[corner_ids] = True
    vertices = np.flatnonzero(used)
    row = np.empty(len(mesh.vertices), dtype=np.int64)
    row[vertices] = np.arange(vertices.size)
    local = mesh.vertices[vertices] @ rotation.T + shift
    f, g, status = counted_read(proxy, local, stats)
    corner = row[corner_ids]  # (N, 3) rows of ``vertices``
    values = f[corner]
    lip = proxy.lipschitz
    bound = np.maximum((values - lip * mesh.reach[faces]).max(axis=1), values.min(axis=1) - lip * mesh.ball[faces])
    near = bound <= search
    stats.faces_skipped = int(faces.size - near.sum())
    corner = corner[near]
    return faces[near], values[near], g[corner], status[corner], local[corner]


def _may_touch(call: SearchCall, proxy, centres: np.ndarray, radii: np.ndarray, stats: CoherenceStats) -> np.ndarray:
    """(N,) bool: the balls (centres (N, 3), radii (N,)) that may hold a point within the search margin of the SDF."""
    outside = np.linalg.norm(np.maximum(call.bounds_lo - centres, 0) + np.maximum(centres - call.bounds_hi, 0), axis=-1)
    rows = np.flatnonzero(outside <= radii + call.search)
    out = np.zeros(len(centres), dtype=bool)
    if rows.size:
        values = counted_read(proxy, centres[rows], stats)[0]
        out[rows] = values - proxy.lipschitz * radii[rows] <= call.search
    return out


def counted_read(proxy, points: np.ndarray, stats: CoherenceStats):
    """``proxy.read_numpy(points)`` (points (N, 3): values, gradients, status), counted in ``stats.proxy_reads``."""
    stats.proxy_reads += int(points.shape[0])
    return proxy.read_numpy(points)


# -- the search inside -----------------------------------------------------------------------------------------------


def _search(call: SearchCall, proxy, memory: FaceMemory, faces, tri, vertex_values, vertex_grads, vertex_status,
            stats: CoherenceStats, line_apex, line_count):
    """Each face's minimum on the proxy, from the proxy at its vertices (values (S, 3), gradients (S, 3, 3), status
    (S, 3)), and its line of starts (``line_apex``, ``line_count`` (S,), :func:`line_starts`): bary (S, 3),
    values (S,), gradients (S, 3), status (S,) int8 there."""
    s = len(faces)
    stats.candidates = s
    rows = np.arange(s)
    lowest = vertex_values.argmin(axis=1)
    bary = np.eye(3)[lowest]
    value, grad, state = vertex_values[rows, lowest], vertex_grads[rows, lowest], vertex_status[rows, lowest]
    # the vertex test: a lowest vertex that is a KKT point is the answer; the screen drops what stays above
    gap = frank_wolfe_gap(tri, bary, grad)
    open_ = np.flatnonzero((gap > call.stop) & (value - gap <= call.search))
    stats.screened = int(np.count_nonzero(value - gap > call.search))
    if open_.size:
        _search_inside(call, proxy, memory, faces[open_], tri[open_], open_, bary, value, grad, state, stats,
                       line_apex[open_], line_count[open_])
    return bary, value, grad, state


def _search_inside(call: SearchCall, proxy, memory: FaceMemory, faces, tri, rows, bary, value, grad, state,
                   stats: CoherenceStats, line_apex, line_count) -> None:
    """The search inside the faces ``faces`` (W,) (``rows`` (W,) of the arrays ``bary``, ``value``, ``grad``,
    ``state``, which hold the lowest vertex's answer and are updated in place): from the last answer where the face
    has one, else the lowest of the pattern's points and its line's (``line_apex``, ``line_count`` (W,)), then up
    to ``call.search_steps`` descents."""
    w = len(faces)
    last = memory.last_bary[faces]  # (W, 3), NaN where none
    warm = np.isfinite(last[:, 0])
    stats.warm, stats.cold = int(warm.sum()), int(w - warm.sum())
    # a warm face: its last answer, unless a corner (its read is that vertex's, at least the lowest's: nothing to read)
    warm_inside = np.flatnonzero(warm & ((last == 0).sum(axis=1) < 2))
    for chosen, starts in ((warm_inside, last[warm_inside][:, None]),
                           (np.flatnonzero(~warm), call.pattern[None])):  # a cold one: the pattern inside it
        if chosen.size:
            _lowest_start(proxy, tri[chosen], rows[chosen], np.broadcast_to(starts, (chosen.size,) + starts.shape[1:]),
                          bary, value, grad, state, stats)
    cold = np.flatnonzero(~warm)
    for count in np.unique(line_count[cold]):  # a long cold face: its line's starts too, lower ones kept
        if count:
            chosen = cold[line_count[cold] == count]
            _lowest_start(proxy, tri[chosen], rows[chosen], line_points(line_apex[chosen], int(count)), bary, value,
                          grad, state, stats, in_band_only=True)
    active = np.arange(w)
    for step in range(call.search_steps):
        if step == call.warm_steps:
            active = active[~warm[active]]
        ra = rows[active]
        gap = frank_wolfe_gap(tri[active], bary[ra], grad[ra])
        active = active[(gap > call.stop) & (value[ra] - gap <= call.search) & (state[ra] == IN_BAND)]
        if not active.size:
            break
        ra = rows[active]
        b, v, gr, st = _descend(proxy, tri[active], bary[ra], value[ra], grad[ra], stats)
        lower = v < value[ra]
        active, ra = active[lower], ra[lower]
        bary[ra], value[ra], grad[ra], state[ra] = b[lower], v[lower], gr[lower], st[lower]
    memory.last_bary[faces] = bary[rows]


def _lowest_start(proxy, tri, rows, starts, bary, value, grad, state, stats, in_band_only: bool = False) -> None:
    """Read the proxy at the starts (W, K, 3) on the triangles (W, 3, 3), all in one read, and keep the lowest where
    it is below the answer held in ``rows`` (W,) of ``bary``, ``value``, ``grad`` and ``state`` (updated in place);
    ``in_band_only``: of the starts read in the proxy's band (a read out of it is a bound, not where the face is
    lowest)."""
    w, k = starts.shape[:2]
    f, g, status = counted_read(proxy, np.einsum("wkv,wvc->wkc", starts, tri).reshape(-1, 3), stats)
    f, g, status = f.reshape(w, k), g.reshape(w, k, 3), status.reshape(w, k)
    if in_band_only:
        f = np.where(status == IN_BAND, f, np.inf)
    best = f.argmin(axis=1)
    at = np.arange(w)
    lower = f[at, best] < value[rows]
    r = rows[lower]
    bary[r], value[r] = starts[at, best][lower], f[at, best][lower]
    grad[r], state[r] = g[at, best][lower], status[at, best][lower]


def _descend(proxy, tri, bary, f0, g, stats):
    """One line search along the steepest descent of the proxy inside each triangle (W, 3, 3) from ``bary`` (W, 3)
    (f0 (W,) and g (W, 3) there), to where it leaves the triangle: -> bary, values, gradients, status at the lower
    of its end and the parabola's minimiser (the parabola through f0, the slope and the end's value)."""
    direction, reach = descent_segment(tri, bary, g)
    end = on_simplex(bary + reach[:, None] * direction)
    p0, p1 = np.einsum("wv,wvc->wc", bary, tri), np.einsum("wv,wvc->wc", end, tri)
    f1, g1, s1 = counted_read(proxy, p1, stats)
    slope = ((p1 - p0) * g).sum(axis=1)  # < 0 along a descent
    curvature = f1 - f0 - slope
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(curvature > 0, np.clip(-slope / (2 * curvature), 0, 1), 1.0)
    t = np.where(np.isfinite(t), t, 0.0)
    mid = on_simplex(bary + (t * reach)[:, None] * direction)
    fm, gm, sm = f1.copy(), g1.copy(), s1.copy()  # where t is 1 the minimiser is the end, read already
    inner = np.flatnonzero(t != 1.0)
    fm[inner], gm[inner], sm[inner] = counted_read(proxy, np.einsum("wv,wvc->wc", mid[inner], tri[inner]), stats)
    end_lower = f1 < fm
    pick = end_lower[:, None]
    return (np.where(pick, end, mid), np.where(end_lower, f1, fm), np.where(pick, g1, gm), np.where(end_lower, s1, sm))


__all__ = ["SearchMesh", "SearchCall", "FaceMemory", "ProxyAnswers", "numpy_search", "counted_read", "line_starts",
           "line_points", "LINE_START_CELLS"]
