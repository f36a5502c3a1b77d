"""The SDF protocol and analytic SDFs with exact answers.

An SDF is any object with
  * ``sdf(points)``: (N, 3) -> (N,), signed distance, negative inside;
  * ``sdf.value_and_grad(points)``: (N, 3) -> ((N,), (N, 3));
  * ``sdf.bounds``: two (3,) tensors, the corners of a box that holds its surface.
Every function in sdfzoo accepts any such object; :class:`SDFBase` is a convenience, not
a requirement.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import torch

from .errors import InputError
from .validation import as_points, positive_float, vector3


@runtime_checkable
class SDF(Protocol):
    bounds: tuple[torch.Tensor, torch.Tensor]

    def __call__(self, points: torch.Tensor) -> torch.Tensor: ...

    def value_and_grad(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...


def check_sdf(sdf) -> None:
    """Raise :class:`InputError` unless ``sdf`` follows the SDF protocol."""
    missing = [a for a in ("__call__", "value_and_grad", "bounds") if not hasattr(sdf, a)]
    if missing:
        raise InputError(
            f"{type(sdf).__name__} is not an SDF: it lacks {', '.join(missing)}; "
            "an SDF is callable on (N, 3) points and has value_and_grad(points) and bounds"
        )


def autograd_value_and_grad(fn, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Value and gradient of a differentiable ``fn``: (N, 3) -> (N,), (N, 3).

    Works under ``torch.no_grad()`` too, and returns tensors detached from any graph.
    """
    with torch.enable_grad():
        x = points.detach().requires_grad_(True)
        d = fn(x)
        (g,) = torch.autograd.grad(d.sum(), x)
    return d.detach(), g.detach()


def value_and_grad_numpy(sdf, points: np.ndarray, dtype: torch.dtype = torch.float32) -> tuple[np.ndarray, np.ndarray]:
    """``sdf``'s values (N,) and gradients (N, 3), float64 numpy, at ``points`` (N, 3) numpy, asked in ``dtype``: through
    its compiled network where it has one for so few points (a NeuralShape's ``value_and_grad_few``: no torch round
    trip, whose fixed cost is most of a small query's), else through ``value_and_grad``. For colliders that ask a
    handful of points many times a step."""
    few = getattr(sdf, "value_and_grad_few", None)
    answer = few(points, dtype) if few is not None else None
    if answer is not None:
        return answer[0].astype(np.float64), answer[1].astype(np.float64)
    with torch.no_grad():
        f, g = sdf.value_and_grad(torch.from_numpy(np.ascontiguousarray(points)).to(dtype))
    return torch.as_tensor(f).reshape(-1).double().cpu().numpy(), torch.as_tensor(g).reshape(-1, 3).double().cpu().numpy()


def query_dtype(sdf) -> torch.dtype:
    """The dtype a simulation asks ``sdf`` in: float64 for an SDF in float64, else float32."""
    return torch.float64 if getattr(sdf, "dtype", None) == torch.float64 else torch.float32


class SDFBase:
    """Validates input, converts dtypes, and derives ``value_and_grad`` by autograd.

    Subclasses implement ``_distance(points)`` on a validated (N, 3) tensor and may
    override ``_value_and_grad`` with a closed form.
    """

    bounds: tuple[torch.Tensor, torch.Tensor]

    def __call__(self, points) -> torch.Tensor:
        return self._distance(as_points(points))

    def value_and_grad(self, points) -> tuple[torch.Tensor, torch.Tensor]:
        return self._value_and_grad(as_points(points))

    def _distance(self, points: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def _value_and_grad(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return autograd_value_and_grad(self._distance, points)

    def _param(self, value, points: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(value, dtype=points.dtype, device=points.device)


def _unit_gradient(offset: torch.Tensor) -> torch.Tensor:
    """Direction of ``offset`` (N, 3); an arbitrary unit vector where it vanishes (medial points)."""
    n = offset.norm(dim=-1, keepdim=True)
    fallback = torch.zeros_like(offset)
    fallback[:, 2] = 1.0
    return torch.where(n > 0, offset / n.clamp_min(torch.finfo(offset.dtype).tiny), fallback)


class Sphere(SDFBase):
    """Sphere of ``radius`` about ``center``."""

    def __init__(self, radius: float = 0.25, center=(0.0, 0.0, 0.0)):
        self.radius = positive_float(radius, "radius")
        self.center = vector3(center, "center")
        self.bounds = (self.center.float() - self.radius, self.center.float() + self.radius)

    def _distance(self, points):
        return (points - self._param(self.center, points)).norm(dim=-1) - self.radius

    def _value_and_grad(self, points):
        off = points - self._param(self.center, points)
        return off.norm(dim=-1) - self.radius, _unit_gradient(off)

    def __repr__(self):
        return f"Sphere(radius={self.radius}, center={self.center.tolist()})"


class Box(SDFBase):
    """Axis-aligned box with ``half_extents`` about ``center``; exact distance inside and out."""

    def __init__(self, half_extents=(0.2, 0.15, 0.1), center=(0.0, 0.0, 0.0)):
        self.half_extents = vector3(half_extents, "half_extents")
        if bool((self.half_extents <= 0).any()):
            raise InputError(f"half_extents must be positive, got {half_extents!r}")
        self.center = vector3(center, "center")
        self.bounds = ((self.center - self.half_extents).float(), (self.center + self.half_extents).float())

    def _distance(self, points):
        q = (points - self._param(self.center, points)).abs() - self._param(self.half_extents, points)
        outside = q.clamp_min(0).norm(dim=-1)
        inside = q.amax(dim=-1).clamp_max(0)
        return outside + inside

    def __repr__(self):
        return f"Box(half_extents={self.half_extents.tolist()}, center={self.center.tolist()})"


class Torus(SDFBase):
    """Torus about ``center`` with its axis along z: ring radius ``major``, tube radius ``minor``."""

    def __init__(self, major: float = 0.25, minor: float = 0.08, center=(0.0, 0.0, 0.0)):
        self.major = positive_float(major, "major")
        self.minor = positive_float(minor, "minor")
        if self.minor >= self.major:
            raise InputError(f"minor ({minor}) must be smaller than major ({major}) for a ring torus")
        self.center = vector3(center, "center")
        r = self.major + self.minor
        ext = torch.tensor([r, r, self.minor], dtype=torch.float64)
        self.bounds = ((self.center - ext).float(), (self.center + ext).float())

    def _closest_on_ring(self, p):
        radial = p.clone()
        radial[:, 2] = 0
        return self.major * _unit_gradient_xy(radial)

    def _distance(self, points):
        p = points - self._param(self.center, points)
        return (p - self._closest_on_ring(p)).norm(dim=-1) - self.minor

    def _value_and_grad(self, points):
        p = points - self._param(self.center, points)
        off = p - self._closest_on_ring(p)
        return off.norm(dim=-1) - self.minor, _unit_gradient(off)

    def __repr__(self):
        return f"Torus(major={self.major}, minor={self.minor}, center={self.center.tolist()})"


def _unit_gradient_xy(radial: torch.Tensor) -> torch.Tensor:
    n = radial.norm(dim=-1, keepdim=True)
    fallback = torch.zeros_like(radial)
    fallback[:, 0] = 1.0  # on the axis every ring point is closest; pick one
    return torch.where(n > 0, radial / n.clamp_min(torch.finfo(radial.dtype).tiny), fallback)


class Capsule(SDFBase):
    """Segment from ``a`` to ``b`` swept by a ball of ``radius``."""

    def __init__(self, a=(0.0, 0.0, -0.2), b=(0.0, 0.0, 0.2), radius: float = 0.1):
        self.a = vector3(a, "a")
        self.b = vector3(b, "b")
        self.radius = positive_float(radius, "radius")
        self.bounds = ((torch.minimum(self.a, self.b) - self.radius).float(), (torch.maximum(self.a, self.b) + self.radius).float())

    def _offset(self, points):
        a, b = self._param(self.a, points), self._param(self.b, points)
        ab = b - a
        denom = (ab * ab).sum().clamp_min(torch.finfo(points.dtype).tiny)
        t = (((points - a) @ ab) / denom).clamp(0, 1)
        return points - (a + t.unsqueeze(-1) * ab)

    def _distance(self, points):
        return self._offset(points).norm(dim=-1) - self.radius

    def _value_and_grad(self, points):
        off = self._offset(points)
        return off.norm(dim=-1) - self.radius, _unit_gradient(off)

    def __repr__(self):
        return f"Capsule(a={self.a.tolist()}, b={self.b.tolist()}, radius={self.radius})"


class TransformedSDF(SDFBase):
    """An SDF placed by a rigid 4x4 transform (world-from-object); distances are unchanged."""

    def __init__(self, sdf, pose: torch.Tensor):
        from .geometry import invert_pose, transform_points
        from .validation import as_pose

        check_sdf(sdf)
        self.sdf = sdf
        self.pose = as_pose(pose, torch.float64)
        self.inverse = invert_pose(self.pose)
        lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
        corners = torch.stack(torch.meshgrid(*[torch.stack([lo[i], hi[i]]) for i in range(3)], indexing="ij"), -1).reshape(-1, 3)
        world = transform_points(self.pose, corners)
        self.bounds = (world.amin(0).float(), world.amax(0).float())

    def _local(self, points):
        from .geometry import transform_points

        return transform_points(self.inverse.to(points), points)

    def _distance(self, points):
        return self.sdf(self._local(points))

    def _value_and_grad(self, points):
        from .geometry import transform_vectors

        d, g = self.sdf.value_and_grad(self._local(points))
        return d, transform_vectors(self.pose.to(g), g)
