"""What a simulation run leaves behind: the trajectory (HDF5 with provenance), per-step stats (JSON), a PNG
and an animation (GIF).

:class:`Recorder` is a ``Simulation.run`` callback that keeps each body's pose and velocity and the
contact points per step; :meth:`Recorder.write` writes ``<name>.h5``, ``<name>.json``, ``<name>.png``
and ``<name>.gif`` (:mod:`zoo.sim.animation`). h5py, matplotlib and Pillow are imported only there
(the ``sim`` extra).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..files import atomic_path, atomic_write_text, sha256_file


class Recorder:
    """Collects, after each step, the time, every body's pose (4, 4) and velocity (6,), and the contact points (K, 3)."""

    def __init__(self, sim, video=None, frame_every: int = 1):
        self.sim = sim
        self.video, self.frame_every = video, max(1, int(frame_every))  # a zoo.sim.render.VideoRecorder, or None
        self.names = list(sim.bodies)
        self.times: list[float] = []
        self.poses: list[np.ndarray] = []  # each (B, 4, 4)
        self.velocities: list[np.ndarray] = []  # each (B, 6)
        self.energy: list[float] = []
        self.contact_points: list[np.ndarray] = []  # each (K, 3) float32, world frame: what the animation draws

    def __call__(self, sim) -> None:
        self.times.append(sim.time)
        self.poses.append(np.stack([sim.pose(n) for n in self.names]))
        self.velocities.append(np.stack([sim.velocity(n) for n in self.names]))
        self.energy.append(sim.energy())
        points = sim.contacts.points if sim.contacts is not None else np.zeros((0, 3))
        self.contact_points.append(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        if self.video is not None and (len(self.times) - 1) % self.frame_every == 0:
            self.video.capture(sim.data)

    def summary(self) -> dict:
        """Totals over the run: steps, contacts, deepest penetration, time per step, warnings."""
        log = self.sim.log
        return {
            "steps": len(log),
            "simulated_s": self.sim.time,
            "max_penetration_m": max((r.max_penetration for r in log), default=0.0),
            "max_contacts": max((r.contacts for r in log), default=0),
            "mean_step_ms": 1e3 * float(np.mean([r.step_s for r in log])) if log else 0.0,
            "mean_collide_ms": 1e3 * float(np.mean([r.collide_s for r in log])) if log else 0.0,
            "speculative_steps": sum(r.speculative for r in log),
            "warnings": self.sim.warnings,
            "finite": bool(all(np.isfinite(p).all() for p in self.poses)),
        }

    def write(self, out_dir: str | os.PathLike, provenance: dict, animation: bool = True, video_format: str = "mp4") -> dict[str, Path]:
        """Write ``<name>.h5`` (trajectory, provenance attributes), ``<name>.json``, ``<name>.png`` and, with
        ``animation``, the video: ``<name>.mp4`` or ``.gif`` from MuJoCo's renderer where the recorder has one,
        else ``<name>.gif`` drawn with matplotlib (:mod:`zoo.sim.animation`)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        name = self.sim.name
        paths = {"h5": out / f"{name}.h5", "json": out / f"{name}.json", "png": out / f"{name}.png"}
        self._write_h5(paths["h5"], provenance)
        stats = {"provenance": provenance, "summary": self.summary(), "steps": [asdict(r) for r in self.sim.log]}
        atomic_write_text(paths["json"], json.dumps(stats, indent=1, default=_jsonable))
        self._write_png(paths["png"], name)
        if animation and self.video is not None and self.video.frames:
            paths["video"] = self.video.write(out / f"{name}.{video_format}", fps=min(30.0, self.fps()))
        elif animation and self.poses:
            from .animation import write_animation

            paths["gif"] = out / f"{name}.gif"
            write_animation(paths["gif"], [self.sim.bodies[n] for n in self.names], np.stack(self.poses), self.contact_points,
                            np.asarray(self.times), title=f"{name} ({self.sim.method})")
        return paths

    def fps(self) -> float:
        """Frames per second that play the captured frames at a quarter of real time (a contact is quick)."""
        return 0.25 / (self.sim.dt * self.frame_every)

    def _write_h5(self, path: Path, provenance: dict) -> None:
        from ..errors import require

        h5py = require("h5py", extra="sim")
        log = self.sim.log
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            for key, value in provenance.items():
                f.attrs[key] = value if isinstance(value, (int, float, str)) else json.dumps(value)
            f.create_dataset("time", data=np.asarray(self.times))
            f.create_dataset("energy", data=np.asarray(self.energy))
            for i, body in enumerate(self.names):
                g = f.create_group(f"bodies/{body}")
                g.create_dataset("pose", data=np.stack([p[i] for p in self.poses]) if self.poses else np.zeros((0, 4, 4)))
                g.create_dataset("velocity", data=np.stack([v[i] for v in self.velocities]) if self.velocities else np.zeros((0, 6)))
            # contact points of every step, ragged: step i's are points[offsets[i]:offsets[i + 1]]
            counts = [len(c) for c in self.contact_points]
            f.create_dataset("contacts/offsets", data=np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]))
            f.create_dataset("contacts/points", data=np.concatenate(self.contact_points) if counts else np.zeros((0, 3), np.float32))
            for key in ("contacts", "raw_contacts", "max_penetration", "collide_s", "step_s", "margin"):
                f.create_dataset(f"stats/{key}", data=np.asarray([getattr(r, key) for r in log]))

    def _write_png(self, path: Path, name: str) -> None:
        from ..errors import require

        require("matplotlib", extra="sim")
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        log = self.sim.log
        t = np.asarray([r.time for r in log])
        fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        axes[0].plot(t, [1e3 * r.max_penetration for r in log], lw=1)
        axes[0].set_ylabel("max penetration (mm)")
        axes[1].plot(t, [r.contacts for r in log], lw=1, label="in the solver")
        axes[1].plot(t, [r.raw_contacts for r in log], lw=1, alpha=0.6, label="zoo.collide")
        axes[1].set_ylabel("contacts")
        axes[1].legend(loc="upper right", fontsize=8)
        axes[2].plot(t, [1e3 * r.step_s for r in log], lw=1, label="step")
        axes[2].plot(t, [1e3 * r.collide_s for r in log], lw=1, label="collide")
        axes[2].set_ylabel("time per step (ms)")
        axes[2].set_xlabel("simulated time (s)")
        axes[2].legend(loc="upper right", fontsize=8)
        fig.suptitle(f"{name}: {len(log)} steps of {self.sim.dt * 1e3:g} ms ({self.sim.method})")
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=100, format="png")
        plt.close(fig)


def _jsonable(value):
    """json.dumps' fallback: numpy scalars as numbers, anything else as its text."""
    return value.item() if isinstance(value, (np.floating, np.integer)) else str(value)


def provenance(sim, scene_path: str | os.PathLike | None = None) -> dict:
    """What produced a run: versions, the scene file's sha256, the models, method, dt, margin."""
    import mujoco

    import zoo

    sim.build()
    m = sim.model
    return {
        "zoo_version": zoo.__version__, "mujoco_version": mujoco.__version__,
        "scene": str(scene_path) if scene_path else "", "scene_sha256": sha256_file(scene_path) if scene_path else "",
        "bodies": json.dumps(sim.labels), "mjcf": str(sim.mjcf or ""), "method": sim.method, "dt": sim.dt,
        "margin": sim.margin, "friction": json.dumps(sim.settings.friction), "solref": json.dumps(sim.settings.solref),
        "integrator": _option_name(mujoco.mjtIntegrator(int(m.opt.integrator))), "cone": _option_name(mujoco.mjtCone(int(m.opt.cone))),
        "impratio": float(m.opt.impratio), "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def _option_name(value) -> str:
    """MuJoCo's enum member as its MJCF attribute value: mjCONE_PYRAMIDAL -> "pyramidal", mjINT_IMPLICITFAST -> "implicitfast"."""
    return value.name.split("_", 1)[1].lower()
