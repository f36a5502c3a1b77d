"""The point of minimum signed distance on each triangle (problem (1) of the paper), and how to judge one.

Solvers, each batched over triangles (M, 3, 3) and returning barycentric coordinates (M, 3):

* :func:`frank_wolfe` - MuJoCo's mesh-SDF rule (the paper's baseline and the detector's label);
* :func:`projected_gradient` - PhysX's triangle-SDF rule;
* :func:`line_search_step` - one Frank-Wolfe step with a parabolic line search from a given start
  (one gradient and a few value queries);
* :func:`line_search_steps` - several in a row, optionally falling back on a known lower point
  (what the amortized detector's answers are polished with);
* :func:`vertex_values` - f at each triangle's vertices;
* :func:`reference` - slow, global and obviously correct: a dense barycentric grid, then a
  pattern search; the yardstick the benchmarks measure the others against.

Metrics: :func:`optimality` (equation (12)), :func:`nme`, :func:`minimum_location`.

Every function accepts any object following the SDF protocol (:mod:`zoo.sdf`): callable on (N, 3)
points, with ``value_and_grad`` and ``bounds``. float32 is the default; float64 triangles give
float64 answers. Degenerate triangles (collinear, or all three vertices equal) give finite
barycentrics on the simplex, never NaN.
"""

from __future__ import annotations

import math

import torch

from .errors import InputError
from .geometry import bary_to_points, barycentric_grid, mean_edge_length, perimeter
from .sdf import check_sdf
from .validation import as_rows, as_simplex, as_triangles, float_in, non_negative_int

VERTEX, EDGE, FACE = 0, 1, 2
"""Codes :func:`minimum_location` returns."""


# --------------------------------------------------------------------------------------------
# Solvers
# --------------------------------------------------------------------------------------------


def frank_wolfe(sdf, triangles, iters: int = 10, init=None, *, warm_start_offset: int = 10) -> torch.Tensor:
    """Frank-Wolfe on the triangle, MuJoCo's mesh-SDF rule.

    Cold start (``init=None``): start at the centroid; at iteration k = 0, 1, ..., iters-1 take
    p = bary . v, g = grad f(p), s = argmin_i g . v_i, gamma = 2 / (k + 2) and
    bary <- (1 - gamma) bary + gamma e_s. The last iterate is returned, as MuJoCo does.

    Warm start (``init`` given, e.g. the amortized detector's answer): the schedule continues as if
    ``init`` were the result of ``warm_start_offset`` earlier iterations, gamma = 2 / (k + offset + 2),
    because gamma = 1 at k = 0 would jump to a vertex and throw ``init`` away. FW's fixed steps
    zig-zag around a minimum on an edge or inside the face, so a refinement could end farther
    from it than it started; a warm start therefore returns the best iterate seen (lowest f,
    ``init`` included): refining never makes an answer worse, and an exact answer stays put.

    Args:
        sdf: any SDF (callable, ``value_and_grad``, ``bounds``).
        triangles: (M, 3, 3).
        iters: number of gradient evaluations (>= 0).
        init: optional (M, 3) barycentric start.
        warm_start_offset: iterations ``init`` is taken to be worth (>= 0); used only with ``init``.

    Returns:
        (M, 3) barycentric coordinates, the dtype of ``triangles``.
    """
    tri = _prepare(sdf, triangles)
    iters = non_negative_int(iters, "iters")
    offset = non_negative_int(warm_start_offset, "warm_start_offset")
    warm = init is not None
    bary = as_simplex(init, tri, "init") if warm else _centroid_bary(tri)
    if not warm:
        offset = 0
    best_bary, best_f = bary, None
    for k in range(iters):
        f, g = _value_and_grad(sdf, tri, bary)
        if warm:
            best_bary, best_f = _keep_lower(best_bary, best_f, bary, f)
        s = _vertex_scores(tri, g).argmin(dim=-1)
        gamma = 2.0 / (k + offset + 2)
        bary = (1.0 - gamma) * bary + gamma * _one_hot(s, bary)
    if warm and iters > 0:
        f = _values(sdf, tri, bary)
        bary, _ = _keep_lower(best_bary, best_f, bary, f)
    # In float32 a hundred convex combinations let the rows drift from summing to 1 by ~1e-7, which
    # moves p off the triangle's plane by as much; put the answer back on the simplex.
    return bary / bary.sum(dim=-1, keepdim=True)


def line_search_step(sdf, triangles, init, vertex_values=None, line_steps: int = 0, start=None) -> torch.Tensor:
    """One Frank-Wolfe step from ``init`` whose length comes from a parabola, not from a schedule.

    At p = init . v take f(p) and g = grad f(p) (one value-and-gradient query), the Frank-Wolfe
    vertex s = argmin_i g . v_i and the direction d = v_s - p. Along p + t d, t in [0, 1], f is
    modelled by the parabola with value f(p) and slope g . d at t = 0 and value f(v_s) at t = 1;
    its minimiser is the answer. A start that already satisfies the KKT conditions (g . d >= 0:
    no descent direction inside the triangle) stays where it is and costs no line query.
    ``line_steps`` more value queries each refine t by successive parabolic interpolation
    (:func:`_interpolation_step`).

    From a good start (the best vertex, or the detector's answer) this one step reaches what
    Frank-Wolfe's fixed 2/(k+2) steps need tens of gradient queries for (README, detector bench).

    Args:
        sdf: any SDF.
        triangles: (M, 3, 3).
        init: (M, 3) barycentric start.
        vertex_values: optional (M, 3) f at the vertices (three value queries per triangle if omitted).
        line_steps: value queries spent on refining the step (>= 0).
        start: optional (f (M,), grad f (M, 3)) at ``init``, where the caller has them already (the
            value-and-gradient query is then skipped).

    Returns:
        (M, 3) barycentric coordinates, the dtype of ``triangles``.
    """
    tri = _prepare(sdf, triangles)
    bary = as_simplex(init, tri, "init")
    line_steps = non_negative_int(line_steps, "line_steps")
    fv = _given_vertex_values(sdf, tri, vertex_values)
    rows = torch.arange(tri.shape[0], device=tri.device)
    f0, g = _value_and_grad(sdf, tri, bary) if start is None else _start_value_and_grad(start, bary)
    scores = _vertex_scores(tri, g)  # (M, 3): g . v_i
    s = scores.argmin(dim=-1)
    p = bary_to_points(tri, bary)
    slope = scores[rows, s] - (g * p).sum(-1)  # d f / d t at t = 0, <= 0 up to rounding
    fs = fv[rows, s]
    descent = slope < 0  # elsewhere the start is already KKT and stays (most minima lie at a vertex)
    t = torch.where(descent, _parabola_minimiser(f0, slope, fs), torch.zeros_like(f0))
    if line_steps and bool(descent.any()):
        # the line queries only where there is a line to search
        a = descent.nonzero().squeeze(-1)
        p_a, d_a, slope_a, t_a = p[a], tri[a, s[a]] - p[a], slope[a], t[a]
        samples_t, samples_f = [torch.zeros_like(t_a), torch.ones_like(t_a)], [f0[a], fs[a]]
        for _ in range(line_steps):
            samples_t.append(t_a)
            samples_f.append(sdf(p_a + t_a.unsqueeze(-1) * d_a).reshape(-1).to(tri))
            t_a = _interpolation_step(torch.stack(samples_t, -1), torch.stack(samples_f, -1), slope_a)
        t = t.index_copy(0, a, t_a)
    return (1.0 - t).unsqueeze(-1) * bary + t.unsqueeze(-1) * _one_hot(s, bary)


def line_search_steps(sdf, triangles, init, vertex_values, steps, line_steps: int = 0, start=None,
                      fallback=None) -> torch.Tensor:
    """``steps`` :func:`line_search_step` calls in a row, each from the last one's answer (``start``:
    (f, grad f) at ``init``, as there). ``steps``: an int, or an int tensor (M,) of steps per row
    (rows of different budgets share each query).

    ``fallback``: optional (bary (M, 3), f (M,), grad f (M, 3)) of a point whose value and gradient
    are known (the lowest vertex, say); each step after the first starts from it instead where it is
    lower than the last answer, so a step that went uphill is not built on. A row whose step left it
    where it was (a KKT point, and no lower fallback) is done: the next step would do the same. Every
    later step costs one value-and-gradient query (at the last answer) and ``line_steps`` values, on the
    rows still moving only.
    """
    tri = _prepare(sdf, triangles)
    bary = as_simplex(init, tri, "init").clone()
    budget = _steps_per_row(steps, tri.shape[0], tri.device)
    fv = _given_vertex_values(sdf, tri, vertex_values)
    rows = (budget > 0).nonzero().squeeze(-1)  # the rows still moving, with f and g at their answers
    if rows.numel() == 0:
        return bary
    if start is None:
        f, g = _value_and_grad(sdf, tri[rows], bary[rows])
    else:
        f, g = (x[rows] for x in _start_value_and_grad(start, bary))
    steps = int(budget.max())
    for k in range(steps):
        if k and fallback is not None:
            back_bary, back_f, back_g = (x[rows] for x in fallback)
            back = back_f.to(f) < f
            bary[rows] = torch.where(back.unsqueeze(-1), back_bary.to(bary), bary[rows])
            f, g = torch.where(back, back_f.to(f), f), torch.where(back.unsqueeze(-1), back_g.to(g), g)
        before = bary[rows]
        after = line_search_step(sdf, tri[rows], before, fv[rows], line_steps=line_steps, start=(f, g))
        bary[rows] = after
        if k + 1 == steps:
            break
        moved = (after != before).any(dim=-1)
        keep = moved if fallback is None else moved | (fallback[1][rows].to(f) < f)
        keep &= budget[rows] > k + 1
        rows, f, g, moved = rows[keep], f[keep], g[keep], moved[keep]
        if rows.numel() == 0:
            break
        if bool(moved.any()):  # the value and gradient at the new answers; a row that stayed keeps its own
            m = moved.nonzero().squeeze(-1)
            f_new, g_new = _value_and_grad(sdf, tri[rows[m]], bary[rows[m]])
            f, g = f.index_copy(0, m, f_new), g.index_copy(0, m, g_new)
    return bary


def _steps_per_row(steps, m: int, device) -> torch.Tensor:
    """``steps`` (an int, or an int tensor (M,)) as a tensor (M,) of non-negative step counts."""
    if isinstance(steps, torch.Tensor):
        if steps.shape != (m,) or steps.dtype.is_floating_point or steps.dtype == torch.bool:
            raise InputError(f"steps must be an int or an integer tensor of shape ({m},), got {steps.dtype} {tuple(steps.shape)}")
        if bool((steps < 0).any()):
            raise InputError("steps must be >= 0 on every row")
        return steps.to(device=device, dtype=torch.int64)
    return torch.full((m,), non_negative_int(steps, "steps"), dtype=torch.int64, device=device)


def vertex_values(sdf, triangles) -> torch.Tensor:
    """f at the three vertices of each triangle: (M, 3, 3) -> (M, 3), one value query per vertex, no gradients."""
    tri = _prepare(sdf, triangles)
    with torch.no_grad():
        return _values(sdf, tri, torch.eye(3, dtype=tri.dtype, device=tri.device).expand(tri.shape[0], 3, 3))


def _given_vertex_values(sdf, tri: torch.Tensor, values) -> torch.Tensor:
    """``values`` (M, 3) checked against ``tri`` (M, 3, 3), or queried where None."""
    fv = vertex_values(sdf, tri) if values is None else as_rows(values, "vertex_values").to(tri)
    if fv.shape != tri.shape[:2]:
        raise InputError(f"vertex_values must have shape {tuple(tri.shape[:2])} (one value per vertex), got {tuple(fv.shape)}")
    return fv


def _start_value_and_grad(start, bary: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    f0, g = (as_rows(x, name).to(bary) for x, name in zip(start, ("start value", "start gradient")))
    if f0.shape != bary.shape[:1] or g.shape != bary.shape:
        raise InputError(f"start must be (f (M,), grad (M, 3)) for {bary.shape[0]} triangles, got {tuple(f0.shape)} and {tuple(g.shape)}")
    return f0, g


def _parabola_minimiser(f0: torch.Tensor, slope: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
    """argmin over [0, 1] of the parabola with q(0) = f0, q'(0) = slope, q(1) = f1: (M,) each -> (M,)."""
    curvature = f1 - f0 - slope  # q(t) = f0 + slope t + curvature t^2
    inner = (-slope / (2.0 * curvature.clamp_min(torch.finfo(f0.dtype).tiny))).clamp(0.0, 1.0)
    end = (f1 < f0).to(f0)  # not bending up: the lower end
    return torch.where(curvature > 0, inner, end)


def _interpolation_step(t: torch.Tensor, f: torch.Tensor, slope0: torch.Tensor) -> torch.Tensor:
    """Successive parabolic interpolation: samples (M, K) at t in [0, 1], the slope (M,) at t = 0 -> the next t (M,).

    Where the lowest sample is the start (t = 0, whose slope is known), the minimiser of the parabola
    with that value and slope through the nearest sample beyond it; elsewhere the vertex of the
    parabola through the lowest sample and its nearest neighbours on either side, kept between
    them; the lowest sample itself where it has no neighbour on a side or the three do not bend up.
    """
    rows = torch.arange(t.shape[0], device=t.device)
    best = f.argmin(dim=-1)
    tb, fb = t[rows, best], f[rows, best]
    left = torch.where(t < tb.unsqueeze(-1), t, torch.full_like(t, -math.inf)).max(dim=-1)
    right = torch.where(t > tb.unsqueeze(-1), t, torch.full_like(t, math.inf)).min(dim=-1)
    tl, tr = left.values, right.values
    fl, fr = f[rows, left.indices], f[rows, right.indices]
    bracketed = torch.isfinite(tl) & torch.isfinite(tr)
    tiny = torch.finfo(t.dtype).tiny
    tl_, tr_ = torch.where(bracketed, tl, tb - 1), torch.where(bracketed, tr, tb + 1)  # finite placeholders
    slope_l = (fb - fl) / (tb - tl_).clamp_min(tiny)
    slope_r = (fr - fb) / (tr_ - tb).clamp_min(tiny)
    curvature = (slope_r - slope_l) / (tr_ - tl_).clamp_min(tiny)
    vertex = 0.5 * (tl_ + tb) - slope_l / (2.0 * curvature.clamp_min(tiny))
    ok = bracketed & (curvature > 0)
    step = torch.where(ok, torch.minimum(torch.maximum(vertex, tl_), tr_), tb)
    # the start is lowest: its value and slope, and the nearest sample beyond, make the parabola
    at_start = (tb == 0) & torch.isfinite(tr)
    reach = torch.where(at_start, tr, torch.ones_like(tr))
    hermite = reach * _parabola_minimiser(fb, slope0 * reach, torch.where(at_start, fr, fb))
    return torch.where(at_start, hermite, step)


def projected_gradient(
    sdf,
    triangles,
    iters: int = 32,
    step: float = 0.25,
    decay: float = 0.8,
    tol: float = 1e-6,
    *,
    return_iterations: bool = False,
):
    """Projected gradient descent in barycentric coordinates, PhysX's triangle-SDF rule.

    Start at the best of the centroid and the three vertices. Each iteration: g = grad f(p)
    normalised (an SDF's gradient is a direction; its length only reflects fitting error),
    slope_i = g . (v_i - p) (the derivative of f along barycentric coordinate i, up to a common
    shift the projection ignores), bary <- project_to_simplex(bary - step_k * slope / L) with L
    the mean edge length (so ``step`` is in units of the triangle and the rule is scale-free),
    step_k = step * decay^k. A triangle stops once its squared barycentric change falls below
    ``tol`` (PhysX's 1e-3 squared); the loop ends when every triangle has stopped.

    Args:
        sdf: any SDF.
        triangles: (M, 3, 3).
        iters: most iterations (>= 0).
        step: first step, in barycentric units per unit slope/edge (> 0).
        decay: step factor per iteration, in (0, 1].
        tol: per-triangle stop threshold on |delta bary|^2 (>= 0).
        return_iterations: also return how many iterations ran (for per-iteration timings).

    Returns:
        (M, 3) barycentric coordinates; with ``return_iterations``, a tuple (bary, iterations run).
    """
    tri = _prepare(sdf, triangles)
    iters = non_negative_int(iters, "iters")
    step = float_in(step, "step", 0.0, math.inf, low_open=True)
    decay = float_in(decay, "decay", 0.0, 1.0, low_open=True)
    tol = float_in(tol, "tol", 0.0, math.inf)
    bary = _best_start(sdf, tri)
    scale = mean_edge_length(tri)
    # A triangle with no extent has one point: leave it where it started.
    inv_scale = torch.where(scale > 0, 1.0 / scale.clamp_min(torch.finfo(tri.dtype).tiny), torch.zeros_like(scale))
    active = torch.ones(tri.shape[0], dtype=torch.bool, device=tri.device)
    step_k, ran = step, 0
    for _ in range(iters):
        idx = active.nonzero().squeeze(-1)
        if idx.numel() == 0:
            break
        ran += 1
        t, b = tri[idx], bary[idx]
        _, g = _value_and_grad(sdf, t, b)
        slope = _vertex_scores(t - bary_to_points(t, b).unsqueeze(1), _unit(g))
        new = project_to_simplex(b - step_k * inv_scale[idx].unsqueeze(-1) * slope)
        bary = bary.index_copy(0, idx, new)
        active = active.index_copy(0, idx, (new - b).square().sum(dim=-1) >= tol)
        step_k *= decay
    return (bary, ran) if return_iterations else bary


def reference(sdf, triangles, resolution: int = 32, polish_iters: int = 100, chunk_points: int = 1 << 20) -> torch.Tensor:
    """The global minimum on each triangle, slowly and surely: the yardstick for the other solvers.

    1. Evaluate f on a dense barycentric grid (every (i, j, k) / resolution with i + j + k =
       resolution: the vertices, points along the edges and inside the face), chunked so that at
       most ``chunk_points`` points are in memory at once, and keep the best grid point. A grid
       this fine sees every basin of a non-convex SDF (a torus) that is wider than a grid cell.
    2. Polish it with a pattern search that uses values only: try the 6 moves along the edge
       directions e_i - e_j, each shortened so as to stop on the boundary; move to the best
       candidate if it is strictly lower, else halve the step. The edge directions generate the
       simplex's tangent cone at every point, so this converges to a vertex, edge or face minimum
       alike, and the value never increases. Run it in float64 for position errors far below the
       float32 solvers'.

    Args:
        sdf: any SDF (only ``sdf(points)`` is called).
        triangles: (M, 3, 3).
        resolution: grid subdivisions per edge (>= 1); (resolution+1)(resolution+2)/2 points per triangle.
        polish_iters: pattern-search iterations (>= 0); stops early once steps fall below rounding.
        chunk_points: most points evaluated in one call of ``sdf``.

    Returns:
        (M, 3) barycentric coordinates.
    """
    tri = _prepare(sdf, triangles)
    resolution = non_negative_int(resolution, "resolution")
    if resolution < 1:
        raise InputError("resolution must be at least 1 (grid subdivisions per edge); 32 is a good default")
    polish_iters = non_negative_int(polish_iters, "polish_iters")
    chunk_points = non_negative_int(chunk_points, "chunk_points")
    grid = barycentric_grid(resolution, dtype=tri.dtype, device=tri.device)
    per_chunk = max(1, chunk_points // grid.shape[0])
    out = [tri.new_zeros((0, 3))]  # the answer when there are no triangles
    for start in range(0, tri.shape[0], per_chunk):
        t = tri[start : start + per_chunk]
        bary, f = _grid_minimum(sdf, t, grid)
        out.append(_pattern_search(sdf, t, bary, f, 1.0 / resolution, polish_iters))
    return torch.cat(out)


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------


def optimality(sdf, triangles, bary) -> torch.Tensor:
    """Equation (12): grad f(p)^T (p - v_min) / perimeter, v_min the vertex minimising grad f(p)^T v.

    This is the Frank-Wolfe duality gap scaled by the triangle's size: 0 at a KKT point, > 0
    elsewhere. It is computed as sum_i bary_i * g . (v_i - v_min), a sum of non-negative terms, so
    rounding can never make it negative; a triangle with zero perimeter gives 0 (one point, optimal).

    Args:
        sdf: any SDF.
        triangles: (M, 3, 3).
        bary: (M, 3) barycentric coordinates.

    Returns:
        (M,) non-negative, the dtype of ``triangles``.
    """
    tri = _prepare(sdf, triangles)
    b = as_simplex(bary, tri, "bary")
    _, g = _value_and_grad(sdf, tri, b)
    scores = _vertex_scores(tri, g)  # (M, 3): g . v_i
    v_min = tri.gather(1, scores.argmin(dim=-1).view(-1, 1, 1).expand(-1, 1, 3))  # (M, 1, 3)
    # g . (v_i - v_min) from edge vectors rather than differences of large dot products: exact 0 for
    # coincident vertices and accurate for tiny triangles far from the origin.
    gaps = _vertex_scores(tri - v_min, g).clamp_min(0)
    gap = (b * gaps).sum(dim=-1)
    per = perimeter(tri)
    return torch.where(per > 0, gap / per.clamp_min(torch.finfo(tri.dtype).tiny), torch.zeros_like(gap))


def nme(bary, ref_bary, triangles) -> torch.Tensor:
    """Normalised mean error: |p - p_ref| / mean edge length, per triangle.

    Args:
        bary: (M, 3) the answer judged.
        ref_bary: (M, 3) the reference answer.
        triangles: (M, 3, 3).

    Returns:
        (M,); 0 for a triangle with no extent.
    """
    tri = as_triangles(triangles)
    p = bary_to_points(tri, as_simplex(bary, tri, "bary"))
    q = bary_to_points(tri, as_simplex(ref_bary, tri, "ref_bary"))
    err = (p - q).norm(dim=-1)
    scale = mean_edge_length(tri)
    return torch.where(scale > 0, err / scale.clamp_min(torch.finfo(tri.dtype).tiny), torch.zeros_like(err))


def minimum_location(bary, tol: float = 1e-4) -> torch.Tensor:
    """Where on the triangle each point lies: 0 (VERTEX), 1 (EDGE) or 2 (FACE interior).

    A coordinate counts as non-zero when it exceeds ``tol``.

    Args:
        bary: (M, 3) barycentric coordinates.
        tol: threshold in [0, 1/3).

    Returns:
        (M,) int64.
    """
    b = as_rows(bary, "bary")
    if b.ndim != 2 or b.shape[-1] != 3:
        raise InputError(f"bary must have shape (M, 3), got {tuple(b.shape)}")
    tol = float_in(tol, "tol", 0.0, 1.0 / 3.0, high_open=True)
    return ((b > tol).sum(dim=-1) - 1).clamp(VERTEX, FACE)


# --------------------------------------------------------------------------------------------
# Simplex helpers
# --------------------------------------------------------------------------------------------


def project_to_simplex(x) -> torch.Tensor:
    """Euclidean projection of each row onto the probability simplex (sort-based, Duchi et al. 2008).

    Args:
        x: (..., n) finite values.

    Returns:
        (..., n) non-negative rows summing to 1, the dtype of ``x``.
    """
    x = as_rows(x, "x")
    n = x.shape[-1]
    u = x.sort(dim=-1, descending=True).values
    css = u.cumsum(dim=-1) - 1.0
    k = torch.arange(1, n + 1, dtype=x.dtype, device=x.device)
    # The support is the longest prefix of the sorted values that stays positive after the shift;
    # the first entry always qualifies, so rho >= 1.
    rho = (u - css / k > 0).sum(dim=-1, keepdim=True).clamp_min(1)
    theta = css.gather(-1, rho - 1) / rho.to(x.dtype)
    return (x - theta).clamp_min(0)


# --------------------------------------------------------------------------------------------
# Internals
# --------------------------------------------------------------------------------------------


def _prepare(sdf, triangles) -> torch.Tensor:
    """Validated triangles (M, 3, 3); M = 0 is normal (a simulation step with nothing near) and gives empty answers."""
    check_sdf(sdf)
    return as_triangles(triangles, allow_empty=True)


def _value_and_grad(sdf, tri: torch.Tensor, bary: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """f and grad f at the points of ``bary`` (M, 3) on ``tri`` (M, 3, 3): (M,), (M, 3)."""
    p = bary_to_points(tri, bary)
    if p.shape[0] == 0:  # no triangles: nothing to ask the SDF (which refuses empty points)
        return p.new_zeros((0,)), p.new_zeros((0, 3))
    f, g = sdf.value_and_grad(p)
    f, g = torch.as_tensor(f), torch.as_tensor(g)
    if f.shape != p.shape[:1] or g.shape != p.shape:
        raise InputError(
            f"{type(sdf).__name__}.value_and_grad on points {tuple(p.shape)} returned shapes "
            f"{tuple(f.shape)} and {tuple(g.shape)}; it must return (N,) and (N, 3)"
        )
    return f.to(tri), g.to(tri)


def _values(sdf, tri: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """f at the points of ``bary`` (..., 3) on ``tri`` (M, 3, 3), bary either (M, 3) or (M, K, 3): (M,) or (M, K)."""
    if bary.ndim == 2:
        p = bary_to_points(tri, bary)
    else:
        p = torch.einsum("mkv,mvc->mkc", bary, tri)
    if p.numel() == 0:  # no triangles: nothing to ask the SDF (which refuses empty points)
        return p.new_zeros(p.shape[:-1])
    f = torch.as_tensor(sdf(p.reshape(-1, 3)))
    if f.numel() != p.numel() // 3:
        raise InputError(f"{type(sdf).__name__} on points ({p.numel() // 3}, 3) returned shape {tuple(f.shape)}; it must return (N,)")
    return f.to(tri).reshape(p.shape[:-1])


def _vertex_scores(tri: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """g . v_i for each vertex: (M, 3, 3), (M, 3) -> (M, 3)."""
    return torch.einsum("mvc,mc->mv", tri, g)


def _one_hot(index: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(M,) vertex indices -> (M, 3) rows of the identity, dtype of ``like``."""
    return torch.nn.functional.one_hot(index, 3).to(like)


def _unit(g: torch.Tensor) -> torch.Tensor:
    """Rows of g (M, 3) scaled to length 1; a zero row (a medial point) stays zero: no direction, no step."""
    n = g.norm(dim=-1, keepdim=True)
    return torch.where(n > 0, g / n.clamp_min(torch.finfo(g.dtype).tiny), torch.zeros_like(g))


def _keep_lower(best_bary, best_f, bary, f):
    """Per triangle, the lower of (best_bary, best_f) and (bary, f); strict, so ties keep the old one."""
    if best_f is None:
        return bary, f
    lower = f < best_f
    return torch.where(lower.unsqueeze(-1), bary, best_bary), torch.where(lower, f, best_f)


def _centroid_bary(tri: torch.Tensor) -> torch.Tensor:
    return torch.full(tri.shape[:2], 1.0 / 3.0, dtype=tri.dtype, device=tri.device)


def _best_start(sdf, tri: torch.Tensor) -> torch.Tensor:
    """PhysX's start: the best of the centroid and the three vertices (ties favour the centroid): (M, 3)."""
    candidates = torch.cat([_centroid_bary(tri)[:1], torch.eye(3, dtype=tri.dtype, device=tri.device)])  # (4, 3)
    cand = candidates.unsqueeze(0).expand(tri.shape[0], -1, -1)
    f = _values(sdf, tri, cand)  # (M, 4)
    return cand.gather(1, f.argmin(dim=-1).view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)


def _grid_minimum(sdf, tri: torch.Tensor, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Best grid point per triangle: (M, 3, 3), (G, 3) -> bary (M, 3), f (M,)."""
    f = _values(sdf, tri, grid.unsqueeze(0).expand(tri.shape[0], -1, -1))  # (M, G)
    f_min, arg = f.min(dim=-1)
    return grid[arg], f_min


# Moves e_i - e_j for the 6 ordered pairs i != j, and the coordinate j each one decreases.
_MOVE_PAIRS = [(i, j) for i in range(3) for j in range(3) if i != j]


def _pattern_search(sdf, tri, bary, f, spacing: float, iters: int) -> torch.Tensor:
    """Compass search on the simplex from ``bary`` (M, 3) with values ``f`` (M,); returns (M, 3)."""
    eye = torch.eye(3, dtype=tri.dtype)
    dirs = torch.stack([eye[i] - eye[j] for i, j in _MOVE_PAIRS]).to(tri.device)  # (6, 3)
    shrinks = torch.tensor([j for _, j in _MOVE_PAIRS], device=tri.device)
    h = torch.full(f.shape, spacing, dtype=tri.dtype, device=tri.device)
    floor = 4 * torch.finfo(tri.dtype).eps  # below this a move no longer changes a coordinate
    rows = torch.arange(tri.shape[0], device=tri.device)
    for _ in range(iters):
        if bool((h < floor).all()):
            break
        # Shorten each move so the coordinate it decreases stops at exactly 0: the boundary is reachable.
        t = torch.minimum(h.unsqueeze(-1), bary[:, shrinks])  # (M, 6)
        cand = (bary.unsqueeze(1) + t.unsqueeze(-1) * dirs).clamp_min(0)  # (M, 6, 3)
        f_cand, arg = _values(sdf, tri, cand).min(dim=-1)
        better = f_cand < f
        bary = torch.where(better.unsqueeze(-1), cand[rows, arg], bary)
        f = torch.where(better, f_cand, f)
        h = torch.where(better, h, h / 2)
    return bary
