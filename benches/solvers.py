"""Solver benchmark: error against run time of Frank-Wolfe, projected gradient and the reference.

Triangles are drawn around an analytic SDF under the paper's four conditions
(:mod:`pipeline.triangle_sampling`); every solver runs on them in batches, float32 as a simulator
would; the reference runs once, in float64, and is the yardstick for NME. Timings are per
triangle (and per iteration), the median over batches of ``batch`` triangles (at least
``repeats`` timed runs). Results go to ``<out_dir>/solvers.json``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

import zoo
from sdfzoo.pipeline.triangle_sampling import sample_constrained_triangles
from zoo import solvers
from zoo.files import atomic_path, atomic_write_text
from zoo.progress import progress_bar

FW_ITERS = (1, 2, 5, 10, 20, 50, 100)
RESULT_NAME = "solvers.json"
PNG_NAME = "solvers.png"


def run_solver_benchmark(
    sdf=None,
    n_triangles: int = 100_000,
    out_dir: str | os.PathLike = "out/bench",
    *,
    fw_iters: tuple[int, ...] = FW_ITERS,
    repeats: int = 3,
    batch: int = 10_000,
    seed: int = 0,
    threads: int | None = None,
    reference_resolution: int = 32,
    reference_polish_iters: int = 100,
    progress: bool = True,
) -> Path:
    """Measure the solvers on ``n_triangles`` sampled triangles and write ``<out_dir>/solvers.json``.

    Args:
        sdf: any SDF; default ``zoo.Torus()`` (non-convex, exact distances).
        n_triangles: triangles sampled (the paper's dataset has 100k per object).
        out_dir: folder for the JSON (created).
        fw_iters: Frank-Wolfe iteration counts measured.
        repeats: least number of timed runs behind each median (batches are the runs; a short
            benchmark re-runs its first batch to reach this).
        batch: triangles per solver call.
        seed: seed of the triangle sampler.
        threads: torch CPU threads (None keeps torch's setting; recorded either way).
        reference_resolution, reference_polish_iters: of :func:`zoo.solvers.reference`.
        progress: show rich progress bars.

    Returns:
        The path of the JSON written.
    """
    if threads:
        torch.set_num_threads(int(threads))
    steady_allocator()
    sdf = zoo.Torus() if sdf is None else sdf
    report = measure_solvers(
        sdf, n_triangles, fw_iters=fw_iters, repeats=repeats, batch=batch, seed=seed,
        reference_resolution=reference_resolution, reference_polish_iters=reference_polish_iters, progress=progress,
    )
    path = Path(out_dir) / RESULT_NAME
    atomic_write_text(path, json.dumps(report, indent=2) + "\n")
    if importlib.util.find_spec("matplotlib") is not None:  # sdfzoo[pipeline]; the JSON holds every number
        error_runtime_plot(report, path.with_name(PNG_NAME))
    return path


def error_runtime_plot(report: dict, path: Path) -> None:
    """Mean and p90 optimality against time per triangle, one line per solver over its iteration counts, log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for (solver, colour), q in ((pair, q) for pair in (("fw", "tab:blue"), ("pgd", "tab:green")) for q in ("mean", "p90")):
        rows = [r for r in report["solvers"] if r["solver"] == solver]  # pgd: one row, its iterations run to convergence
        if rows:
            ax.plot([r["time_per_triangle_ms"] for r in rows], [max(r["optimality"][q], 1e-12) for r in rows],
                    "o-" if q == "mean" else "o--", color=colour, label=f"{solver} ({q})")
            for r in rows if q == "mean" else []:
                ax.annotate(str(r["iters"] or r["iters_run"]), (r["time_per_triangle_ms"], max(r["optimality"][q], 1e-12)),
                            fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per triangle [ms] (labels: iterations)")
    ax.set_ylabel("optimality (eq. 12)")
    ax.set_title(f"error against run time, {report['config']['n_triangles']:,} triangles around {report['config']['sdf']}")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def measure_solvers(
    sdf, n_triangles: int, *, fw_iters=FW_ITERS, repeats: int = 3, batch: int = 10_000, seed: int = 0,
    reference_resolution: int = 32, reference_polish_iters: int = 100, progress: bool = True,
) -> dict:
    """The benchmark's report as a dict (see :func:`run_solver_benchmark`)."""
    with progress_bar(progress) as bar:
        task = bar.add_task("sampling triangles", total=None)
        started = time.perf_counter()
        tri = sample_constrained_triangles(sdf, n_triangles, seed=seed)
        sampling_s = time.perf_counter() - started
        bar.update(task, total=1, completed=1)
        tri64 = tri.double()
        batches = list(torch.split(torch.arange(tri.shape[0]), batch))

        def run_reference(t):
            return solvers.reference(sdf, t.double(), resolution=reference_resolution, polish_iters=reference_polish_iters)

        ref, ref_times, _ = _run_batched(run_reference, tri, batches, 1, bar, "reference (float64)")
        location = solvers.minimum_location(ref)
        off_vertex = location != solvers.VERTEX

        configs: list[tuple[str, int | None, Callable]] = [
            ("fw", k, (lambda t, k=k: (solvers.frank_wolfe(sdf, t, k), k))) for k in fw_iters
        ]
        configs.append(("pgd", None, lambda t: solvers.projected_gradient(sdf, t, return_iterations=True)))
        _warm_up(sdf, tri[: min(64, tri.shape[0])])
        rows = []
        for name, iters, fn in configs:
            label = f"{name}-{iters}" if iters is not None else f"{name} (PhysX rule)"
            bary, times, iters_run = _run_batched(fn, tri, batches, repeats, bar, label)
            rows.append(_solver_row(sdf, name, iters, tri64, bary.double(), ref, off_vertex, times, iters_run))

    return {
        "machine": machine_info(),
        "config": {
            "sdf": repr(sdf),
            "n_triangles": int(tri.shape[0]),
            "batch": batch,
            "repeats": repeats,
            "seed": seed,
            "dtype_solvers": str(tri.dtype),
            "dtype_reference": "torch.float64",
            "reference": {"resolution": reference_resolution, "polish_iters": reference_polish_iters},
            "sampling_seconds": sampling_s,
        },
        "reference": {
            "time_per_triangle_ms": _median_ms(ref_times),
            "location_fraction": {
                "vertex": _fraction(location == solvers.VERTEX),
                "edge": _fraction(location == solvers.EDGE),
                "face": _fraction(location == solvers.FACE),
            },
            "optimality": _stats(solvers.optimality(sdf, tri64, ref)),
            "min_sdf": _stats(_points_sdf(sdf, tri64, ref)),
        },
        "solvers": rows,
    }


# glibc's mallopt parameters, and what steady_allocator sets them to
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
STEADY_ALLOCATOR = {"mmap_threshold_bytes": 1 << 28, "trim_threshold_bytes": 1 << 30}
_allocator_state = "unchanged"


def steady_allocator() -> str:
    """Keep freed memory in the process (glibc ``mallopt``: ``STEADY_ALLOCATOR``), for steady timings.

    With glibc's defaults a batch's tensors of a few MB are mapped and unmapped anew or the heap's top
    is given back and faulted in again, depending on what ran before: one value-and-gradient pass over
    1,690 points took 25 to 49 ms over 30 back-to-back calls on this 2-core machine, 21 to 27 ms with
    these settings. Every method benefits alike (the benches apply it to the whole process, once).
    Returns what was done, recorded in the reports' machine info; elsewhere than glibc, nothing.
    """
    global _allocator_state
    if _allocator_state != "unchanged":
        return _allocator_state
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, STEADY_ALLOCATOR["mmap_threshold_bytes"]) == 1
        ok &= libc.mallopt(_M_TRIM_THRESHOLD, STEADY_ALLOCATOR["trim_threshold_bytes"]) == 1
    except (OSError, AttributeError):
        ok = False
    _allocator_state = "glibc mallopt: " + ", ".join(f"{k} {v}" for k, v in STEADY_ALLOCATOR.items()) if ok else "not glibc: unchanged"
    return _allocator_state


def machine_info() -> dict:
    """What the timings depend on: torch version and threads, CPU model and count, allocator, load."""
    info = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "allocator": _allocator_state,
    }
    if hasattr(os, "getloadavg"):
        info["load_average_1m"] = os.getloadavg()[0]
    return info


def format_table(report: dict) -> list[list[str]]:
    """Rows (strings) for printing: solver, time/tri, time/tri/iter, optimality p50/p90/mean, NME p50/p90, NME off-vertex p50/p90."""
    rows = []
    for r in report["solvers"]:
        name = f"{r['solver']}-{r['iters']}" if r["iters"] is not None else f"{r['solver']} ({r['iters_run']} it)"
        rows.append(
            [name, f"{r['time_per_triangle_ms']:.2e}", f"{r['time_per_triangle_iter_ms']:.2e}"]
            + [f"{r['optimality'][q]:.2e}" for q in ("p50", "p90", "mean")]
            + [f"{r['nme'][q]:.2e}" for q in ("p50", "p90")]
            + [f"{r['nme_edge_or_face'][q]:.2e}" for q in ("p50", "p90")]
        )
    return rows


TABLE_HEADER = ["solver", "ms/tri", "ms/tri/it", "opt p50", "opt p90", "opt mean", "NME p50", "NME p90", "NME e/f p50", "NME e/f p90"]


# ---------------------------------------------------------------------------------------------


def _run_batched(fn, tri, batches, repeats, bar, label):
    """Run ``fn`` (tri_batch -> bary or (bary, iterations)) over all batches, timing each.

    Returns the concatenated bary (M, 3), a list of (seconds, triangles, iterations) per timed run
    (all batches, plus re-runs of the first batch until ``repeats`` runs are timed), and the most
    iterations any run used.
    """
    task = bar.add_task(label, total=len(batches) + max(0, repeats - len(batches)))
    outs, times = [], []
    for idx in batches:
        t = tri[idx]
        bary, iters, seconds = _timed(fn, t)
        outs.append(bary)
        times.append((seconds, t.shape[0], iters))
        bar.advance(task)
    for _ in range(repeats - len(batches)):
        t = tri[batches[0]]
        _, iters, seconds = _timed(fn, t)
        times.append((seconds, t.shape[0], iters))
        bar.advance(task)
    return torch.cat(outs), times, max(i for _, _, i in times)


def _timed(fn, t):
    start = time.perf_counter()
    out = fn(t)
    seconds = time.perf_counter() - start
    bary, iters = out if isinstance(out, tuple) else (out, 1)
    return bary, iters, seconds


def _solver_row(sdf, name, iters, tri64, bary, ref, off_vertex, times, iters_run) -> dict:
    err = solvers.nme(bary, ref, tri64)
    return {
        "solver": name,
        "iters": iters,
        "iters_run": iters_run,
        "time_per_triangle_ms": _median_ms(times),
        "time_per_triangle_iter_ms": statistics.median(1e3 * s / (n * max(i, 1)) for s, n, i in times),
        "timing_repeats": len(times),
        "optimality": _stats(solvers.optimality(sdf, tri64, bary)),
        "nme": _stats(err),
        "nme_edge_or_face": _stats(err[off_vertex]) if bool(off_vertex.any()) else {},
        "min_sdf_excess_over_reference": _stats(_points_sdf(sdf, tri64, bary) - _points_sdf(sdf, tri64, ref)),
    }


def _points_sdf(sdf, tri, bary):
    return torch.as_tensor(sdf(torch.einsum("mv,mvc->mc", bary, tri))).double()


def _warm_up(sdf, tri):
    """One small call of each solver so that first-call costs (allocations, dispatch) stay out of the timings."""
    solvers.frank_wolfe(sdf, tri, 2)
    solvers.projected_gradient(sdf, tri, iters=2)


def _median_ms(times) -> float:
    return statistics.median(1e3 * s / n for s, n, _ in times)


def _stats(x: torch.Tensor) -> dict:
    x = x.double().flatten()
    if x.numel() == 0:
        return {}
    q = torch.quantile(x, torch.tensor([0.5, 0.9, 0.99], dtype=torch.float64)).tolist()
    return {"p50": q[0], "p90": q[1], "p99": q[2], "mean": float(x.mean()), "min": float(x.min()), "max": float(x.max()), "count": int(x.numel())}


def _fraction(mask: torch.Tensor) -> float:
    return float(mask.double().mean())


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
