"""A NeuralSDF shape's value and gradient at a few points without torch: what a simulation step asks.

A simulation step asks the NeuralSDF at a handful of points (the contacts kept). For so few points the arithmetic is
small and torch's cost per operation (a few microseconds, some 60 operations for the value and its chain rule) is
most of the call. :class:`NumpyNetwork` holds one shape's network as numpy arrays and answers
:meth:`zoo.neural.NeuralShape._value_and_grad_by_hand`'s operations (the decoder's forward pass keeping each layer's
activation slope, then the chain rule by hand, layer by layer, and through the code cloud's interpolation) as one
compiled call (:mod:`zoo.neural_kernel`). :meth:`zoo.neural.NeuralShape.value_and_grad` takes this path for at most
``SMALL_BATCH`` points on the CPU without autograd; docs/proxy.md measures it. The same operations in numpy
(:meth:`NumpyNetwork.numpy_value_and_grad`) are the reference the compiled call is tested against.
"""

from __future__ import annotations

import numpy as np

SOFTPLUS_FLOOR = 40.0  # beta x below -this: the smooth activation's softplus is taken there (zoo.neural.activation)
SMALL_BATCH = 512  # points: at most this many, on the CPU and without autograd, are asked without torch


class NumpyNetwork:
    """One shape's network in numpy, in one dtype (float32 or float64), answering in the normalised frame.

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
        self.weights_t = [as_np(np.asarray(w).T) for w in weights]  # the chain rule's: numpy multiplies a transposed view slower
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

    def numpy_value_and_grad(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values (P,) and gradients (P, 3) at normalised points ``x`` (P, 3) in this network's dtype, by numpy
        operations: the reference :meth:`value_and_grad`'s compiled call is tested against (tests/test_neural.py)."""
        z, r, total = self._features(x)
        value, grad_z, grad_x = self._decoder(z, x)
        grad_x += self._features_backward(x, z, grad_z, r, total)
        return value, grad_x

    def _features(self, x):
        """``interpolate_codes_direct_keeping_weights``: features (P, C), r = rsqrt(max(d2, eps)) (P, K), sums (P, 1)."""
        a = np.concatenate([x, (x * x).sum(-1, keepdims=True), np.ones_like(x[:, :1])], axis=-1)  # (P, 5)
        r = 1.0 / np.sqrt(np.maximum(a @ self.cloud_b_t, self.eps))
        out = (r * r * r) @ self.codes_1
        total = out[:, -1:]
        return out[:, :-1] / total, r, total

    def _features_backward(self, x, z, grad_z, r, total):
        """``interpolate_codes_direct_backward``: the gradient (P, 3) at ``x`` of ``(grad_z * z).sum()``."""
        below = r >= (1.0 - 1e-6) * self.eps ** -0.5
        a = grad_z @ self.codes_t - (grad_z * z).sum(-1, keepdims=True)
        r2 = r * r
        with np.errstate(over="ignore", invalid="ignore"):  # r^5 overflows on a code (float32); zeroed just below
            a *= r2 * r2 * r * (-3.0 / total)
        a[below] = 0.0
        return x * a.sum(-1, keepdims=True) - a @ self.positions

    def _decoder(self, z, x):
        """``InferenceDecoder.value_and_input_grad``: value (P,), d/dz (P, C), d/dx (P, 3) (the Fourier features' part
        included)."""
        n, c, w = z.shape[0], z.shape[1], self.width
        parts = [z, x]
        if self.levels:
            angles = x[:, :, None] * self.frequencies  # (P, 3, L)
            parts += [np.concatenate([np.sin(angles), np.cos(angles)], axis=-1).reshape(n, -1)]
        inputs = np.concatenate([*parts, np.ones((n, 1), dtype=self.dtype)], axis=-1)  # [z; x; Fourier; 1]
        n_in = inputs.shape[1] - 1
        slopes = []  # each layer's activation's derivative at its pre-activation
        h, slope = self._activation_and_slope(inputs @ self.weights[0])
        for weight in self.weights[1:]:
            slopes.append(slope)
            h, slope = self._activation_and_slope(np.concatenate([h, inputs], axis=-1) @ weight)
        slopes.append(slope)
        value = (h @ self.out_weight + self.out_bias)[:, 0]
        grad_in = np.zeros((n, n_in), dtype=self.dtype)
        grad_h = self.out_weight[:, 0]  # (width,): the same for every point
        for k in range(len(slopes) - 1, -1, -1):
            rows = (grad_h * slopes[k]) @ self.weights_t[k]  # [h; input; 1], or [input; 1] for k = 0
            if k:
                grad_h = rows[:, :w]
                grad_in += rows[:, w:w + n_in]
            else:
                grad_in += rows[:, :n_in]
        grad_x = grad_in[:, c:c + 3]
        if self.levels:
            g = grad_in[:, c + 3:].reshape(n, 3, 2 * self.levels)
            grad_x = grad_x + ((g[..., :self.levels] * np.cos(angles) - g[..., self.levels:] * np.sin(angles))
                               * self.frequencies).sum(-1)
        return value, grad_in[:, :c], grad_x

    def _activation_and_slope(self, x):
        """``zoo.neural.activation`` and ``zoo.neural.activation_derivative`` at ``x``: the LeakyReLU, or slope x +
        (1 - slope) softplus_beta(x) (torch's threshold of 20, and its input held above ``-SOFTPLUS_FLOOR / beta``: no
        denormal floats). In place where it can be: a step asks a few points, and each temporary costs."""
        if not self.beta:
            positive = x > 0
            return np.where(positive, x, self.slope * x), np.where(positive, 1.0, self.slope).astype(self.dtype)
        bx = self.beta * x
        soft = np.abs(bx)
        np.minimum(soft, SOFTPLUS_FLOOR, out=soft)
        np.negative(soft, out=soft)
        np.exp(soft, out=soft)  # no overflow, no denormals
        np.log1p(soft, out=soft)
        soft += np.maximum(bx, 0)
        soft /= self.beta
        np.copyto(soft, x, where=bx > 20)
        soft *= 1.0 - self.slope
        soft += self.slope * x
        slope = np.tanh(0.5 * bx)  # the sigmoid, no overflow
        slope += 1.0
        slope *= 0.5 * (1.0 - self.slope)
        slope += self.slope
        return soft, slope
