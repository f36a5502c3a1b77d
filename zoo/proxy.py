"""A narrow-band baked proxy of an SDF: cheap values and gradients near its surface, safe bounds elsewhere.

A NeuralSDF costs 5-11 us a point; a simulation step asks it at every face near the surface (culling,
screening, the search), most of which end far from any contact. :class:`ProxySDF` samples the SDF once on
a regular grid of spacing ``h``, but only in *bricks* (8^3 cells, 9^3 nodes: border nodes are stored in
both bricks, so a cell never straddles two) that hold cells within ``band`` of the surface, and reads it
back by trilinear interpolation, all points at once (numpy, no Python loop over points or bricks).

Which cells are baked (:func:`bake_proxy`). A coarse-to-fine pass with a Lipschitz-safe test: f at the
centre of each brick of the SDF's bounds (grown by the band); a block of half-diagonal r whose centre
value has |f| > L r + ``band`` holds no point within the band (f is L-Lipschitz, L the bound
:func:`zoo.collider.motion_lipschitz` gives: 2 for a NeuralSDF), and is dropped; the others are split
into 8 and tested again, down to single cells. The kept cells' nodes are then evaluated (one query per
distinct node). A dropped block leaves, over all its points, the lower bound f(centre) - L r, which is
above ``band`` where f(centre) > 0 (outside) and far below -``band`` where it is < 0 (deep inside).

Lazy baking (``bake_proxy(lazy=True)``, the default of :func:`cached_proxy`). The same test, but only the
coarse part up front: the brick centres are reached coarse to fine too (blocks of 2^k bricks whose centre
passes the test are split, from one block over the whole region down to bricks), so that the bricks far
from the surface are not evaluated; their centres (and a brick's gradient's neighbours) are evaluated when
a read first lands there. A read whose points fall in bricks not made ready yet makes them ready first: their
coarse values, then the bake of those that may hold band cells, all bricks of the read in one batch, exactly
as :func:`bake_proxy` bakes them, so a lazy proxy answers as the eagerly baked one does. The error is
measured at creation on ``ERROR_BRICKS`` random bricks that may hold band cells, baked then.

Reading (:meth:`ProxySDF.read`, :meth:`ProxySDF.read_numpy`), for points (N, 3) in the SDF's frame:

* in a baked cell: the trilinear interpolant of the nodes and its exact gradient (status 0, ``IN_BAND``);
* in a dropped block: a lower bound as the value, f(c) - L |p - c| from the centre c of the point's brick
  (and at least ``band`` where the dropped block was outside), with the coarse gradient (central differences
  of the brick-centre values) for a search to follow; status 1 (``ABOVE``: the bound is above ``band``,
  no contact within the band there) or -1 (``UNKNOWN``: deep inside, the proxy knows nothing but that);
* outside the baked region (the SDF's bounds grown by the band and a cell): the larger of ``band`` plus the
  distance to the region (the surface lies in the bounds, as collide assumes) and the nearest brick's bound
  f(c) - L |p - c| (a box's corners can lie far from a round shape), pointing away from the region (status
  ``ABOVE``).

Error. The proxy's error against the SDF is measured on held-out points (uniform in random baked cells,
none of them a node) and kept with it (``proxy.error``: median, p99, max, in the SDF's units); the bound
culling uses, ``proxy.error_bound``, is ``ERROR_SAFETY`` times the maximum measured. Where the proxy is
in band, f >= proxy - error_bound, so a face whose proxy minimum exceeds ``margin + error_bound`` has no
contact within ``margin``; :class:`zoo.CoherentCollider` (``proxy=``) culls and searches on the proxy at
that margin and asks the SDF itself only at the faces that survive. A lazy proxy measures it in the bricks
of its sample only (``ERROR_BRICKS`` of them), not in every brick it bakes later.

Default spacing (:func:`default_spacing`): the smaller of the margin and the bounds' longest side over
``SPACING_DIVISIONS`` = 256: the mugs' hoi4d_mug_0001 (a 12.6 cm box, margin 1 mm) 0.49 mm; the M16 bolt
(a 4.1 cm box, margin 0.1 mm) 0.1 mm, what its 2 mm-pitch thread needs. The band defaults to the margin
plus ``BAND_CELLS`` = 2 cells (:func:`default_band`), so that a contact at the margin, and a penetration of
two cells, are read in band.

Baked proxies of a model's shapes are cached on disk (:func:`cached_proxy`): keyed by the model's
``sdf.safetensors`` sha256, the shape's name, codes and similarity, the settings (``lazy`` among them) and
``PROXY_VERSION``; one folder per key under ``zoo.hub.zoo_cache_dir()/proxies`` holding ``proxy.safetensors``
(written atomically) and its ``SHA256SUMS``, verified on load; a corrupt or incomplete one is refused
(:class:`zoo.errors.ChecksumError` or :class:`zoo.errors.DataError`) and baked again. A lazy proxy from the
cache writes what it baked since back there (:meth:`ProxySDF.flush`, and at the process's exit), and goes on
baking lazily when loaded again.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import math
import os
import time
import warnings
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .errors import ChecksumError, DataError, InputError, ZooError
from .sdf import check_sdf
from .validation import as_points, non_negative_float, positive_float

PROXY_VERSION = 2  # bump when the bake or the file changes: old cache entries are then not found (2: lazy bricks)
BRICK = 8  # cells per brick side
NODES = BRICK + 1  # nodes per brick side (border nodes stored in both neighbours)
SPACING_DIVISIONS = 256  # default spacing: at most the bounds' longest side over this
BAND_CELLS = 2  # default band: the margin plus this many cells
ERROR_SAMPLES = 16384  # held-out points the error is measured on
ERROR_BRICKS = 64  # a lazy proxy's error is measured in this many random bricks, baked at its creation
ERROR_SAFETY = 2.0  # error_bound = this times the largest error measured
CHUNK = 1 << 15  # points per SDF call while baking, at most
EVAL_MULTIPLE = 64  # every SDF call of a bake asks a multiple of this many points (the last padded): a network's
# float32 answer at a point moved in its last bits where its call's size was not a multiple of 4 (the matrix
# products' remainder rows), and a brick's values must not depend on what it was baked with (docs/proxy.md)
BAKE_BATCH = 4096  # bricks baked together by bake_proxy(lazy=False) (bounds its memory; nodes shared within one)
AHEAD_BATCH = 512  # bricks made ready together by ProxySDF.bake_all (a progress bar that moves)
IN_BAND, ABOVE, UNKNOWN = 0, 1, -1  # read()'s status, and a cell's in ``status``
COARSE = 2  # the cells of row 0, standing for every brick that holds no band cell
NOT_READY = -1  # ``brick_of`` of a lazy proxy's brick whose coarse values or bake are still to come
PROXY_FILE = "proxy.safetensors"

_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])  # (8, 3), corner 4i + 2j + k
_CELL_STRIDES = np.array([BRICK * BRICK, BRICK, 1])  # a cell's (3,) place in its brick -> its index there
_NODE_STRIDES = np.array([NODES * NODES, NODES, 1])  # a node's (3,) place in its brick -> its index there
_LOCAL_STRIDES = np.stack([_CELL_STRIDES, _NODE_STRIDES], axis=1)  # (3, 2): a cell's index, and its first node's
_CORNER_OFFSETS = (_CORNERS @ _NODE_STRIDES)[:, None]  # (8, 1): a cell's corner nodes from its first
_AROUND = np.array([[0, 0, 0], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])  # a brick, 6 neighbours
# every node and cell centre of a brick in half cells from its first node (nodes even, centres odd): (729 + 512, 3)
_BRICK_HALF_POINTS = np.concatenate([2 * np.indices((NODES,) * 3).reshape(3, -1).T,
                                     2 * np.indices((BRICK,) * 3).reshape(3, -1).T + 1])
_HALF_DIAGONAL = math.sqrt(3) / 2  # a cube's half-diagonal over its side


def default_spacing(bounds, margin: float) -> float:
    """The default grid spacing (m) for an SDF with ``bounds`` (two (3,) corners) collided at ``margin``: the
    smaller of the margin (when > 0) and the bounds' longest side over ``SPACING_DIVISIONS``."""
    lo, hi = (torch.as_tensor(b, dtype=torch.float64).reshape(3) for b in bounds)
    side = float((hi - lo).max()) / SPACING_DIVISIONS
    return min(side, margin) if margin > 0 else side


def default_band(margin: float, spacing: float) -> float:
    """The default half-width of the baked band (m): the margin plus ``BAND_CELLS`` cells."""
    return margin + BAND_CELLS * spacing


class _ReadConstants:
    """What a read needs in the points' dtype, cast once rather than at every call."""

    def __init__(self, proxy: ProxySDF, dtype: np.dtype):
        t = dtype.type
        self.lo, self.hi = proxy._lo_np.astype(dtype), proxy._hi_np.astype(dtype)
        self.inv_h, self.band, self.lipschitz = t(1 / proxy.spacing), t(proxy.band), t(proxy.lipschitz)
        self.tiny = np.finfo(dtype).tiny


class ProxyGrid(NamedTuple):
    """A proxy's arrays as a compiled read takes them (:meth:`ProxySDF.grid`, :func:`zoo.proxy_kernel.read`); the
    arrays are described in :class:`ProxySDF`'s docstring."""

    lo: np.ndarray  # (3,) the baked region's low corner
    hi: np.ndarray  # (3,) its high corner
    inv_h: float  # 1 / spacing
    band: float
    lipschitz: float
    brick_of: np.ndarray  # (B,) int64 each brick's row of the baked ones (NOT_READY, or < 0: none)
    nodes: np.ndarray  # (R * 729,) the baked bricks' node values
    status: np.ndarray  # (R * 512,) int8 their cells' status
    coarse_value: np.ndarray  # (B,) each brick centre's value
    coarse_grad: np.ndarray  # (B, 3) its coarse gradient
    n_bricks: np.ndarray  # (3,) int64 bricks along each axis
    brick_side: float  # m
    first_centre: np.ndarray  # (3,) brick (0, 0, 0)'s centre


class ProxySDF:
    """A narrow-band, brick-sparse, trilinear copy of an SDF (see the module docstring); an SDF itself.

    Attributes:
        lo: (3,) float64, the baked region's lower corner (cell (0, 0, 0) starts there); hi: its upper corner.
        spacing: h, the grid spacing (m). band: the half-width of the baked band (m).
        lipschitz: the bound L the bake's tests assumed of the SDF (and that a collider carries bounds with).
        n_bricks: (3,) int64 bricks per axis of the region; ``n_bricks * BRICK`` cells.
        bounds: the source SDF's bounds (two (3,) float32 tensors).
        error: {"median", "p99", "max", "samples"} the error against the source on held-out points in band (m).
        error_bound: ``ERROR_SAFETY`` times the largest error measured (m); a lazy proxy's is measured in its sample
            of ``ERROR_BRICKS`` bricks, not in the bricks it bakes later.
        settings: {"spacing", "band", "lipschitz", "brick", "version", "lazy"}.
        bake_seconds: how long the bake (a lazy proxy's creation) took (0 when loaded).
        lazy: whether bricks are baked when first read (else all were baked up front).
        sdf: the SDF a lazy proxy bakes from (None where loaded without it: a read that needs a bake then raises).
        coarse_to_fine: how a lazy read bakes a brick: coarse to fine as :func:`bake_proxy` (True, the default:
            the faster, docs/proxy.md) or all its nodes and cell centres in one SDF call (False).
        folder, key: the cache folder :meth:`flush` writes to and the key it writes under (None: not cached).
        lazy_bricks, lazy_seconds: bricks baked by reads (and :meth:`bake_at`) since creation or load, and the
            seconds spent making bricks ready.

    The arrays (torch views of the numpy arrays the reads use; R rows, row 0 the coarse row):
        brick_of: (nbx * nby * nbz,) int64, each brick's row (x-major): r >= 1 baked; 0 no band cell in the brick
            (row 0: nodes 0, status ``COARSE``); ``NOT_READY`` (lazy) its coarse values or its bake still to come.
        nodes: (R * 9^3,) float32, the rows' node values, row-major then x, y, z (0 where not evaluated).
        status: (R * 8^3,) int8 per cell of each row: ``IN_BAND`` (its 8 nodes baked), ``ABOVE`` (a block
            holding it was dropped with f above the band), ``UNKNOWN`` (dropped below it), ``COARSE`` (row 0).
        coarse_value: (nbx * nby * nbz,) float32, f at each brick's centre (NaN: not evaluated yet).
        coarse_grad: (nbx * nby * nbz, 3) float32, central differences of f at the brick centres (NaN: not yet).
        baked_bricks: (R - 1,) int64, the brick (flat index) of each baked row.
    """

    def __init__(self, *, lo, spacing, band, lipschitz, n_bricks, brick_of, nodes, status, coarse_value, coarse_grad,
                 bounds, error=None, error_bound=0.0, bake_seconds=0.0, lazy=False, sdf=None):
        self.folder, self.key = None, None  # first: __del__ flushes, even of a proxy whose arrays were refused
        self._unsaved = False  # bricks baked since the last write to ``folder``
        self._complete = False  # every brick ready (:attr:`complete`)
        self.lo = torch.as_tensor(lo, dtype=torch.float64).reshape(3)
        self.spacing, self.band, self.lipschitz = float(spacing), float(band), float(lipschitz)
        self.n_bricks = torch.as_tensor(n_bricks, dtype=torch.int64).reshape(3)
        self.bounds = tuple(torch.as_tensor(b, dtype=torch.float32).reshape(3) for b in bounds)
        self.error = dict(error or {})
        self.error_bound = float(error_bound)
        self.bake_seconds = float(bake_seconds)
        self.lazy, self.sdf, self.coarse_to_fine = bool(lazy), sdf, True
        self.lazy_bricks, self.lazy_seconds = 0, 0.0
        self.hi = self.lo + self.n_bricks.double() * BRICK * self.spacing
        nb = self.n_bricks.numpy()
        self._brick_of_np = _own(brick_of, np.int64)
        self._nodes_np, self._status_np = _own(nodes, np.float32), _own(status, np.int8)
        self._coarse_value_np = _own(coarse_value, np.float32)
        self._coarse_grad_np = _own(coarse_grad, np.float32).reshape(-1, 3)
        self._n_rows = self._nodes_np.size // NODES**3
        n = int(nb.prod())
        if (self._brick_of_np.size != n or self._status_np.size != self._n_rows * BRICK**3 or self._n_rows < 1
                or self._nodes_np.size != self._n_rows * NODES**3 or self._coarse_value_np.size != n
                or self._coarse_grad_np.shape != (n, 3) or int(self._brick_of_np.min()) < NOT_READY
                or int(self._brick_of_np.max()) >= self._n_rows):
            raise DataError("a proxy's arrays do not fit together; delete its file (it is rebuilt on the next use)")
        self._brick_at_row = np.full(self._n_rows, -1, dtype=np.int64)  # (capacity,) each row's brick
        baked = np.flatnonzero(self._brick_of_np > 0)
        self._brick_at_row[self._brick_of_np[baked]] = baked
        # numpy for read(): numpy's per-call cost is a third of torch's on a few points
        self._lo_np, self._hi_np = self.lo.numpy(), self.hi.numpy()
        self._nb = nb
        self._last_cell_np = nb * BRICK - 1
        self._nb_dims = tuple(int(n) for n in nb)
        self._strides_np = np.array([nb[1] * nb[2], nb[2], 1])
        self._brick_side = BRICK * self.spacing
        self._first_centre_np = self._lo_np + BRICK / 2 * self.spacing  # (3,) brick (0, 0, 0)'s centre
        self._half_dims = 2 * nb * BRICK + 1  # the grid of half cells the bake's points lie on
        self._constants = {np.dtype(t): _ReadConstants(self, np.dtype(t)) for t in (np.float32, np.float64)}

    @classmethod
    def empty(cls, *, lo, spacing, band, lipschitz, n_bricks, bounds, lazy, sdf) -> ProxySDF:
        """A proxy of no coarse value and no brick yet (every brick ``NOT_READY``), for :func:`bake_proxy` to fill."""
        n = int(torch.as_tensor(n_bricks).prod())
        status = np.full(BRICK**3, COARSE, dtype=np.int8)
        return cls(lo=lo, spacing=spacing, band=band, lipschitz=lipschitz, n_bricks=n_bricks,
                   brick_of=np.full(n, NOT_READY, dtype=np.int64), nodes=np.zeros(NODES**3, dtype=np.float32),
                   status=status, coarse_value=np.full(n, np.nan, dtype=np.float32),
                   coarse_grad=np.full((n, 3), np.nan, dtype=np.float32), bounds=bounds, lazy=lazy, sdf=sdf)

    @property
    def settings(self) -> dict:
        return {"spacing": self.spacing, "band": self.band, "lipschitz": self.lipschitz, "brick": BRICK,
                "version": PROXY_VERSION, "lazy": self.lazy}

    @property
    def brick_of(self) -> torch.Tensor:
        return torch.from_numpy(self._brick_of_np)

    @property
    def nodes(self) -> torch.Tensor:
        return torch.from_numpy(self._nodes_np[:self._n_rows * NODES**3])

    @property
    def status(self) -> torch.Tensor:
        return torch.from_numpy(self._status_np[:self._n_rows * BRICK**3])

    @property
    def coarse_value(self) -> torch.Tensor:
        return torch.from_numpy(self._coarse_value_np)

    @property
    def coarse_grad(self) -> torch.Tensor:
        return torch.from_numpy(self._coarse_grad_np)

    @property
    def baked_bricks(self) -> torch.Tensor:
        return torch.from_numpy(self._brick_at_row[1:self._n_rows])

    @property
    def n_baked(self) -> int:
        """Bricks baked."""
        return self._n_rows - 1

    @property
    def n_pending(self) -> int:
        """Bricks whose coarse value says they may hold band cells, not baked yet (a lazy proxy's bricks whose coarse
        value is not evaluated yet are not counted: the test says they hold none, if the Lipschitz bound holds)."""
        waiting = np.flatnonzero(self._brick_of_np == NOT_READY)
        return int(self._may_hold_band(waiting).sum())

    @property
    def complete(self) -> bool:
        """Whether every brick is ready (no read will bake); once True, True for good."""
        if not self._complete:
            self._complete = not (self._brick_of_np == NOT_READY).any()
        return self._complete

    @property
    def memory_bytes(self) -> int:
        """Bytes the proxy holds (its rows' storage, spare capacity included, the brick index and the coarse grid)."""
        return sum(a.nbytes for a in (self._brick_of_np, self._nodes_np, self._status_np, self._coarse_value_np,
                                      self._coarse_grad_np, self._brick_at_row))

    def __repr__(self):
        lazy = f", lazy, {self.n_pending} bricks pending" if self.lazy else ""
        return (f"ProxySDF(spacing={self.spacing:.3g}, band={self.band:.3g}, bricks={self.n_baked}{lazy}, "
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
        (deep inside); the gradient out of band is the coarse one (see the module docstring). A lazy proxy bakes
        the bricks the points need first. :meth:`read_numpy` on the CPU."""
        values, grads, status = self.read_numpy(points.detach().cpu().numpy())
        out = torch.from_numpy(values), torch.from_numpy(grads), torch.from_numpy(status)
        return out if points.device.type == "cpu" else tuple(t.to(points.device) for t in out)

    def read_numpy(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Values (N,), gradients (N, 3) and status (N,) int8 at ``p`` (N, 3) float32 or float64 (another dtype is
        read as float64), in its dtype: :meth:`read` without torch, the cheapest way to ask the proxy (about 20 us a
        call of 10 points in band, 40 of 500, docs/proxy.md). A lazy proxy bakes the bricks the points need first."""
        k = self._constants.get(getattr(p, "dtype", None))
        if k is None:
            p = np.asarray(p, dtype=np.float64)
            k = self._constants[p.dtype]
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"points must have shape (N, 3), got {p.shape}")
        if not p.shape[0]:
            return np.zeros(0, p.dtype), np.zeros((0, 3), p.dtype), np.zeros(0, np.int8)
        u = (p - k.lo) * k.inv_h
        floor = np.floor(u)
        cell = floor.astype(np.int64)
        brick = cell >> 3
        try:  # the usual case, every point in the region (inside None): the flat brick index and the check in one call
            brick_flat = np.ravel_multi_index(brick.T, self._nb_dims)
            inside, in_cell = None, u - floor
        except ValueError:  # some are outside it (or not finite)
            inside, in_cell = self._clip_to_region(p, u, cell)
            brick = cell >> 3
            brick_flat = brick @ self._strides_np
        row = self._brick_of_np[brick_flat]
        if row.min() < 0:  # a lazy proxy's bricks not ready yet: one test, false wherever they are
            row = self._rows_made_ready(brick_flat, row, inside)
        index = (cell & (BRICK - 1)) @ _LOCAL_STRIDES  # (N, 2): the cell in its brick, its first node there
        status = self._status_np[row * BRICK**3 + index[:, 0]]
        corners = self._nodes_np[_CORNER_OFFSETS + (row * NODES**3 + index[:, 1])]  # (8, N)
        values, grads = _trilinear(corners.astype(p.dtype, copy=False), in_cell, k.inv_h)
        if inside is None and not status.any():
            return values, grads, status
        return self._out_of_band(p, k, brick, brick_flat, status, inside, values, grads)

    _read = read_numpy  # its earlier name, which callers may still use

    def grid(self) -> ProxyGrid:
        """What a compiled read needs (:func:`zoo.proxy_kernel.read`): the arrays as they are now (baking may replace
        them)."""
        return ProxyGrid(self._lo_np, self._hi_np, 1 / self.spacing, self.band, self.lipschitz, self._brick_of_np,
                         self._nodes_np, self._status_np, self._coarse_value_np, self._coarse_grad_np, self._nb,
                         self._brick_side, self._first_centre_np)

    def make_ready(self, bricks, coarse=()) -> int:
        """Make the bricks ``bricks`` (K,) (flat indices) ready where they are not yet (a lazy proxy), as a read landing
        in them would, and give the bricks ``coarse`` (J,) their coarse values (what a read outside the region next to
        them needs); returns the bricks baked. A compiled read (:func:`zoo.proxy_kernel.read`) reports both, for its
        caller to make ready here."""
        coarse = np.unique(np.asarray(coarse, dtype=np.int64))
        if coarse.size:
            self._complete_coarse(coarse)
        bricks = np.unique(np.asarray(bricks, dtype=np.int64))
        return self._make_ready(bricks[self._brick_of_np[bricks] == NOT_READY])

    def _clip_to_region(self, p: np.ndarray, u: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For points ``p`` (N, 3) some of which lie outside the region (``u`` (N, 3) their places in cells, ``cell``
        (N, 3) int64 theirs, clipped here in place to the region): whether each is inside (N,) bool, and its place in
        its (clipped) cell (N, 3) in [0, 1]."""
        if not np.isfinite(p).all():
            raise InputError("points must be finite (no NaN or Inf)")
        inside = ((cell >= 0) & (cell <= self._last_cell_np)).all(axis=-1)
        np.clip(cell, 0, self._last_cell_np, out=cell)
        return inside, np.clip(u - cell.astype(p.dtype), 0, 1)

    def _out_of_band(self, p, k, brick, brick_flat, status, inside, values, grads):
        """:meth:`read_numpy`'s answers where a point is not in band: ``brick`` (N, 3) and ``brick_flat`` (N,) its
        brick, ``status`` (N,) its cell's, ``inside`` (N,) bool or None (all) whether it is in the region; ``values``
        (N,) and ``grads`` (N, 3) the interpolant's (kept in band)."""
        out = status != IN_BAND
        if inside is not None:
            out |= ~inside
        # the brick centre's bound f(c) - L |p - c|, valid at every point of the brick, and at least the band in an
        # ABOVE cell (a block holding it was dropped with f above the band)
        away = p - (brick * self._brick_side + self._first_centre_np)  # float64 (N, 3), from the brick's centre
        bound = self._coarse_value_np[brick_flat] - k.lipschitz * np.sqrt((away * away).sum(axis=1))
        np.maximum(bound, k.band, out=bound, where=status == ABOVE)
        values = np.where(out, bound, values)
        grads = np.where(out[:, None], self._coarse_grad_np[brick_flat], grads)
        if inside is not None:  # outside the region: also at least the band plus the distance to it; pointing away
            away = p - np.clip(p, k.lo, k.hi)
            gap = np.sqrt((away * away).sum(axis=1))
            values = np.where(inside, values, np.maximum(bound, k.band + gap))
            grads = np.where(inside[:, None], grads, away / np.maximum(gap, k.tiny)[:, None])
        # out of band: ABOVE where the value (a lower bound) is at least the band, else UNKNOWN
        status = np.where(values >= k.band, np.int8(ABOVE), np.int8(UNKNOWN))
        status *= out
        return values.astype(p.dtype, copy=False), grads.astype(p.dtype, copy=False), status

    # -- lazy baking -----------------------------------------------------------------------------

    def bake_at(self, points, coarse_to_fine: bool | None = None) -> int:
        """Make ready the bricks holding ``points`` (N, 3) (those in the region), as a read there would; returns the
        bricks baked. ``coarse_to_fine``: how (default :attr:`coarse_to_fine`)."""
        p = as_points(points).detach().cpu().double().numpy()
        cell = np.floor((p - self._lo_np) / self.spacing).astype(np.int64)
        inside = ((cell >= 0) & (cell <= self._last_cell_np)).all(axis=-1)
        flat = (cell[inside] >> 3) @ self._strides_np
        return self._make_ready(np.unique(flat[self._brick_of_np[flat] == NOT_READY]), coarse_to_fine)

    def bake_all(self, progress: bool | None = None, threads: int | None = None) -> int:
        """Make every brick ready now: evaluate every coarse value still missing and bake every brick that may hold
        band cells, so that no read bakes later (a lazy proxy then answers as an eagerly baked one, and a simulation's
        first steps cost what its later ones do); returns the bricks baked. The bricks' values are those a lazy read
        would have baked (:meth:`_evaluate_keys`).

        Args:
            progress: show a bar of the bricks made ready (default: :func:`zoo.progress.shown`).
            threads: torch threads for the SDF's evaluation (default: every core this process may use).
        """
        from .progress import progress_bar, wanted

        waiting = np.flatnonzero(self._brick_of_np == NOT_READY)
        batches = np.array_split(waiting, -(-waiting.size // AHEAD_BATCH) or 1)
        baked, before = 0, torch.get_num_threads()
        torch.set_num_threads(available_cores() if threads is None else max(1, int(threads)))
        try:
            with progress_bar(wanted(progress) and waiting.size > 0) as bar:
                task = bar.add_task(f"baking the proxy of {getattr(self.sdf, 'name', 'an SDF')} ahead (bricks)",
                                    total=waiting.size)
                for batch in batches:
                    baked += self._make_ready(batch)
                    bar.advance(task, batch.size)
        finally:
            torch.set_num_threads(before)
        return baked

    def _rows_made_ready(self, brick_flat: np.ndarray, row: np.ndarray, inside: np.ndarray | None) -> np.ndarray:
        """The rows (N,) of the bricks ``brick_flat`` (N,) after making ready those not yet (``row`` (N,) < 0) that hold
        points in the region (``inside`` (N,) bool, or None: all); a point outside gets row 0, and its brick (the
        nearest) its coarse value, which bounds the SDF there too."""
        waiting = row < 0
        if inside is not None:
            outside = waiting & ~inside
            if outside.any():
                self._complete_coarse(np.unique(brick_flat[outside]))
            waiting &= inside
        if waiting.any():
            self._make_ready(np.unique(brick_flat[waiting]))
        row = self._brick_of_np[brick_flat]
        return row if inside is None else np.where(inside, row, 0)

    def _make_ready(self, bricks: np.ndarray, coarse_to_fine: bool | None = None, advance=None) -> int:
        """Make the ``NOT_READY`` bricks ``bricks`` (K,) (flat indices) ready: their coarse values and gradients, then
        the bake of those that may hold band cells (all of them in one batch); the others get row 0. Returns the
        bricks baked. ``advance``: called with the points of each SDF call (a progress bar)."""
        if not bricks.size:
            return 0
        started = time.perf_counter()
        self._complete_coarse(bricks, advance)
        near = self._may_hold_band(bricks)
        self._brick_of_np[bricks[~near]] = 0
        baked = self._bake_bricks(bricks[near], self.coarse_to_fine if coarse_to_fine is None else coarse_to_fine,
                                  advance)
        self.lazy_bricks += baked
        self.lazy_seconds += time.perf_counter() - started
        return baked

    def _may_hold_band(self, bricks: np.ndarray) -> np.ndarray:
        """(K,) bool: whether the bricks ``bricks`` (K,) may hold band cells, by the test of their centre's f (False
        where it is not evaluated yet)."""
        radius = _HALF_DIAGONAL * BRICK * self.spacing
        with np.errstate(invalid="ignore"):  # NaN (not evaluated) compares False
            return np.abs(self._coarse_value_np[bricks].astype(np.float64)) <= self.lipschitz * radius + self.band

    def _complete_coarse(self, bricks: np.ndarray, advance=None) -> None:
        """Compute the coarse gradients of the bricks ``bricks`` (K,) that lack one, first evaluating (one batch) the
        centres they need that are not yet: theirs and their 6 neighbours'."""
        need = bricks[np.isnan(self._coarse_grad_np[bricks, 0])]
        if not need.size:
            return
        if self.sdf is None:
            raise InputError("this lazily baked proxy was loaded without its SDF, so it cannot bake the bricks a read "
                             "needs: load it with load_proxy(folder, key, sdf=...) or cached_proxy(sdf, ...)")
        nb = self._nb
        ijk = self._unravel(need)
        around = (ijk[:, None] + _AROUND).reshape(-1, 3)
        around = around[((around >= 0) & (around < nb)).all(axis=-1)]
        flat = np.unique(around @ self._strides_np)
        flat = flat[np.isnan(self._coarse_value_np[flat])]
        if flat.size:
            self._coarse_value_np[flat] = self._evaluate(16 * self._unravel(flat) + 8, advance)  # brick centres
        self._coarse_grad_np[need] = self._coarse_gradient(ijk)

    def _coarse_gradient(self, ijk: np.ndarray) -> np.ndarray:
        """(K, 3) float32 central differences of the brick-centre values at the bricks ``ijk`` (K, 3) (one-sided at the
        region's faces, 0 along an axis of one brick; all NaN where a neighbour is not evaluated)."""
        nb = self._nb
        out = np.empty(ijk.shape, dtype=np.float64)
        for axis in range(3):  # a loop over the 3 axes, not over bricks
            before, after = ijk.copy(), ijk.copy()
            before[:, axis] = np.maximum(ijk[:, axis] - 1, 0)
            after[:, axis] = np.minimum(ijk[:, axis] + 1, nb[axis] - 1)
            steps = after[:, axis] - before[:, axis]
            rise = (self._coarse_value_np[after @ self._strides_np].astype(np.float64)
                    - self._coarse_value_np[before @ self._strides_np])
            out[:, axis] = np.where(steps > 0, rise / (np.maximum(steps, 1) * BRICK * self.spacing), 0.0)
        out[np.isnan(out).any(axis=-1)] = np.nan  # all of it unknown, so that one column tells
        return out.astype(np.float32)

    def _bake_bricks(self, bricks: np.ndarray, coarse_to_fine: bool, advance=None) -> int:
        """Bake the bricks ``bricks`` (K,) (flat) into new rows, all at once: split each into 8 blocks, drop those whose
        centre fails the band test (their cells ABOVE or UNKNOWN by its sign), split the others, down to cells, then
        evaluate the kept cells' nodes. ``coarse_to_fine``: each level asks the SDF at the centres it tests (4 calls);
        else every node and cell centre of the bricks is asked in one call first. Returns K."""
        if not bricks.size:
            return 0
        rows = self._new_rows(bricks.size)
        origins = self._unravel(bricks) * BRICK  # (K, 3) the bricks' first cells
        evaluate = self._evaluate if coarse_to_fine else self._evaluated_at_once(origins, advance)
        blocks, block_rows, size = origins, rows, BRICK
        while size > 1:
            size //= 2
            children = (blocks[:, None] + _CORNERS * size).reshape(-1, 3)
            child_rows = np.repeat(block_rows, 8)
            f = evaluate(2 * children + size, advance)  # their centres, in half cells
            near = np.abs(f) <= self.lipschitz * (_HALF_DIAGONAL * size * self.spacing) + self.band
            self._mark_dropped(children[~near], child_rows[~near], size, f[~near] > 0)
            blocks, block_rows = children[near], child_rows[near]
        index = (blocks & (BRICK - 1)) @ _LOCAL_STRIDES  # the kept cells' (C, 2) indices in their bricks
        values = evaluate(2 * (blocks[:, None] + _CORNERS).reshape(-1, 3), advance).reshape(-1, 8)  # (C, 8) corners
        self._nodes_np[(block_rows * NODES**3 + index[:, 1])[:, None] + _CORNER_OFFSETS.T] = values
        self._status_np[block_rows * BRICK**3 + index[:, 0]] = IN_BAND
        self._brick_of_np[bricks] = rows
        self._brick_at_row[rows] = bricks
        self._unsaved = True
        return bricks.size

    def _mark_dropped(self, blocks: np.ndarray, rows: np.ndarray, size: int, above: np.ndarray) -> None:
        """Mark every cell of the dropped blocks ``blocks`` (D, 3) (first cells) of ``size`` cells a side, in rows
        ``rows`` (D,), ``ABOVE`` where ``above`` (D,) (f at the centre was positive: f exceeds the band on all of
        the block), else ``UNKNOWN``."""
        offsets = np.indices((size,) * 3).reshape(3, -1).T  # (size^3, 3)
        cells = (blocks[:, None] + offsets) & (BRICK - 1)  # (D, size^3, 3) in their bricks
        index = rows[:, None] * BRICK**3 + cells @ _CELL_STRIDES
        self._status_np[index] = np.where(above, ABOVE, UNKNOWN).astype(np.int8)[:, None]

    def _new_rows(self, k: int) -> np.ndarray:
        """``k`` new rows' numbers (k,); the storage doubles when full, so that a lazy proxy does not copy all its rows
        at every bake."""
        start, end = self._n_rows, self._n_rows + k
        capacity = self._brick_at_row.size
        if end > capacity:
            capacity = max(end, 2 * capacity)
            self._nodes_np = _grown(self._nodes_np, capacity * NODES**3, 0)
            self._status_np = _grown(self._status_np, capacity * BRICK**3, UNKNOWN)
            self._brick_at_row = _grown(self._brick_at_row, capacity, -1)
        self._n_rows = end
        return np.arange(start, end)

    def _unravel(self, flat: np.ndarray) -> np.ndarray:
        """Bricks (K, 3) of the flat brick indices ``flat`` (K,)."""
        nb = self._nb
        return np.stack([flat // (nb[1] * nb[2]), (flat // nb[2]) % nb[1], flat % nb[2]], axis=-1)

    def _half_keys(self, half: np.ndarray) -> np.ndarray:
        """Flat keys (M,) of points ``half`` (M, 3) in half cells from ``lo``."""
        return (half[:, 0] * self._half_dims[1] + half[:, 1]) * self._half_dims[2] + half[:, 2]

    def _evaluate(self, half: np.ndarray, advance=None) -> np.ndarray:
        """f (M,) float64 at the points ``half`` (M, 3) int64 in half cells from ``lo`` (a node at even coordinates,
        a cell centre at odd ones), each distinct point asked once."""
        keys, inverse = np.unique(self._half_keys(half), return_inverse=True)
        return self._evaluate_keys(keys, advance)[inverse]

    def _evaluate_keys(self, keys: np.ndarray, advance=None) -> np.ndarray:
        """f (M,) float64 at the points of flat half-cell keys ``keys`` (M,): float32 points, ``CHUNK`` at most a call,
        each call padded to a multiple of ``EVAL_MULTIPLE`` points (copies of its last point), under
        ``torch.no_grad()``. Every bake asks its points this way, so that a point's value is the same whichever
        points were baked with it (lazy or ahead, in any order): a proxy, and a simulation on it, do not depend on
        what the cache held."""
        dy, dz = self._half_dims[1], self._half_dims[2]
        half = np.stack([keys // (dy * dz), (keys // dz) % dy, keys % dz], axis=-1)
        points = torch.from_numpy(self._lo_np + (half / 2) * self.spacing).float()
        out = np.empty(keys.size, dtype=np.float64)
        with torch.no_grad():
            for start in range(0, keys.size, CHUNK):  # a loop over chunks, not points
                chunk = points[start:start + CHUNK]
                n = chunk.shape[0]
                if n % EVAL_MULTIPLE:
                    chunk = torch.cat([chunk, chunk[-1:].expand(EVAL_MULTIPLE - n % EVAL_MULTIPLE, 3)])
                out[start:start + n] = torch.as_tensor(self.sdf(chunk)).detach().cpu().reshape(-1)[:n].double().numpy()
                if advance is not None:
                    advance(n)
        if not np.isfinite(out).all():
            raise InputError("the SDF returned NaN or Inf inside its own bounds; check its evaluation")
        return out

    def _evaluated_at_once(self, origins: np.ndarray, advance=None):
        """Ask the SDF at every node and cell centre of the bricks whose first cells are ``origins`` (K, 3) in one
        batch; returns an ``evaluate(half, advance)`` that reads them back (as :meth:`_evaluate` would give them)."""
        keys = np.unique(self._half_keys((2 * origins[:, None] + _BRICK_HALF_POINTS).reshape(-1, 3)))
        values = self._evaluate_keys(keys, advance)

        def evaluate(half: np.ndarray, advance=None) -> np.ndarray:
            return values[np.searchsorted(keys, self._half_keys(half))]

        return evaluate

    # -- creation --------------------------------------------------------------------------------

    def _coarse_pass(self, everywhere: bool, advance=None) -> None:
        """Evaluate f at the brick centres, at all of them (``everywhere``) or at those of the blocks of bricks that
        a coarse-to-fine band test keeps; compute the gradients whose neighbours are all evaluated; give row 0 to the
        bricks that hold no band cell and have their gradient. The rest stay ``NOT_READY``."""
        nb = self._nb
        bricks = np.indices(nb).reshape(3, -1).T if everywhere else self._bricks_near_band(advance)
        flat = bricks @ self._strides_np
        self._coarse_value_np[flat] = self._evaluate(16 * bricks + 8, advance)  # brick centres, in half cells
        self._coarse_grad_np[flat] = self._coarse_gradient(bricks)
        ready = ~np.isnan(self._coarse_grad_np[flat, 0]) & ~self._may_hold_band(flat)
        self._brick_of_np[flat[ready]] = 0

    def _bricks_near_band(self, advance=None) -> np.ndarray:
        """The bricks (K, 3) of the blocks that a coarse-to-fine band test keeps: from one block of 2^k bricks a side
        over the region, f at each block's centre (the block clipped to the region); a block with |f| > L r + band
        (r its half-diagonal) holds no band cell and is dropped, the others are split into 8, down to bricks."""
        nb = self._nb
        size = 1 << (int(nb.max()) - 1).bit_length()  # the smallest power of 2 with at least the region's bricks
        blocks = np.zeros((1, 3), dtype=np.int64)
        while size > 1:
            ends = np.minimum(blocks + size, nb)
            f = self._evaluate(8 * (blocks + ends), advance)  # the clipped blocks' centres, in half cells
            radius = 0.5 * np.linalg.norm(ends - blocks, axis=-1) * BRICK * self.spacing
            blocks = blocks[np.abs(f) <= self.lipschitz * radius + self.band]
            size //= 2
            children = (blocks[:, None] + _CORNERS * size).reshape(-1, 3)
            blocks = children[(children < nb).all(axis=-1)]
        return blocks

    # -- on disk ---------------------------------------------------------------------------------

    def attach_cache(self, folder, key: str) -> None:
        """Make ``folder`` (under ``key``) the cache :meth:`flush` writes to, also at the process's exit."""
        self.folder, self.key = Path(folder), key
        _FLUSHED_AT_EXIT.add(self)

    def flush(self, force: bool = False) -> bool:
        """Write the proxy as baked so far to its cache folder (atomically, with its ``SHA256SUMS``) if bricks were baked
        since the last write (or ``force``); returns whether it wrote. Every proxy with a cache folder is flushed when
        it is dropped and at the process's exit too."""
        if self.folder is None or not (self._unsaved or force):
            return False
        save_proxy(self, self.folder, self.key or "")
        self._unsaved = False
        return True

    def __del__(self):
        """A proxy dropped before the process exits (a second ``Simulation`` in one script) writes what it baked, as
        the exit would: a baked brick is never lost."""
        try:
            self.flush()
        except Exception as exc:  # noqa: BLE001 - raised in __del__ it would be printed and lost; say it instead
            warnings.warn(f"could not write the proxy's new bricks to {self.folder}: {exc}", stacklevel=1)

    def state(self) -> tuple[dict, dict]:
        """(tensors, metadata strings) that :meth:`from_state` reads back: the rows baked so far."""
        tensors = {"lo": self.lo, "n_bricks": self.n_bricks, "brick_of": self.brick_of, "nodes": self.nodes,
                   "status": self.status, "coarse_value": self.coarse_value,
                   "coarse_grad": self.coarse_grad, "bounds_lo": self.bounds[0], "bounds_hi": self.bounds[1]}
        meta = {"settings": json.dumps(self.settings, sort_keys=True), "error": json.dumps(self.error, sort_keys=True),
                "error_bound": repr(self.error_bound), "bake_seconds": repr(self.bake_seconds)}
        return tensors, meta

    @classmethod
    def from_state(cls, tensors: dict, meta: dict, sdf=None) -> ProxySDF:
        """The proxy of :meth:`state`'s output; ``sdf``: the SDF a lazy one goes on baking from."""
        try:
            settings = json.loads(meta["settings"])
            if settings.get("version") != PROXY_VERSION:
                raise DataError(f"a proxy file of version {settings.get('version')} (this zoo reads {PROXY_VERSION}); "
                                "delete it (it is rebuilt on the next use)")
            return cls(lo=tensors["lo"], spacing=settings["spacing"], band=settings["band"], lipschitz=settings["lipschitz"],
                       n_bricks=tensors["n_bricks"], brick_of=tensors["brick_of"], nodes=tensors["nodes"],
                       status=tensors["status"], coarse_value=tensors["coarse_value"],
                       coarse_grad=tensors["coarse_grad"], bounds=(tensors["bounds_lo"], tensors["bounds_hi"]),
                       error=json.loads(meta["error"]), error_bound=float(meta["error_bound"]),
                       bake_seconds=float(meta.get("bake_seconds", 0.0)), lazy=bool(settings.get("lazy", False)), sdf=sdf)
        except (KeyError, ValueError, TypeError) as exc:
            raise DataError(f"a proxy file lacks or garbles {exc}; delete it (it is rebuilt on the next use)") from exc


def available_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _own(array, dtype) -> np.ndarray:
    """``array`` (a tensor or an array) as a flat, writable, C-contiguous numpy array of ``dtype`` (copied only if
    needed)."""
    a = array.detach().cpu().numpy() if torch.is_tensor(array) else np.asarray(array)
    a = np.ascontiguousarray(a, dtype=dtype).reshape(-1)
    return a if a.flags.writeable else a.copy()


def _grown(array: np.ndarray, size: int, fill) -> np.ndarray:
    """``array`` (n,) copied into a new array (size,) whose rest is ``fill``."""
    out = np.full(size, fill, dtype=array.dtype)
    out[:array.size] = array
    return out


def _trilinear(c: np.ndarray, in_cell: np.ndarray, inv_h) -> tuple[np.ndarray, np.ndarray]:
    """The trilinear interpolant (N,) and its gradient (N, 3) of the corner values ``c`` (8, N) (corner 4i + 2j + k at
    (i, j, k)) at ``in_cell`` (N, 3), the points' places in their cells (of side 1 / ``inv_h``).

    Lerps along z, then y, then x, each time the values and the derivatives so far together, into one buffer: a dozen
    numpy calls whatever N, each a contiguous row per corner (on a few points a call costs its overhead, about half a
    microsecond, not its arithmetic; on hundreds, the rows keep the loops long)."""
    n = c.shape[1]
    buf = np.empty((3, 2, 4, n), dtype=c.dtype)
    z = buf[0]  # (d/dz, value) of the 4 edges along z, (x, y) x-major
    np.subtract(c[1::2], c[0::2], out=z[0])
    np.multiply(z[0], in_cell[:, 2], out=z[1])
    z[1] += c[0::2]
    zy = z.reshape(4, 2, n)  # (d/dz at x0, at x1, value at x0, at x1) by y
    y = buf[1]
    np.subtract(zy[:, 1], zy[:, 0], out=y[0])
    np.multiply(y[0], in_cell[:, 1], out=y[1])
    y[1] += zy[:, 0]
    yx = y.reshape(4, 2, n)  # (d2/dydz, d/dy, d/dz, value) by x
    x = buf[2]
    np.subtract(yx[:, 1], yx[:, 0], out=x[0])  # their d/dx: x[0, 3] the gradient's x
    np.multiply(x[0], in_cell[:, 0], out=x[1])
    x[1] += yx[:, 0]  # (unused, d/dy, d/dz, value)
    grads = np.empty((n, 3), dtype=c.dtype)
    grads[:, 0] = x[0, 3]
    grads[:, 1:] = x[1, 1:3].T
    grads *= inv_h
    return x[1, 3], grads


# -- baking ---------------------------------------------------------------------------------------


def bake_proxy(sdf, margin: float = 1e-3, spacing: float | None = None, band: float | None = None,
               lipschitz: float | None = None, progress: bool | None = None, seed: int = 0, lazy: bool = False,
               error_bricks: int = ERROR_BRICKS) -> ProxySDF:
    """Bake the narrow-band proxy of ``sdf`` (any SDF) for contacts at ``margin`` (see the module docstring).

    Args:
        sdf: the SDF; its ``bounds`` must hold its surface.
        margin: m, the contact margin the proxy serves; sets the defaults of ``spacing`` and ``band``.
        spacing: m, the grid spacing (default :func:`default_spacing`).
        band: m, the half-width of the band baked (default :func:`default_band`); larger than ``margin``.
        lipschitz: the bound of |grad f| the tests assume (default :func:`zoo.collider.motion_lipschitz`).
        progress: show a bar (default: :func:`zoo.progress.shown`).
        seed: of the held-out points the error is measured on (and of a lazy proxy's sample of bricks).
        lazy: bake only the coarse grid near the surface and ``error_bricks`` random bricks that may hold band cells
            (the error is measured on those); reads bake the other bricks when they first need them. Else bake
            every brick now.
    """
    from .collider import motion_lipschitz
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
    proxy = ProxySDF.empty(lo=lo, spacing=h, band=band, lipschitz=lip, n_bricks=n_bricks, bounds=bounds, lazy=lazy,
                           sdf=sdf)
    with progress_bar(wanted(progress)) as bar:
        task = bar.add_task(f"baking the proxy of {getattr(sdf, 'name', type(sdf).__name__)} (SDF points)", total=None)

        def advance(points: int) -> None:
            bar.advance(task, points)

        proxy._coarse_pass(everywhere=not lazy, advance=advance)
        waiting = np.flatnonzero(proxy._brick_of_np == NOT_READY)
        if lazy:  # the sample the error is measured on
            near = waiting[proxy._may_hold_band(waiting)]
            pick = np.random.default_rng(seed).choice(near.size, size=min(error_bricks, near.size), replace=False)
            proxy._make_ready(np.sort(near[pick]), advance=advance)
        else:
            for batch in np.array_split(waiting, -(-waiting.size // BAKE_BATCH) or 1):  # batches of bricks
                proxy._make_ready(batch, advance=advance)
    proxy.lazy_bricks, proxy.lazy_seconds = 0, 0.0  # only what reads bake later
    proxy.error = measure_error(proxy, sdf, seed=seed)
    proxy.error_bound = ERROR_SAFETY * proxy.error["max"]
    proxy.bake_seconds = time.perf_counter() - started
    return proxy


def measure_error(proxy: ProxySDF, sdf, samples: int = ERROR_SAMPLES, seed: int = 0) -> dict:
    """|proxy - f| at ``samples`` held-out points (uniform in random baked cells, none a node) where the proxy is in
    band: {"median", "p99", "max", "samples"} in the SDF's units (zeros when nothing is baked)."""
    cells = (proxy.status[BRICK**3:] == IN_BAND).nonzero().squeeze(-1)  # in the baked rows, 1 on
    if not cells.numel():
        return {"median": 0.0, "p99": 0.0, "max": 0.0, "samples": 0}
    g = torch.Generator().manual_seed(seed)
    pick = cells[torch.randint(cells.numel(), (samples,), generator=g)]
    row, local = pick // BRICK**3, pick % BRICK**3
    brick_index = proxy.baked_bricks[row]
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
                            error_safety=ERROR_SAFETY, error_bricks=ERROR_BRICKS)}
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


def load_proxy(directory, key: str | None = None, sdf=None) -> ProxySDF:
    """The proxy saved in ``directory``, verified against its ``SHA256SUMS`` (:class:`ChecksumError` if it differs,
    :class:`DataError` if incomplete or unreadable) and, if ``key`` is given, against the key it was saved under.
    ``sdf``: the SDF a lazily baked one goes on baking from (without it, a read that needs a new brick raises)."""
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
    return ProxySDF.from_state(tensors, meta, sdf=sdf)


def cached_proxy(sdf, margin: float = 1e-3, spacing: float | None = None, band: float | None = None,
                 lipschitz: float | None = None, cache: bool | str | Path = True, progress: bool | None = None,
                 rebake: bool = False, lazy: bool = True) -> ProxySDF:
    """The proxy of ``sdf`` (as :func:`bake_proxy`'s arguments), from the cache when made before.

    ``cache``: True uses ``zoo.hub.zoo_cache_dir() / "proxies"``, a path another folder, False none. Only a model's
    shapes are cached (:func:`proxy_key`); others are baked every time. A cached proxy that fails its checksum or
    cannot be read is refused with a warning and baked again. ``rebake``: bake it anew and replace the cached one.
    ``lazy`` (the default): bricks are baked when first read, and what was baked is written back to the cache by
    :meth:`ProxySDF.flush` and at the process's exit; the cached proxy goes on baking lazily when loaded again.
    ``lazy=False``: every brick is baked now (minutes for a NeuralSDF at 0.1 mm, docs/proxy.md)."""
    from .collider import motion_lipschitz
    from .hub import zoo_cache_dir

    check_sdf(sdf)
    margin = non_negative_float(margin, "margin")
    bounds = tuple(torch.as_tensor(b, dtype=torch.float64).cpu().reshape(3) for b in sdf.bounds)
    h = default_spacing(bounds, margin) if spacing is None else positive_float(spacing, "spacing")
    band = default_band(margin, h) if band is None else positive_float(band, "band")
    lip = motion_lipschitz(sdf) if lipschitz is None else positive_float(lipschitz, "lipschitz")
    key = proxy_key(sdf, {"spacing": h, "band": band, "lipschitz": lip, "lazy": bool(lazy)}) if cache is not False else None
    folder = None
    if key is not None:
        root = zoo_cache_dir() / "proxies" if cache is True else Path(cache)
        folder = root / f"{getattr(sdf, 'name', 'sdf')}-{key[:24]}"
        if (folder / PROXY_FILE).exists() and not rebake:
            try:
                proxy = load_proxy(folder, key, sdf=sdf)
            except (ChecksumError, DataError) as exc:
                warnings.warn(f"refused the cached proxy in {folder} ({exc}); baking it again", stacklevel=2)
            else:
                proxy.attach_cache(folder, key)
                return proxy
    proxy = bake_proxy(sdf, margin, h, band, lip, progress=progress, lazy=lazy)
    if folder is not None:
        proxy.attach_cache(folder, key)
        proxy.flush(force=True)
    return proxy


@dataclass(frozen=True)
class BakedAhead:
    """What :func:`bake_ahead` did for one shape: the proxy, its shape's name, the bricks baked now (0: the cache had
    them all), the bricks it holds, its bytes in memory and on disk, the seconds it took and its cache folder."""

    proxy: ProxySDF
    shape: str
    baked: int
    bricks: int
    memory_bytes: int
    file_bytes: int
    seconds: float
    folder: Path | None


def bake_ahead(sdf, margin: float = 1e-3, progress: bool | None = None, threads: int | None = None) -> BakedAhead:
    """Make the cached proxy of ``sdf`` at ``margin`` whole (:func:`cached_proxy`, then :meth:`ProxySDF.bake_all`) and
    write it to the cache, so that a simulation at that margin starts with every brick it can reach (``zoo bake``)."""
    started = time.perf_counter()
    proxy = cached_proxy(sdf, margin=margin, progress=progress)
    baked = proxy.bake_all(progress=progress, threads=threads)
    proxy.flush()
    file = None if proxy.folder is None else proxy.folder / PROXY_FILE
    return BakedAhead(proxy=proxy, shape=getattr(sdf, "name", type(sdf).__name__), baked=baked, bricks=proxy.n_baked,
                      memory_bytes=proxy.memory_bytes, file_bytes=file.stat().st_size if file else 0,
                      seconds=time.perf_counter() - started, folder=proxy.folder)


# proxies with a cache folder, written back at exit (weakly held: a proxy no longer used is not kept alive for it)
_FLUSHED_AT_EXIT: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def _flush_at_exit() -> None:
    """Write every cached proxy's new bricks to its folder (:meth:`ProxySDF.flush`), so that a run keeps what it baked."""
    for proxy in list(_FLUSHED_AT_EXIT):
        try:
            proxy.flush()
        except Exception as exc:  # noqa: BLE001 - at exit, a failed write is reported, not raised over the run's end
            warnings.warn(f"could not write the proxy's new bricks to {proxy.folder}: {exc}", stacklevel=1)
