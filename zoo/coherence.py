"""Temporal coherence for ``zoo.collide``: one body pair collided step after step, reusing the last steps.

``zoo.collide`` starts every call from scratch. Along a trajectory the relative pose changes little
between steps, so :class:`CoherentCollider` keeps, for one (SDF, mesh) pair, what it learnt before,
all in the SDF's frame (where the SDF is queried):

* per mesh vertex, a lower bound of f at an anchor point (f itself where the vertex was evaluated,
  else a cell bound of the broad phase). With L the SDF's Lipschitz bound (:func:`motion_lipschitz`),
  at the vertex's new position p, f(p) >= bound - L |p - anchor|, whatever the motion. A triangle's
  lower bound then follows from its vertices' bounds (:func:`zoo.bounds.cell_lower_bounds`, valid for
  any lower bounds at the vertices), and a triangle proven to stay above the margin is skipped with no
  query. Anchors stay put until a vertex is evaluated again, so a triangle cleared with a lot of slack
  is skipped for many steps, until its vertices' displacement since their anchor eats the slack.
  Rounding slack is subtracted as in :mod:`zoo.collision`;
* the triangles that remain get fresh values at their vertices (cell bounds first when there are
  many, as in collide), and every face is tested on the best bounds known: for a 1-Lipschitz SDF the
  candidates are exactly collide's (every bound used is a lower bound of the vertex value collide's own
  cull reads, and the cull is monotone in the values);
* per triangle, its last answer: barycentrics, value, normal, and where the triangle was then. A
  triangle whose answer, less the Lipschitz bound times the farthest its points moved since, stays
  above the margin is skipped with no query (the answer is taken as the triangle's minimum, as
  collide takes it). One that moved less than ``reuse_distance`` (a fifth of the margin) keeps its
  answer, its depth moved to first order along its normal (a persistent contact, as physics engines
  keep them): a body at rest costs no query. One that moved less than ``WARM_REACH`` of its longest
  edge is warm-started there (``warm_start``), whatever the method: the vertex test on its lowest
  vertex (a KKT vertex is the answer, with its gradient as the normal), else :func:`warm_step` (a
  line search along the steepest descent inside the triangle) and the lower of that and the lowest
  vertex. Where the warm answer's Frank-Wolfe gap exceeds ``RETRY_GAP`` the method solves the row from
  scratch too, and the lower answer is kept. New candidates take collide's own narrow phase.

The contacts have collide's fields and meaning (world frame, depths are signed distances, triangles
index the mesh's faces, rows ordered by triangle). A depth only differs from collide's by the solvers'
own error, and a warm one is the lower; a kept answer is as good as the answer it keeps, so on an SDF
with kinks (a box's edges), where the method's answer jumps between nearby poses, pass
``reuse_distance=0`` (tests/test_coherence.py holds them along trajectories; docs/coherence.md measures
the savings). ``coherence=False`` calls ``zoo.collide``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from .bounds import cell_lower_bounds, rounding_slack
from .collider import REUSE_FRACTION, CoherenceStats, motion_lipschitz, moved_along_normal
from .collision import (
    CLUSTER_CULL_MIN,
    ContactArrays,
    Contacts,
    cell_bounds,
    collide,
    contact_normals,
    empty_contacts,
    faces_near_bounds,
    mesh_tensors,
    solve_candidates,
    voxel_of,
)
from .errors import InputError
from .geometry import bary_to_points, edge_lengths, invert_pose, transform_points, transform_vectors
from .methods import check_supports, iterations
from .sdf import check_sdf
from .simplex import descent_segment, frank_wolfe_gap
from .solvers import frank_wolfe, line_search_step
from .validation import as_pose, int_at_least, non_negative_float, positive_float

COLD, WARM, KEPT = 0, 1, 2  # how a candidate is answered: from scratch, from its last answer, or that answer kept
# A persisting candidate is warm-started only while its vertices moved less than this fraction of its
# longest edge since the last step: farther, its last answer says little about the new minimum.
WARM_REACH = 0.5
# Value queries refining each line search of a warm step. One: a second sample lands next to the first once
# the search has converged, and the interpolation through two nearly equal samples can throw the step far
# off (zoo.solvers._interpolation_step).
WARM_LINE_STEPS = 1
BOUNDARY = 1e-6  # barycentric coordinates this small put a warm start on its triangle's boundary
# A warm step that stops on an edge from inside the face takes this many more (an exit point is rarely the
# edge's minimum).
WARM_EDGE_STEPS = 1
# A warm answer whose Frank-Wolfe gap (SDF units) exceeds this is solved from scratch too. Warm answers on smooth
# SDFs stay far below it; on a box, whose SDF has kinks where a line search stalls, many are above.
RETRY_GAP = 1e-4
# When some kept answer is due to be solved again, those that drifted more than this fraction of ``reuse_distance``
# are solved with it: a round of SDF queries costs about as much for a few faces as for a few hundred (each query
# has a fixed cost), and faces solved together fall due together, so most steps need no round at all.
REFRESH_FRACTION = 0.5
# Poses kept for the lasting proofs (one per call): when full, the proofs made at the older half are dropped (those faces
# go back to the exact tests), so the history and its per-call work stay bounded however long the trajectory.
POSE_HISTORY = 64


def _values_at(sdf, tri: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """``sdf`` at the points ``bary`` (N, 3) of the triangles (N, 3, 3): (N,)."""
    if not tri.shape[0]:
        return tri.new_zeros((0,))
    return torch.as_tensor(sdf(bary_to_points(tri, bary))).reshape(-1).to(tri)


def _values(sdf, tri: torch.Tensor) -> torch.Tensor:
    """``sdf`` at the vertices of the triangles (W, 3, 3): (W, 3)."""
    return torch.as_tensor(sdf(tri.reshape(-1, 3))).reshape(tri.shape[:2]).to(tri)


def _gradients_at(sdf, local: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Gradients (W, 3) of ``sdf`` at the mesh vertices ``vertices`` (W,) of ``local`` (V, 3), one query per distinct vertex."""
    distinct, inverse = torch.unique(vertices, return_inverse=True)
    return _value_and_grad(sdf, local[distinct])[1][inverse]


def warm_step(sdf, tri: torch.Tensor, start: torch.Tensor, at_start: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Descent from a warm start on each triangle (W, 3, 3): -> (bary (W, 3), f (W,), grad f (W, 3) there).
    ``at_start``: f (W,) and grad f (W, 3) at the start, where the caller has them (else they are queried).

    A value-and-gradient query at the start, then a line search along the steepest descent inside the
    triangle (:func:`_tangent_step`: towards a minimum inside the face, along the edge the point lies on, or
    to the boundary) and a value-and-gradient query at its end (the depth and the normal), kept where lower.
    An end that stopped on an edge from inside the face takes one more such step, along it (``WARM_EDGE_STEPS``).
    """
    bary = start.clone()
    f, g = _value_and_grad(sdf, bary_to_points(tri, bary)) if at_start is None else (at_start[0].clone(), at_start[1].clone())
    rows = torch.arange(tri.shape[0], device=tri.device)
    for _ in range(1 + WARM_EDGE_STEPS):
        end = _tangent_step(sdf, tri[rows], bary[rows], f[rows], g[rows])
        moved = (end != bary[rows]).any(dim=-1)
        rows, end = rows[moved], end[moved]
        if not rows.numel():
            break
        f1, g1 = _value_and_grad(sdf, bary_to_points(tri[rows], end))
        lower = f1 < f[rows]
        rows, end, f1, g1 = rows[lower], end[lower], f1[lower], g1[lower]
        # stopped on an edge it was not on: the exit point is rarely the edge's minimum
        reached = ((end <= BOUNDARY).sum(dim=-1) == 1) & ((bary[rows] <= BOUNDARY).sum(dim=-1) == 0)
        bary[rows], f[rows], g[rows] = end, f1, g1
        rows = rows[reached]
    return bary, f, g


def screen_bound(tri: torch.Tensor, bary: torch.Tensor, f: torch.Tensor, grads: torch.Tensor,
                 vertex_values: torch.Tensor) -> torch.Tensor:
    """A lower bound (W,) of f on each triangle (W, 3, 3) from one value ``f`` (W,) and gradient ``grads`` (W, 3) at the
    points ``bary`` (W, 3) and the values at the vertices (W, 3): the lower of the linearisation's minimum over the
    triangle (f less its Frank-Wolfe gap, the bound where f is convex) and the lowest vertex (the minimum where f is
    concave, as a distance is across a medial ridge). Neither alone holds for both; NaN values give NaN."""
    return torch.minimum(f - frank_wolfe_gap(tri, bary, grads), vertex_values.amin(dim=-1))


def _value_and_grad(sdf, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``sdf``'s values (N,) and gradients (N, 3) at ``points`` (N, 3), in their dtype."""
    f, g = sdf.value_and_grad(points)
    return torch.as_tensor(f).reshape(-1).to(points), torch.as_tensor(g).to(points)


def _tangent_step(sdf, tri: torch.Tensor, bary: torch.Tensor, f0: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """A line search along the steepest descent of f inside each triangle's plane from ``bary`` (W, 3) (f0 (W,)
    and g (W, 3) there), as far as the triangle reaches: -> bary (W, 3).

    The direction is :func:`zoo.simplex.descent_segment`'s: -g projected onto the plane; where that would leave the
    triangle across the edge the point lies on, onto that edge; where that goes nowhere, towards Frank-Wolfe's vertex.
    The search is :func:`zoo.solvers.line_search_step` on
    the segment from the point to where the direction leaves the triangle (one value query there). Coordinates
    within ``BOUNDARY`` of 0 count as on the boundary (they are set to 0), or rounding would hold a point
    that lies on an edge to a step of nothing."""
    bary = torch.where(bary <= BOUNDARY, torch.zeros_like(bary), bary)
    bary = bary / bary.sum(dim=-1, keepdim=True)
    direction, reach = descent_segment(tri, bary, g, boundary=0.0)  # (W, 3) barycentric, rows sum to 0; (W,)
    rows = (reach * direction.abs().amax(dim=-1) > 0).nonzero().squeeze(-1)
    if not rows.numel():
        return bary
    p = bary_to_points(tri[rows], bary[rows])
    end = bary_to_points(tri[rows], bary[rows] + reach[rows, None] * direction[rows])
    f_end = torch.as_tensor(sdf(end)).reshape(-1).to(f0)
    segment = torch.stack([p, end, end], dim=1)  # the search runs from its first corner towards the others
    first = F.one_hot(torch.zeros_like(rows), 3).to(bary)
    t = 1 - line_search_step(sdf, segment, first, torch.stack([f0[rows], f_end, f_end], -1), WARM_LINE_STEPS,
                             start=(f0[rows], g[rows]))[:, 0]
    out = bary.clone()
    out[rows] = (bary[rows] + (t * reach[rows]).unsqueeze(-1) * direction[rows]).clamp_min(0)
    return out / out.sum(dim=-1, keepdim=True)


class _CountingSDF:
    """An SDF, counting the points asked for (values and gradients alike: what the cell bounds, the proxy's survivors cost)."""

    def __init__(self, sdf):
        self.sdf, self.queries, self.bounds = sdf, 0, sdf.bounds

    def __call__(self, points: torch.Tensor):
        self.queries += int(points.shape[0])
        return self.sdf(points)

    def value_and_grad(self, points: torch.Tensor):
        self.queries += int(points.shape[0])
        return self.sdf.value_and_grad(points)


@dataclass
class VertexBounds:
    """What :class:`CoherentCollider` carries per mesh vertex (V of them): ``anchor`` (V, 3) where its bound holds (SDF
    frame), ``lower`` (V,) the bound of f there, ``exact`` (V,) bool whether the bound is f itself."""

    anchor: torch.Tensor
    lower: torch.Tensor
    exact: torch.Tensor

    @classmethod
    def empty(cls, vertices: torch.Tensor) -> VertexBounds:
        v = vertices
        return cls(torch.zeros_like(v), torch.full(v.shape[:1], -torch.inf, dtype=v.dtype, device=v.device),
                   torch.zeros(v.shape[:1], dtype=torch.bool, device=v.device))

    def known_at(self, vertices: torch.Tensor, here: torch.Tensor) -> torch.Tensor:
        """(K,) bool: f is known exactly at the vertices ``vertices`` (K,) (or ``slice(None)``: all) where they are now,
        ``here`` (K, 3)."""
        return self.exact[vertices] & (self.anchor[vertices] == here).all(dim=-1)

    def hold(self, vertices: torch.Tensor, here: torch.Tensor, lower: torch.Tensor, exact: bool) -> None:
        """The vertices ``vertices`` (K,) now hold the bound ``lower`` (K,) at ``here`` (K, 3) (f itself: ``exact``)."""
        self.anchor[vertices], self.lower[vertices], self.exact[vertices] = here, lower, exact


@dataclass
class FaceAnswers:
    """The last answer per face (F of them): ``bary`` (F, 3), ``value`` (F,) f there (-inf: none), ``at`` (F, 3, 3) the
    face in the SDF's frame when it was answered, ``normal`` (F, 3) the unit gradient there (NaN: not a contact)."""

    bary: torch.Tensor
    value: torch.Tensor
    at: torch.Tensor
    normal: torch.Tensor

    @classmethod
    def empty(cls, vertices: torch.Tensor, n_faces: int) -> FaceAnswers:
        v = vertices
        return cls(v.new_zeros((n_faces, 3)), torch.full((n_faces,), -torch.inf, dtype=v.dtype, device=v.device),
                   v.new_zeros((n_faces, 3, 3)), torch.full((n_faces, 3), torch.nan, dtype=v.dtype, device=v.device))


@dataclass
class ClearedFaces:
    """Faces proven clear of the margin (F of them): ``bound`` (F,) a lower bound of f on the face (-inf: none),
    proven at entry ``pose`` (F,) of ``poses`` (H, 3, 4) (the SDF-from-mesh transforms of the calls so far), with the
    face's centroid then at ``centroid`` (F, 3) (SDF frame)."""

    bound: torch.Tensor
    pose: torch.Tensor
    centroid: torch.Tensor
    poses: torch.Tensor

    @classmethod
    def empty(cls, vertices: torch.Tensor, n_faces: int) -> ClearedFaces:
        d = vertices.device
        return cls(torch.full((n_faces,), -torch.inf, dtype=torch.float64, device=d),
                   torch.zeros(n_faces, dtype=torch.int64, device=d),
                   torch.zeros((n_faces, 3), dtype=torch.float64, device=d), torch.zeros((0, 3, 4), dtype=torch.float64, device=d))


class CoherentCollider:
    """``zoo.collide`` for one SDF-mesh pair along a trajectory, reusing what the last steps proved.

    Args:
        sdf: an SDF protocol object (as for ``zoo.collide``); it must not change between calls
            (call :meth:`reset` if it does).
        mesh: a ``trimesh.Trimesh`` or a ``(vertices (V, 3), faces (F, 3))`` pair, fixed for the pair's life.
        margin, method, iters, refine, voxel_resolution, polish: as for ``zoo.collide``.
        coherence: False makes every call plain ``zoo.collide`` (nothing is kept).
        warm_start: warm-start persisting candidates from their last barycentrics (see the module's
            docstring); False keeps the skipping only, and the contacts are collide's.
        lipschitz: the bound a vertex's carried bound decays with as it moves (default :func:`motion_lipschitz`).
        reuse_distance: m; a candidate whose points moved less than this relative to the SDF since it was solved
            keeps its answer, its depth updated along its normal; default ``REUSE_FRACTION`` of the margin; 0 solves
            every candidate at every step. Applies with ``warm_start`` only.
        proxy: None (default) or False: every query is the SDF's. True: the SDF's cached narrow-band proxy
            (:func:`zoo.proxy.cached_proxy` at this margin, baked on first use), or a :class:`zoo.proxy.ProxySDF`. The
            culling, the screens and the search (Frank-Wolfe, ``iters``, for the faces new to the candidates) then
            run on the proxy at the margin plus its ``error_bound``, and the SDF itself answers only the faces whose
            proxy minimum comes that close: one value and gradient at the proxy's minimiser, a warm step from there
            where its Frank-Wolfe gap exceeds ``POLISH_GAP_FRACTION`` of the margin, and the kept answers of faces
            that moved less than ``reuse_distance``; a face whose proxy minimiser lies out of the proxy's band is
            solved from scratch by ``method`` on the SDF. Every contact's point, depth and normal are the SDF's.
            Needs ``coherence``; not with "voxel-fw".
        deferred: with ``proxy``, a call returns the proxy's contacts (the faces within the margin plus the error bound,
            the proxy's points, depths and normals), and :meth:`exact_contacts` gives the SDF's own for the rows the
            caller keeps (a simulation keeps a few per patch: ``zoo.sim`` asks the SDF for those only).

    Call it with the poses of each step: ``contacts = collider(sdf_pose, mesh_pose)`` (4x4 world-from-object,
    None is the identity). ``stats`` sums :class:`CoherenceStats` over all calls, ``last_stats`` holds the
    last call's, and ``last_candidates`` (C,) the faces the last call solved.
    """

    def __init__(self, sdf, mesh, margin: float = 1e-3, method: str = "fw", *, coherence: bool = True,
                 warm_start: bool = True, iters: int | None = None,
                 refine: int = 0, voxel_resolution=256, polish: bool = True, lipschitz: float | None = None,
                 reuse_distance: float | None = None, proxy=None, deferred: bool = False):
        check_sdf(sdf)
        self.sdf = sdf
        self.method = check_supports(method, sdf).name
        self.margin = non_negative_float(margin, "margin")
        self.iters = iterations(self.method, iters)
        self.refine = int_at_least(refine, "refine")
        if not polish and self.method != "amortized":
            raise InputError(f'polish=False applies to method="amortized" only (got method={method!r}); drop it')
        self.polish = bool(polish)
        self.voxel_resolution = voxel_resolution
        self.coherence = bool(coherence)
        self.warm_start = bool(warm_start)
        self.lipschitz = motion_lipschitz(sdf) if lipschitz is None else positive_float(lipschitz, "lipschitz")
        reuse = REUSE_FRACTION * self.margin if reuse_distance is None else non_negative_float(reuse_distance, "reuse_distance")
        self.reuse_distance = reuse if self.warm_start else 0.0
        self.vertices, self.faces = mesh_tensors(mesh)
        self._on_proxy = self._proxy_collider(proxy, deferred)
        self.proxy = None if self._on_proxy is None else self._on_proxy.proxy
        self.deferred = self._on_proxy is not None and self._on_proxy.deferred
        corners = self.vertices[self.faces].to(torch.float64)  # (F, 3, 3), the mesh's frame
        self._centroid = corners.mean(dim=1)  # (F, 3)
        self._face_radius = (corners - self._centroid.unsqueeze(1)).norm(dim=-1).amax(dim=-1)  # (F,)
        self.stats = CoherenceStats() if self._on_proxy is None else self._on_proxy.stats
        self.last_stats = CoherenceStats()
        self._last_candidates = torch.zeros(0, dtype=torch.int64, device=self.vertices.device)
        self.reset()

    def reset(self) -> None:
        """Forget everything carried over (the next call works from scratch); ``stats`` are kept."""
        v, f = self.vertices, self.faces
        self._vertex = VertexBounds.empty(v)
        self._answers = FaceAnswers.empty(v, f.shape[0])
        self._cleared = ClearedFaces.empty(v, f.shape[0])
        if self._on_proxy is not None:
            self._on_proxy.reset()

    @property
    def last_candidates(self) -> torch.Tensor:
        """(C,) int64: the faces the last call solved (on a proxy, those it kept as its proxy contacts)."""
        return self._last_candidates if self._on_proxy is None else self._on_proxy.last_candidates

    @property
    def proxy_collider(self):
        """The :class:`zoo.proxy_collider.ProxyCollider` this collider runs on, or None without a proxy."""
        return self._on_proxy

    @property
    def thin(self):
        """The :class:`zoo.proxy_collider.Thinning` of the proxy collider this collider runs on, or None."""
        return None if self._on_proxy is None else self._on_proxy.thin

    @thin.setter
    def thin(self, thin) -> None:
        if self._on_proxy is None:
            raise InputError("thin= needs a proxy (proxy=, deferred=True): without one, every contact is the SDF's")
        self._on_proxy.thin = thin

    def _proxy_collider(self, proxy, deferred: bool):
        """The :class:`zoo.proxy_collider.ProxyCollider` this collider runs on (see the class's ``proxy`` argument), or
        None without a proxy."""
        if proxy is None or proxy is False:
            return None
        if not self.coherence:
            raise InputError("proxy= needs coherence: coherence=False is the from-scratch reference, which queries the SDF only")
        if self.method == "voxel-fw":
            raise InputError('proxy= does not apply to method="voxel-fw", which solves on its own grid; use "fw" or "amortized"')
        from .proxy_collider import ProxyCollider

        if proxy is True:
            from .proxy import cached_proxy

            proxy = cached_proxy(self.sdf, margin=self.margin)
        check_sdf(proxy)
        return ProxyCollider(self.sdf, (self.vertices, self.faces), proxy, self.margin, self.method,
                             reuse_distance=self.reuse_distance, deferred=deferred)

    def collide_arrays(self, sdf_pose: np.ndarray, mesh_pose: np.ndarray, margin: float | None = None) -> ContactArrays:
        """:meth:`__call__` for a simulation's step: the poses float64 (4, 4) arrays, the contacts as
        :class:`zoo.collision.ContactArrays`; on a proxy, numpy throughout and the poses taken as given."""
        if self._on_proxy is None:
            return ContactArrays.from_contacts(self(torch.from_numpy(sdf_pose), torch.from_numpy(mesh_pose), margin))
        contacts = self._on_proxy.collide_arrays(sdf_pose, mesh_pose, margin)
        self.last_stats = self._on_proxy.last_stats
        return contacts

    def __call__(self, sdf_pose=None, mesh_pose=None, margin: float | None = None) -> Contacts:
        """Contacts at these poses (4x4 world-from-object, None: identity), as ``zoo.collide`` gives them;
        ``margin`` replaces the collider's for this call (the bounds carried over do not depend on it)."""
        if self._on_proxy is not None:
            contacts = self._on_proxy(sdf_pose, mesh_pose, margin)
            self.last_stats = self._on_proxy.last_stats
            return contacts
        margin = self.margin if margin is None else non_negative_float(margin, "margin")
        if not self.coherence:
            return collide(self.sdf, (self.vertices, self.faces), sdf_pose, mesh_pose, margin, self.method,
                           iters=None if self.method == "amortized" else self.iters, refine=self.refine,
                           voxel_resolution=self.voxel_resolution, polish=self.polish)
        device = self.vertices.device
        sdf_pose = as_pose(sdf_pose, torch.float64, "sdf_pose").to(device)
        mesh_pose = as_pose(mesh_pose, torch.float64, "mesh_pose").to(device)
        stats = CoherenceStats(steps=1)
        t0 = time.perf_counter()
        relative = invert_pose(sdf_pose) @ mesh_pose
        self._record_pose(relative)
        local = transform_points(relative.to(self.vertices.dtype), self.vertices)
        candidates, kind, f_exact = self._broad_phase(local, margin, stats)
        t1 = time.perf_counter()
        if candidates.numel() == 0:
            contacts = empty_contacts(local, self.faces.shape[0], self.method)
            bary, answer_normals, depths = local.new_zeros((0, 3)), local.new_zeros((0, 3)), local.new_zeros((0,))
            kind = torch.zeros(0, dtype=torch.int64, device=device)
            contacts.timings = {"broad": t1 - t0, "narrow": 0.0, "normals": 0.0}
        else:
            bary, depths, grads = self._narrow_phase(local, candidates, kind, f_exact, margin, stats)
            points = bary_to_points(local[self.faces[candidates]], bary)
            keep = depths <= margin
            t2 = time.perf_counter()
            normals = self._normals(points[keep], grads[keep])
            answer_normals = torch.full_like(points, torch.nan)
            answer_normals[keep] = normals
            rows = keep.nonzero().squeeze(-1)
            out_bary, out_depths, out_points = bary[keep], depths[keep], points[keep]
            world = sdf_pose.to(local.dtype)
            contacts = Contacts(
                points=transform_points(world, out_points), depths=out_depths,
                normals=transform_vectors(world, normals), triangles=candidates[rows], bary=out_bary,
                n_triangles=int(self.faces.shape[0]), n_candidates=int(candidates.numel()), method=self.method,
                timings={"broad": t1 - t0, "narrow": t2 - t1, "normals": time.perf_counter() - t2},
            )
        self._remember(local, candidates, bary, depths, answer_normals, kind == KEPT)
        self.last_stats = stats
        self.stats.add(stats)
        return contacts

    def exact_contacts(self, rows) -> Contacts:
        """With ``proxy`` and ``deferred``: the SDF's own contacts at the rows ``rows`` (R,) of the last call's contacts
        (which were the proxy's), as a non-deferred call gives them (world frame, triangles indexing the collider's
        mesh): the rows whose SDF depth is within that call's margin, in the order given."""
        if self._on_proxy is None:
            raise InputError("exact_contacts answers the last call's proxy contacts: call the collider (proxy=, deferred=True) first")
        contacts = self._on_proxy.exact_contacts(rows)
        self.last_stats = self._on_proxy.last_stats
        return contacts

    # -- broad phase ----------------------------------------------------------------------------

    def _broad_phase(self, local: torch.Tensor, margin: float, stats: CoherenceStats
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The vertices in the SDF's frame (V, 3) -> (candidate faces (C,) ascending, how each is answered (C,):
        ``COLD``, ``WARM`` or ``KEPT``, f (V,) at the vertices evaluated at their present position, NaN elsewhere)."""
        near = faces_near_bounds(self.sdf, local, self.faces, margin)
        stats.faces_near = int(near.numel())
        near = near[~self._still_clear(near, margin)]
        slack, moved = self._answer_slack(local, near, margin)
        clears = slack > 0
        answered = ~clears & torch.isfinite(self._answers.value[near])
        reusable = answered & (moved <= self.reuse_distance)
        if (answered & ~reusable).any():  # a round of queries is due anyway: bring the faces soon due along
            reusable &= moved <= REFRESH_FRACTION * self.reuse_distance
            clears &= slack > REFRESH_FRACTION * self.lipschitz * self.reuse_distance
            answered = ~clears & torch.isfinite(self._answers.value[near])
        warmable = answered & ~reusable & self._warm_reach(local, near, moved)
        # kept and warm-started answers need no bounds: only the others go through them
        self._prove_clear(near[clears], slack[clears] + margin, margin)
        kept, warm, near = near[reusable], near[warmable], near[~clears & ~reusable & ~warmable]
        used, corner = torch.unique(self.faces[near], return_inverse=True)  # corner (N, 3): rows of used
        tri = local[self.faces[near]]
        lower = self._carried_lower(local, used)  # (U,)
        open_ = cell_lower_bounds(tri, lower[corner]) <= margin
        stats.faces_skipped = int(stats.faces_near - open_.sum())
        stale = self._stale(used, corner, open_, local)
        if stale.numel() >= CLUSTER_CULL_MIN:  # many vertices: one query per cell first, as collide does
            counted = _CountingSDF(self.sdf)
            bound = cell_bounds(counted, local[used[stale]])
            stats.cell_queries = counted.queries
            lower[stale] = torch.maximum(lower[stale], bound)
            self._vertex.hold(used[stale], local[used[stale]], lower[stale], exact=False)
            open_ &= cell_lower_bounds(tri, lower[corner]) <= margin
            stale = self._stale(used, corner, open_, local)
        if stale.numel():
            with torch.no_grad():
                lower[stale] = torch.as_tensor(self.sdf(local[used[stale]])).reshape(-1).to(lower)
            stats.vertex_queries = int(stale.numel())
            self._vertex.hold(used[stale], local[used[stale]], lower[stale], exact=True)
        # every face from the best bounds known (a face an earlier bound cleared whose vertices were all evaluated
        # is tested again on their values, as collide does: the same faces for a 1-Lipschitz SDF, and for a
        # learned one, where a cell bound can exceed a vertex's value, the same as collide's as far as can be)
        bound = cell_lower_bounds(tri, lower[corner])
        cold = near[bound <= margin]
        self._prove_clear(near[bound > margin], bound[bound > margin], margin)
        stats.vertex_queries += self._evaluate_vertices(local, warm)  # for the warm starts' vertex test
        candidates, order = torch.sort(torch.cat([cold, warm, kept]))
        kind = torch.cat([torch.full_like(cold, COLD), torch.full_like(warm, WARM), torch.full_like(kept, KEPT)])[order]
        stats.candidates, stats.reused = int(candidates.numel()), int(kept.numel())
        stats.faces_skipped -= int(kept.numel() + warm.numel())
        fresh = self._vertex.known_at(slice(None), local)
        return candidates, kind, torch.where(fresh, self._vertex.lower, torch.full_like(self._vertex.lower, torch.nan))

    def _evaluate_vertices(self, local: torch.Tensor, faces: torch.Tensor) -> int:
        """Evaluate f at the vertices of ``faces`` (N,) not yet evaluated where they are now; returns how many."""
        v = torch.unique(self.faces[faces])
        v = v[~self._vertex.known_at(v, local[v])]
        if v.numel():
            with torch.no_grad():
                values = torch.as_tensor(self.sdf(local[v])).reshape(-1).to(self._vertex.lower)
            self._vertex.hold(v, local[v], values, exact=True)
        return int(v.numel())

    def _still_clear(self, faces: torch.Tensor, margin: float) -> torch.Tensor:
        """(N,) bool: the faces ``faces`` (N,) whose proven lower bound, less the Lipschitz bound times how far any
        of their points can have moved since it was proven, is still above ``margin``; no query, no vertex read.

        A point v of a face (centroid g, radius r about it) moved by (A - A_k) v + (b - b_k) between the SDF-from-mesh
        transforms (A_k, b_k) of the proof and (A, b) now: at most |(A - A_k) g + b - b_k| + ||A - A_k||_F r (the
        Frobenius norm bounds the spectral one).
        """
        bound = self._cleared.bound[faces]
        out = torch.zeros(faces.shape, dtype=torch.bool, device=faces.device)
        rows = (bound > margin).nonzero().squeeze(-1)
        if not rows.numel():
            return out
        f, now = faces[rows], self._cleared.poses[-1]
        turn = (self._cleared.poses[:, :, :3] - now[:, :3]).flatten(1).norm(dim=-1)  # (H,) ||A - A_k||_F per call so far
        radius = self._face_radius[f]
        centroid = self._centroid[f] @ now[:, :3].T + now[:, 3]
        reach = (centroid - self._cleared.centroid[f]).norm(dim=-1) + turn[self._cleared.pose[f]] * radius
        size = (centroid.abs().amax(dim=-1) + radius).to(self.vertices.dtype)
        slack = rounding_slack(bound[rows].abs().to(size), reach.to(size), size)
        out[rows] = bound[rows] - self.lipschitz * reach - slack > margin
        return out

    def _prove_clear(self, faces: torch.Tensor, bound: torch.Tensor, margin: float) -> None:
        """The faces ``faces`` (N,) hold f >= ``bound`` (N,) everywhere on them at this call's pose: those with room to
        spare (more than L times ``reuse_distance`` above ``margin``) keep it; the others stay in the exact tests, which
        are tighter and where a round of queries finds them."""
        spare = bound - margin > self.lipschitz * self.reuse_distance
        faces, bound, now = faces[spare], bound[spare], self._cleared.poses[-1]
        self._cleared.bound[faces] = bound.to(self._cleared.bound)
        self._cleared.pose[faces] = self._cleared.poses.shape[0] - 1
        self._cleared.centroid[faces] = self._centroid[faces] @ now[:, :3].T + now[:, 3]

    def _record_pose(self, relative: torch.Tensor) -> None:
        """Append this call's SDF-from-mesh transform (4, 4) to the pose history, dropping its older half when full."""
        if self._cleared.poses.shape[0] == POSE_HISTORY:
            dropped = POSE_HISTORY // 2
            self._cleared.bound[self._cleared.pose < dropped] = -torch.inf
            self._cleared.pose = (self._cleared.pose - dropped).clamp_min(0)
            self._cleared.poses = self._cleared.poses[dropped:]
        self._cleared.poses = torch.cat([self._cleared.poses, relative[:3].unsqueeze(0)])

    def _answer_slack(self, local: torch.Tensor, faces: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
        """((N,), (N,)) for the faces ``faces`` (N,): how far their last answer, less the Lipschitz bound times the
        farthest any of their points moved since (a rigid motion moves a triangle's points at most as far as its
        farthest vertex), is still above ``margin`` (positive: the minimum the method found then cannot have come
        within it), and that farthest motion."""
        answered, now = self._answers.at[faces], local[self.faces[faces]]
        moved = (now - answered).norm(dim=-1).amax(dim=-1)
        answer = self._answers.value[faces]
        size = torch.maximum(now.abs().amax(dim=(1, 2)), answered.abs().amax(dim=(1, 2)))
        return answer - self.lipschitz * moved - rounding_slack(answer.abs(), moved, size) - margin, moved

    def _carried_lower(self, local: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
        """Lower bounds (U,) of f at the vertices ``used`` (U,) at their present position ``local[used]``:
        the anchor's bound less the distance moved since (Lipschitz), less rounding slack; a vertex
        evaluated exactly where it is now keeps its value as it is."""
        here, anchor, bound = local[used], self._vertex.anchor[used], self._vertex.lower[used]
        moved = (here - anchor).norm(dim=-1)
        size = torch.maximum(here.abs().amax(dim=-1), anchor.abs().amax(dim=-1))
        carried = bound - self.lipschitz * moved - rounding_slack(bound.abs(), moved, size)
        unmoved = self._vertex.known_at(used, here)
        return torch.where(unmoved, bound, carried)

    def _stale(self, used: torch.Tensor, corner: torch.Tensor, open_: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """Rows of ``used`` (the open faces' vertices) whose f is not known exactly at their present position."""
        rows = torch.unique(corner[open_])
        v = used[rows]
        return rows[~self._vertex.known_at(v, local[v])]

    # -- narrow phase ---------------------------------------------------------------------------

    def _narrow_phase(self, local: torch.Tensor, candidates: torch.Tensor, kind: torch.Tensor, f_exact: torch.Tensor,
                      margin: float, stats: CoherenceStats) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Answers on the candidates (C,), each answered as ``kind`` (C,) says: bary (C, 3), depths (C,) and
        gradients (C, 3) where a warm start or a kept answer has them (NaN elsewhere)."""
        faces = self.faces[candidates]
        tri = local[faces]  # (C, 3, 3)
        warm, reused = kind == WARM, kind == KEPT
        stats.warm, stats.cold = int(warm.sum()), int((kind == COLD).sum())
        bary = tri.new_zeros((tri.shape[0], 3))
        depths = torch.full_like(tri[:, 0, 0], torch.nan)
        grads = torch.full_like(tri[:, 0], torch.nan)
        solve_sdf = voxel_of(self.sdf, self.voxel_resolution) if self.method == "voxel-fw" else self.sdf
        with torch.no_grad():
            r = reused.nonzero().squeeze(-1)
            if r.numel():
                bary[r], depths[r], grads[r] = self._kept_answers(candidates[r], tri[r])
            cold = (~warm & ~reused).nonzero().squeeze(-1)
            w = warm.nonzero().squeeze(-1)
            if w.numel():
                fv = f_exact[faces[w]] if solve_sdf is self.sdf else _values(solve_sdf, tri[w])
                bary[w], depths[w], grads[w], screened = self._warm(solve_sdf, local, faces[w], tri[w],
                                                                     self._answers.bary[candidates[w]], fv, margin)
                stats.screened = int(screened.sum())
                # a warm answer far from the KKT conditions (a kink of the SDF, a minimum that jumped) is solved
                # again from scratch too, and the lower answer kept; not where the gap proves the face stays above
                # the margin (for a convex f the minimum is at least the answer less its gap: no contact either way)
                gap = frank_wolfe_gap(tri[w], bary[w], grads[w])
                retry = w[(gap > RETRY_GAP) & (depths[w] - gap <= margin) & ~screened]
                stats.retried = int(retry.numel())
                cold = torch.cat([cold, retry])
            if cold.numel():
                b, d = self._cold(solve_sdf, local, faces[cold], tri[cold], f_exact, margin)
                d = torch.where(torch.isnan(d), _values_at(solve_sdf, tri[cold], b), d)
                lower = torch.isnan(depths[cold]) | (d < depths[cold])
                bary[cold] = torch.where(lower.unsqueeze(-1), b, bary[cold])
                depths[cold] = torch.where(lower, d, depths[cold])
                grads[cold] = torch.where(lower.unsqueeze(-1), torch.nan, grads[cold])
            if self.refine:
                bary = frank_wolfe(solve_sdf, tri, iters=self.refine, init=bary)
                depths.fill_(torch.nan)
                grads.fill_(torch.nan)
            unknown = torch.isnan(depths).nonzero().squeeze(-1)
            if unknown.numel():
                depths[unknown] = _values_at(solve_sdf, tri[unknown], bary[unknown])
        return bary, depths, grads

    def _kept_answers(self, faces: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The last answers of the faces ``faces`` (R,), now at ``tri`` (R, 3, 3): bary (R, 3), depths (R,) moved to
        first order along their normal (unchanged where none is known), normals (R, 3) (NaN where unknown)."""
        bary, normal = self._answers.bary[faces], self._answers.normal[faces]
        return bary, moved_along_normal(self._answers.value[faces], normal, tri, self._answers.at[faces], bary), normal

    def _warm_reach(self, local: torch.Tensor, faces: torch.Tensor, moved: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the faces ``faces`` (N,), which moved ``moved`` (N,) since their last answer, moved less than
        ``WARM_REACH`` of their longest edge (and warm starts are on)."""
        if not self.warm_start:
            return torch.zeros(faces.shape, dtype=torch.bool, device=faces.device)
        return moved <= WARM_REACH * edge_lengths(local[self.faces[faces]]).amax(dim=-1)

    def _cold(self, solve_sdf, local, faces, tri, f_exact, margin) -> tuple[torch.Tensor, torch.Tensor]:
        """collide's narrow phase on new candidates (large triangles on their pieces): bary (N, 3), depths (N,)."""
        return solve_candidates(self.sdf, solve_sdf, local, faces, f_exact, margin, self.method, self.iters, self.polish)

    def _warm(self, solve_sdf, local, faces, tri, start, vertex_values, margin):
        """Warm-started answers from the last barycentrics ``start`` (W, 3): bary, depths and gradients at them, and
        which rows the screen settled (W,) bool. ``vertex_values`` (W, 3): ``solve_sdf`` at the triangles' vertices,
        NaN where not evaluated at this step: rows with all three get the screen and the vertex test first
        (:meth:`_warm_from_vertices`), the others :func:`warm_step`."""
        known = torch.isfinite(vertex_values).all(dim=-1)
        bary, depths, grads = tri.new_empty((tri.shape[0], 3)), tri.new_empty(tri.shape[:1]), tri.new_empty((tri.shape[0], 3))
        screened = torch.zeros_like(known)
        k, u = known.nonzero().squeeze(-1), (~known).nonzero().squeeze(-1)
        if k.numel():
            bary[k], depths[k], grads[k], screened[k] = self._warm_from_vertices(
                solve_sdf, local, faces[k], tri[k], start[k], vertex_values[k], margin)
        if u.numel():
            bary[u], depths[u], grads[u] = warm_step(solve_sdf, tri[u], start[u])
        return bary, depths, grads, screened

    def _warm_from_vertices(self, solve_sdf, local, faces, tri, start, vertex_values, margin):
        """:meth:`_warm` where the values at the vertices (W, 3) are known. One gradient at each lowest vertex gives
        the vertex test (a lowest vertex that is a KKT point is the answer) and the screen (:func:`screen_bound`
        there: a face it puts above ``margin`` is answered by that bound, with no descent, and is no contact). The
        others take the value and gradient at their last answer, and the screen again from there (tight where the
        face moved little: its gap is near 0 at a minimiser); the rest get the lower of :func:`warm_step` from that
        query and the vertex. -> bary, depths, gradients, screened (W,)."""
        f_low, lowest = vertex_values.min(dim=-1)
        g_low = _gradients_at(solve_sdf, local, faces.gather(1, lowest.unsqueeze(1)).squeeze(1))
        low_bary = F.one_hot(lowest, 3).to(tri)
        bound = screen_bound(tri, low_bary, f_low, g_low, vertex_values)
        screened = bound > margin
        # the vertex test, as solve_mesh's: a lowest vertex that is a KKT point (its Frank-Wolfe gap is 0) is the answer
        settled = bound >= f_low
        # a screened face keeps its last answer's barycentrics: the next warm start is there
        bary = torch.where(screened.unsqueeze(-1), start, low_bary)
        depths, grads = torch.where(screened, bound, f_low), g_low.clone()
        rows = (~settled & ~screened).nonzero().squeeze(-1)
        if rows.numel():
            f0, g0 = _value_and_grad(solve_sdf, bary_to_points(tri[rows], start[rows]))
            again = screen_bound(tri[rows], start[rows], f0, g0, vertex_values[rows])
            clear = again > margin
            screened[rows[clear]], bary[rows[clear]], depths[rows[clear]] = True, start[rows[clear]], again[clear]
            rows, f0, g0 = rows[~clear], f0[~clear], g0[~clear]
        if rows.numel():  # the others: the best of the last answer and one step from it each way, or the vertex
            moved, f, g = warm_step(solve_sdf, tri[rows], start[rows], (f0, g0))
            better = f < f_low[rows]
            bary[rows] = torch.where(better.unsqueeze(-1), moved, low_bary[rows])
            depths[rows] = torch.where(better, f, f_low[rows])
            grads[rows] = torch.where(better.unsqueeze(-1), g, g_low[rows])
        return bary, depths, grads, screened

    def _normals(self, points: torch.Tensor, grads: torch.Tensor) -> torch.Tensor:
        """Unit normals (K, 3) at the contacts (K, 3): the gradients a warm start took, queried elsewhere."""
        known = ~torch.isnan(grads[:, 0])
        normals = F.normalize(torch.nan_to_num(grads), dim=-1)
        ask = (~known).nonzero().squeeze(-1)
        if ask.numel():
            solve_sdf = voxel_of(self.sdf, self.voxel_resolution) if self.method == "voxel-fw" else self.sdf
            normals[ask] = contact_normals(solve_sdf, points[ask])
        return normals

    def _remember(self, local: torch.Tensor, candidates: torch.Tensor, bary: torch.Tensor, depths: torch.Tensor,
                  normals: torch.Tensor, reused: torch.Tensor) -> None:
        """Keep this step's answers for the next: the solved candidates' barycentrics, values, normals (C, 3) (NaN
        where not a contact) and where they were (a kept answer stays as it was solved), which faces were
        candidates, and the vertices' positions."""
        solved = ~reused
        self._answers.bary[candidates[solved]] = bary[solved].to(self._answers.bary)
        self._answers.value[candidates[solved]] = depths[solved].to(self._answers.value)
        self._answers.at[candidates[solved]] = local[self.faces[candidates[solved]]]
        self._answers.normal[candidates[solved]] = normals[solved].to(self._answers.normal)
        self._last_candidates = candidates
