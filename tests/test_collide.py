"""collide and its broad phase against independent references.

The references are slow and obviously correct: the exact closest point of a triangle to a
sphere's centre (projection onto the plane if it falls inside, else the best of the three
edges), and a dense barycentric sampling for non-convex SDFs (a torus).
"""

import math

import numpy as np
import pytest
import torch
import trimesh

import zoo
import zoo.collision
from zoo.bounds import cell_lower_bounds
from zoo.collision import METHODS, candidate_triangles, clear_voxel_cache
from zoo.errors import InputError
from zoo.geometry import bary_to_points
from zoo.voxel import VoxelSDF

# -- meshes and references ------------------------------------------------------------------


def plane_grid(n=16, size=1.0):
    """A flat square grid mesh in z = 0: (n+1)^2 vertices, 2 n^2 triangles, float64 and int64."""
    x = np.linspace(-size / 2, size / 2, n + 1)
    gx, gy = np.meshgrid(x, x, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return vertices, faces


def subdivided_box(extents=(0.8, 0.8, 0.2), times=3):
    mesh = trimesh.creation.box(extents=extents)
    for _ in range(times):
        mesh = mesh.subdivide()
    return mesh


def closest_points_on_segments(p, a, b):
    """Closest points to p (3,) on segments a-b, a and b (M, 3) -> (M, 3)."""
    ab = b - a
    length2 = (ab * ab).sum(-1)
    t = np.clip(((p - a) * ab).sum(-1) / np.where(length2 > 0, length2, 1), 0, 1)
    return a + t[:, None] * ab


def closest_points_on_triangles(p, tri):
    """Exact closest points to p (3,) on triangles (M, 3, 3) -> (M, 3): the projection onto the
    triangle's plane when it falls inside the triangle, else the nearest of the three edges."""
    candidates = [closest_points_on_segments(p, tri[:, i], tri[:, (i + 1) % 3]) for i in range(3)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n2 = (n * n).sum(-1)
    q = p - (((p - tri[:, 0]) * n).sum(-1) / np.where(n2 > 0, n2, 1))[:, None] * n
    # inside when q is on the inner side of all three edges (never for a zero-area triangle)
    sides = [(np.cross(tri[:, (i + 1) % 3] - tri[:, i], q - tri[:, i]) * n).sum(-1) for i in range(3)]
    inside = (n2 > 0) & (np.min(sides, axis=0) >= 0)
    candidates.append(np.where(inside[:, None], q, np.inf))
    stacked = np.stack(candidates, 1)  # (M, 4, 3)
    best = np.linalg.norm(stacked - p, axis=-1).argmin(1)
    return stacked[np.arange(len(tri)), best]


def sphere_reference(center, radius, triangles):
    """Exact (min signed distance (M,), closest point (M, 3)) of a sphere over each triangle."""
    c = np.asarray(center, dtype=np.float64)
    points = closest_points_on_triangles(c, np.asarray(triangles, dtype=np.float64))
    return np.linalg.norm(points - c, axis=1) - radius, points


def sampled_minimum(sdf, triangles, n=40):
    """Dense barycentric sampling: (M,) an upper bound on each triangle's minimum, tight to
    within the sample spacing for a 1-Lipschitz SDF."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    bary = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], -1) / n  # (G, 3)
    tri = torch.as_tensor(np.asarray(triangles), dtype=torch.float64)
    points = torch.einsum("gv,mvc->mgc", torch.as_tensor(bary), tri)
    return sdf(points.reshape(-1, 3)).reshape(tri.shape[0], -1).amin(dim=1).numpy()


def random_rigid(seed):
    g = np.random.default_rng(seed)
    q, r = np.linalg.qr(g.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = q, g.normal(size=3)
    return pose


def world_triangles(mesh):
    vertices, faces = (mesh.vertices, mesh.faces) if hasattr(mesh, "faces") else mesh
    return np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]


class ExactSphereDetector(zoo.Sphere):
    """A sphere with a ``detect`` that returns the exact closest point (a perfect amortized model)."""

    def detect(self, triangles):
        tri = triangles.double().numpy()
        _, points = sphere_reference(self.center.numpy(), self.radius, tri)
        # barycentrics of the closest points by least squares on [v1 v2 v3; 1 1 1]
        a = np.concatenate([tri.transpose(0, 2, 1), np.ones((len(tri), 1, 3))], axis=1)
        rhs = np.concatenate([points, np.ones((len(tri), 1))], axis=1)
        bary = np.stack([np.linalg.lstsq(a[k], rhs[k], rcond=None)[0] for k in range(len(tri))])
        bary = np.clip(bary, 0, None)
        return torch.as_tensor(bary / bary.sum(1, keepdims=True), dtype=triangles.dtype)


class Counting:
    """Counts the points an SDF is evaluated at through ``__call__`` (where grids are built)."""

    def __init__(self, sdf):
        self.sdf, self.bounds, self.calls = sdf, sdf.bounds, 0

    def __call__(self, points):
        self.calls += points.shape[0]
        return self.sdf(points)

    def value_and_grad(self, points):
        return self.sdf.value_and_grad(points)


# -- broad phase ----------------------------------------------------------------------------


def random_triangles(sdf, m, seed, size=(0.01, 0.15)):
    """Triangles scattered over the SDF's bounds grown by 0.2, edges of varied length: (M, 3, 3)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (b.double() for b in sdf.bounds)
    centres = lo - 0.2 + torch.rand(m, 3, generator=g, dtype=torch.float64) * (hi - lo + 0.4)
    scale = size[0] + torch.rand(m, 1, 1, generator=g, dtype=torch.float64) * (size[1] - size[0])
    return centres.unsqueeze(1) + scale * torch.randn(m, 3, 3, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("margin", [0.0, 1e-3, 0.02])
def test_broad_phase_keeps_every_triangle_of_an_exact_sphere_reference(margin):
    sphere = zoo.Sphere(0.25, center=(0.03, -0.02, 0.01))
    tri = random_triangles(sphere, 3000, seed=1)
    exact, _ = sphere_reference(sphere.center.numpy(), sphere.radius, tri.numpy())
    kept = candidate_triangles(sphere, tri.float(), margin)
    must_keep = np.flatnonzero(exact <= margin)
    assert kept.dtype == torch.int64 and bool((kept[1:] > kept[:-1]).all())
    assert set(must_keep) <= set(kept.tolist())
    assert 0 < len(must_keep) and len(kept) < 0.6 * len(tri)  # it does cull


def test_broad_phase_keeps_every_triangle_of_a_sampled_torus_reference():
    torus = zoo.Torus(0.25, 0.08)
    tri = random_triangles(torus, 1500, seed=2)
    kept = set(candidate_triangles(torus, tri, 1e-3).tolist())
    must_keep = np.flatnonzero(sampled_minimum(torus, tri) <= 1e-3)
    assert len(must_keep) > 20 and set(must_keep) <= kept
    assert len(kept) < 0.7 * len(tri)


@pytest.mark.parametrize("m", [100, 600])  # 300 and 1800 vertices: below and above the size where cells are bounded first
def test_broad_phase_keeps_the_tight_case_of_the_vertex_cull(m):
    # An equilateral triangle square to a sphere's radius, its vertices all at distance margin + R from the
    # sphere (R its circumradius): the vertex bound min f_i - R is exactly the margin.
    g = torch.Generator().manual_seed(3)
    r, margin = 0.25, 1e-3
    u = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=torch.float64), dim=-1)
    w = torch.nn.functional.normalize(torch.linalg.cross(u, torch.randn(m, 3, generator=g, dtype=torch.float64)), dim=-1)
    w2 = torch.linalg.cross(u, w)
    radius = (0.01 + 0.2 * torch.rand(m, generator=g, dtype=torch.float64)).unsqueeze(-1)
    offset = ((r + margin + radius) ** 2 - radius**2).sqrt()  # |centre| that puts the vertices at r + margin + R
    corners = [radius * (torch.cos(a) * w + torch.sin(a) * w2) for a in torch.tensor([0.0, 2.0, 4.0], dtype=torch.float64) * math.pi / 3]
    tri = torch.stack([offset * u + c for c in corners], 1)
    sphere = zoo.Sphere(r)
    torch.testing.assert_close(sphere(tri.reshape(-1, 3)).reshape(m, 3), (margin + radius).expand(m, 3), rtol=0, atol=1e-12)
    # (the vertex cull itself: the bounding-box test before it may drop some, rightly: their centres lie beyond the margin)
    vertex_cull = zoo.collision._vertex_cull
    assert bool(vertex_cull(sphere, *_indexed(tri), margin)[0].all())
    # and just beyond the margin they are all culled: the cull is not merely keeping everything
    assert not bool(vertex_cull(sphere, *_indexed(tri + 0.01 * u.unsqueeze(1)), margin)[0].any())


def test_cell_bounds_drop_only_faces_the_plain_vertex_cull_keeps_in_vain():
    """The cell pre-pass against the plain vertex cull (every vertex queried): it keeps a subset, every
    face it drops beyond that is farther than the margin (exact sphere distances), the values it returns
    are the SDF's, and a face it clears costs no vertex query."""
    collide_module = zoo.collision
    sphere = zoo.Sphere(0.25, center=(0.03, -0.02, 0.01))
    tri = random_triangles(sphere, 3000, seed=4).float()
    exact, _ = sphere_reference(sphere.center.numpy(), sphere.radius, tri.double().numpy())
    margin = 1e-3
    vertices, faces = _indexed(tri)
    with_cells, f = collide_module._vertex_cull(sphere, vertices, faces, margin)
    plain = cell_lower_bounds(tri, torch.as_tensor(sphere(tri.reshape(-1, 3))).reshape(-1, 3)) <= margin
    assert bool((with_cells <= plain).all())
    dropped = (plain & ~with_cells).numpy()
    assert bool((exact[dropped] > margin).all())
    queried = ~torch.isnan(f)
    torch.testing.assert_close(f[queried], torch.as_tensor(sphere(vertices[queried])))
    assert bool(queried[faces[with_cells]].all())  # every kept face's vertices were evaluated
    assert int(queried.sum()) < 0.7 * len(vertices)  # cells bounded by one query cost no vertex query
    assert len(vertices) >= collide_module.CLUSTER_CULL_MIN


def test_broad_phase_drops_triangles_outside_the_bounds_box():
    box = zoo.Box((0.1, 0.1, 0.1))
    far = torch.tensor([[[0.2, 0, 0], [0.3, 0, 0], [0.2, 0.1, 0]]])
    assert len(candidate_triangles(box, far, 1e-3)) == 0
    assert len(candidate_triangles(box, far, 0.1)) == 1  # margin grows the box


# -- collide against analytic geometry ------------------------------------------------------

SPHERE = dict(radius=0.2, center=(0.013, -0.021, 0.15))
METHOD_SETTINGS = {  # method -> (kwargs, tolerance on depth above the exact minimum)
    "fw": (dict(iters=100), 2e-5),
    "amortized": (dict(), 1e-6),
    "fw-refined": (dict(method="amortized", refine=5), 1e-6),
}


@pytest.mark.parametrize("name", list(METHOD_SETTINGS))
def test_sphere_cutting_a_plane_gives_the_analytic_contacts(name):
    kwargs, tol = METHOD_SETTINGS[name]
    kwargs = {"method": name, **kwargs}
    sphere = ExactSphereDetector(**SPHERE)
    vertices, faces = plane_grid(16)
    margin = 0.012
    exact, closest = sphere_reference(SPHERE["center"], SPHERE["radius"], vertices[faces])
    # no triangle's minimum lies within the solvers' tolerance of the margin, so the set is sharp
    assert not np.any(np.abs(exact - margin) < 2e-3)
    c = zoo.collide(sphere, (vertices, faces), margin=margin, **kwargs)

    assert c.triangles.tolist() == np.flatnonzero(exact <= margin).tolist()
    assert len(c) == len(c.triangles) > 30 and c.n_triangles == len(faces)
    assert c.n_candidates >= len(c)
    ref = exact[c.triangles.numpy()]
    d = c.depths.numpy()
    assert np.all(d >= ref - 1e-6) and np.all(d <= ref + tol)
    # every point is on its triangle, at the depth reported, near the exact closest point
    tri = vertices[faces][c.triangles.numpy()]
    np.testing.assert_allclose(np.einsum("kv,kvc->kc", c.bary.numpy(), tri), c.points.numpy(), atol=1e-6)
    assert np.all(c.bary.numpy() >= 0) and np.allclose(c.bary.numpy().sum(1), 1)
    offset = c.points.numpy() - np.array(SPHERE["center"])
    np.testing.assert_allclose(np.linalg.norm(offset, axis=1) - SPHERE["radius"], d, atol=1e-6)
    np.testing.assert_allclose(c.normals.numpy(), offset / np.linalg.norm(offset, axis=1, keepdims=True), atol=1e-6)
    # the position of the minimum is well defined for a sphere: error ~ sqrt(depth error * r)
    assert np.abs(c.points.numpy() - closest[c.triangles.numpy()]).max() <= 3 * math.sqrt(tol * 0.2) + 1e-5


def test_pgd_contacts_are_the_solvers_answers_and_never_below_the_minimum():
    # PhysX's rule stops short of the minimum (its steps decay geometrically), so its depths are
    # checked against the solver itself, and against the exact minimum only from below.
    sphere = zoo.Sphere(**SPHERE)
    vertices, faces = plane_grid(16)
    exact, _ = sphere_reference(SPHERE["center"], SPHERE["radius"], vertices[faces])
    c = zoo.collide(sphere, (vertices, faces), margin=0.012, method="pgd")
    candidates = candidate_triangles(sphere, torch.as_tensor(vertices[faces]), 0.012)
    tri = torch.as_tensor(vertices[faces])[candidates]
    bary = zoo.solvers.projected_gradient(sphere, tri)
    d = sphere(torch.einsum("mv,mvc->mc", bary, tri))
    assert c.triangles.tolist() == candidates[d <= 0.012].tolist()
    torch.testing.assert_close(c.depths, d[d <= 0.012])
    assert set(c.triangles.tolist()) <= set(np.flatnonzero(exact <= 0.012).tolist())
    assert np.all(c.depths.numpy() >= exact[c.triangles.numpy()] - 1e-9)


def test_subdivided_box_against_a_sphere_matches_the_exact_reference():
    mesh = subdivided_box()
    center, radius = (0.1, -0.05, 0.2), 0.15  # dips 0.05 below the box's top face at z = 0.1
    exact, _ = sphere_reference(center, radius, world_triangles(mesh))
    c = zoo.collide(zoo.Sphere(radius, center), mesh, margin=1e-3, iters=100)
    expected = np.flatnonzero(exact <= 1e-3)
    assert len(expected) > 10 and c.triangles.tolist() == expected.tolist()
    assert np.all(np.abs(c.depths.numpy() - exact[expected]) <= 2e-5)


def test_subdivided_box_against_a_torus_matches_brute_force():
    mesh = subdivided_box()
    torus = zoo.Torus(0.25, 0.08, center=(0.0, 0.02, 0.05))  # its tube pokes through the top face
    margin = 1e-3
    upper = sampled_minimum(torus, world_triangles(mesh))  # >= true minimum
    spacing = max(np.asarray(mesh.edges_unique_length)) / 40  # sample spacing bound
    c = zoo.collide(torus, mesh, margin=margin, iters=100)
    got = set(c.triangles.tolist())
    surely_in = set(np.flatnonzero(upper <= margin - 1e-4).tolist())
    possibly_in = set(np.flatnonzero(upper - spacing <= margin).tolist())
    assert len(surely_in) > 10 and surely_in <= got <= possibly_in
    ours = c.depths.numpy()
    best = upper[c.triangles.numpy()]
    # FW's point is on the triangle: never below the true minimum, and close to the sampled one
    assert np.all(ours >= best - spacing) and np.all(ours <= best + 1e-4)
    np.testing.assert_allclose(torus(c.points.double()).numpy(), ours, atol=1e-6)


def test_rigid_motion_moves_the_contacts_with_the_scene():
    mesh = subdivided_box(times=2)
    torus = zoo.Torus(0.25, 0.08, center=(0.0, 0.02, 0.05))
    sdf_pose, motion = random_rigid(1), random_rigid(3)
    turn = np.eye(4)
    turn[:2, :2] = [[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]]
    mesh_pose = sdf_pose @ turn  # the box turned about the torus's axis, still cut by it
    a = zoo.collide(torus, mesh, sdf_pose=sdf_pose, mesh_pose=mesh_pose, iters=30)
    b = zoo.collide(torus, mesh, sdf_pose=motion @ sdf_pose, mesh_pose=motion @ mesh_pose, iters=30)
    assert len(a) > 5 and a.triangles.tolist() == b.triangles.tolist()
    np.testing.assert_allclose(b.depths.numpy(), a.depths.numpy(), atol=1e-9)
    m = torch.as_tensor(motion)
    np.testing.assert_allclose(b.points.numpy(), (a.points @ m[:3, :3].T + m[:3, 3]).numpy(), atol=1e-9)
    np.testing.assert_allclose(b.normals.numpy(), (a.normals @ m[:3, :3].T).numpy(), atol=1e-9)
    # and the relative pose is all that matters: the same as placing the mesh in the SDF's frame
    local = zoo.collide(torus, mesh, mesh_pose=np.linalg.inv(sdf_pose) @ mesh_pose, iters=30)
    assert local.triangles.tolist() == a.triangles.tolist()
    np.testing.assert_allclose(local.depths.numpy(), a.depths.numpy(), atol=1e-9)


def test_input_forms_and_dtypes():
    vertices, faces = plane_grid(8)
    sphere = zoo.Sphere(**SPHERE)
    as_numpy = zoo.collide(sphere, (vertices, faces), sdf_pose=np.eye(4), mesh_pose=np.eye(4))
    as_trimesh = zoo.collide(sphere, trimesh.Trimesh(vertices, faces, process=False))
    as_float32 = zoo.collide(sphere, (torch.tensor(vertices, dtype=torch.float32), torch.tensor(faces)))
    assert as_numpy.depths.dtype == as_trimesh.depths.dtype == torch.float64  # float64 is kept
    assert as_float32.depths.dtype == as_float32.points.dtype == as_float32.normals.dtype == torch.float32
    assert as_float32.triangles.dtype == torch.int64
    assert as_numpy.triangles.tolist() == as_trimesh.triangles.tolist() == as_float32.triangles.tolist()
    np.testing.assert_allclose(as_float32.depths.numpy(), as_numpy.depths.numpy(), atol=1e-5)
    assert bool((as_numpy.depths <= 1e-3).all())


def test_no_contact_gives_empty_contacts_of_the_right_shapes():
    vertices, faces = plane_grid(4)
    c = zoo.collide(zoo.Sphere(0.1, center=(0, 0, 0.5)), (vertices, faces))
    assert len(c) == 0 and c.points.shape == (0, 3) and c.normals.shape == (0, 3) and c.bary.shape == (0, 3)
    assert c.triangles.dtype == torch.int64 and c.n_triangles == len(faces) and c.n_candidates == 0


def assert_empty_contacts(c, dtype=None):
    assert len(c) == 0 and c.n_candidates == 0
    assert c.points.shape == (0, 3) and c.depths.shape == (0,) and c.normals.shape == (0, 3) and c.triangles.shape == (0,)
    assert c.triangles.dtype == torch.int64 and c.bary.shape == (0, 3)
    if dtype is not None:
        assert c.points.dtype == c.depths.dtype == c.normals.dtype == dtype


def empty_meshes():
    """Meshes with no faces, in every form collide takes: a simulation step may hand it any of them."""
    return {
        "trimesh": trimesh.Trimesh(),
        "arrays": (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)),
        "vertices, no faces": (np.random.default_rng(0).random((5, 3)), np.zeros((0, 3), dtype=np.int64)),
        "lists": ([], []),
        "float32 tensors": (torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64)),
    }


@pytest.mark.parametrize("method", ["fw", "pgd", "voxel-fw", "amortized"])
def test_an_empty_mesh_gives_empty_contacts_for_every_method(method):
    sdf = ExactSphereDetector(**SPHERE)
    for name, mesh in empty_meshes().items():
        c = zoo.collide(sdf, mesh, method=method, voxel_resolution=16)
        assert_empty_contacts(c, torch.float32 if name in ("lists", "float32 tensors") else torch.float64)  # float64 kept
        assert c.n_triangles == 0, name


@pytest.mark.parametrize("method", ["fw", "pgd", "voxel-fw", "amortized"])
def test_nothing_near_gives_empty_contacts_for_every_method(method):
    sdf = ExactSphereDetector(0.1)
    corner = np.array([[0.095, 0.095, 0.095], [0.099, 0.095, 0.095], [0.095, 0.099, 0.095]])  # in the bounds box, 0.06 from the sphere
    plane = plane_grid(4)
    for vertices, faces in ((plane[0] + np.array([0.0, 0.0, 0.5]), plane[1]), (corner, np.array([[0, 1, 2]]))):
        c = zoo.collide(sdf, (vertices, faces), method=method, voxel_resolution=16)
        assert_empty_contacts(c)
        assert c.n_triangles == len(faces)


def test_a_model_shape_collides_with_an_empty_mesh_or_nothing_near():
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    far = plane_grid(4)[0] + np.array([10.0, 10.0, 10.0]), plane_grid(4)[1]
    for method in ("amortized", "fw", "pgd", "voxel-fw"):
        for mesh in (trimesh.Trimesh(), far):
            assert_empty_contacts(zoo.collide(shape, mesh, method=method, voxel_resolution=16))
    assert candidate_triangles(shape, torch.zeros(0, 3, 3)).shape == (0,)


def test_degenerate_faces_are_kept_and_answered_exactly():
    vertices = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.05, 0.02, 0], [0.3, 0.3, 0.3]])
    faces = np.array([[0, 1, 2], [3, 3, 3], [0, 0, 1], [4, 4, 4], [0, 1, 3]])  # collinear, point, segment, far point, fine
    sphere = zoo.Sphere(0.1, center=(0.05, 0.0, 0.09))
    exact, _ = sphere_reference(sphere.center.numpy(), 0.1, vertices[faces])
    for method in ("fw", "pgd"):
        c = zoo.collide(sphere, (vertices, faces), margin=0.0, method=method, iters=50)
        assert c.triangles.tolist() == [0, 1, 2, 4]
        assert bool(torch.isfinite(c.points).all() & torch.isfinite(c.normals).all())
        d = c.depths.numpy()
        assert np.all(d >= exact[[0, 1, 2, 4]] - 1e-9) and np.all(d <= exact[[0, 1, 2, 4]] + 1e-3)


# -- methods --------------------------------------------------------------------------------


def test_voxel_method_is_close_and_its_grid_is_built_once():
    clear_voxel_cache()
    vertices, faces = plane_grid(16)
    sdf = Counting(zoo.Sphere(**SPHERE))
    exact, _ = sphere_reference(SPHERE["center"], SPHERE["radius"], vertices[faces])
    c = zoo.collide(sdf, (vertices, faces), method="voxel-fw", voxel_resolution=40, margin=0.01)
    built = sdf.calls
    assert built >= 40**3
    again = zoo.collide(sdf, (vertices, faces), method="voxel-fw", voxel_resolution=40, margin=0.01)
    assert sdf.calls - built < 1000  # the broad phase's centroids only, no new grid
    assert again.triangles.tolist() == c.triangles.tolist()
    cell = 0.44 / 39  # grid side (0.4 padded by 5% each way) / cells
    np.testing.assert_allclose(c.depths.numpy(), exact[c.triangles.numpy()], atol=cell)
    assert c.method == "voxel-fw"
    # a VoxelSDF passed in is used as it is
    grid = VoxelSDF(zoo.Sphere(**SPHERE), resolution=40)
    direct = zoo.collide(grid, (vertices, faces), method="voxel-fw", margin=0.01)
    np.testing.assert_allclose(direct.depths.numpy(), zoo.collide(grid, (vertices, faces), margin=0.01).depths.numpy())
    clear_voxel_cache()


def test_refine_never_makes_the_amortized_answer_worse():
    class RoughDetector(zoo.Sphere):
        def detect(self, triangles):  # always the centroid: a poor amortized model
            return torch.full(triangles.shape[:2], 1 / 3, dtype=triangles.dtype)

    vertices, faces = plane_grid(16)
    sdf = RoughDetector(**SPHERE)
    rough = zoo.collide(sdf, (vertices, faces), method="amortized", margin=0.05)
    refined = zoo.collide(sdf, (vertices, faces), method="amortized", margin=0.05, refine=20)
    assert set(rough.triangles.tolist()) <= set(refined.triangles.tolist())
    common = torch.isin(refined.triangles, rough.triangles)
    assert bool((refined.depths[common] <= rough.depths + 1e-6).all())
    assert float((rough.depths - refined.depths[common]).max()) > 1e-3


def test_amortized_on_a_model_shape_hands_the_candidates_over_as_a_mesh():
    # The bundled mugs model: collide gives detect_mesh the candidates as an indexed mesh and takes
    # its distances as the depths. Against the plain path (detect, then a value pass): the same
    # candidates, a superset of the contacts (the answer is kept only where no vertex is lower),
    # depths that are the SDF's at the reported points, never above the plain ones.
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    s = shape.similarity
    g = np.random.default_rng(0)
    vertices, faces = plane_grid(24, size=1.0)
    vertices = vertices + np.array([0.0, 0.0, 0.05]) + 0.004 * g.normal(size=vertices.shape)  # edges ~0.04
    vertices = s.to_source(vertices)  # a bumpy plane cutting the mug, in its frame
    margin = 0.003 / s.scale
    c = zoo.collide(shape, (vertices, faces), margin=margin, method="amortized")
    assert set(c.timings) == {"broad", "narrow", "normals"}

    class Plain:  # the same shape without detect_mesh: collide's generic amortized path
        bounds = shape.bounds
        __call__ = staticmethod(shape.__call__)
        value_and_grad = staticmethod(shape.value_and_grad)
        detect = staticmethod(shape.detect)

    p = zoo.collide(Plain(), (vertices, faces), margin=margin, method="amortized")
    assert c.n_candidates == p.n_candidates and len(p) > 20
    assert set(p.triangles.tolist()) <= set(c.triangles.tolist())
    np.testing.assert_allclose(shape(c.points).numpy(), c.depths.numpy(), atol=1e-9 / s.scale)
    common = torch.isin(c.triangles, p.triangles)
    assert bool((c.depths[common] <= p.depths + 1e-9 / s.scale).all())

    # detect_mesh gets the distances the broad phase evaluated at the vertices, and needs no other at them
    seen = {}
    real = shape.detect_mesh

    def spy(vertices, faces, **kwargs):
        seen.update(faces=faces, values=kwargs["vertex_values"])
        return real(vertices, faces, **kwargs)

    shape.detect_mesh = spy
    again = zoo.collide(shape, (vertices, faces), margin=margin, method="amortized")
    del shape.detect_mesh
    given = seen["values"][seen["faces"]]
    assert bool(torch.isfinite(given).all())  # every candidate's vertices
    torch.testing.assert_close(given, shape(torch.as_tensor(vertices)[seen["faces"]].reshape(-1, 3)).reshape(-1, 3))
    torch.testing.assert_close(again.points, c.points)


def test_polish_false_gives_the_unpolished_narrow_phase_and_only_for_amortized():
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    s = shape.similarity
    vertices, faces = plane_grid(24, size=1.0)
    vertices = s.to_source(vertices + np.array([0.0, 0.0, 0.05]) + 0.004 * np.random.default_rng(1).normal(size=vertices.shape))
    margin = 0.003 / s.scale
    fast = zoo.collide(shape, (vertices, faces), margin=margin, method="amortized", polish=False)
    tri = torch.as_tensor(vertices)[torch.as_tensor(faces)][fast.triangles]
    # the unpolished narrow phase is solve_mesh's answer without the line search
    expected, _ = shape.detect_mesh(*_indexed(tri), polish=False)
    np.testing.assert_allclose(fast.points.numpy(), bary_to_points(tri, expected).numpy(), atol=1e-9)
    polished = zoo.collide(shape, (vertices, faces), margin=margin, method="amortized")
    both = torch.isin(polished.triangles, fast.triangles)
    assert bool(both.any()) and not torch.allclose(polished.points[both], fast.points, atol=1e-6)
    with pytest.raises(InputError, match="polish=False applies to"):
        zoo.collide(shape, (vertices, faces), margin=margin, method="fw", polish=False)


def _indexed(tri: torch.Tensor):
    """Triangles (M, 3, 3) -> (distinct vertices (V, 3), faces (M, 3))."""
    from zoo.geometry import unique_rows

    v, inverse = unique_rows(tri.reshape(-1, 3))
    return v, inverse.reshape(-1, 3)


def test_a_detect_mesh_of_the_wrong_shape_is_a_typed_error():
    class Broken(zoo.Sphere):
        def detect(self, triangles):
            return torch.full(triangles.shape[:2], 1 / 3, dtype=triangles.dtype)

        def detect_mesh(self, vertices, faces, cutoff=None, known=None, polish=True, vertex_values=None):
            return torch.zeros(len(faces), 2), torch.zeros(len(faces))

    vertices, faces = plane_grid(8)
    with pytest.raises(InputError, match="detect_mesh returned"):
        zoo.collide(Broken(**SPHERE), (vertices, faces), method="amortized", margin=0.05)


# -- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sdf_pose=np.eye(3)), "4x4"),
        (dict(mesh_pose=np.ones((4, 4))), "rotation"),
        (dict(method="gjk"), "'fw', 'pgd', 'voxel-fw', 'amortized'"),
        (dict(method="amortized"), r'method="amortized" needs a shape from a model with a detector: zoo\.load\(NAME\)\.shape'),
        (dict(margin=-1.0), "margin"),
        (dict(margin=float("nan")), "margin"),
        (dict(iters=0), "iters"),
        (dict(refine=-1), "refine"),
        (dict(method="voxel-fw", voxel_resolution=1), "resolution"),
    ],
)
def test_bad_arguments_are_input_errors(kwargs, match):
    vertices, faces = plane_grid(2)
    with pytest.raises(InputError, match=match):
        zoo.collide(zoo.Sphere(**SPHERE), (vertices, faces), **kwargs)


def test_bad_meshes_and_sdfs_are_input_errors():
    vertices, faces = plane_grid(2)
    sphere = zoo.Sphere(**SPHERE)
    bad = vertices.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        zoo.collide(sphere, (bad, faces))
    with pytest.raises(InputError, match="outside"):
        zoo.collide(sphere, (vertices, faces + 100))
    with pytest.raises(InputError, match="integer"):
        zoo.collide(sphere, (vertices, faces.astype(float)))
    with pytest.raises(InputError, match=r"\(F, 3\)"):
        zoo.collide(sphere, (vertices, faces[:, :2]))
    with pytest.raises(InputError, match="Trimesh"):
        zoo.collide(sphere, "mesh.obj")
    with pytest.raises(InputError, match="not an SDF"):
        zoo.collide(object(), (vertices, faces))
    with pytest.raises(InputError, match="not an SDF"):
        candidate_triangles("sphere", torch.zeros(1, 3, 3))
    with pytest.raises(InputError, match="resolution"):  # refused even with nothing near
        zoo.collide(zoo.Sphere(0.1, center=(5, 5, 5)), (vertices, faces), method="voxel-fw", voxel_resolution=1)
    with pytest.raises(InputError, match="iters has no meaning"):
        zoo.collide(ExactSphereDetector(**SPHERE), (vertices, faces), method="amortized", iters=5)


def test_methods_constant_lists_every_method():
    assert set(METHODS) == {"fw", "pgd", "voxel-fw", "amortized"}


# -- triangles far larger than the SDF ------------------------------------------------------

# A 5 cm sphere 1 mm into the top (z = 0.01) of a 30 x 30 x 2 cm box of two triangles a face, at
# the face's centre (on the diagonal both triangles share), off it, and near one of its corners.
BIG_FACE_CENTRES = [(0.0, 0.0), (0.013, -0.021), (-0.061, 0.087), (0.12, 0.12), (-0.1, 0.04)]


@pytest.mark.parametrize("method", ["fw", "pgd", "voxel-fw"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_sphere_1mm_into_a_two_triangle_face_is_found_at_1mm_by_every_method(method, dtype):
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.02))
    vertices, faces = torch.as_tensor(box.vertices, dtype=dtype), torch.as_tensor(box.faces)
    top = set(np.nonzero(box.face_normals[:, 2] > 0.99)[0].tolist())
    for x, y in BIG_FACE_CENTRES:
        sphere = zoo.Sphere(0.05, center=(x, y, 0.01 + 0.05 - 0.001))
        c = zoo.collide(sphere, (vertices, faces), method=method)
        exact, _ = sphere_reference(sphere.center.numpy(), 0.05, world_triangles(box)[c.triangles.numpy()])
        assert len(c) >= 1 and set(c.triangles.tolist()) <= top, (x, y, c)
        assert abs(float(c.depths.min()) + 1e-3) <= 5e-5, (x, y, c.depths)
        np.testing.assert_allclose(c.depths.double().numpy(), exact, atol=5e-5)  # every row: its own triangle's minimum
        assert c.depths.dtype == dtype and c.points.dtype == dtype
        np.testing.assert_allclose(sphere(c.points.double()).numpy(), c.depths.double().numpy(), atol=1e-6)
        bary_points = bary_to_points(torch.as_tensor(world_triangles(box))[c.triangles], c.bary.double())
        np.testing.assert_allclose(bary_points.numpy(), c.points.double().numpy(), atol=1e-6)


@pytest.mark.parametrize("method", ["fw", "pgd", "voxel-fw", "amortized"])
def test_big_and_small_triangles_give_the_exact_minimum_of_a_sphere(method):
    """Random triangles 0.5 to 20 times the sphere's size through it, and the same region as small triangles:
    each triangle's depth is its exact minimum (closest point to the centre), within the method's error."""
    sdf = ExactSphereDetector(**SPHERE) if method == "amortized" else zoo.Sphere(**SPHERE)
    centre, radius = np.asarray(SPHERE["center"]), SPHERE["radius"]
    g = np.random.default_rng(7)
    for size in (0.5, 2.0, 6.0, 20.0):
        tri = g.normal(size=(24, 3, 3)) * size * radius
        tri = tri - tri.mean(axis=1, keepdims=True) + centre + g.uniform(-1, 1, size=(24, 1, 3)) * radius
        c = zoo.collide(sdf, (tri.reshape(-1, 3), np.arange(72).reshape(24, 3)), margin=1e-3, method=method)
        exact, _ = sphere_reference(centre, radius, tri)
        expected = np.nonzero(exact <= 1e-3 - 1e-4)[0]
        assert set(expected.tolist()) <= set(c.triangles.tolist()), (size, c)
        # the methods' own error on pieces a quarter of the radius long, largest where the centre is near the plane
        tolerance = {"fw": 8e-3, "pgd": 5e-3, "voxel-fw": 1e-2, "amortized": 1e-6}[method] * radius
        np.testing.assert_allclose(c.depths.double().numpy(), exact[c.triangles.numpy()], atol=tolerance)
        assert bool((c.depths.double().numpy() >= exact[c.triangles.numpy()] - 1e-6).all())  # attained values


def test_a_box_sdf_resting_1mm_into_a_big_face_is_found_flat():
    """zoo.Box's minimum over a big face parallel to its bottom is exactly its penetration, everywhere under it."""
    box_sdf = zoo.Box(half_extents=(0.02, 0.03, 0.01), center=(0.05, -0.04, 0.01 + 0.01 - 0.001))
    table = trimesh.creation.box(extents=(0.6, 0.6, 0.02))
    for method in ("fw", "pgd", "voxel-fw"):
        c = zoo.collide(box_sdf, table, method=method)
        assert len(c) >= 1 and abs(float(c.depths.min()) + 1e-3) <= 5e-5, (method, c.depths)


def test_large_triangle_pieces_cover_what_can_touch_and_are_small():
    """cut_large's pieces: each at most PIECE_AT_MOST of the SDF's extent, inside its parent, and every
    point of the parent within the margin of the sphere lies in some piece (checked on a dense sample)."""
    from zoo.large_triangles import PIECE_AT_MOST, cut_large

    sphere = zoo.Sphere(0.05, center=(0.01, 0.02, 0.04))
    tri = torch.tensor([[[-0.4, -0.3, 0.0], [0.5, -0.2, 0.0], [0.0, 0.6, 0.0]]], dtype=torch.float64)
    pieces = cut_large(sphere, tri, margin=1e-3)
    assert pieces is not None and pieces.parent.tolist() == [0] * len(pieces.parent) and 4 <= len(pieces.parent) < 2000
    assert float(torch.linalg.vector_norm(pieces.triangles[:, 1:] - pieces.triangles[:, :1], dim=-1).max()) <= PIECE_AT_MOST * 0.1 + 1e-12
    assert bool((pieces.corners >= 0).all()) and torch.allclose(pieces.corners.sum(-1), torch.ones(()).double())
    g = np.random.default_rng(0)
    bary = g.dirichlet(np.ones(3), size=200_000)
    points = bary @ tri[0].numpy()
    touching = bary[(sphere(torch.as_tensor(points)) <= 1e-3).numpy()]
    assert len(touching) > 100
    # barycentrics of each touching point in each piece: non-negative in at least one
    inv = torch.linalg.inv(pieces.corners.transpose(1, 2))  # piece-local = inv @ parent bary
    local = torch.einsum("pij,nj->npi", inv, torch.as_tensor(touching))
    assert bool((local >= -1e-9).all(dim=-1).any(dim=1).all())
    assert cut_large(sphere, tri * 0.02, margin=1e-3) is None  # nothing that long: nothing to do


def test_too_many_pieces_is_refused_not_solved_coarsely(monkeypatch):
    import zoo.large_triangles

    monkeypatch.setattr(zoo.large_triangles, "MAX_PIECES", 50)
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.02))
    with pytest.raises(InputError, match="subdivide the mesh"):
        zoo.collide(zoo.Sphere(0.05, center=(0, 0, 0.059)), box)


def test_the_model_shape_on_a_two_triangle_plane_matches_a_dense_reference():
    """The mugs model's shape over a plane of two triangles 5 times its size, 1% of its size into its
    bottom: every method's depth is the NeuralSDF's minimum over the plane, found by a dense grid."""
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    s = shape.similarity
    g = torch.linspace(-0.5, 0.5, 201, dtype=torch.float64)
    gx, gy = torch.meshgrid(g, g, indexing="ij")

    def plane_minimum(z):  # normalised frame
        points = torch.stack([gx.ravel(), gy.ravel(), torch.full_like(gx.ravel(), z)], -1)
        return float(shape(torch.as_tensor(s.to_source(points.numpy()))).min()) * s.scale

    lo, hi = -0.5, -0.3  # the plane height whose minimum is -0.01 (normalised units), by bisection: the
    # minimum falls monotonically from +0.11 to -0.065 over this range (the mug's bottom)
    for _ in range(30):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if plane_minimum(mid) > -0.01 else (lo, mid)
    z = (lo + hi) / 2
    reference = plane_minimum(z) / s.scale
    corners = np.array([[-2.5, -2.5, z], [2.5, -2.5, z], [2.5, 2.5, z], [-2.5, 2.5, z]])
    mesh = (s.to_source(corners), np.array([[0, 1, 2], [0, 2, 3]]))
    for method in ("amortized", "fw", "pgd"):
        c = zoo.collide(shape, mesh, margin=0.003 / s.scale, method=method)
        assert len(c) >= 1, method
        assert abs(float(c.depths.min()) - reference) <= 0.002 / s.scale, (method, float(c.depths.min()), reference)


def test_the_coherent_collider_finds_the_big_face_too():
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.02))
    sphere = zoo.Sphere(0.05, center=(0.013, -0.021, 0.059))
    collider = zoo.CoherentCollider(sphere, box, margin=1e-3, method="fw")
    for dz in (0.0, -2e-4, -4e-4):
        c = collider(sdf_pose=torch.tensor([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, dz], [0, 0, 0, 1.0]]))
        assert len(c) >= 1 and abs(float(c.depths.min()) - (-1e-3 + dz)) <= 5e-5, (dz, c.depths)
