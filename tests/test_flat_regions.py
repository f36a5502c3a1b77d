"""zoo.sim.flat_regions against brute force: a subdivided mesh comes back to the faces it was cut from, the surface
covered is the input's (every point of a new face lies in an input face under it, and the areas agree), curved
parts, corners and holes stay, and FaceCover names the input face that holds a point as a search over every
input face does."""

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from zoo.geometry import face_normals  # noqa: E402
from zoo.sim.flat_regions import merge_flat_regions  # noqa: E402


def _subdivided(vertices, faces, times: int):
    for _ in range(times):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return np.asarray(vertices), np.asarray(faces)


def _areas(tri):
    return np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2


def _in_face(points, tri, tolerance=1e-9):
    """(P, T) whether each point lies in each triangle: within ``tolerance`` of its plane and inside its edges."""
    normal = face_normals(tri)
    off_plane = np.abs(np.einsum("ptc,tc->pt", points[:, None] - tri[None, :, 0], normal))
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = points[:, None] - tri[None, :, 0]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    p1, p2 = (d * e1).sum(-1), (d * e2).sum(-1)
    det = d11 * d22 - d12 * d12
    s, t = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
    return (off_plane <= tolerance) & (s >= -tolerance) & (t >= -tolerance) & (s + t <= 1 + tolerance)


def _samples(tri, per_face, rng):
    """(T * per_face, 3) uniform points on each triangle (T, 3, 3), face after face."""
    u = rng.random((len(tri), per_face, 2))
    u = np.where(u.sum(-1, keepdims=True) > 1, 1 - u, u)
    return (tri[:, None, 0] + u[..., :1] * (tri[:, None, 1] - tri[:, None, 0])
            + u[..., 1:] * (tri[:, None, 2] - tri[:, None, 0])).reshape(-1, 3)


def _check_same_surface(vertices, faces, merged, cover, rng):
    """Every point sampled on a merged face lies in one of the input faces under it, the cover names such a face,
    each merged face keeps the orientation of the faces under it, and the total area is the input's."""
    tri, source = vertices[merged], vertices[faces]
    assert np.isclose(_areas(tri).sum(), _areas(source).sum(), rtol=1e-9)
    points = _samples(tri, 20, rng)
    owner = np.repeat(np.arange(len(merged)), 20)
    inside = _in_face(points, source)
    assert inside.any(axis=1).all()
    named = cover.input_faces(owner, points)
    assert inside[np.arange(len(points)), named].all()
    assert (np.einsum("pc,pc->p", face_normals(tri)[owner], face_normals(source)[named]) > 1 - 1e-9).all()


def test_a_subdivided_triangle_and_box_come_back_to_their_faces():
    rng = np.random.default_rng(0)
    triangle = (np.array([[0.0, 0.0, 0.0], [0.3, 0.05, 0.0], [0.1, 0.2, 0.01]]), np.array([[0, 1, 2]]))
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    for mesh, expected in ((triangle, 1), ((box.vertices, box.faces), 12)):
        for times in (1, 3):
            v, f = _subdivided(*mesh, times)
            merged, cover = merge_flat_regions(v, f)
            assert len(merged) == expected, (times, len(merged))
            _check_same_surface(v, f, merged, cover, rng)
    v, f = _subdivided(*triangle, 2)
    merged, _ = merge_flat_regions(v, f)
    assert sorted(v[merged[0]].round(12).tolist()) == sorted(triangle[0].round(12).tolist())


def test_a_needle_subdivided_comes_back_and_a_fan_keeps_its_centre():
    """A sliver 200 mm by 0.2 mm (a tessellated cylinder's side) subdivided twice comes back to one face; a flat
    disc fanned about its centre from 48 rim points keeps its 48 faces (the centre's fan is larger than MAX_LINK)
    and, subdivided, comes back to 48 faces."""
    needle = (np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.2, 0.0002, 0.0]]), np.array([[0, 1, 2]]))
    merged, _ = merge_flat_regions(*_subdivided(*needle, 2))
    assert len(merged) == 1
    angle = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    disc_v = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.cos(angle), np.sin(angle), 0 * angle], axis=1) * 0.05])
    disc_f = np.array([[0, 1 + i, 1 + (i + 1) % 48] for i in range(48)])
    assert len(merge_flat_regions(disc_v, disc_f)[0]) == 48
    v, f = _subdivided(disc_v, disc_f, 2)
    merged, cover = merge_flat_regions(v, f)
    assert len(merged) == 48
    _check_same_surface(v, f, merged, cover, np.random.default_rng(1))


def test_curved_meshes_and_holes_stay():
    """An icosphere has no two faces in one plane: nothing changes. A flat square plate with a square hole,
    subdivided, loses its needless vertices but keeps the hole: no point of a merged face lies in it."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    merged, cover = merge_flat_regions(sphere.vertices, sphere.faces)
    assert np.array_equal(merged, sphere.faces) and cover.one_each
    outer = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
    inner = [(-0.3, -0.3), (0.3, -0.3), (0.3, 0.3), (-0.3, 0.3)]
    v = np.array([(x, y, 0.0) for x, y in outer + inner])
    f = np.array([[k, (k + 1) % 4, 4 + (k + 1) % 4] for k in range(4)] + [[k, 4 + (k + 1) % 4, 4 + k] for k in range(4)])
    v, f = _subdivided(v, f, 2)
    merged, cover = merge_flat_regions(v, f)
    assert len(merged) <= 8 < len(f)
    rng = np.random.default_rng(2)
    _check_same_surface(v, f, merged, cover, rng)
    points = _samples(v[merged], 200, rng)
    assert not ((np.abs(points[:, 0]) < 0.3 - 1e-9) & (np.abs(points[:, 1]) < 0.3 - 1e-9)).any()


def test_fine_flat_grid_on_a_cylinder_keeps_the_curved_sides():
    """A capped cylinder of 64 sections, subdivided: each side face's pieces come back to it, the caps' fans to
    their fans; the curved side is not flattened (every merged face is one of the 64 x 2 side faces' planes or a
    cap's)."""
    cylinder = trimesh.creation.cylinder(radius=0.02, height=0.2, sections=64)
    v, f = _subdivided(cylinder.vertices, cylinder.faces, 1)
    merged, cover = merge_flat_regions(v, f)
    assert len(merged) <= len(cylinder.faces)
    _check_same_surface(v, f, merged, cover, np.random.default_rng(3))


def test_merged_faces_stay_within_the_width_asked():
    """A 1 m square floor as a 16 x 16 grid: with no bound it comes back to 2 faces; bounded at 0.1 m, every merged
    face is at most 0.1 m wide (twice its area over its longest edge) and the floor keeps more faces, still fewer
    than the grid's."""
    g = np.linspace(-0.5, 0.5, 17)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange(x.size).reshape(17, 17)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], axis=1), np.stack([a, c, d], axis=1)])
    assert len(merge_flat_regions(v, f)[0]) == 2
    merged, cover = merge_flat_regions(v, f, max_width=0.1)
    tri = v[merged]
    widths = 2 * _areas(tri) / np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    assert widths.max() <= 0.1 + 1e-12 and 2 < len(merged) < len(f)
    _check_same_surface(v, f, merged, cover, np.random.default_rng(4))
