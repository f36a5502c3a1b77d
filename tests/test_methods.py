"""zoo.methods: one registry of narrow-phase methods that collide, the coherent collider and the simulation read."""

from __future__ import annotations

import pytest
import torch

import zoo
from zoo.errors import InputError
from zoo.methods import NARROW_PHASES, check_supports, iterations, method_for, narrow_phase

# a triangle 1 cm inside a 0.25 m sphere's surface: its minimum is at its vertex nearest the centre
TRIANGLE = torch.tensor([[0.24, 0.0, 0.0], [0.26, 0.02, 0.0], [0.26, -0.02, 0.01]], dtype=torch.float64)


def test_every_method_needing_no_detector_finds_the_known_minimum_through_collide_and_the_collider():
    sphere = zoo.Sphere(0.25)
    expected = float(sphere(TRIANGLE[:1]).item())  # the vertex nearest the centre, f = -0.01
    faces = torch.tensor([[0, 1, 2]])
    for name, method in NARROW_PHASES.items():
        if method.needs_detector:
            continue
        found = zoo.collide(sphere, (TRIANGLE, faces), margin=1e-3, method=name)
        assert len(found) == 1 and float(found.depths[0]) == pytest.approx(expected, abs=2e-3), name
        coherent = zoo.CoherentCollider(sphere, (TRIANGLE, faces), margin=1e-3, method=name)()
        assert float(coherent.depths[0]) == pytest.approx(expected, abs=2e-3), name


def test_iterations_default_override_and_one_pass():
    assert iterations("fw", None) == NARROW_PHASES["fw"].default_iters == zoo.collision.DEFAULT_ITERS["fw"]
    assert iterations("pgd", 7) == 7
    assert iterations("amortized", None) is None
    with pytest.raises(InputError, match="one pass"):
        iterations("amortized", 5)
    with pytest.raises(InputError, match="iters"):
        iterations("fw", 0)


def test_an_unknown_method_lists_the_registry():
    with pytest.raises(InputError, match="unknown method 'newton'.*'fw'.*'amortized'"):
        narrow_phase("newton")
    with pytest.raises(InputError, match="unknown method"):
        zoo.collide(zoo.Sphere(0.25), TRIANGLE[None], method="newton")


def test_the_detector_method_refuses_an_sdf_without_one_and_the_simulation_falls_back():
    sphere = zoo.Sphere(0.25)
    with pytest.raises(InputError, match="has no detect"):
        check_supports("amortized", sphere)
    with pytest.raises(InputError, match="has no detect"):
        zoo.collide(sphere, TRIANGLE[None], method="amortized")
    with pytest.raises(InputError, match="has no detect"):
        zoo.CoherentCollider(sphere, (TRIANGLE, torch.tensor([[0, 1, 2]])), method="amortized")
    assert method_for("amortized", sphere) == NARROW_PHASES["amortized"].fallback == "fw"
    assert method_for("pgd", sphere) == "pgd"


def test_a_models_shape_keeps_the_detector():
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    assert method_for("amortized", shape) == "amortized" and check_supports("amortized", shape).needs_detector
