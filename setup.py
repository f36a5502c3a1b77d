"""What the wheel installs: only the project's own top-level names.

``zoo`` (the runtime), and ``sdfzoo.cli``, ``sdfzoo.pipeline``, ``sdfzoo.benches``: the repository's
top-level ``cli/``, ``pipeline/`` and ``benches/`` folders, installed under the project's name so that
no generic ``cli`` or ``pipeline`` shadows (or is shadowed by) a user's module. An editable install maps
the same names onto the same folders; code imports them only as ``sdfzoo.*``.

Build step: the wheel carries the top-level manifests/ and scenes/ as zoo/data/. They stay one source
of truth at the top of the project (text, reviewed in git); a clone or an editable install reads them
there, an installed wheel from zoo/data (see zoo.resources).
"""

import shutil
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

BUNDLED = ("manifests", "scenes")
MAPPED = {"sdfzoo.cli": "cli", "sdfzoo.pipeline": "pipeline", "sdfzoo.benches": "benches"}


class BuildWithBundledData(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return  # an editable install reads the project's own folders
        for folder in BUNDLED:
            target = Path(self.build_lib) / "zoo" / "data" / folder
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(folder, target, ignore=shutil.ignore_patterns("*.py", "__pycache__"))


setup(
    # zoo.pretrained holds no code: listed so that its package data (the weights) is not "an importable
    # package absent from packages" to setuptools, which warned about it at length in every install.
    packages=[*find_packages(include=["zoo", "zoo.*"]), "zoo.pretrained", *MAPPED],
    package_dir=MAPPED,
    cmdclass={"build_py": BuildWithBundledData},
)
