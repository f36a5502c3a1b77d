"""Robot models an MJCF names by ``robots/NAME/...`` and that are not shipped with the project.

A scene's MJCF can include a robot kept outside the repository (the Franka Panda of
``../shared/robots``, whose license keeps it out of the wheel): every file reference of the form
``robots/NAME/...`` (``<include file=...>``, ``<compiler meshdir=...>``) is read from the robots folder,
found in this order: a ``robots`` folder beside the MJCF, ``$ZOO_ROBOTS``, ``$ZOO_DATA/../robots``. The files
reach MuJoCo's parser as its ``include`` and ``assets`` dictionaries, so the MJCF needs no absolute path.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..errors import DataError

REFERENCE = re.compile(r"""(?:file|meshdir|texturedir|assetdir)\s*=\s*["']robots/([^/"']+)""")


def robot_names(xml: str) -> list[str]:
    """The robots (folder names) an MJCF's text refers to as ``robots/NAME/...``."""
    return sorted(set(REFERENCE.findall(xml)))


def robots_folder(mjcf: Path, names: list[str]) -> Path:
    """The folder holding every robot in ``names`` (see the module docstring), or a DataError that says where
    it looked and what to set."""
    candidates = [mjcf.parent / "robots"]
    if os.environ.get("ZOO_ROBOTS"):
        candidates.append(Path(os.environ["ZOO_ROBOTS"]))
    if os.environ.get("ZOO_DATA"):
        candidates.append(Path(os.environ["ZOO_DATA"]).parent / "robots")
    for folder in candidates:
        if all((folder / name).is_dir() for name in names):
            return folder
    looked = ", ".join(str(c) for c in candidates)
    raise DataError(f"{mjcf.name} uses the robot(s) {names}, which are not in the repository: none of {looked} holds "
                    f"them; set ZOO_DATA (the robots folder is $ZOO_DATA/../robots, e.g. ../shared/robots) or ZOO_ROBOTS")


def robot_files(mjcf: Path) -> tuple[dict[str, bytes], dict[str, bytes]]:
    """(include, assets) for ``mujoco.MjSpec.from_file``: every file of each robot ``mjcf`` refers to, keyed
    ``robots/NAME/relative/path`` (XML files as includes, the rest as assets); both empty if it refers to none."""
    names = robot_names(mjcf.read_text(errors="replace"))
    if not names:
        return {}, {}
    folder = robots_folder(mjcf, names)
    include, assets = {}, {}
    for name in names:
        for path in sorted((folder / name).rglob("*")):
            if path.is_file():
                key = f"robots/{path.relative_to(folder).as_posix()}"
                (include if path.suffix.lower() == ".xml" else assets)[key] = path.read_bytes()
    return include, assets
