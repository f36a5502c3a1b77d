"""What a default-path step spends its time on, phase by phase: the compiled loop, the NeuralSDF, the filters.

Runs a scenario of benches/sim_scenarios.py on its default path (the proxy) twice in one process, the first to bake
the bricks its run needs, and times the second's steps, each split into nested phases by timers wrapped around the
functions that make them (the wrapping adds about a microsecond a call):

- ``step``: the whole step (MuJoCo's included); ``contacts``: sdfzoo's detection and the contacts added to MuJoCo
  (``World.add_contacts``);
- ``proxy call``: the proxy collider's call (``ProxyCollider.collide_arrays``), of which ``compiled loop``
  (``zoo.proxy_kernel.search_faces``);
- ``SDF answers``: the NeuralSDF's answers to the contacts kept (``zoo.proxy_collider.exact_arrays_together``), of
  which ``NeuralSDF queries`` (a NeuralShape's ``value_and_grad_few`` and ``value_and_grad``);
- ``filters``: the contacts MuJoCo can use (``zoo.contact_filters.usable_rows``); ``reduction``: their reduction
  (``reduce_contacts``).

Only public functions are wrapped.
``--refine N`` subdivides the fixed meshes N times first (4x their faces each), as ``investigations proxy --refine``.
One torch thread, as in ``zoo bench --sim``:

    python -m investigations step_phases --scene mug-rack --out out/phases-mug-rack.json
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from investigations.report import write_report

PHASES = {  # label: [(module, owner's name or None for a module function, function)]: public names only
    "contacts": [("zoo.sim.world", "World", "add_contacts")],
    "proxy call": [("zoo.proxy_collider", "ProxyCollider", "collide_arrays")],
    "compiled loop": [("zoo.proxy_kernel", None, "search_faces")],
    "SDF answers": [("zoo.proxy_collider", None, "exact_arrays_together")],
    "NeuralSDF queries": [("zoo.neural", "NeuralShape", "value_and_grad_few"), ("zoo.neural", "NeuralShape", "value_and_grad")],
    "filters": [("zoo.sim.world", None, "usable_rows")],
    "reduction": [("zoo.sim.world", None, "reduce_contacts")],
}


def timed(spent: dict):
    """Wrap every function of ``PHASES`` so that its calls' seconds add up in ``spent`` under its label; returns a
    function that puts the originals back."""
    import importlib

    originals = []
    for label, module_name, owner_name, name in ((label, *f) for label, fs in PHASES.items() for f in fs):
        module = importlib.import_module(module_name)
        owner = getattr(module, owner_name) if owner_name else module
        original = getattr(owner, name)

        def wrapper(*args, _original=original, _label=label, **kwargs):
            started = time.perf_counter()
            try:
                return _original(*args, **kwargs)
            finally:
                spent[_label] = spent.get(_label, 0.0) + time.perf_counter() - started

        setattr(owner, name, functools.wraps(original)(wrapper))
        originals.append((owner, name, original))

    def restore() -> None:
        for owner, name, original in originals:
            setattr(owner, name, original)

    return restore


def run_once(name: str, refine: int, spent: dict | None) -> list[dict]:
    """Scenario ``name`` run for its scene's seconds; with ``spent``, each step's phases (ms) as a list of dicts."""
    from investigations.proxy import start_refined
    from sdfzoo.benches.sim_scenarios import advance

    spec, sim, extra, _ = start_refined(name, refine)
    steps = []
    for _ in range(int(round(sim.seconds / sim.dt))):
        if spent is not None:
            spent.clear()
        started = time.perf_counter()
        advance(spec, sim, extra)
        if spent is not None:
            steps.append({"step": 1e3 * (time.perf_counter() - started), **{k: 1e3 * v for k, v in spent.items()}})
    return steps


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mug-rack", help="a scenario of benches/sim_scenarios.py")
    parser.add_argument("--refine", type=int, default=0, help="subdivide the fixed meshes this many times (4x faces each)")
    parser.add_argument("--out", default="out/phases.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    run_once(args.scene, args.refine, None)  # bakes the bricks the run needs
    spent: dict = {}
    restore = timed(spent)
    try:
        steps = run_once(args.scene, args.refine, spent)
    finally:
        restore()
    labels = ["step", *PHASES]
    rows = {label: {"median_ms": float(np.median([s.get(label, 0.0) for s in steps])),
                    "mean_ms": float(np.mean([s.get(label, 0.0) for s in steps]))} for label in labels}
    print(f"{args.scene} (refined {args.refine} times), {len(steps)} steps, ms a step:")
    for label in labels:
        print(f"  {label:<22} median {rows[label]['median_ms']:6.2f}   mean {rows[label]['mean_ms']:6.2f}")
    write_report(args.out, {"scenario": args.scene, "refine": args.refine, "steps": len(steps), "phases": rows},
                 __name__, argv)
