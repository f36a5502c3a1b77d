"""zoo.simplex (the descent on triangles, one implementation for numpy and torch) against naive references, and the
compiled loop's one-face versions (zoo.proxy_kernel) against it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from zoo.simplex import descent_segment, frank_wolfe_gap, on_simplex, plane_descent


def triangles(n: int = 400, seed: int = 3):
    """Random triangles (n, 3, 3), points on them (n, 3) (a quarter on an edge, a tenth at a vertex) and gradients."""
    rng = np.random.default_rng(seed)
    tri = rng.normal(size=(n, 3, 3))
    bary = rng.random((n, 3))
    bary[: n // 4, 0] = 0  # on the edge opposite vertex 0
    bary[n // 4: n // 4 + n // 10, :2] = 0  # at vertex 2
    bary /= bary.sum(axis=1, keepdims=True)
    return tri, bary, rng.normal(size=(n, 3))


def naive_plane_descent(tri, bary, g):
    """One triangle at a time: -g projected onto the triangle's plane by least squares, as barycentric coordinates;
    on an edge where that leaves, -g projected onto the edge; at a vertex where it leaves, zero."""
    out = np.zeros_like(bary)
    for w in range(len(tri)):
        edges = np.stack([tri[w, 1] - tri[w, 0], tri[w, 2] - tri[w, 0]], axis=1)  # (3, 2)
        xy = np.linalg.lstsq(edges, -g[w], rcond=None)[0]
        direction = np.array([-xy.sum(), xy[0], xy[1]])
        blocked = [v for v in range(3) if bary[w, v] <= 1e-9 and direction[v] < 0]
        if len(blocked) == 1:
            j, k = (blocked[0] + 1) % 3, (blocked[0] + 2) % 3
            edge = tri[w, k] - tri[w, j]
            along = -(g[w] @ edge) / (edge @ edge)
            direction = np.zeros(3)
            direction[j], direction[k] = -along, along
        elif len(blocked) > 1:
            direction = np.zeros(3)
        out[w] = direction
    return out


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_plane_descent_is_the_projected_gradient(backend):
    tri, bary, g = triangles()
    expected = naive_plane_descent(tri, bary, g)
    if backend == "torch":
        got = plane_descent(*(torch.from_numpy(a) for a in (tri, bary, g))).numpy()
    else:
        got = plane_descent(tri, bary, g)
    assert np.allclose(got, expected, atol=1e-9)
    assert np.allclose(got.sum(axis=1), 0, atol=1e-12)  # a direction in barycentric coordinates


def test_frank_wolfe_gap_against_the_vertices():
    tri, bary, g = triangles()
    point = np.einsum("wv,wvc->wc", bary, tri)
    expected = [g[w] @ point[w] - min(g[w] @ tri[w, v] for v in range(3)) for w in range(len(tri))]
    assert np.allclose(frank_wolfe_gap(tri, bary, g), expected, atol=1e-12)
    torch_gap = frank_wolfe_gap(*(torch.from_numpy(a) for a in (tri, bary, g)))
    assert np.allclose(torch_gap.numpy(), expected, atol=1e-12)


def test_the_descent_segment_ends_on_the_boundary_and_descends():
    tri, bary, g = triangles()
    direction, reach = descent_segment(tri, bary, g)
    end = bary + reach[:, None] * direction
    moved = np.abs(direction).max(axis=1) * reach > 0
    assert moved.mean() > 0.5
    assert np.allclose(end[moved].min(axis=1), 0, atol=1e-9) and (end[moved] >= -1e-9).all()  # on the boundary
    slope = np.einsum("wc,wc->w", g, np.einsum("wv,wvc->wc", direction, tri))
    assert (slope[moved] < 0).all()  # downhill
    gap = frank_wolfe_gap(tri, bary, g)
    assert (gap[~moved] <= 1e-9).all()  # it stays only where no direction descends (a KKT point)
    torch_direction, torch_reach = descent_segment(*(torch.from_numpy(a) for a in (tri, bary, g)))
    assert np.allclose(torch_direction.numpy(), direction, atol=1e-9) and np.allclose(torch_reach.numpy(), reach)


def test_a_needle_descends_towards_frank_wolfes_vertex():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]])  # no plane
    bary, g = np.array([[0.2, 0.6, 0.2]]), np.array([[1.0, 0, 0]])
    direction, reach = descent_segment(tri, bary, g)
    assert np.allclose(bary + reach[:, None] * direction, [[1, 0, 0]])


def test_on_simplex_clips_and_normalises():
    out = on_simplex(np.array([[-1e-12, 0.5, 0.5000001], [0.2, 0.3, 0.5]]))
    assert (out >= 0).all() and np.allclose(out.sum(axis=1), 1) and np.allclose(out[1], [0.2, 0.3, 0.5])


def test_the_compiled_one_face_steps_are_these():
    from zoo.proxy_kernel import _descent_segment, _frank_wolfe_gap

    tri, bary, g = triangles(200)
    direction, reach = descent_segment(tri, bary, g)
    gap = frank_wolfe_gap(tri, bary, g)
    out = np.empty(3)
    for w in range(len(tri)):
        assert _frank_wolfe_gap(tri[w], *bary[w], *g[w]) == pytest.approx(gap[w], abs=1e-12)
        assert _descent_segment(tri[w], bary[w], *g[w], out) == pytest.approx(reach[w], rel=1e-9, abs=1e-12)
        assert np.allclose(out, direction[w], atol=1e-9)
