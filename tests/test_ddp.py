"""Training under torchrun (gloo on CPU): two processes of B shapes a step follow one process of 2B."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sdfzoo.pipeline.fit_sdf import FitConfig, fit_sdf, load_training_data, preset
from sdfzoo.pipeline.samples import ShapeSamples, write_samples
from zoo.meshes import Similarity

ROOT = Path(__file__).resolve().parents[1]
# each process takes its own batch of 2 shapes: the two processes' 4 are the one process's batch of 4
CONFIG = {"sdf": {"n_codes": 8, "code_dim": 8, "hidden": [16, 16]}, "steps": 12, "shapes_per_step": 2,
          "points_per_shape": 64, "checkpoint_every": 4, "seed": 1}


def write_spheres(folder: Path) -> list[str]:
    rng = np.random.default_rng(0)
    paths = []
    for i, r in enumerate((0.15, 0.2, 0.25, 0.3)):
        pts = rng.uniform(-0.5, 0.5, (500, 3)).astype(np.float32)
        sdf = (np.linalg.norm(pts, axis=1) - r).astype(np.float32)
        paths.append(str(write_samples(folder / f"s{i}.h5", ShapeSamples(f"s{i}", pts, sdf, Similarity.identity()))))
    return paths


def torchrun() -> list[str] | None:
    exe = Path(sys.executable).with_name("torchrun")
    return [str(exe)] if exe.exists() else ([shutil.which("torchrun")] if shutil.which("torchrun") else None)


@pytest.mark.slow
@pytest.mark.skipif(torchrun() is None, reason="torchrun is not installed")
def test_two_processes_agree_with_one(tmp_path):
    files = write_spheres(tmp_path)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    common = ["-m", "sdfzoo.pipeline.fit_sdf", *files, "--preset", "quick", "--config", json.dumps(CONFIG), "--threads", "1",
              "--no-progress"]
    two = subprocess.run([*torchrun(), "--standalone", "--nproc_per_node", "2", *common, "--out", str(tmp_path / "two.pt")],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert two.returncode == 0, two.stderr[-3000:]
    config = FitConfig.from_dict({**preset("quick").to_dict(), **CONFIG, "shapes_per_step": 4})
    one = fit_sdf(load_training_data(files), config, progress=False)  # the same run, one process
    a = {"history": one.history, "model": one.model.state_dict()}
    b = torch.load(tmp_path / "two.pt", weights_only=True)  # tensors, dicts, lists: no pickle
    losses_a = [loss for _, loss in a["history"]]
    losses_b = [loss for _, loss in b["history"]]
    assert np.allclose(losses_a, losses_b, rtol=1e-4, atol=1e-6), (losses_a, losses_b)
    for k, v in a["model"].items():
        assert torch.allclose(v, b["model"][k], atol=1e-5), k
