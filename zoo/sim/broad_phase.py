"""Which of a World's pairs may touch this step, all pairs at once: each pair's margin (grown to see a fast pair
coming), the balls about its two sides, and the pairs' relative motions, in a few array operations over every pair
rather than a dozen small ones per pair (a robot brings dozens of pairs, most of them far apart).

A pair's margin is the larger of the world's and its geoms' margin; where the bodies can close more than that in
one step (:func:`closing_distances`), ``SPECULATIVE_FACTOR`` times the closing distance. A pair is near unless the
ball about its SDF's box and the ball about its surface lie more than that margin apart (a plane: unless the SDF's
ball lies that far above it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..contact_filters import Closing
from ..geometry import cross
from .pairs import Pair, PlanePair

SPECULATIVE_FACTOR = 1.5  # a fast pair's margin covers this much more than one step's closing distance


def body_velocities(model, data) -> np.ndarray:
    """(nbody, 6) every body's origin's linear velocity and its angular velocity, world frame: what
    ``mujoco.mj_objectVelocity`` gives one body (``data.cvel`` is at the subtree centre of mass of the body's root)."""
    angular, linear = data.cvel[:, :3], data.cvel[:, 3:]
    offset = data.xpos - data.subtree_com[model.body_rootid]
    return np.concatenate([linear + cross(angular, offset), angular], axis=1)


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


class BroadPhase:
    """A World's pairs' broad phase (see the module docstring), built once from the pairs and the model."""

    def __init__(self, model, pairs: list[Pair], margin: float):
        self.model, self.pairs = model, pairs
        self.sdf_body = np.array([p.sdf_body.body for p in pairs], dtype=np.int64)
        self.other = np.array([p.body for p in pairs], dtype=np.int64)
        self.margin = np.array([max(margin, p.params.margin) for p in pairs], dtype=np.float64)
        self.reach = np.array([p.sdf_body.reach for p in pairs], dtype=np.float64)
        self.box_centre = np.array([p.sdf_body.box_centre for p in pairs], dtype=np.float64).reshape(-1, 3)
        self.box_radius = np.array([p.sdf_body.box_radius for p in pairs], dtype=np.float64)
        self.plane = np.array([isinstance(p, PlanePair) for p in pairs], dtype=bool)
        self.centre = np.array([p.centre for p in pairs], dtype=np.float64).reshape(-1, 3)
        self.radius = np.array([0.0 if isinstance(p, PlanePair) else p.bounding_radius for p in pairs])
        self.by_geom = np.array([p.frame == "geom" for p in pairs], dtype=bool).reshape(-1, 1)  # the surface's frame
        self.geom = np.array([p.geom if p.frame == "geom" else 0 for p in pairs], dtype=np.int64)
        self.body = np.array([0 if p.frame == "geom" else p.body for p in pairs], dtype=np.int64)

    def near(self, data) -> NearPairs:
        """The pairs that may touch at ``data``'s kinematics (and velocities)."""
        velocity = body_velocities(self.model, data)
        a, b = velocity[self.sdf_body], velocity[self.other]
        xa, xb = data.xpos[self.sdf_body], data.xpos[self.other]
        closing = closing_distances(a, b, xa, xb, self.reach, self.model.opt.timestep)
        speculative = closing > self.margin
        margins = np.where(speculative, SPECULATIVE_FACTOR * closing, self.margin)
        rotation = np.where(self.by_geom, data.geom_xmat[self.geom], data.xmat[self.body]).reshape(-1, 3, 3)
        origin = np.where(self.by_geom, data.geom_xpos[self.geom], data.xpos[self.body])
        sdf_centre = np.einsum("pij,pj->pi", data.xmat[self.sdf_body].reshape(-1, 3, 3), self.box_centre) + xa
        surface_centre = np.einsum("pij,pj->pi", rotation, self.centre) + origin
        gap = sdf_centre - surface_centre
        apart = np.sqrt((gap * gap).sum(axis=1)) - self.box_radius - self.radius > margins
        above = np.einsum("pi,pi->p", rotation[:, :, 2], gap) - self.box_radius > margins  # a plane's z axis
        keep = np.flatnonzero(np.where(self.plane, ~above, ~apart))
        poses = np.zeros((len(keep), 4, 4))
        poses[:, :3, :3], poses[:, :3, 3], poses[:, 3, 3] = rotation[keep], origin[keep], 1.0
        shift = a[keep, :3] - b[keep, :3] - cross(a[keep, 3:], xa[keep]) + cross(b[keep, 3:], xb[keep])
        return NearPairs([self.pairs[i] for i in keep], margins[keep], poses, speculative[keep], shift,
                         a[keep, 3:] - b[keep, 3:], self.model.opt.timestep * SPECULATIVE_FACTOR)


def closing_distances(a: np.ndarray, b: np.ndarray, xa: np.ndarray, xb: np.ndarray, reach: np.ndarray,
                      dt: float) -> np.ndarray:
    """(P,) upper bounds (m) on how much closer each pair's surfaces can get in one step of ``dt`` s, for the bodies'
    velocities ``a``, ``b`` (P, 6) (linear at the origin, angular) and origins ``xa``, ``xb`` (P, 3), ``reach`` (P,)
    the SDF side's farthest point from its origin. A contact lies within ``reach`` of the SDF body's origin, so within
    ``reach`` + |xa - xb| of the other body's: each body's rotation moves it by at most its angular speed times that
    lever."""
    norm = lambda v: np.sqrt((v * v).sum(axis=1))  # noqa: E731
    lever = reach + norm(xa - xb)
    return (norm(a[:, :3] - b[:, :3]) + reach * norm(a[:, 3:]) + lever * norm(b[:, 3:])) * dt

