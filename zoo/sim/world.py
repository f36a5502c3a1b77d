"""sdfzoo's contacts in a user's own MuJoCo model: :func:`attach` and the :class:`World` it returns.

The user keeps their model and their loop. :func:`attach` names bodies of the model whose collision shape
is an SDF (in the body's frame); each is collided with every geom MuJoCo would let it touch
(:mod:`zoo.sim.geoms`), and MuJoCo keeps colliding every other pair itself. At every step, after MuJoCo's
position and velocity stages, the World detects each pair's contacts (``zoo.collide`` or, along the
trajectory, ``zoo.CoherentCollider``), keeps those MuJoCo's solver can use (:mod:`zoo.contact_filters`) and reduces
them to a manifold (:mod:`zoo.sim.contacts`), appends them with ``mj_addContact`` and rebuilds the constraint stage
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
bodies, the one named first in ``bodies`` uses its SDF. Each kind of pair is its own type (:mod:`zoo.sim.pairs`). Triangles larger than a quarter of the SDF are split
once, at attach (``refine``). Fast impacts: a pair whose bodies could close more than the margin within a
step is collided with a margin that covers it (speculative contacts). Before any query, a pair whose
bounding balls (a ball and a half-space for a plane) are farther apart than the margin is passed over, every pair
in one compiled call (:mod:`zoo.sim.broad_phase`): a robot's many geoms far from the object cost next to nothing.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

import zoo

from ..collision import ContactArrays
from ..contact_filters import GRAZING_COS, SEPARATED_COS, Closing, usable_rows
from ..errors import InputError
from ..sdf import query_dtype, value_and_grad_numpy
from ..validation import non_negative_float
from .broad_phase import BroadPhase
from .contacts import add_contacts, contact_rows
from .geoms import (
    body_geoms,
    body_pose,
    excluded_bodies,
    geom_parameters,
    geom_segment,
    geom_surface,
    may_touch,
    mixed_parameters,
    native_colliders,
    partner_geoms,
)
from .pairs import Pair, PairSettings, SdfBody, SegmentPair, SurfacePair, make_pair, segment_contacts
from .reduction import reduce_contacts
from .surface import CONTACT_RESOLUTION, surface_mesh

TESSELLATION_TOLERANCE = 1e-4  # m: a curved primitive's triangles lie within this of its surface


@dataclass
class PairContacts:
    """One pair's contacts at a step (:class:`zoo.collision.ContactArrays`, world frame) and the rows of them MuJoCo
    can use: ``mesh_normals`` (K, 3) their mesh faces' unit normals (zeros where degenerate), ``usable`` (U,) the rows
    kept so far, ``closing`` the pair's relative motion they were filtered with (their depths taken
    ``pair.depth_slack`` below), ``reduced`` whether those rows are already the reduction's, ``near_misses`` (N,) the
    rows usable only as near misses (``pair.near_miss``), which the SDF's answers must pass the filters again."""

    pair: Pair
    contacts: ContactArrays
    mesh_normals: np.ndarray
    usable: np.ndarray
    closing: Closing
    reduced: bool = False
    near_misses: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


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
        self.settings = PairSettings(self.margin, method, self.coherence, self.reduce, self.refine)
        include = {self._geom_id(name) for name in include_geoms}
        self.bodies = {name: self._sdf_body(name, sdf, (int(contype), int(conaffinity))) for name, sdf in bodies.items()}
        surfaces = dict(surfaces or {})
        unknown = set(surfaces) - set(self.bodies)
        if unknown:
            raise InputError(f"surfaces names {sorted(unknown)}, which are not SDF bodies; SDF bodies: {sorted(self.bodies)}")
        self.pairs = self._pairs(include, surfaces)
        self._broad_phase = BroadPhase(model, self.pairs, self.margin)
        self._compile_kernels()
        self._contact_arrays, self._contacts = ContactArrays.empty(), None  # the last step's; as zoo.Contacts when asked
        self.contact_geoms = np.zeros((0, 2), dtype=np.int32)
        self.stats = StepStats(margin=self.margin)
        self._hooks = 0

    # -- building ----------------------------------------------------------------------------------

    def _compile_kernels(self) -> None:
        """A step's compiled kernels compiled (or loaded from numba's cache) now, at attach, not in the steps that first
        meet them: each NeuralSDF's few-point network, the mesh pairs' box test, the contact filter, the reduction
        and MuJoCo's rows, on one placeholder row (each pair's collider loads its own at its creation)."""
        for sdf_body in self.bodies.values():
            value_and_grad_numpy(sdf_body.sdf, np.zeros((1, 3)), query_dtype(sdf_body.sdf))
        for pair in self.pairs:
            if isinstance(pair, SurfacePair):
                pair.boxes_apart(np.eye(4), np.eye(4), 0.0)
        row, up = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
        usable_rows(row, np.zeros(1), up, up, np.zeros(3), np.zeros(3), -1.0, GRAZING_COS, SEPARATED_COS, 0.0)
        reduce_contacts(row, np.zeros(1), up, up, merge_tol=1e-3)
        contact_rows(ContactArrays(row, np.zeros(1), up, np.zeros(1, dtype=np.int64), row), np.zeros(1, dtype=np.int64), (0, 0))

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
                body = int(model.geom_bodyid[geom])
                if segment is not None:  # a sphere or a capsule: exact, no triangles
                    pairs.append(SegmentPair(sdf_body=sdf_body, body=body, geom=geom, params=params, frame="geom",
                                             radius=segment[0], half_length=segment[1], proxy=self._proxy_for(sdf_body),
                                             coherence=self.coherence))
                    continue
                surface = geom_surface(model, geom, self.tolerance)
                pairs.append(make_pair(sdf_body, body, geom, params, "geom", surface, self.settings,
                                       partial(self._proxy_for, sdf_body)))
            for other in sdf_bodies[index + 1:]:  # the earlier-named body's SDF meets the later one's surface
                if not may_touch(model, sdf_body.body, sdf_body.types, other.body, other.types, excluded):
                    continue
                params = mixed_parameters(model, own, geom_parameters(model, other.geom))
                surface = _mesh_pair(surfaces[other.name]) if other.name in surfaces else surface_mesh(other.sdf, CONTACT_RESOLUTION)
                pairs.append(make_pair(sdf_body, other.body, other.geom, params, "body", surface, self.settings,
                                       partial(self._proxy_for, sdf_body)))
        return pairs

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
        self._contact_arrays, self._contacts = ContactArrays.concat(collected), None
        self.contact_geoms = np.concatenate(geoms) if geoms else np.zeros((0, 2), dtype=np.int32)
        return added

    @property
    def contacts(self) -> zoo.Contacts:
        """The contacts that went into MuJoCo's solver at the last detection (world frame, float64), made
        ``zoo.Contacts`` when first asked: a step keeps them as arrays."""
        if self._contacts is None:
            self._contacts = self._contact_arrays.to_contacts()
        return self._contacts

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
            pair.reset()

    def collider_stats(self):
        """``zoo.collider.CoherenceStats`` summed over every pair's collider and call so far."""
        from ..collider import CoherenceStats

        total = CoherenceStats()
        for pair in self.pairs:
            if pair.stats is not None:
                total.add(pair.stats)
        return total

    # -- detection ---------------------------------------------------------------------------------

    def _detect(self, data):
        rows, collected, geoms = [], [], []
        stats = StepStats(margin=self.margin)
        deepest = 0.0
        near = self._broad_phase.near(data)
        if len(near.pairs):
            stats.margin = max(stats.margin, float(near.margins.max()))
            stats.speculative = bool(near.speculative.any())
        sdf_poses = {body: body_pose(data, body) for body in {pair.sdf_body.body for pair in near.pairs}}
        segments = segment_contacts([(pair, near.margins[i], near.surface_poses[i]) for i, pair in enumerate(near.pairs)
                                     if isinstance(pair, SegmentPair)], data)
        found = []  # PairContacts of the pairs with contacts MuJoCo can use
        for i, pair in enumerate(near.pairs):
            closing = near.closing(i)
            if isinstance(pair, SegmentPair):
                contacts, mesh_normals = segments.get(id(pair), (None, None))
            else:
                contacts, mesh_normals = pair.collide(sdf_poses[pair.sdf_body.body], near.surface_poses[i],
                                                      float(near.margins[i]), closing if pair.deferred else None)
            if contacts is None or len(contacts) == 0:
                continue
            usable = self._usable(pair, contacts, mesh_normals, closing)
            stats.raw_contacts += len(usable.contacts)
            found.append(self._reduced_on_proxy(usable))
        for found_pair in self.exact_answers(found):
            keep = found_pair.usable if found_pair.reduced else self._reduced(found_pair)
            if not len(keep):
                continue
            r = contact_rows(found_pair.contacts, keep, (found_pair.pair.sdf_body.geom, found_pair.pair.geom))
            rows.append((r, found_pair.pair.params))
            collected.append(found_pair.contacts.take(keep))
            geoms.append(r.geom)
            deepest = max(deepest, -float(r.dist.min()))
        stats.max_penetration = deepest
        return rows, collected, geoms, stats

    @staticmethod
    def _usable(pair: Pair, contacts, mesh_normals, closing: Closing) -> PairContacts:
        """The pair's contacts (at least one) with the rows MuJoCo can use (:func:`zoo.contact_filters.usable_rows`):
        facing their faces, and touching or closing within the step (the depths taken ``pair.depth_slack`` below),
        and apart from them the near misses (usable with the depths taken ``pair.near_miss`` further below)."""
        usable = usable_mask(contacts, mesh_normals, closing, pair.depth_slack)
        if not pair.near_miss:
            return PairContacts(pair, contacts, mesh_normals, np.flatnonzero(usable), closing)
        near = usable_mask(contacts, mesh_normals, closing, pair.depth_slack + pair.near_miss) & ~usable
        return PairContacts(pair, contacts, mesh_normals, np.flatnonzero(usable), closing, near_misses=np.flatnonzero(near))

    def _reduced_on_proxy(self, found: PairContacts) -> PairContacts:
        """A proxy's pair with ``reduce=True``: reduced on the proxy's depths, so that the NeuralSDF answers only the
        rows kept, its near misses apart (a manifold of their own, added: a near miss the SDF has separated costs no
        other contact its place). Other pairs, and every pair with ``reduce="exact"``, as they are (reduced on the
        SDF's depths)."""
        if self.reduce is not True or not found.pair.deferred:
            return found
        near = self._reduced(found, found.near_misses)
        return PairContacts(found.pair, found.contacts, found.mesh_normals, np.concatenate([self._reduced(found), near]),
                            found.closing, reduced=True, near_misses=near)

    def _reduced(self, found: PairContacts, rows: np.ndarray | None = None) -> np.ndarray:
        """The usable rows (R,) the reduction keeps (all of them with ``reduce=False``): a manifold per patch, on
        the depths ``found`` holds; of ``rows`` (default: the usable ones)."""
        keep = found.usable if rows is None else rows
        if not self.reduce or not len(keep):
            return keep
        c = found.contacts
        return keep[reduce_contacts(c.points[keep], c.depths[keep], c.normals[keep], found.mesh_normals[keep],
                                    merge_tol=found.pair.sdf_body.merge_distance)]

    @staticmethod
    def exact_answers(found: list[PairContacts]) -> list[PairContacts]:
        """``found`` with the SDF's own contacts in place of the proxy's where a pair's proxy chose them (at its usable
        rows, those whose SDF depth is beyond the margin dropped, and where the proxy's were filtered with a slack,
        the rest filtered again on the SDF's depths and normals): the pairs of a step on one SDF ask it together
        (:func:`zoo.proxy_collider.exact_contacts_together`)."""
        from ..proxy_collider import exact_arrays_together

        deferred = [i for i, f in enumerate(found) if len(f.usable) and f.pair.deferred]
        if not deferred:
            return found
        found = list(found)
        answers = exact_arrays_together([(found[i].pair.collider, found[i].usable) for i in deferred])
        for i, contacts in zip(deferred, answers):
            asked = found[i]
            answered = _kept_in_order(asked.contacts.triangles[asked.usable], contacts.triangles)
            mesh_normals = asked.mesh_normals[asked.usable[answered]]
            contacts.triangles = asked.pair.refined.surface_faces(contacts.triangles, contacts.bary)
            # a row the slack or a near miss let through may be separated on the SDF, and not close in time
            usable = np.arange(len(contacts))
            if asked.pair.depth_slack:
                usable = np.flatnonzero(usable_mask(contacts, mesh_normals, asked.closing, 0.0))
            elif len(asked.near_misses):
                near = np.zeros(len(asked.contacts), dtype=bool)
                near[asked.near_misses] = True
                recheck = near[asked.usable[answered]]
                usable = np.flatnonzero(~recheck | usable_mask(contacts, mesh_normals, asked.closing, 0.0))
            found[i] = PairContacts(asked.pair, contacts, mesh_normals, usable, asked.closing, reduced=asked.reduced)
        return found

# -- helpers ---------------------------------------------------------------------------------------


def usable_mask(contacts: ContactArrays, mesh_normals: np.ndarray, closing: Closing, slack: float) -> np.ndarray:
    """(K,) bool: the rows of ``contacts`` MuJoCo can use (:func:`zoo.contact_filters.usable_rows`), their depths
    known within ``slack`` (m)."""
    return usable_rows(contacts.points, contacts.depths, contacts.normals, mesh_normals, *closing, GRAZING_COS,
                       SEPARATED_COS, float(slack))


def _kept_in_order(asked: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the faces ``asked`` (N,) are among ``kept`` (K,), the SDF's answers to them, which keep
    their order less those beyond the margin (a call answers a face once): a walk along both, where a few rows a
    step cost ``np.isin``'s sort more than the walk."""
    out = np.zeros(len(asked), dtype=bool)
    kept = kept.tolist()
    j = 0
    for i, face in enumerate(asked.tolist()):
        if j < len(kept) and face == kept[j]:
            out[i] = True
            j += 1
    if j != len(kept):
        raise AssertionError("the SDF's answers are not the asked faces in their order")
    return out


def _mesh_pair(mesh) -> tuple[np.ndarray, np.ndarray]:
    from .model import mesh_arrays

    return mesh_arrays(mesh, "surface")




__all__ = ["attach", "World", "PairContacts", "StepStats"]
