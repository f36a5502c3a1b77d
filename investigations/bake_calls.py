"""Whether a NeuralSDF's float32 value at a point depends on the call it is asked in: the size of the call, the point's
place in it, the torch threads.

The same random points in the shape's bounds are asked in one call of all of them, and again in calls of ``size``
points (the last one shorter, or padded to a multiple of ``zoo.proxy.EVAL_MULTIPLE`` as a bake pads it), shuffled,
and with 2 threads; reports how many values differ from the one call's in any bit. This is what a proxy's bake rests
on: a brick's values must not depend on which bricks were baked with it (docs/proxy.md).

    python -m investigations bake_calls --out out/bake-calls.json
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

SIZES = (1, 2, 3, 4, 8, 12, 37, 64, 100, 1000, 1024, 4096)
SHAPES = (("mugs", "hoi4d_mug_0001"), ("bolts", "factory_bolt_m16"))


def values_in_calls(sdf, points: torch.Tensor, size: int, multiple: int = 1) -> np.ndarray:
    """f (N,) at ``points`` (N, 3) asked ``size`` points a call, each call padded to a multiple of ``multiple``."""
    out = []
    with torch.no_grad():
        for start in range(0, points.shape[0], size):
            call = points[start:start + size]
            n = call.shape[0]
            if n % multiple:
                call = torch.cat([call, call[-1:].expand(multiple - n % multiple, 3)])
            out.append(torch.as_tensor(sdf(call)).reshape(-1)[:n].numpy())
    return np.concatenate(out)


def measure(model: str, shape: str, n: int, seed: int = 0) -> dict:
    import zoo
    from zoo.proxy import EVAL_MULTIPLE

    sdf = zoo.load(model).shape(shape)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
    g = torch.Generator().manual_seed(seed)
    points = (lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)).float()
    torch.set_num_threads(1)
    whole = values_in_calls(sdf, points, n)
    differ = {str(size): int((values_in_calls(sdf, points, size) != whole).sum()) for size in SIZES}
    padded = {str(size): int((values_in_calls(sdf, points, size, EVAL_MULTIPLE) != whole).sum()) for size in SIZES}
    order = torch.randperm(n, generator=g)
    shuffled = np.empty(n)
    shuffled[order.numpy()] = values_in_calls(sdf, points[order], n)
    torch.set_num_threads(2)
    two_threads = values_in_calls(sdf, points, n)
    torch.set_num_threads(1)
    return {"model": model, "shape": shape, "points": n, "differ_by_call_size": differ,
            "differ_padded_to_multiple": padded, "eval_multiple": EVAL_MULTIPLE,
            "differ_shuffled": int((shuffled != whole).sum()), "differ_two_threads": int((two_threads != whole).sum())}


def main(argv=None) -> None:
    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--out", default="out/bake-calls.json")
    args = parser.parse_args(argv)
    results = [measure(model, shape, args.points) for model, shape in SHAPES]
    for r in results:
        print(f"{r['model']} {r['shape']}: values that differ from one call of {r['points']}, by call size: "
              f"{r['differ_by_call_size']}; padded to a multiple of {r['eval_multiple']}: {r['differ_padded_to_multiple']}; "
              f"shuffled: {r['differ_shuffled']}; 2 threads: {r['differ_two_threads']}")
    write_report(args.out, {"results": results}, "bake_calls", argv)


if __name__ == "__main__":
    main()
