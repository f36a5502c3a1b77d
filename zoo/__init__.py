"""sdfzoo runtime: neural SDFs, amortized NeuralSDF-triangle collision detection, pretrained models.

``import zoo`` loads only torch, numpy and (lazily) trimesh and safetensors; nothing from the
training pipeline.
"""

from __future__ import annotations

from . import errors, geometry, solvers
from .coherence import CoherentCollider
from .collision import Contacts, collide
from .model import Model
from .neural import NeuralSDF, NeuralShape
from .registry import list_models, load
from .sdf import SDF, Box, Capsule, SDFBase, Sphere, Torus, TransformedSDF
from .voxel import VoxelSDF

__version__ = "0.1.0"

# The public contract (docs/DESIGN.md): what tests, benchmarks and the README rely on.
__all__ = [
    "SDF",
    "Box",
    "Capsule",
    "CoherentCollider",
    "Contacts",
    "Model",
    "NeuralSDF",
    "NeuralShape",
    "SDFBase",
    "Sphere",
    "Torus",
    "TransformedSDF",
    "VoxelSDF",
    "collide",
    "errors",
    "geometry",
    "list_models",
    "load",
    "solvers",
]
