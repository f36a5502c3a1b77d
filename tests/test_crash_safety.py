"""Crash safety of `zoo fit-category`: SIGKILL at a random point inside every stage, then rerun.

For each stage of :data:`pipeline.fit_category.STAGES`, `zoo fit-category mugs --preset quick`
runs in a subprocess and is killed with SIGKILL a random time after that stage is seen to start.
Starts are found by polling, no hook in the code: the first stage's by its first file appearing
in the work directory, every later stage's by the log line of the stage before it ("NAME: done
(..)" or "NAME: up to date, skipped (..)", printed as that stage returns). The delay is a
fraction, drawn from a seeded RNG, of the stage's duration in an uninterrupted reference run
(one run shared by all cases), so the kill lands inside the stage; a kill that came too late
(the stage had already logged, e.g. because the machine sped up) is retried with a shorter delay.

To keep the test to minutes, a case for stage k does not recompute stages 1..k-1: it starts
from a copy of the reference run's directories as they were when stage k-1 had just finished
(copied while the reference process was stopped with SIGSTOP), so stages 1..k-1 are cached, as
in a rerun. The case for the first stage starts from nothing.

After the kill, no final file may be partial or corrupt: every file but the atomic writers'
hidden temporaries reads in full, a deterministic output that exists already equals the
reference's, every stage lock names outputs that match it, and a SHA256SUMS that exists
verifies. Then a rerun finishes, skips the stages finished before the kill, and leaves exactly
the reference's files with the reference's contents: arrays and weights bit for bit (HDF5 by
datasets and attributes, not bytes), JSON and checkpoints without timing fields, the package's
SHA256SUMS verified and equal for every weights file, and no leftover in the package directory.

All runs use one OpenMP thread: on the shared two-core machine two threads per process made the
quick preset up to six times slower under load, and one thread keeps float reductions in one order.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from real_meshes import SKIP_REASON, zoo_data

from sdfzoo.pipeline.fit_category import RUN_REPORT_FILE
from zoo.files import CHECKSUMS, read_checksums, sha256_file, verify_directory

ROOT = Path(__file__).resolve().parents[1]
SEED = 7  # fixes every stage's kill point (a fraction of its reference duration)
ATTEMPTS = 4  # a kill that lands after the stage ended is retried with half the delay, then none
TIMEOUT = 600  # seconds per run: the shared CI machine can be heavily loaded
DONE = re.compile(r"^(?P<stage>[\w-]+): (?P<what>done|up to date, skipped) \(")
TIMING_KEYS = re.compile(r"(^|_)(seconds|elapsed|us_per_point)$")  # fit_seconds, query_us_per_point, ...



def stage_names() -> list[str]:
    from sdfzoo.pipeline.fit_category import STAGES

    return [name for name, _ in STAGES]


needs_meshes = pytest.mark.skipif(zoo_data() is None, reason=SKIP_REASON)


# --------------------------------------------------------------------------- one run in a subprocess


class FitProcess:
    """`zoo fit-category mugs --preset quick` writing under ``base`` (work/, out/); its log lines are timed.

    ``on_stage_end(process, stage)`` is called from the reader thread as soon as a stage's line is read.
    """

    def __init__(self, base: Path, on_stage_end=None):
        self.base, self.work, self.out = base, base / "work", base / "out"
        self.on_stage_end = on_stage_end
        env = {**os.environ, "ZOO_DATA": str(zoo_data()), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        cmd = [sys.executable, "-c", "import sys; from cli.main import main; main(sys.argv[1:])", "fit-category", "mugs",
               "--preset", "quick", "--out", str(self.out), "--work", str(self.work), "--no-progress"]
        self.lines: list[tuple[float, str]] = []  # (time.monotonic(), line) as read
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     bufsize=1)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))
            m = DONE.match(line)
            if m and self.on_stage_end is not None:
                self.on_stage_end(self, m["stage"])

    @property
    def log(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def finished(self) -> dict[str, tuple[float, str]]:
        """stage -> (time its line was read, "done" or "up to date, skipped")."""
        out = {}
        for t, line in list(self.lines):
            m = DONE.match(line)
            if m:
                out[m["stage"]] = (t, m["what"])
        return out

    def wait_stage_start(self, stage: str) -> float:
        """Poll until ``stage`` has started; return when that was seen (time.monotonic())."""
        names = stage_names()
        i = names.index(stage)
        deadline = time.monotonic() + TIMEOUT
        while time.monotonic() < deadline:
            if i == 0:
                if self.work.exists():  # the first stage's first file (a normalised mesh) is on its way
                    return time.monotonic()
            else:
                seen = self.finished().get(names[i - 1])
                if seen is not None:
                    return seen[0]
            if self.proc.poll() is not None:
                self._reader.join(5)
                raise AssertionError(f"the run ended (rc {self.proc.returncode}) before stage {stage} started:\n{self.log}")
            time.sleep(0.001)
        raise AssertionError(f"stage {stage} did not start within {TIMEOUT} s:\n{self.log}")

    def kill(self) -> int:
        self.proc.send_signal(signal.SIGKILL)
        rc = self.proc.wait()
        self._reader.join(5)
        return rc

    def wait(self) -> int:
        rc = self.proc.wait(TIMEOUT)
        self._reader.join(5)
        return rc


# --------------------------------------------------------------------------- reading and comparing outputs


def _is_temporary(path: Path) -> bool:
    """zoo.files.atomic_path's temporaries: hidden, beside their target, ``.NAME.XXXX.tmp``."""
    return path.name.startswith(".") and path.name.endswith(".tmp")


def final_files(directory: Path) -> dict[str, Path]:
    """Every file under ``directory`` but atomic writers' temporaries: {relative path: path}."""
    return {p.relative_to(directory).as_posix(): p for p in sorted(directory.rglob("*"))
            if p.is_file() and not _is_temporary(p)}


def copy_final_files(source: Path, target: Path) -> None:
    for rel, path in final_files(source).items():
        (target / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target / rel)


def normalise(obj, bases: tuple[str, ...]):
    """A comparable form: timing keys dropped, run directories replaced, tensors and arrays as bytes."""
    if isinstance(obj, dict):
        return {str(k): normalise(v, bases) for k, v in obj.items() if not TIMING_KEYS.search(str(k))}
    if isinstance(obj, (list, tuple)):
        return [normalise(v, bases) for v in obj]
    if isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().contiguous().numpy()
    if isinstance(obj, np.ndarray):
        return ("array", str(obj.dtype), obj.shape, np.ascontiguousarray(obj).tobytes())
    if isinstance(obj, bytes):
        obj = obj.decode()
    if isinstance(obj, str):
        try:  # JSON-valued HDF5 attributes hold paths and timings too
            parsed = json.loads(obj)
        except ValueError:
            parsed = None
        if isinstance(parsed, (dict, list)):
            return normalise(parsed, bases)
        for base in bases:
            obj = obj.replace(base, "<RUN>")
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def read_h5(path: Path, bases) -> dict:
    """Every dataset (read in full, so a truncated file fails) and every attribute of an HDF5 file."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, item):
            if isinstance(item, h5py.Dataset):
                out[f"{name}/"] = item[...]
            out[f"{name}@"] = dict(item.attrs)

        f.visititems(visit)
        out["@"] = dict(f.attrs)
    return normalise(out, bases)


def read_content(path: Path, bases: tuple[str, ...]):
    """The comparable content of an output file, by type; raises if the file is partial or corrupt."""
    if path.suffix == ".h5":
        return read_h5(path, bases)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return normalise({k: z[k] for k in z.files}, bases)
    if path.suffix == ".json":
        return normalise(json.loads(path.read_text()), bases)
    if path.suffix == ".pt":
        return normalise(torch.load(path, map_location="cpu", weights_only=True), bases)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        load_file(str(path))  # parses it in full
        return sha256_file(path)  # written byte for byte reproducibly: compare the bytes
    if path.name == CHECKSUMS:  # config.json holds timings (fit_seconds); every other file's hash must agree
        return {k: v for k, v in read_checksums(path.parent).items() if k != "config.json"}
    return sha256_file(path)


def is_deterministic(rel: str) -> bool:
    """Whether a file that exists must already equal the reference's. Checkpoints and per-shape
    triangle chunks are snapshots of unfinished work (only readable), the run report a record of the run
    (times, stages found cached); locks hold input hashes,
    and sdf.pt, an input of later stages, records its training time."""
    return (Path(rel).name not in ("checkpoint.pt", RUN_REPORT_FILE) and ".chunks/" not in rel
            and not rel.endswith(".lock.json"))


def check_locks(base: Path) -> None:
    """Each stage lock names outputs that exist beside it with the recorded sha256 (locks are written last)."""
    for lock in base.rglob("*.lock.json"):
        if _is_temporary(lock):
            continue
        record = json.loads(lock.read_text())
        hashes = {sha256_file(p) for p in lock.parent.iterdir() if p.is_file() and not _is_temporary(p)}
        for label, digest in record["outputs"].items():
            assert digest in hashes, f"{lock}: output {label!r} with sha256 {digest[:12]} is missing or changed"


def check_no_partial_files(base: Path, reference: dict, bases) -> None:
    """After a kill: every final file reads in full, and a deterministic one equals the reference's."""
    for rel, path in final_files(base).items():
        try:
            content = read_content(path, bases)
        except Exception as exc:  # noqa: BLE001 - any failure to read is the bug this looks for
            raise AssertionError(f"{rel} is partial or corrupt after SIGKILL: {type(exc).__name__}: {exc}") from exc
        if rel in reference and is_deterministic(rel):
            assert content == reference[rel], f"{rel} exists after SIGKILL but differs from the uninterrupted run's"
    check_locks(base)
    if (base / "out" / CHECKSUMS).is_file():
        verify_directory(base / "out")  # SHA256SUMS is written last: everything it lists is in place


def snapshot(base: Path, bases) -> dict:
    """{relative path: comparable content} of every final file of a finished run."""
    return {rel: read_content(path, bases) for rel, path in final_files(base).items()}


def assert_same_outputs(base: Path, reference: dict, bases) -> None:
    files = final_files(base)
    assert set(files) == set(reference), (f"files differ from the uninterrupted run's: extra {sorted(set(files) - set(reference))}, "
                                          f"missing {sorted(set(reference) - set(files))}")
    # the run report describes a run (its times, which stages it found cached), not what the run made
    different = [rel for rel, path in files.items() if not rel.endswith(".lock.json") and Path(rel).name != RUN_REPORT_FILE
                 and read_content(path, bases) != reference[rel]]
    assert not different, f"after kill and rerun these outputs differ from the uninterrupted run's: {different}"
    check_locks(base)
    verify_directory(base / "out")
    stray = sorted(p.name for p in (base / "out").iterdir() if f"out/{p.name}" not in files)
    assert not stray, f"the package directory holds leftovers of the killed run: {stray}"


# --------------------------------------------------------------------------- the reference run


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted run: its outputs, each stage's duration, and its directories after each stage."""
    base = tmp_path_factory.mktemp("reference")
    seeds = tmp_path_factory.mktemp("after")
    names = stage_names()
    pauses = {}

    def copy_at_stage_end(process, stage):
        if stage == names[-1]:
            return
        t0 = time.monotonic()
        os.kill(process.proc.pid, signal.SIGSTOP)  # nothing moves while the copy is taken
        try:
            copy_final_files(base, seeds / stage)
        finally:
            os.kill(process.proc.pid, signal.SIGCONT)
        pauses[stage] = time.monotonic() - t0

    t0 = time.monotonic()
    run = FitProcess(base, on_stage_end=copy_at_stage_end)
    start = run.wait_stage_start(names[0])
    assert run.wait() == 0, run.log
    finished = run.finished()
    assert list(finished) == names, run.log
    durations, t, previous = {}, start, None
    for name in names:
        durations[name] = finished[name][0] - t - pauses.get(previous, 0.0)
        t, previous = finished[name][0], name
    print(f"reference run: {time.monotonic() - t0:.1f} s; stages {({k: round(v, 3) for k, v in durations.items()})}")
    return {"base": base, "seeds": seeds, "files": snapshot(base, (str(base),)), "durations": durations}


@pytest.mark.slow
@needs_meshes
def test_reference_run_is_complete(reference):
    import zoo

    files = reference["files"]
    for rel in ("out/config.json", "out/sdf.safetensors", "out/detector.safetensors", f"out/{CHECKSUMS}",
                "work/fit/quick/sdf.pt", "work/fit/quick/metrics.json", "work/triangles/quick.h5",
                "work/detector/quick/detector.safetensors"):
        assert rel in files, sorted(files)
    model = zoo.load(reference["base"] / "out")
    assert model.detector is not None and len(model.shapes) == 4


@pytest.mark.slow
@needs_meshes
@pytest.mark.parametrize("stage", stage_names())
def test_sigkill_inside_stage_then_rerun_reproduces_the_outputs(stage, reference, tmp_path):
    names = stage_names()
    index = names.index(stage)
    duration = reference["durations"][stage]
    fraction = np.random.default_rng([SEED, index]).uniform(0.05, 0.95)
    t0 = time.monotonic()
    attempts = []
    for attempt in range(ATTEMPTS):
        base = tmp_path / f"attempt{attempt}"
        if index:  # stages before this one as the reference left them: cached
            copy_final_files(reference["seeds"] / names[index - 1], base)
        run = FitProcess(base)
        started = run.wait_stage_start(stage)
        # the last attempt kills as soon as the stage starts, so a stage far faster than in the reference is still hit
        delay = fraction * duration * 0.5**attempt if attempt < ATTEMPTS - 1 else 0.0
        time.sleep(max(0.0, started + delay - time.monotonic()))
        rc = run.kill()
        finished = run.finished()
        attempts.append(f"delay {delay:.3f} s of {duration:.3f} s: rc {rc}, finished {sorted(finished)}")
        if stage not in finished:
            break
        shutil.rmtree(base)  # the kill came after the stage ended (or the run did): again, earlier
    else:
        pytest.fail(f"could not kill inside stage {stage!r} in {ATTEMPTS} attempts: {attempts}")
    assert rc == -signal.SIGKILL, f"the run ended by itself (rc {rc}) instead of being killed:\n{run.log}"
    assert set(finished) == set(names[:index]), run.log
    left = len(final_files(base))
    bases = (str(base), str(reference["base"]))

    check_no_partial_files(base, reference["files"], bases)

    rerun = FitProcess(base)
    assert rerun.wait() == 0, rerun.log
    redone = rerun.finished()
    assert list(redone) == names, rerun.log
    for name in names[:index]:  # finished before the kill: cached, not redone
        assert redone[name][1] == "up to date, skipped", f"{name} was redone after a kill in {stage}:\n{rerun.log}"
    assert_same_outputs(base, reference["files"], bases)
    resumed = " (fit resumed from its checkpoint)" if "resuming from the checkpoint" in rerun.log else ""
    print(f"{stage}: killed {delay:.3f} s into it (reference {duration:.3f} s, attempt {attempt + 1}, {left} files "
          f"left), rerun{resumed} reproduced the outputs; {time.monotonic() - t0:.1f} s")


# --------------------------------------------------------------------------- what a killed run leaves must not outlive its inputs


def _tiny_detector_data(seed: int):
    import zoo
    from sdfzoo.pipeline.train_detector import TrainingData

    g = torch.Generator().manual_seed(seed)
    tri = torch.randn(16, 3, 3, generator=g) * 0.05 + 0.35
    sdf = zoo.Sphere(0.3)
    with torch.no_grad():
        vertex_sdf = sdf(tri.reshape(-1, 3)).reshape(16, 3)
    return TrainingData(tri, torch.randn(16, 3, 4, generator=g) * 0.05, torch.zeros(16, dtype=torch.long), [sdf], vertex_sdf)


def test_a_detector_checkpoint_of_other_training_data_is_not_resumed(tmp_path):
    """A checkpoint (here the final one of a finished run) of the same config but other data, e.g. a
    refitted NeuralSDF's features, used to be resumed: the stage then returned the old weights."""
    from dataclasses import replace

    from sdfzoo.pipeline.train_detector import preset, train

    base = preset("quick")
    config = replace(base, steps=6, batch_size=8, checkpoint_every=3, validate_every=100, validation_size=8,
                     detector={**base.detector, "feature_dim": 4, "hidden": 8, "weight_hidden": 4})
    old, _ = train(_tiny_detector_data(0), config, out_dir=tmp_path, progress=False)
    assert (tmp_path / "checkpoint.pt").is_file()
    new, history = train(_tiny_detector_data(1), config, out_dir=tmp_path, progress=False)
    fresh, fresh_history = train(_tiny_detector_data(1), config, progress=False)
    for (k, a), b in zip(new.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), k
    assert not all(torch.equal(a, c) for a, c in zip(new.state_dict().values(), old.state_dict().values()))
    assert history["loss"] == fresh_history["loss"]


def test_triangle_chunks_of_another_fit_are_not_reused(tmp_path):
    """Per-shape chunks a killed run leaves are reused only for the same fit (named in provenance)."""
    import zoo
    from sdfzoo.pipeline.triangle_sampling import sample_constrained_triangles
    from sdfzoo.pipeline.triangles import TriangleConfig, read_triangle_dataset, sample_triangle_dataset
    from zoo.neural import interpolate_codes

    class Shape:
        def __init__(self, sdf):
            g = torch.Generator().manual_seed(0)
            self.normalised, self.positions, self.codes = sdf, torch.rand(1, 8, 3, generator=g) - 0.5, torch.randn(1, 8, 4, generator=g)

        def features(self, points):
            return interpolate_codes(points.float().unsqueeze(0), self.positions, self.codes, 1e-16).squeeze(0)

    config = TriangleConfig(n_per_shape=16, n_reference=2, reference_resolution=4, fw_iters=10)
    out = tmp_path / "triangles.h5"

    def killed_after_first_shape(sdf, n, seed=0):
        if killed_after_first_shape.calls:
            raise KeyboardInterrupt  # stands in for SIGKILL: the first shape's chunk is on disk
        killed_after_first_shape.calls += 1
        return sample_constrained_triangles(sdf, n, seed=seed, batch=1024)

    killed_after_first_shape.calls = 0
    old_fit = [("a", Shape(zoo.Sphere(0.30))), ("b", Shape(zoo.Sphere(0.25)))]
    with pytest.raises(KeyboardInterrupt):
        sample_triangle_dataset(old_fit, out, config, sampler=killed_after_first_shape, progress=False,
                                provenance={"fit_sha256": "old"})
    assert any((tmp_path / "triangles.h5.chunks").iterdir())

    def sampler(sdf, n, seed=0):
        return sample_constrained_triangles(sdf, n, seed=seed, batch=1024)

    new_fit = [("a", Shape(zoo.Sphere(0.35))), ("b", Shape(zoo.Sphere(0.25)))]  # same names, refitted
    sample_triangle_dataset(new_fit, out, config, sampler=sampler, progress=False, provenance={"fit_sha256": "new"})
    sample_triangle_dataset(new_fit, tmp_path / "fresh.h5", config, sampler=sampler, progress=False,
                            provenance={"fit_sha256": "new"})
    resumed, fresh = read_triangle_dataset(out), read_triangle_dataset(tmp_path / "fresh.h5")
    for key in ("vertices", "features", "bary", "min_sdf"):
        assert torch.equal(resumed[key], fresh[key]), key


def test_a_torn_detector_checkpoint_warns_and_training_starts_afresh(tmp_path):
    """The detector follows the same rule as the NeuralSDF fit (pipeline.training): an unreadable
    checkpoint used to raise DataError here and be silently ignored there; now both warn and restart."""
    from dataclasses import replace

    from sdfzoo.pipeline.train_detector import preset, train
    from sdfzoo.pipeline.training import CheckpointWarning

    base = preset("quick")
    config = replace(base, steps=6, batch_size=8, checkpoint_every=3, validate_every=100, validation_size=8,
                     detector={**base.detector, "feature_dim": 4, "hidden": 8, "weight_hidden": 4})
    fresh, fresh_history = train(_tiny_detector_data(0), config, progress=False)
    (tmp_path / "checkpoint.pt").write_bytes(b"PK\x03\x04 torn")
    with pytest.warns(CheckpointWarning, match="cannot be read"):
        again, history = train(_tiny_detector_data(0), config, out_dir=tmp_path, progress=False)
    assert history["loss"] == fresh_history["loss"]
    for (k, a), b in zip(fresh.state_dict().items(), again.state_dict().values()):
        assert torch.equal(a, b), k
