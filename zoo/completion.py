"""Shape, pose and scale of an unseen object from a partial view: what :meth:`zoo.Model.fit_observation` runs.

The unknowns are the object's code cloud (its shape in the category) and a similarity from the world to the
category's normalised frame: a scale ``s``, a yaw ``psi`` about ``up`` (optionally a tilt too) and the object's
centre ``c``, so that ``p_n = s Rz(psi) A (p - c)`` where ``A`` turns ``up`` into +z. They are fitted to the
:class:`zoo.observation.Observation` by minimising

    L = mean_i rho(f(p_i) / sigma)                         the surface passes through the observed points
      + mean_j rho(relu(-f(q_j)) / sigma)                  the space a ray crossed before its hit is outside
      + prior * (|codes - codes_0|^2 / sigma_c^2 + |x - x_0|^2 / sigma_x^2) / K     the codes stay near a train shape's

with ``f`` the world-frame signed distance (metres), ``rho(r) = log(1 + r^2)`` (Cauchy: a table pixel left by a
loose mask, or a stray return, costs a bounded amount however far it lies) and ``sigma`` the sensor's noise.

**The prior.** A partial view leaves the far side unconstrained: codes free to move satisfy the visible points
with anything behind them. The codes therefore start from the *nearest train shape's* code cloud (the one whose
posed surface explains the observation best) and are held near it by a Gaussian whose scale is the spread of
the train codes themselves (``sigma_c``, ``sigma_x``), so the unseen side stays that of a real member of the
category, bent towards what was seen. A mean code cloud would be the textbook prior (DeepSDF's zero-mean code),
but a code cloud's codes sit at positions of their own per shape, so the train shapes' codes do not average
into a shape; the feature field's mean (:class:`CategoryPrior`, the baseline ``codes="mean"``) is measurably
worse (docs/observation.md).

**Two stages.** (1) *Pose search on grids*: every train shape (and the mean) is sampled once on a coarse grid
over its normalised cube (:class:`CategoryPrior`, cached on disk); from several starting yaws each
(shape, yaw) hypothesis's scale, yaw and centre are fitted to the observation by the loss above read off the
grids, all hypotheses in one batch. (2) *Refinement with the network*: the best hypotheses (of different yaws)
refine pose and codes together through the decoder; the lowest loss wins, and every starting yaw's outcome is
kept in ``shape.fit`` so that an ambiguous yaw (a mug's handle out of view) shows.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from .errors import InputError
from .observation import Observation

GRID_HALF_WIDTH = 0.6  # the prior grids cover [-0.6, 0.6]^3 of the normalised frame (the shapes fill [-0.5, 0.5]^3)
PRIOR_FORMAT = 2  # bump when CategoryPrior's content changes: old cache files are then ignored
PLANE_FRACTION = 0.02  # points thinner than this fraction of their extent across their best plane are a plane
CODE_CHOICES = ("fit", "nearest", "mean")
EVALUATION_DRAW = 4  # the final loss that ranks hypotheses reads this many times a step's samples


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_observation` searches. ``codes``: "fit" (codes and pose), or the baselines "nearest" (the
    nearest train shape's codes, pose only) and "mean" (the category's mean code cloud, pose only)."""

    yaws: int = 8  # starting yaws, evenly spaced over the full turn
    grid_iters: int = 80  # pose iterations on the grids, all hypotheses at once
    refine_iters: int = 120  # pose (and code) iterations through the network, per refined hypothesis
    refine_hypotheses: int = 2  # how many of the best hypotheses (of different yaws) the network refines
    points: int = 384  # surface points a step
    free_points: int = 384  # free-space samples a step
    sigma: float = 0.002  # the loss's scale (metres): about the sensor's noise
    prior: float = 0.05  # the code prior's weight
    codes: str = "fit"
    full_rotation: bool = False  # also fit a tilt away from ``up`` (for an object not standing upright)
    standing: bool = True  # the object stands on the surface under its lowest points: nothing of it lies below
    seed: int = 0

    def __post_init__(self):
        if self.codes not in CODE_CHOICES:
            raise InputError(f"codes must be one of {', '.join(CODE_CHOICES)}, got {self.codes!r}")
        for name in ("yaws", "grid_iters", "points", "free_points", "refine_hypotheses"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.sigma > 0 or not self.prior >= 0:
            raise InputError(f"sigma must be > 0 and prior >= 0, got {self.sigma} and {self.prior}")


# --------------------------------------------------------------------------- the category prior


@dataclass
class CategoryPrior:
    """What the pose search reads of a model: each train shape's SDF on a grid, and the mean code cloud.

    ``grids`` (S + 1, R, R, R) float32: normalised-frame signed distances at the nodes of a grid over
    ``[-GRID_HALF_WIDTH, GRID_HALF_WIDTH]^3`` indexed [z, y, x] (``grid_sample``'s order), the train shapes in the
    model's order, then the mean; ``z_range`` (S + 1, 2): each one's lowest and highest z inside (normalised);
    ``mean_codes`` (K, C), ``mean_positions`` (K, 3): the mean code cloud (at positions spread over all train
    shapes' code positions by farthest-point sampling, each code the mean of the train shapes' features there);
    ``code_std``, ``position_std``: the spread of the train codes and positions (the prior's scales).
    """

    grids: torch.Tensor
    z_range: torch.Tensor
    mean_codes: torch.Tensor
    mean_positions: torch.Tensor
    code_std: float
    position_std: float


def category_prior(model, resolution: int = 32, progress: bool = False) -> CategoryPrior:
    """The model's :class:`CategoryPrior`: kept on the model, and on disk under ``zoo_cache_dir()/priors`` (keyed by
    the decoder, the code clouds and ``resolution``), so that it is computed once per machine (seconds per ten
    shapes on a CPU)."""
    held = getattr(model, "_category_prior", None)
    if held is not None and held[0] == resolution:
        return held[1]
    path = _prior_path(model, resolution)
    prior = _read_prior(path)
    if prior is None:
        prior = _compute_prior(model, resolution, progress)
        _write_prior(path, prior)
    model._category_prior = (resolution, prior)
    return prior


def _prior_path(model, resolution: int):
    from .hub import zoo_cache_dir
    from .shape_file import model_sha256, tensors_sha256

    sdf = model.sdf
    key = hashlib.sha256(f"{PRIOR_FORMAT}:{resolution}:{model_sha256(sdf.config, sdf.decoder)}:"
                         f"{tensors_sha256(sdf.codes.flatten(0, 1), sdf.positions.flatten(0, 1))}".encode()).hexdigest()
    return zoo_cache_dir() / "priors" / f"{model.name}-{key[:24]}.npz"


def _read_prior(path) -> CategoryPrior | None:
    if not path.is_file():
        return None
    try:
        with np.load(path) as f:
            return CategoryPrior(torch.from_numpy(f["grids"]), torch.from_numpy(f["z_range"]),
                                 torch.from_numpy(f["mean_codes"]), torch.from_numpy(f["mean_positions"]),
                                 float(f["code_std"]), float(f["position_std"]))
    except (OSError, KeyError, ValueError):  # a torn or foreign file: computed again and rewritten
        return None


def _write_prior(path, prior: CategoryPrior) -> None:
    from .files import atomic_path

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, grids=prior.grids.numpy(), z_range=prior.z_range.numpy(), mean_codes=prior.mean_codes.numpy(),
                     mean_positions=prior.mean_positions.numpy(), code_std=prior.code_std, position_std=prior.position_std)
    except OSError:  # a read-only cache costs the next process the same seconds, nothing else
        pass


def _compute_prior(model, resolution: int, progress: bool) -> CategoryPrior:
    from .neural import NeuralShape
    from .progress import task_bar

    sdf = model.sdf
    nodes = torch.linspace(-GRID_HALF_WIDTH, GRID_HALF_WIDTH, resolution)
    z, y, x = torch.meshgrid(nodes, nodes, nodes, indexing="ij")
    points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
    codes, positions = sdf.codes.detach().cpu(), sdf.positions.detach().cpu()
    mean_positions = _farthest_points(positions.reshape(-1, 3), sdf.config.n_codes)
    shapes = [NeuralShape(name, sdf.decoder, sdf.config, codes[i], positions[i]) for i, name in enumerate(model.shapes)]
    features = torch.stack([s.features(mean_positions) for s in shapes])  # (S, K, C)
    shapes.append(NeuralShape("mean", sdf.decoder, sdf.config, features.mean(0), mean_positions))
    grids = []
    with task_bar(progress, "category prior", len(shapes)) as bar:
        for s in shapes:
            grids.append(s(points).reshape(resolution, resolution, resolution).float())
            bar.advance()
    grids = torch.stack(grids)
    z_range = torch.stack([_z_extent(g, nodes) for g in grids])
    return CategoryPrior(grids.contiguous(), z_range, features.mean(0).contiguous(), mean_positions.contiguous(),
                         float(codes.std()), float(positions.std(dim=1).mean()))


def _z_extent(grid: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """Lowest and highest z (2,) of the surface in a grid of distances (R, R, R) indexed [z, y, x]: in each column,
    where the values cross zero below its lowest inside node (linearly between the two nodes), and the highest
    inside node."""
    inside = grid < 0
    rows = inside.flatten(1).any(dim=1).nonzero().flatten()
    if len(rows) == 0:
        return torch.tensor([-0.5, 0.5])
    columns = inside.flatten(1)  # (R, R * R)
    first = columns.float().argmax(0)  # the lowest inside node of each column (0 where none)
    values = grid.flatten(1)
    lowest = float(nodes[rows[0]])
    step = float(nodes[1] - nodes[0])
    for c in (columns.any(0) & (first > 0)).nonzero().flatten().tolist():
        r = int(first[c])
        above, below = float(values[r - 1, c]), float(values[r, c])
        lowest = min(lowest, float(nodes[r - 1]) + step * above / (above - below))
    return torch.tensor([lowest, float(nodes[rows[-1]])])


def _farthest_points(points: torch.Tensor, k: int) -> torch.Tensor:
    """``k`` of ``points`` (N, 3) spread by greedy farthest-point sampling from the first -> (k, 3)."""
    chosen = [0]
    distance = (points - points[0]).square().sum(-1)
    for _ in range(1, min(k, len(points))):
        i = int(distance.argmax())
        chosen.append(i)
        distance = torch.minimum(distance, (points - points[i]).square().sum(-1))
    return points[chosen].clone()


# --------------------------------------------------------------------------- the observation as tensors


@dataclass
class _Evidence:
    """The observation in the form the loss reads: surface points (N, 3), and free-space segments (F, 2, 3) from
    which free samples are drawn (a sample lies on a segment, uniformly; each kind of evidence gets an equal share,
so that a few thousand segments under the support weigh as much as a hundred thousand rays)."""

    points: torch.Tensor
    segments: list[torch.Tensor]  # one (F, 2, 3) tensor per kind of evidence, each drawn from equally
    up: torch.Tensor  # (3,)
    support: float | None  # the height (along up) of the surface the object stands on, if it stands


def _evidence(obs: Observation, up: np.ndarray, sigma: float, standing: bool) -> _Evidence:
    """Free-space segments of an observation: the last part of each surface point's ray (from ``3 sigma`` to half
    the object's extent in front of it), the part of each free ray that passes near the object, (without
    origins) a short segment along each normal, and (``standing``) the space under the surface the object stands
    on, which no sensor sees but which holds nothing of it."""
    points = obs.points
    centre = np.median(points, axis=0)
    reach = max(obs.extent, 1e-3)
    segments = []
    gap = 3.0 * sigma
    if obs.origins is not None:
        ray = points - obs.origins
        length = np.linalg.norm(ray, axis=1, keepdims=True)
        unit = ray / np.maximum(length, 1e-12)
        far = np.minimum(length[:, 0], 0.5 * reach)
        ok = far > gap
        segments.append(np.stack([points[ok] - unit[ok] * far[ok, None], points[ok] - unit[ok] * gap], axis=1))
    elif obs.normals is not None:
        segments.append(np.stack([points + obs.normals * gap, points + obs.normals * (0.25 * reach)], axis=1))
    if obs.free_origins is not None:
        segments.append(_near_part(obs.free_origins, obs.free_ends, centre, reach, gap))
    if standing:
        segments.append(_below_support(points, up, _support_height(obs, up, reach), reach, gap))
    return _Evidence(torch.as_tensor(points, dtype=torch.float32),
                     [torch.as_tensor(s, dtype=torch.float32) for s in segments if len(s)],
                     torch.as_tensor(up, dtype=torch.float32), _support_height(obs, up, reach) if standing else None)


def _support_height(obs: Observation, up: np.ndarray, reach: float) -> float:
    """The height (along ``up``) of the surface the object stands on: where the free rays beside the object end at
    about the height of its lowest points (the table seen around its base), else its lowest points (1st percentile:
    a base's rounded edge seen from above puts them a little higher than the table)."""
    heights = obs.points @ up
    low = float(np.percentile(heights, 1))
    if obs.free_ends is not None:
        ends = obs.free_ends
        beside = np.linalg.norm(np.cross(ends - np.median(obs.points, axis=0), up), axis=1) < reach
        end_heights = ends[beside] @ up
        table = end_heights[np.abs(end_heights - low) < 0.1 * reach]
        if len(table) >= 50:
            return float(np.median(table))
    return low


def _below_support(points: np.ndarray, up: np.ndarray, support: float, reach: float, gap: float, count: int = 48) -> np.ndarray:
    """Vertical segments (count^2, 2, 3) from ``gap`` to ``reach / 2`` below the lowest observed points (the surface
    the object stands on), over a square of 1.5 times the object's extent about them."""
    height = points @ up
    across = points - np.outer(height, up)
    centre = np.median(across, axis=0)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    ticks = np.linspace(-0.75 * reach, 0.75 * reach, count)
    grid = centre + ticks[:, None, None] * a + ticks[None, :, None] * b
    top = grid.reshape(-1, 3) + (support - gap) * up
    return np.stack([top, top - 0.5 * reach * up], axis=1)


def _near_part(origins: np.ndarray, ends: np.ndarray, centre: np.ndarray, reach: float, gap: float) -> np.ndarray:
    """The parts (F, 2, 3) of the rays origin -> end inside the ball of radius ``reach`` about ``centre``, stopped
    ``gap`` short of the end (what the ray hit lies there)."""
    ray = ends - origins
    length = np.linalg.norm(ray, axis=1)
    unit = ray / np.maximum(length, 1e-12)[:, None]
    along = ((centre - origins) * unit).sum(1)
    miss2 = ((centre - origins) ** 2).sum(1) - along**2
    half = np.sqrt(np.maximum(reach**2 - miss2, 0.0))
    start, stop = np.maximum(along - half, 0.0), np.minimum(along + half, length - gap)
    ok = (miss2 < reach**2) & (stop > start)
    return np.stack([origins[ok] + unit[ok] * start[ok, None], origins[ok] + unit[ok] * stop[ok, None]], axis=1)


def _draw(evidence: _Evidence, points: int, free_points: int, generator: torch.Generator
          ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``points`` surface points (P, 3) and about ``free_points`` free samples (Q, 3), drawn with ``generator``."""
    n = len(evidence.points)
    surface = evidence.points[torch.randint(n, (min(points, n),), generator=generator)]
    if not evidence.segments:
        return surface, None
    share = -(-free_points // len(evidence.segments))
    seg = torch.cat([kind[torch.randint(len(kind), (share,), generator=generator)] for kind in evidence.segments])
    t = torch.rand(len(seg), 1, generator=generator)
    return surface, seg[:, 0] + t * (seg[:, 1] - seg[:, 0])


def _loss_terms(f_surface: torch.Tensor, f_free: torch.Tensor | None, sigma: float, kinds: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Cauchy surface and free-space terms (B,) of world-frame distances (B, P) and (B, Q); the free-space term is
    the sum over its ``kinds`` of evidence of each one's mean (they are drawn in equal shares)."""
    surface = torch.log1p((f_surface / sigma).square()).mean(-1)
    if f_free is None:
        return surface, torch.zeros_like(surface)
    return surface, torch.log1p((torch.relu(-f_free) / sigma).square()).mean(-1) * kinds


def _support_term(evidence: _Evidence, poses: _Poses, z_low: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B,): Cauchy cost of the shape's lowest point (``z_low`` (B,), normalised) standing off the support."""
    if evidence.support is None:
        return torch.zeros_like(poses.yaw)
    bottom = poses.centre @ evidence.up + z_low / poses.log_scale.exp()
    return torch.log1p(((bottom - evidence.support) / sigma).square())


# --------------------------------------------------------------------------- poses


@dataclass
class _Poses:
    """B hypotheses' poses as leaf tensors: yaw (B,), log scale (B,), centre (B, 3), tilt (B, 2) (about x and y)."""

    yaw: torch.Tensor
    log_scale: torch.Tensor
    centre: torch.Tensor
    tilt: torch.Tensor

    def parameters(self, full_rotation: bool) -> list[dict]:
        groups = [{"params": [self.yaw], "lr": 0.05}, {"params": [self.log_scale], "lr": 0.02},
                  {"params": [self.centre], "lr": 0.0}]
        if full_rotation:
            groups.append({"params": [self.tilt], "lr": 0.02})
        return groups

    def rotation(self, align: torch.Tensor) -> torch.Tensor:
        """(B, 3, 3): Rz(yaw) R_tilt A, the world-to-normalised rotation."""
        c, s = torch.cos(self.yaw), torch.sin(self.yaw)
        zero, one = torch.zeros_like(c), torch.ones_like(c)
        rz = torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)
        tx, ty = self.tilt[:, 0], self.tilt[:, 1]
        skew = torch.stack([zero, zero, ty, zero, zero, -tx, -ty, tx, zero], -1).reshape(-1, 3, 3)
        return rz @ torch.linalg.matrix_exp(skew) @ align

    def to_normalised(self, points: torch.Tensor, align: torch.Tensor) -> torch.Tensor:
        """World points (P, 3) -> each hypothesis's normalised frame (B, P, 3)."""
        scale = self.log_scale.exp()[:, None, None]
        return scale * (points[None] - self.centre[:, None]) @ self.rotation(align).transpose(1, 2)

    def take(self, rows) -> _Poses:
        return _Poses(*(t.detach()[rows].clone().requires_grad_(True) for t in (self.yaw, self.log_scale, self.centre, self.tilt)))


def _start_poses(evidence: _Evidence, obs: Observation, align: np.ndarray, z_range: torch.Tensor, yaws: int) -> _Poses:
    """Starting poses of every (shape, yaw) pair, shapes outermost: each shape scaled so that its height matches the
    observed points' extent along up, centred over them and pushed back from the sensor by a third of its width."""
    upright = obs.points @ align.T
    low, high = np.percentile(upright[:, 2], [1, 99])
    height = max(high - low, 1e-3)
    middle = np.median(upright[:, :2], axis=0)
    if obs.origins is not None:  # the visible side faces the sensor: the centre lies behind it
        view = (obs.points - obs.origins) @ align.T
        away = view[:, :2].mean(0)
        away = away / max(np.linalg.norm(away), 1e-12)
        middle = middle + away * np.ptp(upright[:, :2], axis=0).max() / 3.0
    scale = (z_range[:, 1] - z_range[:, 0]).clamp_min(0.05) / height  # normalised units per metre
    shapes = len(z_range)
    # the normalised z range [lo, hi] should land on [low, high]: lo / s + c_z = low
    centre_z = torch.as_tensor(low, dtype=torch.float32) - z_range[:, 0] / scale
    centre_up = torch.cat([torch.as_tensor(middle, dtype=torch.float32).expand(shapes, 2), centre_z[:, None]], 1)
    centre = centre_up @ torch.as_tensor(align, dtype=torch.float32)  # back to the world frame (A is orthonormal)
    yaw = torch.arange(yaws, dtype=torch.float32) * (2 * math.pi / yaws)
    return _Poses(yaw.repeat(shapes).requires_grad_(True), scale.log().repeat_interleave(yaws).requires_grad_(True),
                  centre.repeat_interleave(yaws, 0).requires_grad_(True), torch.zeros(shapes * yaws, 2, requires_grad=True))


def _grid_distance(grids: torch.Tensor, points_n: torch.Tensor) -> torch.Tensor:
    """Normalised distances (B, P) read trilinearly off ``grids`` (B, R, R, R) at points (B, P, 3); a point outside
    the grid reads its nearest border node plus its distance to it."""
    inside = points_n.clamp(-GRID_HALF_WIDTH, GRID_HALF_WIDTH)
    coords = (inside / GRID_HALF_WIDTH).reshape(len(points_n), -1, 1, 1, 3)
    read = torch.nn.functional.grid_sample(grids[:, None], coords, align_corners=True, padding_mode="border")
    return read.reshape(len(points_n), -1) + (points_n - inside).norm(dim=-1)


# --------------------------------------------------------------------------- fitting


@dataclass
class _Refined:
    """A hypothesis after the network's refinement: its loss (and terms), pose and code cloud (K, C), (K, 3)."""

    loss: float
    terms: dict[str, float]
    rotation: np.ndarray  # (3, 3) world to normalised
    scale: float  # normalised units per metre
    centre: np.ndarray  # (3,) world
    yaw: float
    codes: torch.Tensor
    positions: torch.Tensor


@dataclass
class _Hypothesis:
    """One (shape, starting yaw) outcome: its pose after the search, and its loss."""

    shape: int
    start_yaw: float
    poses: _Poses
    loss: float
    yaw: float  # the yaw the search ended on (the poses move on if the hypothesis is refined)
    refined: _Refined | None = None


def fit_observation(model, obs: Observation, up=(0.0, 0.0, 1.0), options: FitOptions | None = None,
                    name: str = "observed", progress: bool = False):
    """A NeuralShape in the world frame fitted to ``obs`` (see the module docstring); ``shape.fit`` records how."""
    from .meshes import Similarity, rotation_between
    from .neural import NeuralShape
    from .progress import task_bar

    options = options or FitOptions()
    started = time.perf_counter()
    if not isinstance(obs, Observation):
        raise InputError(f"fit_observation takes a zoo.Observation (from_depth, from_points, from_mujoco), got {type(obs).__name__}")
    up = np.asarray(up, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or not np.linalg.norm(up) > 0:
        raise InputError(f"up must be a non-zero 3-vector, got {up.tolist()}")
    up = up / np.linalg.norm(up)
    _refuse_a_plane(obs)
    align = rotation_between(up, np.array([0.0, 0.0, 1.0]))
    align_t = torch.as_tensor(align, dtype=torch.float32)
    evidence = _evidence(obs, up, options.sigma, options.standing)
    prior = category_prior(model, progress=progress)
    n_train = len(model.shapes)
    shapes = [n_train] if options.codes == "mean" else list(range(n_train))
    generator = torch.Generator().manual_seed(options.seed)
    refined = options.refine_hypotheses if options.codes == "fit" else 1
    with torch.enable_grad(), task_bar(progress, "fit observation", options.grid_iters + refined * options.refine_iters) as bar:
        searched = _grid_search(prior, shapes, evidence, obs, align, align_t, options, generator, bar)
        chosen = _distinct_yaws(searched, refined)
        for h in chosen:
            h.refined = _refine(model, prior, h, evidence, align_t, options, generator, bar)
    best = min(chosen, key=lambda h: h.refined.loss)
    fitted = best.refined
    similarity = Similarity(fitted.scale, fitted.rotation, -fitted.scale * fitted.rotation @ fitted.centre)
    shape = NeuralShape(name, model.sdf.decoder, model.sdf.config, fitted.codes, fitted.positions, similarity, model)
    shape.fit = _record(model, obs, up, options, searched, chosen, best, shape, time.perf_counter() - started)
    return shape


def _refuse_a_plane(obs: Observation) -> None:
    """An observation of a plane (the table alone, a mask that missed the object) cannot be fitted: say so."""
    points = obs.points - obs.points.mean(0)
    if len(points) < 10:
        raise InputError(f"the observation has {len(points)} points; fitting a shape needs at least 10 (more views, "
                         "a closer camera, a mask that covers the object)")
    singular = np.linalg.svd(points[:: max(1, len(points) // 20000)], compute_uv=False)
    spread = singular / math.sqrt(len(points[:: max(1, len(points) // 20000)]))
    if spread[2] < PLANE_FRACTION * spread[0]:
        raise InputError("the observed points lie on one plane (the table alone? a mask that missed the object?): "
                         "there is no object to fit; check the mask or the segmentation")


def _grid_search(prior: CategoryPrior, shapes: list[int], evidence: _Evidence, obs: Observation, align: np.ndarray,
                 align_t: torch.Tensor, options: FitOptions, generator: torch.Generator, bar) -> list[_Hypothesis]:
    """Every (shape, starting yaw) hypothesis's pose fitted on the grids; -> the best shape of each starting yaw."""
    index = torch.as_tensor(shapes)
    poses = _start_poses(evidence, obs, align, prior.z_range[index], options.yaws)
    grids = prior.grids[index].repeat_interleave(options.yaws, 0)
    z_low = prior.z_range[index, 0].repeat_interleave(options.yaws)
    groups = poses.parameters(options.full_rotation)
    groups[2]["lr"] = 0.02 * obs.extent
    optimiser = torch.optim.Adam(groups)
    for _ in range(options.grid_iters):
        points, free = _draw(evidence, options.points, options.free_points, generator)
        loss = _grid_loss(grids, z_low, poses, points, free, align_t, evidence, options.sigma)
        optimiser.zero_grad(set_to_none=True)
        loss.sum().backward()
        optimiser.step()
        bar.advance()
    with torch.no_grad():
        points, free = _draw(evidence, EVALUATION_DRAW * options.points, EVALUATION_DRAW * options.free_points, generator)
        final = _grid_loss(grids, z_low, poses, points, free, align_t, evidence, options.sigma)
    final = final.reshape(len(shapes), options.yaws)
    out = []
    for y in range(options.yaws):
        k = int(final[:, y].argmin())
        row = k * options.yaws + y
        out.append(_Hypothesis(shapes[k], 2 * math.pi * y / options.yaws, poses.take([row]), float(final[k, y]),
                               float(poses.yaw.detach()[row])))
    return out


def _grid_loss(grids, z_low, poses: _Poses, points, free, align_t, evidence: _Evidence, sigma: float) -> torch.Tensor:
    scale = poses.log_scale.exp()[:, None]
    f_surface = _grid_distance(grids, poses.to_normalised(points, align_t)) / scale
    f_free = None if free is None else _grid_distance(grids, poses.to_normalised(free, align_t)) / scale
    surface, free_term = _loss_terms(f_surface, f_free, sigma, len(evidence.segments))
    return surface + free_term + _support_term(evidence, poses, z_low, sigma)


def _distinct_yaws(hypotheses: list[_Hypothesis], count: int) -> list[_Hypothesis]:
    """The ``count`` best hypotheses whose fitted yaws differ by more than 30 degrees (or whose shapes differ)."""
    chosen = []
    for h in sorted(hypotheses, key=lambda h: h.loss):
        if all(h.shape != c.shape or angle_between(h.yaw, c.yaw) > math.radians(30) for c in chosen):
            chosen.append(h)
        if len(chosen) == count:
            break
    return chosen


def angle_between(a: float, b: float) -> float:
    """The angle (radians, in [0, pi]) between two directions given as angles (radians) in a plane."""
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def _refine(model, prior: CategoryPrior, h: _Hypothesis, evidence: _Evidence, align_t: torch.Tensor,
            options: FitOptions, generator: torch.Generator, bar) -> _Refined:
    """Pose (and, with ``codes="fit"``, the code cloud) of one hypothesis refined through the network."""
    from .neural import decode

    sdf = model.sdf
    device = sdf.codes.device
    if h.shape < len(model.shapes):
        codes0, positions0 = sdf.codes[h.shape].detach().clone(), sdf.positions[h.shape].detach().clone()
    else:
        codes0, positions0 = prior.mean_codes.to(device), prior.mean_positions.to(device)
    learn_codes = options.codes == "fit"
    z_low = prior.z_range[h.shape, :1]
    codes = codes0.clone().requires_grad_(learn_codes)
    positions = positions0.clone().requires_grad_(learn_codes)
    poses = h.poses
    groups = poses.parameters(options.full_rotation)
    groups[0]["lr"], groups[1]["lr"] = 0.01, 0.005
    groups[2]["lr"] = 0.002 * float(1.0 / poses.log_scale.detach().exp())
    if learn_codes:
        groups += [{"params": [codes], "lr": 3e-3}, {"params": [positions], "lr": 3e-4}]
    optimiser = torch.optim.Adam(groups)
    decoder = sdf.decoder
    frozen = [p.requires_grad for p in decoder.parameters()]
    decoder.requires_grad_(False)

    def loss_of(points, free):
        everything = points if free is None else torch.cat([points, free])
        f = decode(decoder, poses.to_normalised(everything.to(device), align_t.to(device)), positions[None], codes[None],
                   sdf.config.eps) / poses.log_scale.exp()[:, None]
        surface, free_term = _loss_terms(f[:, : len(points)], None if free is None else f[:, len(points):], options.sigma,
                                         len(evidence.segments))
        code_prior = options.prior * ((codes - codes0).square().mean() / prior.code_std**2
                                      + (positions - positions0).square().mean() / prior.position_std**2)
        terms = {"surface": surface.sum(), "free_space": free_term.sum(),
                 "support": _support_term(evidence, poses, z_low, options.sigma).sum(),
                 "prior": code_prior if learn_codes else torch.zeros(())}
        return sum(terms.values()), terms

    try:
        for _ in range(options.refine_iters):
            points, free = _draw(evidence, options.points, options.free_points, generator)
            loss, _ = loss_of(points, free)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            bar.advance()
        with torch.no_grad():
            points, free = _draw(evidence, EVALUATION_DRAW * options.points, EVALUATION_DRAW * options.free_points,
                                 generator)
            loss, terms = loss_of(points, free)
    finally:
        for p, r in zip(decoder.parameters(), frozen):
            p.requires_grad_(r)
    return _Refined(float(loss), {k: float(v) for k, v in terms.items()},
                    poses.rotation(align_t.to(poses.yaw)).detach()[0].double().numpy(), float(poses.log_scale.detach().exp()),
                    poses.centre.detach()[0].double().numpy(), float(poses.yaw.detach()), codes.detach(), positions.detach())


def _record(model, obs: Observation, up: np.ndarray, options: FitOptions, searched: list[_Hypothesis],
            chosen: list[_Hypothesis], best: _Hypothesis, shape, seconds: float) -> dict:
    """``shape.fit``: the observation's size, the options, the loss terms, the chosen and rejected poses, the scale
    and the residual at the observed points."""
    names = [*model.shapes, "mean"]
    residual = shape(torch.as_tensor(obs.points[:: max(1, len(obs.points) // 20000)], dtype=torch.float32)).abs().numpy()

    def pose_of(h: _Hypothesis) -> dict:
        out = {"start_shape": names[h.shape], "start_yaw_deg": round(math.degrees(h.start_yaw), 3),
               "yaw_deg": round(math.degrees(h.yaw) % 360.0, 3), "search_loss": h.loss}
        if h.refined is not None:
            out.update(refined_loss=h.refined.loss, refined_yaw_deg=round(math.degrees(h.refined.yaw) % 360.0, 3))
        return out

    return {
        "observation": {"points": len(obs.points), "views": obs.views, "origins": obs.origins is not None,
                        "normals": obs.normals is not None,
                        "free_rays": 0 if obs.free_origins is None else len(obs.free_origins)},
        "up": up.tolist(), "codes": options.codes, "full_rotation": options.full_rotation,
        "prior": {"kind": "gaussian about the start shape's code cloud", "weight": options.prior,
                  "code_std": model._category_prior[1].code_std, "start_shape": names[best.shape]},
        "options": {"yaws": options.yaws, "grid_iters": options.grid_iters, "refine_iters": options.refine_iters,
                    "sigma_m": options.sigma, "seed": options.seed},
        "loss": {"total": best.refined.loss, **best.refined.terms},
        "pose": {**pose_of(best), "centre_m": best.refined.centre.tolist()},
        "rejected": [pose_of(h) for h in searched if h is not best],
        "scale": {"normalised_per_m": best.refined.scale, "size_m": 1.0 / best.refined.scale},
        "residual_mm": {"median": float(np.median(residual) * 1e3), "p90": float(np.percentile(residual, 90) * 1e3)},
        "seconds": seconds,
    }
