"""The pairs a :class:`zoo.sim.world.World` collides at each step, one type per kind of surface the SDF meets.

* :class:`MeshPair`: a mesh refined once at attach (its flat regions merged, its large triangles split), answered by
  its ``zoo.CoherentCollider`` (on the SDF's proxy where it has one);
* :class:`NearMeshPair`: a mesh too large to refine once (a ground under a small SDF), clipped to the SDF's box and
  refined there at each step, answered by ``zoo.collide``;
* :class:`PlanePair`: an infinite plane, a patch of it laid under the SDF's box at each step;
* :class:`SegmentPair`: a sphere or capsule, answered in closed form along its axis (:func:`segment_contacts`, every
  such pair of an SDF body in one set of queries).

Each gives its contacts at a step as ``(ContactArrays in the world frame, their faces' world normals (K, 3))``, or
``(None, None)``; :func:`make_pair` builds the right one for a surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import torch
from numba import njit

import zoo

from ..collider import REUSE_FRACTION
from ..collision import ContactArrays
from ..contact_filters import GRAZING_COS, SEPARATED_COS
from ..geometry import face_normals, invert_pose, unit_rows
from ..sdf import query_dtype
from .contacts import MERGE_CELL, REFINE_CELLS, refine_near, refine_to_size, refined_pieces
from .flat_regions import FaceCover, merge_flat_regions
from .geoms import ContactParameters, body_pose, cube_corners, geom_pose
from .segments import SegmentAnswer, SegmentClearance, SegmentMinima, carried_minima, segment_minima

# contacts closer than this fraction of the SDF's smallest extent are one contact (FW-10 scatters the
# copies of a vertex's contact by up to a tenth of the edge)
MERGE_FRACTION = 0.05
# a mesh that refining once would grow past this many faces (a large ground mesh under a small SDF) is
# instead clipped and refined near the SDF at every step, from scratch (no temporal coherence for that pair)
PREREFINE_MAX_FACES = 200_000
# a face merged where the mesh is flat is at most this many of the reduction's cells wide: the reduction keeps one
# contact per cell and a face gives one at most, so wider faces leave a flat support too few contacts
FLAT_WIDTH_CELLS = 0.5
_ORIGIN = np.zeros(3)
_ORIGIN.setflags(write=False)  # shared by every pair whose surface frame is centred


@dataclass
class SdfBody:
    """A body of the model whose collision shape is an SDF (in the body's frame); its box's measures are computed once
    (a step asks them of every pair).

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

    @cached_property
    def reach(self) -> float:
        """The farthest a point of its box lies from the body's origin."""
        return float(np.linalg.norm(np.maximum(np.abs(self.lo), np.abs(self.hi))))

    @cached_property
    def max_edge(self) -> float:
        """The longest mesh edge refinement leaves near it (a thin plate: its side, not its thickness)."""
        return float(np.median(self.hi - self.lo)) / REFINE_CELLS

    @cached_property
    def merge_distance(self) -> float:
        """m: the reduction's ``merge_tol`` for the contacts of its pairs."""
        return MERGE_FRACTION * float((self.hi - self.lo).min())

    @cached_property
    def flat_width(self) -> float:
        """m: the widest face the flat-region pass makes for its pairs (``FLAT_WIDTH_CELLS`` cells)."""
        return FLAT_WIDTH_CELLS * MERGE_CELL * self.merge_distance

    @cached_property
    def box_centre(self) -> np.ndarray:
        """(3,) the centre of its box, body frame."""
        return (self.lo + self.hi) / 2

    @cached_property
    def box_radius(self) -> float:
        """The radius of the ball about ``box_centre`` that holds its box."""
        return float(np.linalg.norm(self.hi - self.lo)) / 2


@dataclass(frozen=True)
class PairSettings:
    """What a World's pairs are built with (:func:`zoo.sim.attach`'s arguments of the same names): ``margin`` (m),
    ``method`` (``zoo.collide``'s), ``coherence``, ``reduce`` (True, False or "exact"), ``refine``."""

    margin: float
    method: str
    coherence: bool
    reduce: bool | str
    refine: bool

    def method_for(self, sdf) -> str:
        from ..methods import method_for

        return method_for(self.method, sdf)


@dataclass(kw_only=True)
class Pair:
    """One SDF body and one thing it may touch; a subclass per kind of surface.

    Attributes:
        sdf_body: the :class:`SdfBody`.
        body: the other body's id; geom: the geom its contacts name.
        params: the pair's mixed contact parameters.
        frame: "geom" (the surface is in ``geom``'s frame) or "body" (in ``body``'s: another SDF body's surface).
    """

    kind = "pair"  # the subclass's name for it, in messages and results

    sdf_body: SdfBody
    body: int
    geom: int
    params: ContactParameters
    frame: str

    @property
    def bounding_radius(self) -> float:
        """Radius of a ball about the surface frame's ``centre`` that holds the surface."""
        raise NotImplementedError

    @property
    def centre(self) -> np.ndarray:
        """The centre (3,) of the surface's box, in its frame."""
        return _ORIGIN

    @property
    def deferred(self) -> bool:
        """Whether its contacts are the proxy's until :meth:`zoo.sim.world.World.exact_answers` asks the SDF."""
        return False

    @property
    def depth_slack(self) -> float:
        """m: how far below its depths the filters take the contacts ``collide`` returns (0: as they are). A deferred
        pair's are its proxy's, within the proxy's error bound of the SDF's; see :func:`proxy_slack`."""
        return 0.0

    @property
    def near_miss(self) -> float:
        """m: beyond ``depth_slack``, how far separated the filters keep a contact of ``collide`` that they would drop,
        for the SDF's answer to decide (0: none); see :func:`proxy_near_miss`."""
        return 0.0

    @property
    def stats(self):
        """``zoo.collider.CoherenceStats`` of its collider so far (None: it has none)."""
        return None

    def reset(self) -> None:
        """Forget what it carried from step to step."""

    def surface_pose(self, data) -> np.ndarray:
        """(4, 4) world-from-surface: the pose of the surface's frame at ``data``'s kinematics."""
        return geom_pose(data, self.geom) if self.frame == "geom" else body_pose(data, self.body)

    def apart(self, t_sdf: np.ndarray, t_other: np.ndarray, margin: float) -> bool:
        """Whether the balls around the two sides (poses ``t_sdf``, ``t_other`` (4, 4)) are more than ``margin``
        apart: no contact, nothing to query."""
        centre, radius = _sdf_ball(self.sdf_body, t_sdf)
        gap = centre - (t_other[:3, :3] @ self.centre + t_other[:3, 3])
        return math.sqrt(gap @ gap) - radius - self.bounding_radius > margin

    def collide(self, t_sdf: np.ndarray, t_other: np.ndarray, margin: float, closing=None):
        """Its contacts at the poses ``t_sdf``, ``t_other`` (4, 4) within ``margin``: (zoo.collision.ContactArrays in the world
        frame, their faces' world normals (K, 3)), or (None, None). ``closing``: the bodies' relative motion
        (:class:`zoo.contact_filters.Closing`), for a collider that keeps only what can close in time."""
        raise NotImplementedError


@dataclass(kw_only=True)
class PlanePair(Pair):
    """An infinite plane (z = 0 of its frame, facing +z): a patch of it under the SDF's box at each step, of cells
    within the refinement's edge (``refine``) or one cell over the box."""

    kind = "plane"
    settings: PairSettings

    @property
    def bounding_radius(self) -> float:
        return math.inf

    def apart(self, t_sdf, t_other, margin) -> bool:
        """Whether the SDF's ball lies more than ``margin`` above the plane."""
        centre, radius = _sdf_ball(self.sdf_body, t_sdf)
        return float(t_other[:3, 2] @ (centre - t_other[:3, 3])) - radius > margin

    def collide(self, t_sdf, t_plane, margin, closing=None):
        sdf_body = self.sdf_body
        plane_from_sdf = invert_pose(t_plane) @ t_sdf
        corners = cube_corners(sdf_body.lo, sdf_body.hi) @ plane_from_sdf[:3, :3].T + plane_from_sdf[:3, 3]
        if corners[:, 2].min() > margin:
            return None, None
        # cells whose diagonal is within the refinement's edge, so that zoo.collide answers them as they are
        if self.settings.refine:
            cell = sdf_body.max_edge / math.sqrt(2)
        else:
            cell = float(np.ptp(corners[:, :2], axis=0).max()) + 2 * margin
        lo = np.floor((corners[:, :2].min(axis=0) - margin) / cell).astype(np.int64)
        hi = np.ceil((corners[:, :2].max(axis=0) + margin) / cell).astype(np.int64)
        vertices, faces = _plane_patch(lo, hi, cell)
        sdf_from_plane = invert_pose(plane_from_sdf)
        local = vertices @ sdf_from_plane[:3, :3].T + sdf_from_plane[:3, 3]
        return _collide_in_sdf_frame(self, local, faces, np.arange(len(faces)), t_sdf, margin)


@dataclass(kw_only=True)
class SegmentPair(Pair):
    """A sphere or capsule: the points within ``radius`` of the segment from -``half_length`` to +``half_length``
    along z of its frame, answered in closed form (:func:`segment_contacts`); ``proxy``: the SDF's
    ``zoo.proxy.ProxySDF`` whose lower bound culls before the SDF is asked (None: none). With ``coherence``, a
    segment that moved less than ``REUSE_FRACTION`` of the margin relative to the SDF since the SDF answered it keeps
    that answer (``last``), moved to first order along its normals, as a mesh pair's faces do; and one the search
    found out of reach is passed over while the bound that showed it (``clearance``) still holds."""

    kind = "segment"
    radius: float
    half_length: float
    proxy: object = None
    coherence: bool = False
    last: SegmentAnswer | None = None
    clearance: SegmentClearance | None = None

    @property
    def bounding_radius(self) -> float:
        return self.half_length + self.radius

    def reset(self) -> None:
        self.last = self.clearance = None

    def collide(self, t_sdf, t_other, margin, closing=None):
        raise TypeError("a segment pair's contacts come from segment_contacts, every segment of its SDF body at once")


@dataclass(kw_only=True)
class SurfacePair(Pair):
    """A mesh: ``vertices`` (V, 3), ``faces`` (F, 3) the surface as given, in its frame; ``lo``, ``hi`` (3,) its box."""

    kind = "mesh"
    vertices: np.ndarray
    faces: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    settings: PairSettings

    @cached_property
    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.hi - self.lo)) / 2

    @cached_property
    def centre(self) -> np.ndarray:
        return (self.lo + self.hi) / 2

    def boxes_apart(self, t_sdf: np.ndarray, t_other: np.ndarray, margin: float) -> bool:
        """Whether the world boxes of the SDF (grown by ``margin``) and of the mesh do not overlap."""
        return _boxes_apart(t_sdf, self.sdf_body.lo, self.sdf_body.hi, float(margin), t_other, self.lo, self.hi)


@dataclass(kw_only=True)
class NearMeshPair(SurfacePair):
    """A mesh too large to refine once: clipped to the SDF's box grown by the margin and refined there at each
    step (no temporal coherence), answered by ``zoo.collide``."""

    def collide(self, t_sdf, t_other, margin, closing=None):
        if self.boxes_apart(t_sdf, t_other, margin):
            return None, None
        sdf_body = self.sdf_body
        sdf_from_mesh = invert_pose(t_sdf) @ t_other
        local = self.vertices @ sdf_from_mesh[:3, :3].T + sdf_from_mesh[:3, 3]
        max_edge = sdf_body.max_edge if self.settings.refine else math.inf
        local, faces, origin = refine_near(local, self.faces, sdf_body.lo - margin, sdf_body.hi + margin, max_edge)
        if len(faces) == 0:
            return None, None
        return _collide_in_sdf_frame(self, local, faces, origin, t_sdf, margin)


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

    def surface_faces(self, triangles: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(K,) int64 the surface's own face that holds each point ``bary`` (K, 3) of the faces ``triangles`` (K,)."""
        if self.cover.one_each:
            return self.cover.members[triangles]
        points = np.einsum("kv,kvc->kc", bary, self.vertices[self.faces[triangles]])
        return np.asarray(self.cover.input_faces(triangles, points), dtype=np.int64)


@dataclass(kw_only=True)
class MeshPair(SurfacePair):
    """A mesh refined once at attach (``refined``, what the collider answers on) and collided along the trajectory
    by ``collider``, a ``zoo.CoherentCollider`` (on the SDF's proxy where it has one)."""

    refined: RefinedMesh
    collider: object

    @property
    def deferred(self) -> bool:
        return bool(getattr(self.collider, "deferred", False))

    @property
    def depth_slack(self) -> float:
        return proxy_slack(self.settings.reduce, self.collider.proxy) if self.deferred else 0.0

    @property
    def near_miss(self) -> float:
        return proxy_near_miss(self.settings.reduce, self.collider.proxy) if self.deferred else 0.0

    @property
    def stats(self):
        return self.collider.stats

    def reset(self) -> None:
        self.collider.reset()

    def collide(self, t_sdf, t_other, margin, closing=None):
        if self.boxes_apart(t_sdf, t_other, margin):
            return None, None
        if closing is not None and getattr(self.collider, "thin", None) is not None:
            self.collider.thin = replace(self.collider.thin, closing=closing)
        contacts = self.collider.collide_arrays(t_sdf, t_other, margin)
        mesh_normals = self.refined.normals[contacts.triangles] @ t_other[:3, :3].T  # (K, 3)
        if not self.deferred:  # a deferred pair's are named when the SDF answers them
            contacts.triangles = self.refined.surface_faces(contacts.triangles, contacts.bary)
        return contacts, mesh_normals


def proxy_slack(reduce: bool | str, proxy) -> float:
    """m: how far below a proxy's depths the contact filters take them, for a World built with ``reduce``: the
    proxy's error bound where the SDF's depths decide what is kept (``"exact"`` or False: the SDF answers every usable
    row before the reduction, and its answers are filtered again without slack); 0 where the reduction picks on the
    proxy's depths (True, the default): a row let through by the slack and picked for a patch's manifold would be
    dropped once the SDF answers it, and the patch would lose its point."""
    return proxy.error_bound if reduce is not True else 0.0


def proxy_near_miss(reduce: bool | str, proxy) -> float:
    """m: where the reduction picks on a proxy's depths (``reduce=True``, the default), how far separated a contact the
    filters would drop (separated on the proxy, not closing within the step) is kept apart, a near miss: the proxy's
    p99 error (``proxy.error``), within which the SDF may have it touching. Near misses are thinned and reduced apart
    from the contacts usable on the proxy's depths, so that they take no point from their manifolds, and the SDF's
    answers to them are filtered again (:meth:`zoo.sim.world.World.exact_answers`). Not the error bound: within it
    (twice the largest error, several times the p99 on a thread) many more rows pass than the SDF has touching, each
    one more answer to ask for. 0 elsewhere (the slack, :func:`proxy_slack`, does it there)."""
    return float(proxy.error.get("p99", 0.0)) if reduce is True else 0.0


def make_pair(sdf_body: SdfBody, body: int, geom: int, params: ContactParameters, frame: str, surface,
              settings: PairSettings, proxy_for=lambda: None) -> Pair:
    """The pair of ``sdf_body`` with a surface (in ``frame``'s frame): ``surface`` None for a plane, else (vertices
    (V, 3), faces (F, 3)). A mesh is refined once where that stays under ``PREREFINE_MAX_FACES`` faces (flat regions
    merged first, for a model's meshes), its collider searching on the proxy ``proxy_for()`` gives (a
    ``zoo.proxy.ProxySDF``, or None; asked only there, as a proxy may be baked when first asked for)."""
    common = dict(sdf_body=sdf_body, body=body, geom=geom, params=params, frame=frame)
    if surface is None:
        return PlanePair(**common, settings=settings)
    vertices, faces = surface
    box = dict(vertices=vertices, faces=faces, lo=vertices.min(axis=0), hi=vertices.max(axis=0), settings=settings)
    max_edge = sdf_body.max_edge if settings.refine else math.inf
    # the flat pass is for a model's meshes: an SDF body's surface is made at the resolution contacts need, and
    # a mesh larger than this is refined near the SDF at every step
    flat = settings.refine and frame == "geom" and len(faces) <= PREREFINE_MAX_FACES
    merged, cover = (merge_flat_regions(vertices, faces, sdf_body.flat_width, refined_pieces(max_edge))
                     if flat else (faces, None))
    refined = refine_to_size(vertices, merged, max_edge, PREREFINE_MAX_FACES)
    if refined is None:
        return NearMeshPair(**common, **box)
    refined_vertices, refined_faces, origin = refined
    cover = (cover or FaceCover.identity(vertices, faces)).take(origin, refined_vertices[refined_faces])
    mesh = (torch.as_tensor(refined_vertices, dtype=torch.float32), torch.as_tensor(refined_faces))
    collider = zoo.CoherentCollider(sdf_body.sdf, mesh, margin=settings.margin, method=settings.method_for(sdf_body.sdf),
                                    coherence=settings.coherence, proxy=proxy_for(), deferred=True)
    if settings.reduce and collider.deferred:  # only what the reduction can keep comes back
        from ..proxy_collider import Thinning

        band = 2 * collider.proxy.error_bound if settings.reduce == "exact" else 0.0
        collider.thin = Thinning(MERGE_CELL * sdf_body.merge_distance, GRAZING_COS, SEPARATED_COS, band=band,
                                 slack=proxy_slack(settings.reduce, collider.proxy),
                                 near_miss=proxy_near_miss(settings.reduce, collider.proxy))
    refined_mesh = RefinedMesh(refined_vertices, refined_faces, cover, face_normals(refined_vertices[refined_faces]))
    return MeshPair(**common, **box, refined=refined_mesh, collider=collider)


def segment_contacts(near: list[tuple[SegmentPair, float, np.ndarray]], data) -> dict:
    """Spheres' and capsules' contacts in closed form, every such pair of a step together (one set of queries per
    SDF body): {id(pair): (contacts in the world frame, their normals as the faces' normals)} for the pairs of
    ``near`` ((pair, its margin, its geom's pose (4, 4)) each) that touch or come within their margin. A pair's contacts are its axis
    segment's points of least f (:func:`zoo.sim.segments.segment_minima`), each at depth f - radius along the SDF's
    normal there."""
    found = {}
    by_body: dict[str, list] = {}
    for pair, margin, t_geom in near:
        by_body.setdefault(pair.sdf_body.name, []).append((pair, margin, t_geom))
    for pairs in by_body.values():
        sdf_body, proxy = pairs[0][0].sdf_body, pairs[0][0].proxy
        t_sdf = body_pose(data, sdf_body.body)
        local = invert_pose(t_sdf) @ np.stack([t_geom for _, _, t_geom in pairs])  # (P, 4, 4): each geom in the SDF's frame
        axis = local[:, :3, 2] * np.array([pair.half_length for pair, _, _ in pairs])[:, None]
        radii = np.array([pair.radius for pair, _, _ in pairs])
        margins = np.array([margin for _, margin, _ in pairs])
        minima = _segment_answers(pairs, local[:, :3, 3] - axis, local[:, :3, 3] + axis, radii + margins, proxy)
        rows = np.flatnonzero(minima.values - radii[minima.owner] <= margins[minima.owner])
        if not len(rows):
            continue
        rows = rows[np.argsort(minima.owner[rows], kind="stable")]  # each pair's rows together, in their order
        owner, normals = minima.owner[rows], unit_rows(minima.grads[rows])
        depths = minima.values[rows] - radii[owner]
        points = minima.points[rows] - radii[owner][:, None] * normals  # each point deepest in the SDF
        rotation, origin = t_sdf[:3, :3], t_sdf[:3, 3]
        points, normals = points @ rotation.T + origin, normals @ rotation.T
        indices, starts = np.unique(owner, return_index=True)
        for index, start, stop in zip(indices, starts, [*starts[1:], len(rows)]):
            k = stop - start
            found[id(pairs[index][0])] = (ContactArrays(points[start:stop], depths[start:stop], normals[start:stop],
                                                        np.full(k, -1, dtype=np.int64), np.zeros((k, 3)), n_triangles=0,
                                                        n_candidates=k, method="closed-form"), normals[start:stop])
    return found


def _segment_answers(pairs: list, a: np.ndarray, b: np.ndarray, reach: np.ndarray, proxy) -> SegmentMinima:
    """The points of least f along the pairs' segments (from ``a`` to ``b`` (P, 3), the SDF's frame): with
    :class:`SegmentPair`'s ``coherence``, a segment whose clearance still holds passed over and each kept answer that
    still holds carried; the others searched together (:func:`zoo.sim.segments.segment_minima`), what the search found
    kept for the next steps."""
    sdf = pairs[0][0].sdf_body.sdf
    kept, asked = [], []
    ends_a, ends_b, reaches = a.tolist(), b.tolist(), reach.tolist()  # Python floats: a pair's test is a few of them
    for index, (pair, margin, _) in enumerate(pairs):
        if pair.coherence and pair.clearance is not None and pair.clearance.holds(ends_a[index], ends_b[index], reaches[index]):
            continue  # out of reach still: no contact, no query
        last = pair.last
        reuse = last is not None and pair.coherence and last.moved(ends_a[index], ends_b[index]) <= REUSE_FRACTION * margin
        (kept if reuse else asked).append(index)
    carried = carried_minima([pairs[i][0].last for i in kept], a[kept], b[kept], np.asarray(kept, dtype=np.int64))
    if not asked:
        return carried
    dtype = query_dtype(sdf)
    lower_bound = None if proxy is None else (lambda p: proxy.read_numpy(p)[0] - proxy.error_bound)
    a, b = a[asked], b[asked]
    search = segment_minima(sdf, a, b, reach[asked], dtype, lower_bound)
    found = search.minima
    found.owner = np.asarray(asked, dtype=np.int64)[found.owner]
    for j, index in enumerate(asked):
        pair = pairs[index][0]
        rows = np.flatnonzero(found.owner == index)
        pair.last = (SegmentAnswer(ends_a[index], ends_b[index], found.params[rows], found.values[rows], found.grads[rows])
                     if pair.coherence and rows.size else None)
        out_of_reach = pair.coherence and search.floors[j] > reach[index]
        pair.clearance = SegmentClearance(ends_a[index], ends_b[index], float(search.floors[j])) if out_of_reach else None
    return SegmentMinima.concat([carried, found])


def _collide_in_sdf_frame(pair: Pair, local: np.ndarray, faces: np.ndarray, origin: np.ndarray, t_sdf: np.ndarray,
                          margin: float):
    """``zoo.collide`` of the pair's SDF with a mesh given in the SDF's frame (``local`` (V, 3), ``faces`` (F, 3)):
    (contacts in the world frame, their faces' world normals (K, 3)); triangles index ``origin``'s faces."""
    used, inverse = np.unique(faces, return_inverse=True)
    mesh = (torch.as_tensor(local[used], dtype=torch.float32), torch.as_tensor(inverse.reshape(-1, 3)))
    world = torch.as_tensor(t_sdf, dtype=torch.float32)  # the mesh is already in the SDF's frame
    contacts = zoo.collide(pair.sdf_body.sdf, mesh, sdf_pose=world, mesh_pose=world, margin=margin,
                           method=pair.settings.method_for(pair.sdf_body.sdf))
    arrays = ContactArrays.from_contacts(contacts)
    mesh_normals = face_normals(local[faces[arrays.triangles]]) @ t_sdf[:3, :3].T  # (K, 3)
    arrays.triangles = origin[arrays.triangles]
    return arrays, mesh_normals


def _sdf_ball(sdf_body: SdfBody, t_sdf: np.ndarray) -> tuple[np.ndarray, float]:
    """The world centre (3,) and radius of the ball about the SDF's box at pose ``t_sdf``."""
    return t_sdf[:3, :3] @ sdf_body.box_centre + t_sdf[:3, 3], sdf_body.box_radius


def _plane_patch(lo: np.ndarray, hi: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
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


@njit(cache=True)
def _boxes_apart(pose_a, lo_a, hi_a, grow, pose_b, lo_b, hi_b):
    """Whether the world boxes (axis-aligned) of the box [lo_a - grow, hi_a + grow] under ``pose_a`` (4, 4) and of
    [lo_b, hi_b] (3,) under ``pose_b`` do not overlap: one compiled call, where numpy's would be a dozen."""
    for axis in range(3):
        centre_a, half_a = pose_a[axis, 3], 0.0
        centre_b, half_b = pose_b[axis, 3], 0.0
        for j in range(3):
            centre_a += pose_a[axis, j] * (lo_a[j] + hi_a[j]) / 2
            half_a += abs(pose_a[axis, j]) * ((hi_a[j] - lo_a[j]) / 2 + grow)
            centre_b += pose_b[axis, j] * (lo_b[j] + hi_b[j]) / 2
            half_b += abs(pose_b[axis, j]) * (hi_b[j] - lo_b[j]) / 2
        if centre_a + half_a < centre_b - half_b or centre_b + half_b < centre_a - half_a:
            return True
    return False


__all__ = ["SdfBody", "PairSettings", "Pair", "PlanePair", "SegmentPair", "SurfacePair", "NearMeshPair", "MeshPair", "RefinedMesh",
           "make_pair", "segment_contacts"]
