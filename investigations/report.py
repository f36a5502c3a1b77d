"""How a bench writes its JSON: with the command that made it (to run it again) and the machine it ran on."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from zoo.files import atomic_write_text


def write_report(path, report: dict, module: str, argv: list[str] | None = None) -> None:
    """Write ``report`` to ``path`` atomically, adding ``machine`` (:func:`benches.solvers.machine_info`) and ``command``:
    ``python -m <module>`` and its arguments, ``argv`` where a caller passed them, else the process's own."""
    from sdfzoo.benches.solvers import machine_info

    args = sys.argv[1:] if argv is None else argv
    full = {**report, "machine": machine_info(), "command": " ".join(["python", "-m", module, *args])}
    atomic_write_text(Path(path), json.dumps(full, indent=1))
    print(f"written: {path}")
