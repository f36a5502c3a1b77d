"""What an SDF body of a MuJoCo model may touch, as MuJoCo would decide it, and the contact parameters of each pair.

:func:`partner_geoms` applies MuJoCo's own collision filter to an SDF body and every geom of the model:
no geom of the body itself nor of a body welded to it, no geom of its parent or child (by weld, unless the
model disables that filter), contype/conaffinity (the SDF body's own are :func:`zoo.sim.attach`'s
``contype`` and ``conaffinity``), and the model's ``<exclude>`` pairs. :func:`geom_segment` gives a sphere or
capsule as a segment and a radius (the SDF meets it in closed form); :func:`geom_surface` gives a geom's
collision geometry in its own frame: a mesh from the model's compiled mesh data, a box as its 12 exact
triangles, a sphere, capsule, cylinder or ellipsoid tessellated to within ``tolerance``, and a plane as
None (an infinite plane: :class:`zoo.sim.pairs.PlanePair` lays a patch of it under the SDF at each step).
:func:`mixed_parameters` mixes two geoms' friction, condim, solref, solimp, margin and gap by MuJoCo's
rules (``mj_contactParam``: the higher priority wins, else condim and friction take the maximum, solref
and solimp mix by solmix, and margin and gap take the maximum).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

MIN_VALUE = 1e-15  # MuJoCo's mjMINVAL


@dataclass(frozen=True)
class ContactParameters:
    """MuJoCo's parameters of the contacts between two geoms, mixed (see the module docstring).

    Attributes:
        condim: 1, 3, 4 or 6.
        friction: (5,) tangent, tangent, torsional, rolling, rolling.
        solref: (2,); solimp: (5,).
        margin: contacts are generated this far apart (m); gap: of which this much is inactive, so the
            constraint acts from ``margin - gap`` (MuJoCo's ``includemargin``).
    """

    condim: int
    friction: tuple
    solref: tuple
    solimp: tuple
    margin: float
    gap: float


def geom_parameters(model, geom: int) -> dict:
    """A geom's own contact parameters, as MuJoCo stores them."""
    return {
        "priority": int(model.geom_priority[geom]), "condim": int(model.geom_condim[geom]),
        "friction": np.asarray(model.geom_friction[geom], dtype=np.float64),
        "solref": np.asarray(model.geom_solref[geom], dtype=np.float64),
        "solimp": np.asarray(model.geom_solimp[geom], dtype=np.float64), "solmix": float(model.geom_solmix[geom]),
        "margin": float(model.geom_margin[geom]), "gap": float(model.geom_gap[geom]),
    }


def mixed_parameters(model, first: dict, second: dict) -> ContactParameters:
    """The contact parameters of two geoms (:func:`geom_parameters`) by MuJoCo's ``mj_contactParam``, with
    ``model.opt``'s overrides where the model enables them."""
    import mujoco

    if first["priority"] != second["priority"]:
        winner = first if first["priority"] > second["priority"] else second
        condim, friction = winner["condim"], winner["friction"]
        solref, solimp = winner["solref"], winner["solimp"]
    else:
        condim = max(first["condim"], second["condim"])
        friction = np.maximum(first["friction"], second["friction"])
        a, b = first["solmix"], second["solmix"]
        if a >= MIN_VALUE and b >= MIN_VALUE:
            mix = a / (a + b)
        elif a < MIN_VALUE and b < MIN_VALUE:
            mix = 0.5
        else:
            mix = 0.0 if a < MIN_VALUE else 1.0
        if first["solref"][0] > 0 and second["solref"][0] > 0:
            solref = mix * first["solref"] + (1 - mix) * second["solref"]
        else:  # direct (negative) references: the smaller
            solref = np.minimum(first["solref"], second["solref"])
        solimp = mix * first["solimp"] + (1 - mix) * second["solimp"]
    margin, gap = max(first["margin"], second["margin"]), max(first["gap"], second["gap"])
    opt = model.opt
    if opt.enableflags & mujoco.mjtEnableBit.mjENBL_OVERRIDE:
        margin, solref, solimp = float(opt.o_margin), np.asarray(opt.o_solref), np.asarray(opt.o_solimp)
        friction = np.asarray(opt.o_friction, dtype=np.float64)  # already MuJoCo's five
    friction = np.asarray(friction, dtype=np.float64).reshape(-1)
    five = (friction[0], friction[0], friction[1], friction[2], friction[2]) if len(friction) == 3 else tuple(friction)
    return ContactParameters(condim=int(condim), friction=tuple(float(f) for f in five),
                             solref=tuple(float(s) for s in solref), solimp=tuple(float(s) for s in solimp),
                             margin=float(margin), gap=float(gap))


def body_geoms(model, body: int) -> list[int]:
    """The geoms (ids) of ``body``."""
    start = int(model.body_geomadr[body])
    return [] if start < 0 else list(range(start, start + int(model.body_geomnum[body])))


def excluded_bodies(model) -> set[tuple[int, int]]:
    """The model's ``<exclude>`` pairs as (smaller body id, larger body id)."""
    return {(int(s) >> 16, int(s) & 0xFFFF) for s in np.asarray(model.exclude_signature).reshape(-1)}


def filtered_by_weld(model, body_a: int, body_b: int) -> bool:
    """MuJoCo's body-pair filter: the same weld body, or (unless disabled) a weld parent and its child."""
    import mujoco

    weld_a, weld_b = int(model.body_weldid[body_a]), int(model.body_weldid[body_b])
    if weld_a == weld_b:
        return True
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT:
        return False
    parent_a = int(model.body_weldid[model.body_parentid[weld_a]])
    parent_b = int(model.body_weldid[model.body_parentid[weld_b]])
    return weld_a != 0 and weld_b != 0 and (weld_a == parent_b or weld_b == parent_a)


def may_touch(model, body_a: int, types_a: tuple[int, int], body_b: int, types_b: tuple[int, int],
              excluded: set[tuple[int, int]]) -> bool:
    """Whether MuJoCo would collide a geom of ``body_a`` with (contype, conaffinity) ``types_a`` and one of
    ``body_b`` with ``types_b``."""
    if body_a == body_b or filtered_by_weld(model, body_a, body_b):
        return False
    if not ((types_a[0] & types_b[1]) or (types_b[0] & types_a[1])):
        return False
    return (min(body_a, body_b), max(body_a, body_b)) not in excluded


def partner_geoms(model, body: int, types: tuple[int, int], skip_bodies: set[int], include: set[int]) -> list[int]:
    """The geoms MuJoCo would let a geom of ``body`` with (contype, conaffinity) ``types`` touch, bodies in
    ``skip_bodies`` left out; geoms in ``include`` count as contype = conaffinity = 1 (visual geoms the caller
    wants collided all the same)."""
    excluded = excluded_bodies(model)
    partners = []
    for geom in range(model.ngeom):
        other = int(model.geom_bodyid[geom])
        if other in skip_bodies:
            continue
        own = (1, 1) if geom in include else (int(model.geom_contype[geom]), int(model.geom_conaffinity[geom]))
        if may_touch(model, body, types, other, own, excluded):
            partners.append(geom)
    return partners


def native_colliders(model, body: int) -> list[str]:
    """Names (or ids) of ``body``'s geoms that MuJoCo's own collision would still use."""
    return [model.geom(g).name or f"#{g}" for g in body_geoms(model, body)
            if model.geom_contype[g] or model.geom_conaffinity[g]]


# -- geometry ---------------------------------------------------------------------------------------


def geom_surface(model, geom: int, tolerance: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (V, 3), faces (F, 3)) of a geom's collision surface in the geom's frame; None for a plane.

    Meshes come from the model's compiled mesh data (the frame MuJoCo put them in, which ``geom_xpos`` and
    ``geom_xmat`` place); a box is exact; curved primitives are tessellated so that no point of the true
    surface lies more than ``tolerance`` (m) outside the triangles.
    """
    import mujoco
    import trimesh

    kind = int(model.geom_type[geom])
    size = np.asarray(model.geom_size[geom], dtype=np.float64)
    types = mujoco.mjtGeom
    if kind == types.mjGEOM_PLANE:
        return None
    if kind == types.mjGEOM_MESH:
        mesh = int(model.geom_dataid[geom])
        v0, nv = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        f0, nf = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        return (np.asarray(model.mesh_vert[v0:v0 + nv], dtype=np.float64),
                np.asarray(model.mesh_face[f0:f0 + nf], dtype=np.int64))
    if kind == types.mjGEOM_BOX:
        box = trimesh.creation.box(extents=2 * size[:3])
        return np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    if kind == types.mjGEOM_SPHERE:
        return _sphere(size[0], np.ones(3), tolerance)
    if kind == types.mjGEOM_ELLIPSOID:
        radius = float(size[:3].max())
        return _sphere(radius, size[:3] / radius, tolerance)
    if kind == types.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[_sections(size[0], tolerance)] * 2)
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    if kind == types.mjGEOM_CYLINDER:
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=_sections(size[0], tolerance))
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    name = model.geom(geom).name or f"#{geom}"
    raise InputError(f"geom {name!r} is a {types(kind).name}, which zoo.sim cannot collide with an SDF; "
                     "give it contype = conaffinity = 0, an <exclude>, or use a mesh or primitive geom")


def _sections(radius: float, tolerance: float) -> int:
    """Sections around a circle of ``radius`` whose chords stay within ``tolerance`` of it."""
    if radius <= tolerance:
        return 8
    return max(8, int(math.ceil(math.pi / math.acos(1.0 - tolerance / radius))))


def _sphere(radius: float, scale: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere of ``radius`` scaled by ``scale`` (3,), subdivided until its edges' sag is within ``tolerance``."""
    import trimesh

    level = 1
    while level < 7 and (1.1 * radius / 2**level) ** 2 / (8 * radius) > tolerance:  # an icosphere's edge is ~1.1 r / 2^level
        level += 1
    mesh = trimesh.creation.icosphere(subdivisions=level, radius=radius)
    return np.asarray(mesh.vertices, dtype=np.float64) * scale, np.asarray(mesh.faces, dtype=np.int64)


def geom_segment(model, geom: int) -> tuple[float, float] | None:
    """(radius, half-length along the geom's z) of a sphere (half-length 0) or capsule geom; None for other types:
    the points within a radius of a segment, which an SDF meets in closed form (no tessellation)."""
    import mujoco

    kind = int(model.geom_type[geom])
    size = model.geom_size[geom]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return float(size[0]), 0.0
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return float(size[0]), float(size[1])
    return None


def cube_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of the box with corners ``lo`` and ``hi`` (3,)."""
    return np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)


def geom_pose(data, geom: int) -> np.ndarray:
    """(4, 4) world-from-geom of ``geom`` at the data's current kinematics."""
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(data.geom_xmat[geom]).reshape(3, 3)
    pose[:3, 3] = data.geom_xpos[geom]
    return pose


def body_pose(data, body: int) -> np.ndarray:
    """(4, 4) world-from-body of ``body`` at the data's current kinematics."""
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(data.xmat[body]).reshape(3, 3)
    pose[:3, 3] = data.xpos[body]
    return pose


def body_velocity(model, data, body: int) -> np.ndarray:
    """(6,) linear velocity of the body's origin and its angular velocity, world frame (``mjOBJ_XBODY``: the body's
    frame; ``mjOBJ_BODY`` would give its centre of mass's)."""
    import mujoco

    res = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, res, 0)
    return np.concatenate([res[3:], res[:3]])
