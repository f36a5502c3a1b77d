"""A scene's first run against its warm runs: what the proxy's bake costs, where it lands, and whether it changes the answer.

Each run is its own process with one torch thread and its own proxy cache (``ZOO_CACHE``): first from an empty cache
with ``proxy="lazy"`` (bricks baked by the steps that first read them) and with the default ``proxy="ahead"`` (every
brick near the surface baked at build, on every core, reported apart as ``bake_s``); then the same scene again from
the cache the ahead run left (warm). Reports each run's median, p90 and largest step (ms), the largest step over the
warm median, the build time, and whether the trajectories agree to the last bit.

    python -m investigations first_steps --scene sim-mug-rack --seconds 0.3 --out out/first-steps.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ONE_RUN = """
import hashlib, json, sys, time
import numpy as np, torch
import zoo.sim
torch.set_num_threads(1)
scene, seconds, proxy = sys.argv[1], float(sys.argv[2]), sys.argv[3]
started = time.perf_counter()
sim = zoo.sim.load_scene(scene, proxy=proxy)
sim.build()
build = time.perf_counter() - started
states = []
for _ in range(int(round(seconds / sim.dt))):
    sim.step()
    states.append(np.concatenate([sim.data.qpos, sim.data.qvel]))
steps = np.array([1e3 * r.step_s for r in sim.log])
print(json.dumps({"build_s": build, "bake_s": sim.world.bake_seconds, "steps": len(steps),
                  "median_ms": float(np.median(steps)), "p90_ms": float(np.percentile(steps, 90)),
                  "max_ms": float(steps.max()), "max_penetration_mm": 1e3 * max(r.max_penetration for r in sim.log),
                  "trajectory_sha256": hashlib.sha256(np.stack(states).tobytes()).hexdigest()}))
"""


def one_run(scene: str, seconds: float, proxy: str, cache: str) -> dict:
    """One run of ``scene`` in its own process with the proxy cache ``cache``: its timings and trajectory's hash."""
    env = {**os.environ, "ZOO_CACHE": cache, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", ONE_RUN, scene, str(seconds), proxy], env=env, capture_output=True,
                          text=True, timeout=3600)
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def measure(scene: str, seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as lazy_cache, tempfile.TemporaryDirectory() as ahead_cache:
        runs = {"first, lazy": one_run(scene, seconds, "lazy", lazy_cache),
                "first, ahead": one_run(scene, seconds, "ahead", ahead_cache),
                "warm": one_run(scene, seconds, "ahead", ahead_cache),
                "warm again": one_run(scene, seconds, "ahead", ahead_cache)}
    warm = min(runs["warm"]["median_ms"], runs["warm again"]["median_ms"])
    for run in runs.values():
        run["max_over_warm_median"] = run["max_ms"] / warm
    same = len({run["trajectory_sha256"] for run in runs.values()}) == 1
    return {"scene": scene, "seconds": seconds, "runs": runs, "same_trajectory": same}


def main(argv=None) -> None:
    from investigations.report import write_report

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", default=[], help="a bundled scene or a path (default: sim-mug-rack)")
    parser.add_argument("--seconds", type=float, default=0.3)
    parser.add_argument("--out", default="out/first-steps.json")
    args = parser.parse_args(argv)
    results = []
    for scene in args.scene or ["sim-mug-rack"]:
        results.append(measure(scene, args.seconds))
        for name, run in results[-1]["runs"].items():
            print(f"{scene} {name:>13}: build {run['build_s']:.1f} s (bake {run['bake_s']:.1f} s), step median "
                  f"{run['median_ms']:.2f} ms, p90 {run['p90_ms']:.2f}, max {run['max_ms']:.1f} "
                  f"({run['max_over_warm_median']:.1f}x the warm median)")
        print(f"{scene}: the same trajectory in every run: {results[-1]['same_trajectory']}")
    write_report(args.out, {"results": results}, "first_steps", argv)


if __name__ == "__main__":
    main()
