"""Stage 1, normalise: one source mesh -> its normalised mesh and the similarity that made it.

Per shape, under ``<work>/normalised/``:

* ``<stem>.npz``  -- ``vertices`` (V, 3) float64 and ``faces`` (F, 3) int64 in the normalised
  frame (up +z, bounding box centred, largest extent 1). npz keeps float64 exactly, unlike OBJ.
* ``<stem>.json`` -- ``{"stem", "source_file", "source_sha256", "up", "similarity"}``, where
  ``similarity`` is :meth:`zoo.meshes.Similarity.to_dict` (normalised = s * R @ source + t).
* ``<stem>.npz.lock.json`` -- the stage record (see :mod:`pipeline.stages`).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zoo.errors import DataError
from zoo.files import atomic_path, atomic_write_text, sha256_file
from zoo.meshes import Similarity, load_mesh, normalise, up_rotation

from .stages import Stage, run_stage

FOLDER = "normalised"


@dataclass
class NormalisedShape:
    """A normalised mesh with where it came from. ``mesh`` is a ``trimesh.Trimesh``."""

    stem: str
    mesh: object
    similarity: Similarity
    source_sha256: str
    source_file: str


def normalised_paths(work_dir: str | os.PathLike, stem: str) -> tuple[Path, Path]:
    """(mesh .npz, transform .json) of one shape."""
    folder = Path(work_dir) / FOLDER
    return folder / f"{stem}.npz", folder / f"{stem}.json"


def up_config(up) -> str | list:
    """The orientation as it goes into a stage config: an axis name, or a rotation as nested lists."""
    return up if isinstance(up, str) else up_rotation(up).tolist()


def run_normalise(mesh_path: str | os.PathLike, work_dir: str | os.PathLike, stem: str | None = None,
                  up="z", force: bool = False) -> Path:
    """Normalise one mesh file unless already done; return the normalised .npz path."""
    mesh_path = Path(mesh_path)
    stem = stem or mesh_path.stem
    npz, meta = normalised_paths(work_dir, stem)
    stage = Stage(
        name="normalise",
        inputs={"mesh": mesh_path},
        config={"stem": stem, "up": up_config(up)},
        outputs={"mesh": npz, "transform": meta},
        code=(__name__,),  # with zoo.meshes and every project module it imports
    )

    def build():
        mesh = load_mesh(mesh_path)
        normalised, sim = normalise(mesh, up)
        with atomic_path(npz) as tmp:
            with open(tmp, "wb") as f:  # a file object, so numpy does not append ".npz" to the temp name
                np.savez(f, vertices=np.asarray(normalised.vertices, np.float64), faces=np.asarray(normalised.faces, np.int64))
        record = {
            "stem": stem,
            "source_file": str(mesh_path),
            "source_sha256": sha256_file(mesh_path),
            "up": up_config(up),
            "similarity": sim.to_dict(),
        }
        atomic_write_text(meta, json.dumps(record, indent=1, sort_keys=True) + "\n")

    run_stage(stage, build, force=force)
    return npz


def read_normalised(npz_path: str | os.PathLike) -> NormalisedShape:
    """Read what :func:`run_normalise` wrote (the .npz and the .json beside it)."""
    import trimesh

    npz_path = Path(npz_path)
    meta_path = npz_path.with_suffix(".json")
    try:
        with np.load(npz_path) as data:
            vertices, faces = data["vertices"], data["faces"]
        meta = json.loads(meta_path.read_text())
        sim = Similarity.from_dict(meta["similarity"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise DataError(f"normalised shape {npz_path} is missing or corrupt ({type(exc).__name__}: {exc}); "
                        "delete it and rerun the pipeline") from exc
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    return NormalisedShape(meta["stem"], mesh, sim, meta["source_sha256"], meta["source_file"])
