"""How deep the torque-driven nut sinks into the bolt on each contact path, and which part of the default path adds depth.

The nut of ``scenes/sim-bolt-nut.toml`` turned by the Bolt-Nut scenario's torque (a feed-forward and a speed servo,
``benches/sim_scenarios.py``), each path in its own process with one torch thread: ``full`` (amortized from scratch,
the reference), ``default`` (the proxy; lazily baked, which gives the same trajectory as baked ahead),
``coherence`` (``proxy=False``) and ``exact-reduce`` (the proxy path with the reduction run on the SDF's own depths
of every usable contact instead of the proxy's: no thinning, every usable row answered by the SDF, then reduced).
Reports the deepest penetration over steps 40-60 (the path's own contacts, and a Frank-Wolfe-100 yardstick at its
three deepest steps), the nut's height at step 60 and the time per step.

    python -m investigations nut_depth --out out/nut-depth.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

VARIANTS = ("full", "default", "coherence", "exact-reduce")

ONE_RUN = """
import json, sys, time
import numpy as np, torch
torch.set_num_threads(1)
import zoo, zoo.sim
from sdfzoo.benches.sim_scenarios import _nut_torque
variant, steps = sys.argv[1], int(sys.argv[2])
options = {"full": dict(coherence=False), "coherence": dict(proxy=False),
           "exact-reduce": dict(proxy="lazy", reduce=False)}.get(variant, dict(proxy="lazy"))
if variant == "exact-reduce":
    from zoo.sim import world
    from zoo.sim.contacts import reduce_contacts
    answered = world.World.exact_answers

    def answered_then_reduced(found):
        out = []
        for pair, contacts, keep, arrays in answered(found):
            if len(keep):
                points, depths, normals = arrays
                keep = keep[reduce_contacts(points[keep], depths[keep], normals[keep], normals[keep],
                                            merge_tol=world.World.merge_distance(pair.sdf_body))]
            out.append((pair, contacts, keep, arrays))
        return out

    world.World.exact_answers = staticmethod(answered_then_reduced)
sim = zoo.sim.load_scene("sim-bolt-nut", **options)
sim.build()
poses, own, heights = [], [], []
started = time.perf_counter()
for _ in range(steps):
    _nut_torque(sim, {})
    sim.step()
    poses.append({name: sim.pose(name) for name in ("bolt", "nut")})
    own.append(sim.log[-1].max_penetration)
    heights.append(float(sim.pose("nut")[2, 3]))
wall = time.perf_counter() - started
window = range(40, min(61, steps))
yardstick = 0.0
for k in sorted(window, key=lambda k: -own[k])[:3]:
    found = zoo.collide(sim.bodies["bolt"].sdf, sim.bodies["nut"].mesh, poses[k]["bolt"], poses[k]["nut"], margin=0.0,
                        method="fw", iters=100)
    yardstick = max(yardstick, own[k], -float(found.depths.min()) if len(found) else 0.0)
print(json.dumps({"variant": variant, "deepest_40_60_mm": 1e3 * max(own[k] for k in window),
                  "yardstick_40_60_mm": 1e3 * yardstick, "height_at_60_m": heights[60],
                  "ms_per_step": 1e3 * wall / steps}))
"""


def one_run(variant: str, steps: int) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", ONE_RUN, variant, str(steps)], env=env, capture_output=True, text=True,
                          timeout=7200)
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", action="append", choices=VARIANTS, default=[], help="default: all")
    parser.add_argument("--steps", type=int, default=70)
    parser.add_argument("--out", default="out/nut-depth.json")
    args = parser.parse_args(argv)
    runs = [one_run(variant, args.steps) for variant in args.variant or VARIANTS]
    full = next((r for r in runs if r["variant"] == "full"), None)
    for run in runs:
        ratio = f", {run['deepest_40_60_mm'] / full['deepest_40_60_mm']:.2f}x the full path's" if full else ""
        print(f"{run['variant']:>12}: deepest over steps 40-60 {run['deepest_40_60_mm']:.4f} mm (yardstick "
              f"{run['yardstick_40_60_mm']:.4f}){ratio}; nut at {1e3 * run['height_at_60_m']:.4f} mm at step 60; "
              f"{run['ms_per_step']:.1f} ms a step")
    write_report(args.out, {"runs": runs}, "nut_depth", argv)


if __name__ == "__main__":
    main()
