"""The amortized detector's answers on a mesh's triangles (:func:`solve_mesh`) and on a batch of triangles
(:func:`detect`): each triangle sorted by size, in-range ones to the vertex test and the network,
longer ones through the subdivision search, every candidate offered to one :class:`BestSoFar`."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..bounds import cell_lower_bounds
from ..detector import AmortizedDetector
from ..errors import InputError
from ..geometry import edge_lengths, transform_points, unique_rows
from ..validation import as_triangles, int_at_least
from . import batching
from .batching import NETWORK_CHUNK
from .best import BestSoFar
from .points import PointTable
from .polish import settled_at_vertex
from .search import search
from .subdivision import (
    BISECTION_LEVEL,
    MAX_FLAT_LEVEL,
    MAX_LEVEL,
    strip_grid,
    strip_levels,
    subdivision_grid,
    subdivision_levels,
)


@dataclass(frozen=True)
class SolveOptions:
    """How :func:`solve_mesh` solves.

    * ``vertex_check``: an in-range triangle's answer is the lowest of the network's, its three
      vertices and the ``known`` point (else the network's as it is);
    * ``cull=False`` evaluates every piece (the exhaustive search; the culls assume the SDF is
      ``zoo.bounds.LIPSCHITZ``-Lipschitz and otherwise give the same answer);
    * ``polish``: the vertex test, then line-search steps from the network's answers (:mod:`zoo.amortized.polish`);
    * ``cutoff`` (source frame, needs ``vertex_check``): triangles and cells whose lower bound
      (:func:`zoo.bounds.cell_lower_bounds`) exceeds it are not solved; such a row's value is only
      proven to be > cutoff (what collide needs of a triangle that is no contact);
    * ``chunk``: pieces per network call at most (a positive int; the default is cache-sized).
    """

    vertex_check: bool = True
    cull: bool = True
    polish: bool = False
    cutoff: float | None = None
    chunk: int = NETWORK_CHUNK

    def __post_init__(self):
        object.__setattr__(self, "chunk", int_at_least(self.chunk, "chunk", minimum=1))
        if self.cutoff is not None and not self.vertex_check:
            raise InputError("solve_mesh: a cutoff needs vertex_check=True (the culls compare against vertex values)")


@dataclass(frozen=True)
class Known:
    """What the caller of :func:`solve_mesh` knows already, in the source frame.

    * ``bary`` (M, 3) and ``values`` (M,): a point per triangle and its distance, taken where lower
      than the answer;
    * ``vertex_values`` (V,): distances at the vertices, NaN where not known (collide passes those its
      broad phase evaluated); they are not queried again.
    """

    bary: torch.Tensor | None = None
    values: torch.Tensor | None = None
    vertex_values: torch.Tensor | None = None


def detect(detector: AmortizedDetector, shape, triangles, chunk: int = NETWORK_CHUNK, vertex_check: bool = False,
           polish: bool = True) -> torch.Tensor:
    """Amortized minimum of ``shape``'s SDF on each triangle: (M, 3, 3) source frame -> bary (M, 3).

    ``shape`` is a fitted NeuralShape (or any object with ``features(points_norm (N, 3)) -> (N, C)``,
    ``normalised`` (its SDF in the normalised frame) and optionally ``similarity``; without
    ``similarity`` the source frame is the normalised one). Barycentric coordinates are invariant
    under the similarity transform, so the triangles are mapped into the normalised frame and the
    answer is returned as is. float64 input gives float64 output; zero triangles give (0, 3).

    In-range triangles get the network's answer (one pass; features computed once per distinct
    vertex). Triangles with an edge longer than the trained range are subdivided into the range
    (up to 7x the range into regular pieces or a needle's strips, :func:`zoo.amortized.subdivision.strip_levels`;
    beyond, by bisection) and the answer is the lowest of the pieces' answers and the grid points
    evaluated on the way (a search with Lipschitz culls, see :func:`solve_mesh`).
    ``vertex_check=True`` also compares each in-range answer with the triangle's best vertex
    and keeps the lower (one more SDF query per triangle and one per distinct vertex).
    ``polish=True`` (the default): an in-range triangle whose lowest vertex passes the vertex test
    (:func:`zoo.amortized.polish.settled_at_vertex`) is answered there; the others end with
    ``POLISH_ROUNDS`` Frank-Wolfe steps with a parabolic line search from the network's answer
    (:func:`zoo.amortized.polish.polish`; each one value-and-gradient query and ``POLISH_LINE_STEPS``
    value queries; on a subdivided triangle, from the lowest piece's answer, inside that piece: one
    step, ``POLISH_ROUNDS`` on a bisected one); ``polish=False`` returns the network's answer of the
    single forward pass.
    """
    tri_src = as_triangles(triangles, allow_empty=True)
    vertices, inverse = unique_rows(tri_src.reshape(-1, 3))
    options = SolveOptions(vertex_check=vertex_check, chunk=chunk, polish=polish)
    bary, _ = solve_mesh(detector, shape, vertices, inverse.reshape(-1, 3), options)
    return bary


def solve_mesh(detector: AmortizedDetector, shape, vertices, faces, options: SolveOptions = SolveOptions(),
               known: Known | None = None):
    """Amortized minima of ``shape``'s SDF on the triangles ``vertices[faces]``: -> bary (M, 3), values (M,) or None.

    ``vertices`` (V, 3) in the shape's source frame (only those ``faces`` (M, 3) name are used),
    ``faces`` int (M, 3). ``values`` are the source-frame signed distances at the returned points
    (None when nothing was evaluated there: ``vertex_check=False`` on in-range triangles only).

    * In-range triangles: the network's answer; with ``options.vertex_check``, the lowest of it, the
      three vertices and the ``known`` point.
    * Longer triangles: the lowest of the answers on the surviving pieces and the grid points
      evaluated (and the ``known`` point), searched with Lipschitz culls (:func:`zoo.amortized.search.search`).
    * ``options.polish``: in-range triangles whose lowest vertex passes the vertex test are answered
      there; each other in-range answer of the network takes ``POLISH_ROUNDS`` line-search steps before
      it is compared with the vertices and the ``known`` point; a subdivided triangle's lowest piece
      answer takes one inside its piece (a bisected triangle's, ``POLISH_ROUNDS``;
      :func:`zoo.amortized.batching.answer_pieces`).
    """
    known = known or Known()
    faces = torch.as_tensor(faces, device=vertices.device).long()
    if faces.shape[0] == 0:
        empty = vertices.new_zeros((0, 3))
        return empty, (vertices.new_zeros((0,)) if options.vertex_check else None)
    used, local = torch.unique(faces, return_inverse=True)
    v_n = to_normalised_frame(shape, vertices[used])
    tri_n = v_n[local]  # (M, 3, 3)
    scale = _scale(shape)
    levels = subdivision_levels(tri_n, detector.edge_range[1])
    single = levels == 1
    strips, apex = strip_levels(tri_n, detector.edge_range[1])
    striped = ~single & (strips > 0)
    # distances are needed at the vertices of subdivided triangles (bounds, candidates), at every
    # vertex with the vertex check, and wherever the detector reads them
    needs_f = torch.ones_like(single) if (options.vertex_check or detector.vertex_sdf) else ~single
    given = _given_vertex_values(known.vertex_values, vertices, used, scale, v_n.dtype)
    table = PointTable(shape, v_n, local, local[needs_f].reshape(-1), given)
    best = _first_candidates(table, local, needs_f, single, known, scale, options.vertex_check)
    cut_n = None if options.cutoff is None else float(options.cutoff) * scale

    # the pieces that reach the network: (rows (P,), their point indices (P, 3), grid coordinates (P, 3, 2), levels (P,))
    pieces = _in_range_pieces(tri_n, table, local, single, best, cut_n, options)
    groups = _subdivided_groups(levels, single, striped, strips, apex)
    if groups:
        # a bisected cell is a piece once its edges are in range (or 1/MAX_LEVEL of its triangle's longest)
        piece_edge = (edge_lengths(tri_n).amax(dim=-1) / MAX_LEVEL).clamp_min(detector.edge_range[1])
        pieces += search(table, groups, levels, piece_edge, best, cut_n, options.cull)
    if pieces:
        batching.answer_pieces(detector, shape, tri_n, table, pieces, best, options.vertex_check, options.polish,
                               options.chunk)
    return best.bary.to(vertices.dtype), _source_values(best, known, scale, options.vertex_check, vertices.dtype)


def _given_vertex_values(vertex_values, vertices: torch.Tensor, used: torch.Tensor, scale: float, dtype):
    """The caller's source-frame distances (V,) at the vertices -> normalised-frame ones (U,) at the used
    vertices ``used`` (U,), NaN where not known; None when none were given."""
    if vertex_values is None:
        return None
    given = torch.as_tensor(vertex_values, device=vertices.device).reshape(-1)
    if given.shape[0] != vertices.shape[0]:
        raise InputError(f"solve_mesh: vertex_values must hold one distance per vertex ({vertices.shape[0]}), got {given.shape[0]}")
    return given[used].to(dtype) * scale


def _first_candidates(table: PointTable, local: torch.Tensor, needs_f: torch.Tensor, single: torch.Tensor, known: Known,
                      scale: float, vertex_check: bool) -> BestSoFar:
    """The best so far before any solving: the lowest vertex where its distances were taken (not for an
    in-range triangle without the vertex check: its answer is the network's), then the ``known`` point."""
    m_rows = local.shape[0]
    best = BestSoFar(m_rows, table.coords.dtype, table.coords.device)
    rows_f = needs_f.nonzero().squeeze(-1)
    if rows_f.numel():  # the vertices are candidates
        value, corner = table.f[local[rows_f]].min(dim=-1)  # (R, 3) -> (R,)
        best.set_vertices(rows_f, corner, value)
    if not vertex_check:
        best.forget_values(single)  # in-range answers are the network's, whatever the vertices
    if known.bary is not None:
        k_bary, k_val = _known_point(known, best.value)
        best.offer_known(k_bary, k_val * scale, vertex_check | ~single)
    return best


def _known_point(known: Known, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The known point's (bary (M, 3), source-frame values (M,)) in the dtype and on the device of ``like``."""
    return tuple(torch.as_tensor(t, device=like.device).to(like.dtype) for t in (known.bary, known.values))


def _in_range_pieces(tri_n, table: PointTable, local, single, best: BestSoFar, cut_n, options: SolveOptions) -> list:
    """The in-range triangles that go to the network, each its own piece: [] or [(rows, corner rows (R, 3),
    grid (R, 3, 2), levels (R,) = 1)]; those the cutoff clears or the vertex test settles do not."""
    single_rows = single.nonzero().squeeze(-1)
    if not single_rows.numel():
        return []
    corners = subdivision_grid(1, tri_n.device).expand(single_rows.numel(), -1, -1)
    idx = local[single_rows]
    if options.cull and cut_n is not None:
        keep = cell_lower_bounds(tri_n[single_rows], table.f[idx]) <= cut_n
        single_rows, idx, corners = single_rows[keep], idx[keep], corners[keep]
    if options.polish:  # rows whose lowest vertex is a KKT point are answered there, without the network
        settled = settled_at_vertex(tri_n, table, single_rows, idx, best)
        single_rows, idx, corners = single_rows[~settled], idx[~settled], corners[~settled]
    if not single_rows.numel():
        return []
    return [(single_rows, idx, corners, torch.ones_like(single_rows))]


def _subdivided_groups(levels, single, striped, strips, apex) -> list:
    """The longer triangles by how they are cut: [(rows (R,), their cells (C, 3, 2) or (R, C, 3, 2) in grid
    coordinates at level n, n, bisected)]: regular pieces and strips per level, then all bisected rows."""
    device = levels.device
    flat = ~single & ~striped & (levels <= MAX_FLAT_LEVEL)
    groups = []
    for n in torch.unique(levels[flat]).tolist():
        rows = (flat & (levels == n)).nonzero().squeeze(-1)
        groups.append((rows, subdivision_grid(n, device), n, False))
    for n in torch.unique(strips[striped]).tolist():
        rows = (striped & (strips == n)).nonzero().squeeze(-1)
        by_apex = torch.stack([strip_grid(n, a, device) for a in range(3)])  # (3, 2n - 1, 3, 2)
        groups.append((rows, by_apex[apex[rows]], n, False))
    bisected = (~single & ~striped & ~flat).nonzero().squeeze(-1)
    if bisected.numel():
        groups.append((bisected, subdivision_grid(1, device) * BISECTION_LEVEL, BISECTION_LEVEL, True))
    return groups


def _source_values(best: BestSoFar, known: Known, scale: float, vertex_check: bool, dtype) -> torch.Tensor | None:
    """Source-frame distances (M,) at the answers (the known point's as given), or None without the vertex check."""
    if not vertex_check:
        return None
    values = best.value / scale
    if known.bary is not None:
        values = torch.where(best.from_known, _known_point(known, best.value)[1], values)
    return values.to(dtype)


def to_normalised_frame(shape, triangles: torch.Tensor) -> torch.Tensor:
    """Triangles (M, 3, 3) (or points (..., 3)) in the shape's source frame -> its normalised frame, same dtype and device."""
    similarity = getattr(shape, "similarity", None)
    if similarity is None:
        return triangles
    return transform_points(torch.as_tensor(similarity.matrix, dtype=triangles.dtype, device=triangles.device), triangles)


def _scale(shape) -> float:
    similarity = getattr(shape, "similarity", None)
    return 1.0 if similarity is None else float(similarity.scale)


def vertex_features(shape, tri: torch.Tensor) -> torch.Tensor:
    """Code-cloud features at the vertices: (M, 3, 3) normalised -> (M, 3, C), one query per distinct vertex."""
    vertices, inverse = unique_rows(tri.reshape(-1, 3))
    with torch.no_grad():
        f = torch.as_tensor(shape.features(vertices))
    return f[inverse].reshape(tri.shape[0], 3, -1)
