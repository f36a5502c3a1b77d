"""zoo.sim.animation: the GIF `zoo simulate` writes of the bodies and their contacts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("matplotlib")
iio = pytest.importorskip("imageio.v3")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from zoo.sim.animation import frame_steps  # noqa: E402
from zoo.sim.record import Recorder  # noqa: E402

STEPS = 20
ROOT = Path(__file__).resolve().parent.parent


def small_plane(half: float = 0.15):
    """A 30 cm square in z = 0 as 2 triangles: (V (4, 3), F (2, 3))."""
    v = np.array([(-half, -half, 0), (half, -half, 0), (half, half, 0), (-half, half, 0)], dtype=np.float64)
    return v, np.array([(0, 1, 2), (0, 2, 3)])


@pytest.fixture(scope="module")
def dropped_sphere(tmp_path_factory):
    """A sphere released 4 mm above a small plane, 20 steps recorded and written: (recorder, paths)."""
    sim = zoo.sim.Simulation(dt=0.002, method="fw")
    sim.name = "drop"
    sim.add_body("ball", sdf=zoo.Sphere(radius=0.05), mass=1.0,
                 pose=np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.054], [0, 0, 0, 1]], dtype=float))
    sim.add_body("ground", mesh=small_plane(), joint="fixed")
    recorder = Recorder(sim)
    sim.run(STEPS * sim.dt, recorder)
    return recorder, recorder.write(tmp_path_factory.mktemp("sim"), {"test": "animation"})


def red(frame: np.ndarray) -> np.ndarray:
    """(H, W) bool: the contact markers' pure red (the sphere is blue, the plane grey)."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (r > 180) & (g < 80) & (b < 80)


def test_gif_has_a_frame_per_step_the_sphere_moves_and_contacts_are_red(dropped_sphere):
    recorder, paths = dropped_sphere
    assert paths["gif"].name == "drop.gif" and paths["gif"].stat().st_size > 0
    frames = iio.imread(paths["gif"], index=None)
    assert frames.shape[0] == STEPS and frames.shape[-1] == 3
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).sum(-1).astype(bool).mean() > 0.001  # it fell
    touching = [len(c) > 0 for c in recorder.contact_points]
    assert any(touching) and not all(touching)  # released above the plane, it lands within the run
    for frame, touches in zip(frames, touching):
        assert red(frame).any() == touches


def test_contacts_are_kept_in_the_trajectory(dropped_sphere):
    import h5py

    recorder, paths = dropped_sphere
    with h5py.File(paths["h5"]) as f:
        offsets, points = f["contacts/offsets"][:], f["contacts/points"][:]
    assert len(offsets) == STEPS + 1 and offsets[-1] == len(points) == sum(len(c) for c in recorder.contact_points)
    assert np.abs(points[:, 2]).max() < 2e-3  # on the plane


def test_frames_are_spread_over_the_run_and_capped():
    assert frame_steps(20, 60).tolist() == list(range(20))
    steps = frame_steps(1000, 60)
    assert len(steps) == 60 and steps[0] == 0 and steps[-1] == 999
    assert len(frame_steps(0)) == 0


@pytest.mark.parametrize("flag, gif", [(["--video", "gif"], True), (["--no-animation"], False)])
def test_zoo_simulate_writes_the_gif_unless_told_not_to(tmp_path, flag, gif):
    """A GIF with a frame per step (MuJoCo's renderer where GL renders, matplotlib where not; the output says which)."""
    from typer.testing import CliRunner

    from sdfzoo.cli import sim as _  # noqa: F401  (registers the command)
    from sdfzoo.cli.main import app, register_commands

    register_commands()
    result = CliRunner().invoke(app, ["simulate", str(ROOT / "scenes" / "ring-rack.toml"), "--seconds", "0.006", "--dt", "0.002",
                                      "--out", str(tmp_path), "--no-progress", *flag])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "ring-rack.png").exists() and (tmp_path / "ring-rack.gif").exists() == gif
    if gif:
        assert "MuJoCo's renderer" in result.output or "matplotlib" in result.output
        assert iio.imread(tmp_path / "ring-rack.gif", index=None).shape[0] == 3


def test_a_moving_mesh_on_a_fixed_sdf_ground_is_drawn(tmp_path):
    """The other way round: the mesh body moves (drawn per frame), the SDF body is a fixed ground (the still)."""
    import torch
    import trimesh

    sim = zoo.sim.Simulation(dt=0.002, method="fw")
    sim.name = "cube"
    sim.add_body("floor", sdf=zoo.Box(half_extents=torch.tensor([0.2, 0.2, 0.02])), joint="fixed")
    sim.add_body("cube", mesh=trimesh.creation.box(extents=(0.06, 0.06, 0.06)), mass=0.2,
                 pose=np.array([[1, 0, 0, 0.02], [0, 1, 0, 0], [0, 0, 1, 0.052], [0, 0, 0, 1]], dtype=float))
    recorder = Recorder(sim)
    sim.run(0.02, recorder)
    frames = iio.imread(recorder.write(tmp_path, {})["gif"], index=None)
    assert frames.shape[0] == 10
    r, g, b = (frames[..., i].astype(int) for i in range(3))
    assert ((b > r + 60) & (b > 120)).any(axis=(1, 2)).all()  # the ground's blue surface points in every frame
    grey = (np.abs(r - g) < 12) & (np.abs(g - b) < 12) & (r > 60) & (r < 200)  # the cube's shaded faces
    assert grey.sum(axis=(1, 2)).min() > 1000
    assert [red(f).any() for f in frames] == [len(c) > 0 for c in recorder.contact_points]
