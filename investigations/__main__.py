"""The runner: ``python -m investigations NAME [ARGS]`` runs ``investigations.NAME.main(ARGS)``; no NAME lists them."""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

from investigations.report import command

NOT_INVESTIGATIONS = {"report", "__main__"}


def names() -> list[str]:
    """The investigations: every module of this folder but the runner and the report helper."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if m.name not in NOT_INVESTIGATIONS)


def summary(name: str) -> str:
    """The first line of investigation ``name``'s docstring."""
    doc = importlib.import_module(f"investigations.{name}").__doc__ or ""
    return doc.strip().splitlines()[0] if doc.strip() else ""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m investigations NAME [ARGS]   (NAME --help for its options)\n")
        for name in names():
            print(f"  {name:<16} {summary(name)}")
        return 0
    name = argv[0].replace("-", "_")
    if name not in names():
        print(f"error: no investigation {argv[0]!r}; one of: {', '.join(names())}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"investigations.{name}")
    saved, sys.argv = sys.argv, [command(name), *argv[1:]]  # what argparse's usage and write_report name
    try:
        return module.main(argv[1:]) or 0
    finally:
        sys.argv = saved


if __name__ == "__main__":
    sys.exit(main())
