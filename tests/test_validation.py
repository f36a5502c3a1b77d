"""zoo.validation: the argument checks zoo and the pipeline share, and the names zoo exports."""

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

import zoo
from zoo import validation as v
from zoo.errors import InputError


def test_scalars_convert_or_raise_the_message_that_names_them():
    assert v.positive_float(2, "radius") == 2.0
    assert v.non_negative_float(0, "margin") == 0.0
    assert v.positive_int(np.int64(3), "n") == 3
    assert v.non_negative_int(0, "iters") == 0
    assert v.int_at_least(4, "refine") == 4
    assert v.float_in(0.5, "decay", 0.0, 1.0, low_open=True) == 0.5
    assert v.interval((1, 2), "edge", positive=True) == (1.0, 2.0)
    for call, message in [
        (lambda: v.positive_float(0, "radius"), "radius must be a positive finite number, got 0"),
        (lambda: v.positive_float("x", "radius"), "radius must be a positive finite number, got 'x'"),
        (lambda: v.non_negative_float(-1.0, "margin"), "margin must be a finite number >= 0, got -1.0"),
        (lambda: v.non_negative_float(None, "margin"), "margin must be a number >= 0, got None"),
        (lambda: v.positive_int(True, "n"), "n must be a positive integer, got True"),
        (lambda: v.non_negative_int(2.5, "iters"), "iters must be a non-negative integer, got 2.5"),
        (lambda: v.int_at_least(0, "iters", minimum=1), "iters must be an int >= 1, got 0"),
        (lambda: v.float_in(math.nan, "tol", 0.0, math.inf), r"tol must be a finite number in \[0.0, inf\], got nan"),
        (lambda: v.interval((2, 1), "edge"), r"edge must be finite with low <= high, got \(2, 1\)"),
        (lambda: v.vector3((1, 2), "center"), r"center must be three finite numbers, got \(1, 2\)"),
    ]:
        with pytest.raises(InputError, match=message):
            call()


def test_tensors_keep_float64_and_refuse_empty_unless_allowed():
    assert v.as_points(np.zeros((2, 3))).dtype == torch.float64
    assert v.as_points([[0, 0, 0]]).dtype == torch.float32
    assert v.as_triangles(torch.zeros(3, 3)).shape == (1, 3, 3)
    assert v.as_triangles([], allow_empty=True).shape == (0, 3, 3)
    assert v.as_points([], allow_empty=True).shape == (0, 3)
    with pytest.raises(InputError, match="points is empty"):
        v.as_points(torch.zeros(0, 3))
    with pytest.raises(InputError, match=r"holds NaN or Inf in 1 row\(s\)"):
        v.as_triangles(torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, math.nan]]]))
    with pytest.raises(InputError, match="project them first"):
        v.as_simplex(torch.tensor([[0.5, 0.6, 0.0]]), torch.zeros(1, 3, 3), "bary")
    with pytest.raises(InputError, match="rotation"):
        v.as_pose(np.ones((4, 4)))


def test_meshes_and_faces():
    vertices, faces = v.mesh_pair((np.zeros((3, 3)), [[0, 1, 2]]))
    assert v.as_faces(faces, 3).tolist() == [[0, 1, 2]]
    assert v.as_faces([], 0).shape == (0, 3)
    with pytest.raises(InputError, match="outside 0..2"):
        v.as_faces([[0, 1, 3]], 3)
    with pytest.raises(InputError, match="Trimesh"):
        v.mesh_pair("mesh.obj")


def test_collide_is_the_function_and_every_exported_name_exists():
    import zoo.collision

    assert callable(zoo.collide) and zoo.collide is zoo.collision.collide
    assert all(hasattr(zoo, name) for name in zoo.__all__)
    assert {"load", "list_models", "collide", "Contacts", "Sphere", "Box", "Torus", "solvers"} <= set(zoo.__all__)


def test_import_zoo_imports_each_public_name_on_first_use():
    """`import zoo` runs zoo/__init__.py alone; a public name imports its own module (and what that
    imports), not the others: an edit of zoo.collision does not touch code that only uses zoo.Sphere."""
    code = ("import sys, zoo; before = sorted(m for m in sys.modules if m.startswith('zoo.')); zoo.Sphere; "
            "from zoo import errors; print(before, 'zoo.sdf' in sys.modules, 'zoo.collision' in sys.modules, "
            "zoo.solvers.frank_wolfe.__module__, zoo.collide.__module__, sorted(dir(zoo)) == sorted(set(dir(zoo))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["[]", "True", "False", "zoo.solvers", "zoo.collision", "True"]
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        zoo.not_a_name  # noqa: B018
