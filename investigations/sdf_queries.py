"""NeuralSDF query cost: values, values and gradients by hand, and the same through autograd, side by side,
against the arithmetic's floor.

Each call is timed ``repeats`` times per point count, the three kinds interleaved so that they share the
machine's state; medians in ms. One torch thread, float32, points uniform in the shape's bounds.

The floor (:func:`flops_per_point`, :func:`matmul_gflops`): the multiply-adds a query needs (the code cloud's
weights and the interpolated code, the decoder's layers; the gradient adds one matmul per layer back and the
weights' derivative), divided by what one thread reaches on a matmul of the decoder's own shape (a batch of
points through one hidden layer). A query at that rate is as fast as this arithmetic gets on this core; the
fraction reached says how much a better kernel could still give.

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


def flops_per_point(shape) -> dict:
    """Floating-point operations per point (a multiply-add counts 2) of a value and of a value and gradient:
    {"value": ..., "value_and_grad": ...}, from the shape's config (code cloud and decoder sizes)."""
    cfg = shape.config
    n_in = cfg.code_dim + 3 + 6 * int(getattr(cfg, "fourier_levels", 0))
    layers, width = [], 0
    for i, h in enumerate(cfg.hidden):
        fan_in = n_in if i == 0 else (width + n_in if cfg.skip_input else width)
        layers.append((fan_in + 1, h))  # the bias rides along as a column of ones
        width = h
    layers.append((width, 1))
    decoder = sum(2 * a * b for a, b in layers)
    codes = 2 * cfg.n_codes * 3 + 2 * cfg.n_codes * cfg.code_dim  # squared distances to the cloud, the weighted sum
    # the gradient: each layer's input gradient (one more matmul of its size), the weights' derivative in x
    back = sum(2 * a * b for a, b in layers) + 2 * cfg.n_codes * cfg.code_dim + 2 * cfg.n_codes * 3
    return {"value": decoder + codes, "value_and_grad": decoder + codes + back}


def matmul_gflops(shape, points: int = 1000, repeats: int = 50) -> float:
    """GFLOP/s one thread reaches on (points, fan_in) @ (fan_in, width): one of the decoder's hidden layers."""
    cfg = shape.config
    width = cfg.hidden[-1]
    fan_in = width + cfg.code_dim + 3 + 6 * int(getattr(cfg, "fourier_levels", 0)) + 1
    a, b = torch.randn(points, fan_in), torch.randn(fan_in, width)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t0)
    return 2 * points * fan_in * width / statistics.median(times) / 1e9


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="bottles")
    parser.add_argument("--shape", default="bulletarm_bottle1")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--out", default="out/sdf-queries.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = zoo.load(args.model)
    shape = model.shape(args.shape)
    rows = time_queries(shape, repeats=args.repeats)
    flops, gflops = flops_per_point(shape), matmul_gflops(shape)
    for r in rows:
        for kind in ("value", "value_and_grad"):
            us = 1e3 * r[f"{kind}_ms"] / r["points"]
            r[f"{kind}_us_per_point"] = us
            r[f"{kind}_fraction_of_matmul_rate"] = flops[kind] / (us * 1e-6) / (gflops * 1e9)
        print(f"{r['points']:>5} points: value {r['value_ms']:.3f} ms, value and gradient {r['value_and_grad_ms']:.3f} ms "
              f"(autograd {r['value_and_grad_autograd_ms']:.3f} ms); value and gradient {r['value_and_grad_us_per_point']:.2f} "
              f"us a point, {100 * r['value_and_grad_fraction_of_matmul_rate']:.0f}% of the matmul rate")
    floor = {k: 1e6 * f / (gflops * 1e9) for k, f in flops.items()}
    print(f"flops a point: {flops}; one thread's matmul of the decoder's layer: {gflops:.1f} GFLOP/s; "
          f"floor: value {floor['value']:.2f} us, value and gradient {floor['value_and_grad']:.2f} us a point")
    write_report(args.out, {"model": f"{model.name}@{model.version}", "shape": args.shape, "rows": rows,
                            "flops_per_point": flops, "matmul_gflops": gflops, "floor_us_per_point": floor},
                 __name__, argv)
