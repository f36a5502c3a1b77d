"""The dynamic code cloud NeuralSDF (DCC-DIF) and one fitted shape of it.

A category model is one shared decoder MLP plus, per shape, a *code cloud*: ``n_codes`` latent
codes ``c_j`` (``code_dim`` numbers each) sitting at learned positions ``x_j`` in the
normalised frame. The feature of a point is the inverse-distance-cubed interpolation

    z(x) = sum_j w_j c_j,   w_j = (|x - x_j|^2 + eps)^(-3/2) / sum_k (|x - x_k|^2 + eps)^(-3/2)

and the signed distance (normalised frame) is ``decoder([z(x); x])``.

Training (:func:`code_weights`, :func:`interpolate_codes`) computes the weights as a softmax of
log-weights ``-1.5 log(d2 + eps)``: that is exact, never divides by zero at a code position (the
code's weight tends to one there) and never overflows, whatever ``eps``. Queries of a fitted
shape (:class:`NeuralShape`) use :func:`interpolate_codes_direct`, the same weights computed
directly as ``rsqrt(max(d2, eps))^3`` with the normalisation applied to the (P, C) result instead of
the (P, K) weights: no log, no exp, about half the time, the same values to float rounding
(it falls back to the softmax form where ``eps`` is so small that ``eps^-1.5`` could overflow).

:class:`NeuralSDF` is the trainable category module (decoder + all code clouds);
:class:`NeuralShape` is one shape of it as an SDF in its source mesh's frame and units.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .config import DictConfig
from .errors import InputError
from .neural_numpy import SMALL_BATCH, SOFTPLUS_FLOOR, NumpyNetwork
from .sdf import SDFBase
from .validation import as_points

# Queries are evaluated in chunks so that the (chunk, n_codes) weight matrix stays around
# 1M floats (4096 points of 256 codes), whatever the number of points: chunks this size keep the
# weights and the decoder's activations in cache, faster per point than large chunks
# (docs/measurements.md, the chunk sweep).
_CHUNK_ELEMENTS = 1 << 20


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class NeuralSDFConfig(DictConfig):
    """Sizes of a code-cloud NeuralSDF; stored as ``config.json["sdf"]`` in a package."""

    _config_name = "NeuralSDF config"
    _ignored_keys = ("type", "n_params", "storage_dtype")  # descriptive keys a package's config.json adds
    _unknown_hint = "; this package needs a newer sdfzoo"

    n_codes: int = 256
    code_dim: int = 32
    hidden: tuple[int, ...] = (256, 256, 256)
    skip_input: bool = True  # re-concatenate [z; x] before every hidden layer (DCC-DIF)
    negative_slope: float = 0.02  # LeakyReLU, as DCC-DIF
    # 0: LeakyReLU (DCC-DIF). > 0: its smooth version, slope x + (1 - slope) softplus_beta(x)
    # (:func:`activation`). A LeakyReLU decoder is piecewise linear: its gradient jumps at every
    # kink, so at a minimum on a triangle's edge the KKT gap of equation (12) does not vanish even
    # at the exact minimiser; a smooth decoder's does.
    smooth_beta: float = 0.0
    # 0: the decoder sees [z; x]. L > 0: also sin and cos of 2^k pi x, k < L, per coordinate (:func:`fourier_features`):
    # detail finer than the code cloud's spacing (a bolt's 2 mm thread in a frame 50 mm across), which the decoder's
    # smooth activations do not reach from x alone
    fourier_levels: int = 0
    eps: float = 1e-16  # the paper's softening of 1/d^3
    position_init: float = 0.5  # positions start uniform in [-position_init, position_init]^3
    code_init_std: float = 0.01

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if self.n_codes < 1 or self.code_dim < 1 or not self.hidden or min(self.hidden) < 1:
            raise InputError(f"n_codes, code_dim and every hidden size must be positive, got {self}")
        if int(self.fourier_levels) != self.fourier_levels or self.fourier_levels < 0:
            raise InputError(f"fourier_levels must be a whole number >= 0 (0: none), got {self.fourier_levels}")
        if not (0.0 <= self.smooth_beta < float("inf")):
            raise InputError(f"smooth_beta must be 0 (LeakyReLU) or a positive finite sharpness, got {self.smooth_beta}")


# --------------------------------------------------------------------------- the interpolation


def code_weights(points: torch.Tensor, positions: torch.Tensor, eps: float) -> torch.Tensor:
    """Normalised inverse-distance-cubed weights of each code at each point.

    points (B, P, 3), positions (B, K, 3) -> weights (B, P, K), rows summing to 1.
    """
    # |x - p|^2 by expansion: one batched matmul instead of a (B, P, K, 3) difference tensor.
    d2 = (
        points.square().sum(-1, keepdim=True)
        + positions.square().sum(-1).unsqueeze(-2)
        - 2.0 * torch.bmm(points, positions.transpose(1, 2))
    ).clamp_min(0.0)
    return torch.softmax(-1.5 * torch.log(d2 + eps), dim=-1)


def interpolate_codes(points: torch.Tensor, positions: torch.Tensor, codes: torch.Tensor, eps: float) -> torch.Tensor:
    """Code-cloud feature of each point: points (B, P, 3), positions (B, K, 3), codes (B, K, C) -> (B, P, C)."""
    return torch.bmm(code_weights(points, positions, eps), codes)


def direct_weights_are_safe(eps: float, n_codes: int, dtype: torch.dtype) -> bool:
    """Whether ``n_codes * (eps)^-1.5`` (the largest possible weight sum) stays far below ``dtype``'s maximum."""
    if eps <= 0:
        return False
    return n_codes * float(eps) ** -1.5 < torch.finfo(dtype).max / 1024


def augmented_code_cloud(positions: torch.Tensor, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The code cloud (K, 3), (K, C) arranged for :func:`interpolate_codes_direct`.

    Returns ``b`` (K, 5) = [-2 x_j, 1, |x_j|^2], so that [p, |p|^2, 1] @ b.T = |p - x_j|^2 in one
    matmul, and ``codes_1`` (K, C + 1) = [c_j, 1], so that one matmul gives both sum_j w_j c_j and
    sum_j w_j.
    """
    b = torch.cat([-2.0 * positions, torch.ones_like(positions[:, :1]), positions.square().sum(-1, keepdim=True)], dim=-1)
    return b, torch.cat([codes, torch.ones_like(codes[:, :1])], dim=-1)


def interpolate_codes_direct(points: torch.Tensor, cloud_b: torch.Tensor, codes_1: torch.Tensor, eps: float) -> torch.Tensor:
    """Code-cloud features of points (P, 3) -> (P, C), from :func:`augmented_code_cloud`'s arrays.

    The same function as :func:`interpolate_codes` (weights (d2 + eps)^-1.5, normalised), computed
    as rsqrt(max(d2, eps))^3 with no log or softmax; the caller checks
    :func:`direct_weights_are_safe`. Differentiable in the points when they require grad
    (out-of-place ops then; in place otherwise, which saves passes over the (P, K) matrix).
    """
    d2 = _squared_distances(points, cloud_b)
    # max(d2, eps) for max(d2, 0) + eps: they differ only where d2 < eps (1e-16: a point on a code,
    # where the expansion's own rounding is ~1e-8 anyway), and it saves a pass over (P, K)
    if torch.is_grad_enabled() and points.requires_grad:
        w = d2.clamp_min(eps).rsqrt().pow(3)
    else:
        w = d2.clamp_min_(eps).rsqrt_().pow_(3)
    out = w @ codes_1  # (P, C + 1): sum_j w_j c_j and sum_j w_j
    return out[:, :-1] / out[:, -1:]


def _squared_distances(points: torch.Tensor, cloud_b: torch.Tensor) -> torch.Tensor:
    """|p - x_j|^2 (P, K) of points (P, 3) to the codes, by expansion in one matmul with :func:`augmented_code_cloud`'s ``b``."""
    a = torch.cat([points, points.square().sum(-1, keepdim=True), torch.ones_like(points[:, :1])], dim=-1)  # (P, 5)
    return a @ cloud_b.T


def interpolate_codes_direct_keeping_weights(points: torch.Tensor, cloud_b: torch.Tensor, codes_1: torch.Tensor, eps: float
                                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`interpolate_codes_direct` without gradients, also returning what its backward reads: -> features (P, C),
    r = rsqrt(max(d2, eps)) (P, K) and the weight sums (P, 1)."""
    r = _squared_distances(points, cloud_b).clamp_min_(eps).rsqrt_()
    out = r.pow(3) @ codes_1  # (P, C + 1): sum_j w_j c_j and sum_j w_j
    total = out[:, -1:]
    return out[:, :-1] / total, r, total


def interpolate_codes_direct_backward(points: torch.Tensor, positions: torch.Tensor, codes: torch.Tensor,
                                      features: torch.Tensor, grad_features: torch.Tensor, r: torch.Tensor,
                                      total: torch.Tensor, eps: float) -> torch.Tensor:
    """The gradient (P, 3) at the points (P, 3) of ``(grad_features * features).sum()``, where ``features`` (P, C),
    ``r`` (P, K) and ``total`` (P, 1) are :func:`interpolate_codes_direct_keeping_weights`'s at the points for the cloud
    ``positions`` (K, 3), ``codes`` (K, C), and ``grad_features`` (P, C) is d(output)/d(features); what autograd gives
    through that function, without a graph. ``r`` is overwritten.

    With w_j = max(d2_j, eps)^-1.5 = r_j^3, S = sum_j w_j and z = sum_j w_j c_j / S:
    dz/dx = sum_j (dw_j/dx) (c_j - z)^T / S and dw_j/dx = -3 r_j^5 (x - x_j) (0 where d2_j <= eps, where the clamp
    holds w_j constant: r_j at its largest, eps^-0.5, to rounding).
    """
    below = r >= (1.0 - 1e-6) * eps ** -0.5
    # a_j = -3 r_j^5 (g . c_j - g . z) / S: the weight of (x - x_j) in the gradient
    a = (grad_features @ codes.T).sub_((grad_features * features).sum(-1, keepdim=True))
    a.mul_(r.pow(5)).mul_(-3.0 / total).masked_fill_(below, 0.0)
    return points * a.sum(-1, keepdim=True) - a @ positions


def chunk_size(n_codes: int) -> int:
    """Points per chunk such that a (chunk, n_codes) matrix stays near ``_CHUNK_ELEMENTS``."""
    return max(1024, _CHUNK_ELEMENTS // max(1, n_codes))


# --------------------------------------------------------------------------- the decoder


def activation(x: torch.Tensor, negative_slope: float, smooth_beta: float, inplace: bool = False) -> torch.Tensor:
    """The decoder's nonlinearity, elementwise on x (any shape).

    ``smooth_beta == 0``: LeakyReLU. Otherwise ``slope x + (1 - slope) softplus_beta(x)``, which
    tends to the LeakyReLU as beta grows (it differs by at most (1 - slope) log(2) / beta, at 0)
    and has a continuous derivative.

    The softplus's input is held above ``-SOFTPLUS_FLOOR / beta``: below it the softplus is under exp(-40) / beta,
    beyond the precision of the slope's term beside it (the sum is the same number), and exp(beta x) would be a
    denormal float, on which a CPU's arithmetic is many times slower (most of a hidden layer's units sit there).
    """
    if not smooth_beta:
        return nn.functional.leaky_relu_(x, negative_slope) if inplace else nn.functional.leaky_relu(x, negative_slope)
    soft = nn.functional.softplus(x.clamp(min=-SOFTPLUS_FLOOR / smooth_beta), beta=smooth_beta)
    if inplace:
        return x.mul_(negative_slope).add_(soft, alpha=1.0 - negative_slope)
    return negative_slope * x + (1.0 - negative_slope) * soft


def activation_derivative(x: torch.Tensor, negative_slope: float, smooth_beta: float) -> torch.Tensor:
    """d activation / dx elementwise (the same shape as x): for the LeakyReLU 1 or the slope (autograd's choice, the
    slope, at 0), for the smooth one slope + (1 - slope) sigmoid(beta x)."""
    if not smooth_beta:
        return torch.where(x > 0, torch.ones_like(x), torch.full_like(x, negative_slope))
    return torch.sigmoid(smooth_beta * x).mul_(1.0 - negative_slope).add_(negative_slope)


def fourier_features(points: torch.Tensor, levels: int) -> torch.Tensor:
    """[sin(2^k pi x_i) for k < levels, then cos(...)] per coordinate i: points (..., 3) -> (..., 6 levels)."""
    angles = points.unsqueeze(-1) * fourier_frequencies(levels, points)  # (..., 3, L)
    return torch.cat([angles.sin(), angles.cos()], dim=-1).flatten(-2)


def fourier_frequencies(levels: int, like: torch.Tensor) -> torch.Tensor:
    """2^k pi for k < levels (L,), in ``like``'s dtype and device."""
    return torch.pi * 2.0 ** torch.arange(levels, dtype=like.dtype, device=like.device)


def fourier_backward(points: torch.Tensor, grad_features: torch.Tensor, levels: int) -> torch.Tensor:
    """The gradient (P, 3) at the points (P, 3) of ``(grad_features * fourier_features(points)).sum()``, grad_features (P, 6 L)."""
    w = fourier_frequencies(levels, points)
    angles = points.unsqueeze(-1) * w  # (P, 3, L)
    g = grad_features.reshape(*points.shape, 2 * levels)
    return ((g[..., :levels] * angles.cos() - g[..., levels:] * angles.sin()) * w).sum(-1)


class Decoder(nn.Module):
    """MLP on [z; x] (and :func:`fourier_features` of x, with ``fourier_levels``) -> signed distance;
    ``skip_input`` re-feeds that input to every hidden layer.

    forward: features (..., C), points (..., 3) -> (...,).
    """

    def __init__(self, config: NeuralSDFConfig):
        super().__init__()
        self.fourier_levels = int(config.fourier_levels)
        n_in = config.code_dim + 3 + 6 * self.fourier_levels
        self.skip_input = config.skip_input
        self.negative_slope = config.negative_slope
        self.smooth_beta = config.smooth_beta
        layers, width = [], 0
        for i, h in enumerate(config.hidden):
            fan_in = n_in if i == 0 else (width + n_in if self.skip_input else width)
            layers.append(nn.Linear(fan_in, h))
            width = h
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(width, 1)

    def forward(self, features: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        extra = [fourier_features(points, self.fourier_levels)] if self.fourier_levels else []
        inp = torch.cat([features, points, *extra], dim=-1)
        h = inp
        for i, layer in enumerate(self.hidden):
            if i and self.skip_input:
                h = torch.cat([h, inp], dim=-1)
            h = activation(layer(h), self.negative_slope, self.smooth_beta)
        return self.out(h).squeeze(-1)


class InferenceDecoder:
    """A :class:`Decoder`'s forward pass for queries without gradients: the same arithmetic, fewer passes.

    Each hidden layer's bias is folded into its weight (a column of ones rides along with the
    input) and the skip input [z; x; 1] sits once in a reused buffer beside the previous layer's
    activation, so a layer is one matmul and one in-place LeakyReLU: no concatenation copies,
    no bias broadcast (less time, the same values). Only for decoders whose
    hidden layers share one width and re-feed the input (every packaged model); others use
    :meth:`Decoder.forward`. Rebuilt when the decoder's parameters change in place.
    """

    def __init__(self, decoder: Decoder):
        self.decoder = decoder
        # each module's own parameter table, read at every check: a walk over the modules costs more than the check
        self._tables = [module._parameters for module in decoder.modules()]
        self.version = self._version()
        width = decoder.hidden[0].out_features
        self.width = width
        with torch.no_grad():
            self.weights = [torch.cat([layer.weight, layer.bias.unsqueeze(1)], dim=1).T.contiguous() for layer in decoder.hidden]
            self.out_weight = decoder.out.weight.T.contiguous()
            self.out_bias = decoder.out.bias.detach().clone()

    @staticmethod
    def supports(decoder: Decoder) -> bool:
        widths = {layer.out_features for layer in decoder.hidden}
        return decoder.skip_input and len(widths) == 1

    def _version(self) -> tuple:
        return tuple((p.data_ptr(), p._version) for table in self._tables for p in table.values() if p is not None)

    @property
    def current(self) -> bool:
        return self._version() == self.version

    def _input_buffer(self, features: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(P, width + n_in + 1): room for the previous layer's activation, then [z; x; Fourier features of x; 1]."""
        n, c = features.shape[0], features.shape[-1]
        w, levels = self.width, self.decoder.fourier_levels
        buf = features.new_empty((n, w + c + 4 + 6 * levels))
        buf[:, w : w + c] = features
        buf[:, w + c : w + c + 3] = points
        if levels:
            buf[:, w + c + 3 : -1] = fourier_features(points, levels)
        buf[:, -1] = 1.0
        return buf

    def __call__(self, features: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        w = self.width
        buf = self._input_buffer(features, points)
        slope, beta = self.decoder.negative_slope, self.decoder.smooth_beta
        h = activation(buf[:, w:] @ self.weights[0], slope, beta, inplace=True)
        for weight in self.weights[1:]:
            buf[:, :w] = h
            h = activation(buf @ weight, slope, beta, inplace=True)
        return torch.addmm(self.out_bias, h, self.out_weight).squeeze(-1)

    def value_and_input_grad(self, features: torch.Tensor, points: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The decoder's value (P,) and its gradients with respect to ``features`` (P, C) and ``points`` (P, 3):
        the forward pass of :meth:`__call__` keeping each layer's pre-activation, then the chain rule by hand,
        layer by layer (what autograd computes, without building a graph: no per-call engine overhead)."""
        n, c = features.shape[0], features.shape[-1]
        w, levels = self.width, self.decoder.fourier_levels
        n_in = c + 3 + 6 * levels
        buf = self._input_buffer(features, points)
        slope, beta = self.decoder.negative_slope, self.decoder.smooth_beta
        pre = [buf[:, w:] @ self.weights[0]]
        for weight in self.weights[1:]:
            buf[:, :w] = activation(pre[-1], slope, beta)
            pre.append(buf @ weight)
        value = torch.addmm(self.out_bias, activation(pre[-1], slope, beta), self.out_weight).squeeze(-1)
        grad_in = features.new_zeros((n, n_in))  # d value / d [z; x; Fourier features]
        grad_h = self.out_weight.T.expand(n, w)
        for k in range(len(pre) - 1, -1, -1):
            grad_pre = grad_h * activation_derivative(pre[k], slope, beta)
            grad_rows = grad_pre @ self.weights[k].T  # (P, rows of layer k): [h; input; 1], or [input; 1] for k = 0
            if k:
                grad_h = grad_rows[:, :w]
                grad_in += grad_rows[:, w : w + n_in]
            else:
                grad_in += grad_rows[:, :n_in]
        grad_x = grad_in[:, c : c + 3]
        if levels:
            grad_x = grad_x + fourier_backward(points, grad_in[:, c + 3 :], levels)
        return value, grad_in[:, :c], grad_x


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# --------------------------------------------------------------------------- the category module


class NeuralSDF(nn.Module):
    """A category NeuralSDF: one decoder and ``n_shapes`` code clouds, all in the normalised frame.

    ``codes`` (S, K, C) and ``positions`` (S, K, 3) are parameters, learned jointly with the
    decoder (auto-decoder training) or, for an unseen shape, alone with the decoder frozen.
    """

    def __init__(self, config: NeuralSDFConfig, n_shapes: int, generator: torch.Generator | None = None):
        super().__init__()
        if n_shapes < 1:
            raise InputError(f"a NeuralSDF needs at least one shape, got n_shapes={n_shapes}")
        self.config = config
        self.decoder = Decoder(config)
        codes, positions = init_code_cloud(config, n_shapes, generator)
        self.codes = nn.Parameter(codes)
        self.positions = nn.Parameter(positions)

    @property
    def n_shapes(self) -> int:
        return self.codes.shape[0]

    def forward(self, points: torch.Tensor, shape_index: torch.Tensor) -> torch.Tensor:
        """Signed distance of each shape's points: points (B, P, 3), shape_index (B,) -> (B, P)."""
        return decode(self.decoder, points, self.positions[shape_index], self.codes[shape_index], self.config.eps)


def init_code_cloud(config: NeuralSDFConfig, n_shapes: int, generator: torch.Generator | None = None):
    """Fresh code clouds: -> codes (S, K, C) ~ N(0, code_init_std^2), positions (S, K, 3) uniform in the cube."""
    k, c, a = config.n_codes, config.code_dim, config.position_init
    codes = torch.randn(n_shapes, k, c, generator=generator) * config.code_init_std
    positions = (torch.rand(n_shapes, k, 3, generator=generator) * 2.0 - 1.0) * a
    return codes, positions


def decode(decoder: Decoder, points: torch.Tensor, positions: torch.Tensor, codes: torch.Tensor, eps: float) -> torch.Tensor:
    """Signed distance (normalised frame): points (B, P, 3), positions (B, K, 3), codes (B, K, C) -> (B, P)."""
    return decoder(interpolate_codes(points, positions, codes, eps), points)


# --------------------------------------------------------------------------- one shape as an SDF


# Converted copies of a decoder (float64, another device, the inference form), kept per decoder and shared by
# every shape of its model: a category of thousands of shapes holds one copy per device and dtype, not one each.
_DECODER_COPIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def shared_decoder_copy(decoder: nn.Module, key: tuple, make, replace: bool = False):
    """The copy of ``decoder`` under ``key`` (made by ``make()`` the first time, or again with ``replace``)."""
    table = _DECODER_COPIES.setdefault(decoder, {})
    if replace or key not in table:
        table[key] = make()
    return table[key]


def converted(decoder: nn.Module, dtype: torch.dtype, device) -> nn.Module:
    """A frozen copy of ``decoder`` in ``dtype`` on ``device``."""
    import copy

    return copy.deepcopy(decoder).to(device=device, dtype=dtype).requires_grad_(False)


class NeuralShape(SDFBase):
    """One fitted shape: an SDF in its source mesh's frame and units.

    Points go to the normalised frame by the shape's similarity (``p_n = s R p + t``), the
    network answers there, and distances come back as ``d / s``; gradients come back rotated,
    ``R^T grad_n`` (the scale cancels). float64 input is evaluated in float64 and stays float64.
    Large inputs are evaluated in chunks.
    """

    def __init__(self, name: str, decoder: Decoder, config: NeuralSDFConfig, codes: torch.Tensor,
                 positions: torch.Tensor, similarity=None, model=None):
        from .meshes import Similarity

        self.name = name
        self.config = config
        self.decoder = decoder
        self.codes = codes.detach()  # (K, C)
        self.positions = positions.detach()  # (K, 3)
        self.similarity = similarity if similarity is not None else Similarity.identity()
        self.model = model
        self.fit: dict = {}  # how the codes were fitted (Model.fit_codes), saved with them
        self.metrics: dict = {}  # how well (zoo fit-codes), saved with them
        self._copies: dict = {}
        self.bounds = self._source_bounds()

    def save(self, path, fit: dict | None = None, metrics: dict | None = None):
        """Write this shape's codes (K, C) and positions (K, 3) with its model's name@version and decoder
        sha256, its similarity, ``fit`` and ``metrics`` (default: the shape's own) as one safetensors file;
        ``zoo.load_shape(path)`` reads it back. Returns the path. See :mod:`zoo.shape_file`."""
        from .shape_file import save_shape

        return save_shape(self, path, fit, metrics)

    # ---- frames

    def _source_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The normalised unit cube's corners mapped to the source frame, as an axis-aligned box."""
        import numpy as np

        corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
        src = self.similarity.to_source(corners)
        return torch.as_tensor(src.min(0), dtype=torch.float32), torch.as_tensor(src.max(0), dtype=torch.float32)

    def _similarity_tensors(self, like: torch.Tensor):
        """scale (), rotation (3, 3), translation (3,) in ``like``'s dtype and device."""
        s = torch.as_tensor(self.similarity.scale, dtype=like.dtype, device=like.device)
        r = torch.as_tensor(self.similarity.rotation, dtype=like.dtype, device=like.device)
        t = torch.as_tensor(self.similarity.translation, dtype=like.dtype, device=like.device)
        return s, r, t

    @property
    def normalised(self) -> NeuralShape:
        """The same shape answering in the normalised frame (unit cube, scale 1); built once, and
        sharing this shape's cache of converted networks."""
        if getattr(self, "_normalised_shape", None) is None:
            n = NeuralShape(self.name, self.decoder, self.config, self.codes, self.positions, None, self.model)
            n._copies = self._copies  # the same decoder and code cloud: share their converted copies
            self._normalised_shape = n
        return self._normalised_shape

    # ---- evaluation

    def _cached(self, dtype: torch.dtype, device: torch.device):
        """(decoder, positions (1, K, 3), codes (1, K, C), augmented cloud or None) in ``dtype`` on ``device``.

        The augmented cloud is :func:`augmented_code_cloud`'s pair where the direct weights are
        safe in ``dtype`` (:func:`direct_weights_are_safe`), else None (the softmax form is used).
        """
        key = (dtype, str(device))
        if key not in self._copies:
            param = next(self.decoder.parameters())
            same = param.dtype == dtype and param.device == torch.device(device)
            # a converted copy only where needed (float64 input is evaluated in float64), one per model
            dec = self.decoder if same else shared_decoder_copy(self.decoder, key, lambda: converted(self.decoder, dtype, device))
            pos = self.positions.to(device=device, dtype=dtype)
            codes = self.codes.to(device=device, dtype=dtype)
            direct = augmented_code_cloud(pos, codes) if direct_weights_are_safe(self.config.eps, pos.shape[0], dtype) else None
            self._copies[key] = (dec, pos.unsqueeze(0), codes.unsqueeze(0), direct)
        return self._copies[key]

    def _decoder_no_grad(self, dtype: torch.dtype, device):
        """The decoder for queries without gradients: an :class:`InferenceDecoder` where it applies."""
        dec = self._cached(dtype, device)[0]
        if not InferenceDecoder.supports(dec):
            return dec
        key = ("inference", dtype, str(device))
        fast = shared_decoder_copy(self.decoder, key, lambda: InferenceDecoder(dec))
        if fast.decoder is not dec or not fast.current:
            fast = shared_decoder_copy(self.decoder, key, lambda: InferenceDecoder(dec), replace=True)
        return fast

    def _interpolate(self, points_n: torch.Tensor) -> torch.Tensor:
        """Code-cloud features of one chunk of normalised points (P, 3) -> (P, C)."""
        _, pos, codes, direct = self._cached(points_n.dtype, points_n.device)
        if direct is not None:
            return interpolate_codes_direct(points_n, *direct, self.config.eps)
        return interpolate_codes(points_n.unsqueeze(0), pos, codes, self.config.eps).squeeze(0)

    def _normalised_distance(self, points_n: torch.Tensor) -> torch.Tensor:
        """Distance in the normalised frame of one chunk: (P, 3) -> (P,), differentiable in the points."""
        if torch.is_grad_enabled() and points_n.requires_grad:
            dec = self._cached(points_n.dtype, points_n.device)[0]
        else:
            dec = self._decoder_no_grad(points_n.dtype, points_n.device)
        return dec(self._interpolate(points_n), points_n)

    def _source_distance(self, points: torch.Tensor) -> torch.Tensor:
        s, r, t = self._similarity_tensors(points)
        return self._normalised_distance(s * points @ r.T + t) / s

    def _distance(self, points: torch.Tensor) -> torch.Tensor:
        n = chunk_size(self.config.n_codes)
        if torch.is_grad_enabled() and points.requires_grad:
            # keep the graph: callers differentiate through the SDF (e.g. detector training)
            return torch.cat([self._source_distance(c) for c in points.split(n)])
        with torch.no_grad():
            return torch.cat([self._source_distance(c) for c in points.split(n)])

    def _value_and_grad(self, points: torch.Tensor, create_graph: bool = False):
        n = chunk_size(self.config.n_codes)
        if not create_graph and not (torch.is_grad_enabled() and points.requires_grad):
            if points.shape[0] <= SMALL_BATCH and points.device.type == "cpu":
                answer = self._few_in_numpy(points.numpy(), points.dtype)
                if answer is not None:
                    return tuple(torch.from_numpy(a) for a in answer)
            fast = self._value_and_grad_by_hand(points, n)
            if fast is not None:
                return fast
        values, grads = [], []
        for chunk in points.split(n):
            with torch.enable_grad():
                x = chunk if (create_graph and chunk.requires_grad) else chunk.detach().requires_grad_(True)
                d = self._source_distance(x)
                (g,) = torch.autograd.grad(d.sum(), x, create_graph=create_graph)
            values.append(d if create_graph else d.detach())
            grads.append(g if create_graph else g.detach())
        return torch.cat(values), torch.cat(grads)

    def value_and_grad_few(self, points: np.ndarray, dtype: torch.dtype = torch.float32):
        """:meth:`value_and_grad` at a few points (at most ``SMALL_BATCH``, (N, 3) numpy, source frame), asked in
        ``dtype`` and answered as numpy arrays in it: (values (N,), gradients (N, 3)), or None where the compiled network
        does not apply (more points, or a decoder it does not support). No validation, no torch: for a collider that
        asks a handful of points many times a step."""
        if len(points) > SMALL_BATCH:
            return None
        return self._few_in_numpy(points, dtype)

    def _few_in_numpy(self, points: np.ndarray, dtype: torch.dtype):
        network = self._numpy_network(dtype)
        if network is None:
            return None
        return network.value_and_grad(points, *self._similarity_numpy(network.dtype))

    def _numpy_network(self, dtype: torch.dtype) -> NumpyNetwork | None:
        """:class:`zoo.neural_numpy.NumpyNetwork` of this shape in ``dtype`` (built once, and again when the decoder's
        parameters change); None where :meth:`_value_and_grad_by_hand` does not apply."""
        held = self._copies.get(("numpy", dtype))
        if held is not None and held[0].current:  # built, and its decoder's parameters unchanged since: a step's path
            return held[1]
        dec = self._decoder_no_grad(dtype, "cpu")
        _, pos, codes, direct = self._cached(dtype, "cpu")
        if direct is None or not isinstance(dec, InferenceDecoder) or dtype not in (torch.float32, torch.float64):
            return None
        key = ("numpy", dtype)
        held = self._copies.get(key)
        if held is None or held[0] is not dec:
            network = NumpyNetwork(weights=[w.detach().numpy() for w in dec.weights], out_weight=dec.out_weight.detach().numpy(),
                                   out_bias=dec.out_bias.detach().numpy(), cloud_b=direct[0].detach().numpy(),
                                   codes_1=direct[1].detach().numpy(), positions=pos[0].detach().numpy(),
                                   codes=codes[0].detach().numpy(), eps=self.config.eps,
                                   negative_slope=self.decoder.negative_slope, smooth_beta=self.decoder.smooth_beta,
                                   fourier_levels=self.decoder.fourier_levels, dtype=np.float32 if dtype == torch.float32 else np.float64)
            held = self._copies[key] = (dec, network)
        return held[1]

    def _similarity_numpy(self, dtype: np.dtype) -> tuple:
        """This shape's similarity (scale, rotation (3, 3), translation (3,)) in numpy ``dtype`` (kept per shape: the
        normalised view shares the networks, not the frame)."""
        held = self.__dict__.setdefault("_similarity_np", {})
        if dtype not in held:
            sim = self.similarity
            held[dtype] = (dtype.type(sim.scale), np.asarray(sim.rotation, dtype=dtype), np.asarray(sim.translation, dtype=dtype))
        return held[dtype]

    def _value_and_grad_by_hand(self, points: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """:meth:`_value_and_grad` with the chain rule written out (:meth:`InferenceDecoder.value_and_input_grad`,
        :func:`interpolate_codes_direct_backward`) in chunks of ``n``; None where those do not apply (a decoder
        :class:`InferenceDecoder` does not support, or the softmax form of the weights)."""
        dec = self._decoder_no_grad(points.dtype, points.device)
        _, pos, codes, direct = self._cached(points.dtype, points.device)
        if direct is None or not isinstance(dec, InferenceDecoder):
            return None
        s, r, t = self._similarity_tensors(points)
        eps = self.config.eps
        values, grads = [], []
        with torch.no_grad():
            for chunk in points.split(n):
                x = s * chunk @ r.T + t
                z, r_codes, total = interpolate_codes_direct_keeping_weights(x, *direct, eps)
                d, grad_z, grad_x = dec.value_and_input_grad(z, x)
                grad_x += interpolate_codes_direct_backward(x, pos[0], codes[0], z, grad_z, r_codes, total, eps)
                values.append(d / s)
                grads.append(grad_x @ r)  # the source frame's gradient: R^T grad_n (the scale cancels)
        return torch.cat(values), torch.cat(grads)

    def value_and_grad(self, points, create_graph: bool = False):
        """Distances (N,) and gradients (N, 3) at points (N, 3), in the source frame.

        ``create_graph=True`` keeps both differentiable (second derivatives, e.g. for a loss on
        the gradient); otherwise they are detached.
        """
        return self._value_and_grad(as_points(points), create_graph)

    def features(self, points_norm) -> torch.Tensor:
        """Code-cloud features at normalised-frame points: (N, 3) -> (N, code_dim).

        Differentiable in the points when they require grad; chunked otherwise.
        """
        p = as_points(points_norm, "points_norm")
        return torch.cat([self._interpolate(c) for c in p.split(chunk_size(self.config.n_codes))])

    def features_and_distances(self, points_norm) -> tuple[torch.Tensor, torch.Tensor]:
        """Code-cloud features (N, code_dim) and signed distances (N,) at normalised-frame points (N, 3).

        One pass: the distance is the decoder on the features, so both cost one distance query
        (what the amortized detector reads at each vertex). No gradients.
        """
        p = as_points(points_norm, "points_norm")
        feats, dists = [], []
        with torch.no_grad():
            dec = self._decoder_no_grad(p.dtype, p.device)
            for c in p.split(chunk_size(self.config.n_codes)):
                z = self._interpolate(c)
                feats.append(z)
                dists.append(dec(z, c))
        return torch.cat(feats), torch.cat(dists)

    def distances_from_features(self, points_norm: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Normalised-frame distances (N,) at points (N, 3) whose features (N, C) are known: the decoder alone."""
        with torch.no_grad():
            dec = self._decoder_no_grad(points_norm.dtype, points_norm.device)
            n = chunk_size(self.config.n_codes)
            return torch.cat([dec(z.to(points_norm), p) for p, z in zip(points_norm.split(n), features.split(n))])

    def detect(self, triangles, polish: bool = True) -> torch.Tensor:
        """Amortized minimum-SDF barycentrics of triangles (M, 3, 3) in the source frame -> (M, 3); see Model.detect."""
        if self.model is None:
            raise InputError(f"shape {self.name!r} is not attached to a model; call model.detect(shape, triangles)")
        return self.model.detect(self, triangles, polish=polish)

    def detect_mesh(self, vertices: torch.Tensor, faces: torch.Tensor, cutoff: float | None = None, known=None,
                    polish: bool = True, vertex_values=None):
        """Contact narrow phase of ``zoo.collide``: minima on the triangles ``vertices[faces]`` (source frame).

        Returns (bary (M, 3), distances (M,) at the returned points). The network's answer is
        compared with each triangle's vertices and the ``known`` point (bary (M, 3), distances
        (M,)), keeping the lowest; with ``cutoff``, triangles proven to stay above it are not
        solved (their distance is then only proven to exceed it). ``polish``: an in-range triangle
        whose lowest vertex passes the vertex test (its gradient there) is answered at that vertex;
        the others' answers take line-search steps (a subdivided triangle's: one, on its lowest piece)
        before that comparison. ``vertex_values`` (V,): distances at ``vertices`` the caller has already
        (NaN where it has none), which are then not queried again. See :func:`zoo.amortized.solve_mesh`.
        """
        if self.model is None:
            raise InputError(f"shape {self.name!r} is not attached to a model; call model.detect(shape, triangles)")
        if getattr(self.model, "detector", None) is None:
            return self.model.detect(self, vertices[faces])  # raises the model's own error
        from .amortized import Known, SolveOptions, solve_mesh

        known = Known(vertex_values=vertex_values) if known is None else Known(*known, vertex_values=vertex_values)
        return solve_mesh(self.model.detector, self, vertices, faces, SolveOptions(cutoff=cutoff, polish=polish), known)

    def scaled(self, factor: float) -> NeuralShape:
        """The same shape ``factor`` times larger, about its frame's origin (a source mesh in other units than
        metres: ``factor`` 0.001 for millimetres). The similarity takes the factor (``p_n = (s / factor) R p + t``),
        so the detector and every query work as on this shape and distances come back ``factor`` times larger."""
        from .meshes import Similarity
        from .validation import positive_float

        factor = positive_float(factor, "scale factor")
        sim = self.similarity
        out = NeuralShape(self.name, self.decoder, self.config, self.codes, self.positions,
                          Similarity(sim.scale / factor, sim.rotation, sim.translation), self.model)
        out._copies = self._copies  # the same decoder and code cloud: share their converted copies
        out.fit, out.metrics = dict(self.fit), dict(self.metrics)
        return out

    def to(self, device) -> NeuralShape:
        """A copy whose tensors live on ``device`` (inputs on other devices are handled too)."""
        import copy

        moved = NeuralShape(self.name, copy.deepcopy(self.decoder).to(device), self.config, self.codes.to(device),
                            self.positions.to(device), self.similarity, self.model)
        moved.fit, moved.metrics = dict(self.fit), dict(self.metrics)
        return moved

    def __repr__(self):
        return f"NeuralShape({self.name!r}, n_codes={self.config.n_codes}, scale={self.similarity.scale:.6g})"
