"""The Hugging Face Hub path: ``hf-hub:ORG/NAME@TAG`` from a hand-made cache, offline; ``zoo push`` at the HfApi boundary.

No test here reaches the network: sockets are refused for the whole module.
"""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path

import pytest
import torch
from tiny_packages import flip_byte

import zoo
from zoo.errors import ChecksumError, ModelNotFoundError
from zoo.files import sha256_file
from zoo.hub import hub_cache_dir, parse_hub_spec

COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise OSError("tests must not reach the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def lay_out_hf_cache(cache: Path, repo_id: str, tag: str, package: Path, commit: str = COMMIT) -> Path:
    """The cache huggingface_hub writes: blobs by hash, snapshots/COMMIT/* linking to them, refs/TAG -> COMMIT."""
    repo = cache / ("models--" + repo_id.replace("/", "--"))
    snapshot = repo / "snapshots" / commit
    snapshot.mkdir(parents=True)
    (repo / "blobs").mkdir()
    for file in sorted(package.iterdir()):
        blob = repo / "blobs" / sha256_file(file)
        shutil.copy(file, blob)
        (snapshot / file.name).symlink_to(os.path.relpath(blob, snapshot))
    (repo / "refs").mkdir()
    (repo / "refs" / tag).write_text(commit)  # no trailing newline, as huggingface_hub writes it
    return snapshot


@pytest.fixture
def hf_cache(released, tmp_path, monkeypatch):
    cache = tmp_path / "hf" / "hub"
    snapshot = lay_out_hf_cache(cache, "acme/mugs", "1.10.0", released / "pretrained" / "mugs-1.10.0")
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    return cache, snapshot


def test_hub_spec_parses_repo_and_tag():
    assert parse_hub_spec("acme/mugs@1.0.0") == ("acme/mugs", "1.0.0")
    assert parse_hub_spec("acme/mugs") == ("acme/mugs", "main")
    with pytest.raises(ModelNotFoundError, match="ORG/NAME@TAG"):
        parse_hub_spec("mugs@1.0.0")


def test_tag_resolves_offline_from_a_hand_made_cache(hf_cache):
    cache, snapshot = hf_cache
    m = zoo.load("hf-hub:acme/mugs@1.10.0")
    assert (m.name, m.version) == ("mugs", "1.10.0")
    assert Path(m.path) == snapshot
    assert m.shape(m.shapes[0])(torch.zeros(2, 3)).shape == (2,)


def test_hf_home_locates_the_cache(hf_cache, monkeypatch):
    cache, snapshot = hf_cache
    monkeypatch.delenv("HF_HUB_CACHE")
    monkeypatch.setenv("HF_HOME", str(cache.parent))
    assert hub_cache_dir() == cache
    assert Path(zoo.load("hf-hub:acme/mugs@1.10.0").path) == snapshot


def test_corrupt_snapshot_file_is_refused(hf_cache):
    cache, snapshot = hf_cache
    weights = (snapshot / "sdf.safetensors").resolve()
    expected = sha256_file(weights)
    flip_byte(weights)
    with pytest.raises(ChecksumError) as info:
        zoo.load("hf-hub:acme/mugs@1.10.0")
    assert "sdf.safetensors" in str(info.value) and expected in str(info.value)


def test_uncached_tag_offline_says_what_to_do(hf_cache):
    with pytest.raises(ModelNotFoundError, match="HF_HUB_OFFLINE"):
        zoo.load("hf-hub:acme/mugs@9.9.9")
    with pytest.raises(ModelNotFoundError, match="not in"):
        zoo.load("hf-hub:acme/teapots@1.0.0")


# --------------------------------------------------------------------------- push


class FakeHfApi:
    """Records the calls `zoo push` makes; the boundary the real HfApi would cross."""

    def __init__(self, token=None):
        self.token, self.calls = token, []

    def create_repo(self, repo_id, **kwargs):
        self.calls.append(("create_repo", repo_id, kwargs))

    def upload_folder(self, **kwargs):
        self.calls.append(("upload_folder", kwargs["repo_id"], kwargs))
        self.uploaded = sorted(p.name for p in Path(kwargs["folder_path"]).iterdir())
        return type("CommitInfo", (), {"oid": COMMIT})()

    def create_tag(self, repo_id, **kwargs):
        self.calls.append(("create_tag", repo_id, kwargs))


def test_push_uploads_the_package_and_tags_its_version(released):
    from sdfzoo.pipeline.package import push_package

    api = FakeHfApi()
    done = push_package("mugs@1.9.0", "acme/mugs", api=api)
    assert [c[0] for c in api.calls] == ["create_repo", "upload_folder", "create_tag"]
    assert all(c[1] == "acme/mugs" for c in api.calls)
    assert Path(api.calls[1][2]["folder_path"]) == released / "pretrained" / "mugs-1.9.0"
    assert "SHA256SUMS" in api.uploaded and "sdf.safetensors" in api.uploaded
    assert api.calls[2][2]["tag"] == "1.9.0" and api.calls[2][2]["revision"] == COMMIT
    assert done["spec"] == "hf-hub:acme/mugs@1.9.0"


def test_push_refuses_a_corrupt_package(released):
    from sdfzoo.pipeline.package import push_package

    flip_byte(released / "pretrained" / "mugs-1.10.0" / "sdf.safetensors")
    api = FakeHfApi()
    with pytest.raises(ChecksumError):
        push_package("mugs@1.10.0", "acme/mugs", api=api)
    assert api.calls == []


def test_cli_push_passes_the_token_to_hfapi(released, monkeypatch):
    import huggingface_hub
    from typer.testing import CliRunner

    from sdfzoo.cli.main import app, register_commands

    made = []
    monkeypatch.setattr(huggingface_hub, "HfApi", lambda token=None: made.append(FakeHfApi(token)) or made[-1])
    register_commands()
    result = CliRunner().invoke(app, ["push", "bottles@1.0.0", "--repo", "acme/bottles", "--token", "hf_x"])
    assert result.exit_code == 0, result.output
    assert made[0].token == "hf_x" and made[0].calls[-1][2]["tag"] == "1.0.0"
    assert "hf-hub:acme/bottles@1.0.0" in result.output


# --------------------------------------------------------------------------- the bundled release, as users get it


def test_bundled_mugs_load_from_a_hand_made_hub_cache(tmp_path, monkeypatch):
    from zoo import registry

    for var in (registry.MANIFESTS_ENV, registry.PRETRAINED_ENV):
        monkeypatch.delenv(var, raising=False)
    record = next(r for r in zoo.list_models() if r["name"] == "mugs" and r["latest"])
    snapshot = lay_out_hf_cache(tmp_path / "hub", "acme/mugs", record["version"], Path(record["path"]))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    m = zoo.load(f"hf-hub:acme/mugs@{record['version']}")
    assert (m.name, m.version, Path(m.path)) == ("mugs", record["version"], snapshot)


# --------------------------------------------------------------------------- a pushed release is pinned to its commit

MOVED = "fedcba9876543210fedcba9876543210fedcba98"


def test_push_records_its_commit_and_the_hub_load_pins_it(released, tmp_path, monkeypatch):
    """After `zoo push`, the tag moving on the Hub (to other weights) changes nothing: the recorded commit loads,
    checked against the manifest's hashes; a pinned snapshot whose files differ from them is refused."""
    from sdfzoo.pipeline.package import push_package
    from zoo import registry

    done = push_package("mugs@1.9.0", "acme/mugs", api=FakeHfApi())
    assert done["commit"] == COMMIT and Path(done["manifest"]) == registry.manifest_path("mugs")
    _, entry = registry.resolve_version("mugs", "1.9.0")
    assert entry["hub"] == {"repo": "acme/mugs", "tag": "1.9.0", "commit": COMMIT}
    cache = tmp_path / "hub"
    pinned = lay_out_hf_cache(cache, "acme/mugs", "1.9.0", released / "pretrained" / "mugs-1.9.0")
    moved = lay_out_hf_cache_commit(cache, "acme/mugs", released / "pretrained" / "mugs-1.10.0", MOVED)
    (cache / "models--acme--mugs" / "refs" / "1.9.0").write_text(MOVED)  # the tag now names other weights
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    m = zoo.load("hf-hub:acme/mugs@1.9.0")
    assert (m.name, m.version, Path(m.path)) == ("mugs", "1.9.0", pinned) and moved != pinned
    flip_byte(Path(os.path.realpath(pinned / "sdf.safetensors")))
    with pytest.raises(ChecksumError):
        zoo.load("hf-hub:acme/mugs@1.9.0")


def test_a_hub_model_this_registry_never_pushed_is_checked_by_its_own_checksums(hf_cache):
    cache, snapshot = hf_cache
    m = zoo.load("hf-hub:acme/mugs@1.10.0")  # not recorded by a push: loads from the tag, its SHA256SUMS verified
    assert Path(m.path) == snapshot and m.name is not None


def test_a_registered_release_without_its_checksums_hash_is_an_error(released):
    from sdfzoo.pipeline.package import read_models_manifest, write_models_manifest
    from zoo.errors import DataError

    manifest = read_models_manifest("bottles")
    del manifest["versions"]["1.0.0"]["files"]["SHA256SUMS"]
    write_models_manifest("bottles", manifest)
    with pytest.raises(DataError, match="cannot be checked"):
        zoo.load("bottles@1.0.0")


def lay_out_hf_cache_commit(cache: Path, repo_id: str, package: Path, commit: str) -> Path:
    """One more snapshot in an existing hand-made cache (another commit of the same repository)."""
    repo = cache / ("models--" + repo_id.replace("/", "--"))
    snapshot = repo / "snapshots" / commit
    snapshot.mkdir(parents=True)
    for file in sorted(package.iterdir()):
        blob = repo / "blobs" / sha256_file(file)
        if not blob.exists():
            shutil.copy(file, blob)
        (snapshot / file.name).symlink_to(os.path.relpath(blob, snapshot))
    return snapshot
