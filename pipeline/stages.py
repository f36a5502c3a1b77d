"""A tiny DVC-like stage runner: rerun a stage only when its inputs, config or code changed.

A :class:`Stage` names its input files, its config (a JSON-able dict) and its output files.
After a successful run, :func:`run_stage` writes a lock record beside the outputs::

    {"stage": name, "code_version": "...", "config": {...}, "config_sha256": "...",
     "inputs": {label: sha256}, "outputs": {label: sha256}}

and the next :func:`run_stage` skips the build when a fresh record of the inputs and config
matches it and every output still exists with its recorded sha256. The build function must
write each output atomically (``zoo.files.atomic_path``); the lock is written last, also
atomically, so an interruption at any point leaves a stage that simply reruns.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from zoo.errors import DataError, InputError
from zoo.files import atomic_write_text, sha256_file

LOCK_SUFFIX = ".lock.json"


def canonical_json(obj) -> str:
    """JSON with sorted keys and no whitespace, so equal configs hash equally."""
    try:
        return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"a stage config must be JSON-serialisable (dicts, lists, str, finite numbers): {exc}") from exc


def config_hash(config: dict) -> str:
    return hashlib.sha256(canonical_json(config).encode()).hexdigest()


@dataclass
class Stage:
    """One cached step: inputs and outputs are {label: path}; ``lock`` defaults beside the first output."""

    name: str
    inputs: dict[str, Path]
    config: dict
    outputs: dict[str, Path]
    code_version: str = "1"
    lock: Path | None = field(default=None)

    def __post_init__(self):
        if not self.outputs:
            raise InputError(f"stage {self.name!r} declares no outputs; a stage must produce at least one file")
        self.inputs = {k: Path(v) for k, v in self.inputs.items()}
        self.outputs = {k: Path(v) for k, v in self.outputs.items()}
        if self.lock is None:
            first = next(iter(self.outputs.values()))
            self.lock = first.with_name(first.name + LOCK_SUFFIX)
        self.lock = Path(self.lock)


def input_record(stage: Stage) -> dict:
    """What determines the outputs: code version, config and input hashes (DataError for a missing input)."""
    hashes = {}
    for label, path in stage.inputs.items():
        if not path.is_file():
            raise DataError(f"stage {stage.name!r}: input {label!r} ({path}) does not exist; run the stage that makes it first")
        hashes[label] = sha256_file(path)
    return {
        "stage": stage.name,
        "code_version": stage.code_version,
        "config": json.loads(canonical_json(stage.config)),
        "config_sha256": config_hash(stage.config),
        "inputs": hashes,
    }


def read_lock(stage: Stage) -> dict | None:
    """The recorded lock, or None when absent or unreadable (an unreadable lock just means: rerun)."""
    try:
        return json.loads(stage.lock.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def is_up_to_date(stage: Stage, record: dict | None = None) -> bool:
    """True when the lock matches the current inputs/config/code and the outputs are intact."""
    lock = read_lock(stage)
    if lock is None:
        return False
    record = input_record(stage) if record is None else record
    if any(lock.get(k) != record[k] for k in ("stage", "code_version", "config_sha256", "inputs")):
        return False
    recorded = lock.get("outputs", {})
    if set(recorded) != set(stage.outputs):
        return False
    return all(path.is_file() and sha256_file(path) == recorded[label] for label, path in stage.outputs.items())


def run_stage(stage: Stage, build: Callable[[], None], force: bool = False) -> bool:
    """Run ``build()`` unless ``stage`` is up to date; return True when it ran.

    ``build`` writes every declared output (atomically); then the lock is written.
    """
    record = input_record(stage)
    if not force and is_up_to_date(stage, record):
        return False
    build()
    missing = [str(p) for p in stage.outputs.values() if not p.is_file()]
    if missing:
        raise DataError(f"stage {stage.name!r} finished without writing {', '.join(missing)}; this is a bug in the stage")
    record["outputs"] = {label: sha256_file(path) for label, path in stage.outputs.items()}
    atomic_write_text(stage.lock, json.dumps(record, indent=1, sort_keys=True) + "\n")
    return True


def reject_unknown_keys(config_class, d: dict, what: str) -> None:
    """Raise InputError naming the keys of ``d`` that the dataclass ``config_class`` does not have."""
    unknown = set(d) - set(config_class.__dataclass_fields__)
    if unknown:
        raise InputError(f"unknown {what} keys {sorted(unknown)}; known: {sorted(config_class.__dataclass_fields__)}")
