"""Stage train-detector: unsupervised training of the amortized detector (paper section III-B).

Loss per triangle, with p the predicted point and f the frozen NeuralSDF (normalised frame):

    L_op  = grad f(p)^T (p - v_min),  v_min = argmin_i grad f(p)^T v_i      (9)
    L_min = max(f(p), 0)                                                      (10)
    L     = L_op + lambda_min * L_min,  lambda_min = 1                        (11)

grad f(p) is taken with ``create_graph=True`` so that L_op is differentiable in the detector's
weights through p (its second-order term is the SDF's Hessian along the triangle). No labels
are used; the dataset's Frank-Wolfe labels only serve validation.

The ``quadratic`` detector (the default) predicts one curvature per edge; it learns it from the
NeuralSDF itself, also without labels: the bending of f along edge (i, j),

    L_curv = smooth_l1(kappa_k / perimeter, (2 f_i + 2 f_j - 4 f(midpoint)) / perimeter),

the value that makes its quadratic model exact at the edge's midpoint. L_op and L_min add nothing
measurable to it (their gradient vanishes wherever the answer is a vertex) at 20x the cost per step,
so its preset trains on L_curv alone (``lambda_curvature``, ``use_op_loss``, ``use_min_loss``).

Vertex features depend only on the vertices, so they are read precomputed from the triangle
dataset (pipeline.triangles), and the SDF is evaluated only at the predicted points.

Checkpoints (weights, optimiser, step, RNG, history) are written atomically every
``checkpoint_every`` steps; a rerun with the same config, training data and code resumes from the
last one (``pipeline.training``).
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from zoo.config import DictConfig
from zoo.detector import AmortizedDetector
from zoo.errors import DataError, InputError
from zoo.files import atomic_path, atomic_write_text
from zoo.geometry import bary_to_points, perimeter
from zoo.validation import as_device, positive_float, positive_int

from .distributed import World, average_gradients
from .presets import Presets
from .stages import code_digest
from .training import Checkpoint, cosine_factor, data_digest, run_fingerprint, set_learning_rates, train_steps

CHECKPOINT = "checkpoint.pt"
WEIGHTS = "detector.safetensors"
CONFIG = "detector.json"


# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class TrainConfig(DictConfig):
    """Everything that determines a training run (hashable into the stage lock)."""

    _config_name = "train config"

    steps: int = 1500
    batch_size: int = 1024
    lr: float = 3e-3
    lr_final_fraction: float = 0.05  # cosine decay from lr to lr * this
    betas: tuple[float, float] = (0.9, 0.999)
    lambda_min: float = 1.0
    use_op_loss: bool = True  # ablation "without L_op" sets False
    use_min_loss: bool = True  # ablation "without L_min" sets False
    create_graph: bool = True  # differentiate L_op through grad f(p) (second order)
    lambda_curvature: float = 0.0  # weight of L_curv (edge-curvature detectors only)
    grad_clip: float = 1.0
    seed: int = 0
    checkpoint_every: int = 200
    validate_every: int = 500
    validation_size: int = 2048
    detector: dict = field(default_factory=lambda: AmortizedDetector().config())


# lr 1e-4 (the paper's) is far too slow for a CPU budget of minutes; 3e-3 with cosine decay
# and clipping trained fastest and stably on the stand-in and on mugs (see the report).
# The default is the quadratic detector: on 8 mugs x 150 fresh triangles (600-3000 steps each) its
# mean optimality was 6.1e-3 against 1.1e-2 to 1.4e-2 for the softmax, sparsemax and grid heads.
QUADRATIC = {**AmortizedDetector().config(), "output": "quadratic", "vertex_sdf": True, "hidden": 64}
_CURVATURE_ONLY = dict(detector=QUADRATIC, lambda_curvature=1.0, use_op_loss=False, use_min_loss=False, lr=2e-3)
PRESETS = Presets(
    "training",
    quick=TrainConfig(steps=40, batch_size=256, checkpoint_every=20, validate_every=40, validation_size=256, **_CURVATURE_ONLY),
    default=TrainConfig(steps=4000, checkpoint_every=500, **_CURVATURE_ONLY),
    paper=TrainConfig(),  # the paper's loss on the softmax head (conditioned on z_tri), 1500 steps
)
preset = PRESETS.lookup


# Steps of the variant that trains the curvature head on L_op + L_min (second order, ~20x a step of L_curv).
OP_MIN_STEPS = 600


def ablation_configs(base: TrainConfig) -> dict[str, TrainConfig]:
    """The paper's Table IV variants of ``base``: without vertex features, without z_tri, and without
    each term of the loss it trains on (for a curvature head trained on L_curv: trained on the
    paper's L_op + L_min instead); a softmax head also gets eq. (8) as printed."""
    det = dict(base.detector)
    variants = {
        "full": base,
        "no_vertex_features": replace(base, detector={**det, "vertex_features": False}),
        "no_triangle_feature": replace(base, detector={**det, "triangle_feature": "none"}),
    }
    if base.lambda_curvature > 0:
        variants["op_min_loss"] = replace(base, lambda_curvature=0.0, use_op_loss=True, use_min_loss=True,
                                          steps=min(base.steps, OP_MIN_STEPS))
    else:
        variants["no_op_loss"] = replace(base, use_op_loss=False)
        variants["no_min_loss"] = replace(base, use_min_loss=False)
        variants["paper_eq8_additive"] = replace(base, detector={**det, "triangle_feature": "additive"})
    return variants


def train_ablations(data: TrainingData, base: TrainConfig, out_dir, progress: bool = True, log=print,
                    device=None) -> dict[str, Path]:
    """Train every :func:`ablation_configs` variant of ``base`` on ``data`` into ``OUT/<variant>``
    (each resumable on its own); -> {variant: directory}, for ``python -m sdfzoo.benches.detector --ablations``."""
    out = {}
    for name, config in ablation_configs(base).items():
        log(f"ablation {name}")
        train(data, config, out_dir=Path(out_dir) / name, progress=progress, log=None if progress else log, device=device)
        out[name] = Path(out_dir) / name
    return out


# --------------------------------------------------------------------------- losses


def detector_losses(sdf, triangles: torch.Tensor, bary: torch.Tensor, create_graph: bool = True):
    """Per-triangle L_op (9) and L_min (10): sdf differentiable, triangles (M, 3, 3), bary (M, 3) -> (M,), (M,).

    ``sdf(points)`` must be differentiable in the points (NeuralShape, analytic SDFs are).
    """
    with torch.enable_grad():
        p = bary_to_points(triangles, bary)  # (M, 3)
        if not p.requires_grad:  # evaluation without a detector graph: still need grad f(p)
            p = p.detach().requires_grad_(True)
        f = sdf(p)  # (M,)
        (g,) = torch.autograd.grad(f.sum(), p, create_graph=create_graph)  # (M, 3)
    scores = torch.einsum("mvc,mc->mv", triangles, g)  # (M, 3): g . v_i
    l_op = (g * p).sum(-1) - scores.min(dim=-1).values  # g . p - min_i g . v_i >= 0
    l_min = f.clamp_min(0)
    return l_op, l_min


def midpoint_curvatures(sdf, triangles: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
    """Bending of ``sdf`` along each edge (M, 3) of triangles (M, 3, 3): 2 f_i + 2 f_j - 4 f((v_i + v_j) / 2).

    Slot k is the edge opposite vertex k; exact (v_i - v_j)^T H (v_i - v_j) / 2 for a quadratic f.
    """
    pairs = ((1, 2), (2, 0), (0, 1))
    out = []
    with torch.no_grad():
        for tri in triangles.split(chunk):
            f = sdf(tri.reshape(-1, 3)).reshape(-1, 3)
            mid = torch.stack([(tri[:, i] + tri[:, j]) / 2 for i, j in pairs], dim=1)  # (m, 3, 3)
            fm = sdf(mid.reshape(-1, 3)).reshape(-1, 3)
            out.append(torch.stack([2 * (f[:, i] + f[:, j]) - 4 * fm[:, k] for k, (i, j) in enumerate(pairs)], dim=-1))
    return torch.cat(out).to(triangles.dtype)


def curvature_loss(detector: AmortizedDetector, data: TrainingData, rows: torch.Tensor) -> torch.Tensor:
    """Mean L_curv over triangles ``rows`` (B,): predicted against midpoint curvature, per perimeter."""
    b = data.batch(rows)
    per = perimeter(b.vertices).clamp_min(1e-12)[:, None]
    predicted = detector.edge_curvatures(b.vertices, b.features, b.vertex_sdf) / per
    target = b.edge_curvature.clamp_min(0) / per  # bending down acts as straight: a vertex wins
    return torch.nn.functional.smooth_l1_loss(predicted, target, beta=0.01)


def total_loss(l_op: torch.Tensor, l_min: torch.Tensor, config: TrainConfig) -> torch.Tensor:
    """Mean of equation (11) over the batch, with the ablation switches applied: (M,), (M,) -> ()."""
    loss = torch.zeros((), dtype=l_op.dtype, device=l_op.device)
    if config.use_op_loss:
        loss = loss + l_op.mean()
    if config.use_min_loss:
        loss = loss + config.lambda_min * l_min.mean()
    return loss


# --------------------------------------------------------------------------- data


@dataclass
class TrainingData:
    """Triangles in the normalised frame with their precomputed vertex features.

    vertices (N, 3, 3), features (N, 3, C), shape_index (N,) int64; ``sdfs[k]`` is shape k's
    differentiable SDF in the normalised frame; ``vertex_sdf`` (N, 3), the distance at each
    vertex, is needed only for detectors built with ``vertex_sdf=True``.
    """

    vertices: torch.Tensor
    features: torch.Tensor
    shape_index: torch.Tensor
    sdfs: list
    vertex_sdf: torch.Tensor | None = None
    edge_curvature: torch.Tensor | None = None  # (N, 3), set by with_edge_curvatures()
    batch_device: torch.device | None = None  # where batches go (None: where the tensors are)

    def __post_init__(self):
        n = self.vertices.shape[0]
        if self.features.shape[:2] != (n, 3) or self.shape_index.shape != (n,):
            raise DataError(
                f"training data disagree in length: vertices {tuple(self.vertices.shape)}, "
                f"features {tuple(self.features.shape)}, shape_index {tuple(self.shape_index.shape)}; regenerate the triangle dataset"
            )
        if n == 0:
            raise DataError("the triangle dataset is empty; regenerate it with more triangles per shape")
        if int(self.shape_index.max()) >= len(self.sdfs):
            raise DataError(f"shape_index refers to shape {int(self.shape_index.max())} but only {len(self.sdfs)} SDFs were given")

    def __len__(self) -> int:
        return self.vertices.shape[0]

    def to(self, device) -> TrainingData:
        """These data with their batches on ``device`` (the SDFs follow their inputs' device). The tensors stay
        where they are: a category's triangles do not go to a GPU whole, each batch goes when it is drawn."""
        return replace(self, batch_device=torch.device(device))

    def with_edge_curvatures(self, world: World = World()) -> TrainingData:
        """These data with each triangle's midpoint curvatures (the L_curv targets), computed once; on several
        processes each computes those of its share of the shapes, and they exchange them."""
        if self.edge_curvature is not None:
            return self
        kappa = torch.zeros(len(self), 3, dtype=self.vertices.dtype, device=self.vertices.device)
        device = self.batch_device or self.vertices.device
        for k in world.share(range(len(self.sdfs))):
            rows = (self.shape_index == k).nonzero().squeeze(-1)
            if len(rows):
                kappa[rows] = midpoint_curvatures(self.sdfs[k], self.vertices[rows].to(device)).to(kappa.device)
        world.sum(kappa)  # each row is non-zero on the one rank that computed it
        return replace(self, edge_curvature=kappa)

    def batch(self, rows: torch.Tensor) -> TriangleBatch:
        """Triangles ``rows`` (B,), on ``batch_device``."""
        device = self.batch_device or self.vertices.device
        rows = rows.to(self.vertices.device)

        def take(t):
            return None if t is None else t[rows].to(device, non_blocking=True)

        return TriangleBatch(take(self.vertices), take(self.features), take(self.shape_index).long(), take(self.vertex_sdf),
                             take(self.edge_curvature))


@dataclass
class TriangleBatch:
    """Rows of :class:`TrainingData`: vertices (B, 3, 3), features (B, 3, C), shape_index (B,) int64,
    vertex_sdf (B, 3) or None, edge_curvature (B, 3) or None."""

    vertices: torch.Tensor
    features: torch.Tensor
    shape_index: torch.Tensor
    vertex_sdf: torch.Tensor | None
    edge_curvature: torch.Tensor | None


def batch_losses(detector: AmortizedDetector, data: TrainingData, rows: torch.Tensor, create_graph: bool = True):
    """Predict and score triangles ``rows`` (B,): -> bary (B, 3), l_op (B,), l_min (B,).

    Triangles of different shapes are scored by their own SDF (a loop over the shapes in the
    batch, never over triangles).
    """
    b = data.batch(rows)
    tri, shape = b.vertices, b.shape_index
    bary = detector(tri, b.features, b.vertex_sdf)
    l_op = torch.empty(len(rows), dtype=tri.dtype, device=tri.device)
    l_min = torch.empty_like(l_op)
    parts_op, parts_min, order = [], [], []
    for k in torch.unique(shape).tolist():
        sel = (shape == k).nonzero().squeeze(-1)
        a, b = detector_losses(data.sdfs[k], tri[sel], bary[sel], create_graph)
        parts_op.append(a)
        parts_min.append(b)
        order.append(sel)
    order = torch.cat(order)
    l_op = l_op.index_put((order,), torch.cat(parts_op))
    l_min = l_min.index_put((order,), torch.cat(parts_min))
    return bary, l_op, l_min


# --------------------------------------------------------------------------- training


def train(data: TrainingData, config: TrainConfig, out_dir=None, progress: bool = True, log=None,
          init: AmortizedDetector | None = None, device=None, world: World = World()) -> tuple[AmortizedDetector, dict]:
    """Train a detector on ``data``; return (detector, history).

    ``device`` (e.g. "cuda"): where the detector, the data and the SDF queries live; default the data's.
    The result is on that device; the files written are device-free.

    With ``out_dir``, checkpoints go there (atomically) and the final weights and config are
    written as ``detector.safetensors`` and ``detector.json``; an existing checkpoint of the same
    config and the same training data is resumed. ``init`` (a detector of the same config) fine-tunes instead of starting
    afresh, e.g. after the NeuralSDF it was trained on was refitted.

    Under several processes (``world``), each takes a batch of its own (step ``s`` of rank ``r`` is the
    one-process run's batch ``s x world + r``: the global batch grows with the processes, the learning
    rate stays the preset's), the gradients are averaged, and rank 0 alone writes.
    """
    _check_config(config)
    torch.manual_seed(config.seed)
    out = Path(out_dir) if out_dir is not None else None
    # of the data as given, wherever they live
    saver = Checkpoint(out / CHECKPOINT if out is not None else None,
                       detector_fingerprint(config, data) if out is not None else "", config.checkpoint_every, config.steps,
                       writer=world.main)
    if device is not None:
        data = data.to(device)
    on = data.batch_device or data.vertices.device  # where the detector trains
    detector = AmortizedDetector.from_config(config.detector).to(on)
    if init is not None:
        detector.load_state_dict(init.state_dict())
    detector.fit_input_statistics(data.features)
    optimiser = torch.optim.Adam([{"params": detector.parameters(), "base_lr": config.lr}], lr=config.lr, betas=config.betas)
    history = {"step": [], "loss": [], "l_op": [], "l_min": [], "validation": [], "seconds": 0.0}
    generator = torch.Generator().manual_seed(config.seed)  # kept in checkpoints for any future random use
    start, history = _resume(saver, detector, optimiser, generator, history)
    if config.lambda_curvature > 0:
        data = data.with_edge_curvatures(world)
    sdf_losses = config.use_op_loss or config.use_min_loss
    validation_rows = torch.randperm(len(data), generator=torch.Generator().manual_seed(config.seed + 1))[: config.validation_size]
    validation_rows = validation_rows.to(data.vertices.device)
    t0 = time.perf_counter() - history["seconds"]

    def step_fn(step: int) -> str:
        rows = batch_rows(len(data), config.batch_size, step * world.size + world.rank, config.seed).to(data.vertices.device)
        set_learning_rates(optimiser, lr_factor(config, step))
        if sdf_losses:
            _, l_op, l_min = batch_losses(detector, data, rows, config.create_graph)
        else:  # the SDF at the predicted points is not needed: skip its (second-order) pass
            l_op = l_min = torch.zeros(len(rows), dtype=data.vertices.dtype, device=on)
        loss = total_loss(l_op, l_min, config)
        if config.lambda_curvature > 0:
            loss = loss + config.lambda_curvature * curvature_loss(detector, data, rows)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        average_gradients(detector.parameters(), world)
        torch.nn.utils.clip_grad_norm_(detector.parameters(), config.grad_clip)
        if _finite_gradients(detector):  # skip a step rather than poison the weights
            optimiser.step()
        _record(history, step, loss, l_op, l_min)
        if (step + 1) % config.validate_every == 0 or step + 1 == config.steps:
            history["validation"].append({"step": step + 1, **validation_metrics(detector, data, validation_rows)})
            if log and world.main:
                log(f"step {step + 1}: {history['validation'][-1]}")
        history["seconds"] = time.perf_counter() - t0
        return f"loss {history['loss'][-1]:.3g}"

    def training_state(done: int) -> dict:
        return {"config": config.to_dict(), "step": done, "detector": detector.state_dict(),
                "optimiser": optimiser.state_dict(), "generator": generator.get_state(),
                "torch_rng": torch.get_rng_state(), "history": history}

    train_steps(start, config.steps, step_fn, saver, training_state, progress and world.main, "train detector")
    if out is not None and world.main:
        save_detector(out, detector, extra={"train": config.to_dict(), "history": _summary(history)})
    return detector, history


def validation_metrics(detector: AmortizedDetector, data: TrainingData, rows: torch.Tensor) -> dict:
    """Mean optimality (eq. 12, L_op / perimeter) and mean L_min on ``rows``, no gradients to weights."""
    with torch.no_grad():
        b = data.batch(rows)
        tri = b.vertices
        bary = detector(tri, b.features, b.vertex_sdf)
    # reuse the loss on a detached prediction: L_op / perimeter is equation (12)
    l_op = torch.empty(len(rows), device=tri.device)
    l_min = torch.empty(len(rows), device=tri.device)
    shape = b.shape_index
    for k in torch.unique(shape).tolist():
        sel = (shape == k).nonzero().squeeze(-1)
        a, b = detector_losses(data.sdfs[k], tri[sel], bary[sel].detach(), create_graph=False)
        l_op[sel], l_min[sel] = a.detach().float(), b.detach().float()
    opt = l_op / perimeter(tri).clamp_min(1e-12).float()
    return {"optimality_mean": float(opt.mean()), "optimality_p50": float(opt.median()), "l_min_mean": float(l_min.mean())}


def _check_config(config: TrainConfig) -> None:
    positive_int(config.steps, "steps")
    positive_int(config.batch_size, "batch_size")
    positive_float(config.lr, "lr")
    if not (config.use_op_loss or config.use_min_loss or config.lambda_curvature > 0):
        raise InputError("at least one of use_op_loss, use_min_loss and lambda_curvature must be on, or nothing trains")
    if config.lambda_curvature > 0 and config.detector.get("output") != "quadratic":
        raise InputError("lambda_curvature trains edge curvatures: it needs a detector with output='quadratic'")


def batch_rows(n: int, batch_size: int, step: int, seed: int) -> torch.Tensor:
    """Rows of batch ``step``: a fixed shuffle per epoch, a function of (seed, epoch) alone, so a
    resumed run sees exactly the batches an uninterrupted one would."""
    per_epoch = max(1, n // batch_size)
    epoch, k = divmod(step, per_epoch)
    order = _epoch_order(n, seed, epoch)
    return order[k * batch_size : (k + 1) * batch_size]


@functools.lru_cache(maxsize=1)  # one epoch's order at a time
def _epoch_order(n: int, seed: int, epoch: int) -> torch.Tensor:
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))


def lr_factor(config: TrainConfig, step: int) -> float:
    """Cosine decay from lr to lr * lr_final_fraction over the run."""
    return cosine_factor(step / max(1, config.steps - 1), config.lr_final_fraction)


def _finite_gradients(module: torch.nn.Module) -> bool:
    return all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in module.parameters())


def _record(history: dict, step: int, loss, l_op, l_min) -> None:
    history["step"].append(step + 1)
    history["loss"].append(float(loss.detach()))
    history["l_op"].append(float(l_op.detach().mean()))
    history["l_min"].append(float(l_min.detach().mean()))


def _summary(history: dict) -> dict:
    return {"steps": len(history["step"]), "final_loss": history["loss"][-1] if history["loss"] else None,
            "validation": history["validation"][-1:] , "seconds": history["seconds"]}


# --------------------------------------------------------------------------- files


def data_fingerprint(data: TrainingData) -> str:
    """sha256 of the training triangles, features, shape indices and vertex distances: a checkpoint
    resumes only a run on the same data (the features change with the NeuralSDF they come from)."""
    return data_digest(data.vertices, data.features, data.shape_index, data.vertex_sdf)


def detector_fingerprint(config: TrainConfig, data: TrainingData) -> str:
    """Identifies a training run (config, data, this module's code): what a checkpoint must match to resume."""
    return run_fingerprint(config.to_dict(), data_fingerprint(data), code_digest([__name__]))


def _resume(saver: Checkpoint, detector, optimiser, generator, history: dict) -> tuple[int, dict]:
    """(first step, history) of this run: from its checkpoint when there is one, else (0, ``history``)."""
    state = saver.load("cpu")  # a GPU run's checkpoint resumes anywhere
    if state is None:
        return 0, history
    detector.load_state_dict(state["detector"])
    optimiser.load_state_dict(state["optimiser"])
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    return int(state["step"]), state["history"]


def save_detector(out, detector: AmortizedDetector, extra: dict | None = None) -> tuple[Path, Path]:
    """Write ``detector.safetensors`` and ``detector.json`` ({"detector": config, ...extra}) atomically."""
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    weights = {k: v.detach().contiguous().cpu() for k, v in detector.state_dict().items()}
    with atomic_path(out / WEIGHTS) as tmp:
        save_file(weights, str(tmp), metadata={"format": "pt"})
    atomic_write_text(out / CONFIG, json.dumps({"detector": detector.config(), **(extra or {})}, indent=1) + "\n")
    return out / WEIGHTS, out / CONFIG


def load_detector(directory) -> AmortizedDetector:
    """Rebuild a detector written by :func:`save_detector`."""
    from safetensors.torch import load_file

    directory = Path(directory)
    if not (directory / WEIGHTS).is_file() or not (directory / CONFIG).is_file():
        raise DataError(f"{directory} lacks {WEIGHTS} or {CONFIG}; train a detector there first (pipeline.train_detector)")
    config = json.loads((directory / CONFIG).read_text())
    detector = AmortizedDetector.from_config(config["detector"])
    detector.load_state_dict(load_file(str(directory / WEIGHTS)))
    return detector.eval()


# --------------------------------------------------------------------------- the fit-category stage


def training_data_from_file(path, model, stems=None) -> TrainingData:
    """TrainingData from a triangle dataset (pipeline.triangles) and the Model whose shapes it samples."""
    from .triangles import read_triangle_dataset

    d = read_triangle_dataset(path, mmap=True)
    names = d["shapes"]
    if stems is not None and list(stems) != names:
        raise DataError(f"the triangle dataset {path} was made for shapes {names}, not {list(stems)}; rerun sample-triangles")
    sdfs = [model.shape(s).normalised for s in names]
    return TrainingData(d["vertices"], d["features"], d["shape_index"], sdfs, d["vertex_sdf"])


def stage_train_detector(run) -> bool:
    """`zoo fit-category` stage: train the detector on the stage sample-triangles' dataset; sets run.detector."""
    from .distributed import run_stage_together
    from .stages import Stage

    config = PRESETS.lookup_or_default(run.preset.name)
    out = run.work_dir / "detector" / run.preset.name
    stage = Stage("train-detector", {"triangles": run.triangles_file, "fit": run.fit_file},
                  {"train": config.to_dict(), "processes": run.world.size},
                  {"weights": out / WEIGHTS, "config": out / CONFIG}, code=(__name__, "zoo.model"))

    def build():
        data = training_data_from_file(run.triangles_file, run.model, run.stems)
        train(data, config, out_dir=out, progress=run.progress, log=None if run.progress else run.log, device=run.device,
              world=run.world)

    did = run_stage_together(run.world, stage, build)
    run.detector = load_detector(out)
    info = json.loads((out / CONFIG).read_text())
    run.detector_info = {"train_preset": run.preset.name, **info.get("history", {})}
    return did


# --------------------------------------------------------------------------- command line


def train_for_model(model_spec, out_dir, triangles_preset: str = "default", train_preset: str = "default",
                    n_per_shape: int | None = None, steps: int | None = None, detector: dict | None = None,
                    progress: bool = True, log=print, triangles_file=None, ablations: bool = False, device=None) -> Path:
    """Sample (cached) and train a detector for an existing package, outside `zoo fit-category`.

    Writes ``OUT/triangles.h5`` (resumable), ``OUT/checkpoint.pt`` and ``OUT/detector.{safetensors,json}``.
    ``triangles_file``: train on this dataset (e.g. the fit-category run's) instead of sampling one.
    ``ablations``: train the Table IV variants into ``OUT/<variant>`` instead (:func:`train_ablations`).
    ``device``: where sampling and training run (e.g. "cuda"); default the CPU.
    """
    import zoo

    from .triangles import preset as triangles_preset_of
    from .triangles import sample_triangle_dataset

    model = zoo.load(model_spec) if isinstance(model_spec, (str, Path)) else model_spec
    out = Path(out_dir)
    tconfig = triangles_preset_of(triangles_preset, **({"n_per_shape": n_per_shape} if n_per_shape else {}))
    triangles = Path(triangles_file) if triangles_file else out / "triangles.h5"
    if not triangles.is_file():
        sample_triangle_dataset([(s, model.shape(s)) for s in model.shapes], triangles, tconfig, progress=progress,
                                provenance={"model": f"{model.name}@{model.version}"}, device=device)
    log(f"triangles: {triangles}")
    overrides = {k: v for k, v in {"steps": steps}.items() if v is not None}
    if detector:
        overrides["detector"] = {**AmortizedDetector().config(), **detector}
    config = preset(train_preset, **overrides)
    data = training_data_from_file(triangles, model, model.shapes)
    if ablations:
        train_ablations(data, config, out, progress=progress, log=log, device=device)
    else:
        train(data, config, out_dir=out, progress=progress, log=log, device=device)
    return out


def main(argv=None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="Train the amortized detector for a packaged NeuralSDF.")
    parser.add_argument("--model", required=True, help="package directory or registered name")
    parser.add_argument("--out", required=True, help="output directory (triangles, checkpoints, detector)")
    parser.add_argument("--preset", default="default", choices=sorted(PRESETS))
    parser.add_argument("--triangles-preset", default="default")
    parser.add_argument("--n-per-shape", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--detector", default=None, help="JSON of AmortizedDetector config fields to override")
    parser.add_argument("--triangles", default=None, help="train on this triangle dataset (HDF5) instead of sampling one")
    parser.add_argument("--ablations", action="store_true", help="train the Table IV variants into OUT/<variant>")
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--device", default="cpu", help="torch device for sampling and training: cpu, cuda, cuda:1, ...")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    as_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    train_for_model(args.model, args.out, args.triangles_preset, args.preset, args.n_per_shape, args.steps,
                    json.loads(args.detector) if args.detector else None, progress=not args.no_progress,
                    triangles_file=args.triangles, ablations=args.ablations, device=args.device)


if __name__ == "__main__":
    main()
