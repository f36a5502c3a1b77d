"""`zoo` commands: bench."""

from __future__ import annotations

import typer  # noqa: F401

from .main import app  # noqa: F401
