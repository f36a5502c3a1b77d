"""An animation of a simulation run: the bodies and their contacts, frame by frame, as a GIF.

Drawn with matplotlib (Agg) and written by Pillow (matplotlib's own dependency): no GPU, no OpenGL. MuJoCo's offscreen renderer
(``mujoco.Renderer``) was tried: it opens a headless context with ``MUJOCO_GL=egl`` on the development
machine (``osmesa`` fails there), but the model zoo.sim builds has nothing to show (one 1 mm carrier
sphere per body; an SDF has no mesh without marching cubes), and many hosts have no EGL at all. So the
picture is :mod:`zoo.scene_picture`'s, drawn by its helpers: mesh bodies as their shaded triangles, SDF
bodies as shaded points on their surface, each step's contacts as red points, drawn last.

Cheap by construction: at most ``max_frames`` frames spread over the run; each SDF body's surface is
sampled once in its own frame and moved by its pose per frame (no SDF query per frame); one fixed
camera (:data:`zoo.scene_picture.VIEW`) frames the bodies over the whole run.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..errors import require
from ..files import atomic_path
from ..scene_picture import _draw_panel, posed, surface_points
from .contacts import face_normals

MAX_FRAMES = 60
FPS = 12.0
SURFACE_POINTS = 4000  # per SDF body: enough to read its shape at a GIF's size
CONTACT_SIZE = 30.0  # marker area, points^2
FOCUS = 3.0  # fixed bodies wider than this many times the moving ones' reach are cut to a view of the moving ones


@dataclass
class Drawable:
    """One body's geometry in its own frame: triangles (F, 3, 3) with normals (F, 3) if it holds a mesh,
    else points on its SDF's surface (P, 3) with normals (P, 3); empty arrays for what it does not draw."""

    triangles: np.ndarray
    face_normals: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    fixed: bool

    def corners(self) -> np.ndarray:
        """The 8 corners of its geometry's box, own frame: (8, 3)."""
        everything = np.concatenate([self.triangles.reshape(-1, 3), self.points])
        lo, hi = everything.min(0), everything.max(0)
        return np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)


def drawable(body, max_points: int = SURFACE_POINTS) -> Drawable:
    """A :class:`zoo.sim.model.Body` as a :class:`Drawable`: its mesh where it holds one (exact and cheap),
    else its SDF's surface sampled once (:func:`zoo.scene_picture.surface_points`)."""
    none = np.zeros((0, 3))
    if body.mesh is not None:
        vertices, faces = body.mesh
        triangles = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
        return Drawable(triangles, face_normals(triangles), none, none, body.joint == "fixed")
    points, normals = surface_points(body.sdf, max_points=max_points)
    return Drawable(none.reshape(0, 3, 3), none, points, normals, body.joint == "fixed")


def frame_steps(n_steps: int, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Indices of the recorded steps drawn: at most ``max_frames``, evenly over the run, the last included."""
    if n_steps <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.linspace(0, n_steps - 1, min(n_steps, max_frames)).round().astype(np.int64))


def framing(drawables: list[Drawable], poses: np.ndarray) -> tuple[np.ndarray, float]:
    """The fixed camera's cube, (centre (3,), half-side): every body over every pose (T, B, 4, 4); where
    the fixed bodies are far wider than the moving ones' path (a large ground), a cube around the moving ones."""
    def box(indices):
        world = np.concatenate([posed(pose, drawables[b].corners()) for b in indices for pose in poses[:, b]])
        lo, hi = world.min(0), world.max(0)
        return (lo + hi) / 2, 0.55 * float((hi - lo).max())

    everything = box(range(len(drawables)))
    moving = [b for b, d in enumerate(drawables) if not d.fixed]
    if not moving:
        return everything
    centre, radius = box(moving)
    return everything if everything[1] <= FOCUS * radius else (centre, 2.0 * radius)


def world_geometry(drawables: list[Drawable], poses: np.ndarray):
    """Every body at one step's poses (B, 4, 4): triangles (F, 3, 3), their normals (F, 3), surface
    points (P, 3) and their normals (P, 3), world frame."""
    rotations = [pose[:3, :3] for pose in poses]
    triangles = np.concatenate([posed(p, d.triangles.reshape(-1, 3)).reshape(-1, 3, 3) for d, p in zip(drawables, poses)])
    tri_normals = np.concatenate([d.face_normals @ r.T for d, r in zip(drawables, rotations)])
    points = np.concatenate([posed(p, d.points) for d, p in zip(drawables, poses)])
    normals = np.concatenate([d.normals @ r.T for d, r in zip(drawables, rotations)])
    return triangles, tri_normals, points, normals


def write_animation(path: str | os.PathLike, bodies: list, poses: np.ndarray, contacts: list[np.ndarray],
                    times: np.ndarray, title: str = "", max_frames: int = MAX_FRAMES, fps: float = FPS,
                    size_px: int = 480) -> int:
    """Write a GIF of a run and return its number of frames.

    Args:
        bodies: the :class:`zoo.sim.model.Body` of each recorded body, in the order of ``poses``.
        poses: (T, B, 4, 4) world-from-body of every body after each step.
        contacts: T arrays (K_t, 3): the contact points of each step, world frame.
        times: (T,) simulated time after each step, s.
    """
    require("matplotlib", extra="sim")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses = np.asarray(poses, dtype=np.float64)
    steps = frame_steps(len(poses), max_frames)
    if not len(steps):
        return 0
    drawables = [drawable(b) for b in bodies]
    centre, radius = framing(drawables, poses)
    fig = plt.figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    ax = fig.add_subplot(projection="3d", computed_zorder=False)
    frames = []
    for t in steps:
        ax.cla()
        _draw_panel(ax, centre, radius, *world_geometry(drawables, poses[t]), np.zeros((0, 3)), None)
        points = np.asarray(contacts[t], dtype=np.float64).reshape(-1, 3)
        if len(points):  # larger than the picture's: a GIF frame is small
            ax.scatter(*points.T, color="red", s=CONTACT_SIZE, depthshade=False, edgecolors="darkred", linewidths=0.5)
        ax.set_title(f"{title}\nt = {times[t]:.3f} s, {len(contacts[t])} contacts (red)", fontsize=9)
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    write_gif(path, frames, fps)
    return len(frames)


def write_gif(path: str | os.PathLike, frames: list[np.ndarray], fps: float) -> None:
    """Frames (H, W, 3) uint8 as a looping GIF with one palette for all of them that holds the contacts' red.

    A GIF has 256 colours; a per-frame adaptive palette merges a few red pixels into the grey around
    them (the contacts vanished) and flickers between frames, so the palette is computed once from
    the frames, with red and dark red added, and every frame is mapped to it without dithering.
    """
    from PIL import Image

    montage = Image.fromarray(np.concatenate(frames[:: max(1, len(frames) // 8)]))  # a few frames stand for all
    palette = montage.quantize(colors=254).getpalette()[: 254 * 3] + [255, 0, 0, 139, 0, 0]
    holder = Image.new("P", (1, 1))
    holder.putpalette(palette)
    images = [Image.fromarray(f).quantize(palette=holder, dither=Image.Dither.NONE) for f in frames]
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=round(1000.0 / fps), loop=0)
