"""`zoo stress --sim`: zoo.sim on stiff and extreme cases, each with what is expected and what happened.

Cases: stiff contacts (solref time constant 2 dt); dt from 0.25 to 4 ms against native MuJoCo at
the same dt; a 1000:1 mass ratio (a 1 t box on a 1 kg plate on the ground); an impact that
crosses the margin in one step (5 m/s: the margin is widened; 50 m/s: reported); deep initial
penetration (pushed out without an explosion); 10 s of resting contact (no energy gain, no drift);
over 1,000 simultaneous contacts. Every case also checks that the state stays finite and lists
MuJoCo's warnings (``d.warning``) and zoo.sim's.

    python -m sdfzoo.benches.stress_sim --out out/stress-sim.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from zoo.files import atomic_write_text

from .sim_check import HALF, MASS, RADIUS, G, box_inertia, grid_plane, native_run, sphere_inertia, two_triangle_plane
from .stress import run_case

CASES = []


def case(name: str):
    def register(fn):
        CASES.append((name, fn))
        return fn

    return register


def _simulation(dt: float = 0.002, **kwargs):
    import zoo.sim

    return zoo.sim.Simulation(dt=dt, method="fw", **kwargs)


def _pose(z: float, x: float = 0.0, y: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def _sphere_on_ground(sim, z: float, velocity=None, ground=None):
    import zoo

    sim.add_body("ball", sdf=zoo.Sphere(radius=RADIUS), mass=MASS, inertia=sphere_inertia(), pose=_pose(z, 0.3, 0.1),
                 velocity=velocity)
    sim.add_body("ground", mesh=two_triangle_plane() if ground is None else ground, joint="fixed")


def _run(sim, seconds: float, body: str) -> dict:
    """Step ``seconds``; heights, speeds, energies per step of ``body``, and whether all stayed finite."""
    z, speed, energy = [], [], []
    for _ in range(int(round(seconds / sim.dt))):
        sim.step()
        z.append(sim.pose(body)[2, 3])
        speed.append(float(np.linalg.norm(sim.velocity(body)[:3])))
        energy.append(sim.energy())
    finite = bool(np.isfinite(z).all() and np.isfinite(speed).all())
    return {"z": np.array(z), "speed": np.array(speed), "energy": np.array(energy), "finite": finite}


def _ball_drop(height: float, speed: float, seconds: float):
    """(sim, run) of the ball thrown down at ``speed`` from ``height`` above the 2-triangle ground."""
    sim = _simulation(0.002)
    _sphere_on_ground(sim, RADIUS + height, velocity=(0, 0, -speed, 0, 0, 0))
    return sim, _run(sim, seconds, "ball")


def _common(sim, run: dict) -> dict:
    return {"finite": run["finite"], "warnings": sim.warnings[:10], "n_warnings": len(sim.warnings),
            "max_contacts": max(r.contacts for r in sim.log), "mean_step_ms": 1e3 * float(np.mean([r.step_s for r in sim.log]))}


@case("stiff contacts: solref time constant 2 dt")
def _stiff(ctx):
    dt = 0.002
    sim = _simulation(dt, solref=(2 * dt, 1.0))
    _sphere_on_ground(sim, RADIUS + 0.01)
    run = _run(sim, 0.5, "ball")
    pen = RADIUS - run["z"][-25:].mean()
    observed = {**_common(sim, run), "resting_penetration_mm": 1e3 * pen, "final_speed": run["speed"][-1]}
    ok = run["finite"] and 0 < pen < 1e-3 and run["speed"][-1] < 1e-2 and not sim.warnings
    return "the ball drops 1 cm and rests (speed < 1 cm/s, penetration < 1 mm); finite; no warning", observed, ok


@case("dt from 0.25 to 4 ms against native MuJoCo")
def _dt_sweep(ctx):

    rows, ok = [], True
    for dt in (0.00025, 0.0005, 0.001, 0.002, 0.004):
        native = native_run("sphere", (0.3, 0.1), RADIUS + 5e-4, seconds=0.3, dt=dt)
        sim = _simulation(dt)
        _sphere_on_ground(sim, RADIUS + 5e-4)
        run = _run(sim, 0.3, "ball")
        tail = max(1, int(round(0.05 / dt)))
        ours, theirs = RADIUS - run["z"][-tail:].mean(), RADIUS - native["z"][-tail:].mean()
        err = ours / theirs - 1
        rows.append({"dt_ms": 1e3 * dt, "native_penetration_mm": 1e3 * theirs, "zoo_penetration_mm": 1e3 * ours,
                     "error": err, "finite": run["finite"], "warnings": sim.warnings[:3]})
        ok &= run["finite"] and abs(err) <= 0.25 and not sim.warnings
    return "at every dt the ball rests within 25% of native MuJoCo's penetration; finite; no warning", {"rows": rows}, ok


def _stack(heavy_on_top: bool) -> tuple[dict, dict]:
    """A 1 kg and a 1 t body stacked on a 2-triangle ground: zoo.sim's and native MuJoCo's (the same boxes
    on MuJoCo's plane). Returns ({top_sink, top_speed, finite, warnings}, native's {top_sink})."""
    import mujoco
    import trimesh

    import zoo

    plate_half, box_half = (0.15, 0.15, 0.01), (HALF, HALF, HALF)
    plate_mass, box_mass = (1.0, 1000.0) if heavy_on_top else (1000.0, 1.0)
    rest_top = 2 * plate_half[2] + HALF
    sim = _simulation(0.002)
    sim.add_body("plate", sdf=zoo.Box(half_extents=plate_half), mesh=trimesh.creation.box(extents=[2 * h for h in plate_half]),
                 mass=plate_mass, inertia=np.asarray(box_inertia(plate_half)) * plate_mass, pose=_pose(plate_half[2] + 2e-4))
    sim.add_body("top", sdf=zoo.Box(half_extents=box_half), mass=box_mass, inertia=np.asarray(box_inertia()) * box_mass,
                 pose=_pose(rest_top + 4e-4))
    sim.add_body("ground", mesh=two_triangle_plane(), joint="fixed")
    run = _run(sim, 0.5, "top")
    ours = {**_common(sim, run), "top_sink_mm": 1e3 * (rest_top - run["z"][-25:].mean()), "top_final_speed": run["speed"][-1]}

    def body(name, half, mass, z):
        inertia = " ".join(str(v * mass) for v in box_inertia(half))
        return (f'<body name="{name}" pos="0 0 {z}"><freejoint/><inertial pos="0 0 0" mass="{mass}" diaginertia="{inertia}"/>'
                f'<geom type="box" size="{" ".join(map(str, half))}"/></body>')

    xml = (f'<mujoco><option timestep="0.002" integrator="implicitfast"/><worldbody><geom type="plane" size="10 10 1"/>'
           f'{body("plate", plate_half, plate_mass, plate_half[2] + 2e-4)}{body("top", box_half, box_mass, rest_top + 4e-4)}'
           f'</worldbody></mujoco>')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    z = []
    for _ in range(250):
        mujoco.mj_step(m, d)
        z.append(float(d.xpos[2, 2]))
    return ours, {"top_sink_mm": 1e3 * (rest_top - np.mean(z[-25:]))}


@case("mass ratio 1:1000: a 1 kg box on a 1 t plate on the ground")
def _light_on_heavy(ctx):
    ours, native = _stack(heavy_on_top=False)
    observed = {**ours, "native_top_sink_mm": native["top_sink_mm"]}
    ok = ours["finite"] and abs(ours["top_sink_mm"]) < 1.0 and ours["top_final_speed"] < 1e-2 and not ours["n_warnings"]
    return "the stack rests (the box sinks < 1 mm in all, speed < 1 cm/s); finite; no warning", observed, ok


@case("mass ratio 1000:1: a 1 t box on a 1 kg plate on the ground")
def _heavy_on_light(ctx):
    ours, native = _stack(heavy_on_top=True)
    observed = {**ours, "native_top_sink_mm": native["top_sink_mm"]}
    err = ours["top_sink_mm"] / native["top_sink_mm"] - 1
    ok = ours["finite"] and abs(err) <= 0.25 and ours["top_final_speed"] < 1e-2
    return ("as native MuJoCo: its contacts' stiffness scales with the lighter body in each contact, so the 1 kg plate "
            "between the 1 t box and the ground gives way by the same depth in both (within 25%); finite; zoo.sim warns "
            "when the penetration passes a quarter of the plate"), observed, ok


@case("impact crossing the margin in one step (5 m/s, dt 2 ms: 10 mm per step, margin 1 mm)")
def _impact(ctx):
    sim, run = _ball_drop(0.02, 5.0, 0.3)
    widened = sum(r.speculative for r in sim.log)
    observed = {**_common(sim, run), "steps_with_widened_margin": widened, "lowest_centre_mm": 1e3 * run["z"].min(),
                "final_height_mm": 1e3 * run["z"][-1]}
    ok = run["finite"] and widened > 0 and run["z"].min() > 0 and run["z"][-1] > RADIUS - 1e-3
    return ("detected (the margin widened to the closing distance on those steps, logged); the ball never passes the "
            "plane (its centre stays above) and rests on it; finite"), observed, ok


@case("impact far too fast to stop (50 m/s, dt 2 ms: 10 cm per step)")
def _impact_extreme(ctx):
    sim, run = _ball_drop(0.2, 50.0, 0.1)
    passed = bool(run["z"].min() < 0)
    observed = {**_common(sim, run), "passed_through": passed, "lowest_centre_mm": 1e3 * run["z"].min()}
    ok = run["finite"] and (not passed or any("deep penetration" in w for w in sim.warnings))
    return "either the ball is stopped or zoo.sim warns of the deep penetration before it passes: never silently", observed, ok


@case("deep initial penetration: a ball starting 3 cm into the ground")
def _deep_start(ctx):
    native = native_run("sphere", (0.3, 0.1), RADIUS - 0.03, seconds=0.6)
    native_jump = native["z"].max() - RADIUS
    sim = _simulation(0.002)
    _sphere_on_ground(sim, RADIUS - 0.03)
    run = _run(sim, 0.6, "ball")
    jump = run["z"].max() - RADIUS
    observed = {**_common(sim, run), "max_speed": run["speed"].max(), "final_penetration_mm": 1e3 * (RADIUS - run["z"][-1]),
                "jump_mm": 1e3 * jump, "native_jump_mm": 1e3 * native_jump}
    ok = (run["finite"] and run["speed"].max() < 2.0 and jump < max(2 * native_jump, 0.01) and RADIUS - run["z"][-1] < 1e-3
          and any("deep penetration" in w for w in sim.warnings))
    return ("pushed out without an explosion (speed < 2 m/s; it jumps no higher than twice native MuJoCo's ball from the "
            "same depth) and rests (< 1 mm); finite; zoo.sim warns of the deep start"), observed, ok


@case("10 s of resting contact: a box on a 2-triangle plane")
def _long_rest(ctx):
    import zoo

    sim = _simulation(0.002)
    sim.add_body("box", sdf=zoo.Box(half_extents=(HALF, HALF, HALF)), mass=MASS, inertia=box_inertia(), pose=_pose(HALF - 1e-4, 0.3, 0.1))
    sim.add_body("ground", mesh=two_triangle_plane(), joint="fixed")
    run = _run(sim, 10.0, "box")
    settled = int(round(0.5 / sim.dt))
    start, end = sim.log[settled], sim.log[-1]
    energy = run["energy"]
    gain = float(energy[settled:].max() - energy[settled])
    drift = float(np.linalg.norm(sim.pose("box")[:2, 3] - [0.3, 0.1]))
    tilt = float(np.degrees(np.arccos(np.clip(sim.pose("box")[2, 2], -1, 1))))
    observed = {**_common(sim, run), "energy_gain_after_0.5s_J": gain, "horizontal_drift_mm": 1e3 * drift, "tilt_deg": tilt,
                "penetration_mm_at_0.5s": 1e3 * start.max_penetration, "penetration_mm_at_10s": 1e3 * end.max_penetration}
    ok = run["finite"] and gain <= 1e-4 and drift < 1e-4 and tilt < 0.1
    return "no energy gain (< 0.1 mJ after settling), no drift (< 0.1 mm, < 0.1 degree); finite", observed, ok


@case("over 1,000 simultaneous contacts (no reduction: a 40 cm box on a 128x128-cell plane)")
def _many(ctx):
    import zoo

    sim = _simulation(0.002, reduce=False)
    half = (0.2, 0.2, 0.02)
    sim.add_body("slab", sdf=zoo.Box(half_extents=half), mass=MASS, inertia=box_inertia(half), pose=_pose(half[2] - 1e-4, 0.002, 0.003))
    sim.add_body("ground", mesh=grid_plane(128, 1.0), joint="fixed")
    run = _run(sim, 0.1, "slab")
    force = sim.normal_force("slab")
    observed = {**_common(sim, run), "normal_force_N": force, "weight_N": MASS * G, "final_speed": run["speed"][-1]}
    ok = run["finite"] and max(r.contacts for r in sim.log) > 1000 and abs(force / (MASS * G) - 1) < 0.05 and not sim.warnings
    return "> 1,000 contacts in MuJoCo's solver, the slab rests (normal force within 5% of m g); finite; no warning", observed, ok


def run_sim_stress(out: str | Path = "out/stress-sim.json", only: list[str] | None = None) -> dict:
    """Run the cases (those whose name starts with one of ``only``); write and return the report."""
    chosen = [(n, f) for n, f in CASES if not only or any(n.startswith(o) for o in only)]
    records = [run_case(name, fn, {}) for name, fn in chosen]
    report = {"machine": platform.machine(), "passed": sum(r["ok"] for r in records),
              "failed": sum(not r["ok"] for r in records), "cases": records}
    atomic_write_text(out, json.dumps(report, indent=1, default=_plain))
    return report


def _plain(value):
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return str(value)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="out/stress-sim.json")
    parser.add_argument("--only", nargs="*", help="run the cases whose name starts with these")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    report = run_sim_stress(args.out, args.only)
    for r in report["cases"]:
        print(f"{'ok  ' if r['ok'] else 'FAIL'} {r['case']:<90} {r['seconds']:.1f}s")
    print(f"{report['passed']} passed, {report['failed']} failed in {time.perf_counter() - t0:.0f} s; wrote {args.out}")
    return 0 if not report["failed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
