"""Contact simulation on MuJoCo with sdfzoo's SDF-mesh contacts (the ``sim`` extra: pip install 'sdfzoo[sim]').

``import zoo`` does not load this package; ``import zoo.sim`` needs ``mujoco``. See DESIGN.md's contract.
"""

from __future__ import annotations

from ..errors import require

require("mujoco", extra="sim")

from .simulation import Simulation, StepRecord  # noqa: E402

__all__ = ["Simulation", "StepRecord", "load_scene"]


def load_scene(path, **overrides) -> Simulation:
    """A :class:`Simulation` from a scene file (see :mod:`zoo.sim.scene`)."""
    from .scene import load_scene as _load

    return _load(path, **overrides)
