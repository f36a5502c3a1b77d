"""`zoo` commands: fit-category, fit-codes."""

from __future__ import annotations

import json

import typer

from .main import app


@app.command("fit-category")
def fit_category(
    category: str = typer.Argument(..., help="Category name (manifests/categories/NAME.toml), e.g. mugs."),
    data: str = typer.Option(None, "--data", help="Folder with one sub-folder per category (default: $ZOO_DATA)."),
    preset: str = typer.Option("default", "--preset",
                               help="default: the shipped models' preset (every train shape, ~40 min on 2 CPU cores); "
                                    "quick: a one-minute pipeline check (4 shapes, a small network) for tests and CI; "
                                    "fine: parts with sub-millimetre detail (threads, gear teeth), Fourier features, 3000 steps, ~20 min a core."),
    out: str = typer.Option(None, "--out", help="The package directory to write (default: out/CATEGORY)."),
    work: str = typer.Option(None, "--work", help="Folder for caches and checkpoints (default: runs/CATEGORY)."),
    device: str = typer.Option("cpu", "--device", help="torch device for training: cpu, cuda, cuda:1, ..."),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads (0: torch's default)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bars (off: plain log lines)."),
    steps: int = typer.Option(None, "--steps", help="Training steps, replacing the preset's (the model card records it)."),
):
    """Fit a category NeuralSDF to its train meshes and write a package that zoo.load(OUT) opens.

    Each stage is cached by the hashes of its inputs, config and code; a killed run resumes.
    """
    import torch

    from sdfzoo.pipeline.fit_category import fit_category as run_fit_category

    if threads:
        torch.set_num_threads(threads)
    run = run_fit_category(category, data, preset, out, work, device=device, progress=progress,
                           log=lambda line: typer.echo(line, err=True), steps=steps)
    train = run.metrics.get("train", {})
    typer.echo(f"{run.category.name}: {len(run.stems)} shapes -> {run.out_dir}")
    if train:
        typer.echo("train |SDF error| near the surface, % of size: "
                   f"p50 {100 * train['near_p50']:.3f}  p90 {100 * train['near_p90']:.3f}; "
                   f"sign agreement {100 * train['sign_agreement']:.2f}%")


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
