"""The per-face passes of :class:`zoo.proxy_collider.ProxyCollider`, compiled: one loop over the faces near the SDF.

The numpy passes of ``ProxyCollider`` (``kernel="numpy"``, the reference these are tested against) cost a few
microseconds a numpy call, and a step makes a few hundred of them over thousands of faces. Here the same algorithm
is one compiled loop (numba, ``cache=True``: compiled once per machine, then loaded): the clusters' cull, each
face's Lipschitz bound on its vertices' proxy values (each vertex read once a call), the vertex test and the screen,
and the warm-started projected-gradient search, with the trilinear read (:func:`read`) inlined. Answers are those of
the numpy passes up to rounding: the same reads at the same points, in the same order per face.

A lazy proxy's brick not ready yet cannot be baked from compiled code (baking asks the SDF): a read that lands in
one records the brick in ``missing`` and leaves its face out; the caller bakes what was recorded and calls again
(:meth:`zoo.proxy_collider.ProxyCollider`), so a call answers as if every brick had been ready.

numba is imported here only: ``import zoo`` does not load it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .contact_filters import closing_speed, usable

try:
    from numba import njit
except ImportError as error:  # pragma: no cover - numba is a dependency of sdfzoo
    raise ImportError("the proxy collider needs numba: pip install numba") from error

IN_BAND, ABOVE, UNKNOWN = 0, 1, -1  # zoo.proxy's read status
MISSING = 2  # a read's status where its brick is not ready (a lazy proxy): the caller bakes it and calls again
BOUNDARY = 1e-9  # as zoo.simplex.BOUNDARY
TINY = np.finfo(np.float64).tiny

# What a call counts (one record; the first five are zoo.collider.CoherenceStats's names)
COUNTS = np.dtype([("faces_near", np.int64), ("faces_skipped", np.int64), ("candidates", np.int64), ("warm", np.int64),
                   ("cold", np.int64), ("screened", np.int64), ("reads", np.int64), ("missing", np.int64),
                   ("searched", np.int64), ("out", np.int64)])


class KernelBuffers(NamedTuple):
    """What :func:`search_faces` writes, sized for the mesh once (:func:`kernel_buffers`)."""

    vertex_stamp: np.ndarray  # (V,) int64: a vertex whose stamp is the call's was read this call,
    vertex_local: np.ndarray  # (V, 3) its place in the SDF's frame
    vertex_answer: np.ndarray  # (V, 5) and its read (value, gradient, status)
    missing: np.ndarray  # (M,) int64 bricks not ready that reads met (-1 - b: brick b's coarse value alone)
    counts: np.ndarray  # (1,) COUNTS, zeroed by the caller
    face: np.ndarray  # (F,) int64 the faces answered at most ``net`` (counts.out rows),
    tri: np.ndarray  # (F, 3, 3) their corners, SDF frame
    bary: np.ndarray  # (F, 3) their minimisers
    value: np.ndarray  # (F,) the proxy there
    grad: np.ndarray  # (F, 3)
    status: np.ndarray  # (F,) int8
    searched_face: np.ndarray  # (F,) int64 the faces searched inside (counts.searched rows)
    searched_bary: np.ndarray  # (F, 3) and their answers: the next call's warm starts


def kernel_buffers(n_vertices: int, n_faces: int, n_missing: int = 4096) -> KernelBuffers:
    """Empty :class:`KernelBuffers` for a mesh of ``n_vertices`` and ``n_faces``."""
    return KernelBuffers(np.zeros(n_vertices, dtype=np.int64), np.zeros((n_vertices, 3)), np.zeros((n_vertices, 5)),
                         np.zeros(n_missing, dtype=np.int64), np.zeros(1, dtype=COUNTS),
                         np.zeros(n_faces, dtype=np.int64), np.zeros((n_faces, 3, 3)), np.zeros((n_faces, 3)),
                         np.zeros(n_faces), np.zeros((n_faces, 3)), np.zeros(n_faces, dtype=np.int8),
                         np.zeros(n_faces, dtype=np.int64), np.zeros((n_faces, 3)))


@njit(cache=True, error_model="numpy", inline="always")
def read(px, py, pz, grid, missing, counts):
    """The proxy ``grid`` (``zoo.proxy.ProxyGrid``) at one point (SDF frame): (value, gx, gy, gz, status), as
    ``ProxySDF.read_numpy`` gives it; status ``MISSING`` (the rest NaN) where the point's brick is not ready, its flat
    index b then added to ``missing`` (-1 - b for a point outside the region: its nearest brick's coarse value alone is
    needed). ``counts``: a ``COUNTS`` record (its reads and missing counted).

    One exit, where every array is used last: numba counts a reference to each array the read unpacks, and prunes
    those counts only where they meet in one block; left in the branches, they cost four times the read."""
    lo, hi, inv_h, band, lip, brick_of, nodes, status, coarse_value, coarse_grad, n_bricks, brick_side, first_centre = grid
    counts.reads += 1
    ux, uy, uz = (px - lo[0]) * inv_h, (py - lo[1]) * inv_h, (pz - lo[2]) * inv_h
    fx, fy, fz = math.floor(ux), math.floor(uy), math.floor(uz)
    cx, cy, cz = int(fx), int(fy), int(fz)
    last_x, last_y, last_z = 8 * n_bricks[0] - 1, 8 * n_bricks[1] - 1, 8 * n_bricks[2] - 1
    inside = 0 <= cx <= last_x and 0 <= cy <= last_y and 0 <= cz <= last_z
    if inside:
        tx, ty, tz = ux - fx, uy - fy, uz - fz
    else:
        cx, cy, cz = min(max(cx, 0), last_x), min(max(cy, 0), last_y), min(max(cz, 0), last_z)
        tx, ty, tz = min(max(ux - cx, 0.0), 1.0), min(max(uy - cy, 0.0), 1.0), min(max(uz - cz, 0.0), 1.0)
    bx, by, bz = cx >> 3, cy >> 3, cz >> 3
    flat = (bx * n_bricks[1] + by) * n_bricks[2] + bz
    row = brick_of[flat]
    value, gx, gy, gz, state = math.nan, math.nan, math.nan, math.nan, MISSING
    if row < 0 and (inside or math.isnan(coarse_value[flat])):  # outside the region, the nearest brick's coarse value is needed
        n = counts.missing
        if n < missing.size:
            missing[n] = flat if inside else -1 - flat
        counts.missing = n + 1
    else:
        row = max(row, 0)
        ix, iy, iz = cx & 7, cy & 7, cz & 7
        cell_status = status[row * 512 + ix * 64 + iy * 8 + iz]
        if inside and cell_status == IN_BAND:
            b = row * 729 + ix * 81 + iy * 9 + iz  # the cell's first node; corner (i, j, k) at b + 81 i + 9 j + k
            c000, c001, c010, c011 = float(nodes[b]), float(nodes[b + 1]), float(nodes[b + 9]), float(nodes[b + 10])
            c100, c101, c110, c111 = float(nodes[b + 81]), float(nodes[b + 82]), float(nodes[b + 90]), float(nodes[b + 91])
            d00, d01, d10, d11 = c001 - c000, c011 - c010, c101 - c100, c111 - c110  # d/dz along the 4 edges
            e00, e01, e10, e11 = c000 + d00 * tz, c010 + d01 * tz, c100 + d10 * tz, c110 + d11 * tz
            a0, a1 = e00 + (e01 - e00) * ty, e10 + (e11 - e10) * ty
            dz0, dz1 = d00 + (d01 - d00) * ty, d10 + (d11 - d10) * ty
            dy0, dy1 = e01 - e00, e11 - e10
            value, gx, gy, gz, state = (a0 + (a1 - a0) * tx, (a1 - a0) * inv_h, (dy0 + (dy1 - dy0) * tx) * inv_h,
                                        (dz0 + (dz1 - dz0) * tx) * inv_h, IN_BAND)
        else:  # out of band: the brick centre's bound f(c) - L |p - c| (at least the band in an ABOVE cell)
            ax = px - (bx * brick_side + first_centre[0])
            ay = py - (by * brick_side + first_centre[1])
            az = pz - (bz * brick_side + first_centre[2])
            value = float(coarse_value[flat]) - lip * math.sqrt(ax * ax + ay * ay + az * az)
            if inside:
                if cell_status == ABOVE:
                    value = max(value, band)
                gx, gy, gz = float(coarse_grad[flat, 0]), float(coarse_grad[flat, 1]), float(coarse_grad[flat, 2])
            else:  # outside the region: also at least the band plus the distance to it; pointing away from it
                ax = px - min(max(px, lo[0]), hi[0])
                ay = py - min(max(py, lo[1]), hi[1])
                az = pz - min(max(pz, lo[2]), hi[2])
                gap = math.sqrt(ax * ax + ay * ay + az * az)
                value = max(value, band + gap)
                scale = 1.0 / max(gap, TINY)
                gx, gy, gz = ax * scale, ay * scale, az * scale
            state = ABOVE if value >= band else UNKNOWN
    arrays = (lo.size + hi.size + brick_of.size + nodes.size + status.size + coarse_value.size + coarse_grad.size
              + n_bricks.size + first_centre.size + missing.size)
    return value, gx, gy, gz, state + 0 * arrays


@njit(cache=True, error_model="numpy", inline="always")
def _frank_wolfe_gap(t, b0, b1, b2, gx, gy, gz):
    """``zoo.simplex.frank_wolfe_gap`` at barycentrics (b0, b1, b2) on the triangle ``t`` (3, 3) with gradient g there."""
    s0 = gx * t[0, 0] + gy * t[0, 1] + gz * t[0, 2]
    s1 = gx * t[1, 0] + gy * t[1, 1] + gz * t[1, 2]
    s2 = gx * t[2, 0] + gy * t[2, 1] + gz * t[2, 2]
    return s0 * b0 + s1 * b1 + s2 * b2 - min(s0, s1, s2)


@njit(cache=True, error_model="numpy", inline="always")
def _descent_segment(t, b, gx, gy, gz, direction):
    """``zoo.simplex.descent_segment`` for one face: the steepest descent's barycentric direction (written
    into ``direction`` (3,)) and how far along it the triangle reaches (returned)."""
    e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    a11, a12, a22 = e1x * e1x + e1y * e1y + e1z * e1z, e1x * e2x + e1y * e2y + e1z * e2z, e2x * e2x + e2y * e2y + e2z * e2z
    r1, r2 = -(gx * e1x + gy * e1y + gz * e1z), -(gx * e2x + gy * e2y + gz * e2z)
    det = a11 * a22 - a12 * a12
    if det > 1e-6 * a11 * a22:
        x, y = (a22 * r1 - a12 * r2) / det, (a11 * r2 - a12 * r1) / det
        direction[0], direction[1], direction[2] = -(x + y), x, y
    else:  # a needle
        direction[0] = direction[1] = direction[2] = 0.0
    blocked, first = 0, 0
    for v in range(3):
        if b[v] <= BOUNDARY and direction[v] < 0:
            if blocked == 0:
                first = v
            blocked += 1
    if blocked == 1:  # along the edge the point lies on (opposite vertex ``first``)
        j, k = (first + 1) % 3, (first + 2) % 3
        ex, ey, ez = t[k, 0] - t[j, 0], t[k, 1] - t[j, 1], t[k, 2] - t[j, 2]
        along = -(gx * ex + gy * ey + gz * ez) / max(ex * ex + ey * ey + ez * ez, TINY)
        direction[first], direction[j], direction[k] = 0.0, -along, along
    elif blocked > 1:
        direction[0] = direction[1] = direction[2] = 0.0
    reach = math.inf
    for v in range(3):
        if direction[v] < 0:
            reach = min(reach, b[v] / -direction[v])
    reach = reach if math.isfinite(reach) else 0.0
    if not reach * max(abs(direction[0]), abs(direction[1]), abs(direction[2])) > 0:
        # nowhere (a needle, or a corner the plane's descent leaves): towards Frank-Wolfe's vertex, a descent wherever
        # its gap is positive
        s0 = gx * t[0, 0] + gy * t[0, 1] + gz * t[0, 2]
        s1 = gx * t[1, 0] + gy * t[1, 1] + gz * t[1, 2]
        s2 = gx * t[2, 0] + gy * t[2, 1] + gz * t[2, 2]
        k = 0 if s0 <= min(s1, s2) else (1 if s1 <= s2 else 2)
        for v in range(3):
            direction[v] = (1.0 if v == k else 0.0) - b[v]
        reach = 1.0
    arrays = t.size + b.size + direction.size  # one exit, every array used last: see read
    return reach + 0 * arrays


@njit(cache=True, error_model="numpy", inline="always")
def _on_simplex(b0, b1, b2):
    b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
    s = b0 + b1 + b2
    return b0 / s, b1 / s, b2 / s


@njit(cache=True, error_model="numpy", inline="always")
def _descend(t, b, f0, gx, gy, gz, grid, missing, counts, direction, answer):
    """``ProxyCollider._descend`` for one face from barycentrics ``b`` (3,) (f0, g there): writes (b0, b1, b2, value,
    gx, gy, gz, status) of the lower of the segment's end and the parabola's minimiser into ``answer`` (8,)."""
    reach = _descent_segment(t, b, gx, gy, gz, direction)
    n0, n1, n2 = _on_simplex(b[0] + reach * direction[0], b[1] + reach * direction[1], b[2] + reach * direction[2])
    p0x, p0y, p0z = b[0] * t[0, 0] + b[1] * t[1, 0] + b[2] * t[2, 0], b[0] * t[0, 1] + b[1] * t[1, 1] + b[2] * t[2, 1], \
        b[0] * t[0, 2] + b[1] * t[1, 2] + b[2] * t[2, 2]
    p1x, p1y, p1z = n0 * t[0, 0] + n1 * t[1, 0] + n2 * t[2, 0], n0 * t[0, 1] + n1 * t[1, 1] + n2 * t[2, 1], \
        n0 * t[0, 2] + n1 * t[1, 2] + n2 * t[2, 2]
    f1, g1x, g1y, g1z, s1 = read(p1x, p1y, p1z, grid, missing, counts)
    found = s1 != MISSING
    slope = (p1x - p0x) * gx + (p1y - p0y) * gy + (p1z - p0z) * gz
    curvature = f1 - f0 - slope
    step = 1.0
    if curvature > 0:
        step = min(max(-slope / (2 * curvature), 0.0), 1.0)
    if not math.isfinite(step):
        step = 0.0
    if found and step == 1.0:  # the parabola's minimiser is the segment's end, read already
        answer[0], answer[1], answer[2], answer[3], answer[4], answer[5], answer[6], answer[7] = n0, n1, n2, f1, g1x, g1y, g1z, s1
    elif found:
        m0, m1, m2 = _on_simplex(b[0] + step * reach * direction[0], b[1] + step * reach * direction[1],
                                 b[2] + step * reach * direction[2])
        fm, gmx, gmy, gmz, sm = read(m0 * t[0, 0] + m1 * t[1, 0] + m2 * t[2, 0], m0 * t[0, 1] + m1 * t[1, 1] + m2 * t[2, 1],
                                     m0 * t[0, 2] + m1 * t[1, 2] + m2 * t[2, 2], grid, missing, counts)
        found = sm != MISSING
        if found and f1 < fm:
            answer[0], answer[1], answer[2], answer[3], answer[4], answer[5], answer[6], answer[7] = n0, n1, n2, f1, g1x, g1y, g1z, s1
        elif found:
            answer[0], answer[1], answer[2], answer[3], answer[4], answer[5], answer[6], answer[7] = m0, m1, m2, fm, gmx, gmy, gmz, sm
    arrays = t.size + b.size + direction.size + answer.size + missing.size + grid.nodes.size  # one exit, every array used last: see read
    return found | (arrays < 0)


@njit(cache=True, error_model="numpy")
def search_faces(call, mesh, grid, memory, out):
    """The cull and the search of one call (``ProxyCollider._near_faces`` then ``_search``, see its module docstring):
    ``call`` a ``zoo.proxy_search.SearchCall``, ``mesh`` a ``SearchMesh``, ``grid`` the proxy (``zoo.proxy.ProxyGrid``),
    ``memory`` the ``FaceMemory`` it reads and updates, ``out`` the :class:`KernelBuffers` it writes."""
    rotation, shift, search, net, stop = call.rotation, call.shift, call.search, call.net, call.stop
    search_steps, warm_steps, pattern, hold, stamp = call.search_steps, call.warm_steps, call.pattern, call.hold, call.stamp
    bounds_lo, bounds_hi, lipschitz = call.bounds_lo, call.bounds_hi, grid.lipschitz
    faces, vertices, reach, ball = mesh.faces, mesh.vertices, mesh.reach, mesh.ball
    clusters, cluster_centre, cluster_radius = mesh.clusters, mesh.cluster_centre, mesh.cluster_radius
    line_apex, line_count = mesh.line_apex, mesh.line_count
    last_bary, cluster_motion, cluster_key, face_key = memory.last_bary, memory.cluster_motion, memory.cluster_key, memory.face_key
    vertex_stamp, vertex_local, vertex_answer, missing = out.vertex_stamp, out.vertex_local, out.vertex_answer, out.missing
    counts = out.counts[0]
    near = np.empty(faces.shape[0], dtype=np.int64)
    cluster_of = np.empty(faces.shape[0], dtype=np.int64)
    n_near = 0
    t = np.empty((3, 3))
    b = np.empty(3)
    direction = np.empty(3)
    answer = np.empty(8)
    size = clusters.shape[1]
    n_clusters = min(call.n_clusters, clusters.shape[0])
    for c in range(n_clusters):
        # the cluster's ball: beyond the SDF's bounds grown by the search margin, or proven above it by one read
        px = rotation[0, 0] * cluster_centre[c, 0] + rotation[0, 1] * cluster_centre[c, 1] + rotation[0, 2] * cluster_centre[c, 2] + shift[0]
        py = rotation[1, 0] * cluster_centre[c, 0] + rotation[1, 1] * cluster_centre[c, 1] + rotation[1, 2] * cluster_centre[c, 2] + shift[1]
        pz = rotation[2, 0] * cluster_centre[c, 0] + rotation[2, 1] * cluster_centre[c, 1] + rotation[2, 2] * cluster_centre[c, 2] + shift[2]
        ox = max(bounds_lo[0] - px, 0.0) + max(px - bounds_hi[0], 0.0)
        oy = max(bounds_lo[1] - py, 0.0) + max(py - bounds_hi[1], 0.0)
        oz = max(bounds_lo[2] - pz, 0.0) + max(pz - bounds_hi[2], 0.0)
        if math.sqrt(ox * ox + oy * oy + oz * oz) > cluster_radius[c] + search:
            continue
        moved = lipschitz * cluster_motion[c]
        if hold and cluster_key[c] - moved > search:  # every face of it held above the margin
            continue
        value = read(px, py, pz, grid, missing, counts)[0]
        if not value - lipschitz * cluster_radius[c] <= search:  # NaN (missing) keeps it: its faces say
            if math.isfinite(value):
                cluster_key[c] = max(cluster_key[c], value - lipschitz * cluster_radius[c] + moved)
                continue
        for slot in range(size):
            face = clusters[c, slot]
            if face >= 0:
                near[n_near] = face
                cluster_of[n_near] = c
                n_near += 1
    counts.faces_near = n_near
    for i in range(n_near):
        face = near[i]
        moved = lipschitz * cluster_motion[cluster_of[i]]
        if hold and face_key[face] - moved > search:
            counts.faces_skipped += 1
            continue
        lost = False  # a read met a brick not ready: the face is left out (the caller calls again)
        for k in range(3):
            v = faces[face, k]
            if vertex_stamp[v] != stamp:
                for a in range(3):
                    vertex_local[v, a] = (rotation[a, 0] * vertices[v, 0] + rotation[a, 1] * vertices[v, 1]
                                          + rotation[a, 2] * vertices[v, 2] + shift[a])
                f, gx, gy, gz, s = read(vertex_local[v, 0], vertex_local[v, 1], vertex_local[v, 2], grid, missing, counts)
                if s == MISSING:
                    lost = True
                    break
                vertex_answer[v, 0], vertex_answer[v, 1], vertex_answer[v, 2], vertex_answer[v, 3], vertex_answer[v, 4] = f, gx, gy, gz, s
                vertex_stamp[v] = stamp
            t[k, 0], t[k, 1], t[k, 2] = vertex_local[v, 0], vertex_local[v, 1], vertex_local[v, 2]
        if lost:
            continue
        v0, v1, v2 = faces[face, 0], faces[face, 1], faces[face, 2]
        f0, f1, f2 = vertex_answer[v0, 0], vertex_answer[v1, 0], vertex_answer[v2, 0]
        # the Lipschitz bound on the vertices' values
        bound = max(max(f0 - lipschitz * reach[face, 0], f1 - lipschitz * reach[face, 1]), f2 - lipschitz * reach[face, 2])
        bound = max(bound, min(f0, f1, f2) - lipschitz * ball[face])
        if bound > search:
            counts.faces_skipped += 1
            face_key[face] = bound + moved
            continue
        counts.candidates += 1
        lowest = 0
        if f1 < f0:
            lowest = 1
        if f2 < (f1 if lowest == 1 else f0):
            lowest = 2
        vl = faces[face, lowest]
        b[0] = b[1] = b[2] = 0.0
        b[lowest] = 1.0
        value, gx, gy, gz, state = vertex_answer[vl, 0], vertex_answer[vl, 1], vertex_answer[vl, 2], vertex_answer[vl, 3], vertex_answer[vl, 4]
        gap = _frank_wolfe_gap(t, b[0], b[1], b[2], gx, gy, gz)
        if value - gap > search:
            counts.screened += 1
            face_key[face] = value - gap + moved
        elif gap > stop:  # the search inside: from the last answer (warm) or the lowest of the pattern's points (cold)
            warm = math.isfinite(last_bary[face, 0])
            n_line = 0
            if warm:
                counts.warm += 1
                first, last = 0, 1
                at_corner = (last_bary[face, 0] == 0) + (last_bary[face, 1] == 0) + (last_bary[face, 2] == 0) >= 2
                if at_corner:  # its read would be that corner's, at least the lowest vertex's: nothing to read
                    first = 1
            else:
                counts.cold += 1
                first, last = 0, pattern.shape[0]
                n_line = line_count[face]  # a long face: its line's starts after the pattern's
            best, best_s = math.inf, 0
            best_b0 = best_b1 = best_b2 = best_gx = best_gy = best_gz = 0.0
            for k in range(first, last + n_line):
                if warm:
                    s0, s1, s2 = last_bary[face, 0], last_bary[face, 1], last_bary[face, 2]
                elif k < last:
                    s0, s1, s2 = pattern[k, 0], pattern[k, 1], pattern[k, 2]
                else:  # zoo.proxy_search.line_points
                    along = (k - last + 1) / (n_line + 1)
                    s0 = s1 = s2 = along / 2
                    apex = line_apex[face]
                    if apex == 0:
                        s0 = 1 - along
                    elif apex == 1:
                        s1 = 1 - along
                    else:
                        s2 = 1 - along
                fs, sx, sy, sz, ss = read(s0 * t[0, 0] + s1 * t[1, 0] + s2 * t[2, 0], s0 * t[0, 1] + s1 * t[1, 1] + s2 * t[2, 1],
                                          s0 * t[0, 2] + s1 * t[1, 2] + s2 * t[2, 2], grid, missing, counts)
                if ss == MISSING:
                    lost = True
                    break
                if k >= last and ss != IN_BAND:  # out of band a read is a bound, not where the face is lowest
                    continue
                if fs < best:
                    best, best_s, best_b0, best_b1, best_b2, best_gx, best_gy, best_gz = fs, ss, s0, s1, s2, sx, sy, sz
            if lost:
                continue
            if best < value:
                b[0], b[1], b[2], value, gx, gy, gz, state = best_b0, best_b1, best_b2, best, best_gx, best_gy, best_gz, best_s
            for step in range(search_steps):
                if warm and step == warm_steps:
                    break
                gap = _frank_wolfe_gap(t, b[0], b[1], b[2], gx, gy, gz)
                if not (gap > stop and value - gap <= search and state == IN_BAND):  # out of band: see ProxyCollider
                    break
                if not _descend(t, b, value, gx, gy, gz, grid, missing, counts, direction, answer):
                    lost = True
                    break
                if not answer[3] < value:
                    break
                b[0], b[1], b[2], value, gx, gy, gz, state = answer[0], answer[1], answer[2], answer[3], answer[4], answer[5], answer[6], answer[7]
            if lost:
                continue
            face_key[face] = value - _frank_wolfe_gap(t, b[0], b[1], b[2], gx, gy, gz) + moved
            n = counts.searched
            out.searched_face[n] = face
            out.searched_bary[n, 0], out.searched_bary[n, 1], out.searched_bary[n, 2] = b[0], b[1], b[2]
            counts.searched = n + 1
        else:  # the lowest vertex is a KKT point
            face_key[face] = value - gap + moved
        if value <= net:
            n = counts.out
            out.face[n] = face
            for k in range(3):
                out.bary[n, k] = b[k]
                for a in range(3):
                    out.tri[n, k, a] = t[k, a]
            out.value[n] = value
            out.grad[n, 0], out.grad[n, 1], out.grad[n, 2] = gx, gy, gz
            out.status[n] = int(state)
            counts.out = n + 1
    last = -1  # the clusters opened: their keys anew, the least of their faces' (the faces come cluster by cluster)
    for i in range(n_near):
        c = cluster_of[i]
        if c != last:
            cluster_key[c], last = math.inf, c
        cluster_key[c] = min(cluster_key[c], face_key[near[i]])


@njit(cache=True)
def frank_wolfe_gaps(tri, bary, grads):
    """``zoo.simplex.frank_wolfe_gap`` (W,) of W faces ``tri`` (W, 3, 3) at ``bary`` (W, 3) with gradients ``grads``
    (W, 3) there, one compiled pass (a step's few faces: numpy's calls cost more than the arithmetic)."""
    gaps = np.empty(tri.shape[0])
    for i in range(tri.shape[0]):
        gaps[i] = _frank_wolfe_gap(tri[i], bary[i, 0], bary[i, 1], bary[i, 2], grads[i, 0], grads[i, 1], grads[i, 2])
    return gaps


@njit(cache=True, error_model="numpy", inline="always")
def _load_face(tri, bary, i, t, b):
    """Face ``i`` of ``tri`` (P, 3, 3) into ``t`` (3, 3), and its barycentrics of ``bary`` (P, 3) into ``b`` (3,)."""
    for k in range(3):
        b[k] = bary[i, k]
        for a in range(3):
            t[k, a] = tri[i, k, a]


@njit(cache=True)
def along_descent(tri, bary, grads, fractions, length):
    """Barycentric points (P, S, 3) along the steepest descent inside each face (P, 3, 3) from ``bary`` (P, 3), the
    gradients ``grads`` (P, 3) there (:func:`_descent_segment`), at the ``fractions`` (S,) of ``length`` (P,) (each
    face's share of its way to the boundary), put back on the simplex: ``zoo.proxy_collider._along_descent``'s numpy
    operations in the same order, one compiled pass (the SDF's own descent on a few faces a step)."""
    n, samples = tri.shape[0], fractions.shape[0]
    out = np.empty((n, samples, 3))
    t = np.empty((3, 3))
    b = np.empty(3)
    direction = np.empty(3)
    for i in range(n):
        _load_face(tri, bary, i, t, b)
        scale = length[i] * _descent_segment(t, b, grads[i, 0], grads[i, 1], grads[i, 2], direction)
        for k in range(samples):
            step = fractions[k] * scale
            out[i, k, 0], out[i, k, 1], out[i, k, 2] = _on_simplex(b[0] + step * direction[0], b[1] + step * direction[1],
                                                                  b[2] + step * direction[2])
    return out


@njit(cache=True)
def world_contacts(tri, bary, grads, rotation, shift):
    """The world points (K, 3) at ``bary`` (K, 3) on the faces ``tri`` (K, 3, 3) (the SDF's frame), and the unit
    normals (K, 3) along ``grads`` (K, 3) there (zeros where a gradient is zero), the SDF's frame turned by
    ``rotation`` (3, 3) and moved by ``shift`` (3,)."""
    k = tri.shape[0]
    points, normals = np.empty((k, 3)), np.empty((k, 3))
    for i in range(k):
        b0, b1, b2 = bary[i, 0], bary[i, 1], bary[i, 2]
        px = b0 * tri[i, 0, 0] + b1 * tri[i, 1, 0] + b2 * tri[i, 2, 0]
        py = b0 * tri[i, 0, 1] + b1 * tri[i, 1, 1] + b2 * tri[i, 2, 1]
        pz = b0 * tri[i, 0, 2] + b1 * tri[i, 1, 2] + b2 * tri[i, 2, 2]
        gx, gy, gz = grads[i, 0], grads[i, 1], grads[i, 2]
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        if length > 0:
            gx, gy, gz = gx / length, gy / length, gz / length
        for a in range(3):
            points[i, a] = rotation[a, 0] * px + rotation[a, 1] * py + rotation[a, 2] * pz + shift[a]
            normals[i, a] = rotation[a, 0] * gx + rotation[a, 1] * gy + rotation[a, 2] * gz
    return points, normals


@njit(cache=True)
def add_cluster_motion(motion, centres, radii, now, then):
    """Add to each cluster's ``motion`` (C,) how far its points can have moved relative to the SDF from the relative
    pose ``then`` to ``now`` (4, 4, SDF-from-mesh): |dR m + dt| + |dR|_F r for its centre m (``centres`` (C, 3)) and
    radius r (``radii`` (C,)), dR and dt the changes of rotation and shift (``zoo.proxy_collider._FaceBounds``)."""
    turn = np.empty((3, 3))
    frobenius = 0.0
    for a in range(3):
        for b in range(3):
            turn[a, b] = now[a, b] - then[a, b]
            frobenius += turn[a, b] * turn[a, b]
    frobenius = math.sqrt(frobenius)
    sx, sy, sz = now[0, 3] - then[0, 3], now[1, 3] - then[1, 3], now[2, 3] - then[2, 3]
    for c in range(centres.shape[0]):
        mx, my, mz = centres[c, 0], centres[c, 1], centres[c, 2]
        dx = turn[0, 0] * mx + turn[0, 1] * my + turn[0, 2] * mz + sx
        dy = turn[1, 0] * mx + turn[1, 1] * my + turn[1, 2] * mz + sy
        dz = turn[2, 0] * mx + turn[2, 1] * my + turn[2, 2] * mz + sz
        motion[c] += math.sqrt(dx * dx + dy * dy + dz * dz) + frobenius * radii[c]


@njit(cache=True, error_model="numpy")
def polish_ends(tri, bary, grads, samples, grid, missing, counts):
    """``ProxyCollider._polish``'s step for P faces, compiled: from ``bary`` (P, 3) on ``tri`` (P, 3, 3) (the SDF's
    frame) along the steepest descent of the SDF's gradient ``grads`` (P, 3) there (:func:`_descent_segment`), the
    lowest on the proxy ``grid`` of ``samples`` points evenly spaced up to the segment's end: their barycentrics
    (P, 3). A read that meets a brick not ready is recorded in ``missing`` (see :func:`read`): the caller makes it
    ready and calls again."""
    n = tri.shape[0]
    ends = np.empty((n, 3))
    t = np.empty((3, 3))
    b = np.empty(3)
    direction = np.empty(3)
    for i in range(n):
        _load_face(tri, bary, i, t, b)
        reach = _descent_segment(t, b, grads[i, 0], grads[i, 1], grads[i, 2], direction)
        best = math.inf
        ends[i, 0], ends[i, 1], ends[i, 2] = b[0], b[1], b[2]
        for k in range(1, samples + 1):
            step = (k / samples) * reach
            s0, s1, s2 = _on_simplex(b[0] + step * direction[0], b[1] + step * direction[1], b[2] + step * direction[2])
            value = read(s0 * t[0, 0] + s1 * t[1, 0] + s2 * t[2, 0], s0 * t[0, 1] + s1 * t[1, 1] + s2 * t[2, 1],
                         s0 * t[0, 2] + s1 * t[1, 2] + s2 * t[2, 2], grid, missing, counts)[0]
            if value < best:  # the first of equals, as numpy's argmin
                best = value
                ends[i, 0], ends[i, 1], ends[i, 2] = s0, s1, s2
    return ends


@njit(cache=True)
def first_of_cell(cells):
    """For each row of ``cells`` (N, 3) int64, the first row (N,) with the same cell: one pass over an open-addressing
    table, where sorting the rows by cell would cost more than the rows' other work. A row in its predecessor's cell
    takes its answer with no lookup (a search's rows come cluster by cluster, neighbours in space)."""
    n = cells.shape[0]
    size = 16
    while size < 2 * n:
        size *= 2
    mask = size - 1
    slot_row = np.full(size, -1, dtype=np.int64)
    first = np.empty(n, dtype=np.int64)
    for i in range(n):
        if i and cells[i, 0] == cells[i - 1, 0] and cells[i, 1] == cells[i - 1, 1] and cells[i, 2] == cells[i - 1, 2]:
            first[i] = first[i - 1]
            continue
        h = (cells[i, 0] * 73856093) ^ (cells[i, 1] * 19349663) ^ (cells[i, 2] * 83492791)
        s = h & mask
        while True:
            r = slot_row[s]
            if r < 0:
                slot_row[s] = i
                first[i] = i
                break
            if cells[r, 0] == cells[i, 0] and cells[r, 1] == cells[i, 1] and cells[r, 2] == cells[i, 2]:
                first[i] = r
                break
            s = (s + 1) & mask
    return first


@njit(cache=True)
def near_deepest_per_cell(cells, values, band):
    """The rows (N,) whose ``values`` (N,) are within ``band`` of the least of the rows sharing their cell ``cells``
    (N, 3) int64: their indices (K,), ascending (band 0: the least and its equals). Two passes: each cell's least
    value (:func:`first_of_cell` names the cells), then the rows near it."""
    n = values.shape[0]
    first = first_of_cell(cells)
    least = np.empty(n)
    for i in range(n):
        least[first[i]] = values[i] if first[i] == i else min(least[first[i]], values[i])
    rows = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if values[i] <= least[first[i]] + band:
            rows[m] = i
            m += 1
    return rows[:m]


@njit(cache=True)
def thinned_rows(values, bary, tri, grads, faces, search, face_normal, rotation, sdf_rotation, sdf_shift, cell,
                 touching_cos, separated_cos, closing_shift, closing_turn, closing_seconds, band, slack, near_miss):
    """The rows (K,) ascending, of a call's answers, that ``zoo.proxy_collider.Thinning`` keeps of its proxy
    contacts (the answers at most ``search``), in one pass: per cell, those a simulation can use
    (:func:`zoo.contact_filters.usable`) within ``band`` of the deepest of them, and apart from them, those usable
    only with ``near_miss`` added to the slack (the near misses) within ``band`` of the deepest of those.

    Args:
        values (N,), bary (N, 3), tri (N, 3, 3), grads (N, 3), faces (N,): the answers (the SDF's frame).
        face_normal (F, 3): the faces' unit normals in the mesh's frame (zeros: degenerate); rotation (3, 3): the
            mesh's in the SDF's frame. sdf_rotation (3, 3), sdf_shift (3,): the SDF's pose in the world.
        cell, touching_cos, separated_cos: the ``Thinning``'s; closing_shift (3,), closing_turn (3,),
            closing_seconds: its ``closing`` (:class:`zoo.contact_filters.Closing`; seconds < 0: none).
        band: m, the ``Thinning``'s (0: the deepest and its equals); slack: m, its ``slack`` (the filters' tests take
            a proxy depth at its least, the depth less this); near_miss: m, its ``near_miss`` (0: none).
    """
    n = values.shape[0]
    cells = np.empty((n, 3), dtype=np.int64)
    rows = np.empty(n, dtype=np.int64)
    kept_values = np.empty(n)
    # the closing motion in the SDF's frame, where the points and normals are: u + w x (R p + t) . R n is
    # (R^T (u + w x t) + R^T w x p) . n, so that only the rows kept are taken to the world (their cells)
    moving, shift, turn = np.empty(3), np.empty(3), np.empty(3)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        moving[a] = closing_shift[a] + closing_turn[b] * sdf_shift[c] - closing_turn[c] * sdf_shift[b]
    for a in range(3):  # R^T: numba's @ would warn on the pose's strided rotation
        shift[a] = sdf_rotation[0, a] * moving[0] + sdf_rotation[1, a] * moving[1] + sdf_rotation[2, a] * moving[2]
        turn[a] = (sdf_rotation[0, a] * closing_turn[0] + sdf_rotation[1, a] * closing_turn[1]
                   + sdf_rotation[2, a] * closing_turn[2])
    facing_at_least = min(touching_cos, separated_cos)  # a row below it fails usable's facing test at any depth
    point, normal = np.empty(3), np.empty(3)
    m = 0
    for i in range(n):
        value = values[i]
        if not value <= search:
            continue
        f = faces[i]
        gx, gy, gz = grads[i, 0], grads[i, 1], grads[i, 2]
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        scale = 1.0 / length if length > 0 else 0.0
        normal[0], normal[1], normal[2] = gx * scale, gy * scale, gz * scale  # the contact's normal, SDF frame
        # the face's normal in the SDF's frame is rotation @ n, so its cosine with the normal is n . (rotation^T normal)
        cos = 0.0
        for a in range(3):
            cos += face_normal[f, a] * (rotation[0, a] * normal[0] + rotation[1, a] * normal[1] + rotation[2, a] * normal[2])
        degenerate = face_normal[f, 0] == 0 and face_normal[f, 1] == 0 and face_normal[f, 2] == 0
        if not degenerate and abs(cos) < facing_at_least:
            continue
        for a in range(3):  # the point, SDF frame
            point[a] = bary[i, 0] * tri[i, 0, a] + bary[i, 1] * tri[i, 1, a] + bary[i, 2] * tri[i, 2, a]
        speed = closing_speed(shift, turn, point, normal) if value > slack else 0.0
        near = 0  # a near miss: its cell is its own (its x index made odd), apart from the usable contacts'
        if not usable(value, cos, degenerate, speed, closing_seconds, touching_cos, separated_cos, slack):
            if not (near_miss > 0 and usable(value, cos, degenerate, speed, closing_seconds, touching_cos, separated_cos,
                                             slack + near_miss)):
                continue
            near = 1
        for a in range(3):  # the cell of the point in the world
            world = sdf_rotation[a, 0] * point[0] + sdf_rotation[a, 1] * point[1] + sdf_rotation[a, 2] * point[2] + sdf_shift[a]
            cells[m, a] = int(math.floor(world / cell))
        cells[m, 0] = 2 * cells[m, 0] + near
        rows[m] = i
        kept_values[m] = value
        m += 1
    return rows[near_deepest_per_cell(cells[:m], kept_values[:m], band)]
