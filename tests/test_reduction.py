"""zoo.sim.reduction: the compiled reduction against its numpy reference (tests/naive_reduction.py), row for row."""

from __future__ import annotations

import numpy as np
import pytest
from naive_reduction import reduce_contacts as naive_reduce
from naive_reduction import tangent_frames

from zoo.collision import ContactArrays
from zoo.sim.contacts import contact_rows
from zoo.sim.reduction import reduce_contacts


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def contact_set(rng: np.random.Generator):
    """A pair's contacts as a step meets them: a few patches (faces of similar normal, some degenerate), points
    scattered over a few centimetres with near copies, SDF normals near their faces' and some slanted (a rim)."""
    n = int(rng.integers(1, 90))
    patch_normals = unit(rng.normal(size=(int(rng.integers(1, 5)), 3)))
    faces = unit(patch_normals[rng.integers(0, len(patch_normals), n)] + rng.normal(scale=0.15, size=(n, 3)))
    faces[rng.random(n) < 0.05] = 0.0  # degenerate faces
    normals = unit(np.where(rng.random((n, 1)) < 0.5, -faces, faces) + rng.normal(scale=0.05, size=(n, 3)) + 1e-9)
    points = rng.uniform(-0.02, 0.02, size=(n, 3))
    copies = rng.random(n) < 0.3
    points[copies] = points[rng.integers(0, n, copies.sum())] + rng.normal(scale=2e-4, size=(copies.sum(), 3))
    depths = rng.uniform(-2e-3, 1e-3, size=n)
    return points, depths, normals, faces


@pytest.mark.parametrize("seed", range(4))
def test_compiled_reduction_keeps_the_rows_the_numpy_reference_keeps(seed):
    """300 contact sets (1 to 90 contacts, up to four patches, copies, degenerate faces), three merge distances and
    patch sizes: the same rows in the same order."""
    rng = np.random.default_rng(seed)
    reduced = 0
    for _ in range(75):
        points, depths, normals, faces = contact_set(rng)
        merge_tol = float(rng.choice([5e-4, 1e-3, 4e-3]))
        max_per_patch = int(rng.choice([1, 3, 4]))
        kept = reduce_contacts(points, depths, normals, faces, merge_tol, max_per_patch=max_per_patch)
        expected = np.asarray(naive_reduce(points, depths, normals, faces, merge_tol, max_per_patch=max_per_patch))
        assert kept.dtype == np.int64 and kept.tolist() == expected.tolist()
        reduced += len(kept) < len(depths)
    assert reduced > 50  # most sets lost rows: the reduction was exercised, not passed through


def test_no_contacts_reduce_to_none():
    empty = np.zeros((0, 3))
    assert reduce_contacts(empty, np.zeros(0), empty, empty, 1e-3).tolist() == []



def test_compiled_contact_rows_are_the_numpy_formulas():
    """MuJoCo's rows (positions p - d n / 2, frames: the normal and two tangents) from the compiled pass against numpy's
    cross products, on normals of every direction, those near x (the other helper axis) included, at rows picked
    out of order; the frames orthonormal and right-handed."""
    rng = np.random.default_rng(7)
    n = 400
    normals = unit(rng.normal(size=(n, 3)))
    normals[:60] = unit(np.array([1.0, 0.0, 0.0]) * rng.choice([-1.0, 1.0], size=(60, 1)) + rng.normal(scale=0.2, size=(60, 3)))
    points, depths = rng.uniform(-0.1, 0.1, size=(n, 3)), rng.uniform(-2e-3, 1e-3, size=n)
    contacts = ContactArrays(points, depths, normals, np.zeros(n, dtype=np.int64), np.zeros((n, 3)), n_triangles=n,
                             n_candidates=n, method="test")
    keep = rng.permutation(n)[:250]
    rows = contact_rows(contacts, keep, (3, 7))
    expected = tangent_frames(normals[keep])
    assert (np.abs(normals[keep, 0]) >= 0.9).sum() > 10  # both helper axes exercised
    np.testing.assert_allclose(rows.frame, expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rows.pos, points[keep] - 0.5 * depths[keep, None] * normals[keep], rtol=0, atol=1e-15)
    assert rows.dist.tolist() == depths[keep].tolist() and rows.geom.tolist() == [[3, 7]] * len(keep)
    axes = rows.frame.reshape(-1, 3, 3)
    np.testing.assert_allclose(axes @ axes.transpose(0, 2, 1), np.broadcast_to(np.eye(3), axes.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(axes[:, [1, 2, 0]]), 1.0, atol=1e-12)  # (t1, t2, n) right-handed
    assert len(contact_rows(contacts, np.zeros(0, dtype=np.int64), (3, 7))) == 0
