"""VoxelSDF: any SDF sampled on a regular grid and read back by trilinear interpolation.

This is the paper's voxel baseline (Isaac Sim / PhysX store SDFs this way). The grid holds
``resolution`` samples per axis spanning the SDF's bounds grown by ``padding`` on every side,
stored as float32. Queries are batched:

* inside the grid box, the value is the trilinear interpolant of the samples and the gradient
  is the exact gradient of that interpolant (it is piecewise: a point on a shared cell face
  takes the gradient of the cell above it, a point on the grid's far face that of the last
  cell; see :meth:`VoxelSDF._cell`);
* outside the grid box, a point ``p`` is clamped to the box (``q = clamp(p)``) and gets
  ``value(q) + |p - q|``. The true SDF is 1-Lipschitz, so ``f(p) <= f(q) + |p - q|``: this is
  an upper bound on the true distance (up to the interpolation error), exact when the surface
  point nearest ``p`` lies straight behind ``q``, continuous across the box's faces and growing
  like the distance far away, so solvers and culls still see a sensible field. Its gradient is
  exact too: the interpolant's gradient along the axes where ``p`` is inside the box, plus the
  unit vector ``(p - q) / |p - q|`` (so its length may exceed 1 slightly).

The memory is ``nx * ny * nz * 4`` bytes (1024^3 is 4 GiB); a grid larger than ``max_bytes``
is refused before anything is allocated.
"""

from __future__ import annotations

import math
import numbers

import torch

from .errors import InputError
from .sdf import check_sdf
from .validation import as_points, positive_float

GiB = 1 << 30
DEFAULT_MAX_BYTES = 4 * GiB
_BYTES_PER_SAMPLE = 4  # float32


class VoxelSDF:
    """A regular-grid, trilinear copy of ``sdf`` that follows the SDF protocol itself.

    Args:
        sdf: any SDF protocol object (callable on (N, 3) points, ``value_and_grad``, ``bounds``).
        resolution: samples per axis, one int or three ints, each >= 2 (cell count is one fewer).
        bounds: two (3,) corners of the box to sample; default ``sdf.bounds``.
        padding: grown onto every side of ``bounds``, as a fraction of the box's longest side,
            so the surface lies inside the grid with room for a contact margin; >= 0.
        chunk: how many grid points are evaluated per call of ``sdf`` while building, which
            bounds the build's extra memory to a few times ``chunk * 3`` floats.
        max_bytes: refuse a grid whose samples would take more than this (default 4 GiB).
        truncation: if given, stored values are clamped to [-truncation, truncation] as Isaac
            Sim does (the paper uses 0.1 for normalised objects); default: no truncation.
        device: where the grid lives; queries on another device use a cached copy there.

    Attributes:
        values: (nx, ny, nz) float32 samples, ``values[i, j, k] = sdf(lo + (i, j, k) * spacing)``.
        lo, hi, spacing: (3,) float64 tensors: the grid box's corners and the sample spacing.
        bounds: the grid box (lo, hi) as float32 (3,) tensors; it holds the interpolated surface.
    """

    def __init__(
        self,
        sdf,
        resolution=128,
        bounds=None,
        padding: float = 0.05,
        chunk: int = 1 << 18,
        max_bytes: int = DEFAULT_MAX_BYTES,
        truncation: float | None = None,
        device=None,
        progress: bool | None = None,
    ):
        check_sdf(sdf)
        self.shape = resolution_per_axis(resolution)
        _check_memory(self.shape, max_bytes)
        self.lo, self.hi = _padded_box(sdf.bounds if bounds is None else bounds, padding)
        self.spacing = (self.hi - self.lo) / (torch.tensor(self.shape, dtype=torch.float64) - 1)
        self.padding = float(padding)
        self.truncation = None if truncation is None else positive_float(truncation, "truncation")
        chunk = int(chunk)
        if chunk < 1:
            raise InputError(f"chunk must be a positive number of grid points per call, got {chunk}")
        device = torch.device("cpu") if device is None else torch.device(device)
        self.values = _sample_grid(sdf, self.lo, self.spacing, self.shape, chunk, device, progress)
        if self.truncation is not None:
            self.values.clamp_(-self.truncation, self.truncation)
        self.bounds = (self.lo.float(), self.hi.float())
        self._copies: dict[torch.device, torch.Tensor] = {}

    # -- on disk ---------------------------------------------------------------------------

    def state(self) -> dict:
        """The grid as tensors and numbers only: ``torch.save`` it, read it back with ``torch.load(path,
        weights_only=True)`` (no pickled object) and :meth:`from_state`."""
        return {"values": self.values, "lo": self.lo, "hi": self.hi, "padding": self.padding, "truncation": self.truncation}

    @classmethod
    def from_state(cls, state: dict) -> VoxelSDF:
        """The VoxelSDF whose :meth:`state` is ``state``; no SDF is sampled again."""
        values = torch.as_tensor(state["values"], dtype=torch.float32)
        if values.ndim != 3 or min(values.shape) < 2:
            raise InputError(f"a VoxelSDF state holds (nx, ny, nz) samples, each >= 2; got shape {tuple(values.shape)}")
        grid = cls.__new__(cls)
        grid.values, grid.shape = values, tuple(values.shape)
        grid.lo, grid.hi = (torch.as_tensor(state[k], dtype=torch.float64) for k in ("lo", "hi"))
        grid.spacing = (grid.hi - grid.lo) / (torch.tensor(grid.shape, dtype=torch.float64) - 1)
        grid.padding, grid.truncation = float(state["padding"]), state["truncation"]
        grid.bounds = (grid.lo.float(), grid.hi.float())
        grid._copies = {}
        return grid

    # -- the SDF protocol -------------------------------------------------------------------

    def __call__(self, points) -> torch.Tensor:
        """Distances at ``points`` (N, 3) -> (N,), in the points' dtype and device."""
        return self._evaluate(as_points(points), want_grad=False)[0]

    def value_and_grad(self, points) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) -> distances (N,) and exact gradients of the interpolant (N, 3)."""
        return self._evaluate(as_points(points), want_grad=True)

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the samples (nx * ny * nz * 4), not counting copies on other devices."""
        return self.values.numel() * self.values.element_size()

    @property
    def resolution(self) -> tuple[int, int, int]:
        return self.shape

    def __repr__(self):
        return f"VoxelSDF(resolution={self.shape}, memory={self.memory_bytes / 2**20:.1f} MiB)"

    # -- interpolation ----------------------------------------------------------------------

    def _evaluate(self, points: torch.Tensor, want_grad: bool):
        """Value (N,) and, if ``want_grad``, gradient (N, 3) at points (N, 3); see the module doc."""
        lo = self.lo.to(points)
        hi = self.hi.to(points)
        inside_box = torch.clamp(points, lo, hi)
        outside = points - inside_box  # (N, 3), zero on every axis where the point is in the box
        gap = outside.norm(dim=-1)  # (N,) distance to the grid box
        index, frac = self._cell(inside_box)
        corners = self._corner_values(index, points)  # (N, 2, 2, 2)
        value = _trilinear(corners, frac) + gap
        if not want_grad:
            return value, None
        grad = _trilinear_grad(corners, frac) / self.spacing.to(points)
        # Along an axis where the point was clamped the interpolant does not move with it.
        grad = torch.where(outside != 0, torch.zeros_like(grad), grad)
        grad = grad + outside / gap.clamp_min(torch.finfo(points.dtype).tiny).unsqueeze(-1)
        return value, grad

    def _cell(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell index (N, 3) int64 and position inside it (N, 3) in [0, 1] of in-box points (N, 3).

        The cell is floor((p - lo) / spacing), kept at most n - 2 so the far face belongs to
        the last cell.
        """
        u = (points - self.lo.to(points)) / self.spacing.to(points)
        top = torch.tensor(self.shape, device=points.device) - 2
        index = torch.minimum(u.floor().long().clamp_min(0), top)
        return index, (u - index.to(u.dtype)).clamp(0, 1)

    def _corner_values(self, index: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Samples at the 8 corners of each cell: index (N, 3) -> (N, 2, 2, 2) in the points' dtype."""
        values = self._values_on(points.device)
        ny, nz = self.shape[1], self.shape[2]
        offsets = torch.tensor(
            [[di * ny * nz + dj * nz + dk for dk in (0, 1)] for di in (0, 1) for dj in (0, 1)],
            device=points.device,
        ).reshape(1, 2, 2, 2)
        base = index[:, 0] * (ny * nz) + index[:, 1] * nz + index[:, 2]
        flat = base.reshape(-1, 1, 1, 1) + offsets
        return values.reshape(-1)[flat].to(points.dtype)

    def _values_on(self, device: torch.device) -> torch.Tensor:
        if device == self.values.device:
            return self.values
        if device not in self._copies:  # one copy per device, not one per query
            self._copies[device] = self.values.to(device)
        return self._copies[device]


def _trilinear(c: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Trilinear blend of corner values c (N, 2, 2, 2) at fractions t (N, 3) -> (N,)."""
    cx = c[:, 0] + t[:, 0, None, None] * (c[:, 1] - c[:, 0])  # (N, 2, 2) over (y, z)
    cy = cx[:, 0] + t[:, 1, None] * (cx[:, 1] - cx[:, 0])  # (N, 2) over z
    return cy[:, 0] + t[:, 2] * (cy[:, 1] - cy[:, 0])


def _trilinear_grad(c: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Gradient of the blend w.r.t. the fractions t: c (N, 2, 2, 2), t (N, 3) -> (N, 3)."""
    tx, ty, tz = t[:, 0, None, None], t[:, 1, None], t[:, 2]
    # d/dtx: the x-differences blended over y and z, and so on for each axis.
    dx = c[:, 1] - c[:, 0]  # (N, 2, 2)
    dx = dx[:, 0] + ty * (dx[:, 1] - dx[:, 0])
    gx = dx[:, 0] + tz * (dx[:, 1] - dx[:, 0])
    cx = c[:, 0] + tx * (c[:, 1] - c[:, 0])  # (N, 2, 2) after blending x
    dy = cx[:, 1] - cx[:, 0]  # (N, 2)
    gy = dy[:, 0] + tz * (dy[:, 1] - dy[:, 0])
    cy = cx[:, 0] + ty * (cx[:, 1] - cx[:, 0])  # (N, 2)
    gz = cy[:, 1] - cy[:, 0]
    return torch.stack([gx, gy, gz], dim=-1)


def _sample_grid(sdf, lo, spacing, shape, chunk: int, device, progress: bool | None = None) -> torch.Tensor:
    """Evaluate ``sdf`` at every grid point, ``chunk`` points per call: -> (nx, ny, nz) float32.

    A fine grid of a NeuralSDF is long work on a CPU: ``progress`` (default: :func:`zoo.progress.shown`)
    shows a bar over the chunks."""
    from .progress import task_bar, wanted

    nx, ny, nz = shape
    values = torch.empty(nx * ny * nz, dtype=torch.float32, device=device)
    lo32, h32 = lo.to(device, torch.float32), spacing.to(device, torch.float32)
    starts = range(0, values.numel(), chunk)
    with torch.no_grad(), task_bar(wanted(progress) and len(starts) > 1, f"VoxelSDF {nx}x{ny}x{nz} grid", len(starts)) as bar:
        for start in starts:  # a loop over chunks, not points
            flat = torch.arange(start, min(start + chunk, values.numel()), device=device)
            ijk = torch.stack([flat // (ny * nz), (flat // nz) % ny, flat % nz], dim=-1)
            d = sdf(lo32 + ijk.to(torch.float32) * h32)
            values[start : start + len(flat)] = torch.as_tensor(d).reshape(-1).to(device, torch.float32)
            bar.advance()
    if not bool(torch.isfinite(values).all()):
        raise InputError("the SDF returned NaN or Inf on its own grid; check its bounds and its evaluation")
    return values.reshape(shape)


def resolution_per_axis(resolution) -> tuple[int, int, int]:
    """One int or three ints, each >= 2, as samples per axis (nx, ny, nz); else InputError."""
    values = [resolution] * 3 if isinstance(resolution, numbers.Integral) else resolution
    try:
        values = list(values)
    except TypeError:
        values = []
    if len(values) != 3 or not all(_is_int(v) and int(v) >= 2 for v in values):
        raise InputError(
            f"resolution must be an int >= 2 or three such ints (samples per axis), got {resolution!r}"
        )
    return tuple(int(v) for v in values)


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _check_memory(shape, max_bytes: int) -> None:
    need = math.prod(shape) * _BYTES_PER_SAMPLE
    if need > max_bytes:
        raise InputError(
            f"a VoxelSDF of resolution {shape} needs {need / GiB:.2f} GiB, more than the limit of "
            f"{max_bytes / GiB:.2f} GiB; lower the resolution or raise max_bytes"
        )


def _padded_box(bounds, padding: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi) as float64 (3,) tensors, each side grown by padding * longest side."""
    try:
        lo, hi = (torch.as_tensor(b, dtype=torch.float64).cpu().reshape(-1) for b in bounds)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"bounds must be two corners of 3 numbers each, got {bounds!r}") from exc
    if lo.shape != (3,) or hi.shape != (3,) or not bool(torch.isfinite(lo).all() & torch.isfinite(hi).all()):
        raise InputError(f"bounds must be two corners of 3 finite numbers each, got {bounds!r}")
    if not bool((hi > lo).all()):
        raise InputError(f"bounds must have lo < hi on every axis, got lo={lo.tolist()} hi={hi.tolist()}")
    padding = float(padding)
    if not (padding >= 0 and math.isfinite(padding)):
        raise InputError(f"padding must be a finite fraction >= 0 of the box's longest side, got {padding!r}")
    pad = padding * float((hi - lo).max())
    return lo - pad, hi + pad
