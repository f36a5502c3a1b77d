"""Which of a pair's contacts a simulation can use: those that face their faces, and that touch or close within the step.

One test, compiled (numba, ``cache=True``) and applied a row at a time: by :mod:`zoo.sim`'s world to every pair's
contacts (:func:`usable_rows`), and by a proxy collider's thinning inside its compiled pass
(``zoo.proxy_kernel.thinned_rows``), which must keep the same rows. ``tests/naive_filters.py`` holds the numpy
reference both are tested against.

**Facing.** A mesh face beside the SDF, not under it (the ground just in front of a sliding box that sinks 0.1 mm into
it), is within the margin of the SDF's side: its contact's normal lies along the face, and MuJoCo would make it a wall
that stops the box. A face ahead of a box's edge that hovers over it reports its own edge's point, with a slanted
normal: MuJoCo's solver resists the box's approach along that normal and lifts it. Neither is a local minimum of the
SDF over the surface: at a minimum inside a face the SDF's gradient is along the face's normal (KKT), at an edge of a
flat continuation the neighbour holds a deeper one. So touching contacts (depth <= 0) within 60 degrees of their face's
normal and separated ones within 15 degrees are kept, either side (open meshes have no reliable orientation).
Degenerate faces (no normal) are kept.

**Closing.** MuJoCo leaves out a contact its own collision finds beyond its margin (``exclude``); one given to its
solver with a positive distance still pushes the bodies apart while they approach (its reference acceleration damps the
approach), at any distance. A separated contact is kept only where the bodies close its gap within the time given: the
speculative contact that stops a fast body before it crosses a thin wall, not a brake on two bodies passing close by.
The pair's relative motion is (u, w): u + w x p is the SDF body's velocity less the mesh body's at the world point p.

**A proxy's depths.** A proxy collider's contacts carry the proxy's depths, within its error bound of the SDF's, until
the SDF answers the rows kept. Filtered on them, a face the SDF has touching by a few micrometres can read as
separated and be dropped before the SDF is asked (a nut's threads lost contacts that held it up). Where the SDF
answers every usable row before the reduction (``zoo.sim``'s ``reduce="exact"`` or False), the tests take such a depth
at its least (``slack``: the depth less the bound), and the SDF's answers are filtered again without it. The default
reduction picks on the proxy's depths: there a row the slack let through, picked for a patch's manifold and dropped
once the SDF answers it, would cost the patch its point, so no slack is taken (``zoo.sim.pairs.proxy_slack``).

``import zoo`` does not load this module, nor numba.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

try:
    from numba import njit
except ImportError as error:  # pragma: no cover - numba is a dependency of sdfzoo
    raise ImportError("sdfzoo's contact filters need numba: pip install numba") from error

GRAZING_COS = 0.5  # a touching contact whose SDF normal is more than 60 degrees from its face's normal is dropped
SEPARATED_COS = math.cos(math.radians(15.0))  # a separated one (distance > 0): more than 15 degrees


class Closing(NamedTuple):
    """A pair's relative motion and the time a separated contact has to close: u + w x p is the SDF body's velocity
    less the mesh body's at the world point p (m/s)."""

    shift: np.ndarray  # (3,) u
    turn: np.ndarray  # (3,) w
    seconds: float  # < 0: every separated contact closes in time


@njit(cache=True)
def closing_speed(shift, turn, point, normal):
    """m/s at which the pair closes along ``normal`` (3,) at the world ``point`` (3,): (u + w x p) . n, for the relative
    motion u = ``shift`` (3,), w = ``turn`` (3,)."""
    speed = 0.0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        speed += (shift[a] + turn[b] * point[c] - turn[c] * point[b]) * normal[a]
    return speed


@njit(cache=True)
def usable(depth, cos, degenerate, speed, seconds, touching_cos, separated_cos, slack):
    """Whether a contact at ``depth`` (m; > 0 separated), known within ``slack`` (m; 0: exactly) and taken at its least,
    is usable: the cosine ``cos`` between its normal and its face's is at least ``touching_cos`` in absolute value
    (``separated_cos`` where separated) or the face is ``degenerate``, and it touches or, closing at ``speed`` (m/s),
    closes within ``seconds`` (< 0: every separated one does)."""
    least = depth - slack
    if not degenerate and abs(cos) < (separated_cos if least > 0 else touching_cos):
        return False
    return least <= 0 or seconds < 0 or speed * seconds >= least


@njit(cache=True)
def usable_rows(points, depths, normals, face_normals, shift, turn, seconds, touching_cos, separated_cos, slack):
    """(K,) bool: the contacts a simulation can use (see the module docstring).

    Args:
        points (K, 3), depths (K,), normals (K, 3): the contacts, world frame; normals from the SDF body to the mesh
            body.
        face_normals (K, 3): their mesh faces' unit normals, world frame (zeros: degenerate).
        shift (3,), turn (3,): the pair's relative motion u, w; seconds: the time it has to close a gap (< 0: any).
        touching_cos, separated_cos: the facing test's cosines (``GRAZING_COS``, ``SEPARATED_COS``).
        slack: m, how far the depths may lie from the SDF's (a proxy's error bound; 0: they are the SDF's).
    """
    n = depths.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    for i in range(n):
        f = face_normals[i]
        cos = f[0] * normals[i, 0] + f[1] * normals[i, 1] + f[2] * normals[i, 2]
        degenerate = f[0] == 0 and f[1] == 0 and f[2] == 0
        speed = closing_speed(shift, turn, points[i], normals[i]) if depths[i] > slack else 0.0
        keep[i] = usable(depths[i], cos, degenerate, speed, seconds, touching_cos, separated_cos, slack)
    return keep
