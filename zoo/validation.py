"""Argument checks shared by zoo and pipeline: numbers, counts and tensors in, typed errors out.

Every check either returns the value converted (a ``float``, an ``int``, a tensor of the shape the
conventions name) or raises :class:`zoo.errors.InputError` with a message that says what was wrong
and what to do. Conventions: points are (N, 3); triangles are (M, 3, 3) (triangle, vertex, xyz);
barycentric coordinates are (M, 3), non-negative, rows summing to 1; poses are 4x4 world-from-object.
float64 input is kept as float64; other numbers become float32 unless a ``dtype`` is named.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch

from .errors import DeviceError, InputError

FLOATS = (torch.float32, torch.float64)

# Coordinates this far below 0, or rows whose sum is this far from 1, are rejected as not barycentric;
# closer ones (rounding from a softmax or from many convex combinations) are snapped back.
SIMPLEX_TOL = 1e-4

# -- devices -------------------------------------------------------------------------------------


def as_device(device) -> torch.device:
    """``device`` ("cpu", "cuda", "cuda:1", a torch.device) as a torch.device this machine can use.

    A malformed name is an :class:`InputError`; a device that torch cannot use here (a CPU-only
    build, no GPU, a GPU index past the last) a :class:`zoo.errors.DeviceError`, checked before any
    tensor is moved (torch's own answer is an ``AssertionError`` deep inside the first copy).
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"device {device!r} is not a torch device name; use cpu, cuda or cuda:N") from exc
    if dev.type == "cuda":
        if torch.version.cuda is None and getattr(torch.version, "hip", None) is None:
            raise DeviceError(f"device {device!r}: this torch {torch.__version__} is built without CUDA; use --device cpu, "
                              "or install a CUDA build of torch (the command for your machine is on pytorch.org)")
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise DeviceError(f"device {device!r}: torch has CUDA but finds no GPU on this machine (check nvidia-smi and "
                              "CUDA_VISIBLE_DEVICES); use --device cpu")
        if dev.index is not None and dev.index >= count:
            raise DeviceError(f"device {device!r}: this machine has {count} GPU(s), cuda:0 to cuda:{count - 1}; pick one of them")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise DeviceError(f"device {device!r}: MPS is not available on this machine; use --device cpu")
    return dev


# -- scalars -------------------------------------------------------------------------------------


def positive_float(value, name: str) -> float:
    """``value`` as a float in (0, inf)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a positive finite number, got {value!r}") from exc
    if not (v > 0 and math.isfinite(v)):
        raise InputError(f"{name} must be a positive finite number, got {value!r}")
    return v


def non_negative_float(value, name: str) -> float:
    """``value`` as a float in [0, inf) (a margin, a padding)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number >= 0, got {value!r}") from exc
    if not (v >= 0 and v < float("inf")):
        raise InputError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def float_in(value, name: str, low: float, high: float, low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a finite float in the interval [low, high]; ``low_open``/``high_open`` exclude an end."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number, got {value!r}") from exc
    too_low = v <= low if low_open else v < low
    too_high = v >= high if high_open else v > high
    if math.isnan(v) or too_low or too_high or math.isinf(v):
        lo, hi = ("(" if low_open else "[") + f"{low}", f"{high}" + (")" if high_open else "]")
        raise InputError(f"{name} must be a finite number in {lo}, {hi}, got {value!r}")
    return v


def positive_int(value, name: str) -> int:
    """``value`` as an int >= 1 (anything with ``__index__``; not a bool)."""
    if isinstance(value, bool) or not hasattr(value, "__index__") or int(value) < 1:
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def non_negative_int(value, name: str) -> int:
    """``value`` as an int >= 0 (anything with ``__index__``; not a bool)."""
    if isinstance(value, bool) or not isinstance(value, int) and not (hasattr(value, "__index__")):
        raise InputError(f"{name} must be a non-negative integer, got {value!r}")
    v = int(value)
    if v < 0:
        raise InputError(f"{name} must be a non-negative integer, got {value!r}")
    return v


def int_at_least(value, name: str, minimum: int = 0) -> int:
    """``value`` as an int >= ``minimum`` (a Python integral; not a bool)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise InputError(f"{name} must be an int >= {minimum}, got {value!r}")
    return int(value)


def interval(value, name: str, positive: bool = False) -> tuple[float, float]:
    """Two finite numbers (low, high) with low <= high (and low > 0 if ``positive``)."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be two numbers (low, high), got {value!r}") from exc
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi) or (positive and lo <= 0):
        raise InputError(f"{name} must be finite with low <= high{' and low > 0' if positive else ''}, got {value!r}")
    return lo, hi


def vector3(value, name: str) -> torch.Tensor:
    """Three finite numbers as a float64 (3,) tensor (a centre, an axis)."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.shape != (3,) or not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} must be three finite numbers, got {value!r}")
    return t


# -- tensors -------------------------------------------------------------------------------------


def as_float_tensor(x, name: str, dtype: torch.dtype | None = None, allow_empty: bool = False) -> torch.Tensor:
    """``x`` as a real float tensor: float64 kept, other numbers float32 unless ``dtype`` says.

    Empty input is refused unless ``allow_empty``.
    """
    try:
        t = torch.as_tensor(x)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name} must be array-like of numbers, got {type(x).__name__}") from exc
    if t.is_complex() or t.dtype == torch.bool:
        raise InputError(f"{name} must hold real numbers, got dtype {t.dtype}")
    if dtype is not None:
        t = t.to(dtype)
    elif t.dtype not in FLOATS:
        t = t.to(torch.float32)
    if t.numel() == 0 and not allow_empty:
        raise InputError(f"{name} is empty (shape {tuple(t.shape)}); pass at least one element")
    return t


def check_finite(t: torch.Tensor, name: str) -> None:
    """Refuse NaN or Inf, counting the rows (last axis) that hold any."""
    if not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).any(dim=-1).sum()) if t.ndim > 1 else int((~torch.isfinite(t)).sum())
        raise InputError(f"{name} holds NaN or Inf in {bad} row(s); remove or fix them before calling")


def as_rows(x, name: str) -> torch.Tensor:
    """Finite float rows (at least one, not a scalar), e.g. values or gradients handed to a solver."""
    try:
        t = torch.as_tensor(x)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name} must be array-like of numbers, got {type(x).__name__}") from exc
    if t.dtype not in FLOATS:
        if t.is_complex() or t.dtype == torch.bool:
            raise InputError(f"{name} must hold real numbers, got dtype {t.dtype}")
        t = t.to(torch.float32)
    if t.numel() == 0 or t.ndim == 0:
        raise InputError(f"{name} is empty or a scalar (shape {tuple(t.shape)}); pass at least one row")
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} holds NaN or Inf; remove or fix those rows before calling")
    return t


def as_points(points, name: str = "points", dtype: torch.dtype | None = None, allow_empty: bool = False) -> torch.Tensor:
    """Validate and convert ``points`` to a float tensor of shape (N, 3).

    Raises :class:`InputError` for wrong shapes, NaN or Inf, and for empty input unless ``allow_empty``.
    """
    t = as_float_tensor(points, name, dtype, allow_empty=allow_empty)
    if allow_empty and t.numel() == 0 and t.ndim < 2:
        t = t.reshape(0, 3)  # an empty list or array: no points
    if t.ndim != 2 or t.shape[-1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {tuple(t.shape)}; reshape with .reshape(-1, 3)")
    check_finite(t, name)
    return t


def as_triangles(triangles, name: str = "triangles", dtype: torch.dtype | None = None, allow_empty: bool = False) -> torch.Tensor:
    """Validate and convert ``triangles`` to a float tensor of shape (M, 3, 3); (3, 3) is one triangle.

    Zero triangles (shape (0, 3, 3)) are refused unless ``allow_empty``.
    """
    t = as_float_tensor(triangles, name, dtype, allow_empty=allow_empty)
    if allow_empty and t.numel() == 0 and t.ndim < 3:
        t = t.reshape(0, 3, 3)  # an empty list or array of any empty shape: no triangles
    if t.ndim == 2 and t.shape == (3, 3):
        t = t.unsqueeze(0)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise InputError(f"{name} must have shape (M, 3, 3) (triangle, vertex, xyz), got {tuple(t.shape)}")
    check_finite(t, name)
    return t


def as_barycentric(bary, triangles: torch.Tensor, name: str = "bary") -> torch.Tensor:
    """Validate barycentric coordinates (M, 3) against triangles (M, 3, 3) (finite, matching shape)."""
    b = as_float_tensor(bary, name, triangles.dtype, allow_empty=triangles.shape[0] == 0).to(triangles.device)
    if b.shape != triangles.shape[:2]:
        raise InputError(f"{name} must have shape {tuple(triangles.shape[:2])} to match the triangles, got {tuple(b.shape)}")
    check_finite(b, name)
    return b


def as_simplex(bary, triangles: torch.Tensor, name: str) -> torch.Tensor:
    """Validate (M, 3) barycentric coordinates and snap rounding-level deviations back onto the simplex."""
    b = as_barycentric(bary, triangles, name)
    if bool((b < -SIMPLEX_TOL).any()) or bool(((b.sum(dim=-1) - 1).abs() > SIMPLEX_TOL).any()):
        raise InputError(
            f"{name} must be barycentric coordinates (non-negative, rows summing to 1); "
            "project them first with zoo.solvers.project_to_simplex"
        )
    b = b.clamp_min(0)
    return b / b.sum(dim=-1, keepdim=True)


def as_pose(pose, dtype: torch.dtype = torch.float32, name: str = "pose") -> torch.Tensor:
    """Validate a 4x4 rigid transform (world-from-object); ``None`` is the identity."""
    if pose is None:
        return torch.eye(4, dtype=dtype)
    t = as_float_tensor(pose, name, dtype)
    if t.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 homogeneous transform, got shape {tuple(t.shape)}")
    check_finite(t, name)
    r = t[:3, :3].double()
    if not torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-4) or float(torch.det(r)) <= 0:
        raise InputError(f"{name}'s upper-left 3x3 block must be a rotation (orthonormal, det +1)")
    return t


def as_pose_array(pose, name: str = "pose") -> np.ndarray:
    """:func:`as_pose` in numpy float64 (4, 4), for the per-step paths where torch's per-call cost shows."""
    if pose is None:
        return np.eye(4)
    t = np.asarray(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64)
    if t.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 homogeneous transform, got shape {tuple(t.shape)}")
    if not np.isfinite(t).all():
        raise InputError(f"{name} has NaN or Inf entries")
    r = t[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) <= 0:
        raise InputError(f"{name}'s upper-left 3x3 block must be a rotation (orthonormal, det +1)")
    return t


# -- meshes --------------------------------------------------------------------------------------


def mesh_pair(mesh, name: str = "mesh") -> tuple:
    """(vertices, faces) as given, from a ``trimesh.Trimesh`` (anything with ``.vertices`` and ``.faces``)
    or a (vertices (V, 3), faces (F, 3)) pair; the caller converts them (:func:`as_points`, :func:`as_faces`)."""
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return mesh.vertices, mesh.faces
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return mesh[0], mesh[1]
    raise InputError(f"{name} must be a trimesh.Trimesh or a (vertices (V, 3), faces (F, 3)) pair, got {type(mesh).__name__}")


def as_faces(faces, n_vertices: int, name: str = "mesh faces") -> torch.Tensor:
    """Faces as an int64 tensor (F, 3) of indices into ``n_vertices`` vertices; no faces (any empty array) is (0, 3)."""
    try:
        f = torch.as_tensor(faces)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name} must be an integer array (F, 3), got {type(faces).__name__}") from exc
    if f.numel() == 0:
        return torch.zeros((0, 3), dtype=torch.int64)  # an empty mesh (or [] faces)
    if f.is_floating_point() or f.is_complex() or f.dtype == torch.bool:
        raise InputError(f"{name} must hold integer vertex indices, got dtype {f.dtype}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"{name} must have shape (F, 3), got {tuple(f.shape)}")
    f = f.long()
    low, high = torch.aminmax(f)  # one pass over the faces instead of two comparisons and two reductions
    if int(low) < 0 or int(high) >= n_vertices:
        raise InputError(f"{name} index vertices outside 0..{n_vertices - 1}; fix the faces array")
    return f
