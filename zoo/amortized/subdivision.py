"""How a triangle longer than the detector's trained range is cut into pieces in range.

Pieces and cells are triangles given by integer grid coordinates (..., 3, 2) at a level n: the point
(i, j) is the parent's barycentric (1 - (i+j)/n, i/n, j/n). Three cuts:

* regular: the n^2 similar pieces of the n-subdivision (:func:`subdivision_levels`);
* strips: a needle's 2n - 1 pieces cut across its long sides (:func:`strip_levels`);
* bisection: beyond ``MAX_FLAT_LEVEL``, cells halved across their longest edge on the fine grid of
  ``BISECTION_LEVEL`` (the search in :mod:`zoo.amortized.search` does the halving).
"""

from __future__ import annotations

import torch

from ..geometry import edge_lengths

MAX_FLAT_LEVEL = 7  # subdivision levels up to this are solved flat; beyond, by bisection
MAX_LEVEL = 64  # pieces per edge at most: a longer triangle is solved on pieces over the trained range
# The grid that bisected cells live on: a midpoint of two of its points is one of its points for
# 15 generations of bisection, more than a triangle of MAX_LEVEL needs (about 2 per halving of its length).
BISECTION_LEVEL = 1 << 15


def subdivision_levels(triangles: torch.Tensor, max_edge: float, max_level: int = MAX_LEVEL) -> torch.Tensor:
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
    return grid_barycentrics(subdivision_grid(n), n, torch.float64).to(dtype=dtype, device=device)


def grid_barycentrics(grid: torch.Tensor, n, dtype) -> torch.Tensor:
    """Integer grid coordinates (..., 2) at level ``n`` -> barycentrics (..., 3): (i, j) is (1 - (i+j)/n, i/n, j/n).
    ``n``: an int, or a tensor that broadcasts against grid's leading dimensions ((C, 1) for grid (C, 3, 2))."""
    g = grid.to(dtype)
    n = torch.as_tensor(n, dtype=dtype, device=grid.device).unsqueeze(-1)
    return torch.cat([n - g.sum(-1, keepdim=True), g], dim=-1) / n


def subdivision_grid(n: int, device=None) -> torch.Tensor:
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
    0 where the regular pieces are as few or the strips would need more than ``MAX_FLAT_LEVEL``;
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
    use = (room > 0) & (regular > 1) & (2 * n - 1 < regular.square()) & (n <= MAX_FLAT_LEVEL)
    return torch.where(use, n, torch.zeros_like(n)), apex


def strip_barycentrics(n: int, apex: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Vertices of the 2n - 1 strip pieces of a triangle with apex vertex ``apex``, as barycentrics of the parent:
    (2n - 1, 3, 3); see :func:`strip_levels`."""
    return grid_barycentrics(strip_grid(n, apex), n, torch.float64).to(dtype=dtype, device=device)


def strip_grid(n: int, apex: int, device=None) -> torch.Tensor:
    """Integer grid coordinates (2n - 1, 3, 2) at level n of the strip pieces: (A, P_1, Q_1), then for each k
    (P_k, P_k+1, Q_k+1) and (P_k, Q_k+1, Q_k), with P_k and Q_k at k/n from the apex A to its next and previous vertex."""
    towards_next = {0: lambda k: (k, 0), 1: lambda k: (n - k, k), 2: lambda k: (0, n - k)}[apex]
    towards_prev = {0: lambda k: (0, k), 1: lambda k: (n - k, 0), 2: lambda k: (k, n - k)}[apex]
    p, q = towards_next, towards_prev
    pieces = [[p(0), p(1), q(1)]]
    for k in range(1, n):
        pieces += [[p(k), p(k + 1), q(k + 1)], [p(k), q(k + 1), q(k)]]
    return torch.tensor(pieces, dtype=torch.int64, device=device)


def corners_from_edge(grid: torch.Tensor, edge: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The corners A, B, C (C, 2) each of cells (C, 3, 2) whose edge ``edge`` (C,) (edge k from corner k to k + 1) runs from A to B."""
    order = (edge.view(-1, 1) + torch.arange(3, device=grid.device)) % 3
    a, b, c = (grid.gather(1, order[:, k].view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1) for k in range(3))
    return a, b, c


def to_parent(local_bary: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Barycentrics (P, 3) in a piece -> in its parent triangle, given the piece's corners in parent barycentrics (P, 3, 3).
    Rows are renormalised to sum to 1 in the working dtype, so the point does not depend on the frame."""
    bary = torch.einsum("pk,pkv->pv", local_bary, corners)
    return bary / bary.sum(dim=-1, keepdim=True)
