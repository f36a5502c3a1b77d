"""Tiny model packages for the registry, hub and manifest tests: random weights, made in seconds."""

from __future__ import annotations

from pathlib import Path

import torch

from zoo.model import Model

MUG_SHAPES = ["hoi4d_mug_0001", "shapenet_mug_128ecbc1", "edf_mug1"]
BOTTLE_SHAPES = ["edf_bottle0", "bulletarm_bottle1"]



def make_fit_output(directory: Path, category: str, shapes: list[str], seed: int = 0) -> Path:
    """A tiny `zoo fit-category` output written by Model.save: random weights, a cache file beside them."""
    from zoo.detector import AmortizedDetector
    from zoo.meshes import Similarity
    from zoo.neural import NeuralSDF, NeuralSDFConfig

    g = torch.Generator().manual_seed(seed)
    sdf = NeuralSDF(NeuralSDFConfig(n_codes=4, code_dim=8, hidden=(8,)), len(shapes), generator=g)
    detector = AmortizedDetector(feature_dim=8, hidden=8, weight_hidden=4)
    model = Model(category, "0.0.0", sdf, shapes, {s: Similarity.identity() for s in shapes}, detector=detector)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "sdf_samples.h5").write_bytes(b"a stage cache that must not be packaged")
    model.save(
        directory,
        metrics={"sdf_abs_error_p50": 0.0012, "command": f"zoo eval {category}"},
        training_data={"category_manifest": f"manifests/categories/{category}.toml", "inputs": {s: "0" * 64 for s in shapes}},
        category=category,
        license="",
    )
    return directory


def flip_byte(path: Path, offset: int = -1) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
