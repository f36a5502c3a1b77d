"""`zoo demo`: a scene on bundled defaults, its contacts, and error against run time.

Needs nothing outside the package: the rack is procedural and the SDF comes from the models
shipped with sdfzoo.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

import zoo

from .scenes import run_scene, scene_from_dict, write_outputs


def demo_scene_spec() -> dict:
    """A torus "handle" hung on the procedural rack's peg, pressing 0.5 mm into it."""
    x = 0.06  # along the peg, which rises at 20 degrees from (0, 0, 0.20)
    peg_top = 0.20 + x * np.tan(np.radians(20.0)) + 0.006
    major, minor = 0.035, 0.008
    return {
        "name": "demo-ring-rack",
        "method": "fw",
        "margin": 1e-3,
        "sdf": {
            "analytic": "torus",
            "params": {"major": major, "minor": minor},
            # axis along x so the peg passes through the hole; the hole's top rests on the peg
            "pose": {"translation": [x, 0.0, peg_top - (major - minor) - 5e-4], "rotation_deg": [0, 90, 0]},
        },
        "mesh": {"procedural": "rack"},
    }


def error_vs_runtime(scene, contacts_fw, iters=(1, 2, 5, 10, 20, 50)) -> list[dict]:
    """Optimality (eq. 12) and time of Frank-Wolfe at several iteration counts on the scene's candidates."""
    from zoo.collide import candidate_triangles
    from zoo.geometry import invert_pose, transform_points

    sdf_from_mesh = invert_pose(torch.as_tensor(scene.sdf_pose, dtype=torch.float64)) @ torch.as_tensor(scene.mesh_pose)
    verts = transform_points(sdf_from_mesh.float(), torch.as_tensor(np.asarray(scene.mesh.vertices), dtype=torch.float32))
    tris = verts[torch.as_tensor(np.asarray(scene.mesh.faces))]
    tris = tris[candidate_triangles(scene.sdf, tris, scene.margin)]
    rows = []
    for k in iters:
        t0 = time.perf_counter()
        bary = zoo.solvers.frank_wolfe(scene.sdf, tris, iters=k)
        dt = time.perf_counter() - t0
        gap = zoo.solvers.optimality(scene.sdf, tris, bary)
        rows.append({"method": f"fw-{k}", "optimality_mean": float(gap.mean()), "optimality_p90": float(gap.quantile(0.9)),
                     "ms_per_triangle": 1e3 * dt / max(len(tris), 1)})
    return rows


def run_demo(out_dir: str = "out/demo") -> dict:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    scene = scene_from_dict(demo_scene_spec())
    contacts = run_scene(scene)
    paths = write_outputs(scene, contacts, Path(out_dir))

    table = Table(title=f"{scene.name}: {len(contacts)} contacts, {contacts.n_candidates} candidates of {contacts.n_triangles} triangles")
    for col in ("triangle", "point (m)", "depth (mm)", "normal"):
        table.add_column(col)
    for t, p, d, n in list(zip(contacts.triangles, contacts.points, contacts.depths, contacts.normals))[:15]:
        table.add_row(str(int(t)), np.array2string(p.numpy(), precision=4, suppress_small=True), f"{1e3 * float(d):+.3f}", np.array2string(n.numpy(), precision=2))
    console.print(table)
    if len(contacts) > 15:
        console.print(f"... {len(contacts) - 15} more in {paths['json']}")

    rows = error_vs_runtime(scene, contacts)
    et = Table(title="error against run time on the candidate triangles")
    for col in ("method", "optimality mean", "optimality p90", "ms / triangle"):
        et.add_column(col)
    for r in rows:
        et.add_row(r["method"], f"{r['optimality_mean']:.2e}", f"{r['optimality_p90']:.2e}", f"{r['ms_per_triangle']:.4f}")
    console.print(et)
    console.print(f"wrote {paths['json']} and {paths['png']}")
    return {"contacts": len(contacts), "paths": paths, "error_vs_runtime": rows}
