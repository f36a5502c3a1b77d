"""Stage package: a `zoo fit-category` output becomes a versioned, self-verifying release.

``package_model`` copies the fit output's config and weights into ``zoo/pretrained/NAME-X.Y.Z/``,
writes the model card (``README.md``) and ``SHA256SUMS``, and adds the version to
``manifests/models/NAME.toml``. ``push_package`` uploads a release to the Hugging Face Hub and
tags it with its version, so ``zoo.load("hf-hub:ORG/NAME@X.Y.Z")`` finds it.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from zoo import registry
from zoo.errors import DataError, InputError, require
from zoo.files import CHECKSUMS, atomic_write_text, sha256_file, verify_directory, write_checksums
from zoo.resources import inside_installed_package

CARD = "README.md"
NONCOMMERCIAL = "non-commercial research only"

# Which upstream terms each training mesh carries, by its file-stem prefix (from
# ../shared/meshes/SOURCES.md). ShapeNet- and HOI4D-derived meshes restrict the weights trained on
# them to non-commercial research; the others are stated here so the model card can list them.
SOURCE_TERMS = (
    ("hoi4d_", "HOI4D scans (via zerchen/object_sim)", "HOI4D dataset terms: non-commercial research", True),
    ("shapenet_", "ShapeNetCore (via NVlabs/mimicgen)", "ShapeNet terms of use and the NVIDIA License: non-commercial research", True),
    ("edf_mug", "3D Warehouse / TurboSquid meshes (via tomato1mule/edf_env, MIT repo)", "upstream terms not restated", False),
    ("edf_bottle", "tomato1mule/edf (MIT repo)", "per-mesh source not stated", False),
    ("bulletarm_", "ColinKohler/BulletArm (MIT repo)", "mesh origin not stated", False),
    ("3dnet_", "3DNet meshes (via ColinKohler/BulletArm, MIT repo)", "3DNet terms not restated", False),
    ("industreal_", "IsaacGymEnvs IndustReal (BSD-3-Clause; gears courtesy of NIST)", "BSD-3-Clause", False),
    ("factory_", "IsaacGymEnvs Factory (BSD-3-Clause)", "BSD-3-Clause", False),
    ("pybullet_", "pybullet 3.2.7 data (zlib)", "zlib", False),
)


@dataclass
class Packaged:
    name: str
    version: str
    path: Path
    manifest: Path
    entry: dict


# --------------------------------------------------------------------------- TOML (write side)
# The manifests are read with tomllib; the standard library has no writer, and the manifests use
# only tables, strings, numbers, booleans and arrays, so a small writer suffices.

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise InputError(f"cannot write {type(value).__name__} {value!r} to a manifest; use str, numbers, lists or tables")


def _is_short_leaf(table: dict) -> bool:
    """Small tables of plain values (a file's sha256 and size) read best inline."""
    return all(not isinstance(v, (dict, list)) for v in table.values()) and len(_toml_value(table)) <= 100


def dumps_toml(data: dict, header: str = "") -> str:
    """TOML text for ``data`` (dicts become tables, small leaf dicts inline tables)."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    _emit_table(lines, [], data)
    return "\n".join(lines).lstrip("\n") + "\n"


def _is_table_array(value) -> bool:
    """A non-empty list of tables: written as ``[[key]]`` blocks (a manifest's meshes), not one long line."""
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _emit_table(lines: list[str], prefix: list[str], table: dict) -> None:
    inline = {k: v for k, v in table.items()
              if not (isinstance(v, dict) or _is_table_array(v)) or (isinstance(v, dict) and v and _is_short_leaf(v))}
    subtables = {k: v for k, v in table.items() if k not in inline}
    if prefix and (inline or not subtables):
        lines += ["", "[" + ".".join(_toml_key(k) for k in prefix) + "]"]
    lines += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in inline.items()]
    for key, sub in subtables.items():
        if isinstance(sub, dict):
            _emit_table(lines, prefix + [key], sub)
            continue
        for row in sub:
            lines += ["", "[[" + ".".join(_toml_key(k) for k in prefix + [key]) + "]]"]
            lines += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in row.items()]


def toml_safe(value):
    """JSON-like data made writable as TOML: None dropped (TOML has no null), tuples to lists."""
    if isinstance(value, dict):
        return {str(k): toml_safe(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [toml_safe(v) for v in value if v is not None]
    if hasattr(value, "item") and callable(value.item):  # numpy / torch scalars
        return value.item()
    if isinstance(value, (_dt.date, Path)):
        return str(value)
    return value


# --------------------------------------------------------------------------- the fit output


def resolve_fit_dir(source: str | os.PathLike, fit_dir: str | os.PathLike | None = None) -> Path:
    """The `zoo fit-category` output to package: ``fit_dir`` if given, ``source`` if it is one, else ``out/CATEGORY``."""
    if fit_dir is not None:
        candidate = Path(fit_dir)
    elif Path(source).is_dir():
        candidate = Path(source)
    else:
        candidate = Path("out") / str(source)
    if not (candidate / "config.json").is_file():
        raise DataError(
            f"{candidate} holds no config.json: it is not a `zoo fit-category` output; "
            f"run `zoo fit-category {source} --out {candidate}` first or pass --fit-dir DIR"
        )
    return candidate


def package_files(fit_dir: Path) -> list[Path]:
    """The files of a fit output that belong in a release: config and weights, not caches or stage locks."""
    files = [
        p
        for p in sorted(fit_dir.iterdir())
        if p.is_file()
        and not p.name.startswith(".")
        and (p.suffix == ".safetensors" or (p.suffix == ".json" and not p.name.endswith(".lock.json")))
    ]
    if not any(p.name == "sdf.safetensors" for p in files):
        raise DataError(f"{fit_dir} has no sdf.safetensors; the NeuralSDF stage of `zoo fit-category` has not finished")
    return files


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{path} is not valid JSON ({exc})") from exc


# --------------------------------------------------------------------------- provenance and license


def license_for(shapes: list[str], declared: str = "") -> tuple[str, list[dict]]:
    """``(license, sources)`` of weights trained on ``shapes`` (mesh file stems).

    Any ShapeNet- or HOI4D-derived mesh makes the weights non-commercial research only, whatever
    ``declared`` says; otherwise ``declared`` (from the fit config) or a pointer to the sources.
    """
    sources: dict[str, dict] = {}
    for shape in shapes:
        match = next((t for t in SOURCE_TERMS if shape.startswith(t[0])), None)
        origin, terms, noncommercial = match[1:] if match else ("unknown source", "unknown: check before use", False)
        row = sources.setdefault(origin, {"source": origin, "terms": terms, "non_commercial": noncommercial, "meshes": 0})
        row["meshes"] += 1
    rows = list(sources.values())
    if any(r["non_commercial"] for r in rows):
        return f"{NONCOMMERCIAL} (trained on ShapeNet- and HOI4D-derived meshes)", rows
    if declared:
        return declared, rows
    return "research use; check the upstream terms of the training meshes listed in the model card", rows


def training_data(config: dict, category: str) -> dict:
    """Provenance for the manifest: the category manifest (and its sha256), the split, input hashes."""
    declared = dict(config.get("training_data") or {})
    shapes = list(config.get("shapes", []))
    category_manifest = declared.get("category_manifest") or f"manifests/categories/{category}.toml"
    path = _category_manifest_path(category_manifest)
    data = {
        "category_manifest": str(category_manifest),
        "split": declared.get("split", "train"),
        "shapes": shapes,
        "inputs": declared.get("inputs") or declared.get("input_sha256") or {},
    }
    if path is not None:
        data["category_manifest_sha256"] = sha256_file(path)
        if not data["inputs"]:
            data["inputs"] = _mesh_hashes_from_category_manifest(path, shapes)
    data.update({k: v for k, v in declared.items() if k not in data and k != "input_sha256"})
    return toml_safe(data)


def _category_manifest_path(name: str) -> Path | None:
    """Find a category manifest named as in a fit config: a path, or relative to the manifests folder."""
    candidates = [registry.manifests_dir().parent / name, registry.manifests_dir() / "categories" / Path(name).name, Path(name)]
    return next((p for p in candidates if p.is_file()), None)


def _mesh_hashes_from_category_manifest(path: Path, shapes: list[str]) -> dict[str, str]:
    """``{stem: sha256}`` of the training meshes, wherever the category manifest records them."""
    wanted, found = set(shapes), {}

    def visit(node, key=None):
        if isinstance(node, dict):
            stem = node.get("stem") or node.get("name") or (Path(node["file"]).stem if "file" in node else key)
            if stem in wanted and isinstance(node.get("sha256"), str):
                found[stem] = node["sha256"]
            for k, v in node.items():
                if k in wanted and isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v):
                    found[k] = v
                visit(v, k)
        elif isinstance(node, list):
            for item in node:
                visit(item, key)

    visit(registry.read_manifest_file(path))
    return dict(sorted(found.items()))


def collect_metrics(config: dict, fit_dir: Path, metrics_file: Path | None) -> dict:
    """The evaluation stage's metrics: the config's, then ``metrics.json`` in the fit output, then ``metrics_file``."""
    metrics = dict(config.get("metrics") or {})
    for path in (fit_dir / "metrics.json", metrics_file):
        if path is not None and Path(path).is_file():
            metrics.update(read_json(Path(path)))
    return toml_safe(metrics)


def metrics_command_of(config: dict, metrics: dict, given: str | None) -> str:
    """How the metrics were measured, as recorded by the evaluation stage (or given by the caller)."""
    for candidate in (given, metrics.pop("command", None), config.get("metrics_command")):
        if candidate:
            return str(candidate)
    return "not recorded" if not metrics else "recorded without its command"


# --------------------------------------------------------------------------- the model card


def _format_number(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _describe(section: dict, keys: tuple[str, ...]) -> str:
    return ", ".join(f"{k} {section[k]}" for k in keys if k in section)


def _flatten(metrics: dict, prefix: str = "") -> list[tuple[str, str]]:
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows += _flatten(value, f"{prefix}{key}.")
        else:
            shown = ", ".join(_format_number(v) for v in value) if isinstance(value, list) else _format_number(value)
            rows.append((f"{prefix}{key}", shown))
    return rows


def model_card(name: str, version: str, config: dict, entry: dict, sources: list[dict]) -> str:
    """The package's README.md: what it is, metrics and how they were measured, data, license, loading."""
    shapes = entry["config"]["shapes"]
    params = entry["parameters"]
    detector = "with an amortized NeuralSDF–triangle collision detector" if "detector" in params else "without a collision detector yet"
    lines = [
        f"# {name} {version}",
        "",
        f"A category-level neural signed distance function for the **{entry['category']}** category, fitted to "
        f"{shapes} real meshes with sdfzoo (dynamic code clouds: one shared decoder, one code cloud per shape), "
        f"{detector}. Parameters count every stored scalar (weights, codes, code positions). Each shape answers in its source mesh's frame and units; signed distance is negative inside.",
        "",
        "| | |",
        "|---|---|",
        f"| version | {version} |",
        f"| date | {entry['date']} |",
        f"| shapes | {shapes} |",
        f"| NeuralSDF | {_describe(config.get('sdf') or {}, ('n_codes', 'code_dim', 'hidden', 'smooth_beta', 'storage_dtype'))} |",
        f"| detector | {_describe(config.get('detector') or {}, ('output', 'vertex_sdf', 'hidden', 'triangle_feature', 'edge_range')) or 'none'} |",
        *[f"| parameters ({key}) | {value:,} |" for key, value in params.items()],
        f"| license | {entry['license']} |",
        "",
        "## Load it",
        "",
        "```python",
        "import zoo",
        f'm = zoo.load("{name}@{version}")  # bundled with sdfzoo; checks every file\'s sha256',
        f"s = m.shape({(config.get('shapes') or ['SHAPE'])[0]!r})  # a NeuralSDF in that mesh's frame and units",
        "d, g = s.value_and_grad(points)  # (N, 3) -> (N,), (N, 3)",
        "```",
        "",
        f"From a copy of this folder: `zoo.load(\"path/to/{name}-{version}\")`; from the Hugging Face Hub once pushed "
        f"(`zoo push {name}@{version} --repo ORG/{name}`): `zoo.load(\"hf-hub:ORG/{name}@{version}\")` "
        "(works offline from the cache with `HF_HUB_OFFLINE=1`).",
        "",
        "## Metrics",
        "",
    ]
    metric_rows = _flatten(entry["metrics"])
    if metric_rows:
        lines += ["| metric | value |", "|---|---|", *[f"| {k} | {v} |" for k, v in metric_rows], ""]
    else:
        lines += ["No metrics were recorded for this release.", ""]
    if any(k.rsplit(".", 1)[-1].startswith(("near_", "sign_agreement")) for k, _ in metric_rows):
        lines += [
            "near_p50 / near_p90 / near_mean: |signed-distance error| at points near the surface, as a fraction of the "
            "object's size (its largest extent), against the mesh's exact SDF in its source frame; sign_agreement: the "
            "fraction of points away from the surface whose sign is right. Per split, each is the median over the "
            "shapes; worst_near_p50 and min_sign_agreement are the worst shape's (see pipeline/evaluate_sdf.py).",
            "",
        ]
    lines += [f"Measured by: `{entry['metrics_command']}`", ""]
    data = entry["training_data"]
    lines += [
        "## Training data",
        "",
        f"{shapes} meshes of the {data.get('split', 'train')} split listed in `{data['category_manifest']}`"
        + (f" (sha256 `{data['category_manifest_sha256']}`)" if "category_manifest_sha256" in data else "")
        + f"; the sha256 of every input mesh is in `manifests/models/{name}.toml`. Meshes are not shipped.",
        "",
        "| source | meshes | terms |",
        "|---|---|---|",
        *[f"| {r['source']} | {r['meshes']} | {r['terms']} |" for r in sources],
        "",
        f"Shapes: {', '.join(config.get('shapes', []))}",
        "",
        *_set_aside_lines(data.get("set_aside") or []),
        *_written_by_lines(data.get("sdfzoo") or {}),
        "## License",
        "",
        f"The weights: **{entry['license']}**. Weights fitted to meshes carry the terms of those meshes: ShapeNet- and "
        "HOI4D-derived training data allow non-commercial research use only. The sdfzoo code itself is MIT.",
        "",
        "## Files",
        "",
        "Every file's sha256 is in `SHA256SUMS`; `zoo.load` refuses a file that does not match.",
        "",
        "| file | bytes | sha256 |",
        "|---|---|---|",
        *[f"| {f} | {r['size']} | `{r['sha256']}` |" for f, r in entry["files"].items() if f not in (CARD, CHECKSUMS)],
        "",
    ]
    return "\n".join(lines)


def _set_aside_lines(set_aside: list[dict]) -> list[str]:
    """The meshes `zoo fit-category` left out of the training, with the stage and the reason."""
    if not set_aside:
        return []
    return [f"Set aside ({len(set_aside)} meshes that failed a stage; the model was fitted without them):", "",
            "| mesh | stage | reason |", "|---|---|---|",
            *[f"| {row['stem']} | {row['stage']} | {row['reason'].replace('|', '/')} |" for row in set_aside], ""]


def _written_by_lines(written_by: dict) -> list[str]:
    if not written_by:
        return []
    commit = f", source commit `{written_by['commit']}`" if written_by.get("commit") else ""
    return [f"Fitted by sdfzoo {written_by.get('version', '?')}{commit}.", ""]


# --------------------------------------------------------------------------- packaging


def file_records(directory: Path) -> dict[str, dict]:
    return {
        p.name: {"sha256": sha256_file(p), "size": p.stat().st_size}
        for p in sorted(directory.iterdir())
        if p.is_file() and not p.name.startswith(".")
    }


def config_summary(config: dict) -> dict:
    """What the manifest keeps of config.json: counts and the network sizes, not per-shape data."""
    summary = {"shapes": len(config.get("shapes", [])), "sdf": config.get("sdf") or {}}
    if config.get("detector"):
        summary["detector"] = config["detector"]
    return toml_safe(summary)


def read_models_manifest(name: str) -> dict:
    path = registry.manifest_path(name)
    if path.is_file():
        return registry.read_manifest_file(path)
    return {"schema_version": registry.MANIFEST_SCHEMA_VERSION, "name": name, "versions": {}}


def write_models_manifest(name: str, manifest: dict) -> Path:
    """Write the manifest with versions newest first, atomically."""
    manifest["versions"] = {v: manifest["versions"][v] for v in registry.sort_versions(manifest["versions"])}
    header = (
        f"sdfzoo model manifest: {name}. Written by `zoo package`; one [versions.\"X.Y.Z\"] table per release.\n"
        "Each release's package lives in zoo/pretrained/<package>; files lists the sha256 and size of each of its files."
    )
    path = registry.manifest_path(name)
    atomic_write_text(path, dumps_toml(manifest, header=header))
    return path


def refuse_installed_package() -> None:
    """A release goes into the registry's folders; from an installed wheel those are inside site-packages,
    which a release must never change: then it asks for folders of the user's (the registry reads them too)."""
    folders = {registry.PRETRAINED_ENV: registry.pretrained_dir(), registry.MANIFESTS_ENV: registry.manifests_dir()}
    inside = {env: folder for env, folder in folders.items() if inside_installed_package(folder)}
    if inside:
        raise InputError(
            f"zoo package writes a release into the registry's folders, here those of the installed package "
            f"({', '.join(str(f) for f in inside.values())}), which it never changes; set "
            + " and ".join(f"${env}" for env in inside)
            + " to folders of yours (zoo.load and `zoo list` read them too), e.g. "
            "ZOO_PRETRAINED=~/zoo/pretrained ZOO_MANIFESTS=~/zoo/manifests zoo package ..., or run it from a clone"
        )


def package_model(
    source: str | os.PathLike,
    version: str,
    name: str | None = None,
    fit_dir: str | os.PathLike | None = None,
    force: bool = False,
    metrics_file: str | os.PathLike | None = None,
    metrics_command: str | None = None,
    date: str | None = None,
) -> Packaged:
    """Release the fit output of ``source`` (a category name or a fit directory) as ``NAME@version``.

    Refuses to replace an existing release unless ``force``. Writes the package into a staging
    folder first and renames it into place, then writes the manifest atomically.
    """
    registry.parse_version(version)
    refuse_installed_package()  # first: from a wheel, nothing else can succeed
    fit = resolve_fit_dir(source, fit_dir)
    if (fit / CHECKSUMS).is_file():
        verify_directory(fit)  # never release a fit output that changed after it was written
    config = read_json(fit / "config.json")
    category = config.get("category") or (str(source) if not Path(source).is_dir() else fit.name)
    name = registry.check_model_name(name or config.get("name") or category)

    manifest = read_models_manifest(name)
    destination = registry.pretrained_dir() / f"{name}-{version}"
    if not force and (version in manifest["versions"] or destination.exists()):
        raise InputError(
            f"{name}@{version} already exists ({destination}); bump the version "
            f"(existing: {', '.join(registry.sort_versions(manifest['versions'])) or 'none'}) or pass --force to replace it"
        )

    staging = destination.with_name(f".{destination.name}.staging-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        entry = _build_package(staging, fit, config, name, version, category, metrics_file, metrics_command, date)
        _replace_directory(staging, destination)
    finally:
        shutil.rmtree(staging, ignore_errors=True)

    manifest["versions"][version] = entry
    path = write_models_manifest(name, manifest)
    problems = registry.validate_manifest(path)
    if problems:
        raise DataError("the manifest just written does not validate: " + "; ".join(problems))
    return Packaged(name, version, destination, path, entry)


def _build_package(staging, fit, config, name, version, category, metrics_file, metrics_command, date) -> dict:
    """Fill ``staging`` with the release and return its manifest entry."""
    for path in package_files(fit):
        if path.name != "config.json":
            shutil.copy2(path, staging / path.name)
    metrics = collect_metrics(config, fit, Path(metrics_file) if metrics_file else None)
    command = metrics_command_of(config, metrics, metrics_command)
    shapes = list(config.get("shapes", []))
    license_text, sources = license_for(shapes, str(config.get("license") or ""))
    data = training_data(config, category)
    config = {**config, "name": name, "version": version, "category": category, "license": license_text,
              "metrics": metrics, "training_data": data}
    config.setdefault("format_version", 1)
    (staging / "config.json").write_text(json.dumps(config, indent=2) + "\n")

    entry = {
        "date": date or _dt.datetime.now(_dt.timezone.utc).date().isoformat(),
        "package": f"{name}-{version}",
        "category": category,
        "format_version": int(config["format_version"]),
        "license": license_text,
        "config": config_summary(config),
        "parameters": registry.parameter_counts(staging),
        "metrics": metrics,
        "metrics_command": command,
        "training_data": data,
        "files": {},
    }
    # The card lists the weights' hashes, so it is written after them and before SHA256SUMS.
    entry["files"] = file_records(staging)
    (staging / CARD).write_text(model_card(name, version, config, entry, sources))
    write_checksums(staging)
    entry["files"] = file_records(staging)
    return entry


def _replace_directory(staging: Path, destination: Path) -> None:
    """Move ``staging`` onto ``destination``; an old release is kept aside until the new one is in place."""
    old = destination.with_name(f".{destination.name}.old-{os.getpid()}")
    if destination.exists():
        os.replace(destination, old)
    try:
        os.replace(staging, destination)
    except BaseException:
        if old.exists():
            os.replace(old, destination)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- the Hub


def push_package(spec: str, repo_id: str, token: str | None = None, private: bool | None = None, api=None) -> dict:
    """Upload release ``NAME@X.Y.Z`` to Hub repository ``repo_id`` and tag the commit with the version.

    ``api`` is an ``HfApi``-like object (tests pass a fake); by default ``HfApi(token=token)``.
    """
    name, _, version = spec.partition("@")
    version, entry = registry.resolve_version(name, version or None)
    folder = registry.package_dir(entry)
    registry.verify_package(folder, expected_checksums_sha256=entry["files"][CHECKSUMS]["sha256"])
    if api is None:
        api = require("huggingface_hub", extra="pipeline").HfApi(token=token)
    api.create_repo(repo_id, repo_type="model", private=private, exist_ok=True)
    commit = api.upload_folder(
        repo_id=repo_id,
        folder_path=str(folder),
        repo_type="model",
        commit_message=f"{name} {version}",
        ignore_patterns=[".*"],
    )
    revision = getattr(commit, "oid", None)
    api.create_tag(repo_id, tag=version, tag_message=f"sdfzoo {name} {version}", revision=revision, repo_type="model")
    recorded = record_push(name, version, {"repo": repo_id, "tag": version, "commit": revision})
    return {"repo": repo_id, "tag": version, "commit": revision, "spec": f"hf-hub:{repo_id}@{version}",
            "manifest": str(recorded) if recorded else None}


def record_push(name: str, version: str, hub: dict) -> Path | None:
    """Write where a release was pushed (repo, tag, commit) into its manifest entry, so that loading it from the
    Hub pins that commit and checks the files against the entry's hashes; -> the manifest, or None for a
    release of the installed package (whose files are never changed: its users load it by name anyway)."""
    if inside_installed_package(registry.manifests_dir()):
        return None
    manifest = read_models_manifest(name)
    manifest["versions"][version]["hub"] = hub
    return write_models_manifest(name, manifest)
