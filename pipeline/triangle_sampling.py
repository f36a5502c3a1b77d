"""Triangles around a shape under the paper's four conditions, by batched rejection sampling.

The conditions (paper, "Training data"): edge lengths in [0.03, 0.08]; area in [0.0002, 0.002];
signed distance of the centroid in [0, 0.1]; minimum signed distance over the triangle > 0, found
by Frank-Wolfe with 100 iterations. The solver benchmark and the detector's dataset stage both
draw their triangles here, so the two see the same distribution.
"""

from __future__ import annotations

import torch

from zoo import geometry, validation
from zoo.errors import DataError
from zoo.sdf import check_sdf
from zoo.solvers import frank_wolfe

EDGE_RANGE = (0.03, 0.08)
AREA_RANGE = (0.0002, 0.002)
CENTROID_SDF_RANGE = (0.0, 0.1)
MIN_SDF_ITERS = 100


def sample_constrained_triangles(
    sdf,
    n: int,
    seed: int = 0,
    *,
    edge_range: tuple[float, float] = EDGE_RANGE,
    area_range: tuple[float, float] = AREA_RANGE,
    centroid_sdf_range: tuple[float, float] = CENTROID_SDF_RANGE,
    min_sdf_iters: int = MIN_SDF_ITERS,
    batch: int | None = None,
    max_rounds: int = 200,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """``n`` triangles (n, 3, 3) near the surface of ``sdf`` that satisfy all four conditions.

    Each round draws ``batch`` candidates: a shape (three edge lengths uniform in ``edge_range``,
    kept if they form a triangle whose area is in ``area_range``), a uniformly random rotation, and
    a centroid placed at a uniformly drawn distance from the surface (a point uniform in the
    SDF's bounds, moved along its gradient onto that level set). The candidates are then filtered
    by every condition measured on the final tensor, so what is returned satisfies them as
    :mod:`zoo.geometry` measures them. Same ``seed``, same triangles, on any device.

    Args:
        sdf: any SDF (callable, ``value_and_grad``, ``bounds``).
        n: number of triangles wanted (>= 1).
        seed: seed of the random generator.
        edge_range, area_range, centroid_sdf_range: closed intervals of the conditions.
        min_sdf_iters: Frank-Wolfe iterations used to certify the minimum is > 0.
        batch: candidates drawn per round; default 4 n clamped to [1024, 65536] (part of what the
            seed reproduces: the same seed with another ``batch`` or ``n`` draws other triangles).
        max_rounds: rounds before giving up with :class:`DataError`.
        dtype, device: of the returned tensor, and where the candidates are filtered (the SDF queries:
            on a GPU, ``device="cuda"``). Candidates are drawn on the CPU in float64, so a seed draws the
            same candidates everywhere; the filter's rounding may differ between devices, which can flip
            a candidate that sits on a condition's boundary.

    Returns:
        (n, 3, 3) triangles.
    """
    check_sdf(sdf)
    n = validation.positive_int(n, "n")
    batch = min(max(4 * n, 1024), 65536) if batch is None else validation.positive_int(batch, "batch")
    edge_lo, edge_hi = validation.interval(edge_range, "edge_range", positive=True)
    area_lo, area_hi = validation.interval(area_range, "area_range", positive=True)
    dist_lo, dist_hi = validation.interval(centroid_sdf_range, "centroid_sdf_range")
    gen = torch.Generator().manual_seed(int(seed))
    kept: list[torch.Tensor] = []
    count = 0
    for _ in range(int(max_rounds)):
        shapes = _triangle_shapes(batch, edge_lo, edge_hi, gen)  # (B, 3, 3), centroid at 0
        shapes = shapes @ _random_rotations(shapes.shape[0], gen).transpose(1, 2)
        centres = _points_near_surface(sdf, shapes.shape[0], dist_lo, dist_hi, gen, device)
        tri = (shapes + centres.unsqueeze(1)).to(device=device, dtype=dtype)
        tri = tri[_meets_conditions(sdf, tri, (edge_lo, edge_hi), (area_lo, area_hi), (dist_lo, dist_hi), min_sdf_iters)]
        kept.append(tri)
        count += tri.shape[0]
        if count >= n:
            return torch.cat(kept)[:n]
    raise DataError(
        f"only {count} of {n} triangles met the conditions after {max_rounds} rounds of {batch}; "
        "the shape may be too thin or the ranges too tight: widen the ranges or raise max_rounds"
    )


def meets_conditions(sdf, triangles, *, edge_range=EDGE_RANGE, area_range=AREA_RANGE,
                     centroid_sdf_range=CENTROID_SDF_RANGE, min_sdf_iters=MIN_SDF_ITERS) -> torch.Tensor:
    """(M,) bool: which of ``triangles`` (M, 3, 3) satisfy the four conditions."""
    check_sdf(sdf)
    tri = validation.as_triangles(triangles)
    return _meets_conditions(sdf, tri, edge_range, area_range, centroid_sdf_range, min_sdf_iters)


def _meets_conditions(sdf, tri, edge_range, area_range, dist_range, min_sdf_iters) -> torch.Tensor:
    edges = geometry.edge_lengths(tri)
    area = geometry.area(tri)
    ok = (edges >= edge_range[0]).all(-1) & (edges <= edge_range[1]).all(-1)
    ok &= (area >= area_range[0]) & (area <= area_range[1])
    d = torch.as_tensor(sdf(geometry.centroid(tri))).to(tri)
    ok &= (d >= dist_range[0]) & (d <= dist_range[1])
    idx = ok.nonzero().squeeze(-1)
    if idx.numel():
        # Only the survivors pay for the Frank-Wolfe certificate (the costly condition).
        sub = tri[idx]
        bary = frank_wolfe(sdf, sub, iters=min_sdf_iters)
        ok[idx] = torch.as_tensor(sdf(geometry.bary_to_points(sub, bary))).to(tri) > 0
    return ok


def _triangle_shapes(count: int, lo: float, hi: float, gen: torch.Generator) -> torch.Tensor:
    """Planar triangles (K, 3, 3) in the xy plane, centroid at the origin, edges uniform in [lo, hi]; K <= count.

    Edge lengths (a, b, c) are opposite vertices (0, 1, 2); draws that violate the triangle
    inequality are dropped. Area is filtered later, with the other conditions.
    """
    a, b, c = (lo + (hi - lo) * torch.rand(3, count, generator=gen, dtype=torch.float64)).unbind(0)
    valid = (a < b + c) & (b < a + c) & (c < a + b)
    a, b, c = a[valid], b[valid], c[valid]
    # v0 at the origin, v1 on the x axis at distance c, v2 at distance b from v0 and a from v1.
    x = (c * c + b * b - a * a) / (2 * c)
    y = (b * b - x * x).clamp_min(0).sqrt()
    zeros = torch.zeros_like(a)
    tri = torch.stack(
        [torch.stack([zeros, zeros, zeros], -1), torch.stack([c, zeros, zeros], -1), torch.stack([x, y, zeros], -1)], dim=1
    )
    return tri - tri.mean(dim=1, keepdim=True)


def _random_rotations(count: int, gen: torch.Generator) -> torch.Tensor:
    """Uniformly random rotation matrices (K, 3, 3), from normalised Gaussian quaternions."""
    q = torch.randn(count, 4, generator=gen, dtype=torch.float64)
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        dim=1,
    )


def _points_near_surface(sdf, count: int, lo: float, hi: float, gen: torch.Generator, device=None) -> torch.Tensor:
    """Points (count, 3) at a distance drawn uniformly in [lo, hi] from the surface (exactly so for an exact SDF).

    A point x uniform in the bounds (grown by ``hi``) moves along the gradient to the wanted level:
    x - (f(x) - target) g(x). For an exact SDF this lands on the level set; for a fitted one the
    centroid condition, checked afterwards, catches the misses. The points are drawn on the CPU
    (float64) and the SDF is queried on ``device``; the result stays on the CPU.
    """
    lower, upper = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
    lower, upper = lower - hi, upper + hi
    x = lower + (upper - lower) * torch.rand(count, 3, generator=gen, dtype=torch.float64)
    target = lo + (hi - lo) * torch.rand(count, generator=gen, dtype=torch.float64)
    f, g = sdf.value_and_grad(x.to(device))  # device None: stays where it is
    f, g = torch.as_tensor(f).to(x), torch.as_tensor(g).to(x)
    g = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return x - (f - target).unsqueeze(-1) * g
