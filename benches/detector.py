"""Error against run time of the amortized detector and its baselines (issue 4 item 4).

Methods, each on the same triangles, timed in the same run:

* ``amortized``: one forward pass of the detector (features at the vertices + network);
* ``amortized+fw{k}``: k Frank-Wolfe steps warm-started from the amortized answer;
* ``fw{k}``: NeuralSDF + Frank-Wolfe from the centroid (MuJoCo's rule), k iterations;
* ``pgd``: projected gradient (PhysX's rule);
* ``vertex+ls``: the polish from the best vertex (what the line search does without the network);
  ``vertex+ls1``: the same with one line-search step;
* ``midpoint-quadratic``: the curvature head's model with exact curvatures, from six SDF values
  per triangle (vertices and edge midpoints): the best any curvature head's forward pass can do;
* ``voxel{r}+fw{k}``: the NeuralSDF sampled on an r^3 grid (zoo.VoxelSDF), then Frank-Wolfe
  on the grid; its answer is judged on the NeuralSDF;
* ``interpolant-p{k}`` (no timing): the minimum of the degree-k polynomial that matches the SDF at the
  triangle's (k+1)(k+2)/2 Lagrange nodes (:func:`interpolant_minimum`): the ceiling of any forward pass
  that models the SDF over the triangle as a degree-k polynomial, however well it predicts one;
* ``reference moved {eps}`` (no timing): the global reference with each off-vertex minimum moved by
  eps x the triangle's mean edge length (:func:`moved_reference`): how precisely an answer must place
  those minima to reach a given mean optimality, whatever method it comes from.

Metrics per method (all scale-free, computed in the normalised frame, where every shape is
compared on the same footing): optimality (equation (12), p50 / p90 / mean), NME against the
global reference (``zoo.solvers.reference``: p50 / p90 / mean, and the mean on the subset whose
reference minimum lies on an edge or inside the face), and time per triangle (median over
``repeats`` of a batch of ``timing_batch`` triangles).

Tables: Table I analog (FW iterations and time needed to reach the amortized model's mean
optimality, and the speed-up), Table III (seen vs unseen shapes), Table IV (ablation variants).
Results are written as ``bench_detector.json`` and a Pareto plot ``bench_detector.png``.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from zoo.amortized import detect
from zoo.errors import InputError
from zoo.files import atomic_path, atomic_write_text
from zoo.geometry import bary_to_points, edge_lengths

from .solvers import machine_info, steady_allocator

JSON_NAME = "bench_detector.json"
# the detector as zoo's detect() runs it by default: the vertex test, then the forward pass and line-search steps
POLISHED = "amortized+ls"
AMORTIZED_METHODS = ("amortized", POLISHED)
# the lowest of the three vertices, nothing else: what a mean metric must fail (most minima are at a vertex)
BEST_VERTEX = "best-vertex"
# the same polish from the best vertex: what the polish does without the network
VERTEX_POLISHED = "vertex+ls"
# ... with one line-search step instead of POLISH_ROUNDS
VERTEX_POLISHED_ONCE = "vertex+ls1"
# the curvature head's model with exact curvatures (three more values per triangle): what no curvature head can beat
MIDPOINT_QUADRATIC = "midpoint-quadratic"
# exact polynomial models of higher degree (10 and 15 values per triangle): how far a richer head's model class could go
INTERPOLANT = "interpolant-p{}"
INTERPOLANT_DEGREES = (3, 4)
PNG_NAME = "bench_detector.png"


@dataclass(frozen=True)
class BenchConfig:
    n_per_shape: int = 500  # metric triangles per shape (each gets the global reference)
    seed: int = 20261122  # differs from the training data's seeds: an independent draw
    fw_iters: tuple[int, ...] = (1, 2, 3, 5, 8, 11, 15, 20, 30, 50, 100)
    refine_iters: tuple[int, ...] = (1, 2, 5)
    voxel_resolutions: tuple[int, ...] = (64, 128, 256)
    voxel_fw_iters: int = 50  # the paper's VoxelSDF+FW iteration limit
    voxel_shapes: int = 1  # grids are built for this many seen shapes (256^3 NeuralSDF queries each)
    timing_batch: int = 10_000
    repeats: int = 3
    max_timed_fw_iters: int = 30  # longer FW runs are timed as (per-iteration time x k), marked so
    reference_resolution: int = 32
    interpolant_degrees: tuple[int, ...] = INTERPOLANT_DEGREES  # the interpolant-p{k} ceiling rows (no timing)
    threads: int | None = None

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


QUICK = BenchConfig(n_per_shape=100, fw_iters=(1, 2, 5, 11, 20), refine_iters=(1, 2), voxel_resolutions=(32,),
                    timing_batch=2000, repeats=2, max_timed_fw_iters=20, reference_resolution=16)


# --------------------------------------------------------------------------- triangles


def bench_triangles(shapes, config: BenchConfig, sampler=None) -> list[torch.Tensor]:
    """Per shape, ``n_per_shape`` fresh triangles (normalised frame) under the paper's four conditions."""
    if sampler is None:
        from sdfzoo.pipeline.triangle_sampling import sample_constrained_triangles as sampler
    return [torch.as_tensor(sampler(s.normalised, config.n_per_shape, seed=bench_seed(config.seed, i), batch=16384)).float()
            for i, s in enumerate(shapes)]


def bench_seed(seed: int, index: int) -> int:
    """The seed of the ``index``-th bench shape's triangles (by position: the bench's shape lists are fixed)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


# --------------------------------------------------------------------------- metrics


def reference_minimum(sdf, triangles: torch.Tensor, ref_bary: torch.Tensor) -> torch.Tensor:
    """The SDF (M,) at the reference minima ``ref_bary`` (M, 3) of ``triangles`` (M, 3, 3): how close each comes to the
    surface. Taken once per split and shape, shared by every method's :func:`quality`."""
    with torch.no_grad():
        return torch.as_tensor(sdf(bary_to_points(triangles, ref_bary))).reshape(-1).float()


def quality(sdf, triangles: torch.Tensor, bary: torch.Tensor, ref_bary: torch.Tensor,
            ref_min: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per triangle: optimality (M,), NME (M,), whether the reference minimum is off the vertices (M,) bool,
    and ``ref_min`` (M,), the SDF at the reference minimum (:func:`reference_minimum`)."""
    from zoo.solvers import EDGE, minimum_location, nme, optimality

    return {
        "optimality": optimality(sdf, triangles, bary).float(),
        "nme": nme(bary.double(), ref_bary.double(), triangles.double()).float(),
        "off_vertex": minimum_location(ref_bary) >= EDGE,
        "reference_min": ref_min,
    }


# Bands of the reference minimum (normalised frame; the training triangles' centroids lie 0-0.1 from the
# surface): where a method's mean optimality comes from, near-touching triangles or those farther out.
MINIMUM_BANDS = (0.0, 0.005, 0.02, 0.05)
WORST_FRACTION = 0.05


def worst_share(values: torch.Tensor, fraction: float = WORST_FRACTION) -> float:
    """The share of ``values``' sum (M,) held by its largest ``fraction`` of entries (at least one)."""
    total = float(values.sum())
    if total <= 0:
        return 0.0
    k = max(1, int(math.ceil(fraction * values.numel())))
    return float(values.topk(k).values.sum()) / total


def by_minimum_band(optimality: torch.Tensor, reference_min: torch.Tensor, bands=MINIMUM_BANDS) -> dict:
    """{band label: {"fraction": share of the triangles, "mean": their mean optimality, "share": their part
    of the total}} for the bands of the reference minimum [b_k, b_k+1) (the last one open above)."""
    total = float(optimality.sum())
    edges = list(bands) + [math.inf]
    out = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (reference_min >= lo) & (reference_min < hi)
        n = int(inside.sum())
        label = f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">={lo:g}"
        out[label] = {"fraction": n / max(1, optimality.numel()),
                      "mean": float(optimality[inside].mean()) if n else None,
                      "share": float(optimality[inside].sum()) / total if n and total > 0 else 0.0}
    return out


def summarise(per_triangle: dict[str, torch.Tensor]) -> dict:
    o, e, off = per_triangle["optimality"], per_triangle["nme"], per_triangle["off_vertex"]
    return {
        "optimality_p50": float(o.median()), "optimality_p90": float(o.quantile(0.9)), "optimality_mean": float(o.mean()),
        "nme_p50": float(e.median()), "nme_p90": float(e.quantile(0.9)), "nme_mean": float(e.mean()),
        "nme_mean_edge_or_face": float(e[off].mean()) if bool(off.any()) else None,
        "fraction_edge_or_face": float(off.float().mean()),
        "optimality_worst5_share": worst_share(o),
        "optimality_by_reference_minimum": by_minimum_band(o, per_triangle["reference_min"]),
        "n": int(o.numel()),
    }


def _concat(parts: list[dict]) -> dict:
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


# --------------------------------------------------------------------------- timing


def median_seconds(fn, repeats: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs, after one untimed warm-up."""
    fn()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


# Copies of the bench triangles in a timing batch are shifted by this much per copy (normalised frame).
_COPY_SHIFT = 1e-5


def timing_batch(triangles: torch.Tensor, n: int) -> torch.Tensor:
    """``n`` triangles (n, 3, 3): the given ones repeated as needed, each copy shifted by a further
    ``_COPY_SHIFT``. The shift keeps every vertex distinct: detect() evaluates each distinct vertex
    once, so exact copies would time it on a fraction of the vertices FW pays for."""
    reps = -(-n // triangles.shape[0])
    shift = _COPY_SHIFT * torch.arange(reps, dtype=triangles.dtype, device=triangles.device).repeat_interleave(triangles.shape[0])
    return (triangles.repeat(reps, 1, 1) + shift[:, None, None])[:n]


# --------------------------------------------------------------------------- the methods


class NormalisedView:
    """A fitted shape seen from its normalised frame: what detect() needs, with the identity similarity."""

    similarity = None

    def __init__(self, shape):
        self.normalised = shape.normalised
        self.features = shape.features


def method_table(detector, config: BenchConfig) -> dict:
    """{name: solve(view, sdf, triangles) -> bary}: ``view`` a NormalisedView, ``sdf`` the normalised SDF."""
    from zoo.solvers import frank_wolfe, projected_gradient

    methods = {}
    if detector is not None:
        methods["amortized"] = lambda shape, sdf, tri: detect(detector, shape, tri, polish=False)
        methods[POLISHED] = lambda shape, sdf, tri: detect(detector, shape, tri, polish=True)
        for k in config.refine_iters:
            methods[f"amortized+fw{k}"] = lambda shape, sdf, tri, k=k: frank_wolfe(
                sdf, tri, iters=k, init=detect(detector, shape, tri, polish=False))
    for k in config.fw_iters:
        methods[f"fw{k}"] = lambda shape, sdf, tri, k=k: frank_wolfe(sdf, tri, iters=k)
    methods["pgd"] = lambda shape, sdf, tri: projected_gradient(sdf, tri)
    methods[BEST_VERTEX] = lambda shape, sdf, tri: best_vertex(sdf, tri)
    methods[VERTEX_POLISHED] = lambda shape, sdf, tri: polished_best_vertex(sdf, tri)
    methods[VERTEX_POLISHED_ONCE] = lambda shape, sdf, tri: polished_best_vertex(sdf, tri, rounds=1)
    methods[MIDPOINT_QUADRATIC] = lambda shape, sdf, tri: midpoint_quadratic(sdf, tri)
    return methods


def midpoint_quadratic(sdf, triangles: torch.Tensor) -> torch.Tensor:
    """The ceiling of the curvature head's model: the exact minimum of the quadratic that matches the SDF at
    the three vertices and the three edge midpoints (six value queries per triangle, no network)."""
    from sdfzoo.pipeline.train_detector import midpoint_curvatures
    from zoo.detector import quadratic_argmin
    from zoo.solvers import vertex_values

    return quadratic_argmin(vertex_values(sdf, triangles), midpoint_curvatures(sdf, triangles).clamp_min(0))


def best_vertex(sdf, triangles: torch.Tensor) -> torch.Tensor:
    """The lowest vertex of each triangle as barycentrics (M, 3): three value queries per triangle."""
    from zoo.solvers import vertex_values

    return torch.nn.functional.one_hot(vertex_values(sdf, triangles).argmin(dim=-1), 3).to(triangles)


def polished_best_vertex(sdf, triangles: torch.Tensor, rounds: int | None = None) -> torch.Tensor:
    """The baseline that isolates the network's part in ``amortized+ls``: the same polish (the vertex test,
    then ``rounds`` line-search steps, default ``POLISH_ROUNDS``) from the lowest vertex instead of the network's answer."""
    from zoo.amortized import POLISH_LINE_STEPS, POLISH_ROUNDS
    from zoo.solvers import line_search_steps, vertex_values

    rounds = POLISH_ROUNDS if rounds is None else rounds

    values = vertex_values(sdf, triangles)
    vertex = torch.nn.functional.one_hot(values.argmin(dim=-1), 3).to(triangles)
    f, g = sdf.value_and_grad(bary_to_points(triangles, vertex))
    f, g = torch.as_tensor(f).reshape(-1).to(triangles), torch.as_tensor(g).to(triangles)
    return line_search_steps(sdf, triangles, vertex, values, rounds, line_steps=POLISH_LINE_STEPS, start=(f, g),
                             fallback=(vertex, f, g))


def _monomials(bary: torch.Tensor, degree: int) -> torch.Tensor:
    """The monomials b1^a b2^c (a + c <= degree) at barycentrics (..., 3) -> (..., (k+1)(k+2)/2)."""
    u, v = bary[..., 1], bary[..., 2]
    return torch.stack([u**a * v**c for a in range(degree + 1) for c in range(degree + 1 - a)], dim=-1)


def interpolant_minimum(sdf, triangles: torch.Tensor, degree: int, grid_level: int = 240, chunk: int = 64) -> torch.Tensor:
    """The minimum of the degree-``degree`` polynomial that equals ``sdf`` at each triangle's Lagrange nodes (the
    (k+1)(k+2)/2 points of ``zoo.geometry.barycentric_grid(k)``), found on
    the barycentric grid of ``grid_level``: triangles (M, 3, 3) -> bary (M, 3), in their dtype.

    The ceiling of a forward pass that models the SDF over the triangle by such a polynomial: it is given the exact
    values a network would have to predict. Grid spacing 1/``grid_level`` of the triangle (0.4% at the default: an
    order below the placement the bench's tolerance rows show matters).
    """
    from zoo.geometry import barycentric_grid

    nodes = barycentric_grid(degree, torch.float64)
    to_coefficients = torch.linalg.inv(_monomials(nodes, degree))  # (N, N): node values -> monomial coefficients
    grid = barycentric_grid(grid_level, torch.float64)  # (Q, 3)
    at_grid = _monomials(grid, degree)  # (Q, N)
    out = []
    with torch.no_grad():
        for tri in triangles.double().split(chunk):
            points = torch.einsum("nv,mvc->mnc", nodes, tri).reshape(-1, 3)
            values = torch.as_tensor(sdf(points)).double().reshape(tri.shape[0], -1)  # (m, N)
            model = (values @ to_coefficients.T) @ at_grid.T  # (m, Q)
            out.append(grid[model.argmin(dim=-1)])
    return torch.cat(out).to(triangles.dtype)


# Placement tolerance rows: the reference minimum moved by these fractions of the triangle's mean edge length
# (vertex minima left exact), to read off how precisely an answer must place the off-vertex minima to reach a
# mean optimality (the paper's 7.8e-4 needs about 2% on mugs@1.3.0).
TOLERANCES = (0.003, 0.01, 0.03, 0.1)
MOVED = "reference moved {:g}"


def moved_reference(triangles: torch.Tensor, ref_bary: torch.Tensor, fraction: float, generator: torch.Generator) -> torch.Tensor:
    """The reference minima ``ref_bary`` (M, 3) of ``triangles`` (M, 3, 3), each off-vertex one moved by ``fraction`` x the
    triangle's mean edge length in a random direction, along its edge for a minimum on an edge, then put back on the
    triangle (the move is shorter where that clips it); a minimum at a vertex stays. -> (M, 3), rows on the simplex."""
    from zoo.solvers import project_to_simplex

    tri, ref = triangles.double(), ref_bary.double()
    zero = ref <= 1e-9  # barycentrics at 0: the minimum's edge (one zero) or vertex (two)
    at_vertex = zero.sum(-1) >= 2
    on_edge = zero.sum(-1) == 1
    direction = torch.randn(ref.shape, generator=generator, dtype=ref.dtype)
    free = ~(on_edge[:, None] & zero)  # an edge minimum moves along its edge only
    direction = direction * free
    direction = direction - (direction.sum(-1, keepdim=True) / free.sum(-1, keepdim=True)) * free  # sums to 0: in the plane
    length = torch.einsum("mv,mvc->mc", direction, tri).norm(dim=-1).clamp_min(1e-30)
    moved = ref + direction * (fraction * edge_lengths(tri).mean(-1) / length)[:, None]
    moved = project_to_simplex(moved) * free  # the projection's rounding would lift an edge minimum's zero
    moved = moved / moved.sum(-1, keepdim=True)
    return torch.where(at_vertex[:, None], ref, moved).to(ref_bary.dtype)


def run_split(detector, shapes, triangles, config: BenchConfig, voxels: dict | None = None, progress=None) -> dict:
    """Quality of every method on one split (shapes with their bench triangles): {method: summary}."""
    from zoo.solvers import frank_wolfe, reference

    methods = method_table(detector, config)
    per_method: dict[str, list] = {m: [] for m in methods}
    for i, (shape, tri) in enumerate(zip(shapes, triangles)):
        view = NormalisedView(shape)
        shape_n = view.normalised
        ref = reference(shape_n, tri.double(), resolution=config.reference_resolution).float()
        # the yardstick's own KKT gap: what no solver can beat on this SDF (0 for a C1 one)
        ref_min = reference_minimum(shape_n, tri, ref)
        per_method.setdefault("reference", []).append(quality(shape_n, tri, ref, ref, ref_min))
        generator = torch.Generator().manual_seed(config.seed + i)
        for fraction in TOLERANCES:
            moved = moved_reference(tri, ref, fraction, generator)
            per_method.setdefault(MOVED.format(fraction), []).append(quality(shape_n, tri, moved, ref, ref_min))
        for degree in config.interpolant_degrees:
            bary = interpolant_minimum(shape_n, tri, degree)
            per_method.setdefault(INTERPOLANT.format(degree), []).append(quality(shape_n, tri, bary, ref, ref_min))
        for name, solve in methods.items():
            per_method[name].append(quality(shape_n, tri, solve(view, shape_n, tri), ref, ref_min))
            if progress:
                progress()
        for r, grids in (voxels or {}).items():
            if i >= len(grids):
                continue
            bary = frank_wolfe(grids[i], tri, iters=config.voxel_fw_iters)
            per_method.setdefault(f"voxel{r}+fw{config.voxel_fw_iters}", []).append(quality(shape_n, tri, bary, ref, ref_min))
    return {name: summarise(_concat(parts)) for name, parts in per_method.items()}


def run_timings(detector, shape, triangles: torch.Tensor, config: BenchConfig, voxel_grids: dict | None = None) -> dict:
    """Seconds per triangle of each method on one batch of ``timing_batch`` triangles of one shape."""
    from zoo.solvers import frank_wolfe

    view = NormalisedView(shape)
    shape_n = view.normalised
    batch = timing_batch(triangles, config.timing_batch)
    out = {}
    with torch.no_grad():
        for name, solve in method_table(detector, config).items():
            k = int(name[2:]) if name.startswith("fw") else None
            if k is not None and k > config.max_timed_fw_iters:
                continue
            out[name] = {"seconds_per_triangle": median_seconds(partial(solve, view, shape_n, batch), config.repeats) / len(batch),
                         "measured": True}
        per_iter = _fw_seconds_per_iteration(out)
        for k in config.fw_iters:
            if k > config.max_timed_fw_iters:
                out[f"fw{k}"] = {"seconds_per_triangle": per_iter * k, "measured": False}
        for r, grid in (voxel_grids or {}).items():
            name = f"voxel{r}+fw{config.voxel_fw_iters}"
            secs = median_seconds(partial(frank_wolfe, grid, batch, iters=config.voxel_fw_iters), config.repeats)
            out[name] = {"seconds_per_triangle": secs / len(batch), "measured": True, "memory_bytes": int(grid.memory_bytes)}
    return out


def _fw_seconds_per_iteration(timings: dict) -> float:
    """Slope of measured FW time per triangle against iterations (least squares through the measured points)."""
    pts = [(int(n[2:]), t["seconds_per_triangle"]) for n, t in timings.items() if n.startswith("fw") and t["measured"]]
    if not pts:
        return float("nan")
    ks = torch.tensor([p[0] for p in pts], dtype=torch.float64)
    ts = torch.tensor([p[1] for p in pts], dtype=torch.float64)
    if len(pts) == 1:
        return float(ts[0] / ks[0])
    a = torch.stack([ks, torch.ones_like(ks)], -1)
    slope = torch.linalg.lstsq(a, ts.unsqueeze(-1)).solution[0, 0]
    return float(slope)


# --------------------------------------------------------------------------- tables


def table_one(split: dict, timings: dict, fw_limit: int = 50, method: str = "amortized") -> dict:
    """FW iterations and time to reach ``method``'s mean optimality, and the speed-up."""
    if method not in split:
        return {}
    target = split[method]["optimality_mean"]
    fw = sorted((int(n[2:]), s) for n, s in split.items() if n.startswith("fw"))
    reached = [(k, s) for k, s in fw if s["optimality_mean"] <= target]
    if reached:
        k, _ = reached[0]
        note = "first FW iteration count whose mean optimality is at most the amortized one"
    else:
        k = max((kk for kk, _ in fw if kk <= fw_limit), default=fw[-1][0])
        note = f"FW did not reach it within the measured iterations; FW-{k}'s time is the comparison"
    t_amortized = timings[method]["seconds_per_triangle"]
    t_fw = timings[f"fw{k}"]["seconds_per_triangle"]
    return {
        "amortized_optimality_mean": target,
        "amortized_ms_per_triangle": 1e3 * t_amortized,
        "fw_iterations": k,
        "fw_reached": bool(reached),
        "fw_ms_per_triangle": 1e3 * t_fw,
        "speedup": t_fw / t_amortized,
        "note": note,
    }


# The manifest's names of the two amortized rows (a release records both).
RELEASE_NAMES = {"amortized": "one_pass", POLISHED: "polished"}


def release_metrics(report: dict) -> dict:
    """The detector's headline numbers from a bench report, flat, as a release's manifest stores them
    (``zoo package --metrics``): per split and amortized row, mean optimality and NME, and the FW
    iterations to the same mean with the speed-up over them (Table I); per row, ms per triangle."""
    out = {}
    for method, label in RELEASE_NAMES.items():
        if method in report["timings"]:
            out[f"detector_{label}_ms_per_triangle"] = 1e3 * report["timings"][method]["seconds_per_triangle"]
        for split, rows in report["splits"].items():
            if method not in rows:
                continue
            key = f"detector_{split}_{label}"
            out[f"{key}_optimality_mean"] = rows[method]["optimality_mean"]
            out[f"{key}_nme_mean"] = rows[method]["nme_mean"]
            table = report.get("table_1", {}).get(split, {}).get(method)
            if table:
                out[f"{key}_fw_iterations_same_optimality"] = table["fw_iterations"]
                out[f"{key}_speedup_vs_fw_same_optimality"] = table["speedup"]
    return out


def ablation_table(variants: dict, shapes, triangles, config: BenchConfig) -> dict:
    """Table IV: {variant: optimality and NME summary} for detectors trained without a component;
    each variant twice: its one-pass answer (``name``) and polished by the line search (``name+ls``)."""
    from zoo.solvers import reference

    refs = [reference(s.normalised, t.double(), resolution=config.reference_resolution).float() for s, t in zip(shapes, triangles)]
    ref_mins = [reference_minimum(s.normalised, t, r) for s, t, r in zip(shapes, triangles, refs)]
    out = {}
    for name, det in variants.items():
        for suffix, polish in (("", False), ("+ls", True)):  # the forward pass alone, then as detect() runs it
            parts = [quality(s.normalised, t, detect(det, NormalisedView(s), t, polish=polish), r, rm)
                     for s, t, r, rm in zip(shapes, triangles, refs, ref_mins)]
            out[name + suffix] = summarise(_concat(parts))
    return out


# --------------------------------------------------------------------------- the whole benchmark


def run_detector_benchmark(detector, seen_shapes, unseen_shapes=(), out_dir="bench-results", config: BenchConfig = BenchConfig(),
                           ablations: dict | None = None, label: str = "", progress: bool = True, log=print) -> Path:
    """Measure every method on seen (and unseen) shapes; write JSON and the Pareto PNG; return the JSON path.

    ``seen_shapes`` / ``unseen_shapes``: lists of fitted shapes (NeuralShape or anything with
    ``normalised`` and ``features``); ``detector``: an AmortizedDetector (or None for baselines
    only); ``ablations``: optional {variant name: AmortizedDetector} for Table IV.
    """
    if not seen_shapes:
        raise InputError("no shapes to benchmark; pass the model's fitted train shapes (model.shape(stem))")
    if config.threads:
        torch.set_num_threads(int(config.threads))
    steady_allocator()
    t_start = time.perf_counter()
    seen_tri = bench_triangles(seen_shapes, config)
    unseen_tri = bench_triangles(list(unseen_shapes), config) if unseen_shapes else []
    log(f"bench triangles: {sum(len(t) for t in seen_tri)} seen, {sum(len(t) for t in unseen_tri)} unseen")
    voxels = build_voxels(seen_shapes, config)
    splits = {"seen": run_split(detector, seen_shapes, seen_tri, config, voxels)}
    log("seen split done")
    if unseen_shapes:
        splits["unseen"] = run_split(detector, list(unseen_shapes), unseen_tri, config)
        log("unseen split done")
    first = {r: grids[0] for r, grids in voxels.items()}
    timings = run_timings(detector, seen_shapes[0], seen_tri[0], config, first)
    log("timings done")
    report = {
        "label": label,
        "config": config.to_dict(),
        "machine": machine_info(),
        "splits": splits,
        "timings": timings,
        "table_1": {name: {m: table_one(split, timings, method=m) for m in AMORTIZED_METHODS if m in split}
                    for name, split in splits.items()},
        "table_3": {name: {m: {k: split[m][k] for k in ("optimality_mean", "nme_mean")} for m in AMORTIZED_METHODS if m in split}
                    for name, split in splits.items()},
        "table_4": ablation_table(ablations, seen_shapes, seen_tri, config) if ablations else {},
        "detector": detector.config() if detector is not None else None,
        "seconds": None,
    }
    report["seconds"] = time.perf_counter() - t_start
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / JSON_NAME, json.dumps(report, indent=1) + "\n")
    pareto_plot(report, out / PNG_NAME)
    return out / JSON_NAME


def build_voxels(shapes, config: BenchConfig) -> dict:
    """{resolution: [VoxelSDF of each shape's normalised SDF]} (built once; build time is not timed)."""
    if not config.voxel_resolutions:
        return {}
    from zoo.voxel import VoxelSDF

    box = (torch.full((3,), -0.5), torch.full((3,), 0.5))
    return {r: [VoxelSDF(s.normalised, resolution=r, bounds=box, padding=0.2) for s in shapes[: config.voxel_shapes]]
            for r in config.voxel_resolutions}


def pareto_plot(report: dict, path: Path) -> None:
    """Mean optimality against time per triangle, one point per method (seen split), log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    split, timings = report["splits"]["seen"], report["timings"]
    fig, ax = plt.subplots(figsize=(7, 5))
    groups = {"fw": ("NeuralSDF+FW", "tab:blue"), "amortized+fw": ("amortized+FW refine", "tab:orange"),
              "amortized": ("amortized, one pass (ours)", "tab:red"), POLISHED: ("amortized + line search (ours)", "darkred"),
              BEST_VERTEX: ("best vertex", "silver"), VERTEX_POLISHED: ("best vertex + line search", "tab:gray"),
              VERTEX_POLISHED_ONCE: ("best vertex + one line-search step", "lightslategray"),
              "pgd": ("projected gradient", "tab:green"),
              MIDPOINT_QUADRATIC: ("quadratic through 6 exact values", "tab:brown"),
              "voxel": ("VoxelSDF+FW", "tab:purple")}
    for prefix, (label, colour) in groups.items():
        names = [n for n in split if n in timings and _group(n) == prefix]
        if not names:
            continue
        xs = [1e3 * timings[n]["seconds_per_triangle"] for n in names]
        ys = [max(split[n]["optimality_mean"], 1e-9) for n in names]
        ax.plot(xs, ys, "o-" if prefix == "fw" else "o", color=colour, label=label)
        for n, x, y in zip(names, xs, ys):
            ax.annotate(n, (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"time per triangle [ms] (batch of {report['config']['timing_batch']:d})")
    ax.set_ylabel("mean optimality (eq. 12)")
    ax.set_title(f"error against run time {report.get('label', '')}")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def _group(name: str) -> str:
    if name in (POLISHED, BEST_VERTEX, VERTEX_POLISHED, VERTEX_POLISHED_ONCE, MIDPOINT_QUADRATIC):
        return name
    if name.startswith("amortized+"):
        return "amortized+fw"
    if name.startswith("voxel"):
        return "voxel"
    if name.startswith("fw"):
        return "fw"
    return name


def _band_text(label: str, band: dict) -> str:
    mean = "-" if band["mean"] is None else f"{band['mean']:.1e}"
    return f"{label}: {band['fraction']:.2f}, {mean}, {band['share']:.2f}"


def format_tables(report: dict) -> str:
    """The report's tables as plain text (for the CLI and the closing note)."""
    lines = []
    for split, rows in report["splits"].items():
        lines.append(f"[{split}] method | opt p50 | opt p90 | opt mean | worst 5% share | NME p50 | NME p90 | NME mean | "
                     "NME edge/face | ms/tri")
        for name, s in rows.items():
            t = report["timings"].get(name, {}).get("seconds_per_triangle")
            ef = s["nme_mean_edge_or_face"]
            worst = s.get("optimality_worst5_share")  # absent from reports written before it was measured
            lines.append(
                f"{name} | {s['optimality_p50']:.2e} | {s['optimality_p90']:.2e} | {s['optimality_mean']:.2e} | "
                f"{'-' if worst is None else f'{worst:.2f}'} | "
                f"{s['nme_p50']:.4f} | {s['nme_p90']:.4f} | {s['nme_mean']:.4f} | {'-' if ef is None else f'{ef:.4f}'} | "
                f"{'-' if t is None else f'{1e3 * t:.4f}'}"
            )
    for split, rows in report["splits"].items():
        for name in AMORTIZED_METHODS:
            bands = rows.get(name, {}).get("optimality_by_reference_minimum")
            if bands:
                lines.append(f"[{split}] {name} by the reference minimum (band: fraction of triangles, mean optimality, "
                             "share of the total): " + "; ".join(_band_text(label, b) for label, b in bands.items()))
    for split, rows in report.get("table_1", {}).items():
        for method, row in rows.items():
            if row:
                lines.append(f"Table I [{split}]: {method} {row['amortized_optimality_mean']:.2e} at {row['amortized_ms_per_triangle']:.4f} ms; "
                             f"FW-{row['fw_iterations']} ({'reached' if row['fw_reached'] else 'not reached'}) "
                             f"{row['fw_ms_per_triangle']:.4f} ms; speed-up {row['speedup']:.1f}x")
    for name, s in report.get("table_4", {}).items():
        lines.append(f"Table IV {name}: optimality {s['optimality_mean']:.2e}, NME {s['nme_mean']:.4f}")
    return "\n".join(lines)


def bench_model(model_spec, out_dir="bench-results", unseen_meshes=(), config: BenchConfig = BenchConfig(),
                max_shapes: int | None = None, fit_iters: int = 500, unseen_category: str | None = None,
                unseen_count: int = 3, data_dir=None, progress: bool = True, log=print) -> Path:
    """`zoo bench --detector MODEL`: load a package, fit unseen meshes with fit_codes, benchmark; -> JSON path.

    Unseen meshes are ``unseen_meshes`` (up axis z) and/or the first ``unseen_count`` test meshes
    of ``unseen_category`` (each with its manifest's up axis).
    """
    import zoo

    model = zoo.load(model_spec) if isinstance(model_spec, (str, Path)) else model_spec
    if model.detector is None:
        raise InputError(f"model {model.name!r} has no detector; train one (zoo fit-category) or bench the solvers only")
    seen = [model.shape(s) for s in model.shapes[:max_shapes]]
    unseen = [model.fit_codes(m, iters=fit_iters) for m in unseen_meshes]
    if unseen_category:
        unseen += unseen_test_shapes(model, unseen_category, data_dir, unseen_count, fit_iters)
    return run_detector_benchmark(model.detector, seen, unseen, out_dir, config, label=f"{model.name}@{model.version}",
                                  progress=progress, log=log)


def unseen_test_shapes(model, category: str, data_dir=None, count: int = 3, iters: int = 500) -> list:
    """The first ``count`` meshes of ``category``'s test split, fitted with the decoder frozen (their own up axes)."""
    from sdfzoo.pipeline.categories import load_category, resolve_data_dir, verify_meshes

    cat = load_category(category)
    stems = cat.stems("test")[:count]
    paths = verify_meshes(cat, resolve_data_dir(data_dir, cat), stems)
    return [model.fit_codes(paths[s], iters=iters, up=cat.entry(s).up, name=s) for s in stems]


def main(argv=None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="Error against run time of the amortized detector and its baselines.")
    parser.add_argument("--model", required=True, help="package directory or registered name (the NeuralSDF)")
    parser.add_argument("--detector", default=None, help="detector directory (detector.safetensors + detector.json); "
                        "default: the package's own detector")
    parser.add_argument("--unseen", nargs="*", default=[], help="meshes never seen in training, fitted with fit_codes (up z)")
    parser.add_argument("--unseen-category", default=None, help="take unseen meshes from this category's test split")
    parser.add_argument("--unseen-count", type=int, default=3, help="how many test meshes of --unseen-category")
    parser.add_argument("--data", default=None, help="mesh folder for --unseen-category (default $ZOO_DATA)")
    parser.add_argument("--ablations", nargs="*", default=[], help="NAME=DIR detector directories for Table IV")
    parser.add_argument("--ablations-only", action="store_true", help="measure Table IV alone (the same seen triangles); "
                        "writes table_4.json")
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--max-shapes", type=int, default=None)
    parser.add_argument("--n-per-shape", type=int, default=None)
    parser.add_argument("--fit-iters", type=int, default=500)
    parser.add_argument("--quick", action="store_true", help="the small QUICK configuration")
    parser.add_argument("--voxels", default=None, help="comma-separated voxel resolutions (default 64,128,256)")
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--metrics-out", default=None, help="also write the detector's headline numbers, flat, to this "
                        "JSON file: what `zoo package --metrics` records in a release's manifest")
    args = parser.parse_args(argv)
    import dataclasses

    import zoo
    from sdfzoo.pipeline.train_detector import load_detector

    config = QUICK if args.quick else BenchConfig()
    if args.n_per_shape:
        config = dataclasses.replace(config, n_per_shape=args.n_per_shape)
    if args.voxels is not None:
        config = dataclasses.replace(config, voxel_resolutions=tuple(int(r) for r in args.voxels.split(",") if r))
    if args.threads:
        config = dataclasses.replace(config, threads=args.threads)
    model = zoo.load(args.model)
    detector = load_detector(args.detector) if args.detector else model.detector
    seen = [model.shape(s) for s in model.shapes[: args.max_shapes]]
    unseen = [model.fit_codes(m, iters=args.fit_iters) for m in args.unseen]
    if args.unseen_category:
        unseen += unseen_test_shapes(model, args.unseen_category, args.data, args.unseen_count, args.fit_iters)
    ablations = {name: load_detector(path) for name, path in (a.split("=", 1) for a in args.ablations)}
    if args.ablations_only:
        if not ablations:
            raise InputError("--ablations-only needs --ablations NAME=DIR ...")
        if config.threads:
            torch.set_num_threads(int(config.threads))
        table = ablation_table(ablations, seen, bench_triangles(seen, config), config)
        Path(args.out).mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(args.out) / "table_4.json", json.dumps(table, indent=1) + "\n")
        print(format_tables({"splits": {}, "table_4": table}))
        return
    path = run_detector_benchmark(detector, seen, unseen, args.out, config, ablations=ablations or None,
                                  label=f"{model.name}@{model.version}")
    report = json.loads(path.read_text())
    print(format_tables(report))
    print(f"written {path} and {path.with_name(PNG_NAME)}")
    if args.metrics_out:
        atomic_write_text(Path(args.metrics_out), json.dumps(release_metrics(report), indent=1) + "\n")
        print(f"written {args.metrics_out}")


if __name__ == "__main__":
    main()
