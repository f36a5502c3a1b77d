"""The one progress bar of sdfzoo (rich): the pipeline's stages, the benches, code fitting, simulations.

:func:`progress_bar` is the factory: a :class:`rich.progress.Progress` with the house columns
(description, bar, done/total, elapsed, remaining), inert when ``enabled`` is False so callers
never branch on it. :func:`task_bar` wraps it for the common case of one task that advances
step by step (training loops, per-shape stages).

rich is imported when a bar is made, not with this module, so ``import zoo`` does not load it.
"""

from __future__ import annotations

from contextlib import contextmanager


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
