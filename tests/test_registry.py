"""The model registry: names and semantic versions, verified loading, listing, packaging, the CLI.

Everything runs on tiny packages built in a temporary folder (``ZOO_MANIFESTS`` and
``ZOO_PRETRAINED`` point there), so the tests neither need nor touch the bundled models.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tiny_packages import BOTTLE_SHAPES, MUG_SHAPES, flip_byte, make_fit_output  # noqa: F401

import zoo
from zoo import registry
from zoo.errors import ChecksumError, DataError, InputError, ModelNotFoundError
from zoo.files import CHECKSUMS, sha256_file, write_checksums
from zoo.model import Model


def stored_scalars(path: Path) -> int:
    from safetensors.torch import load_file

    return sum(t.numel() for t in load_file(str(path)).values())


# --------------------------------------------------------------------------- versions


def test_versions_order_semantically_not_lexically():
    assert registry.parse_version("1.10.0") > registry.parse_version("1.9.0")
    assert registry.sort_versions(["1.9.0", "1.10.0", "0.2.11", "1.9.10"]) == ["1.10.0", "1.9.10", "1.9.0", "0.2.11"]
    for bad in ("1.0", "v1.0.0", "01.0.0", "1.0.0.0", "x"):
        with pytest.raises(InputError, match="semantic"):
            registry.parse_version(bad)


# --------------------------------------------------------------------------- loading by name


def test_name_loads_the_newest_version(released):
    m = zoo.load("mugs")
    assert (m.name, m.version) == ("mugs", "1.10.0")
    assert Path(m.path) == released / "pretrained" / "mugs-1.10.0"
    assert list(m.shapes) == MUG_SHAPES
    assert isinstance(m, Model) and m.detector is not None
    assert m.shape(MUG_SHAPES[0])(torch.zeros(2, 3)).shape == (2,)


def test_pinned_version_loads_that_version(released):
    m = zoo.load("mugs@1.9.0")
    assert (m.name, m.version, Path(m.path).name) == ("mugs", "1.9.0", "mugs-1.9.0")


def test_unknown_version_lists_the_versions(released):
    with pytest.raises(ModelNotFoundError) as info:
        zoo.load("mugs@999.0.0")
    assert "999.0.0" in str(info.value) and "1.10.0, 1.9.0" in str(info.value)


def test_unknown_name_lists_the_models(released):
    with pytest.raises(ModelNotFoundError, match="bottles, mugs"):
        zoo.load("teapots")


def test_directory_loads_and_verifies_itself(released, tmp_path):
    copy = shutil.copytree(released / "pretrained" / "mugs-1.9.0", tmp_path / "elsewhere" / "my-mugs")
    m = zoo.load(copy)
    assert (m.name, m.version, Path(m.path)) == ("mugs", "1.9.0", copy)
    assert zoo.load(str(copy)).version == "1.9.0"


# --------------------------------------------------------------------------- checksums


def test_flipped_byte_in_a_copy_is_refused_naming_file_and_hash(released, tmp_path):
    copy = shutil.copytree(released / "pretrained" / "mugs-1.10.0", tmp_path / "copy")
    expected = sha256_file(copy / "sdf.safetensors")
    flip_byte(copy / "sdf.safetensors")
    with pytest.raises(ChecksumError) as info:
        zoo.load(copy)
    assert "sdf.safetensors" in str(info.value) and expected in str(info.value)


def test_flipped_byte_in_a_bundled_package_is_refused(released):
    config = released / "pretrained" / "mugs-1.10.0" / "config.json"
    expected = sha256_file(config)
    flip_byte(config, offset=0)
    with pytest.raises(ChecksumError, match=expected):
        zoo.load("mugs")


def test_verify_false_skips_the_checksums(released):
    flip_byte(released / "pretrained" / "mugs-1.10.0" / "sdf.safetensors")  # a weight, not the header
    assert zoo.load("mugs", verify=False).version == "1.10.0"


def test_package_rewritten_with_its_checksums_is_caught_by_the_manifest(released):
    package = released / "pretrained" / "mugs-1.10.0"
    flip_byte(package / "detector.safetensors")
    write_checksums(package)  # a consistent but different package: only the manifest knows
    with pytest.raises(ChecksumError, match=CHECKSUMS):
        zoo.load("mugs@1.10.0")


def test_unlisted_weights_are_refused(released, tmp_path):
    copy = shutil.copytree(released / "pretrained" / "bottles-1.0.0", tmp_path / "copy")
    shutil.copy(copy / "sdf.safetensors", copy / "extra.safetensors")
    with pytest.raises(ChecksumError, match="extra.safetensors"):
        zoo.load(copy)


def test_loading_one_model_reads_only_its_files(released):
    (released / "manifests" / "models" / "bottles.toml").write_text("this is [not toml")
    shutil.rmtree(released / "pretrained" / "bottles-1.0.0")
    assert zoo.load("mugs@1.9.0").name == "mugs"


# --------------------------------------------------------------------------- listing


def test_list_models_gives_every_version_with_its_facts(released):
    records = zoo.list_models()
    assert [(r["name"], r["version"], r["latest"]) for r in records] == [
        ("bottles", "1.0.0", True),
        ("mugs", "1.10.0", True),
        ("mugs", "1.9.0", False),
    ]
    mugs = records[1]
    assert mugs["category"] == "mugs" and mugs["shapes"] == 3
    assert mugs["metrics"] == {"sdf_abs_error_p50": 0.0012}
    assert mugs["license"].startswith("non-commercial research only")
    package = released / "pretrained" / "mugs-1.10.0"
    sdf, det = stored_scalars(package / "sdf.safetensors"), stored_scalars(package / "detector.safetensors")
    assert mugs["parameters"] == {"sdf": sdf, "detector": det, "total": sdf + det}


def test_list_models_is_empty_without_manifests(zoo_home):
    assert zoo.list_models() == []


# --------------------------------------------------------------------------- packaging


def test_package_copies_weights_not_caches_and_writes_a_card(released):
    package = released / "pretrained" / "mugs-1.10.0"
    assert sorted(p.name for p in package.iterdir()) == [
        "README.md", "SHA256SUMS", "config.json", "detector.safetensors", "sdf.safetensors"
    ]
    config = json.loads((package / "config.json").read_text())
    assert (config["name"], config["version"]) == ("mugs", "1.10.0")
    card = (package / "README.md").read_text()
    for needed in ('zoo.load("mugs@1.10.0")', "zoo eval mugs", "non-commercial research only", "sdf_abs_error_p50",
                   "manifests/categories/mugs.toml", "ShapeNet", "HOI4D"):
        assert needed in card


def test_package_refuses_an_existing_version_unless_forced(released):
    from sdfzoo.pipeline.package import package_model

    fit = released / "fits" / "mugs"
    with pytest.raises(InputError, match="already exists"):
        package_model(fit, "1.9.0")
    done = package_model(fit, "1.9.0", force=True, date="2026-03-03")
    assert done.entry["date"] == "2026-03-03"
    assert zoo.load("mugs@1.9.0").version == "1.9.0"
    assert not [p for p in (released / "pretrained").iterdir() if p.name.startswith(".")]  # no staging left behind


def test_package_refuses_a_corrupt_fit_output(zoo_home):
    from sdfzoo.pipeline.package import package_model

    fit = make_fit_output(zoo_home / "fits" / "mugs", "mugs", MUG_SHAPES)
    flip_byte(fit / "sdf.safetensors")
    with pytest.raises(ChecksumError, match="sdf.safetensors"):
        package_model(fit, "1.0.0")
    with pytest.raises(DataError, match="fit-category"):
        package_model(zoo_home / "nowhere", "1.0.0")


def test_package_from_an_installed_wheel_refuses_to_write_into_it(zoo_home, monkeypatch):
    """Installed (not a clone), the registry's default folders are the package's own: zoo package names the
    variables that point it at folders of the user's, and writes nothing."""
    from sdfzoo.pipeline.package import package_model
    from zoo import resources

    fit = make_fit_output(zoo_home / "fits" / "mugs", "mugs", MUG_SHAPES)
    monkeypatch.setattr(resources, "in_clone", lambda: False)
    monkeypatch.delenv(registry.PRETRAINED_ENV)
    before = sorted(p for p in resources.package_folder().rglob("*") if "__pycache__" not in p.parts)
    with pytest.raises(InputError, match=r"\$ZOO_PRETRAINED.*folders of yours"):
        package_model(fit, "1.0.0")
    assert sorted(p for p in resources.package_folder().rglob("*") if "__pycache__" not in p.parts) == before
    monkeypatch.setenv(registry.PRETRAINED_ENV, str(zoo_home / "mine"))
    assert package_model(fit, "1.0.0").path == zoo_home / "mine" / "mugs-1.0.0"


def test_license_follows_the_training_meshes():
    from sdfzoo.pipeline.package import license_for

    assert license_for(["hoi4d_mug_0001", "edf_mug1"])[0].startswith("non-commercial research only")
    assert license_for(["shapenet_mug_128ecbc1"])[0].startswith("non-commercial research only")
    assert license_for(["shapenet_mug_128ecbc1"], declared="MIT")[0].startswith("non-commercial")
    assert license_for(["factory_bolt_m8"], declared="BSD-3-Clause")[0] == "BSD-3-Clause"
    assert "upstream terms" in license_for(["edf_bottle0"])[0]


# --------------------------------------------------------------------------- CLI and import weight


def _cli():
    from typer.testing import CliRunner

    from sdfzoo.cli.main import app, register_commands

    register_commands()
    return CliRunner(), app


def test_cli_list_and_info(released):
    runner, app = _cli()
    listed = runner.invoke(app, ["list"])
    assert listed.exit_code == 0, listed.output
    assert "mugs" in listed.output and "1.10.0" in listed.output and "1.9.0" not in listed.output
    assert "1.9.0" in runner.invoke(app, ["list", "--all"]).output
    shown = runner.invoke(app, ["info", "mugs@1.9.0"])
    assert shown.exit_code == 0, shown.output
    assert "README.md" in shown.output and "sha256" in shown.output
    card = (released / "pretrained" / "mugs-1.9.0" / "README.md").read_text()
    assert card.strip() in shown.output  # the card itself, not only its path


def test_list_metrics_cell_keeps_headlines_in_order():
    from sdfzoo.cli.models import _metrics_summary

    metrics = {"fit_seconds": 96.1, "detector_seen_polished_optimality_mean": 2.4e-4,
               "train": {"sign_agreement": 0.9987, "near_p90": 0.005, "near_p50": 0.00136}}
    assert _metrics_summary(metrics).splitlines() == [
        "near p50 0.00136", "near p90 0.005", "sign agr. 0.999", "detect opt. 0.00024"]
    assert _metrics_summary(metrics, limit=2).splitlines() == ["near p50 0.00136", "near p90 0.005"]
    assert _metrics_summary({"fit_seconds": 96.1}) == "see `zoo info`"


def test_cli_package(zoo_home):
    runner, app = _cli()
    fit = make_fit_output(zoo_home / "fits" / "bottles", "bottles", BOTTLE_SHAPES)
    done = runner.invoke(app, ["package", str(fit), "--version", "2.0.0", "--name", "bottles"])
    assert done.exit_code == 0, done.output
    assert 'zoo.load("bottles@2.0.0")' in done.output
    assert zoo.load("bottles").version == "2.0.0"


def test_import_zoo_loads_no_hub_hdf5_cli_or_pipeline():
    code = (
        "import sys, zoo; zoo.list_models; zoo.load; "
        "print(sorted(m for m in ('huggingface_hub', 'h5py', 'typer', 'rich', 'pipeline') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# --------------------------------------------------------------------------- the bundled releases

# Models that must ship in zoo/pretrained.
BUNDLED = ("mugs", "bottles", "gears", "bolts")


@pytest.fixture
def bundled(monkeypatch):
    for var in (registry.MANIFESTS_ENV, registry.PRETRAINED_ENV):
        monkeypatch.delenv(var, raising=False)


@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_model_loads_by_listed_version_and_refuses_corruption(name, bundled, tmp_path):
    listed = [r for r in zoo.list_models() if r["name"] == name]
    assert listed, f"{name} is not registered in manifests/models"
    version = listed[0]["version"]
    m = zoo.load(f"{name}@{version}")
    assert (m.name, m.version) == (name, version) and Path(m.path) == Path(listed[0]["path"])
    with pytest.raises(ModelNotFoundError, match=version):
        zoo.load(f"{name}@999.0.0")
    copy = shutil.copytree(m.path, tmp_path / "copy")
    expected = sha256_file(copy / "sdf.safetensors")
    flip_byte(copy / "sdf.safetensors", offset=len((copy / "sdf.safetensors").read_bytes()) // 2)
    with pytest.raises(ChecksumError, match=expected):
        zoo.load(copy)
