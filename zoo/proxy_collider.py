"""One SDF-mesh pair collided step after step on the SDF's baked proxy: queries that scale with the contacts kept.

:class:`ProxyCollider` is what ``zoo.CoherentCollider(proxy=...)`` and a simulation's mesh pairs run. Steps 1 to 3 of a call run as one
compiled loop over the mesh's faces near the SDF (:mod:`zoo.proxy_kernel`, the default ``kernel="numba"``), or as a
fixed handful of vectorised numpy passes, each with one proxy read (:meth:`zoo.proxy.ProxySDF.read_numpy`) for all
the faces (``kernel="numpy"``: :func:`zoo.proxy_search.numpy_search`, the reference the compiled loop is tested
against); neither loops over faces in Python:

1. **Clusters.** The faces are sorted along a Morton curve once and cut into clusters of ``CLUSTER`` faces, each
   with a bounding ball. A cluster whose ball lies beyond the SDF's bounds grown by the search margin, or whose
   proxy value at its centre, less L times its radius, exceeds the search margin, holds no contact (L: the
   proxy's Lipschitz bound; f >= proxy - error_bound in band, and the proxy is a lower bound of f out of band).
2. **Faces.** The proxy at the vertices of the clusters' faces, and each face's Lipschitz lower bound from its
   three values (:func:`zoo.bounds.triangle_reach`): a face it puts above the search margin holds no contact.
3. **Search.** A face whose lowest vertex is a KKT point on the proxy (its Frank-Wolfe gap below ``CONVERGED_GAP``
   of the margin) has that vertex as its answer; one the screen (:func:`zoo.coherence.screen_bound`'s bound) puts
   above the search margin is dropped. The others start from their last answer (a warm start; not read again where
   it is a corner: its read is that vertex's) or, new, from the lowest of ``PATTERN``'s inner points and, on a face
   at least ``LINE_START_CELLS`` proxy cells long, of points along its length (:func:`zoo.proxy_search.line_starts`:
   a long sliver's minima lie between the pattern's points), and take up to ``SEARCH_STEPS`` projected-gradient
   steps (``WARM_SEARCH_STEPS`` for a warm one), each a line search to where the steepest descent inside the
   triangle leaves it (two reads; one where the parabola's minimiser is the segment's end), leaving the search as
   the gap or the screen settles them. A point out of the proxy's band takes no step: there the read is a bound,
   f(c) - L |p - c| from its brick's centre c, and its gradient the one at c, so a step along it does not follow
   the values read (docs/proxy.md).
4. **Contacts.** The faces whose proxy minimum is within the margin plus the proxy's ``error_bound`` are the
   proxy's contacts. The SDF itself then answers them (or, ``deferred``, the rows the caller keeps: a simulation
   reduces them to a manifold first): its value and gradient at the proxy's minimiser; where the SDF's Frank-Wolfe
   gap there exceeds ``POLISH_GAP_FRACTION`` of the margin, one step along the SDF's steepest descent inside the
   face, its length chosen on the proxy, and the SDF's value and gradient at its end, kept where lower; where the
   proxy's minimiser lies out of its band (a penetration deeper than the band, or a face above it within a
   speculative margin), where the proxy holds only a bound, the SDF's own descent from the lowest of that point and
   the face's corners (:meth:`ProxyCollider._out_of_band`). Colliders on one SDF and proxy answer together (:func:`exact_contacts_together`: a simulation step's
   pairs on one body ask the SDF once). A face that moved less than ``reuse_distance`` since the SDF answered it keeps that answer, its
   depth moved to first order along its normal (a persistent contact). Every contact's point, depth and normal
   are the SDF's.

Between full searches. A full search also keeps its answers on the faces within ``L * reuse_distance`` above the
search margin (a motion of ``reuse_distance`` cannot bring another face within it); while no point of the mesh that
can reach the SDF's bounding ball grown by the search margin has moved more than ``reuse_distance`` relative to the
SDF since (:meth:`ProxyCollider._moved_at_most`: a large mesh's far parts, which move most when the pose turns,
cannot reach it), a call carries those answers, their values moved to first order along their normals, with no read
at all (``stats.reused``): a persistent contact manifold, as the SDF's own answers are kept below.

Held faces (``hold``, the compiled passes). Each full search leaves every face it settled a bound on the proxy's
minimum over it (its Lipschitz bound, the screen's or the search's answer less its Frank-Wolfe gap), and each
cluster the least of its faces'; every call adds to each cluster how far its points can have moved relative to the
SDF (:class:`_FaceBounds`). A face (a whole cluster) whose bound, less L times its motion since, stays above the
search margin is passed over with no read: the faces far from the contacts cost nothing step after step, and the
work goes where the bounds run out. A search that cannot move from a face's corner or along a needle moves towards
Frank-Wolfe's vertex instead, so that such faces settle (and are held) rather than stay open.

Thinning (``thin``, with ``deferred``: what ``zoo.sim`` sets). A simulation keeps, of a pair's contacts, at most
the deepest per cell of its reduction's grid among those its filters let through: a call then returns only those
within its ``band`` of the deepest (:class:`Thinning`, :func:`zoo.proxy_kernel.thinned_rows`), so a finer mesh,
with more faces within the margin, does not cost the caller more rows. Inside, the faces lie cluster after cluster and the vertices in the order the
faces first use them (``_face_id`` maps back to the mesh's faces): a cluster's faces are neighbours in memory.

Why clusters and not a carried bound per vertex (what :class:`zoo.CoherentCollider` does on the SDF itself): on
the proxy a read costs what the bookkeeping of a carried bound would, so one read per cluster and per face near it
is the cheaper proof, and it needs no state but the last answers (the search's warm starts and the kept contacts).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from .bounds import triangle_reach
from .collider import POLISH_GAP_FRACTION, REUSE_FRACTION, CoherenceStats, moved_along_normal
from .collision import ContactArrays, Contacts, mesh_tensors
from .errors import InputError
from .geometry import face_normals, invert_pose, row_norms, unit_rows
from .proxy import IN_BAND, UNKNOWN
from .proxy_search import FaceMemory, ProxyAnswers, SearchCall, SearchMesh, counted_read, line_starts, numpy_search
from .sdf import query_dtype, value_and_grad_numpy
from .simplex import descent_segment, frank_wolfe_gap, on_simplex
from .validation import as_pose_array, non_negative_float

if TYPE_CHECKING:  # numba loads with zoo.contact_filters, where a thinning runs
    from .contact_filters import Closing

CLUSTER = 32  # faces per cluster of the first cull
# projected-gradient steps on the proxy, at most, per face and call: a face new to the search takes several; one
# searched at the last step goes on from its answer there, so one step a call carries its descent along
SEARCH_STEPS, WARM_SEARCH_STEPS = 3, 1
CONVERGED_GAP = 0.02  # a face whose Frank-Wolfe gap on the proxy is below this fraction of the margin stops searching
KERNELS = ("numba", "numpy")  # how the per-face passes run: compiled (zoo.proxy_kernel), or numpy passes
POLISH_SAMPLES = 8  # points on the proxy along the SDF's steepest descent that choose a polishing step's length
DEEP_STEPS = 12  # the most steps of the SDF's own descent on a face out of the proxy's band
DEEP_GAP_FRACTION = 1e-2  # ... which stops where its Frank-Wolfe gap is within this fraction of the margin
# The search's starts (barycentric): the vertices, the edges' midpoints and three inner points, so that a minimum in
# any part of the face has a start near it; the last answer is added per face.
PATTERN = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5],
                    [4 / 6, 1 / 6, 1 / 6], [1 / 6, 4 / 6, 1 / 6], [1 / 6, 1 / 6, 4 / 6], [1 / 3, 1 / 3, 1 / 3]])


@dataclass(frozen=True)
class Thinning:
    """How a ``deferred`` collider thins its proxy contacts before it returns them (``ProxyCollider.thin``): per cell
    of side ``cell`` (m, the world's integer grid), the contacts a simulation can use within ``band`` (m) of the
    deepest of them (0: the deepest and its equals; twice the proxy's ``error_bound``: every one that may be the
    SDF's deepest, for a reduction on the SDF's depths), those that
    face their faces (the normal, the proxy's, within |cos| ``touching_cos`` of the face's where the depth is at
    most 0, ``separated_cos`` beyond; a degenerate face always does) and, separated, close within the time
    (``closing``, a :class:`zoo.contact_filters.Closing` (u, w, seconds): u + w x p is the SDF body's velocity less
    the mesh's at the world point p, and a contact at depth d > 0 counts where (u + w x p) . n * seconds >= d; None:
    every one counts), each test taking a depth at its least, the depth less ``slack`` (m: the proxy's error bound,
    as a simulation sets it). These are :func:`zoo.contact_filters.usable`'s tests, as a simulation applies them to
    every pair's proxy contacts, and its reduction keeps at most the deepest per such cell of what they let through:
    the rest would cost it work per row for nothing (a finer mesh puts more faces within the margin, not more
    contacts in the manifold). With a ``near_miss`` (m), the contacts these tests drop but would keep with the depth
    taken that much further below are kept too, in cells of their own: the deepest of them per cell, beside the
    deepest of the others (a simulation's near misses, :func:`zoo.sim.pairs.proxy_near_miss`)."""

    cell: float
    touching_cos: float
    separated_cos: float
    closing: Closing | None = None
    band: float = 0.0
    slack: float = 0.0
    near_miss: float = 0.0


class ProxyCollider:
    """An SDF-mesh pair on the SDF's proxy (see the module docstring); the interface of :class:`zoo.CoherentCollider`.

    Args:
        sdf: the SDF the contacts are answered on (any SDF protocol object).
        mesh: a ``trimesh.Trimesh`` or a ``(vertices (V, 3), faces (F, 3))`` pair, fixed for the pair's life.
        proxy: the SDF's :class:`zoo.proxy.ProxySDF`.
        margin: m, contacts within it are reported.
        method: the narrow phase the contacts name (``proxy+method``); the SDF answers every face itself, from the
            proxy's minimiser (see the module docstring), whatever the method.
        reuse_distance: m; a face that moved less than this (relative to the SDF) since the SDF answered it keeps
            that answer, its depth moved along its normal; default ``REUSE_FRACTION`` of the margin; 0 answers anew.
        deferred: a call returns the proxy's contacts, and :meth:`exact_contacts` the SDF's for the rows kept.
        kernel: how the per-face passes run: ``"numba"`` compiled (:mod:`zoo.proxy_kernel`, the default) or
            ``"numpy"`` (the reference the compiled passes are tested against; the same answers, slower).
        hold: with the compiled passes, a face (a cluster) whose bound from its last answer, less L times how far
            it has moved since, stays above the search margin is passed over with no read (see the module
            docstring); False answers every face near the SDF at every full search, as the numpy passes do.
        thin: with ``deferred``, a :class:`Thinning`: a call returns, per cell, only the proxy contacts a
            simulation's reduction can keep (None: every face within the margin).
    """

    def __init__(self, sdf, mesh, proxy, margin: float = 1e-3, method: str = "amortized", *,
                 reuse_distance: float | None = None, deferred: bool = False, kernel: str = "numba",
                 hold: bool = True, thin: Thinning | None = None):
        if not callable(getattr(proxy, "read_numpy", None)) or not hasattr(proxy, "error_bound"):
            raise InputError(f"proxy= takes True or a zoo.proxy.ProxySDF, got {type(proxy).__name__}")
        self.sdf, self.proxy, self.method = sdf, proxy, method
        self.margin = non_negative_float(margin, "margin")
        self.reuse_distance = (REUSE_FRACTION * self.margin if reuse_distance is None
                               else non_negative_float(reuse_distance, "reuse_distance"))
        self.deferred = bool(deferred)
        if kernel not in KERNELS:
            raise InputError(f"kernel= takes one of {', '.join(KERNELS)}, got {kernel!r}")
        self.kernel, self.hold = kernel, bool(hold)
        if thin is not None and not isinstance(thin, Thinning):
            raise InputError(f"thin= takes a zoo.proxy_collider.Thinning or None, got {type(thin).__name__}")
        self.thin = thin
        self.reported_method = f"proxy+{method}"
        self._dtype = query_dtype(sdf)  # the SDF's queries
        vertices, faces = mesh_tensors(mesh)
        self.vertices, self.faces = vertices, faces  # torch, for the caller
        v, f = vertices.detach().cpu().numpy().astype(np.float64), faces.cpu().numpy()
        clusters, self._cluster_centre, self._cluster_radius = _clusters(v[f], v[f].mean(axis=1))
        # Inside, the faces lie cluster after cluster and the vertices in the order the faces first use them: a
        # cluster's faces are then neighbours in memory, where the mesh's own order scatters them (on a large mesh
        # the compiled loop's cache misses cost more than its arithmetic). _face_id maps them back to the mesh's.
        self._face_id = clusters[clusters >= 0]  # (F,) the mesh's index of each face inside
        self._clusters = np.where(clusters >= 0, np.arange(clusters.size).reshape(clusters.shape), -1)
        self._f, self._v = _by_first_use(f[self._face_id], v)  # (F, 3), (V', 3) mesh frame
        corners = self._v[self._f]  # (F, 3, 3)
        self._reach, self._ball = (t.numpy() for t in triangle_reach(torch.from_numpy(corners)))  # (F, 3), (F,)
        self._normal = face_normals(corners)  # (F, 3) unit, mesh frame (zeros: degenerate)
        lo, hi = (np.asarray(torch.as_tensor(b, dtype=torch.float64).cpu()).reshape(3) for b in proxy.bounds)
        self._lo, self._hi = lo, hi
        self._mesh = SearchMesh(self._f, self._v, self._reach, self._ball, self._clusters, self._cluster_centre,
                                self._cluster_radius, *line_starts(corners, proxy.spacing))
        self._sdf_centre, self._sdf_radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2  # its bounding ball
        self.stats, self.last_stats = CoherenceStats(), CoherenceStats()
        self.reset()
        if kernel == "numba":
            self._compile_kernels()

    def _compile_kernels(self) -> None:
        """The compiled passes compiled (or loaded from numba's cache) now, not in the first step that meets them: the
        clusters' motion, the search, the thinning, the polish, the Frank-Wolfe gaps, the SDF's own descent, the world
        contacts and a NeuralSDF's few-point network, on no face."""
        from .proxy_kernel import add_cluster_motion, along_descent, frank_wolfe_gaps

        identity = np.eye(4)  # as a call's pose is passed (views of a 4x4): one compiled version
        add_cluster_motion(np.zeros(0), np.zeros((0, 3)), np.zeros(0), identity, identity)
        found = self._compiled_search(self._search_call(identity[:3, :3], identity[:3, 3], self.margin, self.margin,
                                                        n_clusters=0), CoherenceStats())
        thin, self.thin = self.thin, Thinning(cell=self.margin, touching_cos=0.0, separated_cos=0.0)
        self._thinned(identity, identity[:3, :3], self.margin, found)
        self.thin = thin
        self._compiled_polish(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)), CoherenceStats())
        frank_wolfe_gaps(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
        along_descent(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.ones(POLISH_SAMPLES), np.ones(0))
        self._contacts(identity, np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0),
                       np.zeros((0, 3)))
        value_and_grad_numpy(self.sdf, np.zeros((1, 3)), self._dtype)

    def reset(self) -> None:
        """Forget the last answers (the next call searches from the pattern alone); ``stats`` are kept."""
        n = len(self._f)
        self._last_bary = np.full((n, 3), np.nan)  # (F, 3) each face's last proxy answer, the search's warm start (NaN: none)
        self._answers = _SDFAnswers.empty(n)  # the SDF's last answer per face
        self._pending = None  # the last call's proxy contacts (_ProxyContacts), for the SDF to answer
        self._carried = None  # the last full search's answers within its net (_CarriedSearch), carried while the motion is small
        self._buffers = None  # the compiled passes' buffers (zoo.proxy_kernel.KernelBuffers), made at their first call
        self._stamp = 0  # the compiled passes' last call (KernelBuffers.vertex_stamp)
        self._bounds = _FaceBounds.empty(len(self._clusters), n)  # how far each cluster moved, and the faces' bounds
        self._last_faces = np.zeros(0, dtype=np.int64)  # the faces the last call kept (the collider's order)

    @property
    def last_candidates(self) -> torch.Tensor:
        """(C,) int64: the faces (the mesh's numbering) the last call kept as its proxy contacts."""
        return torch.from_numpy(self._face_id[self._last_faces])

    # -- a step --------------------------------------------------------------------------------------------------

    def __call__(self, sdf_pose=None, mesh_pose=None, margin: float | None = None) -> Contacts:
        """Contacts at these poses (4x4 world-from-object, None: identity), as ``zoo.collide`` gives them (the proxy's,
        when ``deferred``); ``margin`` replaces the collider's for this call."""
        arrays = self.collide_arrays(as_pose_array(sdf_pose, "sdf_pose"), as_pose_array(mesh_pose, "mesh_pose"), margin)
        return arrays.to_contacts(self.vertices.dtype)

    def collide_arrays(self, sdf_pose: np.ndarray, mesh_pose: np.ndarray, margin: float | None = None) -> ContactArrays:
        """:meth:`__call__` in numpy, for a simulation's step: the poses float64 (4, 4) rigid transforms, taken as given
        (``__call__`` checks them), the contacts as :class:`zoo.collision.ContactArrays`."""
        margin = self.margin if margin is None else non_negative_float(margin, "margin")
        stats = CoherenceStats(steps=1)
        t0 = time.perf_counter()
        relative = invert_pose(sdf_pose) @ mesh_pose
        rotation, shift = relative[:3, :3], relative[:3, 3]
        self._bounds.move(relative, self._cluster_centre, self._cluster_radius)
        search = margin + self.proxy.error_bound
        carried = self._carried
        if (carried is not None and carried.search == search
                and self._moved_at_most(carried.relative, relative, search) <= self.reuse_distance):
            t1 = time.perf_counter()
            found = carried.carried(self._v[self._f[carried.answers.faces]] @ rotation.T + shift)
            stats.reused = len(found.faces)
        else:
            # the faces a motion of reuse_distance cannot bring within the search margin are left out of what is held
            net = search + self.proxy.lipschitz * self.reuse_distance
            call = self._search_call(rotation, shift, search, net)
            if self.kernel == "numba":
                found = self._compiled_search(call, stats)
            else:
                found = numpy_search(call, self._mesh, self.proxy, self._memory(), stats)
            t1 = time.perf_counter()
            self._carried = _CarriedSearch(relative, search, found)
        if self.deferred and self.thin is not None:
            found = self._deep_rows_valued(found, stats)
            found = found.take(self._thinned(sdf_pose, rotation, search, found))
        else:
            found = found.take(np.flatnonzero(found.values <= search))
        self._pending = _ProxyContacts(sdf_pose, found.faces, found.tri, found.bary, found.status, margin)
        self._last_faces = found.faces
        t2 = time.perf_counter()
        if self.deferred:
            contacts = self._contacts(sdf_pose, found.faces, found.tri, found.bary, found.values, found.grads)
        else:
            contacts = self._exact(np.arange(len(found.faces)), stats)
        contacts.n_candidates = int(stats.candidates)
        contacts.timings = {"broad": t1 - t0, "narrow": t2 - t1, "normals": time.perf_counter() - t2}
        self.last_stats = stats
        self.stats.add(stats)
        return contacts

    def _deep_rows_valued(self, found: ProxyAnswers, stats: CoherenceStats) -> ProxyAnswers:
        """``found`` with the SDF's values and gradients at its rows deeper than the band (``UNKNOWN``), before the
        thinning compares depths: there the proxy's value is only a lower bound, which can lie far below the SDF's
        minimum, so a cell's deepest by it may not be the SDF's (an impact of gear teeth). One query at the proxy's
        minimisers, not a search: the rows kept are answered in full afterwards. ``found`` itself is left as it is
        (a carried search holds it)."""
        deep = np.flatnonzero(found.status == UNKNOWN)
        if not deep.size:
            return found
        values, grads = self._sdf_at(np.einsum("dv,dvc->dc", found.bary[deep], found.tri[deep]), stats)
        return found.with_values(deep, values, grads)

    def _thinned(self, sdf_pose, rotation, search: float, found: ProxyAnswers) -> np.ndarray:
        """The rows (K,) of ``found`` that are proxy contacts (at most ``search``) and that ``thin`` keeps (see
        :class:`Thinning`)."""
        from .proxy_kernel import thinned_rows

        thin = self.thin
        shift, turn, seconds = (np.zeros(3), np.zeros(3), -1.0) if thin.closing is None else thin.closing
        return thinned_rows(found.values, found.bary, found.tri, found.grads, found.faces, search, self._normal,
                            rotation, sdf_pose[:3, :3], sdf_pose[:3, 3], thin.cell, thin.touching_cos, thin.separated_cos,
                            np.asarray(shift, dtype=np.float64), np.asarray(turn, dtype=np.float64), float(seconds),
                            float(thin.band), float(thin.slack), float(thin.near_miss))

    def exact_contacts(self, rows) -> Contacts:
        """With ``deferred``: the SDF's own contacts at the rows ``rows`` (R,) of the last call's (proxy) contacts, in
        the order given, less those whose SDF depth is beyond that call's margin (world frame)."""
        return exact_contacts_together([(self, rows)])[0]

    def _answer_key(self) -> tuple:
        """Colliders with the same key answer their faces alike and may ask the SDF together."""
        return (id(self.sdf), id(self.proxy), self._dtype)

    def _moved_at_most(self, then: np.ndarray, now: np.ndarray, search: float) -> float:
        """A bound (m) of how far a mesh point that can now lie within ``search`` of the SDF's bounding ball (centre s,
        radius R, SDF frame) moved relative to the SDF between the relative poses ``then`` and ``now`` (4x4 SDF-from-mesh).

        A point p of the mesh at distance D from s then moved by (A - A') p + b - b' <= a D + c, with a = ||A - A'||_F
        and c = |(A - A') m + b - b'| for m the mesh point at s then; it is now within R + search of s only if
        D - a D - c <= R + search, so D <= D0 = (R + search + c) / (1 - a), and it moved at most a D0 + c (infinite for
        a >= 1). Points farther cannot come near the SDF (no contact lies outside its bounds grown by the margin)."""
        turn = now[:3, :3] - then[:3, :3]
        a = float(row_norms(turn.reshape(-1)))  # |dR|_F
        if a >= 1:
            return math.inf
        at_centre = then[:3, :3].T @ (self._sdf_centre - then[:3, 3])  # m: the mesh point at s then (mesh frame)
        c = float(row_norms(turn @ at_centre + now[:3, 3] - then[:3, 3]))
        return a * (self._sdf_radius + search + c) / (1 - a) + c

    # -- the search (zoo.proxy_search, zoo.proxy_kernel) -------------------------------------------------------------

    def _search_call(self, rotation, shift, search: float, net: float, n_clusters: int | None = None) -> SearchCall:
        """A search at the pose (``rotation`` (3, 3), ``shift`` (3,): the mesh's in the SDF's frame) over the first
        ``n_clusters`` clusters (default: all): the faces whose proxy minimum may be at most ``search`` are searched,
        and those whose answer is at most ``net`` given."""
        return SearchCall(rotation, shift, search, net, CONVERGED_GAP * max(search, 1e-9), SEARCH_STEPS,
                          WARM_SEARCH_STEPS, len(self._clusters) if n_clusters is None else n_clusters, self._lo,
                          self._hi, PATTERN[3:], self.hold, self._stamp)

    def _memory(self) -> FaceMemory:
        bounds = self._bounds
        return FaceMemory(self._last_bary, bounds.cluster_motion, bounds.cluster_key, bounds.face_key)

    def _compiled_search(self, call: SearchCall, stats: CoherenceStats) -> ProxyAnswers:
        """:func:`zoo.proxy_search.numpy_search` as one compiled loop (:func:`zoo.proxy_kernel.search_faces`), passing
        over the faces held above the margin (``hold``); a lazy proxy's bricks the reads met not ready are made ready
        and the call made again, until none is met."""
        from . import proxy_kernel as kernel

        out, bounds, memory = self._kernel_buffers(), self._bounds, self._memory()
        # a pass that met bricks not ready is made again from the same held bounds: the keys it wrote are dropped,
        # so that the answer is the one a proxy with every brick ready gives (not one that depends on the cache)
        kept_keys = None if self.proxy.complete else (bounds.cluster_key.copy(), bounds.face_key.copy())
        retry = False
        while True:
            if retry:
                bounds.cluster_key[:], bounds.face_key[:] = kept_keys
            self._stamp += 1
            out.counts[:] = 0
            kernel.search_faces(call._replace(stamp=self._stamp), self._mesh, self.proxy.grid(), memory, out)
            counts = dict(zip(kernel.COUNTS.names, out.counts[0].item()))  # Python ints: a record's fields cost more
            missed = counts["missing"]
            if not missed:
                break
            self._make_ready(out.missing, missed)
            retry = True
        stats.faces_near, stats.faces_skipped = counts["faces_near"], counts["faces_skipped"]
        stats.candidates, stats.warm, stats.cold = counts["candidates"], counts["warm"], counts["cold"]
        stats.screened, stats.proxy_reads = counts["screened"], stats.proxy_reads + counts["reads"]
        searched = counts["searched"]
        self._last_bary[out.searched_face[:searched]] = out.searched_bary[:searched]
        n = counts["out"]
        # views: a search's answers stay as it wrote them until the next search, which replaces what carried them
        return ProxyAnswers(out.face[:n], out.tri[:n], out.bary[:n], out.value[:n], out.grad[:n], out.status[:n])

    def _kernel_buffers(self):
        """The compiled passes' :class:`zoo.proxy_kernel.KernelBuffers`, made at their first call."""
        if self._buffers is None:
            from .proxy_kernel import kernel_buffers

            self._buffers = kernel_buffers(len(self._v), len(self._f))
        return self._buffers

    def _make_ready(self, missing: np.ndarray, missed: int) -> None:
        """Bake the bricks a compiled pass recorded in ``missing`` (its first ``missed``, as
        :func:`zoo.proxy_kernel.read` writes them), so that the reads there answer when the pass is made again."""
        missing = missing[:min(missed, missing.size)]
        self.proxy.make_ready(missing[missing >= 0], coarse=-1 - missing[missing < 0])

    # -- the SDF's own answers -----------------------------------------------------------------------------------

    def _exact(self, rows: np.ndarray, stats: CoherenceStats) -> ContactArrays:
        """The SDF's contacts at the rows ``rows`` of the last call's proxy contacts (see the module docstring)."""
        request = self._exact_request(rows, stats)
        _answer_together(self, [request], stats)
        return self._exact_contacts(request)

    def _exact_request(self, rows: np.ndarray, stats: CoherenceStats) -> _ExactRequest:
        """The rows ``rows`` of the last call's proxy contacts, those whose SDF answer carries over (a persistent
        contact: its depth moved to first order along its normal) filled in, the others ``asked`` of the SDF."""
        pending = self._pending
        faces, tri, bary, status = pending.faces[rows], pending.tri[rows], pending.bary[rows].copy(), pending.status[rows]
        n = len(faces)
        stats.exact_faces += n
        values, grads = np.zeros(n), np.zeros((n, 3))
        kept = self._answers.unmoved(faces, tri, self.reuse_distance)
        k = np.flatnonzero(kept)
        if k.size:
            bary[k], values[k], grads[k] = self._answers.carried(faces[k], tri[k])
            stats.exact_kept += int(k.size)
        return _ExactRequest(faces, tri, bary, status, values, grads, np.flatnonzero(~kept), pending.margin)

    def _exact_contacts(self, request: _ExactRequest) -> ContactArrays:
        """The contacts of an answered request (world frame), the SDF's new answers stored."""
        r, a = request, request.asked
        if a.size:
            self._answers.store(r.faces[a], r.tri[a], r.bary[a], r.values[a], r.grads[a])
        contact = np.flatnonzero(r.values <= r.margin)
        return self._contacts(self._pending.sdf_pose, r.faces[contact], r.tri[contact], r.bary[contact], r.values[contact],
                              r.grads[contact])

    def _answer(self, tri, bary, status, margin, stats):
        """The SDF's answers on faces (A, 3, 3) from the proxy's minimisers ``bary`` (A, 3) (``status`` (A,) there),
        within ``margin`` (a float, or (A,) one per face): bary (A, 3), values (A,), gradients (A, 3)."""
        from .proxy_kernel import frank_wolfe_gaps

        bary = bary.copy()
        margin = np.asarray(margin, dtype=np.float64)
        if margin.ndim == 0:
            margin = np.full(len(tri), margin)
        f, g = self._sdf_at(np.einsum("av,avc->ac", bary, tri), stats)
        gap = frank_wolfe_gaps(tri, bary, g)
        out = status != IN_BAND  # the proxy holds only a bound there
        polish = np.flatnonzero((gap > POLISH_GAP_FRACTION * margin) & (f - gap <= margin) & ~out)
        if polish.size:
            b, f1, g1 = self._polish(tri[polish], bary[polish], g[polish], stats)
            lower = f1 < f[polish]
            rows = polish[lower]
            bary[rows], f[rows], g[rows] = b[lower], f1[lower], g1[lower]
        out = np.flatnonzero(out)
        if out.size:  # rare: a penetration deeper than the band, or a speculative margin wider than it
            bary[out], f[out], g[out] = self._out_of_band(tri[out], bary[out], f[out], g[out], margin[out], stats)
        return bary, f, g

    def _out_of_band(self, tri, bary, f, g, margin, stats):
        """The SDF's own descent on faces (D, 3, 3) whose proxy minimiser ``bary`` (D, 3) (``f`` (D,), ``g`` (D, 3) the
        SDF there) lies out of the proxy's band, where it holds only a bound: from the lowest of that point and
        the face's corners, up to ``DEEP_STEPS`` steps along the SDF's steepest descent inside the face, each to the
        lowest of ``POLISH_SAMPLES`` points along it (one query for all the faces; a step that finds none lower than
        where it stands tries again ``POLISH_SAMPLES`` times shorter), until the Frank-Wolfe gap is within
        ``DEEP_GAP_FRACTION`` of the ``margin`` (D,): -> bary (D, 3), values (D,), gradients (D, 3)."""
        from .proxy_kernel import along_descent

        stats.fallback += len(tri)
        bary, f, g = self._lowest_corner(tri, bary.copy(), f.copy(), g.copy(), stats)
        length = np.ones(len(tri))  # of the descent segment, as a fraction of the way to the face's boundary
        t = np.arange(1, POLISH_SAMPLES + 1) / POLISH_SAMPLES
        for _ in range(DEEP_STEPS):
            going = np.flatnonzero(frank_wolfe_gap(tri, bary, g) > DEEP_GAP_FRACTION * margin)
            if not going.size:
                break
            along = along_descent(tri[going], bary[going], g[going], t, length[going])  # (G, S, 3)
            values, grads = self._sdf_at(np.einsum("gsv,gvc->gsc", along, tri[going]).reshape(-1, 3), stats)
            values, grads = values.reshape(len(going), -1), grads.reshape(len(going), -1, 3)
            best = values.argmin(axis=1)
            at = np.arange(len(going))
            moved = values[at, best] < f[going]
            step = going[moved]
            bary[step], f[step], g[step] = along[at, best][moved], values[at, best][moved], grads[at, best][moved]
            length[going] = np.where(moved, 1.0, length[going] / POLISH_SAMPLES)
        return bary, f, g

    def _lowest_corner(self, tri, bary, f, g, stats):
        """``bary`` (D, 3), ``f`` (D,), ``g`` (D, 3) (updated in place and returned) moved to each face's (D, 3, 3)
        lowest corner where the SDF there is below ``f`` (one query)."""
        rows = np.arange(len(tri))
        f_corner, g_corner = self._sdf_at(tri.reshape(-1, 3), stats)
        f_corner, g_corner = f_corner.reshape(-1, 3), g_corner.reshape(-1, 3, 3)
        corner = f_corner.argmin(axis=1)
        lower = f_corner[rows, corner] < f
        bary[lower] = np.eye(3)[corner[lower]]
        f[lower], g[lower] = f_corner[rows, corner][lower], g_corner[rows, corner][lower]
        return bary, f, g

    def _polish(self, tri, bary, g, stats):
        """One step along the SDF's steepest descent inside each triangle (P, 3, 3) from ``bary`` (P, 3) (``g`` (P, 3) the
        SDF's gradient there), as far as the lowest of ``POLISH_SAMPLES`` points along it on the proxy (one read), and
        the SDF's value and gradient at that point (one query): -> bary (P, 3), values (P,), gradients (P, 3) there."""
        if self.kernel == "numba":
            end = self._compiled_polish(tri, bary, g, stats)
        else:
            along = _along_descent(tri, bary, g, np.arange(1, POLISH_SAMPLES + 1) / POLISH_SAMPLES, 1.0)  # (P, S, 3)
            values = counted_read(self.proxy, np.einsum("psv,pvc->psc", along, tri).reshape(-1, 3), stats)[0]
            end = along[np.arange(len(tri)), values.reshape(len(tri), -1).argmin(axis=1)]
        return (end, *self._sdf_at(np.einsum("pv,pvc->pc", end, tri), stats))

    def _compiled_polish(self, tri, bary, g, stats: CoherenceStats) -> np.ndarray:
        """:meth:`_polish`'s ends (P, 3) as one compiled pass (:func:`zoo.proxy_kernel.polish_ends`), the bricks its
        reads met not ready made ready and the pass made again."""
        from . import proxy_kernel as kernel

        out = self._kernel_buffers()
        while True:
            out.counts[:] = 0
            ends = kernel.polish_ends(tri, bary, g, POLISH_SAMPLES, self.proxy.grid(), out.missing, out.counts[0])
            missed = int(out.counts[0]["missing"])
            if not missed:
                break
            self._make_ready(out.missing, missed)
        stats.proxy_reads += int(out.counts[0]["reads"])
        return ends

    def _sdf_at(self, points: np.ndarray, stats: CoherenceStats) -> tuple[np.ndarray, np.ndarray]:
        """The SDF's values (N,) and gradients (N, 3), float64, at ``points`` (N, 3) in its frame, in one query."""
        stats.exact_points += len(points)
        return value_and_grad_numpy(self.sdf, points, self._dtype)

    def _contacts(self, sdf_pose, faces, tri, bary, depths, grads) -> ContactArrays:
        """Contacts in the world frame at ``bary`` (K, 3) on the ``faces`` (K,) at ``tri`` (K, 3, 3) (the SDF's frame),
        at ``depths`` (K,), their normals along the SDF-frame gradients ``grads`` (K, 3) (one compiled pass,
        :func:`zoo.proxy_kernel.world_contacts`)."""
        from .proxy_kernel import world_contacts

        points, normals = world_contacts(tri, bary, grads, sdf_pose[:3, :3], sdf_pose[:3, 3])
        return ContactArrays(points, depths, normals, self._face_id[faces], bary, n_triangles=len(self._f),
                             n_candidates=len(faces), method=self.reported_method)


def exact_contacts_together(requests) -> list[Contacts]:
    """:meth:`ProxyCollider.exact_contacts` for several colliders at once (see :func:`exact_arrays_together`)."""
    arrays = exact_arrays_together(requests)
    return [a.to_contacts(collider.vertices.dtype) for (collider, _), a in zip(requests, arrays)]


def exact_arrays_together(requests) -> list[ContactArrays]:
    """:meth:`ProxyCollider.exact_contacts` for several colliders at once (``requests``: (collider, rows (R,)) pairs,
    each collider a ProxyCollider or a CoherentCollider on one, called ``deferred`` first): the colliders that answer
    on the same SDF and proxy, in the same way, ask the SDF together, one query for all their faces (and one for all their polishing steps), as a step's pairs
    on one body do. The contacts of each, in the order given; each collider's stats count its own faces, the
    first of a group the group's queries."""
    requests = [(getattr(collider, "proxy_collider", collider), rows) for collider, rows in requests]  # a CoherentCollider's
    groups: dict[tuple, list[int]] = {}
    for i, (collider, _) in enumerate(requests):
        if collider._pending is None:
            raise InputError("exact_contacts answers the last call's proxy contacts: call the collider (proxy=, deferred=True) first")
        groups.setdefault(collider._answer_key(), []).append(i)
    out = [None] * len(requests)
    for members in groups.values():
        colliders = [requests[i][0] for i in members]
        stats = [CoherenceStats() for _ in members]
        asked = [c._exact_request(_row_indices(requests[i][1]), s)
                 for c, i, s in zip(colliders, members, stats)]
        _answer_together(colliders[0], asked, stats[0])
        for i, collider, request, s in zip(members, colliders, asked, stats):
            out[i] = collider._exact_contacts(request)
            collider.last_stats.add(s)
            collider.stats.add(s)
    return out


def _answer_together(collider: ProxyCollider, requests: list[_ExactRequest], stats: CoherenceStats) -> None:
    """The SDF's answers to every request's ``asked`` rows, in one :meth:`ProxyCollider._answer` of ``collider``."""
    parts = [(r.tri[r.asked], r.bary[r.asked], r.status[r.asked], np.full(r.asked.size, r.margin)) for r in requests]
    tri, bary, status, margins = (np.concatenate(column) for column in zip(*parts))
    if not margins.size:
        return
    bary, values, grads = collider._answer(tri, bary, status, margins, stats)
    start = 0
    for r in requests:
        end = start + r.asked.size
        r.answered(bary[start:end], values[start:end], grads[start:end])
        start = end


@dataclass
class _ExactRequest:
    """Proxy contacts the SDF answers (:meth:`ProxyCollider._exact_request`): ``faces`` (R,), ``tri`` (R, 3, 3) SDF
    frame, the proxy's ``bary`` (R, 3) and ``status`` (R,), the answers so far ``values`` (R,) and ``grads`` (R, 3)
    (the carried ones filled in), the rows ``asked`` of the SDF, and the call's ``margin``."""

    faces: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    status: np.ndarray
    values: np.ndarray
    grads: np.ndarray
    asked: np.ndarray
    margin: float

    def answered(self, bary: np.ndarray, values: np.ndarray, grads: np.ndarray) -> None:
        """The SDF's answers (bary (A, 3), values (A,), gradients (A, 3)) at the rows ``asked``."""
        self.bary[self.asked], self.values[self.asked], self.grads[self.asked] = bary, values, grads


@dataclass
class _ProxyContacts:
    """One call's proxy contacts, for the SDF to answer (:meth:`ProxyCollider.exact_contacts`): ``sdf_pose`` (4, 4),
    ``faces`` (K,), ``tri`` (K, 3, 3) SDF frame, ``bary`` (K, 3) the proxy's minimisers, ``status`` (K,) the proxy's
    there, and the call's ``margin``."""

    sdf_pose: np.ndarray
    faces: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    status: np.ndarray
    margin: float


@dataclass
class _SDFAnswers:
    """The SDF's last answer per face (F of them): ``bary`` (F, 3), ``value`` (F,) (NaN: none), ``grad`` (F, 3), and
    ``at`` (F, 3, 3) the face in the SDF's frame when it was answered."""

    bary: np.ndarray
    value: np.ndarray
    grad: np.ndarray
    at: np.ndarray

    @classmethod
    def empty(cls, n: int) -> _SDFAnswers:
        return cls(np.zeros((n, 3)), np.full(n, np.nan), np.zeros((n, 3)), np.zeros((n, 3, 3)))

    def unmoved(self, faces: np.ndarray, tri: np.ndarray, reuse_distance: float) -> np.ndarray:
        """(K,) bool: the faces ``faces`` (K,), now at ``tri`` (K, 3, 3), have an answer and moved at most
        ``reuse_distance`` since."""
        if not len(faces):
            return np.zeros(0, dtype=bool)
        moved = row_norms(tri - self.at[faces]).max(axis=-1)
        return np.isfinite(self.value[faces]) & (moved <= reuse_distance)

    def carried(self, faces: np.ndarray, tri: np.ndarray):
        """The answers of the faces ``faces`` (K,) now at ``tri`` (K, 3, 3), their values moved to first order along
        their normals: bary (K, 3), values (K,), gradients (K, 3)."""
        b, g = self.bary[faces], self.grad[faces]
        return b, moved_along_normal(self.value[faces], unit_rows(g), tri, self.at[faces], b), g

    def store(self, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray, values: np.ndarray, grads: np.ndarray) -> None:
        self.bary[faces], self.value[faces], self.grad[faces], self.at[faces] = bary, values, grads, tri


@dataclass
class _FaceBounds:
    """What lets the compiled passes pass over faces held above the margin (``ProxyCollider(hold=True)``): the
    relative pose (4, 4) of the last call (None: none yet), ``cluster_motion`` (C,) how far each cluster's points
    have moved relative to the SDF over the calls (m, the sum of each call's bound), ``cluster_key`` (C,) and
    ``face_key`` (F,) (:func:`zoo.proxy_kernel.search_faces` writes them: a bound on the proxy's minimum plus L
    times the cluster's motion then; -inf: none)."""

    relative: np.ndarray | None
    cluster_motion: np.ndarray
    cluster_key: np.ndarray
    face_key: np.ndarray

    @classmethod
    def empty(cls, n_clusters: int, n_faces: int) -> _FaceBounds:
        return cls(None, np.zeros(n_clusters), np.full(n_clusters, -np.inf), np.full(n_faces, -np.inf))

    def move(self, relative: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> None:
        """Add to each cluster (centres (C, 3), radii (C,), mesh frame) how far its points moved from the last
        call's relative pose to ``relative`` (4, 4): |dR m + dt| + |dR|_F r for dR, dt the change of rotation and
        shift."""
        if self.relative is not None:
            from .proxy_kernel import add_cluster_motion

            add_cluster_motion(self.cluster_motion, centres, radii, relative, self.relative)
        self.relative = relative


@dataclass
class _CarriedSearch:
    """A full search's ``answers`` on the faces within its net: what later calls carry while the mesh moves less
    than ``reuse_distance`` relative to the SDF (a persistent contact manifold), their values moved to first order
    along their normals. ``relative``: the 4x4 SDF-from-mesh pose then; ``search``: the search margin then."""

    relative: np.ndarray
    search: float
    answers: ProxyAnswers

    def carried(self, tri: np.ndarray) -> ProxyAnswers:
        """The answers with the faces now at ``tri`` (H, 3, 3) (the SDF's frame)."""
        a = self.answers
        return ProxyAnswers(a.faces, tri, a.bary, moved_along_normal(a.values, unit_rows(a.grads), tri, a.tri, a.bary),
                            a.grads, a.status)


# -- geometry in numpy (a step's few faces: numpy's per-call cost is a fraction of torch's) ---------------------------


def _clusters(corners: np.ndarray, centroids: np.ndarray, size: int = CLUSTER):
    """Faces (F,) cut into clusters along a Morton curve of their centroids: (clusters (C, size) face indices, -1
    padding; centres (C, 3); radii (C,) of balls holding each cluster's corners)."""
    n = len(centroids)
    if not n:
        return np.zeros((0, size), dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
    lo, hi = centroids.min(axis=0), centroids.max(axis=0)
    q = ((centroids - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.int64)
    order = np.argsort(_morton(q), kind="stable")
    padded = np.full(-(-n // size) * size, -1, dtype=np.int64)
    padded[:n] = order
    clusters = padded.reshape(-1, size)
    pts = corners[np.where(clusters >= 0, clusters, clusters[:, :1])].reshape(len(clusters), -1, 3)  # pad: a member
    centres = (pts.min(axis=1) + pts.max(axis=1)) / 2
    radii = np.linalg.norm(pts - centres[:, None], axis=-1).max(axis=1)
    return clusters, centres, radii


def _by_first_use(faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh ``faces`` (F, 3), ``vertices`` (V, 3) with its vertices renumbered in the order the faces first use
    them (those no face uses left out): (faces (F, 3), vertices (V', 3))."""
    flat = faces.reshape(-1)
    _, first = np.unique(flat, return_index=True)
    order = flat[np.sort(first)]  # the vertices in their first use's order
    number = np.empty(len(vertices), dtype=np.int64)
    number[order] = np.arange(len(order))
    return number[faces], vertices[order]


def _morton(q: np.ndarray) -> np.ndarray:
    """Morton codes (N,) of 10-bit integer coordinates (N, 3)."""
    code = np.zeros(len(q), dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + (2 - axis))
    return code


def _along_descent(tri, bary, g, t, length) -> np.ndarray:
    """Barycentric points (P, S, 3) at the fractions ``t`` (S,) of ``length`` (P,) or a float, each face's share of
    its way to the boundary, along the steepest descent inside each face (P, 3, 3) from ``bary`` (P, 3) with the
    gradients ``g`` (P, 3) there (:func:`zoo.simplex.descent_segment`): the numpy passes' polish (``kernel="numpy"``)
    and the reference of the compiled :func:`zoo.proxy_kernel.along_descent`."""
    direction, reach = descent_segment(tri, bary, g)
    return on_simplex(bary[:, None] + (t[None, :, None] * (length * reach)[:, None, None]) * direction[:, None])


def _row_indices(rows) -> np.ndarray:
    """Rows given as a tensor, an array or a list, as int64 (R,)."""
    if isinstance(rows, torch.Tensor):
        rows = rows.detach().cpu().numpy()
    return np.asarray(rows, dtype=np.int64).reshape(-1)
