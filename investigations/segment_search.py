"""What a Panda scene's capsules cost a step: the segment pairs near the object, passed over, carried and searched.

Runs a Panda scene (``scenes/panda-*.toml``, sdfzoo's default path) whole, in one process, ``--rounds`` times each
way, alternately (this machine's speed drifts; only ratios measured side by side hold):

- ``clearance``: as shipped: a capsule axis the search found out of reach is passed over while its clearance holds
  (``zoo.sim.segments.SegmentClearance``);
- ``no-clearance``: the same, with every clearance taken as lost (``SegmentClearance.holds`` answers False), so such
  an axis is searched again at every step, as before the clearance was kept.

Per step, of the segment (sphere and capsule) pairs the broad phase finds near: those passed over (their clearance,
the same object as at the last step, still held), those whose last answer was carried (the same answer kept), and
those searched (``zoo.sim.segments.segment_minima``); the NeuralSDF queries of the search (calls and points, timed);
the time in ``zoo.sim.world.segment_contacts`` and the whole step (medians and means). Only public names are
wrapped. One torch thread:

    python -m investigations segment_search --scene panda-mug-rack --out out/segment-search.json
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from investigations.report import write_report

WAYS = ("clearance", "no-clearance")


@dataclass
class Tally:
    """What one run's steps added up (totals over its steps)."""

    near: int = 0
    passed_over: int = 0
    carried: int = 0
    searched: int = 0
    queries: int = 0
    points: int = 0
    query_s: float = 0.0
    segments_s: float = 0.0
    step_s: list = field(default_factory=list)

    def per_step(self) -> dict:
        steps = max(len(self.step_s), 1)
        step_ms = 1e3 * np.asarray(self.step_s)
        return {"steps": len(self.step_s), "near": self.near / steps, "passed_over": self.passed_over / steps,
                "carried": self.carried / steps, "searched": self.searched / steps,
                "queries": self.queries / steps, "points": self.points / steps,
                "query_ms": 1e3 * self.query_s / steps, "segment_contacts_ms": 1e3 * self.segments_s / steps,
                "step_ms_median": float(np.median(step_ms)), "step_ms_mean": float(np.mean(step_ms))}


def wrapped(tally: Tally, clearance: bool):
    """Wrap the public functions a step's capsules go through, adding to ``tally``; returns a function that puts the
    originals back."""
    import zoo.sim.pairs as pairs
    import zoo.sim.segments as segments
    import zoo.sim.world as world

    originals = [(pairs, "segment_minima"), (segments, "value_and_grad_numpy"), (world, "segment_contacts"),
                 (segments.SegmentClearance, "holds")]
    saved = [(owner, name, getattr(owner, name)) for owner, name in originals]
    search, query, contacts, holds = (original for _, _, original in saved)

    def counted_search(sdf, a, *args, **kwargs):
        tally.searched += len(a)
        return search(sdf, a, *args, **kwargs)

    def timed_query(sdf, points, *args, **kwargs):
        started = time.perf_counter()
        try:
            return query(sdf, points, *args, **kwargs)
        finally:
            tally.query_s += time.perf_counter() - started
            tally.queries += 1
            tally.points += len(points)

    def classified_contacts(near, data):
        before = {id(pair): (pair.clearance, pair.last) for pair, _, _ in near}
        started = time.perf_counter()
        try:
            return contacts(near, data)
        finally:
            tally.segments_s += time.perf_counter() - started
            tally.near += len(near)
            for pair, _, _ in near:
                clearance, last = before[id(pair)]
                tally.passed_over += clearance is not None and pair.clearance is clearance
                tally.carried += last is not None and pair.last is last

    pairs.segment_minima = counted_search
    segments.value_and_grad_numpy = timed_query
    world.segment_contacts = classified_contacts
    segments.SegmentClearance.holds = holds if clearance else (lambda self, a, b, reach: False)

    def restore() -> None:
        for owner, name, original in saved:
            setattr(owner, name, original)

    return restore


def run(scene: str, clearance: bool) -> dict:
    """One whole run of Panda scene ``scene``: its per-step figures and where the object ended."""
    import zoo.sim
    from sdfzoo.benches.panda_scenarios import SCENES

    sim = zoo.sim.load_scene(SCENES / f"{scene}.toml")
    sim.build()
    tally = Tally()
    restore = wrapped(tally, clearance)
    try:
        for _ in range(int(round(sim.seconds / sim.dt))):
            sim.step()
    finally:
        restore()
    tally.step_s = [r.step_s for r in sim.log]
    obj = "mug" if "mug" in scene else "bottle"
    return {**tally.per_step(), "end": sim.pose(obj)[:3, 3].tolist()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="panda-mug-rack", help="a Panda scene (scenes/panda-*.toml)")
    parser.add_argument("--rounds", type=int, default=2, help="runs each way, alternately")
    parser.add_argument("--out", default="out/segment-search.json")
    args = parser.parse_args(argv)
    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    torch.set_num_threads(1)
    runs = []
    for round_ in range(args.rounds):
        for way in WAYS:
            row = {"way": way, "round": round_, **run(args.scene, way == "clearance")}
            runs.append(row)
            print(f"{way:<13} near {row['near']:5.1f}  passed over {row['passed_over']:5.1f}  carried {row['carried']:5.1f}  "
                  f"searched {row['searched']:5.2f}  queries {row['queries']:4.2f} ({row['points']:5.1f} points, "
                  f"{row['query_ms']:.2f} ms)  segment_contacts {row['segment_contacts_ms']:.2f} ms  "
                  f"step median {row['step_ms_median']:.2f} ms (mean {row['step_ms_mean']:.2f})", flush=True)
    write_report(args.out, {"scene": args.scene, "runs": runs}, __name__, argv)
