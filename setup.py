"""Build step: the wheel carries the top-level manifests/ and scenes/ as zoo/data/.

They stay one source of truth at the top of the project (text, reviewed in git); a clone or an
editable install reads them there, an installed wheel from zoo/data (see zoo.resources).
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

BUNDLED = ("manifests", "scenes")


class BuildWithBundledData(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return  # an editable install reads the project's own folders
        for folder in BUNDLED:
            target = Path(self.build_lib) / "zoo" / "data" / folder
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(folder, target, ignore=shutil.ignore_patterns("*.py", "__pycache__"))


setup(cmdclass={"build_py": BuildWithBundledData})
