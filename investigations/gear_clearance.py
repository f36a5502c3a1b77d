"""How close the Gear-Gear pair comes as the gears turn in mesh, with the large gear as a NeuralSDF and as its mesh.

The medium gear's surface (points sampled on its mesh) is turned in exact mesh with the large gear (the teeth
ratio) through one tooth period of the large gear, at each phase offset of the medium gear about its own axis
(degrees; 0 is the assembly's, positive counter-clockwise seen from +z) and with the medium gear's axis moved
``--shift`` m along +x away from the large gear's. For each offset it gives the smallest signed distance of
those points to the large gear: the exact distance to its mesh, and the NeuralSDF's. A pair that turns in mesh
without jamming needs an offset range where the clearance stays positive (the backlash); the exact column is
the meshes' own, the NeuralSDF column what a simulation on the model sees.

    python -m investigations gear_clearance --shift 0 --out out/gear-clearance.json
"""

from __future__ import annotations

import argparse

import numpy as np

from investigations.report import write_report
from sdfzoo.benches.sim_scenarios import GEAR_CENTRES, GEAR_FILES, count_teeth, data_mesh


def _turn(points: np.ndarray, centre, angle: float) -> np.ndarray:
    """Points (N, 3) turned by ``angle`` rad about the z axis through ``centre`` (2,)."""
    c, s = np.cos(angle), np.sin(angle)
    x, y = points[:, 0] - centre[0], points[:, 1] - centre[1]
    out = points.copy()
    out[:, 0], out[:, 1] = centre[0] + c * x - s * y, centre[1] + s * x + c * y
    return out


def clearance(model: str = "gears", offsets_deg=np.arange(-2.0, 2.01, 0.25), shift: float = 0.0, phases: int = 7,
              samples: int = 300_000, seed: int = 0) -> list[dict]:
    """Per offset: the smallest exact and NeuralSDF distances (m) of the medium gear to the large one over one tooth
    period of the large gear (``phases`` poses), the medium's axis moved ``shift`` m along +x."""
    import torch
    import trimesh

    import zoo
    from zoo.meshes import ExactMeshSDF

    large, medium = data_mesh(GEAR_FILES["large"]), data_mesh(GEAR_FILES["medium"])
    teeth = {name: count_teeth(np.asarray(m.vertices), GEAR_CENTRES[name]) for name, m in (("large", large), ("medium", medium))}
    ratio = teeth["large"] / teeth["medium"]
    shape = zoo.load(model).shape("industreal_gear_large")
    exact = ExactMeshSDF(large)
    c_large = np.asarray(GEAR_CENTRES["large"])
    c_medium = np.asarray(GEAR_CENTRES["medium"]) + [shift, 0.0]
    tip = float(np.hypot(*(np.asarray(large.vertices)[:, :2] - c_large).T).max())
    points = np.asarray(trimesh.sample.sample_surface(medium, samples, seed=seed)[0])
    points[:, 0] += shift
    rows = []
    for offset in offsets_deg:
        worst_exact = worst_model = np.inf
        for k in range(phases):
            turn = k * (2 * np.pi / teeth["large"]) / phases
            # the large gear turned by ``turn``, the medium by -ratio * turn (plus the offset): medium points in the large's frame
            q = _turn(_turn(points, c_medium, -ratio * turn + np.radians(offset)), c_large, -turn)
            q = q[np.hypot(q[:, 0] - c_large[0], q[:, 1] - c_large[1]) < tip + 3e-4]
            with torch.no_grad():
                worst_model = min(worst_model, float(shape(torch.as_tensor(q, dtype=torch.float32)).min()))
            worst_exact = min(worst_exact, float(exact(torch.as_tensor(q)).min()))
        rows.append({"offset_deg": float(offset), "exact_m": worst_exact, "neural_m": worst_model})
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="gears", help="the gears model (name, name@version or a package folder)")
    parser.add_argument("--shift", type=float, default=0.0, help="m: the medium gear's axis moved this far along +x")
    parser.add_argument("--out", default="out/gear-clearance.json", help="JSON file to write")
    args = parser.parse_args(argv)
    rows = clearance(args.model, shift=args.shift)
    print("| offset deg | exact mm | NeuralSDF mm |\n|---|---|---|")
    for r in rows:
        print(f"| {r['offset_deg']:+.2f} | {1e3 * r['exact_m']:.3f} | {1e3 * r['neural_m']:.3f} |")
    write_report(args.out, {"model": args.model, "shift_m": args.shift, "rows": rows}, __name__, argv)
