"""`zoo` commands: models (list, info, package, push)."""

from __future__ import annotations

from pathlib import Path

import typer

from .main import app

# The numbers a reader compares first, in this order, with their labels in `zoo list`; `zoo info` shows every metric.
HEADLINE_METRICS = {
    "near_p50": "near p50",  # SDF error near the surface, fraction of the shape's size
    "near_p90": "near p90",
    "sign_agreement": "sign agr.",
    "detector_seen_polished_optimality_mean": "detect opt.",  # equation (12), mean over the bench's seen triangles
    "optimality_mean": "opt. mean",
    "nme_mean": "NME mean",
}


def _flat_numbers(metrics: dict, prefix: str = "") -> dict[str, float]:
    flat = {}
    for key, value in metrics.items():
        if isinstance(value, dict):
            flat.update(_flat_numbers(value, f"{prefix}{key}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            flat[f"{prefix}{key}"] = value
    return flat


def _metrics_summary(metrics: dict, limit: int = 4) -> str:
    """The headline numbers among ``metrics`` (nested keys are matched by their last part), at most
    ``limit``, one per line under their short label, so that the table cell stays narrow."""
    found = {}
    for key, value in _flat_numbers(metrics).items():
        found.setdefault(key.rsplit(".", 1)[-1], value)  # where two share a name, the first listed
    lines = [f"{label} {found[name]:.3g}" for name, label in HEADLINE_METRICS.items() if name in found]
    return "\n".join(lines[:limit]) or "see `zoo info`"


@app.command("list")
def list_command(all_versions: bool = typer.Option(False, "--all", help="Show every version, not only the newest.")):
    """List the pretrained models: name, version, category, shapes, metrics, license."""
    from rich.console import Console
    from rich.table import Table

    import zoo

    records = [r for r in zoo.list_models() if all_versions or r["latest"]]
    table = Table(title="sdfzoo pretrained models")
    for column in ("name", "version", "category", "shapes", "parameters", "metrics", "license"):
        table.add_column(column, overflow="fold" if column == "metrics" else "ellipsis")
    for r in records:
        table.add_row(
            r["name"], r["version"], r["category"], str(r["shapes"]), f"{r['parameters'].get('total', 0):,}",
            _metrics_summary(r["metrics"]), r["license"].split(" (")[0],  # the reason is in `zoo info`
        )
    Console().print(table if records else "no models registered; create one with `zoo package CATEGORY --version X.Y.Z`")


@app.command()
def info(spec: str = typer.Argument(..., help="NAME or NAME@X.Y.Z")):
    """Show a model's model card and its manifest entry."""
    from rich.console import Console

    from sdfzoo.pipeline.package import dumps_toml
    from zoo.registry import info as model_info

    found = model_info(spec)
    console = Console()
    console.print(f"[bold]{found['name']}@{found['version']}[/bold]  (versions: {', '.join(found['versions'])})")
    console.print(f"manifest:   {found['manifest']}")
    console.print(f"package:    {found['path']}")
    console.print(f"model card: {found['model_card']}")
    console.print(f"load with:  zoo.load(\"{found['name']}@{found['version']}\")\n")
    card = Path(found["model_card"])
    typer.echo(card.read_text() if card.is_file() else f"(no model card at {card})")
    console.print(f"\n[bold]manifest entry[/bold] ({found['manifest']})")
    typer.echo(dumps_toml(found["entry"]))


@app.command()
def package(
    source: str = typer.Argument(..., help="A category name (its fit output is out/CATEGORY) or a `zoo fit-category` output directory."),
    version: str = typer.Option(..., "--version", help="Semantic version of the release, X.Y.Z."),
    name: str = typer.Option(None, "--name", help="Model name (default: the fit config's name or category)."),
    fit_dir: str = typer.Option(None, "--fit-dir", help="The fit output directory, when SOURCE is a category."),
    metrics: str = typer.Option(None, "--metrics", help="A JSON file of evaluation metrics to record with the release."),
    metrics_command: str = typer.Option(None, "--metrics-command", help="The command that measured those metrics."),
    force: bool = typer.Option(False, "--force", help="Replace an existing release of this version."),
):
    """Release a fit output as NAME@X.Y.Z: package folder, model card, SHA256SUMS, manifest entry."""
    from sdfzoo.pipeline.package import package_model

    done = package_model(source, version, name=name, fit_dir=fit_dir, force=force, metrics_file=metrics, metrics_command=metrics_command)
    typer.echo(f"packaged {done.name}@{done.version} in {done.path}")
    typer.echo(f"manifest {done.manifest}; model card {done.path / 'README.md'}")
    typer.echo(f'load with zoo.load("{done.name}@{done.version}")')


@app.command()
def push(
    spec: str = typer.Argument(..., help="NAME@X.Y.Z of a packaged release."),
    repo: str = typer.Option(..., "--repo", help="Hugging Face repository, ORG/NAME."),
    token: str = typer.Option(None, "--token", help="Hugging Face token (default: the one `hf auth login` saved, or HF_TOKEN)."),
    private: bool = typer.Option(None, "--private/--public", help="Visibility when the repository is created."),
):
    """Upload a release to the Hugging Face Hub, tag it with its version, and record the commit in its manifest
    (loading it from the Hub then pins that commit and checks the files against the manifest's hashes)."""
    from sdfzoo.pipeline.package import push_package

    done = push_package(spec, repo, token=token, private=private)
    typer.echo(f"pushed {spec} to {done['repo']} (tag {done['tag']}, commit {done['commit']}); "
               f"load with zoo.load(\"{done['spec']}\")")
    typer.echo(f"recorded in {done['manifest']}" if done["manifest"] else
               "not recorded: the release's manifest belongs to the installed package")
