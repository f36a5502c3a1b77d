"""A picture of a collided scene: both objects and where they touch, from where a person sees it.

Two panels, world frame, equal axes: the whole scene, and a close-up of the contacts. The mesh
object is drawn as its shaded triangles; the SDF object as a shaded cloud of points on its zero
level set (grid points near the surface, projected onto it along the gradient: no marching cubes
needed); contacts as red points with their normals (from the SDF object into the mesh) as arrows,
drawn last so the surfaces never hide them.

matplotlib is imported when a picture is drawn (``zoo.errors.require`` says how to install it), never
by ``import zoo``.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from .errors import require
from .files import atomic_path

LIGHT = np.array([-0.4, -0.6, 0.7]) / np.linalg.norm([-0.4, -0.6, 0.7])  # from the viewer's upper left
SDF_COLOUR, MESH_COLOUR = np.array([0.20, 0.45, 0.85]), np.array([0.62, 0.60, 0.58])
VIEW = {"elev": 18.0, "azim": -62.0}  # from the front left, a little above: a hanging object's side and its support


def surface_points(sdf, box=None, resolution: int = 28, max_points: int = 10_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the zero level set of ``sdf`` and its unit normals there, in its own frame: (P, 3), (P, 3).

    A ``resolution``^3 grid over ``sdf.bounds`` (cut to ``box``, two (3,) corners, if given; grown by two
    cells); around the grid points whose cell the surface may cross (|f| within the cell's half diagonal:
    an SDF is 1-Lipschitz), a grid of half the spacing; its points within half a fine cell of the surface,
    at most ``max_points`` of them, are moved onto it by a Newton step (p - f g). Two levels query a
    few times fewer points than one fine grid, the NeuralSDF's cost.
    """
    lo, hi = (np.asarray(torch.as_tensor(b, dtype=torch.float64)) for b in sdf.bounds)
    if box is not None:
        lo, hi = np.maximum(lo, box[0]), np.minimum(hi, box[1])
        if np.any(hi <= lo):
            return np.zeros((0, 3)), np.zeros((0, 3))
    cell = float((hi - lo).max()) / (resolution - 1)
    axes = [np.arange(a - 2 * cell, b + 2 * cell + 1e-12, cell) for a, b in zip(lo, hi)]
    coarse = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    crossed = coarse[np.abs(_values(sdf, coarse)) <= 0.87 * cell]
    offsets = (np.stack(np.meshgrid(*[[-0.25, 0.25]] * 3, indexing="ij"), axis=-1).reshape(-1, 3) * cell).astype(np.float32)
    fine = (crossed[:, None, :] + offsets).reshape(-1, 3)
    near = fine[np.abs(_values(sdf, fine)) < 0.5 * cell]
    if len(near) > max_points:
        near = near[np.random.default_rng(seed).choice(len(near), max_points, replace=False)]
    if not len(near):
        return np.zeros((0, 3)), np.zeros((0, 3))
    p = torch.from_numpy(near)
    d, g = sdf.value_and_grad(p)
    d, g = torch.as_tensor(d).detach().float(), torch.as_tensor(g).detach().float()
    on_surface = p - d[:, None] * g
    return on_surface.numpy().astype(np.float64), torch.nn.functional.normalize(g, dim=-1).numpy().astype(np.float64)


def _values(sdf, points: np.ndarray) -> np.ndarray:
    """``sdf`` at float32 points (N, 3), in chunks, without gradients: (N,)."""
    with torch.no_grad():
        return torch.cat([torch.as_tensor(sdf(torch.from_numpy(c))).float().reshape(-1)
                          for c in np.array_split(points, max(1, len(points) // 65536))]).numpy()


def shaded(base: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """RGB colours (N, 3) of surfaces with ``normals`` (N, 3) under the fixed light, lit from either side."""
    return np.clip(base * (0.35 + 0.65 * np.abs(normals @ LIGHT))[:, None], 0.0, 1.0)


def posed(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) through a 4x4 pose."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def posed_surface(sdf, pose: np.ndarray, centre=None, radius=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_points` in the world (through ``pose``), within the cube of half-side ``radius``
    around ``centre`` if given: (P, 3), (P, 3)."""
    box = None
    if centre is not None:
        corners = centre + radius * np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T
        local = (corners - pose[:3, 3]) @ pose[:3, :3]  # world -> the SDF's frame (pose is rigid)
        box = (local.min(0), local.max(0))
    points, normals = surface_points(sdf, box)
    return posed(pose, points), normals @ pose[:3, :3].T


def clipped_to_cube(triangles: np.ndarray, centre: np.ndarray, radius: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The parts of ``triangles`` (F, 3, 3) inside the cube of half-side ``radius`` around ``centre``:
    polygons (each (k, 3)) and the index of the triangle each came from. 3D axes do not clip, and a long
    thin triangle (a rack's peg) that crosses the cube must still show its piece."""
    inside = (np.abs(triangles - centre).max(-1) <= radius).all(-1)
    overlaps = ((triangles.min(1) <= centre + radius) & (triangles.max(1) >= centre - radius)).all(-1)
    polygons, source = list(triangles[inside]), list(np.flatnonzero(inside))
    for i in np.flatnonzero(overlaps & ~inside):  # only the crossing ones are clipped, one by one
        polygon = triangles[i]
        for axis in range(3):
            for sign in (1.0, -1.0):  # Sutherland-Hodgman against the plane sign * (x - centre) <= radius
                polygon = _clip(polygon, axis, sign, sign * centre[axis] + radius)
                if len(polygon) < 3:
                    break
            if len(polygon) < 3:
                break
        if len(polygon) >= 3:
            polygons.append(polygon)
            source.append(i)
    return polygons, np.asarray(source, dtype=np.int64)


def _clip(polygon: np.ndarray, axis: int, sign: float, bound: float) -> np.ndarray:
    """The part of a convex polygon (k, 3) where ``sign * x[axis] <= bound``."""
    inside = sign * polygon[:, axis] <= bound
    if inside.all():
        return polygon
    out = []
    for a, b, a_in, b_in in zip(polygon, np.roll(polygon, -1, axis=0), inside, np.roll(inside, -1)):
        if a_in:
            out.append(a)
        if a_in != b_in:  # the edge crosses the plane
            t = (bound - sign * a[axis]) / (sign * (b[axis] - a[axis]))
            out.append(a + t * (b - a))
    return np.asarray(out).reshape(-1, 3)


def plot_scene(scene, contacts, path: str | os.PathLike) -> None:
    """Write a PNG of ``scene`` (a :class:`zoo.scenes.Scene`) and its ``contacts``: overall and close-up."""
    require("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pose = np.asarray(scene.sdf_pose, dtype=np.float64)
    sdf_points, sdf_normals = posed_surface(scene.sdf, pose)
    mesh_pose = np.asarray(scene.mesh_pose, dtype=np.float64)
    triangles = posed(mesh_pose, np.asarray(scene.mesh.vertices, dtype=np.float64))[np.asarray(scene.mesh.faces)]
    face_normals = np.asarray(scene.mesh.face_normals, dtype=np.float64) @ mesh_pose[:3, :3].T
    pts = contacts.points.double().numpy()
    normals = contacts.normals.double().numpy()

    everything = np.concatenate([sdf_points, triangles.reshape(-1, 3)])
    overall = ((everything.min(0) + everything.max(0)) / 2, 0.51 * float(np.ptp(everything, axis=0).max()))
    if len(pts):
        close = (pts.mean(0), max(0.75 * float(np.ptp(pts, axis=0).max()), 0.12 * float(np.ptp(sdf_points, axis=0).max())))
    else:
        close = ((sdf_points.min(0) + sdf_points.max(0)) / 2, 0.5 * float(np.ptp(sdf_points, axis=0).max()))

    fig = plt.figure(figsize=(13, 6.8))
    panels = (("the scene", overall, (sdf_points, sdf_normals), False),
              ("close-up of the contacts", close, posed_surface(scene.sdf, pose, *close), True))
    for i, (title, (centre, radius), surface, arrows) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d", computed_zorder=False)
        draw_panel(ax, centre, radius, triangles, face_normals, *surface, pts, normals if arrows else None)
        ax.set_title(title)
    deepest = f", deepest {1e3 * float(contacts.depths.min()):+.3f} mm" if len(pts) else ""
    fig.suptitle(f"{scene.name}: {scene.sdf_label or 'SDF'} (blue points, its surface) on {scene.mesh_label or 'mesh'} (grey)\n"
                 f"{len(contacts)} contacts ({scene.method}{deepest}): red points; close-up: their normals, into the mesh")
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def draw_panel(ax, centre, radius, triangles, face_normals, sdf_points, sdf_normals, pts, normals) -> None:
    """One panel: what lies within the cube of half-side ``radius`` around ``centre``; ``normals`` (K, 3) of
    the contacts as arrows, if given."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    polygons, source = clipped_to_cube(triangles, centre, radius)
    ax.add_collection3d(Poly3DCollection(polygons, facecolors=shaded(MESH_COLOUR, face_normals[source]), linewidths=0))
    inside = np.abs(sdf_points - centre).max(1) < radius
    ax.scatter(*sdf_points[inside].T, c=shaded(SDF_COLOUR, sdf_normals[inside]), s=3.0 if normals is None else 5.0,
               depthshade=False, linewidths=0)
    if len(pts):
        ax.scatter(*pts.T, color="red", s=12, depthshade=False, edgecolors="darkred", linewidths=0.3)
    if normals is not None and len(pts):
        shown = np.linspace(0, len(pts) - 1, min(len(pts), 40)).round().astype(int)  # a forest of arrows hides the points
        arrows = normals[shown] * 0.15 * radius
        ax.quiver(*pts[shown].T, *arrows.T, color="darkred", linewidth=0.7, arrow_length_ratio=0.3)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - radius, c + radius)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(**VIEW)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
