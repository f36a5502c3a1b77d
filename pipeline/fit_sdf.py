"""Stage 3, fit NeuralSDF: SDF samples of a category -> one decoder and a code cloud per shape.

Auto-decoder training (DeepSDF / DCC-DIF): the decoder, the codes and the code positions are
all parameters, optimised jointly by Adam on the samples of every shape. Every step draws
``shapes_per_step`` shapes and ``points_per_shape`` samples of each from a generator seeded by
(seed, step) alone, so the batch sequence does not depend on when the run was interrupted:
a run resumed from a checkpoint (weights + Adam state + step) follows the same trajectory as an
uninterrupted one.

Checkpoints are written atomically every ``checkpoint_every`` steps; a rerun with the same
fingerprint (config, data and code) resumes from the last one (``pipeline.training``).

Distributed: under ``torchrun`` (``WORLD_SIZE`` > 1) each process takes an equal slice of the
step's shapes and DistributedDataParallel averages the gradients, so N processes follow the
same trajectory as one (gloo on CPU, nccl on CUDA)::

    torchrun --nproc_per_node 2 -m pipeline.fit_sdf WORK/samples/*.h5 --preset quick --out fit.pt
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from zoo.config import DictConfig
from zoo.errors import DataError, InputError
from zoo.files import atomic_path, sha256_file
from zoo.neural import NeuralSDF, NeuralSDFConfig
from zoo.validation import positive_float, positive_int

from .distributed import World, average_gradients, average_rows, join_world
from .presets import Presets
from .stages import code_digest
from .training import Checkpoint, cosine_factor, data_digest, halving_factor, run_fingerprint, set_learning_rates, train_steps

# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class FitConfig(DictConfig):
    """How to train; ``sdf`` holds the network sizes (:class:`zoo.neural.NeuralSDFConfig`)."""

    _config_name = "fit config"

    sdf: NeuralSDFConfig = field(default_factory=NeuralSDFConfig)
    steps: int = 2000
    shapes_per_step: int = 8
    points_per_shape: int = 2048
    lr_decoder: float = 1e-3
    lr_codes: float = 3e-3
    lr_positions: float = 1e-3
    lr_halve_every: int = 0  # steps; 0 = cosine decay to 10% over the run instead
    loss: str = "l1"  # "l1" or "mse", on distances clamped to +-clamp
    clamp: float = 0.1
    code_reg: float = 0.0  # weight of the mean squared code norm (DeepSDF's prior)
    seed: int = 0
    checkpoint_every: int = 100

    def __post_init__(self):
        if isinstance(self.sdf, dict):
            object.__setattr__(self, "sdf", NeuralSDFConfig.from_dict(self.sdf))
        if self.loss not in ("l1", "mse"):
            raise InputError(f"loss must be 'l1' or 'mse', got {self.loss!r}")
        for name in ("steps", "shapes_per_step", "points_per_shape", "checkpoint_every"):
            positive_int(getattr(self, name), name)
        # unclamped, one huge target's squared error overflows float32 and the weights turn NaN
        positive_float(self.clamp, "clamp (a distance, 0.1 is usual)")


# The decoder's activation: the smooth LeakyReLU of sharpness 100 (zoo.neural.activation). With
# plain LeakyReLU the gradient jumps at every kink, and the KKT gap of eq. (12) stays positive even at
# the exact minimiser: the global reference's own mean gap was 7.2e-4 on the detector bench's 800
# seen-mug triangles (mugs@1.2.0), against 3.9e-8 with beta = 100 (mugs@1.3.0), for +25% query time.
SMOOTH_BETA = 100.0

PRESETS = Presets(
    "fit",
    # seconds on this 2-core machine: a handful of shapes, enough to check the pipeline end to end
    quick=FitConfig(sdf=NeuralSDFConfig(n_codes=64, hidden=(64, 64), smooth_beta=SMOOTH_BETA), steps=100, shapes_per_step=4,
                       points_per_shape=512, checkpoint_every=10, lr_decoder=3e-3, lr_codes=1e-2),
    # measured on 8 mugs (see the issue-3 report): 256 codes and a 256x3 decoder with clamped L1
    # beat the paper's 2.9M-parameter decoder, a 128x3 decoder and MSE at equal CPU time;
    # 2000 steps of 8 shapes x 2048 points for the shipped mugs (docs/fit-scale.md gives the time).
    default=FitConfig(sdf=NeuralSDFConfig(n_codes=256, hidden=(256, 256, 256), smooth_beta=SMOOTH_BETA), steps=2000,
                      shapes_per_step=8, points_per_shape=2048, checkpoint_every=50),
)
preset = PRESETS.lookup


# --------------------------------------------------------------------------- data


@dataclass
class TrainingData:
    """All shapes' samples stacked: points (S, N, 3), sdf (S, N), ``counts`` (S,) valid rows per shape."""

    stems: list[str]
    points: torch.Tensor
    sdf: torch.Tensor
    counts: torch.Tensor
    similarities: list

    def fingerprint(self) -> str:
        return data_digest(self.stems, self.points, self.sdf)

    def batch(self, shapes: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Samples ``rows`` (b, P) of shapes ``shapes`` (b,): -> points (b, P, 3), sdf (b, P)."""
        return self.points[shapes.unsqueeze(1), rows], self.sdf[shapes.unsqueeze(1), rows]


class SampleFiles:
    """Every shape's samples left in their HDF5 files (``pipeline.samples``) and read as a step needs them.

    What :func:`fit_sdf` holds in memory is a batch, not the category: the memory of a fit does not grow
    with the number of shapes (apart from their codes). A step reads, of each of its shapes, the HDF5
    chunks that hold its rows; ``fit_sdf`` prepares the next steps' batches in DataLoader workers while
    it trains on this one. The batches are those :class:`TrainingData` of the same files gives.
    """

    def __init__(self, sample_files):
        from .samples import read_sample_header

        self.paths = [Path(p) for p in sample_files]
        if not self.paths:
            raise DataError("no sample files to fit; run the samples stage first (zoo fit-category does)")
        headers = [read_sample_header(p) for p in self.paths]
        self.stems = [h.stem for h in headers]
        self.counts = torch.tensor([h.rows for h in headers])
        self.similarities = [h.similarity for h in headers]

    def fingerprint(self) -> str:
        return data_digest(self.stems, [sha256_file(p) for p in self.paths])

    def batch(self, shapes: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Samples ``rows`` (b, P) of shapes ``shapes`` (b,): -> points (b, P, 3), sdf (b, P)."""
        from .samples import read_sample_rows

        parts = [read_sample_rows(self.paths[int(i)], r.numpy()) for i, r in zip(shapes, rows)]
        points = torch.from_numpy(np.stack([p for p, _ in parts])) if parts else torch.zeros(0, rows.shape[1], 3)
        sdf = torch.from_numpy(np.stack([d for _, d in parts])) if parts else torch.zeros(0, rows.shape[1])
        bad = ~(torch.isfinite(points).all(-1).all(-1) & torch.isfinite(sdf).all(-1)
                & (points.abs().amax((1, 2)) <= MAX_SAMPLE_COORDINATE))
        if bad.any():
            stem = self.stems[int(shapes[bad.nonzero()[0, 0]])]
            raise InputError(f"samples of {stem!r} hold NaN, Inf or points far outside the normalised frame; "
                             "regenerate them (delete the file, rerun the samples stage)")
        return points, sdf


def load_training_data(sample_files) -> TrainingData:
    """Read per-shape HDF5 samples (``pipeline.samples``) into one padded tensor set (small categories, tests;
    :class:`SampleFiles` streams them instead)."""
    from .samples import read_samples

    shapes = [read_samples(p) for p in sample_files]
    if not shapes:
        raise DataError("no sample files to fit; run the samples stage first (zoo fit-category does)")
    return stack_samples([s.stem for s in shapes], [s.points for s in shapes], [s.sdf for s in shapes],
                         [s.similarity for s in shapes])


# Samples live in the normalised frame, where shapes fill [-0.5, 0.5]^3. Points beyond this are
# no samples of the shape (a unit or frame mix-up); near 1e19 their squared distances overflow
# float32, and the code-cloud weights, the loss and every weight after the step become NaN.
MAX_SAMPLE_COORDINATE = 1e6


def stack_samples(stems, points_list, sdf_list, similarities=None) -> TrainingData:
    """Pad per-shape arrays (N_s, 3), (N_s,) to (S, max N_s, ...) tensors.

    InputError for a shape with no samples, mismatched lengths, NaN or Inf, or points farther than
    :data:`MAX_SAMPLE_COORDINATE` from the normalised frame's origin: one such sample would make
    the loss NaN and poison every weight.
    """
    if not len(points_list) or len(points_list) != len(sdf_list) or len(points_list) != len(stems):
        raise InputError(f"need one points and one sdf array per stem, got {len(stems)} stems, {len(points_list)} points "
                         f"and {len(sdf_list)} sdf arrays")
    points_list = [torch.as_tensor(p, dtype=torch.float32) for p in points_list]
    sdf_list = [torch.as_tensor(d, dtype=torch.float32) for d in sdf_list]
    for stem, p, d in zip(stems, points_list, sdf_list):
        if p.ndim != 2 or p.shape[1:] != (3,) or d.shape != (len(p),) or len(p) == 0:
            raise InputError(f"samples of {stem!r}: need points (N, 3) and sdf (N,) with N > 0, got "
                             f"{tuple(p.shape)} and {tuple(d.shape)}; regenerate them (the samples stage)")
        if not (torch.isfinite(p).all() and torch.isfinite(d).all()):
            raise InputError(f"samples of {stem!r} hold NaN or Inf; regenerate them (delete the file, rerun the samples stage)")
        if float(p.abs().max()) > MAX_SAMPLE_COORDINATE:
            raise InputError(f"samples of {stem!r} reach {float(p.abs().max()):.3g} from the origin of the normalised "
                             f"frame, where shapes fill [-0.5, 0.5]^3 (at most {MAX_SAMPLE_COORDINATE:g} is accepted); "
                             "normalise the points first (pipeline.samples does)")
    n = max(len(p) for p in points_list)
    s = len(points_list)
    points = torch.zeros(s, n, 3)
    sdf = torch.zeros(s, n)
    for i, (p, d) in enumerate(zip(points_list, sdf_list)):
        points[i, : len(p)] = p
        sdf[i, : len(d)] = d
    counts = torch.tensor([len(p) for p in points_list])
    return TrainingData(list(stems), points, sdf, counts, list(similarities or [None] * s))


def step_batch(data: TrainingData, config: FitConfig, step: int, rank: int = 0, world: int = 1):
    """This process's share of step ``step``'s batch: -> shape_index (b,), points (b, P, 3), sdf (b, P).

    Each process takes a batch of its own, ``shapes_per_step`` shapes (at most the category's), so the
    global batch grows with the number of processes; the learning rates stay the preset's (Adam's step
    does not grow with the batch). The global batch depends only on (seed, step, world).
    """
    g = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
    n_shapes = len(data.stems)
    b = global_shapes_per_step(config, n_shapes, world)
    shapes = torch.randperm(n_shapes, generator=g)[:b] if b <= n_shapes else _draw_shapes(n_shapes, b, world, g)
    u = torch.rand(b, config.points_per_shape, generator=g)
    rows = (u * data.counts[shapes].unsqueeze(1)).long()
    idx, r = shapes[rank::world], rows[rank::world]
    return (idx, *data.batch(idx, r))


def _draw_shapes(n_shapes: int, b: int, world: int, g: torch.Generator) -> torch.Tensor:
    """``b`` shapes for ``world`` processes when there are fewer than ``b``: each process's share distinct."""
    return torch.stack([torch.randperm(n_shapes, generator=g)[: b // world] for _ in range(world)], 1).reshape(-1)


def global_shapes_per_step(config: FitConfig, n_shapes: int, world: int) -> int:
    """Shapes per step over all processes: ``shapes_per_step`` (at most the category's size) on each."""
    return min(config.shapes_per_step, n_shapes) * world


# --------------------------------------------------------------------------- the loss and the schedule


def sdf_loss(pred: torch.Tensor, target: torch.Tensor, config: FitConfig) -> torch.Tensor:
    """Mean clamped-distance error of (b, P) predictions: |.| for l1, (.)^2 for mse."""
    diff = pred.clamp(-config.clamp, config.clamp) - target.clamp(-config.clamp, config.clamp)
    return diff.abs().mean() if config.loss == "l1" else diff.square().mean()


def lr_factor(config: FitConfig, step: int) -> float:
    """Learning-rate multiplier at ``step``: halving every ``lr_halve_every`` steps, or cosine to 10%."""
    if config.lr_halve_every:
        return halving_factor(step, config.lr_halve_every)
    return cosine_factor(min(step, config.steps) / config.steps, 0.1)


def make_optimizer(model: NeuralSDF, config: FitConfig) -> torch.optim.Adam:
    return torch.optim.Adam([
        {"params": model.decoder.parameters(), "lr": config.lr_decoder, "base_lr": config.lr_decoder},
        {"params": [model.codes], "lr": config.lr_codes, "base_lr": config.lr_codes},
        {"params": [model.positions], "lr": config.lr_positions, "base_lr": config.lr_positions},
    ])


def fit_fingerprint(config: FitConfig, data: TrainingData) -> str:
    """Identifies a training run: a checkpoint resumes only a run with the same fingerprint."""
    return run_fingerprint(config.to_dict(), data.fingerprint(), code_digest([__name__]))


# --------------------------------------------------------------------------- training


@dataclass
class FitResult:
    model: NeuralSDF
    history: list  # [(step, loss)] every ``log_every`` steps
    seconds: float
    resumed_from: int


def fit_sdf(data: TrainingData | SampleFiles, config: FitConfig, checkpoint: str | os.PathLike | None = None,
            device: str | torch.device = "cpu", progress: bool = True, log_every: int = 10,
            log=None, stop_after: int | None = None, workers: int | None = None) -> FitResult:
    """Train a category NeuralSDF on ``data``; resume from ``checkpoint`` when it holds this run's state.

    Returns the trained module (on ``device``) with the loss history. Under torchrun every
    process calls this; rank 0 alone writes checkpoints and shows progress. ``stop_after``
    ends the run early at that step (as an interruption would), for tests. ``workers``: DataLoader
    processes that read the next steps' batches while this one trains (default: 1 for :class:`SampleFiles`,
    none for data in memory).
    """
    world = join_world(device)
    rank, device = world.rank, world.device
    torch.manual_seed(config.seed)
    model = NeuralSDF(config.sdf, len(data.stems), torch.Generator().manual_seed(config.seed)).to(device)
    optimizer = make_optimizer(model, config)
    saver = Checkpoint(checkpoint or None, fit_fingerprint(config, data), config.checkpoint_every, config.steps,
                       writer=rank == 0)
    history: list = []
    start = 0
    state = saver.load(device)
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        history, start = list(state["history"]), int(state["step"])
        if rank == 0:
            print(f"fit NeuralSDF: resuming from the checkpoint at step {start}/{config.steps}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    workers = (1 if isinstance(data, SampleFiles) else 0) if workers is None else workers
    batches = iter(step_batches(data, config, start, world, workers))

    def step(i: int) -> str:
        loss = train_step(model, optimizer, data, config, i, world, next(batches))
        if (i + 1) % log_every == 0 or i + 1 == config.steps:
            history.append((i + 1, loss))
            if log is not None and rank == 0:
                log(i + 1, config.steps, loss, time.perf_counter() - t0, start)
        return f"loss {loss:.5f}"

    def training_state(done: int) -> dict:
        return {"step": done, "model": model.state_dict(), "optimizer": optimizer.state_dict(), "history": history}

    train_steps(start, config.steps, step, saver, training_state, progress and rank == 0, "fit NeuralSDF", stop_after)
    return FitResult(model, history, time.perf_counter() - t0, start)


def step_batches(data, config: FitConfig, start: int, world: World, workers: int = 0):
    """This process's batches of steps ``start``, ``start + 1``, ... (:func:`step_batch`), read ahead by ``workers``
    DataLoader processes (into pinned memory when training on a GPU); ``workers=0`` reads each when it is due."""
    batches = _StepBatches(data, config, start, world.rank, world.size)
    if not workers:
        return (batches[k] for k in range(len(batches)))
    from torch.utils.data import DataLoader

    return DataLoader(batches, batch_size=None, shuffle=False, num_workers=workers, prefetch_factor=4,
                      pin_memory=world.device.type == "cuda")


class _StepBatches(torch.utils.data.Dataset):
    """Item k: (shape_index, points, sdf) of step ``start + k`` for this rank."""

    def __init__(self, data, config: FitConfig, start: int, rank: int, size: int):
        self.data, self.config, self.start, self.rank, self.size = data, config, start, rank, size

    def __len__(self) -> int:
        return max(0, self.config.steps - self.start)

    def __getitem__(self, k: int):
        return step_batch(self.data, self.config, self.start + k, self.rank, self.size)


def train_step(model: NeuralSDF, optimizer, data, config: FitConfig, step: int, world: World = World(),
               batch: tuple | None = None) -> float:
    """One Adam step on this process's batch (``batch``, else :func:`step_batch` of ``data``); returns the mean
    loss over the processes.

    Across processes the decoder's gradient is averaged whole, and the codes' and positions' only in the
    rows of the shapes some process's batch touched (:func:`pipeline.distributed.average_rows`).
    """
    set_learning_rates(optimizer, lr_factor(config, step))
    idx, points, target = batch if batch is not None else step_batch(data, config, step, world.rank, world.size)
    idx = idx.to(world.device)
    points, target = points.to(world.device, non_blocking=True), target.to(world.device, non_blocking=True)
    optimizer.zero_grad(set_to_none=False)  # dense zeros: the rows averaged across processes are indexed
    pred = model(points, idx)
    loss = sdf_loss(pred, target, config)
    if config.code_reg:
        loss = loss + config.code_reg * model.codes[idx].square().sum(-1).mean()
    loss.backward()
    average_gradients(model.decoder.parameters(), world)
    average_rows([model.codes, model.positions], idx, world)
    optimizer.step()
    value = loss.detach()
    if world.distributed:
        import torch.distributed as dist

        dist.all_reduce(value)
        value = value / world.size
    return float(value)


def print_log(step: int, total: int, loss: float, elapsed: float, start: int) -> None:
    """A plain log line (for nohup logs, where a progress bar does not render)."""
    rate = (step - start) / max(elapsed, 1e-9)
    eta = (total - step) / max(rate, 1e-9)
    print(f"step {step}/{total} loss {loss:.6f} {rate:.2f} steps/s eta {eta / 60:.1f} min", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- command line (torchrun)


def save_result(path: str | os.PathLike, result: FitResult, data: TrainingData, config: FitConfig) -> None:
    """Write the trained state (model state dict, stems, config, loss history) atomically."""
    state = {"model": result.model.state_dict(), "stems": data.stems, "config": config.to_dict(),
             "history": result.history, "seconds": result.seconds}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def main(argv: list[str] | None = None) -> None:
    """``[torchrun --nproc_per_node N] python -m sdfzoo.pipeline.fit_sdf SAMPLES.h5... --out FIT.pt``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m sdfzoo.pipeline.fit_sdf", description=main.__doc__)
    parser.add_argument("samples", nargs="+", help="per-shape samples files (pipeline.samples)")
    parser.add_argument("--out", required=True, help="where rank 0 writes the trained state (torch.save)")
    parser.add_argument("--preset", default="default", choices=sorted(PRESETS),
                        help="default: the shipped models' training; quick: a pipeline check for tests")
    parser.add_argument("--config", default=None, help="JSON of FitConfig fields overriding the preset")
    parser.add_argument("--checkpoint", default=None, help="checkpoint file to write and resume from")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch threads per process (0: leave torch's default)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    config = preset(args.preset)
    if args.config:
        overrides = json.loads(args.config)
        config = FitConfig.from_dict({**config.to_dict(), **overrides})
    data = SampleFiles(args.samples)
    result = fit_sdf(data, config, args.checkpoint, device=args.device, progress=not args.no_progress, log=print_log)
    rank = int(os.environ.get("RANK", "0"))
    if rank == 0:
        save_result(args.out, result, data, config)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


if __name__ == "__main__":  # pragma: no cover
    main()
