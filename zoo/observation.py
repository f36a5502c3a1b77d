"""What a robot sees of one object: surface points in the world frame, and the free space in front of them.

:class:`Observation` is the input of :meth:`zoo.Model.fit_observation`. It holds

- ``points`` (N, 3): world-frame points on the object's surface (float64);
- ``origins`` (N, 3) or None: the sensor origin each point was seen from. A point seen from ``o`` says more
  than "the surface passes here": the segment from ``o`` to the point is empty, which bounds the object's
  near side and, through the rays that pass it by, its silhouette;
- ``normals`` (N, 3) or None: outward surface normals, where the sensor gives them (they orient free-space
  evidence when there are no origins);
- ``free_origins``, ``free_ends`` (R, 3) or None: rays known to be empty from origin to end that end on
  something else than the object (the table or the background beside it, in a depth image with a mask);
- ``views``: how many images or scans the points came from.

Cameras follow OpenCV: x right, y down, z forward; depth is the z coordinate in the camera frame, in metres;
``T_world_camera`` is the 4x4 world-from-camera pose. A pixel (u, v) (column, row, 0-based, the centre of the
pixel) at depth z is the camera-frame point ``((u - cx) z / fx, (v - cy) z / fy, z)``. Depth 0 or +inf marks a
pixel with no return; NaN is refused (mark missing returns with 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .validation import as_pose_array

# A depth image's rays that miss the object are free-space evidence; this many at most are kept per observation
# (drawn evenly at random, seeded), which bounds memory for many 640x480 images.
MAX_FREE_RAYS = 200_000


@dataclass(frozen=True)
class Observation:
    """World-frame surface points of one object and the free space in front of them (see the module docstring)."""

    points: np.ndarray
    origins: np.ndarray | None = None
    normals: np.ndarray | None = None
    free_origins: np.ndarray | None = None
    free_ends: np.ndarray | None = None
    views: int = 1

    def __post_init__(self):
        points = _rows(self.points, "points")
        if len(points) == 0:
            raise InputError("the observation has no points: the mask selected nothing, or every depth was 0 (no return); "
                             "check the mask and the depth image's units (metres)")
        object.__setattr__(self, "points", points)
        for name in ("origins", "normals"):
            value = getattr(self, name)
            if value is not None:
                rows = _rows(value, name)
                if rows.shape != points.shape:
                    raise InputError(f"{name} must be (N, 3) like points {points.shape}, got {rows.shape}")
                object.__setattr__(self, name, rows)
        if self.normals is not None:
            norm = np.linalg.norm(self.normals, axis=1, keepdims=True)
            if (norm < 1e-9).any():
                raise InputError("normals has zero-length rows; give unit outward normals or none")
            object.__setattr__(self, "normals", self.normals / norm)
        if (self.free_origins is None) != (self.free_ends is None):
            raise InputError("free_origins and free_ends go together: give both or neither")
        if self.free_origins is not None:
            fo, fe = _rows(self.free_origins, "free_origins"), _rows(self.free_ends, "free_ends")
            if fo.shape != fe.shape:
                raise InputError(f"free_origins {fo.shape} and free_ends {fe.shape} must have the same shape")
            object.__setattr__(self, "free_origins", fo)
            object.__setattr__(self, "free_ends", fe)
        object.__setattr__(self, "views", int(self.views))

    def __len__(self) -> int:
        return len(self.points)

    def __repr__(self):
        free = 0 if self.free_origins is None else len(self.free_origins)
        return (f"Observation({len(self.points)} points, {self.views} view(s), origins={self.origins is not None}, "
                f"normals={self.normals is not None}, {free} free rays)")

    @property
    def extent(self) -> float:
        """The largest side of the points' bounding box (metres)."""
        return float(np.ptp(self.points, axis=0).max())

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_points(cls, points, origins=None, normals=None) -> Observation:
        """Surface points (N, 3), world frame; ``origins`` (N, 3) or (3,) (one sensor for every point) and outward
        ``normals`` (N, 3) where known."""
        points = _rows(points, "points")
        if origins is not None:
            origins = np.asarray(origins, dtype=np.float64)
            if origins.shape == (3,):
                origins = np.broadcast_to(origins, points.shape).copy()
        return cls(points, origins, normals)

    @classmethod
    def from_depth(cls, depth, K, T_world_camera, mask=None, seed: int = 0) -> Observation:
        """One or several depth images: ``depth`` (H, W) or (V, H, W) in metres, ``K`` (3, 3) or (V, 3, 3) pinhole
        intrinsics, ``T_world_camera`` (4, 4) or (V, 4, 4) OpenCV camera to world, ``mask`` (H, W) or (V, H, W)
        booleans selecting the object's pixels (None: every pixel with a return is the object).

        Pixels in the mask become surface points seen from their camera's centre; pixels outside it with a return
        become free rays (they saw past the object), at most ``MAX_FREE_RAYS`` of them (drawn with ``seed``).
        """
        depth = np.asarray(depth, dtype=np.float64)
        if depth.ndim == 2:
            depth = depth[None]
        if depth.ndim != 3 or min(depth.shape) == 0:
            raise InputError(f"depth must be an (H, W) image or a (V, H, W) stack, got shape {depth.shape}")
        views, height, width = depth.shape
        if np.isnan(depth).any():
            raise InputError(f"depth has {int(np.isnan(depth).sum())} NaN pixels; mark pixels with no return as 0 "
                             "(or +inf), not NaN")
        if (depth < 0).any():
            raise InputError("depth has negative values; depth is the distance along the camera's z axis, in metres")
        intrinsics = _per_view(K, (3, 3), views, "K")
        poses = _per_view(T_world_camera, (4, 4), views, "T_world_camera")
        masks = _masks(mask, depth.shape)
        rng = np.random.default_rng(seed)
        points, origins, free_o, free_e = [], [], [], []
        for v in range(views):
            k = _check_intrinsics(intrinsics[v], width, height, v)
            pose = as_pose_array(poses[v], f"T_world_camera[{v}]")
            hit = np.isfinite(depth[v]) & (depth[v] > 0)
            on_object = hit & masks[v]
            world = _backproject(depth[v], k, pose)
            centre = pose[:3, 3]
            points.append(world[on_object])
            origins.append(np.broadcast_to(centre, (int(on_object.sum()), 3)))
            if mask is not None:
                beside = world[hit & ~masks[v]]
                free_e.append(beside)
                free_o.append(np.broadcast_to(centre, beside.shape))
        points = np.concatenate(points)
        if len(points) == 0:
            raise InputError("the mask selects no pixel with a return (depth > 0) in any view: nothing of the object "
                             "was seen; check the mask and that depth is in metres")
        free = None
        if mask is not None:
            fo, fe = np.concatenate(free_o), np.concatenate(free_e)
            if len(fe) > MAX_FREE_RAYS:
                keep = np.sort(rng.choice(len(fe), MAX_FREE_RAYS, replace=False))
                fo, fe = fo[keep], fe[keep]
            free = (np.ascontiguousarray(fo), np.ascontiguousarray(fe)) if len(fe) else None
        return cls(points, np.concatenate(origins), None, *(free or (None, None)), views=views)

    @classmethod
    def from_mujoco(cls, model, data, camera, body=None, width: int = 640, height: int = 480,
                    depth_noise: float = 0.0, seed: int = 0) -> Observation:
        """What MuJoCo's cameras see: ``camera`` a camera's name or id, or a list of them (one image each), rendered
        offscreen (``mujoco.Renderer``: EGL or OSMesa) at ``width`` x ``height``, depth and segmentation.

        ``body`` (a name or id): the object, whose geoms' pixels are the surface points (the others, the table and
        the rest of the scene, give free rays); None: every pixel with a return is the object. ``depth_noise``
        (metres at 0.5 m, growing with the depth squared) adds Gaussian noise, seeded, for simulated sensors.
        ``data`` must be current (``mujoco.mj_forward``).
        """
        import mujoco

        cameras = [camera] if isinstance(camera, (str, int, np.integer)) else list(camera)
        if not cameras:
            raise InputError("from_mujoco needs at least one camera (a name or id of the model's cameras)")
        body_id = None if body is None else _mujoco_id(model, mujoco.mjtObj.mjOBJ_BODY, body, "body")
        ids = [_mujoco_id(model, mujoco.mjtObj.mjOBJ_CAMERA, c, "camera") for c in cameras]
        depth, masks, intrinsics, poses = [], [], [], []
        rng = np.random.default_rng(seed)
        try:
            renderer = mujoco.Renderer(model, height, width)
        except Exception as exc:  # no GL context: a missing EGL/OSMesa, a size past the model's offscreen buffer
            raise InputError(f"MuJoCo's renderer could not start ({exc}); set MUJOCO_GL=egl or osmesa (Debian's "
                             "libosmesa6), and model.vis.global_.offwidth/offheight to at least the image size") from exc
        try:
            for cam in ids:
                renderer.enable_depth_rendering()
                renderer.update_scene(data, camera=cam)
                z = np.array(renderer.render(), dtype=np.float64)
                renderer.disable_depth_rendering()
                renderer.enable_segmentation_rendering()
                renderer.update_scene(data, camera=cam)
                seg = np.array(renderer.render())
                renderer.disable_segmentation_rendering()
                is_geom = (seg[..., 0] >= 0) & (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM))
                z[~is_geom] = 0.0  # the background: no return
                if depth_noise:
                    z = np.where(z > 0, z + rng.normal(size=z.shape) * depth_noise * (z / 0.5) ** 2, 0.0)
                depth.append(np.maximum(z, 0.0))
                if body_id is None:
                    masks.append(is_geom)
                else:
                    masks.append(is_geom & (model.geom_bodyid[np.maximum(seg[..., 0], 0)] == body_id))
                intrinsics.append(mujoco_intrinsics(model, cam, width, height))
                poses.append(mujoco_camera_pose(data, cam))
        finally:
            renderer.close()
        return cls.from_depth(np.stack(depth), np.stack(intrinsics), np.stack(poses),
                              None if body is None else np.stack(masks), seed=seed)


# --------------------------------------------------------------------------- cameras


def mujoco_intrinsics(model, camera: int, width: int, height: int) -> np.ndarray:
    """K (3, 3) of MuJoCo camera ``camera`` (id) for a ``width`` x ``height`` image: square pixels, ``cam_fovy``
    the vertical field of view, the principal point at the image centre (OpenCV's pixel centres: (W - 1) / 2)."""
    f = 0.5 * height / np.tan(np.deg2rad(float(model.cam_fovy[camera])) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def mujoco_camera_pose(data, camera: int) -> np.ndarray:
    """T_world_camera (4, 4) of MuJoCo camera ``camera`` (id) in OpenCV's axes: MuJoCo's camera looks along its -z
    with y up, so its y and z axes are flipped."""
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(data.cam_xmat[camera], dtype=np.float64).reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = data.cam_xpos[camera]
    return pose


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_camera (4, 4) of an OpenCV camera at ``eye`` (3,) looking at ``target`` (3,), image rows going down
    along -``up``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    if not np.linalg.norm(z) > 0:
        raise InputError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if not np.linalg.norm(x) > 1e-9:
        raise InputError("look_at: the view direction is parallel to up; pick another up")
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


def _backproject(depth: np.ndarray, k: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of a depth image (H, W) with intrinsics ``k`` (3, 3) and world-from-camera ``pose``."""
    height, width = depth.shape
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    z = np.where(np.isfinite(depth), depth, 0.0)
    camera = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=-1)
    return camera @ pose[:3, :3].T + pose[:3, 3]


# --------------------------------------------------------------------------- checks


def _rows(value, name: str) -> np.ndarray:
    rows = np.asarray(value, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 3:
        raise InputError(f"{name} must be (N, 3), got shape {rows.shape}")
    if not np.isfinite(rows).all():
        raise InputError(f"{name} has NaN or Inf entries; drop those rows first")
    return np.ascontiguousarray(rows)


def _per_view(value, shape: tuple, views: int, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape == shape:
        a = np.broadcast_to(a, (views, *shape))
    if a.shape != (views, *shape):
        raise InputError(f"{name} must be {shape} or ({views}, {', '.join(map(str, shape))}) for {views} depth image(s), "
                         f"got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name} has NaN or Inf entries")
    return a


def _check_intrinsics(k: np.ndarray, width: int, height: int, view: int) -> np.ndarray:
    if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
        raise InputError(f"K[{view}] is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0: {k.tolist()}")
    cx, cy = k[0, 2], k[1, 2]
    if not (0 <= cx <= width - 1 and 0 <= cy <= height - 1):
        raise InputError(f"K[{view}]'s principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} depth image: "
                         "the image does not match K (is depth (H, W), at the resolution K was calibrated for?)")
    return k


def _masks(mask, shape: tuple) -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.ndim == 2:
        m = m[None]
    if m.shape != shape:
        raise InputError(f"mask must have the depth's shape {shape[1:] if shape[0] == 1 else shape}, got {np.asarray(mask).shape}")
    if m.dtype != bool:
        raise InputError(f"mask must be booleans (True on the object's pixels), got dtype {m.dtype}")
    if not m.any():
        raise InputError("the mask selects no pixel: nothing of the object was seen")
    return m


def _mujoco_id(model, kind, name_or_id, what: str) -> int:
    import mujoco

    count = {"body": model.nbody, "camera": model.ncam}[what]
    if isinstance(name_or_id, (int, np.integer)):
        if not 0 <= int(name_or_id) < count:
            raise InputError(f"{what} id {name_or_id} is out of range: the model has {count} {what}s")
        return int(name_or_id)
    found = mujoco.mj_name2id(model, kind, str(name_or_id))
    if found < 0:
        raise InputError(f"the model has no {what} named {name_or_id!r}")
    return found
