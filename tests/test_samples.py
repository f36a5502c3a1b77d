"""pipeline.normalise + pipeline.samples: per-shape stages, the HDF5 schema, corrupt files."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh
from real_meshes import DATA, needs_data

from sdfzoo.pipeline.normalise import read_normalised
from sdfzoo.pipeline.samples import (
    SCHEMA_VERSION,
    SampleConfig,
    ShapeSamples,
    prepare_category,
    prepare_mesh,
    read_samples,
    samples_path,
    write_samples,
)
from zoo.errors import DataError
from zoo.meshes import Similarity, signed_distance

SMALL = SampleConfig(n_points=2000, seed=3)


@pytest.fixture
def box_file(tmp_path) -> Path:
    """A 40 x 20 x 10 box, off-centre and tall along y, as a source mesh in its own units."""
    box = trimesh.creation.box(extents=(40.0, 20.0, 10.0))
    box.apply_translation([5.0, 100.0, -3.0])
    path = tmp_path / "src" / "crate.stl"
    path.parent.mkdir()
    box.export(path)
    return path


def test_samples_round_trip_through_hdf5(tmp_path):
    rng = np.random.default_rng(0)
    sim = Similarity(0.5, np.eye(3), np.array([0.1, 0.2, 0.3]))
    s = ShapeSamples("thing", rng.normal(size=(100, 3)).astype(np.float32), rng.normal(size=100).astype(np.float32),
                     sim, "ab" * 32, {"n_points": 100})
    path = write_samples(tmp_path / "thing.h5", s)
    back = read_samples(path)
    assert back.stem == "thing" and back.similarity == sim and back.source_sha256 == "ab" * 32
    assert np.array_equal(back.points, s.points) and np.array_equal(back.sdf, s.sdf)
    assert back.config == {"n_points": 100}
    with h5py.File(path) as f:
        assert f.attrs["schema_version"] == SCHEMA_VERSION
        assert f["points"].compression == "gzip" and f["points"].chunks is not None
        assert f.attrs["package_version"]
    assert [p.name for p in tmp_path.iterdir()] == ["thing.h5"]  # no temporary left behind


def test_truncated_garbage_missing_or_foreign_files_are_data_errors(tmp_path):
    s = ShapeSamples("t", np.zeros((5000, 3), np.float32), np.zeros(5000, np.float32), Similarity.identity())
    path = write_samples(tmp_path / "t.h5", s)
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all" * 10)
    for name in ("cut.h5", "junk.h5", "absent.h5"):
        with pytest.raises(DataError):
            read_samples(tmp_path / name)
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(DataError, match="schema version 99"):
        read_samples(path)


def test_prepare_mesh_writes_normalised_samples_that_map_back(box_file, tmp_path):
    work = tmp_path / "work"
    path = prepare_mesh(box_file, work, SMALL, up="y")
    assert path == samples_path(work, "crate")
    s = read_samples(path)
    assert s.points.shape == (2000, 3) and s.sdf.dtype == np.float32
    assert np.abs(s.points).max() < 0.5 + 0.1 + 5 * 0.05
    # the samples are in the normalised frame; mapped back, they measure the source box
    source = trimesh.load(box_file)
    d_src = signed_distance(source, s.similarity.to_source(s.points.astype(np.float64)))
    np.testing.assert_allclose(s.similarity.distance_to_source(s.sdf), d_src, atol=1e-4 * 40)
    shape = read_normalised(work / "normalised" / "crate.npz")
    np.testing.assert_allclose(shape.mesh.extents, [1.0, 0.25, 0.5], atol=1e-12)  # y (20) became z
    assert shape.similarity == s.similarity and s.config["shape_seed"] > 0


def test_prepare_mesh_skips_when_up_to_date_and_reruns_on_change(box_file, tmp_path):
    work = tmp_path / "work"
    path = prepare_mesh(box_file, work, SMALL)
    stamp = path.stat().st_mtime_ns
    prepare_mesh(box_file, work, SMALL)
    assert path.stat().st_mtime_ns == stamp
    prepare_mesh(box_file, work, SampleConfig(n_points=1000, seed=3))
    assert read_samples(path).points.shape == (1000, 3)
    trimesh.creation.box(extents=(1.0, 2.0, 3.0)).export(box_file)  # the source mesh changed
    prepare_mesh(box_file, work, SampleConfig(n_points=1000, seed=3))
    meta = json.loads((work / "normalised" / "crate.json").read_text())
    assert read_samples(path).similarity.scale == pytest.approx(1 / 3) == meta["similarity"]["scale"]


def test_an_edit_of_the_samples_code_reruns_samples_but_not_normalise(box_file, tmp_path, monkeypatch):
    """Stage locks record a digest of the code the stage runs: editing pipeline/samples.py (simulated by
    changing its recorded digest) reruns the samples stage; the normalise stage, which does not import it, skips."""
    import sdfzoo.pipeline.stages as stages

    work = tmp_path / "work"
    path = prepare_mesh(box_file, work, SMALL)
    npz = work / "normalised" / "crate.npz"
    stamps = path.stat().st_mtime_ns, npz.stat().st_mtime_ns
    prepare_mesh(box_file, work, SMALL)
    assert (path.stat().st_mtime_ns, npz.stat().st_mtime_ns) == stamps  # unchanged code: both skipped
    original = stages.code_digest
    monkeypatch.setattr(stages, "code_digest", lambda code, root=None: original(code, root) + (
        "+edited" if "pipeline.samples" in stages.code_closure([c for c in code if isinstance(c, str)], root) else ""))
    prepare_mesh(box_file, work, SMALL)
    assert path.stat().st_mtime_ns != stamps[0] and npz.stat().st_mtime_ns == stamps[1]
    assert json.loads(Path(str(path) + ".lock.json").read_text())["code_sha256"].endswith("+edited")


def test_a_corrupt_samples_file_is_rebuilt(box_file, tmp_path):
    work = tmp_path / "work"
    path = prepare_mesh(box_file, work, SMALL)
    path.write_bytes(b"garbage")
    prepare_mesh(box_file, work, SMALL)
    assert read_samples(path).points.shape == (2000, 3)


def test_samples_are_reproducible(box_file, tmp_path):
    a = read_samples(prepare_mesh(box_file, tmp_path / "a", SMALL))
    b = read_samples(prepare_mesh(box_file, tmp_path / "b", SMALL))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.sdf, b.sdf)


@needs_data
def test_prepare_category_on_real_nuts(tmp_path):
    paths = prepare_category("nuts", DATA, tmp_path, SampleConfig(n_points=1500), split="test", progress=False)
    assert [p.stem for p in paths] == ["factory_nut_m12"]
    s = read_samples(paths[0])
    assert 0.02 < (s.sdf < 0).mean() < 0.6  # a nut is solid: some samples inside, most outside
    assert s.similarity.scale == pytest.approx(1 / 0.02194, rel=1e-3)  # largest extent 21.94 mm, stored in metres
