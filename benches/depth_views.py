"""Simulated depth cameras for the completion benchmark and tests: a z-buffer rasteriser (numba), views of an object
on a table, and a depth sensor's noise. No GL: the same images on every machine.

Cameras follow OpenCV (x right, y down, z forward), depth in metres, poses 4x4 world-from-camera, as
:class:`zoo.Observation` reads them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from zoo.observation import look_at

WIDTH, HEIGHT = 640, 480
FOCAL = 525.0  # pixels: a Kinect-class 640x480 camera (about 62 x 49 degrees)
TABLE_ID, OBJECT_ID = 0, 1


@dataclass(frozen=True)
class DepthViews:
    """Images of one scene: depth (V, H, W) metres (0: no return), label (V, H, W) (-1 background, TABLE_ID,
    OBJECT_ID), K (V, 3, 3), T_world_camera (V, 4, 4)."""

    depth: np.ndarray
    label: np.ndarray
    K: np.ndarray
    T_world_camera: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return self.label == OBJECT_ID


def intrinsics(width: int = WIDTH, height: int = HEIGHT, focal: float = FOCAL) -> np.ndarray:
    return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def table_views(target, count: int, rng: np.random.Generator, distance=(0.4, 0.6), elevation_deg=(20.0, 40.0)) -> np.ndarray:
    """``count`` camera poses (V, 4, 4) looking at ``target`` (3,) from ``distance`` metres, ``elevation_deg`` above
    the table (z up), at azimuths spread evenly around a random start (so a second view sees another side)."""
    start = rng.uniform(0.0, 2.0 * np.pi)
    poses = []
    for v in range(count):
        azimuth = start + 2.0 * np.pi * v / max(count, 1) * (0.5 if count == 2 else 1.0) + rng.uniform(-0.2, 0.2)
        elevation = np.deg2rad(rng.uniform(*elevation_deg))
        r = rng.uniform(*distance)
        eye = np.asarray(target) + r * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                                 np.sin(elevation)])
        poses.append(look_at(eye, target))
    return np.stack(poses)


@dataclass(frozen=True)
class LabelledMesh:
    """Triangles ``vertices[faces]`` (V, 3), (F, 3) in the world frame, each face labelled (``labels`` (F,))."""

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray


def render(scene: LabelledMesh, poses: np.ndarray, K: np.ndarray | None = None, width: int = WIDTH,
           height: int = HEIGHT) -> DepthViews:
    """Depth and label images of ``scene`` from each camera pose (V, 4, 4)."""
    K = intrinsics(width, height) if K is None else K
    depth = np.zeros((len(poses), height, width))
    label = np.full((len(poses), height, width), -1, dtype=np.int32)
    for v, pose in enumerate(poses):
        camera = (np.asarray(scene.vertices, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3]  # world -> camera: R^T (p - t)
        _rasterise(camera, np.asarray(scene.faces, dtype=np.int64), np.asarray(scene.labels, dtype=np.int32), K, depth[v],
                   label[v])
    return DepthViews(depth, label, np.broadcast_to(K, (len(poses), 3, 3)).copy(), np.asarray(poses, dtype=np.float64))


def with_table(vertices: np.ndarray, faces: np.ndarray, half_size: float = 0.6, cells: int = 48) -> LabelledMesh:
    """The object's triangles (labelled OBJECT_ID) and a square table at z = 0 (TABLE_ID) under them, in small cells
    (the rasteriser drops a triangle with a corner behind the camera, so one large quad would vanish)."""
    ticks = np.linspace(-half_size, half_size, cells + 1)
    x, y = np.meshgrid(ticks, ticks, indexing="ij")
    table_v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    b, c, d = a + cells + 1, a + cells + 2, a + 1
    table_f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) + len(vertices)
    labels = np.concatenate([np.full(len(faces), OBJECT_ID), np.full(len(table_f), TABLE_ID)])
    return LabelledMesh(np.concatenate([vertices, table_v]), np.concatenate([faces, table_f]), labels)


def sensor_noise(depth: np.ndarray, rng: np.random.Generator, sigma_at_half_metre: float = 0.001) -> np.ndarray:
    """Gaussian depth noise of ``sigma_at_half_metre`` at 0.5 m, growing with the depth squared (a structured-light or
    time-of-flight sensor's); pixels with no return stay 0."""
    noisy = depth + rng.normal(size=depth.shape) * sigma_at_half_metre * (depth / 0.5) ** 2
    return np.where(depth > 0, np.maximum(noisy, 0.0), 0.0)


@numba.njit(cache=True)
def _rasterise(camera, faces, labels, K, depth, label):  # pragma: no cover - compiled
    """Z-buffer the triangles of camera-frame vertices (V, 3) into depth (H, W) and label (H, W): pixel centres, depth
    interpolated as 1/z (perspective-correct), triangles with a vertex behind z = 1 cm skipped."""
    height, width = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        za, zb, zc = camera[a, 2], camera[b, 2], camera[c, 2]
        if za < 0.01 or zb < 0.01 or zc < 0.01:
            continue
        ua, va = fx * camera[a, 0] / za + cx, fy * camera[a, 1] / za + cy
        ub, vb = fx * camera[b, 0] / zb + cx, fy * camera[b, 1] / zb + cy
        uc, vc = fx * camera[c, 0] / zc + cx, fy * camera[c, 1] / zc + cy
        area = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
        if abs(area) < 1e-12:
            continue
        u0, u1 = max(int(np.ceil(min(ua, ub, uc))), 0), min(int(np.floor(max(ua, ub, uc))), width - 1)
        v0, v1 = max(int(np.ceil(min(va, vb, vc))), 0), min(int(np.floor(max(va, vb, vc))), height - 1)
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                w0 = ((ub - u) * (vc - v) - (uc - u) * (vb - v)) / area
                w1 = ((uc - u) * (va - v) - (ua - u) * (vc - v)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                z = 1.0 / (w0 / za + w1 / zb + w2 / zc)
                if depth[v, u] == 0 or z < depth[v, u]:
                    depth[v, u] = z
                    label[v, u] = labels[f]
