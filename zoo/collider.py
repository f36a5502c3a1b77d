"""What every SDF-mesh narrow phase shares, below them all in the imports: the :class:`Collider` interface that
:class:`zoo.CoherentCollider` and :class:`zoo.proxy_collider.ProxyCollider` implement, the :class:`CoherenceStats` they
count, the Lipschitz bound a bound carried over a motion decays with (:func:`motion_lipschitz`), the reuse and polish
thresholds, and the first-order move of a kept answer's depth (:func:`moved_along_normal`).

``coherence`` uses ``proxy_collider`` and ``proxy``; they use this module, never ``coherence``: no import cycle
inside ``zoo`` (tests/test_layout.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from .bounds import LIPSCHITZ
from .geometry import bary_to_points
from .sdf import Box, Capsule, Sphere, Torus, TransformedSDF
from .validation import positive_float

# The Lipschitz bound a carried vertex bound decays with where the SDF is not an exact distance (a NeuralSDF,
# a voxel grid, a caller's SDF without a ``lipschitz`` attribute). A learned SDF is only roughly 1-Lipschitz
# (docs/coherence.md measures a packaged mug's gradient norms), and a bound carried over a motion inherits the error.
LEARNED_LIPSCHITZ = 2.0
# A candidate whose points moved less than this fraction of the margin (relative to the SDF) since it was last
# solved keeps its answer, its depth moved to first order along its normal, as a persistent contact manifold
# does (Bullet keeps a contact while it drifts a small fraction of the body's size). The depth's error is second
# order in the drift where the surface is smooth, and the drift is measured
# from where the face was last solved, so a sliding contact is solved again every few steps.
REUSE_FRACTION = 0.2
# With a proxy: an answer of the SDF whose Frank-Wolfe gap exceeds this fraction of the margin is polished on the SDF by
# one warm step (:func:`zoo.coherence.warm_step`); below it the proxy's minimiser is taken as the SDF's. 0: every answer
# not at a minimum is polished. Where the proxy's error is comparable to a clearance (a nut's thread), a 2% threshold
# left answers above the SDF's minimum, and the body sank deeper than on the full path (docs/proxy.md, "Fidelity").
POLISH_GAP_FRACTION = 0.0


@dataclass
class CoherenceStats:
    """What a :class:`Collider` did, summed over the steps counted.

    Attributes:
        steps: calls counted.
        faces_near: faces whose box touches the SDF's bounds grown by the margin (collide's first cull, no query).
        faces_skipped: of those, faces proven above the margin by the carried bounds, with no query.
        cell_queries: SDF queries at cell centres (bounds for many vertices at once).
        proxy_reads: with a proxy, the points the proxy was read at (culling and search).
        vertex_queries: SDF queries at mesh vertices.
        candidates: triangles that reached the narrow phase (collide's candidates).
        warm: of those, warm-started from their last barycentrics.
        cold: of those, solved from scratch by the method.
        retried: warm-started ones solved from scratch too (the warm answer's Frank-Wolfe gap exceeded ``zoo.coherence.RETRY_GAP``).
        reused: of the candidates, answers kept from an earlier step with no query (moved less than ``reuse_distance``).
        screened: of the warm-started, those the screen put above the margin (one value-and-gradient query each, no
            descent: :func:`zoo.coherence.screen_bound`).
        exact_faces: with a proxy, the faces whose proxy minimum came within the margin plus the proxy's error bound,
            answered by the SDF itself (the counts above are then of the search on the proxy).
        exact_points: with a proxy, the points the SDF itself was asked at (values and gradients alike).
        exact_kept: of ``exact_faces``, those whose SDF answer was kept from an earlier step (no query).
        fallback: of ``exact_faces``, those whose proxy answer lay out of the proxy's band, answered by the SDF's own
            descent (``zoo.proxy_collider.ProxyCollider._out_of_band``).
    """

    steps: int = 0
    faces_near: int = 0
    faces_skipped: int = 0
    cell_queries: int = 0
    proxy_reads: int = 0
    vertex_queries: int = 0
    candidates: int = 0
    warm: int = 0
    cold: int = 0
    retried: int = 0
    reused: int = 0
    screened: int = 0
    exact_faces: int = 0
    exact_points: int = 0
    exact_kept: int = 0
    fallback: int = 0

    def add(self, other: CoherenceStats) -> None:
        mine, theirs = self.__dict__, other.__dict__  # not asdict, nor getattr: this runs at every step of every pair
        for key in _STATS_FIELDS:
            mine[key] += theirs[key]

    def as_dict(self) -> dict:
        return asdict(self)


_STATS_FIELDS = tuple(f.name for f in fields(CoherenceStats))


def motion_lipschitz(sdf) -> float:
    """The Lipschitz bound a :class:`Collider` assumes of ``sdf`` when it carries a bound over a motion:
    the SDF's own ``lipschitz`` attribute where it has one; :data:`zoo.bounds.LIPSCHITZ` for the exact
    analytic SDFs (also rigidly placed); :data:`LEARNED_LIPSCHITZ` for anything else."""
    given = getattr(sdf, "lipschitz", None)
    if given is not None:
        return positive_float(given, f"{type(sdf).__name__}.lipschitz")
    if isinstance(sdf, TransformedSDF):
        return motion_lipschitz(sdf.sdf)
    return LIPSCHITZ if isinstance(sdf, (Sphere, Box, Torus, Capsule)) else LEARNED_LIPSCHITZ


def moved_along_normal(value, normal, tri, then, bary):
    """A kept answer's depth (N,) now: ``value`` (N,) at barycentrics ``bary`` (N, 3) of faces that were at ``then``
    (N, 3, 3) and are now at ``tri`` (N, 3, 3), moved to first order along its unit ``normal`` (N, 3) (unchanged where
    the normal is NaN: none known). Torch tensors or numpy arrays alike (the same kind back)."""
    if isinstance(value, np.ndarray):
        shift = np.einsum("nv,nvc->nc", bary, tri) - np.einsum("nv,nvc->nc", bary, then)
        along = (shift * normal).sum(axis=-1)
        return value + np.where(np.isnan(along), 0.0, along)  # np.nan_to_num's checks cost more than a few rows
    shift = bary_to_points(tri, bary) - bary_to_points(then, bary)
    return value + torch.nan_to_num((shift * normal).sum(dim=-1))


@runtime_checkable
class Collider(Protocol):
    """One SDF-mesh pair along a trajectory: call it with each step's poses for its contacts.

    ``deferred`` colliders return contacts on an approximation of the SDF (a proxy), and :meth:`exact_contacts` gives
    the SDF's own for the rows the caller keeps; the others return the SDF's contacts directly.
    """

    stats: CoherenceStats  # summed over every call
    last_stats: CoherenceStats  # the last call's
    deferred: bool

    def __call__(self, sdf_pose=None, mesh_pose=None, margin: float | None = None):
        """``zoo.Contacts`` at these poses (4x4 world-from-object, None: identity); ``margin`` for this call only."""

    def exact_contacts(self, rows):
        """The SDF's own ``zoo.Contacts`` for the rows ``rows`` (K,) of the last call's (deferred) contacts."""

    def reset(self) -> None:
        """Forget what was carried over; ``stats`` are kept."""
