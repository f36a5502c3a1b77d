"""The Panda scenarios (issue 36, benches/panda_scenarios.py, scenes/panda-*.toml): a Franka Panda hangs a NeuralSDF
mug on the NDF rack's peg and places a NeuralSDF bottle upright in a holder, each with a shape of the model and one
fitted from a mesh of the test split. The robot is read from $ZOO_DATA/../robots: skips without the development
meshes or without the robot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from real_meshes import SKIP_REASON, zoo_data

pytest.importorskip("mujoco")

ROOT = Path(__file__).resolve().parent.parent
ROBOT = None if zoo_data() is None else Path(zoo_data()).parent / "robots" / "franka_panda"
needs_panda = pytest.mark.skipif(ROBOT is None or not ROBOT.is_dir(), reason=f"{SKIP_REASON}; and the Panda in ../robots")
SCENES = ["panda-bottle-holder", "panda-bottle-holder-unseen", "panda-mug-rack", "panda-mug-rack-unseen"]


@pytest.fixture
def meshes(monkeypatch):
    monkeypatch.setenv("ZOO_DATA", str(zoo_data()))
    return zoo_data()


def test_a_robot_outside_the_repository_is_refused_with_what_to_set(tmp_path, monkeypatch):
    import zoo.sim
    from zoo.errors import DataError

    scene = tmp_path / "robot.xml"
    scene.write_text('<mujoco><worldbody><include file="robots/no_such_robot/chain.xml"/></worldbody></mujoco>')
    monkeypatch.setenv("ZOO_DATA", str(tmp_path / "meshes"))
    monkeypatch.delenv("ZOO_ROBOTS", raising=False)
    with pytest.raises(DataError, match="ZOO_DATA"):
        zoo.sim.Simulation(mjcf=scene)


@needs_panda
def test_scaled_shape_answers_the_scaled_distance(meshes):
    import torch

    import zoo

    shape = zoo.load("bottles").shape("bulletarm_bottle1")
    small = shape.scaled(0.18)
    points = torch.rand(64, 3, dtype=torch.float64) * 0.2 - 0.1
    assert torch.allclose(small(points), 0.18 * shape(points / 0.18), atol=1e-6)
    tri = torch.tensor([[[0.05, 0.0, 0.0], [0.05, 0.02, 0.0], [0.05, 0.0, 0.02]]])
    assert torch.allclose(small.detect(tri), shape.detect(tri / 0.18), atol=1e-3)


@needs_panda
@pytest.mark.parametrize("scene", SCENES)
def test_panda_scene_builds_at_its_first_waypoint(meshes, scene):
    """The scene file compiles with the robot from ../robots, its object standing on the table, the arm at the
    planned initial posture (the gripper's first keyframe, clear of the object)."""
    import mujoco

    import zoo.sim
    from sdfzoo.benches.panda_scenarios import ARM, gripper_pose

    sim = zoo.sim.load_scene(ROOT / "scenes" / f"{scene}.toml")
    sim.build()
    obj = "mug" if "mug" in scene else "bottle"
    q = np.array([sim.data.qpos[sim.model.joint(j).qposadr[0]] for j in ARM])
    assert np.allclose(q, [sim.initial_qpos[j] for j in ARM])
    start = gripper_pose(sim.model, mujoco.MjData(sim.model), q)[:3, 3]
    assert np.linalg.norm(start - sim.pose(obj)[:3, 3]) > 0.05  # clear of the object
    assert sim.model.nu == 9 and sim.model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC


@pytest.mark.slow  # the whole scenario: about 1100 steps with the fingers' 26 geoms near the NeuralSDF
@needs_panda
@pytest.mark.parametrize("scene", SCENES)
def test_panda_scenario_passes_its_check(meshes, scene):
    """The Panda grasps the object, lifts it more than 5 cm, releases it; 1 s after the release the bottle stands
    upright (tilt under 10 degrees) inside the holder, or the mug hangs with its handle's hole round the peg's axis;
    no finger touches it and it is at rest."""
    from sdfzoo.benches.panda_scenarios import run

    result = run(scene)
    assert result["lifted_m"] > 0.05 and result["finger_contacts_end"] == 0, result
    if "bottle" in scene:
        assert result["tilt_deg"] < 10.0 and result["off_axis_m"] < 0.04, result
    else:
        assert result["hole_to_peg_axis_m"] < result["hole_half_size_m"] and 0 < result["along_peg_m"] < 0.174, result
    assert result["speed_end"] < 0.02, result
    assert result["passed"], result


@needs_panda
@pytest.mark.parametrize("scene", SCENES)
def test_the_coacd_reference_cuts_the_mesh_the_neuralsdf_was_fitted_to(meshes, scene):
    """`zoo bench --sim`'s CoACD reference (benches/panda_coacd.py) gives the object the mesh its NeuralSDF came from,
    scaled as the scene scales the SDF: the SDF is near 0 on the mesh's vertices (a wrong mesh, frame or scale is
    centimetres off)."""
    import torch

    from sdfzoo.benches.panda_coacd import object_mesh
    from sdfzoo.benches.panda_scenarios import load_sdf
    from zoo.scenes import read_scene

    spec = read_scene(ROOT / "scenes" / f"{scene}.toml")[0]["bodies"][0]["sdf"]
    vertices, faces, digest, label = object_mesh(spec)
    sdf = load_sdf(spec)
    with torch.no_grad():
        f = np.abs(np.asarray(sdf(torch.as_tensor(vertices[::max(1, len(vertices) // 2000)]))))
    size = float(np.ptp(vertices, axis=0).max())
    assert 0.05 < size < 0.3, (label, size)  # metres, a mug or an 18 cm bottle
    assert np.median(f) < 2e-3 and np.percentile(f, 90) < 5e-3, (label, np.median(f), np.percentile(f, 90))


@pytest.mark.slow
@needs_panda
def test_the_coacd_reference_is_the_same_panda_scene_on_convex_pieces(meshes):
    """The CoACD reference keeps the scene's robot, actuators, initial posture, object mass and waypoints; only the
    object's and the holder's geometry are MuJoCo's convex pieces."""
    pytest.importorskip("coacd")
    import zoo.sim
    from sdfzoo.benches.panda_coacd import native_model

    model, data, scene, info = native_model("panda-bottle-holder")
    sim = zoo.sim.load_scene(ROOT / "scenes" / "panda-bottle-holder.toml")
    sim.build()
    assert [model.actuator(i).name for i in range(model.nu)] == [sim.model.actuator(i).name for i in range(sim.model.nu)]
    assert np.allclose(data.qpos[:9], sim.data.qpos[:9])
    assert model.body_mass[model.body("bottle").id] == pytest.approx(sim.model.body_mass[sim.model.body("bottle").id])
    bottle = model.body("bottle").id
    assert int((model.geom_bodyid == bottle).sum()) == info["bottle"]["pieces"] > 0
    assert model.opt.timestep == sim.model.opt.timestep
