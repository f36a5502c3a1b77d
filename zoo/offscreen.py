"""Which offscreen OpenGL backend MuJoCo's renderer can use here, chosen before ``mujoco`` is imported.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported. :func:`choose_gl` keeps a value the user
set; else it probes EGL, then OSMesa (Debian's ``libosmesa6``), each in a child process, and sets the first
that renders. Kept out of :mod:`zoo.sim` (which imports mujoco) so that it can run first.
"""

from __future__ import annotations

import os
import subprocess
import sys

BACKENDS = ("egl", "osmesa")
PROBE = ("import mujoco; m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"1\"/></worldbody></mujoco>'); "
         "r = mujoco.Renderer(m, 8, 8); d = mujoco.MjData(m); r.update_scene(d); r.render(); r.close()")


def choose_gl() -> str | None:
    """The offscreen GL backend MuJoCo's renderer will use in this process, or None where none renders.

    Sets ``MUJOCO_GL`` where it is unset and ``mujoco`` is not imported yet (it is read at import).
    """
    chosen = os.environ.get("MUJOCO_GL")
    if chosen or "mujoco" in sys.modules:
        return chosen or _probe_current()
    for backend in BACKENDS:
        try:
            done = subprocess.run([sys.executable, "-c", PROBE], env={**os.environ, "MUJOCO_GL": backend},
                                  capture_output=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if done.returncode == 0:
            os.environ["MUJOCO_GL"] = backend
            return backend
    return None


def _probe_current() -> str | None:
    """Whether the already imported mujoco renders (it picked its backend at import)."""
    import mujoco

    try:
        renderer = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>"), 8, 8)
        renderer.close()
    except Exception:  # no GL context: glfw without a display, a missing library
        return None
    return os.environ.get("MUJOCO_GL") or "glfw"


def import_mujoco():
    """``import mujoco``, with a message that says what to do where the ``MUJOCO_GL`` backend named cannot load (mujoco
    imports its renderer at import: ``MUJOCO_GL=osmesa`` without OSMesa fails there with an AttributeError)."""
    from .errors import MissingDependencyError, require

    try:
        return require("mujoco", extra="sim")
    except (AttributeError, OSError, RuntimeError) as exc:
        backend = os.environ.get("MUJOCO_GL")
        if not backend:
            raise
        install = {"osmesa": "Debian's libosmesa6 (apt-get install libosmesa6)", "egl": "an EGL driver (Debian's libegl1)"}
        raise MissingDependencyError(
            f"mujoco could not load its renderer with MUJOCO_GL={backend} ({type(exc).__name__}: {exc}): install "
            f"{install.get(backend, 'the libraries that backend needs')}, or unset MUJOCO_GL (sdfzoo then picks a "
            "backend that works, or falls back where none does)") from exc
