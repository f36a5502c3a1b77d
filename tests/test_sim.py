"""zoo.sim: contacts against MuJoCo's native ones, the contact reduction, stiff and extreme cases, scenes, `zoo simulate`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from sdfzoo.benches import sim_check, stress_sim  # noqa: E402
from zoo.errors import InputError  # noqa: E402
from zoo.geometry import face_normals  # noqa: E402
from zoo.sim.contacts import refine_near, refine_to_size  # noqa: E402
from zoo.sim.reduction import reduce_contacts  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def test_import_zoo_does_not_load_mujoco():
    code = "import sys, zoo; print('mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- against native MuJoCo (the same comparisons as benches/sim_check.py) ---------------------


@pytest.mark.parametrize("name, shape, ground, xy", [
    ("sphere over a vertex of a fine plane", "sphere", "fine", (0.0, 0.0)),
    ("sphere on a 2-triangle plane", "sphere", "coarse", (0.3, 0.1)),
    ("box on a 2-triangle plane", "box", "coarse", (0.3, 0.1)),
])
def test_resting_matches_native(name, shape, ground, xy):
    mesh = sim_check.grid_plane(64, 1.0) if ground == "fine" else sim_check.two_triangle_plane()
    record = sim_check.rest_case(name, shape, mesh, xy=xy)
    assert abs(record["penetration_error"]) <= 0.25, record
    assert abs(record["normal_force_error"]) <= 0.01, record
    assert record["zoo_contacts"] > 0 and not record["warnings"], record


def test_sliding_box_matches_native():
    record = sim_check.slide_case("flat box sliding", sim_check.two_triangle_plane())
    assert abs(record["slide_error"]) <= 0.10, record


def test_raw_contacts_on_a_vertex_are_stiffer_than_native():
    """Why contacts are reduced: the copies of a vertex's contact make the ground harder without it."""
    native = sim_check.resting(sim_check.native_run("sphere", (0.0, 0.0), sim_check.RADIUS + 5e-4, seconds=0.4), sim_check.RADIUS)
    run = sim_check.zoo_run("sphere", sim_check.grid_plane(32, 1.0), (0.0, 0.0), sim_check.RADIUS + 5e-4, seconds=0.4, reduce=False)
    raw = sim_check.resting(run, sim_check.RADIUS)
    assert raw["penetration"] < 0.5 * native["penetration"]


# -- reduction and refinement -----------------------------------------------------------------


def test_reduction_merges_copies_of_one_point():
    points = np.zeros((6, 3)) + np.random.default_rng(0).normal(scale=1e-4, size=(6, 3))
    normals = np.tile([0.0, 0.0, -1.0], (6, 1))
    faces = np.tile([0.0, 0.0, 1.0], (6, 1))
    keep = reduce_contacts(points, np.full(6, -1e-4), normals, faces, merge_tol=1e-3)
    assert len(keep) == 1


def test_reduction_keeps_four_corners_of_a_flat_patch():
    g = np.linspace(-0.05, 0.05, 11)
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    keep = reduce_contacts(points, np.full(len(points), -1e-4), normals, -normals, merge_tol=5e-3)
    assert len(keep) == 4
    assert np.allclose(np.abs(points[keep, :2]), 0.05)


def test_reduction_keeps_one_contact_of_a_sphere_deep_in_a_plane():
    """The rim of a curved contact has slanted normals: it adds no points (MuJoCo's sphere-plane has one)."""
    centre = np.array([0.0, 0.0, 0.02])
    g = np.linspace(-0.04, 0.04, 9)
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    offset = points - centre
    depths = np.linalg.norm(offset, axis=1) - 0.05
    normals = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    keep = reduce_contacts(points, depths, normals, np.tile([0.0, 0.0, 1.0], (len(points), 1)), merge_tol=2.5e-3)
    assert len(keep) == 1 and np.allclose(points[keep[0]], 0)


def test_refine_clips_large_triangles_to_the_box():
    v, f = sim_check.two_triangle_plane()
    lo, hi = np.array([0.2, 0.0, -0.1]), np.array([0.4, 0.2, 0.1])
    rv, rf, origin = refine_near(v, f, lo, hi, max_edge=0.05)
    tri = rv[rf]
    assert len(rf) > 2 and set(origin.tolist()) <= {0, 1}
    assert (tri >= lo - 1e-9).all() and (tri <= hi + 1e-9).all()
    assert np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max() <= 0.05 + 1e-9
    assert np.isclose(np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]).sum() / 2, 0.2 * 0.2)
    assert np.allclose(np.abs(face_normals(tri)[:, 2]), 1)


def test_refinement_covers_each_face_with_pieces_no_longer_than_asked():
    """refine_to_size against the faces it came from: every piece lies in its origin face's plane and inside it
    (barycentric coordinates of its corners >= 0), the pieces of a face add up to its area, no edge is longer than
    asked, orientation is kept; a budget too small gives None; a sliver gives fewer pieces than splitting every edge."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    sliver = (np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.2, 0.002, 0.0]]), np.array([[0, 1, 2]]))
    cylinder = trimesh.creation.cylinder(radius=0.01, height=0.2, sections=32)  # sides: slivers; caps: fans
    for v, f in ((np.asarray(mesh.vertices), np.asarray(mesh.faces)), sliver, (np.asarray(cylinder.vertices), np.asarray(cylinder.faces))):
        rv, rf, origin = refine_to_size(v, f, 0.05, max_faces=100_000)
        tri, source = rv[rf], v[f[origin]]
        assert np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max() <= 0.05 + 1e-12
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
        whole = np.linalg.norm(np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0]), axis=1) / 2
        assert np.allclose(np.bincount(origin, weights=area, minlength=len(f)), whole)
        assert (np.einsum("ij,ij->i", face_normals(tri), face_normals(source)) > 1 - 1e-9).all()
        for corner in range(3):  # inside the origin face: barycentric coordinates by least squares, all >= 0
            edges = np.stack([source[:, 1] - source[:, 0], source[:, 2] - source[:, 0]], axis=2)  # (N, 3, 2)
            uv = np.linalg.lstsq(edges[0], (tri[:, corner] - source[:, 0])[0], rcond=None)[0] if len(f) == 1 else \
                np.stack([np.linalg.lstsq(e, p, rcond=None)[0] for e, p in zip(edges, tri[:, corner] - source[:, 0])])
            uv = np.atleast_2d(uv)
            assert (uv >= -1e-9).all() and (uv.sum(axis=1) <= 1 + 1e-9).all()
    every_edge = trimesh.remesh.subdivide_to_size(*sliver, max_edge=0.05)[1]  # splitting all three edges each time
    assert len(refine_to_size(*sliver, 0.05, max_faces=100_000)[1]) < len(every_edge)
    assert refine_to_size(*sliver, 0.05, max_faces=4) is None


def test_refinement_cuts_a_tessellated_cylinder_across_its_slivers():
    """A finely tessellated cylinder (side faces 1 mm wide, 200 mm long) is cut across its length, not into
    needles: each side face becomes a ladder of 2 n - 1 pieces as wide as the face, with n the fewest strips that
    keep every edge within the bound, and the cut points are shared between neighbouring faces (the refined
    mesh stays watertight, consistently wound, and encloses the same volume). Longest-edge bisection alone
    makes twice as many pieces here."""
    import trimesh

    cylinder = trimesh.creation.cylinder(radius=0.02, height=0.2, sections=128)
    v, f = np.asarray(cylinder.vertices), np.asarray(cylinder.faces)
    rv, rf, origin = refine_to_size(v, f, 0.03, max_faces=100_000)
    refined = trimesh.Trimesh(rv, rf, process=False)
    assert refined.is_watertight and refined.is_winding_consistent
    assert np.isclose(refined.volume, cylinder.volume, rtol=1e-9)
    tri = v[f]
    lengths = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1)
    side = lengths.max(axis=1) > 0.03
    strips = np.ceil(lengths.max(axis=1) / (0.03 - lengths.min(axis=1))).astype(int)
    pieces = np.bincount(origin, minlength=len(f))
    assert side.sum() == 256 and (pieces[side] == 2 * strips[side] - 1).all() and (pieces[~side] == 1).all()
    bisected = _longest_edge_bisection(v, f, 0.03)
    assert bisected >= 2 * len(rf)


def _longest_edge_bisection(v: np.ndarray, f: np.ndarray, max_edge: float) -> int:
    """The number of faces longest-edge bisection alone makes of (v, f) (a naive, face-by-face count)."""
    stack, count = [v[face] for face in f], 0
    while stack:
        tri = stack.pop()
        lengths = np.linalg.norm(tri[[1, 2, 0]] - tri, axis=-1)
        k = int(lengths.argmax())
        if lengths[k] <= max_edge:
            count += 1
            continue
        a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
        middle = (a + b) / 2
        stack += [np.stack([a, middle, c]), np.stack([middle, b, c])]
    return count


# -- stiff and extreme cases (as `zoo stress --sim`) -------------------------------------------


def _deep_penetration_warned(observed: dict) -> bool:
    return any("deep penetration" in w for w in observed["warnings"])


def _stiff(o: dict) -> None:
    assert 0 < o["resting_penetration_mm"] < 1.0 and o["final_speed"] < 1e-2 and o["n_warnings"] == 0


def _impact(o: dict) -> None:
    radius_mm = 1e3 * sim_check.RADIUS
    assert o["steps_with_widened_margin"] > 0  # the closing distance was seen: the margin widened
    assert o["lowest_centre_mm"] > 0 and o["final_height_mm"] > radius_mm - 1.0  # never through the plane; rests on it


def _impact_far(o: dict) -> None:
    assert not o["passed_through"] or _deep_penetration_warned(o)  # stopped, or never silently


def _deep(o: dict) -> None:
    assert o["max_speed"] < 2.0 and o["final_penetration_mm"] < 1.0
    assert o["jump_mm"] < max(2 * o["native_jump_mm"], 10.0)  # no higher than twice native MuJoCo's ball from that depth
    assert _deep_penetration_warned(o)


def _light_on_heavy(o: dict) -> None:
    assert abs(o["top_sink_mm"]) < 1.0 and o["top_final_speed"] < 1e-2 and o["n_warnings"] == 0


SIM_STRESS_CHECKS = {"stiff": _stiff, "impact crossing": _impact, "impact far": _impact_far, "deep": _deep,
                     "mass ratio 1:1000": _light_on_heavy}


@pytest.mark.parametrize("prefix", list(SIM_STRESS_CHECKS))
def test_stress_case(prefix):
    """The `zoo stress --sim` case as the command runs it, judged here on what it observed."""
    name, fn = next((n, f) for n, f in stress_sim.CASES if n.startswith(prefix))
    expected, observed, ok = fn({})
    assert observed["finite"], (name, observed)
    SIM_STRESS_CHECKS[prefix](observed)
    assert ok  # the command's summary agrees


# -- the API ----------------------------------------------------------------------------------


def test_hinge_with_a_velocity_drive_turns_at_its_target():
    sim = zoo.sim.Simulation(dt=0.002)
    sim.add_body("wheel", sdf=zoo.Sphere(radius=0.05), mass=1.0, joint="hinge", axis=(0, 0, 1),
                 drive={"type": "velocity", "target": 2.0, "kv": 50.0})
    sim.run(0.5)
    assert np.isclose(sim.velocity("wheel")[5], 2.0, rtol=0.02)
    assert np.allclose(sim.pose("wheel")[:3, 3], 0, atol=1e-9)


def test_slide_with_a_motor_and_mass_from_the_sdf():
    sim = zoo.sim.Simulation(dt=0.002, gravity=(0, 0, 0))
    body = sim.add_body("block", sdf=zoo.Box(half_extents=(0.05, 0.05, 0.05)), density=1000.0, joint="slide", axis=(1, 0, 0),
                        drive={"type": "motor", "ctrl": 1.0})
    assert np.isclose(body.mass.mass, 1.0, rtol=0.01)  # a 10 cm cube of water
    sim.run(0.2)
    assert np.isclose(sim.velocity("block")[0], 1.0 / body.mass.mass * 0.2, rtol=0.02)


def test_bad_arguments_raise_typed_errors():
    with pytest.raises(InputError, match="integrator"):
        zoo.sim.Simulation(integrator="verlet")
    with pytest.raises(InputError, match="friction cone"):
        zoo.sim.Simulation(cone="round")
    with pytest.raises(InputError, match="impratio"):
        zoo.sim.Simulation(impratio=0.5)
    with pytest.raises(InputError, match="impratio"):
        zoo.sim.Simulation(impratio="ten")
    sim = zoo.sim.Simulation()
    with pytest.raises(InputError, match="joint"):
        sim.add_body("a", sdf=zoo.Sphere(radius=0.1), joint="ball")
    with pytest.raises(InputError, match="sdf, a mesh"):
        sim.add_body("b")
    with pytest.raises(InputError, match="rotation"):
        sim.add_body("c", sdf=zoo.Sphere(radius=0.1), pose=np.diag([2.0, 1.0, 1.0, 1.0]))  # not rigid
    with pytest.raises(InputError, match="no body"):
        sim.pose("missing")


def test_log_records_every_step():
    sim = zoo.sim.Simulation(dt=0.001, method="fw")
    sim.add_body("ball", sdf=zoo.Sphere(radius=0.05), mass=1.0, pose=np.array(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.0502], [0, 0, 0, 1]], dtype=float))
    sim.add_body("ground", mesh=sim_check.two_triangle_plane(), joint="fixed")
    sim.step(20)
    assert len(sim.log) == 20 and sim.log[-1].contacts >= 1
    assert isinstance(sim.contacts, zoo.Contacts) and len(sim.contacts) >= 1
    assert all(r.step_s >= r.collide_s > 0 for r in sim.log)  # every step timed its detection, within the step


# -- scenes and `zoo simulate` ------------------------------------------------------------------


def test_zoo_simulate_writes_trajectory_stats_and_plot(tmp_path):
    from typer.testing import CliRunner

    from sdfzoo.cli import sim as _  # noqa: F401  (registers the command until cli.main does)
    from sdfzoo.cli.main import app, register_commands

    register_commands()
    result = CliRunner().invoke(app, ["simulate", str(ROOT / "scenes" / "ring-rack.toml"), "--seconds", "0.02", "--dt", "0.002",
                                      "--out", str(tmp_path), "--no-progress"])
    assert result.exit_code == 0, result.output
    import h5py

    with h5py.File(tmp_path / "ring-rack.h5") as f:
        assert f["bodies/sdf/pose"].shape == (10, 4, 4)
        assert f.attrs["method"] == "fw" and len(f.attrs["scene_sha256"]) == 64 and f.attrs["dt"] == 0.002
        assert f.attrs["cone"] == "pyramidal" and f.attrs["impratio"] == 1.0  # MuJoCo's defaults: the scene sets neither
    stats = json.loads((tmp_path / "ring-rack.json").read_text())
    assert len(stats["steps"]) == 10 and stats["summary"]["finite"]
    assert (tmp_path / "ring-rack.png").stat().st_size > 0


def test_demo_scene_loads_on_bundled_data():
    sim = zoo.sim.load_scene(ROOT / "scenes" / "sim-demo-mug-rack.toml")
    assert set(sim.bodies) == {"mug", "rack"} and sim.bodies["mug"].mass.mass == 0.3
    assert "mugs@" in sim.labels["mug"]
    sim.step(2)
    assert np.isfinite(sim.pose("mug")).all()


def test_frictionless_contacts_hold_a_body_up_without_a_warning():
    """friction = 0 gives frictionless (1-dimensional) contacts: the box rests on the plane, finite, unwarned."""
    sim = zoo.sim.Simulation(dt=sim_check.DT, method="fw", friction=0.0)
    pose = np.eye(4)
    pose[2, 3] = sim_check.HALF
    sim.add_body("box", sdf=zoo.Box(half_extents=(sim_check.HALF,) * 3), mass=1.0, pose=pose)
    sim.add_body("ground", mesh=sim_check.two_triangle_plane(), joint="fixed")
    sim.run(0.3)
    assert np.isfinite(sim.pose("box")).all()
    assert abs(sim.pose("box")[2, 3] - sim_check.HALF) < 1e-3
    assert abs(sim.normal_force("box") - 9.81) < 0.05 * 9.81
    assert not sim.warnings


def _sphere_towards_plane(gap: float, speed: float, steps: int):
    """A 2 cm zoo.Sphere in zero gravity moving at ``speed`` towards a fixed plane ``gap`` below it (1 mm margin)."""
    sim = zoo.sim.Simulation(dt=0.002, gravity=(0.0, 0.0, 0.0), method="fw", margin=1e-3, friction=1.0)
    pose = np.eye(4)
    pose[2, 3] = 0.02 + gap
    sim.add_body("ball", sdf=zoo.Sphere(radius=0.02), mass=0.1, pose=pose, velocity=(0.0, 0.0, -speed, 0.0, 0.0, 0.0))
    sim.add_body("ground", mesh=sim_check.two_triangle_plane(), joint="fixed")
    sim.run(steps * sim.dt)
    return sim


def test_a_separated_contact_exerts_no_force_until_the_step_can_close_it():
    """A ball 0.8 mm above a plane, inside the 1 mm margin, approaching at 0.1 m/s (0.2 mm a step): nothing
    pushes it while the gap exceeds what 1.5 steps close (MuJoCo's solver would damp the approach of a
    separated contact it is given), so it keeps its speed; it still stops on the plane."""
    sim = _sphere_towards_plane(8e-4, 0.1, 2)
    assert sim.velocity("ball")[2] == pytest.approx(-0.1, abs=1e-9)
    sim.run(0.1)
    assert abs(sim.velocity("ball")[2]) < 0.02
    assert sim.pose("ball")[2, 3] > 0.02 - 5e-4


def test_pose_and_velocity_build_the_model_on_first_use():
    sim = zoo.sim.Simulation(method="fw")
    sim.add_body("ball", sdf=zoo.Sphere(radius=0.05), mass=1.0, pose=np.array(
        [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0.3], [0, 0, 0, 1]], dtype=float))
    assert np.allclose(sim.pose("ball")[:3, 3], [0.1, 0.0, 0.3]) and np.allclose(sim.velocity("ball"), 0.0)


def _strip_floor(strips: int = 200, side: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """A square floor in z = 0 cut into ``strips`` strips along y, each two triangles: (V, 3), (F, 3)."""
    x = np.linspace(-side / 2, side / 2, strips + 1)
    v = np.concatenate([np.stack([x, np.full_like(x, -side / 2), 0 * x], 1), np.stack([x, np.full_like(x, side / 2), 0 * x], 1)])
    a, b = np.arange(strips), np.arange(strips) + 1
    c, d = b + strips + 1, a + strips + 1
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_a_finer_flat_floor_costs_the_pair_no_more_faces_and_contacts_name_its_own_faces():
    """A box resting on a floor of 1 mm strips, and on the same floor subdivided twice (16x the faces): the pair's
    mesh comes back to within 15% of the same size, less than half of what the fine floor refines to as given
    (zoo.sim.flat_regions: the strips are narrower than half the reduction's cell, 1.25 mm), the box settles alike, and each contact names a face of the floor given that holds its point (brute
    force over every face)."""
    import trimesh

    floor = _strip_floor()
    fine = tuple(np.asarray(a) for a in trimesh.remesh.subdivide(*trimesh.remesh.subdivide(*floor)))
    runs = {}
    for name, ground in (("coarse", floor), ("fine", fine)):
        sim = zoo.sim.Simulation(dt=sim_check.DT, method="fw")
        pose = np.eye(4)
        pose[2, 3] = sim_check.HALF
        sim.add_body("box", sdf=zoo.Box(half_extents=(sim_check.HALF,) * 3), mass=1.0, pose=pose)
        sim.add_body("ground", mesh=ground, joint="fixed")
        sim.run(0.2)
        runs[name] = sim
    assert len(fine[1]) == 16 * len(floor[1])
    sizes = [len(sim.world.pairs[0].refined.faces) for sim in runs.values()]
    pair = runs["fine"].world.pairs[0]
    as_given = len(refine_to_size(pair.vertices, pair.faces, pair.sdf_body.max_edge, max_faces=10**6)[1])
    assert sizes[1] <= 1.15 * sizes[0] and 2 * sizes[1] < as_given, (sizes, as_given)
    assert not runs["fine"].world.pairs[0].refined.cover.one_each  # faces were merged: the cover is not the identity
    assert np.allclose(runs["coarse"].pose("box"), runs["fine"].pose("box"), atol=2e-4)
    contacts = runs["fine"].contacts
    assert len(contacts) > 0
    v, f = fine
    tri = v[f[contacts.triangles.numpy()]]
    points = contacts.points.numpy().astype(np.float64)
    # the mesh point of a contact lies in its named triangle: in the floor's plane, inside its edges
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = points - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    s = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
    t = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    assert (np.abs(points[:, 2]) < 1e-6).all()
    assert ((s >= -1e-6) & (t >= -1e-6) & (s + t <= 1 + 1e-6)).all()
