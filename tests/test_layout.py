"""The house: the repository keeps its top-level cli/, pipeline/ and benches/ folders, but they are the
packages sdfzoo.cli, sdfzoo.pipeline and sdfzoo.benches (setup.py maps them), in the clone as in the wheel.
Imported under one name only: a second name would load second copies of modules, whose classes and
registries differ from the first's."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAPPED = ("cli", "pipeline", "benches")


def test_no_module_imports_a_top_level_cli_pipeline_or_benches():
    offenders = []
    for path in sorted(ROOT.rglob("*.py")):
        if {".venv", "build", "pretrained"} & set(path.relative_to(ROOT).parts):
            continue
        for node in ast.walk(ast.parse(path.read_bytes())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            offenders += [f"{path.relative_to(ROOT)}:{node.lineno}: {n}" for n in names if n.split(".")[0] in MAPPED]
    assert not offenders, "import these as sdfzoo.<package>:\n" + "\n".join(offenders)


def test_no_module_imports_another_modules_private_names():
    """A name with a leading underscore is its module's own: a module that needs it from another takes a public
    name (issue 37: one narrow phase shared by collide, coherence and the simulation, not private reach-ins)."""
    offenders = []
    for path in sorted(ROOT.rglob("*.py")):
        if {".venv", "build", "pretrained", "tests"} & set(path.relative_to(ROOT).parts):
            continue
        for node in ast.walk(ast.parse(path.read_bytes())):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                private = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno}: {name}" for name in private]
    assert not offenders, "give these a public name in their module:\n" + "\n".join(offenders)


IMPORT_EVERYTHING = """
import importlib, pkgutil, sys
import sdfzoo.benches, sdfzoo.cli, sdfzoo.pipeline, zoo.errors
skip = {"sdfzoo.cli.__main__"}  # runs the command
for package in (sdfzoo.cli, sdfzoo.pipeline, sdfzoo.benches):
    for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        if info.name not in skip:
            importlib.import_module(info.name)
doubles = sorted(m for m in sys.modules if m.split(".")[0] in ("cli", "pipeline", "benches"))
assert not doubles, doubles
from sdfzoo.pipeline import categories
assert categories.InputError is zoo.errors.InputError
print("ok", sum(m.startswith("sdfzoo.") for m in sys.modules))
"""


@pytest.mark.slow
def test_every_module_imports_under_its_sdfzoo_name_alone_from_the_clone():
    """From the clone's root (where `import pipeline` would find the folder), importing everything
    loads no module under a second, top-level name."""
    done = subprocess.run([sys.executable, "-c", IMPORT_EVERYTHING], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.startswith("ok ")


@pytest.mark.slow
def test_python_m_entry_points_work_from_the_clone(tmp_path):
    for args in (["-m", "sdfzoo.cli", "list"], ["-m", "sdfzoo.cli.main", "list"]):
        done = subprocess.run([sys.executable, *args], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0 and "mugs" in done.stdout, done.stderr[-2000:]
    done = subprocess.run([sys.executable, "-m", "sdfzoo.pipeline.evaluate_sdf", "--help"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "usage" in done.stdout
