"""An animation of a simulation run: the bodies and their contacts, frame by frame, as a GIF.

Drawn with matplotlib (Agg) and written by Pillow (matplotlib's own dependency): no GPU, no OpenGL.
MuJoCo's offscreen renderer (``mujoco.Renderer``) was tried first: it opens a headless context with
``MUJOCO_GL=egl`` on the development machine (``osmesa`` fails there), but the model zoo.sim builds has
nothing to show (one 1 mm carrier sphere per body; an SDF has no mesh without marching cubes), and many
hosts have no EGL at all. So the picture is :mod:`zoo.scene_picture`'s, drawn with its helpers: mesh
bodies as their shaded triangles, SDF bodies as shaded points on their surface, each step's contacts as
red points. As there, draw order is fixed, not depth: meshes, then surface points, then contacts, so a
contact is never hidden (and an SDF body's points show over a mesh even where they are behind it).

Two panels when the run has contacts: the scene, and a close-up of where the contacts lie; each with
one camera (:data:`zoo.scene_picture.VIEW`) for the whole run. Cheap by construction: at most
``max_frames`` frames spread over the run; each SDF body's surface is sampled once in its own frame
(once more, densely, for the close-up) and moved by its pose per frame (no SDF query per frame); fixed
bodies are drawn once as a background that each frame starts from (blitting).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..errors import require
from ..files import atomic_path
from ..geometry import face_normals
from ..scene_picture import MESH_COLOUR, SDF_COLOUR, clipped_to_cube, draw_panel, posed, shaded, surface_points
from .geoms import cube_corners

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
        if not len(everything):
            return np.zeros((0, 3))
        return cube_corners(everything.min(0), everything.max(0))


def drawable(body, box=None, resolution: int = 28, max_points: int = SURFACE_POINTS) -> Drawable:
    """A :class:`zoo.sim.model.Body` as a :class:`Drawable`: its mesh where it holds one (exact and cheap),
    else its SDF's surface sampled once (:func:`zoo.scene_picture.surface_points`), within ``box`` (two (3,)
    corners, its own frame) if given."""
    none = np.zeros((0, 3))
    if body.mesh is not None:
        vertices, faces = body.mesh
        triangles = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
        return Drawable(triangles, face_normals(triangles), none, none, body.joint == "fixed")
    points, normals = surface_points(body.sdf, box, resolution=resolution, max_points=max_points)
    return Drawable(none.reshape(0, 3, 3), none, points, normals, body.joint == "fixed")


def frame_steps(n_steps: int, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Indices of the recorded steps drawn: at most ``max_frames``, evenly over the run, the last included."""
    if n_steps <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.linspace(0, n_steps - 1, min(n_steps, max_frames)).round().astype(np.int64))


def framing(drawables: list[Drawable], poses: np.ndarray) -> tuple[np.ndarray, float]:
    """The whole run's fixed camera cube, (centre (3,), half-side): every body over every pose (T, B, 4, 4);
    where the fixed bodies are far wider than the moving ones' path (a large ground), a cube around the moving ones."""
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


def close_up(contacts: list[np.ndarray], drawables: list[Drawable]) -> tuple[np.ndarray, float] | None:
    """The cube around every contact of the run, (centre (3,), half-side), or None: at least an eighth of the
    largest SDF body (:func:`zoo.scene_picture.plot_scene`'s close-up is around one step's contacts)."""
    points = np.concatenate([np.zeros((0, 3))] + [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in contacts])
    if not len(points):
        return None
    sizes = [float(np.ptp(d.points, axis=0).max()) for d in drawables if len(d.points)]
    lo, hi = points.min(0), points.max(0)
    return (lo + hi) / 2, max(0.6 * float((hi - lo).max()), 0.12 * max(sizes, default=0.0), 1e-4)


def local_box(poses: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The box (two (3,) corners) in a body's frame that holds the world cube around ``centre`` at every pose (T, 4, 4)."""
    corners = cube_corners(centre - radius, centre + radius)
    local = np.concatenate([(corners - p[:3, 3]) @ p[:3, :3] for p in poses])  # world -> body (poses are rigid)
    return local.min(0), local.max(0)


def world_geometry(drawables: list[Drawable], poses: np.ndarray):
    """Bodies at one step's poses (B, 4, 4): triangles (F, 3, 3), their normals (F, 3), surface points (P, 3)
    and their normals (P, 3), world frame."""
    rotations = [pose[:3, :3] for pose in poses]
    triangles = np.concatenate([np.zeros((0, 3, 3))] + [posed(p, d.triangles.reshape(-1, 3)).reshape(-1, 3, 3) for d, p in zip(drawables, poses)])
    tri_normals = np.concatenate([np.zeros((0, 3))] + [d.face_normals @ r.T for d, r in zip(drawables, rotations)])
    points = np.concatenate([np.zeros((0, 3))] + [posed(p, d.points) for d, p in zip(drawables, poses)])
    normals = np.concatenate([np.zeros((0, 3))] + [d.normals @ r.T for d, r in zip(drawables, rotations)])
    return triangles, tri_normals, points, normals


def write_animation(path: str | os.PathLike, bodies: list, poses: np.ndarray, contacts: list[np.ndarray],
                    times: np.ndarray, title: str = "", max_frames: int = MAX_FRAMES, fps: float = FPS,
                    panel_px: int = 440) -> int:
    """Write a GIF of a run and return its number of frames.

    See the module docstring for what is drawn and how.

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
    shown = poses[steps]
    overall = [drawable(b) for b in bodies]
    scene = framing(overall, shown)
    # a fixed SDF body (a ground) may reach far out of the view: sampled again, within it
    overall = [drawable(b, local_box(shown[:1, i], *scene)) if d.fixed else d for i, (b, d) in enumerate(zip(bodies, overall))]
    views = [("the scene", scene, overall)]
    near = close_up([contacts[t] for t in steps], overall)
    if near is not None:
        views.append(("close-up of the contacts", near,
                      [drawable(b, local_box(shown[:, i], *near), 40, 2 * SURFACE_POINTS) for i, b in enumerate(bodies)]))
    fig, axes, caption, background = still_figure(plt, views, shown[0], panel_px)
    frames = []
    for k, t in enumerate(steps):
        fig.canvas.restore_region(background)
        for ax, (_, (centre, radius), drawables) in zip(axes, views):
            moving = np.array([not d.fixed for d in drawables])
            geometry = world_geometry([d for d in drawables if not d.fixed], shown[k, moving])
            draw_moving(ax, centre, radius, *geometry, np.asarray(contacts[t], dtype=np.float64).reshape(-1, 3))
        caption.set_text(f"{title}   t = {times[t]:.3f} s, {len(contacts[t])} contacts (red)")
        fig.draw_artist(caption)
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    write_gif(path, frames, fps)
    return len(frames)


def still_figure(plt, views: list, poses: np.ndarray, panel_px: int):
    """The figure with what never moves drawn: one 3D panel per view (name, (centre, half-side), drawables),
    the fixed bodies at ``poses`` (B, 4, 4); (figure, panels, the caption to fill, the canvas to restore per frame)."""
    fig = plt.figure(figsize=(len(views) * panel_px / 100, panel_px / 100 + 0.4), dpi=100)
    axes, empty = [], np.zeros((0, 3))  # no contacts in the still
    for i, (name, (centre, radius), drawables) in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1, projection="3d", computed_zorder=False)
        fixed = np.array([d.fixed for d in drawables])
        draw_panel(ax, centre, radius, *world_geometry([d for d in drawables if d.fixed], poses[fixed]), empty, None)
        ax.set_title(name, fontsize=9)
        axes.append(ax)
    caption = fig.suptitle("", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.canvas.draw()
    return fig, axes, caption, fig.canvas.copy_from_bbox(fig.bbox)


def draw_moving(ax, centre, radius, triangles, tri_normals, points, normals, contacts) -> None:
    """Draw one frame's moving bodies and contacts over ``ax``'s restored background, then take them off:
    their shaded triangles, their shaded surface points and the contacts (red, last), inside the panel's cube."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    polygons, source = clipped_to_cube(triangles, centre, radius)
    artists = [ax.add_collection3d(Poly3DCollection(polygons, facecolors=shaded(MESH_COLOUR, tri_normals[source]), linewidths=0))]
    inside = np.abs(points - centre).max(1) < radius
    artists.append(ax.scatter(*points[inside].T, c=shaded(SDF_COLOUR, normals[inside]), s=4.0, depthshade=False, linewidths=0))
    inside = np.abs(contacts - centre).max(1) < radius
    artists.append(ax.scatter(*contacts[inside].T, color="red", s=CONTACT_SIZE, depthshade=False, edgecolors="darkred", linewidths=0.5))
    for artist in artists:
        artist.do_3d_projection()  # Axes3D.draw would; drawing one artist alone does not
        ax.draw_artist(artist)
        artist.remove()


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
