"""The Panda scenes with MuJoCo's own contacts: what most users do today, beside sdfzoo's runs of the same scenes.

Each scene of :mod:`benches.panda_scenarios` (``scenes/panda-*.toml``) is rebuilt on the same MJCF (the Panda, its
actuators, the table) with the same waypoints, initial posture, poses, masses and time step, but the object and the
rack or holder are convex pieces cut by CoACD from their meshes (:func:`benches.sim_references.decompose`, cached),
collided by MuJoCo natively. The object's mesh is the one its NeuralSDF was fitted to: the category's source mesh for
a shape of the model, the test-split mesh named in the codes file for an unseen one (its sha256 checked), scaled as
the scene scales the SDF. The run is held to the scenario's own check (:func:`benches.panda_scenarios.check`).

    ZOO_DATA=../shared/meshes python -m sdfzoo.benches.panda_coacd --run panda-mug-rack
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from sdfzoo.benches.panda_scenarios import PLANS, SCENES, check, finger_contacts, load_sdf, step_metrics
from sdfzoo.benches.sim_references import body_mesh, decompose, pieces_mass_properties, source_mesh_file
from zoo.errors import DataError


def object_mesh(sdf_spec: dict) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(vertices (V, 3) in metres, faces (F, 3), digest, label) of the mesh a scene's ``sdf = {...}`` was fitted to,
    scaled by its ``scale``."""
    from safetensors import safe_open

    from sdfzoo.pipeline.categories import load_category
    from zoo.files import sha256_file
    from zoo.meshes import load_mesh

    scale = float(sdf_spec.get("scale", 1.0))
    if "model" in sdf_spec:
        path = source_mesh_file(sdf_spec)
    else:
        with safe_open(str(SCENES / sdf_spec["codes"]), "np") as f:
            meta = f.metadata()
        fit = json.loads(meta["fit"])
        path = Path(os.environ["ZOO_DATA"]) / load_category(meta["model"].split("@")[0]).entry(meta["name"]).file
        if sha256_file(path) != fit["mesh_sha256"]:
            raise DataError(f"{path} is not the mesh {sdf_spec['codes']} was fitted to (sha256 differs)")
    mesh = load_mesh(path)
    digest = f"{sha256_file(path)}@{scale!r}"
    return np.asarray(mesh.vertices, np.float64) * scale, np.asarray(mesh.faces, np.int64), digest, f"{path.name} x {scale:g}"


def native_model(name: str) -> tuple[object, object, dict, dict]:
    """(model, data, the scene's table, {body: decomposition info}) of scene ``name`` with CoACD pieces for its bodies."""
    import mujoco

    from zoo.scenes import pose_matrix, read_scene
    from zoo.sim.model import compile_spec, new_spec, quaternion

    scene = read_scene(SCENES / f"{name}.toml")[0]
    spec = new_spec(SCENES / scene["mjcf"])
    spec.option.timestep = float(scene["sim"]["dt"])
    info = {}
    for body in scene["bodies"]:
        vertices, faces, digest, label = object_mesh(body["sdf"]) if "sdf" in body else body_mesh(body)
        pieces, made = decompose(vertices, faces, digest)
        info[body["name"]] = {"mesh": label, "faces": int(len(faces)), "pieces": len(pieces), **made}
        pose = pose_matrix(body.get("pose"))
        b = spec.worldbody.add_body(name=body["name"], pos=pose[:3, 3], quat=quaternion(pose[:3, :3]))
        if body.get("joint", "free") == "free":
            b.add_freejoint()
            com, inertia = pieces_mass_properties(pieces, float(body["mass"]))
            b.explicitinertial, b.mass, b.ipos = True, float(body["mass"]), com
            b.fullinertia = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
        for i, (v, f) in enumerate(pieces):
            spec.add_mesh(name=f"{body['name']}_{i}", uservert=v.reshape(-1).tolist(), userface=f.reshape(-1).tolist())
            b.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{body['name']}_{i}", density=0.0)
    model, data = compile_spec(spec)
    for joint, value in scene["sim"].get("qpos", {}).items():
        data.qpos[model.jnt_qposadr[model.joint(joint).id]] = float(value)
    return model, data, scene, info


class NativeRun:
    """What :func:`benches.panda_scenarios.check` reads of a run, on the native model."""

    def __init__(self, model, data, sdf):
        self.model, self.data = model, data
        self.bodies = {"mug": SimpleNamespace(sdf=sdf), "bottle": SimpleNamespace(sdf=sdf)}

    def pose(self, name: str) -> np.ndarray:
        from zoo.sim.geoms import body_pose

        return body_pose(self.data, self.model.body(name).id)

    def velocity(self, name: str) -> np.ndarray:
        from zoo.sim.geoms import body_velocity

        return body_velocity(self.model, self.data, self.model.body(name).id)


def object_contacts(model, data, body: int) -> tuple[int, float]:
    """(contacts of ``body`` this step, the deepest one's penetration in m, 0 if none)."""
    n, deepest = 0, 0.0
    for i in range(data.ncon):
        c = data.contact[i]
        if body in (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]):
            n += 1
            deepest = max(deepest, -float(c.dist))
    return n, deepest


def run(name: str, seconds: float | None = None) -> dict:
    """Scene ``name`` on CoACD pieces and MuJoCo's collision: its check, time per step, the object's contacts per step
    and deepest penetration, with :func:`benches.panda_scenarios.run`'s keys."""
    import mujoco

    from zoo.sim.control import Waypoints

    model, data, scene, info = native_model(name)
    obj = "mug" if "mug" in name else "bottle"
    body = model.body(obj).id
    waypoints = Waypoints(model, scene["control"])
    seconds = float(scene["sim"]["seconds"]) if seconds is None else seconds
    steps = int(round(seconds / model.opt.timestep))
    every = max(1, int(round(0.04 / model.opt.timestep)))
    mujoco.mj_forward(model, data)
    run_ = NativeRun(model, data, load_sdf(scene["bodies"][0]["sdf"]) if obj == "mug" else None)
    step_s, contacts, penetration, trace = np.zeros(steps), np.zeros(steps, np.int64), np.zeros(steps), []
    for i in range(steps):
        waypoints.apply(data, float(data.time))
        started = time.perf_counter()
        mujoco.mj_step(model, data)
        step_s[i] = time.perf_counter() - started
        contacts[i], penetration[i] = object_contacts(model, data, body)
        if i % every == 0:
            mujoco.mj_kinematics(model, data)
            trace.append({"time": float(data.time), "pose": run_.pose(obj), "fingers": finger_contacts(run_, obj)})
    mujoco.mj_forward(model, data)
    result = check(run_, name, trace)
    result.update(step_metrics(step_s, contacts, penetration))
    result.update({"scene": name, "method": "coacd-native", "seconds": float(data.time), "decomposition": info,
                   "warnings": [mujoco.mjtWarning(k).name for k, w in enumerate(data.warning) if w.number]})
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", choices=sorted(PLANS), action="append", required=True)
    parser.add_argument("--seconds", type=float)
    args = parser.parse_args(argv)
    for name in args.run:
        print(json.dumps(run(name, args.seconds), indent=1, default=str))


if __name__ == "__main__":
    sys.exit(main())
