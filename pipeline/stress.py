"""`zoo stress`: stiff and extreme cases and malformed input, each with what is expected and what happened.

Every case returns a record ``{case, expected, observed, ok}``; the whole run is written as JSON.
A case never raises: an unexpected exception is recorded as a failure with its message.
"""

from __future__ import annotations

import json
import math
import platform
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np
import torch

import zoo
from zoo.errors import ZooError
from zoo.files import atomic_write_text
from zoo.solvers import frank_wolfe, optimality, projected_gradient, reference

CASES: list[tuple[str, Callable]] = []


def case(name: str):
    def register(fn):
        CASES.append((name, fn))
        return fn

    return register


# ------------------------------------------------------------------------------ helpers


def on_simplex(bary: torch.Tensor, tol: float = 1e-5) -> bool:
    return bool(torch.isfinite(bary).all() and (bary >= -tol).all() and ((bary.sum(-1) - 1).abs() < tol).all())


def sdf_at(sdf, tris, bary) -> torch.Tensor:
    return sdf(zoo.geometry.bary_to_points(tris, bary))


def gap_to_reference(sdf, tris, bary) -> float:
    """Largest excess of f at the answer over f at the global reference minimum."""
    return float(gaps_to_reference(sdf, tris, bary).max())


def gaps_to_reference(sdf, tris, bary) -> torch.Tensor:
    """Excess of f at the answer over f at the global reference minimum: (M,)."""
    return sdf_at(sdf, tris, bary) - sdf_at(sdf, tris, reference(sdf, tris))


def gap_summary(sdf, tris, answers: dict) -> dict:
    out = {}
    for k, b in answers.items():
        g = gaps_to_reference(sdf, tris, b).double()
        out[k] = {"p50": float(g.median()), "p90": float(g.quantile(0.9)), "max": float(g.max())}
    return out


def baseline_gaps(sdf, tris) -> tuple[dict, bool]:
    """FW-10 and PGD on ``tris``: their gap summaries, and whether every answer is on the simplex."""
    answers = solver_answers(sdf, tris)
    return gap_summary(sdf, tris, answers), all(on_simplex(b) for b in answers.values())


def solver_answers(sdf, tris, detector_shape=None) -> dict[str, torch.Tensor]:
    answers = {"fw-10": frank_wolfe(sdf, tris, iters=10), "pgd": projected_gradient(sdf, tris)}
    if detector_shape is not None:
        answers["amortized"] = detector_shape.detect(tris)
    return answers


def triangles_around(sdf, n, size, distance, seed=0, dtype=torch.float32) -> torch.Tensor:
    """(n, 3, 3) random triangles of edge ~``size`` whose centroids lie ``distance`` from the sphere-like surface."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
    centre, radius = (lo + hi) / 2, float((hi - lo).max()) / 2
    direction = torch.randn(n, 3, generator=g, dtype=torch.float64)
    direction /= direction.norm(dim=-1, keepdim=True)
    c = centre + direction * (radius + distance)
    offsets = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * size
    tris = c[:, None, :] + offsets - offsets.mean(1, keepdim=True)
    return tris.to(dtype)


# ------------------------------------------------------------------------------ the cases


@case("degenerate triangles")
def _degenerate(ctx):
    sdf = ctx["sdf"]
    p = torch.tensor([0.3, 0.05, 0.02])
    tris = torch.stack([
        torch.stack([p, p, p]),                                          # a point
        torch.stack([p, p + torch.tensor([0.05, 0, 0]), p + torch.tensor([0.1, 0, 0])]),  # collinear
        torch.stack([p, p, p + torch.tensor([0, 0.05, 0])]),             # two equal vertices
    ])
    answers = solver_answers(sdf, tris, ctx.get("shape_sdf"))
    ok = all(on_simplex(b) for b in answers.values()) and gap_to_reference(sdf, tris, answers["fw-10"]) < 1e-3
    return "finite barycentrics on the simplex, near the reference minimum", {k: "on simplex" if on_simplex(b) else "OFF simplex" for k, b in answers.items()}, ok


@case("slivers")
def _slivers(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 256, 0.04, 0.01)
    tris[:, 2] = tris[:, 0] + 1e-6 * (tris[:, 2] - tris[:, 0]) + (tris[:, 1] - tris[:, 0]) * 0.5
    gaps, simplex = baseline_gaps(sdf, tris)
    return "on the simplex; median gap to the reference minimum below 1e-4", gaps, simplex and all(g["p50"] < 1e-4 for g in gaps.values())


@case("tiny triangles")
def _tiny(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 256, 1e-6, 0.01)
    gaps, simplex = baseline_gaps(sdf, tris)
    return "on the simplex, at the reference minimum (1e-5)", gaps, simplex and all(g["max"] < 1e-5 for g in gaps.values())


@case("huge triangles")
def _huge(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 64, 2.0, 0.0)
    gaps, simplex = baseline_gaps(sdf, tris)  # the model's detector on huge triangles is its own case
    return "on the simplex; the baselines may stop far from the minimum on triangles 10x the object (reported)", gaps, simplex


@case("far-away triangles")
def _far(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 128, 0.05, 1e3)
    c = zoo.collide(sdf, (tris.reshape(-1, 3), torch.arange(len(tris) * 3).reshape(-1, 3)), method="fw")
    answers = solver_answers(sdf, tris)
    return "no contacts, finite answers", {"contacts": len(c), "candidates": c.n_candidates}, len(c) == 0 and all(on_simplex(b) for b in answers.values())


@case("penetrating triangles")
def _penetrating(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 256, 0.05, -0.03)
    answers = solver_answers(sdf, tris)
    gaps = gap_summary(sdf, tris, answers)
    depth = float(sdf_at(sdf, tris, answers["fw-10"]).min())
    ok = depth < 0 and all(on_simplex(b) for b in answers.values()) and all(g["p50"] < 1e-3 for g in gaps.values())
    return "negative minima found; median gap to the reference below 1e-3 (FW's last iterate can sit far off on non-convex cuts: reported)", {"gaps": gaps, "deepest": depth}, ok


@case("near-tangent triangles (FW zig-zag)")
def _tangent(ctx):
    sphere = zoo.Sphere(radius=0.3)
    g = torch.Generator().manual_seed(1)
    # flat triangles tangent to the sphere at random points: the minimum is inside the face and
    # the objective is nearly flat across it, the ill-conditioned case where FW zig-zags.
    n = torch.randn(128, 3, generator=g)
    n /= n.norm(dim=-1, keepdim=True)
    u = torch.linalg.cross(n, torch.randn(128, 3, generator=g))
    u /= u.norm(dim=-1, keepdim=True)
    v = torch.linalg.cross(n, u)
    centre = n * 0.3001
    ang = torch.tensor([0.0, 2.1, 4.2]) + 0.3 * torch.rand(128, 3, generator=g)
    tris = centre[:, None] + 0.04 * (torch.cos(ang)[..., None] * u[:, None] + torch.sin(ang)[..., None] * v[:, None])
    gaps = {k: float(optimality(sphere, tris, frank_wolfe(sphere, tris, iters=k)).mean()) for k in (10, 50, 200)}
    return "FW's optimality falls with iterations (zig-zag slows it); all finite", gaps, gaps[200] < gaps[10] and all(math.isfinite(x) for x in gaps.values())


@case("high curvature (thin torus)")
def _curvature(ctx):
    torus = zoo.Torus(major=0.3, minor=0.002)
    tris = triangles_around(torus, 256, 0.03, 0.0)
    gaps, simplex = baseline_gaps(torus, tris)
    return "finite, on simplex; gaps to the reference reported", gaps, simplex


@case("zero gradient (medial axis)")
def _medial(ctx):
    results = {}
    for sdf, p in ((zoo.Sphere(0.3), [0.0, 0.0, 0.0]), (zoo.Torus(0.3, 0.1), [0.0, 0.0, 0.0]), (zoo.Box((0.2, 0.2, 0.2)), [0.0, 0.0, 0.0])):
        d, g = sdf.value_and_grad(torch.tensor([p]))
        results[repr(sdf)] = {"value": float(d), "grad_finite": bool(torch.isfinite(g).all())}
    ok = all(r["grad_finite"] and math.isfinite(r["value"]) for r in results.values())
    return "finite value and gradient where the gradient is undefined", results, ok


@case("float32 against float64")
def _precision(ctx):
    sdf = ctx["sdf"]
    tris = triangles_around(sdf, 512, 0.05, 0.02, dtype=torch.float64)
    b64 = frank_wolfe(sdf, tris, iters=20)
    b32 = frank_wolfe(sdf, tris.float(), iters=20)
    f64, f32 = sdf_at(sdf, tris, b64), sdf_at(sdf, tris, b32.double())
    diff = float((f64 - f32).abs().max())
    return "float64 kept as float64; minima agree to 1e-4", {"dtype": str(b64.dtype), "max_value_diff": diff}, b64.dtype == torch.float64 and diff < 1e-4


@case("millimetres against metres")
def _units(ctx):
    import trimesh

    box = trimesh.creation.box(extents=(0.2, 0.2, 0.02))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.01)
    sdf_m, sdf_mm = zoo.Sphere(0.05, center=(0, 0, 0.059)), zoo.Sphere(50.0, center=(0, 0, 59.0))
    c_m = zoo.collide(sdf_m, (v, f), margin=1e-3)
    c_mm = zoo.collide(sdf_mm, (v * 1000.0, f), margin=1.0)
    same = len(c_m) == len(c_mm) and bool(torch.equal(c_m.triangles, c_mm.triangles))
    err = float((c_m.depths * 1000 - c_mm.depths).abs().max()) if same and len(c_m) else float("nan")
    return "same contact triangles, depths scale by 1000", {"contacts_m": len(c_m), "contacts_mm": len(c_mm), "depth_diff_mm": err}, same and err < 1e-2


@case("one million points")
def _million(ctx):
    sdf = ctx.get("shape_sdf") or ctx["sdf"]
    pts = torch.rand(1_000_000, 3) - 0.5
    t0 = time.perf_counter()
    d, g = sdf.value_and_grad(pts)
    dt = time.perf_counter() - t0
    ok = d.shape == (1_000_000,) and bool(torch.isfinite(d).all() and torch.isfinite(g).all())
    return "finite values and gradients, memory bounded", {"seconds": dt, "sdf": type(sdf).__name__}, ok


@case("queries at code positions (model)")
def _code_positions(ctx):
    shape = ctx.get("shape_sdf")
    if shape is None:
        return "needs --model", "skipped: no model given", True
    norm = shape.normalised
    d, g = norm.value_and_grad(norm.positions.detach().reshape(-1, 3).float())
    ok = bool(torch.isfinite(d).all() and torch.isfinite(g).all())
    return "finite value and gradient exactly at every code position (inverse-distance weights)", {"points": int(d.numel())}, ok


@case("softmax saturation (model)")
def _saturation(ctx):
    shape, model = ctx.get("shape_sdf"), ctx.get("model")
    if shape is None or model is None or model.detector is None:
        return "needs --model with a detector", "skipped: no detector", True
    from zoo.detector import vertex_features

    tris = triangles_around(shape.normalised, 256, 0.03, 0.02)
    feats = vertex_features(shape, tris)
    results = {}
    for scale in (1.0, 1e3, 1e6):
        with torch.no_grad():
            bary = model.detector(tris, feats * scale)
        results[f"features x{scale:g}"] = "on simplex" if on_simplex(bary) else "OFF simplex or NaN"
    return "barycentrics stay finite on the simplex when the logits saturate", results, all(v == "on simplex" for v in results.values())


@case("amortized on huge and penetrating triangles (model)")
def _amortized_extremes(ctx):
    shape, model = ctx.get("shape_sdf"), ctx.get("model")
    if shape is None or model is None or model.detector is None:
        return "needs --model with a detector", "skipped: no detector", True
    sdf = shape.normalised
    out = {}
    for name, tris in (("huge", triangles_around(sdf, 32, 1.0, 0.0)), ("penetrating", triangles_around(sdf, 128, 0.04, -0.02))):
        bary = model.detect(sdf, tris)
        out[name] = {"on_simplex": on_simplex(bary), **gap_summary(sdf, tris, {"amortized": bary})["amortized"]}
    ok = all(v["on_simplex"] for v in out.values())
    return "on the simplex; gap to the global reference minimum reported (normalised units)", out, ok


BAD_INPUTS = [
    ("NaN points", lambda s: s(torch.tensor([[float("nan"), 0.0, 0.0]]))),
    ("Inf triangles", lambda s: frank_wolfe(s, torch.full((1, 3, 3), float("inf")))),
    ("wrong point shape", lambda s: s(torch.zeros(5, 2))),
    ("wrong triangle shape", lambda s: frank_wolfe(s, torch.zeros(4, 4, 3))),
    ("empty triangles", lambda s: frank_wolfe(s, torch.zeros(0, 3, 3))),
    ("string points", lambda s: s("points")),
    ("complex points", lambda s: s(torch.zeros(2, 3, dtype=torch.complex64))),
    ("negative iterations", lambda s: frank_wolfe(s, torch.rand(2, 3, 3), iters=-1)),
    ("bary off the simplex", lambda s: optimality(s, torch.rand(2, 3, 3), torch.full((2, 3), 0.9))),
    ("bad pose", lambda s: zoo.collide(s, (np.zeros((3, 3)), np.array([[0, 1, 2]])), sdf_pose=np.eye(3))),
    ("unknown method", lambda s: zoo.collide(s, (np.eye(3), np.array([[0, 1, 2]])), method="magic")),
    ("not an SDF", lambda s: frank_wolfe(object(), torch.rand(2, 3, 3))),
    ("face index out of range", lambda s: zoo.collide(s, (np.eye(3), np.array([[0, 1, 7]])))),
    ("unknown model", lambda s: zoo.load("no-such-model")),
    ("unknown model version", lambda s: zoo.load("mugs@999.0.0")),
    ("missing package directory", lambda s: zoo.load("/nonexistent/package/dir")),
]


@case("malformed input")
def _malformed(ctx):
    sdf = ctx["sdf"]
    observed, ok = {}, True
    for name, call in BAD_INPUTS:
        try:
            call(sdf)
            observed[name], ok = "returned without an error", False
        except ZooError as exc:
            observed[name] = f"{type(exc).__name__}: {exc}"
            ok &= len(str(exc)) > 20
        except Exception as exc:  # noqa: BLE001 - anything but a ZooError is a failure here
            observed[name], ok = f"untyped {type(exc).__name__}: {exc}", False
    return "a zoo.errors.ZooError with a message for each", observed, ok


# ------------------------------------------------------------------------------ the run


def run_stress(out: str | Path = "out/stress.json", model: str | None = None, shape: str | None = None) -> dict:
    """Run every case; write and return the report. ``model``/``shape`` add a NeuralSDF to the cases."""
    ctx = {"sdf": zoo.Torus(major=0.3, minor=0.1)}
    if model:
        m = zoo.load(model)
        ctx["model"], ctx["shape_sdf"] = m, m.shape(shape or m.shapes[0])
    records = []
    for name, fn in CASES:
        t0 = time.perf_counter()
        try:
            expected, observed, ok = fn(ctx)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, recorded
            expected, observed, ok = "no exception", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}", False
        records.append({"case": name, "expected": expected, "observed": _jsonable(observed), "ok": bool(ok), "seconds": time.perf_counter() - t0})
    report = {
        "torch": torch.__version__, "machine": platform.machine(), "model": model,
        "passed": sum(r["ok"] for r in records), "failed": sum(not r["ok"] for r in records), "cases": records,
    }
    atomic_write_text(out, json.dumps(report, indent=1))
    return report


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return x
