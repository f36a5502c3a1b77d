"""One fitted shape on disk: what ``NeuralShape.save`` writes and ``zoo.load_shape`` reads back.

A shape fitted to an unseen mesh (``Model.fit_codes``, ``zoo fit-codes``) is its code cloud,
meaningful only with the decoder it was fitted against. The file is one safetensors file::

    codes       (K, C) float32       positions   (K, 3) float32 (normalised frame)
    __metadata__ (strings):
        format = "sdfzoo-shape", format_version = "1", name
        model = "NAME@X.Y.Z"         the model the codes were fitted against, loaded back by that name
        model_sha256                 sha256 of that model's decoder weights and NeuralSDF config
                                     (:func:`model_sha256`), what the codes depend on
        tensors_sha256               sha256 of codes and positions (a damaged file is refused)
        similarity                   the mesh's Similarity (JSON): source frame -> normalised frame
        fit, metrics                 JSON: how it was fitted (mesh, its sha256, iterations, seed, up axis)
                                     and how well (``zoo fit-codes``: near-surface error, sign agreement)

:func:`zoo.registry.load_shape` loads the model through the registry (or takes one), refuses it unless
its ``model_sha256`` matches, and returns the NeuralShape attached to it, in the mesh's frame and units.
This module is the file format alone, below ``zoo.neural`` in the imports.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

from .errors import ChecksumError, DataError, InputError, ModelNotFoundError

FORMAT = "sdfzoo-shape"
FORMAT_VERSION = "1"


def model_sha256(sdf_config, decoder: torch.nn.Module) -> str:
    """sha256 of a NeuralSDF's config (dict or NeuralSDFConfig) and decoder weights (names and float32 bytes)."""
    config = sdf_config if isinstance(sdf_config, dict) else sdf_config.to_dict()
    h = hashlib.sha256(json.dumps(config, sort_keys=True).encode())
    for name, tensor in decoder.state_dict().items():
        h.update(name.encode())
        h.update(tensor.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def tensors_sha256(codes: torch.Tensor, positions: torch.Tensor) -> str:
    h = hashlib.sha256()
    for t in (codes, positions):
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def save_shape(shape, path: str | os.PathLike, fit: dict | None = None, metrics: dict | None = None) -> Path:
    """Write ``shape`` (a NeuralShape attached to a model) to ``path`` atomically; -> the path.
    ``fit`` and ``metrics`` (JSON-able dicts) default to the shape's own ``fit`` and ``metrics``."""
    from .files import write_safetensors

    model = shape.model
    if model is None or not getattr(model, "name", None) or not getattr(model, "version", None):
        raise InputError(f"shape {shape.name!r} is not attached to a model with a name and version, so no file could "
                         "say which decoder its codes need; save shapes from zoo.load(NAME).shape(...) or .fit_codes(...)")
    codes = shape.codes.detach().to("cpu", torch.float32).contiguous()
    positions = shape.positions.detach().to("cpu", torch.float32).contiguous()
    try:
        fit_json = json.dumps(shape.fit if fit is None else fit, sort_keys=True, allow_nan=False)
        metrics_json = json.dumps(shape.metrics if metrics is None else metrics, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"fit and metrics must be JSON-serialisable dicts of finite numbers: {exc}") from exc
    meta = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "name": shape.name,
        "model": f"{model.name}@{model.version}", "model_sha256": model_sha256(shape.config, shape.decoder),
        "tensors_sha256": tensors_sha256(codes, positions), "similarity": shape.similarity.to_json(),
        "fit": fit_json, "metrics": metrics_json,
    }
    return write_safetensors(Path(path), {"codes": codes, "positions": positions}, metadata=meta)


def read_shape_file(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """codes (K, C), positions (K, 3) and the metadata of a shape file, its tensors verified against their sha256."""
    from safetensors import safe_open

    path = Path(path).expanduser()
    if not path.is_file():
        raise ModelNotFoundError(f"{path} does not exist; write a shape file with shape.save(path) or "
                                 "`zoo fit-codes MODEL MESH --out PATH`")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for torn or foreign files
        raise DataError(f"{path} is not a readable safetensors file ({exc}); write it again with shape.save") from exc
    if meta.get("format") != FORMAT:
        raise DataError(f"{path} is not an sdfzoo shape file (format {meta.get('format')!r}); a model package is "
                        "loaded with zoo.load(DIRECTORY), a shape file is written by shape.save or `zoo fit-codes --out`")
    if meta.get("format_version") != FORMAT_VERSION:
        raise DataError(f"{path} has shape format_version {meta.get('format_version')!r}; this sdfzoo reads "
                        f"{FORMAT_VERSION}: upgrade sdfzoo or fit the shape again")
    missing = [k for k in ("name", "model", "model_sha256", "tensors_sha256", "similarity") if k not in meta] + [
        k for k in ("codes", "positions") if k not in tensors]
    if missing:
        raise DataError(f"{path} lacks {', '.join(missing)}; write it again with shape.save")
    codes, positions = tensors["codes"].float(), tensors["positions"].float()
    if tensors_sha256(codes, positions) != meta["tensors_sha256"]:
        raise ChecksumError(f"{path}: its codes or positions do not match their recorded sha256 (the file is damaged "
                            "or was edited); write it again with shape.save or `zoo fit-codes --out`")
    return codes, positions, meta
