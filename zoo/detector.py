"""The amortized NeuralSDF-triangle collision detector (paper section III, equations (6)-(8)).

One forward pass maps a triangle (M, 3, 3) and the shape's code-cloud features at its
vertices (M, 3, C) to the barycentric coordinates (M, 3) of the point of minimum signed
distance on it, replacing tens of Frank-Wolfe iterations that each query the NeuralSDF.

Network (docs/paper-notes.md, "The network, (6)-(8)"):

* g_phi, a shared MLP 3-16-1 with ReLU, scores each vertex from
  [|v_i - centroid| / perimeter, the two cosines cos(z_i, z_j), j != i]; a softmax over the
  three scores gives weights w, and the triangle feature is z_tri = sum_i w_i z_i (7).
* h_psi1, a shared per-vertex MLP, gives one logit per vertex; h_psi2, an MLP 32-32-32-1,
  reads z_tri; the barycentrics are a softmax over the three vertex logits (8).

Equation (8) as printed adds h_psi2(z_tri) to all three logits alike, and a softmax ignores a
common shift, so z_tri would have no effect. ``triangle_feature`` chooses how it acts:

* ``"condition"`` (default): h_psi1 also reads z_tri and two relative cues
  ([z_i; v_i; (v_i - centroid)/perimeter; dz_i; z_tri], dz_i = z_i - mean_j z_j), a head on
  [z_tri; centroid] proposes a descent direction d whose score -d . (v_i - centroid) is added
  (Frank-Wolfe's vertex rule when d is the SDF's gradient), and h_psi2(z_tri) sets the softmax
  temperature (how sharply the answer commits to a vertex).
* ``"context"``: as "condition", but h_psi1 is split around a symmetric pooling (mean, max,
  min over the three vertex embeddings, plus z_tri), so each vertex is scored against the others.
* ``"temperature"``: h_psi1 reads only its own [z_i; v_i]; h_psi2(z_tri) sets the temperature.
* ``"additive"``: equation (8) exactly as printed (z_tri provably has no effect; kept to show it).
* ``"none"``: no triangle feature at all (the ablation "without z_tri").

``vertex_features=False`` zeroes z_i (the ablation "without vertex features").
``vertex_sdf=True`` also feeds f(v_i) (three SDF queries per triangle, no gradients) to h_psi1.
``output``: ``"softmax"`` (the paper's), ``"sparsemax"`` (reaches vertices and edges exactly),
``"grid"`` (vertex scores plus a per-edge curvature term, soft arg-max over a barycentric grid), or
``"quadratic"`` (needs ``vertex_sdf``): the SDF on the triangle is modelled as the quadratic that
takes the three vertex values f_i and bends along each edge by a learned curvature kappa_k,
q(l) = sum_i l_i f_i - sum_k l_i l_j kappa_k (exact for a quadratic SDF), and the answer is its exact
minimum over the triangle (:func:`quadratic_argmin`). The vertex values make the vertex choice exact
(80% of minima lie at a vertex); the network only has to say how much each edge bends.
Features are standardised by fixed statistics of the training set (buffers saved with the weights).

Answering triangles with it (in the trained range or not, one at a time or a whole mesh, with the
polish that follows the forward pass) is :mod:`zoo.amortized`.

Every per-vertex network is shared across the three vertices and every pooling is symmetric
(softmax-weighted sum; the two cosines are sorted), so permuting the vertices permutes the
barycentrics the same way and the predicted point does not move.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .errors import InputError
from .geometry import barycentric_grid, edge_lengths

TRIANGLE_FEATURE_MODES = ("condition", "context", "temperature", "additive", "none")
# softmax: the paper's; sparsemax: the Euclidean projection of the scores onto the simplex, which
# reaches a vertex or an edge exactly (most minima lie at a vertex, where a softmax only tends).
# grid: the vertex scores plus a learned per-edge curvature term define a quadratic score over
# the triangle, and the answer is its soft arg-max over a barycentric grid (edge minima, where
# a per-vertex softmax must balance two logits just so, come out of one edge term).
OUTPUTS = ("softmax", "sparsemax", "grid", "quadratic")
_GRID_RESOLUTION = 24  # grid steps per edge: 325 candidate points per triangle
# the edge (i, j) of each pair slot; slot k is the edge opposite vertex k
EDGE_PAIRS = ((1, 2), (2, 0), (0, 1))

# The paper's training-set edge range (normalised frame); triangles longer than the upper
# bound are subdivided by zoo.amortized, see ``zoo.amortized.subdivision_levels``.
DEFAULT_EDGE_RANGE = (0.03, 0.08)
# Where a temperature is learned it is softplus(h_psi2) + this floor, so it never reaches 0
# (which would flatten every answer to the centroid) and needs no clamping.
_MIN_TEMPERATURE_SCALE = 0.05
# offsets are ~0.3 per perimeter; this gain lets an O(1) direction give logit gaps of several units.
_DIRECTION_GAIN = 10.0
# Edge curvatures per perimeter of SDFs near a surface are ~0.02 (mugs, the torus); starting the
# head there rather than at softplus(0) = 0.7 saves most of a short training run.
_INITIAL_CURVATURE_LOGIT = -4.0
# A perimeter floor that keeps degenerate (zero-size) triangles finite.
_TINY_LENGTH = 1e-12


def _mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers of ``sizes`` with ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class AmortizedDetector(nn.Module):
    """Predicts the barycentric coordinates of a triangle's point of minimum signed distance.

    Works in the shape's normalised frame ([-0.5, 0.5]^3). Call it as
    ``detector(triangles (M, 3, 3), features (M, 3, C)) -> bary (M, 3)``; use :func:`detect`
    to go from a fitted shape and source-frame triangles to barycentrics.
    """

    def __init__(
        self,
        feature_dim: int = 32,
        hidden: int = 32,
        weight_hidden: int = 16,
        triangle_feature: str = "condition",
        vertex_features: bool = True,
        edge_range: tuple[float, float] = DEFAULT_EDGE_RANGE,
        vertex_sdf: bool = False,
        output: str = "softmax",
    ):
        super().__init__()
        if triangle_feature not in TRIANGLE_FEATURE_MODES:
            raise InputError(f"triangle_feature must be one of {TRIANGLE_FEATURE_MODES}, got {triangle_feature!r}")
        lo, hi = (float(e) for e in edge_range)
        if not (0 < lo < hi < math.inf):
            raise InputError(f"edge_range must be two increasing positive lengths, got {edge_range!r}")
        self.feature_dim = int(feature_dim)
        self.hidden = int(hidden)
        self.weight_hidden = int(weight_hidden)
        self.triangle_feature = triangle_feature
        self.vertex_features = bool(vertex_features)
        self.edge_range = (lo, hi)
        self.vertex_sdf = bool(vertex_sdf)
        if output not in OUTPUTS:
            raise InputError(f"output must be one of {OUTPUTS}, got {output!r}")
        self.output = output
        c = self.feature_dim
        # Fixed input standardisation, set from the training data (fit_input_statistics) and saved
        # with the weights: code-cloud features are small (std ~0.04) and differ within a triangle
        # by less still (~0.01), which a freshly initialised MLP would hardly see.
        self.register_buffer("feature_mean", torch.zeros(c))
        self.register_buffer("feature_std", torch.ones(c))
        self.register_buffer("feature_within_std", torch.ones(c))
        self.g_phi = _mlp([3, self.weight_hidden, 1])
        if self.output == "quadratic":
            if not self.vertex_sdf:
                raise InputError("output='quadratic' models the SDF from its vertex values: build it with vertex_sdf=True")
            # the whole network: g_phi for z_tri, and one curvature per edge from
            # [z_i + z_j; |dz_i - dz_j|; z_tri; length; the vertex values], symmetric in the edge's ends
            self.h_edge = _mlp([3 * c + 4, self.hidden, self.hidden, 1])
            with torch.no_grad():  # start near typical curvatures (softplus(-4) = 0.018 per perimeter), not 0.7
                self.h_edge[-1].bias.fill_(_INITIAL_CURVATURE_LOGIT)
            return
        self.h_psi2 = _mlp([c, self.hidden, self.hidden, 1])
        if self.output == "grid":
            # per-edge curvature from both ends' features (symmetric in the two) and the edge's length
            self.h_edge = _mlp([3 * c + 1, self.hidden, self.hidden, 1])
            self.register_buffer("grid", barycentric_grid(_GRID_RESOLUTION), persistent=False)
        if self.triangle_feature in ("condition", "context"):
            # A descent direction for the triangle from z_tri and where the triangle is: the
            # score -d . (v_i - centroid) is Frank-Wolfe's vertex choice when d is the SDF's
            # gradient, a bilinear form an MLP on concatenated inputs would learn only slowly.
            self.h_direction = _mlp([c + 3, self.hidden, self.hidden, 3])
        if self.triangle_feature == "context":
            # h_psi1 split in two around the triangle context: embed each vertex, pool, read out
            self.h_psi1_embed = nn.Sequential(_mlp([self._vertex_input_dim(), self.hidden, self.hidden]), nn.ReLU())
            self.h_psi1 = _mlp([self.hidden * 4 + c, self.hidden, 1])
        else:
            self.h_psi1 = _mlp([self._vertex_input_dim(), self.hidden, self.hidden, 1])

    # ------------------------------------------------------------------ config

    def _vertex_input_dim(self) -> int:
        extra = 2 if self.vertex_sdf else 0  # [f_i / p, (f_i - mean f) / p]
        c = self.feature_dim
        if self.triangle_feature == "context":
            return c + 3 + 3 + c + extra  # [z_i; v_i; offset_i; dz_i], embedded before pooling
        if self.triangle_feature == "condition":
            return c + 3 + 3 + c + c + extra  # [z_i; v_i; offset_i; dz_i; z_tri]
        return c + 3 + extra  # [z_i; v_i], the paper's 35 inputs

    def config(self) -> dict:
        """Everything :meth:`from_config` needs to rebuild this network (JSON-serialisable)."""
        return {
            "feature_dim": self.feature_dim,
            "hidden": self.hidden,
            "weight_hidden": self.weight_hidden,
            "triangle_feature": self.triangle_feature,
            "vertex_features": self.vertex_features,
            "edge_range": list(self.edge_range),
            "vertex_sdf": self.vertex_sdf,
            "output": self.output,
        }

    @classmethod
    def from_config(cls, config: dict) -> AmortizedDetector:
        known = {"feature_dim", "hidden", "weight_hidden", "triangle_feature", "vertex_features", "edge_range", "vertex_sdf", "output"}
        unknown = set(config) - known
        if unknown:
            raise InputError(f"unknown detector config keys {sorted(unknown)}; expected some of {sorted(known)}")
        return cls(**{k: (tuple(v) if k == "edge_range" else v) for k, v in config.items()})

    # ------------------------------------------------------------------ forward

    def forward(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf: torch.Tensor | None = None) -> torch.Tensor:
        """Barycentric coordinates (M, 3) of the predicted minimum.

        ``triangles`` (M, 3, 3) in the normalised frame, ``features`` (M, 3, C): the code-cloud
        feature z_i at each vertex; ``vertex_sdf`` (M, 3), the signed distance at each vertex,
        is needed only by a detector built with ``vertex_sdf=True``. Rows of the result are
        positive and sum to 1.
        """
        if self.output == "quadratic":
            return quadratic_argmin(vertex_sdf, self.edge_curvatures(triangles, features, vertex_sdf))
        if self.output == "grid":
            vertex, edge = self.scores(triangles, features, vertex_sdf)
            return grid_soft_argmax(vertex, edge, self.grid.to(vertex))
        scores = self.logits(triangles, features, vertex_sdf)
        return sparsemax(scores) if self.output == "sparsemax" else torch.softmax(scores, dim=-1)

    def predict(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf: torch.Tensor | None = None):
        """The forward pass with the model's own estimate of the minimum: (bary (M, 3), value (M,) or None).

        The ``quadratic`` output knows the value of its model at its answer (exact at the vertices);
        the other outputs have no model of the SDF and give None.
        """
        if self.output == "quadratic":
            return quadratic_minimum(vertex_sdf, self.edge_curvatures(triangles, features, vertex_sdf))
        return self(triangles, features, vertex_sdf), None

    def logits(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf: torch.Tensor | None = None) -> torch.Tensor:
        """The pre-softmax scores (M, 3) (temperature applied)."""
        return self.scores(triangles, features, vertex_sdf)[0]

    def scores(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf: torch.Tensor | None = None):
        """Vertex scores (M, 3) and, for ``output="grid"``, edge scores (M, 3) (slot k: the edge opposite
        vertex k; else None), both with the temperature applied."""
        self._check_inputs(triangles, features, vertex_sdf)
        z = features if self.vertex_features else torch.zeros_like(features)
        centroid = triangles.mean(dim=1, keepdim=True)  # (M, 1, 3)
        perim = edge_lengths(triangles).sum(dim=-1).clamp_min(_TINY_LENGTH)  # (M,)
        offset = (triangles - centroid) / perim[:, None, None]  # (M, 3, 3), scale-free shape
        z_tri = self.triangle_feature_vector(z, offset)  # (M, C), from the raw features as (7) says
        if self.triangle_feature == "condition":
            y1 = self._conditioned_vertex_scores(z, triangles, offset, z_tri, vertex_sdf, perim)
        else:
            inputs = self._vertex_inputs(z, triangles, offset, z_tri)
            if self.vertex_sdf:
                inputs = torch.cat([inputs, self._sdf_inputs(vertex_sdf, perim)], dim=-1)
            if self.triangle_feature == "context":
                inputs = self._with_context(self.h_psi1_embed(inputs), z_tri)
            y1 = self.h_psi1(inputs).squeeze(-1)  # (M, 3)
        if self.triangle_feature in ("condition", "context"):
            d = self.h_direction(torch.cat([self._standardised(z_tri), centroid.squeeze(1)], dim=-1))  # (M, 3)
            y1 = y1 - _DIRECTION_GAIN * torch.einsum("mc,mvc->mv", d, offset)
        edge = self._edge_scores(z, triangles, perim, z_tri) if self.output == "grid" else None
        if self.triangle_feature in ("condition", "context", "temperature"):
            scale = F.softplus(self.h_psi2(self._standardised(z_tri))) + _MIN_TEMPERATURE_SCALE  # (M, 1)
            return y1 * scale, (None if edge is None else edge * scale)
        if self.triangle_feature == "additive":
            # (M, 3) + (M, 1): a common shift, a no-op under softmax (and on the grid, whose weights sum to 1)
            return y1 + self.h_psi2(self._standardised(z_tri)), edge
        return y1, edge

    def edge_curvatures(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf: torch.Tensor) -> torch.Tensor:
        """Learned bending kappa (M, 3) of the SDF along each edge (slot k: the edge opposite vertex k), >= 0.

        kappa_k = f_i + f_j - 2 f(midpoint) (times 2) for a quadratic SDF; it is scale-covariant
        (the head predicts kappa / perimeter from scale-free inputs), so it transfers across sizes.
        """
        self._check_inputs(triangles, features, vertex_sdf)
        z = features if self.vertex_features else torch.zeros_like(features)
        perim = edge_lengths(triangles).sum(dim=-1).clamp_min(_TINY_LENGTH)  # (M,)
        offset = (triangles - triangles.mean(dim=1, keepdim=True)) / perim[:, None, None]
        z_tri = self.triangle_feature_vector(z, offset)
        if self.triangle_feature == "none":  # the ablation "without z_tri"
            z_tri = self.feature_mean.expand_as(z_tri)  # standardises to 0
        i, j = [p[0] for p in EDGE_PAIRS], [p[1] for p in EDGE_PAIRS]
        f = vertex_sdf.to(triangles) / perim[:, None]  # (M, 3), scale-free
        values = torch.stack([f[:, i] + f[:, j], (f[:, i] - f[:, j]).abs(), f - (f[:, i] + f[:, j]) / 2], dim=-1)
        pair = torch.cat([self._edge_pair_inputs(z, triangles, perim, z_tri), values], dim=-1)  # (M, 3, 3C + 4)
        return perim[:, None] * F.softplus(self.h_edge(pair).squeeze(-1))

    def _edge_scores(self, z, triangles, perim, z_tri) -> torch.Tensor:
        """Per-edge curvature scores (M, 3) of the grid output."""
        return self.h_edge(self._edge_pair_inputs(z, triangles, perim, z_tri)).squeeze(-1)

    def _edge_pair_inputs(self, z, triangles, perim, z_tri) -> torch.Tensor:
        """(M, 3, 3C + 1) per edge (slot k: opposite vertex k): [z_i + z_j; |dz_i - dz_j|; z_tri; |v_i - v_j| / p],
        symmetric in the edge's two ends."""
        zs = self._standardised(z)
        dz = (z - z.mean(dim=1, keepdim=True)) / self.feature_within_std
        i, j = [p[0] for p in EDGE_PAIRS], [p[1] for p in EDGE_PAIRS]
        length = (triangles[:, i] - triangles[:, j]).norm(dim=-1, keepdim=True) / perim[:, None, None]  # (M, 3, 1)
        zt = self._standardised(z_tri).unsqueeze(1).expand(-1, 3, -1)
        return torch.cat([zs[:, i] + zs[:, j], (dz[:, i] - dz[:, j]).abs(), zt, length], dim=-1)

    def triangle_feature_vector(self, z: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        """z_tri (M, C) of equation (7) from z (M, 3, C) and centroid offsets (M, 3, 3)."""
        return (self.vertex_weights(z, offset).unsqueeze(-1) * z).sum(dim=1)

    def vertex_weights(self, z: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        """Softmax weights w (M, 3) of equation (7): g_phi on [|v_i - c|/p, cosines to the others]."""
        radius = offset.norm(dim=-1)  # (M, 3): |v_i - centroid| / perimeter
        unit = z / z.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        cos = unit @ unit.transpose(1, 2)  # (M, 3, 3) cosines, one small batched matmul
        # cosines to the two other vertices, in an order that does not depend on vertex order
        others = torch.stack([cos[:, 0, [1, 2]], cos[:, 1, [0, 2]], cos[:, 2, [0, 1]]], dim=1)  # (M, 3, 2)
        others, _ = others.sort(dim=-1, descending=True)
        scores = self.g_phi(torch.cat([radius.unsqueeze(-1), others], dim=-1)).squeeze(-1)  # (M, 3)
        return torch.softmax(scores, dim=-1)

    @staticmethod
    def _sdf_inputs(vertex_sdf: torch.Tensor, perim: torch.Tensor) -> torch.Tensor:
        """(M, 3) vertex distances -> (M, 3, 2): each relative to the perimeter, absolute and centred."""
        rel = vertex_sdf / perim[:, None]
        return torch.stack([rel, rel - rel.mean(dim=-1, keepdim=True)], dim=-1)

    @staticmethod
    def _with_context(e: torch.Tensor, z_tri: torch.Tensor) -> torch.Tensor:
        """Vertex embeddings (M, 3, H) -> (M, 3, 4H + C): each with the symmetric pools over the
        triangle (mean, max, min) and z_tri, so a vertex's logit can weigh itself against the others."""
        pools = [e.mean(dim=1), e.amax(dim=1), e.amin(dim=1), z_tri]
        ctx = torch.cat(pools, dim=-1).unsqueeze(1).expand(-1, 3, -1)
        return torch.cat([e, ctx], dim=-1)

    def fit_input_statistics(self, features: torch.Tensor, chunk: int = 65536) -> None:
        """Set the fixed standardisation from training features (N, 3, C): global and within-triangle spread.

        Sums are taken ``chunk`` triangles at a time in float64, so features memory-mapped from a file are
        read once, a chunk in memory at a time."""
        n = features.shape[0] * 3
        total = torch.zeros(features.shape[-1], dtype=torch.float64)
        squares, within_squares = torch.zeros_like(total), torch.zeros_like(total)
        for part in features.detach().split(chunk):
            f = part.to("cpu", torch.float64)
            total += f.sum((0, 1))
            squares += f.square().sum((0, 1))
            within_squares += (f - f.mean(dim=1, keepdim=True)).square().sum((0, 1))  # within-triangle means are 0
        mean = total / n
        variance = (squares - n * mean.square()).clamp_min(0) / max(n - 1, 1)  # unbiased, as torch.std
        self.feature_mean.copy_(mean)
        self.feature_std.copy_(variance.sqrt().clamp_min(1e-6))
        self.feature_within_std.copy_((within_squares / max(n - 1, 1)).sqrt().clamp_min(1e-6))

    def _standardised(self, z: torch.Tensor) -> torch.Tensor:
        return (z - self.feature_mean) / self.feature_std

    def _conditioned_vertex_scores(self, z, triangles, offset, z_tri, vertex_sdf, perim) -> torch.Tensor:
        """h_psi1 on [z_i; v_i; offset_i; dz_i; z_tri (; f_i)] -> (M, 3), without building the input.

        The first layer is applied block by block (the same weights as on the concatenation), so
        the per-triangle block z_tri is multiplied once per triangle rather than once per vertex
        and no (M, 3, 102) tensor is materialised: the detector's cost is mostly this layer.
        """
        first = self.h_psi1[0]
        c = self.feature_dim
        blocks = [(self._standardised(z), c), (triangles, 3), (offset, 3), ((z - z.mean(dim=1, keepdim=True)) / self.feature_within_std, c)]
        w, col = first.weight, 0
        h = first.bias
        for x, width in blocks:
            h = h + x @ w[:, col : col + width].T
            col += width
        h = h + (self._standardised(z_tri) @ w[:, col : col + c].T).unsqueeze(1)  # (M, 1, H): per triangle
        col += c
        if self.vertex_sdf:
            h = h + self._sdf_inputs(vertex_sdf, perim) @ w[:, col : col + 2].T
        return self.h_psi1[1:](h).squeeze(-1)

    def _vertex_inputs(self, z, triangles, offset, z_tri) -> torch.Tensor:
        """Per-vertex inputs of h_psi1: (M, 3, C + 3), context (M, 3, 2C + 6), conditioned (M, 3, 3C + 6).

        The paper's [z_i; v_i] with z standardised; the richer modes add the vertex's offset from
        the centroid (per perimeter) and its feature's deviation from the triangle's mean feature
        (dz_i), which is what tells the three vertices apart.
        """
        zs = self._standardised(z)
        if self.triangle_feature not in ("context", "condition"):
            return torch.cat([zs, triangles], dim=-1)
        dz = (z - z.mean(dim=1, keepdim=True)) / self.feature_within_std
        if self.triangle_feature == "context":
            return torch.cat([zs, triangles, offset, dz], dim=-1)
        return torch.cat([zs, triangles, offset, dz, self._standardised(z_tri).unsqueeze(1).expand_as(z)], dim=-1)

    def _check_inputs(self, triangles: torch.Tensor, features: torch.Tensor, vertex_sdf) -> None:
        if self.vertex_sdf and (vertex_sdf is None or vertex_sdf.shape != triangles.shape[:2]):
            got = None if vertex_sdf is None else tuple(vertex_sdf.shape)
            raise InputError(f"this detector reads the signed distance at each vertex: pass vertex_sdf of shape (M, 3), got {got}")
        if triangles.ndim != 3 or triangles.shape[1:] != (3, 3):
            raise InputError(f"triangles must have shape (M, 3, 3), got {tuple(triangles.shape)}")
        if features.shape != (triangles.shape[0], 3, self.feature_dim):
            raise InputError(
                f"features must have shape (M, 3, {self.feature_dim}) to match {triangles.shape[0]} triangles, "
                f"got {tuple(features.shape)}; compute them with shape.features(vertices) reshaped to (M, 3, C)"
            )


def grid_soft_argmax(vertex: torch.Tensor, edge: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Soft arg-max (M, 3) of the quadratic score s(l) = sum_i l_i y_i + sum_k l_i l_j c_k over the grid.

    ``vertex`` y (M, 3), ``edge`` c (M, 3) (slot k: edge (i, j) opposite vertex k), ``grid`` (G, 3).
    On edge (i, j) the score peaks inside at l_i = 1/2 + (y_i - y_j) / (2 c) when c > 0: a
    parabola per edge, the shape an SDF takes along an edge near its minimum.
    """
    i, j = [p[0] for p in EDGE_PAIRS], [p[1] for p in EDGE_PAIRS]
    pair = grid[:, i] * grid[:, j]  # (G, 3)
    s = vertex @ grid.T + edge @ pair.T  # (M, G)
    return torch.softmax(s, dim=-1) @ grid


def quadratic_argmin(values: torch.Tensor, curvature: torch.Tensor) -> torch.Tensor:
    """Exact minimiser (M, 3) over the triangle of q(l) = sum_i l_i f_i - sum_k l_i l_j kappa_k: see :func:`quadratic_minimum`."""
    return quadratic_minimum(values, curvature)[0]


def quadratic_minimum(values: torch.Tensor, curvature: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact minimiser (M, 3) over the triangle of q(l) = sum_i l_i f_i - sum_k l_i l_j kappa_k, and q there (M,).

    ``values`` f (M, 3) at the vertices, ``curvature`` kappa (M, 3) (slot k: edge (i, j) opposite
    vertex k). For f(x) = a + b.x + x^T H x / 2 on the triangle, q is f itself with
    kappa_k = (v_i - v_j)^T H (v_i - v_j) / 2. The minimum of a quadratic on a triangle is at a vertex,
    at an edge's own minimum (a parabola, when it bends upwards) or at the interior stationary point
    (when q is convex there): every candidate is computed in closed form and the lowest is kept.
    Differentiable in kappa wherever the answer lies on an edge or inside.
    """
    m = values.shape[0]
    eye = torch.eye(3, dtype=values.dtype, device=values.device)
    cands, scores = [eye.expand(m, 3, 3)], [values]  # the vertices
    for k, (i, j) in enumerate(EDGE_PAIRS):  # each edge's parabola t f_i + (1 - t) f_j - t (1 - t) kappa
        kap, fi, fj = curvature[:, k], values[:, i], values[:, j]
        bends = kap > 0
        t = (0.5 - (fi - fj) / (2 * torch.where(bends, kap, torch.ones_like(kap)))).clamp(0, 1)
        t = torch.where(bends, t, (fi < fj).to(t))  # straight or bending down: the lower end
        cands.append((t[:, None] * eye[i] + (1 - t)[:, None] * eye[j]).unsqueeze(1))
        scores.append((t * fi + (1 - t) * fj - t * (1 - t) * kap).unsqueeze(1))
    # inside: l = (1 - a - b, a, b), grad q = 0 is a 2x2 system, a minimum where its matrix is positive definite
    k0, k1, k2 = curvature.unbind(-1)
    f0, f1, f2 = values.unbind(-1)
    a11, a22, a12 = 2 * k2, 2 * k1, k1 + k2 - k0
    det = a11 * a22 - a12 * a12
    convex = (det > 0) & (a11 > 0)
    r1, r2 = k2 - (f1 - f0), k1 - (f2 - f0)
    safe = torch.where(convex, det, torch.ones_like(det))
    a, b = (r1 * a22 - a12 * r2) / safe, (a11 * r2 - a12 * r1) / safe
    inside = convex & (a > 0) & (b > 0) & (a + b < 1)
    lam = torch.stack([1 - a - b, a, b], dim=-1)
    lam = torch.where(inside[:, None], lam, torch.full_like(lam, 1 / 3))
    q = (lam * values).sum(-1) - lam[:, 1] * lam[:, 2] * k0 - lam[:, 2] * lam[:, 0] * k1 - lam[:, 0] * lam[:, 1] * k2
    cands.append(lam.unsqueeze(1))
    scores.append(torch.where(inside, q, torch.full_like(q, math.inf)).unsqueeze(1))
    lowest, best = torch.cat(scores, dim=1).min(dim=1)  # (M,) of 7 candidates
    return torch.cat(cands, dim=1)[torch.arange(m, device=values.device), best], lowest


def sparsemax(scores: torch.Tensor) -> torch.Tensor:
    """Euclidean projection of each row of ``scores`` (M, K) onto the simplex (Martins & Astudillo 2016).

    Differentiable almost everywhere (autograd through sort, cumsum and clamp gives the sparsemax
    Jacobian); rows are non-negative and sum to 1.
    """
    from .solvers import project_to_simplex

    return project_to_simplex(scores - scores.amax(dim=-1, keepdim=True))  # shift-invariant; keeps values small
