"""Scene benchmark: the object-level comparison of the paper's Table II, on this machine.

For every scene file (default: the paper's four, ``scenes/{mug-rack,bottle-holder,gear-gear,
bolt-nut}.toml``) and every method, one row: contacts, candidate and total triangles, the time
of a whole ``zoo.collide`` call (median of ``repeats`` after one warm-up call) and the peak
memory of a fresh process that loads the scene and collides it once. Methods:

* ``amortized``: ``zoo.collide``'s default: the vertex test, the model's detector where it fails, polished;
* ``amortized-no-polish``: one pass of the detector with ``polish=False`` (no gradient query in the narrow phase);
  its own optimality and the FW iterations that match it are reported beside it
  (``no_polish_optimality_mean``, ``fw_matched_iters_no_polish``);
* ``amortized+refine``: the same, then ``refine`` Frank-Wolfe steps warm-started from it;
* ``fw-matched``: NeuralSDF + Frank-Wolfe at the fewest iterations whose mean optimality
  (equation (12), over the candidate triangles) is no worse than the amortized answer's (the
  paper's "FW at the same optimality"; the answer collide's amortized narrow phase gives, the
  network's or a lower vertex, without a margin to stop at; the network's alone is reported as
  ``network_optimality_mean``); the sweep goes past 100 iterations (``FW_SWEEP_EXTENSION``, up to 800)
  only while FW has not matched it, and ``fw_matched`` says whether it did; without a detector,
  Frank-Wolfe at its default 10;
* ``voxel-fw-256``, ``voxel-fw-512``: Frank-Wolfe on a VoxelSDF of the same SDF with the sample
  spacing of a 256^3 / 512^3 grid over the SDF's bounds. Building such a grid from a NeuralSDF
  takes 16.7 M / 134 M network queries (minutes to an hour on two CPU cores), so only the part
  of it that the scene's candidate triangles can reach is built (their bounding box, grown)
  and handed to ``zoo.collide`` as its grid: query time is that of the full grid (trilinear
  lookups are local), and the memory reported for the grid is the full grid's
  (``nx * ny * nz * 4`` bytes), next to what was built. Frank-Wolfe runs the matched iterations.

Besides, per scene: the speed-up of the amortized collide over ``fw-matched``, the two timed
interleaved (``speedup``; the method rows are timed one after the other, so their ratio moves with
the machine's load); the amortized narrow phase against one batched value-and-gradient pass of the
SDF over the same candidates (the floor: that pass is needed for the contact features anyway),
and the error-against-run-time sweep of Frank-Wolfe. The narrow phase is timed as ``zoo.collide``
runs it (``Contacts.timings["narrow"]``: for a model's shape, ``detect_mesh`` on the candidates,
which also returns the depths, so collide makes no value pass of its own), interleaved with the
floor, medians of ``repeats``; ``detect(triangles)`` alone (the network's answers, no depths) is
reported beside it. Each method row also gives collide's phases (broad, narrow, normals) and
its time per candidate, and, where the paper gives one, that time scaled to the paper's
candidate count (an extrapolation, labelled so).

``contact-check`` (a pseudo-scene, run with the default set or by name): issue 6's check of
amortized contacts on a mug cut by a 20k-triangle icosphere against the multi-start reference
(recall and precision, in float64 and float32), and the amortized collide against Frank-Wolfe
at its default iterations, timed side by side.

Peak memory is the resident-set high-water mark of a child process per (scene, method), torch's
allocations included (tracemalloc does not see them): ``VmHWM`` from /proc (``ru_maxrss`` only
where /proc is missing: Linux carries ru_maxrss over from the parent across execve, so a child
of the benchmark would report the benchmark's own size). The child loads the scene (baseline mark), then collides it once; the
report gives both marks and their difference. Voxel rows report their grid's bytes instead (a
child would build the grid again), and a sub-grid of more than ``MAX_VOXEL_SAMPLES`` samples is
not built at all (the row says so).

When a scene names a model that is not packaged yet, its SDF is a stand-in: a VoxelSDF of the
exact signed distance of the mesh the shape was fitted on (``zoo.meshes.ExactMeshSDF``, signed by
winding number as the training samples are; the category manifest gives the file), over the region
the scene needs, cached in ``<out>/standins``. A stand-in has no detector, so the amortized rows say
so instead of giving numbers, and its voxel rows are skipped (it is a grid already). Every row says
which SDF it ran on.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import zoo
from zoo.collision import DEFAULT_ITERS, candidate_triangles
from zoo.errors import InputError, ModelNotFoundError
from zoo.files import atomic_write_text
from zoo.geometry import bary_to_points, invert_pose, transform_points
from zoo.scenes import Scene, load_collision_scene, read_scene, resolve_scene, scene_from_dict
from zoo.voxel import VoxelSDF

from .solvers import machine_info, steady_allocator

PAPER_SCENES = ("mug-rack", "bottle-holder", "gear-gear", "bolt-nut")
# Rounds of the narrow phase's timing per ``repeats``: a round costs about one amortized collide and a
# half (mug-rack 0.8 s, bolt-nut 1.7 s), and the ratio to the floor is the closest call of the bench.
NARROW_ROUNDS_PER_REPEAT = 3
METHODS = ("amortized", "amortized-no-polish", "amortized+refine", "fw-matched", "voxel-fw-256", "voxel-fw-512")
NO_POLISH = "amortized-no-polish"
FW_SWEEP = (1, 2, 3, 4, 5, 6, 8, 10, 12, 15, 20, 30, 50, 100)
# Swept only while FW has not matched the amortized optimality yet: mug-rack's needle-shaped rack triangles
# (1.2-3.0 long, 0.002-0.009 wide, in the mug's normalised frame) need 400-800 iterations.
FW_SWEEP_EXTENSION = (200, 400, 800)
RESULT_NAME = "scenes.json"
MAX_VOXEL_SAMPLES = 4_000_000  # about 100 s of NeuralSDF queries on one CPU core
PAPER_TABLE_II = {  # candidate / total triangles and whole-collision seconds, amortized and FW
    "mug-rack": {"candidates": 18, "triangles": 228, "amortized_s": 0.150, "fw_s": 1.778},
    "bottle-holder": {"candidates": 132, "triangles": 924, "amortized_s": 0.926, "fw_s": 7.619},
    "gear-gear": {"candidates": 93, "triangles": 2800, "amortized_s": 4.94, "fw_s": 8.79},
    "bolt-nut": {"candidates": 1714, "triangles": 9548, "amortized_s": 14.2, "fw_s": 61.7},
}
# bolt-nut-start (the nut at the start of engagement, ~1,800 candidates) is our Bolt-Nut at the paper's scale
PAPER_TABLE_II["bolt-nut-start"] = PAPER_TABLE_II["bolt-nut"]
CONTACT_CHECK = "contact-check"


@dataclass
class BenchScene:
    """A loaded scene, its SDF's provenance, and its mesh as float32 tensors (as a simulator holds it)."""

    scene: Scene
    sdf_kind: str  # "model" or "stand-in (why)"
    vertices: torch.Tensor  # (V, 3) float32, the mesh's frame
    faces: torch.Tensor  # (F, 3) int64
    note: str = ""  # why a stand-in was used

    @property
    def mesh(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.vertices, self.faces

    @property
    def has_detector(self) -> bool:
        """A model's shape whose model has a detector (a NeuralShape has ``detect`` either way)."""
        sdf = self.scene.sdf
        model = getattr(sdf, "model", None)
        if model is not None and getattr(model, "detector", None) is None:
            return False
        return callable(getattr(sdf, "detect", None)) and self.sdf_kind == "model"


# =========================================================================== loading


def scene_paths(names=None) -> list[Path]:
    """Scene files: names of the paper's scenes ("bolt-nut"), or paths; default the four."""
    out = []
    for n in names or PAPER_SCENES:
        p = Path(n)
        out.append(p if p.suffix == ".toml" else resolve_scene(n))
    return out


def load_bench_scene(path: str | os.PathLike, standin_dir: str | os.PathLike = "out/bench/standins",
                     allow_standin: bool = True) -> BenchScene:
    """Load a scene; where its model is not packaged yet, put a stand-in SDF in (see the module doc)."""
    path = Path(path)
    note = ""
    try:
        scene, kind = load_collision_scene(path), "model"
    except ModelNotFoundError as exc:
        note = str(exc)
        if not allow_standin:
            raise
        spec, _ = read_scene(path)
        sdf_spec = spec["sdf"]
        no_model = {**spec, "sdf": {"analytic": "sphere", "pose": sdf_spec.get("pose")}}
        scene = scene_from_dict(no_model, base_dir=path.parent)  # everything but the SDF
        scene.sdf, kind = standin_sdf(sdf_spec["model"], sdf_spec["shape"], scene, Path(standin_dir)), f"stand-in ({exc.__class__.__name__})"
        scene.sdf_label = f"stand-in:exact-mesh-voxel:{sdf_spec['model']}:{sdf_spec['shape']}"
    vertices = torch.as_tensor(np.asarray(scene.mesh.vertices), dtype=torch.float32)
    faces = torch.as_tensor(np.asarray(scene.mesh.faces), dtype=torch.int64)
    return BenchScene(scene, kind, vertices, faces, note)


# =========================================================================== stand-ins


def standin_sdf(model: str, shape: str, scene: Scene, cache_dir: Path, spacing_cells: int = 128,
                max_points: int = 1_500_000) -> VoxelSDF:
    """A VoxelSDF of the exact SDF of ``shape``'s source mesh over the region the scene's mesh reaches.

    The region is the source mesh's bounding box cut to the other mesh's (in the SDF's frame),
    grown by 5% of the shape's size; the spacing is the shape's longest side / ``spacing_cells``,
    coarsened if the region would need more than ``max_points`` samples. Cached by name.
    """
    from sdfzoo.pipeline.categories import load_category, resolve_data_dir
    from zoo.meshes import ExactMeshSDF, load_mesh

    category = load_category(model)
    mesh_path = resolve_data_dir(None, category) / category.entry(shape).file
    # grids signed by the pseudonormal had no "-winding"; pickled VoxelSDFs were "<key>.pt", tensors are "<key>.grid.pt"
    key = f"{model}-{shape}-{scene.name}-{spacing_cells}-winding"
    cache = cache_dir / f"{key}.grid.pt"
    if cache.is_file():
        return VoxelSDF.from_state(torch.load(cache, weights_only=True))
    source = load_mesh(mesh_path)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in source.bounds)
    size = float((hi - lo).max())
    sdf_from_mesh = np.linalg.inv(scene.sdf_pose) @ scene.mesh_pose
    other = np.asarray(scene.mesh.vertices) @ sdf_from_mesh[:3, :3].T + sdf_from_mesh[:3, 3]
    grow = 0.05 * size
    r_lo = np.maximum(lo, other.min(0)) - grow
    r_hi = np.minimum(hi, other.max(0)) + grow
    if np.any(r_hi <= r_lo):
        r_lo, r_hi = lo - grow, hi + grow  # no overlap: the scene has no contacts; any box will do
    spacing = size / spacing_cells
    while np.prod(np.ceil((r_hi - r_lo) / spacing) + 1) > max_points:
        spacing *= 1.25
    shape_res = tuple(int(n) for n in np.ceil((r_hi - r_lo) / spacing) + 1)
    grid = VoxelSDF(ExactMeshSDF(source), resolution=shape_res, bounds=(r_lo, r_hi), padding=0.0, chunk=1 << 16)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp")
    torch.save(grid.state(), tmp)
    os.replace(tmp, cache)
    return grid


def voxel_region(sdf, candidate_tri: torch.Tensor, resolution: int, margin: float):
    """The part of a ``resolution``^3 VoxelSDF of ``sdf`` that the candidates reach.

    Returns (lo (3,), hi (3,), per-axis samples, full grid bytes). The full grid spans
    ``sdf.bounds`` grown by VoxelSDF's default padding (5% of the longest side); the part has the
    same spacing and covers the candidates' bounding box grown by ``margin`` and two cells, cut to
    the full grid's box.
    """
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
    pad = 0.05 * float((hi - lo).max())
    spacing = ((hi - lo) + 2 * pad) / (resolution - 1)  # (3,)
    t = candidate_tri.double().reshape(-1, 3)
    full_lo, full_hi = lo - pad, hi + pad  # beyond the full grid's box, a VoxelSDF extrapolates: no samples there
    r_lo = torch.maximum(t.amin(0) - margin - 2 * spacing, full_lo)
    r_hi = torch.minimum(t.amax(0) + margin + 2 * spacing, full_hi)
    samples = tuple(int(n) for n in (torch.ceil((r_hi - r_lo) / spacing) + 1).tolist())
    r_hi = r_lo + spacing * (torch.tensor(samples, dtype=torch.float64) - 1)  # exactly the full grid's spacing
    return r_lo, r_hi, samples, resolution**3 * 4


def install_voxel_part(sdf, resolution: int, lo, hi, samples) -> VoxelSDF:
    """Build the part of the grid and hand it to ``zoo.collide`` as its grid of ``sdf`` at ``resolution``.

    ``collide(method="voxel-fw")`` caches its grids by SDF and resolution and builds a missing one
    over the whole of ``sdf.bounds``; putting the part there first keeps everything else of the
    call as it is (the broad phase on ``sdf``, the solver on the grid).
    """
    from zoo.collision import install_voxel_grid

    grid = VoxelSDF(sdf, resolution=samples, bounds=(lo, hi), padding=0.0)
    install_voxel_grid(sdf, resolution, grid)
    return grid


# =========================================================================== measuring


def candidate_set(bs: BenchScene) -> tuple[torch.Tensor, torch.Tensor]:
    """The broad phase's candidates: indices (C,) and triangles (C, 3, 3) in the SDF's frame."""
    s = bs.scene
    pose = invert_pose(torch.as_tensor(s.sdf_pose, dtype=torch.float64)) @ torch.as_tensor(s.mesh_pose, dtype=torch.float64)
    tri = transform_points(pose.float(), bs.vertices)[bs.faces]
    idx = candidate_triangles(s.sdf, tri, s.margin)
    return idx, tri[idx]


def median_seconds(fn, repeats: int) -> tuple[float, object]:
    """Median wall time of ``fn()`` over ``repeats`` calls after one warm-up call; and its last result."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def interleaved_times(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Wall times (one list per name, one entry per round) of the calls ``fns[name]()``, interleaved (one of
    each per round, after a warm-up round) so that a machine's changing load hits them alike; and each
    one's results."""
    results = {name: [] for name in fns}
    times = {name: [] for name in fns}
    for fn in fns.values():
        fn()
    for _ in range(max(1, repeats)):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            out = fn()
            times[name].append(time.perf_counter() - t0)
            results[name].append(out)
    return times, results


def interleaved_seconds(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Median wall time of each ``fns[name]()``, timed by :func:`interleaved_times`; and each one's results."""
    times, results = interleaved_times(fns, repeats)
    return medians(times), results


def medians(times: dict) -> dict:
    """The median of each list of wall times in ``times``."""
    return {name: statistics.median(t) for name, t in times.items()}


def paired_ratio(numerators: list, denominators: list) -> float:
    """Median over rounds of numerator / denominator, each pair timed in the same round: steadier than a
    ratio of medians where the machine's speed drifts between rounds (a value-and-gradient pass of one
    scene took 25 to 49 ms over 30 back-to-back calls on this 2-core machine)."""
    return statistics.median(n / d for n, d in zip(numerators, denominators, strict=True))


def median_phases(contacts: list) -> dict:
    """Median of each phase of ``Contacts.timings`` over several collide results."""
    phases = [c.timings for c in contacts if getattr(c, "timings", None)]
    return {k: statistics.median(t[k] for t in phases) for k in phases[0]} if phases else {}


def fw_sweep(sdf, tri: torch.Tensor, iters=FW_SWEEP, until: float | None = None) -> list[dict]:
    """Mean and p90 optimality of Frank-Wolfe at each iteration count, on the candidate triangles; then, while
    the mean is still above ``until`` (the amortized answer's), at the counts of ``FW_SWEEP_EXTENSION``."""
    rows = []
    for k in (*iters, *FW_SWEEP_EXTENSION):
        if k not in iters and (until is None or rows[-1]["optimality_mean"] <= until):
            break
        with torch.no_grad():
            bary = zoo.solvers.frank_wolfe(sdf, tri, iters=k)
        gap = zoo.solvers.optimality(sdf, tri, bary)
        rows.append({"iters": k, "optimality_mean": float(gap.mean()), "optimality_p90": float(gap.quantile(0.9))})
    return rows


def matched_iterations(sweep: list[dict], target: float | None) -> int:
    """Fewest FW iterations whose mean optimality is <= ``target`` (the last swept if none is; 10 without a target)."""
    if target is None:
        return DEFAULT_ITERS["fw"]
    for row in sweep:
        if row["optimality_mean"] <= target:
            return row["iters"]
    return sweep[-1]["iters"]


def method_call(bs: BenchScene, name: str, fw_iters: int, refine: int, region=None):
    """(kwargs for zoo.collide, the SDF to pass) of one method row."""
    if name == "amortized":
        return {"method": "amortized"}, bs.scene.sdf
    if name == NO_POLISH:
        return {"method": "amortized", "polish": False}, bs.scene.sdf
    if name == "amortized+refine":
        return {"method": "amortized", "refine": refine}, bs.scene.sdf
    if name == "fw-matched":
        return {"method": "fw", "iters": fw_iters}, bs.scene.sdf
    if name.startswith("voxel-fw-"):
        resolution = int(name.rsplit("-", 1)[1])
        install_voxel_part(bs.scene.sdf, resolution, *region[:3])
        return {"method": "voxel-fw", "voxel_resolution": resolution, "iters": fw_iters}, bs.scene.sdf
    raise InputError(f"unknown bench method {name!r}; use one of {', '.join(METHODS)}")


def collide_once(bs: BenchScene, sdf, kwargs: dict):
    s = bs.scene
    with torch.no_grad():
        return zoo.collide(sdf, bs.mesh, sdf_pose=s.sdf_pose, mesh_pose=s.mesh_pose, margin=s.margin, **kwargs)


def narrow_phase_ratio(bs: BenchScene, tri: torch.Tensor, repeats: int) -> dict:
    """The amortized narrow phase against one value-and-gradient pass at the candidates' centroids.

    ``detect_s`` / ``ratio``: the narrow phase as ``zoo.collide(method="amortized")`` runs it
    (its ``timings["narrow"]``, depths included); ``detect_no_polish_s`` / ``ratio_no_polish``: the
    same with ``polish=False``; ``detect_only_s`` / ``detect_only_ratio``:
    ``sdf.detect(candidates)``, the network's answers alone. All timed interleaved, medians.
    """
    sdf = bs.scene.sdf
    points = bary_to_points(tri, torch.full(tri.shape[:2], 1 / 3, dtype=tri.dtype))
    fns = {"value_and_grad": lambda: sdf.value_and_grad(points)}
    if bs.has_detector:
        fns["detect_only"] = lambda: sdf.detect(tri)
        fns["collide"] = lambda: collide_once(bs, sdf, {"method": "amortized"})
        fns["collide_no_polish"] = lambda: collide_once(bs, sdf, {"method": "amortized", "polish": False})
    rounds = NARROW_ROUNDS_PER_REPEAT * repeats
    times, results = interleaved_times(fns, rounds)
    seconds = medians(times)
    vg = times["value_and_grad"]
    out = {"candidates": int(tri.shape[0]), "value_and_grad_s": seconds["value_and_grad"], "rounds": rounds}
    if bs.has_detector:
        narrow = [c.timings["narrow"] for c in results["collide"]]
        no_polish = [c.timings["narrow"] for c in results["collide_no_polish"]]
        out.update(detect_s=statistics.median(narrow), ratio=paired_ratio(narrow, vg),
                   detect_no_polish_s=statistics.median(no_polish), ratio_no_polish=paired_ratio(no_polish, vg),
                   ratio_of_medians=statistics.median(narrow) / seconds["value_and_grad"],
                   detect_only_s=seconds["detect_only"], detect_only_ratio=paired_ratio(times["detect_only"], vg),
                   collide_s=seconds["collide"], collide_phases_s=median_phases(results["collide"]),
                   definition="detect_s: collide's amortized narrow phase (timings['narrow'], depths included); "
                              "detect_only_s: sdf.detect(candidates); value_and_grad_s: one pass at the candidates' "
                              "centroids; ratios: median over rounds of the two timed in the same round")
    return out


def speedup_over_fw(bs: BenchScene, fw_iters: int, repeats: int) -> dict:
    """The amortized collide against Frank-Wolfe at the matched iterations, timed interleaved (medians of
    ``repeats`` each): the speed-up stands even where the machine's load changes between the method rows,
    which are timed one after the other."""
    fns = {"amortized": lambda: collide_once(bs, bs.scene.sdf, {"method": "amortized"}),
           "fw": lambda: collide_once(bs, bs.scene.sdf, {"method": "fw", "iters": fw_iters})}
    times, _ = interleaved_times(fns, repeats)
    return {"fw_iters": fw_iters, "amortized_s": statistics.median(times["amortized"]), "fw_s": statistics.median(times["fw"]),
            "speedup": paired_ratio(times["fw"], times["amortized"]), "repeats": repeats}


def amortized_answers(sdf, tri: torch.Tensor, polish: bool = True) -> torch.Tensor:
    """What ``zoo.collide(method="amortized", polish=polish)`` answers on the triangles, without a margin to
    stop at: ``detect_mesh`` (the lowest of its answer, the vertices and the known point) where the SDF has it,
    else ``detect``."""
    if callable(getattr(sdf, "detect_mesh", None)):
        from zoo.geometry import unique_rows

        vertices, inverse = unique_rows(tri.reshape(-1, 3))
        return sdf.detect_mesh(vertices, inverse.reshape(-1, 3), polish=polish)[0]
    return sdf.detect(tri)


def measure_scene(bs: BenchScene, methods=METHODS, repeats: int = 5, refine: int = 5, memory: bool = True,
                  scene_path: Path | None = None, standin_dir: str = "out/bench/standins", progress=print) -> dict:
    """One scene's rows (see the module doc)."""
    s = bs.scene
    idx, tri = candidate_set(bs)
    amortized_opt = network_opt = no_polish_opt = None
    if bs.has_detector and len(tri):
        with torch.no_grad():
            network_opt = float(zoo.solvers.optimality(s.sdf, tri, s.sdf.detect(tri)).mean())
            amortized_opt = float(zoo.solvers.optimality(s.sdf, tri, amortized_answers(s.sdf, tri)).mean())
            no_polish_opt = float(zoo.solvers.optimality(s.sdf, tri, amortized_answers(s.sdf, tri, polish=False)).mean())
    sweep = fw_sweep(s.sdf, tri, until=amortized_opt) if len(tri) else []
    k = matched_iterations(sweep, amortized_opt) if sweep else 10
    report = {
        "scene": s.name, "sdf": s.sdf_label, "sdf_kind": bs.sdf_kind, "sdf_note": bs.note, "mesh": s.mesh_label, "margin": s.margin,
        "n_triangles": int(bs.faces.shape[0]), "n_candidates": int(idx.numel()),
        "amortized_optimality_mean": amortized_opt, "network_optimality_mean": network_opt, "fw_matched_iters": k,
        "fw_matched": bool(sweep) and amortized_opt is not None and sweep[-1]["optimality_mean"] <= amortized_opt,
        "no_polish_optimality_mean": no_polish_opt,
        "fw_matched_iters_no_polish": matched_iterations(sweep, no_polish_opt) if sweep and no_polish_opt is not None else None,
        "fw_sweep": sweep,
        "narrow_phase": narrow_phase_ratio(bs, tri, repeats) if len(tri) else None,
        "speedup": speedup_over_fw(bs, k, repeats) if bs.has_detector and len(tri) and "fw-matched" in methods else None,
        "paper": PAPER_TABLE_II.get(s.name), "rows": [],
    }
    for name in methods:
        progress(f"  {s.name}: {name}")
        report["rows"].append(measure_method(bs, name, k, refine, tri, repeats, memory, scene_path, standin_dir))
    return report


def measure_method(bs, name, fw_iters, refine, tri, repeats, memory, scene_path, standin_dir) -> dict:
    row = {"method": name}
    if name.startswith("amortized") and not bs.has_detector:
        return {**row, "skipped": f"no detector ({bs.sdf_kind}: {bs.scene.sdf_label})"}
    region = None
    if name.startswith("voxel-fw-"):
        if isinstance(bs.scene.sdf, VoxelSDF):
            return {**row, "skipped": "the stand-in SDF is a voxel grid already"}
        if len(tri) == 0:
            return {**row, "skipped": "no candidate triangles"}
        resolution = int(name.rsplit("-", 1)[1])
        region = voxel_region(bs.scene.sdf, tri, resolution, bs.scene.margin)
        row.update(grid_samples_built=int(np.prod(region[2])), grid_bytes_full=region[3], grid_per_axis_built=list(region[2]))
        if row["grid_samples_built"] > MAX_VOXEL_SAMPLES:
            return {**row, "skipped": f"building {row['grid_samples_built']:,} samples of the SDF exceeds the limit of "
                                      f"{MAX_VOXEL_SAMPLES:,} (benches.scenes.MAX_VOXEL_SAMPLES)"}
    t0 = time.perf_counter()
    kwargs, sdf = method_call(bs, name, fw_iters, refine, region)  # builds the voxel grid, if any
    row["setup_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    first = collide_once(bs, sdf, kwargs)
    row["first_call_s"] = time.perf_counter() - t0
    seconds, results = interleaved_seconds({"collide": lambda: collide_once(bs, sdf, kwargs)}, repeats)
    seconds, c = seconds["collide"], results["collide"][-1]
    del first
    row.update(kwargs={k: (list(v) if isinstance(v, tuple) else v) for k, v in kwargs.items()}, time_s=seconds,
               repeats=repeats, n_contacts=len(c), n_candidates=c.n_candidates, n_triangles=c.n_triangles,
               min_depth=float(c.depths.min()) if len(c) else None, phases_s=median_phases(results["collide"]),
               per_candidate_ms=1e3 * seconds / max(c.n_candidates, 1))
    paper = PAPER_TABLE_II.get(bs.scene.name)
    if paper is not None and c.n_candidates:
        row["at_paper_candidates_s"] = seconds / c.n_candidates * paper["candidates"]  # an extrapolation, not a measurement
    if name.startswith("voxel-fw-"):
        # the grid dominates; a child process would build it again, so report its bytes instead
        row["memory"] = {"grid_mb_full": row["grid_bytes_full"] / 2**20, "grid_mb_built": row["grid_samples_built"] * 4 / 2**20}
    elif memory and scene_path is not None:
        row["memory"] = peak_memory_in_child(scene_path, name, fw_iters, refine, standin_dir)
    return row


# =========================================================================== memory


def peak_memory_in_child(scene_path: Path, method: str, fw_iters: int, refine: int, standin_dir: str) -> dict:
    """Peak RSS (MB) of a fresh process: after loading the scene, and after one collide with ``method``."""
    cmd = [sys.executable, "-m", "sdfzoo.benches.scenes", "--child", str(scene_path), method, str(fw_iters), str(refine), standin_dir]
    env = {**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)  # this process's folder: relative paths read the same
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def _peak_rss_mb() -> float:
    """This process's peak resident set (MB): VmHWM where /proc has it, else getrusage's ru_maxrss.

    Not ru_maxrss first: Linux keeps it across execve, so a child started by a large parent
    (the benchmark holds the models and meshes, ~500 MB) would report the parent's size at the
    fork as its own peak. VmHWM belongs to the address space, which execve makes anew.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def _child(scene_path: str, method: str, fw_iters: str, refine: str, standin_dir: str) -> None:
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads())))
    bs = load_bench_scene(scene_path, standin_dir)
    loaded = _peak_rss_mb()
    kwargs, sdf = method_call(bs, method, int(fw_iters), int(refine))
    collide_once(bs, sdf, kwargs)
    peak = _peak_rss_mb()
    print(json.dumps({"peak_rss_loaded_mb": loaded, "peak_rss_mb": peak, "collide_extra_mb": peak - loaded}))


# =========================================================================== the report


def run_scene_benchmark(scenes=None, out_dir: str | os.PathLike = "out/bench", methods=METHODS, repeats: int = 5,
                        refine: int = 5, threads: int | None = None, memory: bool = True, progress=print) -> Path:
    """Measure every scene and write ``<out_dir>/scenes.json``; returns its path."""
    if threads:
        torch.set_num_threads(int(threads))
    steady_allocator()
    standin_dir = str(Path(out_dir) / "standins")
    names = list(scenes) if scenes else [*PAPER_SCENES, CONTACT_CHECK]
    check = CONTACT_CHECK in names
    names = [n for n in names if n != CONTACT_CHECK]
    reports = []
    for path in scene_paths(names) if names else []:
        progress(f"{path.stem}: loading")
        bs = load_bench_scene(path, standin_dir)
        reports.append(measure_scene(bs, methods, repeats, refine, memory, path, standin_dir, progress))
    report = {"machine": machine_info(), "config": {"repeats": repeats, "refine": refine, "methods": list(methods),
              "memory": "peak RSS (VmHWM, else getrusage ru_maxrss) of one child process per scene and method",
              "mesh_dtype": "float32"}, "scenes": reports}
    if check:
        progress(f"{CONTACT_CHECK}: reference and timings")
        report["contact_check"] = contact_check(repeats=repeats)
    out = Path(out_dir) / RESULT_NAME
    atomic_write_text(out, json.dumps(report, indent=1) + "\n")
    return out


TABLE_HEADER = ["scene", "SDF", "cand / tris", "method", "contacts", "time (ms)", "peak RSS (MB)", "+collide (MB)", "paper (s)"]


def format_table(report: dict) -> list[list[str]]:
    rows = []
    for sc in report["scenes"]:
        paper = sc.get("paper") or {}
        for r in sc["rows"]:
            name = r["method"] + (f" ({sc['fw_matched_iters']} it)" if r["method"] == "fw-matched" else "")
            if r["method"] == NO_POLISH and sc.get("fw_matched_iters_no_polish"):
                name += f" (= FW {sc['fw_matched_iters_no_polish']} it)"
            ref = paper.get("amortized_s") if r["method"] == "amortized" else paper.get("fw_s") if r["method"] == "fw-matched" else None
            kind = "model" if sc["sdf_kind"] == "model" else "stand-in"
            if "skipped" in r:
                rows.append([sc["scene"], kind, f"{sc['n_candidates']} / {sc['n_triangles']}", name, "-", "n/a", "", "", ""])
                continue
            mem = r.get("memory", {})
            peak = f"{mem['peak_rss_mb']:.0f}" if "peak_rss_mb" in mem else f"grid {mem.get('grid_mb_full', float('nan')):.0f}"
            rows.append([sc["scene"], kind, f"{r['n_candidates']} / {r['n_triangles']}", name, str(r["n_contacts"]),
                         f"{1e3 * r['time_s']:.1f}", peak, f"{mem.get('collide_extra_mb', float('nan')):.0f}",
                         "" if ref is None else f"{ref:g}"])
    return rows


# =========================================================================== the contact check (issue 6)

CHECK_MODEL, CHECK_SHAPE = "mugs", "hoi4d_mug_0001"
CHECK_MARGIN_NORMALISED = 0.005  # contact margin in the shape's normalised frame (unit cube)


def cutting_mesh(sdf) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere of 20,480 triangles whose surface cuts a mug's wall and handle: vertices (V, 3) float64, faces.

    Built in the shape's normalised frame (radius 1.1, centre (-0.8, 0, -0.6): edges about 0.038,
    in the detector's trained range) and mapped to the source frame by the shape's similarity.
    """
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.1)
    vertices = np.asarray(sphere.vertices) + np.array([-0.8, 0.0, -0.6])
    return sdf.similarity.to_source(vertices).astype(np.float64), np.asarray(sphere.faces)


def check_margin(sdf) -> float:
    """The contact check's margin in the shape's source frame."""
    return CHECK_MARGIN_NORMALISED / float(sdf.similarity.scale)


def reference_contacts(sdf, triangles: torch.Tensor, margin: float) -> tuple[set, set]:
    """(contacts, counted): triangle indices whose multi-start reference minimum is <= margin, and the counted ones.

    Counted: the triangles whose centroid lies outside the margin, among those that PhysX's ball
    test, f(centroid) <= bounding radius + margin, cannot rule out (computed here, not by
    zoo.collide's broad phase). The reference is :func:`zoo.solvers.reference` (every point of a
    dense barycentric grid a start, the best polished in float64), which shares no code with the
    detector or Frank-Wolfe.
    """
    centroids = triangles.mean(dim=1)
    radius = (triangles - centroids.unsqueeze(1)).norm(dim=-1).amax(dim=-1)
    with torch.no_grad():
        f_centroid = torch.cat([torch.as_tensor(sdf(c)).double() for c in centroids.split(4096)])
    counted = ((f_centroid > margin) & (f_centroid <= radius + margin + 1e-9)).nonzero().squeeze(-1)
    bary = zoo.solvers.reference(sdf, triangles[counted], resolution=10, polish_iters=40)
    with torch.no_grad():
        f_min = torch.as_tensor(sdf(torch.einsum("mv,mvc->mc", bary, triangles[counted]))).double()
    return set(counted[f_min <= margin].tolist()), set(counted.tolist())


def recall_precision(contacts, reference: set, counted: set) -> dict:
    found = set(contacts.triangles.tolist()) & counted
    hit = len(found & reference)
    return {"recall": hit / max(len(reference), 1), "precision": hit / max(len(found), 1), "found": len(found),
            "missed": sorted(reference - found), "extra": sorted(found - reference)}


def contact_check(repeats: int = 5, model: str = CHECK_MODEL, shape: str = CHECK_SHAPE) -> dict:
    """Issue 6's contact check: recall and precision against the reference, and amortized against FW (default iterations)."""
    m = zoo.load(model)
    if m.detector is None:
        return {"skipped": f"{m.name}@{m.version} has no detector"}
    sdf = m.shape(shape)
    vertices, faces = cutting_mesh(sdf)
    margin = check_margin(sdf)
    t0 = time.perf_counter()
    reference, counted = reference_contacts(sdf, torch.as_tensor(vertices[faces]), margin)
    out = {"model": f"{m.name}@{m.version}", "shape": shape, "n_triangles": int(len(faces)), "margin": margin,
           "reference_contacts": len(reference), "counted": len(counted), "reference_s": time.perf_counter() - t0}
    mesh64 = (vertices, faces)
    mesh32 = (torch.as_tensor(vertices, dtype=torch.float32), torch.as_tensor(faces, dtype=torch.int64))
    with torch.no_grad():
        for name, mesh in (("float64", mesh64), ("float32", mesh32)):
            c = zoo.collide(sdf, mesh, margin=margin, method="amortized")
            out[name] = {"n_candidates": c.n_candidates, "n_contacts": len(c), **recall_precision(c, reference, counted)}
        fw_iters = DEFAULT_ITERS["fw"]
        times, results = interleaved_times({
            "amortized": lambda: zoo.collide(sdf, mesh32, margin=margin, method="amortized"),
            "fw": lambda: zoo.collide(sdf, mesh32, margin=margin, method="fw"),
        }, repeats)
    seconds = medians(times)
    out["timing"] = {"mesh_dtype": "float32", "repeats": repeats, "amortized_s": seconds["amortized"], "fw_s": seconds["fw"],
                     "fw_iters": fw_iters, "fw_over_amortized": paired_ratio(times["fw"], times["amortized"]),
                     "amortized_phases_s": median_phases(results["amortized"]), "fw_phases_s": median_phases(results["fw"]),
                     "fw": recall_precision(results["fw"][-1], reference, counted)}
    return out


if __name__ == "__main__":  # the memory probe's child process
    if len(sys.argv) == 7 and sys.argv[1] == "--child":
        _child(*sys.argv[2:])
    else:
        raise SystemExit("usage: python -m sdfzoo.benches.scenes --child SCENE METHOD FW_ITERS REFINE STANDIN_DIR")
