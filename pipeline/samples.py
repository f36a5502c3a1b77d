"""Stage 2, SDF samples: a normalised mesh -> exact signed-distance samples in HDF5.

One file per shape, ``<work>/samples/<stem>.h5`` (schema version 1):

* dataset ``points`` (N, 3) float32 -- sample positions in the NORMALISED frame;
* dataset ``sdf``    (N,)   float32 -- exact signed distance there, negative inside, normalised units;
  both chunked and gzip-compressed (with the shuffle filter);
* attributes: ``schema_version`` (int, 1), ``stem``, ``source_sha256`` (the raw mesh file),
  ``config`` (JSON of :class:`SampleConfig` plus ``shape_seed``, the per-shape seed actually used),
  ``similarity`` (JSON of :class:`zoo.meshes.Similarity`, source -> normalised),
  ``package_version`` (sdfzoo's version).

Multiply a normalised distance by ``1 / similarity.scale`` for source units.
Files are written to a temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import zoo
from zoo.config import DictConfig
from zoo.errors import DataError, InputError, require
from zoo.files import atomic_path
from zoo.meshes import (
    DEFAULT_FRACTIONS,
    DEFAULT_N_POINTS,
    DEFAULT_NEAR_SIGMAS,
    DEFAULT_PADDING,
    Similarity,
    sample_sdf,
)
from zoo.progress import task_bar

from .normalise import read_normalised, run_normalise
from .presets import Presets
from .stages import Stage, run_stage

SCHEMA_VERSION = 1
FOLDER = "samples"
_CHUNK_ROWS = 32_768


@dataclass(frozen=True)
class SampleConfig(DictConfig):
    """How many samples and where; see :func:`zoo.meshes.sample_sdf` for the meaning and defaults."""

    _config_name = "sample config"

    n_points: int = DEFAULT_N_POINTS
    seed: int = 0
    near_sigmas: tuple[float, float] = DEFAULT_NEAR_SIGMAS
    fractions: tuple[float, float, float] = DEFAULT_FRACTIONS
    padding: float = DEFAULT_PADDING


PRESETS = Presets("sample", quick=SampleConfig(n_points=50_000), default=SampleConfig())
preset = PRESETS.lookup


@dataclass
class ShapeSamples:
    """One shape's samples: points (N, 3) and sdf (N,) float32, both in the normalised frame."""

    stem: str
    points: np.ndarray
    sdf: np.ndarray
    similarity: Similarity
    source_sha256: str = ""
    config: dict = field(default_factory=dict)


def samples_path(work_dir: str | os.PathLike, stem: str) -> Path:
    return Path(work_dir) / FOLDER / f"{stem}.h5"


def shape_seed(seed: int, stem: str) -> int:
    """A per-shape seed, so shapes do not share one noise pattern yet each file is reproducible."""
    return int.from_bytes(hashlib.sha256(f"{int(seed)}:{stem}".encode()).digest()[:8], "little")


# --------------------------------------------------------------------------- HDF5


def write_samples(path: str | os.PathLike, samples: ShapeSamples) -> Path:
    """Write one shape's samples (schema above) atomically; return the path."""
    h5py = require("h5py")
    path = Path(path)
    points = np.ascontiguousarray(samples.points, dtype=np.float32)
    sdf = np.ascontiguousarray(samples.sdf, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or sdf.shape != (len(points),) or len(points) == 0:
        raise InputError(f"samples need points (N, 3) and sdf (N,) with N > 0, got {points.shape} and {sdf.shape}")
    rows = min(_CHUNK_ROWS, len(points))
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("points", data=points, chunks=(rows, 3), compression="gzip", compression_opts=4, shuffle=True)
            f.create_dataset("sdf", data=sdf, chunks=(rows,), compression="gzip", compression_opts=4, shuffle=True)
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["stem"] = samples.stem
            f.attrs["source_sha256"] = samples.source_sha256
            f.attrs["config"] = json.dumps(samples.config, sort_keys=True)
            f.attrs["similarity"] = samples.similarity.to_json()
            f.attrs["package_version"] = zoo.__version__
    return path


def read_samples(path: str | os.PathLike) -> ShapeSamples:
    """Read a samples file; DataError if it is missing, corrupt, truncated or of another schema."""
    h5py = require("h5py")
    path = Path(path)
    if not path.is_file():
        raise DataError(f"samples file {path} does not exist; run `zoo fit-category` (or prepare_category) to make it")
    try:
        with h5py.File(path, "r") as f:
            _check_schema(path, f)
            points = f["points"][...]
            sdf = f["sdf"][...]
            out = ShapeSamples(
                stem=str(f.attrs["stem"]),
                points=points,
                sdf=sdf,
                similarity=Similarity.from_json(str(f.attrs["similarity"])),
                source_sha256=str(f.attrs.get("source_sha256", "")),
                config=json.loads(str(f.attrs.get("config", "{}"))),
            )
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:  # h5py reports truncation/corruption as OSError
        raise DataError(f"samples file {path} is corrupt or truncated ({type(exc).__name__}: {exc}); "
                        "delete it and rerun the samples stage") from exc
    if points.dtype != np.float32 or points.ndim != 2 or points.shape[1:] != (3,) or sdf.shape != (len(points),):
        raise DataError(f"{path} holds points {points.shape} {points.dtype} and sdf {sdf.shape}; expected (N, 3) and (N,) "
                        "float32: delete it and rerun the samples stage")
    return out


@dataclass(frozen=True)
class SampleHeader:
    """What a samples file says about itself without reading its arrays."""

    stem: str
    rows: int
    similarity: Similarity


def read_sample_header(path: str | os.PathLike) -> SampleHeader:
    """The stem, row count and similarity of a samples file; DataError as :func:`read_samples`."""
    h5py = require("h5py")
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            _check_schema(path, f)
            rows = f["sdf"].shape[0]
            if f["points"].shape != (rows, 3) or f["points"].dtype != np.float32 or f["sdf"].dtype != np.float32 or not rows:
                raise DataError(f"{path} holds points {f['points'].shape} and sdf {f['sdf'].shape}; expected (N, 3) and "
                                "(N,) float32 with N > 0: delete it and rerun the samples stage")
            return SampleHeader(str(f.attrs["stem"]), int(rows), Similarity.from_json(str(f.attrs["similarity"])))
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise DataError(f"samples file {path} is missing, corrupt or truncated ({type(exc).__name__}: {exc}); "
                        "delete it and rerun the samples stage") from exc


def read_sample_rows(path: str | os.PathLike, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``rows`` (P,) of a samples file, in that order, repeats allowed: -> points (P, 3), sdf (P,) float32.

    Only the HDF5 chunks that hold them are read and decompressed."""
    h5py = require("h5py")
    wanted, order = np.unique(np.asarray(rows, dtype=np.int64), return_inverse=True)
    try:
        with h5py.File(path, "r") as f:
            points, sdf = f["points"][wanted], f["sdf"][wanted]
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise DataError(f"cannot read rows of samples file {path} ({type(exc).__name__}: {exc}); "
                        "delete it and rerun the samples stage") from exc
    return points[order], sdf[order]


def _check_schema(path: Path, f) -> None:
    version = int(f.attrs.get("schema_version", -1))
    if version != SCHEMA_VERSION:
        raise DataError(f"{path} has samples schema version {version}, this sdfzoo reads {SCHEMA_VERSION}; "
                        "delete it and rerun the samples stage")


# --------------------------------------------------------------------------- stages


def run_samples(normalised_npz: str | os.PathLike, work_dir: str | os.PathLike, config: SampleConfig | None = None,
                force: bool = False) -> Path:
    """Sample one normalised shape (from :func:`pipeline.normalise.run_normalise`) unless done; return the .h5 path."""
    config = config or SampleConfig()
    normalised_npz = Path(normalised_npz)
    stem = normalised_npz.stem
    out = samples_path(work_dir, stem)
    stage = Stage(
        name="samples",
        inputs={"mesh": normalised_npz, "transform": normalised_npz.with_suffix(".json")},
        config={"stem": stem, **config.to_dict()},
        outputs={"samples": out},
        code=(__name__,),  # with zoo.meshes.sample_sdf and every project module it imports
    )

    def build():
        shape = read_normalised(normalised_npz)
        seed = shape_seed(config.seed, stem)
        points, sdf = sample_sdf(shape.mesh, config.n_points, seed, config.near_sigmas, config.fractions, config.padding)
        record = {**config.to_dict(), "shape_seed": seed}
        write_samples(out, ShapeSamples(stem, points, sdf, shape.similarity, shape.source_sha256, record))

    run_stage(stage, build, force=force)
    return out


def prepare_mesh(mesh_path: str | os.PathLike, work_dir: str | os.PathLike, config: SampleConfig | None = None,
                 up="z", stem: str | None = None, force: bool = False) -> Path:
    """Normalise and sample one mesh file (e.g. an unseen mesh for fit-codes); return its .h5 path."""
    npz = run_normalise(mesh_path, work_dir, stem=stem, up=up, force=force)
    return run_samples(npz, work_dir, config, force=force)


def prepare_category(category, data_dir: str | os.PathLike | None, work_dir: str | os.PathLike,
                     config: SampleConfig | None = None, split: str | None = "train", force: bool = False,
                     progress: bool = True) -> list[Path]:
    """Normalise and sample every mesh of a category's split (None: all); return the .h5 paths in stem order.

    ``category`` is a name ("mugs"), a manifest path or a :class:`pipeline.categories.Category`.
    Meshes are checked against the manifest's sha256 first. Each mesh is its own cached stage,
    so an interrupted run loses at most the mesh in progress.
    """
    from .categories import Category, load_category, verify_meshes

    cat = category if isinstance(category, Category) else load_category(category)
    stems = cat.stems(split)
    paths = verify_meshes(cat, data_dir, stems)
    out: list[Path] = []
    with task_bar(progress, f"{cat.name}: normalise + sample", total=len(stems)) as bar:
        for stem in stems:
            bar.describe(f"{cat.name}: {stem}")
            out.append(prepare_mesh(paths[stem], work_dir, config, up=cat.entry(stem).up, stem=stem, force=force))
            bar.advance()
    return out
