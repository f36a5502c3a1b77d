"""Stage sample-triangles: the detector's training and evaluation triangles, labelled.

Per shape, in its normalised frame ([-0.5, 0.5]^3), triangles are drawn under the paper's
four conditions (edge lengths, area, centroid signed distance, positive minimum signed
distance; ``pipeline.triangle_sampling``), and each is labelled with its minimum found by
Frank-Wolfe with 100 iterations (barycentrics and signed distance). On a subset the slow
global reference (``zoo.solvers.reference``) is stored too, for NME. The code-cloud features
at the vertices are stored as well: they depend only on the vertices, and precomputing them
saves the detector's training from recomputing them every epoch.

HDF5 layout (``SCHEMA_VERSION``)::

    vertices        (N, 3, 3) float32   normalised frame
    features        (N, 3, C) float32   shape.features at each vertex
    vertex_sdf      (N, 3)    float32   f at each vertex
    bary            (N, 3)    float32   Frank-Wolfe (fw_iters) minimum
    min_sdf         (N,)      float32   f at that minimum
    shape_index     (N,)      int32     row of attrs["shapes"]
    reference/rows  (K,)      int64     rows that have a global reference
    reference/bary  (K, 3)    float32
    reference/min_sdf (K,)    float32
    attrs: schema_version, shapes (JSON list of names), provenance (JSON: config, seeds, versions)

Each shape is written to its own chunk file first (``<out>.chunks/<name>.h5``, atomically), so an
interrupted run resumes at the next shape; the chunks are then merged into the output, atomically.
A shape's seed comes from its name, so its chunk is the same file whatever the other shapes and
however many processes share the work; the same shapes, config and seed give identical arrays.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from zoo.config import DictConfig
from zoo.errors import DataError, InputError, require
from zoo.files import atomic_path
from zoo.geometry import bary_to_points
from zoo.progress import task_bar

from .presets import Presets

SCHEMA_VERSION = 1
ARRAYS = ("vertices", "features", "vertex_sdf", "bary", "min_sdf", "shape_index")
CHUNK_ARRAYS = ARRAYS[:-1]  # a chunk is one shape's: its row in the merged file comes with the merge
REFERENCE_ARRAYS = ("rows", "bary", "min_sdf")


@dataclass(frozen=True)
class TriangleConfig(DictConfig):
    """How many triangles per shape and how they are labelled."""

    _config_name = "triangle config"

    n_per_shape: int = 100_000  # the paper's count
    fw_iters: int = 100
    n_reference: int = 1000  # triangles per shape that also get the global reference
    reference_resolution: int = 32
    seed: int = 0
    chunk: int = 8192  # triangles labelled per batch (bounds memory)
    sampler_batch: int = 16384  # candidates per rejection round of the sampler


PRESETS = Presets(
    "triangle",
    quick=TriangleConfig(n_per_shape=256, n_reference=32, reference_resolution=16, sampler_batch=4096),
    # CPU-sized; "paper" is 100k per shape. The detector is data-bound: in a trial on 54 mugs x 500,
    # half of the triangles gave a mean optimality on fresh ones of 5.7e-3 against 4.2e-3 for all, so
    # the default takes 1500 per shape (81k for the mugs: ~20 min of certifying and labelling by
    # FW-100 on one core of the shared machine).
    default=TriangleConfig(n_per_shape=1500, n_reference=50, sampler_batch=4096),
    paper=TriangleConfig(),
)
preset = PRESETS.lookup


def shape_seed(seed: int, name: str) -> int:
    """A per-shape seed derived from the run's seed and the shape's name (not its position in a list)."""
    digest = hashlib.sha256(f"{int(seed)}:{name}".encode()).digest()
    return int(np.random.SeedSequence([int(seed), int.from_bytes(digest[:8], "little")]).generate_state(1)[0])


# --------------------------------------------------------------------------- one shape


def label_triangles(sdf, triangles: torch.Tensor, config: TriangleConfig) -> dict[str, np.ndarray]:
    """Frank-Wolfe labels of triangles (M, 3, 3): {"bary": (M, 3), "min_sdf": (M,)} float32 arrays."""
    from zoo.solvers import frank_wolfe

    bary, fmin = [], []
    for part in triangles.split(config.chunk):
        b = frank_wolfe(sdf, part, iters=config.fw_iters)
        with torch.no_grad():
            fmin.append(torch.as_tensor(sdf(bary_to_points(part, b))).float())
        bary.append(b.float())
    return {"bary": torch.cat(bary).cpu().numpy(), "min_sdf": torch.cat(fmin).cpu().numpy()}


def reference_labels(sdf, triangles: torch.Tensor, config: TriangleConfig) -> dict[str, np.ndarray]:
    """Global reference on the first ``n_reference`` triangles: {"rows", "bary", "min_sdf"}."""
    from zoo.solvers import reference

    k = min(config.n_reference, triangles.shape[0])
    if k == 0:
        return {"rows": np.zeros(0, np.int64), "bary": np.zeros((0, 3), np.float32), "min_sdf": np.zeros(0, np.float32)}
    tri = triangles[:k].double()  # float64: the reference's positions are far more exact than the solvers'
    b = reference(sdf, tri, resolution=config.reference_resolution)
    with torch.no_grad():
        f = torch.as_tensor(sdf(bary_to_points(tri, b)))
    return {"rows": np.arange(k, dtype=np.int64), "bary": b.float().cpu().numpy(), "min_sdf": f.float().cpu().numpy()}


def shape_triangles(shape, name: str, config: TriangleConfig, sampler=None, device=None) -> dict:
    """Sample and label one shape's triangles; -> dict of numpy arrays (see the module's layout).

    ``shape`` has ``normalised`` (its SDF in the normalised frame) and ``features(points (N, 3))``.
    ``sampler(sdf, n, seed=...) -> (M, 3, 3)`` defaults to the paper's four-condition sampler.
    ``device``: where the SDF is queried (sampling, features, labels); default the CPU.
    """
    sdf = shape.normalised
    if sampler is None:
        from functools import partial

        from sdfzoo.pipeline.triangle_sampling import sample_constrained_triangles

        sampler = partial(sample_constrained_triangles, batch=config.sampler_batch, device=device)
    tri = torch.as_tensor(sampler(sdf, config.n_per_shape, seed=shape_seed(config.seed, name))).float()
    tri = tri.to(device)  # device None: stays where the sampler put it
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise DataError(f"the triangle sampler returned shape {tuple(tri.shape)}; expected (M, 3, 3)")
    with torch.no_grad():
        feat = torch.cat([torch.as_tensor(shape.features(p.reshape(-1, 3))).float() for p in tri.split(config.chunk)])
        vsdf = torch.cat([torch.as_tensor(sdf(p.reshape(-1, 3))).float() for p in tri.split(config.chunk)])
    labels = label_triangles(sdf, tri, config)
    ref = reference_labels(sdf, tri, config)
    return {
        "vertices": tri.cpu().numpy(),
        "features": feat.reshape(tri.shape[0], 3, -1).cpu().numpy(),
        "vertex_sdf": vsdf.reshape(tri.shape[0], 3).cpu().numpy(),
        "bary": labels["bary"],
        "min_sdf": labels["min_sdf"],
        "reference": ref,
    }


# --------------------------------------------------------------------------- the dataset


def sample_triangle_dataset(shapes, out_path, config: TriangleConfig = TriangleConfig(), sampler=None,
                            progress: bool = True, provenance: dict | None = None, device=None) -> Path:
    """Write the labelled triangle dataset of ``shapes`` [(name, shape), ...] to ``out_path`` (HDF5), in one process.

    ``device`` (e.g. "cuda") is where the SDF queries run; the file is the same wherever they ran, up to
    rounding (see :func:`pipeline.triangle_sampling.sample_constrained_triangles`).

    Resumes from per-shape chunk files in ``<out_path>.chunks/`` written by an interrupted run
    with the same config and ``provenance`` (which should name the fit the shapes come from);
    removes them once the merged file is in place.
    """
    shapes = list(shapes)
    if not shapes:
        raise InputError("no shapes given; pass [(name, shape), ...] with at least one fitted shape")
    with task_bar(progress, "sample triangles", len(shapes)) as bar:
        for name, shape in shapes:
            write_shape_chunk(name, shape, out_path, config, provenance, sampler, device)
            bar.advance(description=f"sample triangles {name}")
    return merge_triangle_chunks(out_path, [name for name, _ in shapes], config, provenance)


def chunk_path(out_path, name: str) -> Path:
    """Where shape ``name``'s labelled triangles wait to be merged into ``out_path``."""
    out_path = Path(out_path)
    return out_path.with_name(out_path.name + ".chunks") / f"{name}.h5"


def write_shape_chunk(name: str, shape, out_path, config: TriangleConfig, provenance: dict | None = None,
                      sampler=None, device=None) -> Path:
    """Sample and label one shape into its chunk file, unless a current chunk is there; -> its path."""
    h5py = require("h5py")
    path = chunk_path(out_path, name)
    tag = _run_tag(name, config, provenance)
    if not _chunk_is_current(h5py, path, tag):
        _write_chunk(h5py, path, shape_triangles(shape, name, config, sampler, device), tag)
    return path


def merge_triangle_chunks(out_path, names: list[str], config: TriangleConfig, provenance: dict | None = None,
                          extra: dict | None = None) -> Path:
    """Merge the chunks of ``names`` (in that order) into ``out_path``, atomically; then remove them."""
    h5py = require("h5py")
    out_path = Path(out_path)
    chunks = [chunk_path(out_path, name) for name in names]
    meta = {
        "config": config.to_dict(),
        "shape_seeds": [shape_seed(config.seed, name) for name in names],
        "fw_iters": config.fw_iters,
        "frame": "normalised",
        "sdfzoo": _version(),
        **(provenance or {}),
        **(extra or {}),
    }
    _merge_chunks(h5py, chunks, out_path, names, meta)
    for path in chunks:
        path.unlink(missing_ok=True)
    chunk_dir = chunks[0].parent
    if chunk_dir.is_dir() and not any(chunk_dir.iterdir()):
        chunk_dir.rmdir()
    return out_path


def read_triangle_dataset(path, mmap: bool = False) -> dict:
    """Load a dataset written by :func:`sample_triangle_dataset` as torch tensors.

    -> {"vertices", "features", "bary", "min_sdf", "shape_index" (int64), "reference": {...},
    "shapes": [names], "provenance": dict}. With ``mmap``, the per-triangle arrays are views of the file
    (copy-on-write memory maps, shape_index int32): the operating system reads the pages a training batch
    touches, and the process holds no copy of the category's triangles.
    """
    h5py = require("h5py")
    path = Path(path)
    if not path.is_file():
        raise DataError(f"triangle dataset {path} does not exist; run the sample-triangles stage first")
    with h5py.File(path, "r") as f:
        version = int(f.attrs.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise DataError(f"{path} has schema version {version}, this sdfzoo reads {SCHEMA_VERSION}; regenerate it")
        out = {k: torch.from_numpy(_mapped(path, f[k]) if mmap else f[k][...]) for k in ARRAYS}
        out["shape_index"] = out["shape_index"] if mmap else out["shape_index"].long()
        out["reference"] = {k: torch.from_numpy(f["reference"][k][...]) for k in REFERENCE_ARRAYS}
        out["shapes"] = json.loads(f.attrs["shapes"])
        out["provenance"] = json.loads(f.attrs["provenance"])
    return out


def _mapped(path: Path, dataset) -> np.ndarray:
    """A contiguous HDF5 dataset as a copy-on-write memory map of its bytes in the file (read whole where it is
    chunked or compressed, as files merged before the layout was contiguous are)."""
    offset = dataset.id.get_offset()
    if offset is None or dataset.chunks is not None or dataset.compression is not None or not dataset.size:
        return dataset[...]
    return np.memmap(path, dtype=dataset.dtype, mode="c", offset=offset, shape=dataset.shape)


def read_provenance(path) -> dict:
    """A triangle dataset's provenance attribute alone (its arrays are not read)."""
    h5py = require("h5py")
    try:
        with h5py.File(path, "r") as f:
            return json.loads(f.attrs["provenance"])
    except (OSError, KeyError, ValueError) as exc:
        raise DataError(f"triangle dataset {path} is missing or corrupt ({exc}); delete it and rerun sample-triangles") from exc


def _run_tag(name: str, config: TriangleConfig, provenance: dict | None = None) -> str:
    """What a chunk must match to be reused: the config, the shape's name (it fixes the seed) and the
    provenance, which names the fit the shape comes from (a chunk of another fit holds other labels)."""
    blob = json.dumps({"config": config.to_dict(), "shape": name, "schema": SCHEMA_VERSION,
                       **({"provenance": provenance} if provenance else {})}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def _chunk_is_current(h5py, path: Path, tag: str) -> bool:
    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("run_tag") == tag
    except OSError:  # a chunk that cannot be read is redone
        return False


def _write_chunk(h5py, path: Path, arrays: dict, tag: str) -> None:
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["run_tag"] = tag
            for k in CHUNK_ARRAYS:
                f.create_dataset(k, data=arrays[k])
            g = f.create_group("reference")
            for k in REFERENCE_ARRAYS:
                g.create_dataset(k, data=arrays["reference"][k])


def _merge_chunks(h5py, chunks: list[Path], out_path: Path, names: list[str], meta: dict) -> None:
    """Copy the chunks into one file, one chunk in memory at a time (a category's triangles need not fit in RAM)."""
    sizes, ref_sizes, shapes = [], [], {}
    for path in chunks:
        with h5py.File(path, "r") as f:
            sizes.append(len(f["vertices"]))
            ref_sizes.append(len(f["reference"]["rows"]))
            shapes = {k: (f[k].shape[1:], f[k].dtype) for k in CHUNK_ARRAYS}
            shapes.update({f"reference/{k}": (f["reference"][k].shape[1:], f["reference"][k].dtype) for k in REFERENCE_ARRAYS})
    shapes["shape_index"] = ((), np.dtype(np.int32))
    offsets, ref_offsets = np.cumsum([0, *sizes]), np.cumsum([0, *ref_sizes])
    with atomic_path(out_path) as tmp:
        with h5py.File(tmp, "w") as out:
            out.attrs["schema_version"] = SCHEMA_VERSION
            out.attrs["shapes"] = json.dumps(names)
            out.attrs["provenance"] = json.dumps(meta, sort_keys=True)
            for k in ARRAYS:  # contiguous and uncompressed: training memory-maps them (read_triangle_dataset)
                tail, dtype = shapes[k]
                out.create_dataset(k, shape=(int(offsets[-1]), *tail), dtype=dtype)
            for k in REFERENCE_ARRAYS:
                tail, dtype = shapes[f"reference/{k}"]
                out.create_dataset(f"reference/{k}", shape=(int(ref_offsets[-1]), *tail), dtype=dtype)
            for index, path in enumerate(chunks):
                rows, refs = slice(offsets[index], offsets[index + 1]), slice(ref_offsets[index], ref_offsets[index + 1])
                with h5py.File(path, "r") as f:
                    for k in CHUNK_ARRAYS:
                        out[k][rows] = f[k][...]
                    out["shape_index"][rows] = index
                    out["reference/rows"][refs] = f["reference"]["rows"][...] + offsets[index]
                    for k in ("bary", "min_sdf"):
                        out[f"reference/{k}"][refs] = f["reference"][k][...]


def weights_sha256(module: torch.nn.Module) -> str:
    """sha256 of a module's state (names and tensor bytes): the same weights give the same digest."""
    h = hashlib.sha256()
    for name, tensor in module.state_dict().items():
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _version() -> str:
    import zoo

    return zoo.__version__


def relabel_triangle_dataset(in_path, shapes, out_path, config: TriangleConfig = TriangleConfig(), progress: bool = True) -> Path:
    """Re-label a dataset's triangles for a new fit of the same shapes; -> ``out_path``.

    The vertices are kept; features, vertex distances, FW labels and the reference are recomputed
    with ``shapes`` [(name, shape), ...] (same names and order as the dataset's). Triangles that no
    longer meet the distance conditions under the new fit (centroid distance in [0, 0.1],
    positive minimum) are dropped. Useful when a NeuralSDF is refitted: sampling is the costly part.
    """
    from sdfzoo.pipeline.triangle_sampling import CENTROID_SDF_RANGE

    h5py = require("h5py")
    old = read_triangle_dataset(in_path)
    names = [n for n, _ in shapes]
    out_path = Path(out_path)
    if names != old["shapes"]:
        raise DataError(f"{in_path} holds shapes {old['shapes'][:3]}..., not {names[:3]}...; pass the same shapes in the same order")
    with task_bar(progress, "relabel triangles", len(shapes)) as bar:
        for index, (name, shape) in enumerate(shapes):
            tri = old["vertices"][old["shape_index"] == index]
            sdf = shape.normalised
            with torch.no_grad():
                centre = torch.as_tensor(sdf(tri.mean(dim=1))).float()
            labels = label_triangles(sdf, tri, config)
            keep = torch.as_tensor(labels["min_sdf"] > 0) & (centre >= CENTROID_SDF_RANGE[0]) & (centre <= CENTROID_SDF_RANGE[1])
            tri = tri[keep]
            with torch.no_grad():
                feat = torch.as_tensor(shape.features(tri.reshape(-1, 3))).float().reshape(tri.shape[0], 3, -1)
                vsdf = torch.as_tensor(sdf(tri.reshape(-1, 3))).float().reshape(-1, 3)
            _write_chunk(h5py, chunk_path(out_path, name), {
                "vertices": tri.numpy(), "features": feat.numpy(), "vertex_sdf": vsdf.numpy(),
                "bary": labels["bary"][keep.numpy()], "min_sdf": labels["min_sdf"][keep.numpy()],
                "reference": reference_labels(sdf, tri, config),
            }, _run_tag(name, config))
            bar.advance(description=f"relabel triangles {name}")
    provenance = {k: v for k, v in old["provenance"].items() if k not in ("config", "shape_seeds", "fw_iters")}
    return merge_triangle_chunks(out_path, names, old_config(old), provenance,
                                 {"relabelled_from": str(in_path), "relabel_config": config.to_dict()})


def old_config(dataset: dict) -> TriangleConfig:
    """The config a dataset (:func:`read_triangle_dataset`) was sampled with."""
    return TriangleConfig.from_dict(dataset["provenance"]["config"])


# --------------------------------------------------------------------------- the fit-category stage


def stage_sample_triangles(run) -> bool:
    """`zoo fit-category` stage: the labelled triangles of every fitted train shape (cached by the fit's hash).

    Each rank samples and labels its share of the shapes into their chunk files; rank 0 merges them. A shape
    whose sampling fails is set aside (its reason kept in the dataset, so a cached rerun lists it again)."""
    from .distributed import run_stage_together
    from .stages import Stage

    config = PRESETS.lookup_or_default(run.preset.name)
    out = run.work_dir / "triangles" / f"{run.preset.name}.h5"
    stage = Stage("sample-triangles", {"fit": run.fit_file}, {"triangles": config.to_dict(), "stems": run.stems},
                  {"triangles": out}, code=(__name__, "pipeline.triangle_sampling", "zoo.solvers", "zoo.model"))
    # the fitted weights' sha256 ties the per-shape chunks a killed run leaves to the fit they were labelled on
    provenance = {"category": run.category.name, "fit": str(run.fit_file),
                  "fit_weights_sha256": weights_sha256(run.model.sdf)}

    def build():
        before = len(run.set_aside)
        run.each_mesh("sample-triangles", lambda stem: write_shape_chunk(
            stem, run.model.shape(stem), out, config, provenance, device=run.device))
        if run.world.main:
            set_aside = [asdict(s) for s in run.set_aside[before:]]
            merge_triangle_chunks(out, run.stems, config, provenance, {"set_aside": set_aside})

    did = run_stage_together(run.world, stage, build)
    if not did:
        run.restore_set_aside(read_provenance(out).get("set_aside", []))
    run.triangles_file = out
    return did
