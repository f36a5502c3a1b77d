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


def test_investigations_and_benches_reach_no_private_attribute():
    """Investigations and benches measure the package through its public names: no ``obj._name`` on anything but
    their own ``self``/``cls`` (and ``sys._getframe``), so that a private rename cannot silently change what they
    time or patch."""
    offenders = []
    for folder in ("investigations", "benches"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_bytes())):
                if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
                    continue
                owner = node.value.id if isinstance(node.value, ast.Name) else None
                if owner in ("self", "cls") or (owner, node.attr) == ("sys", "_getframe"):
                    continue
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.attr}")
    assert not offenders, "use (or make) a public name:\n" + "\n".join(offenders)


def zoo_import_graph() -> dict[str, set[str]]:
    """{zoo module: the zoo modules it imports}, from every import statement in it (a function's own too: an import
    deferred to call time still ties the two modules together). ``zoo`` itself (the package's lazy names) is left
    out: every module may ``import zoo`` for its public API."""
    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
               for p in (ROOT / "zoo").rglob("*.py") if "pretrained" not in p.parts}
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_bytes())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(parts + ([node.module] if node.module else []))
                # `from X import m` names the module X.m where there is one, else a name of X itself
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in targets:
                while target not in modules and "." in target:
                    target = target.rpartition(".")[0]
                if target in modules and target not in (name, "zoo"):
                    found.add(target)
        graph[name] = found
    return graph


def import_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of ``graph`` (its modules in order, the first repeated at the end), or [] where there is none."""
    state, path = {}, []

    def visit(module: str) -> list[str]:
        state[module] = "open"
        path.append(module)
        for other in sorted(graph[module]):
            if state.get(other) == "open":
                return path[path.index(other):] + [other]
            if other not in state and (cycle := visit(other)):
                return cycle
        state[module] = "done"
        path.pop()
        return []

    for module in sorted(graph):
        if module not in state and (cycle := visit(module)):
            return cycle
    return []


def test_import_cycle_finds_a_cycle_and_passes_a_tree():
    assert import_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert import_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []


def test_no_import_cycle_inside_zoo():
    """The modules of ``zoo`` form layers: none imports, even inside a function, a module that imports it back
    (issue 50: coherence, proxy and proxy_collider imported each other; they share zoo.collider now)."""
    graph = zoo_import_graph()
    assert {"zoo.coherence", "zoo.collider", "zoo.proxy", "zoo.sim.world"} <= set(graph)  # the graph is read
    assert "zoo.collider" in graph["zoo.proxy_collider"] and "zoo.proxy" in graph["zoo.coherence"]
    cycle = import_cycle(graph)
    assert not cycle, "an import cycle: " + " -> ".join(cycle)


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
