"""How far a scenario's end moves when its start moves by a micrometre: the scale of its trajectory bars.

Runs a scenario of benches/sim_scenarios.py one way (``investigations proxy``'s ``WAYS``: the default proxy path,
the coherent one, or the full from-scratch reference) from its scene's start, then again with the moving body's
start shifted by ``--shift`` (m) along x, -x, y and -y, and reports how far each end lies from the unshifted run's
(and, for bolt-nut, along the bolt). A landing or sliding contact amplifies a small change, so two paths whose
contacts differ by rounding end this far apart even when each is right: read the accuracy bars of
``investigations proxy --sim`` against it. One torch thread:

    python -m investigations sensitivity --scene mug-rack --way proxy --out out/sensitivity-mug-rack.json
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from investigations.report import write_report

DIRECTIONS = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0)}


def end_position(scenario: str, way: str, shift: np.ndarray) -> np.ndarray:
    """The moving body's end position (3,) (m) of ``scenario`` run ``way``, its start shifted by ``shift`` (3,) (m)."""
    import mujoco

    from investigations.proxy import WAYS, start_refined
    from sdfzoo.benches.sim_scenarios import advance

    spec, sim, extra, _ = start_refined(scenario, **WAYS[way])
    moving = next(name for name, body in sim.bodies.items() if body.joint != "fixed")
    joint = sim.model.body(moving).jntadr[0]
    start = sim.model.jnt_qposadr[joint]
    sim.data.qpos[start:start + 3] += shift  # a free joint's position
    mujoco.mj_forward(sim.model, sim.data)
    for _ in range(int(round(sim.seconds / sim.dt))):
        advance(spec, sim, extra)
    return sim.pose(moving)[:3, 3].copy()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mug-rack", help="a scenario of benches/sim_scenarios.py")
    parser.add_argument("--way", default="proxy", choices=["full", "coherent", "proxy"])
    parser.add_argument("--shift", type=float, default=1e-6, help="m, how far the start moves")
    parser.add_argument("--out", default="out/sensitivity.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    base = end_position(args.scene, args.way, np.zeros(3))
    rows = {}
    for label, direction in DIRECTIONS.items():
        end = end_position(args.scene, args.way, args.shift * np.asarray(direction, dtype=np.float64))
        rows[label] = {"end_from_unshifted_mm": 1e3 * float(np.linalg.norm(end - base)),
                       "along_z_mm": 1e3 * float(end[2] - base[2])}
        print(f"{args.scene} {args.way}, start {label} {args.shift * 1e6:g} um: end {rows[label]['end_from_unshifted_mm']:.3f} mm "
              f"from the unshifted run's ({rows[label]['along_z_mm']:+.4f} mm along z)")
    write_report(args.out, {"scenario": args.scene, "way": args.way, "shift_m": args.shift, "shifted": rows}, __name__, argv)


if __name__ == "__main__":
    main()
