"""`zoo fit-category` on a category of its user's own: many meshes, several processes, broken files.

The category is 24 deformed variants of six real mugs (benches.deformed) in .obj, .ply, .stl and .glb, plus
one truncated .ply; its manifest comes from `zoo manifest`. The same run on one process, on two (`--nproc 2`)
and on two torchrun launchers (`--nnodes 2`, rendezvous on localhost) must write the same per-mesh files,
set the truncated mesh aside with its reason, and give a package that loads by path and detects.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from real_meshes import SKIP_REASON, zoo_data

from sdfzoo.benches.deformed import build_deformed_category, smallest_meshes
from sdfzoo.pipeline.categories import load_category
from zoo.files import sha256_file

pytestmark = [pytest.mark.slow, pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)]

SOURCES = 6
VARIANTS = 4
TIMEOUT = 1200
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def zoo_cli(*args, cwd, check: bool = True, timeout: int = TIMEOUT) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "sdfzoo.cli", *map(str, args)], cwd=cwd, env=ENV,
                            capture_output=True, text=True, timeout=timeout)
    if check:
        assert result.returncode == 0, result.stderr[-4000:]
    return result


def fit_args(base: Path, name: str) -> list:
    return ["fit-category", base / "deformed.toml", "--preset", "quick", "--max-shapes", "0", "--no-progress",
            "--work", base / name / "work", "--out", base / name / "out"]


@pytest.fixture(scope="module")
def category(tmp_path_factory):
    base = tmp_path_factory.mktemp("deformed")
    built = build_deformed_category(smallest_meshes(zoo_data() / "mug", SOURCES), base / "meshes", VARIANTS)
    zoo_cli("manifest", base / "meshes", "deformed", "--out", base / "deformed.toml", "--test-fraction", "0", cwd=base)
    return base, built


@pytest.fixture(scope="module")
def runs(category):
    """{processes: the finished run's stderr} for one process and for two."""
    base, _ = category
    return {n: zoo_cli(*fit_args(base, f"nproc{n}"), "--nproc", n, cwd=base).stderr for n in (1, 2)}


def per_mesh_files(work: Path) -> dict[str, bytes]:
    """{relative path: bytes} of the per-mesh outputs (normalised meshes, their SDF samples, and the stages' locks;
    of a lock, all but the sdfzoo commit that wrote it, which is provenance and not a product of the run)."""
    files = sorted([*work.glob("normalised/*"), *work.glob("samples/*")])
    return {str(p.relative_to(work)): _without_provenance(p) if p.name.endswith(".lock.json") else p.read_bytes()
            for p in files}


def _without_provenance(lock: Path) -> bytes:
    record = json.loads(lock.read_text())
    record.pop("sdfzoo")
    return json.dumps(record, sort_keys=True).encode()


def test_the_manifest_lists_every_mesh_with_its_hash(category):
    base, built = category
    cat = load_category(base / "deformed.toml")
    assert len(cat.stems("train")) == SOURCES * VARIANTS + 1
    assert cat.data_dir == (base / "meshes").resolve()
    suffixes = {Path(e.file).suffix for e in cat.meshes.values()}
    assert {".obj", ".ply", ".stl", ".glb"} <= suffixes
    for entry in cat.meshes.values():
        assert sha256_file(base / "meshes" / entry.file) == entry.sha256
    assert set(cat.sources) == {"cad", "scans"}


def test_one_and_two_processes_write_the_same_per_mesh_files(category, runs):
    base, _ = category
    one, two = per_mesh_files(base / "nproc1" / "work"), per_mesh_files(base / "nproc2" / "work")
    assert len(one) == 5 * SOURCES * VARIANTS  # every mesh but the truncated one: .npz, .json, .h5 and two locks
    assert one.keys() == two.keys()
    assert [k for k in one if one[k] != two[k]] == []


def test_the_truncated_mesh_is_set_aside_with_its_reason(category, runs):
    base, built = category
    stem = "scans_broken_download"
    for n, stderr in runs.items():
        assert f"{stem} at samples: DataError" in stderr and "unexpected length" in stderr, stderr[-3000:]
        listed = json.loads((base / f"nproc{n}" / "work" / "set-aside.json").read_text())
        assert [row["stem"] for row in listed] == [stem] and listed[0]["stage"] == "samples"
        config = json.loads((base / f"nproc{n}" / "out" / "config.json").read_text())
        assert [row["stem"] for row in config["training_data"]["set_aside"]] == [stem]
        assert stem not in config["shapes"] and len(config["shapes"]) == SOURCES * VARIANTS
    from sdfzoo.pipeline.package import model_card, training_data

    config = json.loads((base / "nproc2" / "out" / "config.json").read_text())
    entry = {"config": {"shapes": len(config["shapes"])}, "parameters": {"sdf": 1}, "category": "deformed",
             "date": "today", "license": "unspecified", "metrics": {}, "metrics_command": "zoo fit-category",
             "training_data": training_data(config, "deformed"), "files": {}}
    card = model_card("deformed", "0.1.0", config, entry, [])
    assert f"| {stem} | samples | DataError" in card


def test_the_package_loads_by_path_and_detects(category, runs):
    import zoo
    from zoo.solvers import frank_wolfe

    base, _ = category
    model = zoo.load(base / "nproc2" / "out")
    shape = model.shape(model.shapes[0])
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in shape.bounds)
    g = torch.Generator().manual_seed(0)
    centres = lo + (hi - lo) * torch.rand(64, 1, 3, generator=g)
    triangles = centres + 0.05 * float((hi - lo).max()) * torch.randn(64, 3, 3, generator=g)
    bary = model.detect(shape, triangles)
    assert bary.shape == (64, 3) and torch.isfinite(bary).all()
    assert torch.allclose(bary.sum(-1), torch.ones(64), atol=1e-5) and (bary >= -1e-6).all()
    # the detector's minima are no worse than a few Frank-Wolfe steps' (the slow, obviously-correct search)
    found = shape((bary.unsqueeze(-1) * triangles).sum(1))
    reference = shape((frank_wolfe(shape, triangles, iters=100).unsqueeze(-1) * triangles).sum(1))
    assert float((found - reference).median()) < 1e-3 * float((hi - lo).max())


def test_strict_stops_at_the_first_broken_mesh(category):
    base, _ = category
    result = zoo_cli(*fit_args(base, "strict"), "--strict", cwd=base, check=False)
    assert result.returncode != 0 and "broken_download" in result.stderr and "unexpected length" in result.stderr


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_torchrun_launchers_write_the_same_per_mesh_files(category, runs):
    """Two machines, as torchrun sees them: two launchers of one process each, meeting on localhost."""
    base, _ = category
    port = free_port()
    launchers = [subprocess.Popen([sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
                                   "--node-rank", str(rank), "--master-addr", "127.0.0.1", "--master-port", str(port),
                                   "-m", "sdfzoo.cli", *map(str, fit_args(base, "nodes2"))],
                                  cwd=base, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for rank in (0, 1)]
    outputs = [p.communicate(timeout=TIMEOUT) for p in launchers]
    assert [p.returncode for p in launchers] == [0, 0], outputs[0][1][-3000:] + outputs[1][1][-3000:]
    one, nodes = per_mesh_files(base / "nproc1" / "work"), per_mesh_files(base / "nodes2" / "work")
    assert one.keys() == nodes.keys() and [k for k in one if one[k] != nodes[k]] == []
    # two processes are two processes, on one machine or two: the same training, the same labelled triangles
    assert_same_triangles(base / "nproc2" / "work", base / "nodes2" / "work")
    for weights in ("sdf.safetensors", "detector.safetensors"):
        assert sha256_file(base / "nproc2" / "out" / weights) == sha256_file(base / "nodes2" / "out" / weights), weights


def triangles(work: Path) -> dict[str, np.ndarray]:
    import h5py

    with h5py.File(work / "triangles" / "quick.h5", "r") as f:
        return {k: f[k][...] for k in ("vertices", "features", "vertex_sdf", "bary", "min_sdf", "shape_index")}


def assert_same_triangles(a: Path, b: Path) -> None:
    x, y = triangles(a), triangles(b)
    assert [k for k in x if not np.array_equal(x[k], y[k])] == []


def worker_pids(launcher_pid: int) -> list[int]:
    """The processes torchrun started for a `zoo fit-category --nproc` run (they carry LOCAL_RANK)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            environ = (proc / "environ").read_bytes().split(b"\0")
            cmdline = (proc / "cmdline").read_bytes()
        except OSError:
            continue
        if b"sdfzoo.cli" in cmdline and any(v.startswith(b"LOCAL_RANK=") for v in environ) and _descends(proc, launcher_pid):
            pids.append(int(proc.name))
    return pids


def _descends(proc: Path, ancestor: int) -> bool:
    pid = int(proc.name)
    while pid > 1:
        if pid == ancestor:
            return True
        try:
            pid = int((Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            return False
    return False


def test_a_rank_killed_while_labelling_triangles_resumes_to_the_same_files(category, runs):
    base, _ = category
    work = base / "killed" / "work"
    shutil.copytree(base / "nproc2" / "work", work, ignore=shutil.ignore_patterns("triangles", "detector"))
    command = [sys.executable, "-m", "sdfzoo.cli", *map(str, fit_args(base, "killed")), "--nproc", "2"]
    chunks = work / "triangles" / "quick.h5.chunks"
    proc = subprocess.Popen(command, cwd=base, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + TIMEOUT
    while time.time() < deadline and proc.poll() is None and len(list(chunks.glob("*.h5"))) < 4:
        time.sleep(0.02)
    done_before = len(list(chunks.glob("*.h5")))
    workers = worker_pids(proc.pid)
    assert len(workers) == 2 and 0 < done_before < SOURCES * VARIANTS, (workers, done_before)
    os.kill(workers[1], signal.SIGKILL)
    proc.communicate(timeout=TIMEOUT)
    assert proc.returncode != 0 and not (work / "triangles" / "quick.h5").exists()
    again = zoo_cli(*fit_args(base, "killed"), "--nproc", "2", cwd=base)
    assert "sample-triangles: done" in again.stderr and "fit-sdf: up to date" in again.stderr
    assert_same_triangles(base / "nproc2" / "work", work)


def test_triangles_do_not_depend_on_the_number_of_processes(category, runs, tmp_path):
    """The triangle stage's per-mesh output for one fit, labelled on one process and shared out over two."""
    base, _ = category
    script = tmp_path / "label.py"
    script.write_text(LABEL_SCRIPT)
    model_dir, two = base / "nproc1" / "out", tmp_path / "two.h5"
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                             str(script), str(model_dir), str(two)], env=ENV, capture_output=True, text=True,
                            timeout=TIMEOUT)
    assert result.returncode == 0, result.stderr[-3000:]
    result = subprocess.run([sys.executable, str(script), str(model_dir), str(tmp_path / "one.h5")], env=ENV,
                            capture_output=True, text=True, timeout=TIMEOUT)
    assert result.returncode == 0, result.stderr[-3000:]
    import h5py

    with h5py.File(tmp_path / "one.h5", "r") as a, h5py.File(two, "r") as b:
        for key in ("vertices", "features", "vertex_sdf", "bary", "min_sdf", "shape_index"):
            assert np.array_equal(a[key][...], b[key][...]), key


LABEL_SCRIPT = """
import sys

import zoo
from sdfzoo.pipeline.distributed import join_world, leave_world
from sdfzoo.pipeline.per_mesh import for_each_mesh
from sdfzoo.pipeline.triangles import PRESETS, merge_triangle_chunks, write_shape_chunk

model, out = zoo.load(sys.argv[1]), sys.argv[2]
config = PRESETS["quick"]
world = join_world()
for_each_mesh(world, "label", model.shapes, lambda s: write_shape_chunk(s, model.shape(s), out, config), strict=True,
              progress=False)
world.barrier()
if world.main:
    merge_triangle_chunks(out, model.shapes, config)
leave_world(world)
"""


def test_editing_the_detector_reruns_neither_samples_nor_the_fit(tmp_path, monkeypatch):
    """The stages' code digests cover the modules they run: an edit of zoo/detector.py retrains the detector
    and leaves the samples and the NeuralSDF cached (on a copy of the sources, as the stages hash them)."""
    import sdfzoo.pipeline.stages as stages
    from sdfzoo.pipeline.fit_category import fit_category

    root = tmp_path / "project"
    for package in ("pipeline", "zoo"):
        shutil.copytree(stages.ROOT / package, root / package, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(stages, "ROOT", root)
    options = dict(preset="quick", work_dir=tmp_path / "work", out_dir=tmp_path / "out", progress=False, log=lambda _: None)
    first = fit_category("mugs", zoo_data(), **options)
    assert all(first.ran.values())
    detector = root / "zoo" / "detector.py"
    detector.write_text(detector.read_text() + "\n\ndef an_edit():\n    return 1\n")
    again = fit_category("mugs", zoo_data(), **options)
    assert not again.ran["samples"] and not again.ran["fit-sdf"] and not again.ran["sample-triangles"]
    assert again.ran["train-detector"]  # it runs the detector's code
