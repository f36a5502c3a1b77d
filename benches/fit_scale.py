"""`zoo bench --fit-scale`: `zoo fit-category` on more processes and on more meshes.

Two questions, each answered by runs of `zoo fit-category` side by side in one bench (fresh work folders,
the quick preset, categories of deformed real mugs from :mod:`benches.deformed`):

* **processes:** the wall time of the per-mesh stages (samples, evaluate, sample-triangles) on the
  same N meshes with ``--nproc 2`` against ``--nproc 1``, every process on one thread;
* **meshes:** every stage's peak resident memory (rank 0's) with N and with 3N meshes, beside the size of
  the category's samples, which a stage that held them all would add.

Each run writes WORK/run-report.json (the closing table); the bench gathers them into one JSON.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

from .deformed import build_deformed_category, smallest_meshes

PER_MESH_STAGES = ("samples", "evaluate", "sample-triangles")
SOURCES = 6
# Every process on one thread (torch and libigl), so that 2 processes against 1 measures what the processes add;
# on one process libigl's own threads would already share the samples stage over the cores.
ONE_THREAD = {"OMP_NUM_THREADS": "1", "IGL_NUM_THREADS": "1"}
TABLE_HEADER = ["stage", "1 process s", "2 processes s", "speed-up", "peak MB, N", "peak MB, 3N", "3N / N"]


def fit(manifest: Path, base: Path, nproc: int, preset: str) -> dict:
    """One fresh `zoo fit-category` run; -> its run report and its wall time."""
    work = base / "work"
    command = [sys.executable, "-m", "sdfzoo.cli", "fit-category", str(manifest), "--preset", preset, "--max-shapes", "0",
               "--no-progress", "--work", str(work), "--out", str(base / "out"), "--nproc", str(nproc)]
    t0 = time.perf_counter()
    result = subprocess.run(command, env={**os.environ, **ONE_THREAD}, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if result.returncode != 0:
        raise RuntimeError(f"`{' '.join(command)}` failed:\n{result.stderr[-3000:]}")
    return {"wall_seconds": seconds, "stages": json.loads((work / "run-report.json").read_text())["stages"]}


def category(base: Path, data_dir: Path, variants: int) -> tuple[Path, int]:
    """A deformed category of SOURCES x ``variants`` meshes and its manifest; -> (manifest, meshes)."""
    from sdfzoo.pipeline.manifest import write_manifest

    built = build_deformed_category(smallest_meshes(data_dir / "mug", SOURCES), base / "meshes", variants, truncate=False)
    return write_manifest(built.folder, base.name, base / f"{base.name}.toml", test_fraction=0.0), len(built.files)


def run_fit_scale_benchmark(out_dir: str | os.PathLike, data_dir: str | os.PathLike, variants: int = 4,
                            preset: str = "quick") -> Path:
    """Run the bench (N = 6 x ``variants`` meshes, 3N = 6 x 3 ``variants``); -> the JSON report's path."""
    out_dir, data_dir = Path(out_dir), Path(data_dir)
    work = out_dir / "fit-scale"
    small, n = category(work / "n", data_dir, variants)
    large, n3 = category(work / "n3", data_dir, 3 * variants)
    runs = {"N, 1 process": fit(small, work / "n-1", 1, preset), "N, 2 processes": fit(small, work / "n-2", 2, preset),
            "3N, 1 process": fit(large, work / "n3-1", 1, preset)}
    report = {
        "config": {"preset": preset, "meshes": {"N": n, "3N": n3}, "per_mesh_stages": list(PER_MESH_STAGES),
                   "samples_mb": {"N": _folder_mb(work / "n-1" / "work" / "samples"),
                                  "3N": _folder_mb(work / "n3-1" / "work" / "samples")}},
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "torch": torch.__version__},
        "runs": runs,
        "command": f"zoo bench --fit-scale --fit-scale-variants {variants}",
    }
    per_mesh = {k: sum(s["seconds"] for s in runs[k]["stages"] if s["stage"] in PER_MESH_STAGES) for k in runs}
    report["per_mesh_speedup"] = per_mesh["N, 1 process"] / per_mesh["N, 2 processes"]
    report["per_mesh_seconds"] = per_mesh
    path = out_dir / "fit_scale.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1))
    return path


def _folder_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.glob("*.h5")) / 2**20


def format_table(report: dict) -> list[list[str]]:
    """Rows of :data:`TABLE_HEADER`, one per stage."""
    runs = report["runs"]
    by_stage = {k: {s["stage"]: s for s in run["stages"]} for k, run in runs.items()}
    rows = []
    for stage in by_stage["N, 1 process"]:
        one, two = by_stage["N, 1 process"][stage], by_stage["N, 2 processes"][stage]
        small, large = one["peak_memory_mb"], by_stage["3N, 1 process"][stage]["peak_memory_mb"]
        rows.append([stage, f"{one['seconds']:.1f}", f"{two['seconds']:.1f}", f"{one['seconds'] / max(two['seconds'], 1e-9):.2f}x",
                     f"{small:.0f}", f"{large:.0f}", f"{large / small:.2f}"])
    return rows
