"""The model manifests in git, validated as torchvision validates its weights' metadata.

Every ``manifests/models/*.toml`` must have the required keys, semantic version keys, file
hashes and sizes that match the bundled packages, and parameter counts that match the weights.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from tiny_packages import MUG_SHAPES, make_fit_output

from zoo import registry
from zoo.model import Model

ROOT = Path(__file__).resolve().parent.parent
BUNDLED_MANIFESTS = sorted((ROOT / "manifests" / "models").glob("*.toml"))
PRETRAINED = ROOT / "zoo" / "pretrained"
BUDGET_BYTES = 30 * 1024 * 1024


@pytest.fixture
def repo_layout(monkeypatch):
    """Read the project's own manifests and packages, whatever the environment says."""
    monkeypatch.delenv(registry.MANIFESTS_ENV, raising=False)
    monkeypatch.delenv(registry.PRETRAINED_ENV, raising=False)


@pytest.mark.parametrize("manifest", BUNDLED_MANIFESTS, ids=lambda p: p.stem)
def test_bundled_manifest_is_valid(manifest, repo_layout):
    assert registry.validate_manifest(manifest) == []


def test_every_bundled_package_is_registered(repo_layout):
    assert PRETRAINED.is_dir(), f"{PRETRAINED} is missing: the package ships its pretrained models there"
    packages = {p.name for p in PRETRAINED.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))}
    registered = {
        entry["package"] for m in BUNDLED_MANIFESTS for entry in registry.read_manifest_file(m)["versions"].values()
    }
    assert packages <= registered, f"packages without a manifest entry: {sorted(packages - registered)}"


def test_bundled_weights_fit_the_budget():
    assert PRETRAINED.is_dir(), f"{PRETRAINED} is missing: the package ships its pretrained models there"
    total = sum(p.stat().st_size for p in PRETRAINED.rglob("*") if p.is_file())
    assert total <= BUDGET_BYTES, f"zoo/pretrained holds {total / 2**20:.1f} MB; the budget is 30 MB"


# --------------------------------------------------------------------------- the validator itself


def _rewrite(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_a_fresh_manifest_validates(released):
    assert registry.validate_manifest(released / "manifests" / "models" / "mugs.toml") == []


def test_validator_catches_wrong_hashes_sizes_and_counts(released):
    manifest = released / "manifests" / "models" / "bottles.toml"
    entry = registry.read_manifest_file(manifest)["versions"]["1.0.0"]
    sha = entry["files"]["sdf.safetensors"]["sha256"]
    size = entry["files"]["sdf.safetensors"]["size"]
    total = entry["parameters"]["total"]
    _rewrite(manifest, sha, "f" * 64)
    _rewrite(manifest, f"size = {size} ", f"size = {size + 1} ")
    _rewrite(manifest, f"total = {total}", f"total = {total + 1}")
    problems = " | ".join(registry.validate_manifest(manifest))
    assert "sdf.safetensors sha256" in problems and "bytes" in problems and "parameters" in problems


def test_validator_catches_missing_keys_and_bad_versions(released):
    manifest = released / "manifests" / "models" / "mugs.toml"
    _rewrite(manifest, 'license = "', 'licence = "')
    _rewrite(manifest, '[versions."1.9.0"]', '[versions."1.9"]')
    problems = " | ".join(registry.validate_manifest(manifest, check_files=False))
    assert "license must be str" in problems and "semantic" in problems


def test_toml_writer_round_trips():
    tomllib = registry.toml_parser()

    from sdfzoo.pipeline.package import dumps_toml

    data = {
        "schema_version": 1,
        "name": 'odd "name"\n',
        "versions": {
            "1.10.0": {
                "ok": True, "x": 1.5e-5, "big": float("inf"), "list": [1, 2.0, "three"],
                "files": {"a b.json": {"sha256": "0" * 64, "size": 3}},
                "nested": {"deep": {"deeper": {"k": "v"}}, "empty": {}},
            }
        },
    }
    assert tomllib.loads(dumps_toml(data, header="a header\nwith two lines")) == data


def test_parameter_counts_read_safetensors_headers(tmp_path):
    fit = make_fit_output(tmp_path / "fit", "mugs", MUG_SHAPES)
    model = Model.from_directory(fit)
    sdf = sum(t.numel() for t in model.sdf.state_dict().values())  # weights, codes and positions
    detector = sum(t.numel() for t in model.detector.state_dict().values())  # buffers are stored too
    assert registry.parameter_counts(fit) == {"detector": detector, "sdf": sdf, "total": sdf + detector}
    assert set(registry.safetensors_shapes(fit / "sdf.safetensors")) >= {"codes", "positions"}
