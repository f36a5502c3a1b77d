"""Simulation scenes: a TOML file names bodies (an SDF and/or a mesh each), masses, joints, drives and a [sim] table,
optionally on top of an MJCF file (a robot, a gripper) whose bodies can be given SDFs.

```toml
name = "sim-demo-mug-rack"
method = "amortized"            # zoo.collide's narrow phase
margin = 0.001
# mjcf = "gripper.xml"          # start from this MJCF (beside the scene file); its options hold unless [sim] sets them

[sim]
dt = 0.002                      # default 0.002 (or the MJCF's)
seconds = 0.5                   # what `zoo simulate` runs unless --seconds says otherwise
gravity = [0, 0, -9.81]
friction = 1.0                  # friction, solref, solimp: of the geoms the scene adds (default MuJoCo's)
solref = [0.02, 1.0]
solimp = [0.9, 0.95, 0.001, 0.5, 2.0]
integrator = "implicitfast"     # or "euler", "implicit", "rk4" (default implicitfast, or the MJCF's)
cone = "pyramidal"              # MuJoCo's friction cone, or "elliptic"; with impratio = 10 for a grasp
impratio = 1.0
coherence = true                # carry bounds and answers from step to step (zoo.CoherentCollider)
proxy = true                    # cull and search on a narrow-band proxy of each model shape (zoo.proxy), baked ahead
                                # ("lazy": as steps need it; false: none)
camera = "side"                 # the video's camera: one of the MJCF's, or { lookat = [x, y, z], distance = 0.3,
                                # azimuth = 135, elevation = -25 }; default: aimed at the SDF bodies
# qpos = { joint = 0.5 }        # initial positions of the MJCF's hinge and slide joints (default: the MJCF's qpos0)

[[control]]                     # waypoints (zoo.sim.control): mocap positions and actuator controls over time
time = 0.0
mocap = { hand_target = [0, 0, 0.13] }
ctrl = { left = 0.015, right = 0.015 }

[[bodies]]
name = "mug"
sdf = { model = "mugs", shape = "hoi4d_mug_0001" }   # as a collision scene's [sdf] (model, analytic, fit)
mass = 0.3                      # or density = 1000; or inertia = [ixx, iyy, izz] (with mass, com)
joint = "free"                  # free | fixed | hinge | slide (axis = [...], anchor = [...])
pose = { translation = [0, 0, 0.2], rotation_deg = [0, 0, 0] }
velocity = [0, 0, 0, 0, 0, 0]   # linear, angular (world); one number for a hinge or slide
# drive = { type = "velocity", target = 1.0, kv = 100 }  # or { type = "motor", ctrl = 0.1, gear = 1 }

[[bodies]]
name = "rack"
mesh = { procedural = "rack" }  # as a collision scene's [mesh] (procedural, file, scale)
joint = "fixed"
```

A ``[[bodies]]`` entry whose name is a body of the MJCF has only an ``sdf``: it is attached to that body
(its joints, inertia and visual geom are the MJCF's). A collision scene (``[sdf]`` and ``[mesh]`` tables, as ``zoo collide`` reads) also loads: its SDF
becomes a free body ``sdf`` (mass from ``[sim]``'s ``sdf_mass``, default 0.3 kg), raised by
``[sim]``'s ``drop`` (m, default 0), and its mesh a fixed body ``mesh``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scenes import build_mesh, build_sdf, pose_matrix, read_scene
from .simulation import Simulation

SIM_KEYS = {"dt", "seconds", "gravity", "friction", "solref", "solimp", "integrator", "cone", "impratio", "sdf_mass", "drop",
            "reduce", "refine", "coherence", "camera", "qpos", "proxy"}
SCENE_ONLY = ("seconds", "drop", "sdf_mass", "camera", "qpos")  # [sim] keys that are not Simulation's arguments
BODY_KEYS = {"name", "sdf", "mesh", "mass", "density", "inertia", "com", "joint", "axis", "anchor", "pose", "velocity", "drive"}


def simulation_from_file(path: str | os.PathLike, **overrides) -> Simulation:
    """A :class:`Simulation` from a scene file (a path or a bundled scene's name); ``overrides`` replace the
    file's values: Simulation's arguments (dt, method, margin, friction, ...) and [sim]'s seconds, drop,
    sdf_mass; None keeps the file's. ``sim.scene_path`` is the file read."""
    spec, resolved = read_scene(path)
    sim = scene_simulation(spec, base_dir=resolved.parent, **overrides)
    sim.scene_path = resolved
    return sim


def simulation_settings(spec: dict, **overrides) -> dict:
    """:class:`Simulation`'s arguments from a scene's table (its [sim] values, defaults for the rest) and
    ``overrides`` (None keeps the file's); [sim]'s seconds, drop and sdf_mass are not among them."""
    sim_spec = spec.get("sim", {})
    unknown = set(sim_spec) - SIM_KEYS
    if unknown:
        raise InputError(f"unknown [sim] keys {sorted(unknown)}; known: {sorted(SIM_KEYS)}")
    settings = {
        "dt": sim_spec.get("dt"), "gravity": sim_spec.get("gravity"),
        "method": spec.get("method", "amortized"), "margin": float(spec.get("margin", 1e-3)),
        "friction": sim_spec.get("friction"), "solref": sim_spec.get("solref"),
        "solimp": sim_spec.get("solimp"), "integrator": sim_spec.get("integrator"),
        "cone": sim_spec.get("cone"), "impratio": sim_spec.get("impratio"),
        "reduce": sim_spec.get("reduce", True), "refine": sim_spec.get("refine", True),
        "coherence": sim_spec.get("coherence", True), "proxy": sim_spec.get("proxy", True),
    }
    settings.update({k: v for k, v in overrides.items() if v is not None and k not in SCENE_ONLY})
    return settings


def scene_simulation(spec: dict, base_dir: Path = Path("."), **overrides) -> Simulation:
    """A :class:`Simulation` from a scene's table (see the module docstring)."""
    sim_spec = dict(spec.get("sim", {}))
    sim_spec.update({k: overrides.pop(k) for k in SCENE_ONLY if overrides.get(k) is not None})
    settings = simulation_settings({**spec, "sim": sim_spec}, **overrides)
    mjcf = spec.get("mjcf")
    sim = Simulation(**settings, mjcf=None if mjcf is None else base_dir / mjcf)
    sim.name = spec.get("name", "scene")
    sim.seconds = float(sim_spec.get("seconds", 1.0))
    sim.camera = sim_spec.get("camera")
    sim.initial_qpos = dict(sim_spec.get("qpos", {}))
    sim.control = list(spec.get("control", []))
    bodies = spec.get("bodies")
    if bodies is None:
        bodies = _collision_scene_bodies(spec, sim_spec)
    if not bodies:
        raise InputError("a simulation scene needs [[bodies]] (or a collision scene's [sdf] and [mesh]), or an mjcf and bodies to attach")
    for body in bodies:
        _add_body(sim, body, base_dir)
    return sim


def _collision_scene_bodies(spec: dict, sim_spec: dict) -> list[dict]:
    """A collision scene's [sdf] and [mesh] as a free SDF body over a fixed mesh body."""
    if "sdf" not in spec or "mesh" not in spec:
        return []
    pose = pose_matrix(spec["sdf"].get("pose"))
    pose[2, 3] += float(sim_spec.get("drop", 0.0))
    sdf = {k: v for k, v in spec["sdf"].items() if k != "pose"}
    mesh = {k: v for k, v in spec["mesh"].items() if k != "pose"}
    return [
        {"name": "sdf", "sdf": sdf, "mass": float(sim_spec.get("sdf_mass", 0.3)), "joint": "free", "pose": pose.tolist()},
        {"name": "mesh", "mesh": mesh, "joint": "fixed", "pose": spec["mesh"].get("pose")},
    ]


def _add_body(sim: Simulation, spec: dict, base_dir: Path) -> None:
    unknown = set(spec) - BODY_KEYS
    if unknown:
        raise InputError(f"body {spec.get('name', '?')!r}: unknown keys {sorted(unknown)}; known: {sorted(BODY_KEYS)}")
    if "name" not in spec:
        raise InputError("every [[bodies]] entry needs a name")
    sdf = mesh = None
    labels = []
    if "sdf" in spec:
        sdf, label = build_sdf(spec["sdf"], base_dir)
        labels.append(label)
    if "mesh" in spec:
        mesh, label = build_mesh(spec["mesh"], base_dir)
        labels.append(label)
    sim.labels[spec["name"]] = " + ".join(labels)
    if sim.spec.body(spec["name"]) is not None:  # a body of the scene's MJCF: its SDF is attached to it
        sim.add_body(spec["name"], sdf=sdf, mesh=mesh, mass=spec.get("mass"), pose=spec.get("pose"), velocity=spec.get("velocity"))
        return
    sim.add_body(
        spec["name"], sdf=sdf, mesh=mesh, mass=spec.get("mass"), density=spec.get("density"), inertia=spec.get("inertia"),
        com=spec.get("com"), pose=pose_matrix(spec.get("pose")), joint=spec.get("joint", "free"),
        axis=spec.get("axis", (0.0, 0.0, 1.0)), anchor=spec.get("anchor", (0.0, 0.0, 0.0)),
        velocity=None if spec.get("velocity") is None else np.asarray(spec["velocity"], dtype=np.float64),
        drive=spec.get("drive"),
    )
