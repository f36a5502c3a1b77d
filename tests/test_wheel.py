"""What a user installs is the wheel: build it from this checkout, install it into a fresh environment
with only torch beside it (and the extras from the index), and run the README's flows from outside the
clone: models by name, the bundled scenes, the category manifests, the `zoo` command and `python -m`."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest
import torch
from real_meshes import SKIP_REASON, zoo_data

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ("mugs", "bottles", "gears", "bolts")

USE_THE_MODELS = """
import sys, torch, zoo, zoo.errors
names = {m["name"] for m in zoo.list_models()}
assert names >= set(sys.argv[1].split(",")), names
m = zoo.load("mugs")
assert "site-packages" in str(m.path), m.path
s = m.shape(m.shapes[0])
triangles = torch.rand(64, 3, 3, generator=torch.Generator().manual_seed(0)) * 0.05
bary = m.detect(s, triangles)
assert bary.shape == (64, 3), bary.shape
assert bool((bary >= 0).all()) and torch.allclose(bary.sum(1), torch.ones(64)), bary
assert not {"h5py", "sdfzoo", "mujoco", "huggingface_hub"} & {k.split(".")[0] for k in sys.modules}
from sdfzoo.pipeline import categories  # one copy of every module: the pipeline raises zoo's own errors
assert categories.InputError is zoo.errors.InputError
assert "mugs" in categories.list_categories(), categories.manifests_folder()
assert not {"cli", "pipeline", "benches"} & set(sys.modules)
print("ok", m.name, m.version)
"""


def _run(cmd: list[str], cwd: Path, env: dict, ok: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    if ok:
        assert result.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    return result


def _checkout_copy(target: Path) -> Path:
    """This checkout's files (tracked, and untracked but not ignored) without build/ or caches: a wheel built
    in the clone itself would also pick up modules left in its build/lib by an earlier build."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True, check=True)
    for name in filter(None, listed.stdout.decode().split("\0")):
        source = ROOT / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target / name)
    return target


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    source = _checkout_copy(tmp / "src")
    _run([sys.executable, "-m", "pip", "wheel", source, "--no-deps", "--no-build-isolation", "-q", "-w", tmp / "dist"], tmp, dict(os.environ))
    (built,) = (tmp / "dist").glob("sdfzoo-*.whl")
    return built


@pytest.fixture(scope="module")
def installed_wheel(wheel, tmp_path_factory):
    """A fresh virtual environment holding torch and the wheel with its extras (pipeline, sim)."""
    tmp = tmp_path_factory.mktemp("env")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ZOO_", "PYTHON", "VIRTUAL_ENV"))}
    venv.create(tmp / "env", with_pip=True)
    python = tmp / "env" / "bin" / "python"
    torch_version = torch.__version__.split("+")[0]
    _run([python, "-m", "pip", "install", "-q", f"torch=={torch_version}"], tmp, env)
    _run([python, "-m", "pip", "install", "-q", f"{wheel}[pipeline,sim]"], tmp, env)
    work = tmp / "elsewhere"  # not the clone: nothing may be read from it
    work.mkdir()
    return python, work, env


@pytest.mark.slow
def test_the_wheel_installs_only_the_projects_own_top_level_names(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"zoo", "sdfzoo"}, top  # no investigations/: it stays in the repository
    packages = {n.rsplit("/", 1)[0] for n in names if n.endswith(".py")}
    assert {"sdfzoo/cli", "sdfzoo/pipeline", "sdfzoo/benches", "zoo", "zoo/sim"} <= packages
    assert "zoo/data/manifests/categories/mugs.toml" in names and "zoo/data/scenes/demo-mug-rack.toml" in names


SIM_BENCH_FILES = """
import pathlib, zoo
from sdfzoo.benches import panda_scenarios, sim_bench, sim_references, sim_scenarios
package = pathlib.Path(zoo.__file__).parent
scenes = [sim_scenarios.SCENES / s.scene for s in sim_scenarios.SCENARIOS.values()]
scenes += [sim_references.SCENES / name for name in sim_references.SCENARIOS.values()]
scenes += [sim_scenarios.SCENES / name for name in sim_bench.SCENES.values()]
scenes += [panda_scenarios.SCENES / f"{name}.toml" for name in sim_bench.PANDA_SCENES] + [panda_scenarios.SCENES / "panda.xml"]
assert all(path.is_file() and path.is_relative_to(package) for path in scenes), scenes
assert not sim_references.CACHE.resolve().is_relative_to(package.parent), sim_references.CACHE.resolve()
print("ok", len(scenes))
"""


@pytest.mark.slow
def test_the_wheels_sim_benches_read_the_bundled_scenes_and_cache_outside_the_package(installed_wheel):
    """`zoo bench --sim`'s scenarios and references find their scene files in the wheel, and CoACD's cache is
    written under the working folder, never into site-packages."""
    python, work, env = installed_wheel
    assert _run([python, "-c", SIM_BENCH_FILES], work, env).stdout.startswith("ok ")


@pytest.mark.slow
def test_the_wheel_lists_loads_and_detects(installed_wheel):
    python, work, env = installed_wheel
    out = _run([python, "-c", USE_THE_MODELS, ",".join(RELEASED)], work, env).stdout
    assert out.startswith("ok mugs ")


@pytest.mark.slow
def test_the_wheels_zoo_command_runs_the_readme_flows_on_bundled_data(installed_wheel):
    python, work, env = installed_wheel
    zoo_command = python.parent / "zoo"
    listing = _run([zoo_command, "list"], work, env).stdout
    assert all(name in listing for name in RELEASED)
    assert "mugs" in _run([python, "-m", "sdfzoo.cli", "list"], work, env).stdout
    assert "## Load it" in _run([zoo_command, "info", "mugs"], work, env).stdout  # the model card itself

    collided = _run([zoo_command, "collide", "demo-mug-rack", "--out", work / "scenes"], work, env).stdout
    assert "contacts from" in collided and "depth (mm)" in collided
    assert (work / "scenes" / "demo-mug-rack.json").is_file() and (work / "scenes" / "demo-mug-rack.png").is_file()

    simulated = _run([zoo_command, "simulate", "sim-demo-mug-rack", "--seconds", "0.01", "--no-animation", "--no-progress",
                      "--out", work / "sim"], work, env).stdout
    assert "steps" in simulated and list((work / "sim").glob("*.h5"))

    import trimesh

    trimesh.creation.annulus(r_min=0.03, r_max=0.04, height=0.09).export(work / "cup.obj")
    fitted = _run([zoo_command, "fit-codes", "mugs", work / "cup.obj", "--iters", "20", "--no-progress"], work, env).stdout
    assert '"near_p50"' in fitted

    import numpy as np

    from sdfzoo.benches import depth_views

    cup = trimesh.creation.annulus(r_min=0.035, r_max=0.04, height=0.09)
    cup.apply_translation([0.0, 0.0, 0.045])  # standing on the table, z = 0
    images = depth_views.render(depth_views.with_table(np.asarray(cup.vertices), np.asarray(cup.faces)),
                                depth_views.table_views([0.0, 0.0, 0.045], 2, np.random.default_rng(0)))
    np.savez(work / "seen.npz", depth=images.depth, K=images.K, T_world_camera=images.T_world_camera, mask=images.mask)
    seen = _run([zoo_command, "fit-codes", "mugs", "--depth", work / "seen.npz", "--out", work / "seen.safetensors",
                 "--no-progress"], work, env).stdout
    assert '"residual_mm"' in seen and (work / "seen.safetensors").is_file()


@pytest.mark.slow
def test_the_wheels_zoo_package_refuses_to_write_into_site_packages(installed_wheel):
    python, work, env = installed_wheel
    site = Path(_run([python, "-c", "import zoo, pathlib; print(pathlib.Path(zoo.__file__).parent)"], work, env).stdout.strip())
    before = sorted(p for p in site.rglob("*") if "__pycache__" not in p.parts)
    refused = _run([python.parent / "zoo", "package", "mugs", "--version", "9.9.9"], work, env, ok=False)
    assert refused.returncode == 2 and "$ZOO_PRETRAINED" in refused.stderr and "Traceback" not in refused.stderr
    assert sorted(p for p in site.rglob("*") if "__pycache__" not in p.parts) == before


@pytest.mark.slow
@pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)
def test_the_wheels_zoo_fit_category_finds_the_category_by_name(installed_wheel):
    python, work, env = installed_wheel
    env = {**env, "ZOO_DATA": str(zoo_data())}
    out = work / "mugs-q"
    _run([python.parent / "zoo", "fit-category", "mugs", "--preset", "quick", "--out", out, "--work", work / "runs",
          "--no-progress"], work, env)
    loaded = _run([python, "-c", "import sys, zoo; m = zoo.load(sys.argv[1]); print(len(m.shapes))", out], work, env).stdout
    assert int(loaded) == 4
