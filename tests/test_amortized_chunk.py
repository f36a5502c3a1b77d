"""zoo.amortized's chunk: the network is called on at most ``chunk`` pieces at a time, whatever ``chunk`` is."""

from __future__ import annotations

import pytest
import torch

import zoo
from zoo.amortized import SolveOptions, detect
from zoo.amortized.batching import NETWORK_CHUNK
from zoo.errors import InputError


def test_chunk_is_the_network_batch_size_and_does_not_change_answers():
    model = zoo.load("mugs")
    shape = model.shape(model.shapes[0])
    lo, hi = (b.float() for b in shape.bounds)
    g = torch.Generator().manual_seed(0)
    centres = lo + (hi - lo) * (0.3 + 0.4 * torch.rand(4500, 1, 3, generator=g))
    triangles = centres + 0.05 * (hi - lo).max() * torch.randn(4500, 3, 3, generator=g)
    sizes = []
    real = model.detector.predict

    def spy(coords, *args, **kwargs):
        sizes.append(coords.shape[0])
        return real(coords, *args, **kwargs)

    model.detector.predict = spy
    try:
        small = detect(model.detector, shape, triangles, chunk=1000, polish=False)
        small_sizes, sizes[:] = list(sizes), []
        large = detect(model.detector, shape, triangles, chunk=NETWORK_CHUNK * 4, polish=False)
    finally:
        del model.detector.predict
    assert max(small_sizes) <= 1000 and len(small_sizes) > 4
    assert len(sizes) == 1 and sizes[0] == sum(small_sizes) > NETWORK_CHUNK  # one call: not capped at the default
    torch.testing.assert_close(small, large, rtol=0, atol=1e-6)
    assert SolveOptions().chunk == NETWORK_CHUNK
    for bad in (0, -1, 2.5, True):
        with pytest.raises(InputError, match="chunk"):
            SolveOptions(chunk=bad)
