"""The sample-triangles stage: conditions, labels, determinism, resume, schema."""

import h5py
import numpy as np
import pytest
import torch

import zoo
from sdfzoo.pipeline.triangle_sampling import meets_conditions, sample_constrained_triangles
from sdfzoo.pipeline.triangles import (
    ARRAYS,
    SCHEMA_VERSION,
    TriangleConfig,
    read_triangle_dataset,
    sample_triangle_dataset,
)
from zoo.errors import DataError, InputError
from zoo.geometry import bary_to_points
from zoo.neural import interpolate_codes
from zoo.solvers import frank_wolfe

CONFIG = TriangleConfig(n_per_shape=64, n_reference=8, reference_resolution=8, fw_iters=100)


class StandInShape:
    """An analytic SDF with a fixed random code cloud: what the stage uses of a NeuralShape."""

    def __init__(self, sdf, seed=0):
        g = torch.Generator().manual_seed(seed)
        self.normalised = sdf
        self.positions = torch.rand(1, 32, 3, generator=g) - 0.5
        self.codes = torch.randn(1, 32, 32, generator=g)

    def features(self, points):
        return interpolate_codes(points.float().unsqueeze(0), self.positions, self.codes, 1e-16).squeeze(0)


def small_sampler(sdf, n, seed=0):
    return sample_constrained_triangles(sdf, n, seed=seed, batch=2048)


def shapes():
    return [("torus", StandInShape(zoo.Torus(0.3, 0.08))), ("sphere", StandInShape(zoo.Sphere(0.3), seed=1))]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("tri") / "triangles.h5"
    sample_triangle_dataset(shapes(), path, CONFIG, sampler=small_sampler, progress=False)
    return path


def test_layout_and_labels(dataset):
    d = read_triangle_dataset(dataset)
    n = 2 * CONFIG.n_per_shape
    assert d["vertices"].shape == (n, 3, 3) and d["features"].shape == (n, 3, 32)
    assert d["bary"].shape == (n, 3) and d["min_sdf"].shape == (n,)
    assert d["shapes"] == ["torus", "sphere"]
    assert torch.equal(d["shape_index"], torch.repeat_interleave(torch.arange(2), CONFIG.n_per_shape))
    with h5py.File(dataset, "r") as f:
        assert int(f.attrs["schema_version"]) == SCHEMA_VERSION
    assert d["provenance"]["config"]["fw_iters"] == 100 and len(d["provenance"]["shape_seeds"]) == 2
    # every triangle meets the paper's conditions and its label is FW-100's answer, recomputed here
    for k, (_, shape) in enumerate(shapes()):
        rows = d["shape_index"] == k
        tri = d["vertices"][rows]
        assert meets_conditions(shape.normalised, tri).all()
        assert torch.allclose(d["bary"][rows], frank_wolfe(shape.normalised, tri, iters=100), atol=1e-6)
        assert torch.allclose(d["min_sdf"][rows], shape.normalised(bary_to_points(tri, d["bary"][rows])), atol=1e-6)
        assert (d["min_sdf"][rows] > 0).all()
        assert torch.allclose(d["features"][rows], shape.features(tri.reshape(-1, 3)).reshape(-1, 3, 32))
    # the global reference is never worse than FW-100 on its subset
    ref = d["reference"]
    assert len(ref["rows"]) == 2 * CONFIG.n_reference
    assert (ref["min_sdf"] <= d["min_sdf"][ref["rows"]] + 1e-5).all()


def test_same_seed_gives_identical_arrays(dataset, tmp_path):
    again = tmp_path / "again.h5"
    sample_triangle_dataset(shapes(), again, CONFIG, sampler=small_sampler, progress=False)
    with h5py.File(dataset, "r") as a, h5py.File(again, "r") as b:
        for k in ARRAYS:
            assert np.array_equal(a[k][...], b[k][...]), k
        for k in ("rows", "bary", "min_sdf"):
            assert np.array_equal(a["reference"][k][...], b["reference"][k][...]), k
    other = tmp_path / "other.h5"
    from dataclasses import replace

    sample_triangle_dataset(shapes(), other, replace(CONFIG, seed=1), sampler=small_sampler, progress=False)
    with h5py.File(dataset, "r") as a, h5py.File(other, "r") as b:
        assert not np.array_equal(a["vertices"][...], b["vertices"][...])


def test_an_interrupted_run_resumes_at_the_next_shape(tmp_path):
    calls = []

    def failing_on_second(sdf, n, seed=0):
        calls.append(seed)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return small_sampler(sdf, n, seed)

    path = tmp_path / "t.h5"
    with pytest.raises(KeyboardInterrupt):
        sample_triangle_dataset(shapes(), path, CONFIG, sampler=failing_on_second, progress=False)
    assert not path.exists() and len(list((tmp_path / "t.h5.chunks").iterdir())) == 1
    calls.clear()
    sample_triangle_dataset(shapes(), path, CONFIG, sampler=failing_on_second, progress=False)
    assert len(calls) == 1  # only the second shape was sampled again
    assert not (tmp_path / "t.h5.chunks").exists()
    assert read_triangle_dataset(path)["vertices"].shape[0] == 2 * CONFIG.n_per_shape


def test_errors_say_what_to_do(tmp_path):
    with pytest.raises(InputError, match="no shapes"):
        sample_triangle_dataset([], tmp_path / "x.h5", CONFIG, progress=False)
    with pytest.raises(DataError, match="sample-triangles"):
        read_triangle_dataset(tmp_path / "missing.h5")


def test_relabelling_for_the_same_fit_reproduces_the_labels(dataset, tmp_path):
    from sdfzoo.pipeline.triangles import relabel_triangle_dataset

    out = relabel_triangle_dataset(dataset, shapes(), tmp_path / "re.h5", CONFIG, progress=False)
    a, b = read_triangle_dataset(dataset), read_triangle_dataset(out)
    for k in ("vertices", "features", "vertex_sdf", "bary", "min_sdf", "shape_index"):
        assert torch.allclose(a[k].double(), b[k].double(), atol=1e-6), k
    assert b["provenance"]["relabelled_from"] == str(dataset)
    with pytest.raises(DataError, match="same shapes"):
        relabel_triangle_dataset(dataset, shapes()[::-1], tmp_path / "bad.h5", CONFIG, progress=False)


# Where the SDF queries run: the CPU always, a GPU where the machine has one (the device tool runs it there).
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_a_device_gives_the_arrays_of_the_cpu(dataset, tmp_path, device):
    path = tmp_path / "on_device.h5"
    sample_triangle_dataset(shapes(), path, CONFIG, progress=False, device=device,
                            sampler=lambda sdf, n, seed=0: sample_constrained_triangles(sdf, n, seed=seed, batch=2048, device=device))
    with h5py.File(dataset, "r") as a, h5py.File(path, "r") as b:
        for k in ARRAYS:
            if device == "cpu":
                assert np.array_equal(a[k][...], b[k][...]), k
            else:  # another device's rounding
                assert np.allclose(a[k][...], b[k][...], atol=1e-5), k


def test_a_detector_trained_on_the_mapped_file_is_the_one_trained_in_memory(dataset, tmp_path):
    """training_data_from_file maps the dataset (no copy of the category's triangles in memory); the weights it
    trains are bit for bit those of the same triangles read whole."""
    from sdfzoo.pipeline.train_detector import PRESETS, TrainingData, train, training_data_from_file

    class StandInModel:
        def __init__(self):
            self.shapes = dict(shapes())

        def shape(self, name):
            return self.shapes[name]

    model = StandInModel()
    mapped = training_data_from_file(dataset, model)
    assert str(dataset) in open("/proc/self/maps").read()  # the file is mapped, not read into the heap
    whole = read_triangle_dataset(dataset)
    in_memory = TrainingData(whole["vertices"], whole["features"], whole["shape_index"],
                             [s.normalised for _, s in shapes()], whole["vertex_sdf"])
    config = PRESETS["quick"]
    a, _ = train(in_memory, config, progress=False)
    b, _ = train(mapped, config, tmp_path / "mapped", progress=False)
    for (k, v), w in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(v, w), k
