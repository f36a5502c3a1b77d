"""numpy references for :mod:`zoo.contact_filters`: the filters written as array expressions, for tests only."""

from __future__ import annotations

import numpy as np

from zoo.contact_filters import GRAZING_COS, SEPARATED_COS


def facing_faces(normals: np.ndarray, faces: np.ndarray, depths: np.ndarray, slack: float = 0.0) -> np.ndarray:
    """(K,) bool: the contact's SDF normal (K, 3) is close enough to its face's unit normal (K, 3), zeros: degenerate
    (kept): |cos| at least ``GRAZING_COS`` where it may touch (depth - ``slack`` <= 0), ``SEPARATED_COS`` where
    separated."""
    cos = np.abs(np.einsum("ij,ij->i", normals, faces))
    degenerate = ~(np.abs(faces).sum(axis=1) > 0)
    return (cos >= np.where(depths - slack > 0, SEPARATED_COS, GRAZING_COS)) | degenerate


def closing_in_time(points: np.ndarray, depths: np.ndarray, normals: np.ndarray, sdf_motion, mesh_motion,
                    seconds: float, slack: float = 0.0) -> np.ndarray:
    """(K,) bool: the contact may touch (depth - ``slack`` <= 0) or its bodies close what is left of its gap within
    ``seconds``.

    Args:
        points (K, 3), depths (K,), normals (K, 3): the contacts, world frame; normals from the SDF body to the mesh body.
        sdf_motion, mesh_motion: each body's (origin (3,), velocity (6,): its origin's linear velocity, then angular), world.
    """
    def point_velocity(motion):
        origin, velocity = motion
        return velocity[:3] + np.cross(velocity[3:], points - origin)

    closing = np.einsum("ij,ij->i", point_velocity(sdf_motion) - point_velocity(mesh_motion), normals)
    least = depths - slack
    return (least <= 0) | (closing * seconds >= least)


def relative_motion(sdf_motion, mesh_motion) -> tuple[np.ndarray, np.ndarray]:
    """(u (3,), w (3,)): the SDF body's velocity less the mesh body's at a world point p is u + w x p."""
    (a_origin, a), (b_origin, b) = sdf_motion, mesh_motion
    return a[:3] - b[:3] - np.cross(a[3:], a_origin) + np.cross(b[3:], b_origin), a[3:] - b[3:]
