"""The baked narrow-band proxy (zoo.proxy): bake time, memory and error per shape, and simulations with and without it.

``--bake``: for each shape (the mugs' hoi4d_mug_0001 at margin 1 mm, the bolts' factory_bolt_m16 and the gears'
industreal_gear_large at 0.1 mm, the margins of their scenes), a fresh bake (written to the cache, replacing what was
there, so that ``--sim`` reads it): its seconds, memory,
bricks, cells in band, the error against the NeuralSDF on held-out points and the culling bound, and what a read costs
against the NeuralSDF's value and gradient (microseconds a point, 8 and 1,000 points a call).

``--sim``: each scenario of benches/sim_scenarios.py named (its scene, control and check) run three ways in one process,
stepping in turn so that the machine's load falls on all alike: the full path (amortized, no coherence), the default
(amortized with coherence) and the default on the proxy (``proxy=True``: from the cache, baked first if absent). Per way:
collision and step time per step (median, mean), contacts, deepest penetration, the end pose's distance from the full
path's (and along the bolt, for bolt-nut), the scenario's check, and the collider's counts (NeuralSDF points).

    python -m investigations proxy --bake --out out/proxy-bake.json
    python -m investigations proxy --sim mug-rack --sim bolt-nut --out out/proxy-sim.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from investigations.report import write_report

SHAPES = [("mugs", "hoi4d_mug_0001", 1e-3), ("bolts", "factory_bolt_m16", 1e-4), ("gears", "industreal_gear_large", 1e-4)]
WAYS = {"full": {"method": "amortized", "coherence": False}, "default": {"method": "amortized", "coherence": True},
        "proxy": {"method": "amortized", "coherence": True, "proxy": True}}


def per_call_us(fn, points: torch.Tensor, repeats: int) -> float:
    """Median microseconds a point of ``fn(points)`` over ``repeats`` calls."""
    fn(points)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn(points)
        times.append(time.perf_counter() - started)
    return 1e6 * float(np.median(times)) / points.shape[0]


def bake(model: str, shape: str, margin: float) -> dict:
    """A fresh bake of ``model``'s ``shape`` for ``margin``: its costs and error (see the module docstring)."""
    import zoo
    from zoo.proxy import IN_BAND, cached_proxy

    sdf = zoo.load(model).shape(shape)
    proxy = cached_proxy(sdf, margin=margin, progress=True, rebake=True)
    cells = (proxy.status[:-512] == IN_BAND).nonzero().squeeze(-1)
    g = torch.Generator().manual_seed(1)
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in sdf.bounds)
    reads = {}
    for n in (8, 1000):
        points = lo + (hi - lo) * torch.rand(n, 3, generator=g)
        reads[n] = {"proxy_value_and_grad_us_per_point": per_call_us(proxy.value_and_grad, points, 200),
                    "neural_value_and_grad_us_per_point": per_call_us(sdf.value_and_grad, points, 20)}
    return {"model": model, "shape": shape, "margin_m": margin, "spacing_m": proxy.spacing, "band_m": proxy.band,
            "lipschitz": proxy.lipschitz, "bake_s": proxy.bake_seconds, "memory_mb": proxy.memory_bytes / 2**20,
            "bricks": proxy.n_baked, "cells_in_band": int(cells.numel()), "error_m": proxy.error,
            "error_bound_m": proxy.error_bound, "reads": reads}


def refine_fixed_meshes(sim, times: int) -> int:
    """Subdivide every fixed mesh body of ``sim`` (not built yet) ``times`` times (each 4x the faces, the same
    surface); returns the faces the fixed meshes hold then."""
    import trimesh

    faces = 0
    for body in sim.bodies.values():
        if body.joint == "fixed" and body.mesh is not None:
            v, f = body.mesh
            for _ in range(times):
                v, f = trimesh.remesh.subdivide(v, f)
            body.mesh = (np.asarray(v, np.float64), np.asarray(f, np.int64))
            faces += len(f)
    return faces


def simulate(scenario: str, steps: int | None, ways: list[str] | None = None, refine: int = 0) -> dict:
    """``scenario`` run the ways of ``WAYS`` named (all by default) in turn, step by step (see the module docstring);
    the end poses are measured from the first way's (the full path's, when it runs). ``refine``: the fixed meshes
    subdivided that many times (4x their faces each)."""
    import zoo.sim
    from sdfzoo.benches.sim_scenarios import SCENARIOS, SCENES, advance

    spec = SCENARIOS[scenario]
    runs = {}
    for way, options in WAYS.items():
        if ways and way not in ways:
            continue
        sim = zoo.sim.load_scene(SCENES / spec.scene, **options)
        fixed_faces = refine_fixed_meshes(sim, refine)
        sim.build()  # the proxy is baked or read here, before the timed steps
        runs[way] = {"sim": sim, "extra": spec.prepare(sim) or {}, "trace": [], "wall": []}
    reference = next(iter(runs))
    first = runs[reference]["sim"]
    steps = int(round(first.seconds / first.dt)) if steps is None else steps
    for _ in range(steps):
        for run in runs.values():
            started = time.perf_counter()
            advance(spec, run["sim"], run["extra"])
            run["wall"].append(time.perf_counter() - started)
            run["trace"].append({"time": run["sim"].time, **spec.record(run["sim"])})
    moving = next(name for name, body in first.bodies.items() if body.joint != "fixed")
    end = {way: run["sim"].pose(moving) for way, run in runs.items()}
    out = {"scenario": scenario, "steps": steps, "dt": first.dt, "body": moving, "refine": refine,
           "fixed_mesh_faces": fixed_faces, "ways": {}}
    for way, run in runs.items():
        sim, log = run["sim"], run["sim"].log
        stats = sim.collider_stats().as_dict()
        row = {
            "options": WAYS[way],
            "step_ms": {"median": 1e3 * float(np.median(run["wall"])), "mean": 1e3 * float(np.mean(run["wall"]))},
            "collide_ms": {"median": 1e3 * float(np.median([r.collide_s for r in log])),
                           "mean": 1e3 * float(np.mean([r.collide_s for r in log]))},
            "contacts_per_step": float(np.mean([r.contacts for r in log])),
            "max_penetration_mm": 1e3 * max((r.max_penetration for r in log), default=0.0),
            "end_position": end[way][:3, 3].tolist(),
            "end_from_full_mm": 1e3 * float(np.linalg.norm(end[way][:3, 3] - end[reference][:3, 3])),
            "check": spec.check(sim, [{"time": 0.0, **spec.record(sim)}] + run["trace"], run["extra"]),
            "collider": {k: v / max(stats["steps"], 1) for k, v in stats.items() if k != "steps"} | {"calls": stats["steps"]},
        }
        if scenario == "bolt-nut":
            row["end_along_bolt_from_full_mm"] = 1e3 * float(end[way][2, 3] - end[reference][2, 3])
        out["ways"][way] = row
    out["reference"] = reference
    full_pen = out["ways"][reference]["max_penetration_mm"]
    for row in out["ways"].values():
        row["penetration_vs_full"] = row["max_penetration_mm"] / full_pen if full_pen > 0 else float("nan")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bake", action="store_true", help="bake each shape afresh and measure it")
    parser.add_argument("--shape", action="append", default=[], help="with --bake: only these shapes (names)")
    parser.add_argument("--sim", action="append", default=[], help="a scenario of benches/sim_scenarios.py, run three ways")
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default: the scene's seconds)")
    parser.add_argument("--way", action="append", default=[], choices=sorted(WAYS),
                        help="with --sim: only these ways (default all; the first named is the reference of the end poses)")
    parser.add_argument("--refine", type=int, action="append", default=[],
                        help="with --sim: subdivide the fixed meshes this many times (4x faces each; repeatable: one run each)")
    parser.add_argument("--out", default="out/proxy.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    report = {"threads": torch.get_num_threads()}
    if args.bake:
        report["bake"] = []
        for model, shape, margin in SHAPES:
            if args.shape and shape not in args.shape:
                continue
            row = bake(model, shape, margin)
            report["bake"].append(row)
            print(f"{shape}: {row['bake_s']:.1f} s, {row['memory_mb']:.1f} MB, spacing {1e3 * row['spacing_m']:.3f} mm, "
                  f"error median {1e6 * row['error_m']['median']:.1f} um, p99 {1e6 * row['error_m']['p99']:.1f}, "
                  f"max {1e6 * row['error_m']['max']:.1f}, bound {1e6 * row['error_bound_m']:.1f} um", flush=True)
    if args.sim:
        from sdfzoo.benches.sim_scenarios import require_meshes

        require_meshes()
        report["sim"] = []
        for scenario in args.sim:
            for refine in args.refine or [0]:
                result = simulate(scenario, args.steps, [w for w in WAYS if w in args.way] or None, refine)
                report["sim"].append(result)
                for way, row in result["ways"].items():
                    print(f"{scenario} ({result['fixed_mesh_faces']} fixed faces) {way:>8}: step {row['step_ms']['median']:.1f} ms (mean {row['step_ms']['mean']:.1f}), "
                          f"collide {row['collide_ms']['median']:.1f}, contacts {row['contacts_per_step']:.1f}, "
                          f"penetration {row['max_penetration_mm']:.3f} mm ({row['penetration_vs_full']:.2f} of {result['reference']}), "
                          f"end {row['end_from_full_mm']:.3f} mm from {result['reference']}, check {row['check'].get('passed')}",
                          flush=True)
    write_report(args.out, report, __name__, argv)
