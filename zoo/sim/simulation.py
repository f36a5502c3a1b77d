"""The convenience builder: bodies added in Python (or by a scene file) onto an MjSpec, then :func:`zoo.sim.attach`.

For scenes without an MJCF of their own, and for scenes that add SDF bodies to one. Each body gets one mesh
geom that MuJoCo draws and does not collide itself (its mesh, or for an SDF body its surface extracted by
marching cubes); every SDF body is attached with its SDF (:mod:`zoo.sim.world`), and the bodies holding only
a mesh are the geoms the SDFs collide with (``include_geoms``). Bodies of a base MJCF keep MuJoCo's own
collision among themselves, and the SDFs collide with them by MuJoCo's rules. Stepping is the World's
(``mj_step1``, sdfzoo's contacts, ``mj_step2``), followed by the kinematics of the new state for
:meth:`Simulation.pose`; the step's record and warnings are kept in ``log``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

import zoo

from ..errors import InputError
from ..validation import as_pose, float_in
from .control import Waypoints
from .model import (
    INTEGRATORS,
    JOINTS,
    Body,
    Settings,
    add_body,
    apply_settings,
    bind_bodies,
    compile_spec,
    explicit_mass_properties,
    mesh_arrays,
    mesh_mass_properties,
    new_spec,
    sdf_mass_properties,
)
from .surface import VISUAL_RESOLUTION, surface_mesh
from .world import attach

CONES = ("pyramidal", "elliptic")
TUNNEL_FRACTION = 0.25  # of the thinnest SDF body's smallest extent


@dataclass
class StepRecord:
    """One step of ``Simulation.log``."""

    time: float
    contacts: int
    raw_contacts: int
    max_penetration: float
    collide_s: float
    step_s: float
    margin: float
    speculative: bool = False
    warnings: list = field(default_factory=list)


class Simulation:
    """A MuJoCo simulation whose SDF contacts come from sdfzoo (see the module docstring).

    Args:
        dt: time step, s (default 0.002, or the MJCF's).
        gravity: (3,) m/s^2 (default (0, 0, -9.81), or the MJCF's).
        method: ``zoo.collide``'s narrow phase ("fw", "pgd", "voxel-fw", "amortized"); an SDF
            without a detector falls back to "fw" under "amortized".
        margin: contact margin, m: contacts are found this far before touching.
        friction, solref, solimp: the contact parameters of the geoms the simulation adds (MuJoCo mixes
            them with the other geom's; with no MJCF, every contact's); None keeps MuJoCo's defaults.
        integrator: "implicitfast" (default), "euler", "implicit" or "rk4" (or the MJCF's).
        cone, impratio: MuJoCo's friction cone ("pyramidal" or "elliptic") and the ratio of its frictional to
            normal constraint impedance (default pyramidal and 1, or the MJCF's). MuJoCo's defaults let a
            grasped object creep under its soft friction; a grasp wants MuJoCo's own grasping settings,
            elliptic and 10.
        coherence: carry each pair's bounds and answers from step to step (:class:`zoo.CoherentCollider`);
            False collides every pair from scratch with ``zoo.collide``.
        reduce: reduce contacts to a manifold per patch (False: every contact, for comparison; "exact": on the
            NeuralSDF's depths where a proxy searches, see ``zoo.sim.attach``).
        refine: split mesh triangles larger than a quarter of the SDF, and remove the vertices a mesh's flat parts
            do not need, once, at build (``zoo.sim.flat_regions``; False: the mesh as given).
        proxy: with ``coherence`` (the default), the model shapes' mesh pairs cull and search on a narrow-band proxy,
            baked ahead at build where the cache lacks it ("lazy": when a step first needs it), and the shape answers
            only the contacts kept (:func:`zoo.sim.attach`'s ``proxy``; a dict names the bodies and may give their
            proxies). False queries the
            shape itself for everything; ``method="amortized", coherence=False`` is the full from-scratch reference.
        mjcf: an MJCF file (path) to start from (a robot, a gripper, a table): its bodies, joints, actuators, mocap
            and options; :meth:`add_body` adds to it, and an SDF given for one of its bodies is attached to it.

    Attributes:
        control: waypoints for the model's mocap bodies and actuators (:mod:`zoo.sim.control`), set before the
            first step.
        initial_qpos: {joint name: position} for the MJCF's hinge and slide joints at the start (a robot's
            home posture; a scene's ``[sim] qpos``), set before the first step.
        name, seconds, labels, camera, scene_path: what a scene file said (``zoo simulate`` reads them): the run's
            name, its length (s), each body's source, the camera of its video, and the file.
        model, data: MuJoCo's own objects (after the first step or :meth:`build`).
        world: the :class:`zoo.sim.World` the simulation attached.
        contacts: ``zoo.Contacts`` of the last step that went into MuJoCo's solver (after the
            reduction), world frame, all pairs concatenated.
        log: one :class:`StepRecord` per step.
        warnings: every warning of the log (MuJoCo's ``d.warning``, a full contact buffer, deep
            penetration, a non-finite state), with its time.
    """

    def __init__(self, dt: float | None = None, gravity=None, method: str = "amortized", margin: float = 1e-3,
                 friction: float | None = None, solref=None, solimp=None,
                 integrator: str | None = None, cone: str | None = None, impratio: float | None = None,
                 coherence: bool = True, reduce: bool | str = True, refine: bool = True, mjcf=None, proxy: bool | str | dict = True):
        if dt is not None and not (dt > 0 and math.isfinite(dt)):
            raise InputError(f"dt must be positive, got {dt}")
        if integrator is not None and integrator.lower() not in INTEGRATORS:
            raise InputError(f"integrator {integrator!r} is not supported; use one of {sorted(INTEGRATORS)}")
        if not (margin >= 0 and math.isfinite(margin)):
            raise InputError(f"margin must be >= 0, got {margin}")
        if friction is not None and not (friction >= 0 and math.isfinite(friction)):
            raise InputError(f"friction must be >= 0, got {friction}")
        if cone is not None and cone not in CONES:
            raise InputError(f"cone {cone!r} is not a friction cone; use one of {CONES}")
        if impratio is not None:
            impratio = float_in(impratio, "impratio (MuJoCo's default is 1)", 1.0, math.inf, high_open=True)
        self.spec = new_spec(mjcf)
        self.mjcf = mjcf
        if mjcf is None:  # MuJoCo's defaults but for the timestep and the integrator, sdfzoo's
            dt, integrator = 0.002 if dt is None else dt, "implicitfast" if integrator is None else integrator
        self.settings = Settings(dt=dt, gravity=None if gravity is None else tuple(float(g) for g in gravity),
                                 integrator=integrator, cone=cone, impratio=impratio,
                                 friction=None if friction is None else float(friction),
                                 solref=None if solref is None else tuple(solref), solimp=None if solimp is None else tuple(solimp))
        self.method, self.margin = method, float(margin)
        self.coherence, self.reduce, self.refine, self.proxy = coherence, reduce, refine, proxy
        self.bodies: dict[str, Body] = {}
        self.attached: dict[str, object] = {}  # SDFs given for bodies of the MJCF
        self.log: list[StepRecord] = []
        self.model = self.data = self.world = None
        # what a scene file says of the run (zoo.sim.scene): its name, length, bodies' sources, camera, file
        self.name, self.seconds, self.labels, self.camera, self.scene_path = "simulation", 1.0, {}, None, None
        self.control: list[dict] = []  # waypoints (zoo.sim.control), applied before every step
        self.initial_qpos: dict[str, float] = {}  # initial positions of the MJCF's hinge and slide joints, by name
        self.waypoints = None
        self._warnings_seen = None

    @property
    def dt(self) -> float:
        return float(self.model.opt.timestep) if self.model is not None else float(self.settings.dt or self.spec.option.timestep)

    # -- building -----------------------------------------------------------------------

    def add_body(self, name: str, sdf=None, mesh=None, mass: float | None = None, density: float | None = None,
                 inertia=None, com=None, pose=None, joint: str = "free", axis=(0.0, 0.0, 1.0), anchor=(0.0, 0.0, 0.0),
                 velocity=None, drive: dict | None = None) -> Body | None:
        """Add a body holding an SDF and/or a mesh (both in the body's frame); see :class:`zoo.sim.model.Body`.

        Mass properties: ``inertia`` (with ``mass``, optional ``com``) as given; else integrated
        from the SDF (or the mesh) with ``mass`` or ``density``. A ``name`` that is a body of the MJCF
        attaches ``sdf`` to that body (nothing else may be given). Bodies can be added until the first step.
        """
        if self.model is not None:
            raise InputError("bodies must be added before the first step")
        if name in self.bodies or name in self.attached or not name or not name.replace("_", "").replace("-", "").isalnum():
            raise InputError(f"body name {name!r} is empty, not alphanumeric (with - and _) or already used")
        if self.spec.body(name) is not None:
            given = {"mesh": mesh, "mass": mass, "density": density, "inertia": inertia, "com": com, "pose": pose,
                     "velocity": velocity, "drive": drive}
            extra = sorted(k for k, v in given.items() if v is not None)
            if sdf is None or extra:
                raise InputError(f"body {name!r} is the MJCF's: give it an sdf and nothing else (not {extra}); "
                                 "its joints, inertia and pose are the MJCF's")
            zoo.sdf.check_sdf(sdf)
            self.attached[name] = sdf
            return None
        if sdf is None and mesh is None:
            raise InputError(f"body {name!r} needs an sdf, a mesh or both")
        if joint not in JOINTS:
            raise InputError(f"body {name!r}: unknown joint {joint!r}; use one of {JOINTS}")
        if sdf is not None:
            zoo.sdf.check_sdf(sdf)
        arrays = mesh_arrays(mesh) if mesh is not None else None
        pose = np.eye(4) if pose is None else as_pose(pose, torch.float64, f"body {name!r} pose").numpy()
        body = Body(name=name, sdf=sdf, mesh=arrays, pose=pose, joint=joint, axis=np.asarray(axis, dtype=np.float64),
                    anchor=np.asarray(anchor, dtype=np.float64), velocity=velocity, drive=drive)
        if joint != "fixed":
            body.mass = self._mass_properties(body, mass, density, inertia, com)
        self.bodies[name] = body
        return body

    @staticmethod
    def _mass_properties(body: Body, mass, density, inertia, com):
        if inertia is not None:
            if mass is None:
                raise InputError(f"body {body.name!r}: an explicit inertia needs a mass")
            return explicit_mass_properties(mass, inertia, com)
        if body.sdf is not None:
            return sdf_mass_properties(body.sdf, mass, density)
        return mesh_mass_properties(*body.mesh, mass=mass, density=density)

    def build(self) -> None:
        """Build the MuJoCo model now (the first step does it otherwise); bodies can no longer be added."""
        if self.model is None:
            self._build()

    def _build(self):
        import mujoco

        apply_settings(self.spec, self.settings)
        bodies = list(self.bodies.values())
        for body in bodies:
            visual = body.mesh if body.mesh is not None else surface_mesh(body.sdf, VISUAL_RESOLUTION)
            add_body(self.spec, body, self.settings, visual)
        self.model, self.data = compile_spec(self.spec)
        bind_bodies(bodies, self.model, self.data)
        self._set_initial_qpos()
        if self.model.nv == 0:
            raise InputError("nothing moves: every body is fixed; give one a free, hinge or slide joint")
        sdfs = {b.name: b.sdf for b in bodies if b.sdf is not None}
        sdfs.update(self.attached)
        if not sdfs:
            raise InputError("no body holds an SDF: add one with sdf=...")
        self.world = attach(self.model, sdfs, method=self.method, margin=self.margin, coherence=self.coherence,
                            reduce=self.reduce, refine=self.refine, proxy=self.proxy,
                            surfaces={b.name: b.mesh for b in bodies if b.sdf is not None and b.mesh is not None},
                            include_geoms=[b.name for b in bodies if b.sdf is None])
        if self.control:
            self.waypoints = Waypoints(self.model, self.control)
            self.waypoints.apply(self.data, 0.0)
        self._warnings_seen = np.array([w.number for w in self.data.warning])
        # a body pushed deeper than this into a mesh is reported: past its middle a thin mesh's contacts push it through
        self._tunnel_depth = TUNNEL_FRACTION * min((float((b.hi - b.lo).min()) for b in self.world.bodies.values()), default=math.inf)
        mujoco.mj_forward(self.model, self.data)  # kinematics of the initial state, for pose()

    def _set_initial_qpos(self) -> None:
        import mujoco

        for name, value in self.initial_qpos.items():
            joint = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if joint < 0 or int(self.model.jnt_type[joint]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                raise InputError(f"initial qpos names {name!r}, which is not a hinge or slide joint of the model")
            self.data.qpos[self.model.jnt_qposadr[joint]] = float(value)

    # -- stepping -----------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of ``dt``."""
        self.build()
        for _ in range(int(n)):
            self._step_once()

    def run(self, seconds: float, callback=None) -> None:
        """Advance ``seconds`` (rounded to whole steps); ``callback(sim)`` after each step."""
        self.build()
        for _ in range(max(0, int(round(seconds / self.dt)))):
            self.step()
            if callback is not None:
                callback(self)

    def _step_once(self) -> None:
        import mujoco

        m, d = self.model, self.data
        t0 = time.perf_counter()
        if self.waypoints is not None:
            self.waypoints.apply(d, float(d.time))
        self.world.step(d)
        # poses and velocities of the new state for pose()/velocity() (the next step recomputes them)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        stats = self.world.stats
        warnings = self._new_warnings()
        if stats.dropped:
            warnings.append(f"contact buffer full: {stats.dropped} contacts dropped")
        self.log.append(StepRecord(
            time=float(d.time), contacts=stats.contacts, raw_contacts=stats.raw_contacts,
            max_penetration=stats.max_penetration, collide_s=stats.collide_s, step_s=time.perf_counter() - t0,
            margin=stats.margin, speculative=stats.speculative, warnings=warnings,
        ))
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            self.log[-1].warnings.append("non-finite state")
        if stats.max_penetration > self._tunnel_depth:
            self.log[-1].warnings.append(
                f"deep penetration {stats.max_penetration * 1e3:.3g} mm, over a quarter of the thinnest SDF body: it may "
                "pass through a thin mesh (use a smaller dt or a larger solref time constant)")

    @property
    def contacts(self):
        """``zoo.Contacts`` of the last step that went into MuJoCo's solver (None before the model is built)."""
        return None if self.world is None else self.world.contacts

    def _new_warnings(self) -> list[str]:
        import mujoco

        counts = self.data.warning.number.copy()  # (mjNWARNING,) one array read, not one per warning kind
        fresh = np.nonzero(counts > self._warnings_seen)[0]
        self._warnings_seen = counts
        return [f"mujoco: {mujoco.mjtWarning(int(i)).name}" for i in fresh]

    # -- state --------------------------------------------------------------------------

    def _body_id(self, name: str) -> int:
        """The model's id of body ``name`` (one the simulation added, or the MJCF's)."""
        import mujoco

        if self.model is None:
            if name not in self.bodies and self.spec.body(name) is None:
                raise InputError(f"no body named {name!r}; bodies: {sorted(self.bodies) + sorted(self.attached)}")
            self._build()
        body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            raise InputError(f"no body named {name!r}; bodies: {sorted(self.bodies) + sorted(self.attached)}")
        return body

    def pose(self, name: str) -> np.ndarray:
        """(4, 4) world-from-body of body ``name`` at the current time."""
        from .geoms import body_pose

        body = self._body_id(name)  # builds the model first where needed
        return body_pose(self.data, body)

    def velocity(self, name: str) -> np.ndarray:
        """(6,) linear velocity of the body's origin and angular velocity, world frame."""
        from .geoms import body_velocity

        body = self._body_id(name)
        return body_velocity(self.model, self.data, body)

    def normal_force(self, name: str) -> float:
        """Total normal force (N) of the last step's contacts on body ``name``."""
        import mujoco

        body, m, d = self._body_id(name), self.model, self.data
        total, force = 0.0, np.zeros(6)
        for i in range(d.ncon):
            if body in (m.geom_bodyid[d.contact.geom1[i]], m.geom_bodyid[d.contact.geom2[i]]):
                mujoco.mj_contactForce(m, d, i, force)
                total += force[0]
        return float(total)

    def set_control(self, name: str, value: float) -> None:
        """A driven joint's control: torque/force for a motor, target speed for a velocity drive."""
        self._body_id(name)
        body = self.bodies.get(name)
        if body is None or body.actuator_id < 0:
            raise InputError(f"body {name!r} has no drive (an MJCF's actuators are set through sim.data.ctrl)")
        self.data.ctrl[body.actuator_id] = float(value)

    def collider_stats(self):
        """``zoo.collider.CoherenceStats`` summed over every pair's collider and step so far (all zero without coherence)."""
        from ..collider import CoherenceStats

        return CoherenceStats() if self.world is None else self.world.collider_stats()

    @property
    def time(self) -> float:
        return 0.0 if self.data is None else float(self.data.time)

    def energy(self) -> float:
        """Potential plus kinetic energy (J) as of the last step's kinematics."""
        if self.data is None:
            self._build()
        return float(self.data.energy.sum())

    @property
    def warnings(self) -> list[str]:
        """Every warning the log recorded, with the time of its step."""
        return [f"t={r.time:.4f}s: {w}" for r in self.log for w in r.warnings]
