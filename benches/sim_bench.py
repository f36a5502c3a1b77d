"""`zoo bench --sim`: the paper's scenarios as simulations, timed per contact method, with two references.

For every scenario (scenes/sim-*.toml on the real meshes) and every way of finding its contacts:

- ``amortized+proxy``: the default (``proxy=True``, :mod:`zoo.proxy_collider`: culling and search on the SDF's
  narrow-band proxy, the NeuralSDF answers the contacts kept);
- ``amortized+coherence``: the NeuralSDF itself with coherence (``proxy=False``, ``zoo.CoherentCollider``: bounds and
  answers carried over steps), the default before the proxy;
- ``amortized``: the same detector, every step from scratch (``zoo.collide``);
- ``fw-10``: Frank-Wolfe, 10 iterations, every step from scratch (the paper's baseline);
- ``voxel-fw``: Frank-Wolfe on a 256^3 voxel grid of the SDF, from scratch;

and, where they apply (:mod:`benches.sim_references`), MuJoCo's own analytic SDF collision on its nut,
bolt and gears (``mujoco-sdf-plugin``) and MuJoCo's native collision on a CoACD convex decomposition
of the same meshes (``coacd-native``), it records steps per second, time per step and collision time
per step (median, p90), contacts per step, penetration (per step the deepest contact; p50, p99, max
over steps) and peak memory (each run is its own process: its ``ru_maxrss``). Each method reports the
depth of its own contacts, and a detector that stops above a triangle's minimum reports less than the
bodies penetrate; so the deepest penetration is also measured on one yardstick for every method
(:func:`yardstick_penetration`: Frank-Wolfe at 100 iterations at the run's deepest steps).

A method on the proxy runs twice, each in its own process: the first bakes the bricks its run needs (a lazy proxy;
they are written to the cache when the process ends) and loads the compiled collider, the second is timed, as a user's
later runs are; the first run's steps per second are kept beside (``first_run_steps_per_s``).

It also runs issue 25's three-way check on ``mug-hanging`` (the mug released 2 mm above where it
hangs): the default against amortized from scratch and FW-10, per-step time ratios and how far apart
the three trajectories end. Then the four Panda scenes (:mod:`benches.panda_scenarios`: the Panda hangs a mug on
the rack and places a bottle in a holder, seen and unseen shapes), each run whole and held to its check, with sdfzoo's
default contacts and with MuJoCo's on a CoACD decomposition of the object and the rack or holder
(:mod:`benches.panda_coacd`). Writes ``sim.json`` and ``sim.png`` (time per step against penetration).

    python -m sdfzoo.benches.sim_bench --out out/bench --seconds 0.2          # or: zoo bench --sim
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from zoo.files import atomic_write_text
from zoo.resources import bundled

SCENES = {  # scenario -> scene file; the scenario's control (a torque on the nut) comes from benches.sim_scenarios
    "mug-hanging": "sim-mug-hanging.toml",
    "bottle-holder": "sim-bottle-holder.toml",
    "bolt-nut": "sim-bolt-nut.toml",
    "mug-rack": "sim-mug-rack.toml",
    "gear-gear": "sim-gear-gear.toml",
}
METHODS = {
    "amortized+proxy": {"method": "amortized", "coherence": True, "proxy": True},
    "amortized+coherence": {"method": "amortized", "coherence": True, "proxy": False},
    "amortized": {"method": "amortized", "coherence": False},
    "fw-10": {"method": "fw", "coherence": False},
    "voxel-fw": {"method": "voxel-fw", "coherence": False},
}
# the Panda scenes (benches.panda_scenarios), each run whole (its check is 1 s after the release), sdfzoo's default
# beside MuJoCo's own contacts on CoACD pieces (benches.panda_coacd)
PANDA_SCENES = ("panda-bottle-holder", "panda-bottle-holder-unseen", "panda-mug-rack", "panda-mug-rack-unseen")
DEFAULT = "amortized+proxy"  # what Simulation and attach run unless told otherwise
PANDA_METHODS = (DEFAULT, "coacd-native")
REFERENCES = {"mujoco-sdf-plugin": ("bolt-nut", "gear-gear"), "coacd-native": ("mug-rack", "bottle-holder", "gear-gear", "bolt-nut")}
# issue 25's bars
COLLIDE_MS_MAX = 10.0  # median collision time per step with coherence, Mug-Rack and Bottle-Holder
SPEEDUP_OVER_FW = 5.0  # whole simulation against FW-10 contacts, same scenes
BOLT_STEPS_PER_S = 10.0
CHECK_OVER_FW, CHECK_OVER_SCRATCH, CHECK_APART_M = 5.0, 3.0, 2e-3
# issue 37's bars: a whole step, MuJoCo included, one torch thread
STEP_MS_MAX = {"mug-rack": 4.0, "bottle-holder": 4.0}
STEPS_PER_S_MIN = {"bolt-nut": 50.0, "gear-gear": 50.0}
YARDSTICK_ITERS = 100  # Frank-Wolfe iterations of the common penetration yardstick
YARDSTICK_STEPS = 3  # the run's deepest steps (by its own depths) measured on it


def percentiles(values, qs) -> dict:
    values = np.asarray(values, dtype=np.float64)
    return {f"p{q}" if q != 50 else "median": float(np.percentile(values, q)) if len(values) else 0.0 for q in qs}


def simulate(scenario: str, method: str, seconds: float) -> dict:
    """One (scenario, method) run in this process: the metrics (see the module docstring) and the end pose."""
    import zoo.sim
    from sdfzoo.benches.sim_scenarios import SCENARIOS

    sim = zoo.sim.load_scene(bundled("scenes") / SCENES[scenario], **METHODS[method])
    sim.build()
    control = SCENARIOS[scenario].control if scenario in SCENARIOS else None
    extra = (SCENARIOS[scenario].prepare(sim) or {}) if control is not None else {}
    pairs = sdf_mesh_pairs(sim)
    poses = []
    started = time.perf_counter()
    for _ in range(int(round(seconds / sim.dt))):
        if control is not None:
            control(sim, extra)
        sim.step()
        poses.append({name: sim.pose(name) for pair in pairs for name in pair})
    wall = time.perf_counter() - started
    log = sim.log
    own = [r.max_penetration for r in log]
    moving = next(name for name, body in sim.bodies.items() if body.joint != "fixed")
    return {
        "scenario": scenario, "method": method, "dt": sim.dt, "steps": len(log), "wall_s": wall,
        "steps_per_s": len(log) / wall,
        "step_ms": percentiles([1e3 * r.step_s for r in log], (50, 90)),
        "collide_ms": percentiles([1e3 * r.collide_s for r in log], (50, 90)),
        "contacts_per_step": float(np.mean([r.contacts for r in log])),
        "penetration_mm": {**percentiles([1e3 * r.max_penetration for r in log], (50, 99)),
                           "max": 1e3 * max((r.max_penetration for r in log), default=0.0),
                           "yardstick_max": 1e3 * yardstick_penetration(sim, pairs, poses, own)},
        "coherence": sim.collider_stats().as_dict() if METHODS[method]["coherence"] else None,
        "warnings": sim.warnings[:5], "end_position": sim.pose(moving)[:3, 3].tolist(), "body": moving,
    }


def sdf_mesh_pairs(sim) -> list[tuple[str, str]]:
    """The (SDF body, mesh body) name pairs of a ``zoo.sim.Simulation``: what the yardstick measures."""
    return [(a, b) for a, sdf_body in sim.bodies.items() for b, mesh_body in sim.bodies.items()
            if a != b and sdf_body.sdf is not None and mesh_body.mesh is not None]


def yardstick_depth(sim, pairs: list[tuple[str, str]], poses: dict) -> float:
    """The deepest penetration (m, 0 where none) at the bodies' ``poses`` ({name: (4, 4)}), measured the same way
    whatever a run's detector: ``zoo.collide`` with Frank-Wolfe at ``YARDSTICK_ITERS`` iterations (margin 0) on each
    of ``pairs`` (:func:`sdf_mesh_pairs`)."""
    import zoo

    deepest = 0.0
    for a, b in pairs:
        found = zoo.collide(sim.bodies[a].sdf, sim.bodies[b].mesh, poses[a], poses[b], margin=0.0, method="fw",
                            iters=YARDSTICK_ITERS)
        if len(found):
            deepest = max(deepest, -float(found.depths.min()))
    return deepest


def yardstick_penetration(sim, pairs: list[tuple[str, str]], poses: list[dict], own: list[float]) -> float:
    """The deepest penetration (m) at the ``YARDSTICK_STEPS`` steps where the run's own contacts were deepest: the
    deeper of its own contact and :func:`yardstick_depth` at that step's poses."""
    return max([0.0] + [max(own[k], yardstick_depth(sim, pairs, poses[k]))
                        for k in np.argsort(own)[::-1][:YARDSTICK_STEPS]])


def reference(kind: str, scenario: str, seconds: float, dt: float = 0.002) -> dict:
    from sdfzoo.benches import sim_references

    run = {"mujoco-sdf-plugin": sim_references.mujoco_sdf_plugin, "coacd-native": sim_references.coacd_native}[kind]
    return run(scenario, seconds, dt)


def panda(scene: str, method: str) -> dict:
    """One Panda scene, run whole, with sdfzoo's default contacts or MuJoCo's on CoACD pieces; its check's verdict
    and figures."""
    if method == "coacd-native":
        from sdfzoo.benches.panda_coacd import run
    else:
        from sdfzoo.benches.panda_scenarios import run
    row = run(scene)
    return {k: v for k, v in row.items() if k not in ("scene", "decomposition")} | {
        "decomposition": {b: {k: d[k] for k in ("mesh", "pieces", "seconds")} for b, d in row.get("decomposition", {}).items()}}


def run_isolated(args: list[str], timeout: float) -> dict:
    """One run in its own process (its own peak memory, no state shared): the child's JSON plus ``peak_memory_mb``."""
    command = [sys.executable, "-m", "sdfzoo.benches.sim_bench", *args]
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env={**os.environ})
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def three_way_check(rows: list[dict]) -> dict:
    """Issue 25's check on mug-hanging: per-step time ratios and how far apart the end positions are."""
    by = {r["method"]: r for r in rows if r["scenario"] == "mug-hanging" and "error" not in r}
    if not {DEFAULT, "amortized", "fw-10"} <= set(by):
        return {"passed": False, "why": "a run is missing"}
    default = by[DEFAULT]
    over = {m: by[m]["step_ms"]["median"] / default["step_ms"]["median"] for m in ("fw-10", "amortized")}
    apart = {m: float(np.linalg.norm(np.subtract(by[m]["end_position"], default["end_position"]))) for m in ("fw-10", "amortized")}
    return {"faster_per_step_than_fw": over["fw-10"], "faster_per_step_than_scratch": over["amortized"],
            "end_apart_mm": {m: 1e3 * d for m, d in apart.items()},
            "passed": over["fw-10"] >= CHECK_OVER_FW and over["amortized"] >= CHECK_OVER_SCRATCH and max(apart.values()) < CHECK_APART_M}


def speed_bars(rows: list[dict]) -> dict:
    """Issue 25's speed bars, each with what was measured."""
    bars = {}
    for scenario in ("mug-rack", "bottle-holder"):
        by = {r["method"]: r for r in rows if r["scenario"] == scenario and "error" not in r}
        if {DEFAULT, "fw-10"} <= set(by):
            ours, fw = by[DEFAULT], by["fw-10"]
            # penetration on the common yardstick where both runs have it, else as each detector reports it
            key = "yardstick_max" if all("yardstick_max" in r["penetration_mm"] for r in (ours, fw)) else "max"
            bars[scenario] = {
                "collide_ms_median": ours["collide_ms"]["median"], "collide_ok": ours["collide_ms"]["median"] <= COLLIDE_MS_MAX,
                "speedup_over_fw": fw["wall_s"] / ours["wall_s"] * ours["steps"] / fw["steps"],
                "max_penetration_mm": [ours["penetration_mm"][key], fw["penetration_mm"][key]], "penetration_measure": key,
            }
            bars[scenario]["passed"] = bool(bars[scenario]["collide_ok"] and bars[scenario]["speedup_over_fw"] >= SPEEDUP_OVER_FW
                                            and ours["penetration_mm"][key] <= fw["penetration_mm"][key])
    bolt = [r for r in rows if r["scenario"] == "bolt-nut" and r["method"] == DEFAULT and "error" not in r]
    if bolt:
        bars["bolt-nut"] = {"steps_per_s": bolt[0]["steps_per_s"], "passed": bolt[0]["steps_per_s"] >= BOLT_STEPS_PER_S}
    return bars


def step_bars(rows: list[dict], method: str = DEFAULT) -> dict:
    """Issue 37's bars on ``method``'s runs: ms a whole step (median) and steps a second, each with what was measured."""
    by = {r["scenario"]: r for r in rows if r["method"] == method and "error" not in r}
    bars = {}
    for scenario, most in STEP_MS_MAX.items():
        if scenario in by:
            ms = by[scenario]["step_ms"]["median"]
            bars[scenario] = {"step_ms_median": ms, "bar_ms": most, "passed": ms <= most}
    for scenario, least in STEPS_PER_S_MIN.items():
        if scenario in by:
            rate = 1e3 / by[scenario]["step_ms"]["median"]
            bars[scenario] = {"steps_per_s": rate, "bar_steps_per_s": least, "passed": rate >= least}
    return bars


def plot(rows: list[dict], path: Path) -> None:
    """Time per step (median) against the deepest penetration, one marker per method, one colour per scenario."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    markers = {"amortized+coherence": "o", "amortized+proxy": "P", "amortized": "s", "fw-10": "^", "voxel-fw": "v", "mujoco-sdf-plugin": "*", "coacd-native": "D"}
    scenarios = sorted({r["scenario"] for r in rows})
    colours = dict(zip(scenarios, plt.cm.tab10.colors))
    fig, ax = plt.subplots(figsize=(8, 5.5))
    for r in rows:
        if "error" in r:
            continue
        ax.scatter(r["step_ms"]["median"], max(r["penetration_mm"]["max"], 1e-4), marker=markers.get(r["method"], "x"),
                   color=colours[r["scenario"]], s=60)
    for method, marker in markers.items():
        ax.scatter([], [], marker=marker, color="grey", label=method)
    for scenario, colour in colours.items():
        ax.scatter([], [], marker="o", color=colour, label=scenario)
    ax.set(xscale="log", yscale="log", xlabel="time per step, median (ms)", ylabel="max penetration (mm)",
           title="zoo bench --sim: time per step against contact quality")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    os.replace(tmp, path)


def run_sim_benchmark(out_dir: Path, seconds: float = 0.2, scenarios=None, methods=None, references: bool = True,
                      progress=print, timeout: float = 1800, threads: int | None = None, panda_scenes=PANDA_SCENES) -> Path:
    """Every (scenario, method) and reference, each in its own process, then the Panda scenes ``panda_scenes`` (whole
    runs: ``seconds`` does not apply) with sdfzoo and with CoACD + MuJoCo; writes ``out_dir/sim.json`` and ``sim.png``.
    ``threads``: torch CPU threads of every run (None: torch's default, which ``OMP_NUM_THREADS`` sets)."""
    from sdfzoo.benches.sim_scenarios import require_meshes
    from sdfzoo.benches.solvers import machine_info

    require_meshes()
    scenarios = list(SCENES if scenarios is None else scenarios)
    rows = []
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "sim.json"

    def write() -> None:  # after every run: a long bench stopped early keeps what it measured
        machine = {**machine_info(), **({"threads": threads} if threads else {})}  # the runs' threads, not this process's
        report = {"seconds": seconds, "machine": machine, "rows": rows, "check_mug_hanging": three_way_check(rows),
                  "speed_bars": speed_bars(rows), "step_bars": step_bars(rows), "command": "python -m sdfzoo.benches.sim_bench " + " ".join(sys.argv[1:])}
        atomic_write_text(path, json.dumps(report, indent=1))

    for scenario in scenarios:
        runs = [(method, ["--one", scenario, method]) for method in methods or METHODS]
        runs += [(kind, ["--reference", kind, scenario]) for kind, applies in REFERENCES.items() if references and scenario in applies]
        for method, args in runs:
            progress(f"{scenario}: {method} ...")
            timing = ["--seconds", str(seconds)] + (["--threads", str(threads)] if threads else [])
            first = None
            if METHODS.get(method, {}).get("proxy"):  # a first run bakes the proxy's bricks (kept in the cache at its exit)
                first = run_isolated([*args, *timing], timeout).get("steps_per_s")
            rows.append({"scenario": scenario, "method": method, **run_isolated([*args, *timing], timeout),
                         **({"first_run_steps_per_s": first} if first is not None else {})})
            progress(f"  {_summary(rows[-1])}")
            write()
        plot(rows, out_dir / "sim.png")
    for scene in panda_scenes or ():
        for method in PANDA_METHODS:
            progress(f"{scene}: {method} (the whole run) ...")
            threading = ["--threads", str(threads)] if threads else []
            rows.append({"scenario": scene, "method": method, **run_isolated(["--panda", scene, method, *threading], timeout)})
            progress(f"  {_summary(rows[-1])}, check {'passed' if rows[-1].get('passed') else 'FAILED'}")
            write()
        plot(rows, out_dir / "sim.png")
    return path


def _summary(row: dict) -> str:
    if "error" in row:
        return f"error: {row['error']}"
    collide = f", collide {row['collide_ms']['median']:.1f} ms" if "collide_ms" in row else ""
    return (f"{row['steps_per_s']:.1f} steps/s, step {row['step_ms']['median']:.1f} ms (p90 {row['step_ms']['p90']:.1f}){collide}, "
            f"{row['contacts_per_step']:.1f} contacts, penetration max {row['penetration_mm']['max']:.3f} mm, "
            f"{row.get('peak_memory_mb', 0):.0f} MB")


def format_table(report: dict) -> list[list[str]]:
    """Rows for printing: scenario, method, steps/s, step ms median/p90, collide ms median, contacts, penetration p50/p99/max,
    max on the yardstick, MB."""
    out = []
    for r in report["rows"]:
        if "error" in r:
            out.append([r["scenario"], r["method"], "error: " + r["error"][:60]] + [""] * 9)
            continue
        c = r.get("collide_ms")
        p = r["penetration_mm"]
        out.append([r["scenario"], r["method"], f"{r['steps_per_s']:.1f}", f"{r['step_ms']['median']:.1f}", f"{r['step_ms']['p90']:.1f}",
                    f"{c['median']:.1f}" if c else "-", f"{r['contacts_per_step']:.1f}", f"{p['median']:.3f}", f"{p['p99']:.3f}",
                    f"{p['max']:.3f}", f"{p['yardstick_max']:.3f}" if "yardstick_max" in p else "-", f"{r.get('peak_memory_mb', 0):.0f}"])
    return out


TABLE_HEADER = ["scenario", "method", "steps/s", "step ms", "p90", "collide ms", "contacts", "pen p50 mm", "p99", "max",
                "max, FW-100 yardstick", "peak MB"]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench"))
    parser.add_argument("--seconds", type=float, default=0.2)
    parser.add_argument("--scenario", action="append", choices=sorted(SCENES))
    parser.add_argument("--method", action="append", choices=sorted(METHODS))
    parser.add_argument("--no-references", action="store_true")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads; 0 keeps torch's default")
    parser.add_argument("--one", nargs=2, metavar=("SCENARIO", "METHOD"), help="one run, JSON on stdout (internal)")
    parser.add_argument("--reference", nargs=2, metavar=("KIND", "SCENARIO"), help="one reference run, JSON on stdout (internal)")
    parser.add_argument("--panda", nargs=2, metavar=("SCENE", "METHOD"), help="one Panda run, JSON on stdout (internal)")
    parser.add_argument("--no-panda", action="store_true", help="leave out the Panda scenes")
    parser.add_argument("--panda-only", action="store_true", help="the Panda scenes only")
    args = parser.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.one or args.reference or args.panda:
        if args.panda:
            row = panda(*args.panda)
        else:
            row = simulate(*args.one, args.seconds) if args.one else reference(*args.reference, args.seconds)
        row["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        row["threads"] = torch.get_num_threads()
        print(json.dumps(row, default=float))
        return
    path = run_sim_benchmark(args.out, args.seconds, [] if args.panda_only else args.scenario, args.method, references=not args.no_references,
                             threads=args.threads or None, panda_scenes=() if args.no_panda else PANDA_SCENES)
    report = json.loads(path.read_text())
    for row in format_table(report):
        print(" | ".join(row))
    print(json.dumps({"check_mug_hanging": report["check_mug_hanging"], "speed_bars": report["speed_bars"],
                      "step_bars": report.get("step_bars", {})}, indent=1))
    print(f"written: {path}")


if __name__ == "__main__":
    main()
