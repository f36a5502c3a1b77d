"""sdfzoo runtime: neural SDFs, amortized NeuralSDF-triangle collision detection, pretrained models.

``import zoo`` imports nothing but this file: each public name below is imported on first use
(PEP 562 module ``__getattr__``), so ``import zoo`` loads no h5py, typer, mujoco or pipeline
module, and code that imports one submodule (``from zoo.neural import NeuralSDF``) does not run,
or depend on, the others. ``zoo.collide``, ``from zoo import load`` and ``zoo.solvers.frank_wolfe``
work as with eager imports.
"""

from __future__ import annotations

import importlib
import importlib.util

__version__ = "0.1.0"

# Public name -> the submodule that defines it. Strings, not import statements, on purpose: a
# stage's code digest (pipeline.stages) follows import statements, and a stage that imports
# zoo.neural must not be rerun by an edit of zoo.collision.
_EXPORTS = {
    "SDF": "sdf", "Box": "sdf", "Capsule": "sdf", "SDFBase": "sdf", "Sphere": "sdf", "Torus": "sdf",
    "TransformedSDF": "sdf",
    "CoherentCollider": "coherence",
    "Contacts": "collision", "collide": "collision",
    "Model": "model",
    "NeuralSDF": "neural", "NeuralShape": "neural",
    "Observation": "observation",
    "list_models": "registry", "load": "registry", "load_shape": "registry",
    "VoxelSDF": "voxel",
}
_SUBMODULES = ("errors", "geometry", "solvers")

# The public contract (docs/design.md): what tests, benchmarks and the README rely on.
__all__ = sorted([*_EXPORTS, *_SUBMODULES])


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    elif not name.startswith("__") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f".{name}", __name__)  # any submodule, as after `import zoo.<name>`
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__():
    return sorted({*globals(), *__all__})
