"""`zoo` commands: bench.

`zoo bench` runs one or more sections, each chosen by its flag (``--solvers``, ...); with no
section flag it runs the solver section. A new section adds its flag to :func:`bench` and a
runner to ``_SECTIONS``; the shared options travel in :class:`BenchOptions`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import typer

from .main import app

DEFAULT_SECTION = "solvers"


@dataclass
class BenchOptions:
    """Options every section may read."""

    out: Path
    triangles: int
    seed: int
    threads: int | None
    progress: bool = True
    scenes: list[str] | None = None  # --scenes: scene names or files (default: the paper's four)
    model: str | None = None  # --detector: the package whose detector is measured
    unseen_category: str | None = None  # --detector: its test meshes, fitted with fit_codes, are the unseen split
    max_shapes: int | None = None  # --detector: seen shapes measured
    n_per_shape: int = 200  # --detector: bench triangles per shape
    sim_seconds: float = 0.2  # --sim: simulated seconds per run
    panda: bool = True  # --sim: the Panda scenes too
    completion_limit: int | None = None  # --completion: test meshes per category (default: all)
    fit_scale_variants: int = 4  # --fit-scale: deformed variants per source mesh (N = 6 x this)


def _table(title: str, header: list[str], rows: list[list[str]]):
    """A rich table of right-justified columns."""
    from rich.table import Table

    table = Table(title=title)
    for column in header:
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(*row)
    return table


def _run_solvers(opts: BenchOptions) -> None:
    import json

    from rich.console import Console
    from rich.table import Table

    from sdfzoo.benches.solvers import PNG_NAME, TABLE_HEADER, format_table, run_solver_benchmark

    path = run_solver_benchmark(
        n_triangles=opts.triangles, out_dir=opts.out, seed=opts.seed, threads=opts.threads, progress=opts.progress
    )
    report = json.loads(path.read_text())
    ref = report["reference"]
    machine = report["machine"]
    table = Table(
        title=f"solvers on {report['config']['n_triangles']:,} triangles around {report['config']['sdf']} "
        f"(torch {machine['torch']}, {machine['threads']} thread(s), {machine['cpu']})"
    )
    for column in TABLE_HEADER:
        table.add_column(column, justify="right", no_wrap=True)
    for row in format_table(report):
        table.add_row(*row)
    console = Console(width=max(Console().width, 150))  # a narrow terminal would crop the numbers
    console.print(table)
    loc = ref["location_fraction"]
    console.print(
        f"reference: {ref['time_per_triangle_ms']:.3g} ms/triangle; minimum at a vertex {loc['vertex']:.1%}, "
        f"on an edge {loc['edge']:.1%}, inside the face {loc['face']:.1%}"
    )
    png = path.with_name(PNG_NAME)
    console.print(f"written: {path}" + (f" and {png}" if png.is_file() else " (no PNG: pip install matplotlib, or sdfzoo[pipeline])"))


def _run_scenes(opts: BenchOptions) -> None:
    import json

    from rich.console import Console

    from sdfzoo.benches.scenes import TABLE_HEADER, format_table, run_scene_benchmark

    console = Console(width=max(Console().width, 150))
    path = run_scene_benchmark(opts.scenes, out_dir=opts.out, threads=opts.threads,
                               progress=console.print if opts.progress else (lambda *_: None))
    report = json.loads(path.read_text())
    machine = report["machine"]
    table = _table(f"scenes (Table II analog; torch {machine['torch']}, {machine['threads']} thread(s), {machine['cpu']})",
                   TABLE_HEADER, format_table(report))
    console.print(table)
    for sc in report["scenes"]:
        np_ = sc.get("narrow_phase") or {}
        if "ratio" in np_:
            console.print(f"{sc['scene']}: amortized narrow phase {1e3 * np_['detect_s']:.1f} ms, {np_['ratio']:.2f}x one "
                          f"value-and-gradient pass ({1e3 * np_['value_and_grad_s']:.1f} ms) over {np_['candidates']} candidates; "
                          f"without the polish {1e3 * np_['detect_no_polish_s']:.1f} ms, {np_['ratio_no_polish']:.2f}x "
                          f"(ratios: medians over {np_['rounds']} rounds of the pair timed in the same round)")
            if sc.get("speedup"):
                su = sc["speedup"]
                console.print(f"{sc['scene']}: amortized {1e3 * su['amortized_s']:.1f} ms against FW-{su['fw_iters']} "
                              f"{1e3 * su['fw_s']:.1f} ms, timed interleaved: {su['speedup']:.1f}x (median over {su['repeats']} rounds)")
            matched = "matches it at" if sc.get("fw_matched", True) else "does not reach it by"
            console.print(f"{sc['scene']}: mean optimality amortized {sc['amortized_optimality_mean']:.2e} (FW {matched} "
                          f"{sc['fw_matched_iters']} it), without the polish {sc['no_polish_optimality_mean']:.2e} "
                          f"({sc['fw_matched_iters_no_polish']} it)")
    console.print(f"written: {path}")


def _run_detector(opts: BenchOptions) -> None:
    import json

    from rich.console import Console

    from sdfzoo.benches.detector import BenchConfig, bench_model, format_tables

    config = BenchConfig(threads=opts.threads, n_per_shape=opts.n_per_shape)
    path = bench_model(opts.model, opts.out, config=config, max_shapes=opts.max_shapes, unseen_category=opts.unseen_category,
                       progress=opts.progress)
    console = Console(width=max(Console().width, 150))
    console.print(format_tables(json.loads(path.read_text())))
    console.print(f"written: {path} and the Pareto plot beside it")


def _run_sim(opts: BenchOptions) -> None:
    import json

    from rich.console import Console

    from zoo.errors import require

    require("mujoco", "sim")
    from sdfzoo.benches.sim_bench import PANDA_SCENES, TABLE_HEADER, format_table, run_sim_benchmark

    console = Console(width=max(Console().width, 150))
    path = run_sim_benchmark(opts.out, seconds=opts.sim_seconds, progress=console.print if opts.progress else (lambda *_: None),
                             threads=opts.threads, panda_scenes=PANDA_SCENES if opts.panda else ())
    report = json.loads(path.read_text())
    machine = report["machine"]
    table = _table(f"simulations, {report['seconds']} s each (torch {machine['torch']}, {machine['threads']} thread(s), {machine['cpu']})",
                   TABLE_HEADER, format_table(report))
    console.print(table)
    console.print_json(json.dumps({"check_mug_hanging": report["check_mug_hanging"], "speed_bars": report["speed_bars"],
                                   "step_bars": report.get("step_bars", {})}))
    console.print(f"written: {path} and sim.png beside it")


def _run_completion(opts: BenchOptions) -> None:
    import json

    from rich.console import Console

    from sdfzoo.benches.completion import TABLE_HEADER, format_table, run_completion_benchmark

    console = Console(width=max(Console().width, 150))
    path = run_completion_benchmark(opts.out, limit=opts.completion_limit, seed=opts.seed, threads=opts.threads,
                                    progress=console.print if opts.progress else (lambda *_: None))
    report = json.loads(path.read_text())
    machine = report["machine"]
    console.print(_table(f"shape completion from depth images, test-split meshes (torch {machine['torch']}, "
                         f"{machine['threads']} thread(s), {machine['cpu']})", TABLE_HEADER, format_table(report)))
    console.print(f"written: {path} and completion.png beside it")


def _run_fit_scale(opts: BenchOptions) -> None:
    import json

    from rich.console import Console

    from sdfzoo.benches.fit_scale import TABLE_HEADER, format_table, run_fit_scale_benchmark
    from sdfzoo.pipeline.categories import resolve_data_dir

    path = run_fit_scale_benchmark(opts.out, resolve_data_dir(None), variants=opts.fit_scale_variants)
    report = json.loads(path.read_text())
    meshes, machine = report["config"]["meshes"], report["machine"]
    console = Console(width=max(Console().width, 120))
    console.print(_table(f"zoo fit-category --preset quick: N = {meshes['N']} and 3N = {meshes['3N']} meshes "
                         f"({machine['cores']} cores, torch {machine['torch']})", TABLE_HEADER, format_table(report)))
    seconds = report["per_mesh_seconds"]
    console.print(f"per-mesh stages: {seconds['N, 1 process']:.1f} s on 1 process, {seconds['N, 2 processes']:.1f} s on 2: "
                  f"{report['per_mesh_speedup']:.2f}x; written: {path}")


_SECTIONS: dict[str, Callable[[BenchOptions], None]] = {"solvers": _run_solvers, "scenes": _run_scenes, "detector": _run_detector,
                                                        "sim": _run_sim, "completion": _run_completion,
                                                        "fit-scale": _run_fit_scale}


@app.command()
def bench(
    solvers: bool = typer.Option(False, "--solvers", help="Frank-Wolfe, projected gradient and the reference: error against run time."),
    triangles: int = typer.Option(100_000, "--triangles", min=1, help="Triangles sampled under the paper's conditions."),
    out: Path = typer.Option(Path("out/bench"), "--out", help="Folder for the JSON results."),
    seed: int = typer.Option(0, "--seed", help="Seed of the triangle sampler."),
    threads: int = typer.Option(0, "--threads", min=0, help="torch CPU threads; 0 keeps torch's default."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bars."),
    scenes: bool = typer.Option(False, "--scenes", help="The paper's Table II analog: contacts, triangles, time and memory per scene and method."),
    scene: list[str] = typer.Option(None, "--scene", help="With --scenes: a scene name or .toml file (repeatable; default the paper's four)."),
    detector: str = typer.Option(None, "--detector", help="MODEL (name, name@version or package folder): its detector "
                                 "against FW, PGD and VoxelSDF+FW, Tables I, III; JSON and a Pareto PNG."),
    unseen_category: str = typer.Option(None, "--unseen-category", help="With --detector: fit this category's first 3 test "
                                        "meshes with fit_codes as the unseen split (needs $ZOO_DATA)."),
    max_shapes: int = typer.Option(4, "--max-shapes", min=1, help="With --detector: seen shapes measured."),
    n_per_shape: int = typer.Option(200, "--n-per-shape", min=1, help="With --detector: triangles per shape."),
    sim: bool = typer.Option(False, "--sim", help="The scenarios simulated (needs $ZOO_DATA): steps/s, time per step, contacts, "
                             "penetration and memory per contact method, MuJoCo's SDF plugin and CoACD references; JSON and a PNG."),
    sim_seconds: float = typer.Option(0.2, "--sim-seconds", min=0.002, help="With --sim: simulated seconds per run."),
    panda: bool = typer.Option(True, "--panda/--no-panda", help="With --sim: the four Panda scenes too, each run whole "
                               "(minutes each), with sdfzoo's contacts and with MuJoCo's on CoACD pieces."),
    completion: bool = typer.Option(False, "--completion", help="Shape completion from 1-3 simulated depth images of the "
                                    "mugs' and bottles' test meshes (needs $ZOO_DATA): fit_observation against the nearest "
                                    "train shape and the mean codes, fit_codes on the whole mesh as the ceiling; JSON and a PNG."),
    completion_limit: int = typer.Option(None, "--completion-limit", min=1, help="With --completion: test meshes per category."),
    fit_scale: bool = typer.Option(False, "--fit-scale", help="zoo fit-category on 1 and 2 processes and on N and 3N "
                                   "meshes (deformed real mugs, needs $ZOO_DATA): per-mesh stages' speed-up, every "
                                   "stage's peak memory; JSON."),
    fit_scale_variants: int = typer.Option(4, "--fit-scale-variants", min=1, help="With --fit-scale: deformed variants of "
                                           "each of 6 mugs (N = 6 x this)."),
):
    """Measure error against run time and write the results as JSON (solver section by default)."""
    chosen = [name for name, on in {"solvers": solvers, "scenes": scenes, "detector": detector is not None, "sim": sim,
                                    "completion": completion, "fit-scale": fit_scale}.items() if on]
    chosen = chosen or [DEFAULT_SECTION]
    opts = BenchOptions(out=out, triangles=triangles, seed=seed, threads=threads or None, progress=not no_progress,
                        scenes=scene or None, model=detector, unseen_category=unseen_category, max_shapes=max_shapes,
                        n_per_shape=n_per_shape, sim_seconds=sim_seconds, panda=panda, completion_limit=completion_limit,
                        fit_scale_variants=fit_scale_variants)
    for name in chosen:
        _SECTIONS[name](opts)
