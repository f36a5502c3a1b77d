"""Every `zoo stress` case, its extreme training batches in detail, and malformed meshes given to
fit_codes (API and CLI)."""

from __future__ import annotations

import json

import pytest

import zoo
from sdfzoo.benches.stress import CASES, MODEL_CASES, run_case, run_stress, stress_context
from zoo.errors import DataError, ZooError

STRESS_MODEL = "mugs"  # shipped in the package: the model cases need no $ZOO_DATA
SLOW_CASES = {"extreme training batches", "amortized on huge and penetrating triangles (model)"}  # 5-12 s each


@pytest.fixture(scope="module")
def stress_contexts():
    """The context of `zoo stress` (an analytic torus) and of `zoo stress --model mugs` (None if not packaged)."""
    try:
        with_model = stress_context(STRESS_MODEL)
    except ZooError:
        with_model = None
    return {"plain": stress_context(), "model": with_model}


@pytest.mark.parametrize("name", [pytest.param(name, marks=[pytest.mark.slow] if name in SLOW_CASES else [])
                                  for name, _ in CASES])
def test_stress_case(name, stress_contexts):
    """Each case of the list `zoo stress` runs, as it runs it: the model cases on the shipped mugs model (as
    `--model mugs`), the others on the analytic torus (the default; with a NeuralSDF "one million points"
    alone takes minutes)."""
    ctx = stress_contexts["model"] if name in MODEL_CASES else stress_contexts["plain"]
    if ctx is None:
        pytest.skip(f"needs the {STRESS_MODEL!r} model packaged (zoo.load({STRESS_MODEL!r}) failed)")
    record = run_case(name, dict(CASES)[name], ctx)
    assert record["ok"], json.dumps(record, indent=1)[:4000]
    assert "skipped" not in json.dumps(record["observed"])  # a model case that found no model did not run


def test_stress_reports_extreme_training_batches_ok(tmp_path, monkeypatch):
    import sdfzoo.benches.stress as stress

    monkeypatch.setattr(stress, "CASES", [c for c in CASES if c[0] == "extreme training batches"])
    report = run_stress(tmp_path / "s.json")
    assert (report["passed"], report["failed"]) == (1, 0), json.dumps(report["cases"], indent=1)[:4000]
    observed = json.loads((tmp_path / "s.json").read_text())["cases"][0]["observed"]
    fit, det = observed["fit-sdf"], observed["train-detector"]
    assert all(v["finite"] for k, v in fit.items() if not k.startswith("refused"))
    refused = [v for k, v in fit.items() if k.startswith("refused")]
    assert len(refused) == 3 and all(v.startswith("InputError") for v in refused), refused
    runs = [v for v in det.values() if isinstance(v, dict)]
    assert runs and all(v["finite"] and v["clip_held"] for v in runs)
    # the paper's loss on huge triangles has gradient norms far over grad_clip: clipping engaged
    assert det["steps clipped in all"] > 0


# --------------------------------------------------------------------------- malformed meshes for fit_codes

TETRA_FACES = "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
BAD_MESHES = {
    "nan-vertex.obj": ("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\n" + TETRA_FACES).encode(),
    "inf-vertex.obj": ("v 0 0 0\nv 1 0 0\nv 0 inf 0\nv 0 0 1\n" + TETRA_FACES).encode(),
    "empty.obj": b"",
    "vertices-only.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "garbage.ply": b"ply\nthis is not a mesh\x00\xff\xfe" * 20,
    "garbage.obj": bytes(range(256)) * 8,
    "mesh.txt": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n" + TETRA_FACES).encode(),
}


@pytest.fixture(scope="module")
def model():
    return zoo.load("mugs")


@pytest.mark.parametrize("name", [*BAD_MESHES, "missing.obj"])
def test_fit_codes_refuses_a_malformed_mesh_with_a_data_error(name, model, tmp_path):
    path = tmp_path / name
    if name in BAD_MESHES:
        path.write_bytes(BAD_MESHES[name])
    with pytest.raises(DataError) as info:
        model.fit_codes(path, iters=2, n_points=1000)
    message = str(info.value)
    assert str(path) in message and len(message) > len(str(path)) + 20  # what was wrong and what to do
    if "vertex" in name:  # NaN/Inf vertices: trimesh would silently drop them with their faces
        assert "NaN or Inf" in message


@pytest.mark.parametrize("name", ["nan-vertex.obj", "empty.obj", "garbage.ply", "missing.obj"])
def test_zoo_fit_codes_cli_prints_one_error_line(name, tmp_path, capsys):
    from sdfzoo.cli.main import main

    path = tmp_path / name
    if name in BAD_MESHES:
        path.write_bytes(BAD_MESHES[name])
    with pytest.raises(SystemExit) as info:
        main(["fit-codes", "mugs", str(path), "--iters", "2", "--no-progress"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and str(path) in err[0], err
    assert "Traceback" not in "\n".join(err)


def _zoo(args, capsys):
    """`zoo ARGS` in this process: (exit code, stdout, stderr)."""
    from sdfzoo.cli.main import main

    capsys.readouterr()
    try:
        main(args)
        code = 0
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def test_zoo_stress_sim_without_mujoco_names_the_extra_in_one_line(monkeypatch, tmp_path, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco raises ImportError, as without sdfzoo[sim]
    code, out, err = _zoo(["stress", "--sim", "--out", str(tmp_path / "s.json")], capsys)
    assert code == 2 and "FAIL" not in out + err, out + err
    assert err.strip().count("\n") == 0 and "sdfzoo[sim]" in err and "mujoco" in err
    assert not (tmp_path / "s.json").exists()


def test_zoo_help_keeps_its_brackets(capsys):
    """Help texts print as written: rich markup took "[sim]" and "[@VERSION]" for tags and dropped them."""
    code, out, _ = _zoo(["stress", "--help"], capsys)
    assert code == 0
    assert "sdfzoo[sim]" in out and "NAME[@VERSION]" in out


def test_a_failed_stress_case_says_why_on_the_console(monkeypatch, tmp_path, capsys):
    import sdfzoo.benches.stress as stress

    def broken(ctx):
        raise RuntimeError("the reason it failed")

    monkeypatch.setattr(stress, "CASES", [("a broken case", broken)])
    code, out, err = _zoo(["stress", "--out", str(tmp_path / "s.json")], capsys)
    assert code == 1 and "FAIL a broken case" in out
    assert "RuntimeError: the reason it failed" in out and "0 passed, 1 failed" in out
    assert "stress case: a broken case ..." in err  # its progress line (stderr is not a terminal here)
