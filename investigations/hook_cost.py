"""What ``world.hooked()`` costs against ``world.step(data)``: the same model, the same steps, timed side by side.

Both add sdfzoo's contacts at the same point of MuJoCo's step (after the velocity stage, before the solver) and give
the same trajectory; the hook goes through MuJoCo's control callback, a Python call per ``mj_step``. Runs each way
on fresh copies of one model, alternating blocks of steps so that the machine's load falls on both alike, and
reports the median time per step of each, their ratio and difference, and whether the trajectories agree.
Models: "ball" (an analytic sphere on a plane: the overhead stands out) and "mug" (the mugs model's NeuralSDF mug
held between two pads over a plane).

    python -m investigations hook_cost --out out/hook-cost.json
"""

from __future__ import annotations

import argparse
import statistics
import time
from contextlib import nullcontext

import numpy as np

BALL_XML = """<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="1 1 0.1"/>
<body name="body" pos="0 0 0.05"><freejoint/><geom type="sphere" size="0.05" contype="0" conaffinity="0" mass="0.5"/></body>
</worldbody></mujoco>"""
MUG_XML = """<mujoco><option timestep="0.002" cone="elliptic" impratio="10"/><worldbody><geom type="plane" size="1 1 0.1"/>
<geom type="box" size="0.01 0.005 0.03" pos="0 0.0465 0.065"/><geom type="box" size="0.01 0.005 0.03" pos="0 -0.0465 0.065"/>
<body name="body" pos="0 0 0.0446"><freejoint/><geom type="cylinder" size="0.04 0.045" contype="0" conaffinity="0" mass="0.2"/></body>
</worldbody></mujoco>"""


def _sdf(name: str):
    import zoo

    return zoo.Sphere(radius=0.05) if name == "ball" else zoo.load("mugs").shape("hoi4d_mug_0001")


def measure(name: str, steps: int, block: int = 10) -> dict:
    """Median seconds per step through ``world.step`` and through ``mj_step`` under ``world.hooked()``."""
    import mujoco

    import zoo.sim

    xml = BALL_XML if name == "ball" else MUG_XML
    runs = {}
    for way in ("step", "hooked"):
        model = mujoco.MjModel.from_xml_string(xml)
        runs[way] = {"model": model, "data": mujoco.MjData(model), "times": [], "states": []}
        runs[way]["world"] = zoo.sim.attach(model, {"body": _sdf(name)})
    for _ in range(0, steps, block):
        for way, run in runs.items():
            model, data, world = run["model"], run["data"], run["world"]
            with world.hooked() if way == "hooked" else nullcontext():  # a user's loop runs inside one hook
                for _ in range(block):
                    start = time.perf_counter()
                    if way == "step":
                        world.step(data)
                    else:
                        mujoco.mj_step(model, data)
                    run["times"].append(time.perf_counter() - start)
                    run["states"].append(np.concatenate([data.qpos, data.qvel]))
    medians = {way: statistics.median(run["times"]) for way, run in runs.items()}
    return {
        "model": name, "steps": steps,
        "step_median_ms": 1e3 * medians["step"], "hooked_median_ms": 1e3 * medians["hooked"],
        "hooked_over_step": medians["hooked"] / medians["step"],
        "hooked_minus_step_us": 1e6 * (medians["hooked"] - medians["step"]),
        "identical": bool(np.array_equal(np.stack(runs["step"]["states"]), np.stack(runs["hooked"]["states"]))),
    }


def main(argv=None) -> None:
    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=("ball", "mug"), action="append", default=[], help="default: both")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", default="out/hook-cost.json")
    args = parser.parse_args(argv)
    results = [measure(name, args.steps) for name in (args.model or ["ball", "mug"])]
    for r in results:
        print(r)
    write_report(args.out, {"results": results}, "hook_cost", argv)


if __name__ == "__main__":
    main()
