"""sdfzoo runtime: neural SDFs, amortized NeuralSDF-triangle collision detection, pretrained models.

``import zoo`` loads only torch, numpy and (lazily) trimesh and safetensors; nothing from the
training pipeline.
"""

from __future__ import annotations

from . import errors, geometry
from .sdf import SDF, Box, Capsule, SDFBase, Sphere, Torus, TransformedSDF

__version__ = "0.1.0"
