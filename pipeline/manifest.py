"""`zoo manifest`: a category manifest for a folder of meshes, so a user's own category fits by file.

Every mesh file trimesh reads (:data:`zoo.meshes.MESH_SUFFIXES`) under the folder becomes a ``[[mesh]]``
with its sha256; its stem is its path below the folder with ``/`` as ``_`` (unique even where two
sub-folders hold files of one name); its source is its first sub-folder (``"."`` for files at the top);
a seeded shuffle of the stems puts ``test_fraction`` of each source in the test split. The manifest names
the folder as its data folder (``data``, relative to the manifest), so `zoo fit-category NAME.toml` needs
no ``--data``. See :mod:`pipeline.categories` for the format.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

from zoo.errors import DataError, InputError
from zoo.files import atomic_write_text, sha256_file
from zoo.meshes import MESH_SUFFIXES, up_rotation

from .package import dumps_toml


def mesh_files(folder: Path) -> list[Path]:
    """The mesh files under ``folder`` (any depth), sorted by their path below it."""
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


def stem_of(relative: Path) -> str:
    """A manifest stem for a file's path below the data folder: ``mug/a.obj`` -> ``mug_a``."""
    return "_".join(relative.with_suffix("").parts)


def build_manifest(folder: str | os.PathLike, name: str, up: str = "z", test_fraction: float = 0.2, seed: int = 0,
                   license: str = "unspecified", manifest_dir: str | os.PathLike | None = None) -> dict:
    """The manifest of the meshes under ``folder`` as a dict (see the module); ``manifest_dir`` is where it
    will be written (its ``data`` is relative to it)."""
    folder = Path(folder).expanduser().resolve()
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder; give the folder that holds the category's meshes")
    up_rotation(up)  # a bad axis fails here, not when the category is fitted
    if not 0 <= test_fraction < 1:
        raise InputError(f"test_fraction must be in [0, 1), got {test_fraction}")
    files = mesh_files(folder)
    if not files:
        raise DataError(f"{folder} holds no mesh files ({', '.join(MESH_SUFFIXES)})")
    rows = []
    for path in files:
        relative = path.relative_to(folder)
        rows.append({"stem": stem_of(relative), "file": relative.as_posix(), "sha256": sha256_file(path),
                     "split": "train", "source": relative.parts[0] if len(relative.parts) > 1 else "."})
    duplicates = sorted({r["stem"] for r in rows if sum(q["stem"] == r["stem"] for q in rows) > 1})
    if duplicates:
        raise DataError(f"{folder}: files {', '.join(duplicates)} differ only in their suffix; keep one of each")
    _split(rows, test_fraction, seed)
    data = os.path.relpath(folder, Path(manifest_dir or ".").resolve())
    sources = {s: {"origin": str(folder / s) if s != "." else str(folder), "license": license, "up": up}
               for s in sorted({r["source"] for r in rows})}
    return {"category": name, "description": f"{len(rows)} meshes under {folder}", "data": Path(data).as_posix(),
            "sources": sources, "mesh": rows}


def _split(rows: list[dict], test_fraction: float, seed: int) -> None:
    """Mark ``test_fraction`` of each source's meshes (rounded down, by a seeded shuffle of the stems) as test."""
    for source in sorted({r["source"] for r in rows}):
        mine = sorted((r for r in rows if r["source"] == source), key=lambda r: r["stem"])
        random.Random(f"{seed}:{source}").shuffle(mine)
        for row in mine[: int(len(mine) * test_fraction)]:
            row["split"] = "test"


def write_manifest(folder: str | os.PathLike, name: str, out: str | os.PathLike | None = None, **options) -> Path:
    """Write the manifest of ``folder``'s meshes to ``out`` (default NAME.toml here); -> its path."""
    out = Path(out or f"{name}.toml")
    manifest = build_manifest(folder, name, manifest_dir=out.parent, **options)
    header = f"Category {name!r}, written by `zoo manifest`: one [[mesh]] per file, sha256 of each."
    atomic_write_text(out, dumps_toml(manifest, header))
    return out
