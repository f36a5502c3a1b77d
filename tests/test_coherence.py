"""zoo.coherence.CoherentCollider against zoo.collide from scratch, along trajectories.

At every step the coherent contacts are held against ``zoo.collide`` at the same poses: every face
collide finds in contact among the candidates, the same contact triangles except where a depth is
within tolerance of the margin, depths within tolerance and never notably above collide's (a warm
start only polishes further). The skipping is checked against a
brute-force minimum (a dense barycentric sampling of every face) on random motions, and the counters
and a counting SDF show what was saved.

``python tests/test_coherence.py`` measures the savings on the demo mug sliding along the rack's peg
(docs/coherence.md).
"""

from __future__ import annotations

import math
import sys
import time
from functools import partial

import numpy as np
import pytest
import torch
import trimesh

import zoo
from zoo.coherence import CoherentCollider, screen_bound
from zoo.collider import LEARNED_LIPSCHITZ, motion_lipschitz
from zoo.errors import InputError
from zoo.geometry import bary_to_points, barycentric_grid, invert_pose, transform_points
from zoo.parts import plane

# Tolerances on depths (m): how far a coherent depth may be from collide's, which is the method's own error
# from scratch (10 Frank-Wolfe iterations on these 1 cm triangles: up to 2.7e-5 above the minimum under the
# sphere, 8.6e-5 under the torus; projected gradient: 1.7e-4; the amortized path on the demo mug: 3.7e-5;
# the coherent depths are the lower ones), and how far above collide's it may be (a
# warm start only descends further: within rounding for analytic SDFs; on a voxel grid, whose gradient jumps
# between cells, and on the NeuralSDF, a little more).
CLOSE = {"fw": 1e-4, "voxel-fw": 1e-4, "pgd": 2.5e-4, "amortized": 1e-4}
WORSE = {"fw": 1e-6, "voxel-fw": 1e-5, "pgd": 1e-6, "amortized": 1e-5}


# -- poses and meshes -----------------------------------------------------------------------------


def rotation(axis, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (radians) about ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def pose(rot=None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 world-from-object."""
    t = np.eye(4)
    t[:3, :3] = np.eye(3) if rot is None else rot
    t[:3, 3] = translation
    return t


def plane_mesh(size=0.3, max_edge=0.01):
    """A flat square in z = 0 (procedural part), float32 vertices."""
    mesh = plane(size=size, max_edge=max_edge)
    return np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces)


def icosphere_mesh(radius=0.3, subdivisions=4):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces)


def sphere_rolling_over_plane(step):
    """A sphere of radius 0.05 sliding along x over a plane turning about z, sinking 0.1 mm per step."""
    sdf_pose = pose(rotation((0, 1, 0), 0.02 * step), (-0.05 + 0.002 * step, 0.01, 0.0505 - 1e-4 * step))
    return sdf_pose, pose(rotation((0, 0, 1), 0.01 * step))


def box_turning_on_icosphere(step):
    """A box resting 0.5 mm deep on an icosphere's top, tilted by 0.01 rad, turning 0.03 rad per step about the
    vertical and sliding 1 mm per step."""
    turn = rotation((0, 0, 1), 0.03 * step) @ rotation((1, 0, 0), 0.01)
    return pose(turn, (0.001 * step, 0.0, 0.3 + 0.0995)), None


def torus_on_tilted_plane(step):
    """A torus lying on a tilted plane, rolling its ring 0.05 rad per step and moving 2 mm per step."""
    mesh_pose = pose(rotation((1, 0, 0), 0.3))
    normal = mesh_pose[:3, :3] @ np.array([0.0, 0.0, 1.0])
    centre = 0.0195 * normal + np.array([0.002 * step, 0.001 * step, 0.0])
    return pose(rotation(normal, 0.05 * step) @ mesh_pose[:3, :3], centre), mesh_pose


# -- comparisons -----------------------------------------------------------------------------------


def local_vertices(vertices, sdf_pose, mesh_pose):
    """The mesh's vertices in the SDF's frame, as collide computes them: (V, 3)."""
    sdf_pose = torch.as_tensor(np.eye(4) if sdf_pose is None else sdf_pose, dtype=torch.float64)
    mesh_pose = torch.as_tensor(np.eye(4) if mesh_pose is None else mesh_pose, dtype=torch.float64)
    v = torch.as_tensor(vertices)
    return transform_points((invert_pose(sdf_pose) @ mesh_pose).to(v.dtype), v)


def check_against_scratch(coherent, scratch, margin: float, close: float, worse: float) -> None:
    """Hold one step's coherent contacts against collide's (the tolerances: :data:`CLOSE`, :data:`WORSE`)."""
    ours = {int(k): i for i, k in enumerate(coherent.triangles)}
    theirs = {int(k): i for i, k in enumerate(scratch.triangles)}
    for k in set(ours) ^ set(theirs):  # only a depth within tolerance of the margin may fall either side
        depth = coherent.depths[ours[k]] if k in ours else scratch.depths[theirs[k]]
        assert abs(float(depth) - margin) <= close, f"triangle {k}: depth {float(depth)} is not near the margin {margin}"
    common = sorted(set(ours) & set(theirs))
    a = torch.tensor([ours[k] for k in common], dtype=torch.long)
    b = torch.tensor([theirs[k] for k in common], dtype=torch.long)
    diff = (coherent.depths[a] - scratch.depths[b]).double()
    assert bool((diff.abs() <= close).all()), f"depths differ by {float(diff.abs().max())}"
    assert bool((diff <= worse).all()), f"a coherent depth is {float(diff.max())} above collide's"
    # the same contact: the normals agree, and they are unit vectors in the world frame
    cos = (coherent.normals[a] * scratch.normals[b]).sum(-1)
    assert bool((cos > 0.99).all()), f"normals differ: cos {float(cos.min())}"
    assert torch.allclose(coherent.normals.norm(dim=-1), torch.ones(len(coherent), dtype=coherent.normals.dtype), atol=1e-5)
    assert coherent.n_triangles == scratch.n_triangles and coherent.method == scratch.method


def check_against_reference(sdf, triangles, coherent, scratch) -> None:
    """Both ways against the reference minimum on the contact triangles (analytic SDFs): the coherent depths
    are at the SDF at their points, and on average no farther above the minimum than collide's."""
    if not len(coherent):
        return
    ref = sdf(bary_to_points(triangles, zoo.solvers.reference(sdf, triangles.double(), resolution=16).to(triangles)))
    points = bary_to_points(triangles, coherent.bary)
    assert torch.allclose(sdf(points), coherent.depths, atol=1e-6)
    if torch.equal(coherent.triangles, scratch.triangles) and len(coherent):
        assert float((coherent.depths - ref).mean()) <= float((scratch.depths - ref).mean()) + 1e-7


def run_trajectory(sdf, mesh, poses, steps, margin=1e-3, method="fw", reference_every=6, **kwargs):
    """Collide both ways at every step; checks the candidates and the contacts; returns the collider."""
    collider = CoherentCollider(sdf, mesh, margin=margin, method=method, **kwargs)
    vertices, faces = (torch.as_tensor(x) for x in mesh)
    for step in range(steps):
        sdf_pose, mesh_pose = poses(step)
        coherent = collider(sdf_pose, mesh_pose)
        scratch = zoo.collide(sdf, mesh, sdf_pose, mesh_pose, margin=margin, method=method, **kwargs)
        local = local_vertices(vertices, sdf_pose, mesh_pose)
        # every face collide finds in contact was solved here too (collide's candidates, less the faces whose last
        # answer keeps them above the margin, plus faces warm-started without the vertex bounds collide culls by)
        assert bool(torch.isin(scratch.triangles, collider.last_candidates).all()), f"step {step}: a contact face was skipped"
        check_against_scratch(coherent, scratch, margin, CLOSE[method], WORSE[method])
        if reference_every and step % reference_every == reference_every - 1:
            check_against_reference(sdf, local[faces[coherent.triangles]], coherent, scratch)
    return collider


# -- along trajectories -----------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["fw", "pgd", "voxel-fw"])
def test_sphere_on_plane_matches_collide(method):
    # "voxel-fw" answers on the grid's interpolant, not the sphere: no reference check there
    collider = run_trajectory(zoo.Sphere(0.05), plane_mesh(), sphere_rolling_over_plane, 25, method=method,
                              voxel_resolution=96, reference_every=0 if method == "voxel-fw" else 6)
    stats = collider.stats
    assert stats.steps == 25 and stats.faces_skipped > stats.faces_near / 2  # most near faces skipped, no query
    assert stats.cold < stats.candidates / 5


def test_box_on_icosphere_matches_collide():
    collider = run_trajectory(zoo.Box((0.05, 0.04, 0.1)), icosphere_mesh(), box_turning_on_icosphere, 25)
    assert collider.stats.cold < collider.stats.candidates / 5  # (every face in the box's bounds is in contact)


def test_torus_on_tilted_plane_matches_collide():
    collider = run_trajectory(zoo.Torus(0.08, 0.02), plane_mesh(), torus_on_tilted_plane, 20)
    assert collider.stats.faces_skipped > 0 and collider.stats.warm > 0


def test_without_warm_start_the_contacts_are_collides():
    """Skipping alone changes nothing: the same candidates, solved the same way."""
    sdf, mesh = zoo.Sphere(0.05), plane_mesh()
    collider = CoherentCollider(sdf, mesh, margin=1e-3, method="fw", warm_start=False)
    for step in range(12):
        sdf_pose, mesh_pose = sphere_rolling_over_plane(step)
        ours, theirs = collider(sdf_pose, mesh_pose), zoo.collide(sdf, mesh, sdf_pose, mesh_pose, margin=1e-3)
        assert torch.equal(ours.triangles, theirs.triangles)
        for name in ("points", "depths", "normals", "bary"):
            assert torch.allclose(getattr(ours, name), getattr(theirs, name), atol=1e-7, rtol=0), name
    assert collider.stats.warm == 0 and collider.stats.faces_skipped > 0


class CountingSDF:
    """An SDF that counts the points it is asked about (values, and values with gradients)."""

    lipschitz = 1.0  # an exact distance

    def __init__(self, sdf):
        self.sdf, self.bounds, self.values, self.gradients = sdf, sdf.bounds, 0, 0

    def __call__(self, points):
        self.values += points.shape[0]
        return self.sdf(points)

    def value_and_grad(self, points):
        self.gradients += points.shape[0]
        return self.sdf.value_and_grad(points)


def test_a_body_at_rest_costs_no_query_and_a_drifting_one_keeps_collides_contacts():
    """Kept answers: a sphere resting on a plane, then drifting 24 um a step (the reuse distance is a fifth of the
    margin: 200 um): no query at rest, and the contacts stay collide's, their depths moved along their normals
    (second order in the drift: 0.4 um at 200 um on a 5 cm sphere, under FW-10's own scatter here, 2 um)."""
    sphere, mesh = zoo.Sphere(0.05), plane_mesh()
    counted = CountingSDF(sphere)
    collider = CoherentCollider(counted, mesh, margin=1e-3, method="fw")
    tilt = rotation((1, 1, 0), 0.01)
    poses = [pose(tilt, (0.0, 0.0, 0.0497))] * 3 + [pose(tilt, (2e-5 * k, 1e-5 * k, 0.0497 - 1e-5 * k)) for k in range(1, 9)]
    for step, sdf_pose in enumerate(poses):
        before = counted.values + counted.gradients
        coherent = collider(sdf_pose, None)
        scratch = zoo.collide(sphere, mesh, sdf_pose, None, margin=1e-3, method="fw")
        assert torch.equal(coherent.triangles, scratch.triangles), f"step {step}"
        assert torch.allclose(coherent.depths, scratch.depths, atol=5e-6, rtol=0), f"step {step}"
        assert float((coherent.normals * scratch.normals).sum(-1).min()) > 0.9999
        if step in (1, 2):  # the same pose again: every answer kept, nothing asked of the SDF
            assert counted.values + counted.gradients == before and collider.last_stats.reused == len(collider.last_candidates)
    assert collider.stats.reused > collider.stats.candidates / 2


def test_answers_falling_due_at_different_steps_keep_collides_contacts():
    """A sphere turning in place on a plane: faces drift at rates proportional to their distance from the axis, so
    their kept answers fall due at different steps, and a round of queries also solves those due soon
    (REFRESH_FRACTION). The contacts stay collide's (faces within the method's error of the margin aside), and
    at most half the steps ask anything of the SDF."""
    sphere, mesh = zoo.Sphere(0.05), plane_mesh()
    counted = CountingSDF(sphere)
    collider = CoherentCollider(counted, mesh, margin=1e-3, method="fw")
    asking = 0
    for step in range(40):
        before = counted.values + counted.gradients
        sdf_pose = pose(rotation((0, 0, 1), 0.004 * step), (0.0, 0.0, 0.0493))
        coherent = collider(sdf_pose, None)
        scratch = zoo.collide(sphere, mesh, sdf_pose, None, margin=1e-3, method="fw")
        asking += counted.values + counted.gradients > before
        common, mine, theirs = np.intersect1d(coherent.triangles.numpy(), scratch.triangles.numpy(), return_indices=True)
        only = torch.cat([coherent.depths[np.setdiff1d(np.arange(len(coherent)), mine)],
                          scratch.depths[np.setdiff1d(np.arange(len(scratch)), theirs)]])
        assert bool(((only - 1e-3).abs() <= CLOSE["fw"]).all()), f"step {step}: a contact far inside the margin differs"
        assert torch.allclose(coherent.depths[mine], scratch.depths[theirs], atol=5e-6, rtol=0), f"step {step}"
    assert asking <= 20

def test_queries_saved():
    """The same trajectory costs fewer SDF queries coherently (counted at the SDF), and the counters add up."""
    mesh = plane_mesh()
    coherent_sdf, scratch_sdf = CountingSDF(zoo.Sphere(0.05)), CountingSDF(zoo.Sphere(0.05))
    collider = CoherentCollider(coherent_sdf, mesh, margin=1e-3)
    for step in range(20):
        sdf_pose, mesh_pose = sphere_rolling_over_plane(step)
        collider(sdf_pose, mesh_pose)
        zoo.collide(scratch_sdf, mesh, sdf_pose, mesh_pose, margin=1e-3)
    stats = collider.stats
    assert stats.candidates == stats.warm + stats.cold
    assert coherent_sdf.values + coherent_sdf.gradients < 0.6 * (scratch_sdf.values + scratch_sdf.gradients)
    assert coherent_sdf.gradients < 0.5 * scratch_sdf.gradients  # a warm step instead of 10 Frank-Wolfe iterations


# -- the skip is safe ---------------------------------------------------------------------------------


def sampled_minima(sdf, triangles, resolution=12):
    """f's least value (M,) on a barycentric grid of each triangle (M, 3, 3): an upper bound of its minimum."""
    grid = barycentric_grid(resolution, dtype=triangles.dtype)
    points = torch.einsum("gv,mvc->mgc", grid, triangles)
    return sdf(points.reshape(-1, 3)).reshape(triangles.shape[0], -1).amin(dim=1)


@pytest.mark.parametrize("sdf,rest", [(zoo.Sphere(0.06), 0.06), (zoo.Box((0.05, 0.03, 0.04)), 0.045),
                                      (zoo.Torus(0.06, 0.02), 0.04)], ids=["sphere", "box", "torus"])
def test_no_triangle_within_the_margin_is_skipped(sdf, rest, monkeypatch):
    """Random rigid motions over an icosphere (steps of 2 mm and 0.03 rad, and every 13th a jump of 3 cm and
    0.5 rad), the SDF's centre ``rest`` +- 1 cm off the surface: every face whose brute-force minimum is within
    the margin is among the candidates. A short pose history makes the lasting proofs' history drop its older
    half several times along the way."""
    monkeypatch.setattr(zoo.coherence, "POSE_HISTORY", 8)
    rng = np.random.default_rng(0)
    vertices, faces = icosphere_mesh(radius=0.3, subdivisions=4)
    margin = 2e-3
    collider = CoherentCollider(sdf, (vertices, faces), margin=margin)
    tri_index = torch.as_tensor(faces)
    turn, where, height = np.eye(3), np.array([0.0, 0.0, 1.0]), 0.0
    for step in range(40):
        jump = step % 13 == 12
        turn = rotation(rng.normal(size=3), rng.normal() * (0.5 if jump else 0.03)) @ turn
        where = where + (0.1 if jump else 0.007) * rng.normal(size=3)
        where /= np.linalg.norm(where)
        height = float(np.clip(height + (0.01 if jump else 0.002) * rng.normal(), -0.01, 0.01))
        sdf_pose = pose(turn, where * (0.3 + rest + height))
        collider(sdf_pose, None)
        local = local_vertices(vertices, sdf_pose, None)
        within = (sampled_minima(sdf, local.double()[tri_index]) <= margin).nonzero().squeeze(-1)
        assert bool(torch.isin(within, collider.last_candidates).all()), f"step {step}: a face within the margin was skipped"
    if not isinstance(sdf, zoo.Box):  # a box's bounds are its surface: a face in them is nearly always within the margin
        assert collider.stats.faces_skipped > 0


class Hollow:
    """The inside of a hollow ball of radius ``radius`` about the origin: f(x) = radius - |x|, a concave f (as a distance
    is across a medial ridge), with its exact gradient."""

    def __init__(self, radius: float):
        self.radius = radius

    def __call__(self, points):
        return self.radius - torch.as_tensor(points).norm(dim=-1)

    def value_and_grad(self, points):
        points = torch.as_tensor(points)
        return self(points), -points / points.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("sdf", [zoo.Sphere(0.05), Hollow(0.3)], ids=["convex", "concave"])
def test_the_screen_bound_is_below_every_triangles_minimum(sdf):
    """screen_bound, from one value and gradient anywhere on a triangle and its vertex values, stays below the
    triangle's minimum (sampled finely: an upper bound of it) for a convex and for a concave f, and is the
    minimum itself at a minimiser inside the face of the convex one."""
    rng = np.random.default_rng(1)
    centres = rng.normal(size=(300, 1, 3)) * 0.1
    tri = torch.as_tensor(centres + rng.normal(size=(300, 3, 3)) * rng.uniform(0.005, 0.08, size=(300, 1, 1)))
    bary = torch.as_tensor(rng.dirichlet(np.ones(3), size=300))
    f, g = sdf.value_and_grad(bary_to_points(tri, bary))
    bound = screen_bound(tri, bary, f, g, sdf(tri.reshape(-1, 3)).reshape(300, 3))
    assert bool((bound <= sampled_minima(sdf, tri, resolution=40) + 1e-12).all())
    if isinstance(sdf, zoo.Sphere):  # a flat triangle whose centroid is right below the centre: the minimiser, gap 0
        flat = torch.tensor([[[-0.03, -0.01, -0.06], [0.03, -0.01, -0.06], [0.0, 0.02, -0.06]]], dtype=torch.float64)
        centroid = torch.full((1, 3), 1.0 / 3.0, dtype=torch.float64)
        f, g = sdf.value_and_grad(bary_to_points(flat, centroid))
        bound = screen_bound(flat, centroid, f, g, sdf(flat.reshape(-1, 3)).reshape(1, 3))
        assert float(bound) == pytest.approx(0.01, abs=1e-12)


def test_the_screen_clears_faces_far_above_the_margin_and_keeps_collides_contacts():
    """A sphere falling past a coarse wall (faces 30 times the gap) lands on a floor: the wall's faces, which the
    vertex bounds cannot clear, are screened with one gradient per lowest vertex instead of a descent, and the
    contacts stay collide's at every step."""
    wall = plane(size=0.6, max_edge=0.3)
    # the wall upright, facing (1, 1, 0) 6.6 mm from the sphere (inside its bounding box's corner); the floor in z = 0
    turn = rotation((0, 0, 1), math.pi / 4) @ rotation((0, 1, 0), math.pi / 2)
    wall_v = np.asarray(wall.vertices) @ turn.T + np.array([0.04, 0.04, 0.3])
    floor = plane(size=0.3, max_edge=0.02)
    vertices = np.concatenate([wall_v, np.asarray(floor.vertices)]).astype(np.float32)
    faces = np.concatenate([np.asarray(wall.faces), np.asarray(floor.faces) + len(wall_v)])
    sphere = zoo.Sphere(0.05)

    def falling(step):
        return pose(None, (0.0, 0.0, max(0.0495, 0.09 - 0.5 * 9.81 * (0.004 * step) ** 2))), None

    collider = run_trajectory(sphere, (vertices, faces), falling, 30, margin=2e-3, reference_every=5)
    assert collider.stats.screened > 0


# -- the NeuralSDF ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mug_rack():
    from zoo.scenes import load_collision_scene

    scene = load_collision_scene("demo-mug-rack")
    mesh = (np.asarray(scene.mesh.vertices, dtype=np.float32), np.asarray(scene.mesh.faces))
    return scene, mesh


PEG = np.array([math.cos(math.radians(20)), 0.0, math.sin(math.radians(20))])  # the rack's peg axis


def slide_along_peg(start: np.ndarray, step_length: float, spin: float = 0.0):
    """Poses of the mug sliding along the peg by ``step_length`` per step, turning ``spin`` rad per step about it."""

    def poses(step):
        return pose(rotation(PEG, spin * step) @ start[:3, :3], start[:3, 3] + PEG * step_length * step), None

    return poses


def test_mug_on_rack_matches_collide(mug_rack):
    """The demo mug on the procedural rack, moving 2 mm and 0.01 rad per step: amortized, as collide."""
    scene, mesh = mug_rack
    collider = run_trajectory(scene.sdf, mesh, slide_along_peg(scene.sdf_pose, 2e-3, 0.01), 8, margin=scene.margin,
                              method="amortized", reference_every=0)
    stats = collider.stats
    assert stats.faces_skipped > 0.5 * (stats.faces_near - stats.faces_near / stats.steps)  # after the first step
    assert stats.warm > stats.cold


def test_neural_sdf_bounds_decay_faster():
    assert motion_lipschitz(zoo.Sphere(0.1)) == 1.0
    assert motion_lipschitz(zoo.TransformedSDF(zoo.Box(), torch.eye(4))) == 1.0
    assert motion_lipschitz(CountingSDF(zoo.Sphere(0.1))) == 1.0  # its own attribute
    assert motion_lipschitz(zoo.load("mugs").shape("hoi4d_mug_0001")) == LEARNED_LIPSCHITZ


# -- the switch, reset and errors -------------------------------------------------------------------


def test_coherence_off_is_collide():
    sdf, mesh = zoo.Sphere(0.05), plane_mesh()
    collider = CoherentCollider(sdf, mesh, margin=1e-3, method="pgd", coherence=False)
    for step in (0, 5):
        sdf_pose, mesh_pose = sphere_rolling_over_plane(step)
        ours, theirs = collider(sdf_pose, mesh_pose), zoo.collide(sdf, mesh, sdf_pose, mesh_pose, 1e-3, "pgd")
        assert torch.equal(ours.triangles, theirs.triangles) and torch.equal(ours.depths, theirs.depths)
    assert collider.stats.steps == 0  # nothing kept, nothing counted


def test_reset_starts_from_scratch():
    collider = CoherentCollider(zoo.Sphere(0.05), plane_mesh(), margin=1e-3)
    for step in range(3):
        collider(*sphere_rolling_over_plane(step))
    collider.reset()
    collider(*sphere_rolling_over_plane(3))
    assert collider.last_stats.warm == 0 and collider.last_stats.faces_skipped == 0
    assert collider.stats.steps == 4


def test_no_contact_and_empty_mesh():
    far = pose(None, (0.0, 0.0, 1.0))
    collider = CoherentCollider(zoo.Sphere(0.05), plane_mesh(), margin=1e-3)
    for _ in range(2):
        contacts = collider(far)
        assert len(contacts) == 0 and contacts.n_candidates == 0 and contacts.n_triangles > 0
    empty = CoherentCollider(zoo.Sphere(0.05), (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)))
    assert len(empty()) == 0 and len(empty()) == 0


def test_float64_mesh_keeps_float64():
    vertices, faces = plane_mesh()
    collider = CoherentCollider(zoo.Sphere(0.05), (vertices.astype(np.float64), faces), margin=1e-3)
    for step in range(3):
        contacts = collider(*sphere_rolling_over_plane(step))
        assert contacts.depths.dtype == torch.float64 and contacts.points.dtype == torch.float64 and len(contacts)


def test_bad_arguments():
    mesh = plane_mesh()
    with pytest.raises(InputError, match="unknown method"):
        CoherentCollider(zoo.Sphere(0.05), mesh, method="newton")
    with pytest.raises(InputError, match="detect"):
        CoherentCollider(zoo.Sphere(0.05), mesh, method="amortized")
    with pytest.raises(InputError, match="margin"):
        CoherentCollider(zoo.Sphere(0.05), mesh, margin=-1)
    with pytest.raises(InputError, match="lipschitz"):
        CoherentCollider(zoo.Sphere(0.05), mesh, lipschitz=0)


# -- what it saves (python tests/test_coherence.py) ---------------------------------------------------


def measure(steps: int = 50, step_length: float = 5e-4, threads: int = 1) -> dict:
    """The demo mug sliding along the rack's peg, ``step_length`` per step: median ms per step and SDF points
    queried per step (code-cloud lookups: values and gradients alike), from scratch and coherent."""
    from zoo.neural import NeuralShape
    from zoo.scenes import load_collision_scene

    torch.set_num_threads(threads)
    scene = load_collision_scene("demo-mug-rack")
    mesh = (np.asarray(scene.mesh.vertices, dtype=np.float32), np.asarray(scene.mesh.faces))
    poses = slide_along_peg(scene.sdf_pose.astype(np.float32), step_length)
    counted = {"points": 0}
    lookup = NeuralShape._interpolate

    def counting(self, points):
        counted["points"] += points.shape[0]
        return lookup(self, points)

    NeuralShape._interpolate = counting
    collider = CoherentCollider(scene.sdf, mesh, margin=scene.margin, method="amortized")
    runs = {"scratch": ([], []), "coherent": ([], [])}
    try:
        for step in range(steps):
            sdf_pose, _ = poses(step)
            for name, collide_now in (("coherent", collider),
                                      ("scratch", partial(zoo.collide, scene.sdf, mesh, margin=scene.margin, method="amortized"))):
                counted["points"] = 0
                t0 = time.perf_counter()
                collide_now(sdf_pose)
                runs[name][0].append(1e3 * (time.perf_counter() - t0))
                runs[name][1].append(counted["points"])
    finally:
        NeuralShape._interpolate = lookup
    # the first step is cold both ways: the medians are over the steps after it
    out = {name: {"median_ms": float(np.median(ms[1:])), "median_points": float(np.median(pts[1:])),
                  "first_ms": ms[0]} for name, (ms, pts) in runs.items()}
    out["stats"] = collider.stats.as_dict()
    return out


if __name__ == "__main__":
    print(measure(steps=int(sys.argv[1]) if len(sys.argv) > 1 else 50))
