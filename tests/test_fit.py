"""NeuralSDF training: it learns, it resumes exactly, and `zoo fit-category` survives kill -9."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from real_meshes import SKIP_REASON, zoo_data

from sdfzoo.pipeline.fit_sdf import FitConfig, fit_sdf, stack_samples, step_batch
from sdfzoo.pipeline.training import CheckpointWarning
from zoo.neural import NeuralSDFConfig

ROOT = Path(__file__).resolve().parents[1]
TINY = FitConfig(sdf=NeuralSDFConfig(n_codes=8, code_dim=8, hidden=(16, 16)), steps=30, shapes_per_step=2,
                 points_per_shape=128, checkpoint_every=5, lr_decoder=3e-3, lr_codes=1e-2, seed=3)


def sphere_data(radii=(0.2, 0.3, 0.4), n=2000, seed=0):
    """Exact SDF samples of spheres of the given radii, in the normalised frame."""
    rng = np.random.default_rng(seed)
    pts = [rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32) for _ in radii]
    sdf = [np.linalg.norm(p, axis=1) - r for p, r in zip(pts, radii)]
    return stack_samples([f"sphere{i}" for i in range(len(radii))], pts, sdf)


def test_batches_depend_only_on_seed_and_step():
    data = sphere_data()
    a = step_batch(data, TINY, 7)
    b = step_batch(data, TINY, 7)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    # each of two processes takes a batch of its own size: together, a one-process batch twice as large
    r0, r1 = step_batch(data, TINY, 7, 0, 2), step_batch(data, TINY, 7, 1, 2)
    assert len(r0[0]) == len(r1[0]) == TINY.shapes_per_step
    four = sphere_data(radii=(0.1, 0.2, 0.3, 0.4))
    whole = step_batch(four, replace(TINY, shapes_per_step=4), 7)
    r0, r1 = step_batch(four, TINY, 7, 0, 2), step_batch(four, TINY, 7, 1, 2)
    for mine, rank in ((r0, 0), (r1, 1)):
        assert all(torch.equal(x, y[rank::2]) for x, y in zip(mine, whole))
    # more processes than shapes: each process's own shapes are distinct
    assert all(len(set(step_batch(data, TINY, s, r, 4)[0].tolist())) == 2 for s in range(5) for r in range(4))


def test_training_reduces_the_loss():
    torch.manual_seed(0)
    result = fit_sdf(sphere_data(), replace(TINY, steps=40), progress=False, log_every=5)
    losses = [loss for _, loss in result.history]
    assert losses[-1] < 0.5 * losses[0]


def test_resume_from_checkpoint_matches_an_uninterrupted_run(tmp_path):
    data = sphere_data()
    straight = fit_sdf(data, TINY, tmp_path / "a.pt", progress=False)
    # an interrupted run: the first 15 steps, then a fresh process resumes from the checkpoint
    partial = tmp_path / "b.pt"
    first = fit_sdf(data, TINY, partial, progress=False, log_every=10, stop_after=15)
    assert first.history[-1][0] == 10
    resumed = fit_sdf(data, TINY, partial, progress=False)
    assert resumed.resumed_from == 15
    for (k, v), (_, w) in zip(straight.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.allclose(v, w, atol=1e-6), k


def test_a_checkpoint_of_another_config_is_ignored(tmp_path):
    data = sphere_data()
    fit_sdf(data, replace(TINY, steps=10), tmp_path / "c.pt", progress=False)
    with pytest.warns(CheckpointWarning, match="another run"):  # not reused, and not silently
        other = fit_sdf(data, replace(TINY, steps=10, seed=4), tmp_path / "c.pt", progress=False)
    assert other.resumed_from == 0


def test_a_torn_checkpoint_warns_and_training_starts_afresh(tmp_path):
    """The one rule of pipeline.training for both training stages: an unreadable checkpoint is not
    resumed; a warning says so and the run restarts from step 0 (and ends where a fresh run does)."""
    data = sphere_data()
    fresh = fit_sdf(data, replace(TINY, steps=10), progress=False)
    torn = tmp_path / "torn.pt"
    fit_sdf(data, replace(TINY, steps=10), torn, progress=False)
    torn.write_bytes(torn.read_bytes()[:100])  # a half-written file (what a non-atomic writer would leave)
    with pytest.warns(CheckpointWarning, match="cannot be read"):
        again = fit_sdf(data, replace(TINY, steps=10), torn, progress=False)
    assert again.resumed_from == 0 and again.history == fresh.history
    for (k, v), w in zip(fresh.model.state_dict().items(), again.model.state_dict().values()):
        assert torch.equal(v, w), k
    assert fit_sdf(data, replace(TINY, steps=10), torn, progress=False).resumed_from == 10  # rewritten whole



@pytest.mark.slow
@pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)
def test_fit_category_quick_survives_kill_9(tmp_path):
    """Killed with SIGKILL mid-run, rerun finishes (resuming), a third run skips every stage."""
    env = {**os.environ, "ZOO_DATA": str(zoo_data()), "OMP_NUM_THREADS": "2"}
    cmd = [sys.executable, "-c", "import sys; from cli.main import main; main(sys.argv[1:])", "fit-category", "mugs", "--preset", "quick",
           "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"), "--no-progress"]
    checkpoint = tmp_path / "work" / "fit" / "quick" / "checkpoint.pt"
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.time() + 600  # generous: the shared CI machine can be heavily loaded
    while not checkpoint.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)  # kill as soon as training has checkpointed: the rerun must resume, not restart
    proc.send_signal(signal.SIGKILL)  # at once: on an idle machine the quick fit's 100 steps take about a second
    proc.wait()
    assert checkpoint.exists(), "no training checkpoint was written before the kill"
    assert not (tmp_path / "out" / "config.json").exists(), "the first run finished before it could be killed"

    second = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr
    assert "resuming from the checkpoint" in second.stderr

    third = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert third.returncode == 0, third.stderr
    from sdfzoo.pipeline.fit_category import STAGES

    assert third.stderr.count("up to date, skipped") == len(STAGES), third.stderr
    assert ": done (" not in third.stderr, third.stderr  # every stage skipped, none ran again

    import zoo

    model = zoo.load(tmp_path / "out")
    shape = model.shape(model.shapes[0])
    d = shape(torch.zeros(5, 3))
    assert d.shape == (5,) and torch.isfinite(d).all()


def test_steps_option_replaces_the_presets_training_length_and_is_recorded():
    from sdfzoo.pipeline.fit_category import PRESETS, fit_category
    from zoo.errors import InputError

    default = PRESETS.lookup("default")
    longer = replace(default, steps=123)
    assert default.fit_config(54).steps == 2000 and longer.fit_config(54).steps == 123  # from epochs, then replaced
    assert longer.fit_config(4).steps == 123
    # epochs: each shape's samples seen as often whatever the category's size or the number of processes
    for shapes, processes in ((54, 1), (20, 1), (5000, 1), (5000, 8)):
        steps = default.fit_config(shapes, processes).steps
        assert default.epochs_seen(steps, shapes, processes) == pytest.approx(default.epochs, rel=1e-3)
    assert default.fit_config(5000, 8).steps * 8 == pytest.approx(default.fit_config(5000).steps, abs=8)
    assert (default.options, longer.options) == ("--preset default", "--preset default --steps 123")
    with pytest.raises(InputError, match="steps"):
        fit_category("mugs", preset="quick", steps=0)


def test_samples_streamed_from_their_files_train_the_same_model(tmp_path):
    """SampleFiles reads a step's rows from HDF5 (in DataLoader workers or not): the fit is the in-memory fit."""
    from sdfzoo.pipeline.fit_sdf import SampleFiles, load_training_data
    from sdfzoo.pipeline.samples import ShapeSamples, write_samples
    from zoo.meshes import Similarity

    data = sphere_data(n=3000)
    files = [write_samples(tmp_path / f"{stem}.h5", ShapeSamples(stem, data.points[i, : int(data.counts[i])].numpy(),
                                                                  data.sdf[i, : int(data.counts[i])].numpy(),
                                                                  Similarity.identity()))
             for i, stem in enumerate(data.stems)]
    config = replace(TINY, steps=12)
    in_memory = fit_sdf(load_training_data(files), config, progress=False)
    for workers in (0, 1):
        streamed = fit_sdf(SampleFiles(files), config, progress=False, workers=workers)
        assert streamed.history == in_memory.history
        for (k, v), w in zip(in_memory.model.state_dict().items(), streamed.model.state_dict().values()):
            assert torch.equal(v, w), (workers, k)
    streamed = SampleFiles(files)
    rows = torch.tensor([[5, 2, 5, 2999]])
    points, sdf = streamed.batch(torch.tensor([1]), rows)
    assert torch.equal(points[0], data.points[1, rows[0]]) and torch.equal(sdf[0], data.sdf[1, rows[0]])
