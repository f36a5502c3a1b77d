"""The code-cloud NeuralSDF, NeuralShape frames, and the Model package round trip."""

from __future__ import annotations

import copy
import dataclasses
import json
import math

import naive_network
import numpy as np
import pytest
import torch

import zoo
from zoo import neural
from zoo.errors import ChecksumError, InputError, ModelNotFoundError
from zoo.meshes import Similarity
from zoo.model import Model, fit_code_cloud
from zoo.neural import NeuralSDF, NeuralSDFConfig, NeuralShape, code_weights, interpolate_codes
from zoo.neural_kernel import _exp_negative, _log1p_unit
from zoo.neural_numpy import SMALL_BATCH, SOFTPLUS_FLOOR

SMALL = NeuralSDFConfig(n_codes=16, code_dim=8, hidden=(16, 16))


def small_model(n_shapes=2, seed=0) -> NeuralSDF:
    torch.manual_seed(seed)
    return NeuralSDF(SMALL, n_shapes, torch.Generator().manual_seed(seed))


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


SIM = Similarity(2.5, rotation_z(0.7), np.array([0.1, -0.2, 0.05]))


def test_weights_are_finite_and_pick_the_code_at_its_position():
    pos = torch.rand(1, 16, 3) - 0.5
    codes = torch.randn(1, 16, 8)
    pts = torch.cat([pos[:, :3], torch.rand(1, 5, 3) - 0.5], dim=1)  # three points exactly on codes
    w = code_weights(pts, pos, eps=1e-16)
    assert torch.isfinite(w).all()
    assert torch.allclose(w.sum(-1), torch.ones(1, 8))
    z = interpolate_codes(pts, pos, codes, eps=1e-16)
    assert torch.allclose(z[0, :3], codes[0, :3], atol=1e-5)


def test_weights_match_inverse_distance_cubed():
    pos = torch.rand(1, 16, 3, dtype=torch.float64) - 0.5
    pts = torch.rand(1, 10, 3, dtype=torch.float64) - 0.5
    d2 = ((pts[0, :, None] - pos[0, None]) ** 2).sum(-1)
    w = d2 ** -1.5
    w = w / w.sum(-1, keepdim=True)
    assert torch.allclose(code_weights(pts, pos, eps=1e-16)[0], w, rtol=1e-6)


def test_batched_forward_matches_each_shape():
    m = small_model(3)
    pts = torch.rand(3, 50, 3) - 0.5
    d = m(pts, torch.arange(3))
    for i in range(3):
        s = NeuralShape(f"s{i}", m.decoder, SMALL, m.codes[i], m.positions[i])
        assert torch.allclose(s(pts[i]), d[i].detach(), atol=1e-6)


def test_source_frame_scales_distances_and_rotates_gradients():
    m = small_model(1)
    src = NeuralShape("a", m.decoder, SMALL, m.codes[0], m.positions[0], SIM)
    p = torch.rand(64, 3, dtype=torch.float64) * 0.3
    d, g = src.value_and_grad(p)
    pn = torch.as_tensor(SIM.to_normalised(p.numpy()))
    dn, gn = src.normalised.value_and_grad(pn)
    assert torch.allclose(d, dn / SIM.scale, atol=1e-10)
    assert torch.allclose(g, gn @ torch.as_tensor(SIM.rotation), atol=1e-10)
    # finite differences in the source frame
    h = 1e-6
    for axis in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[axis] = h
        fd = (src(p + e) - src(p - e)) / (2 * h)
        assert torch.allclose(fd, g[:, axis], atol=1e-5)


@pytest.mark.parametrize("smooth_beta,fourier_levels", [(0.0, 0), (100.0, 0), (100.0, 5)], ids=["leaky", "smooth", "fourier"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_value_and_grad_by_hand_matches_autograd(smooth_beta, fourier_levels, dtype):
    """The chain rule written out (InferenceDecoder.value_and_input_grad, interpolate_codes_direct_backward,
    fourier_backward) gives autograd's values and gradients through the same forward pass, points on code positions
    included."""
    config = dataclasses.replace(SMALL, hidden=(32, 32, 32), smooth_beta=smooth_beta, fourier_levels=fourier_levels)
    torch.manual_seed(3)
    m = NeuralSDF(config, 1, torch.Generator().manual_seed(3))
    with torch.no_grad():
        m.codes.normal_(0.0, 0.3)  # features that matter: the interpolation's gradient is not negligible
    shape = NeuralShape("a", m.decoder, config, m.codes[0], m.positions[0], SIM)
    p = (torch.rand(500, 3, dtype=torch.float64) - 0.5) * 0.5
    p[:3] = torch.as_tensor(SIM.to_source(m.positions[0, :3].detach().double().numpy()))  # exactly on codes
    p = p.to(dtype)
    d, g = shape.value_and_grad(p)
    assert shape._value_and_grad_by_hand(p, 1024) is not None  # the hand-written path is the one taken
    x = p.clone().requires_grad_(True)
    with torch.enable_grad():
        (ref_g,) = torch.autograd.grad(shape(x).sum(), x)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert d.dtype == g.dtype == dtype
    assert torch.allclose(d, shape(p), atol=tol, rtol=0)
    assert torch.allclose(g[3:], ref_g[3:], atol=tol * float(ref_g.abs().max()), rtol=0)
    assert torch.isfinite(g[:3]).all()


@pytest.mark.parametrize("smooth_beta,fourier_levels", [(0.0, 0), (100.0, 0), (100.0, 5)], ids=["leaky", "smooth", "fourier"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_compiled_network_for_a_few_points_matches_autograd(smooth_beta, fourier_levels, dtype):
    """A few points (at most SMALL_BATCH, as a simulation step asks) take zoo.neural_numpy's path (the compiled
    network); its values and gradients are autograd's through the torch forward pass, points on code positions
    included."""
    config = dataclasses.replace(SMALL, hidden=(32, 32, 32), smooth_beta=smooth_beta, fourier_levels=fourier_levels)
    torch.manual_seed(4)
    m = NeuralSDF(config, 1, torch.Generator().manual_seed(4))
    with torch.no_grad():
        m.codes.normal_(0.0, 0.3)
    shape = NeuralShape("a", m.decoder, config, m.codes[0], m.positions[0], SIM)
    p = (torch.rand(SMALL_BATCH, 3, dtype=torch.float64) - 0.5) * 0.5
    p[:3] = torch.as_tensor(SIM.to_source(m.positions[0, :3].detach().double().numpy()))  # exactly on codes
    p = p.to(dtype)
    assert shape._numpy_network(dtype) is not None  # the compiled path is the one taken
    for n in (1, 2, 3, 7, SMALL_BATCH):
        d, g = shape.value_and_grad(p[:n])
        x = p[:n].clone().requires_grad_(True)
        with torch.enable_grad():
            (ref_g,) = torch.autograd.grad(shape(x).sum(), x)
        # float64: the chain rule by hand sums in another order than autograd; over 512 points the worst gradient
        # differs by 1.2e-9 of the largest
        tol = 1e-4 if dtype == torch.float32 else 2e-9
        assert d.dtype == g.dtype == dtype and d.shape == (n,) and g.shape == (n, 3)
        assert torch.allclose(d, shape(p[:n]), atol=tol, rtol=0)
        assert torch.allclose(g[3:], ref_g[3:], atol=tol * float(ref_g.abs().max()), rtol=0)
        assert torch.isfinite(g).all()
        few = shape.value_and_grad_few(p[:n].double().numpy(), dtype)  # numpy in, numpy out: the same answers
        assert few[0].dtype == few[1].dtype == p.numpy().dtype
        assert np.array_equal(few[0], d.numpy()) and np.array_equal(few[1], g.numpy())
    assert shape.value_and_grad_few(np.zeros((SMALL_BATCH + 1, 3)), dtype) is None  # too many: the caller's torch path


@pytest.mark.parametrize("smooth_beta,fourier_levels", [(0.0, 0), (100.0, 0), (100.0, 5)], ids=["leaky", "smooth", "fourier"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_network_is_the_numpy_network(smooth_beta, fourier_levels, dtype):
    """zoo.neural_kernel's compiled call against NumpyNetwork's numpy operations at the same 1 to 5 points, and at all
    of them at once (on code positions, near them, far out, and where the activations saturate): the same values and
    gradients up to the dtype's rounding (float32: exp and log1p by series, sums in another order); and at
    source-frame points, the similarity applied and undone in the call, numpy's answers through the same
    similarity."""
    config = dataclasses.replace(SMALL, hidden=(64, 64, 64), smooth_beta=smooth_beta, fourier_levels=fourier_levels)
    m = NeuralSDF(config, 1, torch.Generator().manual_seed(5))
    with torch.no_grad():
        m.codes.normal_(0.0, 0.3)
    shape = NeuralShape("a", m.decoder, config, m.codes[0], m.positions[0], SIM)
    net = shape._numpy_network(torch.float32 if dtype == np.float32 else torch.float64)
    rng = np.random.default_rng(6)
    points = np.concatenate([m.positions[0, :2].detach().numpy() + [[0, 0, 0], [1e-5, 0, 0]],
                             rng.uniform(-0.6, 0.6, (30, 3)), rng.uniform(-3, 3, (4, 3))]).astype(dtype)
    tol = 2e-5 if dtype == np.float32 else 1e-9  # float64: a point 1e-5 from a code sums terms of 1e25
    identity = (dtype(1.0), np.eye(3, dtype=dtype), np.zeros(3, dtype=dtype))
    turn = np.radians(30.0)
    similarity = (dtype(0.8), np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]],
                                       dtype=dtype), np.array([0.1, -0.2, 0.05], dtype=dtype))
    for start in range(len(points) + 1):
        x = points[start:start + 1 + start % 5] if start < len(points) else points
        values, grads = net.value_and_grad(x.astype(np.float64), *identity)
        ref_values, ref_grads = naive_network.value_and_grad(net, x)
        assert values.dtype == grads.dtype == dtype and values.shape == (len(x),) and grads.shape == (len(x), 3)
        scale = 1.0 + np.abs(ref_values).max()
        np.testing.assert_allclose(values, ref_values, rtol=0, atol=tol * scale)
        np.testing.assert_allclose(grads, ref_grads, rtol=0, atol=tol * (1.0 + np.abs(ref_grads).max()))
        if start >= 2:  # source-frame points, away from the codes: the call applies the similarity and undoes it
            s, r, t = similarity
            source = np.random.default_rng(start).uniform(-0.6, 0.6, (len(x), 3))
            values, grads = net.value_and_grad(source, s, r, t)
            ref_values, ref_grads = naive_network.value_and_grad(net, s * source.astype(dtype) @ r.T + t)
            ref_values, ref_grads = ref_values / s, ref_grads @ r
            np.testing.assert_allclose(values, ref_values, rtol=0, atol=tol * (1.0 + np.abs(ref_values).max()))
            np.testing.assert_allclose(grads, ref_grads, rtol=0, atol=tol * (1.0 + np.abs(ref_grads).max()))


def test_float32_exp_and_log1p_by_series_are_numpys_to_float32_rounding():
    """The compiled network's float32 exp(-a) (a in [0, the softplus floor]) and log(1 + e) (e in [0, 1]), series with
    no libm call, against numpy's in float64 on a dense grid: within 2e-7 of the answer (float32's rounding is 6e-8)."""
    a = np.linspace(0.0, SOFTPLUS_FLOOR, 400_001).astype(np.float32)
    by_series = a.copy()
    _exp_negative(by_series, np.empty(by_series.size, np.int32))
    exact = np.exp(-a.astype(np.float64))
    assert np.abs(by_series / exact - 1.0).max() < 2e-7
    e = np.linspace(0.0, 1.0, 100_001).astype(np.float32)
    by_series = np.array([_log1p_unit(v) for v in e[::97]] + [_log1p_unit(e[-1])], dtype=np.float32)
    exact = np.log1p(np.concatenate([e[::97], e[-1:]]).astype(np.float64))
    assert np.abs(by_series - exact).max() < 2e-7 * exact.max() and by_series[0] == 0.0


def test_dtypes_are_kept_and_bad_input_rejected():
    m = small_model(1)
    s = NeuralShape("a", m.decoder, SMALL, m.codes[0], m.positions[0], SIM)
    assert s(torch.zeros(4, 3)).dtype == torch.float32
    assert s(torch.zeros(4, 3, dtype=torch.float64)).dtype == torch.float64
    with pytest.raises(InputError):
        s(torch.zeros(4, 2))
    with pytest.raises(InputError):
        s(torch.full((2, 3), float("nan")))


def test_large_inputs_are_chunked(monkeypatch):
    m = small_model(1)
    s = NeuralShape("a", m.decoder, SMALL, m.codes[0], m.positions[0], SIM)
    p = torch.rand(3000, 3) - 0.5
    whole, whole_g = s(p), s.value_and_grad(p)[1]
    monkeypatch.setattr(neural, "_CHUNK_ELEMENTS", 16 * 100)  # force chunks of 1024 points
    assert neural.chunk_size(16) == 1024
    assert torch.allclose(s(p), whole, atol=1e-6)
    assert torch.allclose(s.value_and_grad(p)[1], whole_g, atol=1e-6)


def test_features_and_differentiable_call():
    m = small_model(1)
    s = NeuralShape("a", m.decoder, SMALL, m.codes[0], m.positions[0], SIM)
    assert s.features(torch.rand(10, 3) - 0.5).shape == (10, 8)
    p = torch.rand(5, 3, requires_grad=True)
    s(p).sum().backward()  # the graph is kept when the caller asks for it
    assert p.grad is not None and torch.isfinite(p.grad).all()
    assert isinstance(s, zoo.sdf.SDFBase) and len(s.bounds) == 2


def make_model(tmp_path=None) -> Model:
    sdf = small_model(2)
    return Model("toys", "0.0.1", sdf, ["toy_a", "toy_b"], {"toy_a": SIM, "toy_b": Similarity.identity()},
                 {"category": "toys"})


@pytest.mark.parametrize("fp16", [False, True])
def test_package_round_trip(tmp_path, fp16):
    model = make_model()
    out = model.save(tmp_path / "pkg", fp16=fp16, metrics={"near_p50": 0.004}, license="MIT")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["SHA256SUMS", "config.json", "sdf.safetensors"]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["format_version"] == 1 and cfg["shapes"] == ["toy_a", "toy_b"] and cfg["detector"] is None
    loaded = Model.from_directory(out)
    assert (loaded.name, loaded.version, loaded.shapes) == ("toys", "0.0.1", ["toy_a", "toy_b"])
    assert loaded.sdf.codes.dtype == torch.float32
    p = torch.rand(100, 3) * 0.2
    tol = 1e-3 if fp16 else 1e-6
    assert torch.allclose(loaded.shape("toy_a")(p), model.shape("toy_a")(p), atol=tol)
    assert loaded.shape("toy_a").similarity == SIM
    assert zoo.load(out).shapes == ["toy_a", "toy_b"]


def test_unknown_shape_missing_detector_and_corruption(tmp_path):
    model = make_model()
    out = model.save(tmp_path / "pkg")
    with pytest.raises(ModelNotFoundError, match="toy_a"):
        model.shape("nope")
    with pytest.raises(ModelNotFoundError, match="no detector"):
        model.detect(model.shape("toy_a"), torch.rand(2, 3, 3))
    data = bytearray((out / "sdf.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (out / "sdf.safetensors").write_bytes(bytes(data))
    with pytest.raises(ChecksumError):
        Model.from_directory(out)


def test_fit_code_cloud_recovers_a_shape_of_the_model():
    """Samples drawn from shape 0 of a model; a fresh cloud with the decoder frozen fits them."""
    torch.manual_seed(0)
    m = small_model(1)
    pts = torch.rand(4000, 3) - 0.5
    with torch.no_grad():
        target = m(pts.unsqueeze(0), torch.tensor([0]))[0]
    fresh = NeuralShape("f", m.decoder, SMALL, *neural.init_code_cloud(SMALL, 1, torch.Generator().manual_seed(5)))
    fresh = NeuralShape("f", m.decoder, SMALL, fresh.codes[0], fresh.positions[0])
    before = (fresh(pts) - target).abs().mean()
    codes, positions = fit_code_cloud(m, pts, target, iters=60, points_per_iter=256)
    after = (NeuralShape("f", m.decoder, SMALL, codes, positions)(pts) - target).abs().mean()
    assert after < 0.5 * before
    assert all(p.requires_grad for p in m.decoder.parameters())  # restored after fitting


# --------------------------------------------------------------------------- the smooth activation


@pytest.mark.parametrize("slope", [0.0, 0.02])
def test_smooth_activation_tends_to_leaky_relu_within_its_bound(slope):
    x = torch.linspace(-3, 3, 20001, dtype=torch.float64)
    leaky = torch.nn.functional.leaky_relu(x, slope)
    for beta in (10.0, 100.0, 1000.0):
        gap = (neural.activation(x, slope, beta) - leaky).abs().max()
        assert gap <= (1 - slope) * np.log(2) / beta + 1e-12  # the largest gap is at 0
        assert gap >= 0.99 * (1 - slope) * np.log(2) / beta
    assert torch.equal(neural.activation(x, slope, 0.0), leaky)
    y = x.clone()
    torch.testing.assert_close(neural.activation(y, slope, 100.0, inplace=True), neural.activation(x, slope, 100.0),
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_floored_softplus_is_the_activation_without_denormals(dtype):
    """The activation with its softplus floored (torch's and the numpy network's) against slope x + (1 - slope)
    softplus_beta(x) with torch's softplus unfloored: the same numbers where beta x is above the floor, within the
    dtype's rounding of the terms below it (the slope's term hides the softplus there), and no denormal float in the
    floored softplus's exponential (the floor's reason: CPUs are slow on them) where the unfloored one has many."""
    from zoo.neural_numpy import SOFTPLUS_FLOOR, NumpyNetwork

    slope, beta = 0.01, 100.0
    x = torch.linspace(-3, 3, 60001, dtype=dtype)
    unfloored = slope * x + (1 - slope) * torch.nn.functional.softplus(x, beta=beta)
    rounding = 4 * torch.finfo(dtype).eps * (x.abs() + 1 / beta)  # the terms summed are at most this large
    floored = neural.activation(x, slope, beta)
    above = beta * x >= -SOFTPLUS_FLOOR
    assert torch.equal(floored[above], unfloored[above])
    assert ((floored - unfloored).abs() <= rounding).all()
    net = NumpyNetwork(weights=[np.zeros((1, 1))], out_weight=np.zeros((1, 1)), out_bias=np.zeros(1),
                       cloud_b=np.zeros((1, 5)), codes_1=np.zeros((1, 2)), positions=np.zeros((1, 3)),
                       codes=np.zeros((1, 1)), eps=1e-8, negative_slope=slope, smooth_beta=beta, fourier_levels=0,
                       dtype=np.float32 if dtype == torch.float32 else np.float64)
    assert (np.abs(naive_network.activation_and_slope(net, x.numpy())[0] - unfloored.numpy()) <= rounding.numpy()).all()
    tiny = torch.finfo(dtype).tiny
    denormal = lambda t: int(((t > 0) & (t < tiny)).sum())  # noqa: E731
    assert denormal(torch.exp(beta * x.clamp(min=-SOFTPLUS_FLOOR / beta))) == 0
    if dtype == torch.float32:
        assert denormal(torch.exp(beta * x)) > 1000


def _gradient_jumps(config: NeuralSDFConfig) -> float:
    """Largest change of the decoder's gradient between neighbouring points 1.3e-4 apart along a line."""
    torch.manual_seed(0)
    sdf = NeuralSDF(config, 1, torch.Generator().manual_seed(0)).double()
    t = torch.linspace(-0.4, 0.4, 8001, dtype=torch.float64)
    p = (torch.stack([t, 0.3 * t + 0.05, -0.7 * t], -1)).unsqueeze(0).requires_grad_(True)
    (g,) = torch.autograd.grad(sdf(p, torch.zeros(1, dtype=torch.long)).sum(), p)
    # neighbours 1e-4 apart; a kink makes the gradient jump by O(|W|) whatever the spacing
    return float((g[0, 1:] - g[0, :-1]).norm(dim=-1).max() / (t[1] - t[0]))


def test_smooth_decoder_has_a_continuous_gradient_and_leaky_relu_does_not():
    """Equation (12)'s gap vanishes at a minimiser only if the gradient is continuous there: with
    LeakyReLU it jumps at every kink; with smooth_beta its change is bounded by the spacing."""
    leaky = _gradient_jumps(dataclasses.replace(SMALL, hidden=(64, 64)))
    smooth = _gradient_jumps(dataclasses.replace(SMALL, hidden=(64, 64), smooth_beta=100.0))
    assert smooth < 0.1 * leaky


def test_fourier_features_are_the_decoders_input_and_round_trip():
    """fourier_levels L adds sin and cos of 2^k pi x (k < L) per coordinate to the decoder's input: 6 L more inputs,
    exact values at known points, validated, kept through a config round trip and absent (0) from old configs."""
    c = dataclasses.replace(SMALL, fourier_levels=3)
    assert NeuralSDFConfig.from_dict(c.to_dict()) == c
    assert NeuralSDFConfig.from_dict({k: v for k, v in SMALL.to_dict().items() if k != "fourier_levels"}).fourier_levels == 0
    with pytest.raises(InputError, match="fourier_levels"):
        NeuralSDFConfig(fourier_levels=-1)
    assert neural.Decoder(c).hidden[0].in_features == SMALL.code_dim + 3 + 18
    x = torch.tensor([[0.25, 0.5, -0.125]], dtype=torch.float64)
    f = neural.fourier_features(x, 3).reshape(3, 6)
    expected = torch.tensor([[math.sin(math.pi * 2**k * v) for k in range(3)] + [math.cos(math.pi * 2**k * v) for k in range(3)]
                             for v in (0.25, 0.5, -0.125)], dtype=torch.float64)
    torch.testing.assert_close(f, expected, atol=1e-12, rtol=0)
    m = NeuralSDF(c, 2, torch.Generator().manual_seed(0))
    assert m(torch.rand(2, 5, 3), torch.tensor([0, 1])).shape == (2, 5)


def test_smooth_beta_is_validated_and_round_trips():
    with pytest.raises(InputError, match="smooth_beta"):
        NeuralSDFConfig(smooth_beta=-1.0)
    c = dataclasses.replace(SMALL, smooth_beta=100.0)
    assert NeuralSDFConfig.from_dict(c.to_dict()) == c
    assert NeuralSDFConfig.from_dict({k: v for k, v in SMALL.to_dict().items() if k != "smooth_beta"}).smooth_beta == 0.0


def test_shapes_of_one_model_share_one_converted_decoder():
    """A float64 query converts the decoder once per model, not once per shape (thousands of shapes)."""
    sdf = NeuralSDF(NeuralSDFConfig(n_codes=8, code_dim=8, hidden=(16, 16)), 3, torch.Generator().manual_seed(0))
    a, b = (NeuralShape(f"s{i}", sdf.decoder, sdf.config, sdf.codes[i], sdf.positions[i]) for i in (0, 1))
    points = torch.rand(5, 3, dtype=torch.float64) - 0.5
    a(points), b(points)
    assert a._cached(torch.float64, torch.device("cpu"))[0] is b._cached(torch.float64, torch.device("cpu"))[0]
    with torch.no_grad():  # the shared copy answers as a copy of each shape's own would
        own = copy.deepcopy(sdf.decoder).double()
        expected = own(interpolate_codes(points.unsqueeze(0), sdf.positions[1:2].double(), sdf.codes[1:2].double(),
                                         sdf.config.eps).squeeze(0), points)
    assert torch.allclose(b(points), expected, atol=1e-12)
