"""A loaded sdfzoo package: a category NeuralSDF, its shapes, and (optionally) its detector.

Package directory layout (``Model.save`` writes it, ``Model.from_directory`` reads it)::

    config.json        {format_version: 1, name, version, category, shapes: [...],
                        sdf: {NeuralSDFConfig fields, type, n_params, storage_dtype},
                        detector: {AmortizedDetector.config()} | null,
                        similarities: {stem: Similarity.to_dict()}, metrics: {}, license,
                        training_data: {}}
    sdf.safetensors    decoder.* weights, ``codes`` (S, K, C), ``positions`` (S, K, 3);
                       fp16 allowed, cast to float32 on load
    detector.safetensors   the detector's state dict (only with a detector)
    README.md          the model card (written by ``zoo package``)
    SHA256SUMS         sha256 of every other file
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from .errors import DataError, InputError, ModelNotFoundError
from .neural import NeuralSDF, NeuralSDFConfig, NeuralShape, count_parameters, decode, init_code_cloud
from .progress import task_bar

FORMAT_VERSION = 1
CONFIG = "config.json"
SDF_WEIGHTS = "sdf.safetensors"
DETECTOR_WEIGHTS = "detector.safetensors"


class Model:
    """A category NeuralSDF with its fitted shapes (and detector): what ``zoo.load`` returns.

    ``name``, ``version``, ``path`` (package directory or None), ``shapes`` (stems),
    ``config`` (the package's config.json as a dict), ``sdf`` (the :class:`NeuralSDF` module),
    ``similarities`` ({stem: Similarity}), ``detector`` (an ``AmortizedDetector`` or None).
    """

    def __init__(self, name: str, version: str, sdf: NeuralSDF, shapes: list[str], similarities: dict,
                 config: dict | None = None, detector=None, path: str | os.PathLike | None = None):
        if len(shapes) != sdf.n_shapes:
            raise InputError(f"{len(shapes)} shape names for a NeuralSDF with {sdf.n_shapes} code clouds")
        self.name = name
        self.version = version
        self.sdf = sdf.requires_grad_(False).eval()
        self.shapes = list(shapes)
        self.similarities = dict(similarities)
        self.detector = detector.requires_grad_(False).eval() if detector is not None else None
        self.path = Path(path) if path is not None else None
        self.config = config if config is not None else {}
        self._index = {s: i for i, s in enumerate(self.shapes)}

    @property
    def sdf_config(self) -> NeuralSDFConfig:
        return self.sdf.config

    @property
    def device(self) -> torch.device:
        return self.sdf.codes.device

    def __repr__(self):
        det = "with detector" if self.detector is not None else "no detector"
        return f"Model({self.name!r}, version={self.version!r}, shapes={len(self.shapes)}, {det})"

    # ------------------------------------------------------------------ shapes

    def shape(self, stem: str) -> NeuralShape:
        """The fitted shape ``stem`` as an SDF in its source mesh's frame and units."""
        if stem not in self._index:
            some = ", ".join(self.shapes[:8]) + (", ..." if len(self.shapes) > 8 else "")
            raise ModelNotFoundError(f"model {self.name!r} has no shape {stem!r}; it has {len(self.shapes)}: {some} "
                                     "(see model.shapes), or fit a new mesh with model.fit_codes(path)")
        i = self._index[stem]
        return NeuralShape(stem, self.sdf.decoder, self.sdf.config, self.sdf.codes[i], self.sdf.positions[i],
                           self.similarities.get(stem), self)

    def fit_codes(self, mesh_path: str | os.PathLike, iters: int = 500, seed: int = 0, up="z", n_points: int = 100_000,
                  points_per_iter: int = 1024, lr: float = 1e-2, lr_positions: float = 1e-3, name: str | None = None,
                  progress: bool = False) -> NeuralShape:
        """Fit an unseen mesh: normalise and sample it, then optimise a fresh code cloud, decoder frozen.

        ``up`` is the mesh's up axis ("z", "y", ...). Returns a NeuralShape in the mesh's frame
        and units (attached to this model, so ``detect`` works on it; ``shape.fit`` records the
        mesh's sha256 and these arguments; ``shape.save(path)`` keeps it). Sampling exact signed
        distances needs libigl, from the ``sdfzoo[pipeline]`` extra.
        """
        from .files import sha256_file
        from .meshes import load_mesh, normalise, sample_sdf

        mesh_path = Path(mesh_path)
        mesh, similarity = normalise(load_mesh(mesh_path), up)
        points, sdf = sample_sdf(mesh, n_points, seed)
        codes, positions = fit_code_cloud(self.sdf, torch.as_tensor(points), torch.as_tensor(sdf), iters=iters,
                                          seed=seed, points_per_iter=points_per_iter, lr=lr,
                                          lr_positions=lr_positions, clamp=self.config.get("fit", {}).get("clamp", 0.1),
                                          progress=progress)
        shape = NeuralShape(name or mesh_path.stem, self.sdf.decoder, self.sdf.config, codes, positions, similarity, self)
        shape.fit = {"mesh": mesh_path.name, "mesh_sha256": sha256_file(mesh_path), "up": str(up), "iters": int(iters),
                     "seed": int(seed), "n_points": int(n_points), "points_per_iter": int(points_per_iter),
                     "lr": float(lr), "lr_positions": float(lr_positions)}
        return shape

    def fit_observation(self, obs, up=(0.0, 0.0, 1.0), name: str = "observed", progress: bool = False,
                        **options) -> NeuralShape:
        """Shape, pose and scale of an unseen object from what a sensor saw of it: a NeuralShape in the world frame.

        ``obs`` is a :class:`zoo.Observation` (``from_depth``, ``from_points``, ``from_mujoco``); ``up`` (3,) the
        world's up, about which the object's yaw is searched (it stands upright on a surface; ``full_rotation=True``
        fits a tilt too). The code cloud starts from the train shape that explains the view best and stays near it
        (the category's prior for the unseen side); the similarity (scale, yaw, centre) is fitted with it.
        ``shape.fit`` records the observation's size, the loss terms, the chosen and the rejected poses (one per
        starting yaw), the fitted size and the residual at the observed points (mm). Keyword ``options`` are
        :class:`zoo.completion.FitOptions` fields (``yaws``, ``refine_iters``, ``sigma``, ``prior``, ``codes``:
        "fit", or the baselines "nearest" and "mean", ``seed``, ...). No libigl needed.
        """
        from dataclasses import fields

        from .completion import FitOptions, fit_observation

        unknown = set(options) - {f.name for f in fields(FitOptions)}
        if unknown:
            raise InputError(f"fit_observation got unknown options {sorted(unknown)}; it takes "
                             f"{', '.join(f.name for f in fields(FitOptions))}")
        return fit_observation(self, obs, up, FitOptions(**options), name=name, progress=progress)

    # ------------------------------------------------------------------ detection

    def detect(self, shape, triangles, polish: bool = True) -> torch.Tensor:
        """Amortized minimum-SDF barycentrics of ``triangles`` (M, 3, 3) against ``shape`` -> (M, 3).

        ``polish`` (default): a triangle whose lowest vertex satisfies the KKT conditions (its gradient
        there, one query per distinct vertex) is answered at that vertex; the others take the network's
        answer and ``zoo.amortized.POLISH_ROUNDS`` Frank-Wolfe steps with a line search (each one
        value-and-gradient query and up to ``zoo.amortized.POLISH_LINE_STEPS`` value queries);
        ``polish=False``: the forward pass alone. Zero triangles give (0, 3).
        """
        if self.detector is None:
            raise ModelNotFoundError(
                f"model {self.name!r} has no detector (its package holds no {DETECTOR_WEIGHTS}); "
                "train one with `zoo fit-category` (detector stage), or use zoo.solvers.frank_wolfe(shape, triangles)"
            )
        from .amortized import detect

        return detect(self.detector, shape, triangles, polish=polish)

    # ------------------------------------------------------------------ devices

    def to(self, device) -> Model:
        """Move the networks to ``device`` (in place); returns self."""
        self.sdf.to(device)
        if self.detector is not None:
            self.detector.to(device)
        return self

    # ------------------------------------------------------------------ files

    @classmethod
    def from_directory(cls, path: str | os.PathLike, name: str | None = None, version: str | None = None,
                       verify: bool = True, device: str | torch.device = "cpu") -> Model:
        """Load a package directory (layout in the module docstring); verify SHA256SUMS first unless told not to."""
        from .files import verify_directory

        path = Path(path).expanduser()
        if not path.is_dir():
            raise ModelNotFoundError(f"{path} is not a package directory; pass the folder that holds {CONFIG}")
        if verify:
            verify_directory(path)
        config = read_config(path)
        sdf = load_sdf_weights(path / SDF_WEIGHTS, config)
        detector = load_detector(path, config)
        similarities = read_similarities(config)
        model = cls(name or config["name"], version or config["version"], sdf, list(config["shapes"]), similarities,
                    config, detector, path)
        return model.to(device) if str(device) != "cpu" else model

    def save(self, directory: str | os.PathLike, fp16: bool = True, metrics: dict | None = None,
             license: str | None = None, training_data: dict | None = None, category: str | None = None,
             extra: dict | None = None) -> Path:
        """Write this model as a package directory; return it.

        ``fp16`` stores the code clouds (codes and positions) in float16, halving the file; the
        decoder stays float32. Files are written atomically, SHA256SUMS last.
        """
        from .files import atomic_path, atomic_write_text, write_checksums

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        config = self.package_config(fp16, metrics, license, training_data, category, extra)
        save_sdf_weights(directory / SDF_WEIGHTS, self.sdf, fp16)
        det_path = directory / DETECTOR_WEIGHTS
        if self.detector is not None:
            from safetensors.torch import save_file

            with atomic_path(det_path) as tmp:
                save_file({k: v.detach().float().cpu().contiguous() for k, v in self.detector.state_dict().items()}, str(tmp))
        elif det_path.exists():
            det_path.unlink()  # a stale detector of an earlier model must not be listed as this one's
        atomic_write_text(directory / CONFIG, json.dumps(config, indent=1, sort_keys=True) + "\n")
        write_checksums(directory)
        self.path, self.config = directory, config
        return directory

    def package_config(self, fp16: bool = True, metrics: dict | None = None, license: str | None = None,
                       training_data: dict | None = None, category: str | None = None, extra: dict | None = None) -> dict:
        """config.json for this model; keys not given keep the values this model was loaded with."""
        old = self.config
        sdf = {**self.sdf.config.to_dict(), "type": "dcc-dif", "n_params": count_parameters(self.sdf.decoder),
               "storage_dtype": "float16" if fp16 else "float32"}
        config = {
            **{k: v for k, v in old.items()},
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "version": self.version,
            "category": category if category is not None else old.get("category", self.name),
            "shapes": self.shapes,
            "sdf": sdf,
            "detector": self.detector.config() if self.detector is not None else None,
            "similarities": {s: self.similarities[s].to_dict() for s in self.shapes if self.similarities.get(s) is not None},
            "metrics": metrics if metrics is not None else old.get("metrics", {}),
            "license": license if license is not None else old.get("license", "unspecified"),
            "training_data": training_data if training_data is not None else old.get("training_data", {}),
        }
        config.update(extra or {})
        return config


# --------------------------------------------------------------------------- fitting one shape


def fit_code_cloud(sdf: NeuralSDF, points: torch.Tensor, target: torch.Tensor, iters: int = 500, seed: int = 0,
                   points_per_iter: int = 4096, lr: float = 1e-2, lr_positions: float = 1e-3, clamp: float = 0.1,
                   progress: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Optimise one fresh code cloud against SDF samples with the decoder frozen.

    points (N, 3) and target (N,) in the normalised frame -> codes (K, C), positions (K, 3).
    Clamped L1 loss, Adam; deterministic given ``seed``.
    """
    if points.ndim != 2 or points.shape[-1] != 3 or target.shape != points.shape[:1] or len(points) == 0:
        raise InputError(f"fit_code_cloud needs points (N, 3) and sdf (N,), got {tuple(points.shape)} and {tuple(target.shape)}")
    device = sdf.codes.device
    g = torch.Generator().manual_seed(seed)
    codes, positions = init_code_cloud(sdf.config, 1, g)
    codes = codes.to(device).requires_grad_(True)
    positions = positions.to(device).requires_grad_(True)
    points, target = points.to(device, torch.float32), target.to(device, torch.float32)
    decoder = sdf.decoder
    frozen = [p.requires_grad for p in decoder.parameters()]
    decoder.requires_grad_(False)
    opt = torch.optim.Adam([{"params": [codes], "lr": lr}, {"params": [positions], "lr": lr_positions}])
    try:
        with task_bar(progress, "fit codes", iters) as bar:
            for _ in range(iters):
                rows = torch.randint(len(points), (points_per_iter,), generator=g).to(device)
                pred = decode(decoder, points[rows].unsqueeze(0), positions, codes, sdf.config.eps).squeeze(0)
                loss = (pred.clamp(-clamp, clamp) - target[rows].clamp(-clamp, clamp)).abs().mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                bar.advance()
    finally:
        for p, r in zip(decoder.parameters(), frozen):
            p.requires_grad_(r)
    return codes.detach()[0], positions.detach()[0]


# --------------------------------------------------------------------------- reading and writing


def read_config(path: Path) -> dict:
    file = path / CONFIG
    try:
        config = json.loads(file.read_text())
    except FileNotFoundError:
        raise DataError(f"{path} has no {CONFIG}: it is not an sdfzoo package (make one with `zoo fit-category`)") from None
    except json.JSONDecodeError as exc:
        raise DataError(f"{file} is not valid JSON ({exc}); re-create the package") from exc
    if config.get("format_version") != FORMAT_VERSION:
        raise DataError(f"{file} has format_version {config.get('format_version')!r}; this sdfzoo reads "
                        f"{FORMAT_VERSION}: upgrade sdfzoo or re-create the package")
    missing = [k for k in ("name", "version", "shapes", "sdf") if k not in config]
    if missing:
        raise DataError(f"{file} lacks {', '.join(missing)}; re-create the package")
    return config


def read_similarities(config: dict) -> dict:
    from .meshes import Similarity

    return {stem: Similarity.from_dict(d) for stem, d in config.get("similarities", {}).items()}


def save_sdf_weights(path: Path, sdf: NeuralSDF, fp16: bool) -> None:
    from .files import write_safetensors

    cloud_dtype = torch.float16 if fp16 else torch.float32
    tensors = {f"decoder.{k}": v.detach().float().cpu().contiguous() for k, v in sdf.decoder.state_dict().items()}
    tensors["codes"] = sdf.codes.detach().to("cpu", cloud_dtype).contiguous()
    tensors["positions"] = sdf.positions.detach().to("cpu", cloud_dtype).contiguous()
    write_safetensors(path, tensors, metadata={"format": "sdfzoo-dcc-dif", "format_version": str(FORMAT_VERSION)})


def load_sdf_weights(path: Path, config: dict) -> NeuralSDF:
    """The NeuralSDF of a package, float32 whatever the storage dtype."""
    from safetensors.torch import load_file

    if not path.is_file():
        raise DataError(f"{path} is missing; the package is incomplete: re-create it")
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types for torn files
        raise DataError(f"{path} is not a readable safetensors file ({exc}); re-create the package") from exc
    sdf_config = NeuralSDFConfig.from_dict(config["sdf"])
    if "codes" not in tensors or "positions" not in tensors:
        raise DataError(f"{path} lacks 'codes' or 'positions'; it is not a NeuralSDF weights file")
    n_shapes = tensors["codes"].shape[0]
    if n_shapes != len(config["shapes"]):
        raise DataError(f"{path} holds {n_shapes} code clouds but config.json lists {len(config['shapes'])} shapes; "
                        "re-create the package")
    sdf = NeuralSDF(sdf_config, n_shapes)
    state = {k: v.float() for k, v in tensors.items()}
    try:
        sdf.load_state_dict(state)
    except RuntimeError as exc:
        raise DataError(f"{path} does not match the sizes in config.json ({exc}); re-create the package") from exc
    return sdf


def load_detector(path: Path, config: dict):
    """The package's detector, or None when it has none."""
    det_config = config.get("detector")
    file = path / DETECTOR_WEIGHTS
    if not det_config:
        return None
    if not file.is_file():
        raise DataError(f"config.json describes a detector but {file} is missing; re-create the package")
    from safetensors.torch import load_file

    from .detector import AmortizedDetector

    detector = AmortizedDetector.from_config(det_config)
    try:
        detector.load_state_dict({k: v.float() for k, v in load_file(str(file)).items()})
    except Exception as exc:
        raise DataError(f"{file} does not match the detector config ({exc}); re-create the package") from exc
    return detector
