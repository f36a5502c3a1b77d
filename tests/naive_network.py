"""numpy reference for :mod:`zoo.neural_kernel`: a NeuralSDF shape's value and gradient by numpy operations (the
chain rule by hand of ``zoo.neural.NeuralShape._value_and_grad_by_hand``), for tests only."""

from __future__ import annotations

import numpy as np

from zoo.neural_numpy import SOFTPLUS_FLOOR, NumpyNetwork


def value_and_grad(net: NumpyNetwork, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values (P,) and gradients (P, 3) of ``net`` at normalised points ``x`` (P, 3) in its dtype, by numpy
    operations: the reference ``NumpyNetwork.value_and_grad``'s compiled call is tested against."""
    z, r, total = _features(net, x)
    value, grad_z, grad_x = _decoder(net, z, x)
    grad_x += _features_backward(net, x, z, grad_z, r, total)
    return value, grad_x


def _features(net, x):
    """``interpolate_codes_direct_keeping_weights``: features (P, C), r = rsqrt(max(d2, eps)) (P, K), sums (P, 1)."""
    a = np.concatenate([x, (x * x).sum(-1, keepdims=True), np.ones_like(x[:, :1])], axis=-1)  # (P, 5)
    r = 1.0 / np.sqrt(np.maximum(a @ net.cloud_b_t, net.eps))
    out = (r * r * r) @ net.codes_1
    total = out[:, -1:]
    return out[:, :-1] / total, r, total


def _features_backward(net, x, z, grad_z, r, total):
    """``interpolate_codes_direct_backward``: the gradient (P, 3) at ``x`` of ``(grad_z * z).sum()``."""
    below = r >= (1.0 - 1e-6) * net.eps ** -0.5
    a = grad_z @ net.codes_t - (grad_z * z).sum(-1, keepdims=True)
    r2 = r * r
    with np.errstate(over="ignore", invalid="ignore"):  # r^5 overflows on a code (float32); zeroed just below
        a *= r2 * r2 * r * (-3.0 / total)
    a[below] = 0.0
    return x * a.sum(-1, keepdims=True) - a @ net.positions


def _decoder(net, z, x):
    """``InferenceDecoder.value_and_input_grad``: value (P,), d/dz (P, C), d/dx (P, 3) (the Fourier features' part
    included)."""
    n, c, w = z.shape[0], z.shape[1], net.width
    parts = [z, x]
    if net.levels:
        angles = x[:, :, None] * net.frequencies  # (P, 3, L)
        parts += [np.concatenate([np.sin(angles), np.cos(angles)], axis=-1).reshape(n, -1)]
    inputs = np.concatenate([*parts, np.ones((n, 1), dtype=net.dtype)], axis=-1)  # [z; x; Fourier; 1]
    n_in = inputs.shape[1] - 1
    slopes = []  # each layer's activation's derivative at its pre-activation
    h, slope = activation_and_slope(net, inputs @ net.weights[0])
    for weight in net.weights[1:]:
        slopes.append(slope)
        h, slope = activation_and_slope(net, np.concatenate([h, inputs], axis=-1) @ weight)
    slopes.append(slope)
    value = (h @ net.out_weight + net.out_bias)[:, 0]
    grad_in = np.zeros((n, n_in), dtype=net.dtype)
    grad_h = net.out_weight[:, 0]  # (width,): the same for every point
    for k in range(len(slopes) - 1, -1, -1):
        rows = (grad_h * slopes[k]) @ net.weights_t[k]  # [h; input; 1], or [input; 1] for k = 0
        if k:
            grad_h = rows[:, :w]
            grad_in += rows[:, w:w + n_in]
        else:
            grad_in += rows[:, :n_in]
    grad_x = grad_in[:, c:c + 3]
    if net.levels:
        g = grad_in[:, c + 3:].reshape(n, 3, 2 * net.levels)
        grad_x = grad_x + ((g[..., :net.levels] * np.cos(angles) - g[..., net.levels:] * np.sin(angles))
                           * net.frequencies).sum(-1)
    return value, grad_in[:, :c], grad_x


def activation_and_slope(net, x):
    """``zoo.neural.activation`` and ``zoo.neural.activation_derivative`` at ``x``: the LeakyReLU, or slope x +
    (1 - slope) softplus_beta(x) (torch's threshold of 20, and its input held above ``-SOFTPLUS_FLOOR / beta``: no
    denormal floats). In place where it can be: a step asks a few points, and each temporary costs."""
    if not net.beta:
        positive = x > 0
        return np.where(positive, x, net.slope * x), np.where(positive, 1.0, net.slope).astype(net.dtype)
    bx = net.beta * x
    soft = np.abs(bx)
    np.minimum(soft, SOFTPLUS_FLOOR, out=soft)
    np.negative(soft, out=soft)
    np.exp(soft, out=soft)  # no overflow, no denormals
    np.log1p(soft, out=soft)
    soft += np.maximum(bx, 0)
    soft /= net.beta
    np.copyto(soft, x, where=bx > 20)
    soft *= 1.0 - net.slope
    soft += net.slope * x
    slope = np.tanh(0.5 * bx)  # the sigmoid, no overflow
    slope += 1.0
    slope *= 0.5 * (1.0 - net.slope)
    slope += net.slope
    return soft, slope
