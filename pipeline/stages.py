"""A tiny DVC-like stage runner: rerun a stage only when its inputs, config or code changed.

A :class:`Stage` names its input files, its config (a JSON-able dict), the code it runs and its
output files. The code is hashed, not versioned by hand (:func:`code_digest`): each entry of
``Stage.code`` is a module name, standing for the source of that module and of every module of
``pipeline`` and ``zoo`` it imports when it is imported (transitively; an import inside a function
is not followed, so a stage names the modules it reaches that way itself: the samples stage does
not hash the detector that some function of ``zoo.neural`` may import), or a function, standing
for its own source (a stage's build function defined beside other stages). What is hashed is the code without its comments
and docstrings (:func:`source_digest`): editing the code reruns the stage and, when its outputs
change, the stages that read them; editing a comment or a docstring does not. After a successful run,
:func:`run_stage` writes a lock record beside the outputs::

    {"stage": name, "code": [modules...], "code_sha256": "...", "config": {...}, "config_sha256": "...",
     "libraries": {name: version}, "inputs": {label: sha256}, "outputs": {label: sha256},
     "sdfzoo": {"version": ..., "commit": ...}}

``libraries`` are the versions of the third-party libraries whose results a stage's outputs hold
(:data:`OUTPUT_LIBRARIES`): a new torch or libigl reruns the stage; ``sdfzoo`` is provenance only
(which version and source commit wrote the outputs), not part of what must match.

and the next :func:`run_stage` skips the build when a fresh record of the inputs and config
matches it and every output still exists with its recorded sha256. The build function must
write each output atomically (``zoo.files.atomic_path``); the lock is written last, also
atomically, so an interruption at any point leaves a stage that simply reruns.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import inspect
import json
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from zoo.errors import DataError, InputError
from zoo.files import atomic_write_text, sha256_file

LOCK_SUFFIX = ".lock.json"
# The project's own packages, whose sources a stage's code digest covers; third-party code is not hashed.
PROJECT_PACKAGES = ("pipeline", "zoo")
ROOT = Path(__file__).resolve().parent.parent
# Distributions whose numbers end up in the stages' outputs: exact distances (libigl), meshes
# (trimesh), arrays (numpy), networks (torch).
OUTPUT_LIBRARIES = ("libigl", "numpy", "torch", "trimesh")


@functools.cache
def library_versions() -> dict[str, str]:
    """{distribution: installed version} of :data:`OUTPUT_LIBRARIES` ("absent" where not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in OUTPUT_LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "absent"
    return out


@functools.cache
def provenance() -> dict[str, str]:
    """Which sdfzoo wrote an output: {"version", "commit"}; the commit of the clone the code runs from
    (with "+dirty" when its tracked files differ from it), "" for an installed wheel."""
    import subprocess

    import zoo

    commit = ""
    if (ROOT / ".git").exists():
        try:
            git = ["git", "-C", str(ROOT)]
            commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10).stdout.strip()
            dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                   text=True, timeout=10).stdout.strip()
            commit += "+dirty" if commit and dirty else ""
        except (OSError, subprocess.SubprocessError):
            commit = ""
    return {"version": zoo.__version__, "commit": commit}


# --------------------------------------------------------------------------- code digests


def canonical_module(name: str) -> str:
    """A project module's name in digests: "sdfzoo.pipeline.samples" (as setup.py installs pipeline/) is "pipeline.samples"."""
    return name.removeprefix("sdfzoo.")


def _package_folder(package: str) -> Path:
    """The folder of a project package as imported (a clone's top-level folder, or site-packages/sdfzoo/pipeline and zoo)."""
    if package == "pipeline":
        return Path(__file__).resolve().parent
    import zoo

    return Path(zoo.__file__).resolve().parent


def module_file(name: str, root: Path | None = None) -> Path | None:
    """The source file of project module ``name`` ("pipeline.samples") under ``root`` (default the imported packages), or None."""
    parts = canonical_module(name).split(".")
    if parts[0] not in PROJECT_PACKAGES:
        return None
    if root is None and all((ROOT / package).is_dir() for package in PROJECT_PACKAGES):
        root = ROOT  # a clone: its top-level folders (an installed wheel has no zoo/ beside sdfzoo/pipeline/)
    base = root.joinpath(*parts) if root is not None else _package_folder(parts[0]).joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _import_time_nodes(tree: ast.Module):
    """The nodes that run when the module is imported: everything but the bodies of functions."""
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        yield node
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            todo.extend(ast.iter_child_nodes(node))


@functools.cache
def _imports(path: Path, name: str, stamp: tuple) -> frozenset:
    """Project modules that importing ``path`` (module ``name``) imports, relative imports resolved;
    ``stamp`` (mtime, size) makes an edited file parse again."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in _import_time_nodes(ast.parse(path.read_bytes())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([node.module] if node.module else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)  # `from . import x`: x may be a module
    parents = {".".join(m.split(".")[:i]) for m in found for i in range(1, m.count(".") + 1)}  # importing runs them
    found = {canonical_module(m) for m in found | parents}
    return frozenset(m for m in found if m.split(".")[0] in PROJECT_PACKAGES)


def code_closure(modules, root: Path | None = None) -> dict[str, Path]:
    """{module: source file} of ``modules`` and every project module they import, transitively."""
    out: dict[str, Path] = {}
    todo = [canonical_module(m) for m in modules]
    while todo:
        name = todo.pop()
        path = None if name in out else module_file(name, root)
        if path is None:
            continue
        out[name] = path
        stat = path.stat()
        todo.extend(_imports(path, name, (stat.st_mtime_ns, stat.st_size)))
    return dict(sorted(out.items()))


def _without_docstrings(tree: ast.AST) -> ast.AST:
    """``tree`` with the docstring of every module, class and function removed (in place)."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                node.body = node.body[1:] or [ast.Pass()]
    return tree


@functools.lru_cache(maxsize=1024)
def source_digest(source: str | bytes) -> str:
    """sha256 of Python source as code: its syntax tree without docstrings, so comments, docstrings,
    blank lines and line numbers do not count (the tree's dump carries no positions). Source that
    does not parse on its own (a lambda's line) is hashed as text."""
    try:
        tree = _without_docstrings(ast.parse(textwrap.dedent(source) if isinstance(source, str) else source))
    except SyntaxError:
        return hashlib.sha256(source.encode() if isinstance(source, str) else source).hexdigest()
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()


def code_digest(code, root: Path | None = None) -> str:
    """sha256 of the code a stage runs: module names (with their project imports) and functions (their
    source), comments and docstrings aside (see :func:`source_digest`)."""
    h = hashlib.sha256()
    names = [c for c in code if isinstance(c, str)]
    for name, path in code_closure(names, root).items():
        h.update(f"{name}\0{source_digest(path.read_bytes())}\0".encode())
    for fn in (c for c in code if not isinstance(c, str)):
        h.update(f"{fn.__module__}.{fn.__qualname__}\0{source_digest(inspect.getsource(fn))}\0".encode())
    return h.hexdigest()


def _code_names(code) -> list[str]:
    return [c if isinstance(c, str) else f"{c.__module__}.{c.__qualname__}" for c in code]


# --------------------------------------------------------------------------- stages


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
    """One cached step: inputs and outputs are {label: path}; ``code`` the modules (names) and
    functions it runs (see :func:`code_digest`); ``lock`` defaults beside the first output."""

    name: str
    inputs: dict[str, Path]
    config: dict
    outputs: dict[str, Path]
    code: tuple = ()
    lock: Path | None = field(default=None)

    def __post_init__(self):
        if not self.outputs:
            raise InputError(f"stage {self.name!r} declares no outputs; a stage must produce at least one file")
        if not self.code:
            raise InputError(f"stage {self.name!r} names no code; pass code=(module names or functions it runs) "
                             "so that editing them reruns it")
        self.code = tuple(self.code)
        self.inputs = {k: Path(v) for k, v in self.inputs.items()}
        self.outputs = {k: Path(v) for k, v in self.outputs.items()}
        if self.lock is None:
            first = next(iter(self.outputs.values()))
            self.lock = first.with_name(first.name + LOCK_SUFFIX)
        self.lock = Path(self.lock)


def input_record(stage: Stage) -> dict:
    """What determines the outputs: code digest, config and input hashes (DataError for a missing input)."""
    hashes = {}
    for label, path in stage.inputs.items():
        if not path.is_file():
            raise DataError(f"stage {stage.name!r}: input {label!r} ({path}) does not exist; run the stage that makes it first")
        hashes[label] = sha256_file(path)
    return {
        "stage": stage.name,
        "code": _code_names(stage.code),
        "code_sha256": code_digest(stage.code),
        "config": json.loads(canonical_json(stage.config)),
        "config_sha256": config_hash(stage.config),
        "libraries": library_versions(),
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
    if any(lock.get(k) != record[k] for k in ("stage", "code_sha256", "config_sha256", "libraries", "inputs")):
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
    write_lock(stage, record)
    return True


def write_lock(stage: Stage, record: dict) -> None:
    """Record a finished stage: ``record`` (:func:`input_record`) with its outputs' hashes and the provenance."""
    missing = [str(p) for p in stage.outputs.values() if not p.is_file()]
    if missing:
        raise DataError(f"stage {stage.name!r} finished without writing {', '.join(missing)}; this is a bug in the stage")
    record = {**record, "outputs": {label: sha256_file(path) for label, path in stage.outputs.items()},
              "sdfzoo": provenance()}
    atomic_write_text(stage.lock, json.dumps(record, indent=1, sort_keys=True) + "\n")

