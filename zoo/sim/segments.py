"""Where an SDF is least along segments: the axes of the capsules (and the centres of the spheres) that meet an SDF
body, whose contacts lie at the SDF's minimum over the axis less the radius (``zoo.sim.world``'s segment pairs).

All segments of a step on one SDF are searched together, each stage one query of the SDF's value and gradient: the
samples, then two Hermite steps. A segment's few dozen points per query cost a NeuralSDF the overhead of a call
more than its arithmetic, so the search spends calls, not points: the gradient along the axis picks the side of the
lowest sample the minimum lies on, and each step reads two guesses from the bracket's two ends (their values and
slopes): the cubic's minimum (exact where f is smooth) and where their tangents meet (exact at a kink).

Between searches, a segment that moved less than a reuse distance since the SDF answered it keeps that answer
(:class:`SegmentAnswer`), its values moved to first order along their normals (:func:`carried_minima`), as a mesh
pair's faces keep theirs; and a segment the search found out of reach keeps the lower bound of f along it that showed
so (:class:`SegmentClearance`): f being Lipschitz, the bound less ``SEGMENT_LIPSCHITZ`` times how far the segment has
moved since still holds, and while it stays above the reach the segment is passed over with no query at all (a
robot's links beside an object it carries). ``zoo.sim.pairs`` decides which.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from ..collider import moved_along_normal
from ..geometry import unit_rows
from ..sdf import value_and_grad_numpy

SEGMENT_SAMPLES = 9  # points along a capsule's axis where f is read before the search narrows around the lowest
SEGMENT_STEPS = 2  # steps in the bracket the samples leave: each one query (two points a segment) for all segments
SEGMENT_LIPSCHITZ = 2.0  # |grad f| bound used to drop a segment from its samples (a learned SDF's, zoo.coherence's)


@dataclass
class SegmentMinima:
    """Points on segments and the SDF there (the SDF's frame): ``points`` (C, 3), ``owner`` (C,) the segment each
    lies on, ``params`` (C,) where along it (0 at a, 1 at b), ``values`` (C,) and ``grads`` (C, 3) the SDF's value and
    gradient."""

    points: np.ndarray
    owner: np.ndarray
    params: np.ndarray
    values: np.ndarray
    grads: np.ndarray

    @classmethod
    def empty(cls) -> SegmentMinima:
        return cls(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3)))

    @classmethod
    def concat(cls, parts: list[SegmentMinima]) -> SegmentMinima:
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))


@dataclass
class SegmentAnswer:
    """A segment's last answer from the SDF, for the steps it moves less than a reuse distance (a persistent contact):
    its ends ``a``, ``b`` (3 floats each) then (the SDF's frame) and its points of least f then (``params`` (k,) along a -> b,
    ``values`` (k,), ``grads`` (k, 3)); k = 0 is never kept (a segment the search dropped is searched again)."""

    a: list[float]
    b: list[float]
    params: np.ndarray
    values: np.ndarray
    grads: np.ndarray

    def moved(self, a: list[float], b: list[float]) -> float:
        """How far (m) any point of the segment moved since, now that its ends are ``a``, ``b`` (3 floats each)
        (:func:`segment_moved`)."""
        return segment_moved(self.a, self.b, a, b)


def segment_moved(a0, b0, a, b) -> float:
    """How far (m) any point of a segment moved when its ends went from ``a0``, ``b0`` to ``a``, ``b`` (3 floats each:
    lists, where a numpy row would cost math.dist more than its arithmetic): a point at t moves by (1 - t) da + t db,
    at most the larger of the two."""
    return max(math.dist(a, a0), math.dist(b, b0))


@dataclass
class SegmentClearance:
    """A segment the search found out of reach: its ends ``a``, ``b`` (3 floats each) then (the SDF's frame) and ``floor``, a
    lower bound of f along it then (:attr:`SegmentSearch.floors`)."""

    a: list[float]
    b: list[float]
    floor: float

    def holds(self, a: list[float], b: list[float], reach: float) -> bool:
        """Whether f still stays above ``reach`` along the segment now that its ends are ``a``, ``b`` (3 floats each): each of its
        points moved at most :func:`segment_moved`, and f at most ``SEGMENT_LIPSCHITZ`` times that."""
        return self.floor - SEGMENT_LIPSCHITZ * segment_moved(self.a, self.b, a, b) > reach


@dataclass
class SegmentSearch:
    """What :func:`segment_minima` found for segments (S of them): ``minima``, the points of least f of those within
    reach, and ``floors`` (S,), per segment, a lower bound of f along it where it is out of reach (above its reach),
    -inf where it is within."""

    minima: SegmentMinima
    floors: np.ndarray


def carried_minima(answers: list[SegmentAnswer], a: np.ndarray, b: np.ndarray, owners: np.ndarray) -> SegmentMinima:
    """Segments' kept ``answers`` at their new ends ``a``, ``b`` (S, 3), each value moved to first order along its unit
    normal (the same points along the axis; the gradients kept), as rows of the segments ``owners`` (S,): all at once."""
    if not answers:
        return SegmentMinima.empty()
    counts = np.array([len(answer.params) for answer in answers])
    params = np.concatenate([answer.params for answer in answers])
    values = np.concatenate([answer.values for answer in answers])
    grads = np.concatenate([answer.grads for answer in answers])
    then_a, then_b = np.array([answer.a for answer in answers]), np.array([answer.b for answer in answers])
    then = np.repeat(np.stack([then_a, then_b, then_b], axis=1), counts, axis=0)
    now = np.repeat(np.stack([a, b, b], axis=1), counts, axis=0)  # each segment as a flat triangle a, b, b
    bary = np.stack([1.0 - params, params, np.zeros(len(params))], axis=1)
    values = moved_along_normal(values, unit_rows(grads), now, then, bary)
    points = now[:, 0] + params[:, None] * (now[:, 1] - now[:, 0])
    return SegmentMinima(points, np.repeat(owners, counts), params, values, grads)


def segment_minima(sdf, a: np.ndarray, b: np.ndarray, reach: np.ndarray, dtype: torch.dtype,
                   lower_bound=None) -> SegmentSearch:
    """The points of the segments from ``a`` to ``b`` (S, 3) where ``sdf`` is least, all segments at once.

    Each segment is sampled at ``SEGMENT_SAMPLES`` points; a segment whose samples, less the Lipschitz bound times
    half their spacing, stay above its ``reach`` (S,) (its radius plus margin) is dropped. For the others the slope
    along the axis at the lowest sample gives the side of it the minimum lies on, and ``SEGMENT_STEPS`` steps narrow
    that bracket (see the module docstring); the lowest point read, and the segment's two ends, are returned (a capsule lying on a flat
    face touches along its length: its ends hold it level). A segment of no length (a sphere) gives its one point.
    Queries ``sdf.value_and_grad`` in ``dtype``, 1 + ``SEGMENT_STEPS`` times. ``lower_bound``: a cheap lower bound
    of f (numpy points (N, 3) -> (N,), an SDF's proxy less its error) that drops the segments it keeps out of reach
    before the SDF is asked at all. Returns the minima with, per segment, the lower bound of f along it that showed it
    out of reach (:class:`SegmentSearch`).
    """
    axis = b - a  # (S, 3)
    lengths = np.linalg.norm(axis, axis=1)
    spacing = lengths / (SEGMENT_SAMPLES - 1)
    t = np.where(lengths[:, None] > 0, np.linspace(0.0, 1.0, SEGMENT_SAMPLES)[None], 0.0)  # (S, T): a sphere's at its centre
    floors = np.full(len(a), -np.inf)
    alive = np.arange(len(a))
    if lower_bound is not None and len(a):
        bounds = lower_bound((a[:, None] + t[..., None] * axis[:, None]).reshape(-1, 3)).reshape(t.shape)
        alive = _within_reach(bounds, spacing, reach, floors)
    if not len(alive):
        return SegmentSearch(SegmentMinima.empty(), floors)
    values, slopes, grads = _along(sdf, a[alive], axis[alive], t[alive], dtype)
    near = _within_reach(values, spacing[alive], reach[alive], floors, alive)
    alive = alive[near]
    if not len(alive):
        return SegmentSearch(SegmentMinima.empty(), floors)
    a, axis, t, values, slopes, grads = a[alive], axis[alive], t[alive], values[near], slopes[near], grads[near]
    rows = np.arange(len(alive))
    best = np.argmin(values, axis=1)
    # the bracket: from the lowest sample towards its lower side (its slope's sign), or no width at an end it falls to
    other = np.clip(best - np.sign(slopes[rows, best]).astype(np.int64), 0, SEGMENT_SAMPLES - 1)
    left, right = np.minimum(best, other), np.maximum(best, other)
    known = [np.stack([x[rows, left], x[rows, right]], axis=1) for x in (t, values, slopes)]  # (A, 2) each: t, f, df/dt
    low_t, low_f, low_g = t[rows, best], values[rows, best], grads[rows, best]
    for _ in range(SEGMENT_STEPS):
        (t0, t1), (f0, f1), (d0, d1) = ((x[:, 0], x[:, 1]) for x in known)
        at = np.stack([_hermite_minimum(t0, f0, d0, t1, f1, d1), _tangents_meet(t0, f0, d0, t1, f1, d1)], axis=1)
        f, d, g = _along(sdf, a, axis, at, dtype)
        j = np.argmin(f, axis=1)
        lower = f[rows, j] < low_f
        low_t, low_f = np.where(lower, at[rows, j], low_t), np.where(lower, f[rows, j], low_f)
        low_g = np.where(lower[:, None], g[rows, j], low_g)
        known = _narrowed(*(np.concatenate(pair, axis=1) for pair in zip(known, (at, f, d))))
    sphere = lengths[alive] == 0
    ends = (0, SEGMENT_SAMPLES - 1)
    params = np.stack([t[:, 0], low_t, t[:, -1]], axis=1)  # (A, 3): an end, the minimum, the other end
    keep = (np.repeat(~sphere, 3) | np.tile([False, True, False], len(alive)))  # a sphere: its centre once
    return SegmentSearch(SegmentMinima(
        points=(a[:, None] + params[..., None] * axis[:, None]).reshape(-1, 3)[keep],
        owner=np.repeat(alive, 3)[keep],
        params=params.reshape(-1)[keep],
        values=np.stack([values[:, ends[0]], low_f, values[:, ends[1]]], axis=1).reshape(-1)[keep],
        grads=np.stack([grads[:, ends[0]], low_g, grads[:, ends[1]]], axis=1).reshape(-1, 3)[keep]), floors)


def _within_reach(values: np.ndarray, spacing: np.ndarray, reach: np.ndarray, floors: np.ndarray,
                  rows: np.ndarray | None = None) -> np.ndarray:
    """The segments (indices (K,) into ``values``) whose samples' values (S, T) (or lower bounds), less the Lipschitz
    bound times half their ``spacing`` (S,), come within their ``reach`` (S,): between two samples f can dip that
    much, no more. The others' such bound is written into ``floors`` at their ``rows`` (S,) (default: 0..S-1)."""
    least = values.min(axis=1) - SEGMENT_LIPSCHITZ * spacing / 2
    within = least <= reach
    floors[np.arange(len(least)) if rows is None else rows] = np.where(within, -np.inf, least)
    return np.nonzero(within)[0]


def _narrowed(t: np.ndarray, f: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
    """Of points read along each segment (t, f, df/dt: (A, K) each), the two that bracket the minimum: the lowest
    and its neighbour on its slope's lower side (itself at an end it falls to): [t, f, d], (A, 2) each."""
    order = np.argsort(t, axis=1, kind="stable")
    t, f, d = (np.take_along_axis(x, order, axis=1) for x in (t, f, d))
    rows = np.arange(len(t))
    j = np.argmin(f, axis=1)
    k = np.clip(j - np.sign(d[rows, j]).astype(np.int64), 0, t.shape[1] - 1)
    left, right = np.minimum(j, k), np.maximum(j, k)
    return [np.stack([x[rows, left], x[rows, right]], axis=1) for x in (t, f, d)]


def _hermite_minimum(t0, f0, d0, t1, f1, d1) -> np.ndarray:
    """(N,) t in [t0, t1] where the cubic with values ``f0``, ``f1`` and slopes ``d0``, ``d1`` at ``t0``, ``t1`` is
    least (of its ends and its critical points between): exact where f is a cubic (smooth SDFs, nearly)."""
    width = t1 - t0
    a, b = d0 * width, d1 * width  # the slopes per unit of s = (t - t0) / width
    c2 = 3 * (f1 - f0) - 2 * a - b
    c3 = 2 * (f0 - f1) + a + b
    qa, qb, qc = 3 * c3, 2 * c2, a  # p'(s) = qc + qb s + qa s^2
    root = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.stack([np.zeros_like(f0), np.ones_like(f0), (-qb - root) / (2 * qa), (-qb + root) / (2 * qa),
                      -qc / qb], axis=1)
    s = np.clip(np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    p = f0[:, None] + s * (a[:, None] + s * (c2[:, None] + s * c3[:, None]))
    return t0 + width * s[np.arange(len(f0)), np.argmin(p, axis=1)]


def _tangents_meet(t0, f0, d0, t1, f1, d1) -> np.ndarray:
    """(N,) t in [t0, t1] where the tangents at the two ends meet (exact where f has a kink between: a box's
    inside, the max of its faces' planes), the middle where they do not fall towards each other."""
    falling = (d0 < 0) & (d1 > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        meet = (f1 - f0 + d0 * t0 - d1 * t1) / (d0 - d1)
    return np.where(falling, np.clip(np.nan_to_num(meet), t0, t1), 0.5 * (t0 + t1))


def _along(sdf, a: np.ndarray, axis: np.ndarray, at: np.ndarray, dtype: torch.dtype):
    """f, its slope df/dt and its gradient at the points ``a + at * axis`` of each segment: a (S, 3), axis (S, 3),
    at (S, k) -> (S, k), (S, k), (S, k, 3), one query."""
    points = a[:, None] + at[..., None] * axis[:, None]
    values, grads = value_and_grad_numpy(sdf, points.reshape(-1, 3), dtype)
    values, grads = values.reshape(at.shape), grads.reshape(*at.shape, 3)
    return values, np.einsum("skc,sc->sk", grads, axis), grads
