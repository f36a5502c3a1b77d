"""`zoo bench --completion`: shape completion from depth images against its baselines, on the test-split meshes.

Each test mesh of a category is set upright on a table (z up, its base at z = 0) at a seeded random yaw and at a
real size (``SIZES``), seen by 1, 2 and 3 simulated cameras (:mod:`sdfzoo.benches.depth_views`: 640x480, 0.4-0.6 m
away, 20-40 degrees above the table, depth noise 1 mm at 0.5 m growing with the depth squared) and fitted with
``Model.fit_observation`` ("fit") and its baselines ("nearest": the nearest train shape placed by the same pose fit;
"mean": the category's mean code cloud placed by the same pose fit), beside the ceiling ``Model.fit_codes`` on
the whole true mesh (its true pose given). Reported per method and number of views:

- surface error both ways, as a fraction of the true mesh's bounding-box diagonal: the median and 90th percentile
  of |f_true| over the fitted surface (marching cubes of the fitted shape) and of |f_fit| over the true surface;
- yaw error (mugs: the direction of the handle, the horizontal principal axis of the surface signed by its third
  moment; a bottle is too near symmetric about its axis for a yaw to mean anything);
- scale error: the fitted surface's height against the true one's;
- seconds per fit.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from zoo.completion import angle_between

from . import depth_views

SIZES = {"mugs": 0.12, "bottles": 0.22}  # metres: the largest side of a test object as placed on the table
METHODS = ("fit", "nearest", "mean")
YAW_CATEGORIES = ("mugs",)


@dataclass
class PlacedObject:
    """A test mesh on the table: world-frame vertices (V, 3) and faces (F, 3), its yaw (radians) and world-from-mesh
    pose of the file's own frame is not kept: the true SDF is the placed mesh itself."""

    stem: str
    category: str
    vertices: np.ndarray
    faces: np.ndarray
    yaw: float
    diagonal: float


def place(mesh, up, size: float, rng: np.random.Generator, stem: str, category: str) -> PlacedObject:
    """``mesh`` upright (its ``up`` axis to +z), its largest side ``size`` metres, turned by a random yaw, its base on
    z = 0 and its centre within 3 cm of the origin."""
    from zoo.meshes import normalise

    unit, _ = normalise(mesh, up)
    yaw = float(rng.uniform(0.0, 2.0 * math.pi))
    c, s = math.cos(yaw), math.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = np.asarray(unit.vertices) * size @ rz.T
    vertices[:, :2] += rng.uniform(-0.03, 0.03, size=2)
    vertices[:, 2] -= vertices[:, 2].min()
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    return PlacedObject(stem, category, vertices, np.asarray(unit.faces), yaw, diagonal)


def observe(obj: PlacedObject, views: int, rng: np.random.Generator, noise: float = 0.001):
    """``views`` noisy depth images of ``obj`` on its table and the :class:`zoo.Observation` they make (object mask from
    the renderer's labels) -> (Observation, DepthViews)."""
    import zoo

    target = np.array([*obj.vertices[:, :2].mean(0), 0.5 * obj.vertices[:, 2].max()])
    images = depth_views.render(depth_views.with_table(obj.vertices, obj.faces), depth_views.table_views(target, views, rng))
    depth = depth_views.sensor_noise(images.depth, rng, noise)
    return zoo.Observation.from_depth(depth, images.K, images.T_world_camera, images.mask), images


def surface_errors(shape, obj: PlacedObject, samples: int = 20000, seed: int = 0) -> dict:
    """|f_true| over the fitted surface and |f_fit| over the true surface (fractions of the diagonal), the height
    ratio and the fitted surface's yaw."""
    import igl
    import trimesh

    from zoo.sim.surface import surface_mesh

    fv, ff = surface_mesh(shape, resolution=96)
    rng = np.random.default_rng(seed)
    true_mesh = trimesh.Trimesh(obj.vertices, obj.faces, process=False)
    fitted = trimesh.Trimesh(fv, ff, process=False)
    on_fit = trimesh.sample.sample_surface(fitted, samples, seed=int(rng.integers(1 << 31)))[0]
    on_true = trimesh.sample.sample_surface(true_mesh, samples, seed=int(rng.integers(1 << 31)))[0]
    d_true, _, _ = igl.point_mesh_squared_distance(on_fit, np.asarray(obj.vertices, dtype=np.float64),
                                                   np.asarray(obj.faces, dtype=np.int64))
    f_true = np.sqrt(d_true)
    f_fit = shape(torch.as_tensor(on_true, dtype=torch.float32)).abs().numpy()
    diag = obj.diagonal
    return {
        "fit_to_true_p50": float(np.median(f_true) / diag), "fit_to_true_p90": float(np.percentile(f_true, 90) / diag),
        "true_to_fit_p50": float(np.median(f_fit) / diag), "true_to_fit_p90": float(np.percentile(f_fit, 90) / diag),
        "scale_error": float(abs(np.ptp(fv[:, 2]) / np.ptp(obj.vertices[:, 2]) - 1.0)),
        "yaw_error_deg": float(math.degrees(angle_between(handle_yaw(on_fit), handle_yaw(on_true)))),
    }


def handle_yaw(points: np.ndarray) -> float:
    """The horizontal direction in which a surface sample (N, 3) reaches out furthest: its principal horizontal axis,
    signed towards its longer tail (a mug's handle)."""
    xy = points[:, :2] - points[:, :2].mean(0)
    _, _, vt = np.linalg.svd(xy, full_matrices=False)
    axis = vt[0]
    along = xy @ axis
    if (along**3).mean() < 0:
        axis = -axis
    return math.atan2(axis[1], axis[0])


# --------------------------------------------------------------------------- the run

JSON_NAME, PNG_NAME = "completion.json", "completion.png"
TABLE_HEADER = ["category", "views", "method", "objects", "surface p50 %", "fit->true p50 %", "true->fit p50 %",
                "fit->true p90 %", "yaw err deg p50", "scale err p50 %", "s/fit p50"]


def run_completion_benchmark(out_dir, categories=("mugs", "bottles"), views=(1, 2, 3), limit: int | None = None,
                             seed: int = 0, threads: int | None = None, ceiling: bool = True,
                             progress=lambda *_: None):
    """Every test mesh of ``categories`` seen from each number of ``views``, fitted by each method (and the ceiling);
    per-object rows and per (category, views, method) medians written to ``out_dir/completion.json`` and a PNG."""
    from pathlib import Path

    import zoo
    from sdfzoo.pipeline.categories import load_category, resolve_data_dir
    from zoo.completion import category_prior
    from zoo.files import atomic_write_text
    from zoo.meshes import load_mesh

    from .solvers import machine_info

    if threads:
        torch.set_num_threads(threads)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in categories:
        category = load_category(name)
        root = resolve_data_dir(None, category)
        model = zoo.load(name)
        started = time.perf_counter()
        category_prior(model)
        prior_seconds = time.perf_counter() - started
        for i, stem in enumerate(category.test_stems[:limit]):
            entry = category.entry(stem)
            mesh = load_mesh(root / entry.file)
            obj = place(mesh, entry.up, SIZES[name], np.random.default_rng([seed, i]), stem, name)
            if ceiling:
                rows.append(_ceiling_row(model, mesh, entry.up, obj, seed))
            for n in views:
                obs, _ = observe(obj, n, np.random.default_rng([seed, i, n]))
                for method in METHODS:
                    started = time.perf_counter()
                    shape = model.fit_observation(obs, codes=method, seed=seed)
                    seconds = time.perf_counter() - started
                    errors = surface_errors(shape, obj, seed=seed)
                    rows.append({"category": name, "stem": stem, "views": n, "method": method, "seconds": seconds,
                                 "points": len(obs), "start_shape": shape.fit["pose"]["start_shape"],
                                 "residual_mm_p50": shape.fit["residual_mm"]["median"], **errors})
                    progress(f"{name} {stem} views={n} {method}: surface p50 {100 * _symmetric(errors):.2f}% "
                             f"of the diagonal, {seconds:.1f} s")
        rows.append({"category": name, "method": "prior", "seconds": prior_seconds})
    report = {"machine": machine_info(), "config": {"categories": list(categories), "views": list(views), "seed": seed,
                                                     "sizes_m": SIZES, "noise_m_at_half_metre": 0.001,
                                                     "image": [depth_views.WIDTH, depth_views.HEIGHT]},
              "rows": rows, "summary": summarise(rows)}
    path = out_dir / JSON_NAME
    atomic_write_text(path, json.dumps(report, indent=1) + "\n")
    _plot(report, out_dir / PNG_NAME)
    return path


def _ceiling_row(model, mesh, up, obj: PlacedObject, seed: int) -> dict:
    """``fit_codes`` on the whole true mesh, placed by the true pose: the best a code cloud can do."""
    import tempfile
    from pathlib import Path

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        placed = mesh.copy()
        placed.vertices = obj.vertices  # the file's faces, the placed vertices: the true object in the world
        path = Path(tmp) / f"{obj.stem}.ply"
        placed.export(path)
        shape = model.fit_codes(path, up="z", seed=seed)
    seconds = time.perf_counter() - started
    return {"category": obj.category, "stem": obj.stem, "views": 0, "method": "ceiling", "seconds": seconds,
            **surface_errors(shape, obj, seed=seed)}


def _symmetric(errors: dict) -> float:
    """The headline surface error: the mean of the two directions' medians."""
    return 0.5 * (errors["fit_to_true_p50"] + errors["true_to_fit_p50"])


def summarise(rows: list[dict]) -> list[dict]:
    """Medians over objects per (category, views, method)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["method"] != "prior":
            groups.setdefault((r["category"], r["views"], r["method"]), []).append(r)
    out = []
    for (category, views, method), group in sorted(groups.items()):
        med = lambda key, group=group: float(np.median([g[key] for g in group]))
        out.append({"category": category, "views": views, "method": method, "objects": len(group),
                    "surface_p50": float(np.median([_symmetric(g) for g in group])),
                    "fit_to_true_p50": med("fit_to_true_p50"), "true_to_fit_p50": med("true_to_fit_p50"),
                    "fit_to_true_p90": med("fit_to_true_p90"), "true_to_fit_p90": med("true_to_fit_p90"),
                    "yaw_error_deg_p50": med("yaw_error_deg") if category in YAW_CATEGORIES else None,
                    "scale_error_p50": med("scale_error"), "seconds_p50": med("seconds")})
    return out


def format_table(report: dict) -> list[list[str]]:
    rows = []
    for s in report["summary"]:
        yaw = "-" if s["yaw_error_deg_p50"] is None else f"{s['yaw_error_deg_p50']:.1f}"
        rows.append([s["category"], str(s["views"]) if s["views"] else "whole mesh", s["method"], str(s["objects"]),
                     f"{100 * s['surface_p50']:.2f}", f"{100 * s['fit_to_true_p50']:.2f}", f"{100 * s['true_to_fit_p50']:.2f}",
                     f"{100 * s['fit_to_true_p90']:.2f}", yaw, f"{100 * s['scale_error_p50']:.1f}", f"{s['seconds_p50']:.1f}"])
    return rows


def _plot(report: dict, path) -> None:
    """Surface error (median over objects) against the number of views, per category and method."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    categories = report["config"]["categories"]
    fig, axes = plt.subplots(1, len(categories), figsize=(5 * len(categories), 4), squeeze=False)
    for ax, category in zip(axes[0], categories):
        summary = [s for s in report["summary"] if s["category"] == category]
        for method in METHODS:
            pts = sorted((s["views"], 100 * s["surface_p50"]) for s in summary if s["method"] == method)
            if pts:
                ax.plot(*zip(*pts), marker="o", label=method)
        ceiling = [100 * s["surface_p50"] for s in summary if s["method"] == "ceiling"]
        if ceiling:
            ax.axhline(ceiling[0], color="k", linestyle="--", label="fit_codes, whole mesh")
        ax.set_xlabel("views")
        ax.set_ylabel("surface error, median, % of diagonal")
        ax.set_title(category)
        ax.set_xticks(report["config"]["views"])
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
