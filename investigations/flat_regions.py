"""What a simulation's flat-region pass does to each scenario's meshes: their faces as given, merged and refined.

For each scenario of benches/sim_scenarios.py (``--scene``, repeatable; all by default) and each ``--refine`` (the
fixed meshes subdivided that many times first, 4x their faces each, as ``investigations proxy --refine``), builds
the simulation and prints per mesh pair: the faces of the mesh as given, after
:func:`zoo.sim.flat_regions.merge_flat_regions` (timed on its own, one call) and after the refinement to the SDF's
size (the mesh the collider answers on), with the area the merge changed:

    python -m investigations flat_regions --refine 0 --refine 1 --refine 2 --out out/flat-regions.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from investigations.report import write_report


def _area(vertices: np.ndarray, faces: np.ndarray) -> float:
    tri = vertices[faces]
    return 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def pair_rows(name: str, refine: int) -> list[dict]:
    """One row per mesh pair of scenario ``name`` built with its fixed meshes subdivided ``refine`` times."""
    from investigations.proxy import start_refined
    from zoo.sim.contacts import refined_pieces
    from zoo.sim.flat_regions import merge_flat_regions
    from zoo.sim.pairs import MeshPair

    _, sim, _, _ = start_refined(name, refine)
    rows = []
    for pair in sim.world.pairs:
        if not isinstance(pair, MeshPair):  # no mesh refined once
            continue
        start = time.perf_counter()
        merged, _ = merge_flat_regions(pair.vertices, pair.faces, pair.sdf_body.flat_width,
                                       refined_pieces(pair.sdf_body.max_edge))
        seconds = time.perf_counter() - start
        area = _area(pair.vertices, pair.faces)
        rows.append({
            "scenario": name, "refine": refine, "pair": [pair.sdf_body.name, sim.model.body(pair.body).name],
            "faces": len(pair.faces), "merged": len(merged), "refined": len(pair.refined.faces),
            "merge_s": round(seconds, 3), "area_change": abs(_area(pair.vertices, merged) - area) / area,
        })
    return rows


def main(argv=None) -> None:
    from sdfzoo.benches.sim_scenarios import SCENARIOS, require_meshes

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", choices=sorted(SCENARIOS), help="a scenario (repeatable; default all)")
    parser.add_argument("--refine", type=int, action="append", help="subdivide the fixed meshes this many times first "
                        "(repeatable: one build each; default 0)")
    parser.add_argument("--out", default="out/flat-regions.json")
    args = parser.parse_args(argv)
    require_meshes()
    rows = []
    for name in args.scene or sorted(SCENARIOS):
        for refine in args.refine or [0]:
            for row in pair_rows(name, refine):
                print(json.dumps(row))
                rows.append(row)
    write_report(args.out, {"rows": rows}, __name__, argv)
