"""Each optimised inference path held against the naive computation it replaces.

* NeuralShape queries: the direct inverse-distance-cubed weights against the softmax-of-logs
  formula training uses (values and gradients), the fused features-and-distances pass;
* the detector's bookkeeping: distinct rows, per-distinct-vertex features against per-triangle
  ones, the Lipschitz lower bound of a cell, the pieces of a bisected triangle and the points they share;
* the search with culls against the exhaustive one (every piece solved), and against the
  previous subdivision (every piece solved, the lowest piece's answer kept): never worse;
* the cutoff and the known point that collide passes: the same contacts as without them.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import zoo
import zoo.amortized.batching
import zoo.amortized.search
from zoo import neural
from zoo.amortized import (
    POLISH_LINE_STEPS,
    POLISH_ROUNDS,
    Known,
    SolveOptions,
    detect,
    solve_mesh,
    strip_barycentrics,
    strip_levels,
    subdivision_barycentrics,
    subdivision_levels,
    vertex_features,
)
from zoo.amortized.subdivision import grid_barycentrics
from zoo.bounds import cell_lower_bounds
from zoo.detector import AmortizedDetector
from zoo.errors import InputError
from zoo.geometry import bary_to_points, edge_lengths, unique_rows
from zoo.meshes import Similarity
from zoo.neural import (
    NeuralSDF,
    NeuralSDFConfig,
    NeuralShape,
    augmented_code_cloud,
    decode,
    direct_weights_are_safe,
    interpolate_codes,
    interpolate_codes_direct,
)

SMALL = NeuralSDFConfig(n_codes=32, code_dim=8, hidden=(32, 32))


def small_shape(similarity=None, seed=0, config=SMALL) -> NeuralShape:
    torch.manual_seed(seed)
    m = NeuralSDF(config, 1, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        m.codes.normal_(0, 0.3)
    return NeuralShape("a", m.decoder.requires_grad_(False), config, m.codes[0], m.positions[0], similarity)


def rotation(seed):
    q = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))[0]
    return (q * torch.sign(torch.det(q))).numpy()


# --------------------------------------------------------------------------- NeuralShape queries


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_direct_weights_give_the_softmax_formulas_features(dtype):
    g = torch.Generator().manual_seed(1)
    pos = (torch.rand(64, 3, generator=g, dtype=torch.float64) - 0.5).to(dtype)
    codes = torch.randn(64, 16, generator=g, dtype=torch.float64).to(dtype)
    pts = torch.cat([pos[:5], torch.rand(300, 3, generator=g, dtype=torch.float64).to(dtype) - 0.5])  # five exactly on codes
    old = interpolate_codes(pts.unsqueeze(0), pos.unsqueeze(0), codes.unsqueeze(0), 1e-16).squeeze(0)
    new = interpolate_codes_direct(pts, *augmented_code_cloud(pos, codes), 1e-16)
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(new, old, atol=tol, rtol=tol)
    torch.testing.assert_close(new[:5], codes[:5], atol=tol, rtol=tol)  # a point on a code takes that code


def test_direct_path_matches_the_training_formula_in_values_and_gradients():
    shape = small_shape(Similarity(2.5, rotation(3), np.array([0.1, -0.2, 0.05])))
    p = torch.rand(500, 3, dtype=torch.float64) * 0.3
    d, g = shape.value_and_grad(p)
    # the training formula (softmax of log-weights), by autograd, in the normalised frame
    s, r, t = (torch.as_tensor(v, dtype=torch.float64) for v in (shape.similarity.scale, shape.similarity.rotation, shape.similarity.translation))
    x = p.clone().requires_grad_(True)
    pn = s * x @ r.T + t
    ref = decode(shape.decoder.double(), pn.unsqueeze(0), shape.positions.double().unsqueeze(0),
                 shape.codes.double().unsqueeze(0), SMALL.eps).squeeze(0) / s
    (ref_g,) = torch.autograd.grad(ref.sum(), x)
    shape.decoder.float()
    torch.testing.assert_close(d, ref.detach(), atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(g, ref_g, atol=1e-10, rtol=1e-8)


def test_tiny_eps_falls_back_to_the_softmax_form():
    assert direct_weights_are_safe(1e-16, 256, torch.float32)
    assert not direct_weights_are_safe(1e-40, 256, torch.float32) and not direct_weights_are_safe(0.0, 256, torch.float64)
    config = NeuralSDFConfig(n_codes=32, code_dim=8, hidden=(32, 32), eps=1e-40)
    m = NeuralSDF(config, 1, torch.Generator().manual_seed(0))
    shape = NeuralShape("a", m.decoder.requires_grad_(False), config, m.codes[0], m.positions[0])
    pts = torch.cat([m.positions[0, :3].detach(), torch.rand(20, 3) - 0.5])
    ref = decode(m.decoder, pts.unsqueeze(0), m.positions.detach(), m.codes.detach(), 1e-40).squeeze(0)
    assert shape._cached(torch.float32, "cpu")[3] is None
    torch.testing.assert_close(shape(pts), ref.detach())
    assert torch.isfinite(shape.value_and_grad(pts)[1]).all()


def test_features_and_distances_is_features_then_the_decoder(monkeypatch):
    shape = small_shape()
    p = torch.rand(3000, 3) - 0.5
    monkeypatch.setattr(neural, "_CHUNK_ELEMENTS", 32 * 100)  # several chunks
    z, d = shape.features_and_distances(p)
    torch.testing.assert_close(z, shape.features(p))
    torch.testing.assert_close(d, shape.normalised(p))
    torch.testing.assert_close(shape.distances_from_features(p, z), d)
    assert shape.normalised is shape.normalised  # built once, sharing the converted networks


@pytest.mark.parametrize("smooth_beta,fourier_levels", [(0.0, 0), (100.0, 0), (100.0, 4)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_inference_decoder_is_the_decoder_and_follows_its_weights(dtype, smooth_beta, fourier_levels):
    shape = small_shape(config=dataclasses.replace(SMALL, smooth_beta=smooth_beta, fourier_levels=fourier_levels))
    p = (torch.rand(700, 3, dtype=torch.float64) - 0.5).to(dtype)
    z = shape.features(p)
    dec = shape._cached(dtype, "cpu")[0]
    fast = shape._decoder_no_grad(dtype, "cpu")
    assert isinstance(fast, neural.InferenceDecoder)
    with torch.no_grad():
        torch.testing.assert_close(fast(z, p), dec(z, p), atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)
        torch.testing.assert_close(shape.normalised(p), dec(z, p), atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)
        dec.hidden[0].bias.add_(0.5)  # weights changed in place (an optimiser step): the folded copy follows
        torch.testing.assert_close(shape._decoder_no_grad(dtype, "cpu")(z, p), dec(z, p), atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)
        dec.hidden[1].weight = torch.nn.Parameter(dec.hidden[1].weight * 0.5)  # a parameter replaced: followed too
        torch.testing.assert_close(shape._decoder_no_grad(dtype, "cpu")(z, p), dec(z, p), atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)
    assert not neural.InferenceDecoder.supports(neural.Decoder(NeuralSDFConfig(n_codes=8, code_dim=4, hidden=(16, 8))))


# --------------------------------------------------------------------------- the detector's bookkeeping


class TorusWithCodes:
    """An exact torus SDF (1-Lipschitz) with a fixed random code cloud: what detect() reads of a shape."""

    def __init__(self, similarity=None):
        g = torch.Generator().manual_seed(0)
        self.normalised = zoo.Torus(0.3, 0.06)
        self.positions = torch.rand(1, 64, 3, generator=g) - 0.5
        self.codes = torch.randn(1, 64, 32, generator=g)
        self.similarity = similarity
        self.feature_points = 0

    def features(self, points_norm):
        self.feature_points += points_norm.shape[0]
        p = torch.as_tensor(points_norm).float()
        return interpolate_codes(p.unsqueeze(0), self.positions, self.codes, 1e-16).squeeze(0)


def detector(seed=0, **kwargs) -> AmortizedDetector:
    torch.manual_seed(seed)
    return AmortizedDetector(**kwargs).eval()


def grid_mesh(n=12, size=0.5, z=0.0, jitter=0.0, seed=0):
    """A square grid mesh (vertices (V, 3) float64, faces (F, 3)) in the plane at height z."""
    x = np.linspace(-size / 2, size / 2, n + 1)
    gx, gy = np.meshgrid(x, x, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], -1)
    v += jitter * np.random.default_rng(seed).normal(size=v.shape)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return torch.as_tensor(v), torch.as_tensor(np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]))


def test_unique_rows_is_exact_and_inverts():
    v, f = grid_mesh(6)
    rows = v[f].reshape(-1, 3)
    uniq, inverse = unique_rows(rows)
    assert torch.equal(uniq[inverse], rows)
    assert uniq.shape[0] == v.shape[0] == torch.unique(rows, dim=0).shape[0]
    assert torch.equal(uniq, torch.unique(rows, dim=0))  # the same rows, in lexicographic order


def test_per_vertex_features_equal_per_triangle_features_with_fewer_queries():
    shape = TorusWithCodes()
    v, f = grid_mesh(10)
    tri = v[f].float()
    per_triangle = shape.features(tri.reshape(-1, 3)).reshape(-1, 3, 32)
    shape.feature_points = 0
    torch.testing.assert_close(vertex_features(shape, tri), per_triangle, atol=0, rtol=0)
    assert shape.feature_points == v.shape[0] < tri.shape[0] * 3 / 4  # each vertex once


def test_in_range_answers_are_the_networks_on_per_triangle_features():
    shape, det = TorusWithCodes(), detector()
    v, f = grid_mesh(12, size=0.5, z=0.05, jitter=0.003)  # edges ~0.04: in range
    tri = v[f].float()
    assert bool((subdivision_levels(tri, det.edge_range[1]) == 1).all())
    with torch.no_grad():
        naive = det(tri, shape.features(tri.reshape(-1, 3)).reshape(-1, 3, 32))
    torch.testing.assert_close(detect(det, shape, tri, polish=False), naive, atol=1e-6, rtol=0)


def naive_polish(sdf, tri, net, rounds):
    """The polish as its definition reads, one triangle at a time: the lowest vertex where its own
    gradient has no descent direction into the triangle (the vertex test); else ``rounds`` line-search
    steps from the network's answer, each later one from the lower of the last answer and that vertex."""
    out = []
    for t, b in zip(tri, net):
        t = t.unsqueeze(0)
        f_v = sdf(t[0]).reshape(1, 3)
        low = int(f_v.argmin())
        _, g_low = sdf.value_and_grad(t[0, low : low + 1])
        scores = (t[0] @ g_low[0])  # g . v_i
        vertex = torch.nn.functional.one_hot(torch.tensor([low]), 3).to(t)
        if bool(scores.min() >= scores[low]):
            out.append(vertex[0])
            continue
        b = zoo.solvers.line_search_step(sdf, t, b.unsqueeze(0), f_v, line_steps=POLISH_LINE_STEPS)
        for _ in range(rounds - 1):
            f_b, g_b = sdf.value_and_grad(bary_to_points(t, b))
            if bool(f_v[0, low] < f_b[0]):
                b, start = vertex, (f_v[0, low : low + 1], g_low)
            else:
                start = (f_b, g_b)
            b = zoo.solvers.line_search_step(sdf, t, b, f_v, line_steps=POLISH_LINE_STEPS, start=start)
        out.append(b[0])
    return torch.stack(out)


def test_polished_answers_are_the_vertex_test_then_line_search_steps_from_the_networks():
    shape, det = TorusWithCodes(), detector()
    v, f = grid_mesh(12, size=0.5, z=0.05, jitter=0.003)
    tri = v[f].double()  # float64: flat interior minima make float32 line searches differ by rounding alone
    net = detect(det, shape, tri, polish=False)
    naive = naive_polish(shape.normalised, tri, net, POLISH_ROUNDS)
    polished = detect(det, shape, tri)
    torch.testing.assert_close(polished, naive, atol=1e-7, rtol=0)
    settled = (naive == 1).any(dim=-1)
    assert 0 < int(settled.sum()) < tri.shape[0]  # both branches of the vertex test are exercised
    assert not torch.allclose(polished[~settled], net[~settled], atol=1e-3)  # the steps did move answers
    gap = zoo.solvers.optimality(shape.normalised, tri, polished)
    assert float(gap[settled].abs().max()) < 1e-6  # a settled vertex satisfies the KKT conditions
    assert gap.mean() < 0.5 * zoo.solvers.optimality(shape.normalised, tri, net).mean()


def test_cell_lower_bound_never_exceeds_the_minimum_of_a_1_lipschitz_sdf():
    sdf = zoo.Sphere(0.25)
    g = torch.Generator().manual_seed(4)
    centres = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g, dtype=torch.float64), dim=-1) * 0.3
    size = 0.005 + 0.2 * torch.rand(4000, 1, 1, generator=g, dtype=torch.float64)
    tri = centres.unsqueeze(1) + size * torch.randn(4000, 3, 3, generator=g, dtype=torch.float64)
    tri[:50, 2] = tri[:50, 0] + 0.5 * (tri[:50, 1] - tri[:50, 0])  # degenerate: collinear
    bound = cell_lower_bounds(tri, sdf(tri.reshape(-1, 3)).reshape(-1, 3))
    grid = subdivision_barycentrics(40, torch.float64).reshape(-1, 3)
    sampled = sdf(torch.einsum("gv,mvc->mgc", grid, tri).reshape(-1, 3)).reshape(4000, -1).amin(-1)
    exact_gap = sampled - bound  # sampled >= true minimum >= bound
    assert bool((exact_gap >= -1e-12).all())
    assert float(exact_gap.median()) < 0.1  # and it is not vacuous


# --------------------------------------------------------------------------- the search


def mixed_triangles(seed=0, m=40):
    """Triangles hovering over and cutting the torus, longest edges 0.1-1.3 (levels 2-17)."""
    g = torch.Generator().manual_seed(seed)
    angle = torch.rand(m, generator=g) * 2 * math.pi
    centre = torch.stack([0.3 * torch.cos(angle), 0.3 * torch.sin(angle), 0.03 + 0.08 * torch.rand(m, generator=g) - 0.04], -1)
    size = 0.06 + 0.7 * torch.rand(m, 1, 1, generator=g) ** 2
    return (centre.unsqueeze(1) + size * torch.randn(m, 3, 3, generator=g) * torch.tensor([1.0, 1.0, 0.2])).double()


def naive_subdivided(det, shape, tri, n):
    """The previous subdivision: every piece of level n solved, the piece whose answer is lowest kept."""
    pieces_bary = subdivision_barycentrics(n, tri.dtype)
    pieces = torch.einsum("pjk,mkc->mpjc", pieces_bary, tri).reshape(-1, 3, 3)
    with torch.no_grad():
        local = det(pieces.float(), shape.features(pieces.reshape(-1, 3)).reshape(-1, 3, 32)).double()
    parent = torch.einsum("mpj,pjk->mpk", local.reshape(tri.shape[0], -1, 3), pieces_bary)
    f = shape.normalised(bary_to_points(tri.repeat_interleave(pieces_bary.shape[0], 0), parent.reshape(-1, 3)))
    best = f.reshape(tri.shape[0], -1).argmin(-1)
    return parent[torch.arange(tri.shape[0]), best]


def flat_pieces(tri: torch.Tensor, n: int, max_edge: float) -> torch.Tensor:
    """The pieces (P, 3, 3), in parent barycentrics, that solve_mesh searches flat on triangle ``tri`` (3, 3) of level n:
    strips for a needle (strip_levels), else the n^2 regular pieces."""
    strips, apex = strip_levels(tri[None], max_edge)
    if int(strips[0]):
        return strip_barycentrics(int(strips[0]), int(apex[0]), tri.dtype)
    return subdivision_barycentrics(n, tri.dtype)


def test_strips_tile_a_needle_with_pieces_in_range_and_fewer_than_the_regular_ones():
    g = torch.Generator().manual_seed(7)
    a = torch.randn(300, 3, generator=g, dtype=torch.float64)
    along = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    across = torch.nn.functional.normalize(torch.linalg.cross(along, torch.randn(300, 3, generator=g, dtype=torch.float64)), dim=-1)
    length = (0.09 + 0.5 * torch.rand(300, 1, generator=g, dtype=torch.float64))
    width = 0.04 * torch.rand(300, 1, generator=g, dtype=torch.float64)
    tri = torch.stack([a, a + length * along, a + length * along + width * across], 1)[:, torch.randperm(3, generator=g)]
    max_edge = 0.08
    strips, apex = strip_levels(tri, max_edge)
    regular = subdivision_levels(tri, max_edge)
    used = strips > 0
    assert int(used.sum()) > 100  # those short and thin enough (the rest need more than 7 strips, or are regular)
    assert bool((2 * strips[used] - 1 < regular[used] ** 2).all())
    for i in used.nonzero().squeeze(-1).tolist():
        corners = strip_barycentrics(int(strips[i]), int(apex[i]), tri.dtype)
        pieces = torch.einsum("pjk,kc->pjc", corners, tri[i])
        assert float(edge_lengths(pieces).max()) <= max_edge + 1e-12  # in range
        parent = torch.linalg.cross(tri[i, 1] - tri[i, 0], tri[i, 2] - tri[i, 0], dim=-1)
        cross = torch.linalg.cross(pieces[:, 1] - pieces[:, 0], pieces[:, 2] - pieces[:, 0], dim=-1)
        assert bool(((cross @ parent) > 0).all())  # oriented as the parent, so no overlap...
        torch.testing.assert_close(cross.norm(dim=-1).sum(), parent.norm(), rtol=1e-12, atol=0)  # ...and no gap


def pieces_reaching_the_network(monkeypatch, det, shape, vertices, faces) -> list:
    """solve_mesh without culls; -> the pieces it hands the network: [(rows (P,), grid (P, 3, 2), levels (P,))]."""
    seen = []
    real = zoo.amortized.batching.answer_pieces

    def spy(detector_, shape_, tri_n, table, pieces, *args, **kwargs):
        seen.extend((p[0], p[2], p[3]) for p in pieces)
        return real(detector_, shape_, tri_n, table, pieces, *args, **kwargs)

    monkeypatch.setattr(zoo.amortized.batching, "answer_pieces", spy)
    solve_mesh(det, shape, vertices, faces, SolveOptions(vertex_check=False, cull=False))
    return seen


def test_bisected_pieces_tile_a_long_triangle_and_are_in_range(monkeypatch):
    # Needles (a rack's 3.0 x 0.003) and fat triangles, 8 to 100 times the range (100: over _MAX_LEVEL,
    # whose pieces stop at 1/64 of the triangle's longest edge).
    g = torch.Generator().manual_seed(11)
    length = torch.tensor([0.7, 1.5, 3.0, 3.0, 0.9, 8.0], dtype=torch.float64)
    width = torch.tensor([0.003, 0.01, 0.003, 0.5, 0.6, 0.02], dtype=torch.float64)
    a = torch.randn(6, 3, generator=g, dtype=torch.float64) * 0.1
    along = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=-1)
    across = torch.nn.functional.normalize(torch.linalg.cross(along, torch.randn(6, 3, generator=g, dtype=torch.float64)), dim=-1)
    tri = torch.stack([a, a + length[:, None] * along, a + 0.3 * length[:, None] * along + width[:, None] * across], 1)
    shape, det = TorusWithCodes(), detector()
    max_edge = det.edge_range[1]
    assert bool((subdivision_levels(tri, max_edge) > 7).all())  # all bisected
    v, inv = unique_rows(tri.reshape(-1, 3))
    seen = pieces_reaching_the_network(monkeypatch, det, shape, v, inv.reshape(-1, 3))
    rows, grid, level = (torch.cat(t) for t in zip(*seen))
    corners = grid_barycentrics(grid, level.view(-1, 1), torch.float64)  # (P, 3, 3) parent barycentrics
    pieces = torch.einsum("pjk,pkc->pjc", corners, tri[rows])
    longest = edge_lengths(tri).amax(dim=-1)
    allowed = torch.clamp_min(longest / 64, max_edge)[rows]
    assert bool((edge_lengths(pieces).amax(dim=-1) <= allowed * (1 + 1e-9)).all())  # in range
    for r in range(tri.shape[0]):
        mine = pieces[rows == r]
        parent = torch.linalg.cross(tri[r, 1] - tri[r, 0], tri[r, 2] - tri[r, 0], dim=-1)
        cross = torch.linalg.cross(mine[:, 1] - mine[:, 0], mine[:, 2] - mine[:, 0], dim=-1)
        assert bool(((cross @ parent) > 0).all())  # oriented as the parent, so no overlap...
        torch.testing.assert_close(cross.norm(dim=-1).sum(), parent.norm(), rtol=1e-9, atol=0)  # ...and no gap
    # a needle's pieces stay needles along it: a few per range of its length (200 here), not the
    # n^2 = 1,444 similar pieces of a regular subdivision
    n = math.ceil(3.0 / max_edge)
    assert int((rows == 2).sum()) < 6 * n


def test_bisected_neighbours_share_the_points_on_their_common_edge(monkeypatch):
    # Two long triangles on either side of one edge, listed with opposite orientations: every point
    # evaluated is distinct, so the edge's points were evaluated once for both.
    v = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.7, 0.4, 0.05], [1.3, -0.5, 0.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [1, 0, 3]])
    shape, det = TorusWithCodes(), detector()
    seen = pieces_reaching_the_network(monkeypatch, det, shape, v, faces)
    rows, grid, level = (torch.cat(t) for t in zip(*seen))
    corners = grid_barycentrics(grid, level.view(-1, 1), torch.float64)
    points = torch.einsum("pjk,pkc->pjc", corners, v[faces][rows]).reshape(-1, 3)
    on_edge = points[:, 1].abs() < 1e-12
    distinct = unique_rows(points.round(decimals=9))[0]
    assert int(unique_rows(points[on_edge].round(decimals=9))[0].shape[0]) > 10  # both sides cut the edge
    shape.feature_points = 0
    solve_mesh(det, shape, v, faces, SolveOptions(vertex_check=False, cull=False))
    assert shape.feature_points == distinct.shape[0]  # each point once, the edge's shared


def test_search_gives_the_exhaustive_answer_and_evaluates_less():
    shape, det = TorusWithCodes(), detector()
    tri = mixed_triangles()
    v, inv = unique_rows(tri.reshape(-1, 3))
    levels = subdivision_levels(tri, det.edge_range[1])
    assert int((levels > 1).sum()) > 30 and int(levels.max()) > 8  # flat and bisected levels both
    shape.feature_points = 0
    culled, _ = solve_mesh(det, shape, v, inv.reshape(-1, 3), SolveOptions(vertex_check=False))
    culled_points, shape.feature_points = shape.feature_points, 0
    exhaustive, _ = solve_mesh(det, shape, v, inv.reshape(-1, 3), SolveOptions(vertex_check=False, cull=False))
    # an exact (1-Lipschitz) SDF: the culls drop only pieces that cannot hold the answer
    f_culled, f_exhaustive = (shape.normalised(bary_to_points(tri, b)) for b in (culled, exhaustive))
    torch.testing.assert_close(f_culled, f_exhaustive, atol=1e-12, rtol=0)
    torch.testing.assert_close(culled, exhaustive, atol=1e-9, rtol=0)
    assert culled_points < 0.5 * shape.feature_points


def test_search_in_parts_gives_the_answers_of_one_search(monkeypatch):
    """A mesh whose cells exceed the budget is searched in parts of whole rows, each row's cells
    together: rows are independent, so the answers are those of one search over all."""
    shape, det = TorusWithCodes(), detector()
    tri = mixed_triangles()
    v, inv = unique_rows(tri.reshape(-1, 3))
    whole = solve_mesh(det, shape, v, inv.reshape(-1, 3))
    parts = []
    real = zoo.amortized.search.search_part
    monkeypatch.setattr(zoo.amortized.search, "search_part", lambda *a, **k: parts.append(a[1]) or real(*a, **k))
    monkeypatch.setattr(zoo.amortized.search, "CELL_BUDGET", 64)
    split = solve_mesh(det, shape, v, inv.reshape(-1, 3))
    assert len(parts) > 3
    assert sum(len(set(p.tolist())) for p in parts) == len(set(torch.cat(parts).tolist()))  # each row in one part only
    for a, b in zip(whole, split):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_search_is_never_worse_than_the_previous_subdivision():
    shape, det = TorusWithCodes(), detector(seed=1)
    tri = mixed_triangles(seed=2, m=60)
    levels = subdivision_levels(tri, det.edge_range[1])
    ours = detect(det, shape, tri, polish=False)
    f_ours = shape.normalised(bary_to_points(tri, ours))
    needles = strip_levels(tri, det.edge_range[1])[0] > 0
    for n in torch.unique(levels).tolist():
        rows = (levels == n) & ~needles  # needles are cut into strips, not into the pieces the previous subdivision had
        if n == 1 or n > 7 or not bool(rows.any()):  # in range: the network's answer (tested above); beyond 7: level c * 2^k >= n
            continue
        f_old = shape.normalised(bary_to_points(tri[rows], naive_subdivided(det, shape, tri[rows], n)))
        # 1e-7: the network runs in float32, and its answers for the same piece differ by rounding
        # (~1e-8 in f) with the batch they are computed in
        assert bool((f_ours[rows] <= f_old + 1e-7).all()), (n, float((f_ours[rows] - f_old).max()))


def test_a_subdivided_triangle_polishes_its_lowest_piece_inside_that_piece():
    shape, det = TorusWithCodes(), detector(seed=3)
    tri = mixed_triangles(seed=4, m=80)
    levels = subdivision_levels(tri, det.edge_range[1])
    rows = (levels > 1) & (levels <= 7)  # searched flat: with cull=False every piece of level n reaches the network
    tri = tri[rows]
    v, inv = unique_rows(tri.reshape(-1, 3))
    ours, _ = solve_mesh(det, shape, v, inv.reshape(-1, 3), SolveOptions(vertex_check=False, cull=False, polish=True))
    sdf = shape.normalised
    for i, n in enumerate(levels[rows].tolist()):
        corners = flat_pieces(tri[i], n, det.edge_range[1])  # (P, 3, 3) pieces in parent barycentrics
        pieces = torch.einsum("pjk,kc->pjc", corners, tri[i])
        with torch.no_grad():
            local = det(pieces.float(), shape.features(pieces.reshape(-1, 3)).reshape(-1, 3, 32)).double()
        answers = torch.einsum("pj,pjk->pk", local, corners)
        f_answers = sdf(bary_to_points(tri[i].expand(len(answers), 3, 3), answers))
        low = int(f_answers.argmin())
        piece_f = sdf(pieces[low])
        polished = zoo.solvers.line_search_step(sdf, pieces[low : low + 1], local[low : low + 1], piece_f[None],
                                                line_steps=POLISH_LINE_STEPS)[0] @ corners[low]
        grid_f = sdf(pieces.reshape(-1, 3))
        expected = min(float(f_answers.min()), float(grid_f.min()), float(sdf((polished @ tri[i])[None])))
        assert abs(float(sdf((ours[i] @ tri[i])[None])) - expected) < 1e-7, (i, n)
    unpolished, _ = solve_mesh(det, shape, v, inv.reshape(-1, 3), SolveOptions(vertex_check=False, cull=False, polish=False))
    gap = lambda b: zoo.solvers.optimality(sdf, tri, b).mean()  # noqa: E731
    assert gap(ours) < 0.5 * gap(unpolished)


def test_a_quadratic_head_evaluates_only_the_piece_its_own_model_puts_lowest():
    # The quadratic head knows its model's value at its answer, so solve_mesh ranks a subdivided
    # triangle's pieces by it and evaluates (and polishes) only the lowest: the answer is the lower
    # of the grid points and that one piece's polished answer, computed here piece by piece.
    shape, det = TorusWithCodes(), detector(seed=5, output="quadratic", vertex_sdf=True)
    tri = mixed_triangles(seed=6, m=80)
    levels = subdivision_levels(tri, det.edge_range[1])
    rows = (levels > 1) & (levels <= 7)
    tri = tri[rows]
    v, inv = unique_rows(tri.reshape(-1, 3))
    ours, _ = solve_mesh(det, shape, v, inv.reshape(-1, 3), SolveOptions(vertex_check=False, cull=False, polish=True))
    sdf = shape.normalised
    for i, n in enumerate(levels[rows].tolist()):
        corners = flat_pieces(tri[i], n, det.edge_range[1])
        pieces = torch.einsum("pjk,kc->pjc", corners, tri[i])
        piece_f = sdf(pieces.reshape(-1, 3)).reshape(-1, 3)
        with torch.no_grad():
            local, predicted = det.predict(pieces.float(), shape.features(pieces.reshape(-1, 3)).reshape(-1, 3, 32), piece_f.float())
        low = int(predicted.argmin())
        polished = zoo.solvers.line_search_step(sdf, pieces[low : low + 1], local[low : low + 1].double(), piece_f[low : low + 1],
                                                line_steps=POLISH_LINE_STEPS)[0] @ corners[low]
        expected = min(float(piece_f.min()), float(sdf((polished @ tri[i])[None])))
        assert abs(float(sdf((ours[i] @ tri[i])[None])) - expected) < 1e-6, (i, n)


def test_vertex_check_keeps_the_lower_of_the_answer_and_the_best_vertex():
    shape, det = TorusWithCodes(), detector()
    v, f = grid_mesh(12, size=0.5, z=0.03, jitter=0.004)
    tri = v[f]
    plain = detect(det, shape, tri, polish=False)
    checked, values = solve_mesh(det, shape, v, f, SolveOptions(vertex_check=True))
    f_plain, f_checked = (shape.normalised(bary_to_points(tri, b)) for b in (plain, checked))
    f_vertex = shape.normalised(tri.reshape(-1, 3)).reshape(-1, 3).amin(-1)
    torch.testing.assert_close(f_checked, torch.minimum(f_plain, f_vertex), atol=1e-12, rtol=0)
    torch.testing.assert_close(values, f_checked, atol=1e-12, rtol=0)  # the distances at the answers come back


def mixed_mesh_in_source(sim: Similarity, seed: int):
    """Mixed triangles and a grid over the torus, in the source frame of ``sim``: triangles (M, 3, 3), vertices (V, 3), faces (M, 3)."""
    tri_n = torch.cat([mixed_triangles(seed=seed), grid_mesh(14, 0.7, 0.04, 0.01)[0][grid_mesh(14)[1]]])
    tri = torch.as_tensor(sim.to_source(tri_n.reshape(-1, 3).numpy())).reshape(-1, 3, 3)
    v, inv = unique_rows(tri.reshape(-1, 3))
    return tri, v, inv.reshape(-1, 3)


def test_vertex_values_given_are_used_as_the_queried_ones_and_spare_their_queries():
    """collide hands solve_mesh the distances its broad phase took at the vertices (NaN where none):
    the same answers as when solve_mesh queries them, and exactly those queries fewer."""
    sim = Similarity(4.0, rotation(5), np.array([0.02, -0.1, 0.3]))
    shape, det = TorusWithCodes(sim), detector()
    tri, v, faces = mixed_mesh_in_source(sim, seed=4)
    extra = torch.zeros(3, 3, dtype=v.dtype)  # vertices no face names: their values are not read
    v = torch.cat([v, extra])
    exact = shape.normalised(torch.as_tensor(sim.to_normalised(v.numpy()))) / sim.scale
    counted = []

    class Counting:  # the torus, counting the points of its value queries
        def __init__(self, sdf):
            self.sdf, self.bounds = sdf, sdf.bounds

        def __call__(self, p):
            counted.append(len(p))
            return self.sdf(p)

        def value_and_grad(self, p):
            return self.sdf.value_and_grad(p)

    shape.normalised = Counting(shape.normalised)
    for polish in (False, True):
        counted.clear()
        bary, values = solve_mesh(det, shape, v, faces, SolveOptions(polish=polish))
        queried = sum(counted)
        for share in (1.0, 0.5):
            given = exact.clone()
            given[torch.rand(len(v), generator=torch.Generator().manual_seed(1)) >= share] = float("nan")
            given[-3:] = float("nan")
            counted.clear()
            bary_g, values_g = solve_mesh(det, shape, v, faces, SolveOptions(polish=polish), Known(vertex_values=given))
            torch.testing.assert_close(bary_g, bary, atol=1e-12, rtol=0)
            torch.testing.assert_close(values_g, values, atol=1e-12, rtol=0)
            assert sum(counted) == queried - int(torch.isfinite(given).sum())
    with pytest.raises(InputError, match="one distance per vertex"):
        solve_mesh(det, shape, v, faces, known=Known(vertex_values=exact[:-1]))


def test_cutoff_and_known_point_keep_every_contact_and_its_depth():
    sim = Similarity(4.0, rotation(7), np.array([0.02, -0.1, 0.3]))
    shape, det = TorusWithCodes(sim), detector()
    tri, v, faces = mixed_mesh_in_source(sim, seed=3)
    source = lambda p: shape.normalised(torch.as_tensor(sim.to_normalised(p.numpy()))) / sim.scale  # noqa: E731
    cutoff = 0.004 / sim.scale
    full_bary, full = solve_mesh(det, shape, v, faces)
    centroids = tri.mean(1)
    known = (torch.full(tri.shape[:2], 1 / 3, dtype=tri.dtype), source(centroids))
    cut_bary, cut = solve_mesh(det, shape, v, faces, SolveOptions(cutoff=cutoff), Known(*known))
    contacts = full <= cutoff
    assert 20 < int(contacts.sum()) < len(tri) - 20
    torch.testing.assert_close(cut <= cutoff, contacts | (known[1] <= cutoff))  # the same contacts (and the centroid's)
    assert bool((cut[contacts] <= full[contacts] + 1e-12).all())  # depths no worse
    # the distances returned are the SDF's at the returned points, in the source frame
    torch.testing.assert_close(cut, source(bary_to_points(tri, cut_bary)), atol=1e-9, rtol=0)
    torch.testing.assert_close(full, source(bary_to_points(tri, full_bary)), atol=1e-9, rtol=0)


def test_best_so_far_keeps_the_lowest_candidate_per_row_like_a_loop():
    # Candidates offered in several batches, with repeated rows, ties and rows never offered: the
    # best per row is the lowest value, the first such in order (a later equal one does not replace
    # it), and a row that takes a candidate is no longer the known point's.
    from zoo.amortized import BestSoFar

    g = torch.Generator().manual_seed(3)
    m = 40
    best = BestSoFar(m, torch.float64, "cpu")
    best.from_known[:] = True
    value = [math.inf] * m
    bary = [[1 / 3] * 3 for _ in range(m)]
    from_known = [True] * m
    for _ in range(6):
        q = 90
        rows = torch.randint(0, m - 5, (q,), generator=g)  # the last five rows are never offered
        values = torch.randint(0, 12, (q,), generator=g).double() / 4  # coarse values: many ties
        b = torch.rand(q, 3, generator=g, dtype=torch.float64)
        best.offer(rows, values, b)
        for r, v, row_bary in zip(rows.tolist(), values.tolist(), b.tolist()):
            if v < value[r]:
                value[r], bary[r], from_known[r] = v, row_bary, False
    torch.testing.assert_close(best.value, torch.tensor(value, dtype=torch.float64), atol=0, rtol=0)
    torch.testing.assert_close(best.bary, torch.tensor(bary, dtype=torch.float64), atol=0, rtol=0)
    assert best.from_known.tolist() == from_known
    assert best.from_known[-5:].all() and bool(torch.isinf(best.value[-5:]).all())
    best.offer(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64))
    torch.testing.assert_close(best.value, torch.tensor(value, dtype=torch.float64), atol=0, rtol=0)


def test_solve_options_refuse_a_cutoff_without_the_vertex_check():
    with pytest.raises(InputError, match="cutoff needs vertex_check=True"):
        SolveOptions(cutoff=1e-3, vertex_check=False)


def test_zero_triangles_give_empty_answers():  # detect's dtypes and polish settings: tests/test_detector.py
    shape, det = TorusWithCodes(), detector()
    bary, values = solve_mesh(det, shape, torch.rand(4, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64))
    assert bary.shape == (0, 3) and values.shape == (0,) and values.dtype == torch.float64
    bary, values = solve_mesh(det, shape, torch.rand(4, 3), torch.zeros(0, 3, dtype=torch.int64), SolveOptions(vertex_check=False))
    assert bary.shape == (0, 3) and values is None
    assert detect(det, shape, []).shape == (0, 3)
