"""sdfzoo's contacts in a user's own MuJoCo model: :func:`attach` and the :class:`World` it returns.

The user keeps their model and their loop. :func:`attach` names bodies of the model whose collision shape
is an SDF (in the body's frame); each is collided with every geom MuJoCo would let it touch
(:mod:`zoo.sim.geoms`), and MuJoCo keeps colliding every other pair itself. At every step, after MuJoCo's
position and velocity stages, the World detects each pair's contacts (``zoo.collide`` or, along the
trajectory, ``zoo.CoherentCollider``), keeps those MuJoCo's solver can use and reduces them to a manifold
(:mod:`zoo.sim.contacts`), appends them with ``mj_addContact`` and rebuilds the constraint stage
(``mj_makeConstraint``, ``mj_island``, ``mj_projectConstraint``, ``mj_referenceConstraint``: adding a
contact clears the constraint rows). Two ways to run it, with identical trajectories:

* ``world.step(data)`` in place of ``mujoco.mj_step(model, data)``: ``mj_step1``, the contacts, ``mj_step2``;
* ``with world.hooked():`` makes every ``mujoco.mj_step`` and ``mj_forward`` of that model add them, from
  MuJoCo's control callback (which runs after the velocity stage and before the solver; a callback the
  user had is chained and called first). The managed viewer, gymnasium and dm_control loops call
  ``mj_step`` and so get the contacts. RK4 runs this way too (its four stages each detect).

Pairs: an SDF body meets a mesh geom through the model's compiled mesh, a box through its 12 triangles, a
sphere or capsule in closed form (f along its axis segment, less its radius), a cylinder or ellipsoid
through a tessellation within ``tolerance``, a plane through a patch of it laid under the SDF at each step
(a plane is infinite), and another SDF body through that body's
surface mesh (``surfaces`` names one, else it is extracted once from its SDF by marching cubes); of two SDF
bodies, the one named first in ``bodies`` uses its SDF. Triangles larger than a quarter of the SDF are split
once, at attach (``refine``). Fast impacts: a pair whose bodies could close more than the margin within a
step is collided with a margin that covers it (speculative contacts). Before any query, a pair whose
bounding balls (a ball and a half-space for a plane) are farther apart than the margin is passed over: a
robot's many geoms far from the object cost a few microseconds each.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import torch

import zoo

from ..errors import InputError
from ..geometry import face_normals, invert_pose
from ..methods import method_for
from ..validation import non_negative_float
from .contacts import (
    GRAZING_COS,
    MERGE_CELL,
    REFINE_CELLS,
    SEPARATED_COS,
    add_contacts,
    as_numpy,
    closing_in_time,
    contact_rows,
    facing_faces,
    reduce_contacts,
    refine_near,
    refine_to_size,
    refined_pieces,
)
from .flat_regions import FaceCover, merge_flat_regions
from .geoms import (
    ContactParameters,
    body_geoms,
    body_pose,
    body_velocity,
    cube_corners,
    excluded_bodies,
    geom_parameters,
    geom_pose,
    geom_segment,
    geom_surface,
    may_touch,
    mixed_parameters,
    native_colliders,
    partner_geoms,
)
from .segments import segment_minima
from .surface import CONTACT_RESOLUTION, surface_mesh

# contacts closer than this fraction of the SDF's smallest extent are one contact (FW-10 scatters the
# copies of a vertex's contact by up to a tenth of the edge)
MERGE_FRACTION = 0.05
SPECULATIVE_FACTOR = 1.5  # a fast pair's margin covers this much more than one step's closing distance
# a mesh that refining once would grow past this many faces (a large ground mesh under a small SDF) is
# instead clipped and refined near the SDF at every step, from scratch (no temporal coherence for that pair)
PREREFINE_MAX_FACES = 200_000
# a face merged where the mesh is flat is at most this many of the reduction's cells wide: the reduction keeps one
# contact per cell and a face gives one at most, so wider faces leave a flat support too few contacts
FLAT_WIDTH_CELLS = 0.5
TESSELLATION_TOLERANCE = 1e-4  # m: a curved primitive's triangles lie within this of its surface


@dataclass
class SdfBody:
    """A body of the model whose collision shape is an SDF (in the body's frame).

    Attributes:
        name, body: its name and id in the model.
        geom: the geom sdfzoo's contacts name for it (the body's first geom): MuJoCo's solver takes the body
            from it, and its friction, condim, solref, solimp, solmix, priority, margin and gap are the SDF's.
        sdf: the SDF.
        lo, hi: (3,) the box that holds its surface, body frame.
        types: (contype, conaffinity) the SDF collides with.
    """

    name: str
    body: int
    geom: int
    sdf: object
    lo: np.ndarray
    hi: np.ndarray
    types: tuple[int, int]

    @property
    def reach(self) -> float:
        """The farthest a point of its box lies from the body's origin."""
        return float(np.linalg.norm(np.maximum(np.abs(self.lo), np.abs(self.hi))))

    @property
    def max_edge(self) -> float:
        """The longest mesh edge refinement leaves near it (a thin plate: its side, not its thickness)."""
        return float(np.median(self.hi - self.lo)) / REFINE_CELLS


@dataclass
class RefinedMesh:
    """A pair's surface at the SDF's resolution, made once: its flat regions' needless vertices removed
    (:func:`zoo.sim.flat_regions.merge_flat_regions`), then its large triangles split
    (:func:`zoo.sim.contacts.refine_to_size`), in the frame of the surface it comes from: vertices (V, 3), faces
    (F, 3), cover (:class:`zoo.sim.flat_regions.FaceCover`) the surface's own faces under each face, normals (F, 3)
    unit face normals."""

    vertices: np.ndarray
    faces: np.ndarray
    cover: FaceCover
    normals: np.ndarray

    def surface_faces(self, triangles, bary) -> torch.Tensor:
        """(K,) int64 the surface's own face that holds each point ``bary`` (K, 3) of the faces ``triangles`` (K,)."""
        triangles, bary = np.asarray(triangles, dtype=np.int64), np.asarray(bary, dtype=np.float64)
        if self.cover.one_each:
            return torch.as_tensor(self.cover.members[triangles])
        points = np.einsum("kv,kvc->kc", bary, self.vertices[self.faces[triangles]])
        return torch.as_tensor(self.cover.input_faces(triangles, points))


@dataclass
class Pair:
    """One SDF body and one thing it may touch.

    Attributes:
        sdf_body: the :class:`SdfBody`.
        body: the other body's id; geom: the geom its contacts name.
        params: the pair's mixed contact parameters.
        frame: "geom" (the surface is in ``geom``'s frame) or "body" (in ``body``'s: another SDF body's surface).
        kind: "mesh" (triangles), "plane" (an infinite plane, z = 0 of its frame, facing +z) or "segment" (a sphere
            or capsule: the points within ``radius`` of the segment from -``half_length`` to +``half_length``
            along z, answered in closed form).
        vertices, faces: (V, 3), (F, 3) the other side's surface in that frame as given (a mesh); lo, hi: its box.
        refined: the :class:`RefinedMesh` the collider answers on, or None where the refinement happens near
            the SDF at each step (a large mesh) or not at all (a plane).
        collider: the pair's ``zoo.CoherentCollider`` on ``refined`` (None without it).
    """

    sdf_body: SdfBody
    body: int
    geom: int
    params: ContactParameters
    frame: str
    kind: str = "mesh"
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    refined: RefinedMesh | None = None
    collider: object = None
    radius: float = 0.0
    half_length: float = 0.0
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None

    @property
    def is_plane(self) -> bool:
        return self.kind == "plane"

    @property
    def bounding_radius(self) -> float:
        """Radius of a ball about the surface frame's ``centre`` that holds the surface (inf for a plane)."""
        if self.kind == "plane":
            return math.inf
        if self.kind == "segment":
            return self.half_length + self.radius
        return float(np.linalg.norm(self.hi - self.lo)) / 2

    @property
    def centre(self) -> np.ndarray:
        """The centre (3,) of the surface's box, in its frame."""
        return np.zeros(3) if self.kind in ("plane", "segment") else (self.lo + self.hi) / 2

    def surface_pose(self, data) -> np.ndarray:
        """(4, 4) world-from-surface: the pose of the frame ``vertices`` and ``refined`` are in, at ``data``'s kinematics."""
        return geom_pose(data, self.geom) if self.frame == "geom" else body_pose(data, self.body)


@dataclass
class PairContacts:
    """One pair's contacts at a step (world frame) and the rows of them MuJoCo can use: ``points`` (K, 3),
    ``depths`` (K,), ``normals`` (K, 3) (the SDF's, as :func:`as_numpy` gives them), ``faces_world`` (K, 3) their
    mesh faces' unit normals (zeros where degenerate), ``usable`` (U,) the rows kept so far, ``reduced`` whether
    those are already the reduction's."""

    pair: Pair
    contacts: object  # zoo.Contacts
    points: np.ndarray
    depths: np.ndarray
    normals: np.ndarray
    faces_world: np.ndarray
    usable: np.ndarray
    reduced: bool = False


@dataclass
class StepStats:
    """What the last detection did: contacts added (after the reduction), found (before it), the deepest
    penetration (m, >= 0), the largest margin used, whether a pair was speculative, its wall time (s) and
    the contacts MuJoCo's full buffer dropped."""

    contacts: int = 0
    raw_contacts: int = 0
    max_penetration: float = 0.0
    margin: float = 0.0
    speculative: bool = False
    collide_s: float = 0.0
    dropped: int = 0


PROXY_CHOICES = ("ahead", "lazy")  # a proxy's bricks baked at attach, or when a read first needs them


def proxy_choice(value, name: str = "proxy") -> str | bool:
    """``attach``'s ``proxy`` as "ahead", "lazy" or False (True is "ahead")."""
    if value is True:
        return "ahead"
    if value is False or value is None:
        return False
    if value in PROXY_CHOICES:
        return value
    raise InputError(f"{name} must be True, False or one of {PROXY_CHOICES}, got {value!r}")


def reduce_choice(value) -> bool | str:
    """``attach``'s ``reduce`` as True, False or "exact"."""
    if value is True or value is False or value == "exact":
        return value
    raise InputError(f'reduce must be True, False or "exact", got {value!r}')


def attach(model, bodies: dict, *, method: str = "amortized", margin: float = 1e-3, coherence: bool = True,
           reduce: bool | str = True, refine: bool = True, contype: int = 1, conaffinity: int = 1,
           surfaces: dict | None = None, include_geoms=(), tolerance: float = TESSELLATION_TOLERANCE,
           proxy: bool | str | dict = True) -> World:
    """sdfzoo's contacts for the SDF bodies of a user's ``mujoco.MjModel`` (see the module docstring).

    Args:
        model: the user's ``mujoco.MjModel`` (any MJCF: robots, mocap, actuators, equality, options).
        bodies: {body name: SDF in that body's frame}: any SDF (a NeuralShape, ``zoo.Sphere``, a
            ``TransformedSDF``...). Each body needs a geom (its visual mesh) with contype = conaffinity = 0.
        method: ``zoo.collide``'s narrow phase; "amortized" falls back to "fw" for an SDF without a detector.
        margin: m; contacts are detected this far before touching (at least each pair's MuJoCo margin).
        coherence: carry each pair's bounds and answers from step to step (``zoo.CoherentCollider``); False
            collides every pair from scratch with ``zoo.collide``.
        reduce: reduce contacts to a manifold per patch (False: every usable contact, for comparison). Where a proxy
            searches, True picks the manifold on the proxy's depths and the NeuralSDF answers the rows kept; "exact"
            has the NeuralSDF answer every cell's candidates (those within twice the proxy's error of the cell's
            deepest) and picks on its own depths, at the cost of those answers (docs/proxy.md, Fidelity).
        refine: split triangles larger than a quarter of the SDF, and remove the vertices the meshes' flat parts do
            not need, once (``zoo.sim.flat_regions``; False: the meshes as the model has them).
        contype, conaffinity: the SDF's collision bits, as a geom's (MuJoCo's defaults).
        surfaces: {SDF body name: mesh (trimesh or (V, F), body frame)} the surface another SDF body collides
            with, instead of one extracted from its SDF.
        include_geoms: names of geoms MuJoCo does not collide (contype = conaffinity = 0) that the SDF bodies
            collide with all the same (a flat mesh MuJoCo cannot take as a collision mesh).
        tolerance: m; how far a tessellated primitive's triangles may lie inside its true surface.
        proxy: with ``coherence`` (default True), each model shape's mesh pairs cull and search on its narrow-band
            proxy (:func:`zoo.proxy.cached_proxy` at ``margin``, cached on disk), and the shape answers only the
            contacts kept (:mod:`zoo.proxy_collider`); other SDFs, and planes and spheres, are unchanged.
            True or "ahead": every brick near the shape's surface is baked here, at attach, on every core with a
            progress bar, unless the cache has it (``zoo bake`` prepares the cache); so no step bakes.
            "lazy": bricks are baked when a step first reads them (a quick start, uneven first steps). Either
            way the contacts are the same, and what was baked is written back to the cache. False: every query
            is the shape's. A dict {SDF body name: a ``zoo.proxy.ProxySDF``, True, "ahead" or "lazy"} gives
            those bodies theirs (any SDF), and no other.
    """
    return World(model, bodies, method=method, margin=margin, coherence=coherence, reduce=reduce, refine=refine,
                 contype=contype, conaffinity=conaffinity, surfaces=surfaces, include_geoms=include_geoms,
                 tolerance=tolerance, proxy=proxy)


class World:
    """The SDF bodies of one ``mujoco.MjModel`` and their pairs; made by :func:`attach`.

    Attributes:
        model: the model.
        bodies: {name: :class:`SdfBody`}.
        pairs: every :class:`Pair` collided at each step.
        contacts: ``zoo.Contacts`` that went into MuJoCo's solver at the last detection, world frame.
        contact_geoms: (K, 2) int the geoms of each of those contacts (the SDF body's, the other's).
        stats: :class:`StepStats` of the last detection.
        proxies: {SDF body name: its ``zoo.proxy.ProxySDF``, or None}.
        bake_seconds: the time attach spent baking proxies ahead (0 where the cache held them).
    """

    def __init__(self, model, bodies: dict, *, method: str = "amortized", margin: float = 1e-3, coherence: bool = True,
                 reduce: bool = True, refine: bool = True, contype: int = 1, conaffinity: int = 1,
                 surfaces: dict | None = None, include_geoms=(), tolerance: float = TESSELLATION_TOLERANCE,
                 proxy: bool | str | dict = True):
        import mujoco

        if not isinstance(model, mujoco.MjModel):
            raise InputError(f"attach needs a mujoco.MjModel, got {type(model).__name__}")
        if not bodies:
            raise InputError("attach needs at least one {body name: SDF}")
        self.model = model
        self.method = method
        self.margin = non_negative_float(margin, "margin")
        self.coherence, self.reduce, self.refine = bool(coherence), reduce_choice(reduce), bool(refine)
        self.proxy = dict(proxy) if isinstance(proxy, dict) else proxy_choice(proxy, "proxy")
        if isinstance(self.proxy, dict):
            self.proxy = {name: given if hasattr(given, "read") else proxy_choice(given, f"proxy[{name!r}]")
                          for name, given in self.proxy.items()}
        if isinstance(self.proxy, dict) and set(self.proxy) - set(bodies):
            raise InputError(f"proxy names {sorted(set(self.proxy) - set(bodies))}, which are not SDF bodies; SDF bodies: "
                             f"{sorted(bodies)}")
        self.proxies: dict[str, object] = {}  # SDF body name -> its zoo.proxy.ProxySDF, where one is used
        self.bake_seconds = 0.0  # spent at attach baking the proxies ahead (proxy="ahead")
        self.tolerance = float(tolerance)
        include = {self._geom_id(name) for name in include_geoms}
        self.bodies = {name: self._sdf_body(name, sdf, (int(contype), int(conaffinity))) for name, sdf in bodies.items()}
        surfaces = dict(surfaces or {})
        unknown = set(surfaces) - set(self.bodies)
        if unknown:
            raise InputError(f"surfaces names {sorted(unknown)}, which are not SDF bodies; SDF bodies: {sorted(self.bodies)}")
        self.pairs = self._pairs(include, surfaces)
        self.contacts = _concat_contacts([])
        self.contact_geoms = np.zeros((0, 2), dtype=np.int32)
        self.stats = StepStats(margin=self.margin)
        self._hooks = 0

    # -- building ----------------------------------------------------------------------------------

    def _geom_id(self, name: str) -> int:
        import mujoco

        geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if geom < 0:
            raise InputError(f"the model has no geom named {name!r}")
        return geom

    def _sdf_body(self, name: str, sdf, types: tuple[int, int]) -> SdfBody:
        import mujoco

        zoo.sdf.check_sdf(sdf)
        body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            names = [self.model.body(i).name for i in range(self.model.nbody)]
            raise InputError(f"the model has no body named {name!r}; its bodies: {names}")
        geoms = body_geoms(self.model, body)
        if not geoms:
            raise InputError(f"body {name!r} has no geom: give it one (its visual mesh, contype=\"0\" conaffinity=\"0\"); "
                             "sdfzoo's contacts name it, and MuJoCo's solver finds the body through it")
        native = native_colliders(self.model, body)
        if native:
            raise InputError(f"body {name!r}'s geoms {native} still collide in MuJoCo's own collision, beside its SDF: "
                             "set contype=\"0\" conaffinity=\"0\" on them (the SDF is the body's collision shape)")
        lo, hi = (np.asarray(torch.as_tensor(b).detach().cpu(), dtype=np.float64).reshape(3) for b in sdf.bounds)
        return SdfBody(name=name, body=body, geom=geoms[0], sdf=sdf, lo=lo, hi=hi, types=types)

    def _pairs(self, include: set[int], surfaces: dict) -> list[Pair]:
        import mujoco

        model = self.model
        if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
            return []
        sdf_bodies = list(self.bodies.values())
        sdf_body_ids = {b.body for b in sdf_bodies}
        excluded = excluded_bodies(model)
        pairs = []
        for index, sdf_body in enumerate(sdf_bodies):
            own = geom_parameters(model, sdf_body.geom)
            for geom in partner_geoms(model, sdf_body.body, sdf_body.types, sdf_body_ids, include):
                params = mixed_parameters(model, own, geom_parameters(model, geom))
                segment = geom_segment(model, geom)
                if segment is not None:  # a sphere or a capsule: exact, no triangles
                    pairs.append(Pair(sdf_body=sdf_body, body=int(model.geom_bodyid[geom]), geom=geom, params=params,
                                      frame="geom", kind="segment", radius=segment[0], half_length=segment[1]))
                    continue
                surface = geom_surface(model, geom, self.tolerance)
                pairs.append(self._pair(sdf_body, int(model.geom_bodyid[geom]), geom, params, "geom", surface))
            for other in sdf_bodies[index + 1:]:  # the earlier-named body's SDF meets the later one's surface
                if not may_touch(model, sdf_body.body, sdf_body.types, other.body, other.types, excluded):
                    continue
                params = mixed_parameters(model, own, geom_parameters(model, other.geom))
                surface = _mesh_pair(surfaces[other.name]) if other.name in surfaces else surface_mesh(other.sdf, CONTACT_RESOLUTION)
                pairs.append(self._pair(sdf_body, other.body, other.geom, params, "body", surface))
        return pairs

    def _pair(self, sdf_body: SdfBody, body: int, geom: int, params: ContactParameters, frame: str, surface) -> Pair:
        pair = Pair(sdf_body=sdf_body, body=body, geom=geom, params=params, frame=frame)
        if surface is None:
            pair.kind = "plane"
            return pair
        pair.vertices, pair.faces = surface
        pair.lo, pair.hi = pair.vertices.min(axis=0), pair.vertices.max(axis=0)
        max_edge = sdf_body.max_edge if self.refine else math.inf
        # the flat pass is for a model's meshes: an SDF body's surface is made at the resolution contacts need, and
        # a mesh larger than this is refined near the SDF at every step
        flat = self.refine and frame == "geom" and len(pair.faces) <= PREREFINE_MAX_FACES
        merged, cover = (merge_flat_regions(pair.vertices, pair.faces, self.flat_width(sdf_body), refined_pieces(max_edge))
                         if flat else (pair.faces, None))
        refined = refine_to_size(pair.vertices, merged, max_edge, PREREFINE_MAX_FACES)
        if refined is not None:
            vertices, faces, origin = refined
            cover = (cover or FaceCover.identity(pair.vertices, pair.faces)).take(origin, vertices[faces])
            mesh = (torch.as_tensor(vertices, dtype=torch.float32), torch.as_tensor(faces))
            pair.collider = zoo.CoherentCollider(sdf_body.sdf, mesh, margin=self.margin, method=self._method_for(sdf_body.sdf),
                                                 coherence=self.coherence, proxy=self._proxy_for(sdf_body), deferred=True)
            if self.reduce and pair.collider.deferred:  # only what the reduction can keep comes back
                from ..proxy_collider import Thinning

                band = 2 * pair.collider.proxy.error_bound if self.reduce == "exact" else 0.0
                pair.collider.thin = Thinning(MERGE_CELL * self.merge_distance(sdf_body), GRAZING_COS, SEPARATED_COS,
                                              band=band)
            pair.refined = RefinedMesh(vertices, faces, cover, face_normals(vertices[faces]))
        return pair

    def _proxy_for(self, sdf_body: SdfBody):
        """The proxy ``sdf_body``'s mesh pairs search on (one per body, from the cache where baked before), or None:
        without ``proxy`` or ``coherence``, and for SDFs that are not a model's shapes (analytic ones are cheap)."""
        given = self.proxy.get(sdf_body.name, False) if isinstance(self.proxy, dict) else self.proxy
        if given is False or given is None or not self.coherence:
            return None
        if sdf_body.name not in self.proxies:
            from ..proxy import bake_ahead, cached_proxy, proxy_key

            if isinstance(given, str) and (isinstance(self.proxy, dict) or proxy_key(sdf_body.sdf, {}) is not None):
                if given == "ahead":
                    done = bake_ahead(sdf_body.sdf, margin=self.margin)
                    self.bake_seconds += done.seconds if done.baked else 0.0
                    self.proxies[sdf_body.name] = done.proxy
                else:
                    self.proxies[sdf_body.name] = cached_proxy(sdf_body.sdf, margin=self.margin)
            else:  # the caller's own proxy, or None: an SDF that is not a model's shape
                self.proxies[sdf_body.name] = None if isinstance(given, str) else given
        return self.proxies[sdf_body.name]

    def _method_for(self, sdf) -> str:
        return method_for(self.method, sdf)

    # -- running -----------------------------------------------------------------------------------

    def step(self, data, nstep: int = 1) -> None:
        """``nstep`` steps of ``mujoco.mj_step(model, data)`` with sdfzoo's contacts in the solver."""
        import mujoco

        m = self.model
        for _ in range(int(nstep)):
            if self._hooks or m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
                with self.hooked():  # RK4's stages each run the control callback; nested hooks are one
                    mujoco.mj_step(m, data)
                continue
            mujoco.mj_step1(m, data)
            self.add_contacts(data)
            mujoco.mj_step2(m, data)

    @contextmanager
    def hooked(self):
        """Within it, every ``mujoco.mj_step`` / ``mj_forward`` of this model includes sdfzoo's contacts.

        Installs MuJoCo's control callback (global to the process); a callback set before is called first,
        and restored on exit.
        """
        import mujoco

        if self._hooks:
            yield self
            return
        previous = mujoco.get_mjcb_control()
        address = self.model._address

        def control(m, d):
            if previous is not None:
                previous(m, d)
            if m._address == address:
                self.add_contacts(d)

        mujoco.set_mjcb_control(control)
        self._hooks += 1
        try:
            yield self
        finally:
            self._hooks -= 1
            mujoco.set_mjcb_control(previous)

    def add_contacts(self, data) -> int:
        """Detect at ``data``'s current position and velocity stages, append the contacts and rebuild the
        constraint stage; returns how many were added. What ``step`` and the hook call between MuJoCo's
        velocity stage and its solver; call it yourself only there."""
        import mujoco

        start = time.perf_counter()
        rows, collected, geoms, stats = self._detect(data)
        added = 0
        for r, params in rows:
            added += add_contacts(self.model, data, r, params)
        wanted = sum(len(r) for r, _ in rows)
        if added:
            mujoco.mj_makeConstraint(self.model, data)
            mujoco.mj_island(self.model, data)
            mujoco.mj_projectConstraint(self.model, data)
            mujoco.mj_referenceConstraint(self.model, data)
        stats.contacts, stats.dropped = added, wanted - added
        stats.collide_s = time.perf_counter() - start
        self.stats = stats
        self.contacts = _concat_contacts(collected)
        self.contact_geoms = np.concatenate(geoms) if geoms else np.zeros((0, 2), dtype=np.int32)
        return added

    def pair(self, sdf_body: str, other_body: str) -> Pair:
        """The first pair of SDF body ``sdf_body`` with a geom (or the surface) of body ``other_body``."""
        import mujoco

        other = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, other_body)
        for pair in self.pairs:
            if pair.sdf_body.name == sdf_body and pair.body == other:
                return pair
        raise InputError(f"no pair of SDF body {sdf_body!r} with body {other_body!r}")

    def reset(self) -> None:
        """Forget what the colliders carried from step to step (after a reset of the data, say)."""
        for pair in self.pairs:
            if pair.collider is not None:
                pair.collider.reset()

    def collider_stats(self):
        """``zoo.collider.CoherenceStats`` summed over every pair's collider and call so far."""
        from ..collider import CoherenceStats

        total = CoherenceStats()
        for pair in self.pairs:
            if pair.collider is not None:
                total.add(pair.collider.stats)
        return total

    # -- detection ---------------------------------------------------------------------------------

    def _detect(self, data):
        rows, collected, geoms = [], [], []
        stats = StepStats(margin=self.margin)
        deepest = 0.0
        velocities: dict[int, np.ndarray] = {}
        poses: dict[int, np.ndarray] = {}
        near = []  # (pair, its margin this step): the pairs the bounding balls cannot rule out
        for pair in self.pairs:
            for body in (pair.sdf_body.body, pair.body):
                if body not in velocities:
                    velocities[body] = body_velocity(self.model, data, body)
                    poses[body] = body_pose(data, body)
            margin = max(self.margin, pair.params.margin)
            closing = self._closing_distance(pair, data, velocities)
            if closing > margin:  # would cross the margin in one step: see it coming
                margin = SPECULATIVE_FACTOR * closing
            if self._apart(pair, poses[pair.sdf_body.body], pair.surface_pose(data), margin):
                continue
            stats.margin = max(stats.margin, margin)
            stats.speculative |= closing > max(self.margin, pair.params.margin)
            near.append((pair, margin))
        segments = self._collide_segments([(p, m) for p, m in near if p.kind == "segment"], data)
        found = []  # PairContacts of the pairs with contacts MuJoCo can use
        for pair, margin in near:
            if pair.kind == "segment":
                contacts, faces_world = segments.get(id(pair), (None, None))
            else:
                self._give_closing(pair, data, velocities)
                contacts, faces_world = self._collide(pair, data, margin)
            usable = self._usable(pair, data, contacts, faces_world, velocities)
            if usable is not None:
                stats.raw_contacts += len(usable.depths)
                found.append(self._reduced_on_proxy(usable))
        for found_pair in self.exact_answers(found):
            keep = found_pair.usable if found_pair.reduced else self._reduced(found_pair)
            if not len(keep):
                continue
            r = contact_rows((found_pair.points, found_pair.depths, found_pair.normals), keep,
                             (found_pair.pair.sdf_body.geom, found_pair.pair.geom))
            rows.append((r, found_pair.pair.params))
            collected.append(_select(found_pair.contacts, keep))
            geoms.append(r.geom)
            deepest = max(deepest, -float(r.dist.min()))
        stats.max_penetration = deepest
        return rows, collected, geoms, stats

    @staticmethod
    def _apart(pair: Pair, t_sdf: np.ndarray, t_other: np.ndarray, margin: float) -> bool:
        """Whether the balls (or, for a plane, the ball and the half-space) around the two sides are more than
        ``margin`` apart: no contact, nothing to query."""
        sdf_body = pair.sdf_body
        centre = t_sdf[:3, :3] @ ((sdf_body.lo + sdf_body.hi) / 2) + t_sdf[:3, 3]
        radius = float(np.linalg.norm(sdf_body.hi - sdf_body.lo)) / 2
        if pair.kind == "plane":
            return float(t_other[:3, 2] @ (centre - t_other[:3, 3])) - radius > margin
        other = t_other[:3, :3] @ pair.centre + t_other[:3, 3]
        return float(np.linalg.norm(centre - other)) - radius - pair.bounding_radius > margin

    def _closing_distance(self, pair: Pair, data, velocities: dict) -> float:
        """Upper bound (m) on how much closer the pair's surfaces can get in one step.

        A contact lies within ``reach`` of the SDF body's origin, so within ``reach`` + |x_a - x_b| of the
        other body's: each body's rotation moves it by at most its angular speed times that lever.
        """
        a, b = velocities[pair.sdf_body.body], velocities[pair.body]
        reach = pair.sdf_body.reach
        lever = reach + float(np.linalg.norm(data.xpos[pair.sdf_body.body] - data.xpos[pair.body]))
        linear = float(np.linalg.norm(a[:3] - b[:3]))
        return (linear + reach * float(np.linalg.norm(a[3:])) + lever * float(np.linalg.norm(b[3:]))) * self.model.opt.timestep

    def _give_closing(self, pair: Pair, data, velocities: dict) -> None:
        """Give the pair's proxy collider, where it thins its contacts, this step's relative motion of the two bodies
        (``Thinning.closing``: what :func:`closing_in_time` tests in :meth:`_usable`)."""
        collider = pair.collider
        if getattr(collider, "thin", None) is None:
            return
        a, b = velocities[pair.sdf_body.body], velocities[pair.body]
        shift = a[:3] - b[:3] - np.cross(a[3:], data.xpos[pair.sdf_body.body]) + np.cross(b[3:], data.xpos[pair.body])
        collider.thin = replace(collider.thin, closing=(shift, a[3:] - b[3:], self.model.opt.timestep * SPECULATIVE_FACTOR))

    def _collide(self, pair: Pair, data, margin: float):
        """(zoo.Contacts in the world frame, their faces' world normals (K, 3)) of a mesh or plane pair, or (None, None)."""
        sdf_body = pair.sdf_body
        t_sdf, t_other = body_pose(data, sdf_body.body), pair.surface_pose(data)
        if pair.kind == "plane":
            return self._collide_plane(pair, t_sdf, t_other, margin)
        world_lo, world_hi = _world_box(t_sdf, sdf_body.lo - margin, sdf_body.hi + margin)
        mesh_lo, mesh_hi = _world_box(t_other, pair.lo, pair.hi)
        if (world_hi < mesh_lo).any() or (mesh_hi < world_lo).any():
            return None, None
        if pair.collider is None:
            return self._collide_refining_near(pair, t_sdf, t_other, margin)
        contacts = pair.collider(torch.from_numpy(t_sdf), torch.from_numpy(t_other), margin=margin)
        faces_world = pair.refined.normals[np.asarray(contacts.triangles)] @ t_other[:3, :3].T  # (K, 3)
        if not getattr(pair.collider, "deferred", False):  # a deferred pair's are named when the SDF answers them
            contacts.triangles = pair.refined.surface_faces(contacts.triangles, contacts.bary)
        return contacts, faces_world

    def _usable(self, pair: Pair, data, contacts, faces_world, velocities: dict) -> PairContacts | None:
        """The pair's contacts with the rows MuJoCo can use, or None where there are none: facing their faces, and
        touching or closing within the step (a separated one beyond that would only brake the bodies at a distance).
        """
        if contacts is None or len(contacts) == 0:
            return None
        sdf_body = pair.sdf_body
        points, depths, normals = as_numpy(contacts)
        motion_a = (data.xpos[sdf_body.body].copy(), velocities[sdf_body.body])
        motion_b = (data.xpos[pair.body].copy(), velocities[pair.body])
        usable = facing_faces(normals, faces_world, depths) & closing_in_time(
            points, depths, normals, motion_a, motion_b, self.model.opt.timestep, SPECULATIVE_FACTOR)
        return PairContacts(pair, contacts, points, depths, normals, faces_world, np.nonzero(usable)[0])

    def _reduced_on_proxy(self, found: PairContacts) -> PairContacts:
        """A proxy's pair with ``reduce=True``: reduced on the proxy's depths, so that the NeuralSDF answers only the
        rows kept. Other pairs, and every pair with ``reduce="exact"``, as they are (reduced on the SDF's depths)."""
        if self.reduce is not True or not getattr(found.pair.collider, "deferred", False):
            return found
        return replace(found, usable=self._reduced(found), reduced=True)

    def _reduced(self, found: PairContacts) -> np.ndarray:
        """The usable rows (R,) the reduction keeps (all of them with ``reduce=False``): a manifold per patch, on
        the depths ``found`` holds."""
        keep = found.usable
        if not self.reduce or not len(keep):
            return keep
        return keep[reduce_contacts(found.points[keep], found.depths[keep], found.normals[keep], found.faces_world[keep],
                                    merge_tol=self.merge_distance(found.pair.sdf_body))]

    @classmethod
    def flat_width(cls, sdf_body: SdfBody) -> float:
        """m: the widest face the flat-region pass makes for ``sdf_body``'s pairs (``FLAT_WIDTH_CELLS`` cells)."""
        return FLAT_WIDTH_CELLS * MERGE_CELL * cls.merge_distance(sdf_body)

    @staticmethod
    def merge_distance(sdf_body: SdfBody) -> float:
        """m: the reduction's ``merge_tol`` for the contacts of ``sdf_body``'s pairs."""
        return MERGE_FRACTION * float((sdf_body.hi - sdf_body.lo).min())

    @staticmethod
    def exact_answers(found: list[PairContacts]) -> list[PairContacts]:
        """``found`` with the SDF's own contacts in place of the proxy's where a pair's proxy chose them (at its usable
        rows, those whose SDF depth is beyond the margin dropped, every row of the rest usable): the pairs of a step
        on one SDF ask it together (:func:`zoo.proxy_collider.exact_contacts_together`)."""
        from ..proxy_collider import exact_contacts_together

        deferred = [i for i, f in enumerate(found) if len(f.usable) and getattr(f.pair.collider, "deferred", False)]
        if not deferred:
            return found
        found = list(found)
        answers = exact_contacts_together([(found[i].pair.collider, found[i].usable) for i in deferred])
        for i, contacts in zip(deferred, answers):
            asked = found[i]
            # the answers keep the asked rows' order, less those beyond the margin; a call answers a face once
            answered = np.isin(np.asarray(asked.contacts.triangles)[asked.usable], np.asarray(contacts.triangles))
            faces_world = asked.faces_world[asked.usable[answered]]
            contacts.triangles = asked.pair.refined.surface_faces(contacts.triangles, contacts.bary)
            found[i] = PairContacts(asked.pair, contacts, *as_numpy(contacts), faces_world, np.arange(len(contacts)),
                                    asked.reduced)
        return found

    def _collide_refining_near(self, pair: Pair, t_sdf: np.ndarray, t_other: np.ndarray, margin: float):
        """(zoo.Contacts in the world frame, their faces' world normals (K, 3)) of a pair whose mesh is refined near
        the SDF at this step, or (None, None) when no face reaches the SDF's box."""
        sdf_body = pair.sdf_body
        sdf_from_mesh = invert_pose(torch.from_numpy(t_sdf)).numpy() @ t_other  # rigid: a transpose, not a general inverse
        local = pair.vertices @ sdf_from_mesh[:3, :3].T + sdf_from_mesh[:3, 3]
        max_edge = sdf_body.max_edge if self.refine else math.inf
        local, faces, origin = refine_near(local, pair.faces, sdf_body.lo - margin, sdf_body.hi + margin, max_edge)
        if len(faces) == 0:
            return None, None
        return self._collide_in_sdf_frame(pair, local, faces, origin, t_sdf, margin)

    def _collide_plane(self, pair: Pair, t_sdf: np.ndarray, t_plane: np.ndarray, margin: float):
        """The pair's contacts with a patch of its (infinite) plane under the SDF's box, at this step."""
        sdf_body = pair.sdf_body
        plane_from_sdf = invert_pose(torch.from_numpy(t_plane)).numpy() @ t_sdf
        corners = cube_corners(sdf_body.lo, sdf_body.hi) @ plane_from_sdf[:3, :3].T + plane_from_sdf[:3, 3]
        if corners[:, 2].min() > margin:
            return None, None
        # cells whose diagonal is within the refinement's edge, so that zoo.collide answers them as they are
        cell = sdf_body.max_edge / math.sqrt(2) if self.refine else float(np.ptp(corners[:, :2], axis=0).max()) + 2 * margin
        lo = np.floor((corners[:, :2].min(axis=0) - margin) / cell).astype(np.int64)
        hi = np.ceil((corners[:, :2].max(axis=0) + margin) / cell).astype(np.int64)
        vertices, faces = _grid(lo, hi, cell)
        sdf_from_plane = invert_pose(torch.from_numpy(plane_from_sdf)).numpy()
        local = vertices @ sdf_from_plane[:3, :3].T + sdf_from_plane[:3, 3]
        return self._collide_in_sdf_frame(pair, local, faces, np.arange(len(faces)), t_sdf, margin)

    def _collide_segments(self, near: list, data) -> dict:
        """Spheres' and capsules' contacts in closed form, every such pair of a step together (one set of queries per
        SDF body): {id(pair): (contacts in the world frame, their normals as the faces' normals)} for the pairs that
        touch or come within their margin. A pair's contacts are its axis segment's points of least f
        (:func:`segment_minima`), each at depth f - radius along the SDF's normal there."""
        found = {}
        by_body: dict[str, list] = {}
        for pair, margin in near:
            by_body.setdefault(pair.sdf_body.name, []).append((pair, margin))
        for pairs in by_body.values():
            sdf_body = pairs[0][0].sdf_body
            t_sdf = body_pose(data, sdf_body.body)
            sdf_from_world = invert_pose(torch.from_numpy(t_sdf)).numpy()
            ends = []
            for pair, _ in pairs:
                t_geom = sdf_from_world @ pair.surface_pose(data)
                axis = t_geom[:3, 2] * pair.half_length
                ends.append((t_geom[:3, 3] - axis, t_geom[:3, 3] + axis))
            radii = np.array([pair.radius for pair, _ in pairs])
            margins = np.array([margin for _, margin in pairs])
            dtype = torch.float64 if getattr(sdf_body.sdf, "dtype", None) == torch.float64 else torch.float32
            proxy = self._proxy_for(sdf_body)
            lower_bound = None if proxy is None else (lambda p, proxy=proxy: proxy.read_numpy(p)[0] - proxy.error_bound)
            minima = segment_minima(sdf_body.sdf, np.array([e[0] for e in ends]), np.array([e[1] for e in ends]),
                                    radii + margins, dtype, lower_bound)
            if not len(minima.points):
                continue
            centres, owner, values, grads = minima.points, minima.owner, minima.values, minima.grads
            length = np.linalg.norm(grads, axis=1, keepdims=True)
            normals = grads / np.where(length > 0, length, 1.0)
            depths = values - radii[owner]
            rotation, origin = t_sdf[:3, :3], t_sdf[:3, 3]
            for index, (pair, margin) in enumerate(pairs):
                rows = np.nonzero((owner == index) & (depths <= margin))[0]
                if not len(rows):
                    continue
                points = centres[rows] - pair.radius * normals[rows]  # its point deepest in the SDF
                normals_world = normals[rows] @ rotation.T
                k = len(rows)
                found[id(pair)] = (zoo.Contacts(
                    points=torch.as_tensor(points @ rotation.T + origin), depths=torch.as_tensor(depths[rows]),
                    normals=torch.as_tensor(normals_world), triangles=torch.full((k,), -1, dtype=torch.long),
                    bary=torch.zeros(k, 3, dtype=torch.float64), n_triangles=0, n_candidates=k, method="closed-form"),
                    normals_world)
        return found

    def _collide_in_sdf_frame(self, pair: Pair, local: np.ndarray, faces: np.ndarray, origin: np.ndarray,
                              t_sdf: np.ndarray, margin: float):
        """``zoo.collide`` of the pair's SDF with a mesh given in the SDF's frame: (contacts in the world frame,
        their faces' world normals (K, 3)); triangles index ``origin``'s faces."""
        used, inverse = np.unique(faces, return_inverse=True)
        mesh = (torch.as_tensor(local[used], dtype=torch.float32), torch.as_tensor(inverse.reshape(-1, 3)))
        world = torch.as_tensor(t_sdf, dtype=torch.float32)  # the mesh is already in the SDF's frame
        contacts = zoo.collide(pair.sdf_body.sdf, mesh, sdf_pose=world, mesh_pose=world, margin=margin,
                               method=self._method_for(pair.sdf_body.sdf))
        faces_world = face_normals(local[faces[np.asarray(contacts.triangles)]]) @ t_sdf[:3, :3].T  # (K, 3)
        contacts.triangles = torch.as_tensor(origin)[contacts.triangles]
        return contacts, faces_world


# -- helpers ---------------------------------------------------------------------------------------


def _mesh_pair(mesh) -> tuple[np.ndarray, np.ndarray]:
    from .model import mesh_arrays

    return mesh_arrays(mesh, "surface")


def _grid(lo: np.ndarray, hi: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat grid in z = 0 over cells lo..hi (2,) int of side ``cell``: vertices (V, 3), faces (F, 3) facing +z."""
    xs = cell * np.arange(lo[0], hi[0] + 1)
    ys = cell * np.arange(lo[1], hi[1] + 1)
    nx, ny = len(xs), len(ys)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([a, c, d], axis=1)])
    return vertices, faces


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

    def cat(key):
        return torch.cat([getattr(p, key).to(parts[0].points.dtype) if key != "triangles" else p.triangles for p in parts])

    return zoo.Contacts(points=cat("points"), depths=cat("depths"), normals=cat("normals"), triangles=cat("triangles"),
                        bary=cat("bary"), n_triangles=sum(p.n_triangles for p in parts),
                        n_candidates=sum(p.n_candidates for p in parts), method=parts[0].method)


__all__ = ["attach", "World", "SdfBody", "Pair", "RefinedMesh", "StepStats"]
