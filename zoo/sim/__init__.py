"""Contact simulation on MuJoCo with sdfzoo's SDF contacts (the ``sim`` extra: pip install 'sdfzoo[sim]').

``import zoo`` does not load this package; ``import zoo.sim`` needs ``mujoco``. The user's own model and loop:
:func:`attach` (``world.step(data)`` or ``with world.hooked():``); a model built in Python or from a scene
file: :class:`Simulation`. See the design's "zoo.sim" contract.
"""

from __future__ import annotations

from ..errors import MissingDependencyError
from ..offscreen import import_mujoco

if not hasattr(import_mujoco(), "mj_addContact"):  # the Python binding zoo.sim adds its contacts with
    raise MissingDependencyError("zoo.sim needs a mujoco whose Python bindings have mj_addContact (tested on 4.0.0): "
                                 "pip install -U 'mujoco>=4'")

from .simulation import Simulation, StepRecord  # noqa: E402
from .world import World, attach  # noqa: E402

__all__ = ["Simulation", "StepRecord", "World", "attach", "load_scene"]


def load_scene(path, **overrides) -> Simulation:
    """A :class:`Simulation` from a scene file (see :mod:`zoo.sim.scene`); ``zoo.scenes.load_collision_scene`` reads a
    collision scene for ``zoo.collide``."""
    from .scene import simulation_from_file

    return simulation_from_file(path, **overrides)
