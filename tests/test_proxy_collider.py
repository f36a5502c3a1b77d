"""zoo.proxy_collider: the proxy path's passes (compiled, and numpy) held against slow, obviously correct references.

Each face's answer against a brute-force minimum of the SDF over a dense barycentric grid of the face (every face
whose minimum lies within the margin is reported, at a depth no further from that minimum than the search's
tolerance); the compiled passes against the numpy ones; the clusters against their faces; the numpy descent direction against coherence's torch one; empty
inputs give empty contacts.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_coherence import plane_mesh, pose, rotation

import zoo
from zoo.geometry import barycentric_grid
from zoo.proxy import bake_proxy
from zoo.proxy_collider import CLUSTER, KERNELS, ProxyCollider, _clusters
from zoo.sdf import SDFBase


def brute_minima(sdf, tri: torch.Tensor, resolution: int = 40) -> torch.Tensor:
    """The lowest of ``sdf`` over a barycentric grid of ``resolution`` per edge on each triangle (F, 3, 3): (F,)."""
    grid = barycentric_grid(resolution, dtype=torch.float64)  # (G, 3)
    points = torch.einsum("gv,fvc->fgc", grid, tri.double()).reshape(-1, 3)
    with torch.no_grad():
        values = torch.as_tensor(sdf(points.float())).double().reshape(tri.shape[0], -1)
    return values.amin(dim=1)


def world_triangles(mesh, sdf_pose, mesh_pose) -> torch.Tensor:
    """The mesh's triangles (F, 3, 3) in the SDF's frame."""
    vertices, faces = (torch.as_tensor(np.asarray(a)) for a in mesh)
    mesh_pose = np.eye(4) if mesh_pose is None else mesh_pose
    relative = torch.linalg.inv(torch.as_tensor(sdf_pose, dtype=torch.float64)) @ torch.as_tensor(mesh_pose, dtype=torch.float64)
    local = vertices.double() @ relative[:3, :3].T + relative[:3, 3]
    return local[faces]


def check_against_brute_force(sdf, collider, mesh, sdf_pose, mesh_pose, margin: float, tolerance: float,
                              resolution: int = 40, fine: bool = True) -> int:
    """Every face whose brute-force minimum is within ``margin - tolerance`` is a contact; every contact's depth is within
    ``tolerance`` above its face's brute-force minimum (and not below what the grid's spacing allows); returns the
    contacts counted. ``fine``: the grid is fine enough that no point of a face lies more than ``tolerance`` below its
    samples (checked too). Faces wholly outside the SDF's bounds grown by the margin are left out (no contact there)."""
    contacts = collider(sdf_pose, mesh_pose)
    tri = world_triangles(mesh, sdf_pose, mesh_pose)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) - s * margin for b, s in zip(sdf.bounds, (1, -1)))
    inside = ((tri.amax(dim=1) >= lo) & (tri.amin(dim=1) <= hi)).all(dim=-1)
    minima = torch.full(tri.shape[:1], torch.inf, dtype=torch.float64)
    minima[inside] = brute_minima(sdf, tri[inside], resolution)
    reported = set(contacts.triangles.tolist())
    must = set(torch.nonzero(minima <= margin - tolerance).squeeze(-1).tolist())
    assert must <= reported, f"faces missed: {sorted(must - reported)[:10]}"
    depths = contacts.depths.double()
    brute = minima[contacts.triangles]
    assert float((depths - brute).max()) <= tolerance
    if fine:
        assert float((brute - depths).max()) <= tolerance
    return len(contacts)


@pytest.mark.parametrize("kernel", KERNELS)
def test_sphere_over_a_plane_against_brute_force(kernel):
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3)
    mesh = plane_mesh(max_edge=0.01)
    collider = ProxyCollider(sphere, mesh, proxy, margin=1e-3, method="fw", kernel=kernel)
    counted = 0
    for step in range(6):
        sdf_pose = pose(rotation((0, 0, 1), 0.3 * step), (0.002 * step, -0.001 * step, 0.0498 - 2e-4 * step))
        counted += check_against_brute_force(sphere, collider, mesh, sdf_pose, None, 1e-3, 2e-5)
    assert counted > 6 and collider.stats.exact_faces == counted


@pytest.mark.parametrize("kernel", KERNELS)
def test_small_motions_carry_the_last_search_and_stay_at_the_minima(kernel):
    """A sphere settling onto a plane by 0.02 mm a step (under ``reuse_distance``, 0.2 mm): the calls between full
    searches carry the last one's answers, their depths moved along their normals, and stay within 2e-5 of the
    brute-force minima with no face within the margin missed; a step of 1 mm searches again."""
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3)
    mesh = plane_mesh(max_edge=0.01)
    collider = ProxyCollider(sphere, mesh, proxy, margin=1e-3, method="fw", kernel=kernel)
    searched = []
    for step in range(14):
        sdf_pose = pose(None, (0.0, 0.0, 0.0505 - 2e-5 * step))
        check_against_brute_force(sphere, collider, mesh, sdf_pose, None, 1e-3, 2e-5)
        if not collider.last_stats.reused:
            searched.append(step)
    assert searched[:2] == [0, 11] or searched[:2] == [0, 10], searched  # 0.2 mm in steps of 0.02 mm, then again
    check_against_brute_force(sphere, collider, mesh, pose(None, (0.001, 0.0, 0.0495)), None, 1e-3, 2e-5)
    assert collider.last_stats.reused == 0


@pytest.mark.slow
def test_the_mug_on_the_rack_against_brute_force():
    """The mugs NeuralSDF (its proxy on a 2 mm grid, for a quick bake) on the rack's faces within 1 cm of it, resting
    and sinking: no face within the margin is missed, no depth above its face's brute-force minimum by 0.1 mm."""
    from zoo.scenes import load_collision_scene

    mug = zoo.load("mugs").shape("hoi4d_mug_0001")
    scene = load_collision_scene("demo-mug-rack")
    start = np.asarray(scene.sdf_pose, dtype=np.float64)
    vertices, faces = np.asarray(scene.mesh.vertices, dtype=np.float32), np.asarray(scene.mesh.faces)
    with torch.no_grad():  # the brute force's cost is per face: the faces near the mug only
        near = (torch.as_tensor(mug(world_triangles((vertices, faces), start, None).mean(dim=1).float())) < 0.01).numpy()
    mesh = (vertices, faces[near])
    proxy = bake_proxy(mug, margin=scene.margin, spacing=2e-3)
    collider = ProxyCollider(mug, mesh, proxy, margin=scene.margin, method="amortized")
    counted = 0
    for step in range(2):
        sdf_pose = start.copy()
        sdf_pose[:3, 3] += np.array([0.0, 0.0, -8e-4 * step])
        counted += check_against_brute_force(mug, collider, mesh, sdf_pose, None, scene.margin, 1e-4, resolution=12, fine=False)
    assert counted > 10


def test_compiled_passes_answer_as_the_numpy_passes():
    """The compiled per-face passes (zoo.proxy_kernel) against the numpy ones, on a lazily baked proxy (so that the
    compiled reads meet bricks not ready and the call is made again): a sphere sliding, turning and sinking over a plane
    of long thin faces; the same proxy contacts (faces, depths, points) and the same counts at every step."""
    sphere = zoo.Sphere(0.05)
    vertices, faces = plane_mesh(max_edge=0.004)
    vertices = np.asarray(vertices) * np.array([1.0, 0.3, 1.0])  # long thin faces
    mesh = (vertices, faces)
    colliders = {kernel: ProxyCollider(sphere, mesh, bake_proxy(sphere, margin=1e-3, spacing=1e-3, lazy=True), margin=1e-3,
                                       method="fw", deferred=True, reuse_distance=0.0, kernel=kernel, hold=False)
                 for kernel in KERNELS}
    compared = 0
    for step in range(8):
        sdf_pose = pose(rotation((0.3, 0.2, 1), 0.03 * step), (4e-4 * step, -2e-4 * step, 0.0502 - 2e-4 * step))
        contacts = {kernel: collider(sdf_pose, None) for kernel, collider in colliders.items()}
        a, b = contacts["numpy"], contacts["numba"]
        assert a.triangles.tolist() == b.triangles.tolist()
        torch.testing.assert_close(a.depths.double(), b.depths.double(), rtol=0, atol=1e-9)
        torch.testing.assert_close(a.points.double(), b.points.double(), rtol=0, atol=1e-9)
        sa, sb = colliders["numpy"].last_stats, colliders["numba"].last_stats
        for count in ("faces_near", "faces_skipped", "candidates", "warm", "cold", "screened", "proxy_reads"):
            assert getattr(sa, count) == getattr(sb, count), count
        compared += len(a)
    assert compared > 50 and colliders["numba"].stats.warm > 0 and colliders["numba"].proxy.lazy_bricks > 0


def test_a_descent_reads_no_parabola_minimiser_that_is_its_end():
    """The numpy search's line search (``zoo.proxy_search._descend``) reads the parabola's minimiser only where it is
    not the segment's end, and answers as a naive one that reads both points on every face: the same barycentrics,
    values, gradients and status, bit for bit, with one read fewer per face whose minimiser is its end."""
    from zoo.collider import CoherenceStats
    from zoo.proxy_search import _descend
    from zoo.simplex import descent_segment, on_simplex

    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3, lazy=True)
    rng = np.random.default_rng(3)
    n = 400
    axis = rng.normal(size=(n, 3))
    centre = axis / np.linalg.norm(axis, axis=1, keepdims=True) * (0.05 + rng.uniform(-5e-4, 5e-4, size=(n, 1)))
    size = np.where(np.arange(n) % 2, 3e-3, 1.5e-2)[:, None, None]  # faces of 1-6 mm and of 5-30 mm, tilted every way
    tri = centre[:, None, :] + size * rng.uniform(-1, 1, size=(n, 3, 3))
    bary = rng.dirichlet(np.ones(3), size=n)
    f0, g0, _ = proxy.read_numpy(np.einsum("nv,nvc->nc", bary, tri))
    stats = CoherenceStats()
    got = _descend(proxy, tri, bary, f0, g0, stats)

    direction, reach = descent_segment(tri, bary, g0)
    end = on_simplex(bary + reach[:, None] * direction)
    f1, g1, s1 = proxy.read_numpy(np.einsum("nv,nvc->nc", end, tri))
    slope = ((np.einsum("nv,nvc->nc", end, tri) - np.einsum("nv,nvc->nc", bary, tri)) * g0).sum(axis=1)
    curvature = f1 - f0 - slope
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(curvature > 0, np.clip(-slope / (2 * curvature), 0, 1), 1.0)
    t = np.where(np.isfinite(t), t, 0.0)
    mid = on_simplex(bary + (t * reach)[:, None] * direction)
    fm, gm, sm = proxy.read_numpy(np.einsum("nv,nvc->nc", mid, tri))
    end_lower = f1 < fm
    naive = (np.where(end_lower[:, None], end, mid), np.where(end_lower, f1, fm), np.where(end_lower[:, None], g1, gm),
             np.where(end_lower, s1, sm))
    for a, b in zip(got, naive):
        assert np.array_equal(a, b)
    at_end = int(np.count_nonzero(t == 1.0))
    assert 0 < at_end < n
    assert stats.proxy_reads == 2 * n - at_end


def test_compiled_descent_points_are_the_numpy_ones_to_the_bit():
    """``zoo.proxy_kernel.along_descent`` (the SDF's own descent out of the band) against the numpy operations it
    replaces (``_along_descent``): the same points, bit for bit, on faces with area, needles, points at corners and
    on edges, and shortened steps, so that a simulation's trajectory does not depend on which ran."""
    from zoo.proxy_collider import _along_descent
    from zoo.proxy_kernel import along_descent

    rng = np.random.default_rng(0)
    n = 5000
    tri = rng.normal(size=(n, 3, 3)) * 0.01
    tri[:500, 2] = tri[:500, 0] + 1e-9 * rng.normal(size=(500, 3))  # needles
    bary = rng.dirichlet(np.ones(3), size=n)
    bary[1000:2000] = np.eye(3)[rng.integers(0, 3, size=1000)]  # at a corner
    bary[2000 + np.arange(1000), rng.integers(0, 3, size=1000)] = 0.0  # on an edge
    bary /= bary.sum(axis=1, keepdims=True)
    grads = rng.normal(size=(n, 3))
    fractions = np.arange(1, 9) / 8
    length = rng.choice([1.0, 1 / 8, 1 / 64], size=n)
    compiled, numpy = along_descent(tri, bary, grads, fractions, length), _along_descent(tri, bary, grads, fractions, length)
    assert np.array_equal(compiled.view(np.int64), numpy.view(np.int64))
    assert np.ptp(compiled[:, :, 0]) > 0.5  # the points move: not all stuck


class WavyFloor(SDFBase):
    """Height above a floor that waves along x (period 30 mm, 0.1 mm high) and dips 0.4 mm once (about x = 73.1 mm),
    scaled to stay 1-Lipschitz: along a face long in x, local minima and one deepest, as a gear's flank meets a
    NeuralSDF that varies along it."""

    bounds = (torch.tensor([-0.03, -0.02, -0.01]), torch.tensor([0.1, 0.02, 0.01]))

    def _distance(self, p):
        x = p[:, 0]
        floor = 1e-4 * torch.sin(2 * math.pi * x / 3e-2) - 4e-4 * torch.exp(-(((x - 0.0731) / 3e-3) ** 2))
        return (p[:, 2] + floor) / 1.2


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_long_faces_cold_search_starts_along_its_length(kernel, monkeypatch):
    """A sliver 100 mm long (100 proxy cells) 0.5 mm over the wavy floor: the pattern's starts lie 6 mm and more
    from the deepest dip and their descents stop in another minimum; the starts along the sliver's length
    (zoo.proxy_search.line_starts, one every 4 cells) find the brute-force minimum within 2 um."""
    import zoo.proxy_search

    sdf = WavyFloor()
    proxy = bake_proxy(sdf, margin=1e-3, spacing=1e-3)
    vertices = np.array([[-0.016, 0.0, 5e-4], [0.084, -5e-4, 5e-4], [0.084, 5e-4, 5e-4]], dtype=np.float32)
    mesh = (vertices, np.array([[0, 1, 2]]))
    truth = float(brute_minima(sdf, world_triangles(mesh, np.eye(4), None), resolution=400)[0])

    def answer() -> float:
        contacts = ProxyCollider(sdf, mesh, proxy, margin=1e-3, method="fw", kernel=kernel)(np.eye(4), None)
        assert contacts.triangles.tolist() == [0]
        return float(contacts.depths[0])

    assert abs(answer() - truth) < 2e-6
    monkeypatch.setattr(zoo.proxy_search, "LINE_START_CELLS", 10**9)  # the pattern's starts alone
    assert answer() - truth > 5e-5


def test_held_faces_are_those_that_hold_no_contact():
    """Passing over the faces held above the margin (hold=True) against answering every face near the SDF: a sphere
    rolling, turning and sinking over a plane of long thin faces, some steps standing still and one jumping back,
    gives the same contacts (faces, depths, points) at every step, with fewer faces screened and searched, and fewer
    reads."""
    sphere = zoo.Sphere(0.05)
    vertices, faces = plane_mesh(max_edge=0.004)
    mesh = (np.asarray(vertices) * np.array([1.0, 0.3, 1.0]), faces)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3)
    colliders = {hold: ProxyCollider(sphere, mesh, proxy, margin=1e-3, method="fw", reuse_distance=0.0, hold=hold)
                 for hold in (False, True)}
    steps = [0, 1, 2, 2, 3, 4, 5, 5, 5, 6, 7, 8, 1, 9, 10, 11, 12]  # standing still, and back to step 1
    compared = 0
    for step in steps:
        sdf_pose = pose(rotation((0.3, 0.2, 1), 0.002 * step), (2e-4 * step, -1e-4 * step, 0.0503 - 1e-4 * step))
        a, b = (colliders[hold](sdf_pose, None) for hold in (False, True))
        assert a.triangles.tolist() == b.triangles.tolist()
        torch.testing.assert_close(a.depths.double(), b.depths.double(), rtol=0, atol=1e-9)
        torch.testing.assert_close(a.points.double(), b.points.double(), rtol=0, atol=1e-9)
        compared += len(a)
    held, every = colliders[True].stats, colliders[False].stats
    assert compared > 50 and held.candidates < every.candidates and held.screened < every.screened / 1.5
    assert held.proxy_reads < 0.7 * every.proxy_reads


class CountingSphere:
    """zoo.Sphere(0.05), counting the value-and-gradient queries asked of it."""

    def __init__(self):
        self.sphere, self.queries = zoo.Sphere(0.05), 0
        self.bounds = self.sphere.bounds

    def __call__(self, points):
        return self.sphere(points)

    def value_and_grad(self, points):
        self.queries += 1
        return self.sphere.value_and_grad(points)


def test_pairs_on_one_sdf_ask_it_together():
    """Two meshes on one SDF and proxy (a floor under the sphere and a wall beside it), deferred: answered together
    (zoo.proxy_collider.exact_contacts_together, as a simulation step's pairs on one body are), they give each the
    contacts it gives alone, with half the SDF queries."""
    from zoo.proxy_collider import exact_contacts_together

    sdf = CountingSphere()
    proxy = bake_proxy(sdf.sphere, margin=1e-3, spacing=1e-3)
    floor = plane_mesh(max_edge=0.004)
    wall = (np.asarray(floor[0]) @ rotation((0, 1, 0), np.pi / 2)[:3, :3].T, floor[1])  # the plane x = 0
    meshes = {"floor": (floor, None), "wall": (wall, None)}
    sdf_pose = pose(rotation((0.3, 0.2, 1), 0.1), (0.0504, 0.001, 0.0503))  # within the margin of both, sinking a little
    answers = {}
    for together in (False, True):
        colliders = [ProxyCollider(sdf, mesh, proxy, margin=1e-3, method="fw", deferred=True) for mesh, _ in meshes.values()]
        rows = [torch.arange(len(c(sdf_pose, None))) for c in colliders]
        before = sdf.queries
        if together:
            answers[together] = exact_contacts_together(list(zip(colliders, rows)))
        else:
            answers[together] = [c.exact_contacts(r) for c, r in zip(colliders, rows)]
        answers[together, "queries"] = sdf.queries - before
    for alone, with_other in zip(answers[False], answers[True]):
        assert len(alone) > 3 and alone.triangles.tolist() == with_other.triangles.tolist()
        torch.testing.assert_close(alone.depths, with_other.depths, rtol=0, atol=1e-7)
        torch.testing.assert_close(alone.points, with_other.points, rtol=0, atol=1e-7)
    assert answers[True, "queries"] * 2 == answers[False, "queries"]


def test_near_deepest_per_cell_against_a_dictionary():
    """zoo.proxy_kernel.near_deepest_per_cell against a dictionary of each cell's least value: many rows per cell,
    negative cells, ties, a band of none and of some."""
    from zoo.proxy_kernel import near_deepest_per_cell

    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 3000):
        cells = rng.integers(-4, 4, size=(n, 3))
        values = rng.integers(0, 20, size=n) * 1e-4  # ties
        least = {}
        for i in range(n):
            key = tuple(cells[i].tolist())
            least[key] = min(least.get(key, np.inf), values[i])
        for band in (0.0, 2.5e-4):
            expected = [i for i in range(n) if values[i] <= least[tuple(cells[i].tolist())] + band]
            assert near_deepest_per_cell(cells, values, band).tolist() == expected
            if n == 3000:
                assert len(expected) > len(least) if band else len(expected) >= len(least)


@pytest.mark.parametrize("band_bounds, slack, near_miss", [(0, 0.0, 0.0), (2, 0.0, 0.0), (0, 2e-4, 0.0), (0, 0.0, 2e-4)])
def test_thinned_contacts_are_the_deepest_per_cell_of_those_a_simulation_can_use(band_bounds, slack, near_miss):
    """A deferred collider with a Thinning against the same collider without: a sphere sliding, turning and sinking
    over a plane of long thin faces (contacts that face their faces and contacts that do not, separated contacts the
    bodies close in time and ones they do not) gives, at every step, per cell of the world's grid the contacts
    within the band (none, or twice the proxy's error bound) of the deepest of those that the numpy filters
    (tests/naive_filters.py) let through, each depth taken at its least (less a slack: none, or 0.2 mm), and apart
    from them, the same of the near misses (those let through only with 0.2 mm more), as a dictionary picks them
    from every contact; and the reduction a simulation makes keeps the same contacts from either."""
    from naive_filters import closing_in_time, facing_faces

    from zoo.contact_filters import GRAZING_COS, SEPARATED_COS, Closing
    from zoo.geometry import face_normals
    from zoo.proxy_collider import Thinning
    from zoo.sim.reduction import reduce_contacts

    sphere = zoo.Sphere(0.05)
    vertices, faces = plane_mesh(max_edge=0.004)
    vertices = np.asarray(vertices, dtype=np.float64) * np.array([1.0, 0.3, 1.0])
    mesh = (torch.from_numpy(vertices), torch.as_tensor(np.asarray(faces)))  # float64: the contacts' points as the cells'
    normals = face_normals(vertices[np.asarray(faces)])
    proxy = bake_proxy(sphere, margin=2e-3, spacing=1e-3)
    cell, seconds = 1.37e-3, 0.003
    # the sphere's motion: its centre sinking and sliding, turning about a tilted axis; the plane at rest
    sphere_motion = (np.array([0.01, 0.02, -0.3]), np.array([0.5, -1.0, 2.0]))  # (velocity, angular velocity)
    band = band_bounds * proxy.error_bound
    every, thinned = (ProxyCollider(sphere, mesh, proxy, margin=2e-3, method="fw", deferred=True, thin=t)
                      for t in (None, Thinning(cell, GRAZING_COS, SEPARATED_COS, band=band, slack=slack,
                                               near_miss=near_miss)))
    # the mesh moved off the cells' faces (its vertices on x, y, z = 0: rounding could put a point either side)
    off = np.array([0.3, 0.2, 0.4]) * cell
    lift = pose(None, off)
    compared = left_out = beyond_deepest = by_slack = near_kept = 0
    for step in range(10):
        sdf_pose = pose(rotation((0.3, 0.2, 1), 0.05 * step), off + (4e-4 * step, -2e-4 * step, 0.0495 - 1e-4 * step))
        origin = sdf_pose[:3, 3]
        v, w = sphere_motion
        thinned.thin = Thinning(cell, GRAZING_COS, SEPARATED_COS, closing=Closing(v - np.cross(w, origin), w, seconds), band=band,
                                slack=slack, near_miss=near_miss)
        a, b = every(sdf_pose, lift), thinned(sdf_pose, lift)
        points, depths, contact_normals = (x.double().numpy() for x in (a.points, a.depths, a.normals))
        face_world = normals[a.triangles.numpy()]  # the mesh is only moved
        usable, within_near_miss = [facing_faces(contact_normals, face_world, depths, known) & closing_in_time(
            points, depths, contact_normals, (origin, np.concatenate(sphere_motion)), (np.zeros(3), np.zeros(6)), seconds,
            known) for known in (slack, slack + near_miss)]
        near = within_near_miss & ~usable
        # each row's key: its cell, and whether it is a near miss
        keys = {i: (*np.floor(points[i] / cell).astype(np.int64).tolist(), bool(near[i]))
                for i in np.flatnonzero(usable | near)}
        least = {}
        for i, key in keys.items():
            least[key] = min(least.get(key, np.inf), depths[i])
        expected = [i for i, key in keys.items() if depths[i] <= least[key] + band]
        assert a.triangles[expected].tolist() == b.triangles.tolist()
        beyond_deepest += len(expected) - len(least)
        near_kept += int(near[expected].sum())
        torch.testing.assert_close(a.depths[expected], b.depths, rtol=0, atol=0)
        kept = reduce_contacts(*(x[usable] for x in (points, depths, contact_normals, face_world)), merge_tol=2 * cell)
        b_usable = np.flatnonzero(usable[expected])  # the thinned rows that are not near misses
        b_points, b_depths, b_normals = (x.double().numpy()[b_usable] for x in (b.points, b.depths, b.normals))
        kept_thinned = reduce_contacts(b_points, b_depths, b_normals, normals[b.triangles.numpy()[b_usable]],
                                       merge_tol=2 * cell)
        assert a.triangles[np.flatnonzero(usable)[kept]].tolist() == b.triangles[b_usable[kept_thinned]].tolist()
        compared += len(b)
        left_out += int(((depths > 0) & ~usable).sum()) * (step >= 3)
        by_slack += int((usable & ~closing_in_time(points, depths, contact_normals, (origin, np.concatenate(sphere_motion)),
                                                   (np.zeros(3), np.zeros(6)), seconds)).sum())
    assert compared > 100 and left_out > 0  # separated contacts the motion does not close were among them
    if band:
        assert beyond_deepest > 0  # cells where more than the proxy's deepest may be the SDF's
    assert (by_slack > 0) == (slack > 0)  # separated contacts kept only because they may touch
    assert (near_kept > 0) == (near_miss > 0)


def test_empty_inputs_give_empty_contacts():
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=2e-3)
    empty = ProxyCollider(sphere, (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)), proxy, margin=1e-3, method="fw")
    assert len(empty(None, None)) == 0
    for kernel in KERNELS:
        far = ProxyCollider(sphere, plane_mesh(), proxy, margin=1e-3, method="fw", deferred=True, kernel=kernel)
        assert len(far(pose(None, (0.0, 0.0, 1.0)), None)) == 0
    assert len(far.exact_contacts(torch.zeros(0, dtype=torch.int64))) == 0


def test_clusters_hold_every_face_once_within_their_balls():
    rng = np.random.default_rng(0)
    corners = rng.normal(size=(1000, 3, 3))
    clusters, centres, radii = _clusters(corners, corners.mean(axis=1))
    members = clusters[clusters >= 0]
    assert sorted(members.tolist()) == list(range(1000)) and clusters.shape[1] == CLUSTER
    for c in range(len(clusters)):
        faces = clusters[c][clusters[c] >= 0]
        assert np.linalg.norm(corners[faces].reshape(-1, 3) - centres[c], axis=1).max() <= radii[c] + 1e-12


def test_every_narrow_phase_is_a_collider_and_the_default_one_on_a_proxy_answers_its_calls():
    """zoo.collider.Collider is the one interface of the narrow phases: CoherentCollider (with and without a proxy) and
    ProxyCollider implement it, and CoherentCollider(proxy=...) answers through its ProxyCollider: the same contacts."""
    from zoo.collider import Collider

    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=2e-3, spacing=1e-3)
    mesh = plane_mesh(max_edge=0.01)
    on_proxy = zoo.CoherentCollider(sphere, mesh, margin=2e-3, method="fw", proxy=proxy)
    plain = ProxyCollider(sphere, mesh, proxy, margin=2e-3, method="fw")
    for collider in (zoo.CoherentCollider(sphere, mesh, margin=2e-3, method="fw"), on_proxy, plain):
        assert isinstance(collider, Collider)
    assert not isinstance(object(), Collider)
    at = pose(translation=(0.0, 0.0, 0.0495))
    a, b = on_proxy(at), plain(at)  # the SDF's pose; the plane's is the identity
    assert len(a) > 0 and torch.equal(a.triangles, b.triangles) and torch.equal(a.depths, b.depths)
