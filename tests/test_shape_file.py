"""A fitted shape saved and loaded back: NeuralShape.save, zoo.load_shape, `zoo fit-codes --out`, a scene's `codes`."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from real_meshes import zoo_data

import zoo
from zoo.errors import ChecksumError, DataError, InputError, ModelNotFoundError
from zoo.scenes import scene_from_dict

DATA = zoo_data()
# A mug of the test split (SOURCES.md): never seen by the mugs model. EDF mugs are y-up (manifests/categories/mugs.toml).
UNSEEN = "mug/edf_mug6.stl"
needs_meshes = pytest.mark.skipif(DATA is None, reason="needs the real meshes ($ZOO_DATA with mug/)")


@pytest.fixture(scope="module")
def mugs():
    return zoo.load("mugs")


@pytest.fixture(scope="module")
def fitted(mugs):
    if DATA is None:
        pytest.skip("needs the real meshes ($ZOO_DATA with mug/)")
    return mugs.fit_codes(DATA / UNSEEN, iters=40, n_points=20_000, up="y", seed=3)


def query_points(shape, n=2000, seed=0):
    lo, hi = (b.double() for b in shape.bounds)
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)


@needs_meshes
def test_a_shape_fitted_to_an_unseen_mug_loads_back_with_the_same_values(fitted, mugs, tmp_path):
    path = fitted.save(tmp_path / "cup.safetensors", metrics={"near_p50": 0.01})
    loaded = zoo.load_shape(path)
    p = query_points(fitted)
    torch.testing.assert_close(loaded(p), fitted(p), rtol=0, atol=0)
    d0, g0 = fitted.value_and_grad(p)
    d1, g1 = loaded.value_and_grad(p)
    torch.testing.assert_close((d1, g1), (d0, g0), rtol=0, atol=0)
    assert loaded.name == "edf_mug6" and (loaded.model.name, loaded.model.version) == (mugs.name, mugs.version)
    np.testing.assert_array_equal(loaded.similarity.matrix, fitted.similarity.matrix)
    assert loaded.metrics == {"near_p50": 0.01}
    assert loaded.fit["mesh"] == "edf_mug6.stl" and loaded.fit["iters"] == 40 and loaded.fit["up"] == "y"
    assert len(loaded.fit["mesh_sha256"]) == 64
    # attached to its model: the detector answers on it as on the fitted shape
    tri = torch.stack([p[:3], p[3:6]]).float()
    torch.testing.assert_close(loaded.detect(tri), fitted.detect(tri))


@needs_meshes
def test_another_model_is_refused(fitted, tmp_path):
    path = fitted.save(tmp_path / "cup.safetensors")
    with pytest.raises(ChecksumError, match="fitted against mugs@"):
        zoo.load_shape(path, model="bottles")
    assert zoo.load_shape(path, model=fitted.model).model is fitted.model  # the same model, given, is taken


@needs_meshes
def test_a_damaged_or_foreign_file_is_a_typed_error(fitted, tmp_path):
    path = fitted.save(tmp_path / "cup.safetensors")
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF  # a bit of the last tensor
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(bytes(data))
    with pytest.raises(ChecksumError, match="do not match their recorded sha256"):
        zoo.load_shape(bad)
    with pytest.raises(DataError, match="not an sdfzoo shape file"):
        zoo.load_shape(zoo.load("mugs").path / "sdf.safetensors")
    (tmp_path / "torn.safetensors").write_bytes(path.read_bytes()[:100])
    with pytest.raises(DataError, match="not a readable safetensors"):
        zoo.load_shape(tmp_path / "torn.safetensors")
    with pytest.raises(ModelNotFoundError, match="does not exist"):
        zoo.load_shape(tmp_path / "absent.safetensors")


def test_a_model_shape_saves_and_a_detached_one_is_refused(mugs, tmp_path):
    shape = mugs.shape(mugs.shapes[0])
    loaded = zoo.load_shape(shape.save(tmp_path / "s.safetensors"))
    p = query_points(shape)
    torch.testing.assert_close(loaded(p), shape(p), rtol=0, atol=0)
    detached = zoo.NeuralShape("x", shape.decoder, shape.config, shape.codes, shape.positions)
    with pytest.raises(InputError, match="not attached to a model"):
        detached.save(tmp_path / "x.safetensors")
    with pytest.raises(InputError, match="JSON"):
        shape.save(tmp_path / "y.safetensors", metrics={"bad": float("nan")})


def test_a_scene_takes_a_saved_shape(mugs, tmp_path):
    shape = mugs.shape(mugs.shapes[1])
    shape.save(tmp_path / "mine.safetensors")
    mesh = {"procedural": "plane"}
    scene = scene_from_dict({"sdf": {"codes": "mine.safetensors"}, "mesh": mesh}, base_dir=tmp_path)
    p = query_points(shape)
    torch.testing.assert_close(scene.sdf(p), shape(p), rtol=0, atol=0)
    assert scene.sdf_label == f"mugs@{mugs.version}:mine.safetensors"
    with pytest.raises(ChecksumError):
        scene_from_dict({"sdf": {"codes": "mine.safetensors", "model": "bottles"}, "mesh": mesh}, base_dir=tmp_path)


@needs_meshes
def test_zoo_fit_codes_out_writes_a_file_zoo_load_shape_reads(tmp_path):
    from sdfzoo.pipeline.fit_category import fit_codes

    out = tmp_path / "cup.safetensors"
    summary = fit_codes("mugs", DATA / UNSEEN, out, iters=20, up="y", progress=False)
    loaded = zoo.load_shape(out)
    assert summary["out"] == str(out) and loaded.name == "edf_mug6"
    assert set(loaded.metrics) == {"near_p50", "near_p90", "sign_agreement", "size"}
    assert loaded.metrics["near_p50"] == pytest.approx(summary["near_p50"])
    assert loaded.fit["iters"] == 20 and loaded.fit["seconds"] == pytest.approx(summary["fit_seconds"])
    assert json.loads(json.dumps(loaded.fit)) == loaded.fit
