"""NeuralSDF query cost: values, values and gradients by hand, and the same through autograd, side by side.

Each call is timed ``repeats`` times per point count, the three kinds interleaved so that they share the
machine's state; medians in ms. One torch thread, float32, points uniform in the shape's bounds.

    python -m investigations sdf_queries --model bottles --shape bulletarm_bottle1 --out out/sdf-queries.json
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import zoo
from investigations.report import write_report

POINT_COUNTS = (8, 100, 1000)


def autograd_value_and_grad(shape, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The value and gradient through autograd's graph (what NeuralShape.value_and_grad did before the chain rule by hand)."""
    x = points.clone().requires_grad_(True)
    with torch.enable_grad():
        d = shape(x)
        (g,) = torch.autograd.grad(d.sum(), x)
    return d.detach(), g


def time_queries(shape, counts=POINT_COUNTS, repeats: int = 30, seed: int = 0) -> list[dict]:
    """Median ms per call of each kind of query, per point count."""
    lo, hi = shape.bounds
    g = torch.Generator().manual_seed(seed)
    kinds = {"value": lambda p: shape(p), "value_and_grad": shape.value_and_grad,
             "value_and_grad_autograd": lambda p: autograd_value_and_grad(shape, p)}
    rows = []
    for n in counts:
        points = lo + (hi - lo) * torch.rand(n, 3, generator=g)
        times = {k: [] for k in kinds}
        for _ in range(repeats):
            for kind, fn in kinds.items():
                t0 = time.perf_counter()
                fn(points)
                times[kind].append(time.perf_counter() - t0)
        rows.append({"points": n, **{f"{k}_ms": 1e3 * statistics.median(v) for k, v in times.items()}})
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="bottles")
    parser.add_argument("--shape", default="bulletarm_bottle1")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--out", default="out/sdf-queries.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = zoo.load(args.model)
    rows = time_queries(model.shape(args.shape), repeats=args.repeats)
    for r in rows:
        print(f"{r['points']:>5} points: value {r['value_ms']:.3f} ms, value and gradient {r['value_and_grad_ms']:.3f} ms "
              f"(autograd {r['value_and_grad_autograd_ms']:.3f} ms)")
    write_report(args.out, {"model": f"{model.name}@{model.version}", "shape": args.shape, "rows": rows},
                 __name__, argv)
