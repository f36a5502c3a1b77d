"""How deep each contact path lets bodies sink, and where they end, on scenes no tuning of the fast path used.

Each scene runs on the default path (the proxy, baked lazily: the same trajectory as baked ahead, its reduction on
the proxy's depths), on the proxy with ``reduce="exact"`` (the reduction on the NeuralSDF's depths) and on the full
path (amortized from scratch, ``coherence=False``, the reference), each in its own process with one torch thread:

- ``nut-torque``: the nut of ``scenes/sim-bolt-nut.toml`` turned by the Bolt-Nut scenario's torque
  (``benches/sim_scenarios.py``: a feed-forward and a speed servo), 70 steps;
- ``nut-torque-x2``: the same nut under twice the feed-forward, servoed to twice the speed;
- ``nut-heavy``: the scenario's torque on a nut four times as heavy (its mass and inertia);
- ``mug-rack-2mm``: the mug of ``scenes/mug-rack.toml`` released 2 mm above its hanging pose on the peg, 0.3 s;
- ``mug-drop-5cm``: the same mug dropped from 5 cm onto the rack, 0.4 s;
- ``gear-gear``: ``scenes/sim-gear-gear.toml`` over ``zoo bench --sim``'s 0.2 s (200 steps), the medium gear tracked.

Reports per scene and path the deepest penetration (the path's own contacts; the nut's over steps 40-60, the
mug's over the whole run) and the median over those steps of a step's deepest and of its contacts, where the tracked
body ends (the nut along the bolt, the mug's position), the time per step, and each proxy path against the full path.

With ``--starts 5``, each run is repeated from four more starts, the tracked body's shifted by ``--shift`` (1 um
by default) along +x, -x, +y and -y (``investigations sensitivity``'s directions; a hinged body, the gear, turned
so that a point 1 cm from its axis moves by +1, -1, +2 and -2 shifts): on the threads one step's
deepest penetration moves by tens of micrometres from one contact choice to the next, so the deepest of one run is
a noisy figure. Each path is then also compared by the median over the starts of each start's deepest, and the
spread of the full path's own deepest over the starts is the scale to read a ratio against.

With ``--friction F``, every scene runs with friction F in place of its own (the gears with 0: their deepest comes
from a jam that friction at a tooth's chamfered rim makes, docs/proxy.md).

With ``--yardstick``, each path's poses are also measured by one yardstick, whatever the path: at the poses each step
of the window detected its contacts at, ``zoo bench --sim``'s (``benches/sim_bench.py``'s ``yardstick_depth``: FW-100,
margin 0, every NeuralSDF-mesh pair; slow: some 10,000 of the nut's faces lie within microns of the bolt).

    python -m investigations fidelity --out out/fidelity.json
    python -m investigations fidelity --path default --path full --starts 5 --out out/fidelity-starts.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

# scene name -> (scene file, steps, the window of steps whose deepest penetration counts, options of the run)
SCENES = {
    "nut-torque": ("sim-bolt-nut", 70, (40, 61), {"torque": 1.0, "speed": 1.0, "mass": 1.0}),
    "nut-torque-x2": ("sim-bolt-nut", 70, (40, 61), {"torque": 2.0, "speed": 2.0, "mass": 1.0}),
    "nut-heavy": ("sim-bolt-nut", 70, (40, 61), {"torque": 1.0, "speed": 1.0, "mass": 4.0}),
    "mug-rack-2mm": ("mug-rack", 150, (0, 150), {"drop": 0.002}),
    "mug-drop-5cm": ("mug-rack", 200, (0, 200), {"drop": 0.05}),
    "gear-gear": ("sim-gear-gear", 200, (0, 200), {"body": "medium"}),
}
PATHS = {"default": {"proxy": "lazy"}, "exact": {"proxy": "lazy", "reduce": "exact"}, "full": {"coherence": False}}

ONE_RUN = """
import json, sys, time
import numpy as np, torch
torch.set_num_threads(1)
import zoo, zoo.sim
from sdfzoo.benches.sim_bench import sdf_mesh_pairs, yardstick_depth
from sdfzoo.benches.sim_scenarios import NUT_KV, NUT_SPEED, NUT_TORQUE
scene, steps, lo, hi, options, path = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), json.loads(sys.argv[5]), json.loads(sys.argv[6])
yardstick, shift, friction = sys.argv[7] == "yardstick", json.loads(sys.argv[8]), json.loads(sys.argv[9])
nut = "torque" in options
sim = zoo.sim.load_scene(scene, drop=options.get("drop"), **path, **({} if friction is None else {"friction": friction}))
sim.build()
body = options.get("body", "nut" if nut else "sdf")  # scenes/mug-rack.toml names its mug "sdf"
joint = sim.model.body(body).jntadr[0]
start = sim.model.jnt_qposadr[joint]
if any(shift):  # the body's start moved: a free joint's position, a hinge's angle (a point 1 cm out moves by the shift)
    import mujoco
    if sim.model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
        sim.data.qpos[start:start + 3] += shift
    else:
        sim.data.qpos[start] += (shift[0] + 2 * shift[1]) / 0.01
    mujoco.mj_forward(sim.model, sim.data)
if nut:
    i = sim.bodies["nut"].body_id
    sim.model.body_mass[i] *= options["mass"]
    sim.model.body_inertia[i] *= options["mass"]
pairs = sdf_mesh_pairs(sim)
deepest, contacts, poses, started = [], [], [], time.perf_counter()
for k in range(steps):
    if yardstick and lo <= k < hi:
        poses.append({name: sim.pose(name) for pair in pairs for name in pair})
    if nut:
        spin = float(sim.velocity("nut")[5])
        sim.data.xfrc_applied[i, 3:] = (0.0, 0.0, options["torque"] * NUT_TORQUE + NUT_KV * (options["speed"] * NUT_SPEED - spin))
    sim.step()
    deepest.append(sim.log[-1].max_penetration)
    contacts.append(sim.log[-1].contacts)
wall = time.perf_counter() - started
row = {"deepest_mm": 1e3 * max(deepest[lo:hi]), "median_deepest_mm": 1e3 * float(np.median(deepest[lo:hi])),
       "median_contacts": float(np.median(contacts[lo:hi])), "end_m": sim.pose(body)[:3, 3].tolist(),
       "end_qpos": float(sim.data.qpos[start]),
       "ms_per_step": 1e3 * wall / steps}
if yardstick:
    measured = [yardstick_depth(sim, pairs, pose) for pose in poses]
    row.update(yardstick_mm=1e3 * max(measured), median_yardstick_mm=1e3 * float(np.median(measured)))
print(json.dumps(row))
"""


STARTS = {"as is": (0, 0, 0), "+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0)}  # --starts' order


def one_run(scene: str, path: str, yardstick: bool = False, start: str = "as is", shift: float = 0.0,
            friction: float | None = None) -> dict:
    """One run of ``scene`` on ``path`` in its own process, the tracked body's start moved ``shift`` (m) along
    ``start`` (a key of ``STARTS``), with ``friction`` for the scene's (None: its own)."""
    file, steps, (lo, hi), options = SCENES[scene]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    moved = [shift * c for c in STARTS[start]]
    done = subprocess.run([sys.executable, "-c", ONE_RUN, file, str(steps), str(lo), str(hi), json.dumps(options),
                           json.dumps(PATHS[path]), "yardstick" if yardstick else "own", json.dumps(moved),
                           json.dumps(friction)],
                          env=env, capture_output=True, text=True, timeout=7200)
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    return {"scene": scene, "path": path, "start": start, **json.loads(done.stdout.strip().splitlines()[-1])}


def over_starts(scene: str, runs: list[dict]) -> dict:
    """Each path's deepest over the starts of ``scene``: per start, their median, least and most, and the
    default's median against the full path's."""
    by_path = {}
    for run in runs:
        by_path.setdefault(run["path"], []).append(run["deepest_mm"])
    out = {"scene": scene, "starts": len(next(iter(by_path.values())))}
    for path, depths in by_path.items():
        out[path] = {"deepest_mm": depths, "median_mm": float(np.median(depths)), "least_mm": min(depths),
                     "most_mm": max(depths)}
    if "full" in by_path:
        for path in (p for p in by_path if p != "full"):
            out[f"{path}_median_ratio"] = out[path]["median_mm"] / out["full"]["median_mm"]
    return out


def compared(default: dict, full: dict) -> dict:
    """The default path against the full one: depth ratio, and how far apart they end (the nut along the bolt)."""
    ends = [default["end_m"], full["end_m"]]
    if default["scene"].startswith("nut"):
        apart = abs(ends[0][2] - ends[1][2])
    elif default["scene"] == "gear-gear":  # a hinge: how far a point 1 cm from the axis ends apart
        apart = 0.01 * abs(default["end_qpos"] - full["end_qpos"])
    else:
        apart = sum((a - b) ** 2 for a, b in zip(*ends)) ** 0.5
    ratio = lambda a, b: a / b if b else None  # noqa: E731  # the gears' median step has no contact
    return {"scene": default["scene"], "depth_ratio": default["deepest_mm"] / full["deepest_mm"],
            "median_depth_ratio": ratio(default["median_deepest_mm"], full["median_deepest_mm"]),
            "ends_apart_mm": 1e3 * apart, "speedup": full["ms_per_step"] / default["ms_per_step"],
            **({"yardstick_ratio": default["yardstick_mm"] / full["yardstick_mm"]} if "yardstick_mm" in full else {})}


def main(argv=None) -> None:
    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", choices=sorted(SCENES), default=[], help="default: all")
    parser.add_argument("--path", action="append", choices=sorted(PATHS), default=[],
                        help="default: all (a comparison needs full)")
    parser.add_argument("--yardstick", action="store_true",
                        help="also measure each path's poses by FW-100 (see the module docstring; minutes a nut step)")
    parser.add_argument("--starts", type=int, choices=range(1, len(STARTS) + 1), default=1,
                        help="each run also from up to four starts moved by --shift (see the module docstring)")
    parser.add_argument("--shift", type=float, default=1e-6, help="m, how far --starts moves a start")
    parser.add_argument("--friction", type=float, help="every scene's friction (default: each scene's own)")
    parser.add_argument("--out", default="out/fidelity.json")
    args = parser.parse_args(argv)
    runs, comparisons, spreads = [], [], []
    paths = args.path or sorted(PATHS)
    for scene in args.scene or SCENES:
        done = {path: one_run(scene, path, args.yardstick, friction=args.friction) for path in paths}
        runs += list(done.values())
        if args.starts > 1:
            moved = [one_run(scene, path, args.yardstick, start, args.shift, args.friction)
                     for start in list(STARTS)[1:args.starts] for path in paths]
            runs += moved
            spreads.append(over_starts(scene, list(done.values()) + moved))
            print(f"{scene:>14} over {args.starts} starts: " + "; ".join(
                f"{p} deepest median {spreads[-1][p]['median_mm']:.4f} mm ({spreads[-1][p]['least_mm']:.4f} to "
                f"{spreads[-1][p]['most_mm']:.4f})" for p in paths)
                + "".join(f"; {p} vs full {spreads[-1][f'{p}_median_ratio']:.2f}x" for p in paths
                          if f"{p}_median_ratio" in spreads[-1]), flush=True)
        if "full" not in done:
            print(f"{scene:>14}: " + "; ".join(f"{p} deepest {r['deepest_mm']:.4f} mm (a step's median "
                                               f"{r['median_deepest_mm']:.4f}), {r['ms_per_step']:.1f} ms a step"
                                               for p, r in done.items()), flush=True)
            continue
        full = done["full"]
        for path in (p for p in done if p != "full"):
            comparisons.append({"path": path, **compared(done[path], full)})
            c, run = comparisons[-1], done[path]
            print(f"{scene:>14}, {path}: deepest {run['deepest_mm']:.4f} mm (full {full['deepest_mm']:.4f}, "
                  f"{c['depth_ratio']:.2f}x; a step's median {c['median_depth_ratio'] or 0:.2f}x); ends {c['ends_apart_mm']:.4f} mm "
                  f"apart; {run['ms_per_step']:.1f} ms a step (full {full['ms_per_step']:.0f})"
                  + (f"; yardstick {run['yardstick_mm']:.4f} mm (full {full['yardstick_mm']:.4f}, {c['yardstick_ratio']:.2f}x)"
                     if "yardstick_ratio" in c else ""), flush=True)
    write_report(args.out, {"runs": runs, "compared": comparisons, "over_starts": spreads}, "fidelity", argv)


if __name__ == "__main__":
    main()
