"""SDF-mesh contacts: broad phase, per-triangle narrow phase, contact features.

``collide(sdf, mesh)`` finds, for every mesh triangle that comes within ``margin`` of the SDF's
surface, the point of the triangle with the smallest signed distance (problem (1) of the
paper), and reports it as a contact:

1. the mesh's vertices are moved into the SDF's frame (``inverse(sdf_pose) @ mesh_pose``);
2. broad phase (:func:`candidate_triangles`): triangles whose bounding box misses the SDF's
   bounds grown by ``margin`` are dropped (tested per vertex, without building all F
   triangles), then those whose Lipschitz lower bound from f at their vertices exceeds
   ``margin`` (one query per distinct vertex, about half a query per triangle); both are exact
   for a 1-Lipschitz SDF (no triangle that reaches within ``margin`` is dropped);
3. narrow phase: barycentric coordinates of the minimum by ``method``, then ``refine``
   Frank-Wolfe steps warm-started from them;
4. features ``p = bary . v`` and ``d = f(p)``; rows with ``d <= margin`` are kept, and only
   those get ``n = grad f(p) / |grad f(p)|`` (one value pass over the candidates, one
   value-and-gradient pass over the contacts); all in the SDF's frame, mapped to the world by
   ``sdf_pose``.

``method="amortized"`` on a shape that offers ``detect_mesh(vertices, faces, cutoff, vertex_values)``
(a model's NeuralShape) hands it the candidates as an indexed mesh with the distances the broad
phase evaluated at their vertices: features are computed once per distinct vertex, the network's
answer is compared with the vertices (keeping the lowest), triangles and subdivision cells
proven to stay above the margin are not solved, and the distances it returns at its answers
are the depths (no second value pass). Any other SDF with a ``detect(triangles)`` gets step 3
and 4 as written.

Every method evaluates the contact points on the true SDF except ``"voxel-fw"``, which, like a
simulator that only holds the voxel grid, solves and reports on the grid's interpolant. The
broad phase always uses the given SDF, so every method sees the same candidate triangles.

Degenerate faces (zero area: repeated or collinear vertices) are kept and treated like any
other: their minimum lies on a segment or a point, which every solver handles.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .bounds import cell_lower_bounds, rounding_slack
from .errors import InputError
from .geometry import bary_to_points, faces_touching_box, invert_pose, transform_points, transform_vectors, unique_rows
from .large_triangles import best_pieces, cut_large
from .methods import NARROW_PHASES, check_supports, iterations
from .sdf import check_sdf
from .validation import as_faces, as_points, as_pose, as_triangles, int_at_least, mesh_pair, non_negative_float

METHODS = tuple(NARROW_PHASES)  # the registry's names (zoo.methods)
DEFAULT_ITERS = {name: m.default_iters for name, m in NARROW_PHASES.items() if m.default_iters is not None}


@dataclass
class Contacts:
    """One row per contact, in the world frame (the frame the poses map into).

    Attributes:
        points: (K, 3) the point of minimum signed distance on each contacting triangle.
        depths: (K,) signed distance of that point to the SDF's surface (negative = penetration).
        normals: (K, 3) unit outward normal of the SDF at the point (pointing from the SDF
            towards the mesh when they touch); all zeros where the SDF's gradient vanishes.
        triangles: (K,) int64, the index of each contact's triangle in the mesh's faces.
        bary: (K, 3) barycentric coordinates of each point on its triangle.
        n_triangles: number of faces in the mesh.
        n_candidates: number of triangles that survived the broad phase.
        method: the narrow-phase method that produced the contacts.
        timings: wall-clock seconds of the call's phases: ``broad`` (pose, bounds and vertex
            cull), ``narrow`` (the method, refine steps and the depths) and ``normals``.
    """

    points: torch.Tensor
    depths: torch.Tensor
    normals: torch.Tensor
    triangles: torch.Tensor
    bary: torch.Tensor
    n_triangles: int = 0
    n_candidates: int = 0
    method: str = "fw"
    timings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.depths.shape[0])

    def __repr__(self):
        return (
            f"Contacts({len(self)} contacts from {self.n_candidates} candidates of "
            f"{self.n_triangles} triangles, method={self.method!r})"
        )


@dataclass
class ContactArrays:
    """:class:`Contacts` as float64 numpy arrays, for a simulation's per-step paths, where torch's cost per call
    shows (the same fields and frames): ``points`` (K, 3), ``depths`` (K,), ``normals`` (K, 3) unit (zeros where the
    SDF's gradient vanishes), ``triangles`` (K,) int64, ``bary`` (K, 3), and ``n_triangles``, ``n_candidates``,
    ``method``, ``timings`` as :class:`Contacts` has them."""

    points: np.ndarray
    depths: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    bary: np.ndarray
    n_triangles: int = 0
    n_candidates: int = 0
    method: str = "fw"
    timings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.depths.shape[0])

    @classmethod
    def empty(cls, method: str = "fw") -> ContactArrays:
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)),
                   method=method)

    @classmethod
    def from_contacts(cls, contacts: Contacts) -> ContactArrays:
        """A :class:`Contacts`'s rows, its normals made unit."""
        as_array = lambda t: np.asarray(t.detach().cpu(), dtype=np.float64)  # noqa: E731
        normals = as_array(contacts.normals)
        length = np.sqrt((normals * normals).sum(axis=1, keepdims=True))
        normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
        return cls(as_array(contacts.points), as_array(contacts.depths), normals,
                   np.asarray(contacts.triangles.detach().cpu(), dtype=np.int64), as_array(contacts.bary),
                   contacts.n_triangles, contacts.n_candidates, contacts.method, contacts.timings)

    @classmethod
    def concat(cls, parts: list[ContactArrays]) -> ContactArrays:
        """The rows of ``parts`` one after the other (their triangle and candidate counts summed)."""
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        column = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        return cls(column("points"), column("depths"), column("normals"), column("triangles"), column("bary"),
                   sum(p.n_triangles for p in parts), sum(p.n_candidates for p in parts), parts[0].method)

    def take(self, rows: np.ndarray) -> ContactArrays:
        """The rows ``rows`` (R,), in that order."""
        return ContactArrays(self.points[rows], self.depths[rows], self.normals[rows], self.triangles[rows],
                             self.bary[rows], self.n_triangles, self.n_candidates, self.method, self.timings)

    def to_contacts(self, dtype: torch.dtype = torch.float64) -> Contacts:
        """These rows as :class:`Contacts` in ``dtype`` (triangles int64)."""
        as_tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(dtype)  # noqa: E731
        return Contacts(points=as_tensor(self.points), depths=as_tensor(self.depths), normals=as_tensor(self.normals),
                        triangles=torch.from_numpy(np.ascontiguousarray(self.triangles, dtype=np.int64)),
                        bary=as_tensor(self.bary), n_triangles=self.n_triangles, n_candidates=self.n_candidates,
                        method=self.method, timings=self.timings)


# -- broad phase ----------------------------------------------------------------------------


def candidate_triangles(sdf, triangles, margin: float = 1e-3) -> torch.Tensor:
    """Indices of the triangles that may come within ``margin`` of the surface.

    Args:
        sdf: an SDF protocol object; triangles are in its frame.
        triangles: (M, 3, 3).
        margin: contact margin, >= 0.

    Returns:
        (C,) int64 indices into ``triangles``, ascending. A triangle is dropped only when that
        is proven for a 1-Lipschitz SDF: its bounding box misses ``sdf.bounds`` grown by
        ``margin`` (points outside the box are farther from the surface than from the box), or
        the lower bound of f over it from its vertex values exceeds ``margin``
        (:func:`_vertex_cull`).
    """
    check_sdf(sdf)
    triangles = as_triangles(triangles, allow_empty=True)
    margin = non_negative_float(margin, "margin")
    near_box = _overlaps_bounds(sdf, triangles, margin).nonzero().squeeze(-1)
    if near_box.numel() == 0:
        return near_box
    vertices, faces = unique_rows(triangles[near_box].reshape(-1, 3))
    return near_box[_vertex_cull(sdf, vertices, faces.reshape(-1, 3), margin)[0]]


def _overlaps_bounds(sdf, triangles: torch.Tensor, margin: float) -> torch.Tensor:
    """(M, 3, 3) -> (M,) bool: triangle's AABB touches the SDF's bounds grown by ``margin``."""
    lo, hi = (torch.as_tensor(b).to(triangles).reshape(3) for b in sdf.bounds)
    t_lo, t_hi = triangles.amin(dim=1), triangles.amax(dim=1)
    return ((t_hi >= lo - margin) & (t_lo <= hi + margin)).all(dim=-1)


def faces_near_bounds(sdf, vertices: torch.Tensor, faces: torch.Tensor, margin: float) -> torch.Tensor:
    """Indices (N,) of the faces whose AABB touches the SDF's bounds grown by ``margin``
    (:func:`_overlaps_bounds`'s test without building the (F, 3, 3) triangles)."""
    lo, hi = (torch.as_tensor(b).to(vertices).reshape(3) for b in sdf.bounds)
    return faces_touching_box(vertices, faces, lo - margin, hi + margin)


# From this many distinct vertices on, the broad phase first bounds f at every vertex by one query per
# cell of about _CLUSTER_SIZE vertices, and evaluates f only at the vertices of the faces those bounds
# do not clear: on a large mesh near a small SDF, far fewer queries than one per vertex (docs/results.md, the scenes).
CLUSTER_CULL_MIN = 512
_CLUSTER_SIZE = 8


def _vertex_cull(sdf, vertices: torch.Tensor, faces: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Faces (N, 3) into ``vertices`` (V, 3) (the SDF's frame) -> (may touch (N,) bool, f at the vertices (V,)).

    A face is dropped when the lower bound of a 1-Lipschitz f over it, from f at its three vertices
    (:func:`zoo.bounds.cell_lower_bounds`), exceeds ``margin``. f is evaluated once per distinct
    vertex, about half as many queries as one per face, and the amortized narrow phase reuses the
    values; entries of the returned f are NaN where it was not evaluated. Many vertices first go
    through :func:`cell_bounds`: a face its cheaper bounds clear costs no vertex query.
    """
    f = torch.full(vertices.shape[:1], math.nan, dtype=vertices.dtype, device=vertices.device)
    if faces.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool, device=vertices.device), f
    used, corner = torch.unique(faces, return_inverse=True)  # corner (N, 3): rows of used
    tri = vertices[faces]
    points = vertices[used]
    lower = None
    need = torch.arange(used.numel(), device=used.device)
    if used.numel() >= CLUSTER_CULL_MIN:
        lower = cell_bounds(sdf, points)
        need = torch.unique(corner[cell_lower_bounds(tri, lower[corner]) <= margin])
    if need.numel():
        with torch.no_grad():
            f[used[need]] = torch.as_tensor(sdf(points[need])).reshape(-1).to(f)
    values = f[used] if lower is None else torch.where(torch.isnan(f[used]), lower, f[used])
    return cell_lower_bounds(tri, values[corner]) <= margin, f


def cell_bounds(sdf, points: torch.Tensor) -> torch.Tensor:
    """Lower bounds (N,) of a 1-Lipschitz f at ``points`` (N, 3) from one query per cell of about ``_CLUSTER_SIZE``.

    Points are binned on a grid of about N / ``_CLUSTER_SIZE`` occupied cells (a surface's vertices
    fill cells as the square of the grid's resolution); each point's bound is f(centre) - |p - centre|
    at its cell's centre, less rounding slack.
    """
    lo, hi = points.amin(dim=0), points.amax(dim=0)
    per_axis = max(1, round(math.sqrt(points.shape[0] / _CLUSTER_SIZE)))
    size = ((hi - lo).amax() / per_axis).clamp_min(torch.finfo(points.dtype).tiny)
    ijk = ((points - lo) / size).floor().long().clamp(0, per_axis)
    side = per_axis + 1
    _, cell = torch.unique((ijk[:, 0] * side + ijk[:, 1]) * side + ijk[:, 2], return_inverse=True)
    n = int(cell.max()) + 1
    count = torch.bincount(cell, minlength=n).to(points).unsqueeze(-1)
    centre = points.new_zeros((n, 3)).index_add_(0, cell, points) / count
    with torch.no_grad():
        f = torch.as_tensor(sdf(centre)).reshape(-1).to(points)[cell]
    reach = (points - centre[cell]).norm(dim=-1)
    # f is rounded to the dtype: the bound keeps a few ulps so that the cull never drops what exact arithmetic would keep
    return f - reach - rounding_slack(f.abs().nan_to_num(0, 0, 0), reach, points.abs().amax(dim=-1))


# -- collide --------------------------------------------------------------------------------


def collide(
    sdf,
    mesh,
    sdf_pose=None,
    mesh_pose=None,
    margin: float = 1e-3,
    method: str = "fw",
    iters: int | None = None,
    refine: int = 0,
    voxel_resolution=256,
    polish: bool = True,
) -> Contacts:
    """Contacts between an SDF and a triangle mesh, one per triangle within ``margin``.

    Args:
        sdf: an SDF protocol object (``zoo.Sphere``, a NeuralSDF shape, a ``VoxelSDF``...).
        mesh: a ``trimesh.Trimesh`` (or anything with ``.vertices`` and ``.faces``), or a
            ``(vertices (V, 3), faces (F, 3) int)`` pair. Vertices' float64 is kept; other
            dtypes become float32. The computation runs on the vertices' device.
        sdf_pose, mesh_pose: 4x4 world-from-object rigid transforms (tensor or array); None is
            the identity.
        margin: contact margin (>= 0): triangles whose minimum signed distance is at most this
            are reported.
        method: narrow phase: "fw" (Frank-Wolfe, MuJoCo's rule), "pgd" (projected gradient,
            PhysX's rule), "voxel-fw" (Frank-Wolfe on a ``VoxelSDF`` of ``sdf``, cached per
            SDF object and resolution), "amortized" (``sdf.detect(triangles)``, one pass).
        iters: solver iterations; default 10 for "fw" and "voxel-fw", 32 for "pgd"; not
            accepted for "amortized" (use ``refine``).
        refine: Frank-Wolfe steps warm-started from the method's answer (0: none).
        voxel_resolution: samples per axis of the grid for "voxel-fw".
        polish: "amortized" on a model's shape only: the vertex test, then line-search steps from
            the network's answers where it fails (``zoo.amortized.solve_mesh``). False is the forward
            pass alone (no gradient query in the narrow phase), less precise: the scene bench
            (``zoo bench --scenes``) measures both.

    Returns:
        :class:`Contacts`, rows ordered by triangle index.
    """
    check_sdf(sdf)
    method = check_supports(method, sdf).name
    iters = iterations(method, iters)
    if method == "voxel-fw":
        from .voxel import resolution_per_axis

        resolution_per_axis(voxel_resolution)  # refuse a bad resolution even when nothing is near
    refine = int_at_least(refine, "refine")
    if not polish and method != "amortized":
        raise InputError(f'polish=False applies to method="amortized" only (got method={method!r}); drop it')
    margin = non_negative_float(margin, "margin")
    vertices, faces = mesh_tensors(mesh)
    sdf_pose = as_pose(sdf_pose, torch.float64, "sdf_pose").to(vertices.device)
    mesh_pose = as_pose(mesh_pose, torch.float64, "mesh_pose").to(vertices.device)

    t0 = time.perf_counter()
    sdf_from_mesh = (invert_pose(sdf_pose) @ mesh_pose).to(vertices.dtype)
    local = transform_points(sdf_from_mesh, vertices)  # (V, 3) in the SDF's frame
    # The broad phase as candidate_triangles, without building or re-validating all F triangles.
    candidates = faces_near_bounds(sdf, local, faces, margin)
    survives, f_vertices = _vertex_cull(sdf, local, faces[candidates], margin)
    candidates = candidates[survives]
    tri = local[faces[candidates]]  # (N, 3, 3)
    t1 = time.perf_counter()
    if candidates.numel() == 0:
        empty = empty_contacts(local, faces.shape[0], method)
        empty.timings = {"broad": t1 - t0, "narrow": 0.0, "normals": 0.0}
        return empty
    solve_sdf = voxel_of(sdf, voxel_resolution) if method == "voxel-fw" else sdf
    with torch.no_grad():
        bary, depths = solve_candidates(sdf, solve_sdf, local, faces[candidates], f_vertices, margin, method, iters,
                                        polish, refine)
        points = bary_to_points(tri, bary)
    keep = depths <= margin
    t2 = time.perf_counter()
    normals = contact_normals(solve_sdf, points[keep])  # gradients only where there is a contact
    world = sdf_pose.to(tri.dtype)
    return Contacts(
        points=transform_points(world, points[keep]),
        depths=depths[keep],
        normals=transform_vectors(world, normals),
        triangles=candidates[keep],
        bary=bary[keep].to(tri),
        n_triangles=int(faces.shape[0]),
        n_candidates=int(candidates.numel()),
        method=method,
        timings={"broad": t1 - t0, "narrow": t2 - t1, "normals": time.perf_counter() - t2},
    )


def solve_candidates(sdf, solve_sdf, local: torch.Tensor, faces: torch.Tensor, f_vertices: torch.Tensor, margin: float,
                     method: str, iters: int | None, polish: bool = True, refine: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The narrow phase on the candidate faces (C, 3) into ``local`` (V, 3) (the SDF's frame): bary (C, 3), depths (C,).

    ``f_vertices`` (V,): f at ``local`` where the broad phase has it (NaN elsewhere). Triangles far larger
    than the SDF are solved on their pieces near it (:mod:`zoo.large_triangles`), each keeping its lowest
    piece's answer; a triangle with no piece left gets its centroid and, as depth, a lower bound of f
    over it that exceeds the margin. Otherwise depths are ``solve_sdf`` at the answers.
    """
    tri = local[faces]
    pieces = cut_large(sdf, tri, margin, f_vertices[faces])
    if pieces is not None:  # the pieces as a mesh of their own: their corners, with the values the cut evaluated
        local, inverse = unique_rows(pieces.triangles.reshape(-1, 3))
        f_vertices = torch.full(local.shape[:1], math.nan, dtype=local.dtype, device=local.device)
        known = ~torch.isnan(pieces.values.reshape(-1))
        f_vertices[inverse[known]] = pieces.values.reshape(-1)[known]
        faces, tri = inverse.reshape(-1, 3), pieces.triangles
        if tri.shape[0] == 0:  # every piece proven above the margin
            return torch.full((pieces.floor.shape[0], 3), 1 / 3, dtype=tri.dtype, device=tri.device), pieces.floor
    depths = None
    if method == "amortized" and callable(getattr(sdf, "detect_mesh", None)):
        bary, depths = _amortized_mesh(sdf, local, faces, tri, f_vertices, margin, polish)
    else:
        bary = _narrow_phase(solve_sdf, sdf, tri, method, iters)
    if refine:
        bary, depths = _solvers().frank_wolfe(solve_sdf, tri, iters=refine, init=bary), None
    if depths is None:
        depths = torch.as_tensor(solve_sdf(bary_to_points(tri, bary))).reshape(-1).to(tri)
    if pieces is None:
        return bary, depths
    best = best_pieces(depths, pieces.parent, pieces.floor.shape[0])
    found = (best >= 0).nonzero().squeeze(-1)
    parent_bary = torch.full((pieces.floor.shape[0], 3), 1 / 3, dtype=tri.dtype, device=tri.device)
    parent_bary[found] = pieces.to_parent(best[found], bary[best[found]])
    parent_depths = pieces.floor.clone()
    parent_depths[found] = torch.minimum(depths[best[found]], pieces.floor[found])  # the floor only where above the margin
    return parent_bary, parent_depths


def _amortized_mesh(sdf, local: torch.Tensor, faces: torch.Tensor, tri: torch.Tensor, f_vertices: torch.Tensor,
                    margin: float, polish: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The amortized narrow phase on the candidates as an indexed mesh: (bary (C, 3), depths (C,)).
    ``f_vertices`` (V,): the broad phase's distances at ``local``'s vertices, NaN where not evaluated."""
    bary, depths = sdf.detect_mesh(local, faces, cutoff=margin, vertex_values=f_vertices, polish=polish)
    bary, depths = torch.as_tensor(bary).to(tri), torch.as_tensor(depths).reshape(-1).to(tri)
    if bary.shape != tri.shape[:2] or depths.shape != tri.shape[:1] or not bool(torch.isfinite(bary).all()):
        raise InputError(
            f"{type(sdf).__name__}.detect_mesh returned {tuple(bary.shape)} barycentrics (or non-finite values) for "
            f"{tri.shape[0]} triangles; it must return finite barycentrics (M, 3) and distances (M,)"
        )
    return bary, depths


def contact_normals(sdf, points: torch.Tensor) -> torch.Tensor:
    """Unit gradients (K, 3) of ``sdf`` at the contact points (K, 3); zeros where the gradient vanishes."""
    if points.shape[0] == 0:
        return points.new_zeros((0, 3))
    _, grads = sdf.value_and_grad(points)
    return torch.nn.functional.normalize(torch.as_tensor(grads).to(points), dim=-1)


def _narrow_phase(solve_sdf, sdf, triangles: torch.Tensor, method: str, iters: int | None) -> torch.Tensor:
    """Barycentrics (C, 3) of each candidate triangle's minimum by ``method``."""
    if method == "amortized":
        bary = torch.as_tensor(sdf.detect(triangles)).to(triangles)
        if bary.shape != triangles.shape[:2] or not bool(torch.isfinite(bary).all()):
            raise InputError(
                f"{type(sdf).__name__}.detect returned {tuple(bary.shape)} (or non-finite values) for "
                f"{triangles.shape[0]} triangles; it must return finite barycentrics (M, 3)"
            )
        return bary
    solvers = _solvers()
    if method == "pgd":
        return solvers.projected_gradient(solve_sdf, triangles, iters=iters)
    return solvers.frank_wolfe(solve_sdf, triangles, iters=iters)


def _solvers():
    from . import solvers  # imported late: collide only needs it once there are candidates

    return solvers


# -- the voxel cache ------------------------------------------------------------------------

_VOXEL_CACHE_SIZE = 2  # grids at 256^3 are 64 MiB each; keep the working set small
_voxel_cache: dict[tuple[int, tuple], tuple[object, object]] = {}


def voxel_of(sdf, resolution):
    """The cached ``VoxelSDF`` of ``sdf`` at ``resolution``; built on first use.

    Keyed by the SDF object's identity; the cache holds the SDF itself so its id cannot be
    reused while the entry lives. An SDF changed in place (new codes, new parameters) needs
    :func:`clear_voxel_cache`.
    """
    from .voxel import VoxelSDF, resolution_per_axis

    if isinstance(sdf, VoxelSDF):
        return sdf  # already a grid: solving on a grid of a grid would only blur it
    hit = _voxel_cache.get((id(sdf), resolution_per_axis(resolution)))
    grid = VoxelSDF(sdf, resolution=resolution) if hit is None else hit[1]
    install_voxel_grid(sdf, resolution, grid)  # re-inserted last: the dict's order is the recency order
    return grid


def install_voxel_grid(sdf, resolution, grid) -> None:
    """Make ``grid`` (a ``VoxelSDF``) the cached grid of ``sdf`` at ``resolution``, in place of one built over the
    whole of ``sdf.bounds`` on first use: for a caller that samples only the part of the grid it needs."""
    from .voxel import resolution_per_axis

    key = (id(sdf), resolution_per_axis(resolution))
    _voxel_cache.pop(key, None)
    _voxel_cache[key] = (sdf, grid)  # the SDF held: its id cannot be reused while the entry lives
    while len(_voxel_cache) > _VOXEL_CACHE_SIZE:
        _voxel_cache.pop(next(iter(_voxel_cache)))


def clear_voxel_cache() -> None:
    """Forget every cached voxel grid of ``collide(method="voxel-fw")``."""
    _voxel_cache.clear()


# -- input checks ---------------------------------------------------------------------------


def mesh_tensors(mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """Validated vertices (V, 3) float and faces (F, 3) int64 from a mesh or a (V, F) pair; an empty mesh is no error."""
    vertices, faces = mesh_pair(mesh)
    vertices = as_points(vertices, "mesh vertices", allow_empty=True)
    return vertices, as_faces(faces, vertices.shape[0]).to(vertices.device)


def empty_contacts(triangles: torch.Tensor, n_triangles: int, method: str) -> Contacts:
    z = triangles.new_zeros
    return Contacts(
        points=z((0, 3)),
        depths=z((0,)),
        normals=z((0, 3)),
        triangles=torch.zeros(0, dtype=torch.int64, device=triangles.device),
        bary=z((0, 3)),
        n_triangles=int(n_triangles),
        n_candidates=0,
        method=method,
    )
