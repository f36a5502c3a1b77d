"""Where the project's bundled text lives: model manifests and scene files.

One source of truth each, at the top of the project (``manifests/``, ``scenes/``). A clone or an
editable install reads those folders; an installed wheel carries copies under ``zoo/data/``
(setup.py's build step puts them there).
"""

from __future__ import annotations

from pathlib import Path

BUNDLED_KINDS = ("manifests", "scenes")


def bundled(kind: str) -> Path:
    """The folder of bundled ``kind`` ("manifests" or "scenes"): the project's own, else the wheel's."""
    if kind not in BUNDLED_KINDS:
        raise ValueError(f"unknown bundled folder {kind!r}; one of {BUNDLED_KINDS}")
    package = Path(__file__).resolve().parent
    project = package.parent
    in_clone = project / kind
    if in_clone.is_dir() and (project / "pyproject.toml").is_file():
        return in_clone
    return package / "data" / kind
