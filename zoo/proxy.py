"""A narrow-band baked proxy of an SDF: cheap values and gradients near its surface, safe bounds elsewhere.

A NeuralSDF costs 5-11 us a point; a simulation step asks it at every face near the surface (culling,
screening, the search), most of which end far from any contact. :class:`ProxySDF` samples the SDF once on
a regular grid of spacing ``h``, but only in *bricks* (8^3 cells, 9^3 nodes: border nodes are stored in
both bricks, so a cell never straddles two) that hold cells within ``band`` of the surface, and reads it
back by trilinear interpolation, all points at once (torch, no Python loop over points or bricks).

Which cells are baked (:func:`bake_proxy`). A coarse-to-fine pass with a Lipschitz-safe test: f at the
centre of each brick of the SDF's bounds (grown by the band); a block of half-diagonal r whose centre
value has |f| > L r + ``band`` holds no point within the band (f is L-Lipschitz, L the bound
:func:`zoo.coherence.motion_lipschitz` gives: 2 for a NeuralSDF), and is dropped; the others are split
into 8 and tested again, down to single cells. The kept cells' nodes are then evaluated (one query per
distinct node). A dropped block leaves, over all its points, the lower bound f(centre) - L r, which is
above ``band`` where f(centre) > 0 (outside) and far below -``band`` where it is < 0 (deep inside).

Reading (:meth:`ProxySDF.read`), for points (N, 3) in the SDF's frame:

* in a baked cell: the trilinear interpolant of the nodes and its exact gradient (status 0, ``IN_BAND``);
* in a dropped block: a lower bound as the value, f(c) - L |p - c| from the centre c of the point's brick
  (and at least ``band`` where the dropped block was outside), with the coarse gradient (central differences
  of the brick-centre values) for a search to follow; status 1 (``ABOVE``: the bound is above ``band``,
  no contact within the band there) or -1 (``UNKNOWN``: deep inside, the proxy knows nothing but that);
* outside the baked region (the SDF's bounds grown by the band and a cell): ``band`` plus the distance to
  the region, pointing away from it (status ``ABOVE``; the surface lies in the bounds, as collide assumes).

Error. The proxy's error against the SDF is measured on held-out points (uniform in random baked cells,
none of them a node) and kept with it (``proxy.error``: median, p99, max, in the SDF's units); the bound
culling uses, ``proxy.error_bound``, is ``ERROR_SAFETY`` times the maximum measured. Where the proxy is
in band, f >= proxy - error_bound, so a face whose proxy minimum exceeds ``margin + error_bound`` has no
contact within ``margin``; :class:`zoo.CoherentCollider` (``proxy=``) culls and searches on the proxy at
that margin and asks the SDF itself only at the faces that survive.

Default spacing (:func:`default_spacing`): the smaller of the margin and the bounds' longest side over
``SPACING_DIVISIONS`` = 256: the mugs' hoi4d_mug_0001 (a 12.6 cm box, margin 1 mm) 0.49 mm; the M16 bolt
(a 4.1 cm box, margin 0.1 mm) 0.1 mm, what its 2 mm-pitch thread needs. The band defaults to the margin
plus ``BAND_CELLS`` = 2 cells (:func:`default_band`), so that a contact at the margin, and a penetration of
two cells, are read in band.

Baked proxies of a model's shapes are cached on disk (:func:`cached_proxy`): keyed by the model's
``sdf.safetensors`` sha256, the shape's name, codes and similarity, the settings and ``PROXY_VERSION``;
one folder per key under ``zoo.hub.zoo_cache_dir()/proxies`` holding ``proxy.safetensors`` (written
atomically) and its ``SHA256SUMS``, verified on load; a corrupt or incomplete one is refused
(:class:`zoo.errors.ChecksumError` or :class:`zoo.errors.DataError`) and baked again.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from pathlib import Path

import numpy as np
import torch

from .errors import ChecksumError, DataError, InputError, ZooError
from .sdf import check_sdf
from .validation import as_points, non_negative_float, positive_float

PROXY_VERSION = 1  # bump when the bake or the file changes: old cache entries are then not found
BRICK = 8  # cells per brick side
NODES = BRICK + 1  # nodes per brick side (border nodes stored in both neighbours)
SPACING_DIVISIONS = 256  # default spacing: at most the bounds' longest side over this
BAND_CELLS = 2  # default band: the margin plus this many cells
ERROR_SAMPLES = 16384  # held-out points the error is measured on
ERROR_SAFETY = 2.0  # error_bound = this times the largest error measured
CHUNK = 1 << 15  # points per SDF call while baking
IN_BAND, ABOVE, UNKNOWN = 0, 1, -1  # read()'s status, and a cell's in ``status``
COARSE = 2  # the cells of the row standing for every brick not baked
PROXY_FILE = "proxy.safetensors"

_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64)  # (8, 3)
_NODE_OFFSETS = (_CORNERS * torch.tensor([NODES * NODES, NODES, 1])).sum(-1)  # (8,) into a brick's flat nodes
_NODE_OFFSETS_NP = _NODE_OFFSETS.numpy()
_CELL_STRIDES = np.array([BRICK * BRICK, BRICK, 1])
_NODE_STRIDES = np.array([NODES * NODES, NODES, 1])


def default_spacing(bounds, margin: float) -> float:
    """The default grid spacing (m) for an SDF with ``bounds`` (two (3,) corners) collided at ``margin``: the
    smaller of the margin (when > 0) and the bounds' longest side over ``SPACING_DIVISIONS``."""
    lo, hi = (torch.as_tensor(b, dtype=torch.float64).reshape(3) for b in bounds)
    side = float((hi - lo).max()) / SPACING_DIVISIONS
    return min(side, margin) if margin > 0 else side


def default_band(margin: float, spacing: float) -> float:
    """The default half-width of the baked band (m): the margin plus ``BAND_CELLS`` cells."""
    return margin + BAND_CELLS * spacing


class ProxySDF:
    """A narrow-band, brick-sparse, trilinear copy of an SDF (see the module docstring); an SDF itself.

    Attributes:
        lo: (3,) float64, the baked region's lower corner (cell (0, 0, 0) starts there); hi: its upper corner.
        spacing: h, the grid spacing (m). band: the half-width of the baked band (m).
        lipschitz: the bound L the bake's tests assumed of the SDF (and that a collider carries bounds with).
        n_bricks: (3,) int64 bricks per axis of the region; ``n_bricks * BRICK`` cells.
        brick_of: (nbx * nby * nbz,) int64, each brick's row (x-major); B (the row after the B baked ones) where
            not baked.
        nodes: ((B + 1) * 9^3,) float32, the rows' node values, row-major then x, y, z (0 where not baked).
        status: ((B + 1) * 8^3,) int8 per cell of each row: ``IN_BAND`` (its 8 nodes baked), ``ABOVE`` (a block
            holding it was dropped with f above the band), ``UNKNOWN`` (dropped below it), ``COARSE`` (row B).
        coarse_value: (nbx * nby * nbz,) float32, f at each brick's centre.
        coarse_grad: (nbx * nby * nbz, 3) float32, central differences of f at the brick centres.
        bounds: the source SDF's bounds (two (3,) float32 tensors).
        error: {"median", "p99", "max", "samples"} the error against the source on held-out points in band (m).
        error_bound: ``ERROR_SAFETY`` times the largest error measured (m).
        settings: {"spacing", "band", "lipschitz", "brick", "version"}.
        bake_seconds: how long the bake took (0 when loaded).
    """

    def __init__(self, *, lo, spacing, band, lipschitz, n_bricks, brick_of, nodes, status, coarse_value, coarse_grad,
                 bounds, error=None, error_bound=0.0, bake_seconds=0.0):
        self.lo = torch.as_tensor(lo, dtype=torch.float64).reshape(3)
        self.spacing, self.band, self.lipschitz = float(spacing), float(band), float(lipschitz)
        self.n_bricks = torch.as_tensor(n_bricks, dtype=torch.int64).reshape(3)
        self.brick_of, self.nodes, self.status = brick_of, nodes, status
        self.coarse_value, self.coarse_grad = coarse_value, coarse_grad
        self.bounds = tuple(torch.as_tensor(b, dtype=torch.float32).reshape(3) for b in bounds)
        self.error = dict(error or {})
        self.error_bound = float(error_bound)
        self.bake_seconds = float(bake_seconds)
        self.hi = self.lo + self.n_bricks.double() * BRICK * self.spacing
        nb = self.n_bricks.numpy()
        n_rows = nodes.numel() // NODES**3
        if (brick_of.numel() != nb.prod() or status.numel() != n_rows * BRICK**3 or coarse_value.numel() != nb.prod()
                or coarse_grad.shape != (nb.prod(), 3) or int(brick_of.min()) < 0 or int(brick_of.max()) >= n_rows):
            raise DataError("a proxy's arrays do not fit together; delete its file (it is rebuilt on the next use)")
        # numpy views for read(): numpy's per-call cost is a third of torch's on a few points
        self._lo_np, self._hi_np = self.lo.numpy(), self.hi.numpy()
        self._last_cell_np = nb * BRICK - 1
        self._brick_strides_np = np.array([nb[1] * nb[2], nb[2], 1])
        self._brick_of_np, self._nodes_np, self._status_np = brick_of.numpy(), nodes.numpy(), status.numpy()
        self._coarse_value_np, self._coarse_grad_np = coarse_value.numpy(), coarse_grad.numpy()

    @property
    def settings(self) -> dict:
        return {"spacing": self.spacing, "band": self.band, "lipschitz": self.lipschitz, "brick": BRICK, "version": PROXY_VERSION}

    @property
    def n_baked(self) -> int:
        """Bricks baked."""
        return int(self.nodes.numel() // NODES**3) - 1

    @property
    def memory_bytes(self) -> int:
        """Bytes the proxy holds (nodes, masks, bounds, the brick index and the coarse grid)."""
        return sum(t.numel() * t.element_size() for t in (self.brick_of, self.nodes, self.status, self.coarse_value,
                                                          self.coarse_grad))

    def __repr__(self):
        return (f"ProxySDF(spacing={self.spacing:.3g}, band={self.band:.3g}, bricks={self.n_baked}, "
                f"memory={self.memory_bytes / 2**20:.1f} MiB, error_bound={self.error_bound:.3g})")

    # -- the SDF protocol ------------------------------------------------------------------------

    def __call__(self, points) -> torch.Tensor:
        """Values (N,) at ``points`` (N, 3): the interpolant in band, a lower bound of f elsewhere."""
        return self.read(as_points(points))[0]

    def value_and_grad(self, points) -> tuple[torch.Tensor, torch.Tensor]:
        """Values (N,) and gradients (N, 3) at ``points`` (N, 3) (:meth:`read` without the status)."""
        values, grads, _ = self.read(as_points(points))
        return values, grads

    def read(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Values (N,), gradients (N, 3) and status (N,) int8 at ``points`` (N, 3), in the points' dtype and device.

        Status ``IN_BAND`` (0): the trilinear interpolant and its gradient, within ``error_bound`` of f;
        ``ABOVE`` (1): a lower bound of f that is at least ``band``; ``UNKNOWN`` (-1): a lower bound of f below it
        (deep inside); the gradient out of band is the coarse one (see the module docstring). numpy on the CPU:
        a call costs a few tens of microseconds for a few points, a few times less than the same in torch."""
        p = points.detach().cpu().numpy()
        values, grads, status = self._read(p)
        return (torch.from_numpy(values).to(points.device), torch.from_numpy(grads).to(points.device),
                torch.from_numpy(status).to(points.device))

    def _read(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`read` on a numpy array (N, 3): values (N,), gradients (N, 3), status (N,) int8."""
        dtype = p.dtype
        u = (p - self._lo_np.astype(dtype)) * dtype.type(1 / self.spacing)
        cell = np.floor(u).astype(np.int64)
        all_inside = bool(cell.min() >= 0) and bool((cell <= self._last_cell_np).all())  # one test for the usual case
        if all_inside:
            inside = np.ones(p.shape[0], dtype=bool)
        else:
            inside = ((cell >= 0) & (cell <= self._last_cell_np)).all(axis=-1)
            np.clip(cell, 0, self._last_cell_np, out=cell)
        f = u - cell.astype(dtype)
        if not all_inside:
            np.clip(f, 0, 1, out=f)
        brick_flat = (cell >> 3) @ self._brick_strides_np
        row = self._brick_of_np[brick_flat]
        local = cell & (BRICK - 1)
        status = self._status_np[row * BRICK**3 + local @ _CELL_STRIDES]
        c = self._nodes_np[(row * NODES**3 + local @ _NODE_STRIDES)[:, None] + _NODE_OFFSETS_NP].astype(dtype, copy=False)
        c = c.reshape(-1, 2, 2, 2)
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        gx, gy, gz = 1 - fx, 1 - fy, 1 - fz
        cz = c[..., 0] * gz[:, None, None] + c[..., 1] * fz[:, None, None]  # (N, 2, 2) over x, y
        dz = c[..., 1] - c[..., 0]
        cy = cz[..., 0] * gy[:, None] + cz[..., 1] * fy[:, None]  # (N, 2) over x
        dy = cz[..., 1] - cz[..., 0]
        dzy = dz[..., 0] * gy[:, None] + dz[..., 1] * fy[:, None]
        values = cy[:, 0] * gx + cy[:, 1] * fx
        grads = np.stack([cy[:, 1] - cy[:, 0], dy[:, 0] * gx + dy[:, 1] * fx, dzy[:, 0] * gx + dzy[:, 1] * fx], axis=-1)
        grads *= dtype.type(1 / self.spacing)
        if all_inside and not status.any():
            return values, grads, status
        out = (status != IN_BAND) | ~inside
        coarse = self._coarse_value_np[brick_flat].astype(dtype)
        # the brick centre's bound f(c) - L |p - c|, valid at every point of the brick, and at least the band in an
        # ABOVE cell (a block holding it was dropped with f above the band)
        centre = (self._lo_np + ((cell >> 3) * BRICK + BRICK / 2) * self.spacing).astype(dtype)
        coarse = coarse - dtype.type(self.lipschitz) * np.linalg.norm(p - centre, axis=-1)
        values = np.where(out, np.where(status == ABOVE, np.maximum(coarse, dtype.type(self.band)), coarse), values)
        grads = np.where(out[:, None], self._coarse_grad_np[brick_flat].astype(dtype), grads)
        if not all_inside:  # outside the region: band plus the distance to it, pointing away
            clamped = np.clip(p, self._lo_np.astype(dtype), self._hi_np.astype(dtype))
            away = p - clamped
            gap = np.linalg.norm(away, axis=-1)
            values = np.where(inside, values, self.band + gap)
            grads = np.where(inside[:, None], grads, away / np.maximum(gap, np.finfo(dtype).tiny)[:, None])
            coarse = np.where(inside, coarse, np.inf)
        status = np.where(out, np.where((status == ABOVE) | (coarse >= self.band), ABOVE, UNKNOWN), IN_BAND).astype(np.int8)
        return values.astype(dtype, copy=False), grads.astype(dtype, copy=False), status

    # -- on disk ---------------------------------------------------------------------------------

    def state(self) -> tuple[dict, dict]:
        """(tensors, metadata strings) that :meth:`from_state` reads back."""
        tensors = {"lo": self.lo, "n_bricks": self.n_bricks, "brick_of": self.brick_of, "nodes": self.nodes,
                   "status": self.status, "coarse_value": self.coarse_value,
                   "coarse_grad": self.coarse_grad, "bounds_lo": self.bounds[0], "bounds_hi": self.bounds[1]}
        meta = {"settings": json.dumps(self.settings, sort_keys=True), "error": json.dumps(self.error, sort_keys=True),
                "error_bound": repr(self.error_bound), "bake_seconds": repr(self.bake_seconds)}
        return tensors, meta

    @classmethod
    def from_state(cls, tensors: dict, meta: dict) -> ProxySDF:
        try:
            settings = json.loads(meta["settings"])
            return cls(lo=tensors["lo"], spacing=settings["spacing"], band=settings["band"], lipschitz=settings["lipschitz"],
                       n_bricks=tensors["n_bricks"], brick_of=tensors["brick_of"], nodes=tensors["nodes"],
                       status=tensors["status"], coarse_value=tensors["coarse_value"],
                       coarse_grad=tensors["coarse_grad"], bounds=(tensors["bounds_lo"], tensors["bounds_hi"]),
                       error=json.loads(meta["error"]), error_bound=float(meta["error_bound"]),
                       bake_seconds=float(meta.get("bake_seconds", 0.0)))
        except (KeyError, ValueError, TypeError) as exc:
            raise DataError(f"a proxy file lacks or garbles {exc}; delete it (it is rebuilt on the next use)") from exc


# -- baking ---------------------------------------------------------------------------------------


def bake_proxy(sdf, margin: float = 1e-3, spacing: float | None = None, band: float | None = None,
               lipschitz: float | None = None, progress: bool | None = None, seed: int = 0) -> ProxySDF:
    """Bake the narrow-band proxy of ``sdf`` (any SDF) for contacts at ``margin`` (see the module docstring).

    Args:
        sdf: the SDF; its ``bounds`` must hold its surface.
        margin: m, the contact margin the proxy serves; sets the defaults of ``spacing`` and ``band``.
        spacing: m, the grid spacing (default :func:`default_spacing`).
        band: m, the half-width of the band baked (default :func:`default_band`); larger than ``margin``.
        lipschitz: the bound of |grad f| the tests assume (default :func:`zoo.coherence.motion_lipschitz`).
        progress: show a bar (default: :func:`zoo.progress.shown`).
        seed: of the held-out points the error is measured on.
    """
    import time

    from .coherence import motion_lipschitz
    from .progress import progress_bar, wanted

    check_sdf(sdf)
    margin = non_negative_float(margin, "margin")
    bounds = tuple(torch.as_tensor(b, dtype=torch.float64).cpu().reshape(3) for b in sdf.bounds)
    h = default_spacing(bounds, margin) if spacing is None else positive_float(spacing, "spacing")
    band = default_band(margin, h) if band is None else positive_float(band, "band")
    if band <= margin:
        raise InputError(f"band ({band}) must exceed the margin ({margin}): contacts within the margin must be read in band")
    lip = motion_lipschitz(sdf) if lipschitz is None else positive_float(lipschitz, "lipschitz")
    started = time.perf_counter()
    pad = band + h
    lo = bounds[0] - pad
    n_bricks = torch.ceil((bounds[1] + pad - lo) / (BRICK * h)).long().clamp_min(1)
    nb = [int(n) for n in n_bricks]
    with progress_bar(wanted(progress)) as bar:
        task = bar.add_task(f"baking the proxy of {getattr(sdf, 'name', type(sdf).__name__)}", total=math.prod(nb))

        def evaluate(cells: torch.Tensor, size: float) -> torch.Tensor:
            """f (N,) float64 at the centres of the blocks of ``size`` cells whose first cells are ``cells`` (N, 3)."""
            return _evaluate(sdf, lo + (cells.double() + size / 2) * h, bar, task)

        grid = torch.stack(torch.meshgrid(*[torch.arange(n) for n in nb], indexing="ij"), dim=-1).reshape(-1, 3)
        f0 = evaluate(grid * BRICK, BRICK)
        if not bool(torch.isfinite(f0).all()):
            raise InputError("the SDF returned NaN or Inf inside its own bounds; check its evaluation")
        radius = math.sqrt(3) / 2 * BRICK * h
        coarse_value = f0.float()
        coarse_grad = torch.stack(torch.gradient(f0.reshape(nb), spacing=BRICK * h), dim=-1).reshape(-1, 3).float()
        keep = f0.abs() <= lip * radius + band
        bricks = grid[keep]
        n_rows = bricks.shape[0]
        brick_of = torch.full((grid.shape[0],), n_rows, dtype=torch.int64)  # row n_rows: every brick not baked
        brick_of[keep] = torch.arange(n_rows)
        strides = torch.tensor([nb[1] * nb[2], nb[2], 1])
        status = torch.full(((n_rows + 1) * BRICK**3,), UNKNOWN, dtype=torch.int8)
        status[n_rows * BRICK**3:] = COARSE
        origins, size = bricks * BRICK, BRICK
        while size > 1:  # split the kept blocks into 8, test their centres; drop the far ones
            size //= 2
            bar.update(task, total=bar.tasks[task].total + 8 * origins.shape[0])
            children = (origins.unsqueeze(1) + _CORNERS * size).reshape(-1, 3)
            f = evaluate(children, size)
            r = math.sqrt(3) / 2 * size * h
            near = f.abs() <= lip * r + band
            _set_status(status, brick_of, strides, children[~near], size, f[~near] > 0)
            origins = children[near]
        cells = origins  # (K, 3) the kept cells
        node_keys, inverse = torch.unique(_node_key(cells.unsqueeze(1) + _CORNERS, nb), return_inverse=True)  # (K, 8)
        bar.update(task, total=bar.tasks[task].total + node_keys.shape[0])
        node_values = _evaluate_nodes(sdf, node_keys, nb, lo, h, bar, task)
        row = brick_of[((cells >> 3) * strides).sum(-1)]  # (K,)
        local = cells & (BRICK - 1)
        nodes = torch.zeros((n_rows + 1) * NODES**3, dtype=torch.float32)
        at = (row * NODES**3 + (local * torch.from_numpy(_NODE_STRIDES)).sum(-1)).unsqueeze(-1) + _NODE_OFFSETS
        nodes[at.reshape(-1)] = node_values[inverse.reshape(-1)].float()
        status[row * BRICK**3 + (local * torch.from_numpy(_CELL_STRIDES)).sum(-1)] = IN_BAND
    proxy = ProxySDF(lo=lo, spacing=h, band=band, lipschitz=lip, n_bricks=n_bricks, brick_of=brick_of, nodes=nodes,
                     status=status, coarse_value=coarse_value, coarse_grad=coarse_grad, bounds=bounds)
    proxy.error = measure_error(proxy, sdf, seed=seed)
    proxy.error_bound = ERROR_SAFETY * proxy.error["max"]
    proxy.bake_seconds = time.perf_counter() - started
    return proxy


def _node_key(nodes: torch.Tensor, nb: list[int]) -> torch.Tensor:
    """Flat keys (...,) of grid nodes (..., 3) (the region has ``nb * BRICK + 1`` nodes per axis)."""
    ny, nz = nb[1] * BRICK + 1, nb[2] * BRICK + 1
    return (nodes[..., 0] * ny + nodes[..., 1]) * nz + nodes[..., 2]


def _evaluate_nodes(sdf, keys: torch.Tensor, nb: list[int], lo: torch.Tensor, h: float, bar, task) -> torch.Tensor:
    """f (N,) float64 at the grid nodes with flat keys ``keys`` (N,)."""
    ny, nz = nb[1] * BRICK + 1, nb[2] * BRICK + 1
    ijk = torch.stack([keys // (ny * nz), (keys // nz) % ny, keys % nz], dim=-1)
    out = _evaluate(sdf, lo + ijk.double() * h, bar, task)
    if not bool(torch.isfinite(out).all()):
        raise InputError("the SDF returned NaN or Inf near its surface; check its evaluation")
    return out


def _evaluate(sdf, points: torch.Tensor, bar, task) -> torch.Tensor:
    """f (N,) float64 at ``points`` (N, 3), asked in float32 ``CHUNK`` points a call, advancing the bar's task."""
    out = torch.empty(points.shape[0], dtype=torch.float64)
    with torch.no_grad():
        for start in range(0, points.shape[0], CHUNK):  # a loop over chunks, not points
            chunk = points[start:start + CHUNK]
            out[start:start + CHUNK] = torch.as_tensor(sdf(chunk.float())).reshape(-1).double()
            bar.advance(task, chunk.shape[0])
    return out


def _set_status(status: torch.Tensor, brick_of: torch.Tensor, strides: torch.Tensor, blocks: torch.Tensor, size: int,
                above: torch.Tensor) -> None:
    """Mark every cell of the dropped blocks (D, 3) of ``size`` cells a side ``ABOVE`` where ``above`` (D,) bool (f at
    the block's centre was positive: f exceeds the band on all of it), else ``UNKNOWN``."""
    if not blocks.shape[0]:
        return
    offsets = torch.stack(torch.meshgrid(*[torch.arange(size)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    cells = (blocks.unsqueeze(1) + offsets).reshape(-1, 3)  # (D * size^3, 3)
    row = brick_of[((cells >> 3) * strides).sum(-1)]
    index = row * BRICK**3 + ((cells & (BRICK - 1)) * torch.from_numpy(_CELL_STRIDES)).sum(-1)
    status[index] = torch.where(above, ABOVE, UNKNOWN).to(torch.int8).repeat_interleave(size**3)


def measure_error(proxy: ProxySDF, sdf, samples: int = ERROR_SAMPLES, seed: int = 0) -> dict:
    """|proxy - f| at ``samples`` held-out points (uniform in random baked cells, none a node) where the proxy is in
    band: {"median", "p99", "max", "samples"} in the SDF's units (zeros when nothing is baked)."""
    cells = (proxy.status[:-BRICK**3] == IN_BAND).nonzero().squeeze(-1)
    if not cells.numel():
        return {"median": 0.0, "p99": 0.0, "max": 0.0, "samples": 0}
    g = torch.Generator().manual_seed(seed)
    pick = cells[torch.randint(cells.numel(), (samples,), generator=g)]
    brick, local = pick // BRICK**3, pick % BRICK**3
    brick_index = (proxy.brick_of < proxy.n_baked).nonzero().squeeze(-1)[brick]  # rows are in flat brick order
    nb = proxy.n_bricks
    b3 = torch.stack([brick_index // (nb[1] * nb[2]), (brick_index // nb[2]) % nb[1], brick_index % nb[2]], dim=-1)
    l3 = torch.stack([local // (BRICK * BRICK), (local // BRICK) % BRICK, local % BRICK], dim=-1)
    points = proxy.lo + ((b3 * BRICK + l3).double() + torch.rand(samples, 3, generator=g, dtype=torch.float64)) * proxy.spacing
    points = points.float()
    values, _, status = proxy.read(points)
    with torch.no_grad():
        truth = torch.as_tensor(sdf(points)).reshape(-1).to(values)
    err = (values - truth).abs()[status == IN_BAND].double()
    return {"median": float(err.median()), "p99": float(torch.quantile(err, 0.99)), "max": float(err.max()),
            "samples": int(err.numel())}


# -- the cache ------------------------------------------------------------------------------------


def proxy_key(sdf, settings: dict) -> str | None:
    """The cache key (hex sha256) of ``sdf``'s proxy with ``settings``, or None for an SDF that cannot be keyed (not a
    model's shape). It covers the model's ``sdf.safetensors`` sha256 (or, for a model without a package, its
    decoder's weights), the shape's name, codes, positions and similarity, the settings and ``PROXY_VERSION``."""
    from .neural import NeuralShape

    if not isinstance(sdf, NeuralShape):
        return None
    model = sdf.model
    if model is not None and getattr(model, "path", None) is not None:
        from .files import read_checksums

        try:
            weights = read_checksums(model.path)["sdf.safetensors"]
        except (ZooError, KeyError):
            weights = _tensors_digest(sdf.decoder.state_dict())
    else:
        weights = _tensors_digest(sdf.decoder.state_dict())
    sim = sdf.similarity
    key = {"weights": weights, "shape": sdf.name, "codes": _tensors_digest({"codes": sdf.codes, "positions": sdf.positions}),
           "similarity": [float(sim.scale), torch.as_tensor(sim.rotation).double().reshape(-1).tolist(),
                          torch.as_tensor(sim.translation).double().reshape(-1).tolist()],
           "settings": dict(settings, version=PROXY_VERSION, brick=BRICK, error_samples=ERROR_SAMPLES,
                            error_safety=ERROR_SAFETY)}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def _tensors_digest(tensors: dict) -> str:
    h = hashlib.sha256()
    for name in sorted(tensors):
        h.update(name.encode())
        h.update(tensors[name].detach().cpu().contiguous().float().numpy().tobytes())
    return h.hexdigest()


def save_proxy(proxy: ProxySDF, directory, key: str = "") -> Path:
    """Write ``proxy`` to ``directory``/``PROXY_FILE`` (atomically) with the folder's ``SHA256SUMS``; returns the folder."""
    from .files import write_checksums, write_safetensors

    directory = Path(directory)
    tensors, meta = proxy.state()
    write_safetensors(directory / PROXY_FILE, tensors, dict(meta, key=key))
    write_checksums(directory)
    return directory


def load_proxy(directory, key: str | None = None) -> ProxySDF:
    """The proxy saved in ``directory``, verified against its ``SHA256SUMS`` (:class:`ChecksumError` if it differs,
    :class:`DataError` if incomplete or unreadable) and, if ``key`` is given, against the key it was saved under."""
    from safetensors import safe_open

    from .files import verify_directory

    directory = Path(directory)
    verify_directory(directory)
    try:
        with safe_open(str(directory / PROXY_FILE), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except Exception as exc:  # safetensors raises its own errors on a garbled file
        raise DataError(f"{directory / PROXY_FILE} is unreadable ({exc}); delete it (it is rebuilt on the next use)") from exc
    if key is not None and meta.get("key") != key:
        raise DataError(f"{directory / PROXY_FILE} was saved for another SDF or settings (key {meta.get('key')!r}, "
                        f"expected {key!r}); delete it")
    return ProxySDF.from_state(tensors, meta)


def cached_proxy(sdf, margin: float = 1e-3, spacing: float | None = None, band: float | None = None,
                 lipschitz: float | None = None, cache: bool | str | Path = True, progress: bool | None = None,
                 rebake: bool = False) -> ProxySDF:
    """The proxy of ``sdf`` (as :func:`bake_proxy`'s arguments), from the cache when baked before.

    ``cache``: True uses ``zoo.hub.zoo_cache_dir() / "proxies"``, a path another folder, False none. Only a model's
    shapes are cached (:func:`proxy_key`); others are baked every time. A cached proxy that fails its checksum or
    cannot be read is refused with a warning and baked again. ``rebake``: bake it anew and replace the cached one."""
    from .coherence import motion_lipschitz
    from .hub import zoo_cache_dir

    check_sdf(sdf)
    margin = non_negative_float(margin, "margin")
    bounds = tuple(torch.as_tensor(b, dtype=torch.float64).cpu().reshape(3) for b in sdf.bounds)
    h = default_spacing(bounds, margin) if spacing is None else positive_float(spacing, "spacing")
    band = default_band(margin, h) if band is None else positive_float(band, "band")
    lip = motion_lipschitz(sdf) if lipschitz is None else positive_float(lipschitz, "lipschitz")
    key = proxy_key(sdf, {"spacing": h, "band": band, "lipschitz": lip}) if cache is not False else None
    folder = None
    if key is not None:
        root = zoo_cache_dir() / "proxies" if cache is True else Path(cache)
        folder = root / f"{getattr(sdf, 'name', 'sdf')}-{key[:24]}"
        if (folder / PROXY_FILE).exists() and not rebake:
            try:
                return load_proxy(folder, key)
            except (ChecksumError, DataError) as exc:
                warnings.warn(f"refused the cached proxy in {folder} ({exc}); baking it again", stacklevel=2)
    proxy = bake_proxy(sdf, margin, h, band, lip, progress=progress)
    if folder is not None:
        save_proxy(proxy, folder, key)
    return proxy
