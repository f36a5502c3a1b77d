"""Procedural scene parts, so scenes and the demo need no external meshes.

Every part is a ``trimesh.Trimesh`` in metres, z up, remeshed so no edge exceeds ``max_edge``
(the detector is trained on a range of triangle sizes; meshes near that range need no
subdivision at query time).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .errors import InputError


def _finish(parts: list[trimesh.Trimesh], max_edge: float) -> trimesh.Trimesh:
    mesh = trimesh.util.concatenate(parts)
    if max_edge <= 0:
        raise InputError(f"max_edge must be positive, got {max_edge}")
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge, max_iter=20)
    return trimesh.Trimesh(vertices, faces, process=True)


def rack(
    height: float = 0.30,
    post_radius: float = 0.012,
    peg_length: float = 0.09,
    peg_radius: float = 0.006,
    peg_height: float = 0.20,
    peg_angle_deg: float = 20.0,
    base: float = 0.16,
    max_edge: float = 0.006,
) -> trimesh.Trimesh:
    """A mug tree: a base plate, a vertical post at the origin, one peg along +x rising by ``peg_angle_deg``."""
    plate = trimesh.creation.box(extents=(base, base, 0.01), transform=trimesh.transformations.translation_matrix((0, 0, 0.005)))
    post = trimesh.creation.cylinder(radius=post_radius, segment=[(0, 0, 0.01), (0, 0, height)], sections=24)
    a = np.radians(peg_angle_deg)
    tip = (peg_length * np.cos(a), 0.0, peg_height + peg_length * np.sin(a))
    peg = trimesh.creation.cylinder(radius=peg_radius, segment=[(0, 0, peg_height), tip], sections=16)
    return _finish([plate, post, peg], max_edge)


def holder(
    inner_radius: float = 0.045, wall: float = 0.006, height: float = 0.08, floor: float = 0.006, max_edge: float = 0.008
) -> trimesh.Trimesh:
    """A cup-shaped bottle holder: an annular wall on a disc floor, opening upward, floor at z = 0."""
    wall_mesh = trimesh.creation.annulus(
        r_min=inner_radius, r_max=inner_radius + wall, height=height, sections=48,
        transform=trimesh.transformations.translation_matrix((0, 0, height / 2)),
    )
    floor_mesh = trimesh.creation.cylinder(
        radius=inner_radius + wall, height=floor, sections=48,
        transform=trimesh.transformations.translation_matrix((0, 0, -floor / 2)),
    )
    return _finish([wall_mesh, floor_mesh], max_edge)


def plane(size: float = 0.3, max_edge: float = 0.01) -> trimesh.Trimesh:
    """A square in the z = 0 plane, normal +z."""
    h = size / 2
    square = trimesh.Trimesh(vertices=[(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], faces=[(0, 1, 2), (0, 2, 3)])
    return _finish([square], max_edge)


PARTS = {"rack": rack, "holder": holder, "plane": plane}


def make_part(kind: str, **params) -> trimesh.Trimesh:
    """Build a procedural part by name with keyword parameters."""
    if kind not in PARTS:
        raise InputError(f"unknown procedural part {kind!r}; choose one of {sorted(PARTS)}")
    try:
        return PARTS[kind](**params)
    except TypeError as exc:
        raise InputError(f"bad parameters for procedural part {kind!r}: {exc}") from exc
