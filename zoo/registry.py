"""Pretrained models by name: the model manifests, semantic versions, ``zoo.load`` and ``zoo.list_models``.

A model's releases are described by ``manifests/models/NAME.toml`` (text, in git); each release
points at a package directory under ``zoo/pretrained/`` (config.json, safetensors weights, a model
card and ``SHA256SUMS``). Loading verifies the sha256 of every file it reads: ``SHA256SUMS``
against the manifest, every other file against ``SHA256SUMS``.

Where things are found (read at call time, so tests and users can point elsewhere):
  * ``ZOO_MANIFESTS``: the manifests folder (holding ``models/``); default the project's
    ``manifests/`` (a clone or an editable install), else the wheel's ``zoo/data/manifests``.
  * ``ZOO_PRETRAINED``: the folder holding the package directories; default ``zoo/pretrained``.
"""

from __future__ import annotations

import json
import os
import re
import struct
from pathlib import Path

from .errors import ChecksumError, DataError, InputError, ModelNotFoundError
from .files import CHECKSUMS, read_checksums, sha256_file, verify_directory
from .resources import bundled
from .validation import as_device

MANIFESTS_ENV = "ZOO_MANIFESTS"
PRETRAINED_ENV = "ZOO_PRETRAINED"
MANIFEST_SCHEMA_VERSION = 1
HUB_PREFIX = "hf-hub:"

# A model name is what goes before "@" in "NAME@X.Y.Z" and the stem of its manifest file.
_NAME = re.compile(r"[a-z0-9][a-z0-9_.-]*")
_SEMVER = re.compile(r"(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)")

# Keys every version entry of a manifest carries; see ``validate_manifest``.
REQUIRED_VERSION_KEYS = {
    "date": str,
    "package": str,
    "category": str,
    "format_version": int,
    "license": str,
    "config": dict,
    "parameters": dict,
    "files": dict,
    "training_data": dict,
    "metrics": dict,
    "metrics_command": str,
}
REQUIRED_PACKAGE_FILES = ("config.json", "sdf.safetensors", "README.md", CHECKSUMS)


# --------------------------------------------------------------------------- versions


def parse_version(text: str) -> tuple[int, int, int]:
    """``"1.10.0"`` -> ``(1, 10, 0)``: versions compare as numbers, so 1.10.0 > 1.9.0."""
    match = _SEMVER.fullmatch(str(text))
    if match is None:
        raise InputError(f"version {text!r} is not semantic MAJOR.MINOR.PATCH (for example 1.0.0)")
    return tuple(int(part) for part in match.groups())  # type: ignore[return-value]


def sort_versions(versions) -> list[str]:
    """Newest first, by semantic version."""
    return sorted(versions, key=parse_version, reverse=True)


def check_model_name(name: str) -> str:
    if not _NAME.fullmatch(name):
        raise InputError(
            f"model name {name!r} is not valid: use lower-case letters, digits, '_', '-' or '.', "
            "starting with a letter or digit (for example 'mugs')"
        )
    return name


# --------------------------------------------------------------------------- where things live


def manifests_dir() -> Path:
    """The manifests folder: ``$ZOO_MANIFESTS``, else the project's ``manifests/`` (a clone), else the wheel's copy."""
    override = os.environ.get(MANIFESTS_ENV)
    return Path(override) if override else bundled("manifests")


def model_manifests_dir() -> Path:
    return manifests_dir() / "models"


def pretrained_dir() -> Path:
    """The folder of package directories: ``$ZOO_PRETRAINED``, else ``zoo/pretrained``."""
    override = os.environ.get(PRETRAINED_ENV)
    return Path(override) if override else Path(__file__).resolve().parent / "pretrained"


def manifest_path(name: str) -> Path:
    return model_manifests_dir() / f"{name}.toml"


def model_names() -> list[str]:
    """Names of the registered models (manifest file stems); reads no manifest."""
    folder = model_manifests_dir()
    return sorted(p.stem for p in folder.glob("*.toml")) if folder.is_dir() else []


# --------------------------------------------------------------------------- manifests


def toml_parser():
    """The TOML parser module: ``tomllib``, or on Python 3.10 ``tomli`` (the same parser, a dependency there)."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    return tomllib


def read_manifest_file(path: str | os.PathLike) -> dict:
    path = Path(path)
    try:
        return toml_parser().loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"model manifest {path} does not exist") from None
    except ValueError as exc:  # tomllib.TOMLDecodeError derives from ValueError
        raise DataError(f"model manifest {path} is not valid TOML ({exc}); fix it or re-create it with `zoo package`") from exc


def read_manifest(name: str) -> dict:
    """The manifest of one model; an unknown name is an error listing the models that exist."""
    path = manifest_path(name)
    if not path.is_file():
        known = model_names()
        raise ModelNotFoundError(
            f"no model named {name!r}; the models are: {', '.join(known) or 'none'} "
            f"(manifests in {model_manifests_dir()}); `zoo list` shows them with their versions"
        )
    return read_manifest_file(path)


def versions_of(manifest: dict) -> list[str]:
    return sort_versions(manifest.get("versions", {}))


def resolve_version(name: str, version: str | None = None) -> tuple[str, dict]:
    """``(version, entry)`` of ``name``: the newest when ``version`` is None."""
    manifest = read_manifest(name)
    versions = versions_of(manifest)
    if not versions:
        raise ModelNotFoundError(f"model {name!r} has no versions in {manifest_path(name)}; add one with `zoo package`")
    if version is None:
        version = versions[0]
    if version not in manifest["versions"]:
        raise ModelNotFoundError(
            f"model {name!r} has no version {version!r}; its versions are: {', '.join(versions)} "
            f"(load the newest with zoo.load({name!r}))"
        )
    return version, manifest["versions"][version]


def package_dir(entry: dict) -> Path:
    """The package directory a manifest entry points at (relative to the pretrained folder)."""
    return pretrained_dir() / entry["package"]


# --------------------------------------------------------------------------- weights


def safetensors_shapes(path: str | os.PathLike) -> dict[str, list[int]]:
    """Tensor name -> shape, read from a safetensors header alone (no weights are loaded)."""
    path = Path(path)
    with open(path, "rb") as f:
        raw = f.read(8)
        if len(raw) != 8:
            raise DataError(f"{path} is not a safetensors file (shorter than its 8-byte header length)")
        (length,) = struct.unpack("<Q", raw)
        if length > os.path.getsize(path):
            raise DataError(f"{path} is not a safetensors file (header length {length} exceeds the file)")
        header = json.loads(f.read(length))
    return {key: list(value["shape"]) for key, value in header.items() if key != "__metadata__"}


def parameter_count(path: str | os.PathLike) -> int:
    """Number of scalars stored in a safetensors file: network weights, per-shape codes and buffers alike."""
    total = 0
    for shape in safetensors_shapes(path).values():
        n = 1
        for dim in shape:
            n *= dim
        total += n
    return total


def parameter_counts(directory: str | os.PathLike) -> dict[str, int]:
    """``{"sdf": n, "detector": m, "total": n + m}`` from the package's ``*.safetensors`` files."""
    counts = {p.stem: parameter_count(p) for p in sorted(Path(directory).glob("*.safetensors"))}
    counts["total"] = sum(counts.values())
    return counts


# --------------------------------------------------------------------------- verification


def verify_package(directory: str | os.PathLike, expected_checksums_sha256: str | None = None) -> dict[str, str]:
    """Check a package directory before anything in it is used; return its ``SHA256SUMS`` listing.

    Every file listed in ``SHA256SUMS`` must match its sha256; the config and every weights file
    must be listed (an unlisted file would be read unverified). ``expected_checksums_sha256``, from
    a manifest, pins ``SHA256SUMS`` itself, so a package rewritten together with its listing is
    caught too.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise DataError(f"{directory} is not a directory; a package is a folder with config.json and {CHECKSUMS}")
    if expected_checksums_sha256 is not None:
        listing = directory / CHECKSUMS
        if not listing.is_file():
            raise DataError(f"{listing} is missing; re-create the package with `zoo package`")
        actual = sha256_file(listing)
        if actual != expected_checksums_sha256:
            raise ChecksumError(
                f"{listing} is corrupt or changed: sha256 {actual} but the manifest expects "
                f"{expected_checksums_sha256}; restore the package (git checkout / re-download) or re-create it with `zoo package`"
            )
    sums = read_checksums(directory)
    unlisted = [
        p.name for p in sorted(directory.iterdir()) if (p.name == "config.json" or p.suffix == ".safetensors") and p.name not in sums
    ]
    if unlisted:
        raise ChecksumError(
            f"{directory} has files not listed in {CHECKSUMS}: {', '.join(unlisted)}; "
            "they cannot be verified: re-create the package with `zoo package`"
        )
    return verify_directory(directory)


# --------------------------------------------------------------------------- loading


def _open_model(path: Path, name: str | None, version: str | None, device: str):
    """The one place a verified package directory becomes a model object.

    Checksums were verified by the caller, so the model does not hash the files a second time.
    """
    from .model import Model

    return Model.from_directory(path, name=name, version=version, verify=False, device=device)


def _is_path_spec(spec) -> bool:
    if isinstance(spec, os.PathLike):
        return True
    return any(sep in spec for sep in ("/", "\\", os.sep)) or spec.startswith((".", "~"))


def load(spec: str | os.PathLike, device: str = "cpu", verify: bool = True):
    """Load a pretrained model.

    ``spec`` is ``"NAME"`` (its newest version), ``"NAME@X.Y.Z"``, a package directory, or
    ``"hf-hub:ORG/NAME@REVISION"`` (through huggingface_hub's cache; works offline with
    ``HF_HUB_OFFLINE=1`` when the revision is cached). With ``verify`` (the default) every file
    is checked against its sha256 first: a corrupt file raises :class:`~zoo.errors.ChecksumError`.
    """
    if isinstance(spec, str) and spec.startswith(HUB_PREFIX):
        return load_from_hub(spec[len(HUB_PREFIX):], device=device, verify=verify)
    if _is_path_spec(spec):
        return load_directory(spec, device=device, verify=verify)
    name, _, version = str(spec).partition("@")
    if name not in model_names() and Path(spec).is_dir():
        return load_directory(spec, device=device, verify=verify)  # a bare folder name in the working directory
    return load_registered(name, version or None, device=device, verify=verify)


def load_registered(name: str, version: str | None = None, device: str = "cpu", verify: bool = True):
    """Load ``name`` at ``version`` (newest if None) from the bundled packages."""
    as_device(device)  # an unusable device is a typed error before any file is read
    version, entry = resolve_version(name, version)
    path = package_dir(entry)
    if not path.is_dir():
        raise DataError(
            f"{name}@{version}: its package directory {path} is missing though the manifest lists it; "
            "restore it (git checkout / git lfs pull) or re-create it with `zoo package`"
        )
    if verify:
        verify_package(path, expected_checksums_sha256=checksums_sha256(entry, f"{name}@{version}"))
    return _open_model(path, name, version, device)


def checksums_sha256(entry: dict, release: str) -> str:
    """The sha256 of a release's SHA256SUMS as its manifest records it; DataError where it does not (a release
    whose files cannot be checked against its manifest is not loaded unchecked)."""
    digest = (entry.get("files", {}).get(CHECKSUMS) or {}).get("sha256")
    if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
        raise DataError(f"{release}: its manifest entry lacks files.{CHECKSUMS}.sha256, so its files cannot be "
                        "checked; re-create the release with `zoo package`")
    return digest


def hub_release(repo_id: str, revision: str) -> tuple[str, str, dict] | None:
    """(name, version, entry) of the registered release that `zoo push` sent to ``repo_id`` as tag or commit
    ``revision``, or None (a model of someone else's: its own SHA256SUMS is all there is to check)."""
    for name in model_names():
        for version, entry in read_manifest(name).get("versions", {}).items():
            hub = entry.get("hub") or {}
            if hub.get("repo") == repo_id and revision in (hub.get("tag"), hub.get("commit")):
                return name, version, entry
    return None


def load_from_hub(spec: str, device: str = "cpu", verify: bool = True):
    """``ORG/NAME@REVISION`` through huggingface_hub's cache. A release this registry pushed is downloaded at the
    commit `zoo push` recorded (a tag moved on the Hub does not change what loads) and its files are checked
    against the manifest's hashes; any other is checked against its own SHA256SUMS."""
    from .hub import parse_hub_spec, snapshot_dir

    as_device(device)
    repo_id, revision = parse_hub_spec(spec)
    release = hub_release(repo_id, revision)
    if release is None:
        return load_directory(snapshot_dir(spec), device=device, verify=verify)
    name, version, entry = release
    folder = snapshot_dir(spec, pin=entry["hub"]["commit"])
    if verify:
        verify_package(folder, expected_checksums_sha256=checksums_sha256(entry, f"{name}@{version}"))
    return _open_model(folder, name, version, device)


def load_directory(path: str | os.PathLike, device: str = "cpu", verify: bool = True):
    """Load the package in ``path``; its own ``SHA256SUMS`` verifies it."""
    as_device(device)
    path = Path(path).expanduser()
    if not path.is_dir():
        raise ModelNotFoundError(
            f"{path} is not a directory; pass a model name (one of: {', '.join(model_names()) or 'none'}), "
            "NAME@X.Y.Z, a package directory or hf-hub:ORG/NAME@TAG"
        )
    if verify:
        verify_package(path)
    return _open_model(path, None, None, device)


# --------------------------------------------------------------------------- listing


def model_record(name: str, version: str, entry: dict, newest: bool) -> dict:
    """One row of :func:`list_models`."""
    return {
        "name": name,
        "version": version,
        "category": entry.get("category", ""),
        "shapes": int(entry.get("config", {}).get("shapes", 0)),
        "metrics": dict(entry.get("metrics", {})),
        "license": entry.get("license", ""),
        "date": entry.get("date", ""),
        "parameters": dict(entry.get("parameters", {})),
        "path": str(package_dir(entry)),
        "latest": newest,
    }


def list_models(name: str | None = None) -> list[dict]:
    """Every registered model version, one dict each (name, version, category, shapes, metrics,
    license, date, parameters, path, latest), by name and newest version first.

    ``name`` restricts the list to one model.
    """
    records = []
    for model in [name] if name else model_names():
        manifest = read_manifest(model)
        for i, version in enumerate(versions_of(manifest)):
            records.append(model_record(model, version, manifest["versions"][version], newest=i == 0))
    return records


def info(spec: str) -> dict:
    """The manifest entry of ``NAME`` or ``NAME@X.Y.Z`` with where it lives: for ``zoo info``."""
    name, _, version = spec.partition("@")
    version, entry = resolve_version(name, version or None)
    path = package_dir(entry)
    return {
        "name": name,
        "version": version,
        "versions": versions_of(read_manifest(name)),
        "manifest": str(manifest_path(name)),
        "path": str(path),
        "model_card": str(path / "README.md"),
        "entry": entry,
    }


# --------------------------------------------------------------------------- schema


def validate_manifest(path: str | os.PathLike, check_files: bool = True) -> list[str]:
    """Problems with one model manifest (empty when it is valid).

    Checks the required keys and their types, semantic version keys, and, with ``check_files``,
    that each version's package exists, that every file's sha256 and size match the disk, that
    the package lists the same files, and that the parameter counts match the safetensors weights.
    """
    path = Path(path)
    try:
        manifest = read_manifest_file(path)
    except DataError as exc:
        return [str(exc)]
    problems = []
    if manifest.get("schema_version") != MANIFEST_SCHEMA_VERSION:
        problems.append(f"{path}: schema_version must be {MANIFEST_SCHEMA_VERSION}")
    if manifest.get("name") != path.stem:
        problems.append(f"{path}: name {manifest.get('name')!r} must equal the file stem {path.stem!r}")
    versions = manifest.get("versions")
    if not isinstance(versions, dict) or not versions:
        return problems + [f"{path}: no [versions.\"X.Y.Z\"] tables"]
    for version, entry in versions.items():
        where = f"{path} version {version}"
        try:
            parse_version(version)
        except InputError as exc:
            problems.append(f"{where}: {exc}")
        problems += _entry_problems(where, entry, check_files)
    return problems


def _entry_problems(where: str, entry: dict, check_files: bool) -> list[str]:
    problems = [
        f"{where}: {key} must be {kind.__name__}, got {type(entry.get(key)).__name__}"
        for key, kind in REQUIRED_VERSION_KEYS.items()
        if not isinstance(entry.get(key), kind)
    ]
    if problems:
        return problems
    if "shapes" not in entry["config"]:
        problems.append(f"{where}: config.shapes (the number of shapes) is missing")
    if "inputs" not in entry["training_data"] or "category_manifest" not in entry["training_data"]:
        problems.append(f"{where}: training_data needs category_manifest and inputs (mesh sha256s)")
    missing_files = [name for name in REQUIRED_PACKAGE_FILES if name not in entry["files"]]
    if missing_files:
        problems.append(f"{where}: files lacks {', '.join(missing_files)}")
    for name, record in entry["files"].items():
        if not (isinstance(record, dict) and re.fullmatch(r"[0-9a-f]{64}", str(record.get("sha256"))) and isinstance(record.get("size"), int)):
            problems.append(f"{where}: files.{name} needs sha256 (64 hex digits) and size (bytes)")
    if check_files and not problems:
        problems += _disk_problems(where, entry)
    return problems


def _disk_problems(where: str, entry: dict) -> list[str]:
    directory = package_dir(entry)
    if not directory.is_dir():
        return [f"{where}: package directory {directory} does not exist"]
    problems = []
    on_disk = sorted(p.name for p in directory.iterdir() if p.is_file() and not p.name.startswith("."))
    if on_disk != sorted(entry["files"]):
        problems.append(f"{where}: files on disk {on_disk} differ from the manifest's {sorted(entry['files'])}")
    for name, record in entry["files"].items():
        file = directory / name
        if not file.is_file():
            continue
        if file.stat().st_size != record["size"]:
            problems.append(f"{where}: {name} is {file.stat().st_size} bytes, the manifest says {record['size']}")
        if sha256_file(file) != record["sha256"]:
            problems.append(f"{where}: {name} sha256 differs from the manifest's {record['sha256']}")
    listed = read_checksums(directory) if (directory / CHECKSUMS).is_file() else {}
    manifest_sums = {k: v["sha256"] for k, v in entry["files"].items() if k != CHECKSUMS}
    if listed != manifest_sums:
        problems.append(f"{where}: {CHECKSUMS} in the package disagrees with the manifest's file hashes")
    counts = parameter_counts(directory)
    if counts != entry["parameters"]:
        problems.append(f"{where}: parameters {entry['parameters']} but the weights hold {counts}")
    return problems


def load_shape(path: str | os.PathLike, model=None, device: str = "cpu", verify: bool = True):
    """The NeuralShape saved in ``path`` (by ``NeuralShape.save``, :mod:`zoo.shape_file`), attached to its model.

    ``model``: None loads the model the file names (``NAME@X.Y.Z``) through the registry
    (``zoo.load``); a spec string (a package directory, ``hf-hub:...``) or a loaded Model is used
    instead. Either way the model's decoder must be the one the codes were fitted against (its
    sha256 is compared): another one is refused with :class:`~zoo.errors.ChecksumError`.
    """
    from .meshes import Similarity
    from .neural import NeuralShape
    from .shape_file import model_sha256, read_shape_file

    codes, positions, meta = read_shape_file(path)
    if model is None or isinstance(model, (str, os.PathLike)):
        model = load(meta["model"] if model is None else model, device=device, verify=verify)
    found = model_sha256(model.sdf.config, model.sdf.decoder)
    if found != meta["model_sha256"]:
        raise ChecksumError(
            f"{path} was fitted against {meta['model']} (decoder sha256 {meta['model_sha256'][:12]}...), but the model "
            f"given is {model.name}@{model.version} with decoder sha256 {found[:12]}...; its codes mean nothing to "
            f"another decoder: load {meta['model']} (zoo.load_shape(path) does), or fit the mesh again against this model"
        )
    config = model.sdf.config
    if tuple(codes.shape) != (config.n_codes, config.code_dim) or tuple(positions.shape) != (config.n_codes, 3):
        raise DataError(f"{path} holds codes {tuple(codes.shape)} and positions {tuple(positions.shape)}; "
                        f"{meta['model']} needs ({config.n_codes}, {config.code_dim}) and ({config.n_codes}, 3)")
    dev = model.sdf.codes.device
    shape = NeuralShape(meta["name"], model.sdf.decoder, config, codes.to(dev), positions.to(dev),
                        Similarity.from_json(meta["similarity"]), model)
    shape.fit, shape.metrics = json.loads(meta.get("fit", "{}")), json.loads(meta.get("metrics", "{}"))
    return shape
