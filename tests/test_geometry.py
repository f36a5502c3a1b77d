"""zoo.sdf.value_and_grad_numpy against the function it stands in for."""

from __future__ import annotations

import numpy as np
import torch

import zoo
from zoo.sdf import value_and_grad_numpy


def test_value_and_grad_numpy_is_the_sdfs_own():
    sdf = zoo.Torus(0.05, 0.01)
    points = np.random.default_rng(1).uniform(-0.07, 0.07, size=(40, 3))
    values, grads = value_and_grad_numpy(sdf, points, torch.float64)
    f, g = sdf.value_and_grad(torch.from_numpy(points))
    assert values.dtype == np.float64 and values.shape == (40,) and grads.shape == (40, 3)
    assert np.allclose(values, f.numpy(), atol=1e-12) and np.allclose(grads, g.numpy(), atol=1e-12)
