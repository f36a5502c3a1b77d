"""After the forward pass: the vertex test, then line-search steps from the network's answers.

The vertex test: the gradient at each in-range triangle's lowest vertex (one value-and-gradient query
per distinct vertex, shared by the triangles around it); where no other vertex has a lower g . v_i,
that vertex satisfies the KKT conditions and is the answer, with no network and no further query. The
rest take the network's answer and ``POLISH_ROUNDS`` Frank-Wolfe steps with a parabolic line search
(:func:`zoo.solvers.line_search_steps`: the exact gradient at the point, ``POLISH_LINE_STEPS`` values
along the step).
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from .best import BestSoFar
from .points import PointTable

# Value queries after the polish's gradient query (zoo.solvers.line_search_step): two, where the detector
# bench's optimality stops improving (docs/detector-notes.md, the polish).
POLISH_LINE_STEPS = 2
# Line-search steps per polished in-range answer (a regularly subdivided triangle's lowest piece takes one). The
# vertex test settles most in-range triangles first, so the polish runs on the rest only; a third step would
# improve optimality but cost the scene bench's contact check its lead over FW (docs/detector-notes.md).
POLISH_ROUNDS = 2


def settled_at_vertex(tri_n, table: PointTable, rows, vertex_rows, best: BestSoFar) -> torch.Tensor:
    """The vertex test: which in-range triangles ``rows`` (R,) have their minimum at their lowest vertex, (R,) bool.

    ``tri_n`` (M, 3, 3): all the triangles, normalised frame; ``vertex_rows`` (R, 3): the tested
    triangles' vertices in ``table``. With g the gradient at the lowest vertex v_b, the vertex satisfies
    the KKT conditions of problem (1) when no other vertex has a lower g . v_i (Frank-Wolfe's gap,
    equation (12), is then exactly 0 there). Such rows take that vertex as their answer in ``best`` and
    need neither the network nor the polish. Gradients are taken once per distinct vertex, shared by the
    triangles around it, which is what makes the test cheaper than a gradient query per triangle. A row
    whose ``known`` point is lower than its vertices is not settled.
    """
    f_low, lowest, low_rows = table.lowest_vertices(vertex_rows)
    scores = torch.einsum("rc,rvc->rv", table.gradients(low_rows), tri_n[rows])  # g . v_i
    settled = (scores.amin(dim=-1) >= scores.gather(1, lowest.unsqueeze(1)).squeeze(1)) & ~best.from_known[rows]
    best.set_vertices(rows[settled], lowest[settled], f_low[settled])
    return settled


def polish(shape, triangles: torch.Tensor, bary: torch.Tensor, table: PointTable, vertex_rows: torch.Tensor,
           rounds) -> torch.Tensor:
    """The network's answers ``bary`` (P, 3) on ``triangles`` (P, 3, 3) (normalised frame) after ``rounds``
    (an int, or (P,) per row) Frank-Wolfe steps with a parabolic line search
    (:func:`zoo.solvers.line_search_steps`): the exact gradient at the answer fixes what the network's
    model of the SDF got wrong. ``vertex_rows`` (P, 3): the triangles' corners in ``table``.

    Each later step starts from the lower of the last answer and the lowest corner where the vertex
    test took that corner's gradient already: an answer the first step left above the vertex would
    otherwise be improved on, and the vertex, though lower, keep its gap.
    """
    from ..solvers import line_search_steps

    f_low, lowest, low_rows = table.lowest_vertices(vertex_rows)
    n_vertices = table.grad.shape[0]  # gradients are kept at the mesh's vertices only, not at grid points
    g_low = table.grad[low_rows.clamp_max(n_vertices - 1)]
    known = (low_rows < n_vertices) & ~torch.isnan(g_low[:, 0])
    f_low = torch.where(known, f_low, torch.full_like(f_low, math.inf))  # no gradient: never fall back
    fallback = (F.one_hot(lowest, 3).to(bary), f_low, torch.nan_to_num(g_low))
    return line_search_steps(shape.normalised, triangles, bary, table.f[vertex_rows], rounds,
                             line_steps=POLISH_LINE_STEPS, fallback=fallback)
