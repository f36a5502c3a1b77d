"""Videos from MuJoCo's own renderer (``mujoco.Renderer``), offscreen: EGL or OSMesa, no window.

MuJoCo picks its GL backend from ``MUJOCO_GL`` when ``mujoco`` is first imported, so
:func:`zoo.offscreen.choose_gl` runs before that (``zoo simulate`` calls it first). Where no backend renders,
callers fall back to the matplotlib drawing of :mod:`zoo.sim.animation` and say so.

:class:`VideoRecorder` renders a model's state frame by frame: its geoms (an SDF body is drawn as its visual
geom, for :class:`zoo.sim.Simulation` a mesh extracted from its SDF) and the step's contacts (MuJoCo draws
``data.contact``, which holds sdfzoo's after a step), from a camera of the model or a free camera aimed at
the SDF bodies; it writes MP4 (with ``imageio-ffmpeg``) or GIF.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError, require
from ..files import atomic_path

FPS = 30


def free_camera(model, data, bodies: list[int], lookat=None, distance: float | None = None,
                azimuth: float = 135.0, elevation: float = -25.0):
    """A free ``mujoco.MjvCamera`` aimed at ``bodies`` (ids): at their centre, from 3 times their spread
    (at least 15 cm), unless ``lookat`` (3,) and ``distance`` (m) are given."""
    import mujoco

    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    centres = np.asarray([data.xipos[b] for b in bodies]) if bodies else np.zeros((1, 3))
    camera.lookat[:] = centres.mean(axis=0) if lookat is None else np.asarray(lookat, dtype=np.float64)
    spread = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 0.0
    camera.distance = float(distance) if distance is not None else max(0.15, 3.0 * spread)
    camera.azimuth, camera.elevation = float(azimuth), float(elevation)
    return camera


def scene_camera(sim):
    """The camera a :class:`zoo.sim.Simulation`'s video uses: its scene's ``camera`` (a camera of its model by name,
    or a table of :func:`free_camera`'s lookat, distance, azimuth and elevation), else a free camera aimed at its
    SDF bodies."""
    sim.build()
    bodies = [b.body for b in sim.world.bodies.values()]
    if isinstance(sim.camera, str):
        return sim.camera
    if isinstance(sim.camera, dict):
        unknown = set(sim.camera) - {"lookat", "distance", "azimuth", "elevation"}
        if unknown:
            raise InputError(f"[sim] camera: unknown keys {sorted(unknown)}; use lookat, distance, azimuth, elevation")
        return free_camera(sim.model, sim.data, bodies, **sim.camera)
    if sim.camera is not None:
        raise InputError(f"[sim] camera must be a camera's name or a table, got {sim.camera!r}")
    return free_camera(sim.model, sim.data, bodies)


class VideoRecorder:
    """Frames of a model's state from MuJoCo's renderer, with the contacts drawn; :meth:`write` saves them.

    Args:
        model: the ``mujoco.MjModel``.
        camera: a camera of the model (its name), a ``mujoco.MjvCamera``, or None (MuJoCo's default free camera).
        width, height: pixels.
        contacts: draw ``data.contact``'s points and forces.
    """

    def __init__(self, model, camera=None, width: int = 480, height: int = 360, contacts: bool = True):
        import mujoco

        self.model = model
        try:
            self.renderer = mujoco.Renderer(model, height, width)
        except Exception as exc:
            raise InputError(f"MuJoCo's renderer cannot open an offscreen context ({exc}); set MUJOCO_GL=egl or osmesa "
                             "(Debian: apt-get install libosmesa6), or use the matplotlib drawing") from exc
        if isinstance(camera, str) and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            self.close()
            raise InputError(f"the model has no camera named {camera!r}")
        self.camera = camera
        self.option = mujoco.MjvOption()
        if contacts:
            self.option.flags[mujoco.mjtVisFlag.mjVIS_CONTACTPOINT] = True
            self.option.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = True
        self.frames: list[np.ndarray] = []

    def capture(self, data) -> np.ndarray:
        """Render ``data``'s current state (its kinematics and contacts as they stand); returns the frame (H, W, 3)."""
        self.renderer.update_scene(data, camera=self.camera if self.camera is not None else -1, scene_option=self.option)
        frame = self.renderer.render().copy()
        self.frames.append(frame)
        return frame

    def write(self, path: str | os.PathLike, fps: float = FPS) -> Path:
        """Save the frames as MP4 (``.mp4``, needs imageio-ffmpeg) or GIF (any other suffix); returns the path."""
        if not self.frames:
            raise InputError("no frames to write: capture some first")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        imageio = require("imageio", extra="sim")
        with atomic_path(path) as tmp:
            scratch = tmp.with_name(tmp.name + path.suffix)  # the writers choose the container by the suffix
            if path.suffix.lower() == ".mp4":
                require("imageio_ffmpeg", extra="sim")
                imageio.mimwrite(scratch, self.frames, fps=fps, codec="libx264", macro_block_size=8)
            else:
                imageio.mimwrite(scratch, self.frames, duration=1000.0 / fps, loop=0)
            os.replace(scratch, tmp)
        return path

    def close(self) -> None:
        renderer, self.renderer = getattr(self, "renderer", None), None
        if renderer is not None:
            renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
