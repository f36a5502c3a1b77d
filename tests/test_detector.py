"""The amortized detector against slow, obviously-correct references.

Stand-in for a fitted NeuralShape: an analytic torus (exact SDF) with a fixed random code
cloud for the vertex features, in a frame that a known similarity maps to the normalised one.
"""

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import zoo
from sdfzoo.pipeline.train_detector import (
    TrainConfig,
    TrainingData,
    detector_losses,
    load_detector,
    midpoint_curvatures,
    save_detector,
    train,
)
from sdfzoo.pipeline.triangle_sampling import sample_constrained_triangles
from zoo.amortized import detect, subdivision_barycentrics
from zoo.detector import AmortizedDetector, quadratic_argmin, quadratic_minimum
from zoo.errors import InputError
from zoo.geometry import bary_to_points, barycentric_grid, perimeter
from zoo.meshes import Similarity
from zoo.neural import interpolate_codes
from zoo.solvers import optimality, reference

MODES = ("condition", "context", "temperature", "additive", "none")


class StandInShape:
    """Torus SDF + fixed random code cloud, the interface detect() uses of a NeuralShape."""

    def __init__(self, similarity=None, n_codes=64, dim=32, seed=0):
        g = torch.Generator().manual_seed(seed)
        self.normalised = zoo.Torus(0.3, 0.06)
        self.positions = torch.rand(1, n_codes, 3, generator=g) - 0.5
        self.codes = torch.randn(1, n_codes, dim, generator=g)
        self.similarity = similarity

    def features(self, points_norm):
        p = torch.as_tensor(points_norm).float()
        return interpolate_codes(p.unsqueeze(0), self.positions, self.codes, 1e-16).squeeze(0)

    def source_sdf(self):
        """The same torus in the source frame (for references): f_src(x) = f_n(S x) / s."""
        sim, f = self.similarity, self.normalised

        class Src(zoo.SDFBase):
            bounds = (torch.full((3,), -10.0), torch.full((3,), 10.0))

            def _distance(self, x):
                m = torch.as_tensor(sim.matrix, dtype=x.dtype)
                return f(x @ m[:3, :3].T + m[:3, 3]) / sim.scale

        return Src()


def random_inputs(m=64, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    tri = (torch.rand(m, 3, 3, generator=g, dtype=torch.float64) - 0.5).to(dtype)
    feat = torch.randn(m, 3, 32, generator=g, dtype=torch.float64).to(dtype)
    return tri, feat


def features_of(shape, tri):
    return shape.features(tri.reshape(-1, 3)).reshape(tri.shape[0], 3, -1)


@pytest.fixture(scope="module")
def torus_data():
    shape = StandInShape()
    tri = sample_constrained_triangles(shape.normalised, 3072, seed=1, batch=8192)
    return shape, tri, features_of(shape, tri)


@pytest.fixture(scope="module")
def trained(torus_data):
    torch.set_num_threads(1)
    shape, tri, feat = torus_data
    vsdf = vertex_sdf_of(shape.normalised, tri[:2560])
    data = TrainingData(tri[:2560], feat[:2560], torch.zeros(2560, dtype=torch.long), [shape.normalised], vsdf)
    # the variant that also reads f at the vertices: random stand-in features carry no shape, and
    # a feature-only detector needs far more than a test's few seconds to learn the torus
    detector_config = {**AmortizedDetector().config(), "vertex_sdf": True}
    config = TrainConfig(steps=400, batch_size=512, lr=1e-2, validate_every=400, checkpoint_every=400, validation_size=256,
                         detector=detector_config)
    detector, _ = train(data, config, progress=False)
    return detector.eval()


def vertex_sdf_of(sdf, tri):
    return sdf(tri.reshape(-1, 3)).reshape(-1, 3)


# --------------------------------------------------------------------------- structure


@pytest.mark.parametrize("mode", MODES)
def test_every_vertex_order_gives_the_same_point(mode):
    torch.manual_seed(0)
    det = AmortizedDetector(triangle_feature=mode)
    tri, feat = random_inputs()
    with torch.no_grad():
        p0 = bary_to_points(tri, det(tri, feat))
        for perm in itertools.permutations(range(3)):
            bary = det(tri[:, perm], feat[:, perm])
            assert torch.allclose(bary_to_points(tri[:, perm], bary), p0, atol=1e-6), perm


@pytest.mark.parametrize("output", ["sparsemax", "grid", "quadratic"])
def test_other_outputs_are_order_invariant_and_on_the_simplex(output):
    torch.manual_seed(1)
    det = AmortizedDetector(output=output, vertex_sdf=True)
    tri, feat = random_inputs(m=50, seed=4)
    vsdf = tri.norm(dim=-1) - 0.3
    with torch.no_grad():
        b = det(tri, feat * 20, vsdf)
        assert (b >= 0).all() and torch.allclose(b.sum(-1), torch.ones(50), atol=1e-5)
        p0 = bary_to_points(tri, b)
        for perm in itertools.permutations(range(3)):
            p = bary_to_points(tri[:, perm], det(tri[:, perm], feat[:, perm] * 20, vsdf[:, perm]))
            assert torch.allclose(p, p0, atol=1e-5), perm
    with pytest.raises(InputError, match="vertex_sdf"):
        det(tri, feat)


@pytest.mark.parametrize("mode", MODES)
def test_output_lies_on_the_simplex(mode):
    det = AmortizedDetector(triangle_feature=mode, vertex_features=(mode != "none"))
    tri, feat = random_inputs(m=200, seed=3)
    with torch.no_grad():
        b = det(tri, feat * 50)  # large features: logits far apart
    assert (b >= 0).all() and torch.allclose(b.sum(-1), torch.ones(200), atol=1e-6)


def answers_before_and_after_changing_z_tri(mode: str, change):
    """The detector's answers on random inputs, then again with z_tri replaced by ``change(z_tri)``."""
    torch.manual_seed(0)
    det = AmortizedDetector(triangle_feature=mode)
    tri, feat = random_inputs()
    with torch.no_grad():
        before = det(tri, feat)
        original = det.triangle_feature_vector
        det.triangle_feature_vector = lambda z, off: change(original(z, off))
        after = det(tri, feat)
    return before, after


def test_triangle_feature_changes_the_answer_when_conditioned():
    before, after = answers_before_and_after_changing_z_tri("condition", lambda z_tri: z_tri + 1.0)
    assert (after - before).abs().max() > 1e-3


def test_paper_equation_8_as_printed_ignores_the_triangle_feature():
    before, after = answers_before_and_after_changing_z_tri("additive", lambda z_tri: z_tri + torch.randn_like(z_tri) * 10)
    assert torch.allclose(after, before, atol=1e-6)


def test_config_round_trip_and_files(tmp_path):
    det = AmortizedDetector(triangle_feature="temperature", hidden=16)
    again = AmortizedDetector.from_config(det.config())
    again.load_state_dict(det.state_dict())
    tri, feat = random_inputs()
    with torch.no_grad():
        assert torch.equal(det(tri, feat), again(tri, feat))
    save_detector(tmp_path, det)
    loaded = load_detector(tmp_path)
    with torch.no_grad():
        assert torch.equal(det(tri, feat), loaded(tri, feat))
    with pytest.raises(InputError, match="unknown detector config"):
        AmortizedDetector.from_config({**det.config(), "bogus": 1})
    with pytest.raises(InputError, match="triangle_feature"):
        AmortizedDetector(triangle_feature="sum")


def test_degenerate_triangles_give_finite_answers():
    det = AmortizedDetector()
    shape = StandInShape()
    p = torch.tensor([0.3, 0.1, 0.1])
    tri = torch.stack([
        p.expand(3, 3),  # a point
        torch.stack([p, p + 0.01, p + 0.02]),  # collinear
        torch.stack([p, p, p + torch.tensor([0.05, 0.0, 0.0])]),  # two vertices equal
    ])
    b = detect(det, shape, tri)
    assert torch.isfinite(b).all() and torch.allclose(b.sum(-1), torch.ones(3))


def test_bad_features_shape_is_a_typed_error():
    det = AmortizedDetector()
    tri, feat = random_inputs()
    with pytest.raises(InputError, match="features must have shape"):
        det(tri, feat[..., :16])


# --------------------------------------------------------------------------- loss


def test_optimality_loss_is_equation_12_times_perimeter(torus_data):
    shape, tri, _ = torus_data
    tri = tri[:300].double()
    bary = torch.distributions.Dirichlet(torch.ones(3, dtype=torch.float64)).sample((300,))
    l_op, l_min = detector_losses(shape.normalised, tri, bary, create_graph=False)
    assert torch.allclose(l_op, optimality(shape.normalised, tri, bary) * perimeter(tri), atol=1e-12)
    # and by hand: g . p - min over the three vertices of g . v
    p = bary_to_points(tri, bary)
    f, g = shape.normalised.value_and_grad(p)
    by_hand = torch.tensor([float(g[m] @ p[m] - min(g[m] @ tri[m, i] for i in range(3))) for m in range(300)],
                           dtype=torch.float64)
    assert torch.allclose(l_op, by_hand, atol=1e-12)
    assert torch.allclose(l_min, f.clamp_min(0))


def test_optimality_loss_reaches_the_detector_through_the_sdf_gradient(torus_data):
    shape, tri, feat = torus_data
    det = AmortizedDetector()
    bary = det(tri[:64], feat[:64])
    l_op, _ = detector_losses(shape.normalised, tri[:64], bary, create_graph=True)
    l_op.mean().backward()
    grads = [p.grad for p in det.h_psi1.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.abs().max() > 0 for g in grads)


# --------------------------------------------------------------------------- training and use


# --------------------------------------------------------------------------- the quadratic head


def brute_force_quadratic_min(values, curvature, n=240):
    """min over an n-step barycentric grid of q(l) = sum l_i f_i - sum_k l_i l_j kappa_k: (M,)."""
    grid = barycentric_grid(n, values.dtype)
    g0, g1, g2 = grid.unbind(-1)
    q = values @ grid.T - curvature[:, :1] * (g1 * g2) - curvature[:, 1:2] * (g2 * g0) - curvature[:, 2:] * (g0 * g1)
    return q.min(dim=1).values


def quadratic_value(bary, values, curvature):
    l0, l1, l2 = bary.unbind(-1)
    k0, k1, k2 = curvature.unbind(-1)
    return (bary * values).sum(-1) - l1 * l2 * k0 - l2 * l0 * k1 - l0 * l1 * k2


def test_quadratic_argmin_is_the_minimum_of_a_dense_grid_search():
    g = torch.Generator().manual_seed(5)
    values = torch.randn(3000, 3, generator=g, dtype=torch.float64)
    curvature = 4 * torch.randn(3000, 3, generator=g, dtype=torch.float64)  # bending up, down and mixed
    curvature[:1000] = curvature[:1000].abs()
    bary = quadratic_argmin(values, curvature)
    assert (bary >= 0).all() and torch.allclose(bary.sum(-1), torch.ones(3000, dtype=torch.float64))
    ours = quadratic_value(bary, values, curvature)
    grid = brute_force_quadratic_min(values, curvature)
    assert (ours <= grid + 1e-12).all()  # never above the grid's best
    assert (grid - ours).max() < 1e-3  # and the grid comes close to it: the same minimum
    same, lowest = quadratic_minimum(values, curvature)  # the model's value there, which predict() gives
    assert torch.equal(same, bary)
    torch.testing.assert_close(lowest, ours, atol=1e-12, rtol=0)


def test_exact_curvatures_solve_a_quadratic_sdf_exactly():
    # |x - c|^2 is quadratic, so its vertex values and midpoint curvatures define it on every triangle, and
    # its minimum on a triangle is the triangle's closest point to c: the exact minimum of a sphere's SDF
    c = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    squared = lambda x: ((x - c) ** 2).sum(-1)  # noqa: E731
    g = torch.Generator().manual_seed(6)
    tri = c + 0.3 * (torch.rand(400, 3, 3, generator=g, dtype=torch.float64) - 0.5)
    bary = quadratic_argmin(squared(tri.reshape(-1, 3)).reshape(-1, 3), midpoint_curvatures(squared, tri))
    ref = reference(zoo.Sphere(0.01, c), tri, resolution=64)
    gap = (bary_to_points(tri, bary) - c).norm(dim=-1) - (bary_to_points(tri, ref) - c).norm(dim=-1)
    assert gap.max() < 1e-9


def test_curvature_training_beats_the_best_vertex_on_held_out_triangles(torus_data):
    torch.set_num_threads(1)
    shape, tri, feat = torus_data
    sdf = shape.normalised
    data = TrainingData(tri[:2560], feat[:2560], torch.zeros(2560, dtype=torch.long), [sdf], vertex_sdf_of(sdf, tri[:2560]))
    detector_config = {**AmortizedDetector().config(), "output": "quadratic", "vertex_sdf": True, "hidden": 64}
    config = TrainConfig(steps=300, batch_size=512, lr=3e-3, validate_every=300, checkpoint_every=300, validation_size=256,
                         detector=detector_config, lambda_curvature=1.0, use_op_loss=False, use_min_loss=False)
    detector, history = train(data, config, progress=False)
    assert history["loss"][-1] < 0.5 * history["loss"][0]
    test_tri, test_feat = tri[2560:], feat[2560:]
    with torch.no_grad():
        pred = detector(test_tri, test_feat, vertex_sdf_of(sdf, test_tri))
    vertex_f = vertex_sdf_of(sdf, test_tri)
    best_vertex = torch.nn.functional.one_hot(vertex_f.argmin(-1), 3).float()
    assert optimality(sdf, test_tri, pred).mean() < 0.7 * optimality(sdf, test_tri, best_vertex).mean()


def test_quadratic_head_needs_vertex_values_and_curvature_loss_needs_the_head():
    with pytest.raises(InputError, match="vertex_sdf=True"):
        AmortizedDetector(output="quadratic")
    tri, feat = random_inputs(m=8)
    data = TrainingData(tri, feat, torch.zeros(8, dtype=torch.long), [zoo.Sphere(0.2)])
    with pytest.raises(InputError, match="quadratic"):
        train(data, TrainConfig(steps=1, lambda_curvature=1.0), progress=False)


def test_short_training_beats_the_centroid_and_the_best_vertex(torus_data, trained):
    shape, tri, feat = torus_data
    sdf = shape.normalised
    test_tri, test_feat = tri[2560:], feat[2560:]
    with torch.no_grad():
        pred = trained(test_tri, test_feat, vertex_sdf_of(sdf, test_tri))
    centroid = torch.full_like(pred, 1 / 3)
    vertex_f = torch.stack([sdf(test_tri[:, i]) for i in range(3)], -1)
    best_vertex = torch.nn.functional.one_hot(vertex_f.argmin(-1), 3).float()
    ours = optimality(sdf, test_tri, pred).mean()
    assert ours < 0.1 * optimality(sdf, test_tri, centroid).mean()
    assert ours < optimality(sdf, test_tri, best_vertex).mean()


# Where training runs: the CPU always, a GPU where the machine has one.
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_training_resumes_from_its_checkpoint_on_the_cpu(torus_data, tmp_path, monkeypatch, device):
    import sdfzoo.pipeline.train_detector as td

    shape, tri, feat = torus_data
    data = TrainingData(tri[:512], feat[:512], torch.zeros(512, dtype=torch.long), [shape.normalised])
    config = TrainConfig(steps=6, batch_size=128, checkpoint_every=3, validate_every=6, validation_size=64)
    straight, _ = train(data, config, progress=False)
    on_device, _ = train(data, config, progress=False, device=device)
    assert all(p.device.type == torch.device(device).type for p in on_device.parameters())
    original, calls = td.batch_losses, {"n": 0}

    def crash_at_step_five(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(td, "batch_losses", crash_at_step_five)
    with pytest.raises(KeyboardInterrupt):
        train(data, config, out_dir=tmp_path, progress=False, device=device)
    monkeypatch.setattr(td, "batch_losses", original)
    resumed, history = train(data, config, out_dir=tmp_path, progress=False)  # the device's checkpoint, on the CPU
    assert history["step"] == list(range(1, 7))
    for a, b, c in zip(straight.state_dict().values(), on_device.state_dict().values(), resumed.state_dict().values()):
        assert torch.allclose(a, b.cpu(), atol=1e-5) and torch.allclose(a, c, atol=1e-6)
    assert (tmp_path / "detector.safetensors").is_file()


def test_detect_works_in_the_source_frame(torus_data, trained):
    shape, tri, feat = torus_data
    rot = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64))[0]
    rot = rot * torch.sign(torch.det(rot))
    sim = Similarity(2.5, rot.numpy(), np.array([0.1, -0.2, 0.05]))
    src_shape = StandInShape(similarity=sim)
    tri_n = tri[2560:2700].double()
    tri_src = torch.as_tensor(sim.to_source(tri_n.numpy()))
    b_src = detect(trained, src_shape, tri_src, polish=False)
    b_norm = detect(trained, StandInShape(), tri_n.float(), polish=False)
    assert b_src.dtype == torch.float64
    assert torch.allclose(b_src.float(), b_norm, atol=1e-4)
    # the polish divides differences of SDF values, so compare it at one precision (float64 here)
    polished_src, polished_norm = detect(trained, src_shape, tri_src), detect(trained, StandInShape(), tri_n)
    assert torch.allclose(polished_src, polished_norm, atol=1e-6)
    assert not torch.allclose(polished_src, b_src, atol=1e-3)


def test_huge_triangle_is_subdivided_and_lands_near_the_reference(trained):
    shape = StandInShape()
    sdf = shape.normalised
    # triangles 0.3-0.6 long hovering over the torus, far outside the trained 0.03-0.08
    g = torch.Generator().manual_seed(2)
    base = torch.tensor([[0.25, -0.2, 0.09], [0.45, 0.15, 0.1], [0.05, 0.3, 0.11]])
    tri = torch.stack([base + 0.05 * torch.randn(3, 3, generator=g) * torch.tensor([1, 1, 0.1]) for _ in range(8)])
    ours = detect(trained, shape, tri)
    ref = reference(sdf, tri.double())
    f_ours = sdf(bary_to_points(tri, ours))
    f_ref = sdf(bary_to_points(tri.double(), ref)).float()
    assert (f_ours - f_ref).max() < 2e-3  # within the pieces' size tolerance of the global minimum
    # and the subdivision itself tiles the parent: pieces oriented as the parent (no overlap) whose
    # areas sum to the parent's (no gap)
    t = tri[0].double()
    pieces = subdivision_barycentrics(4, dtype=torch.float64) @ t  # (16, 3, 3)
    assert pieces.shape == (16, 3, 3)
    parent = torch.linalg.cross(t[1] - t[0], t[2] - t[0], dim=-1)
    cross = torch.linalg.cross(pieces[:, 1] - pieces[:, 0], pieces[:, 2] - pieces[:, 0], dim=-1)
    assert bool(((cross @ parent) > 0).all())
    torch.testing.assert_close(cross.norm(dim=-1).sum(), parent.norm(), rtol=1e-12, atol=0)


def test_penetrating_triangle_gets_a_point_inside(trained):
    shape = StandInShape()
    sdf = shape.normalised
    # triangles cutting through the tube (ring radius 0.3 in the xy plane, tube 0.06)
    g = torch.Generator().manual_seed(4)
    angle = torch.rand(32, generator=g) * 2 * math.pi
    centre = torch.stack([0.3 * torch.cos(angle), 0.3 * torch.sin(angle), torch.zeros(32)], -1)
    offsets = torch.tensor([[0.04, 0.0, 0.0], [-0.02, 0.035, 0.0], [-0.02, -0.035, 0.01]])
    tri = centre[:, None] + offsets
    b = detect(trained, shape, tri)
    f = sdf(bary_to_points(tri, b))
    assert (f < 0).all()
    vertex_f = torch.stack([sdf(tri[:, i]) for i in range(3)], -1)
    assert (f <= vertex_f.min(-1).values + 1e-6).float().mean() > 0.5 or (f < 0.5 * vertex_f.min(-1).values).all()


# --------------------------------------------------------------------------- benchmark


def test_benchmark_writes_tables_and_a_plot(trained, tmp_path):
    import json

    from sdfzoo.benches.detector import BenchConfig, format_tables, run_detector_benchmark

    config = BenchConfig(n_per_shape=40, fw_iters=(1, 3, 50), refine_iters=(1,), voxel_resolutions=(16,), timing_batch=200,
                         repeats=1, max_timed_fw_iters=3, reference_resolution=8)
    path = run_detector_benchmark(trained, [StandInShape()], [StandInShape(seed=1)], tmp_path, config,
                                  ablations={"full": trained}, log=lambda *a: None)
    report = json.loads(path.read_text())
    assert (tmp_path / "bench_detector.png").stat().st_size > 1000
    seen = report["splits"]["seen"]
    assert {"amortized", "amortized+ls", "best-vertex", "vertex+ls", "vertex+ls1", "amortized+fw1", "fw1", "fw3", "fw50", "pgd",
            "voxel16+fw50", "interpolant-p3", "interpolant-p4"} <= set(seen)
    assert "interpolant-p3" not in report["timings"] and "vertex+ls1" in report["timings"]
    # the lowest vertex is a KKT point wherever the reference minimum is at a vertex: exactly 0 there
    assert seen["best-vertex"]["optimality_p50"] == 0
    assert seen["best-vertex"]["optimality_mean"] > seen["vertex+ls"]["optimality_mean"]  # the polish moves off it
    assert seen["fw50"]["optimality_mean"] < seen["fw1"]["optimality_mean"]
    assert report["timings"]["fw50"]["measured"] is False and report["timings"]["fw3"]["measured"] is True
    for method in ("amortized", "amortized+ls"):
        t1 = report["table_1"]["seen"][method]
        assert t1["speedup"] > 0 and t1["fw_iterations"] in (1, 3, 50)
    assert set(report["table_3"]) == {"seen", "unseen"} and {"full", "full+ls"} <= set(report["table_4"])
    assert "Table I" in format_tables(report)
    # what a release's manifest records is the report's own numbers, under the manifest's names
    from sdfzoo.benches.detector import release_metrics

    flat = release_metrics(report)
    assert flat["detector_seen_polished_optimality_mean"] == seen["amortized+ls"]["optimality_mean"]
    assert flat["detector_unseen_one_pass_nme_mean"] == report["splits"]["unseen"]["amortized"]["nme_mean"]
    assert flat["detector_seen_one_pass_fw_iterations_same_optimality"] == report["table_1"]["seen"]["amortized"]["fw_iterations"]
    assert flat["detector_polished_ms_per_triangle"] == 1e3 * report["timings"]["amortized+ls"]["seconds_per_triangle"]
    assert len(flat) == 2 + 2 * 2 * 4
    # the reference moved off its minima loses optimality, more the farther it is moved
    assert seen["reference moved 0.1"]["optimality_mean"] > seen["reference moved 0.003"]["optimality_mean"] > 0
    for row in seen.values():  # every method's mean is accounted for by the bands, and the worst 5% hold part of it
        bands = row["optimality_by_reference_minimum"].values()
        assert abs(sum(b["fraction"] for b in bands) - 1) < 1e-6
        assert 0 <= row["optimality_worst5_share"] <= 1
        if row["optimality_mean"] > 0:
            assert abs(sum(b["share"] for b in bands) - 1) < 1e-4


def test_worst_share_and_bands_against_a_plain_loop():
    """The bench's account of where a mean comes from, against sorting and counting by hand."""
    from sdfzoo.benches.detector import by_minimum_band, worst_share

    gen = torch.Generator().manual_seed(3)
    gaps = torch.rand(203, generator=gen) ** 4  # heavy-tailed, as optimality is
    minima = torch.rand(203, generator=gen) * 0.12
    k = 11  # ceil(5% of 203)
    ordered = sorted(gaps.tolist(), reverse=True)
    assert abs(worst_share(gaps) - sum(ordered[:k]) / sum(ordered)) < 1e-6
    assert worst_share(torch.zeros(5)) == 0.0
    bands = by_minimum_band(gaps, minima, bands=(0.0, 0.02, 0.05))
    assert list(bands) == ["0-0.02", "0.02-0.05", ">=0.05"]
    for (lo, hi), label in zip(((0.0, 0.02), (0.02, 0.05), (0.05, 1.0)), bands):
        members = [g for g, m in zip(gaps.tolist(), minima.tolist()) if lo <= m < hi]
        assert bands[label]["fraction"] == len(members) / 203
        assert abs(bands[label]["mean"] - sum(members) / len(members)) < 1e-6
        assert abs(bands[label]["share"] - sum(members) / float(gaps.sum())) < 1e-6


def test_zoo_bench_detector_runs_the_detector_section(monkeypatch, tmp_path):
    """`zoo bench --detector MODEL` hands its options to benches.detector.bench_model and prints its tables."""
    from typer.testing import CliRunner

    import sdfzoo.benches.detector as bd
    from sdfzoo.cli.main import app, register_commands

    calls = {}

    def fake_bench_model(model, out, config, max_shapes, unseen_category, progress):
        calls.update(model=model, out=out, n=config.n_per_shape, threads=config.threads, max_shapes=max_shapes,
                     unseen=unseen_category)
        path = Path(out) / bd.JSON_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"splits": {}, "table_4": {"full": {"optimality_mean": 1e-3, "nme_mean": 0.01}}}))
        return path

    monkeypatch.setattr(bd, "bench_model", fake_bench_model)
    register_commands()
    result = CliRunner().invoke(app, ["bench", "--detector", "mugs@1.3.0", "--unseen-category", "mugs", "--max-shapes", "2",
                                      "--n-per-shape", "7", "--threads", "1", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert calls == {"model": "mugs@1.3.0", "out": tmp_path, "n": 7, "threads": 1, "max_shapes": 2, "unseen": "mugs"}
    assert "Table IV full" in result.output


def test_moved_reference_moves_off_vertex_minima_by_the_fraction_within_the_triangle():
    from sdfzoo.benches.detector import moved_reference
    from zoo.geometry import edge_lengths

    g = torch.Generator().manual_seed(0)
    tri = torch.rand(300, 3, 3, generator=g, dtype=torch.float64)
    kinds = torch.arange(300) % 3  # at a vertex, on an edge, inside
    ref = torch.where((kinds == 0)[:, None], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                      torch.where((kinds == 1)[:, None], torch.tensor([0.0, 0.45, 0.55], dtype=torch.float64),
                                  torch.tensor([0.3, 0.3, 0.4], dtype=torch.float64)))
    fraction = 0.02
    moved = moved_reference(tri, ref, fraction, torch.Generator().manual_seed(1))
    assert (moved >= 0).all() and torch.allclose(moved.sum(-1), torch.ones(300, dtype=torch.float64))
    assert torch.equal(moved[kinds == 0], ref[kinds == 0])  # a vertex minimum stays
    assert (moved[kinds == 1, 0] == 0).all()  # an edge minimum stays on its edge
    step = torch.einsum("mv,mvc->mc", moved - ref, tri).norm(dim=-1)
    inside = (kinds > 0) & (moved.amin(-1) > 0) | (kinds == 1) & (moved[:, 1:].amin(-1) > 0)
    want = fraction * edge_lengths(tri).mean(-1)
    assert inside.sum() > 150 and torch.allclose(step[inside], want[inside], rtol=1e-9)  # unclipped: exactly that far
    assert (step[kinds > 0] <= want[kinds > 0] + 1e-12).all()  # clipped: no farther


def test_interpolant_minimum_is_the_brute_force_minimum_where_the_sdf_is_such_a_polynomial():
    from sdfzoo.benches.detector import interpolant_minimum

    a = torch.tensor([0.6, -0.3, 0.2], dtype=torch.float64)

    def cubic(p):  # a cubic in space, so a cubic on every triangle: its degree-3 interpolant is itself
        p = torch.as_tensor(p, dtype=torch.float64)
        return (p @ a) ** 3 + 2 * ((p - 0.1) ** 2).sum(-1) - 0.4 * p[:, 2]

    g = torch.Generator().manual_seed(3)
    tri = 0.1 * torch.randn(40, 3, 3, generator=g, dtype=torch.float64) + 0.2 * torch.randn(40, 1, 3, generator=g, dtype=torch.float64)
    level = 90
    grid = barycentric_grid(level, torch.float64)  # the brute force: the true function on the same grid
    brute = grid[cubic(torch.einsum("qv,mvc->mqc", grid, tri).reshape(-1, 3)).reshape(40, -1).argmin(-1)]
    torch.testing.assert_close(interpolant_minimum(cubic, tri, 3, grid_level=level), brute, atol=1e-12, rtol=0)
    torch.testing.assert_close(interpolant_minimum(cubic, tri, 4, grid_level=level), brute, atol=1e-12, rtol=0)
    quadratic = interpolant_minimum(cubic, tri, 2, grid_level=level)
    assert not torch.allclose(quadratic, brute)  # a lower degree misses the cubic term


# --------------------------------------------------------------------------- the shared barycentric grid


def private_grid_of_the_detector(n: int) -> torch.Tensor:
    """The grid the detector's soft-argmax head was trained on, as it built it before the shared builder."""
    ij = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    return torch.tensor([(i / n, j / n, (n - i - j) / n) for i, j in ij], dtype=torch.float32)


@pytest.mark.parametrize("n", [1, 2, 7, 24])
def test_the_shared_grid_has_the_detectors_rows_in_its_order_bit_for_bit(n):
    # the soft-argmax head sums over the grid's rows in their order: a trained head gives the same
    # outputs only if every row is the same, in the same place
    assert torch.equal(barycentric_grid(n), private_grid_of_the_detector(n))
    assert torch.equal(barycentric_grid(n, torch.float64).float(), private_grid_of_the_detector(n))


def test_a_grid_head_gives_the_same_outputs_on_the_shared_grid():
    torch.manual_seed(0)
    det = AmortizedDetector(output="grid").eval()
    with torch.no_grad():
        for p in det.parameters():
            p.add_(0.3 * torch.randn_like(p))  # weights away from their initial values, as after training
    assert torch.equal(det.grid, private_grid_of_the_detector(24))  # zoo.detector._GRID_RESOLUTION
    g = torch.Generator().manual_seed(1)
    tri = 0.05 * torch.randn(64, 3, 3, generator=g)
    feats = torch.randn(64, 3, det.feature_dim, generator=g)
    with torch.no_grad():
        shared = det(tri, feats)
        det.grid = private_grid_of_the_detector(24)
        private = det(tri, feats)
    assert torch.equal(shared, private)


# --------------------------------------------------------------------------- empty input


def test_detect_on_zero_triangles_gives_zero_rows():
    shape, det = StandInShape(), AmortizedDetector()
    for dtype in (torch.float32, torch.float64):
        for polish in (False, True):
            bary = detect(det, shape, torch.zeros(0, 3, 3, dtype=dtype), polish=polish)
            assert bary.shape == (0, 3) and bary.dtype == dtype


def test_model_detect_on_zero_triangles_gives_zero_rows():
    try:
        m = zoo.load("mugs")
    except zoo.errors.ZooError as exc:  # pragma: no cover - a checkout without the packaged model
        pytest.skip(f"no mugs model: {exc}")
    shape = m.shape(m.shapes[0])
    for polish in (False, True):
        assert m.detect(shape, torch.zeros(0, 3, 3), polish=polish).shape == (0, 3)
    assert shape.detect(torch.zeros(0, 3, 3, dtype=torch.float64)).dtype == torch.float64


def test_input_statistics_in_chunks_match_the_whole_tensors():
    """fit_input_statistics sums a chunk at a time (features memory-mapped from a file): the same as torch's
    mean and std over all features at once."""
    g = torch.Generator().manual_seed(0)
    features = torch.randn(1000, 3, 5, generator=g) * torch.tensor([1.0, 2.0, 0.1, 5.0, 1e-3]) + 3.0
    detector = AmortizedDetector.from_config({"feature_dim": 5})
    detector.fit_input_statistics(features, chunk=97)
    flat = features.reshape(-1, 5)
    within = (features - features.mean(dim=1, keepdim=True)).reshape(-1, 5)
    assert torch.allclose(detector.feature_mean, flat.mean(0), rtol=1e-6, atol=1e-7)
    assert torch.allclose(detector.feature_std, flat.std(0).clamp_min(1e-6), rtol=1e-5)
    assert torch.allclose(detector.feature_within_std, within.std(0).clamp_min(1e-6), rtol=1e-5)
