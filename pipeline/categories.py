"""Category manifests: which meshes make a category, their split, orientation and sha256.

A manifest is ``manifests/categories/<name>.toml``::

    category = "mugs"
    [sources.hoi4d]              # one table per source
    origin = "..."  license = "..."  up = "z"  evidence = "how the up axis was decided"
    [[mesh]]                     # one table per mesh
    stem = "hoi4d_mug_0001"  file = "mug/hoi4d_mug_0001.obj"  sha256 = "..."
    split = "train"  source = "hoi4d"  license = "..."   # optional: up = "y" overrides the source's

``file`` is relative to the data folder, which comes from an explicit argument, else the manifest's
top-level ``data = "DIR"`` (relative to the manifest's folder; ``zoo manifest`` writes it), else ``$ZOO_DATA``.
The meshes themselves are never part of the project.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from zoo.errors import DataError, InputError
from zoo.files import sha256_file
from zoo.meshes import up_rotation
from zoo.registry import toml_parser
from zoo.resources import bundled

tomllib = toml_parser()

DATA_ENV = "ZOO_DATA"
SPLITS = ("train", "test", "scene")


@dataclass(frozen=True)
class MeshEntry:
    """One mesh of a category; ``up`` is an axis name or a (3, 3) rotation as nested lists."""

    stem: str
    file: str
    sha256: str
    split: str
    source: str
    license: str
    up: str | list


@dataclass
class Category:
    name: str
    description: str
    meshes: dict[str, MeshEntry]
    sources: dict[str, dict]
    manifest: Path
    data_dir: Path | None = None  # the manifest's own data folder, if it names one

    def stems(self, split: str | None = None) -> list[str]:
        """Sorted stems of one split ("train", "test", "scene"), or of all when ``split`` is None."""
        if split is not None and split not in SPLITS:
            raise InputError(f"unknown split {split!r}; use one of {', '.join(SPLITS)} or None for all")
        return sorted(s for s, m in self.meshes.items() if split is None or m.split == split)

    @property
    def train_stems(self) -> list[str]:
        return self.stems("train")

    @property
    def test_stems(self) -> list[str]:
        return self.stems("test")

    def entry(self, stem: str) -> MeshEntry:
        try:
            return self.meshes[stem]
        except KeyError:
            raise InputError(f"{stem!r} is not a mesh of category {self.name!r} ({self.manifest}); "
                             f"known stems start {', '.join(self.stems()[:5])}, ...") from None

    @property
    def folders(self) -> list[str]:
        """Top-level folders of the data folder this category reads (e.g. ["mug"])."""
        return sorted({m.file.split("/")[0] for m in self.meshes.values()})


def manifests_folder() -> Path:
    """The bundled category manifests (:func:`zoo.resources.bundled`): the clone's ``manifests/categories``,
    else the installed wheel's copy."""
    return bundled("manifests") / "categories"


def list_categories(manifest_dir: str | os.PathLike | None = None) -> list[str]:
    return sorted(p.stem for p in Path(manifest_dir or manifests_folder()).glob("*.toml"))


def manifest_path(category: str | os.PathLike, manifest_dir: str | os.PathLike | None = None) -> Path:
    """A category name ("mugs") or a path to a .toml manifest -> the manifest's path."""
    p = Path(category)
    if p.suffix == ".toml":
        if not p.is_file():
            raise DataError(f"category manifest {p} does not exist")
        return p
    manifest_dir = Path(manifest_dir or manifests_folder())
    p = manifest_dir / f"{category}.toml"
    if not p.is_file():
        known = ", ".join(list_categories(manifest_dir)) or "none"
        raise InputError(f"unknown category {str(category)!r}; known categories: {known} (manifests in {manifest_dir})")
    return p


def load_category(category: str | os.PathLike, manifest_dir: str | os.PathLike | None = None) -> Category:
    """Parse and check a category manifest (by name or path)."""
    path = manifest_path(category, manifest_dir)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise DataError(f"cannot read category manifest {path}: {exc}; fix the TOML") from exc
    sources = doc.get("sources", {})
    meshes: dict[str, MeshEntry] = {}
    for i, row in enumerate(doc.get("mesh", [])):
        entry = _mesh_entry(row, sources, path, i)
        if entry.stem in meshes:
            raise DataError(f"{path}: stem {entry.stem!r} is listed twice; stems must be unique")
        meshes[entry.stem] = entry
    if not meshes:
        raise DataError(f"{path} lists no meshes; add [[mesh]] tables")
    data = doc.get("data")
    data_dir = (path.parent / data).resolve() if isinstance(data, str) and data else None
    return Category(doc.get("category", path.stem), doc.get("description", ""), meshes, sources, path, data_dir)


def _mesh_entry(row: dict, sources: dict, path: Path, i: int) -> MeshEntry:
    missing = [k for k in ("stem", "file", "sha256", "split", "source") if k not in row]
    if missing:
        raise DataError(f"{path}: mesh #{i + 1} lacks {', '.join(missing)}; every [[mesh]] needs stem, file, sha256, split, source")
    if row["split"] not in SPLITS:
        raise DataError(f"{path}: mesh {row['stem']!r} has split {row['split']!r}; use one of {', '.join(SPLITS)}")
    if row["source"] not in sources:
        raise DataError(f"{path}: mesh {row['stem']!r} names source {row['source']!r}, which has no [sources.{row['source']}] table")
    source = sources[row["source"]]
    up = row.get("up", source.get("up", "z"))
    try:
        up_rotation(up)
    except InputError as exc:
        raise DataError(f"{path}: mesh {row['stem']!r} has a bad orientation: {exc}") from exc
    return MeshEntry(row["stem"], row["file"], row["sha256"].lower(), row["split"], row["source"],
                     row.get("license", source.get("license", "")), up)


def resolve_data_dir(data_dir: str | os.PathLike | None = None, category: Category | None = None) -> Path:
    """The data folder: ``data_dir`` if given, else the manifest's, else ``$ZOO_DATA``; checked to hold the
    category's folders."""
    if data_dir is None and category is not None:
        data_dir = category.data_dir
    if data_dir is None:
        data_dir = os.environ.get(DATA_ENV)
        if not data_dir:
            raise DataError(f"no data folder given: pass --data DIR or set ${DATA_ENV} to the folder that holds "
                            "one sub-folder per category (mug/, bottle/, ...)")
    root = Path(data_dir).expanduser()
    if not root.is_dir():
        raise DataError(f"data folder {root} does not exist; pass --data DIR or set ${DATA_ENV}")
    if category is not None:
        absent = [f for f in category.folders if not (root / f).is_dir()]
        if absent:
            raise DataError(f"data folder {root} lacks {', '.join(f + '/' for f in absent)} needed by category "
                            f"{category.name!r}; point --data / ${DATA_ENV} at the folder that holds them")
    return root


def verify_meshes(category: Category, data_dir: str | os.PathLike | None = None,
                  stems: list[str] | None = None) -> dict[str, Path]:
    """Check each mesh's file against its recorded sha256; return {stem: path}.

    A missing or changed mesh is a :class:`DataError` naming the file and both hashes.
    """
    root = resolve_data_dir(data_dir, category)
    return {stem: verified_mesh(category, root, stem) for stem in (category.stems() if stems is None else stems)}


def verified_mesh(category: Category, root: Path, stem: str) -> Path:
    """The file of mesh ``stem`` under the data folder ``root``, checked against its recorded sha256."""
    entry = category.entry(stem)
    path = root / entry.file
    if not path.is_file():
        raise DataError(f"mesh {path} of category {category.name!r} is missing (expected sha256 {entry.sha256}); "
                        "restore it in the data folder")
    actual = sha256_file(path)
    if actual != entry.sha256:
        raise DataError(f"mesh {path} has changed: sha256 {actual}, but {category.manifest.name} expects {entry.sha256}; "
                        "restore the original file, or update the manifest if the change is intended")
    return path
