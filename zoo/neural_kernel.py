"""A NeuralSDF shape's value and gradient at a few points as one compiled function: what a simulation step asks
(the answers and the polishing step of its contacts, a capsule's samples).

:class:`zoo.neural_numpy.NumpyNetwork` in numpy makes some 60 numpy calls for a query whatever its size; at a few
points their per-call cost is most of its time. Here the same operations (the shape's similarity into the normalised
frame and back, the code cloud's features, the decoder's layers keeping each activation's slope, the chain rule back
through both) are one compiled call (numba, ``cache=True``): each layer's products in BLAS (``np.dot``, which numba
takes from SciPy), the rest in loops over the points. In float32 the smooth activation's exp and log1p are series
with no libm call (:func:`_exp_negative`, :func:`_log1p_unit`), so that its loops are vectorised; float64 takes
libm's. Answers agree with the numpy operations' up to rounding (tests/test_neural.py).

numba is imported here only: ``import zoo`` does not load it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

try:
    from numba import njit
except ImportError as error:  # pragma: no cover - numba is a dependency of sdfzoo
    raise ImportError("the compiled network needs numba: pip install numba") from error


class NetworkArrays(NamedTuple):
    """One shape's network as :class:`zoo.neural_numpy.NumpyNetwork` holds it, in one dtype: ``weights`` and
    ``weights_t`` (tuples of each hidden layer's (rows, width) matrix and its transpose, bias folded in as the last
    row), ``out_weight`` (width, 1), ``out_bias`` (1,), ``cloud_b_t`` (5, K), ``codes_1`` (K, C + 1), ``positions``
    (K, 3), ``codes_t`` (C, K), ``frequencies`` (L,) the Fourier features' (none: L = 0), and the scalars ``eps``,
    ``slope`` (the LeakyReLU's), ``beta`` (the smooth activation's; 0: none) and ``floor`` (its softplus input's)."""

    weights: tuple
    weights_t: tuple
    out_weight: np.ndarray
    out_bias: np.ndarray
    cloud_b_t: np.ndarray
    codes_1: np.ndarray
    positions: np.ndarray
    codes_t: np.ndarray
    frequencies: np.ndarray
    eps: float
    slope: float
    beta: float
    floor: float


# no nnan/ninf: the code cloud's weights are held finite by hand below, and an overflow must not be assumed away
FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def value_and_grad(points, scale, rotation, shift, net):
    """Distances (P,) and gradients (P, 3) at source-frame points ``points`` (P, 3), float64: the network ``net`` (a
    :class:`NetworkArrays`) at the normalised points ``scale * points @ rotation.T + shift`` in ``rotation``'s dtype
    (``net``'s), the distances over ``scale`` and the gradients turned back (R^T g; the scale cancels):
    :meth:`zoo.neural_numpy.NumpyNetwork.value_and_grad`'s answers. The similarity is in the compiled call: at a
    point or two, its few numpy operations would cost as much as the network."""
    x = _normalised(points, scale, rotation, shift)
    r, sums, inputs = _features(x, net)
    values, slopes = _decoder(inputs, net)
    grad_in = _chain_rule(slopes, net, inputs.shape[1])
    grads = _grad_x(x, inputs, grad_in, r, sums, net)
    source_grads = np.empty_like(grads)
    for p in range(len(values)):
        values[p] /= scale
        for b in range(3):
            source_grads[p, b] = grads[p, 0] * rotation[0, b] + grads[p, 1] * rotation[1, b] + grads[p, 2] * rotation[2, b]
    return values, source_grads


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _normalised(points, scale, rotation, shift):
    """``scale * points @ rotation.T + shift`` (P, 3), the points cast to ``rotation``'s dtype first, as numpy does."""
    dt = rotation.dtype.type
    x = np.empty((points.shape[0], 3), rotation.dtype)
    for p in range(points.shape[0]):
        p0, p1, p2 = scale * dt(points[p, 0]), scale * dt(points[p, 1]), scale * dt(points[p, 2])
        for a in range(3):
            x[p, a] = p0 * rotation[a, 0] + p1 * rotation[a, 1] + p2 * rotation[a, 2] + shift[a]
    return x


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _features(x, net):
    """The code cloud's inverse distances r (P, K), their weighted sums (P, C + 1) (the codes', then the weights'),
    and the decoder's inputs (P, C + 3 + 6 L): [z; x; Fourier features of x]."""
    dt = x.dtype.type
    n, k_codes, c_dim, levels = x.shape[0], net.cloud_b_t.shape[1], net.codes_t.shape[0], net.frequencies.shape[0]
    cloud, eps = net.cloud_b_t, dt(net.eps)
    r = np.empty((n, k_codes), x.dtype)
    for p in range(n):
        x0, x1, x2 = x[p, 0], x[p, 1], x[p, 2]
        sq = x0 * x0 + x1 * x1 + x2 * x2
        for k in range(k_codes):  # |x - code|^2 as [x; |x|^2; 1] . cloud_b
            d2 = x0 * cloud[0, k] + x1 * cloud[1, k] + x2 * cloud[2, k] + sq * cloud[3, k] + cloud[4, k]
            r[p, k] = dt(1.0) / np.sqrt(max(d2, eps))
    sums = np.zeros((n, c_dim + 1), x.dtype)
    for k in range(k_codes):
        row = net.codes_1[k]
        for p in range(n):
            weight = r[p, k] * r[p, k] * r[p, k]
            for c in range(c_dim + 1):
                sums[p, c] += weight * row[c]
    inputs = np.empty((n, c_dim + 3 + 6 * levels), x.dtype)
    for p in range(n):
        for c in range(c_dim):
            inputs[p, c] = sums[p, c] / sums[p, c_dim]
        for axis in range(3):
            inputs[p, c_dim + axis] = x[p, axis]
            first = c_dim + 3 + 2 * levels * axis  # sin at each level, then cos
            for level in range(levels):
                angle = x[p, axis] * net.frequencies[level]
                inputs[p, first + level] = np.sin(angle)
                inputs[p, first + levels + level] = np.cos(angle)
    return r, sums, inputs


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _decoder(inputs, net):
    """The decoder's values (P,) and each hidden layer's activation slope at its pre-activation (layers, P, width):
    each layer's products in BLAS (``np.dot``: layer 0's rows are [input; 1], the others' [h; input; 1])."""
    dt = inputs.dtype.type
    n, n_in, width, n_layers = inputs.shape[0], inputs.shape[1], net.weights[0].shape[1], len(net.weights)
    h = np.empty((n, width), inputs.dtype)
    slopes = np.empty((n_layers, n, width), inputs.dtype)
    for layer in range(n_layers):
        weight = net.weights[layer]
        first = 0 if layer == 0 else width
        pre = np.dot(inputs, weight[first:first + n_in])
        if layer:
            pre += np.dot(h, weight[:width])
        _activation_and_slope(pre, weight[first + n_in], dt(net.slope), dt(net.beta), dt(net.floor), h, slopes[layer])
    values = np.empty(n, inputs.dtype)
    for p in range(n):
        value = net.out_bias[0]
        for j in range(width):
            value += h[p, j] * net.out_weight[j, 0]
        values[p] = value
    return values, slopes


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _activation_and_slope(pre, bias, slope, beta, floor, h, slopes):
    """``zoo.neural.activation`` and its derivative at ``pre + bias`` (P, W), written to ``h`` and ``slopes``: the
    LeakyReLU (``beta`` 0), or slope v + (1 - slope) softplus_beta(v), softplus's input held above ``-floor`` and v
    itself above torch's threshold of 20. Every scalar in the arrays' dtype (a Python number would widen float32 to
    float64). The loops hold selects and no call, so that the compiler vectorises them: for float32, exp and log1p by
    :func:`_exp_negative` and :func:`_log1p_unit` (float64: libm's, in a loop of their own)."""
    n, width = pre.shape
    one = slope / slope
    zero = one - one
    single = pre.itemsize == 4
    e = np.empty(width, pre.dtype)  # exp(-|beta v|), then log(1 + that)
    log1p = np.empty(width, pre.dtype)
    bits = np.empty(width, np.int32)  # _exp_negative's powers of two, one buffer for every point and layer
    for p in range(n):
        if beta == zero:
            for j in range(width):
                v = pre[p, j] + bias[j]
                h[p, j] = v if v > zero else slope * v
                slopes[p, j] = one if v > zero else slope
            continue
        for j in range(width):
            e[j] = min(abs(beta * (pre[p, j] + bias[j])), floor)
        if single:  # each loop apart, with no call in it: vectorised
            _exp_negative(e, bits)
            for j in range(width):
                log1p[j] = _log1p_unit(e[j])
        else:
            for j in range(width):
                e[j] = np.exp(-e[j])  # no overflow, no denormals
                log1p[j] = np.log1p(e[j])
        for j in range(width):
            v = pre[p, j] + bias[j]
            bx = beta * v
            soft = v if bx > 20 * one else (log1p[j] + max(bx, zero)) / beta
            h[p, j] = (one - slope) * soft + slope * v
            slopes[p, j] = slope + (one - slope) * (one if bx >= zero else e[j]) / (one + e[j])


LN2_HIGH, LN2_LOW = 0.693145751953125, 1.428606765330187e-06  # ln 2 in two parts: k ln 2 exact in float32 for k < 256


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _exp_negative(a, bits):
    """exp(-a) in place for ``a`` (W,) float32 in [0, 87] (2^-k a normal float32): 2^-k exp(-r), r = a - k ln 2 within
    ln 2 / 2, the power of two built in the exponent's bits and exp(-r) its Taylor series to r^7 (within 2e-7 of the
    answer, tests/test_neural.py): no libm call, so the loop is vectorised. ``bits`` (W,) int32: scratch."""
    powers = bits.view(np.float32)
    log2e, high, low = np.float32(1.4426950408889634), np.float32(LN2_HIGH), np.float32(LN2_LOW)
    c2, c3, c4, c5, c6, c7 = np.float32(1 / 2), np.float32(1 / 6), np.float32(1 / 24), np.float32(1 / 120), np.float32(1 / 720), np.float32(1 / 5040)
    one = np.float32(1.0)
    for j in range(a.shape[0]):
        k = np.int32(a[j] * log2e + np.float32(0.5))
        bits[j] = (127 - k) << 23  # 2^-k
        r = (np.float32(k) * high - a[j]) + np.float32(k) * low  # -a + k ln 2
        a[j] = one + r * (one + r * (c2 + r * (c3 + r * (c4 + r * (c5 + r * (c6 + r * c7))))))
    for j in range(a.shape[0]):
        a[j] *= powers[j]


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _log1p_unit(e):
    """log(1 + e) for a float32 ``e`` in [0, 1]: 2 atanh(s), s = e / (2 + e) at most 1/3, by its series to s^15
    (within 2e-7 of the answer, tests/test_neural.py): no libm call."""
    s = e / (np.float32(2.0) + e)
    t = s * s
    c1, c2, c3, c4 = np.float32(1 / 3), np.float32(1 / 5), np.float32(1 / 7), np.float32(1 / 9)
    c5, c6, c7 = np.float32(1 / 11), np.float32(1 / 13), np.float32(1 / 15)
    return np.float32(2.0) * s * (np.float32(1.0) + t * (c1 + t * (c2 + t * (c3 + t * (c4 + t * (c5 + t * (c6 + t * c7)))))))


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _chain_rule(slopes, net, n_in):
    """d value / d input (P, n_in), back through the layers from their ``slopes`` (layers, P, width), each layer's
    product in BLAS."""
    n_layers, n, width = slopes.shape
    grad_h = np.empty((n, width), slopes.dtype)
    for p in range(n):
        grad_h[p] = net.out_weight[:, 0]
    grad_in = np.zeros((n, n_in), slopes.dtype)
    for layer in range(n_layers - 1, -1, -1):
        rows = np.dot(grad_h * slopes[layer], net.weights_t[layer])  # [h; input; 1], or [input; 1] for layer 0
        first = 0 if layer == 0 else width
        if layer:
            grad_h = np.ascontiguousarray(rows[:, :width])
        grad_in += rows[:, first:first + n_in]
    return grad_in


@njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy", inline="always")
def _grad_x(x, inputs, grad_in, r, sums, net):
    """The gradient (P, 3) at ``x``: the decoder's through x and its Fourier features, and through the features z
    (``zoo.neural.interpolate_codes_direct_backward``; a code's own weight, r at its cap, contributes nothing)."""
    dt = x.dtype.type
    n, k_codes, c_dim, levels = x.shape[0], r.shape[1], net.codes_t.shape[0], net.frequencies.shape[0]
    cap = (dt(1.0) - dt(1e-6)) / np.sqrt(dt(net.eps))
    a = np.zeros((n, k_codes), x.dtype)  # grad_z . codes
    for c in range(c_dim):
        row = net.codes_t[c]
        for p in range(n):
            gc = grad_in[p, c]
            for k in range(k_codes):
                a[p, k] += gc * row[k]
    grads = np.empty((n, 3), x.dtype)
    for p in range(n):
        grad_z_z = dt(0.0)
        for c in range(c_dim):
            grad_z_z += grad_in[p, c] * inputs[p, c]
        scale = dt(-3.0) / sums[p, c_dim]
        total, moment = dt(0.0), np.zeros(3, x.dtype)
        for k in range(k_codes):
            rk = r[p, k]
            if rk < cap:
                r2 = rk * rk
                ak = (a[p, k] - grad_z_z) * (r2 * r2 * rk * scale)
                total += ak
                for axis in range(3):
                    moment[axis] += ak * net.positions[k, axis]
        for axis in range(3):
            g = grad_in[p, c_dim + axis]
            first = c_dim + 3 + 2 * levels * axis
            for level in range(levels):
                angle = x[p, axis] * net.frequencies[level]
                g += (grad_in[p, first + level] * np.cos(angle) - grad_in[p, first + levels + level] * np.sin(angle)) * net.frequencies[level]
            grads[p, axis] = g + x[p, axis] * total - moment[axis]
    return grads
