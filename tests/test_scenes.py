"""Scene files, procedural parts, the demo and the stress harness."""

import json

import numpy as np
import pytest

import zoo
from sdfzoo.benches.stress import run_stress
from zoo import parts
from zoo.errors import DataError, InputError
from zoo.scenes import load_collision_scene, pose_matrix, resolve_scene, run_scene, scene_from_dict, write_outputs


def sphere_on_plane(method="fw"):
    return {
        "name": "ball",
        "method": method,
        "margin": 0.002,
        "sdf": {"analytic": "sphere", "params": {"radius": 0.05}, "pose": {"translation": [0.01, -0.02, 0.049]}},
        "mesh": {"procedural": "plane", "params": {"size": 0.2, "max_edge": 0.01}},
    }


def exact_plane_distances(mesh, centre, radius):
    """Independent: each triangle's exact distance to the ball, its closest point's distance minus r (F,)."""
    from test_collide import closest_points_on_triangles

    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    return np.linalg.norm(closest_points_on_triangles(centre, tri) - centre, axis=1) - radius


def test_scene_matches_independent_contacts():
    scene = scene_from_dict(sphere_on_plane())
    contacts = run_scene(scene)
    exact = exact_plane_distances(scene.mesh, np.array([0.01, -0.02, 0.049]), 0.05)
    # triangles within FW's tolerance of the margin may fall either way; every other one must match
    sharp = np.abs(exact - scene.margin) > 1e-4
    assert sharp.sum() > len(exact) - 20
    found = np.zeros(len(exact), dtype=bool)
    found[contacts.triangles.numpy()] = True
    assert np.array_equal(found[sharp], (exact <= scene.margin)[sharp]) and found.sum() > 20
    assert float(contacts.depths.min()) == pytest.approx(-0.001, abs=2e-4)  # the ball sinks 1 mm into the plane
    assert bool((contacts.normals[:, 2] < -0.9).all())  # normals point from the ball down into the plane


def test_scene_file_round_trip(tmp_path):
    (tmp_path / "s.toml").write_text(
        'name = "ball"\nmargin = 0.002\n[sdf]\nanalytic = "sphere"\nparams = { radius = 0.05 }\n'
        'pose = { translation = [0.01, -0.02, 0.049] }\n[mesh]\nprocedural = "plane"\nparams = { size = 0.2, max_edge = 0.01 }\n'
    )
    scene = load_collision_scene(tmp_path / "s.toml")
    contacts = run_scene(scene)
    paths = write_outputs(scene, contacts, tmp_path / "out")
    report = json.loads(paths["json"].read_text())
    assert report["n_contacts"] == len(contacts) > 0
    assert paths["png"].stat().st_size > 1000


def test_pose_matrix_is_rigid_and_matches_euler():
    m = pose_matrix({"translation": [1, 2, 3], "rotation_deg": [0, 0, 90]})
    assert np.allclose(m[:3, :3] @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(m[:3, 3], [1, 2, 3])
    with pytest.raises(InputError):
        pose_matrix({"translate": [0, 0, 0]})


def test_bad_scenes_raise_typed_errors(tmp_path):
    with pytest.raises(DataError):
        load_collision_scene(tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("name = [")
    with pytest.raises(DataError):
        load_collision_scene(tmp_path / "bad.toml")
    with pytest.raises(InputError):
        scene_from_dict({"sdf": {"analytic": "blob"}, "mesh": {"procedural": "plane"}})
    with pytest.raises(InputError):
        scene_from_dict({"sdf": {"analytic": "sphere"}, "mesh": {"procedural": "teapot"}})


def test_procedural_parts_respect_max_edge():
    for make in (parts.rack, parts.holder, parts.plane):
        mesh = make(max_edge=0.02)
        assert mesh.edges_unique_length.max() <= 0.02 + 1e-9
        assert len(mesh.faces) > 0


def test_stress_report_is_written(tmp_path, monkeypatch):
    import sdfzoo.benches.stress as stress

    monkeypatch.setattr(stress, "CASES", [c for c in stress.CASES if c[0] in ("zero gradient (medial axis)", "float32 against float64")])
    report = run_stress(tmp_path / "s.json")
    assert report["passed"] == 2 and report["failed"] == 0
    assert json.loads((tmp_path / "s.json").read_text())["cases"][0]["expected"]


def test_demo_error_against_run_time_on_the_bundled_model():
    from sdfzoo.benches.demo import demo_scene, error_vs_runtime

    scene, _ = demo_scene()  # the bundled mugs model on a procedural rack: no ../shared needed
    rows = {r["method"]: r for r in error_vs_runtime(scene, iters=(1, 10), repeats=1)}
    assert set(rows) == {"amortized", "fw-1", "fw-10"}
    assert all(r["ms_per_triangle"] > 0 for r in rows.values())
    assert rows["fw-10"]["optimality_mean"] < rows["fw-1"]["optimality_mean"]
    # the detector's polished answer beats ten Frank-Wolfe iterations on the hanging mug's candidates
    assert rows["amortized"]["optimality_mean"] < rows["fw-10"]["optimality_mean"]


# --------------------------------------------------------------------------- the bundled demo scene


def test_the_bundled_demo_scene_loads_by_name_without_zoo_data_and_collides(tmp_path, monkeypatch):
    monkeypatch.delenv("ZOO_DATA", raising=False)
    monkeypatch.chdir(tmp_path)  # not the clone: the bare name and the clone-relative path are both looked up
    assert resolve_scene("demo-mug-rack") == resolve_scene("scenes/demo-mug-rack.toml")
    scene = load_collision_scene("demo-mug-rack")
    assert scene.name == "demo-mug-rack" and scene.mesh_label == "procedural:rack" and scene.method == "amortized"
    contacts = run_scene(scene)
    assert set(scene.timings) >= {"first_collide_s", "collide_s"}  # the time of a warm call, and of the first
    assert contacts.n_candidates > len(contacts) > 50  # the handle's bar on the peg
    assert -2e-3 < float(contacts.depths.min()) < 0  # pressed about half a millimetre in, as the file says
    top_of_peg = contacts.points[:, 2] > 0.19  # the peg rises from z 0.193; the base and the post are far below
    assert bool(top_of_peg.all())


def test_zoo_collide_prints_the_contact_table_and_writes_json_and_png(tmp_path, capsys):
    from sdfzoo.cli.main import main

    main(["collide", "demo-mug-rack", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    written = json.loads((tmp_path / "demo-mug-rack.json").read_text())
    assert (tmp_path / "demo-mug-rack.png").stat().st_size > 10_000
    assert "depth (mm)" in out and "normal" in out  # the README's contact table
    first = written["contacts"][0]
    assert f"{1e3 * first['depth']:+.3f}" in out and str(first["triangle"]) in out
    assert f"{written['n_contacts'] - 15} more in" in out


@pytest.mark.slow
def test_the_demo_scene_file_holds_the_pose_hanging_pose_computes():
    from sdfzoo.benches.demo import mug_rack_scene

    computed, bundled = mug_rack_scene(zoo.load("mugs")), load_collision_scene("demo-mug-rack")
    np.testing.assert_allclose(bundled.sdf_pose, computed.sdf_pose, rtol=0, atol=1e-12)
    assert bundled.margin == pytest.approx(computed.margin, rel=1e-12) and bundled.sdf_label == computed.sdf_label
    np.testing.assert_array_equal(bundled.mesh.vertices, computed.mesh.vertices)


def test_a_bare_scene_name_is_found_in_the_installed_packages_data(tmp_path, monkeypatch):
    import zoo.resources

    package = tmp_path / "site-packages" / "zoo"
    (package / "data" / "scenes").mkdir(parents=True)
    (package / "data" / "scenes" / "ball.toml").write_text('name = "ball"\n')
    monkeypatch.setattr(zoo.resources, "__file__", str(package / "resources.py"))  # as a wheel installs it
    monkeypatch.chdir(tmp_path)
    assert resolve_scene("ball") == package / "data" / "scenes" / "ball.toml"
    assert resolve_scene("scenes/ball.toml") == package / "data" / "scenes" / "ball.toml"
    with pytest.raises(DataError, match="one of: ball"):
        resolve_scene("teapot")


def test_a_triangle_crossing_the_pictures_cube_is_clipped_to_it():
    from zoo.scene_picture import clipped_to_cube

    inside = [[0.1, 0.1, 0.0], [0.2, 0.1, 0.0], [0.1, 0.2, 0.0]]
    crossing = [[-2.0, -0.5, 0.0], [2.0, -0.5, 0.0], [0.0, 0.5, 0.0]]  # a long, thin triangle: a rack's peg
    outside = [[5.0, 5.0, 5.0], [6.0, 5.0, 5.0], [5.0, 6.0, 5.0]]
    polygons, source = clipped_to_cube(np.array([inside, crossing, outside]), np.zeros(3), 1.0)
    assert source.tolist() == [0, 1]
    np.testing.assert_array_equal(polygons[0], inside)
    piece = polygons[1]
    assert np.abs(piece).max() <= 1.0 + 1e-12
    x, y = piece[:, 0], piece[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert area == pytest.approx(1.5)  # the part with |x| <= 1: 1 below y = 0, 0.5 above
