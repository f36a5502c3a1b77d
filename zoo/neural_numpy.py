"""A NeuralSDF shape's value and gradient at a few points without torch: what a simulation step asks.

A simulation step asks the NeuralSDF at a handful of points (the contacts kept). For so few points the arithmetic is
small and torch's cost per operation (a few microseconds, some 60 operations for the value and its chain rule) is
most of the call. :class:`NumpyNetwork` holds one shape's network as numpy arrays and answers
:meth:`zoo.neural.NeuralShape._value_and_grad_by_hand`'s operations (the decoder's forward pass keeping each layer's
activation slope, then the chain rule by hand, layer by layer, and through the code cloud's interpolation) as one
compiled call (:mod:`zoo.neural_kernel`). :meth:`zoo.neural.NeuralShape.value_and_grad` takes this path for at most
``SMALL_BATCH`` points on the CPU without autograd; docs/proxy.md measures it. The same operations in numpy
(tests/naive_network.py) are the reference the compiled call is tested against.
"""

from __future__ import annotations

import numpy as np

SOFTPLUS_FLOOR = 40.0  # beta x below -this: the smooth activation's softplus is taken there (zoo.neural.activation)
SMALL_BATCH = 512  # points: at most this many, on the CPU and without autograd, are asked without torch


class NumpyNetwork:
    """One shape's network as numpy arrays, in one dtype (float32 or float64), answered by one compiled call.

    Args:
        weights: the hidden layers' (rows, width) matrices, bias folded in as the last row (an
            ``InferenceDecoder``'s ``weights``): layer 0's rows are [z; x; Fourier features; 1], the others' [h; that].
        out_weight (width, 1), out_bias (1,): the output layer.
        cloud_b (K, 5), codes_1 (K, C + 1): the code cloud as ``zoo.neural.augmented_code_cloud`` arranges it.
        positions (K, 3), codes (K, C): the code cloud. eps: the interpolation's epsilon.
        negative_slope, smooth_beta, fourier_levels: the decoder's.
    """

    def __init__(self, *, weights, out_weight, out_bias, cloud_b, codes_1, positions, codes, eps, negative_slope,
                 smooth_beta, fourier_levels, dtype):
        as_np = lambda t: np.ascontiguousarray(np.asarray(t, dtype=dtype))  # noqa: E731
        self.weights = [as_np(w) for w in weights]
        self.weights_t = [as_np(np.asarray(w).T) for w in weights]  # the chain rule's, each row contiguous for BLAS
        self.out_weight, self.out_bias = as_np(out_weight), as_np(out_bias)
        self.cloud_b_t, self.codes_1 = as_np(np.asarray(cloud_b).T), as_np(codes_1)
        self.positions, self.codes_t = as_np(positions), as_np(np.asarray(codes).T)
        self.eps, self.dtype = float(eps), np.dtype(dtype)
        self.slope, self.beta, self.levels = float(negative_slope), float(smooth_beta), int(fourier_levels)
        self.width = self.weights[0].shape[1]
        self.frequencies = (np.pi * 2.0 ** np.arange(self.levels)).astype(dtype)
        self._kernel_arrays = None

    def value_and_grad(self, points: np.ndarray, scale, rotation: np.ndarray, shift: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Distances (P,) and gradients (P, 3), in this network's dtype, at source-frame points ``points`` (P, 3): the
        network at ``scale * points @ rotation.T + shift`` (a shape's similarity in this dtype: a scalar, (3, 3),
        (3,)), the distances over the scale and the gradients in the source frame (R^T g): one compiled call,
        similarity included (:mod:`zoo.neural_kernel`)."""
        from .neural_kernel import value_and_grad

        # a writable C-ordered float64 copy: the one array type the call is compiled for (at a simulation's attach),
        # whatever view a caller passes
        return value_and_grad(np.array(points, dtype=np.float64, order="C"), scale, rotation, shift, self._arrays())

    def _arrays(self):
        """This network as :class:`zoo.neural_kernel.NetworkArrays` (made at the first compiled call)."""
        if self._kernel_arrays is None:
            from .neural_kernel import NetworkArrays

            self._kernel_arrays = NetworkArrays(tuple(self.weights), tuple(self.weights_t), self.out_weight, self.out_bias,
                                           self.cloud_b_t, self.codes_1, self.positions, self.codes_t, self.frequencies,
                                           self.eps, self.slope, self.beta, SOFTPLUS_FLOOR)
        return self._kernel_arrays
