"""Where the tests that need the real development meshes find them, and why they skip without them."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BESIDE_CHECKOUT = ROOT.parent / "shared" / "meshes"


def zoo_data() -> Path | None:
    """$ZOO_DATA, else ../shared/meshes beside the checkout, if it holds the mugs (mug/); else None."""
    for candidate in (os.environ.get("ZOO_DATA"), BESIDE_CHECKOUT):
        if candidate and (Path(candidate) / "mug").is_dir():
            return Path(candidate)
    return None


SKIP_REASON = f"needs the real meshes: a folder with mug/ in $ZOO_DATA or at {BESIDE_CHECKOUT}"

# The folder the data tests read (categories, meshes, samples): $ZOO_DATA, else beside the checkout.
DATA = Path(os.environ.get("ZOO_DATA", BESIDE_CHECKOUT))
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"data folder {DATA} not present (set ZOO_DATA)")
