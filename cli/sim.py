"""`zoo simulate SCENE.toml`: a contact simulation (MuJoCo with sdfzoo's contacts), its trajectory, stats, plot and animation.

Registered by :func:`cli.main.register_commands`; needs the ``sim`` extra (mujoco, h5py).
"""

from __future__ import annotations

from pathlib import Path

import typer

from .main import app


@app.command()
def simulate(
    scene: str = typer.Argument(..., help="A simulation scene ([[bodies]] and a [sim] table) or a collision scene (its SDF dropped on its mesh): "
                                "a path or a bundled scene's name (sim-demo-mug-rack)."),
    seconds: float = typer.Option(None, "--seconds", help="Simulated time (default: the scene's [sim] seconds)."),
    dt: float = typer.Option(None, "--dt", help="Time step, s (default: the scene's)."),
    method: str = typer.Option(None, "--method", help="zoo.collide's narrow phase: fw, pgd, voxel-fw, amortized (default: the scene's)."),
    out: Path = typer.Option(Path("out/simulate"), "--out", help="Folder for <name>.h5, .json, .png and the video."),
    animation: bool = typer.Option(True, "--animation/--no-animation", help="Also write a video of the bodies and their contacts: "
                                   "MuJoCo's renderer (offscreen: EGL or OSMesa) from the scene's camera, else matplotlib (a GIF)."),
    video: str = typer.Option("mp4", "--video", help="The rendered video's format: mp4 or gif."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar with ETA."),
):
    """Simulate a scene: HDF5 trajectory (with provenance), per-step stats (JSON), a PNG of penetration, contacts and time per step,
    and a video of the bodies and their contacts."""
    from rich.console import Console

    from zoo.errors import InputError
    from zoo.offscreen import choose_gl

    if video not in ("mp4", "gif"):
        raise InputError(f"--video {video!r}: use mp4 or gif")
    gl = choose_gl() if animation else None  # before mujoco is imported: it reads MUJOCO_GL once

    import zoo.sim
    from zoo.progress import task_bar
    from zoo.sim.animation import MAX_FRAMES
    from zoo.sim.record import Recorder, provenance

    console = Console()
    sim = zoo.sim.load_scene(scene, dt=dt, method=method)
    seconds = sim.seconds if seconds is None else seconds
    steps = max(0, int(round(seconds / sim.dt)))
    camera = None
    if animation and gl:
        from zoo.sim.render import VideoRecorder, scene_camera

        sim.build()
        camera = VideoRecorder(sim.model, camera=scene_camera(sim))
        console.print(f"rendering with MuJoCo's renderer (MUJOCO_GL={gl})")
    elif animation:
        console.print("[yellow]no OpenGL for MuJoCo's offscreen renderer (MUJOCO_GL=egl, or osmesa with Debian's libosmesa6): "
                      "drawing the animation with matplotlib[/yellow]")
    recorder = Recorder(sim, video=camera, frame_every=max(1, steps // 120))
    with task_bar(progress, f"{sim.name}: {seconds:g} s at dt {sim.dt * 1e3:g} ms", steps) as bar:
        for _ in range(steps):
            sim.step()
            recorder(sim)
            bar.advance()
    if animation and camera is None:
        console.print(f"drawing the animation ({min(steps, MAX_FRAMES)} frames)")
    try:
        paths = recorder.write(out, provenance(sim, sim.scene_path), animation=animation, video_format=video)
    finally:
        if camera is not None:
            camera.close()
    summary = recorder.summary()
    console.print(
        f"{summary['steps']} steps, {summary['simulated_s']:.3f} s simulated; max penetration "
        f"{1e3 * summary['max_penetration_m']:.3f} mm; up to {summary['max_contacts']} contacts; "
        f"{summary['mean_step_ms']:.1f} ms per step ({summary['mean_collide_ms']:.1f} collide); "
        f"{summary['speculative_steps']} steps with a widened margin (fast approach)"
    )
    for name, body in sim.bodies.items():
        if body.joint != "fixed":
            console.print(f"  {name}: position {sim.pose(name)[:3, 3].round(4).tolist()} m, velocity {sim.velocity(name)[:3].round(3).tolist()} m/s")
    if summary["warnings"]:
        console.print(f"[yellow]{len(summary['warnings'])} warning(s):[/yellow]")
        for w in summary["warnings"][:20]:
            console.print(f"  {w}")
    if not summary["finite"]:
        console.print("[red]the state became non-finite (NaN/Inf)[/red]")
    for path in paths.values():
        console.print(f"wrote {path}")


@app.command()
def bake(
    spec: str = typer.Argument(..., help="MODEL[@VERSION][:SHAPE]: every shape of the model, or the one named."),
    margin: float = typer.Option(1e-3, "--margin", help="m, the contact margin of the simulations to come (a scene's "
                                 "`margin`: 0.001 for the mugs and bottles scenes, 0.0001 for bolt-nut and gear-gear)."),
    threads: int = typer.Option(None, "--threads", help="torch threads (default: every core)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
):
    """Bake the proxies of a model's shapes into the cache ahead of a simulation (what attach would bake on a first run),
    so that a simulation's first steps cost what its later ones do."""
    from rich.console import Console
    from rich.table import Table

    import zoo
    from zoo.errors import InputError
    from zoo.hub import zoo_cache_dir
    from zoo.proxy import bake_ahead

    name, _, shape = spec.partition(":")
    model = zoo.load(name)
    if shape and shape not in model.shapes:
        raise InputError(f"{model.name}@{model.version} has no shape {shape!r}; its shapes: {', '.join(model.shapes)}")
    table = Table("shape", "bricks baked now", "bricks", "memory (MB)", "file (MB)", "seconds",
                  title=f"proxies of {model.name}@{model.version} at margin {margin:g} m")
    for stem in [shape] if shape else model.shapes:
        done = bake_ahead(model.shape(stem), margin=margin, progress=progress, threads=threads)
        table.add_row(done.shape, str(done.baked), str(done.bricks), f"{done.memory_bytes / 1e6:.1f}",
                      f"{done.file_bytes / 1e6:.1f}", f"{done.seconds:.1f}")
    console = Console()
    console.print(table)
    console.print(f"cache: {zoo_cache_dir() / 'proxies'} (ZOO_CACHE sets it)")
