"""A descent on triangles in barycentric coordinates, written once for numpy arrays and torch tensors alike.

The SDF's own warm steps (:mod:`zoo.coherence`, torch, on any device) and the proxy collider's answers and its numpy
passes (:mod:`zoo.proxy_collider`, numpy) take their steps here; the compiled loop (:mod:`zoo.proxy_kernel`) is the
same maths written for one face at a time, and ``tests/test_simplex.py`` holds both against naive references.

Shapes: W triangles ``tri`` (W, 3, 3) (corner, coordinate), points on them ``bary`` (W, 3), gradients ``g`` (W, 3).
"""

from __future__ import annotations

import math

import numpy as np
import torch

BOUNDARY = 1e-9  # barycentric coordinates this small put a point on its triangle's boundary


def frank_wolfe_gap(tri, bary, grads):
    """Frank-Wolfe's gap g . p - min_i g . v_i (W,) at the points ``bary`` with the gradients ``grads`` there: 0 at a
    KKT point, and a bound of how far above the minimum the point is where f is convex."""
    xp = _namespace(tri)
    scores = xp.einsum("wc,wvc->wv", grads, tri)
    return (scores * bary).sum(-1) - xp.amin(scores, -1)


def plane_descent(tri, bary, g, boundary: float = BOUNDARY):
    """-g projected onto each triangle's plane, in barycentric coordinates (W, 3) summing to 0; along the edge a point
    on the boundary (a coordinate at most ``boundary``) lies on where it would leave across it; zero at a vertex it
    would leave, and on a needle (no plane)."""
    xp = _namespace(tri)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    a11, a12, a22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    r1, r2 = -(g * e1).sum(-1), -(g * e2).sum(-1)
    det = a11 * a22 - a12 * a12
    flat = det > 1e-6 * a11 * a22  # a triangle with area, not a needle
    det = xp.where(flat, det, 1.0)
    x, y = (a22 * r1 - a12 * r2) / det, (a11 * r2 - a12 * r1) / det
    direction = xp.where(flat[:, None], xp.stack([-(x + y), x, y], -1), 0.0)
    blocked = (bary <= boundary) & (direction < 0)
    count = (blocked * 1).sum(-1)
    # on one edge (the coordinate i at 0): the descent along that edge, from vertex j = i + 1 to k = i + 2
    i = (blocked * 1).argmax(-1)
    on_edge = _one_hot(xp, (i + 2) % 3, tri) - _one_hot(xp, (i + 1) % 3, tri)
    edge = xp.einsum("wv,wvc->wc", on_edge, tri)
    along = -(g * edge).sum(-1) / (edge * edge).sum(-1).clip(xp.finfo(tri.dtype).tiny)
    direction = xp.where((count == 1)[:, None], along[:, None] * on_edge, direction)
    return xp.where((count > 1)[:, None], 0.0, direction)


def descent_segment(tri, bary, g, boundary: float = BOUNDARY):
    """The steepest descent inside each triangle from ``bary``: its barycentric direction (W, 3)
    (:func:`plane_descent`) and how far along it the triangle reaches (W,). Where that goes nowhere (a needle, or a
    corner the plane's descent leaves), the direction to Frank-Wolfe's vertex, a descent wherever its gap is
    positive, reaching it."""
    xp = _namespace(tri)
    direction = plane_descent(tri, bary, g, boundary)
    leaving = direction < 0
    reach = xp.amin(xp.where(leaving, bary / xp.where(leaving, -direction, 1.0), math.inf), -1)
    reach = xp.where(xp.isfinite(reach), reach, 0.0)
    stuck = reach * xp.amax(xp.abs(direction), -1) <= 0
    if stuck.any():
        vertex = xp.einsum("wvc,wc->wv", tri[stuck], g[stuck]).argmin(-1)
        direction[stuck] = _one_hot(xp, vertex, tri) - bary[stuck]
        reach[stuck] = 1.0
    return direction, reach


def on_simplex(bary):
    """Barycentric coordinates (..., 3) a step left a rounding error off the triangle: clipped at 0, summing to 1."""
    out = bary.clip(0)
    return out / out.sum(-1)[..., None]


def _namespace(array):
    return torch if isinstance(array, torch.Tensor) else np


def _one_hot(xp, corner, like):
    """(W, 3) the unit barycentric coordinates of the corners ``corner`` (W,), in ``like``'s dtype (and device)."""
    if xp is np:
        return (np.arange(3) == corner[:, None]).astype(like.dtype)
    return (torch.arange(3, device=like.device) == corner[:, None]).to(like.dtype)


__all__ = ["BOUNDARY", "frank_wolfe_gap", "plane_descent", "descent_segment", "on_simplex"]
