"""zoo.meshes: loading, the similarity transform, normalisation, exact signed distance, samples."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from real_meshes import DATA, needs_data

from zoo.errors import DataError, InputError
from zoo.meshes import Similarity, exterior_faces, load_mesh, normalise, sample_sdf, signed_distance, up_rotation


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def box_sdf(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


# --------------------------------------------------------------------------- Similarity


def test_similarity_maps_points_and_distances_both_ways():
    rng = np.random.default_rng(0)
    sim = Similarity(2.5, random_rotation(rng), rng.normal(size=3))
    p = rng.normal(size=(100, 3))
    n = sim.to_normalised(p)
    np.testing.assert_allclose(n, 2.5 * p @ sim.rotation.T + sim.translation)
    np.testing.assert_allclose(sim.to_source(n), p, atol=1e-12)
    homo = np.c_[p, np.ones(len(p))]
    np.testing.assert_allclose((homo @ sim.matrix.T)[:, :3], n, atol=1e-12)
    np.testing.assert_allclose(sim.matrix @ sim.inverse_matrix, np.eye(4), atol=1e-12)
    assert sim.distance_to_source(np.array([2.5]))[0] == pytest.approx(1.0)
    assert sim.distance_to_normalised(np.array([1.0]))[0] == pytest.approx(2.5)


def test_similarity_json_round_trip_is_exact():
    rng = np.random.default_rng(1)
    sim = Similarity(0.0123456789, random_rotation(rng), rng.normal(size=3))
    assert Similarity.from_json(sim.to_json()) == sim
    assert Similarity.from_dict(sim.to_dict()) == sim


def test_similarity_keeps_float32_points_float32():
    sim = Similarity(2.0, np.eye(3), np.ones(3))
    assert sim.to_normalised(np.zeros((4, 3), np.float32)).dtype == np.float32


@pytest.mark.parametrize("scale, rotation", [(0.0, np.eye(3)), (1.0, np.diag([1, 1, -1])), (1.0, 2 * np.eye(3))])
def test_similarity_rejects_bad_scale_or_rotation(scale, rotation):
    with pytest.raises(InputError):
        Similarity(scale, rotation, np.zeros(3))


def test_similarity_from_bad_json_is_a_data_error():
    with pytest.raises(DataError):
        Similarity.from_json("{not json")
    with pytest.raises(DataError):
        Similarity.from_dict({"scale": 1.0})


# --------------------------------------------------------------------------- orientation and normalise


@pytest.mark.parametrize("axis, vector", [("z", [0, 0, 1]), ("y", [0, 1, 0]), ("x", [1, 0, 0]), ("-z", [0, 0, -1]), ("-y", [0, -1, 0])])
def test_up_rotation_takes_the_up_axis_to_plus_z(axis, vector):
    r = up_rotation(axis)
    np.testing.assert_allclose(r @ np.array(vector, float), [0, 0, 1], atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_up_rotation_rejects_unknown_axes_and_non_rotations():
    with pytest.raises(InputError):
        up_rotation("w")
    with pytest.raises(InputError):
        up_rotation(np.diag([1.0, 1.0, -1.0]))


def test_normalise_fills_the_unit_cube_and_maps_back():
    mesh = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    mesh.apply_translation([10.0, -3.0, 7.0])
    out, sim = normalise(mesh, up_axis="z")
    lo, hi = out.bounds
    np.testing.assert_allclose(hi - lo, [1.0, 0.5, 0.25], atol=1e-12)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-12)
    assert out.vertices.min() >= -0.5 - 1e-12 and out.vertices.max() <= 0.5 + 1e-12
    np.testing.assert_allclose(sim.to_source(out.vertices), mesh.vertices, atol=1e-12)
    assert sim.scale == pytest.approx(0.25)


def test_normalise_turns_a_y_up_mesh_z_up():
    tall_along_y = trimesh.creation.box(extents=(1.0, 3.0, 1.0))
    out, _ = normalise(tall_along_y, up_axis="y")
    np.testing.assert_allclose(out.extents, [1 / 3, 1 / 3, 1.0], atol=1e-12)


# --------------------------------------------------------------------------- loading


def test_load_mesh_merges_seams_and_drops_degenerate_faces(tmp_path):
    box = trimesh.creation.box()
    soup = trimesh.Trimesh(box.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False)  # unshared vertices
    soup = trimesh.Trimesh(np.r_[soup.vertices, [[0, 0, 0]] * 3], np.r_[soup.faces, [[36, 37, 38]]], process=False)
    path = tmp_path / "soup.obj"
    path.write_text(trimesh.exchange.obj.export_obj(soup))
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12 and mesh.is_watertight


def test_load_mesh_reads_a_double_sided_mesh_with_an_inside(tmp_path):
    box = trimesh.creation.box()
    double = trimesh.Trimesh(box.vertices, np.r_[box.faces, box.faces[:, ::-1]], process=False)
    path = tmp_path / "double.ply"
    double.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12
    assert signed_distance(mesh, np.zeros((1, 3)))[0] == pytest.approx(-0.5)


@pytest.mark.parametrize("content", [b"", b"this is not a mesh\x00\xff", b"v 0 0 0\nv 1 0 0\n"])
def test_load_mesh_rejects_garbage_or_empty_files(tmp_path, content):
    path = tmp_path / "bad.obj"
    path.write_bytes(content)
    with pytest.raises(DataError):
        load_mesh(path)


def test_load_mesh_missing_file_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        load_mesh(tmp_path / "nope.obj")


# --------------------------------------------------------------------------- signed distance


def test_signed_distance_of_a_box_is_exact():
    half = np.array([0.2, 0.15, 0.1])
    mesh = trimesh.creation.box(extents=2 * half)
    p = np.random.default_rng(2).uniform(-0.5, 0.5, size=(3000, 3))
    np.testing.assert_allclose(signed_distance(mesh, p), box_sdf(p, half), atol=1e-9)


def test_signed_distance_of_a_sphere_matches_the_analytic_sdf():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    p = np.random.default_rng(3).uniform(-0.5, 0.5, size=(3000, 3))
    d = signed_distance(mesh, p)
    # the polyhedron lies inside the sphere, at most r (1 - cos(edge angle / 2)) ~ 1e-3 from it
    np.testing.assert_allclose(d, np.linalg.norm(p, axis=1) - 0.3, atol=2e-3)


def test_signed_distance_signs_the_inside_of_an_open_box_negative():
    half = np.array([0.2, 0.2, 0.2])
    box = trimesh.creation.box(extents=2 * half)
    top = np.where(box.triangles_center[:, 2] > 0.19)[0]
    open_box = trimesh.Trimesh(box.vertices, np.delete(box.faces, top, axis=0), process=False)
    assert not open_box.is_watertight
    rng = np.random.default_rng(4)
    inside = rng.uniform(-0.15, 0.1, size=(500, 3))  # below the missing lid
    outside = rng.uniform(0.25, 0.5, size=(500, 3)) * rng.choice([-1, 1], size=(500, 3))
    assert (signed_distance(open_box, inside) < 0).all()
    assert (signed_distance(open_box, outside) > 0).all()


def test_faces_buried_where_two_parts_touch_are_not_surface():
    """Two closed boxes stacked face to face are one box: the shared faces must not count as surface."""
    lower = trimesh.creation.box(extents=(0.4, 0.4, 0.2))
    lower.apply_translation([0, 0, -0.1])
    upper = lower.copy()
    upper.apply_translation([0, 0, 0.2])
    stacked = trimesh.util.concatenate([lower, upper])
    assert (~exterior_faces(stacked)).sum() == 4  # two triangles on each side of the shared square
    p = np.random.default_rng(5).uniform(-0.5, 0.5, size=(2000, 3))
    np.testing.assert_allclose(signed_distance(stacked, p), box_sdf(p, np.array([0.2, 0.2, 0.2])), atol=1e-9)


def test_signed_distance_is_right_for_an_inward_facing_mesh():
    box = trimesh.creation.box()
    inverted = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    assert signed_distance(inverted, np.zeros((1, 3)))[0] == pytest.approx(-0.5)


def test_signed_distance_keeps_float32_and_validates_points():
    mesh = trimesh.creation.box()
    assert signed_distance(mesh, np.zeros((2, 3), np.float32)).dtype == np.float32
    assert signed_distance(mesh, np.zeros((2, 3))).dtype == np.float64
    with pytest.raises(InputError):
        signed_distance(mesh, np.zeros((2, 2)))
    with pytest.raises(InputError):
        signed_distance(mesh, np.full((2, 3), np.nan))


# --------------------------------------------------------------------------- samples


def test_sample_sdf_is_deterministic_by_seed():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    a = sample_sdf(mesh, 3000, seed=7)
    b = sample_sdf(mesh, 3000, seed=7)
    c = sample_sdf(mesh, 3000, seed=8)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    assert a[0].dtype == np.float32 and a[1].dtype == np.float32 and a[0].shape == (3000, 3)


def test_sample_sdf_puts_points_in_the_two_bands_and_the_padded_cube():
    mesh = trimesh.creation.box(extents=(0.8, 0.6, 1.0))
    points, sdf = sample_sdf(mesh, 10_000, seed=0, near_sigmas=(0.005, 0.05), fractions=(0.4, 0.4, 0.2), padding=0.1)
    fine, coarse, uniform = sdf[:4000], sdf[4000:8000], points[8000:]
    # |sdf| <= |noise|, and a 3-d Gaussian rarely exceeds 4.5 sigma
    assert np.quantile(np.abs(fine), 0.99) < 4.5 * 0.005
    assert np.quantile(np.abs(coarse), 0.99) < 4.5 * 0.05
    assert np.median(np.abs(coarse)) > 3 * np.median(np.abs(fine))
    assert np.abs(uniform).max() <= 0.6 and np.abs(uniform).max() > 0.55
    assert 0.2 < (sdf < 0).mean() < 0.8  # both sides of the surface are sampled


def test_sample_sdf_validates_its_arguments():
    mesh = trimesh.creation.box()
    with pytest.raises(InputError):
        sample_sdf(mesh, 0)
    with pytest.raises(InputError):
        sample_sdf(mesh, 10, fractions=(0.5, 0.5, 0.5))


# --------------------------------------------------------------------------- real meshes


@needs_data
def test_a_real_double_sided_mug_gets_an_inside():
    """edf_mug10 lists every face twice, with opposite windings; its winding number would be 0 everywhere."""
    mesh, _ = normalise(load_mesh(DATA / "mug" / "edf_mug10.ply"), up_axis="y")
    _, sdf = sample_sdf(mesh, 4000, seed=0)
    assert (sdf < 0).mean() > 0.05


@needs_data
def test_a_real_scanned_mug_normalises_upright():
    mesh, sim = normalise(load_mesh(DATA / "mug" / "hoi4d_mug_0001.obj"), up_axis="z")
    assert mesh.extents.max() == pytest.approx(1.0)
    # the opening is up: straight up from the centre there is no surface, straight down there is
    hits_up = mesh.ray.intersects_location([[0, 0, 0]], [[0, 0, 1]])[0]
    hits_down = mesh.ray.intersects_location([[0, 0, 0]], [[0, 0, -1]])[0]
    assert len(hits_up) == 0 and len(hits_down) > 0
