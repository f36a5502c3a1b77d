"""`zoo fit-category`: a category's meshes -> a package directory that ``zoo.load(DIR)`` opens.

The run is a list of stages (:data:`STAGES`), each a function of a shared :class:`FitRun`:

1. ``samples``   normalise + SDF samples of each training mesh (``pipeline.normalise`` /
                 ``pipeline.samples``; cached per mesh);
2. ``fit-sdf``   the auto-decoder NeuralSDF (``pipeline.fit_sdf``; cached by the hashes of the
                 sample files and the fit config; checkpointed, so a killed run resumes);
3. ``evaluate``  metrics of the fitted train shapes against their meshes (``pipeline.evaluate_sdf``;
                 cached likewise);
4. ``package``   the package directory at ``--out`` (``zoo.model.Model.save``).

Later stages (triangle sampling, detector training) insert themselves before ``package`` with
:func:`add_stage`; a stage that produces a detector sets ``run.detector``, which ``package`` saves.
Every stage writes atomically and records a lock (``pipeline.stages``), so a rerun skips what is
done and a third run only re-verifies hashes.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from zoo.errors import DataError
from zoo.files import atomic_path, atomic_write_text
from zoo.validation import int_at_least

from .distributed import World, join_world, leave_world, run_stage_together
from .evaluate_sdf import EvalConfig, evaluate_shape, summarise
from .fit_sdf import FitConfig, SampleFiles, fit_sdf, print_log, save_result
from .fit_sdf import preset as fit_preset
from .per_mesh import SET_ASIDE_FILE, SetAside, for_each_mesh, write_set_aside
from .presets import Presets
from .samples import SampleConfig, prepare_mesh
from .stages import Stage, provenance

# --------------------------------------------------------------------------- presets


@dataclass(frozen=True)
class Preset:
    """Everything a preset fixes: sampling, training, evaluation, and how many train shapes (None: all)."""

    name: str
    samples: SampleConfig
    fit: FitConfig
    evaluation: EvalConfig
    max_shapes: int | None = None
    # training length in epochs: how many times, on average, each shape's samples are seen; the steps
    # follow from the category's size and the number of processes (None: fit.steps whatever they are)
    epochs: float | None = None
    steps: int | None = None  # ``--steps``: train exactly this many steps, whatever the rules above give

    @property
    def options(self) -> str:
        """The `zoo fit-category` options that select this preset."""
        return f"--preset {self.name}" + ("" if self.steps is None else f" --steps {self.steps}")

    def epoch_steps(self, n_shapes: int, processes: int = 1) -> int:
        """Steps that show each of ``n_shapes`` shapes' samples ``epochs`` times (or fit.steps without epochs)."""
        if self.epochs is None:
            return self.fit.steps
        per_step = processes * min(self.fit.shapes_per_step, n_shapes) * self.fit.points_per_shape
        return max(1, int(round(self.epochs * n_shapes * self.samples.n_points / per_step)))

    def epochs_seen(self, steps: int, n_shapes: int, processes: int = 1) -> float:
        """How many times ``steps`` steps show each shape's samples, on average."""
        per_step = processes * min(self.fit.shapes_per_step, n_shapes) * self.fit.points_per_shape
        return steps * per_step / (n_shapes * self.samples.n_points)

    def fit_config(self, n_shapes: int, processes: int = 1) -> FitConfig:
        """The training config for a category of ``n_shapes`` train shapes on ``processes`` processes."""
        return replace(self.fit, steps=self.steps if self.steps is not None else self.epoch_steps(n_shapes, processes))


PRESETS = Presets(
    "fit-category",
    # a pipeline check for tests and CI: four shapes, a small network, well under a minute of training
    quick=Preset("quick", SampleConfig(n_points=20_000), fit_preset("quick"),
                 EvalConfig(n_near=2_000, n_uniform=2_000), max_shapes=4, epochs=2.56),
    # the shipped models: every train shape; see pipeline.fit_sdf.PRESETS["default"] for the budget
    # 100k samples per shape: training visits ~300k points per shape, and exact SDF sampling of
    # 54 meshes at 250k points each took longer than the training budget on the shared machine
    # each shape's 100k samples seen about 6 times: 2000 steps of 8 shapes x 2048 points for the 54 mugs
    # (docs/fit-scale.md gives the time), 741 for the 20 bottles
    default=Preset("default", SampleConfig(n_points=100_000), fit_preset("default"),
                   EvalConfig(n_near=10_000, n_uniform=10_000), epochs=6.068),
    # small categories of parts with sub-millimetre detail (a bolt's thread, gear teeth), where default's 600
    # steps leave the NeuralSDF off the mesh by more than a part's clearance: samples 2.5x denser and 60% of
    # them in a band of sigma 0.002 (0.1 mm on an M16 bolt), and a decoder that also sees 8 levels of Fourier
    # features of the position; each shape's samples seen about 49 times: 3000 steps of 3 shapes x 4096 points
    # for the 3 bolts (about 20 minutes on one core of the 2-core machine; docs/sim-scenarios.md gives what it
    # reached, and what it did without them)
    fine=Preset("fine", SampleConfig(n_points=250_000, near_sigmas=(0.002, 0.02), fractions=(0.6, 0.3, 0.1)),
                replace(fit_preset("default"), sdf=replace(fit_preset("default").sdf, fourier_levels=8), steps=3000,
                        shapes_per_step=3, points_per_shape=4096, checkpoint_every=200),
                EvalConfig(n_near=10_000, n_uniform=10_000), epochs=49.152),
)


# --------------------------------------------------------------------------- the run


@dataclass
class StageReport:
    """One line of the run's closing table."""

    stage: str
    meshes: int
    seconds: float
    peak_memory_mb: float  # this process's peak resident memory during the stage (rank 0's)
    set_aside: int
    ran: bool


@dataclass
class FitRun:
    """State shared by the stages of one `zoo fit-category` run."""

    category: object  # pipeline.categories.Category
    data_dir: Path
    work_dir: Path
    out_dir: Path
    preset: Preset
    device: str = "cpu"
    progress: bool = True
    version: str = "0.1.0"
    world: World = field(default_factory=World)
    strict: bool = False  # a mesh that fails ends the run, instead of being set aside
    stems: list[str] = field(default_factory=list)  # the train meshes still in the run
    mesh_paths: dict[str, Path] = field(default_factory=dict)
    set_aside: list[SetAside] = field(default_factory=list)
    sample_files: list[Path] = field(default_factory=list)
    fit_file: Path | None = None
    model: object = None  # zoo.model.Model, after fit-sdf
    metrics: dict = field(default_factory=dict)
    detector: object = None  # set by a detector stage
    detector_info: dict = field(default_factory=dict)
    ran: dict[str, bool] = field(default_factory=dict)  # stage name -> whether it did work (False: cached)
    reports: list[StageReport] = field(default_factory=list)
    log: Callable[[str], None] = print

    @property
    def fit_dir(self) -> Path:
        return self.work_dir / "fit" / self.preset.name

    @property
    def set_aside_file(self) -> Path:
        return self.work_dir / SET_ASIDE_FILE

    def each_mesh(self, stage: str, work: Callable[[str], object]) -> dict:
        """``work(stem)`` on every mesh of the run, shared out over the ranks; meshes that fail are set aside
        (and leave ``stems``); -> {stem: result} of the meshes that finished, on every rank."""
        results = for_each_mesh(self.world, stage, self.stems, work, self.strict, self.progress)
        self.set_aside += results.set_aside
        self.stems = [s for s in self.stems if s in results.done]
        if not self.stems:
            raise DataError(f"every mesh of {self.category.name!r} was set aside at stage {stage!r}; the first: "
                            f"{self.set_aside[0].stem}: {self.set_aside[0].reason}")
        return results.done

    def restore_set_aside(self, rows: list[dict]) -> None:
        """What a cached stage had set aside when it ran ({stem, stage, reason} rows): listed again, out of ``stems``."""
        known = {s.stem for s in self.set_aside}
        self.set_aside += [SetAside(**row) for row in rows if row["stem"] not in known]
        gone = {row["stem"] for row in rows}
        self.stems = [s for s in self.stems if s not in gone]


StageFn = Callable[[FitRun], bool]  # returns True when it did work, False when it was cached
RUN_REPORT_FILE = "run-report.json"


@dataclass(frozen=True)
class PreparedMesh:
    """A train mesh after the samples stage: its samples file, and whether this run (re)made it."""

    samples: Path
    ran: bool


def stage_samples(run: FitRun) -> bool:
    """Normalise and sample each training mesh (each one cached on its own; shared out over the ranks)."""
    from .categories import verified_mesh

    stems = run.category.stems("train")
    if run.preset.max_shapes:
        stems = stems[: run.preset.max_shapes]
    run.stems = stems
    run.mesh_paths = {s: run.data_dir / run.category.entry(s).file for s in stems}

    def prepare(stem: str) -> PreparedMesh:
        path = verified_mesh(run.category, run.data_dir, stem)
        before = _lock_mtime(run.work_dir, stem)
        out = prepare_mesh(path, run.work_dir, run.preset.samples, up=run.category.entry(stem).up, stem=stem)
        return PreparedMesh(out, _lock_mtime(run.work_dir, stem) != before)

    done = run.each_mesh("samples", prepare)
    run.sample_files = [done[s].samples for s in run.stems]
    return any(p.ran for p in done.values())


def _lock_mtime(work_dir: Path, stem: str):
    lock = work_dir / "samples" / f"{stem}.h5.lock.json"
    return lock.stat().st_mtime_ns if lock.exists() else None


def stage_fit_sdf(run: FitRun) -> bool:
    """Train the category NeuralSDF under DDP on every rank (resuming from its checkpoint after an interruption)."""
    out = run.fit_dir / "sdf.pt"
    checkpoint = run.fit_dir / "checkpoint.pt"
    config = run.preset.fit_config(len(run.stems), run.world.size)
    _warn_short_training(run, config)
    stage = Stage("fit-sdf", {p.stem: p for p in run.sample_files},
                  {"fit": config.to_dict(), "stems": run.stems, "processes": run.world.size},
                  {"fit": out}, code=("pipeline.fit_sdf", stage_fit_sdf))

    def build():
        data = SampleFiles(run.sample_files)
        result = fit_sdf(data, config, checkpoint, device=run.device, progress=run.progress,
                         log=None if run.progress else print_log)
        if run.world.main:
            save_result(out, result, data, config)

    did = run_stage_together(run.world, stage, build)
    run.fit_file = out
    run.model = model_from_fit(out, run)
    return did


def _warn_short_training(run: FitRun, config: FitConfig) -> None:
    """Say so before training when ``--steps`` shows each shape's samples fewer times than the preset intends."""
    intended = run.preset.epoch_steps(len(run.stems), run.world.size)
    if run.world.main and config.steps < intended:
        seen = run.preset.epochs_seen(config.steps, len(run.stems), run.world.size)
        wanted = run.preset.epochs_seen(intended, len(run.stems), run.world.size)
        run.log(f"warning: {config.steps} steps show each of the {len(run.stems)} shapes' samples {seen:.2f} times; "
                f"preset {run.preset.name!r} intends {wanted:.2f} ({intended} steps). Drop --steps for the preset's length.")


def model_from_fit(path: Path, run: FitRun):
    """The Model of a fit-sdf output, with the samples' similarities (source -> normalised)."""
    from zoo.model import Model
    from zoo.neural import NeuralSDF

    from .samples import read_samples

    state = torch.load(path, map_location="cpu", weights_only=True)  # tensors, dicts, lists: no pickle
    config = FitConfig.from_dict(state["config"])
    sdf = NeuralSDF(config.sdf, len(state["stems"]))
    sdf.load_state_dict(state["model"])
    similarities = {p.stem: read_samples(p).similarity for p in run.sample_files}
    return Model(run.category.name, run.version, sdf, list(state["stems"]), similarities,
                 {"fit": config.to_dict(), "fit_seconds": state.get("seconds")})


def stage_evaluate(run: FitRun) -> bool:
    """Compare every fitted train shape with its mesh's exact SDF, in the source frame (shared out over the ranks)."""
    out = run.fit_dir / "metrics.json"
    ev = run.preset.evaluation
    stage = Stage("evaluate", {"fit": run.fit_file, **{s: run.mesh_paths[s] for s in run.stems}}, {"evaluation": ev.to_dict()}, {"metrics": out},
                  code=("pipeline.evaluate_sdf", "zoo.model", stage_evaluate))

    def build():
        from zoo.meshes import load_mesh

        before = len(run.set_aside)
        per_shape = run.each_mesh("evaluate", lambda stem: evaluate_shape(run.model.shape(stem),
                                                                          load_mesh(run.mesh_paths[stem]), ev, run.device))
        metrics = {"train": summarise(per_shape), "per_shape": per_shape,
                   "command": f"zoo fit-category {run.category.name} {run.preset.options}",
                   "evaluation": ev.to_dict(), "set_aside": [asdict(s) for s in run.set_aside[before:]]}
        if run.world.main:
            with atomic_path(out) as tmp:
                Path(tmp).write_text(json.dumps(metrics, indent=1, sort_keys=True))

    did = run_stage_together(run.world, stage, build)
    run.metrics = json.loads(out.read_text())
    if not did:  # the meshes this stage set aside when it ran
        run.restore_set_aside(run.metrics.get("set_aside", []))
    return did


def stage_package(run: FitRun) -> bool:
    """Write the package directory (config.json, sdf.safetensors, [detector.safetensors], SHA256SUMS); rank 0 alone."""
    if not run.world.main:
        return False
    _remove_temporaries(run.out_dir)
    model = run.model
    model.detector = run.detector.requires_grad_(False).eval() if run.detector is not None else None
    metrics = {"train": run.metrics.get("train", {}), "fit_seconds": model.config.get("fit_seconds"),
               **({"detector": run.detector_info} if run.detector_info else {})}
    training_data = {
        "category_manifest": manifest_reference(run.category.manifest),
        "split": "train",
        "inputs": {s: run.category.entry(s).sha256 for s in run.stems},
        "preset": run.preset.name,
        "set_aside": [asdict(s) for s in run.set_aside],
        "processes": run.world.size,
        "sdfzoo": provenance(),
    }
    kwargs = dict(fp16=True, metrics=metrics, license=license_of(run), training_data=training_data,
                  category=run.category.name, extra={"metrics_command": run.metrics.get("command", "")})
    if _same_package(run.out_dir, model.package_config(**kwargs)):
        return False
    model.save(run.out_dir, **kwargs)
    return True


def _remove_temporaries(out_dir: Path) -> None:
    """Delete the atomic writers' temporaries (``.NAME.XXXX.tmp``) that a killed run left in the package
    directory: never listed in SHA256SUMS nor released, but copied by anyone who uploads the folder."""
    if out_dir.is_dir():
        for p in out_dir.iterdir():
            if p.is_file() and p.name.startswith(".") and p.name.endswith(".tmp"):
                p.unlink(missing_ok=True)


def _same_package(out_dir: Path, wanted: dict) -> bool:
    """True when ``out_dir`` already holds a verified package with exactly this config."""
    from zoo.errors import ZooError
    from zoo.files import verify_directory

    try:
        verify_directory(out_dir)
        return json.loads((out_dir / "config.json").read_text()) == json.loads(json.dumps(wanted))
    except (ZooError, OSError, json.JSONDecodeError):
        return False


def manifest_reference(manifest: Path) -> str:
    """How a package names its category manifest: a bundled one by its place in the project, a user's by its path."""
    from .categories import manifests_folder

    if manifest.resolve().parent == manifests_folder().resolve():
        return f"manifests/categories/{manifest.name}"
    return str(manifest.resolve())


def license_of(run: FitRun) -> str:
    """The training meshes' licenses, one line each (the weights inherit their terms)."""
    licenses = sorted({run.category.entry(s).license for s in run.stems})
    return " | ".join(licenses)


STAGES: list[tuple[str, StageFn]] = [
    ("samples", stage_samples),
    ("fit-sdf", stage_fit_sdf),
    ("evaluate", stage_evaluate),
    ("package", stage_package),
]


def add_stage(name: str, fn: StageFn, before: str = "package") -> None:
    """Insert a stage (e.g. triangle sampling, detector training) before ``before``; idempotent by name."""
    names = [n for n, _ in STAGES]
    if name in names:
        STAGES[names.index(name)] = (name, fn)
        return
    STAGES.insert(names.index(before), (name, fn))


# --------------------------------------------------------------------------- entry point


def fit_category(category: str | os.PathLike, data_dir: str | os.PathLike | None = None, preset: str = "default",
                 out_dir: str | os.PathLike | None = None, work_dir: str | os.PathLike | None = None,
                 device: str = "cpu", progress: bool = True, log: Callable[[str], None] = print,
                 steps: int | None = None, strict: bool = False, max_shapes: int | None = None) -> FitRun:
    """Run every stage of :data:`STAGES` for ``category``; return the finished run (``run.model``, ``run.out_dir``).

    ``category`` is a bundled category's name or a manifest file (``zoo manifest`` writes one). Defaults:
    ``out_dir`` = out/CATEGORY, ``work_dir`` = runs/CATEGORY (caches, checkpoints); ``steps`` replaces the
    preset's training length; ``max_shapes`` its number of train shapes (0: all). A mesh that fails is set
    aside (listed at the end, in WORK/set-aside.json and in the package's config), unless ``strict``.
    Under torchrun (``WORLD_SIZE`` > 1) every process calls this: the stages share the work out
    (:mod:`pipeline.distributed`); the work folder must be one that every process sees.
    """
    from .categories import load_category, resolve_data_dir

    world = join_world(device)  # checks the device first: a missing GPU is a typed error, not a late AssertionError
    cat = load_category(category)
    p = PRESETS.lookup(preset)
    if steps is not None:
        p = replace(p, steps=int_at_least(steps, "steps", 1))
    if max_shapes is not None:
        p = replace(p, max_shapes=int_at_least(max_shapes, "max_shapes", 0) or None)
    run = FitRun(cat, resolve_data_dir(data_dir, cat), Path(work_dir or Path("runs") / cat.name),
                 Path(out_dir or Path("out") / cat.name), p, device=str(world.device), progress=progress,
                 world=world, strict=strict, log=log if world.main else _silent)
    try:
        for name, fn in STAGES:
            run_timed(run, name, fn)
        if world.main:
            write_set_aside(run.set_aside_file, run.set_aside)
            write_run_report(run)
            log(summary_table(run))
    finally:
        leave_world(world)
    return run


def _silent(line: str) -> None:
    """The log of ranks other than 0: rank 0 speaks for the run."""


def run_timed(run: FitRun, name: str, fn: StageFn) -> None:
    """Run one stage, timing it and measuring this process's peak memory during it."""
    reset_peak_memory()
    before = len(run.set_aside)
    t0 = time.perf_counter()
    did = bool(fn(run))
    seconds = time.perf_counter() - t0
    run.ran[name] = did
    set_aside = len(run.set_aside) - before
    run.reports.append(StageReport(name, len(run.stems) + set_aside, seconds, peak_memory_mb(), set_aside, did))
    run.log(f"{name}: {'done' if did else 'up to date, skipped'} ({seconds:.1f} s)")


def summary_table(run: FitRun) -> str:
    """The closing table (stage, meshes, seconds, peak memory, set aside) and the set-aside meshes."""
    lines = [f"{'stage':<18}{'meshes':>8}{'seconds':>10}{'peak MB':>10}{'set aside':>11}"]
    lines += [f"{r.stage:<18}{r.meshes:>8}{r.seconds:>10.1f}{r.peak_memory_mb:>10.0f}{r.set_aside:>11}"
              + ("" if r.ran else "  (cached)") for r in run.reports]
    if run.set_aside:
        lines.append(f"set aside ({len(run.set_aside)}; listed in {run.set_aside_file}):")
        lines += [f"  {s.stem} at {s.stage}: {s.reason}" for s in run.set_aside]
    return "\n".join(lines)


def write_run_report(run: FitRun) -> Path:
    """WORK/run-report.json: the closing table as data (what `zoo bench --fit-scale` gathers)."""
    path = run.work_dir / RUN_REPORT_FILE
    report = {"category": run.category.name, "preset": run.preset.name, "processes": run.world.size,
              "meshes": len(run.stems), "set_aside": [asdict(s) for s in run.set_aside],
              "stages": [asdict(r) for r in run.reports], "sdfzoo": provenance()}
    atomic_write_text(path, json.dumps(report, indent=1) + "\n")
    return path


def reset_peak_memory() -> None:
    """Start a new peak of this process's resident memory (Linux; elsewhere the peak is the process's)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_memory_mb() -> float:
    """This process's peak resident memory since :func:`reset_peak_memory`, in MB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def fit_codes(model_spec: str, mesh: str | os.PathLike, out: str | os.PathLike | None = None, iters: int = 500,
              up: str = "z", seed: int = 0, device: str = "cpu", progress: bool = True) -> dict:
    """`zoo fit-codes`: fit an unseen mesh's code cloud against a model; optionally save it; -> summary."""
    import zoo
    from zoo.meshes import load_mesh

    model = zoo.load(model_spec, device=device) if isinstance(model_spec, (str, os.PathLike)) else model_spec
    t0 = time.perf_counter()
    shape = model.fit_codes(mesh, iters=iters, seed=seed, up=up, progress=progress)
    seconds = time.perf_counter() - t0
    metrics = evaluate_shape(shape, load_mesh(mesh), EvalConfig(n_near=5_000, n_uniform=5_000))
    summary = {"model": f"{model.name}@{model.version}", "mesh": str(mesh), "shape": shape.name,
               "fit_seconds": seconds, **{k: metrics[k] for k in ("near_p50", "near_p90", "sign_agreement")}}
    shape.fit["seconds"] = seconds
    shape.metrics = {k: metrics[k] for k in ("near_p50", "near_p90", "sign_agreement", "size")}
    if out is not None:
        shape.save(out)
        summary["out"] = str(out)
    return summary


# --------------------------------------------------------------------------- detector stages (issue 4)

from .train_detector import stage_train_detector  # noqa: E402  (they import nothing from here)
from .triangles import stage_sample_triangles  # noqa: E402

add_stage("sample-triangles", stage_sample_triangles)
add_stage("train-detector", stage_train_detector)
