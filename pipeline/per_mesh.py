"""Per-mesh stages: each rank works through its share of the meshes; a mesh that fails is set aside.

A category of thousands of meshes from the wild holds a few that do not load, do not close, or
defeat a sampler. :func:`for_each_mesh` runs one stage's work on every mesh of this rank's share
(:meth:`pipeline.distributed.World.share`), catches what a mesh raises, and records it as a
:class:`SetAside` (stem, stage, reason) instead of ending the run; with ``strict`` the first failure
ends the run as before. The ranks then exchange their results, so every rank knows every mesh's.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from zoo.files import atomic_write_text
from zoo.progress import task_bar

from .distributed import World

SET_ASIDE_FILE = "set-aside.json"


@dataclass(frozen=True)
class SetAside:
    """A mesh left out of the run: at which stage, and why (the error's type and message)."""

    stem: str
    stage: str
    reason: str


@dataclass
class MeshResults:
    """What a per-mesh stage returned for each mesh it finished, and the meshes it set aside."""

    done: dict = field(default_factory=dict)  # stem -> the stage's result for that mesh
    set_aside: list[SetAside] = field(default_factory=list)


def for_each_mesh(world: World, stage: str, stems: list[str], work: Callable[[str], object], strict: bool = False,
                  progress: bool = True) -> MeshResults:
    """``work(stem)`` for each stem of this rank's share; -> every rank's results, gathered on every rank.

    ``work`` returns a small picklable result (a path, a dict of metrics). A mesh whose ``work`` raises is
    set aside (``strict``: the error propagates and the run stops). Rank 0 shows the progress of the
    whole stage, counting each mesh it finishes for ``world.size`` (every rank has as many, give or take one).
    """
    mine = MeshResults()
    with task_bar(progress and world.main, stage, total=len(stems)) as bar:
        for stem in world.share(stems):
            bar.describe(f"{stage}: {stem}")
            try:
                mine.done[stem] = work(stem)
            except Exception as exc:  # a mesh from the wild can fail in any library: it is set aside, with why
                if strict:
                    raise
                mine.set_aside.append(SetAside(stem, stage, f"{type(exc).__name__}: {exc}"))
            bar.advance(world.size)
    return merge_results(world.gather(mine))


def merge_results(parts: list[MeshResults]) -> MeshResults:
    """One :class:`MeshResults` of every rank's, in stem order."""
    done = {stem: result for part in parts for stem, result in part.done.items()}
    set_aside = [entry for part in parts for entry in part.set_aside]
    return MeshResults(dict(sorted(done.items())), sorted(set_aside, key=lambda s: s.stem))


def write_set_aside(path: Path, set_aside: list[SetAside]) -> Path:
    """The set-aside list as JSON (a list of {stem, stage, reason}), written atomically."""
    atomic_write_text(path, json.dumps([asdict(s) for s in set_aside], indent=1) + "\n")
    return path

