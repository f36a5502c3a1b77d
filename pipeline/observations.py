"""`zoo fit-codes MODEL --points FILE.ply | --depth FILE.npz`: read what a sensor saw, fit it, save the shape.

File formats:

- ``--points FILE.ply``: a point cloud, world frame, metres; per-vertex normals (``nx ny nz``) are used where present;
  ``--origin X,Y,Z`` names the sensor the points were seen from (free-space evidence).
- ``--depth FILE.npz``: ``depth`` (H, W) or (V, H, W) metres (0: no return), ``K`` (3, 3) or (V, 3, 3),
  ``T_world_camera`` (4, 4) or (V, 4, 4) (OpenCV camera to world), optionally ``mask`` (booleans, the object's pixels).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from zoo.errors import DataError, InputError

DEPTH_KEYS = ("depth", "K", "T_world_camera")


def read_points(path: str | os.PathLike, origin=None):
    """A :class:`zoo.Observation` of the points (and normals) of a PLY (or any point file trimesh reads)."""
    import trimesh

    import zoo

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path} does not exist; give a .ply point cloud (world frame, metres)")
    try:
        cloud = trimesh.load(path)
    except Exception as exc:  # trimesh raises many types for a file it cannot parse
        raise DataError(f"{path} is not a readable point cloud ({exc}); write it as PLY with x y z (and nx ny nz)") from exc
    points = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=np.float64)
    raw = cloud.metadata.get("_ply_raw", {}).get("vertex", {}).get("data") if hasattr(cloud, "metadata") else None
    normals = None
    if raw is not None and raw.dtype.names and {"nx", "ny", "nz"} <= set(raw.dtype.names):
        normals = np.stack([raw["nx"], raw["ny"], raw["nz"]], axis=1).astype(np.float64)
    return zoo.Observation.from_points(points, origins=origin, normals=normals)


def read_depth(path: str | os.PathLike):
    """A :class:`zoo.Observation` of the depth images in an .npz file (module docstring)."""
    import zoo

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path} does not exist; give an .npz with depth, K and T_world_camera (and mask)")
    try:
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as exc:  # a torn or foreign file
        raise DataError(f"{path} is not a readable .npz file ({exc}); write it with numpy.savez") from exc
    missing = [k for k in DEPTH_KEYS if k not in arrays]
    if missing:
        raise InputError(f"{path} lacks {', '.join(missing)}; it needs depth (metres), K and T_world_camera "
                         "(OpenCV camera to world), and may hold mask")
    return zoo.Observation.from_depth(arrays["depth"], arrays["K"], arrays["T_world_camera"], arrays.get("mask"))


def fit_observed(model_spec, obs, out: str | os.PathLike | None = None, up=(0.0, 0.0, 1.0), seed: int = 0,
                 device: str = "cpu", name: str = "observed", progress: bool = True) -> dict:
    """Fit ``obs`` against a model (``Model.fit_observation``); optionally save the shape; -> summary."""
    import zoo

    model = zoo.load(model_spec, device=device) if isinstance(model_spec, (str, os.PathLike)) else model_spec
    started = time.perf_counter()
    shape = model.fit_observation(obs, up=up, seed=seed, name=name, progress=progress)
    fit = shape.fit
    summary = {"model": f"{model.name}@{model.version}", "shape": shape.name, "observation": fit["observation"],
               "fit_seconds": time.perf_counter() - started, "pose": fit["pose"], "size_m": fit["scale"]["size_m"],
               "residual_mm": fit["residual_mm"], "loss": fit["loss"],
               "other_yaws": [{k: r[k] for k in ("start_yaw_deg", "yaw_deg", "search_loss")} for r in fit["rejected"]]}
    if out is not None:
        shape.save(out)
        summary["out"] = str(out)
    return summary
