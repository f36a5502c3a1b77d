"""How an investigation writes its JSON: with the command that made it (to run it again) and the machine it ran on."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from zoo.files import atomic_write_text


def command(module: str) -> str:
    """The runner's command for investigation ``module`` (its ``__name__``, or its bare name): ``python -m investigations NAME``."""
    return f"python -m investigations {module.rsplit('.', 1)[-1]}"


def write_report(path, report: dict, module: str, argv: list[str] | None = None) -> None:
    """Write ``report`` to ``path`` atomically, adding ``machine`` (:func:`sdfzoo.benches.solvers.machine_info`) and
    ``command``: the runner's command for ``module`` with its arguments, ``argv`` where a caller passed them, else the
    process's own (the runner leaves them in ``sys.argv[1:]``)."""
    from sdfzoo.benches.solvers import machine_info

    args = sys.argv[1:] if argv is None else argv
    full = {**report, "machine": machine_info(), "command": " ".join([command(module), *args])}
    atomic_write_text(Path(path), json.dumps(full, indent=1))
    print(f"written: {path}")
