"""zoo.sim.segments.segment_minima (the SDF's least value along capsule axes, a few queries for all of them) against
brute force: every segment sampled densely."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import zoo
from zoo.sim.segments import SEGMENT_STEPS, segment_minima

DENSE = 4001  # samples per segment of the brute-force reference


def dense_minima(sdf, a: np.ndarray, b: np.ndarray, dtype=torch.float64) -> tuple[np.ndarray, np.ndarray]:
    """(S,) the least value of ``sdf`` over each segment, and (S, 3) where, from DENSE samples."""
    t = np.linspace(0.0, 1.0, DENSE)
    points = a[:, None] + t[None, :, None] * (b - a)[:, None]
    with torch.no_grad():
        values = torch.as_tensor(sdf(torch.as_tensor(points.reshape(-1, 3), dtype=dtype))).double().numpy()
    values = values.reshape(len(a), DENSE)
    best = values.argmin(axis=1)
    return values[np.arange(len(a)), best], points[np.arange(len(a)), best]


class CountingSDF:
    """An SDF that counts its value_and_grad calls."""

    def __init__(self, sdf):
        self.sdf, self.calls = sdf, 0

    def value_and_grad(self, points):
        self.calls += 1
        return self.sdf.value_and_grad(points)


@pytest.mark.parametrize("shape", ["torus", "box"])
def test_segment_minima_match_dense_sampling_on_analytic_sdfs(shape):
    """Random segments around a torus (two dips along many a segment) and a box: no segment that comes within its reach
    is dropped; the lowest point found is within 1e-6 of the dense minimum's value (the box's kinks included), and
    every point's value and gradient are the SDF's there; 1 + SEGMENT_STEPS queries for all of them."""
    sdf = zoo.Torus(0.05, 0.015) if shape == "torus" else zoo.Box((0.04, 0.03, 0.02))
    rng = np.random.default_rng(3)
    centres = rng.uniform(-0.08, 0.08, size=(300, 3))
    half = rng.normal(size=(300, 3))
    half *= (rng.uniform(0.0, 0.06, size=300) / np.linalg.norm(half, axis=1))[:, None]
    half[:5] = 0.0  # spheres
    a, b = centres - half, centres + half
    reach = np.full(300, 0.02)
    counting = CountingSDF(sdf)
    search = segment_minima(counting, a, b, reach, torch.float64)
    found = search.minima
    assert counting.calls == 1 + SEGMENT_STEPS
    least, _ = dense_minima(sdf, a, b)
    reached = np.flatnonzero(least <= reach)
    assert len(reached) > 50 and set(reached) <= set(found.owner.tolist())
    lowest = np.full(300, np.inf)
    np.minimum.at(lowest, found.owner, found.values)
    assert np.all(lowest[reached] <= least[reached] + 1e-6), np.max(lowest[reached] - least[reached])
    with torch.no_grad():
        f, g = sdf.value_and_grad(torch.as_tensor(found.points))
    np.testing.assert_allclose(found.values, f.numpy(), atol=1e-12)
    np.testing.assert_allclose(found.grads, g.numpy(), atol=1e-12)
    # every segment out of reach has a floor: a lower bound of f along it, above its reach; the others none
    out = np.setdiff1d(np.arange(300), found.owner)
    assert np.all(search.floors[out] > reach[out]) and np.all(search.floors[out] <= least[out])
    assert np.all(search.floors[np.unique(found.owner)] == -np.inf)
    spheres = found.owner < 5
    assert np.bincount(found.owner[spheres], minlength=5).tolist() == [1 if i in reached else 0 for i in range(5)]
    np.testing.assert_allclose(found.points[spheres], centres[found.owner[spheres]])


def test_segment_minima_match_dense_sampling_on_a_neural_sdf():
    """The mugs model's mug: segments across its wall and handle; the lowest point found is within 20 um of the dense
    minimum's value (a network's surface is smooth but not a cubic)."""
    mug = zoo.load("mugs").shape("hoi4d_mug_0001")
    lo, hi = (np.asarray(x, dtype=np.float64) for x in mug.bounds)
    rng = np.random.default_rng(4)
    a = lo + rng.uniform(size=(60, 3)) * (hi - lo)
    b = lo + rng.uniform(size=(60, 3)) * (hi - lo)
    b = a + (b - a) * (0.06 / np.linalg.norm(b - a, axis=1))[:, None]  # 6 cm axes
    found = segment_minima(mug, a, b, np.full(60, 0.01), torch.float32).minima
    least, _ = dense_minima(mug, a, b, torch.float32)
    reached = np.flatnonzero(least <= 0.01)
    assert len(reached) > 10 and set(reached) <= set(found.owner.tolist())
    lowest = np.full(60, np.inf)
    np.minimum.at(lowest, found.owner, found.values)
    assert np.all(lowest[reached] <= least[reached] + 2e-5), np.max(lowest[reached] - least[reached])


def test_a_lower_bound_drops_segments_before_the_sdf_is_asked_and_changes_no_minimum():
    """With a lower bound of f (a proxy's, less its error: here the torus's own less 1 mm), the segments it keeps out
    of reach are never asked of the SDF, and those that reach give the same minima as without it."""
    torus = zoo.Torus(0.05, 0.015)
    rng = np.random.default_rng(6)
    centres = rng.uniform(-0.12, 0.12, size=(200, 3))
    half = rng.normal(size=(200, 3)) * 0.01
    a, b, reach = centres - half, centres + half, np.full(200, 0.01)

    class CountingPoints(CountingSDF):
        points = 0

        def value_and_grad(self, points):
            self.points += len(points)
            return super().value_and_grad(points)

    def lower_bound(p):
        with torch.no_grad():
            return torus(torch.as_tensor(p)).numpy() - 1e-3

    plain, bounded = CountingPoints(torus), CountingPoints(torus)
    every = segment_minima(plain, a, b, reach, torch.float64).minima
    culled = segment_minima(bounded, a, b, reach, torch.float64, lower_bound).minima
    assert bounded.points < plain.points / 2
    for field in ("points", "owner", "values", "grads"):
        np.testing.assert_array_equal(getattr(every, field), getattr(culled, field))
    assert len(np.unique(culled.owner)) > 10


def test_no_segments_give_no_minima():
    search = segment_minima(zoo.Sphere(0.05), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), torch.float64)
    assert search.minima.points.shape == (0, 3) and search.minima.owner.shape == (0,) and search.floors.shape == (0,)


def test_segments_that_barely_moved_keep_their_answer_moved_to_first_order():
    """A capsule pair with coherence keeps its segment's last SDF answer while the segment moves less than
    REUSE_FRACTION of the margin (no query), its values moved along their normals: within second order of a fresh
    search's at the new ends; a larger move, or no coherence, asks the SDF again."""
    from types import SimpleNamespace

    from zoo.collider import REUSE_FRACTION
    from zoo.sim.pairs import _segment_answers

    torus = zoo.Torus(0.05, 0.015)
    margin = 1e-3
    a, b = np.array([0.04, -0.01, 0.03]), np.array([0.06, 0.012, 0.028])  # above the tube, f about 1.5 cm
    reach = np.array([0.02])

    def pair(coherence):
        return SimpleNamespace(sdf_body=SimpleNamespace(sdf=CountingSDF(torus)), last=None, clearance=None, coherence=coherence)

    kept, plain = pair(True), pair(False)
    for p in (kept, plain):
        first = _segment_answers([(p, margin, None)], a[None], b[None], reach, None)
        assert p.sdf_body.sdf.calls == 1 + SEGMENT_STEPS and len(first.points)
        np.testing.assert_allclose(first.points, a + first.params[:, None] * (b - a), atol=1e-15)
    shift = 0.8 * REUSE_FRACTION * margin * np.array([0.6, -0.5, 0.4]) / np.sqrt(0.77)  # 0.8 of the reuse distance
    moved = _segment_answers([(kept, margin, None)], (a + shift)[None], (b + shift)[None], reach, None)
    assert kept.sdf_body.sdf.calls == 1 + SEGMENT_STEPS  # no query
    fresh = segment_minima(torus, (a + shift)[None], (b + shift)[None], reach, torch.float64).minima
    np.testing.assert_allclose(moved.values.min(), fresh.values.min(), atol=1e-6)
    np.testing.assert_allclose(moved.points, first.points + shift, atol=1e-15)
    _segment_answers([(plain, margin, None)], (a + shift)[None], (b + shift)[None], reach, None)
    assert plain.sdf_body.sdf.calls == 2 * (1 + SEGMENT_STEPS)  # no coherence: asked again
    _segment_answers([(kept, margin, None)], (a + 2 * shift)[None], (b + 2 * shift)[None], reach, None)
    assert kept.sdf_body.sdf.calls == 2 * (1 + SEGMENT_STEPS)  # 1.6 reuse distances from where it was answered


def test_a_segment_out_of_reach_is_passed_over_while_its_clearance_holds():
    """A capsule pair with coherence whose segment the search found out of reach is not asked again while its floor,
    less SEGMENT_LIPSCHITZ times how far the segment moved since, stays above its reach; past that (or with no
    coherence) it is searched again. Every segment passed over is out of reach by brute force."""
    from types import SimpleNamespace

    from zoo.sim.pairs import _segment_answers
    from zoo.sim.segments import SEGMENT_LIPSCHITZ

    torus = zoo.Torus(0.05, 0.015)
    margin = 1e-3
    a, b = np.array([0.04, -0.01, 0.045]), np.array([0.06, 0.012, 0.043])  # above the tube, f about 3 cm
    reach = np.array([0.012])

    def pair(coherence):
        return SimpleNamespace(sdf_body=SimpleNamespace(sdf=CountingSDF(torus)), last=None, clearance=None,
                               coherence=coherence)

    held, plain = pair(True), pair(False)
    for p in (held, plain):
        assert not len(_segment_answers([(p, margin, None)], a[None], b[None], reach, None).points)
    assert held.clearance is not None and plain.clearance is None
    room = (held.clearance.floor - reach[0]) / SEGMENT_LIPSCHITZ  # how far it may move and stay out of reach
    assert room > 1e-3
    toward = np.array([0.0, 0.0, -1.0])  # straight down onto the tube
    for fraction in (0.3, 0.9):
        shift = fraction * room * toward
        assert not len(_segment_answers([(held, margin, None)], (a + shift)[None], (b + shift)[None], reach, None).points)
        assert held.sdf_body.sdf.calls == 1  # passed over: the first search's sample query only
        assert dense_minima(torus, (a + shift)[None], (b + shift)[None])[0][0] > reach[0]
        _segment_answers([(plain, margin, None)], (a + shift)[None], (b + shift)[None], reach, None)
    assert plain.sdf_body.sdf.calls == 3  # no coherence: asked every time
    shift = 1.1 * room * toward
    _segment_answers([(held, margin, None)], (a + shift)[None], (b + shift)[None], reach, None)
    assert held.sdf_body.sdf.calls == 2  # beyond its room from where the floor was found: searched again
