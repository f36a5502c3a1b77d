"""The faces a simulation step must answer: how many of a scenario's mesh faces lie within the margin, and their shape.

Runs a scenario of benches/sim_scenarios.py (its scene, control and default settings) for ``--steps``
steps, then collides each (SDF body, mesh body) pair's mesh as the simulation holds it (refined once at
build) with ``zoo.collide`` from scratch at that pose, and prints per pair: the mesh's faces, those whose
minimum lies within the margin (the contacts any method must find), their depths and their widths
(twice the area over the longest edge) and lengths. A profile of what a step costs, not a timing:

    python -m investigations contact_faces --scene mug-rack --steps 80 [--refine 2]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from investigations.report import write_report
from zoo.geometry import edge_lengths

PERCENTILES = (0, 10, 50, 90, 100)


def face_shapes(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(widths (F,), longest edges (F,)) of the triangles (F, 3, 3): a sliver is narrow and long."""
    longest = edge_lengths(torch.from_numpy(triangles)).amax(dim=1).numpy()
    area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    return 2.0 * area / np.maximum(longest, 1e-300), longest


def _mm_percentiles(values: np.ndarray) -> dict:
    return {f"p{q}": round(1e3 * float(np.percentile(values, q)), 4) for q in PERCENTILES} if len(values) else {}


def simulated(name: str, steps: int, refine: int = 0):
    """Scenario ``name``'s simulation (its scene, control and default settings) after ``steps`` steps, its fixed
    meshes subdivided ``refine`` times first (4x their faces each, as ``investigations proxy --refine``)."""
    from investigations.proxy import start_refined
    from sdfzoo.benches.sim_scenarios import advance

    scenario, sim, extra, _ = start_refined(name, refine)
    for _ in range(steps):
        advance(scenario, sim, extra)
    return sim


def faces_within_margin(sim, sdf_name: str, mesh_name: str):
    """``zoo.collide``'s contacts (amortized, from scratch, at ``sim``'s margin) of the pair's mesh as the
    simulation holds it (refined once at build), at the current poses; None where the pair is refined near
    the SDF at every step instead (no fixed mesh)."""
    import zoo
    from zoo.sim.pairs import MeshPair

    pair = sim.world.pair(sdf_name, mesh_name)
    if not isinstance(pair, MeshPair):
        return None
    mesh = (torch.as_tensor(pair.refined.vertices, dtype=torch.float32), torch.as_tensor(pair.refined.faces))
    return zoo.collide(sim.bodies[sdf_name].sdf, mesh, sdf_pose=torch.from_numpy(sim.pose(sdf_name)),
                       mesh_pose=torch.from_numpy(pair.surface_pose(sim.data)), margin=sim.margin, method="amortized")


def contact_faces(name: str, steps: int, refine: int = 0) -> list[dict]:
    """Per mesh pair of scenario ``name`` after ``steps`` steps: the faces within the margin (see the module docstring)."""
    sim = simulated(name, steps, refine)
    rows = []
    for pair in sim.world.pairs:
        sdf_name, mesh_name = pair.sdf_body.name, sim.model.body(pair.body).name
        contacts = faces_within_margin(sim, sdf_name, mesh_name)
        if contacts is None:
            continue
        faces = np.asarray(contacts.triangles)
        refined = pair.refined
        widths, lengths = face_shapes(refined.vertices[refined.faces[faces]])
        rows.append({
            "pair": [sdf_name, mesh_name], "step": steps, "refine": refine, "margin_mm": 1e3 * sim.margin,
            "mesh_faces": len(refined.faces), "own_faces": len(pair.faces),
            "within_margin": len(faces), "own_faces_within_margin": len(refined.cover.under(faces)),
            "depth_mm": _mm_percentiles(np.asarray(contacts.depths)),
            "width_mm": _mm_percentiles(widths), "longest_edge_mm": _mm_percentiles(lengths),
        })
    return rows


def main(argv=None) -> None:
    from sdfzoo.benches.sim_scenarios import SCENARIOS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=sorted(SCENARIOS), required=True)
    parser.add_argument("--steps", type=int, default=80, help="steps simulated before counting (default 80)")
    parser.add_argument("--refine", type=int, default=0, help="subdivide the fixed meshes this many times (4x faces each)")
    parser.add_argument("--out", default="out/contact-faces.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    rows = contact_faces(args.scene, args.steps, args.refine)
    for row in rows:
        print(json.dumps(row))
    write_report(args.out, {"scenario": args.scene, "steps": args.steps, "refine": args.refine, "rows": rows}, __name__, argv)
