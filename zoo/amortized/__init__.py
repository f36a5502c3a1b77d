"""Answering triangles with the amortized detector (:mod:`zoo.detector`): :func:`detect` on a batch of
triangles, :func:`solve_mesh` on a mesh's triangles (what ``zoo.collide`` runs as its narrow phase).

One module per job: :mod:`.subdivision` (how long triangles are cut into pieces), :mod:`.points` (the
point table: each point evaluated once), :mod:`.best` (the best answer so far per triangle),
:mod:`.search` (branch and bound over cells), :mod:`.polish` (the vertex test and the line search),
:mod:`.batching` (the network's answers on every piece in one batch) and :mod:`.solve` (the entry points).

Triangles in the trained edge range take one forward pass; longer ones are cut into pieces in the
range and searched with a Lipschitz bound, and the best answer is mapped back to the triangle's
barycentrics.

After the forward pass comes the polish (``polish=True``, the default). First the vertex test: the gradient at
each in-range triangle's lowest vertex (one value-and-gradient query per distinct vertex, shared by the
triangles around it); where no other vertex has a lower g . v_i, that vertex satisfies the KKT
conditions and is the answer, with no network and no further query (most in-range triangles:
docs/results.md measures how many, on the detector bench and the scenes). The rest take the network's answer and
``POLISH_ROUNDS`` Frank-Wolfe steps with a parabolic line search (:func:`zoo.solvers.line_search_step`:
the exact gradient at the point, ``POLISH_LINE_STEPS`` values along the step), which get what
Frank-Wolfe's fixed steps need tens of gradient queries for; ``polish=False`` gives the forward pass
alone. The polish does most of the work: from the lowest vertex instead of the network's answer the
same steps do as well (README, detector bench). The NeuralSDF must have a continuous gradient for
either to reach the KKT conditions (equation (12)): see ``NeuralSDFConfig.smooth_beta``.
"""

from __future__ import annotations

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
from .best import BestSoFar
from .polish import POLISH_LINE_STEPS, POLISH_ROUNDS
from .solve import Known, SolveOptions, detect, solve_mesh, to_normalised_frame, vertex_features
from .subdivision import strip_barycentrics, strip_levels, subdivision_barycentrics, subdivision_levels

__all__ = [
    "POLISH_LINE_STEPS",
    "POLISH_ROUNDS",
    "BestSoFar",
    "Known",
    "SolveOptions",
    "detect",
    "solve_mesh",
    "strip_barycentrics",
    "strip_levels",
    "subdivision_barycentrics",
    "subdivision_levels",
    "to_normalised_frame",
    "vertex_features",
]
