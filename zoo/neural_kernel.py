"""A NeuralSDF shape's value and gradient at a few points as one compiled call (numba): what a simulation step asks.

:class:`zoo.neural_numpy.NumpyNetwork` makes some 60 numpy operations a call, each costing a microsecond or more
whatever its size; at the handful of points a step asks, that is most of the call. :func:`value_and_grad` makes the
same arithmetic in one compiled function, the matrix products by BLAS (``np.dot``), the rest as loops.
:class:`CompiledNetwork` holds a ``NumpyNetwork``'s arrays in the layout it needs. numba is imported by this module
only; :class:`zoo.proxy_collider.ProxyCollider`, which compiles its own loop when it is made, asks through it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .neural_numpy import NumpyNetwork


class CompiledNetwork:
    """A :class:`zoo.neural_numpy.NumpyNetwork`'s arithmetic as one compiled call (see the module docstring).

    Args:
        network: the shape's ``NumpyNetwork`` (its arrays are rearranged here, not changed).
    """

    def __init__(self, network: NumpyNetwork):
        w, dtype = network.width, network.dtype
        first, hidden = network.weights[0], network.weights[1:]
        n_in = first.shape[0] - 1  # [z; x; Fourier; 1]
        as_np = lambda a: np.ascontiguousarray(a, dtype=dtype)  # noqa: E731
        self.dtype = dtype
        self.first = as_np(first)  # (n_in + 1, w)
        self.first_t = as_np(first[:n_in].T)  # (w, n_in)
        stacked = np.stack(hidden) if hidden else np.zeros((0, w + n_in + 1, w), dtype=dtype)  # (H, w + n_in + 1, w)
        self.hidden_h, self.hidden_in = as_np(stacked[:, :w]), as_np(stacked[:, w:])  # (H, w, w), (H, n_in + 1, w)
        self.hidden_h_t = as_np(stacked[:, :w].transpose(0, 2, 1))  # (H, w, w)
        self.hidden_in_t = as_np(stacked[:, w:w + n_in].transpose(0, 2, 1))  # (H, w, n_in)
        self.out_weight, self.out_bias = as_np(network.out_weight[:, 0]), float(network.out_bias[0])
        self.cloud_b_t, self.codes_1 = network.cloud_b_t, network.codes_1
        self.positions, self.codes_t = network.positions, network.codes_t
        self.frequencies = as_np(network.frequencies)
        self.eps, self.slope, self.beta = network.eps, network.slope, network.beta

    def value_and_grad(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (P,) and gradients (P, 3) at normalised-frame points ``x`` (P, 3) (read in this network's dtype)."""
        x = np.ascontiguousarray(x, dtype=self.dtype)
        return value_and_grad(x, self.first, self.first_t, self.hidden_h, self.hidden_in, self.hidden_h_t,
                              self.hidden_in_t, self.out_weight, self.out_bias, self.cloud_b_t, self.codes_1,
                              self.positions, self.codes_t, self.frequencies, self.eps, self.slope, self.beta)


@njit(cache=True, error_model="numpy")
def _activate(pre, slope, beta, h, derivative):
    """``NumpyNetwork._activation`` and ``_derivative`` of ``pre`` (P, w), into ``h`` and ``derivative``."""
    for i in range(pre.shape[0]):
        for j in range(pre.shape[1]):
            x = pre[i, j]
            if beta == 0.0:
                h[i, j] = x if x > 0 else slope * x
                derivative[i, j] = 1.0 if x > 0 else slope
            else:  # softplus_beta and its derivative, the sigmoid, from one exponential
                bx = beta * x
                if bx > 20:  # as torch's threshold; the sigmoid is 1 to float precision
                    soft, sigmoid = x, 1.0
                elif bx < -20:  # exp(bx) < 2e-9: softplus and sigmoid are that small
                    e = math.exp(bx)
                    soft, sigmoid = e / beta, e
                else:
                    e = math.exp(-abs(bx))
                    soft = (math.log1p(e) + max(bx, 0.0)) / beta
                    sigmoid = 1.0 / (1.0 + e) if bx >= 0 else e / (1.0 + e)
                h[i, j] = slope * x + (1.0 - slope) * soft
                derivative[i, j] = slope + (1.0 - slope) * sigmoid


@njit(cache=True, error_model="numpy")
def value_and_grad(x, first, first_t, hidden_h, hidden_in, hidden_h_t, hidden_in_t, out_weight, out_bias, cloud_b_t,
                   codes_1, positions, codes_t, frequencies, eps, slope, beta):
    """``NumpyNetwork.value_and_grad`` compiled: distances (P,) and gradients (P, 3) at ``x`` (P, 3); the arrays as
    :class:`CompiledNetwork` holds them."""
    p, k = x.shape[0], cloud_b_t.shape[1]
    c = codes_t.shape[0]
    w = first.shape[1]
    n_layers = hidden_h.shape[0] + 1
    levels = frequencies.shape[0]
    n_in = first_t.shape[1]
    dtype = x.dtype
    # the code cloud's interpolation: z = sum_k r_k^3 codes_k / sum_k r_k^3, r_k = rsqrt(max(|x - pos_k|^2, eps))
    a = np.empty((p, 5), dtype)
    for i in range(p):
        a[i, 0], a[i, 1], a[i, 2] = x[i, 0], x[i, 1], x[i, 2]
        a[i, 3], a[i, 4] = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2], 1.0
    r = np.dot(a, cloud_b_t)  # (P, K) squared distances
    r3 = np.empty_like(r)
    for i in range(p):
        for j in range(k):
            rij = 1.0 / math.sqrt(max(r[i, j], eps))
            r[i, j] = rij
            r3[i, j] = rij * rij * rij
    out = np.dot(r3, codes_1)  # (P, C + 1)
    inputs = np.empty((p, n_in + 1), dtype)  # [z; x; Fourier; 1]
    total = np.empty(p, dtype)
    for i in range(p):
        total[i] = out[i, c]
        for j in range(c):
            inputs[i, j] = out[i, j] / total[i]
        for d in range(3):
            inputs[i, c + d] = x[i, d]
            for level in range(levels):
                angle = x[i, d] * frequencies[level]
                inputs[i, c + 3 + d * 2 * levels + level] = math.sin(angle)
                inputs[i, c + 3 + d * 2 * levels + levels + level] = math.cos(angle)
        inputs[i, n_in] = 1.0
    # the decoder, keeping each layer's activation derivative
    derivatives = np.empty((n_layers, p, w), dtype)
    h = np.empty((p, w), dtype)
    _activate(np.dot(inputs, first), slope, beta, h, derivatives[0])
    for layer in range(1, n_layers):
        pre = np.dot(h, hidden_h[layer - 1]) + np.dot(inputs, hidden_in[layer - 1])
        _activate(pre, slope, beta, h, derivatives[layer])
    values = np.dot(h, out_weight) + out_bias
    # the chain rule, layer by layer
    grad_in = np.zeros((p, n_in), dtype)
    grad_h = np.empty((p, w), dtype)
    for i in range(p):
        grad_h[i] = out_weight
    for layer in range(n_layers - 1, -1, -1):
        t = grad_h * derivatives[layer]
        if layer:
            grad_in += np.dot(t, hidden_in_t[layer - 1])
            grad_h = np.dot(t, hidden_h_t[layer - 1])
        else:
            grad_in += np.dot(t, first_t)
    grads = np.empty((p, 3), dtype)
    for i in range(p):
        for d in range(3):
            g = grad_in[i, c + d]
            for level in range(levels):
                angle = x[i, d] * frequencies[level]
                g += (grad_in[i, c + 3 + d * 2 * levels + level] * math.cos(angle)
                      - grad_in[i, c + 3 + d * 2 * levels + levels + level] * math.sin(angle)) * frequencies[level]
            grads[i, d] = g
    # through the interpolation: d/dx of (grad_z . z), zero where a code sits on the point (r clamped by eps)
    grad_z = np.ascontiguousarray(grad_in[:, :c])
    b = np.dot(grad_z, codes_t)  # (P, K)
    clamped = (1.0 - 1e-6) / math.sqrt(eps)
    for i in range(p):
        dot = 0.0
        for j in range(c):
            dot += grad_z[i, j] * inputs[i, j]
        scale = -3.0 / total[i]
        for j in range(k):
            rij = r[i, j]
            if rij >= clamped:
                b[i, j] = 0.0
            else:
                r2 = rij * rij
                b[i, j] = (b[i, j] - dot) * r2 * r2 * rij * scale
    along = np.dot(b, positions)  # (P, 3)
    for i in range(p):
        s = 0.0
        for j in range(k):
            s += b[i, j]
        for d in range(3):
            grads[i, d] += x[i, d] * s - along[i, d]
    return values, grads
