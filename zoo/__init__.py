"""sdfzoo runtime: neural SDFs, amortized NeuralSDF-triangle collision detection, pretrained models.

``import zoo`` loads only torch, numpy and (lazily) trimesh and safetensors; nothing from the
training pipeline.
"""

from __future__ import annotations

from . import errors, geometry
from . import solvers
from .sdf import SDF, Box, Capsule, SDFBase, Sphere, Torus, TransformedSDF
from .collide import Contacts, collide
from .voxel import VoxelSDF
from .registry import list_models, load
from .model import Model
from .neural import NeuralSDF, NeuralShape

__version__ = "0.1.0"
