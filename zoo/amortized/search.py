"""Branch and bound over the cells of subdivided triangles, with Lipschitz culls.

Each cell is evaluated at its corners (through the point table, so shared corners cost one query)
and dropped when its lower bound (:func:`zoo.bounds.cell_lower_bounds`) exceeds its row's best value
so far or the cutoff; a flat cell that survives is a piece for the network, a bisected one is halved
across its longest edge until its edges are in range, and evaluated and culled at every step.
"""

from __future__ import annotations

import torch

from ..bounds import cell_lower_bounds
from ..geometry import edge_lengths
from .best import BestSoFar
from .points import PointTable
from .subdivision import corners_from_edge, grid_barycentrics

CELL_BUDGET = 1 << 20  # cells alive at once in the search (about 50 MB of bookkeeping)


def search(table: PointTable, groups: list, levels, piece_edge, best: BestSoFar, cut_n, cull: bool) -> list:
    """Search of the subdivided triangles: -> their surviving pieces, a list of (rows (P,), point indices
    (P, 3), grid coordinates (P, 3, 2), levels (P,)).

    ``groups``: (rows (R,), cells (C, 3, 2) shared or (R, C, 3, 2) per row, in grid coordinates at
    level n, n, bisected). Each cell is evaluated at its corners and culled; a flat cell that survives
    is a piece; a bisected cell is halved at the midpoint of its longest edge until its
    edges are at most ``piece_edge`` (M,) of its row, and evaluated and culled at every step. All
    groups share each step's queries, a step costing its bookkeeping once, not once per group.
    ``best`` is offered every grid point evaluated. Rows are searched in parts of about ``CELL_BUDGET``
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
    part = (finest.cumsum(0) - finest) // CELL_BUDGET
    first = torch.ones_like(part, dtype=torch.bool)
    first[1:] = rows[1:] != rows[:-1]
    part = part[first][torch.cumsum(first, 0) - 1]  # each cell in its row's first cell's part
    pieces = []
    for p in torch.unique(part).tolist():
        take = part == p
        pieces += search_part(table, rows[take], grid[take], level[take], bisect[take], piece_edge, best, cut_n, cull)
    return pieces


def search_part(table: PointTable, cell_rows, grid, level, bisect, piece_edge, best: BestSoFar, cut_n,
                cull: bool) -> list:
    """:func:`search` on cells (C,) of rows ``cell_rows``, grid coordinates ``grid`` (C, 3, 2) at ``level`` (C,),
    ``bisect`` (C,) bool: still to be halved down to ``piece_edge``."""
    pieces = []
    while cell_rows.numel():
        idx = table.grid_points(cell_rows.repeat_interleave(3), grid.reshape(-1, 2), level.repeat_interleave(3)).reshape(-1, 3)
        values = table.f[idx]  # (C, 3)
        corner_bary = grid_barycentrics(grid, level.view(-1, 1), values.dtype)  # (C, 3, 3)
        best.offer(cell_rows.repeat_interleave(3), values.reshape(-1), corner_bary.reshape(-1, 3))
        if cull:
            lower = cell_lower_bounds(table.coords[idx], values)
            keep = lower <= best.value[cell_rows]
            if cut_n is not None:
                keep &= lower <= cut_n
            cell_rows, grid, idx, level, bisect = cell_rows[keep], grid[keep], idx[keep], level[keep], bisect[keep]
        # only bisected cells are measured: a flat cell is a piece as it stands
        go = bisect.nonzero().squeeze(-1)
        longest, edge = edge_lengths(table.coords[idx[go]]).max(dim=-1)
        a, b, c = corners_from_edge(grid[go], edge)
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
