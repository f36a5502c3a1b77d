"""What a user installs is the wheel: build it, install it into a fresh environment with only
torch beside it, and use the models and the bundled demo scene from outside the clone."""

from __future__ import annotations

import os
import subprocess
import sys
import venv
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ("mugs", "bottles", "gears", "bolts")

USE_THE_MODELS = """
import sys, torch, zoo
names = {m["name"] for m in zoo.list_models()}
assert names >= set(sys.argv[1].split(",")), names
m = zoo.load("mugs")
assert "site-packages" in str(m.path), m.path
s = m.shape(m.shapes[0])
triangles = torch.rand(64, 3, 3, generator=torch.Generator().manual_seed(0)) * 0.05
bary = m.detect(s, triangles)
assert bary.shape == (64, 3), bary.shape
assert bool((bary >= 0).all()) and torch.allclose(bary.sum(1), torch.ones(64)), bary
assert not {"h5py", "pipeline", "mujoco", "huggingface_hub"} & {k.split(".")[0] for k in sys.modules}
print("ok", m.name, m.version)
"""


def _run(cmd: list[str], cwd: Path, env: dict) -> str:
    result = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, f"{' '.join(cmd)} failed:\n{result.stdout}\n{result.stderr}"
    return result.stdout


@pytest.fixture(scope="module")
def installed_wheel(tmp_path_factory):
    """A fresh virtual environment holding torch and the wheel built from this checkout."""
    tmp = tmp_path_factory.mktemp("wheel")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ZOO_", "PYTHON", "VIRTUAL_ENV"))}
    _run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp / "dist")], tmp, env)
    (wheel,) = (tmp / "dist").glob("sdfzoo-*.whl")
    venv.create(tmp / "env", with_pip=True)
    python = tmp / "env" / "bin" / "python"
    torch_version = torch.__version__.split("+")[0]
    _run([str(python), "-m", "pip", "install", "-q", f"torch=={torch_version}"], tmp, env)
    _run([str(python), "-m", "pip", "install", "-q", str(wheel)], tmp, env)
    work = tmp / "elsewhere"  # not the clone: nothing may be read from it
    work.mkdir()
    return python, work, env


@pytest.mark.slow
def test_the_wheel_lists_loads_and_detects(installed_wheel):
    python, work, env = installed_wheel
    out = _run([str(python), "-c", USE_THE_MODELS, ",".join(RELEASED)], work, env)
    assert out.startswith("ok mugs ")


@pytest.mark.slow
def test_the_wheels_zoo_command_lists_every_release_and_collides_the_demo_scene(installed_wheel):
    python, work, env = installed_wheel
    zoo_command = str(python.parent / "zoo")
    listing = _run([zoo_command, "list"], work, env)
    for name in RELEASED:
        assert name in listing
    collided = _run([zoo_command, "collide", "demo-mug-rack", "--out", str(work / "scenes")], work, env)
    assert "contacts" in collided
    assert (work / "scenes").is_dir()
