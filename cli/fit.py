"""`zoo` commands: fit-category, fit-codes."""

from __future__ import annotations

import json

import typer

from .main import app


@app.command("fit-category")
def fit_category(
    category: str = typer.Argument(..., help="A bundled category's name (manifests/categories/NAME.toml), e.g. mugs, "
                                   "or a manifest file (zoo manifest writes one)."),
    data: str = typer.Option(None, "--data", help="Folder with one sub-folder per category (default: the manifest's, "
                             "else $ZOO_DATA)."),
    preset: str = typer.Option("default", "--preset",
                               help="default: the shipped models' preset (every train shape, each shape's samples seen "
                                    "about 6 times; docs/fit-scale.md gives its time for the 54 mugs); "
                                    "quick: a one-minute pipeline check (4 shapes, a small network) for tests and CI; "
                                    "fine: parts with sub-millimetre detail (threads, gear teeth), Fourier features, "
                                    "~49 epochs, ~20 min a core for 3 bolts."),
    out: str = typer.Option(None, "--out", help="The package directory to write (default: out/CATEGORY)."),
    work: str = typer.Option(None, "--work", help="Folder for caches and checkpoints (default: runs/CATEGORY); under "
                             "several machines, one folder that all of them see."),
    device: str = typer.Option("cpu", "--device", help="torch device for every stage: cpu, cuda, cuda:1, ... (under "
                               "torchrun each process takes the GPU of its LOCAL_RANK)."),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads per process (0: torch's default; 1 under --nproc)."),
    nproc: int = typer.Option(1, "--nproc", help="Processes on this machine (torchrun's launcher starts them); every "
                              "stage shares its work out. For several machines run torchrun yourself: torchrun "
                              "--nnodes N --nproc-per-node P -m sdfzoo.cli fit-category ..."),
    strict: bool = typer.Option(False, "--strict", help="Stop at the first mesh that fails, instead of setting it aside."),
    max_shapes: int = typer.Option(None, "--max-shapes", help="Train on the first N train meshes (0: all; default: "
                                   "the preset's, all but quick's 4)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bars (off: plain log lines)."),
    steps: int = typer.Option(None, "--steps", help="Training steps, replacing the preset's epochs (the model card "
                              "records it; a run that shows each shape less than the preset intends says so)."),
):
    """Fit a category NeuralSDF and its detector to the train meshes and write a package that zoo.load(OUT) opens.

    Each stage is cached by the hashes of its inputs, config, code and libraries; a killed run resumes. A mesh
    that fails to load, normalise, sample or label is set aside (listed at the end and in WORK/set-aside.json).
    """
    import torch

    from sdfzoo.pipeline.distributed import launch_local, launched_size
    from sdfzoo.pipeline.fit_category import fit_category as run_fit_category
    from zoo.validation import int_at_least

    if int_at_least(nproc, "--nproc", 1) > 1 and launched_size() == 1:
        raise typer.Exit(launch_local(nproc, _fit_category_args(locals())))
    if threads:
        torch.set_num_threads(threads)
    run = run_fit_category(category, data, preset, out, work, device=device, progress=progress,
                           log=lambda line: typer.echo(line, err=True), steps=steps, strict=strict, max_shapes=max_shapes)
    if not run.world.main:
        return
    train = run.metrics.get("train", {})
    typer.echo(f"{run.category.name}: {len(run.stems)} shapes -> {run.out_dir}"
               + (f" ({len(run.set_aside)} set aside)" if run.set_aside else ""))
    if train:
        typer.echo("train |SDF error| near the surface, % of size: "
                   f"p50 {100 * train['near_p50']:.3f}  p90 {100 * train['near_p90']:.3f}; "
                   f"sign agreement {100 * train['sign_agreement']:.2f}%")


def _fit_category_args(options: dict) -> list[str]:
    """The `zoo fit-category` arguments that repeat this call's options in each process torchrun starts."""
    args = ["fit-category", options["category"], "--preset", options["preset"], "--device", options["device"]]
    for name in ("data", "out", "work", "steps", "max_shapes"):
        if options[name] is not None:
            args += [f"--{name.replace('_', '-')}", str(options[name])]
    args += [f"--threads={options['threads']}", "--progress" if options["progress"] else "--no-progress"]
    return args + (["--strict"] if options["strict"] else [])


@app.command("manifest")
def manifest(
    folder: str = typer.Argument(..., help="The folder of the category's meshes (sub-folders: one per source)."),
    name: str = typer.Argument(..., help="The category's name."),
    out: str = typer.Option(None, "--out", help="The manifest to write (default: NAME.toml here)."),
    up: str = typer.Option("z", "--up", help="The meshes' up axis: x, y, z, -x, -y, -z."),
    test_fraction: float = typer.Option(0.2, "--test-fraction", help="Share of each source's meshes in the test split."),
    seed: int = typer.Option(0, "--seed", help="Seed of the train/test split."),
    license: str = typer.Option("unspecified", "--license", help="The meshes' license (the weights inherit its terms)."),
):
    """Write a category manifest for a folder of meshes (sha256 of each, a seeded train/test split); then
    `zoo fit-category NAME.toml` fits it."""
    from sdfzoo.pipeline.manifest import write_manifest

    path = write_manifest(folder, name, out, up=up, test_fraction=test_fraction, seed=seed, license=license)
    typer.echo(f"wrote {path}")


@app.command("fit-codes")
def fit_codes(
    model: str = typer.Argument(..., help="A model: NAME, NAME@X.Y.Z, a package directory or hf-hub:ORG/NAME@TAG."),
    mesh: str = typer.Argument(None, help="The unseen mesh (.obj, .ply, .stl, .off); or give --points or --depth."),
    points: str = typer.Option(None, "--points", help="What a sensor saw instead of a mesh: a .ply point cloud, world "
                               "frame, metres (normals nx ny nz used where present)."),
    depth: str = typer.Option(None, "--depth", help="What cameras saw instead of a mesh: an .npz with depth (H, W) or "
                              "(V, H, W) metres, K, T_world_camera (OpenCV camera to world) and optionally mask."),
    origin: str = typer.Option(None, "--origin", help="With --points: the sensor's position X,Y,Z (free-space evidence)."),
    out: str = typer.Option(None, "--out", help="Write the fitted shape here (safetensors, with its model and accuracy): zoo.load_shape(OUT) or a scene's [sdf] codes = OUT reads it."),
    iters: int = typer.Option(500, "--iters", help="Adam iterations on the code cloud (decoder frozen)."),
    up: str = typer.Option("z", "--up", help="The mesh's up axis: x, y, z, -x, -y, -z; with --points or --depth the world's "
                           "up as an axis or X,Y,Z (the object stands on a surface under it)."),
    seed: int = typer.Option(0, "--seed"),
    device: str = typer.Option("cpu", "--device", help="torch device: cpu, cuda, ..."),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
):
    """Fit an unseen object: its mesh (code cloud, decoder frozen; prints its accuracy), or what a sensor saw of it
    (--points, --depth: codes, scale, yaw and position in the world frame; prints the pose and the residual)."""
    from zoo.errors import InputError

    given = [name for name, value in (("MESH", mesh), ("--points", points), ("--depth", depth)) if value]
    if len(given) != 1:
        raise InputError(f"fit-codes takes one of MESH, --points FILE.ply or --depth FILE.npz, got {given or 'none'}")
    if mesh:
        from sdfzoo.pipeline.fit_category import fit_codes as run_fit_codes

        summary = run_fit_codes(model, mesh, out, iters=iters, up=up, seed=seed, device=device, progress=progress)
    else:
        from sdfzoo.pipeline.observations import fit_observed, read_depth, read_points

        obs = read_points(points, _vector(origin, "--origin")) if points else read_depth(depth)
        summary = fit_observed(model, obs, out, up=_up_vector(up), seed=seed, device=device, progress=progress)
    typer.echo(json.dumps(summary, indent=1))


def _vector(text: str | None, option: str):
    """X,Y,Z -> a list of three floats (None stays None)."""
    from zoo.errors import InputError

    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise InputError(f"{option} takes three numbers X,Y,Z, got {text!r}")
    return values


def _up_vector(text: str):
    """An axis name (x, -y, ...) or X,Y,Z -> a 3-vector."""
    axes = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}
    name = text.strip().lower()
    if name.lstrip("+-") in axes:
        return [(-v if name.startswith("-") else v) for v in axes[name.lstrip("+-")]]
    return _vector(text, "--up")
