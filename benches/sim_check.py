"""zoo.sim against MuJoCo's native contacts, the same bodies in the same run.

Cases: a sphere dropped exactly over a vertex of a finely triangulated plane, a sphere on a
2-triangle plane, a box resting (on both planes), a box sliding at 1 m/s with friction 1. Each
compares the resting penetration (within 25% of native), the normal force (within 1% of m g) and
the sliding distance (within 10% of native).

    python -m sdfzoo.benches.sim_check --out out/sim-check.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from zoo.files import atomic_write_text

DT = 0.002
SETTLE_S = 0.6  # a 1 kg body on solref (0.02, 1) settles within 0.2 s
AVERAGE_S = 0.1  # resting values are means over the last 0.1 s
MASS = 1.0
RADIUS = 0.05
HALF = 0.05  # the resting box's half side (a cube)
# The sliding box is flat: a cube with friction 1 is exactly at the tipping threshold (friction's moment
# about the front edge equals gravity's), where the outcome depends on where within a millimetre the
# front contacts lie; MuJoCo's box-plane corners hold it, any other contact set tips it.
SLIDER = (0.1, 0.1, 0.025)
G = 9.81
TOLERANCE = {"penetration": 0.25, "normal_force": 0.01, "slide": 0.10}


# -- geometry ---------------------------------------------------------------------------------


def two_triangle_plane(half: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A 10 m square ground in z = 0 as 2 triangles: (V (4, 3), F (2, 3))."""
    v = np.array([(-half, -half, 0), (half, -half, 0), (half, half, 0), (-half, half, 0)], dtype=np.float64)
    return v, np.array([(0, 1, 2), (0, 2, 3)])


def grid_plane(cells: int = 64, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A square of ``size`` in z = 0, ``cells`` x ``cells`` squares split in 2 triangles; (0, 0) is a vertex (even cells)."""
    g = np.linspace(-size / 2, size / 2, cells + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    b = a + cells + 1
    return v, np.concatenate([np.stack([a, b, b + 1], 1), np.stack([a, b + 1, a + 1], 1)])


def sphere_inertia() -> list[float]:
    return [0.4 * MASS * RADIUS ** 2] * 3


def box_inertia(half=(HALF, HALF, HALF)) -> list[float]:
    x, y, z = (2 * h for h in half)
    return [MASS * (y * y + z * z) / 12, MASS * (x * x + z * z) / 12, MASS * (x * x + y * y) / 12]


# -- native MuJoCo ----------------------------------------------------------------------------


def native_run(shape: str, xy=(0.0, 0.0), z0: float = 0.0, velocity=(0.0, 0.0, 0.0), seconds: float = SETTLE_S,
               half=(HALF, HALF, HALF), dt: float = DT) -> dict:
    """The body on MuJoCo's own plane: trajectory of heights and x, and the normal forces."""
    import mujoco

    inertia = sphere_inertia() if shape == "sphere" else box_inertia(half)
    geom = f'type="sphere" size="{RADIUS}"' if shape == "sphere" else f'type="box" size="{" ".join(map(str, half))}"'
    xml = f"""<mujoco><option timestep="{dt}" integrator="implicitfast"/><worldbody>
<geom type="plane" size="10 10 1" friction="1 0.005 0.0001"/>
<body pos="{xy[0]} {xy[1]} {z0}"><freejoint/><inertial pos="0 0 0" mass="{MASS}" diaginertia="{' '.join(map(str, inertia))}"/>
<geom {geom} friction="1 0.005 0.0001"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:3] = velocity
    heights, xs, forces = [], [], []
    force = np.zeros(6)
    for _ in range(int(round(seconds / dt))):
        mujoco.mj_step(m, d)
        heights.append(float(d.qpos[2]))
        xs.append(float(d.qpos[0]))
        total = 0.0
        for i in range(d.ncon):
            mujoco.mj_contactForce(m, d, i, force)
            total += force[0]
        forces.append(total)
    return {"z": np.array(heights), "x": np.array(xs), "force": np.array(forces), "contacts": int(d.ncon)}


# -- zoo.sim ----------------------------------------------------------------------------------


def zoo_run(shape: str, ground, xy=(0.0, 0.0), z0: float = 0.0, velocity=(0.0, 0.0, 0.0), seconds: float = SETTLE_S,
            method: str = "fw", reduce: bool = True, half=(HALF, HALF, HALF), refine: bool = True) -> dict:
    import zoo
    import zoo.sim

    sim = zoo.sim.Simulation(dt=DT, method=method, friction=1.0, reduce=reduce, refine=refine)
    sdf = zoo.Sphere(radius=RADIUS) if shape == "sphere" else zoo.Box(half_extents=half)
    pose = np.eye(4)
    pose[:3, 3] = (xy[0], xy[1], z0)
    sim.add_body("body", sdf=sdf, mass=MASS, inertia=sphere_inertia() if shape == "sphere" else box_inertia(half), pose=pose,
                 velocity=(*velocity, 0.0, 0.0, 0.0))
    sim.add_body("ground", mesh=ground, joint="fixed")
    heights, xs, forces = [], [], []
    for _ in range(int(round(seconds / DT))):
        sim.step()
        p = sim.pose("body")
        heights.append(float(p[2, 3]))
        xs.append(float(p[0, 3]))
        forces.append(sim.normal_force("body"))
    return {"z": np.array(heights), "x": np.array(xs), "force": np.array(forces), "contacts": sim.log[-1].contacts,
            "collide_ms": 1e3 * float(np.mean([r.collide_s for r in sim.log])), "warnings": sim.warnings}


# -- cases ------------------------------------------------------------------------------------


def resting(run: dict, half: float) -> dict:
    """Mean penetration (m) and normal force (N) over the last AVERAGE_S."""
    tail = int(round(AVERAGE_S / DT))
    return {"penetration": float(np.mean(half - run["z"][-tail:])), "normal_force": float(np.mean(run["force"][-tail:]))}


def rest_case(name: str, shape: str, ground, xy=(0.0, 0.0), reduce: bool = True) -> dict:
    half = RADIUS if shape == "sphere" else HALF
    z0 = half + 5e-4  # released half a millimetre above the plane
    native = resting(native_run(shape, xy, z0), half)
    run = zoo_run(shape, ground, xy, z0, reduce=reduce)
    ours = resting(run, half)
    pen_err = ours["penetration"] / native["penetration"] - 1
    force_err = ours["normal_force"] / (MASS * G) - 1
    return {
        "case": name, "native_penetration_mm": 1e3 * native["penetration"], "zoo_penetration_mm": 1e3 * ours["penetration"],
        "penetration_error": float(pen_err), "native_normal_force_N": native["normal_force"], "zoo_normal_force_N": ours["normal_force"],
        "normal_force_error": float(force_err), "zoo_contacts": run["contacts"], "collide_ms_per_step": run["collide_ms"],
        "warnings": run["warnings"],
        "ok": bool(abs(pen_err) <= TOLERANCE["penetration"] and abs(force_err) <= TOLERANCE["normal_force"] and not run["warnings"]),
    }


def slide_case(name: str, ground, speed: float = 1.0) -> dict:
    z0 = SLIDER[2] - 1e-4  # resting depth, so the slide starts on the ground
    native = native_run("box", z0=z0, velocity=(speed, 0, 0), seconds=0.3, half=SLIDER)
    run = zoo_run("box", ground, z0=z0, velocity=(speed, 0, 0), seconds=0.3, half=SLIDER)
    nd, zd = native["x"][-1] - native["x"][0], run["x"][-1] - run["x"][0]
    err = zd / nd - 1
    return {"case": name, "native_slide_m": float(nd), "zoo_slide_m": float(zd), "coulomb_slide_m": speed ** 2 / (2 * G),
            "slide_error": float(err), "zoo_contacts": run["contacts"], "warnings": run["warnings"],
            "ok": bool(abs(err) <= TOLERANCE["slide"] and not run["warnings"])}


def run_check() -> dict:
    fine, coarse = grid_plane(64, 1.0), two_triangle_plane()
    t0 = time.perf_counter()
    cases = [
        rest_case("sphere over a vertex of a 64x64-cell plane (8,192 triangles)", "sphere", fine),
        rest_case("sphere on a 2-triangle plane", "sphere", coarse, xy=(0.3, 0.1)),
        rest_case("box resting on a 2-triangle plane", "box", coarse, xy=(0.3, 0.1)),
        rest_case("box resting on a 64x64-cell plane", "box", fine),
        slide_case("flat box sliding at 1 m/s, friction 1, 2-triangle plane", coarse),
        slide_case("flat box sliding at 1 m/s, friction 1, 64x64-cell plane", fine),
    ]
    return {"tolerance": TOLERANCE, "dt": DT, "mass_kg": MASS, "seconds": time.perf_counter() - t0,
            "platform": platform.platform(), "cases": cases, "ok": all(c["ok"] for c in cases)}


def tessellation_table(cells=(1, 2, 4, 8, 16, 64), seconds: float = SETTLE_S) -> list[dict]:
    """Resting penetration of a sphere over the centre of a 1 m plane of 2 * cells^2 triangles (a vertex for even
    cells) and of a box there: native MuJoCo, zoo.sim's reduced contacts, every contact zoo.collide gives on the
    refined mesh (raw), and on the mesh as given (unrefined raw: no clipping of large triangles either)."""
    rows = []
    for shape in ("sphere", "box"):
        half = RADIUS if shape == "sphere" else HALF
        z0 = half + 5e-4
        native = resting(native_run(shape, (0.0, 0.0), z0, seconds=seconds), half)["penetration"]
        for n in cells:
            plane = grid_plane(n, 1.0)
            row = {"shape": shape, "triangles": 2 * n * n, "native_mm": 1e3 * native}
            for label, reduce, refine in (("reduced", True, True), ("raw", False, True), ("unrefined_raw", False, False)):
                run = zoo_run(shape, plane, (0.0, 0.0), z0, seconds=seconds, reduce=reduce, refine=refine)
                row[f"{label}_mm"] = 1e3 * resting(run, half)["penetration"]
                row[f"{label}_contacts"] = int(run["contacts"])
            rows.append(row)
    return rows


def table(report: dict) -> str:
    lines = ["| case | native | zoo.sim | error | ok |", "|---|---|---|---|---|"]
    for c in report["cases"]:
        if "slide_error" in c:
            lines.append(f"| {c['case']} | slide {c['native_slide_m']:.4f} m | {c['zoo_slide_m']:.4f} m | {100 * c['slide_error']:+.1f}% | {c['ok']} |")
        else:
            lines.append(f"| {c['case']} | pen. {c['native_penetration_mm']:.3f} mm | {c['zoo_penetration_mm']:.3f} mm | "
                         f"{100 * c['penetration_error']:+.1f}% (force {100 * c['normal_force_error']:+.2f}% of m g) | {c['ok']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="out/sim-check.json")
    parser.add_argument("--tessellation", action="store_true", help="also the resting penetration on planes of 2 to 8,192 "
                        "triangles, native vs reduced vs raw contacts (docs/sim-contacts.md)")
    args = parser.parse_args(argv)
    report = run_check()
    if args.tessellation:
        report["tessellation"] = tessellation_table()
        print("| shape | triangles | native (mm) | reduced (mm, contacts) | raw (mm, contacts) | unrefined raw (mm, contacts) |\n"
              "|---|---|---|---|---|---|")
        for r in report["tessellation"]:
            print(f"| {r['shape']} | {r['triangles']} | {r['native_mm']:.3f} | {r['reduced_mm']:.3f} ({r['reduced_contacts']}) | "
                  f"{r['raw_mm']:.3f} ({r['raw_contacts']}) | {r['unrefined_raw_mm']:.3f} ({r['unrefined_raw_contacts']}) |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(report, indent=1))
    print(table(report))
    print(f"{'all within tolerance' if report['ok'] else 'SOME CASES FAIL'}; written to {out}")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
