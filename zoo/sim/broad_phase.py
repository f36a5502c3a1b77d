"""Which of a World's pairs may touch this step, all pairs at once: each pair's margin (grown to see a fast pair
coming), the balls about its two sides, and the pairs' relative motions, in one compiled loop over the pairs
rather than a dozen numpy calls per pair (a robot brings dozens of pairs, most of them far apart).

A pair's margin is the larger of the world's and its geoms' margin; where the bodies can close more than that in
one step, ``SPECULATIVE_FACTOR`` times the closing distance. A pair is near unless the ball about its SDF's box and
the ball about its surface lie more than that margin apart (a plane: unless the SDF's ball lies that far above it).
tests/test_broad_phase.py holds it against the per-pair test it replaced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from ..contact_filters import Closing
from .pairs import Pair, PlanePair

SPECULATIVE_FACTOR = 1.5  # a fast pair's margin covers this much more than one step's closing distance


def body_velocities(model, data) -> np.ndarray:
    """(nbody, 6) every body's origin's linear velocity and its angular velocity, world frame: what
    ``mujoco.mj_objectVelocity`` (``mjOBJ_XBODY``) gives one body."""
    velocity = np.empty((model.nbody, 6))
    _body_velocities(data.cvel, data.xpos, data.subtree_com, model.body_rootid, velocity)
    return velocity


@njit(cache=True, nogil=True)
def _body_velocities(cvel, xpos, subtree_com, rootid, out):
    """``out`` (B, 6): each body's [v at its origin; w] from ``cvel`` (B, 6) [w; v at its root's subtree centre of
    mass]: v + w x (origin - centre)."""
    for body in range(len(cvel)):
        w0, w1, w2 = cvel[body, 0], cvel[body, 1], cvel[body, 2]
        centre = subtree_com[rootid[body]]
        d0, d1, d2 = xpos[body, 0] - centre[0], xpos[body, 1] - centre[1], xpos[body, 2] - centre[2]
        out[body, 0] = cvel[body, 3] + w1 * d2 - w2 * d1
        out[body, 1] = cvel[body, 4] + w2 * d0 - w0 * d2
        out[body, 2] = cvel[body, 5] + w0 * d1 - w1 * d0
        out[body, 3], out[body, 4], out[body, 5] = w0, w1, w2


@dataclass
class NearPairs:
    """The pairs that may touch this step: ``pairs`` (N,), their ``margins`` (N,) and surfaces' poses ``surface_poses``
    (N, 4, 4), whether each margin was grown (``speculative`` (N,)), and the relative motion of each pair's bodies
    (``shift`` (N, 3), ``turn`` (N, 3), :class:`zoo.contact_filters.Closing`'s), ``seconds`` the time a separated
    contact has to close."""

    pairs: list[Pair]
    margins: np.ndarray
    surface_poses: np.ndarray
    speculative: np.ndarray
    shift: np.ndarray
    turn: np.ndarray
    seconds: float

    def closing(self, i: int) -> Closing:
        """The ``i``-th pair's :class:`zoo.contact_filters.Closing`."""
        return Closing(self.shift[i], self.turn[i], self.seconds)


class PairArrays(NamedTuple):
    """A World's pairs as arrays (P pairs): the SDF body's id ``sdf_body`` and the other body's ``other``, the pair's
    ``margin`` (the world's or its geoms', the larger), the SDF body's ``reach`` (its box's farthest point from its
    origin), ``box_centre`` (P, 3) and ``box_radius`` (its ball), whether the surface is a ``plane``, the surface's ball
    (``centre`` (P, 3) in its frame, ``radius``), and its frame: geom ``surface`` if ``by_geom``, else body ``surface``."""

    sdf_body: np.ndarray
    other: np.ndarray
    margin: np.ndarray
    reach: np.ndarray
    box_centre: np.ndarray
    box_radius: np.ndarray
    plane: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    surface: np.ndarray
    by_geom: np.ndarray


class BroadPhase:
    """A World's pairs' broad phase (see the module docstring), built once from the pairs and the model."""

    def __init__(self, model, pairs: list[Pair], margin: float):
        self.model, self.pairs = model, pairs
        by_geom = [p.frame == "geom" for p in pairs]
        self.arrays = PairArrays(
            sdf_body=np.array([p.sdf_body.body for p in pairs], dtype=np.int64),
            other=np.array([p.body for p in pairs], dtype=np.int64),
            margin=np.array([max(margin, p.params.margin) for p in pairs], dtype=np.float64),
            reach=np.array([p.sdf_body.reach for p in pairs], dtype=np.float64),
            box_centre=np.array([p.sdf_body.box_centre for p in pairs], dtype=np.float64).reshape(-1, 3),
            box_radius=np.array([p.sdf_body.box_radius for p in pairs], dtype=np.float64),
            plane=np.array([isinstance(p, PlanePair) for p in pairs], dtype=np.bool_),
            centre=np.array([p.centre for p in pairs], dtype=np.float64).reshape(-1, 3),
            radius=np.array([0.0 if isinstance(p, PlanePair) else p.bounding_radius for p in pairs], dtype=np.float64),
            surface=np.array([p.geom if g else p.body for p, g in zip(pairs, by_geom)], dtype=np.int64),
            by_geom=np.array(by_geom, dtype=np.bool_))
        import mujoco

        self.near(mujoco.MjData(model))  # compiled (or loaded from numba's cache) now, not in the first step

    def near(self, data) -> NearPairs:
        """The pairs that may touch at ``data``'s kinematics (and velocities)."""
        velocity = body_velocities(self.model, data)
        n = len(self.pairs)
        margins, near, speculative = np.empty(n), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
        poses, shift, turn = np.zeros((n, 4, 4)), np.empty((n, 3)), np.empty((n, 3))
        _near(self.arrays, velocity, data.xpos, data.xmat, data.geom_xpos, data.geom_xmat, self.model.opt.timestep,
              SPECULATIVE_FACTOR, margins, near, speculative, poses, shift, turn)
        keep = np.flatnonzero(near)
        return NearPairs([self.pairs[i] for i in keep], margins[keep], poses[keep], speculative[keep], shift[keep],
                         turn[keep], self.model.opt.timestep * SPECULATIVE_FACTOR)


@njit(cache=True, nogil=True)
def _near(pairs, velocity, xpos, xmat, geom_xpos, geom_xmat, dt, factor, margins, near, speculative, poses, shift, turn):
    """Each pair's margin this step, whether it was grown (``speculative``) and whether the pair is ``near``, its
    surface's pose (4, 4) and its relative motion (``shift``, ``turn``: the SDF body's velocity less the other's at a
    world point p is shift + turn x p), written into the arrays given (P rows each)."""
    for i in range(len(pairs.margin)):
        a, b = pairs.sdf_body[i], pairs.other[i]
        xa, xb, va, vb = xpos[a], xpos[b], velocity[a], velocity[b]
        # a contact lies within reach of the SDF body's origin, so within reach + |xa - xb| of the other body's: each
        # body's rotation moves it by at most its angular speed times that lever
        reach = pairs.reach[i]
        lever = reach + _norm3(xa[0] - xb[0], xa[1] - xb[1], xa[2] - xb[2])
        closing = (_norm3(va[0] - vb[0], va[1] - vb[1], va[2] - vb[2]) + reach * _norm3(va[3], va[4], va[5])
                   + lever * _norm3(vb[3], vb[4], vb[5])) * dt
        speculative[i] = closing > pairs.margin[i]
        margins[i] = factor * closing if speculative[i] else pairs.margin[i]
        s = pairs.surface[i]
        rotation = (geom_xmat[s] if pairs.by_geom[i] else xmat[s]).reshape(3, 3)
        origin = geom_xpos[s] if pairs.by_geom[i] else xpos[s]
        poses[i, :3, :3], poses[i, :3, 3], poses[i, 3, 3] = rotation, origin, 1.0
        sdf_rotation = xmat[a].reshape(3, 3)
        gap = np.empty(3)  # the SDF's ball's centre less the surface's, world frame
        for k in range(3):
            gap[k] = (_row_dot(sdf_rotation, k, pairs.box_centre[i]) + xa[k]
                      - _row_dot(rotation, k, pairs.centre[i]) - origin[k])
        if pairs.plane[i]:  # the SDF's ball above the plane (z = 0 of its frame, facing +z)
            height = rotation[0, 2] * gap[0] + rotation[1, 2] * gap[1] + rotation[2, 2] * gap[2]
            apart = height - pairs.box_radius[i] > margins[i]
        else:
            apart = _norm3(gap[0], gap[1], gap[2]) - pairs.box_radius[i] - pairs.radius[i] > margins[i]
        near[i] = not apart
        for k in range(3):  # u = va - wa x xa - (vb - wb x xb): the velocity field's value at the world origin
            k1, k2 = (k + 1) % 3, (k + 2) % 3
            shift[i, k] = (va[k] - (va[3 + k1] * xa[k2] - va[3 + k2] * xa[k1])
                           - vb[k] + (vb[3 + k1] * xb[k2] - vb[3 + k2] * xb[k1]))
            turn[i, k] = va[3 + k] - vb[3 + k]


@njit(cache=True, nogil=True, inline="always")
def _norm3(x, y, z):
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True, nogil=True, inline="always")
def _row_dot(m, k, v):
    """(m v)[k] for a 3x3 ``m`` (numba's matrix product is a call into SciPy's BLAS, dearer than nine products)."""
    return m[k, 0] * v[0] + m[k, 1] * v[1] + m[k, 2] * v[2]
