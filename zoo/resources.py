"""Where the project's bundled files live: model manifests, category manifests, scene files.

One source of truth each, at the top of the project (``manifests/``, ``scenes/``). A clone or an
editable install reads those folders; an installed wheel carries copies under ``zoo/data/``
(setup.py's build step puts them there). Every reader finds them through :func:`bundled`.
"""

from __future__ import annotations

import os
from pathlib import Path

BUNDLED_KINDS = ("manifests", "scenes")


def package_folder() -> Path:
    """The folder of the ``zoo`` package imported."""
    return Path(__file__).resolve().parent


def in_clone() -> bool:
    """True when ``zoo`` is imported from the project's own folder (a clone or an editable install)."""
    project = package_folder().parent
    return (project / "pyproject.toml").is_file() and (project / "manifests").is_dir()


def bundled(kind: str) -> Path:
    """The folder of bundled ``kind`` ("manifests" or "scenes"): the project's own, else the wheel's."""
    if kind not in BUNDLED_KINDS:
        raise ValueError(f"unknown bundled folder {kind!r}; one of {BUNDLED_KINDS}")
    return package_folder().parent / kind if in_clone() else package_folder() / "data" / kind


def inside_installed_package(path: str | os.PathLike) -> bool:
    """True when ``path`` lies inside an installed (not a clone's) ``zoo`` package: a place to read, never to write."""
    if in_clone():
        return False
    return Path(path).resolve().is_relative_to(package_folder())
