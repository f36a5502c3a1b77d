"""Answering triangles with the amortized detector (:mod:`zoo.detector`): :func:`detect` on a batch of
triangles, :func:`solve_mesh` on a mesh's triangles (what ``zoo.collide`` runs as its narrow phase).

Triangles in the trained edge range take one forward pass; longer ones are cut into pieces in the
range and searched with a Lipschitz bound, and the best answer is mapped back to the triangle's
barycentrics.

After the forward pass comes the polish (``polish=True``, the default). First the vertex test: the gradient at
each in-range triangle's lowest vertex (one value-and-gradient query per distinct vertex, shared by the
triangles around it); where no other vertex has a lower g . v_i, that vertex satisfies the KKT
conditions and is the answer (81% of the bench's mug triangles, 68-99% of the scenes' in-range
candidates), with no network and no further query. The rest take the network's answer and
``POLISH_ROUNDS`` Frank-Wolfe steps with a parabolic line search (:func:`zoo.solvers.line_search_step`:
the exact gradient at the point, ``POLISH_LINE_STEPS`` values along the step), which get what
Frank-Wolfe's fixed steps need tens of gradient queries for; ``polish=False`` gives the forward pass
alone. The polish does most of the work: from the lowest vertex instead of the network's answer the
same steps do as well (README, detector bench). The NeuralSDF must have a continuous gradient for
either to reach the KKT conditions (equation (12)): see ``NeuralSDFConfig.smooth_beta``.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from .detector import AmortizedDetector
from .errors import InputError
from .geometry import bary_to_points, edge_lengths
from .validation import as_triangles

# Value queries after the polish's gradient query (zoo.solvers.line_search_step). On the bench's 800
# seen-mug triangles (4 mugs x 200, mugs@1.3.0) the polished mean optimality was 1.4e-3 with none,
# 6.5e-4 with one, 3.6e-4 with two and 3.2e-4 with three (one step, before the vertex test).
POLISH_LINE_STEPS = 2
# Line-search steps per polished in-range answer (a regularly subdivided triangle's lowest piece takes one). The
# vertex test settles 80-99% of in-range triangles first, so the polish runs on the rest only. Same
# triangles: 3.3e-4 with one step, 2.4e-4 with two, 1.4e-4 with three; but three cost the scene bench's
# contact check (a mug cut by a 20k-triangle mesh, 29% of its candidates polished) its 2x over FW.
POLISH_ROUNDS = 2

# How detect() and solve_mesh() spend their time (the network is cheap next to the NeuralSDF's
# decoder, so the count of SDF queries is what matters):
#
# * every distinct vertex is evaluated once (features, and distances where they are needed):
#   a mesh shares each vertex among about six triangles;
# * triangles up to 7x longer than the trained range are solved on the pieces of a regular
#   subdivision (a needle's strips); longer ones are bisected across their longest edge until their
#   pieces are in range, all triangles' cells one step at a time: the SDF is evaluated at the
#   corners of a cell (shared between cells, between steps and, along the mesh's edges, between
#   neighbouring triangles), and a cell whose Lipschitz lower bound exceeds the best value found so
#   far is dropped with everything inside it; the pieces that survive run the network, and a head
#   that models the SDF has only its lowest piece's answer evaluated. Bisection keeps a needle's
#   pieces as thin as it is: a rack's 3.0 x 0.003 triangle costs about 10 points, not the 30 of
#   similar pieces (mug-rack: 7,900 grid points instead of 25,300);
# * with ``vertex_check`` (what collide uses) the network's answer on an in-range triangle is
#   compared with the best vertex (and any known point), keeping the lower; distances collide's
#   broad phase took at the vertices are not taken again; with a ``cutoff`` (collide's margin) a
#   triangle or cell proven to stay above it is not solved at all.

LIPSCHITZ = 1.0  # the bound the culls assume of the SDF, as collide's broad phase does
_MAX_FLAT_LEVEL = 7  # subdivision levels up to this are solved flat; beyond, by bisection
_MAX_LEVEL = 64  # pieces per edge at most: a longer triangle is solved on pieces over the trained range
# The grid that bisected cells live on: a midpoint of two of its points is one of its points for
# 15 generations of bisection, more than a triangle of _MAX_LEVEL needs (about 2 per halving of its length).
_BISECTION_LEVEL = 1 << 15
_CELL_BUDGET = 1 << 20  # cells alive at once in the search (about 50 MB of bookkeeping)
_KEY_ROW_BITS = 29  # point keys hold a triangle or an edge index below 2^29 and grid coordinates below 2^16
_NETWORK_CHUNK = 4096  # pieces per network call (cache-sized: ~5% faster than one call on 16k)
_TAG_EDGE = 1 << 62
_TAG_FACE = 1 << 61


def detect(detector: AmortizedDetector, shape, triangles, chunk: int = 65536, vertex_check: bool = False,
           polish: bool = True) -> torch.Tensor:
    """Amortized minimum of ``shape``'s SDF on each triangle: (M, 3, 3) source frame -> bary (M, 3).

    ``shape`` is a fitted NeuralShape (or any object with ``features(points_norm (N, 3)) -> (N, C)``,
    ``normalised`` (its SDF in the normalised frame) and optionally ``similarity``; without
    ``similarity`` the source frame is the normalised one). Barycentric coordinates are invariant
    under the similarity transform, so the triangles are mapped into the normalised frame and the
    answer is returned as is. float64 input gives float64 output.

    In-range triangles get the network's answer (one pass; features computed once per distinct
    vertex). Triangles with an edge longer than the trained range are subdivided into the range
    (up to 7x the range into regular pieces or a needle's strips, :func:`strip_levels`; beyond, by
    bisection) and the answer is the lowest of the pieces' answers and the grid points evaluated on
    the way (a search with Lipschitz culls, see :func:`solve_mesh`).
    ``vertex_check=True`` also compares each in-range answer with the triangle's best vertex
    and keeps the lower (one more SDF query per triangle and one per distinct vertex).
    ``polish=True`` (the default): an in-range triangle whose lowest vertex passes the vertex test
    (:func:`_settled_at_vertex`) is answered there; the others end with ``POLISH_ROUNDS`` Frank-Wolfe
    steps with a parabolic line search from the network's answer (:func:`_polish`; each one
    value-and-gradient query and ``POLISH_LINE_STEPS`` value queries; on a subdivided triangle, from
    the lowest piece's answer, inside that piece: one step, ``POLISH_ROUNDS`` on a bisected one);
    ``polish=False`` returns the network's answer of the single forward pass.
    """
    tri_src = as_triangles(triangles)
    vertices, inverse = unique_rows(tri_src.reshape(-1, 3))
    bary, _ = solve_mesh(detector, shape, vertices, inverse.reshape(-1, 3), vertex_check=vertex_check, chunk=chunk,
                         polish=polish)
    return bary


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


def to_normalised_frame(shape, triangles: torch.Tensor) -> torch.Tensor:
    """Triangles (M, 3, 3) (or points (..., 3)) in the shape's source frame -> its normalised frame, same dtype and device."""
    similarity = getattr(shape, "similarity", None)
    if similarity is None:
        return triangles
    m = torch.as_tensor(similarity.matrix, dtype=triangles.dtype, device=triangles.device)  # (4, 4)
    return triangles @ m[:3, :3].T + m[:3, 3]


def _scale(shape) -> float:
    similarity = getattr(shape, "similarity", None)
    return 1.0 if similarity is None else float(similarity.scale)


def subdivision_levels(triangles: torch.Tensor, max_edge: float, max_level: int = _MAX_LEVEL) -> torch.Tensor:
    """How many pieces per edge (M,) int64 bring every edge to at most ``max_edge``.

    Level n splits a triangle into n^2 similar pieces with edges 1/n as long. Capped at
    ``max_level`` (4096 pieces): a triangle longer than that is solved on coarser pieces.
    """
    longest = edge_lengths(triangles).amax(dim=-1)
    return torch.ceil(longest / max_edge).clamp(1, max_level).to(torch.int64)


def subdivision_barycentrics(n: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Vertices of the n^2 pieces of the regular n-subdivision, as barycentrics of the parent: (n^2, 3, 3).

    Piece k's vertex j is ``result[k, j] @ parent_vertices``. Pieces are listed with a
    consistent orientation (the "up" pieces then the "down" pieces).
    """
    return _grid_barycentrics(_subdivision_grid(n), n, torch.float64).to(dtype=dtype, device=device)


def _grid_barycentrics(grid: torch.Tensor, n, dtype) -> torch.Tensor:
    """Integer grid coordinates (..., 2) at level ``n`` -> barycentrics (..., 3): (i, j) is (1 - (i+j)/n, i/n, j/n).
    ``n``: an int, or a tensor that broadcasts against grid's leading dimensions ((C, 1) for grid (C, 3, 2))."""
    g = grid.to(dtype)
    n = torch.as_tensor(n, dtype=dtype, device=grid.device).unsqueeze(-1)
    return torch.cat([n - g.sum(-1, keepdim=True), g], dim=-1) / n


def _subdivision_grid(n: int, device=None) -> torch.Tensor:
    """Integer grid coordinates (n^2, 3, 2) of the pieces' vertices: (i, j) is the point (1 - (i+j)/n, i/n, j/n)."""
    ij = [(i, j) for i in range(n) for j in range(n - i)]
    up = [[(i, j), (i + 1, j), (i, j + 1)] for i, j in ij]
    down = [[(i + 1, j), (i + 1, j + 1), (i, j + 1)] for i, j in ij if i + j <= n - 2]
    return torch.tensor(up + down, dtype=torch.int64, device=device)


def strip_levels(triangles: torch.Tensor, max_edge: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Where a needle is better cut into strips than into the n^2 pieces of :func:`subdivision_levels`.

    A triangle (M, 3, 3) with apex A opposite its shortest edge BC is cut by the points P_k, Q_k at
    k/n along AB and AC into 2n - 1 pieces (:func:`strip_barycentrics`): sides of at most
    max(|AB|, |AC|) / n, rungs of at most |BC|, diagonals of at most |BC| + max(|AB|, |AC|) / n, so
    n = ceil(max(|AB|, |AC|) / (max_edge - |BC|)) keeps every edge in range. Returns (n (M,) int64,
    0 where the regular pieces are as few or the strips would need more than ``_MAX_FLAT_LEVEL``;
    apex 0-2 (M,)). The scenes' long triangles are such needles (a nut's 0.16 x 0.009, a gear's
    0.16 x 0.001 in their normalised frames): 3 or 5 pieces instead of 4 or 9.
    """
    e = edge_lengths(triangles)  # (M, 3): edge k from vertex k to k + 1, opposite vertex k + 2
    short, edge = e.min(dim=-1)
    apex = (edge + 2) % 3
    room = max_edge - short
    longest = e.amax(dim=-1)
    n = torch.ceil(longest / room.clamp_min(torch.finfo(e.dtype).tiny)).clamp(1, 1 << 20).to(torch.int64)
    regular = subdivision_levels(triangles, max_edge)
    use = (room > 0) & (regular > 1) & (2 * n - 1 < regular.square()) & (n <= _MAX_FLAT_LEVEL)
    return torch.where(use, n, torch.zeros_like(n)), apex


def strip_barycentrics(n: int, apex: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Vertices of the 2n - 1 strip pieces of a triangle with apex vertex ``apex``, as barycentrics of the parent:
    (2n - 1, 3, 3); see :func:`strip_levels`."""
    return _grid_barycentrics(_strip_grid(n, apex), n, torch.float64).to(dtype=dtype, device=device)


def _strip_grid(n: int, apex: int, device=None) -> torch.Tensor:
    """Integer grid coordinates (2n - 1, 3, 2) at level n of the strip pieces: (A, P_1, Q_1), then for each k
    (P_k, P_k+1, Q_k+1) and (P_k, Q_k+1, Q_k), with P_k and Q_k at k/n from the apex A to its next and previous vertex."""
    towards_next = {0: lambda k: (k, 0), 1: lambda k: (n - k, k), 2: lambda k: (0, n - k)}[apex]
    towards_prev = {0: lambda k: (0, k), 1: lambda k: (n - k, 0), 2: lambda k: (k, n - k)}[apex]
    p, q = towards_next, towards_prev
    pieces = [[p(0), p(1), q(1)]]
    for k in range(1, n):
        pieces += [[p(k), p(k + 1), q(k + 1)], [p(k), q(k + 1), q(k)]]
    return torch.tensor(pieces, dtype=torch.int64, device=device)


def cell_lower_bounds(cells: torch.Tensor, values: torch.Tensor, lipschitz: float = LIPSCHITZ) -> torch.Tensor:
    """A lower bound (C,) of an L-Lipschitz SDF over each triangle (C, 3, 3) from its vertex values (C, 3).

    The larger of two bounds: ``max_i f_i - L * reach_i`` (reach_i: the longest edge at vertex i,
    the farthest any point of the triangle is from it) and ``min_i f_i - L * R`` (R: the radius of
    the smallest ball holding the triangle, circumradius or half the longest edge, which is the
    farthest any point of the triangle is from its nearest vertex). Rounding slack is subtracted.
    """
    e = torch.stack([(cells[:, 1] - cells[:, 2]).norm(dim=-1), (cells[:, 2] - cells[:, 0]).norm(dim=-1),
                     (cells[:, 0] - cells[:, 1]).norm(dim=-1)], dim=-1)  # (C, 3): edge k opposite vertex k
    reach = torch.stack([torch.maximum(e[:, 1], e[:, 2]), torch.maximum(e[:, 0], e[:, 2]), torch.maximum(e[:, 0], e[:, 1])], dim=-1)
    by_vertex = (values - lipschitz * reach).amax(dim=-1)
    longest = e.amax(dim=-1)
    twice_area = torch.linalg.cross(cells[:, 1] - cells[:, 0], cells[:, 2] - cells[:, 0], dim=-1).norm(dim=-1)
    not_acute = 2 * longest.square() >= e.square().sum(dim=-1)  # longest^2 >= the other two's squares summed
    circumradius = e.prod(dim=-1) / (2 * twice_area).clamp_min(torch.finfo(cells.dtype).tiny)
    radius = torch.where(not_acute, 0.5 * longest, circumradius)
    by_ball = values.amin(dim=-1) - lipschitz * radius
    bound = torch.maximum(by_vertex, by_ball)
    slack = 16 * torch.finfo(cells.dtype).eps * (values.abs().amax(dim=-1) + longest + cells.abs().amax(dim=(1, 2)))
    return bound - slack


# --------------------------------------------------------------------------- the point table


class _PointTable:
    """Every point the search has evaluated: normalised coordinates, features and distances.

    Rows 0..U-1 are the mesh's distinct vertices; grid points of subdivided triangles follow,
    found by an int64 key: a point on a mesh edge by (the edge, and the reduced fraction along it
    from its lower-numbered vertex), so neighbouring triangles share it; any other grid point by
    (its triangle, its grid coordinates).
    """

    def __init__(self, shape, vertices_n: torch.Tensor, faces: torch.Tensor, values_for: torch.Tensor,
                 given: torch.Tensor | None = None):
        """``values_for``: vertex rows whose distances are needed now; ``given``: (U,) normalised-frame
        distances at the vertices known already (NaN where not), which are not queried again."""
        if 3 * faces.shape[0] >= 1 << _KEY_ROW_BITS:  # each triangle, and each edge, must fit a key
            raise InputError(f"solve_mesh takes fewer than {(1 << _KEY_ROW_BITS) // 3} triangles at once, got {faces.shape[0]}: "
                             "split the mesh")
        self.shape = shape
        self.faces = faces
        self.n_vertices = vertices_n.shape[0]
        self._face_edges: torch.Tensor | None = None  # (M, 3) edge indices, taken when a grid point first needs them
        self.coords = vertices_n
        self.f = torch.full(vertices_n.shape[:1], float("nan"), dtype=vertices_n.dtype, device=vertices_n.device)
        self.has_f = torch.zeros(vertices_n.shape[0], dtype=torch.bool, device=vertices_n.device)
        if given is not None:
            self.has_f = ~torch.isnan(given)
            self.f = torch.where(self.has_f, given, self.f)
        # code-cloud features, taken where the decoder or the network needs them (rows with given values may need neither)
        self.z: torch.Tensor | None = None
        self.has_z = torch.zeros(vertices_n.shape[0], dtype=torch.bool, device=vertices_n.device)
        self.keys = torch.zeros(0, dtype=torch.int64, device=vertices_n.device)  # sorted
        self.slots = torch.zeros(0, dtype=torch.int64, device=vertices_n.device)
        # gradients at vertex rows only (the vertex test of solve_mesh), NaN until asked for
        self.grad = torch.full_like(vertices_n, float("nan"))
        self.ensure_values(values_for)

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """Code-cloud features (..., C) at the int rows ``rows`` (...), computed where new."""
        need = torch.unique(rows.reshape(-1))
        need = need[~self.has_z[need]]
        if need.numel():
            z = _features(self.shape, self.coords[need])
            if self.z is None:
                self.z = z.new_zeros((self.coords.shape[0], z.shape[-1]))
            self.z[need] = z
            self.has_z[need] = True
        return self.z[rows]

    def ensure_values(self, rows: torch.Tensor) -> None:
        """Distances at the vertex rows ``rows`` (the decoder on the features already computed)."""
        rows = torch.unique(rows)
        rows = rows[~self.has_f[rows]]
        if rows.numel():
            self.f[rows] = _distances_from_features(self.shape, self.coords[rows], self.features(rows))
            self.has_f[rows] = True

    def gradients(self, rows: torch.Tensor) -> torch.Tensor:
        """Normalised-frame SDF gradients (R, 3) at the vertex rows ``rows`` (R,): one value-and-gradient
        query per distinct vertex not asked for before."""
        need = torch.unique(rows)
        need = need[torch.isnan(self.grad[need, 0])]
        if need.numel():
            with torch.no_grad():
                f, g = self.shape.normalised.value_and_grad(self.coords[need])
            self.grad[need] = torch.as_tensor(g).to(self.grad)
            self.f[need] = torch.as_tensor(f).reshape(-1).to(self.f)
            self.has_f[need] = True
        return self.grad[rows]

    def lowest_vertices(self, vertex_rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each triangle's lowest corner, from its corner rows (R, 3): value (R,), which corner 0-2 (R,), its row (R,)."""
        self.ensure_values(vertex_rows.reshape(-1))
        value, corner = self.f[vertex_rows].min(dim=-1)
        return value, corner, vertex_rows.gather(1, corner.unsqueeze(1)).squeeze(1)

    def grid_points(self, rows: torch.Tensor, ij: torch.Tensor, n) -> torch.Tensor:
        """Row indices (Q,) of the grid points (i, j) (Q, 2) of triangles ``rows`` (Q,) at their levels ``n``
        (an int, or (Q,): a triangle keeps one level); evaluated if new."""
        i, j = ij[:, 0], ij[:, 1]
        n = torch.as_tensor(n, dtype=i.dtype, device=i.device).expand_as(i)
        out = torch.empty_like(i)
        face = self.faces[rows]  # (Q, 3)
        corner = torch.full_like(i, -1)
        corner = torch.where((i == 0) & (j == 0), 0, corner)
        corner = torch.where(i == n, 1, corner)
        corner = torch.where(j == n, 2, corner)
        is_corner = corner >= 0
        out[is_corner] = face[is_corner].gather(1, corner[is_corner].unsqueeze(1)).squeeze(1)
        rest = (~is_corner).nonzero().squeeze(-1)
        if rest.numel() == 0:
            return out
        i, j, n, face, r = i[rest], j[rest], n[rest], face[rest], rows[rest]
        # a point on an edge: (a, b, t) with t the fraction from a to b, t = num / n
        on01, on02, on12 = j == 0, i == 0, (i + j == n)
        edge = on01 | on02 | on12
        a = torch.where(on12, face[:, 1], face[:, 0])
        b = torch.where(on01, face[:, 1], face[:, 2])
        num = torch.where(on01, i, j)
        swap = a > b
        a, b, num = torch.where(swap, b, a), torch.where(swap, a, b), torch.where(swap, n - num, num)
        den = n
        g = torch.gcd(num, den).clamp_min(1)
        num, den = num // g, den // g
        edge_id = self.face_edges()[r].gather(1, torch.where(on01, 0, torch.where(on02, 1, 2)).unsqueeze(1)).squeeze(1)
        edge_key = _TAG_EDGE | (edge_id << 32) | (num << 16) | den
        face_key = _TAG_FACE | (r << 32) | (i << 16) | j
        key = torch.where(edge, edge_key, face_key)
        # coordinates: along the edge from the canonical end, else barycentric in the triangle
        t = (num.to(self.coords.dtype) / den.to(self.coords.dtype)).unsqueeze(-1)
        va, vb = self.coords[a], self.coords[b]
        along = va + t * (vb - va)
        w = torch.stack([n - i - j, i, j], dim=-1).to(self.coords.dtype) / n.unsqueeze(-1).to(self.coords.dtype)  # (Q, 3)
        inside = torch.einsum("qv,qvc->qc", w, self.coords[face])
        xyz = torch.where(edge.unsqueeze(-1), along, inside)
        out[rest] = self._lookup_or_add(key, xyz)
        return out

    def face_edges(self) -> torch.Tensor:
        """Each triangle's edges (M, 3) as indices of the mesh's distinct edges: its edges 0-1, 0-2 and 1-2."""
        if self._face_edges is None:
            f = self.faces
            ends = torch.stack([f[:, [0, 1]], f[:, [0, 2]], f[:, [1, 2]]], dim=1)  # (M, 3, 2)
            code = ends.amin(dim=-1) * self.n_vertices + ends.amax(dim=-1)
            self._face_edges = torch.unique(code, return_inverse=True)[1]
        return self._face_edges

    def _lookup_or_add(self, key: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        uniq, first_inverse = torch.unique(key, return_inverse=True)
        slot = torch.empty_like(uniq)
        if self.keys.numel():
            pos = torch.searchsorted(self.keys, uniq).clamp_max(self.keys.numel() - 1)
            found = self.keys[pos] == uniq
            slot[found] = self.slots[pos[found]]
        else:
            found = torch.zeros_like(uniq, dtype=torch.bool)
        missing = (~found).nonzero().squeeze(-1)
        if missing.numel():
            # one representative query per missing key
            rep = torch.full((uniq.numel(),), key.numel(), dtype=torch.int64, device=key.device)
            rep.scatter_reduce_(0, first_inverse, torch.arange(key.numel(), device=key.device), "amin")
            p = xyz[rep[missing]]
            z = _features(self.shape, p)
            f = _distances_from_features(self.shape, p, z)
            start = self.coords.shape[0]
            new_slots = torch.arange(start, start + missing.numel(), device=key.device)
            self.coords = torch.cat([self.coords, p])
            if self.z is None:  # no row had features yet: zeros (has_z False) for the rows before
                self.z = z.new_zeros((start, z.shape[-1]))
            self.z = torch.cat([self.z, z])
            self.has_z = torch.cat([self.has_z, torch.ones(missing.numel(), dtype=torch.bool, device=key.device)])
            self.f = torch.cat([self.f, f])
            self.has_f = torch.cat([self.has_f, torch.ones(missing.numel(), dtype=torch.bool, device=key.device)])
            slot[missing] = new_slots
            keys = torch.cat([self.keys, uniq[missing]])
            slots = torch.cat([self.slots, new_slots])
            order = torch.argsort(keys)
            self.keys, self.slots = keys[order], slots[order]
        return slot[first_inverse]


def _features(shape, points: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return torch.as_tensor(shape.features(points)).to(points)


def _distances_from_features(shape, points: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """Normalised-frame distances at ``points``: the shape's decoder on features already computed
    where it offers one (``distances_from_features``), else a plain query of ``shape.normalised``."""
    with torch.no_grad():
        fast = getattr(shape, "distances_from_features", None)
        if callable(fast):
            return torch.as_tensor(fast(points, features)).to(points)
        return torch.as_tensor(shape.normalised(points)).reshape(-1).to(points)


# --------------------------------------------------------------------------- solving a mesh


def solve_mesh(detector: AmortizedDetector, shape, vertices, faces, cutoff: float | None = None, known=None,
               vertex_check: bool = True, cull: bool = True, chunk: int = 65536, polish: bool = False,
               vertex_values=None):
    """Amortized minima of ``shape``'s SDF on the triangles ``vertices[faces]``: -> bary (M, 3), values (M,) or None.

    ``vertices`` (V, 3) in the shape's source frame (only those ``faces`` (M, 3) name are used),
    ``faces`` int (M, 3). ``values`` are the source-frame signed distances at the returned points
    (None when nothing was evaluated there: ``vertex_check=False`` on in-range triangles only).

    * In-range triangles: the network's answer; with ``vertex_check``, the lowest of it, the three
      vertices and the ``known`` point.
    * Longer triangles: the lowest of the answers on the surviving pieces and the grid points
      evaluated (and the ``known`` point), searched with Lipschitz culls (:func:`_search`).
    * ``known``: (bary (M, 3), values (M,)) a point per triangle whose source-frame distance is
      known already, taken where lower than the answer.
    * ``vertex_values``: (V,) source-frame distances at ``vertices`` known already, NaN where not
      (collide passes those its broad phase evaluated); they are not queried again.
    * ``cutoff`` (source frame, needs ``vertex_check``): triangles and cells whose lower bound
      (:func:`cell_lower_bounds`) exceeds it are not solved; such a row's value is only proven
      to be > cutoff (what collide needs of a triangle that is no contact).
    * ``cull=False`` evaluates every piece (the exhaustive search; the culls assume the SDF is
      ``LIPSCHITZ``-Lipschitz and otherwise give the same answer).
    * ``polish``: in-range triangles whose lowest vertex passes the vertex test are answered there
      (:func:`_settled_at_vertex`); each other in-range answer of the network takes ``POLISH_ROUNDS``
      line-search steps (:func:`_polish`) before it is compared with the vertices and the ``known``
      point; a subdivided triangle's lowest piece answer takes one inside its piece (a bisected
      triangle's, ``POLISH_ROUNDS``; :func:`_answer_pieces`).
    """
    if cutoff is not None and not vertex_check:
        raise InputError("solve_mesh: a cutoff needs vertex_check=True (the culls compare against vertex values)")
    faces = torch.as_tensor(faces, device=vertices.device).long()
    if faces.shape[0] == 0:
        empty = vertices.new_zeros((0, 3))
        return empty, (vertices.new_zeros((0,)) if vertex_check else None)
    used, local = torch.unique(faces, return_inverse=True)
    v_n = to_normalised_frame(shape, vertices[used])
    tri_n = v_n[local]  # (M, 3, 3)
    m_rows = local.shape[0]
    scale = _scale(shape)
    levels = subdivision_levels(tri_n, detector.edge_range[1])
    single = levels == 1
    strips, apex = strip_levels(tri_n, detector.edge_range[1])
    striped = ~single & (strips > 0)
    # distances are needed at the vertices of subdivided triangles (bounds, candidates), at every
    # vertex with the vertex check, and wherever the detector reads them
    needs_f = torch.ones_like(single) if (vertex_check or detector.vertex_sdf) else ~single
    given = None
    if vertex_values is not None:
        given = torch.as_tensor(vertex_values, device=vertices.device).reshape(-1)
        if given.shape[0] != vertices.shape[0]:
            raise InputError(f"solve_mesh: vertex_values must hold one distance per vertex ({vertices.shape[0]}), got {given.shape[0]}")
        given = given[used].to(v_n.dtype) * scale
    table = _PointTable(shape, v_n, local, local[needs_f].reshape(-1), given)

    dtype = v_n.dtype
    best_val = torch.full((m_rows,), float("inf"), dtype=dtype, device=v_n.device)
    best_bary = torch.full((m_rows, 3), 1 / 3, dtype=dtype, device=v_n.device)
    from_known = torch.zeros(m_rows, dtype=torch.bool, device=v_n.device)
    rows_f = needs_f.nonzero().squeeze(-1)
    if rows_f.numel():  # the vertices are candidates
        fv = table.f[local[rows_f]]  # (R, 3)
        val, arg = fv.min(dim=-1)
        best_val[rows_f] = val
        best_bary[rows_f] = F.one_hot(arg, 3).to(dtype)
    if not vertex_check:
        best_val[single] = float("inf")  # in-range answers are the network's, whatever the vertices
    if known is not None:
        k_bary, k_val = (torch.as_tensor(t, device=v_n.device).to(dtype) for t in known)
        better = (k_val * scale < best_val) & (vertex_check | ~single)
        best_val = torch.where(better, k_val * scale, best_val)
        best_bary = torch.where(better.unsqueeze(-1), k_bary, best_bary)
        from_known = better
    cut_n = None if cutoff is None else float(cutoff) * scale

    # the pieces that reach the network: (rows (P,), their point indices (P, 3), grid coordinates (P, 3, 2), levels (P,))
    pieces: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = []
    single_rows = single.nonzero().squeeze(-1)
    if single_rows.numel():
        corners = _subdivision_grid(1, v_n.device).expand(single_rows.numel(), -1, -1)
        idx = local[single_rows]
        if cull and cut_n is not None:
            keep = cell_lower_bounds(tri_n[single_rows], table.f[idx]) <= cut_n
            single_rows, idx, corners = single_rows[keep], idx[keep], corners[keep]
        if polish:  # rows whose lowest vertex is a KKT point are answered there, without the network
            settled = _settled_at_vertex(tri_n, table, single_rows, idx, best_val, best_bary, from_known)
            single_rows, idx, corners = single_rows[~settled], idx[~settled], corners[~settled]
        if single_rows.numel():
            pieces.append((single_rows, idx, corners, torch.ones_like(single_rows)))
    flat = ~single & ~striped & (levels <= _MAX_FLAT_LEVEL)
    groups = []  # (rows (R,), their cells (C, 3, 2) or (R, C, 3, 2) in grid coordinates at level n, n, bisected)
    for n in torch.unique(levels[flat]).tolist():
        rows = (flat & (levels == n)).nonzero().squeeze(-1)
        groups.append((rows, _subdivision_grid(n, v_n.device), n, False))
    for n in torch.unique(strips[striped]).tolist():
        rows = (striped & (strips == n)).nonzero().squeeze(-1)
        by_apex = torch.stack([_strip_grid(n, a, v_n.device) for a in range(3)])  # (3, 2n - 1, 3, 2)
        groups.append((rows, by_apex[apex[rows]], n, False))
    bisected = (~single & ~striped & ~flat).nonzero().squeeze(-1)
    if bisected.numel():
        groups.append((bisected, _subdivision_grid(1, v_n.device) * _BISECTION_LEVEL, _BISECTION_LEVEL, True))
    if groups:
        # a bisected cell is a piece once its edges are in range (or 1/_MAX_LEVEL of its triangle's longest)
        piece_edge = (edge_lengths(tri_n).amax(dim=-1) / _MAX_LEVEL).clamp_min(detector.edge_range[1])
        pieces += _search(table, groups, levels, piece_edge, best_val, best_bary, from_known, cut_n, cull)

    if pieces:
        _answer_pieces(detector, shape, tri_n, table, pieces, best_val, best_bary, from_known, vertex_check, polish, chunk)

    values = None
    if vertex_check:
        values = best_val / scale
        if known is not None:
            values = torch.where(from_known, k_val, values)
    return best_bary.to(vertices.dtype), None if values is None else values.to(vertices.dtype)


def _settled_at_vertex(tri_n, table: _PointTable, rows, vertex_rows, best_val, best_bary, from_known) -> torch.Tensor:
    """The vertex test: which in-range triangles ``rows`` (R,) have their minimum at their lowest vertex, (R,) bool.

    ``vertex_rows`` (R, 3): the triangles' vertices in ``table``. With g the gradient at the lowest
    vertex v_b, the vertex satisfies the KKT conditions of problem (1) when no other vertex has a lower
    g . v_i (Frank-Wolfe's gap, equation (12), is then exactly 0 there). Such rows take that vertex as
    their answer (``best_*`` updated) and need neither the network nor the polish. Gradients are taken
    once per distinct vertex, shared by the triangles around it, which is what makes the test cheaper
    than a gradient query per triangle. A row whose ``known`` point is lower than its vertices is not settled.
    """
    f_low, lowest, low_rows = table.lowest_vertices(vertex_rows)
    scores = torch.einsum("rc,rvc->rv", table.gradients(low_rows), tri_n[rows])  # g . v_i
    settled = (scores.amin(dim=-1) >= scores.gather(1, lowest.unsqueeze(1)).squeeze(1)) & ~from_known[rows]
    won = rows[settled]
    best_val[won] = f_low[settled]
    best_bary[won] = F.one_hot(lowest[settled], 3).to(best_bary)
    return settled


def _answer_pieces(detector: AmortizedDetector, shape, tri_n, table: _PointTable, pieces: list, best_val, best_bary,
                   from_known, vertex_check: bool, polish: bool, chunk: int) -> None:
    """The network's answers on every piece that reached it, polished and compared with ``best_*``.

    ``pieces``: per group, (rows (P,), the pieces' point rows in ``table`` (P, 3), their grid
    coordinates (P, 3, 2), levels n (P,)); an in-range triangle is its own piece (n = 1). All groups
    share one network batch and one polish, so that each query pays its fixed cost once.

    * In-range triangles: the answer takes ``POLISH_ROUNDS`` line-search steps (:func:`_polish`); without
      ``vertex_check`` it is the answer as is, else it is evaluated and kept where lower.
    * A subdivided triangle: only its lowest piece's answer is polished (inside that piece: one step,
      ``POLISH_ROUNDS`` on a bisected triangle's pieces) and evaluated. Lowest by the network's own estimate of the SDF there (``AmortizedDetector.predict``),
      which spares a query per piece; a head without one has every piece's answer evaluated. The polish
      moves a point by a fraction of its piece, and the piece is in the trained range, so the parabola
      spans no more than the polish of an in-range triangle does (a whole subdivided triangle's edge
      would be too long for it).
    """
    rows = torch.cat([p[0] for p in pieces])
    idx = torch.cat([p[1] for p in pieces])
    level = torch.cat([p[3] for p in pieces])
    grid = torch.cat([p[2] for p in pieces])
    corners = _grid_barycentrics(grid, level.view(-1, 1), tri_n.dtype)  # (P, 3, 3): piece vertex k in parent bary
    local, predicted = _network_answers(detector, table, idx, chunk)
    local = local.to(tri_n.dtype)

    single = (level == 1).nonzero().squeeze(-1)
    multi = (level > 1).nonzero().squeeze(-1)
    if multi.numel() and predicted is None:  # no model of the SDF: every piece's answer is evaluated
        bary = _to_parent(local[multi], corners[multi])
        values = _values_at(shape, tri_n[rows[multi]], bary)
        _improve(best_val, best_bary, from_known, rows[multi], values, bary)
        estimate = values
    else:
        estimate = None if predicted is None else predicted.to(tri_n.dtype)[multi]
    if multi.numel() and (polish or predicted is not None):
        multi = multi[_lowest_per_row(rows[multi], estimate)]
    else:
        multi = multi[:0]  # evaluated above, and nothing to polish
    chosen = torch.cat([single, multi])
    piece_bary = local[chosen]
    if polish:
        # A flat piece takes one step. A bisected triangle's pieces are slivers of a needle far over the
        # range, whose minimum lies on a long side more often than not: one step heads for a corner, the
        # second reaches the side (mug-rack, contacts' mean optimality 8.7e-4 with one step, 4.4e-4 with two).
        bisected = level[chosen] == _BISECTION_LEVEL
        rounds = torch.where((level[chosen] == 1) | bisected, POLISH_ROUNDS, 1)
        piece_bary = _polish(shape, table.coords[idx[chosen]], piece_bary, table, idx[chosen], rounds)
    bary = _to_parent(piece_bary, corners[chosen])
    r = rows[chosen]
    if not vertex_check:  # in-range answers are the network's (polished) as they are
        best_bary[r[: single.numel()]] = bary[: single.numel()]
        r, bary = r[single.numel() :], bary[single.numel() :]
    _improve(best_val, best_bary, from_known, r, _values_at(shape, tri_n[r], bary), bary)


def _network_answers(detector: AmortizedDetector, table: _PointTable, idx: torch.Tensor, chunk: int):
    """The network on the pieces whose corners are the ``table`` rows ``idx`` (P, 3): local bary (P, 3), and
    the model's estimate of the SDF there (P,), or None for a head without one."""
    param = next(detector.parameters())
    answers, estimates = [], []
    for i in idx.split(min(chunk, _NETWORK_CHUNK)):
        vsdf = table.f[i].to(param) if detector.vertex_sdf else None
        with torch.no_grad():
            bary, value = detector.predict(table.coords[i].to(param), table.features(i).to(param), vsdf)
        answers.append(bary)
        estimates.append(value)
    return torch.cat(answers), None if estimates[0] is None else torch.cat(estimates)


def _lowest_per_row(rows: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Index (R,) of the lowest of ``values`` (P,) for each distinct row in ``rows`` (P,) (the first such, by row)."""
    order = torch.argsort(values, stable=True)
    order = order[torch.argsort(rows[order], stable=True)]  # by row, lowest value first
    first = torch.ones_like(order, dtype=torch.bool)
    first[1:] = rows[order][1:] != rows[order][:-1]
    return order[first]


def _values_at(shape, triangles: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Normalised-frame SDF (P,) at barycentrics (P, 3) of ``triangles`` (P, 3, 3)."""
    if bary.shape[0] == 0:
        return bary.new_zeros((0,))
    with torch.no_grad():
        return torch.as_tensor(shape.normalised(bary_to_points(triangles, bary))).reshape(-1).to(bary)


def _polish(shape, triangles: torch.Tensor, bary: torch.Tensor, table: _PointTable, vertex_rows: torch.Tensor,
            rounds) -> torch.Tensor:
    """The network's answers ``bary`` (P, 3) on ``triangles`` (P, 3, 3) (normalised frame) after ``rounds``
    (an int, or (P,) per row) Frank-Wolfe steps with a parabolic line search
    (:func:`zoo.solvers.line_search_steps`): the exact gradient at the answer fixes what the network's
    model of the SDF got wrong. ``vertex_rows`` (P, 3): the triangles' corners in ``table``.

    Each later step starts from the lower of the last answer and the lowest corner where the vertex
    test took that corner's gradient already: an answer the first step left above the vertex would
    otherwise be improved on, and the vertex, though lower, keep its gap.
    """
    from .solvers import line_search_steps

    f_low, lowest, low_rows = table.lowest_vertices(vertex_rows)
    n_vertices = table.grad.shape[0]  # gradients are kept at the mesh's vertices only, not at grid points
    g_low = table.grad[low_rows.clamp_max(n_vertices - 1)]
    known = (low_rows < n_vertices) & ~torch.isnan(g_low[:, 0])
    f_low = torch.where(known, f_low, torch.full_like(f_low, math.inf))  # no gradient: never fall back
    fallback = (F.one_hot(lowest, 3).to(bary), f_low, torch.nan_to_num(g_low))
    return line_search_steps(shape.normalised, triangles, bary, table.f[vertex_rows], rounds,
                             line_steps=POLISH_LINE_STEPS, fallback=fallback)


def _to_parent(local_bary: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Barycentrics (P, 3) in a piece -> in its parent triangle, given the piece's corners in parent barycentrics (P, 3, 3).
    Rows are renormalised to sum to 1 in the working dtype, so the point does not depend on the frame."""
    bary = torch.einsum("pk,pkv->pv", local_bary, corners)
    return bary / bary.sum(dim=-1, keepdim=True)


def _search(table: _PointTable, groups: list, levels, piece_edge, best_val, best_bary, from_known, cut_n,
            cull: bool) -> list:
    """Search of the subdivided triangles: -> their surviving pieces, a list of (rows (P,), point indices
    (P, 3), grid coordinates (P, 3, 2), levels (P,)).

    ``groups``: (rows (R,), cells (C, 3, 2) shared or (R, C, 3, 2) per row, in grid coordinates at
    level n, n, bisected). Each cell is evaluated at its corners and culled; a flat cell that survives
    is a piece; a bisected cell is halved at the midpoint of its longest edge until its
    edges are at most ``piece_edge`` (M,) of its row, and evaluated and culled at every step. All
    groups share each step's queries, a step costing its bookkeeping once, not once per group.
    ``best_*`` take every grid point evaluated. Rows are searched in parts of about ``_CELL_BUDGET``
    cells at their finest (a bisected row of subdivision level n (``levels`` (M,)): 2 n^2 at most).
    """
    rows, grid, level, bisect = [], [], [], []
    for r, base, n, bisected in groups:
        cells_per_row = base.shape[-3]
        rows.append(r.repeat_interleave(cells_per_row))
        grid.append(base.reshape(-1, 3, 2) if base.dim() == 4 else base.repeat(r.numel(), 1, 1))
        level.append(torch.full_like(rows[-1], n))
        bisect.append(torch.full_like(rows[-1], bisected, dtype=torch.bool))
    rows, grid, level, bisect = (torch.cat(t) for t in (rows, grid, level, bisect))
    finest = torch.where(bisect, 2 * levels[rows].square(), 1)  # a row's cells are adjacent, so parts keep rows whole
    part = (finest.cumsum(0) - finest) // _CELL_BUDGET
    first = torch.ones_like(part, dtype=torch.bool)
    first[1:] = rows[1:] != rows[:-1]
    part = part[first][torch.cumsum(first, 0) - 1]  # each cell in its row's first cell's part
    pieces = []
    for p in torch.unique(part).tolist():
        take = part == p
        pieces += _search_part(table, rows[take], grid[take], level[take], bisect[take], piece_edge, best_val, best_bary,
                               from_known, cut_n, cull)
    return pieces


def _search_part(table: _PointTable, cell_rows, grid, level, bisect, piece_edge, best_val, best_bary, from_known,
                 cut_n, cull: bool) -> list:
    """:func:`_search` on cells (C,) of rows ``cell_rows``, grid coordinates ``grid`` (C, 3, 2) at ``level`` (C,),
    ``bisect`` (C,) bool: still to be halved down to ``piece_edge``."""
    pieces = []
    while cell_rows.numel():
        idx = table.grid_points(cell_rows.repeat_interleave(3), grid.reshape(-1, 2), level.repeat_interleave(3)).reshape(-1, 3)
        values = table.f[idx]  # (C, 3)
        corner_bary = _grid_barycentrics(grid, level.view(-1, 1), values.dtype)  # (C, 3, 3)
        _improve(best_val, best_bary, from_known, cell_rows.repeat_interleave(3), values.reshape(-1), corner_bary.reshape(-1, 3))
        if cull:
            lower = cell_lower_bounds(table.coords[idx], values)
            keep = lower <= best_val[cell_rows]
            if cut_n is not None:
                keep &= lower <= cut_n
            cell_rows, grid, idx, level, bisect = cell_rows[keep], grid[keep], idx[keep], level[keep], bisect[keep]
        # only bisected cells are measured: a flat cell is a piece as it stands
        go = bisect.nonzero().squeeze(-1)
        longest, edge = edge_lengths(table.coords[idx[go]]).max(dim=-1)
        a, b, c = _corners_from_edge(grid[go], edge)
        on_grid = ((a + b) % 2 == 0).all(dim=-1)  # the midpoint is a grid point
        halve = (longest > piece_edge[cell_rows[go]]) & on_grid
        go, a, b, c = go[halve], a[halve], b[halve], c[halve]
        done = torch.ones_like(bisect)
        done[go] = False
        if bool(done.any()):
            pieces.append((cell_rows[done], idx[done], grid[done], level[done]))
        # the halves (A, M, C) then (M, B, C): all first halves, then all second ones, oriented as the parent
        m = (a + b) // 2
        grid = torch.cat([torch.stack([a, m, c], 1), torch.stack([m, b, c], 1)])
        cell_rows, level, bisect = (t[go].repeat(2) for t in (cell_rows, level, bisect))
    return pieces


def _corners_from_edge(grid: torch.Tensor, edge: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The corners A, B, C (C, 2) each of cells (C, 3, 2) whose edge ``edge`` (C,) (edge k from corner k to k + 1) runs from A to B."""
    order = (edge.view(-1, 1) + torch.arange(3, device=grid.device)) % 3
    a, b, c = (grid.gather(1, order[:, k].view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1) for k in range(3))
    return a, b, c


def _improve(best_val, best_bary, from_known, rows, values, bary) -> None:
    """Where a candidate (rows (Q,), values (Q,), bary (Q, 3)) beats its row's best, take it (the first such, in order)."""
    if rows.numel() == 0:
        return
    new = best_val.clone().scatter_reduce_(0, rows, values, "amin")
    improved = new < best_val
    if not bool(improved.any()):
        return
    win = (values == new[rows]) & improved[rows]
    first = torch.full(best_val.shape, rows.numel(), dtype=torch.int64, device=rows.device)
    first.scatter_reduce_(0, rows[win], win.nonzero().squeeze(-1), "amin")
    changed = improved.nonzero().squeeze(-1)
    best_bary[changed] = bary[first[changed]]
    best_val.copy_(new)
    from_known[changed] = False


def vertex_features(shape, tri: torch.Tensor) -> torch.Tensor:
    """Code-cloud features at the vertices: (M, 3, 3) normalised -> (M, 3, C), one query per distinct vertex."""
    vertices, inverse = unique_rows(tri.reshape(-1, 3))
    with torch.no_grad():
        f = torch.as_tensor(shape.features(vertices))
    return f[inverse].reshape(tri.shape[0], 3, -1)
