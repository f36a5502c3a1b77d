"""The baked narrow-band proxy (zoo.proxy): bake time, memory and error per shape, and simulations with and without it.

``--bake``: for each shape (the mugs' hoi4d_mug_0001 at margin 1 mm, the bolts' factory_bolt_m16 and the gears'
industreal_gear_large at 0.1 mm, the margins of their scenes), a fresh bake of every brick (``lazy=False``, written to
the cache, replacing what was there): its seconds, memory, bricks, cells in band, the error against the NeuralSDF on
held-out points and the culling bound, and what a read costs against the NeuralSDF's value and gradient (microseconds
a point, 8 and 1,000 points a call).

``--bake --lazy``: the lazy proxy instead (``cached_proxy(lazy=True)``, written to the cache afresh, so that ``--sim``
reads it: a simulation's ``proxy=True`` is the lazy one): its creation's seconds and memory, the brick centres
evaluated, the error on its sample of bricks; then what baking a brick lazily costs (milliseconds a brick: reads at
the centres of bricks not baked yet, one brick a read and 32 a read, each way a brick can be baked: coarse to fine,
and all its nodes in one call, alternating; and the SDF points each asked a brick), what the bricks took in memory,
and the write of what was baked (``flush``).

``--reads``: what the numpy read costs a call (``read_numpy``, or ``_read`` in code that predates it) on the mug's
proxy at 10 and 500 points: near the surface (all in band) and uniform in the mug's bounds (most out of band),
float32 and float64; the bricks those points need are baked before the timing.

``--kernels SCENARIO``: the proxy collider's compiled passes (``kernel="numba"``, the default) and its numpy ones side
by side on the poses of the scenario's default run: milliseconds a call, whether their contacts agree, and how long
making each collider took (the compiled one loads its kernel then). ``--network``: what a NeuralSDF's value and
gradient costs a call at 1 to 1,000 points, on the path ``value_and_grad`` takes and on torch's by-hand path.

``--sim``: each scenario of benches/sim_scenarios.py named (its scene, control and check) run three ways in one process,
stepping in turn so that the machine's load falls on all alike: the full path (amortized, no coherence), the coherent
collider on the NeuralSDF itself (``proxy=False``, the default before the proxy) and the default, on the proxy
(``proxy=True``: from the cache, baked lazily where absent). Per way:
collision and step time per step (median, mean), contacts, deepest penetration, the end pose's distance from the full
path's (and along the bolt, for bolt-nut), the scenario's check, and the collider's counts (NeuralSDF points).

    python -m investigations proxy --bake --out out/proxy-bake.json
    python -m investigations proxy --bake --lazy --reads --out out/proxy-lazy.json
    python -m investigations proxy --sim mug-rack --sim bolt-nut --out out/proxy-sim.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from investigations.report import write_report

SHAPES = [("mugs", "hoi4d_mug_0001", 1e-3), ("bolts", "factory_bolt_m16", 1e-4), ("gears", "industreal_gear_large", 1e-4)]
WAYS = {"full": {"method": "amortized", "coherence": False},
        "coherent": {"method": "amortized", "coherence": True, "proxy": False},
        "proxy": {"method": "amortized", "coherence": True, "proxy": True}}  # proxy: the default


def per_call_us(fn, points, repeats: int) -> float:
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
    from zoo.proxy import BRICK, IN_BAND, cached_proxy

    sdf = zoo.load(model).shape(shape)
    proxy = cached_proxy(sdf, margin=margin, progress=True, rebake=True, lazy=False)
    cells = (proxy.status[BRICK**3:] == IN_BAND).nonzero().squeeze(-1)  # row 0 is the coarse row
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


class CountingSDF:
    """``sdf`` counting the points it is asked (``points``)."""

    def __init__(self, sdf):
        self.sdf, self.points = sdf, 0

    def __call__(self, points):
        self.points += len(points)
        return self.sdf(points)


def bake_lazily(model: str, shape: str, margin: float, bricks_per_way: int = 96, seed: int = 0) -> dict:
    """A fresh lazy proxy of ``model``'s ``shape`` for ``margin``: its creation, and what a lazily baked brick costs
    (see the module docstring)."""
    import zoo
    from zoo.proxy import BRICK, cached_proxy

    sdf = zoo.load(model).shape(shape)
    started = time.perf_counter()
    proxy = cached_proxy(sdf, margin=margin, rebake=True, lazy=True)
    created_s = time.perf_counter() - started
    row = {"model": model, "shape": shape, "margin_m": margin, "spacing_m": proxy.spacing, "band_m": proxy.band,
           "create_s": proxy.bake_seconds, "create_and_write_s": created_s, "memory_mb": proxy.memory_bytes / 2**20,
           "bricks": int(proxy.n_bricks.prod()), "centres_evaluated": int(torch.isfinite(proxy.coarse_value).sum()),
           "sample_bricks": proxy.n_baked, "pending_bricks": proxy.n_pending, "error_m": proxy.error,
           "error_bound_m": proxy.error_bound}
    # bricks not baked yet that may hold band cells, in random order; a read at a brick's centre bakes that brick
    waiting = (proxy.brick_of == -1).nonzero().squeeze(-1)
    near = waiting[proxy.coarse_value[waiting].double().abs() <= proxy.lipschitz * 3**0.5 / 2 * BRICK * proxy.spacing + proxy.band]
    order = near[torch.randperm(near.numel(), generator=torch.Generator().manual_seed(seed))]
    nb = proxy.n_bricks
    ijk = torch.stack([order // (nb[1] * nb[2]), (order // nb[2]) % nb[1], order % nb[2]], dim=-1)
    centres = (proxy.lo + (ijk * BRICK + BRICK / 2).double() * proxy.spacing).numpy()
    times = {True: {1: [], 32: []}, False: {1: [], 32: []}}
    points_asked = {True: 0, False: 0}
    counting = CountingSDF(proxy.sdf)
    proxy.sdf = counting
    at, rows_before, memory_before = 0, proxy.n_baked, proxy.memory_bytes
    for group in (1, 32):
        for _ in range(bricks_per_way // group):
            for coarse_to_fine in (True, False):  # alternating, so that the machine's load falls on both alike
                proxy.coarse_to_fine = coarse_to_fine
                points = centres[at:at + group]
                at += group
                asked = counting.points
                started = time.perf_counter()
                proxy.read_numpy(points)
                times[coarse_to_fine][group].append((time.perf_counter() - started) / group)
                points_asked[coarse_to_fine] += counting.points - asked
    proxy.coarse_to_fine, proxy.sdf = True, counting.sdf
    row["lazy_brick_ms"] = {("coarse_to_fine" if way else "all_nodes"): {
        f"{group}_a_read": {"median": 1e3 * float(np.median(t)), "mean": 1e3 * float(np.mean(t)), "reads": len(t)}
        for group, t in by_group.items()} for way, by_group in times.items()}
    row["sdf_points_per_brick"] = {("coarse_to_fine" if way else "all_nodes"): n / (at / 2)
                                   for way, n in points_asked.items()}
    row["lazy_bricks_baked"] = proxy.n_baked - rows_before
    row["memory_per_brick_kb"] = (proxy.memory_bytes - memory_before) / max(proxy.n_baked - rows_before, 1) / 1024
    started = time.perf_counter()
    row["flush_wrote"] = proxy.flush()
    row["flush_s"] = time.perf_counter() - started
    return row


def surface_points(sdf, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) float64 points within about 0.2 mm of ``sdf``'s surface: random points near it moved onto it by two
    Newton steps, then off it along the normal by up to 0.2 mm."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in sdf.bounds)
    p = lo + (hi - lo) * torch.rand(40 * n, 3, generator=g)
    with torch.no_grad():
        p = p[sdf(p).abs() < 0.005][:2 * n]
        for _ in range(2):
            d, grad = sdf.value_and_grad(p)
            p = p - (d / grad.square().sum(-1)).unsqueeze(-1) * grad
        d, grad = sdf.value_and_grad(p)
    p = p + 2e-4 * (2 * torch.rand(p.shape[0], 1, generator=g) - 1) * torch.nn.functional.normalize(grad, dim=-1)
    return p[d.abs() < 1e-4][:n].double().numpy()


def read_costs(model: str = "mugs", shape: str = "hoi4d_mug_0001", margin: float = 1e-3, repeats: int = 3000) -> dict:
    """Microseconds a call of the proxy's numpy read (``read_numpy``) at 10 and 500 points,
    near the surface and uniform in the bounds, float32 and float64 (median of ``repeats`` calls)."""
    import zoo
    from zoo.proxy import IN_BAND, cached_proxy

    sdf = zoo.load(model).shape(shape)
    proxy = cached_proxy(sdf, margin=margin)
    read = proxy.read_numpy
    lo, hi = (b.double().numpy() for b in sdf.bounds)
    kinds = {"near the surface": surface_points(sdf, 500),
             "uniform in the bounds": lo + (hi - lo) * np.random.default_rng(0).random((500, 3))}
    out = {"function": read.__name__}
    for kind, points in kinds.items():
        read(points)  # bakes the bricks these points need (a lazy proxy), outside the timing
        out[kind] = {"in_band_fraction": float((read(points)[2] == IN_BAND).mean())}
        for n in (10, 500):
            for dtype in (np.float32, np.float64):
                p = np.ascontiguousarray(points[:n], dtype=dtype)
                out[kind][f"{n}_{np.dtype(dtype).name}_us"] = per_call_us(read, p, repeats) * n
    return out


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


def start_refined(name: str, refine: int = 0, **options):
    """(the Scenario, its Simulation built, what its ``prepare`` computed, the faces its fixed meshes hold) of scenario
    ``name``, its scene loaded with ``options`` (``zoo.sim.load_scene``'s) and its fixed meshes subdivided ``refine``
    times before the build (4x their faces each: :func:`refine_fixed_meshes`)."""
    import zoo.sim
    from sdfzoo.benches.sim_scenarios import SCENARIOS, SCENES

    spec = SCENARIOS[name]
    sim = zoo.sim.load_scene(SCENES / spec.scene, **options)
    fixed_faces = refine_fixed_meshes(sim, refine)
    sim.build()  # the proxy is baked or read here
    return spec, sim, spec.prepare(sim) or {}, fixed_faces


def simulate(scenario: str, steps: int | None, ways: list[str] | None = None, refine: int = 0) -> dict:
    """``scenario`` run the ways of ``WAYS`` named (all by default) in turn, step by step (see the module docstring);
    the end poses are measured from the first way's (the full path's, when it runs). ``refine``: the fixed meshes
    subdivided that many times (4x their faces each)."""
    from sdfzoo.benches.sim_scenarios import advance

    runs = {}
    for way, options in WAYS.items():
        if ways and way not in ways:
            continue
        spec, sim, extra, fixed_faces = start_refined(scenario, refine, **options)  # built before the timed steps
        runs[way] = {"sim": sim, "extra": extra, "trace": [], "wall": []}
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
            "found_per_step": float(np.mean([r.raw_contacts for r in log])),  # the colliders returned, before filters
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


def kernels(scenario: str, steps: int | None) -> dict:
    """``scenario`` simulated on its default path; at every step two more proxy colliders on the same SDF, mesh and
    proxy, one per kernel (``ProxyCollider(kernel=...)``: compiled, numpy), answer the step's poses (deferred: the
    proxy's contacts) in turn: their milliseconds a call (median, mean), how far their contacts agree (the steps whose
    faces or depths (by 1e-9 m) differ, the faces only one reports, the largest depth gap on the faces both report:
    rounding, in reads at the same points summed in another order, can tip a comparison), and how long making each
    collider took (the compiled one loads its kernel then)."""
    from sdfzoo.benches.sim_scenarios import advance, start
    from zoo.proxy_collider import KERNELS, ProxyCollider
    from zoo.sim.geoms import body_pose

    spec, sim, extra = start(scenario)
    pair = next(p for p in sim.world.pairs if getattr(getattr(p, "collider", None), "proxy", None) is not None)
    source = pair.collider.proxy_collider
    made = {}
    for kernel in KERNELS:
        started = time.perf_counter()
        made[kernel] = ProxyCollider(source.sdf, (source.vertices, source.faces), source.proxy, source.margin,
                                     source.method, deferred=True, kernel=kernel)
        made[kernel + "_made_s"] = time.perf_counter() - started
    times = {kernel: [] for kernel in KERNELS}
    disagree, only_one, deepest_gap = 0, 0, 0.0
    steps = int(round(sim.seconds / sim.dt)) if steps is None else steps
    for _ in range(steps):
        advance(spec, sim, extra)
        poses = body_pose(sim.data, pair.sdf_body.body), pair.surface_pose(sim.data)
        answers = {}
        for kernel in KERNELS:
            started = time.perf_counter()
            answers[kernel] = made[kernel](*poses)
            times[kernel].append(time.perf_counter() - started)
        a, b = answers.values()
        rows_a = {int(f): i for i, f in enumerate(a.triangles)}
        rows_b = {int(f): i for i, f in enumerate(b.triangles)}
        common = sorted(set(rows_a) & set(rows_b))
        gap = max((abs(float(a.depths[rows_a[f]]) - float(b.depths[rows_b[f]])) for f in common), default=0.0)
        only_one += len(set(rows_a) ^ set(rows_b))
        deepest_gap = max(deepest_gap, gap)
        disagree += bool(set(rows_a) ^ set(rows_b)) or gap > 1e-9
    return {"scenario": scenario, "steps": steps, "mesh_faces": int(source.faces.shape[0]), "steps_disagreeing": disagree,
            "faces_in_one_only": only_one, "largest_depth_gap_m": deepest_gap,
            "made_s": {k: made[k + "_made_s"] for k in KERNELS},
            "call_ms": {k: {"median": 1e3 * float(np.median(t[1:])), "mean": 1e3 * float(np.mean(t[1:]))} for k, t in times.items()}}


def network_costs(repeats: int = 200) -> dict:
    """A NeuralSDF's value and gradient (``value_and_grad``) at 1, 3, 10, 64, 256, 512 and 1,000 points: microseconds
    a call on the path it takes (the compiled network up to ``SMALL_BATCH`` points, torch's chain rule by hand above), and on torch's by-hand path
    at the same points, float32, the mugs' hoi4d_mug_0001 and the bolts' factory_bolt_m16."""
    import zoo
    from zoo.neural_numpy import SMALL_BATCH

    out = {"small_batch": SMALL_BATCH}
    for model, shape_name, _ in SHAPES[:2]:
        shape = zoo.load(model).shape(shape_name)
        lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in shape.bounds)
        rows = {}
        for n in (1, 3, 10, 64, 256, 512, 1000):
            points = lo + torch.rand(n, 3, generator=torch.Generator().manual_seed(n)) * (hi - lo)
            taken = per_call_us(shape.value_and_grad, points, repeats) * n
            by_hand = per_call_us(torch_by_hand(shape.value_and_grad), points, repeats) * n
            rows[str(n)] = {"taken_us": taken, "torch_by_hand_us": by_hand, "taken_us_a_point": taken / n}
        out[shape_name] = rows
    return out


def torch_by_hand(value_and_grad):
    """``value_and_grad`` made to take torch's chain rule by hand at any number of points: the numpy network's
    threshold (``zoo.neural.SMALL_BATCH``) set to 0 for the call."""
    import zoo.neural

    def call(points):
        small_batch, zoo.neural.SMALL_BATCH = zoo.neural.SMALL_BATCH, 0
        try:
            return value_and_grad(points)
        finally:
            zoo.neural.SMALL_BATCH = small_batch

    return call


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bake", action="store_true", help="bake each shape afresh and measure it")
    parser.add_argument("--shape", action="append", default=[], help="with --bake: only these shapes (names)")
    parser.add_argument("--lazy", action="store_true", help="with --bake: the lazy proxy, and what a lazily baked brick costs")
    parser.add_argument("--reads", action="store_true", help="what the numpy read costs a call on the mug's proxy")
    parser.add_argument("--sim", action="append", default=[], help="a scenario of benches/sim_scenarios.py, run three ways")
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default: the scene's seconds)")
    parser.add_argument("--way", action="append", default=[], choices=sorted(WAYS),
                        help="with --sim: only these ways (default all; the first named is the reference of the end poses)")
    parser.add_argument("--refine", type=int, action="append", default=[],
                        help="with --sim: subdivide the fixed meshes this many times (4x faces each; repeatable: one run each)")
    parser.add_argument("--kernels", action="append", default=[],
                        help="a scenario: the proxy collider's compiled and numpy kernels on its poses, side by side")
    parser.add_argument("--network", action="store_true", help="what a NeuralSDF's value and gradient costs a call")
    parser.add_argument("--out", default="out/proxy.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    report = {"threads": torch.get_num_threads()}
    if args.bake:
        report["bake"] = []
        for model, shape, margin in SHAPES:
            if args.shape and shape not in args.shape:
                continue
            if args.lazy:
                row = bake_lazily(model, shape, margin)
                report["bake"].append(row)
                ways = ", ".join(f"{way} {t['1_a_read']['median']:.1f} ms a brick alone, {t['32_a_read']['median']:.1f} in 32 "
                                 f"({row['sdf_points_per_brick'][way]:.0f} SDF points a brick)"
                                 for way, t in row["lazy_brick_ms"].items())
                print(f"{shape} lazy: created in {row['create_s']:.2f} s ({row['create_and_write_s']:.2f} s with the write), "
                      f"{row['memory_mb']:.1f} MB, {row['centres_evaluated']} of {row['bricks']} brick centres, "
                      f"{row['pending_bricks']} bricks to bake; error on {row['sample_bricks']} bricks: median "
                      f"{1e6 * row['error_m']['median']:.1f} um, p99 {1e6 * row['error_m']['p99']:.1f}, max "
                      f"{1e6 * row['error_m']['max']:.1f}, bound {1e6 * row['error_bound_m']:.1f} um; {ways}; "
                      f"{row['memory_per_brick_kb']:.1f} kB a brick; flush {row['flush_s']:.2f} s", flush=True)
                continue
            row = bake(model, shape, margin)
            report["bake"].append(row)
            print(f"{shape}: {row['bake_s']:.1f} s, {row['memory_mb']:.1f} MB, spacing {1e3 * row['spacing_m']:.3f} mm, "
                  f"error median {1e6 * row['error_m']['median']:.1f} um, p99 {1e6 * row['error_m']['p99']:.1f}, "
                  f"max {1e6 * row['error_m']['max']:.1f}, bound {1e6 * row['error_bound_m']:.1f} um", flush=True)
    if args.reads:
        report["reads"] = read_costs()
        print(f"reads ({report['reads']['function']}): " + "; ".join(
            f"{kind}: " + ", ".join(f"{k} {v:.1f}" for k, v in row.items() if k.endswith("_us"))
            for kind, row in report["reads"].items() if kind != "function"), flush=True)
    if args.kernels:
        report["kernels"] = []
        for scenario in args.kernels:
            row = kernels(scenario, args.steps)
            report["kernels"].append(row)
            print(f"{scenario} kernels: " + ", ".join(f"{k} {v['median']:.2f} ms a call median ({v['mean']:.2f} mean), made in "
                  f"{row['made_s'][k]:.2f} s" for k, v in row["call_ms"].items()) + f"; {row['steps_disagreeing']} of "
                  f"{row['steps']} steps differ (by more than 1e-9 m), {row['faces_in_one_only']} faces in one only, depths "
                  f"{row['largest_depth_gap_m']:.2g} m apart at most", flush=True)
    if args.network:
        report["network"] = network_costs()
        print("network: " + "; ".join(f"{shape}: " + ", ".join(f"{n} points {r['taken_us']:.0f} us ({r['torch_by_hand_us']:.0f} "
              "torch)" for n, r in rows.items()) for shape, rows in report["network"].items() if shape != "small_batch"), flush=True)
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
