"""Each contact path at the full path's own gear states, every deepest contact held against the NeuralSDF on its face.

``investigations fidelity`` holds each path's deepest penetration against the full path's (``method="amortized",
coherence=False``) on the gears. This asks whether the full path is right there. It runs the full path on
``sim-gear-gear`` (friction 0 by default: no jam) and records the state before each step; from each state, each path
detects its contacts (its colliders reset first) and reports its deepest. That contact's face is then searched by
brute force: the NeuralSDF's least over a barycentric grid of ``--grid`` points a side (``zoo.geometry.barycentric_grid``),
the face in the bodies' poses at that state. A state's truth is the deepest of those over the faces any path
reported. A path can fall short of it in two ways: it misreports (its deepest is shallower than the grid's least on
its own face) or it misses (another path's face holds the truth, and this path reported less).

    python -m investigations gear_states --out out/gear-states.json
"""

from __future__ import annotations

import argparse
from typing import NamedTuple

import numpy as np

from investigations.fidelity import PATHS

SCENE = "sim-gear-gear"
SHORT = 5e-6  # m: a path this far short of a state's truth counts as missing it

parser = argparse.ArgumentParser(prog="python -m investigations gear_states", description=__doc__.splitlines()[0])
parser.add_argument("--path", action="append", choices=sorted(PATHS), default=[], help="default: all")
parser.add_argument("--friction", type=float, default=0.0)
parser.add_argument("--steps", type=int, default=200)
parser.add_argument("--grid", type=int, default=200, help="barycentric grid points a side on each face")
parser.add_argument("--out", default="out/gear-states.json")


def gear_simulation(path: str, friction: float):
    """The gears on contact path ``path`` (a key of ``investigations.fidelity.PATHS``), their one SDF-mesh pair."""
    import zoo.sim

    sim = zoo.sim.load_scene(SCENE, friction=friction, **PATHS[path])
    sim.build()
    if len(sim.world.pairs) != 1:
        raise SystemExit(f"{SCENE} was expected to hold one SDF-mesh pair, it holds {len(sim.world.pairs)}")
    return sim


def full_path_states(friction: float, steps: int) -> list[dict]:
    """The full path's states before each of its first ``steps`` steps."""
    sim = gear_simulation("full", friction)
    states = []
    for _ in range(steps):
        d = sim.data
        states.append({"qpos": d.qpos.copy(), "qvel": d.qvel.copy(), "act": d.act.copy(), "ctrl": d.ctrl.copy(),
                       "time": float(d.time)})
        sim.step()
    return states


def set_state(sim, state: dict) -> None:
    import mujoco

    d = sim.data
    d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:], d.time = state["qpos"], state["qvel"], state["act"], state["ctrl"], state["time"]
    mujoco.mj_forward(sim.model, d)


def deepest_contact(sim, state: dict) -> tuple[float, int]:
    """The deepest contact ``sim``'s world detects at ``state`` (its colliders reset): (penetration m, >= 0; its face,
    -1 where none)."""
    set_state(sim, state)
    sim.world.reset()
    sim.world.add_contacts(sim.data)
    contacts = sim.world.contacts
    if not len(contacts):
        return 0.0, -1
    i = int(np.argmin(np.asarray(contacts.depths)))
    return max(0.0, -float(contacts.depths[i])), int(contacts.triangles[i])


class FacePoses(NamedTuple):
    """The pair's surface pose and its SDF body's pose (4, 4) at one state, world frame."""

    surface: np.ndarray
    sdf: np.ndarray


def face_poses(sim, state: dict) -> FacePoses:
    """The poses of the scene's first pair at ``state``."""
    from zoo.sim.geoms import body_pose

    set_state(sim, state)
    pair = sim.world.pairs[0]
    return FacePoses(pair.surface_pose(sim.data), body_pose(sim.data, pair.sdf_body.body))


def grid_depth(pair, poses: FacePoses, face: int, grid) -> float:
    """The NeuralSDF's least over mesh face ``face`` of ``pair`` at ``poses`` (:func:`face_poses`), on the barycentric
    ``grid`` (G, 3): penetration m."""
    import torch

    other, sdf_pose = poses.surface, poses.sdf
    corners = pair.vertices[pair.faces[face]] @ other[:3, :3].T + other[:3, 3]  # world
    local = (corners - sdf_pose[:3, 3]) @ sdf_pose[:3, :3]  # the SDF's frame
    with torch.no_grad():
        values = pair.sdf_body.sdf(torch.as_tensor(grid @ local, dtype=torch.float32))
    return max(0.0, -float(values.min()))


def main(argv=None) -> None:
    import torch

    from investigations.report import write_report
    from zoo.geometry import barycentric_grid

    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    paths = args.path or sorted(PATHS)
    states = full_path_states(args.friction, args.steps)
    found = {}
    for path in paths:
        sim = gear_simulation(path, args.friction)
        found[path] = [deepest_contact(sim, state) for state in states]
    grid = barycentric_grid(args.grid, dtype=torch.float64).numpy()
    sim = gear_simulation("full", args.friction)
    rows, truth = [], []
    for k, state in enumerate(states):
        faces = sorted({found[path][k][1] for path in paths} - {-1})
        poses = face_poses(sim, state) if faces else None
        on_face = {face: grid_depth(sim.world.pairs[0], poses, face, grid) for face in faces}
        truth.append(max(on_face.values(), default=0.0))
        rows.append({"step": k, "truth_mm": 1e3 * truth[-1],
                     **{path: {"deepest_mm": 1e3 * found[path][k][0], "face": found[path][k][1],
                               "grid_on_its_face_mm": 1e3 * on_face.get(found[path][k][1], 0.0)} for path in paths}})
    summary = {}
    for path in paths:
        own = np.array([found[path][k][0] for k in range(len(states))])
        on_own = np.array([row[path]["grid_on_its_face_mm"] * 1e-3 for row in rows])
        short = np.array(truth) - own
        summary[path] = {"states_with_contact": int(np.count_nonzero(own > 0)), "deepest_mm": 1e3 * float(own.max()),
                         "misreport_mean_um": 1e6 * float(np.mean(np.abs(on_own - own))),
                         "misreport_max_um": 1e6 * float(np.max(on_own - own)),
                         "short_of_truth_states": int(np.count_nonzero(short > SHORT)),
                         "short_of_truth_max_um": 1e6 * float(short.max())}
        s = summary[path]
        print(f"{path:>8}: deepest {s['deepest_mm']:.4f} mm at these states; its deepest against the grid on its face: "
              f"{s['misreport_mean_um']:.1f} um on average, {s['misreport_max_um']:.1f} at most shallower; short of "
              f"the truth by more than {SHORT * 1e6:.0f} um at {s['short_of_truth_states']} of {len(states)} states "
              f"(by {s['short_of_truth_max_um']:.1f} um at most)", flush=True)
    print(f"   truth: deepest {1e3 * max(truth):.4f} mm (the grid's least over the faces any path reported)")
    write_report(args.out, {"scene": SCENE, "friction": args.friction, "grid": args.grid, "rows": rows,
                            "summary": summary, "truth_deepest_mm": 1e3 * max(truth)}, "gear_states", argv)


if __name__ == "__main__":
    main()
