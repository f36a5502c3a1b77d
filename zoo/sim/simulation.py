"""The step loop: MuJoCo integrates and solves, sdfzoo detects.

Each step: ``mj_step1`` (kinematics; MuJoCo's own collision finds nothing: every geom is a
carrier with contype 0), then every (SDF body, mesh body) pair whose world boxes overlap is
collided by ``zoo.collide`` in the world frame, its contacts refined and reduced
(:mod:`zoo.sim.contacts`) and appended with ``mj_addContact``; the constraint stage is rebuilt
(``mj_makeConstraint``, ``mj_island``, ``mj_projectConstraint``, ``mj_referenceConstraint``) and
``mj_step2`` solves and integrates. Anything that calls ``mj_forward`` or ``mj_step`` would
recompute collision and drop the added contacts, so this module never does.

Fast impacts: before colliding a pair, the distance its bodies can close in one step (relative
speed times dt, rotation included) is compared with the margin. Where it is larger, the pair is
collided with a margin that covers it (speculative contacts: MuJoCo's solver sees the contact
before the bodies cross it) and the step's log says so.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

import zoo

from ..errors import InputError
from ..geometry import invert_pose
from ..validation import as_pose, float_in
from .contacts import (
    REFINE_CELLS,
    add_contacts,
    as_numpy,
    closing_in_time,
    contact_rows,
    face_normals,
    facing_faces,
    reduce_contacts,
    refine_near,
    refine_to_size,
)
from .model import (
    JOINTS,
    Body,
    build_model,
    explicit_mass_properties,
    mesh_arrays,
    mesh_mass_properties,
    sdf_mass_properties,
)

INTEGRATORS = {"implicitfast": "implicitfast", "euler": "Euler"}
CONES = ("pyramidal", "elliptic")
# contacts closer than this fraction of the SDF's smallest extent are one contact (FW-10 scatters the
# copies of a vertex's contact by up to a tenth of the edge: 3 mm on 3 cm triangles)
MERGE_FRACTION = 0.05
SPECULATIVE_FACTOR = 1.5  # a fast pair's margin covers this much more than one step's closing distance
TUNNEL_FRACTION = 0.25  # of the thinnest SDF body's smallest extent
# a mesh that refining once at build would grow past this many faces (a large plane under a small SDF) is
# instead clipped and refined near the SDF at every step, from scratch (no temporal coherence for that pair)
PREREFINE_MAX_FACES = 200_000


@dataclass
class PairMesh:
    """The mesh one (SDF body, mesh body) pair is collided with, fixed for the whole simulation.

    Attributes:
        vertices: (V, 3) the mesh body's mesh refined once (:func:`refine_to_size`), body frame.
        faces: (F, 3).
        origin: (F,) the body's own face each face comes from.
        normals: (F, 3) unit face normals, body frame.
        collider: the pair's :class:`zoo.CoherentCollider` on that mesh (from scratch when coherence is off).
    """

    vertices: np.ndarray
    faces: np.ndarray
    origin: np.ndarray
    normals: np.ndarray
    collider: object


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
    """A MuJoCo simulation whose SDF-mesh contacts come from sdfzoo (see the module docstring).

    Args:
        dt: time step, s.
        gravity: (3,) m/s^2.
        method: ``zoo.collide``'s narrow phase ("fw", "pgd", "voxel-fw", "amortized"); an SDF
            without a detector falls back to "fw" under "amortized".
        margin: contact margin, m: contacts are found this far before touching.
        friction: Coulomb friction of every contact.
        solref, solimp: MuJoCo's contact softness, for every contact.
        integrator: "implicitfast" or "euler" (RK4 would recompute collision and lose the contacts).
        cone, impratio: MuJoCo's friction cone ("pyramidal" or "elliptic") and the ratio of its frictional to
            normal constraint impedance. MuJoCo's defaults (pyramidal, 1) let a grasped object creep under its
            soft friction; a grasp wants MuJoCo's own grasping settings, elliptic and 10.
        coherence: carry each pair's bounds and answers from step to step (:class:`zoo.CoherentCollider`):
            triangles proven to stay above the margin are skipped, persisting contacts warm-started.
            False collides every pair from scratch with ``zoo.collide``.
        reduce: reduce contacts to a manifold per patch (False: every contact zoo.collide gives, for
            comparison).
        refine: split mesh triangles larger than a quarter of the SDF once, at build (False: the mesh as
            given). A mesh that would grow past ``PREREFINE_MAX_FACES`` is clipped to the SDF's box and
            refined there at every step instead, from scratch.

    Attributes:
        contacts: ``zoo.Contacts`` of the last step that went into MuJoCo's solver (after the
            reduction), world frame, all pairs concatenated.
        log: one :class:`StepRecord` per step.
        warnings: every warning of the log (MuJoCo's ``d.warning``, a full contact buffer, deep
            penetration, a non-finite state), with its time.
    """

    def __init__(self, dt: float = 0.002, gravity=(0.0, 0.0, -9.81), method: str = "amortized", margin: float = 1e-3,
                 friction: float = 1.0, solref=(0.02, 1.0), solimp=(0.9, 0.95, 0.001, 0.5, 2.0),
                 integrator: str = "implicitfast", cone: str = "pyramidal", impratio: float = 1.0, coherence: bool = True,
                 reduce: bool = True, refine: bool = True):
        if not (dt > 0 and math.isfinite(dt)):
            raise InputError(f"dt must be positive, got {dt}")
        if integrator.lower() not in INTEGRATORS:
            raise InputError(f"integrator {integrator!r} is not supported; use one of {sorted(INTEGRATORS)} (RK4 drops added contacts)")
        if not (margin >= 0 and math.isfinite(margin)):
            raise InputError(f"margin must be >= 0, got {margin}")
        if not (friction >= 0 and math.isfinite(friction)):
            raise InputError(f"friction must be >= 0, got {friction}")
        if cone not in CONES:
            raise InputError(f"cone {cone!r} is not a friction cone; use one of {CONES}")
        impratio = float_in(impratio, "impratio (MuJoCo's default is 1)", 1.0, math.inf, high_open=True)
        self.dt, self.gravity, self.method, self.margin = float(dt), tuple(float(g) for g in gravity), method, float(margin)
        self.friction, self.solref, self.solimp = float(friction), tuple(solref), tuple(solimp)
        self.integrator, self.coherence = INTEGRATORS[integrator.lower()], coherence
        self.cone, self.impratio = cone, impratio
        self.reduce, self.refine = reduce, refine
        self.bodies: dict[str, Body] = {}
        self.log: list[StepRecord] = []
        self.contacts = None
        self.model = self.data = None
        self._warnings_seen = None

    # -- building -----------------------------------------------------------------------

    def add_body(self, name: str, sdf=None, mesh=None, mass: float | None = None, density: float | None = None,
                 inertia=None, com=None, pose=None, joint: str = "free", axis=(0.0, 0.0, 1.0), anchor=(0.0, 0.0, 0.0),
                 velocity=None, drive: dict | None = None) -> Body:
        """Add a body holding an SDF and/or a mesh (both in the body's frame); see :class:`zoo.sim.model.Body`.

        Mass properties: ``inertia`` (with ``mass``, optional ``com``) as given; else integrated
        from the SDF (or the mesh) with ``mass`` or ``density``. Bodies can be added until the
        first step.
        """
        if self.model is not None:
            raise InputError("bodies must be added before the first step")
        if name in self.bodies or not name or not name.replace("_", "").replace("-", "").isalnum():
            raise InputError(f"body name {name!r} is empty, not alphanumeric (with - and _) or already used")
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

        self.model, self.data = build_model(list(self.bodies.values()), self.dt, self.gravity, self.integrator,
                                              self.cone, self.impratio)
        if self.model.nv == 0:
            raise InputError("nothing moves: every body is fixed; give one a free, hinge or slide joint")
        self._warnings_seen = np.array([w.number for w in self.data.warning])
        self._pairs = _pairs(list(self.bodies.values()))
        self._sdf_boxes = {b.name: _bounds(b.sdf) for b in self.bodies.values() if b.sdf is not None}
        self._reaches = {name: float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)))) for name, (lo, hi) in self._sdf_boxes.items()}
        # a body pushed deeper than this into a mesh is reported: past its middle a thin mesh's contacts push it through
        self._tunnel_depth = TUNNEL_FRACTION * min((float((hi - lo).min()) for lo, hi in self._sdf_boxes.values()), default=math.inf)
        self._mesh_boxes = {b.name: (b.mesh[0].min(axis=0), b.mesh[0].max(axis=0)) for b in self.bodies.values() if b.mesh is not None}
        self._pair_meshes = {(a.name, b.name): self._pair_mesh(a, b) for a, b in self._pairs}
        mujoco.mj_step1(self.model, self.data)  # kinematics of the initial state, for pose()

    # -- stepping -----------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of ``dt``."""
        self.build()
        for _ in range(int(n)):
            self._step_once()

    def run(self, seconds: float, callback=None) -> None:
        """Advance ``seconds`` (rounded to whole steps); ``callback(sim)`` after each step."""
        for _ in range(max(0, int(round(seconds / self.dt)))):
            self.step()
            if callback is not None:
                callback(self)

    def _step_once(self) -> None:
        import mujoco

        m, d = self.model, self.data
        t0 = time.perf_counter()
        mujoco.mj_step1(m, d)
        t1 = time.perf_counter()
        rows, raw, used_margin, speculative, collected = self._detect()
        t2 = time.perf_counter()
        added = sum(add_contacts(m, d, r, self.friction, self.solref, self.solimp) for r in rows)
        mujoco.mj_makeConstraint(m, d)
        mujoco.mj_island(m, d)
        mujoco.mj_projectConstraint(m, d)
        mujoco.mj_referenceConstraint(m, d)
        mujoco.mj_step2(m, d)
        # poses and velocities of the new state for pose()/velocity() (the next mj_step1 recomputes them)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        warnings = self._new_warnings()
        if added < sum(len(r) for r in rows):
            warnings.append(f"contact buffer full: {sum(len(r) for r in rows) - added} contacts dropped")
        self.contacts = _concat_contacts(collected)
        depth = min((float(r.dist.min()) for r in rows if len(r)), default=math.inf)
        self.log.append(StepRecord(
            time=float(d.time), contacts=added, raw_contacts=raw, max_penetration=max(0.0, -depth),
            collide_s=t2 - t1, step_s=time.perf_counter() - t0, margin=used_margin, speculative=speculative,
            warnings=warnings,
        ))
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            self.log[-1].warnings.append("non-finite state")
        if -depth > self._tunnel_depth:
            self.log[-1].warnings.append(
                f"deep penetration {-depth * 1e3:.3g} mm, over a quarter of the thinnest SDF body: it may pass through "
                "a thin mesh (use a smaller dt or a larger solref time constant)")

    def _detect(self):
        """Contacts of every overlapping pair: (rows per pair, raw count, largest margin used, any speculative, Contacts)."""
        rows, raw, used, speculative, collected = [], 0, self.margin, False, []
        for sdf_body, mesh_body in self._pairs:
            closing = self._closing_distance(sdf_body, mesh_body)
            margin = self.margin
            if closing > self.margin:  # would cross the margin in one step: see it coming
                margin, speculative = SPECULATIVE_FACTOR * closing, True
            used = max(used, margin)
            found = self._collide_pair(sdf_body, mesh_body, margin)
            if found is None or len(found[0]) == 0:
                continue
            contacts, keep, arrays = found
            raw += len(contacts)
            rows.append(contact_rows(arrays, keep, (sdf_body.geom_id, mesh_body.geom_id)))
            collected.append(_select(contacts, keep))
        return rows, raw, used, speculative, collected

    def _max_edge(self, sdf_body: Body) -> float:
        """The longest mesh edge refinement leaves near ``sdf_body``'s SDF (inf without refinement)."""
        lo, hi = self._sdf_boxes[sdf_body.name]
        return float(np.median(hi - lo)) / REFINE_CELLS if self.refine else math.inf  # a thin plate: its side, not its thickness

    def _pair_mesh(self, sdf_body: Body, mesh_body: Body) -> PairMesh | None:
        """The pair's fixed mesh and collider, or None when the mesh is too large to refine once (see ``refine``)."""
        refined = refine_to_size(*mesh_body.mesh, self._max_edge(sdf_body), PREREFINE_MAX_FACES)
        if refined is None:
            return None
        vertices, faces, origin = refined
        mesh = (torch.as_tensor(vertices, dtype=torch.float32), torch.as_tensor(faces))
        collider = zoo.CoherentCollider(sdf_body.sdf, mesh, margin=self.margin, method=self._method_for(sdf_body.sdf),
                                        coherence=self.coherence)
        return PairMesh(vertices=vertices, faces=faces, origin=origin, normals=face_normals(vertices[faces]), collider=collider)

    def _collide_pair(self, sdf_body: Body, mesh_body: Body, margin: float):
        """(zoo.Contacts in the world frame, kept indices, its :func:`as_numpy` arrays) of one pair, or None when their boxes miss."""
        t_sdf, t_mesh = self.pose(sdf_body.name), self.pose(mesh_body.name)
        lo, hi = self._sdf_boxes[sdf_body.name]
        world_lo, world_hi = _world_box(t_sdf, lo - margin, hi + margin)
        mesh_lo, mesh_hi = _world_box(t_mesh, *self._mesh_boxes[mesh_body.name])
        if (world_hi < mesh_lo).any() or (mesh_hi < world_lo).any():
            return None
        pair = self._pair_meshes[(sdf_body.name, mesh_body.name)]
        if pair is None:
            contacts, faces_world = self._collide_refining_near(sdf_body, mesh_body, t_sdf, t_mesh, margin)
        else:
            contacts = pair.collider(torch.from_numpy(t_sdf), torch.from_numpy(t_mesh), margin=margin)
            faces_world = pair.normals[np.asarray(contacts.triangles)] @ t_mesh[:3, :3].T  # (K, 3)
            contacts.triangles = torch.as_tensor(pair.origin)[contacts.triangles]  # back to the body's own faces
        if contacts is None:
            return None
        points, depths, normals = as_numpy(contacts)
        # the contacts MuJoCo can use, before the reduction picks among them: facing their faces, and touching or
        # closing within the step (a separated one beyond that would only brake the bodies at a distance)
        usable = facing_faces(normals, faces_world, depths) & closing_in_time(
            points, depths, normals, self._motion(sdf_body), self._motion(mesh_body), self.dt, SPECULATIVE_FACTOR)
        keep = np.nonzero(usable)[0]
        if self.reduce and len(keep):
            merge = MERGE_FRACTION * float((hi - lo).min())
            keep = keep[reduce_contacts(points[keep], depths[keep], normals[keep], faces_world[keep], merge_tol=merge)]
        return contacts, keep, (points, depths, normals)

    def _collide_refining_near(self, sdf_body: Body, mesh_body: Body, t_sdf: np.ndarray, t_mesh: np.ndarray, margin: float):
        """(zoo.Contacts in the world frame, their faces' world normals (K, 3)) of a pair whose mesh is refined
        near the SDF at this step, or (None, None) when no face reaches the SDF's box."""
        lo, hi = self._sdf_boxes[sdf_body.name]
        vertices, faces = mesh_body.mesh
        # the mesh in the SDF's frame, cut to the SDF's box and with large faces refined there
        sdf_from_mesh = invert_pose(torch.from_numpy(t_sdf)).numpy() @ t_mesh  # rigid: a transpose, not a general inverse
        local = vertices @ sdf_from_mesh[:3, :3].T + sdf_from_mesh[:3, 3]
        local, faces, origin = refine_near(local, faces, lo - margin, hi + margin, self._max_edge(sdf_body))
        if len(faces) == 0:
            return None, None
        used_v, inverse = np.unique(faces, return_inverse=True)
        mesh = (torch.as_tensor(local[used_v], dtype=torch.float32), torch.as_tensor(inverse.reshape(-1, 3)))
        world = torch.as_tensor(t_sdf, dtype=torch.float32)  # the mesh is already in the SDF's frame
        contacts = zoo.collide(sdf_body.sdf, mesh, sdf_pose=world, mesh_pose=world, margin=margin, method=self._method_for(sdf_body.sdf))
        faces_world = face_normals(local[faces[np.asarray(contacts.triangles)]]) @ t_sdf[:3, :3].T  # (K, 3)
        contacts.triangles = torch.as_tensor(origin)[contacts.triangles]  # back to the body's own faces
        return contacts, faces_world

    def _method_for(self, sdf) -> str:
        if self.method == "amortized" and not callable(getattr(sdf, "detect", None)):
            return "fw"
        return self.method

    def _closing_distance(self, a: Body, b: Body) -> float:
        """Upper bound (m) on how much closer the two bodies' surfaces can get in one step.

        A contact lies within ``reach`` of SDF body a's origin, so within ``reach`` + |x_a - x_b| of
        mesh body b's: each body's rotation moves it by at most its angular speed times that lever.
        """
        a_velocity, b_velocity = self.velocity(a.name), self.velocity(b.name)
        reach = self._reaches[a.name]
        lever_b = reach + float(np.linalg.norm(self.pose(a.name)[:3, 3] - self.pose(b.name)[:3, 3]))
        linear = float(np.linalg.norm(a_velocity[:3] - b_velocity[:3]))
        return (linear + reach * float(np.linalg.norm(a_velocity[3:])) + lever_b * float(np.linalg.norm(b_velocity[3:]))) * self.dt

    def _new_warnings(self) -> list[str]:
        import mujoco

        counts = np.array([w.number for w in self.data.warning])
        fresh = np.nonzero(counts > self._warnings_seen)[0]
        self._warnings_seen = counts
        return [f"mujoco: {mujoco.mjtWarning(int(i)).name}" for i in fresh]

    # -- state --------------------------------------------------------------------------

    def _body(self, name: str) -> Body:
        if name not in self.bodies:
            raise InputError(f"no body named {name!r}; bodies: {sorted(self.bodies)}")
        if self.model is None:
            self._build()
        return self.bodies[name]

    def pose(self, name: str) -> np.ndarray:
        """(4, 4) world-from-body of body ``name`` at the current time."""
        body, d = self._body(name), self.data
        pose = np.eye(4)
        pose[:3, :3] = d.xmat[body.body_id].reshape(3, 3)
        pose[:3, 3] = d.xpos[body.body_id]
        return pose

    def _motion(self, body: Body) -> tuple[np.ndarray, np.ndarray]:
        """(origin (3,), velocity (6,)) of ``body``, world frame, as :func:`closing_in_time` takes them."""
        return self.pose(body.name)[:3, 3], self.velocity(body.name)

    def velocity(self, name: str) -> np.ndarray:
        """(6,) linear velocity of the body's origin and angular velocity, world frame."""
        import mujoco

        body = self._body(name)
        res = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_BODY, body.body_id, res, 0)
        return np.concatenate([res[3:], res[:3]])

    def normal_force(self, name: str) -> float:
        """Total normal force (N) of the last step's contacts on body ``name``."""
        import mujoco

        body, m, d = self._body(name), self.model, self.data
        total, force = 0.0, np.zeros(6)
        for i in range(d.ncon):
            if body.geom_id in (d.contact.geom1[i], d.contact.geom2[i]):
                mujoco.mj_contactForce(m, d, i, force)
                total += force[0]
        return float(total)

    def set_control(self, name: str, value: float) -> None:
        """A driven joint's control: torque/force for a motor, target speed for a velocity drive."""
        body = self._body(name)
        if body.actuator_id < 0:
            raise InputError(f"body {name!r} has no drive")
        self.data.ctrl[body.actuator_id] = float(value)

    def collider_stats(self):
        """``zoo.coherence.CoherenceStats`` summed over every pair's collider and step so far (all zero without coherence)."""
        from ..coherence import CoherenceStats

        total = CoherenceStats()
        for pair in getattr(self, "_pair_meshes", {}).values():
            if pair is not None:
                total.add(pair.collider.stats)
        return total

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


def _pairs(bodies: list[Body]) -> list[tuple[Body, Body]]:
    """(SDF body, mesh body) pairs to collide: one per two bodies, so two bodies that both hold an SDF and a
    mesh are not collided both ways (two contact sets for one touch would make it twice as stiff); the
    earlier-added body's SDF meets the later one's mesh. Fixed bodies never meet each other."""
    pairs, seen = [], set()
    for a in bodies:
        for b in bodies:
            key = frozenset((a.name, b.name))
            if a is b or a.sdf is None or b.mesh is None or key in seen or (a.joint == "fixed" and b.joint == "fixed"):
                continue
            seen.add(key)
            pairs.append((a, b))
    return pairs


def _bounds(sdf) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (np.asarray(torch.as_tensor(b).detach().cpu(), dtype=np.float64).reshape(3) for b in sdf.bounds)
    return lo, hi


def _world_box(pose: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of the box [lo, hi] (body frame) under ``pose``."""
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    c = pose[:3, :3] @ centre + pose[:3, 3]
    h = np.abs(pose[:3, :3]) @ half
    return c - h, c + h


def _select(contacts, keep: np.ndarray):
    idx = torch.as_tensor(keep, dtype=torch.long)
    return zoo.Contacts(points=contacts.points[idx], depths=contacts.depths[idx], normals=contacts.normals[idx],
                        triangles=contacts.triangles[idx], bary=contacts.bary[idx], n_triangles=contacts.n_triangles,
                        n_candidates=contacts.n_candidates, method=contacts.method, timings=contacts.timings)


def _concat_contacts(parts):
    if not parts:
        z = torch.zeros(0, 3)
        return zoo.Contacts(points=z, depths=torch.zeros(0), normals=z, triangles=torch.zeros(0, dtype=torch.long), bary=z)
    if len(parts) == 1:
        return parts[0]
    cat = lambda key: torch.cat([getattr(p, key).to(parts[0].points.dtype) if key != "triangles" else p.triangles for p in parts])  # noqa: E731
    return zoo.Contacts(points=cat("points"), depths=cat("depths"), normals=cat("normals"), triangles=cat("triangles"),
                        bary=cat("bary"), n_triangles=sum(p.n_triangles for p in parts),
                        n_candidates=sum(p.n_candidates for p in parts), method=parts[0].method)
