"""The commands of `zoo`. Each parses, calls pipeline or zoo, and prints; no logic lives here."""

from __future__ import annotations

import typer

from .main import app


@app.command()
def demo(out: str = typer.Option("out/demo", help="Folder for the demo's JSON and PNG.")):
    """Run the bundled demo scene on the pretrained models shipped in the package."""
    from pipeline.demo import run_demo

    run_demo(out)


@app.command()
def collide(
    scene: str = typer.Argument(..., help="Scene file (TOML): an SDF object, a mesh object, poses, margin, method."),
    out: str = typer.Option("out/scenes", help="Folder for the contacts JSON and PNG."),
    method: str = typer.Option(None, help="Override the scene's method: fw | pgd | voxel-fw | amortized."),
):
    """Detect contacts in a scene; print a table and write JSON and a PNG."""
    from pipeline.scenes import contacts_summary, load_scene, run_scene, write_outputs

    s = load_scene(scene)
    if method:
        s.method = method
    contacts = run_scene(s)
    paths = write_outputs(s, contacts, out)
    summary = contacts_summary(s, contacts)
    typer.echo(
        f"{s.name}: {summary['n_contacts']} contacts from {summary['n_candidates']} candidates of "
        f"{summary['n_triangles']} triangles in {1e3 * s.timings['collide_s']:.1f} ms ({s.method}); "
        f"min depth {summary['min_depth']}"
    )
    typer.echo(f"wrote {paths['json']} and {paths['png']}")
