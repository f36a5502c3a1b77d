"""`zoo demo --observed`: see a never-seen mug with two depth cameras, fit it, hang the fitted shape on a rack.

1. A MuJoCo model holds a table and a test-split mug (from ``$ZOO_DATA``, never used in training) standing on it at
   a seeded yaw, and two cameras 0.5 m away, 30 degrees above the table, 100 degrees apart around it.
2. MuJoCo's renderer takes a depth and a segmentation image from each (640x480, depth noise 1 mm at 0.5 m growing
   with the depth squared): :meth:`zoo.Observation.from_mujoco`. Where no offscreen GL renders, the same images come
   from :mod:`sdfzoo.benches.depth_views`'s rasteriser, and the demo says so.
3. ``zoo.load("mugs").fit_observation`` fits codes, scale, yaw and position; the shape is saved.
4. A scene file hangs the fitted shape by its handle (found from the fitted SDF alone) on the procedural rack's
   peg (thinned to 80% of the handle's hole where that is narrower), released 1 cm above; ``zoo simulate`` runs it
   and writes the video.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zoo.errors import InputError
from zoo.observation import look_at

DEMO_MUG = "hoi4d_mug_0047"  # a test-split mug
MUG_SIZE = 0.12  # metres: the largest side of the mug as placed
CAMERAS = ("left", "right")


@dataclass
class Seen:
    """What the demo saw: the observation, the true mug (world vertices (V, 3), faces (F, 3)) and how it was rendered."""

    observation: object
    vertices: np.ndarray
    faces: np.ndarray
    renderer: str


def place_test_mug(stem: str = DEMO_MUG, seed: int = 0):
    """The test mug ``stem`` upright on the table (z = 0), ``MUG_SIZE`` across, at a seeded yaw -> PlacedObject."""
    from sdfzoo.pipeline.categories import load_category, resolve_data_dir
    from zoo.meshes import load_mesh

    from .completion import place

    category = load_category("mugs")
    entry = category.entry(stem)
    if entry.split != "test":
        raise InputError(f"{stem} is a {entry.split} mesh of the mugs model; the demo fits a never-seen (test) mug")
    mesh = load_mesh(resolve_data_dir(None, category) / entry.file)
    return place(mesh, entry.up, MUG_SIZE, np.random.default_rng(seed), stem, "mugs")


def camera_poses(target, distance: float = 0.5, elevation_deg: float = 30.0, azimuths_deg=(20.0, 120.0)) -> np.ndarray:
    """OpenCV T_world_camera (V, 4, 4) of cameras aimed at ``target`` (3,)."""
    e = math.radians(elevation_deg)
    poses = []
    for a in np.radians(azimuths_deg):
        eye = np.asarray(target) + distance * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        poses.append(look_at(eye, target))
    return np.stack(poses)


def scene_xml(mesh_file: Path, poses: np.ndarray, names=CAMERAS) -> str:
    """An MJCF of a table (its top at z = 0), the mug (a fixed, drawn-only mesh body "mug") and cameras at ``poses``
    (OpenCV T_world_camera; MuJoCo's camera looks along its -z with y up)."""
    cameras = []
    for name, pose in zip(names, poses):
        x, y = pose[:3, 0], -pose[:3, 1]
        cameras.append(f'<camera name="{name}" pos="{" ".join(map(repr, pose[:3, 3].tolist()))}" '
                       f'xyaxes="{" ".join(map(repr, [*x.tolist(), *y.tolist()]))}" fovy="45"/>')
    return f"""<mujoco model="see-a-mug">
  <visual><global offwidth="640" offheight="480"/></visual>
  <asset><mesh name="mug" file="{mesh_file}" inertia="shell"/></asset>
  <worldbody>
    <light pos="0 0 1.5" dir="0 0 -1"/>
    <geom name="table" type="box" size="0.4 0.4 0.02" pos="0 0 -0.02" rgba="0.6 0.5 0.4 1"/>
    <body name="mug"><geom type="mesh" mesh="mug" contype="0" conaffinity="0" rgba="0.9 0.9 0.95 1"/></body>
    {chr(10).join(cameras)}
  </worldbody>
</mujoco>"""


def see(out_dir: Path, stem: str = DEMO_MUG, seed: int = 0, noise: float = 0.001, log=print) -> Seen:
    """Steps 1 and 2 of the module docstring."""
    import trimesh

    import zoo
    from zoo.offscreen import choose_gl

    obj = place_test_mug(stem, seed)
    target = np.array([*obj.vertices[:, :2].mean(0), 0.5 * obj.vertices[:, 2].max()])
    poses = camera_poses(target)
    if choose_gl():
        import mujoco

        mesh_file = out_dir / f"{stem}-placed.stl"
        trimesh.Trimesh(obj.vertices, obj.faces, process=False).export(mesh_file)
        model = mujoco.MjModel.from_xml_string(scene_xml(mesh_file.resolve(), poses))
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        obs = zoo.Observation.from_mujoco(model, data, list(CAMERAS), body="mug", depth_noise=noise, seed=seed)
        return Seen(obs, obj.vertices, obj.faces, "MuJoCo's renderer")
    from . import depth_views

    log("no OpenGL for MuJoCo's offscreen renderer (MUJOCO_GL=egl, or osmesa with Debian's libosmesa6): the depth "
        "images come from sdfzoo's own rasteriser instead")
    k = depth_views.intrinsics(focal=0.5 * depth_views.HEIGHT / math.tan(math.radians(22.5)))
    images = depth_views.render(depth_views.with_table(obj.vertices, obj.faces), poses, k)
    depth = depth_views.sensor_noise(images.depth, np.random.default_rng(seed), noise)
    obs = zoo.Observation.from_depth(depth, images.K, images.T_world_camera, images.mask)
    return Seen(obs, obj.vertices, obj.faces, "sdfzoo's rasteriser")


def hanging_scene(shape_file: Path, shape, lift: float = 0.01, seconds: float = 0.4) -> dict:
    """A simulation scene (as a dict for TOML) that hangs ``shape`` (saved in ``shape_file``) by its handle on the
    procedural rack scaled to it, released ``lift`` above the hanging pose."""
    from .demo import rack_for

    rack, pose = rack_for(shape, fit_peg=True)  # a fitted handle's hole may be narrower than the train mugs'
    pose[2, 3] += lift
    return {
        "name": "observed-mug-rack", "method": "amortized", "margin": 0.001,
        "sim": {"dt": 0.002, "seconds": seconds, "friction": 1.0, "solref": [0.02, 1.0],
                "camera": {"lookat": [0.04, 0.0, 0.6 * rack["height"]], "distance": 2.2 * rack["height"], "azimuth": 120.0,
                           "elevation": -15.0}},
        "bodies": [
            {"name": "mug", "sdf": {"codes": shape_file.name}, "mass": 0.3, "joint": "free", "pose": pose.tolist()},
            {"name": "rack", "mesh": {"procedural": "rack", "params": rack}, "joint": "fixed"},
        ],
    }


def prepare(out_dir: str | Path = "out/observed", stem: str = DEMO_MUG, seed: int = 0, log=print) -> Path:
    """Steps 1-4 up to the scene file: -> the path of the scene ``zoo simulate`` runs."""
    import zoo
    from sdfzoo.pipeline.package import dumps_toml, toml_safe

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seen = see(out_dir, stem, seed, log=log)
    log(f"saw {stem} from {seen.observation.views} cameras ({seen.renderer}): {len(seen.observation)} points")
    shape = zoo.load("mugs").fit_observation(seen.observation, seed=seed, name=f"observed_{stem}")
    fit = shape.fit
    log(f"fitted in {fit['seconds']:.1f} s from {fit['pose']['start_shape']}: size {1e3 * fit['scale']['size_m']:.1f} mm, "
        f"yaw {fit['pose']['refined_yaw_deg']:.1f} deg, residual at the points {fit['residual_mm']['median']:.2f} mm "
        f"(median), {fit['residual_mm']['p90']:.2f} mm (p90)")
    shape_file = shape.save(out_dir / f"observed_{stem}.safetensors")
    scene = hanging_scene(Path(shape_file), shape)
    path = out_dir / "observed-mug-rack.toml"
    path.write_text(dumps_toml(toml_safe(scene), header="written by `zoo demo --observed`: a mug fitted from two depth "
                                                       "images, hung on the rack"))
    (out_dir / "observed-fit.json").write_text(json.dumps(fit, indent=1) + "\n")
    log(f"wrote {shape_file} and {path}")
    return path
