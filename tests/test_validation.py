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


# -- devices: an unusable device is a typed error that says what to do, before any work -----------


def test_a_cuda_device_without_a_cuda_build_is_a_device_error(monkeypatch):
    from zoo.errors import DeviceError

    monkeypatch.setattr(torch.version, "cuda", None)
    monkeypatch.setattr(torch.version, "hip", None, raising=False)
    with pytest.raises(DeviceError, match="built without CUDA.*--device cpu"):
        v.as_device("cuda")
    with pytest.raises(DeviceError):
        zoo.load("mugs", device="cuda:0")  # before a file is read or a tensor moved
    assert v.as_device("cpu") == torch.device("cpu")


def test_a_gpu_index_past_the_last_and_a_bad_name_are_typed(monkeypatch):
    from zoo.errors import DeviceError

    monkeypatch.setattr(torch.version, "cuda", "12.4")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert v.as_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(DeviceError, match="2 GPU"):
        v.as_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    with pytest.raises(DeviceError, match="no GPU"):
        v.as_device("cuda")
    with pytest.raises(InputError, match="not a torch device"):
        v.as_device("gpu-please")


def test_zoo_fit_category_on_a_missing_gpu_prints_one_line_and_exits_2(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    from sdfzoo.cli.main import app, register_commands

    monkeypatch.setattr(torch.version, "cuda", None)
    monkeypatch.setattr(torch.version, "hip", None, raising=False)
    register_commands()
    done = CliRunner().invoke(app, ["fit-category", "mugs", "--device", "cuda", "--data", str(tmp_path)])
    assert isinstance(done.exception, zoo.errors.DeviceError), done.output
    assert not list(tmp_path.iterdir())
