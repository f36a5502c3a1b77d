"""The commands of `zoo`. Each parses, calls zoo or benches, and prints; no logic lives here."""

from __future__ import annotations

from pathlib import Path

import typer

from .main import app


@app.command()
def demo(
    out: str = typer.Option(None, help="Folder for the demo's files (default: out/demo, with --observed out/observed)."),
    observed: bool = typer.Option(False, "--observed", help="Instead: two depth cameras see a never-seen test mug on a "
                                  "table (MuJoCo's renderer), the mugs model fits it (fit_observation), and the fitted shape "
                                  "is hung on a rack and simulated, with a video (needs $ZOO_DATA)."),
    stem: str = typer.Option(None, "--stem", help="With --observed: the test-split mug to see (default hoi4d_mug_0047)."),
    seed: int = typer.Option(0, "--seed", help="With --observed: the mug's yaw and the sensor noise."),
):
    """Run the bundled demo scene on the pretrained models shipped in the package."""
    from zoo.progress import shown

    if observed:
        from sdfzoo.benches.see_and_hang import DEMO_MUG, prepare

        from .sim import simulate

        out = out or "out/observed"
        with shown():
            scene = prepare(out, stem or DEMO_MUG, seed, log=typer.echo)
        simulate(str(scene), seconds=None, dt=None, method=None, out=Path(out), animation=True, video="mp4", progress=True)
        return
    from sdfzoo.benches.demo import run_demo

    with shown():
        run_demo(out or "out/demo")


@app.command()
def collide(
    scene: str = typer.Argument(..., help="Scene file (TOML: an SDF object, a mesh object, poses, margin, method) or a bundled scene's name, e.g. demo-mug-rack."),
    out: str = typer.Option("out/scenes", help="Folder for the contacts JSON and PNG."),
    method: str = typer.Option(None, help="Override the scene's method: fw | pgd | voxel-fw | amortized."),
):
    """Detect contacts in a scene; print a table and write JSON and a PNG."""
    from rich.console import Console

    from sdfzoo.benches.demo import CONTACT_ROWS, contacts_table
    from zoo.progress import shown
    from zoo.scenes import contacts_summary, load_collision_scene, run_scene, write_outputs

    s = load_collision_scene(scene)
    if method:
        s.method = method
    with shown():
        contacts = run_scene(s)
    paths = write_outputs(s, contacts, out)
    summary = contacts_summary(s, contacts)
    Console().print(contacts_table(s, contacts))
    if len(contacts) > CONTACT_ROWS:
        typer.echo(f"... {len(contacts) - CONTACT_ROWS} more in {paths['json']}")
    typer.echo(
        f"{s.name}: {summary['n_contacts']} contacts from {summary['n_candidates']} candidates of "
        f"{summary['n_triangles']} triangles in {_duration(s.timings['collide_s'])} ({s.method}; the first call, "
        f"with its one-time setup, {_duration(s.timings['first_collide_s'])}); min depth {summary['min_depth']}"
    )
    typer.echo(f"wrote {paths['json']}" + (f" and {paths['png']}" if paths["png"] else " (no PNG: pip install matplotlib, or sdfzoo[pipeline], for the picture)"))


def _duration(seconds: float) -> str:
    return f"{1e3 * seconds:.1f} ms" if seconds < 1 else f"{seconds:.1f} s"


@app.command()
def stress(
    out: str = typer.Option("out/stress.json", help="Where to write the JSON report."),
    model: str = typer.Option(None, help="Also stress a packaged model's NeuralSDF and detector (NAME[@VERSION])."),
    shape: str = typer.Option(None, help="The model's shape to use (default: its first)."),
    sim: bool = typer.Option(False, "--sim", help="Stress zoo.sim instead (MuJoCo contact simulation; needs sdfzoo[sim]): "
                             "stiff contacts, dt 0.25-4 ms, mass ratios, impacts, deep starts, 10 s at rest, 1,000+ contacts."),
):
    """Stiff and extreme cases and malformed input; each case says what was expected and what happened."""
    from zoo.progress import shown

    if sim:
        from zoo.errors import require

        require("mujoco", "sim")  # one line naming the extra, not a failed case per scenario
        from sdfzoo.benches.stress_sim import run_sim_stress

        out = "out/stress-sim.json" if out == "out/stress.json" else out
        with shown():
            report = run_sim_stress(out)
    else:
        from sdfzoo.benches.stress import run_stress

        with shown():
            report = run_stress(out, model=model, shape=shape)
    for r in report["cases"]:
        typer.echo(f"{'ok  ' if r['ok'] else 'FAIL'} {r['case']:<40} {r['seconds']:.2f}s")
        if not r["ok"]:
            typer.echo(f"     expected {r['expected']}\n     observed {str(r['observed']).splitlines()[0][:300]}")
    typer.echo(f"{report['passed']} passed, {report['failed']} failed; wrote {out}")
    if report["failed"]:
        raise typer.Exit(1)
