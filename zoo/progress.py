"""The one progress bar of sdfzoo (rich): the pipeline's stages, the benches, code fitting, simulations.

:func:`progress_bar` is the factory: a :class:`rich.progress.Progress` with the house columns
(description, bar, done/total, elapsed, remaining), inert when ``enabled`` is False so callers
never branch on it. :func:`task_bar` wraps it for the common case of one task that advances
step by step (training loops, per-shape stages).

Library calls that take no ``progress`` argument (the voxel grid ``zoo.collide`` builds on first use,
a stress case) show theirs only inside :func:`shown`, which the ``zoo`` command turns on; a library
user sees nothing unless they ask. :func:`activity` is the indicator of one long step of unknown
length: a spinner with the time spent on a terminal, one line on stderr otherwise.

rich is imported when a bar is made, not with this module, so ``import zoo`` does not load it.
"""

from __future__ import annotations

import contextvars
import sys
from contextlib import contextmanager

_SHOWN = contextvars.ContextVar("zoo_progress_shown", default=False)


@contextmanager
def shown(enabled: bool = True):
    """Within this block, progress that a caller left unset (``None``) is shown (``enabled``) or not."""
    token = _SHOWN.set(bool(enabled))
    try:
        yield
    finally:
        _SHOWN.reset(token)


def wanted(enabled: bool | None) -> bool:
    """``enabled`` where a caller set it, else whether :func:`shown` is on."""
    return _SHOWN.get() if enabled is None else bool(enabled)


@contextmanager
def activity(description: str, enabled: bool | None = None):
    """One long step of unknown length: a spinner with the elapsed time on a terminal, else a line on stderr."""
    if not wanted(enabled):
        yield
        return
    from rich.console import Console

    console = Console(stderr=True)
    if not console.is_terminal:
        print(f"{description} ...", file=sys.stderr, flush=True)
        yield
        return
    with progress_bar(True) as bar:
        bar.add_task(description, total=None)
        yield


def progress_bar(enabled: bool = True):
    """A rich Progress with the house columns; disabled (draws nothing) when ``enabled`` is False."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), disable=not enabled)


class TaskBar:
    """One task of a :func:`progress_bar`: ``advance(description=...)`` moves it one step on."""

    def __init__(self, bar, task):
        self.bar, self.task = bar, task

    def advance(self, steps: int = 1, description: str | None = None) -> None:
        self.bar.update(self.task, advance=steps, **({"description": description} if description is not None else {}))

    def describe(self, description: str) -> None:
        self.bar.update(self.task, description=description)


@contextmanager
def task_bar(enabled: bool, description: str, total: int | None, completed: int = 0):
    """Context manager yielding a :class:`TaskBar` of ``total`` steps, ``completed`` of them already done."""
    with progress_bar(enabled) as bar:
        yield TaskBar(bar, bar.add_task(description, total=total, completed=completed))
