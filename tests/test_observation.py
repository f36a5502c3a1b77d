"""zoo.Observation and Model.fit_observation: a shape, pose and scale from depth images or points.

References: an analytic sphere seen by a camera (the backprojected points must lie on it, the optical axis's depth
is |eye - centre| - r), a train shape of the mugs model posed at a known yaw and position (the fit must find its
surface), and MuJoCo itself (a never-seen mug seen by its renderer, fitted, must rest where the true mesh rests).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import trimesh
from real_meshes import SKIP_REASON, zoo_data

import zoo
from sdfzoo.benches import depth_views
from sdfzoo.benches.completion import PlacedObject, observe, surface_errors
from zoo.errors import InputError
from zoo.observation import look_at


@pytest.fixture(scope="module")
def mugs():
    return zoo.load("mugs")


def _sphere_views(centre, radius, eyes):
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    scene = depth_views.with_table(np.asarray(sphere.vertices) + centre, np.asarray(sphere.faces))
    return depth_views.render(scene, np.stack([look_at(e, centre) for e in eyes]))


def test_depth_images_backproject_onto_the_surface_they_saw():
    centre, radius = np.array([0.02, -0.01, 0.06]), 0.05
    eyes = [centre + [0.5, 0.0, 0.25], centre + [-0.2, 0.45, 0.3]]
    images = _sphere_views(centre, radius, eyes)
    obs = zoo.Observation.from_depth(images.depth, images.K, images.T_world_camera, images.mask)
    assert obs.views == 2 and len(obs) > 5000
    off = np.abs(np.linalg.norm(obs.points - centre, axis=1) - radius)
    assert off.max() < 3e-4  # the icosphere's facets lie within 0.2 mm of the sphere
    # each point is seen from its camera, and on the camera's side of the sphere
    to_camera = obs.origins - obs.points
    assert ((obs.points - centre) * to_camera).sum(1).min() > 0
    # the optical axis: the image centre's depth is the distance to the sphere along it
    h, w = images.depth.shape[1:]
    middle = images.depth[0, (h - 1) // 2 : h // 2 + 1, (w - 1) // 2 : w // 2 + 1].mean()
    assert middle == pytest.approx(np.linalg.norm(eyes[0] - centre) - radius, abs=3e-4)
    # the table's pixels become free rays that end on the table (z = 0)
    assert obs.free_ends is not None and np.abs(obs.free_ends[:, 2]).max() < 1e-9


def test_bad_observations_are_refused_with_what_to_do(mugs):
    centre = np.array([0.0, 0.0, 0.06])
    images = _sphere_views(centre, 0.05, [centre + [0.5, 0.0, 0.25]])
    depth, k, pose, mask = images.depth[0], images.K[0], images.T_world_camera[0], images.mask[0]
    with pytest.raises(InputError, match="NaN"):
        zoo.Observation.from_depth(np.where(mask, np.nan, depth), k, pose, mask)
    with pytest.raises(InputError, match="selects no pixel"):
        zoo.Observation.from_depth(depth, k, pose, np.zeros_like(mask))
    with pytest.raises(InputError, match="does not match K"):
        zoo.Observation.from_depth(depth[::2, ::2], k, pose, mask[::2, ::2])
    with pytest.raises(InputError, match="mask must have"):
        zoo.Observation.from_depth(depth, k, pose, mask[:-1])
    with pytest.raises(InputError, match="no points"):
        zoo.Observation.from_points(np.zeros((0, 3)))
    with pytest.raises(InputError, match="NaN"):
        zoo.Observation.from_points([[0.0, 0.0, np.nan]])
    table = zoo.Observation.from_depth(depth, k, pose, images.label[0] == depth_views.TABLE_ID)
    with pytest.raises(InputError, match="one plane"):
        mugs.fit_observation(table)
    with pytest.raises(InputError, match="unknown options"):
        mugs.fit_observation(zoo.Observation.from_depth(depth, k, pose, mask), iterations=3)


def _posed_train_mug(mugs, yaw: float, shift) -> PlacedObject:
    """hoi4d_mug_0001's own NeuralSDF surface, turned by ``yaw`` about z, its base on z = 0, moved by ``shift``."""
    from zoo.sim.surface import surface_mesh

    v, f = surface_mesh(mugs.shape("hoi4d_mug_0001"), resolution=96)
    c, s = math.cos(yaw), math.sin(yaw)
    v = v @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    v = v - [0.0, 0.0, v[:, 2].min()] + [*shift, 0.0]
    return PlacedObject("hoi4d_mug_0001", "mugs", v, f, yaw, float(np.linalg.norm(np.ptp(v, axis=0))))


@pytest.fixture(scope="module")
def posed(mugs):
    obj = _posed_train_mug(mugs, yaw=2.0, shift=(0.03, -0.02))
    obs, _ = observe(obj, 2, np.random.default_rng(3))
    return obj, obs, mugs.fit_observation(obs, seed=0)


def test_a_posed_train_mug_is_found_with_its_pose_and_size(posed):
    obj, obs, shape = posed
    errors = surface_errors(shape, obj, samples=5000)
    assert 0.5 * (errors["fit_to_true_p50"] + errors["true_to_fit_p50"]) < 0.01
    assert errors["scale_error"] < 0.1
    assert errors["yaw_error_deg"] < 15.0
    fit = shape.fit
    assert fit["observation"]["points"] == len(obs) and fit["observation"]["views"] == 2
    assert fit["residual_mm"]["median"] < 1.0
    assert len(fit["rejected"]) == fit["options"]["yaws"] - 1  # every other starting yaw, with its loss
    assert all(r["search_loss"] >= 0 for r in fit["rejected"])
    assert set(fit["loss"]) >= {"total", "surface", "free_space", "support", "prior"}


def test_the_fit_beats_its_baselines_on_a_posed_train_mug(mugs, posed):
    obj, obs, shape = posed
    ours = surface_errors(shape, obj, samples=5000)
    mean = surface_errors(mugs.fit_observation(obs, codes="mean"), obj, samples=5000)
    assert ours["true_to_fit_p50"] < mean["true_to_fit_p50"]


def test_a_fitted_shape_saves_and_loads_with_its_fit(posed, tmp_path):
    _, _, shape = posed
    path = shape.save(tmp_path / "seen.safetensors")
    back = zoo.load_shape(path)
    assert back.fit == json.loads(json.dumps(shape.fit))
    points = torch.rand(200, 3) * 0.2 - 0.1
    torch.testing.assert_close(back(points), shape(points))


def test_noise_and_outliers_do_not_break_the_fit(mugs):
    obj = _posed_train_mug(mugs, yaw=-1.0, shift=(0.0, 0.02))
    rng = np.random.default_rng(5)
    obs, _ = observe(obj, 2, rng, noise=0.002)
    lo, hi = obs.points.min(0) - 0.05, obs.points.max(0) + 0.05
    outliers = rng.uniform(lo, hi, size=(len(obs) // 20, 3))  # 5% stray returns around the object
    noisy = zoo.Observation(np.concatenate([obs.points, outliers]), np.concatenate([obs.origins, obs.origins[: len(outliers)]]),
                            free_origins=obs.free_origins, free_ends=obs.free_ends, views=2)
    shape = mugs.fit_observation(noisy)
    errors = surface_errors(shape, obj, samples=5000)
    assert 0.5 * (errors["fit_to_true_p50"] + errors["true_to_fit_p50"]) < 0.02


def test_points_without_sensor_origins_fit_too(mugs):
    obj = _posed_train_mug(mugs, yaw=0.5, shift=(0.0, 0.0))
    obs, _ = observe(obj, 3, np.random.default_rng(7))
    shape = mugs.fit_observation(zoo.Observation.from_points(obs.points), refine_iters=60)
    errors = surface_errors(shape, obj, samples=5000)
    assert errors["true_to_fit_p50"] < 0.01  # the seen surface is matched; the far side is the prior's


@pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)
def test_a_mug_seen_by_mujoco_rests_on_the_table_where_the_true_mesh_rests(tmp_path, mugs):
    """A never-seen (test split) mug, seen by MuJoCo's renderer from two cameras, fitted, attached as a free body in a
    MuJoCo model: after 0.4 s on a table it rests within 2 mm of the height at which MuJoCo rests the true mesh."""
    from zoo.offscreen import choose_gl

    if choose_gl() is None:
        pytest.skip("no offscreen OpenGL here (MUJOCO_GL=egl, or osmesa with Debian's libosmesa6)")
    import mujoco

    import zoo.sim
    from sdfzoo.benches.see_and_hang import see

    seen = see(tmp_path, "hoi4d_mug_0047")
    assert seen.renderer == "MuJoCo's renderer"
    shape = mugs.fit_observation(seen.observation)
    centre = shape.fit["pose"]["centre_m"]
    trimesh.Trimesh(seen.vertices, seen.faces, process=False).export(tmp_path / "true.stl")

    def settled_height(body_geom: str, asset: str = "") -> tuple[float, float]:
        xml = f"""<mujoco><option timestep="0.002"/><asset>{asset}</asset><worldbody>
          <geom name="table" type="plane" size="1 1 0.1"/>
          <body name="mug" pos="0 0 0.005"><freejoint/>{body_geom}</body></worldbody></mujoco>"""
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        world = zoo.sim.attach(model, {"mug": shape}) if "contype" in body_geom else None
        for _ in range(200):
            world.step(data) if world is not None else mujoco.mj_step(model, data)
        tilt = math.degrees(math.acos(min(1.0, float(data.xmat[1].reshape(3, 3)[2, 2]))))
        return float(data.xpos[1][2]), tilt

    true_z, true_tilt = settled_height('<geom type="mesh" mesh="true" mass="0.3"/>',
                                       f'<mesh name="true" file="{tmp_path / "true.stl"}" inertia="convex"/>')
    fitted_z, fitted_tilt = settled_height(f'<geom type="sphere" size="0.01" pos="{centre[0]} {centre[1]} {centre[2]}" '
                                           'contype="0" conaffinity="0" mass="0.3"/>')
    assert true_tilt < 3.0 and fitted_tilt < 3.0  # both stand on their base
    assert abs(fitted_z - true_z) < 2e-3


def test_fit_codes_takes_depth_images_and_points_on_the_command_line(tmp_path, posed):
    from typer.testing import CliRunner

    from sdfzoo.cli.main import app, register_commands

    register_commands()
    obj, _, _ = posed
    images = depth_views.render(depth_views.with_table(obj.vertices, obj.faces),
                                depth_views.table_views([0.03, -0.02, 0.04], 2, np.random.default_rng(1)))
    np.savez(tmp_path / "seen.npz", depth=images.depth, K=images.K, T_world_camera=images.T_world_camera, mask=images.mask)
    out = tmp_path / "seen.safetensors"
    result = CliRunner().invoke(app, ["fit-codes", "mugs", "--depth", str(tmp_path / "seen.npz"), "--out", str(out),
                                      "--no-progress"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output[result.output.index("{"):])
    assert summary["observation"]["views"] == 2 and summary["residual_mm"]["median"] < 1.0
    assert zoo.load_shape(out).fit["observation"]["views"] == 2
    cloud = trimesh.PointCloud(zoo.Observation.from_depth(images.depth, images.K, images.T_world_camera, images.mask).points)
    cloud.export(tmp_path / "seen.ply")
    result = CliRunner().invoke(app, ["fit-codes", "mugs", "--points", str(tmp_path / "seen.ply"), "--no-progress"])
    assert result.exit_code == 0, result.output
    result = CliRunner().invoke(app, ["fit-codes", "mugs", "--points", str(tmp_path / "seen.ply"), "--depth", "x.npz"])
    assert result.exit_code != 0


def test_the_category_prior_is_computed_once_and_read_back_from_its_cache(tmp_path, monkeypatch, mugs):
    from zoo import completion

    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))
    fresh = zoo.load("mugs")
    prior = completion.category_prior(fresh, resolution=12)
    assert list(tmp_path.glob("priors/mugs-*.npz"))
    # a node's value is the shape's own distance there
    nodes = torch.linspace(-completion.GRID_HALF_WIDTH, completion.GRID_HALF_WIDTH, 12)
    point = torch.stack([nodes[3], nodes[7], nodes[5]])[None]  # x, y, z of grid[z=5, y=7, x=3]
    torch.testing.assert_close(prior.grids[0, 5, 7, 3], fresh.shape(fresh.shapes[0]).normalised(point)[0], atol=1e-5, rtol=0)
    monkeypatch.setattr(completion, "_compute_prior", lambda *a: pytest.fail("the cached prior was computed again"))
    again = completion.category_prior(zoo.load("mugs"), resolution=12)
    torch.testing.assert_close(again.grids, prior.grids)


def test_a_tilted_fit_keeps_a_proper_rotation_near_upright(mugs, posed):
    obj, obs, _ = posed
    shape = mugs.fit_observation(obs, full_rotation=True, grid_iters=40, refine_iters=40, refine_hypotheses=1)
    r = shape.similarity.rotation
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-5)
    assert np.degrees(np.arccos(np.clip(r[2, 2], -1, 1))) < 10.0  # the mug stood upright: little tilt found
    assert surface_errors(shape, obj, samples=5000)["true_to_fit_p50"] < 0.01
