"""Bodies and the MuJoCo model built from them.

A :class:`Body` holds an SDF and/or a mesh (both in the body's frame), its mass properties, its
initial pose and velocity, a joint to its parent (the world) and an optional drive. :func:`add_body`
writes one into an ``mujoco.MjSpec`` (empty, or an MJCF file's: :func:`new_spec`) with one mesh geom that
MuJoCo draws and its own collision ignores (contype = conaffinity = 0): the body's mesh, or for an SDF
body its surface extracted by marching cubes. :func:`zoo.sim.attach` collides the SDFs with them.

Mass properties come from the geometry and a mass or a density: an SDF's inside volume is integrated
on a grid over its ``bounds``; a mesh uses trimesh's mass properties (its convex hull where the mesh
does not enclose a volume); or ``inertia`` and ``com`` are given.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..validation import as_faces, as_points, mesh_pair

JOINTS = ("free", "fixed", "hinge", "slide")
DRIVES = ("motor", "velocity")
DEFAULT_DENSITY = 1000.0  # kg/m^3, water: used when neither a mass nor a density is given
INERTIA_GRID = 40  # samples per axis when integrating an SDF's inside


@dataclass
class MassProperties:
    """Mass (kg), centre of mass (3,) and inertia (3, 3) about it, in the body's frame."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray


@dataclass
class Body:
    """One rigid body of a simulation.

    Attributes:
        name: unique name.
        sdf: an SDF protocol object in the body's frame, or None.
        mesh: (vertices (V, 3) float64, faces (F, 3) int64) in the body's frame, or None.
        pose: (4, 4) initial world-from-body.
        joint: "free", "fixed", "hinge" or "slide".
        axis, anchor: the hinge or slide axis and a point on it, in the body's frame.
        velocity: (6,) initial linear and angular velocity, world frame (free joint), or (1,) for a
            hinge/slide; None is at rest.
        drive: None, or {"type": "motor", "gear": g} (control = torque/force) or
            {"type": "velocity", "kv": gain, "target": v} (a velocity servo that prescribes the joint's speed).
        mass: the body's mass properties (None for a fixed body).
    """

    name: str
    sdf: object = None
    mesh: tuple | None = None
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    joint: str = "free"
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray | None = None
    drive: dict | None = None
    mass: MassProperties | None = None
    # ids in the built model, filled by build_model
    body_id: int = -1
    geom_id: int = -1
    qpos_adr: int = -1
    dof_adr: int = -1
    actuator_id: int = -1


def mesh_arrays(mesh, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) from a trimesh or a (V, F) pair, validated."""
    vertices, faces = mesh_pair(mesh, name)
    vertices = as_points(torch.as_tensor(np.asarray(vertices, dtype=np.float64)), f"{name} vertices", allow_empty=True)
    faces = as_faces(faces, int(vertices.shape[0]), f"{name} faces")
    return vertices.numpy(), faces.numpy()


def sdf_mass_properties(sdf, mass: float | None = None, density: float | None = None,
                        resolution: int = INERTIA_GRID) -> MassProperties:
    """Mass properties of an SDF's inside (f < 0) by midpoint integration on a grid over ``sdf.bounds``.

    ``resolution`` samples per axis (a 40^3 grid puts a sphere's volume within 0.5%); the mass is
    ``mass`` when given, else ``density`` (default water) times the volume.
    """
    lo, hi = (np.asarray(torch.as_tensor(b).detach().cpu(), dtype=np.float64).reshape(3) for b in sdf.bounds)
    step = (hi - lo) / resolution
    axes = [lo[i] + (np.arange(resolution) + 0.5) * step[i] for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.zeros(len(grid), dtype=bool)
    with torch.no_grad():
        for start in range(0, len(grid), 65536):  # bounded memory for a network SDF
            chunk = torch.as_tensor(grid[start:start + 65536], dtype=torch.float32)
            inside[start:start + 65536] = torch.as_tensor(sdf(chunk)).reshape(-1).cpu().numpy() < 0
    points = grid[inside]
    if len(points) == 0:
        raise InputError(f"the SDF has no inside on a {resolution}^3 grid over its bounds; give mass, inertia and com explicitly")
    volume = len(points) * float(np.prod(step))
    return _point_cloud_properties(points, _mass(mass, density, volume), step)


def mesh_mass_properties(vertices: np.ndarray, faces: np.ndarray, mass: float | None = None,
                         density: float | None = None) -> MassProperties:
    """Mass properties of a mesh's volume (its convex hull where the mesh encloses none)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if not mesh.is_volume:
        mesh = mesh.convex_hull
    if mesh.volume <= 0:
        raise InputError("the mesh encloses no volume (flat?); give the body mass, inertia and com explicitly, or make it fixed")
    m = _mass(mass, density, float(mesh.volume))
    scale = m / float(mesh.volume)  # trimesh's properties are for density 1
    return MassProperties(m, np.asarray(mesh.center_mass, dtype=np.float64), np.asarray(mesh.moment_inertia) * scale)


def _mass(mass, density, volume: float) -> float:
    if mass is not None:
        if not (mass > 0 and math.isfinite(mass)):
            raise InputError(f"mass must be positive and finite, got {mass}")
        return float(mass)
    density = DEFAULT_DENSITY if density is None else density
    if not (density > 0 and math.isfinite(density)):
        raise InputError(f"density must be positive and finite, got {density}")
    return float(density) * volume


def _point_cloud_properties(points: np.ndarray, mass: float, cell: np.ndarray) -> MassProperties:
    """Mass properties of equal point masses at cell centres (N, 3), each cell a small box of sides ``cell``."""
    com = points.mean(axis=0)
    r = points - com
    second = r.T @ r / len(points)  # (3, 3) E[r r^T]
    inertia = mass * (np.trace(second) * np.eye(3) - second)
    inertia += mass * np.diag([cell[1] ** 2 + cell[2] ** 2, cell[0] ** 2 + cell[2] ** 2, cell[0] ** 2 + cell[1] ** 2]) / 12
    return MassProperties(mass, com, inertia)


def explicit_mass_properties(mass: float, inertia, com=None) -> MassProperties:
    """Given mass (kg), inertia ((3,) diagonal or (3, 3)) about the centre of mass, and com (3,)."""
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape == (3,):
        inertia = np.diag(inertia)
    if inertia.shape != (3, 3) or not np.isfinite(inertia).all():
        raise InputError(f"inertia must be (3,) or (3, 3) and finite, got shape {inertia.shape}")
    com = np.zeros(3) if com is None else np.asarray(com, dtype=np.float64).reshape(3)
    return MassProperties(_mass(mass, None, 0.0), com, inertia)


# -- the MuJoCo model ------------------------------------------------------------------------

SDF_RGBA = (0.85, 0.55, 0.25, 1.0)
MESH_RGBA = (0.6, 0.65, 0.75, 1.0)


@dataclass
class Settings:
    """The model-wide settings a :class:`zoo.sim.Simulation` writes into its model; None keeps what the base
    model (an MJCF the scene names) has, or MuJoCo's default where there is none.

    ``friction``, ``solref`` and ``solimp`` are those of the geoms the simulation adds (MuJoCo mixes them
    with the other geom's at each contact, ``mj_contactParam``); None leaves MuJoCo's default."""

    dt: float | None = None
    gravity: tuple | None = None
    integrator: str | None = None
    cone: str | None = None
    impratio: float | None = None
    friction: float | None = None
    solref: tuple | None = None
    solimp: tuple | None = None


def quaternion(rotation: np.ndarray) -> np.ndarray:
    """(4,) w, x, y, z of a (3, 3) rotation, as MuJoCo writes it."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rotation, dtype=np.float64).reshape(9))
    return q


INTEGRATORS = {"implicitfast": "mjINT_IMPLICITFAST", "euler": "mjINT_EULER", "implicit": "mjINT_IMPLICIT", "rk4": "mjINT_RK4"}
CONES = {"pyramidal": "mjCONE_PYRAMIDAL", "elliptic": "mjCONE_ELLIPTIC"}
MEMORY = 256 * 2**20  # bytes of MuJoCo's arena when the base model sets none: room for thousands of contacts


def new_spec(mjcf: str | os.PathLike | None = None):
    """An ``mujoco.MjSpec``: the MJCF file's, or an empty one."""
    import mujoco

    if mjcf is None:
        return mujoco.MjSpec()
    path = Path(mjcf)
    if not path.is_file():
        raise InputError(f"no MJCF file at {path}")
    from .robots import robot_files  # robots/NAME/... references: a robot kept outside the repository

    include, assets = robot_files(path)
    try:
        if include or assets:
            return mujoco.MjSpec.from_file(str(path), include=include, assets=assets)
        return mujoco.MjSpec.from_file(str(path))
    except Exception as exc:  # MuJoCo's parser: a ValueError with its own message
        raise InputError(f"MuJoCo cannot read {path}: {exc}") from exc


def apply_settings(spec, settings: Settings) -> None:
    """Write ``settings``' model-wide options into ``spec`` (None keeps the spec's)."""
    import mujoco

    opt = spec.option
    if settings.dt is not None:
        opt.timestep = float(settings.dt)
    if settings.gravity is not None:
        opt.gravity = [float(g) for g in settings.gravity]
    if settings.integrator is not None:
        opt.integrator = getattr(mujoco.mjtIntegrator, INTEGRATORS[settings.integrator.lower()])
    if settings.cone is not None:
        opt.cone = getattr(mujoco.mjtCone, CONES[settings.cone])
    if settings.impratio is not None:
        opt.impratio = float(settings.impratio)
    opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY  # Simulation.energy()
    if spec.memory < 0:
        spec.memory = MEMORY


def add_body(spec, body: Body, settings: Settings, visual: tuple[np.ndarray, np.ndarray]) -> None:
    """Add ``body`` to ``spec``'s world: its joint, inertia, drive and one mesh geom ``visual`` (vertices (V, 3),
    faces (F, 3), body frame) that MuJoCo draws and does not collide (contype = conaffinity = 0): sdfzoo
    collides it (:func:`zoo.sim.attach`)."""
    import mujoco

    pose = np.asarray(body.pose, dtype=np.float64)
    b = spec.worldbody.add_body(name=body.name, pos=pose[:3, 3].tolist(), quat=quaternion(pose[:3, :3]).tolist())
    if body.joint == "free":
        b.add_freejoint(name=body.name)
    elif body.joint in ("hinge", "slide"):
        kind = mujoco.mjtJoint.mjJNT_HINGE if body.joint == "hinge" else mujoco.mjtJoint.mjJNT_SLIDE
        b.add_joint(name=body.name, type=kind, axis=body.axis.tolist(), pos=body.anchor.tolist())
    if body.mass is not None and body.joint != "fixed":
        mp, full = body.mass, body.mass.inertia
        b.explicitinertial = True
        b.mass = float(mp.mass)
        b.ipos = mp.com.tolist()
        b.fullinertia = [full[0, 0], full[1, 1], full[2, 2], full[0, 1], full[0, 2], full[1, 2]]
    vertices, faces = visual
    mesh = spec.add_mesh(name=body.name, uservert=np.asarray(vertices, dtype=np.float64).reshape(-1).tolist(),
                         userface=np.asarray(faces, dtype=np.int64).reshape(-1).tolist())
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # an open or flat mesh has no volume
    geom = b.add_geom(name=body.name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=body.name, contype=0, conaffinity=0,
                      mass=0.0, rgba=list(SDF_RGBA if body.sdf is not None else MESH_RGBA))
    if settings.friction is not None:
        geom.friction[0] = settings.friction  # sliding; torsional and rolling keep MuJoCo's defaults
    if settings.solref is not None:
        geom.solref = list(settings.solref)
    if settings.solimp is not None:
        geom.solimp = list(settings.solimp)
    if body.drive:
        _add_drive(spec, body)


def _add_drive(spec, body: Body) -> None:
    import mujoco

    drive = body.drive
    if body.joint not in ("hinge", "slide"):
        raise InputError(f"body {body.name!r}: a drive needs a hinge or slide joint, not {body.joint!r}")
    kind = drive.get("type", "motor")
    actuator = spec.add_actuator(name=body.name, target=body.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    if kind == "motor":
        actuator.set_to_motor()
        actuator.gear = [float(drive.get("gear", 1.0)), 0, 0, 0, 0, 0]
    elif kind == "velocity":
        actuator.set_to_velocity(kv=float(drive.get("kv", 100.0)))
    else:
        raise InputError(f"body {body.name!r}: unknown drive type {kind!r}; use one of {DRIVES}")


def compile_spec(spec):
    """(MjModel, MjData) of ``spec``, with MuJoCo's compile error as an InputError."""
    import mujoco

    try:
        model = spec.compile()
    except Exception as exc:
        raise InputError(f"MuJoCo cannot compile the simulation's model: {exc}") from exc
    return model, mujoco.MjData(model)


def bind_bodies(bodies: list[Body], model, data) -> None:
    """Fill each body's ids in ``model``, and set its initial velocity and drive target in ``data``."""
    import mujoco

    for body in bodies:
        body.body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body.name)
        body.geom_id = int(model.body_geomadr[body.body_id])
        if body.joint != "fixed" and int(model.body_jntnum[body.body_id]):
            joint = int(model.body_jntadr[body.body_id])
            body.qpos_adr, body.dof_adr = int(model.jnt_qposadr[joint]), int(model.jnt_dofadr[joint])
        if body.drive:
            body.actuator_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, body.name)
            data.ctrl[body.actuator_id] = float(body.drive.get("target", body.drive.get("ctrl", 0.0)))
        _set_velocity(body, data)


def _set_velocity(body: Body, data) -> None:
    """Initial velocity: a free joint's qvel is linear (world) then angular (body frame)."""
    if body.velocity is None or body.joint == "fixed":
        return
    v = np.asarray(body.velocity, dtype=np.float64).reshape(-1)
    if body.joint == "free":
        if v.shape != (6,):
            raise InputError(f"body {body.name!r}: a free body's velocity is (6,) linear, angular; got {v.shape}")
        data.qvel[body.dof_adr:body.dof_adr + 3] = v[:3]
        data.qvel[body.dof_adr + 3:body.dof_adr + 6] = np.asarray(body.pose)[:3, :3].T @ v[3:]
    else:
        if v.size != 1:
            raise InputError(f"body {body.name!r}: a {body.joint} joint's velocity is one number; got {v.shape}")
        data.qvel[body.dof_adr] = float(v[0])
