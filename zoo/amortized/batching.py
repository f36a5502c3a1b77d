"""The network's answers on every piece that reached it, in one batch, polished and offered to the best so far."""

from __future__ import annotations

import torch

from ..detector import AmortizedDetector
from ..geometry import bary_to_points
from .best import BestSoFar
from .points import PointTable
from .polish import POLISH_ROUNDS, polish
from .subdivision import BISECTION_LEVEL, grid_barycentrics, to_parent

NETWORK_CHUNK = 4096  # default pieces per network call, cache-sized like the NeuralShape chunks (docs/measurements.md)


def answer_pieces(detector: AmortizedDetector, shape, tri_n, table: PointTable, pieces: list, best: BestSoFar,
                  vertex_check: bool, polish_answers: bool, chunk: int) -> None:
    """The network's answers on every piece that reached it, polished and offered to ``best``.

    ``pieces``: per group, (rows (P,), the pieces' point rows in ``table`` (P, 3), their grid
    coordinates (P, 3, 2), levels n (P,)); an in-range triangle is its own piece (n = 1). All groups
    share one network batch and one polish, so that each query pays its fixed cost once.

    * In-range triangles: the answer takes ``POLISH_ROUNDS`` line-search steps (:func:`zoo.amortized.polish.polish`);
      without ``vertex_check`` it is the answer as is, else it is evaluated and kept where lower.
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
    corners = grid_barycentrics(grid, level.view(-1, 1), tri_n.dtype)  # (P, 3, 3): piece vertex k in parent bary
    local, predicted = network_answers(detector, table, idx, chunk)
    local = local.to(tri_n.dtype)

    single = (level == 1).nonzero().squeeze(-1)
    multi = (level > 1).nonzero().squeeze(-1)
    if multi.numel() and predicted is None:  # no model of the SDF: every piece's answer is evaluated
        bary = to_parent(local[multi], corners[multi])
        values = values_at(shape, tri_n[rows[multi]], bary)
        best.offer(rows[multi], values, bary)
        estimate = values
    else:
        estimate = None if predicted is None else predicted.to(tri_n.dtype)[multi]
    if multi.numel() and (polish_answers or predicted is not None):
        multi = multi[lowest_per_row(rows[multi], estimate)]
    else:
        multi = multi[:0]  # evaluated above, and nothing to polish
    chosen = torch.cat([single, multi])
    piece_bary = local[chosen]
    if polish_answers:
        # A flat piece takes one step. A bisected triangle's pieces are slivers of a needle far over the
        # range, whose minimum lies on a long side more often than not: one step heads for a corner, the
        # second reaches the side (mug-rack, contacts' mean optimality 8.7e-4 with one step, 4.4e-4 with two).
        bisected = level[chosen] == BISECTION_LEVEL
        rounds = torch.where((level[chosen] == 1) | bisected, POLISH_ROUNDS, 1)
        piece_bary = polish(shape, table.coords[idx[chosen]], piece_bary, table, idx[chosen], rounds)
    bary = to_parent(piece_bary, corners[chosen])
    r = rows[chosen]
    if not vertex_check:  # in-range answers are the network's (polished) as they are
        best.place(r[: single.numel()], bary[: single.numel()])
        r, bary = r[single.numel() :], bary[single.numel() :]
    best.offer(r, values_at(shape, tri_n[r], bary), bary)


def network_answers(detector: AmortizedDetector, table: PointTable, idx: torch.Tensor, chunk: int):
    """The network on the pieces whose corners are the ``table`` rows ``idx`` (P, 3): local bary (P, 3), and
    the model's estimate of the SDF there (P,), or None for a head without one."""
    param = next(detector.parameters())
    answers, estimates = [], []
    for i in idx.split(chunk):
        vsdf = table.f[i].to(param) if detector.vertex_sdf else None
        with torch.no_grad():
            bary, value = detector.predict(table.coords[i].to(param), table.features(i).to(param), vsdf)
        answers.append(bary)
        estimates.append(value)
    return torch.cat(answers), None if estimates[0] is None else torch.cat(estimates)


def lowest_per_row(rows: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Index (R,) of the lowest of ``values`` (P,) for each distinct row in ``rows`` (P,) (the first such, by row)."""
    order = torch.argsort(values, stable=True)
    order = order[torch.argsort(rows[order], stable=True)]  # by row, lowest value first
    first = torch.ones_like(order, dtype=torch.bool)
    first[1:] = rows[order][1:] != rows[order][:-1]
    return order[first]


def values_at(shape, triangles: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Normalised-frame SDF (P,) at barycentrics (P, 3) of ``triangles`` (P, 3, 3)."""
    if bary.shape[0] == 0:
        return bary.new_zeros((0,))
    with torch.no_grad():
        return torch.as_tensor(shape.normalised(bary_to_points(triangles, bary))).reshape(-1).to(bary)
