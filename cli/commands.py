"""The commands of `zoo`. Each parses, calls pipeline or zoo, and prints; no logic lives here."""

from __future__ import annotations

import typer

from .main import app


@app.command()
def demo(out: str = typer.Option("out/demo", help="Folder for the demo's JSON and PNG.")):
    """Run the bundled demo scene on the pretrained models shipped in the package."""
    from pipeline.demo import run_demo

    run_demo(out)
