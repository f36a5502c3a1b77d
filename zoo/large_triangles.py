"""Triangles much larger than the SDF, cut into pieces near it before the narrow phase.

Every narrow-phase method answers a triangle by an iterative rule whose error grows with the
triangle's size against the SDF's curvature: Frank-Wolfe's fixed steps end a step of
2/(iters + 1) of the triangle away from the minimum, PhysX's rule runs out of step. A face of
a ground plane or a table (two triangles, far larger than the object on it) then reports no
contact, or one at the wrong depth, for an object resting 1 mm into it. :func:`cut_large` cuts
every triangle longer than ``SPLIT_ABOVE`` of the SDF's median extent (the simulation refines
its meshes to that size at build, so its triangles pass through untouched) into pieces of at
most ``PIECE_AT_MOST`` of it, splitting each piece at its edges' midpoints level by level and
dropping, at every level, the pieces proven to stay above the margin: those whose box misses
the SDF's bounds grown by the margin, and those whose Lipschitz lower bound from f at their
corners exceeds it (:func:`zoo.bounds.cell_lower_bounds`). What is left is a few hundred
pieces around the SDF, whatever the triangle's size; the narrow phase solves them and
:func:`best_pieces` keeps, per triangle, the piece with the lowest answer, so a triangle still
gives one contact. docs/measurements.md measures the error with and without.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .bounds import cell_lower_bounds, rounding_slack
from .errors import InputError
from .geometry import edge_lengths, unique_rows

SPLIT_ABOVE = 1 / 4  # a triangle whose longest edge exceeds this fraction of the SDF's median extent is cut
PIECE_AT_MOST = 1 / 8  # into pieces whose longest edge is at most this fraction of it
MAX_PIECES = 1 << 20  # more pieces than this in one call is refused, not solved on fewer


@dataclass
class Pieces:
    """Candidate triangles (C, 3, 3) with the large ones replaced by their pieces near the SDF.

    Attributes:
        triangles: (P, 3, 3) the pieces; a triangle that was not cut is its own single piece.
        parent: (P,) int64, the index of each piece's triangle among the C candidates.
        corners: (P, 3, 3) each piece's corners as barycentrics of its parent (row k: corner k).
        values: (P, 3) f at each piece's corners, NaN where it was not evaluated.
        floor: (C,) a lower bound of f over the parts of each triangle that were dropped (+inf
            where none was): a triangle with no piece left stays above it, and above the margin.
    """

    triangles: torch.Tensor
    parent: torch.Tensor
    corners: torch.Tensor
    values: torch.Tensor
    floor: torch.Tensor

    def to_parent(self, index: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """Barycentrics (K, 3) on the pieces ``index`` (K,) -> on their parents (K, 3), rows summing to 1."""
        out = torch.einsum("kc,kcv->kv", bary, self.corners[index])
        return out / out.sum(dim=-1, keepdim=True)


def split_length(sdf) -> tuple[float, float]:
    """(longest edge a triangle may have before it is cut, longest edge of a piece) for ``sdf``, from
    the median extent of its bounds; (inf, inf) for unbounded SDFs."""
    lo, hi = (torch.as_tensor(b, dtype=torch.float64).reshape(3) for b in sdf.bounds)
    extent = float((hi - lo).median())
    if not math.isfinite(extent) or extent <= 0:
        return math.inf, math.inf
    return SPLIT_ABOVE * extent, PIECE_AT_MOST * extent


def cut_large(sdf, triangles: torch.Tensor, margin: float, vertex_values: torch.Tensor | None = None) -> Pieces | None:
    """The candidates (C, 3, 3) (the SDF's frame) with every triangle longer than :func:`split_length` allows
    cut into pieces near the SDF; None when no triangle is that long (nothing to do).

    ``vertex_values`` (C, 3): f at the triangles' corners where the caller has it (NaN elsewhere); carried
    into :attr:`Pieces.values` for the triangles that are not cut. Raises :class:`InputError` when the cut
    would need more than ``MAX_PIECES`` pieces.
    """
    split_above, piece_max = split_length(sdf)
    longest = edge_lengths(triangles).amax(dim=-1)
    large = longest > split_above
    if not bool(large.any()):
        return None
    n, dtype, device = triangles.shape[0], triangles.dtype, triangles.device
    lo, hi = (torch.as_tensor(b).to(triangles).reshape(3) for b in sdf.bounds)
    eye = torch.eye(3, dtype=dtype, device=device)
    values = (torch.full((n, 3), math.nan, dtype=dtype, device=device) if vertex_values is None
              else torch.as_tensor(vertex_values).to(triangles).reshape(n, 3))
    floor = torch.full((n,), math.inf, dtype=dtype, device=device)
    small = (~large).nonzero().squeeze(-1)
    done = [(small, eye.expand(small.numel(), 3, 3), values[small])]
    parent = large.nonzero().squeeze(-1)
    corners = eye.expand(parent.numel(), 3, 3)
    total = small.numel()
    while parent.numel():
        parent, corners = parent.repeat_interleave(4), _quarters(corners)
        pts = torch.einsum("pkv,pvc->pkc", corners, triangles[parent])
        # f outside the bounds is at least the distance to them: a piece whose box is farther than the margin
        # from the bounds stays above the margin
        gap = torch.maximum(lo - pts.amax(dim=1), pts.amin(dim=1) - hi).clamp_min(0).norm(dim=-1)
        near = gap - rounding_slack(torch.zeros_like(gap), gap, pts.abs().amax(dim=(1, 2))) <= margin
        floor.scatter_reduce_(0, parent[~near], gap[~near], "amin")
        parent, corners, pts = parent[near], corners[near], pts[near]
        if parent.numel() + total > MAX_PIECES:
            raise InputError(
                f"a triangle {float(longest.max()):.3g} long is {float(longest.max()) / piece_max:.3g} times the piece "
                f"size the narrow phase needs near this SDF, and cutting it near the SDF needs over {MAX_PIECES} "
                "pieces; subdivide the mesh first (trimesh.remesh.subdivide_to_size) or collide a smaller region of it"
            )
        if parent.numel() == 0:
            break
        unique, inverse = unique_rows(pts.reshape(-1, 3))
        with torch.no_grad():
            f = torch.as_tensor(sdf(unique)).reshape(-1).to(pts)[inverse].reshape(-1, 3)
        bound = cell_lower_bounds(pts, f)
        reach = bound <= margin
        floor.scatter_reduce_(0, parent[~reach], bound[~reach], "amin")
        parent, corners, pts, f = parent[reach], corners[reach], pts[reach], f[reach]
        fine = edge_lengths(pts).amax(dim=-1) <= piece_max
        done.append((parent[fine], corners[fine], f[fine]))
        total += int(fine.sum())
        parent, corners = parent[~fine], corners[~fine]
    parent = torch.cat([d[0] for d in done])
    corners = torch.cat([d[1] for d in done])
    return Pieces(torch.einsum("pkv,pvc->pkc", corners, triangles[parent]), parent, corners,
                  torch.cat([d[2] for d in done]), floor)


def _quarters(corners: torch.Tensor) -> torch.Tensor:
    """Each piece (P, 3, 3) (corners as parent barycentrics) cut at its edges' midpoints -> (4P, 3, 3)."""
    c0, c1, c2 = corners.unbind(dim=1)
    m01, m12, m20 = (c0 + c1) / 2, (c1 + c2) / 2, (c2 + c0) / 2
    four = [(c0, m01, m20), (m01, c1, m12), (m20, m12, c2), (m01, m12, m20)]  # each keeps the parent's orientation
    return torch.stack([torch.stack(t, dim=1) for t in four], dim=1).reshape(-1, 3, 3)


def best_pieces(depths: torch.Tensor, parent: torch.Tensor, n: int) -> torch.Tensor:
    """Per triangle, the piece with the lowest depth: depths (P,), parent (P,) -> index (n,) into the pieces,
    -1 for a triangle with no piece (ties: the first piece)."""
    lowest = torch.full((n,), math.inf, dtype=depths.dtype, device=depths.device)
    lowest.scatter_reduce_(0, parent, depths, "amin")
    rows = torch.arange(parent.numel(), device=parent.device)
    at_lowest = depths <= lowest[parent]
    index = torch.full((n,), parent.numel(), dtype=torch.int64, device=parent.device)
    index.scatter_reduce_(0, parent[at_lowest], rows[at_lowest], "amin")
    return torch.where(index == parent.numel(), -1, index)
