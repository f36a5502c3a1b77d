"""What a scenario's steps spend on NeuralSDF queries, by the code that asks: a profile, for docs/sim-bench.md.

Runs a scenario of benches/sim_scenarios.py (its scene, control and default settings: the proxy, its
NeuralSDF answering the contacts kept) and times every NeuralSDF query (values, values and gradients) with
the two functions that asked for it (its call site). Prints per site the calls, points and milliseconds per
step, and the collision time per step that the queries leave (bookkeeping: bounds, selection, the solvers'
own arithmetic). The first ``--skip`` steps are not counted. One torch thread; the timers add a little.

    python -m investigations query_sites --scene mug-rack --steps 100 --out out/query-sites-mug-rack.json
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from investigations.report import write_report

_INSIDE = ("neural.py", "sdf.py", "query_sites.py")  # frames of the query itself, not its caller


def call_site(depth: int = 2) -> str:
    """The ``depth`` innermost functions on the stack outside the SDF's own modules: "caller < its caller"."""
    frame, names = sys._getframe(1), []
    while frame is not None and len(names) < depth:
        file = Path(frame.f_code.co_filename)
        if file.name not in _INSIDE:
            names.append(f"{file.stem}.{frame.f_code.co_name}")
        frame = frame.f_back
    return " < ".join(names)


@contextmanager
def timed_queries():
    """Within the block, every NeuralShape value and value-and-gradient query is counted (its public entry points:
    ``__call__``, ``value_and_grad`` and the numpy ``value_and_grad_few``): yields a dict (kind, site) -> [calls,
    points, seconds], filled as queries run."""
    from zoo.neural import NeuralShape

    sites = defaultdict(lambda: [0, 0, 0.0])
    originals = {name: getattr(NeuralShape, name) for name in ("__call__", "value_and_grad", "value_and_grad_few")}
    kinds = {"__call__": "value", "value_and_grad": "value+grad", "value_and_grad_few": "value+grad"}

    def timed(name):
        original, kind = originals[name], kinds[name]

        def wrapper(self, points, *args, **kwargs):
            started = time.perf_counter()
            out = original(self, points, *args, **kwargs)
            entry = sites[(kind, call_site())]
            entry[0] += 1
            entry[1] += int(len(points))
            entry[2] += time.perf_counter() - started
            return out

        return wrapper

    for name in originals:
        setattr(NeuralShape, name, timed(name))
    try:
        yield sites
    finally:
        for name, original in originals.items():
            setattr(NeuralShape, name, original)


def profile(name: str, steps: int, skip: int) -> dict:
    """Scenario ``name`` for ``skip`` + ``steps`` steps, its queries by site over the last ``steps``."""
    from sdfzoo.benches.sim_scenarios import advance, start

    scenario, sim, extra = start(name)
    for _ in range(skip):
        advance(scenario, sim, extra)
    with timed_queries() as sites:
        for _ in range(steps):
            advance(scenario, sim, extra)
    collide = np.array([1e3 * r.collide_s for r in sim.log[skip:]])
    rows = sorted(({"kind": kind, "site": site, "calls_per_step": c / steps, "points_per_step": p / steps,
                    "ms_per_step": 1e3 * s / steps} for (kind, site), (c, p, s) in sites.items()),
                  key=lambda r: -r["ms_per_step"])
    queries = sum(r["ms_per_step"] for r in rows)
    return {"scenario": name, "steps": steps, "skipped": skip, "collide_ms_median": float(np.median(collide)),
            "collide_ms_mean": float(collide.mean()), "query_ms_per_step": queries,
            "other_ms_per_step": float(collide.mean()) - queries, "sites": rows}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mug-rack", help="a scenario of benches/sim_scenarios.py")
    parser.add_argument("--steps", type=int, default=100, help="steps counted")
    parser.add_argument("--skip", type=int, default=10, help="steps run first, not counted")
    parser.add_argument("--out", default="out/query-sites.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    result = profile(args.scene, args.steps, args.skip)
    print(f"{args.scene}, steps {args.skip}-{args.skip + args.steps - 1}: collision {result['collide_ms_mean']:.1f} ms a step "
          f"(median {result['collide_ms_median']:.1f}), of it NeuralSDF queries {result['query_ms_per_step']:.1f} ms, "
          f"the rest {result['other_ms_per_step']:.1f} ms")
    print(f"{'kind':<10} {'calls':>5} {'points':>7} {'ms':>6}  site (per step)")
    for r in result["sites"]:
        print(f"{r['kind']:<10} {r['calls_per_step']:>5.1f} {r['points_per_step']:>7.0f} {r['ms_per_step']:>6.2f}  {r['site']}")
    write_report(args.out, result, __name__, argv)
