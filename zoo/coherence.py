"""Temporal coherence for ``zoo.collide``: one body pair collided step after step, reusing the last steps.

``zoo.collide`` starts every call from scratch. Along a trajectory the relative pose changes little
between steps, so :class:`CoherentCollider` keeps, for one (SDF, mesh) pair, what it learnt before,
all in the SDF's frame (where the SDF is queried):

* per mesh vertex, a lower bound of f at an anchor point (f itself where the vertex was evaluated,
  else a cell bound of the broad phase). The SDF is 1-Lipschitz (:data:`zoo.bounds.LIPSCHITZ`), so at
  the vertex's new position p, f(p) >= bound - |p - anchor|: a vertex that moved by delta loses delta
  of its slack, whatever the motion. A triangle's lower bound then follows from its vertices' bounds
  (:func:`zoo.bounds.cell_lower_bounds`, valid for any lower bounds at the vertices), and a triangle
  proven to stay above the margin is skipped with no query. Anchors stay put until a vertex is
  evaluated again, so a triangle cleared with a lot of slack is skipped for many steps, until its
  vertices' displacement since their anchor eats the slack. Rounding slack is subtracted as in
  :mod:`zoo.collision`;
* the triangles that remain get fresh values at their vertices (cell bounds first when there are
  many, as in collide) and the same vertex cull as collide: the candidates are exactly collide's
  (every bound used is a lower bound of the vertex value collide's own cull reads, and the cull is
  monotone in the values);
* per triangle, the barycentrics of its last answer. A candidate that was a candidate at the last
  step too, and whose vertices moved less than half its longest edge since, is warm-started there
  (``warm_start``): ``"amortized"`` takes ``POLISH_ROUNDS`` line-search steps from it
  (:func:`zoo.solvers.line_search_steps`) and keeps the lower of that and its lowest vertex, instead
  of the vertex test, the network and the polish; a start that is already a KKT point costs one
  value-and-gradient query, which gives its depth and its normal too. ``"fw"`` and ``"voxel-fw"``
  take ``warm_iters`` Frank-Wolfe iterations warm-started there (:func:`zoo.solvers.frank_wolfe`,
  which never returns a point worse than its start) instead of ``iters`` from the centroid.
  ``"pgd"`` has no warm start (PhysX's rule starts from its own point): only the skipping applies.
  New candidates take collide's own narrow phase.

The contacts have collide's fields and meaning (world frame, depths are signed distances, triangles
index the mesh's faces, rows ordered by triangle). Without warm starts they are collide's; with
them, a depth can only differ by the solvers' own error (tests/test_coherence.py holds both along
trajectories; docs/coherence.md measures the savings). ``coherence=False`` calls ``zoo.collide``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import torch
from torch.nn import functional as F

from .amortized.polish import POLISH_LINE_STEPS
from .bounds import LIPSCHITZ, cell_lower_bounds, rounding_slack
from .collision import (
    _CLUSTER_CULL_MIN,
    Contacts,
    _amortized_mesh,
    _cell_bounds,
    _contact_normals,
    _empty_contacts,
    _faces_near_bounds,
    _iters,
    _mesh_arrays,
    _method,
    _narrow_phase,
    _voxel_of,
    collide,
)
from .errors import InputError
from .geometry import bary_to_points, edge_lengths, invert_pose, transform_points, transform_vectors
from .sdf import Box, Capsule, Sphere, Torus, TransformedSDF, check_sdf
from .solvers import frank_wolfe, line_search_steps
from .validation import as_pose, int_at_least, non_negative_float, positive_float

# A persisting candidate is warm-started only while its vertices moved less than this fraction of its
# longest edge since the last step: farther, its last answer says little about the new minimum.
WARM_REACH = 0.5
# The Lipschitz bound a carried vertex bound decays with where the SDF is not an exact distance (a NeuralSDF,
# a voxel grid, a caller's SDF without a ``lipschitz`` attribute). The mugs model's hoi4d_mug_0001 has
# |grad f| <= 1.68 at 99.9% of points within 2 mm of its surface (2.4 at most; 2.1 and 3.4 within 3 cm):
# a learned SDF is only roughly 1-Lipschitz, and a bound carried over a motion inherits the error.
LEARNED_LIPSCHITZ = 2.0
DEFAULT_WARM_ITERS = 3
# Line-search steps from a warm start ("amortized"): the start is the last step's polished answer, and one
# step lands within 3.4e-6 m of the reference minimum on the demo mug sliding along the rack's peg (two:
# the same; from scratch, network and two steps: 3.7e-5 m); tests/test_coherence.py.
WARM_ROUNDS = 1  # Frank-Wolfe iterations from a warm start ("fw", "voxel-fw")


@dataclass
class CoherenceStats:
    """What :class:`CoherentCollider` did, summed over the steps counted.

    Attributes:
        steps: calls counted.
        faces_near: faces whose box touches the SDF's bounds grown by the margin (collide's first cull, no query).
        faces_skipped: of those, faces proven above the margin by the carried bounds, with no query.
        cell_queries: SDF queries at cell centres (bounds for many vertices at once).
        vertex_queries: SDF queries at mesh vertices.
        candidates: triangles that reached the narrow phase (collide's candidates).
        warm: of those, warm-started from their last barycentrics.
        cold: of those, solved from scratch by the method.
    """

    steps: int = 0
    faces_near: int = 0
    faces_skipped: int = 0
    cell_queries: int = 0
    vertex_queries: int = 0
    candidates: int = 0
    warm: int = 0
    cold: int = 0

    def add(self, other: CoherenceStats) -> None:
        for key, value in asdict(other).items():
            setattr(self, key, getattr(self, key) + value)

    def as_dict(self) -> dict:
        return asdict(self)


def motion_lipschitz(sdf) -> float:
    """The Lipschitz bound :class:`CoherentCollider` assumes of ``sdf`` when it carries a bound over a motion:
    the SDF's own ``lipschitz`` attribute where it has one; :data:`zoo.bounds.LIPSCHITZ` for the exact
    analytic SDFs (also rigidly placed); :data:`LEARNED_LIPSCHITZ` for anything else."""
    given = getattr(sdf, "lipschitz", None)
    if given is not None:
        return positive_float(given, f"{type(sdf).__name__}.lipschitz")
    if isinstance(sdf, TransformedSDF):
        return motion_lipschitz(sdf.sdf)
    return LIPSCHITZ if isinstance(sdf, (Sphere, Box, Torus, Capsule)) else LEARNED_LIPSCHITZ


class _CountingSDF:
    """An SDF's values, counting the points asked for (what the cell bounds cost)."""

    def __init__(self, sdf):
        self.sdf, self.queries = sdf, 0

    def __call__(self, points: torch.Tensor):
        self.queries += int(points.shape[0])
        return self.sdf(points)


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
        warm_iters: Frank-Wolfe iterations of a warm start for "fw" and "voxel-fw" (default 3).
        lipschitz: the bound a vertex's carried bound decays with as it moves (default :func:`motion_lipschitz`).

    Call it with the poses of each step: ``contacts = collider(sdf_pose, mesh_pose)`` (4x4 world-from-object,
    None is the identity). ``stats`` sums :class:`CoherenceStats` over all calls, ``last_stats`` holds the
    last call's, and ``last_candidates`` (C,) the faces the last call solved.
    """

    def __init__(self, sdf, mesh, margin: float = 1e-3, method: str = "fw", *, coherence: bool = True,
                 warm_start: bool = True, warm_iters: int = DEFAULT_WARM_ITERS, iters: int | None = None,
                 refine: int = 0, voxel_resolution=256, polish: bool = True, lipschitz: float | None = None):
        check_sdf(sdf)
        self.sdf = sdf
        self.method = _method(method)
        if self.method == "amortized" and not callable(getattr(sdf, "detect", None)):
            raise InputError(
                f'method="amortized" needs a shape from a model with a detector: zoo.load(NAME).shape(...); '
                f"{type(sdf).__name__} has no detect(triangles)"
            )
        self.margin = non_negative_float(margin, "margin")
        self.iters = _iters(self.method, iters)
        self.refine = int_at_least(refine, "refine")
        if not polish and self.method != "amortized":
            raise InputError(f'polish=False applies to method="amortized" only (got method={method!r}); drop it')
        self.polish = bool(polish)
        self.voxel_resolution = voxel_resolution
        self.coherence = bool(coherence)
        self.warm_start = bool(warm_start) and self.method != "pgd"
        self.warm_iters = int_at_least(warm_iters, "warm_iters", minimum=1)
        self.lipschitz = motion_lipschitz(sdf) if lipschitz is None else positive_float(lipschitz, "lipschitz")
        self.vertices, self.faces = _mesh_arrays(mesh)
        self.stats = CoherenceStats()
        self.last_stats = CoherenceStats()
        self.last_candidates = torch.zeros(0, dtype=torch.int64, device=self.vertices.device)
        self.reset()

    def reset(self) -> None:
        """Forget everything carried over (the next call works from scratch); ``stats`` are kept."""
        v, f = self.vertices, self.faces
        self._anchor = torch.zeros_like(v)  # (V, 3) where each vertex's bound holds, SDF frame
        self._lower = torch.full(v.shape[:1], -torch.inf, dtype=v.dtype, device=v.device)  # (V,) bound of f there
        self._exact = torch.zeros(v.shape[:1], dtype=torch.bool, device=v.device)  # (V,) the bound is f itself
        self._bary = v.new_zeros((f.shape[0], 3))  # (F, 3) each face's last answer
        self._persists = torch.zeros(f.shape[0], dtype=torch.bool, device=v.device)  # (F,) a candidate last step
        self._previous = None  # (V, 3) the vertices in the SDF's frame at the last step

    def __call__(self, sdf_pose=None, mesh_pose=None) -> Contacts:
        """Contacts at these poses (4x4 world-from-object, None: identity), as ``zoo.collide`` gives them."""
        if not self.coherence:
            return collide(self.sdf, (self.vertices, self.faces), sdf_pose, mesh_pose, self.margin, self.method,
                           iters=None if self.method == "amortized" else self.iters, refine=self.refine,
                           voxel_resolution=self.voxel_resolution, polish=self.polish)
        device = self.vertices.device
        sdf_pose = as_pose(sdf_pose, torch.float64, "sdf_pose").to(device)
        mesh_pose = as_pose(mesh_pose, torch.float64, "mesh_pose").to(device)
        stats = CoherenceStats(steps=1)
        t0 = time.perf_counter()
        local = transform_points((invert_pose(sdf_pose) @ mesh_pose).to(self.vertices.dtype), self.vertices)
        candidates, f_exact = self._broad_phase(local, stats)
        t1 = time.perf_counter()
        if candidates.numel() == 0:
            contacts = _empty_contacts(local, self.faces.shape[0], self.method)
            bary = local.new_zeros((0, 3))
            contacts.timings = {"broad": t1 - t0, "narrow": 0.0, "normals": 0.0}
        else:
            bary, depths, grads = self._narrow_phase(local, candidates, f_exact, stats)
            points = bary_to_points(local[self.faces[candidates]], bary)
            keep = depths <= self.margin
            t2 = time.perf_counter()
            normals = self._normals(points[keep], grads[keep])
            world = sdf_pose.to(local.dtype)
            contacts = Contacts(
                points=transform_points(world, points[keep]), depths=depths[keep],
                normals=transform_vectors(world, normals), triangles=candidates[keep], bary=bary[keep],
                n_triangles=int(self.faces.shape[0]), n_candidates=int(candidates.numel()), method=self.method,
                timings={"broad": t1 - t0, "narrow": t2 - t1, "normals": time.perf_counter() - t2},
            )
        self._remember(local, candidates, bary)
        self.last_stats = stats
        self.stats.add(stats)
        return contacts

    # -- broad phase ----------------------------------------------------------------------------

    def _broad_phase(self, local: torch.Tensor, stats: CoherenceStats) -> tuple[torch.Tensor, torch.Tensor]:
        """The vertices in the SDF's frame (V, 3) -> (collide's candidate faces (C,) ascending, f (V,) at the
        vertices evaluated at their present position, NaN elsewhere)."""
        near = _faces_near_bounds(self.sdf, local, self.faces, self.margin)
        stats.faces_near = int(near.numel())
        used, corner = torch.unique(self.faces[near], return_inverse=True)  # corner (N, 3): rows of used
        tri = local[self.faces[near]]
        lower = self._carried_lower(local, used)  # (U,)
        open_ = cell_lower_bounds(tri, lower[corner]) <= self.margin
        stats.faces_skipped = int(near.numel() - open_.sum())
        stale = self._stale(used, corner, open_, local)
        if stale.numel() >= _CLUSTER_CULL_MIN:  # many vertices: one query per cell first, as collide does
            counted = _CountingSDF(self.sdf)
            bound = _cell_bounds(counted, local[used[stale]])
            stats.cell_queries = counted.queries
            lower[stale] = torch.maximum(lower[stale], bound)
            self._anchor_at(used[stale], local, lower[stale], exact=False)
            open_ &= cell_lower_bounds(tri, lower[corner]) <= self.margin
            stale = self._stale(used, corner, open_, local)
        if stale.numel():
            with torch.no_grad():
                lower[stale] = torch.as_tensor(self.sdf(local[used[stale]])).reshape(-1).to(lower)
            stats.vertex_queries = int(stale.numel())
            self._anchor_at(used[stale], local, lower[stale], exact=True)
        candidates = near[open_ & (cell_lower_bounds(tri, lower[corner]) <= self.margin)]
        stats.candidates = int(candidates.numel())
        fresh = self._exact & (self._anchor == local).all(dim=-1)
        return candidates, torch.where(fresh, self._lower, torch.full_like(self._lower, torch.nan))

    def _carried_lower(self, local: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
        """Lower bounds (U,) of f at the vertices ``used`` (U,) at their present position ``local[used]``:
        the anchor's bound less the distance moved since (Lipschitz), less rounding slack; a vertex
        evaluated exactly where it is now keeps its value as it is."""
        here, anchor, bound = local[used], self._anchor[used], self._lower[used]
        moved = (here - anchor).norm(dim=-1)
        size = torch.maximum(here.abs().amax(dim=-1), anchor.abs().amax(dim=-1))
        carried = bound - self.lipschitz * moved - rounding_slack(bound.abs(), moved, size)
        unmoved = self._exact[used] & (here == anchor).all(dim=-1)
        return torch.where(unmoved, bound, carried)

    def _stale(self, used: torch.Tensor, corner: torch.Tensor, open_: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """Rows of ``used`` (the open faces' vertices) whose f is not known exactly at their present position."""
        rows = torch.unique(corner[open_])
        v = used[rows]
        known = self._exact[v] & (self._anchor[v] == local[v]).all(dim=-1)
        return rows[~known]

    def _anchor_at(self, vertices: torch.Tensor, local: torch.Tensor, lower: torch.Tensor, exact: bool) -> None:
        """Vertices ``vertices`` (K,) now hold the bound ``lower`` (K,) at their present position."""
        self._anchor[vertices] = local[vertices]
        self._lower[vertices] = lower
        self._exact[vertices] = exact

    # -- narrow phase ---------------------------------------------------------------------------

    def _narrow_phase(self, local: torch.Tensor, candidates: torch.Tensor, f_exact: torch.Tensor,
                      stats: CoherenceStats) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Answers on the candidates (C,): bary (C, 3), depths (C,) and gradients (C, 3) where a warm start
        already took them at the answer (NaN elsewhere)."""
        faces = self.faces[candidates]
        tri = local[faces]  # (C, 3, 3)
        warm = self._warm_rows(local, candidates, tri)
        stats.warm, stats.cold = int(warm.sum()), int((~warm).sum())
        bary = tri.new_zeros((tri.shape[0], 3))
        depths = torch.full_like(tri[:, 0, 0], torch.nan)
        grads = torch.full_like(tri[:, 0], torch.nan)
        solve_sdf = _voxel_of(self.sdf, self.voxel_resolution) if self.method == "voxel-fw" else self.sdf
        with torch.no_grad():
            cold = (~warm).nonzero().squeeze(-1)
            if cold.numel():
                bary[cold], depths[cold] = self._cold(solve_sdf, local, faces[cold], tri[cold], f_exact)
            w = warm.nonzero().squeeze(-1)
            if w.numel():
                bary[w], depths[w], grads[w] = self._warm(solve_sdf, local, faces[w], tri[w], self._bary[candidates[w]],
                                                          f_exact[faces[w]])
            if self.refine:
                bary = frank_wolfe(solve_sdf, tri, iters=self.refine, init=bary)
                depths.fill_(torch.nan)
                grads.fill_(torch.nan)
            unknown = torch.isnan(depths).nonzero().squeeze(-1)
            if unknown.numel():
                points = bary_to_points(tri[unknown], bary[unknown])
                depths[unknown] = torch.as_tensor(solve_sdf(points)).reshape(-1).to(depths)
        return bary, depths, grads

    def _warm_rows(self, local: torch.Tensor, candidates: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
        """(C,) bool: candidates that were candidates at the last step and moved less than ``WARM_REACH``
        of their longest edge since."""
        if not self.warm_start or self._previous is None:
            return torch.zeros(candidates.shape, dtype=torch.bool, device=candidates.device)
        faces = self.faces[candidates]
        moved = (local[faces] - self._previous[faces]).norm(dim=-1).amax(dim=-1)  # (C,)
        return self._persists[candidates] & (moved <= WARM_REACH * edge_lengths(tri).amax(dim=-1))

    def _cold(self, solve_sdf, local, faces, tri, f_exact) -> tuple[torch.Tensor, torch.Tensor]:
        """collide's narrow phase on new candidates: bary (N, 3), depths (N,) (NaN where not evaluated)."""
        if self.method == "amortized" and callable(getattr(self.sdf, "detect_mesh", None)):
            return _amortized_mesh(self.sdf, local, faces, tri, f_exact, self.margin, self.polish)
        bary = _narrow_phase(solve_sdf, self.sdf, tri, self.method, self.iters)
        return bary, torch.full_like(tri[:, 0, 0], torch.nan)

    def _warm(self, solve_sdf, local, faces, tri, start, vertex_values):
        """Warm-started answers from the last barycentrics ``start`` (W, 3): bary, depths and gradients (NaN
        where not taken). ``vertex_values`` (W, 3): f at the triangles' vertices, all evaluated this step."""
        nan = torch.full_like(tri[:, 0, 0], torch.nan)
        if self.method != "amortized":
            return frank_wolfe(solve_sdf, tri, iters=self.warm_iters, init=start), nan, nan.unsqueeze(-1).expand(-1, 3)
        f_low, lowest = vertex_values.min(dim=-1)
        g_low = self._gradients_at(local, faces.gather(1, lowest.unsqueeze(1)).squeeze(1))
        low_bary = F.one_hot(lowest, 3).to(tri)
        # the vertex test, as solve_mesh's: a lowest vertex that is a KKT point is the answer
        scores = torch.einsum("wc,wvc->wv", g_low, tri)
        settled = scores.amin(dim=-1) >= scores.gather(1, lowest.unsqueeze(1)).squeeze(1)
        bary, depths, grads = low_bary.clone(), f_low.clone(), g_low.clone()
        rows = (~settled).nonzero().squeeze(-1)
        if rows.numel():  # the others: line-search steps from the last answer, then the lower of it and the vertex
            polished = line_search_steps(solve_sdf, tri[rows], start[rows], vertex_values[rows], WARM_ROUNDS,
                                         line_steps=POLISH_LINE_STEPS, fallback=(low_bary[rows], f_low[rows], g_low[rows]))
            f, g = solve_sdf.value_and_grad(bary_to_points(tri[rows], polished))
            f, g = torch.as_tensor(f).reshape(-1).to(tri), torch.as_tensor(g).to(tri)
            better = f < f_low[rows]
            bary[rows] = torch.where(better.unsqueeze(-1), polished, low_bary[rows])
            depths[rows] = torch.where(better, f, f_low[rows])
            grads[rows] = torch.where(better.unsqueeze(-1), g, g_low[rows])
        return bary, depths, grads

    def _gradients_at(self, local: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """Gradients (W, 3) of the SDF at the mesh vertices ``vertices`` (W,) (present positions), one query per
        distinct vertex."""
        distinct, inverse = torch.unique(vertices, return_inverse=True)
        _, g = self.sdf.value_and_grad(local[distinct])
        return torch.as_tensor(g).to(local)[inverse]

    def _normals(self, points: torch.Tensor, grads: torch.Tensor) -> torch.Tensor:
        """Unit normals (K, 3) at the contacts (K, 3): the gradients a warm start took, queried elsewhere."""
        known = ~torch.isnan(grads[:, 0])
        normals = F.normalize(torch.nan_to_num(grads), dim=-1)
        ask = (~known).nonzero().squeeze(-1)
        if ask.numel():
            solve_sdf = _voxel_of(self.sdf, self.voxel_resolution) if self.method == "voxel-fw" else self.sdf
            normals[ask] = _contact_normals(solve_sdf, points[ask])
        return normals

    def _remember(self, local: torch.Tensor, candidates: torch.Tensor, bary: torch.Tensor) -> None:
        """Keep this step's answers for the next: the candidates' barycentrics and the vertices' positions."""
        self._persists.zero_()
        self._persists[candidates] = True
        self._bary[candidates] = bary.to(self._bary)
        self._previous = local
        self.last_candidates = candidates
