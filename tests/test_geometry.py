"""zoo.geometry.cross and zoo.sdf.value_and_grad_numpy against the functions they stand in for."""

from __future__ import annotations

import numpy as np
import torch

import zoo
from zoo.geometry import cross
from zoo.sdf import value_and_grad_numpy


def test_cross_is_numpys_to_the_bit():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    assert np.array_equal(cross(a, b), np.cross(a, b))
    assert np.array_equal(cross(a[0], b[0]), np.cross(a[0], b[0]))  # two vectors
    assert np.array_equal(cross(a[0], b), np.cross(a[0], b))  # one against many
    assert cross(a[:0], b[:0]).shape == (0, 3)


def test_value_and_grad_numpy_is_the_sdfs_own():
    sdf = zoo.Torus(0.05, 0.01)
    points = np.random.default_rng(1).uniform(-0.07, 0.07, size=(40, 3))
    values, grads = value_and_grad_numpy(sdf, points, torch.float64)
    f, g = sdf.value_and_grad(torch.from_numpy(points))
    assert values.dtype == np.float64 and values.shape == (40,) and grads.shape == (40, 3)
    assert np.allclose(values, f.numpy(), atol=1e-12) and np.allclose(grads, g.numpy(), atol=1e-12)
