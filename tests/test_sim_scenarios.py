"""The paper's scenarios as simulations on the real meshes (benches/sim_scenarios.py, scenes/sim-*.toml):
the geometry the checks compare with (teeth, thread pitch) measured on the meshes, every scene builds, and
the checks that fit in a test's time. Skips without the development meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from real_meshes import SKIP_REASON, zoo_data

import zoo

pytest.importorskip("mujoco")

ROOT = Path(__file__).resolve().parent.parent
needs_meshes = pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)


@pytest.fixture
def meshes(monkeypatch):
    monkeypatch.setenv("ZOO_DATA", str(zoo_data()))
    return zoo_data()


@needs_meshes
def test_teeth_counted_on_the_industreal_gears(meshes):
    from sdfzoo.benches.sim_scenarios import count_teeth, data_mesh

    centres = {"large": (-0.0302, 0.0), "medium": (0.02025, 0.0), "small": (0.05075, 0.0)}  # axes along z
    teeth = {name: count_teeth(np.asarray(data_mesh(f"gear/industreal_gear_{name}.obj").vertices), c) for name, c in centres.items()}
    assert teeth == {"large": 60, "medium": 40, "small": 20}  # module 1 mm: pitch radii 30, 20 and 10 mm


@pytest.mark.slow  # exact distances of 3 x 3 x 40,000 points to the large gear's mesh: 15-50 s
@needs_meshes
def test_gear_meshes_turn_in_mesh_with_backlash_at_their_assembly_pose(meshes):
    from investigations.gear_clearance import clearance

    rows = clearance(offsets_deg=[-1.0, 0.0, 1.0], phases=3, samples=40_000)
    exact = {r["offset_deg"]: r["exact_m"] for r in rows}
    # the meshes' backlash: clear through a tooth period at the assembly's phase, their teeth overlapping a degree off it
    assert 0.1e-3 < exact[0.0] < 0.3e-3
    assert exact[-1.0] < 0 and exact[1.0] < 0
    assert all(np.isfinite(r["neural_m"]) for r in rows)


@needs_meshes
def test_m16_thread_is_right_handed_with_a_2_mm_pitch(meshes):
    from sdfzoo.benches.sim_scenarios import BOLT_FILE, data_mesh, thread_pitch

    pitch, hand = thread_pitch(np.asarray(data_mesh(BOLT_FILE).vertices))
    assert hand == "right" and pitch == pytest.approx(0.002, abs=2.5e-5)  # ISO M16 coarse


def test_count_teeth_and_thread_pitch_on_synthetic_geometry():
    from sdfzoo.benches.sim_scenarios import count_teeth, thread_pitch

    angle = np.linspace(-np.pi, np.pi, 20000, endpoint=False)
    radius = 0.02 + 0.001 * np.clip(2 * np.cos(17 * angle), -1, 1)  # flat tips and roots, 17 teeth
    gear = np.stack([0.5 + radius * np.cos(angle), radius * np.sin(angle), np.zeros_like(angle)], axis=1)
    assert count_teeth(gear, (0.5, 0.0)) == 17
    turns = np.linspace(0, 10 * 2 * np.pi, 20000)  # a left-hand helix of 1.5 mm pitch on the crest radius
    helix = np.stack([0.008 * np.cos(-turns), 0.008 * np.sin(-turns), 0.019 + 0.0015 * turns / (2 * np.pi)], axis=1)
    pitch, hand = thread_pitch(helix)
    assert hand == "left" and pitch == pytest.approx(0.0015, abs=2.5e-5)


def test_screw_asymmetry_is_zero_only_for_the_threads_own_screw():
    """investigations/screw_symmetry.py against a field known in closed form: r - R - A cos(2 pi z / p - phi) is unchanged by
    a right-hand screw of pitch p, and changed by a pure turn and by the left-hand screw."""
    from investigations.screw_symmetry import advance_per_rad, asymmetry

    pitch, amplitude = 0.002, 2e-4

    def thread(points):
        phi = np.arctan2(points[:, 1], points[:, 0])
        return np.hypot(points[:, 0], points[:, 1]) - 0.008 - amplitude * np.cos(2 * np.pi * points[:, 2] / pitch - phi)

    rng = np.random.default_rng(0)
    angle, z = rng.uniform(-np.pi, np.pi, 500), rng.uniform(0.02, 0.03, 500)
    points = np.stack([0.008 * np.cos(angle), 0.008 * np.sin(angle), z], axis=1)
    angles = (0.01, 1.0)
    right = asymmetry(thread, points, angles, advance_per_rad(pitch, "right"))
    assert [r["theta"] for r in right] == [0.01, -0.01, 1.0, -1.0]
    assert max(r["p100_mm"] for r in right) < 1e-9
    # a pure turn shifts the thread's phase by theta, the left-hand screw by 2 theta; A |cos(a) - cos(a + s)| is at
    # most 2 A |sin(s / 2)|, reached where a = -s / 2
    for advance, shift in ((0.0, 1), (advance_per_rad(pitch, "left"), 2)):
        for r in asymmetry(thread, points, angles, advance):
            most = 1e3 * 2 * amplitude * abs(np.sin(shift * r["theta"] / 2))
            assert 0.5 * most < r["p100_mm"] <= most + 1e-9


@needs_meshes
@pytest.mark.parametrize("scene", ["mug-rack", "bottle-holder", "gear-gear", "bolt-nut", "gripper-mug"])
def test_scene_builds_with_its_bodies_and_joints(meshes, scene):
    import zoo.sim

    sim = zoo.sim.load_scene(ROOT / "scenes" / f"sim-{scene}.toml")
    sim.pose(next(iter(sim.bodies)))  # builds the MuJoCo model
    joints = {name: body.joint for name, body in sim.bodies.items()}
    expected = {
        "mug-rack": {"mug": "free", "rack": "fixed"},
        "bottle-holder": {"bottle": "free", "holder": "fixed"},
        "gear-gear": {"large": "hinge", "medium": "hinge"},
        "bolt-nut": {"bolt": "fixed", "nut": "free"},
        "gripper-mug": {"mug": "free"},  # the gripper and the table are scenes/gripper.xml's
    }[scene]
    assert joints == expected
    moving = [body.body_id for body in sim.bodies.values() if body.joint != "fixed"]
    assert np.all(sim.model.body_mass[moving] > 0)


@pytest.mark.slow  # 80 steps of the NeuralSDF bottle in the holder: 20-110 s on 2 shared cores
@needs_meshes
def test_bottle_lowered_into_the_holder_rests_upright(meshes):
    from sdfzoo.benches.sim_scenarios import run

    result = run("bottle-holder", seconds=0.16)  # lands at 0.075 s; the scene's 0.3 s rests at 0.25 degree
    check = result["check"]
    assert result["finite"] and not result["warnings"], result["warnings"]
    assert check["tilt_deg_end"] < 1.0 and check["contacts"] > 0 and check["speed_end"] < 0.05, check  # 1 degree at release
    assert result["passed"]


@needs_meshes
def test_gripper_lifts_and_carries_the_mug(meshes):
    """scenes/gripper.xml's fingers (slide joints under position actuators, the hand welded to a mocap target) close
    on the NeuralSDF mug standing on the table, lift it 3 cm and carry it 2 cm by the scene's waypoints: it rests on
    the table until grasped, then rises and moves with the hand, slipping less than 2 mm, held by both pads."""
    from sdfzoo.benches.sim_scenarios import run

    result = run("gripper-mug")
    check = result["check"]
    assert result["finite"] and not result["warnings"], result["warnings"]
    assert check["on_table_before_grasp"] and check["resting_drift_mm"] < 2.0, check
    assert check["mug_rise_mm"] > 25.0 and check["mug_shift_mm"] > 15.0 and check["slip_mm"] < 2.0, check
    assert check["pads_touching_end"] == ["left_pad", "right_pad"] and result["passed"], check


@pytest.mark.slow  # 300 steps of the nut on the bolts model's thread: 100-240 s on 2 shared cores
@needs_meshes
def test_nut_turned_on_the_bolt_advances_one_pitch_per_turn(meshes):
    """The nut, driven by a torque about the bolt's axis, turns and rides the thread: 2 mm (the pitch measured on
    the mesh) per turn within 5%, with the thread's hand (bolts@1.2.0; with a threadless NeuralSDF it slid down)."""
    from sdfzoo.benches.sim_scenarios import run

    result = run("bolt-nut")
    check = result["check"]
    assert result["finite"] and not result["warnings"], result["warnings"]
    assert abs(check["turns"]) > 0.05 and check["advance_mm"] * check["turns"] > 0, check  # it turned and advanced with the thread
    assert check["relative_error"] <= 0.05 and result["passed"], check


@pytest.mark.slow  # 150 steps of the gears at dt 1 ms: 35-90 s on 2 shared cores
@needs_meshes
def test_driven_gear_turns_the_other_at_the_teeth_ratio(meshes):
    """The large gear (gears@1.3.0's NeuralSDF) driven at 4 rad/s turns the medium gear's mesh 60/40 times as fast,
    within 5%, with the servo holding its speed (gears@1.2.0's teeth, too fat for the backlash, jammed; so did
    separated contacts given to MuJoCo's solver, which braked the driven gear's back flank at a distance)."""
    from sdfzoo.benches.sim_scenarios import run

    result = run("gear-gear")
    check = result["check"]
    assert result["finite"] and not result["warnings"], result["warnings"]
    assert check["expected_ratio"] == 1.5 and check["w_large"] > 3.8, check  # the servo held its 4 rad/s
    assert check["relative_error"] <= 0.05 and result["passed"], check


def test_face_shapes_of_a_sliver_and_a_right_triangle():
    from investigations.contact_faces import face_shapes

    triangles = np.array([[[0, 0, 0], [3, 0, 0], [0, 4, 0]], [[0, 0, 0], [20, 0, 0], [10, 0.1, 0]]], dtype=np.float64)
    widths, longest = face_shapes(triangles)
    np.testing.assert_allclose(longest, [5.0, 20.0])
    np.testing.assert_allclose(widths, [2 * 6.0 / 5.0, 0.1])  # twice the area over the longest edge: the height on it


def test_faces_counted_within_the_margin_are_those_a_brute_force_search_finds():
    """investigations/contact_faces.py's count of the faces a step must answer, on the bottle resting in the holder (bundled
    data), against the minimum of the bottle's SDF over a barycentric grid of every face of the holder's mesh."""
    from investigations.contact_faces import faces_within_margin, simulated
    from zoo.geometry import barycentric_grid

    sim = simulated("bottle-holder", 45)  # landed at step 38
    contacts = faces_within_margin(sim, "bottle", "holder")
    pair = sim.world.pair("bottle", "holder").refined
    sdf_from_mesh = np.linalg.inv(sim.pose("bottle")) @ sim.world.pair("bottle", "holder").surface_pose(sim.data)
    local = pair.vertices @ sdf_from_mesh[:3, :3].T + sdf_from_mesh[:3, 3]
    triangles = torch.as_tensor(local[pair.faces])
    grid = barycentric_grid(24, dtype=torch.float64)
    near = np.nonzero(np.linalg.norm(local[pair.faces].mean(axis=1), axis=1) < 1.0)[0]  # the bottle is 0.5 units tall
    with torch.no_grad():
        values = sim.bodies["bottle"].sdf(torch.einsum("gv,fvc->fgc", grid, triangles[near]).reshape(-1, 3).float())
    brute = values.reshape(len(near), -1).amin(dim=1).double().numpy()
    edge = np.linalg.norm(local[pair.faces[near]][:, [1, 2, 0]] - local[pair.faces[near]], axis=-1).max(axis=1)
    slack = 2.0 * edge / 24  # the SDF's Lipschitz bound for a NeuralSDF times the grid's spacing
    found = set(np.asarray(contacts.triangles).tolist())
    assert len(found) > 0
    must = near[brute <= sim.margin - 1e-4]  # clearly within the margin on the grid alone
    assert set(must.tolist()) <= found
    may = set(near[brute - slack <= sim.margin + 1e-4].tolist())
    assert found <= may


def test_the_timeline_windows_add_up_to_the_run():
    """investigations/sim_timeline.py on the bottle landing in the holder (bundled data): the windows cover every step once,
    their collider counters add up to the colliders' totals and their medians are the log's."""
    from investigations.sim_timeline import COUNTERS, timeline

    result = timeline("bottle-holder", seconds=0.05, window=10)  # 25 steps of the fall: two full windows and one of 5
    windows = result["windows"]
    assert [(w["first_step"], w["steps"]) for w in windows] == [(0, 10), (10, 10), (20, 5)]
    assert all(w["collide_ms_median"] <= w["collide_ms_p90"] for w in windows)
    assert all(w["contacts_per_step"] == 0 and w["speed_cm_s_end"] > 0 for w in windows)  # falling: no contact yet
    for counter in COUNTERS:
        assert sum(w[f"{counter}_per_step"] * w["steps"] for w in windows) == pytest.approx(result["totals"][counter])
    assert result["totals"]["candidates"] > 0  # the holder's wall lies within the falling bottle's bounds


def test_query_sites_counts_each_query_with_the_function_that_asked():
    """investigations/query_sites.py: the queries made inside ``timed_queries`` are counted by kind and caller, points
    included, and the NeuralSDF's own methods are restored afterwards."""
    from investigations.query_sites import timed_queries
    from zoo.neural import NeuralShape

    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    points = torch.zeros(7, 3)

    def ask_twice():
        shape(points)
        shape.value_and_grad(points[:5])

    with timed_queries() as sites:
        ask_twice()
        ask_twice()
    site = "test_sim_scenarios.ask_twice < test_sim_scenarios.test_query_sites_counts_each_query_with_the_function_that_asked"
    assert set(sites) == {("value", site), ("value+grad", site)}
    assert sites[("value", site)][:2] == [2, 14] and sites[("value+grad", site)][:2] == [2, 10]
    assert all(seconds > 0 for _, _, seconds in sites.values())
    shape(points)
    assert sites[("value", site)][0] == 2 and "timed" not in NeuralShape._distance.__name__
