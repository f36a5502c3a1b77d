"""The dynamic code cloud NeuralSDF (DCC-DIF) and one fitted shape of it.

A category model is one shared decoder MLP plus, per shape, a *code cloud*: ``n_codes`` latent
codes ``c_j`` (``code_dim`` numbers each) sitting at learned positions ``x_j`` in the
normalised frame. The feature of a point is the inverse-distance-cubed interpolation

    z(x) = sum_j w_j c_j,   w_j = (|x - x_j|^2 + eps)^(-3/2) / sum_k (|x - x_k|^2 + eps)^(-3/2)

and the signed distance (normalised frame) is ``decoder([z(x); x])``.

The weights are computed as a softmax of log-weights ``-1.5 log(d2 + eps)``: that is exact,
never divides by zero at a code position (the code's weight tends to one there) and never
overflows, whatever ``eps``.

:class:`NeuralSDF` is the trainable category module (decoder + all code clouds);
:class:`NeuralShape` is one shape of it as an SDF in its source mesh's frame and units.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from torch import nn

from .errors import InputError
from .geometry import as_points
from .sdf import SDFBase

# Queries are evaluated in chunks so that the (chunk, n_codes) weight matrix stays around
# 16M floats (64 MB in float32), whatever the number of points.
_CHUNK_ELEMENTS = 1 << 24


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class NeuralSDFConfig:
    """Sizes of a code-cloud NeuralSDF; stored as ``config.json["sdf"]`` in a package."""

    n_codes: int = 256
    code_dim: int = 32
    hidden: tuple[int, ...] = (256, 256, 256)
    skip_input: bool = True  # re-concatenate [z; x] before every hidden layer (DCC-DIF)
    negative_slope: float = 0.02  # LeakyReLU, as DCC-DIF
    eps: float = 1e-16  # the paper's softening of 1/d^3
    position_init: float = 0.5  # positions start uniform in [-position_init, position_init]^3
    code_init_std: float = 0.01

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if self.n_codes < 1 or self.code_dim < 1 or not self.hidden or min(self.hidden) < 1:
            raise InputError(f"n_codes, code_dim and every hidden size must be positive, got {self}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "NeuralSDFConfig":
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known - {"type", "n_params", "storage_dtype"}  # descriptive keys
        if unknown:
            raise InputError(f"unknown NeuralSDF config keys {sorted(unknown)}; this package needs a newer sdfzoo")
        return cls(**{k: v for k, v in d.items() if k in known})


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


def chunk_size(n_codes: int) -> int:
    """Points per chunk such that a (chunk, n_codes) matrix stays near ``_CHUNK_ELEMENTS``."""
    return max(1024, _CHUNK_ELEMENTS // max(1, n_codes))


# --------------------------------------------------------------------------- the decoder


class Decoder(nn.Module):
    """MLP on [z; x] -> signed distance; ``skip_input`` re-feeds [z; x] to every hidden layer.

    forward: features (..., C), points (..., 3) -> (...,).
    """

    def __init__(self, config: NeuralSDFConfig):
        super().__init__()
        n_in = config.code_dim + 3
        self.skip_input = config.skip_input
        self.negative_slope = config.negative_slope
        layers, width = [], 0
        for i, h in enumerate(config.hidden):
            fan_in = n_in if i == 0 else (width + n_in if self.skip_input else width)
            layers.append(nn.Linear(fan_in, h))
            width = h
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(width, 1)

    def forward(self, features: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        inp = torch.cat([features, points], dim=-1)
        h = inp
        for i, layer in enumerate(self.hidden):
            if i and self.skip_input:
                h = torch.cat([h, inp], dim=-1)
            h = nn.functional.leaky_relu(layer(h), self.negative_slope)
        return self.out(h).squeeze(-1)


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
        self._copies: dict = {}
        self.bounds = self._source_bounds()

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
    def normalised(self) -> "NeuralShape":
        """The same shape answering in the normalised frame (unit cube, scale 1)."""
        return NeuralShape(self.name, self.decoder, self.config, self.codes, self.positions, None, self.model)

    # ---- evaluation

    def _network(self, dtype: torch.dtype, device: torch.device):
        """(decoder, positions (1, K, 3), codes (1, K, C)) in ``dtype`` on ``device``, cached."""
        key = (dtype, str(device))
        if key not in self._copies:
            import copy

            param = next(self.decoder.parameters())
            same = param.dtype == dtype and param.device == torch.device(device)
            # a converted copy only where needed: float64 input is evaluated in float64
            dec = self.decoder if same else copy.deepcopy(self.decoder).to(device=device, dtype=dtype).requires_grad_(False)
            self._copies[key] = (
                dec,
                self.positions.to(device=device, dtype=dtype).unsqueeze(0),
                self.codes.to(device=device, dtype=dtype).unsqueeze(0),
            )
        return self._copies[key]

    def _normalised_distance(self, points_n: torch.Tensor) -> torch.Tensor:
        """Distance in the normalised frame of one chunk: (P, 3) -> (P,), differentiable in the points."""
        dec, pos, codes = self._network(points_n.dtype, points_n.device)
        return decode(dec, points_n.unsqueeze(0), pos, codes, self.config.eps).squeeze(0)

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
        values, grads = [], []
        for chunk in points.split(n):
            with torch.enable_grad():
                x = chunk if (create_graph and chunk.requires_grad) else chunk.detach().requires_grad_(True)
                d = self._source_distance(x)
                (g,) = torch.autograd.grad(d.sum(), x, create_graph=create_graph)
            values.append(d if create_graph else d.detach())
            grads.append(g if create_graph else g.detach())
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
        _, pos, codes = self._network(p.dtype, p.device)
        parts = [interpolate_codes(c.unsqueeze(0), pos, codes, self.config.eps).squeeze(0)
                 for c in p.split(chunk_size(self.config.n_codes))]
        return torch.cat(parts)

    def detect(self, triangles) -> torch.Tensor:
        """Amortized minimum-SDF barycentrics of triangles (M, 3, 3) in the source frame -> (M, 3)."""
        if self.model is None:
            raise InputError(f"shape {self.name!r} is not attached to a model; call model.detect(shape, triangles)")
        return self.model.detect(self, triangles)

    def to(self, device) -> "NeuralShape":
        """A copy whose tensors live on ``device`` (inputs on other devices are handled too)."""
        import copy

        return NeuralShape(self.name, copy.deepcopy(self.decoder).to(device), self.config, self.codes.to(device),
                           self.positions.to(device), self.similarity, self.model)

    def __repr__(self):
        return f"NeuralShape({self.name!r}, n_codes={self.config.n_codes}, scale={self.similarity.scale:.6g})"
