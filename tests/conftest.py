"""Fixtures shared across test files: a temporary model home and tiny released packages in it."""

from __future__ import annotations

import pytest
from tiny_packages import BOTTLE_SHAPES, MUG_SHAPES, make_fit_output

from zoo import registry
from zoo.offscreen import choose_gl

choose_gl()  # before any test imports mujoco, which reads MUJOCO_GL once: EGL or OSMesa where one renders


@pytest.fixture
def zoo_home(tmp_path, monkeypatch):
    """Empty manifests and pretrained folders for this test only."""
    monkeypatch.setenv(registry.MANIFESTS_ENV, str(tmp_path / "manifests"))
    monkeypatch.setenv(registry.PRETRAINED_ENV, str(tmp_path / "pretrained"))
    (tmp_path / "manifests" / "models").mkdir(parents=True)
    return tmp_path


@pytest.fixture
def released(zoo_home):
    """mugs 1.9.0 and 1.10.0 (lexically smaller, semantically newer) and bottles 1.0.0."""
    from sdfzoo.pipeline.package import package_model

    mugs = make_fit_output(zoo_home / "fits" / "mugs", "mugs", MUG_SHAPES)
    bottles = make_fit_output(zoo_home / "fits" / "bottles", "bottles", BOTTLE_SHAPES, seed=1)
    package_model(mugs, "1.9.0", date="2026-01-01")
    package_model(mugs, "1.10.0", date="2026-02-01")
    package_model(bottles, "1.0.0", date="2026-02-01")
    return zoo_home
