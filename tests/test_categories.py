"""pipeline.categories: manifests match the data folder, splits match SOURCES.md, changes are caught."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
from real_meshes import DATA, needs_data

from sdfzoo.pipeline.categories import list_categories, load_category, resolve_data_dir, verify_meshes
from zoo.errors import DataError, InputError

SPLIT_COUNTS = {  # (train, test, scene), from ../shared/meshes/SOURCES.md
    "mugs": (54, 17, 0),
    "bottles": (20, 7, 0),
    "gears": (4, 3, 0),
    "bolts": (3, 1, 0),
    "nuts": (4, 1, 0),
    "scene_parts": (0, 0, 10),
}


def test_every_category_has_a_manifest():
    assert set(SPLIT_COUNTS) <= set(list_categories())


@pytest.mark.parametrize("name", sorted(SPLIT_COUNTS))
def test_splits_match_sources_md(name):
    cat = load_category(name)
    assert tuple(len(cat.stems(s)) for s in ("train", "test", "scene")) == SPLIT_COUNTS[name]
    assert not set(cat.train_stems) & set(cat.test_stems)
    for stem, entry in cat.meshes.items():
        assert Path(entry.file).stem == stem and len(entry.sha256) == 64
        assert entry.license and entry.source in cat.sources
        assert "evidence" in cat.sources[entry.source]


def test_orientation_per_source():
    mugs = load_category("mugs")
    assert {mugs.entry(s).up for s in mugs.stems() if s.startswith("edf_")} == {"y"}
    assert {mugs.entry(s).up for s in mugs.stems() if not s.startswith("edf_")} == {"z"}
    assert mugs.entry("hoi4d_mug_0041").split == "test" and mugs.entry("edf_mug9").split == "train"


@needs_data
@pytest.mark.parametrize("name", sorted(SPLIT_COUNTS))
def test_every_listed_mesh_exists_with_its_sha256(name):
    cat = load_category(name)
    paths = verify_meshes(cat, DATA)
    assert sorted(paths) == cat.stems()


@needs_data
def test_the_manifests_cover_every_staged_mesh():
    listed = {e.file for name in SPLIT_COUNTS for e in load_category(name).meshes.values()}
    staged = {p.relative_to(DATA).as_posix() for p in DATA.glob("*/*") if p.suffix in (".obj", ".ply", ".stl")}
    assert listed == staged


@needs_data
def test_an_edited_mesh_is_a_data_error_with_both_hashes(tmp_path):
    cat = load_category("nuts")
    entry = cat.entry("factory_nut_m4")
    shutil.copytree(DATA / "nut", tmp_path / "nut")
    edited = tmp_path / entry.file
    edited.write_bytes(edited.read_bytes() + b"\n# edited\n")
    actual = hashlib.sha256(edited.read_bytes()).hexdigest()
    with pytest.raises(DataError) as err:
        verify_meshes(cat, tmp_path, ["factory_nut_m4"])
    assert str(edited) in str(err.value) and entry.sha256 in str(err.value) and actual in str(err.value)
    edited.unlink()
    with pytest.raises(DataError, match="missing"):
        verify_meshes(cat, tmp_path, ["factory_nut_m4"])


def write_manifest(tmp_path, up='"z"') -> Path:
    mesh = tmp_path / "data" / "thing" / "a.obj"
    mesh.parent.mkdir(parents=True)
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    digest = hashlib.sha256(mesh.read_bytes()).hexdigest()
    manifest = tmp_path / "things.toml"
    manifest.write_text(
        f'category = "things"\n[sources.s]\nlicense = "MIT"\nup = {up}\nevidence = "test"\n'
        f'[[mesh]]\nstem = "a"\nfile = "thing/a.obj"\nsha256 = "{digest}"\nsplit = "train"\nsource = "s"\n'
    )
    return manifest


def test_a_manifest_by_path_with_a_rotation(tmp_path):
    cat = load_category(write_manifest(tmp_path, up="[[1, 0, 0], [0, 0, -1], [0, 1, 0]]"))
    assert cat.name == "things" and cat.train_stems == ["a"] and cat.entry("a").up == [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    assert verify_meshes(cat, tmp_path / "data") == {"a": tmp_path / "data" / "thing" / "a.obj"}


def test_a_bad_orientation_in_a_manifest_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="orientation"):
        load_category(write_manifest(tmp_path, up='"sideways"'))


def test_the_data_folder_comes_from_the_argument_or_zoo_data(tmp_path, monkeypatch):
    cat = load_category(write_manifest(tmp_path))
    monkeypatch.delenv("ZOO_DATA", raising=False)
    with pytest.raises(DataError, match="ZOO_DATA"):
        resolve_data_dir(None, cat)
    monkeypatch.setenv("ZOO_DATA", str(tmp_path / "data"))
    assert resolve_data_dir(None, cat) == tmp_path / "data"
    with pytest.raises(DataError, match="lacks thing/"):
        resolve_data_dir(tmp_path, cat)
    with pytest.raises(DataError, match="does not exist"):
        resolve_data_dir(tmp_path / "nowhere", cat)


def test_unknown_category_or_stem_is_an_input_error():
    with pytest.raises(InputError, match="known categories"):
        load_category("teapots")
    with pytest.raises(InputError):
        load_category("mugs").entry("teapot_1")
    with pytest.raises(InputError):
        load_category("mugs").stems("validation")
