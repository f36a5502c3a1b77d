"""Evaluate a fitted SDF against its mesh's exact signed distance, in the mesh's own frame.

Metrics (all lengths as a fraction of the object's size, the largest bounding-box extent):

* ``near_p50``, ``near_p90``, ``near_mean``: |predicted - exact| at points near the surface
  (surface samples displaced by Gaussian noise of ``near_sigma`` x size, kept where the exact
  |distance| is below ``far_threshold`` x size);
* ``sign_agreement``: fraction of points farther than ``far_threshold`` x size from the surface
  (the band points beyond it and points uniform in the padded bounding box) whose predicted sign
  is the exact one;
* ``chamfer``: symmetric mean Chamfer distance between the mesh surface and the fitted zero
  level set (points of a marching-cubes grid), each direction the mean nearest distance;
  only with ``chamfer_resolution`` > 0.

The exact distance is :func:`zoo.meshes.signed_distance` (libigl; winding-number sign).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch

from zoo.config import DictConfig
from zoo.meshes import sample_surface, signed_distance


@dataclass(frozen=True)
class EvalConfig(DictConfig):
    """How many fresh points, where, and whether to measure Chamfer (all lengths x the object's size)."""

    _config_name = "evaluation config"
    n_near: int = 20_000
    n_uniform: int = 20_000
    near_sigma: float = 0.01  # x size
    far_threshold: float = 0.02  # x size
    padding: float = 0.1  # x size, around the bounding box for the uniform points
    chamfer_resolution: int = 0  # marching-cubes grid per axis; 0 skips Chamfer
    chamfer_points: int = 20_000
    seed: int = 1234  # differs from the samples stage's seeds: these are fresh points


def evaluation_points(mesh, config: EvalConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """Fresh test points and their exact distances in the mesh's frame.

    -> near points (n_near, 3), uniform points (n_uniform, 3), size (float).
    """
    rng = np.random.default_rng(config.seed)
    lo, hi = np.asarray(mesh.bounds[0], float), np.asarray(mesh.bounds[1], float)
    size = float((hi - lo).max())
    near = sample_surface(mesh, config.n_near, rng) + rng.normal(size=(config.n_near, 3)) * config.near_sigma * size
    pad = config.padding * size
    uniform = rng.uniform(lo - pad, hi + pad, size=(config.n_uniform, 3))
    return near, uniform, size


def evaluate_shape(sdf, mesh, config: EvalConfig | None = None, device: str | torch.device = "cpu") -> dict:
    """Compare ``sdf`` (any SDF in ``mesh``'s frame and units) with the mesh's exact SDF; -> metrics dict.

    ``device``: where the SDF is queried (a GPU for a NeuralSDF); the metrics are computed on the CPU."""
    config = config or EvalConfig()
    near, uniform, size = evaluation_points(mesh, config)
    points = np.concatenate([near, uniform])
    exact = signed_distance(mesh, points)
    t0 = time.perf_counter()
    with torch.no_grad():
        pred = sdf(torch.as_tensor(points, dtype=torch.float64, device=device)).double().cpu().numpy()
    query_seconds = time.perf_counter() - t0
    err = np.abs(pred - exact) / size
    n = len(near)
    near_mask = np.abs(exact[:n]) < config.far_threshold * size
    far_mask = np.abs(exact) > config.far_threshold * size
    near_err = err[:n][near_mask]
    out = {
        "size": size,
        "near_p50": float(np.median(near_err)),
        "near_p90": float(np.percentile(near_err, 90)),
        "near_mean": float(near_err.mean()),
        "sign_agreement": float((np.sign(pred[far_mask]) == np.sign(exact[far_mask])).mean()),
        "n_near": int(near_mask.sum()),
        "n_far": int(far_mask.sum()),
        "query_us_per_point": query_seconds / len(points) * 1e6,
    }
    if config.chamfer_resolution:
        out["chamfer"] = chamfer_to_level_set(sdf, mesh, size, config)
    return out


def chamfer_to_level_set(sdf, mesh, size: float, config: EvalConfig) -> float | None:
    """Symmetric mean Chamfer distance (fraction of size) between the mesh and ``sdf``'s zero set.

    The zero set is extracted by marching cubes (libigl) on a grid over the padded bounding
    box; None when the fitted SDF has no zero crossing there.
    """
    import igl
    from scipy.spatial import cKDTree

    r = config.chamfer_resolution
    lo, hi = np.asarray(mesh.bounds[0], float), np.asarray(mesh.bounds[1], float)
    pad = config.padding * size
    axes = [np.linspace(lo[i] - pad, hi[i] + pad, r) for i in range(3)]
    # libigl's marching cubes wants x fastest
    gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    grid = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    with torch.no_grad():
        values = sdf(torch.as_tensor(grid, dtype=torch.float64)).double().cpu().numpy()
    if values.min() >= 0 or values.max() <= 0:
        return None
    result = igl.marching_cubes(values, grid, r, r, r, 0.0)
    verts = result[0]
    if len(verts) == 0:
        return None
    rng = np.random.default_rng(config.seed + 1)
    ref = sample_surface(mesh, config.chamfer_points, rng)
    fit = verts[rng.choice(len(verts), size=min(len(verts), config.chamfer_points), replace=False)]
    d_ref, _ = cKDTree(fit).query(ref)
    d_fit, _ = cKDTree(ref).query(fit)
    return float((d_ref.mean() + d_fit.mean()) / 2.0 / size)


def summarise(per_shape: dict[str, dict]) -> dict:
    """Aggregate per-shape metrics: the median over shapes of each, plus the worst shape's near_p50."""
    keys = ["near_p50", "near_p90", "near_mean", "sign_agreement", "chamfer"]
    out = {"n_shapes": len(per_shape)}
    for k in keys:
        vals = [m[k] for m in per_shape.values() if m.get(k) is not None]
        if vals:
            out[k] = float(np.median(vals))
    if per_shape:
        out["worst_near_p50"] = float(max(m["near_p50"] for m in per_shape.values()))
        out["min_sign_agreement"] = float(min(m["sign_agreement"] for m in per_shape.values()))
    return out


def evaluate_unseen(model, category: str, data_dir=None, stems: list[str] | None = None, split: str = "test",
                    iters: int = 500, config: EvalConfig | None = None, seed: int = 0, log=print) -> dict:
    """Fit each unseen mesh with ``model.fit_codes`` (decoder frozen) and evaluate it in its source frame.

    ``stems`` defaults to the category's ``split``. -> {"summary": ..., "per_shape": {stem: metrics + fit_seconds}}.
    """
    from zoo.meshes import load_mesh

    from .categories import load_category, verify_meshes

    cat = load_category(category)
    stems = stems or cat.stems(split)
    paths = verify_meshes(cat, data_dir, stems)
    per_shape = {}
    for stem in stems:
        t0 = time.perf_counter()
        shape = model.fit_codes(paths[stem], iters=iters, seed=seed, up=cat.entry(stem).up, name=stem)
        seconds = time.perf_counter() - t0
        per_shape[stem] = {**evaluate_shape(shape, load_mesh(paths[stem]), config), "fit_seconds": seconds}
        if log is not None:
            m = per_shape[stem]
            log(f"{stem}: p50 {100 * m['near_p50']:.3f}% p90 {100 * m['near_p90']:.3f}% "
                f"sign {100 * m['sign_agreement']:.2f}% fit {seconds:.1f} s")
    summary = summarise(per_shape)
    summary["fit_seconds"] = float(np.median([m["fit_seconds"] for m in per_shape.values()]))
    return {"summary": summary, "per_shape": per_shape}


def evaluate_train(model, category: str, data_dir=None, stems: list[str] | None = None,
                   config: EvalConfig | None = None, log=print) -> dict:
    """Evaluate a model's own fitted shapes against their meshes, in the source frames."""
    from zoo.meshes import load_mesh

    from .categories import load_category, verify_meshes

    cat = load_category(category)
    stems = stems or list(model.shapes)
    paths = verify_meshes(cat, data_dir, stems)
    per_shape = {}
    for stem in stems:
        per_shape[stem] = evaluate_shape(model.shape(stem), load_mesh(paths[stem]), config)
        if log is not None:
            m = per_shape[stem]
            log(f"{stem}: p50 {100 * m['near_p50']:.3f}% p90 {100 * m['near_p90']:.3f}% sign {100 * m['sign_agreement']:.2f}%")
    return {"summary": summarise(per_shape), "per_shape": per_shape}


def main(argv: list[str] | None = None) -> None:
    """``python -m sdfzoo.pipeline.evaluate_sdf MODEL CATEGORY --test S1,S2 [--train S3,S4] --out FILE``."""
    import argparse
    import json

    import zoo
    from zoo.files import atomic_write_text

    parser = argparse.ArgumentParser(description="SDF accuracy of a model in source frames: unseen shapes after fit_codes, train shapes.")
    parser.add_argument("model", help="NAME[@X.Y.Z] or a package directory")
    parser.add_argument("category", help="category manifest the stems come from (needs $ZOO_DATA)")
    parser.add_argument("--test", default="", help="comma-separated unseen stems: fit_codes, then evaluate")
    parser.add_argument("--train", default="", help="comma-separated train stems to evaluate")
    parser.add_argument("--out", required=True, help="JSON file to write")
    args = parser.parse_args(argv)
    model = zoo.load(args.model)
    report = {"model": args.model, "category": args.category}
    for split, stems, run in (("test", args.test, evaluate_unseen), ("train", args.train, evaluate_train)):
        stems = [s for s in stems.split(",") if s]
        if stems:
            config = EvalConfig(n_near=10_000, n_uniform=10_000, chamfer_resolution=48)
            report[split] = run(model, args.category, None, stems, config=config, log=partial(print, split, flush=True))
            print(split, json.dumps(report[split]["summary"]), flush=True)
    atomic_write_text(args.out, json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
