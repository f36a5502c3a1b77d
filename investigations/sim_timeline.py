"""Where a scenario's collision time goes along its run: the steps in windows, each with what the bodies do then.

Runs a scenario of benches/sim_scenarios.py (its scene, control and default settings: amortized with
coherence) for ``--seconds`` and prints, per window of ``--window`` steps:

- the collision time per step (median, p90);
- the candidates per step, and how many of them were warm-started or kept (the colliders' counters);
- the contacts given to MuJoCo per step, the deepest penetration, and the moving body's speed at the
  window's end.

A median over a whole run mixes phases: a falling body, an impact, a body at rest. This shows which phase
costs what. One torch thread, as in ``zoo bench --sim``:

    python -m investigations sim_timeline --scene mug-rack --seconds 0.6 --out out/timeline-mug-rack.json
"""

from __future__ import annotations

import argparse
from dataclasses import asdict

import numpy as np
import torch

from investigations.report import write_report

COUNTERS = ("candidates", "warm", "reused", "cold")


def window_row(log, first: int, counters: dict, speed: float) -> dict:
    """One window's figures from its steps' records ``log`` (the simulation's StepRecords), the colliders' counters
    summed over the window, and the moving body's speed (m/s) at its end."""
    collide = [1e3 * r.collide_s for r in log]
    return {"first_step": first, "steps": len(log), "collide_ms_median": float(np.median(collide)),
            "collide_ms_p90": float(np.percentile(collide, 90)),
            **{f"{k}_per_step": counters[k] / len(log) for k in COUNTERS},
            "contacts_per_step": float(np.mean([r.contacts for r in log])),
            "penetration_mm_max": 1e3 * max(r.max_penetration for r in log), "speed_cm_s_end": 100 * speed}


def timeline(name: str, seconds: float, window: int) -> dict:
    """Scenario ``name`` run for ``seconds``, its steps in windows of ``window`` (see the module docstring)."""
    from sdfzoo.benches.sim_scenarios import advance, start

    scenario, sim, extra = start(name)
    moving = next(body for body, b in sim.bodies.items() if b.joint != "fixed")
    steps, rows, before = int(round(seconds / sim.dt)), [], asdict(sim.collider_stats())
    for k in range(steps):
        advance(scenario, sim, extra)
        if (k + 1) % window == 0 or k + 1 == steps:
            now = asdict(sim.collider_stats())
            first = len(rows) * window
            rows.append(window_row(sim.log[first:], first, {c: now[c] - before[c] for c in COUNTERS},
                                   float(np.linalg.norm(sim.velocity(moving)[:3]))))
            before = now
    collide = [1e3 * r.collide_s for r in sim.log]
    totals = asdict(sim.collider_stats())
    return {"scenario": name, "seconds": seconds, "dt": sim.dt, "window": window, "body": moving,
            "collide_ms_median": float(np.median(collide)), "totals": {c: totals[c] for c in COUNTERS}, "windows": rows}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mug-rack", help="a scenario of benches/sim_scenarios.py")
    parser.add_argument("--seconds", type=float, default=0.6)
    parser.add_argument("--window", type=int, default=25, help="steps per window")
    parser.add_argument("--out", default="out/timeline.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    result = timeline(args.scene, args.seconds, args.window)
    print(f"{args.scene}: collision ms per step, median over the run {result['collide_ms_median']:.1f}")
    print("   steps | collide p50  p90 | candidates  warm  kept | contacts | pen. max mm | speed cm/s")
    for r in result["windows"]:
        print(f"{r['first_step']:>3}-{r['first_step'] + r['steps'] - 1:<4}| {r['collide_ms_median']:>11.1f} {r['collide_ms_p90']:>4.1f} |"
              f" {r['candidates_per_step']:>10.0f} {r['warm_per_step']:>5.0f} {r['reused_per_step']:>5.0f} |"
              f" {r['contacts_per_step']:>8.1f} | {r['penetration_mm_max']:>11.2f} | {r['speed_cm_s_end']:>10.2f}")
    write_report(args.out, result, __name__, argv)
