"""The training infrastructure both training stages use (fit_sdf, train_detector).

* :func:`run_fingerprint`: what identifies a run (its config, a digest of its data and of the
  code that trains); a checkpoint resumes only the run it was written by.
* :class:`Checkpoint`: atomic saves (temporary file + rename: a kill -9 mid-write leaves the
  previous checkpoint) every ``every`` steps and at the end; :meth:`Checkpoint.load` returns the
  saved state of this run, or None to start afresh. A checkpoint of another run (other config,
  data or code) and a torn or unreadable one are handled the same way, in both stages: a
  :class:`CheckpointWarning` says why it is not used, and training restarts from step 0 (the
  file is overwritten at the next save). Restarting is always correct, since every run is a
  function of (config, data) alone; resuming a file that cannot be trusted is not.
* :func:`cosine_factor`, :func:`halving_factor`, :func:`set_learning_rates`: the learning-rate
  schedules, as multipliers of each parameter group's ``base_lr``.
* :func:`train_steps`: the loop over steps with the progress bar and the checkpointing.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

from zoo.files import atomic_path
from zoo.progress import task_bar


class CheckpointWarning(UserWarning):
    """A checkpoint was found but not resumed (another run's, or unreadable): training starts afresh."""


# --------------------------------------------------------------------------- fingerprints


def data_digest(*parts) -> str:
    """sha256 of training data: tensors by dtype, shape and bytes (wherever they live); None skipped;
    anything else (names, lists) by its JSON."""
    h = hashlib.sha256()
    for part in parts:
        if part is None:
            continue
        if isinstance(part, torch.Tensor):
            t = part.detach().cpu().contiguous()
            h.update(f"{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy())  # the buffer itself: a memory-mapped tensor is not copied
        else:
            h.update(json.dumps(part, sort_keys=True).encode())
    return h.hexdigest()


def run_fingerprint(config: dict, data: str, code: str) -> str:
    """Identifies a training run: its config (a JSON-able dict), its data digest and its code digest."""
    blob = json.dumps({"config": config, "data": data, "code": code}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


# --------------------------------------------------------------------------- checkpoints


class Checkpoint:
    """The checkpoint file of one run: ``path`` (None: no checkpointing), the run's ``fingerprint``,
    saved every ``every`` steps and after step ``total``; ``writer`` False on processes that only read."""

    def __init__(self, path, fingerprint: str, every: int, total: int, writer: bool = True):
        self.path = Path(path) if path is not None else None
        self.fingerprint, self.every, self.total, self.writer = fingerprint, every, total, writer

    def load(self, map_location=None) -> dict | None:
        """This run's saved state, or None (no file; another run's or an unreadable one, with a warning)."""
        if self.path is None or not self.path.is_file():
            return None
        try:
            state = torch.load(self.path, map_location=map_location, weights_only=True)  # tensors and dicts: no pickle
        except Exception as exc:  # torn or foreign: any reader error means the same, it cannot be resumed
            return self._discard(f"it cannot be read ({type(exc).__name__}: {exc})")
        if not isinstance(state, dict) or state.get("fingerprint") != self.fingerprint:
            return self._discard("it belongs to another run (other config, training data or code)")
        return state

    def _discard(self, why: str) -> None:
        warnings.warn(f"checkpoint {self.path} is not resumed: {why}; training starts afresh and overwrites it",
                      CheckpointWarning, stacklevel=3)
        return None

    def due(self, done: int) -> bool:
        """True when a state after ``done`` steps should be saved."""
        return self.path is not None and self.writer and (done % self.every == 0 or done == self.total)

    def save(self, state: dict) -> None:
        """Write ``state`` (plus this run's fingerprint) atomically."""
        with atomic_path(self.path) as tmp:
            torch.save({**state, "fingerprint": self.fingerprint}, tmp)


# --------------------------------------------------------------------------- learning rates


def cosine_factor(t: float, final: float) -> float:
    """Cosine decay from 1 at ``t`` = 0 to ``final`` at ``t`` = 1."""
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * t))


def halving_factor(step: int, every: int) -> float:
    """Halve every ``every`` steps."""
    return 0.5 ** (step // every)


def set_learning_rates(optimizer: torch.optim.Optimizer, factor: float) -> None:
    """Every parameter group's lr = its ``base_lr`` x ``factor``."""
    for group in optimizer.param_groups:
        group["lr"] = group["base_lr"] * factor


# --------------------------------------------------------------------------- the loop


def train_steps(start: int, total: int, step: Callable[[int], str], checkpoint: Checkpoint | None,
                state: Callable[[int], dict], progress: bool, description: str, stop_after: int | None = None) -> None:
    """Run ``step(i)`` for i in [start, total) under a progress bar; save ``state(i + 1)`` when due.

    ``step`` returns a short status ("loss 0.0123") shown after ``description``; ``stop_after``
    ends the loop after that many steps in all, as an interruption would (for tests).
    """
    with task_bar(progress, description, total, completed=start) as bar:
        for i in range(start, total):
            status = step(i)
            if checkpoint is not None and checkpoint.due(i + 1):
                checkpoint.save(state(i + 1))
            bar.advance(description=f"{description}  {status}")
            if stop_after is not None and i + 1 >= stop_after:
                break
