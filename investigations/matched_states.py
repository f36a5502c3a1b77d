"""Each contact path at the full path's own states: which contacts hold the nut up, the trajectories' chaos taken out.

``investigations fidelity`` compares whole runs, where a micrometre's difference in one step's contacts sends the nut
down another trajectory. This runs the full path (``method="amortized", coherence=False``) on one of its nut scenes
and records the state before each step of the scene's window (steps 40-60); then, from each recorded state, each
path detects its contacts and takes one step (its colliders reset first: nothing carried over), and reports the
contacts MuJoCo got, the deepest, and the nut's velocity along the bolt after the step. From the same state, a path
whose contacts hold the nut up less lets it fall faster.

    python -m investigations matched_states --scene nut-heavy --out out/matched-states.json
"""

from __future__ import annotations

import argparse

import numpy as np

from investigations.fidelity import PATHS, SCENES

NUT_SCENES = sorted(name for name, (file, *_) in SCENES.items() if file == "sim-bolt-nut")


def nut_simulation(scene: str, path: str):
    """The nut scene ``scene`` built on contact path ``path`` (a key of ``investigations.fidelity.PATHS``), the nut's
    mass and inertia scaled as the scene says: (simulation, the nut's body id, the scene's options)."""
    import zoo.sim

    file, _, _, options = SCENES[scene]
    sim = zoo.sim.load_scene(file, **PATHS[path])
    sim.build()
    nut = sim.bodies["nut"].body_id
    sim.model.body_mass[nut] *= options["mass"]
    sim.model.body_inertia[nut] *= options["mass"]
    return sim, nut, options


def full_path_states(scene: str) -> list[dict]:
    """The full path's states before each step of ``scene``'s window, the nut driven as ``investigations fidelity``
    drives it (the Bolt-Nut scenario's feed-forward torque and speed servo, scaled)."""
    from sdfzoo.benches.sim_scenarios import NUT_KV, NUT_SPEED, NUT_TORQUE

    sim, nut, options = nut_simulation(scene, "full")
    lo, hi = SCENES[scene][2]
    states = []
    for k in range(hi):
        spin = float(sim.velocity("nut")[5])
        sim.data.xfrc_applied[nut, 3:] = (0.0, 0.0, options["torque"] * NUT_TORQUE + NUT_KV * (options["speed"] * NUT_SPEED - spin))
        if k >= lo:
            states.append({"step": k, "qpos": sim.data.qpos.copy(), "qvel": sim.data.qvel.copy(),
                           "xfrc": sim.data.xfrc_applied.copy(), "time": float(sim.data.time)})
        sim.step()
    return states


def step_from(sim, state: dict) -> dict:
    """One step of ``sim`` from ``state``, its colliders reset: the contacts MuJoCo got, the deepest (mm) and the
    nut's velocity along the bolt after the step (mm/s)."""
    import mujoco

    data = sim.data
    data.qpos[:], data.qvel[:], data.xfrc_applied[:], data.time = state["qpos"], state["qvel"], state["xfrc"], state["time"]
    mujoco.mj_forward(sim.model, data)
    sim.world.reset()
    sim.step()
    depths = np.asarray(sim.world.contacts.depths, dtype=np.float64)
    return {"contacts": int(len(depths)), "deepest_mm": -1e3 * float(depths.min()) if len(depths) else 0.0,
            "vz_after_mm_s": 1e3 * float(data.qvel[2])}


def main(argv=None) -> None:
    import torch

    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=NUT_SCENES, default="nut-heavy")
    parser.add_argument("--path", action="append", choices=sorted(PATHS), default=[], help="default: all")
    parser.add_argument("--out", default="out/matched-states.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    paths = args.path or sorted(PATHS)
    states = full_path_states(args.scene)
    rows = {}
    for path in paths:
        sim = nut_simulation(args.scene, path)[0]
        rows[path] = [step_from(sim, state) for state in states]
    summary = {}
    for path, got in rows.items():
        summary[path] = {key: float(np.mean([r[key] for r in got])) for key in ("contacts", "deepest_mm", "vz_after_mm_s")}
        if "full" in rows and path != "full":
            gap = [abs(a["vz_after_mm_s"] - b["vz_after_mm_s"]) for a, b in zip(got, rows["full"])]
            summary[path].update(vz_gap_mean_mm_s=float(np.mean(gap)), states_over_1mm_s=int(sum(g > 1.0 for g in gap)))
        print(f"{path:>8}: {summary[path]['contacts']:.1f} contacts, deepest {summary[path]['deepest_mm']:.4f} mm, "
              f"the nut's velocity after {summary[path]['vz_after_mm_s']:+.3f} mm/s (means over {len(states)} states)"
              + (f"; from the full path's by {summary[path]['vz_gap_mean_mm_s']:.3f} mm/s on average, by more than "
                 f"1 mm/s at {summary[path]['states_over_1mm_s']}" if "vz_gap_mean_mm_s" in summary[path] else ""),
              flush=True)
    write_report(args.out, {"scene": args.scene, "steps": [s["step"] for s in states], "rows": rows,
                            "summary": summary}, "matched_states", argv)


if __name__ == "__main__":
    main()
