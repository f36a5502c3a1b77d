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
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import zoo
from zoo.errors import ZooError
from zoo.files import atomic_write_text
from zoo.solvers import frank_wolfe, optimality, projected_gradient, reference

CASES: list[tuple[str, Callable]] = []  # (name, case(ctx) -> (expected, observed, ok)): what `zoo stress` runs, in order
MODEL_CASES: set[str] = set()  # the names of the cases that stress a packaged model (`zoo stress --model`)


def case(name: str, needs_model: bool = False):
    def register(fn):
        CASES.append((name, fn))
        if needs_model:
            MODEL_CASES.add(name)
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
    """Per solver: its gaps to the reference minimum (median, p90, max) and whether its answers are on the simplex."""
    out = {}
    for k, b in answers.items():
        g = gaps_to_reference(sdf, tris, b).double()
        out[k] = {"p50": float(g.median()), "p90": float(g.quantile(0.9)), "max": float(g.max()), "on_simplex": on_simplex(b)}
    return out


def baseline_gaps(sdf, tris) -> tuple[dict, bool]:
    """FW-10 and PGD on ``tris``: their gap summaries, and whether every answer is on the simplex."""
    gaps = gap_summary(sdf, tris, solver_answers(sdf, tris))
    return gaps, all(g["on_simplex"] for g in gaps.values())


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
    gap = gap_to_reference(sdf, tris, answers["fw-10"])
    ok = all(on_simplex(b) for b in answers.values()) and gap < 1e-3
    observed = {k: "on simplex" if on_simplex(b) else "OFF simplex" for k, b in answers.items()} | {"fw-10 gap to the reference": gap}
    return "finite barycentrics on the simplex, near the reference minimum", observed, ok


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
    simplex = all(on_simplex(b) for b in solver_answers(sdf, tris).values())
    return "no contacts, finite answers", {"contacts": len(c), "candidates": c.n_candidates, "on_simplex": simplex}, len(c) == 0 and simplex


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


@case("zero triangles")
def _zero_triangles(ctx):
    sdf = ctx["sdf"]
    tris = torch.zeros(0, 3, 3)
    answers = solver_answers(sdf, tris, ctx.get("shape_sdf"))
    c = zoo.collide(sdf, (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)), method="fw")
    observed = {k: list(b.shape) for k, b in answers.items()} | {"contacts": len(c)}
    ok = all(b.shape == (0, 3) for b in answers.values()) and len(c) == 0
    return "an empty answer, (0, 3) barycentrics from every solver and no contacts from an empty mesh (not an error)", observed, ok


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
    observed = {"contacts_m": len(c_m), "contacts_mm": len(c_mm), "same_triangles": same, "depth_diff_mm": err}
    return "same contact triangles, depths scale by 1000", observed, same and err < 1e-2


@case("one million points")
def _million(ctx):
    sdf = ctx.get("shape_sdf") or ctx["sdf"]
    pts = torch.rand(1_000_000, 3) - 0.5
    t0 = time.perf_counter()
    d, g = sdf.value_and_grad(pts)
    dt = time.perf_counter() - t0
    finite = bool(torch.isfinite(d).all() and torch.isfinite(g).all())
    ok = d.shape == (1_000_000,) and finite
    return "finite values and gradients, memory bounded", {"seconds": dt, "sdf": type(sdf).__name__, "values": d.numel(), "finite": finite}, ok


@case("queries at code positions (model)", needs_model=True)
def _code_positions(ctx):
    shape = ctx.get("shape_sdf")
    if shape is None:
        return "needs --model", "skipped: no model given", True
    norm = shape.normalised
    d, g = norm.value_and_grad(norm.positions.detach().reshape(-1, 3).float())
    ok = bool(torch.isfinite(d).all() and torch.isfinite(g).all())
    return "finite value and gradient exactly at every code position (inverse-distance weights)", {"points": int(d.numel()), "finite": ok}, ok


@case("softmax saturation (model)", needs_model=True)
def _saturation(ctx):
    shape, model = ctx.get("shape_sdf"), ctx.get("model")
    if shape is None or model is None or model.detector is None:
        return "needs --model with a detector", "skipped: no detector", True
    from zoo.amortized import vertex_features

    tris = triangles_around(shape.normalised, 256, 0.03, 0.02)
    feats = vertex_features(shape, tris)
    vertex_sdf = None
    if model.detector.vertex_sdf:  # a detector that also reads the distance at each vertex
        with torch.no_grad():
            vertex_sdf = torch.as_tensor(shape.normalised(tris.reshape(-1, 3))).reshape(-1, 3).float()
    results = {}
    for scale in (1.0, 1e3, 1e6):
        with torch.no_grad():
            bary = model.detector(tris, feats * scale, vertex_sdf)
        results[f"features x{scale:g}"] = "on simplex" if on_simplex(bary) else "OFF simplex or NaN"
    return "barycentrics stay finite on the simplex when the logits saturate", results, all(v == "on simplex" for v in results.values())


@case("amortized on huge and penetrating triangles (model)", needs_model=True)
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


def _uniform(g: torch.Generator, n: int, half: float = 0.5) -> torch.Tensor:
    return (torch.rand(n, 3, generator=g) * 2 - 1) * half


def _fit_extremes() -> tuple[dict, bool]:
    """A few NeuralSDF training steps (pipeline.fit_sdf.train_step, a tiny network) on each extreme
    batch, with the presets' clamped L1 loss and with an unclamped MSE (clamp 1e9), whose gradients
    grow with the targets."""
    from dataclasses import replace

    from sdfzoo.pipeline.fit_sdf import make_optimizer, preset, stack_samples, train_step
    from zoo.neural import NeuralSDF, NeuralSDFConfig

    quick = preset("quick")
    tiny = replace(quick, sdf=NeuralSDFConfig(n_codes=4, code_dim=4, hidden=(8, 8)), steps=3, shapes_per_step=2,
                   points_per_shape=32, checkpoint_every=1000)
    losses = {f"{quick.loss} clamped at {quick.clamp:g}": tiny, "mse clamped at 1e9": replace(tiny, loss="mse", clamp=1e9)}
    g = torch.Generator().manual_seed(0)
    near = _uniform(g, 64)
    far = _uniform(g, 64, 1e6)  # a million object sizes away: distances far beyond the loss's clamp
    batches = {
        "batch of 1 (one shape, one point)": ([near[:1]], [torch.tensor([0.05])], dict(shapes_per_step=1, points_per_shape=1)),
        "far points (1e6 away)": ([far, near], [far.norm(dim=-1), near.norm(dim=-1) - 0.3], {}),
        "huge SDF targets (+-3e38)": ([near, near], [torch.full((64,), 3e38), torch.full((64,), -3e38)], {}),
        "all points on one spot": ([torch.zeros(64, 3), near], [torch.zeros(64), near.norm(dim=-1) - 0.3], {}),
    }
    out, ok = {}, True
    for name, (points, sdf, overrides) in batches.items():
        data = stack_samples([f"s{i}" for i in range(len(points))], points, sdf)
        for lname, config in losses.items():
            config = replace(config, **overrides)
            model = NeuralSDF(config.sdf, len(points), torch.Generator().manual_seed(0))
            optimizer = make_optimizer(model, config)
            values, norms = [], []
            for step in range(config.steps):
                values.append(train_step(model, optimizer, data, config, step))
                norms.append(float(torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in model.parameters() if p.grad is not None]))))
            finite = all(math.isfinite(x) for x in values + norms) and all(bool(torch.isfinite(p).all()) for p in model.parameters())
            out[f"{name} / {lname}"] = {"losses": values, "max_grad_norm": max(norms), "finite": finite}
            ok &= finite
    # what no batch may hold, and a loss that could not stay finite: refused before they can poison the weights
    refused = {
        "NaN target": lambda: stack_samples(["bad"], [near], [torch.full((64,), float("nan"))]),
        "a point at 1e20 (its squared distance overflows float32)": lambda: stack_samples(["bad"], [near * 1e20], [near.norm(dim=-1)]),
        "no clamp (clamp=inf: a huge target's squared error overflows)": lambda: replace(tiny, loss="mse", clamp=float("inf")),
    }
    for name, call in refused.items():
        try:
            call()
            out[f"refused: {name}"], ok = "accepted", False
        except ZooError as exc:
            out[f"refused: {name}"] = f"{type(exc).__name__}: {exc}"
    return out, ok


class _ClipRecorder:
    """Records, for every ``torch.nn.utils.clip_grad_norm_`` call while active, the gradient norm
    before clipping, the bound and the norm after it (the detector's training loop calls it by name)."""

    def __enter__(self):
        self.calls, self.original = [], torch.nn.utils.clip_grad_norm_

        def recorder(parameters, max_norm, *args, **kwargs):
            parameters = [p for p in parameters if p.grad is not None] if not isinstance(parameters, torch.Tensor) else [parameters]
            before = self.original(parameters, max_norm, *args, **kwargs)
            after = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in parameters])) if parameters else torch.zeros(())
            self.calls.append((float(before), float(max_norm), float(after)))
            return before

        torch.nn.utils.clip_grad_norm_ = recorder
        return self

    def __exit__(self, *exc):
        torch.nn.utils.clip_grad_norm_ = self.original
        return False


def _detector_extremes(sdf) -> tuple[dict, bool]:
    """A few steps of pipeline.train_detector.train (tiny detectors, two losses) on each extreme batch."""
    from dataclasses import replace

    from sdfzoo.pipeline.train_detector import TrainConfig, TrainingData, preset, train

    def tiny(config):
        return replace(config, steps=3, batch_size=8, validate_every=1000, validation_size=8, checkpoint_every=1000,
                       detector={**config.detector, "feature_dim": 4, "hidden": 8, "weight_hidden": 4})

    configs = {"quick preset": tiny(preset("quick")), "paper loss (L_op + L_min)": tiny(TrainConfig())}
    g = torch.Generator().manual_seed(0)
    normal = triangles_around(sdf, 8, 0.02, 0.01, seed=1)
    equal2 = normal.clone()
    equal2[:, 2] = equal2[:, 0]
    batches = {
        "batch of 1": normal[:1],
        "degenerate (three equal vertices)": normal.mean(dim=1, keepdim=True).expand(-1, 3, -1).clone(),
        "two equal vertices": equal2,
        "tiny (edges 1e-9)": triangles_around(sdf, 8, 1e-9, 0.01, seed=2),
        "huge coordinates (x1e6)": normal * 1e6,
        "far away (1e6 off)": normal + 1e6,
        "huge triangles (edges 1e3)": triangles_around(sdf, 8, 1e3, 0.0, seed=3),
        "mixed: normal and x1e6": torch.cat([normal[:4], normal[4:] * 1e6]),
    }
    out, ok, clipped = {}, True, 0
    for name, tri in batches.items():
        n = tri.shape[0]
        features = torch.randn(n, 3, 4, generator=g) * 0.05
        with torch.no_grad():
            vertex_sdf = torch.as_tensor(sdf(tri.reshape(-1, 3))).reshape(n, 3).float()
        data = TrainingData(tri.float(), features, torch.zeros(n, dtype=torch.long), [sdf], vertex_sdf)
        for cname, config in configs.items():
            with _ClipRecorder() as clip:
                detector, history = train(data, replace(config, batch_size=min(config.batch_size, n)), progress=False)
            finite = all(math.isfinite(x) for x in history["loss"]) and all(bool(torch.isfinite(p).all()) for p in detector.parameters())
            # a norm over the bound is clipped to it; a non-finite one leaves gradients that the loop must skip
            held = all(after <= bound * (1 + 1e-4) for before, bound, after in clip.calls if math.isfinite(before) and before > bound)
            clipped += sum(before > bound for before, bound, _ in clip.calls)
            out[f"{name} / {cname}"] = {"losses": history["loss"], "max_grad_norm": max((c[0] for c in clip.calls), default=0.0),
                                        "clipped_steps": sum(b > m for b, m, _ in clip.calls), "finite": finite, "clip_held": held,
                                        "steps": config.steps, "clip_calls": len(clip.calls)}
            ok &= finite and held and len(clip.calls) == config.steps
    out["steps clipped in all"] = clipped
    return out, ok


@case("extreme training batches")
def _extreme_training(ctx):
    fit, fit_ok = _fit_extremes()
    det, det_ok = _detector_extremes(ctx["sdf"])
    return ("NeuralSDF and detector training (tiny networks, a few steps) on batches of 1, far points, huge targets, "
            "degenerate, tiny and huge triangles: every loss, gradient norm and weight finite; a gradient norm over "
            "grad_clip is clipped to it; samples with NaN or beyond float32's range refused with a ZooError"), \
        {"fit-sdf": fit, "train-detector": det}, fit_ok and det_ok


BAD_INPUTS = [
    ("NaN points", lambda s: s(torch.tensor([[float("nan"), 0.0, 0.0]]))),
    ("Inf triangles", lambda s: frank_wolfe(s, torch.full((1, 3, 3), float("inf")))),
    ("wrong point shape", lambda s: s(torch.zeros(5, 2))),
    ("wrong triangle shape", lambda s: frank_wolfe(s, torch.zeros(4, 4, 3))),
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


def stress_context(model: str | None = None, shape: str | None = None) -> dict:
    """What the cases run on: an analytic torus; with ``model`` (NAME[@VERSION]), also that model and its
    ``shape`` (default its first) as a NeuralSDF."""
    ctx = {"sdf": zoo.Torus(major=0.3, minor=0.1)}
    if model:
        m = zoo.load(model)
        ctx["model"], ctx["shape_sdf"] = m, m.shape(shape or m.shapes[0])
    return ctx


def run_case(name: str, fn: Callable, ctx: dict) -> dict:
    """One case's record ``{case, expected, observed, ok, seconds}``; an exception is a failure, recorded."""
    from zoo.progress import activity

    t0 = time.perf_counter()
    try:
        with activity(f"stress case: {name}"):
            expected, observed, ok = fn(ctx)
    except Exception as exc:  # noqa: BLE001 - a crash is a failed case, recorded
        expected, observed, ok = "no exception", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}", False
    return {"case": name, "expected": expected, "observed": _jsonable(observed), "ok": bool(ok), "seconds": time.perf_counter() - t0}


def run_stress(out: str | Path = "out/stress.json", model: str | None = None, shape: str | None = None) -> dict:
    """Run every case; write and return the report. ``model``/``shape`` add a NeuralSDF to the cases."""
    ctx = stress_context(model, shape)
    records = [run_case(name, fn, ctx) for name, fn in CASES]
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
