"""What the code and the docs cite exists: every docs/*.md that a module, a test or a document names, every
`python -m` command that the docs, the README, the manifests, the model cards and the code give, and every file
of the repository that they point to."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

from investigations.__main__ import names as investigations

ROOT = Path(__file__).resolve().parents[1]
CODE = sorted(p for folder in ("zoo", "pipeline", "cli", "benches", "investigations") for p in (ROOT / folder).rglob("*.py")
              if "pretrained" not in p.parts)
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RELEASES = [*sorted((ROOT / "manifests" / "models").glob("*.toml")), *sorted((ROOT / "zoo" / "pretrained").glob("*/README.md"))]
TESTS = sorted((ROOT / "tests").glob("*.py"))


def _citations(pattern: str, paths: list[Path]) -> dict[str, str]:
    """Each match of ``pattern`` in ``paths`` (its first group, whitespace collapsed) -> the first file citing it."""
    found: dict[str, str] = {}
    for path in paths:
        for match in re.finditer(pattern, path.read_text()):
            found.setdefault(" ".join(match.group(1).split()), str(path.relative_to(ROOT)))
    return found


def test_every_document_the_code_and_the_docs_cite_exists():
    cited = _citations(r"(?<![\w/.-])(docs/[\w.-]+\.md)\b", CODE + TESTS + DOCS)
    assert len(cited) >= 5, "no citation found: the pattern is out of date"
    assert not [f"{doc} (cited in {where})" for doc, where in sorted(cited.items()) if not (ROOT / doc).is_file()]


def _runs(command: str) -> bool:
    module, *args = command.split()
    if module == "investigations":  # the runner: its NAME must be one (NAME and --options are placeholders)
        return not args or args[0].isupper() or args[0].startswith("-") or args[0] in investigations()
    if module.split(".")[0] in ("cli", "pipeline", "benches"):  # found from the clone's root, but not their name
        return False
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # its package does not exist
        return False


@pytest.mark.parametrize("texts", ["releases", "docs", "code"])
def test_every_python_m_command_cited_exists(texts):
    """The commands name modules that exist (a renamed bench left the releases citing `python -m
    pipeline.bench_detector`, the docs `python -m benches.sim_bench`); `python -m investigations NAME`, an
    investigation that exists. A command may be wrapped across lines."""
    paths = {"releases": RELEASES, "docs": DOCS, "code": CODE}[texts]
    cited = _citations(r"python -m\s+([\w.]+(?:[ \t]+[\w-]+)?)", paths)
    assert cited, "no command found: the pattern is out of date"
    assert not [f"python -m {command} (in {where})" for command, where in sorted(cited.items()) if not _runs(command)]


def test_every_repository_file_the_docs_point_to_exists():
    """docs/ and the README name source files (`investigations/query_sites.py`, `benches/sim_scenarios.py`, scene files):
    each must be there."""
    folders = "zoo|pipeline|cli|benches|investigations|tests|scenes|manifests"
    cited = _citations(rf"(?<![\w/.-])((?:{folders})/[\w/.-]+\.(?:py|toml|xml|md))\b", DOCS)
    assert len(cited) >= 5, "no path found: the pattern is out of date"
    assert not [f"{path} (in {where})" for path, where in sorted(cited.items()) if not (ROOT / path).is_file()]
