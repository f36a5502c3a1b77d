"""Every `zoo stress` case, its extreme training batches in detail, and malformed meshes given to
fit_codes (API and CLI)."""

from __future__ import annotations

import json
import math

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


# What each case must show, judged here on what it observed (the case's own "ok" is the command's summary).


def _solvers_on_simplex(observed: dict) -> None:
    assert all(g["on_simplex"] for g in observed.values())


def _median_gaps_below(bound: float):
    def check(observed: dict) -> None:
        _solvers_on_simplex(observed)
        assert all(g["p50"] < bound for g in observed.values())

    return check


def _degenerate(observed: dict) -> None:
    gap = observed.pop("fw-10 gap to the reference")
    assert set(observed) >= {"fw-10", "pgd"} and set(observed.values()) == {"on simplex"}
    assert gap < 1e-3


def _tiny(observed: dict) -> None:
    _solvers_on_simplex(observed)
    assert all(g["max"] < 1e-5 for g in observed.values())


def _far(observed: dict) -> None:
    assert observed["contacts"] == 0 and observed["candidates"] == 0 and observed["on_simplex"]


def _penetrating(observed: dict) -> None:
    _median_gaps_below(1e-3)(observed["gaps"])
    assert observed["deepest"] < 0


def _tangent(observed: dict) -> None:
    gaps = {int(k): v for k, v in observed.items()}
    assert all(math.isfinite(v) and v >= 0 for v in gaps.values())
    assert gaps[200] < gaps[10]


def _zero(observed: dict) -> None:
    assert observed.pop("contacts") == 0
    assert set(observed) >= {"fw-10", "pgd"} and all(shape == [0, 3] for shape in observed.values())


def _medial(observed: dict) -> None:
    assert len(observed) == 3 and all(r["grad_finite"] and math.isfinite(r["value"]) for r in observed.values())


def _precision(observed: dict) -> None:
    assert observed["dtype"] == "torch.float64" and observed["max_value_diff"] < 1e-4


def _units(observed: dict) -> None:
    assert observed["contacts_m"] == observed["contacts_mm"] > 0 and observed["same_triangles"]
    assert observed["depth_diff_mm"] < 1e-2


def _million(observed: dict) -> None:
    assert observed["values"] == 1_000_000 and observed["finite"]


def _code_positions(observed: dict) -> None:
    assert observed["points"] > 0 and observed["finite"]


def _saturation(observed: dict) -> None:
    assert len(observed) == 3 and set(observed.values()) == {"on simplex"}


def _amortized_extremes(observed: dict) -> None:
    assert set(observed) == {"huge", "penetrating"} and all(v["on_simplex"] for v in observed.values())
    assert observed["penetrating"]["p50"] < 1e-2  # normalised units: the detector's answer is near the global minimum


def _extreme_training(observed: dict) -> None:
    fit, det = observed["fit-sdf"], observed["train-detector"]
    assert all(v["finite"] for k, v in fit.items() if not k.startswith("refused"))
    refused = [v for k, v in fit.items() if k.startswith("refused")]
    assert len(refused) == 3 and all(v.startswith("InputError") for v in refused), refused
    runs = [v for v in det.values() if isinstance(v, dict)]
    assert len(runs) == 16 and all(v["finite"] and v["clip_held"] and v["clip_calls"] == v["steps"] for v in runs)
    # the paper's loss on huge triangles has gradient norms far over grad_clip: clipping engaged
    assert det["steps clipped in all"] > 0


def _malformed(observed: dict) -> None:
    from sdfzoo.benches.stress import BAD_INPUTS

    error_names = {cls.__name__ for cls in _subclasses(ZooError)}
    assert set(observed) == {name for name, _ in BAD_INPUTS}
    for case, line in observed.items():
        name, _, message = line.partition(": ")
        assert name in error_names and len(message) > 20, (case, line)


def _subclasses(cls):
    return {cls} | {s for sub in cls.__subclasses__() for s in _subclasses(sub)}


CHECKS = {
    "degenerate triangles": _degenerate,
    "slivers": _median_gaps_below(1e-4),
    "tiny triangles": _tiny,
    "huge triangles": _solvers_on_simplex,  # the baselines may stop far from the minimum on triangles 10x the object
    "far-away triangles": _far,
    "penetrating triangles": _penetrating,
    "near-tangent triangles (FW zig-zag)": _tangent,
    "zero triangles": _zero,
    "high curvature (thin torus)": _solvers_on_simplex,
    "zero gradient (medial axis)": _medial,
    "float32 against float64": _precision,
    "millimetres against metres": _units,
    "one million points": _million,
    "queries at code positions (model)": _code_positions,
    "softmax saturation (model)": _saturation,
    "amortized on huge and penetrating triangles (model)": _amortized_extremes,
    "extreme training batches": _extreme_training,
    "malformed input": _malformed,
}


def test_every_stress_case_has_a_check_here():
    assert [name for name, _ in CASES] == list(CHECKS)


@pytest.mark.parametrize("name", [pytest.param(name, marks=[pytest.mark.slow] if name in SLOW_CASES else [])
                                  for name, _ in CASES])
def test_stress_case(name, stress_contexts):
    """Each case of the list `zoo stress` runs, as it runs it: the model cases on the shipped mugs model (as
    `--model mugs`), the others on the analytic torus (the default; with a NeuralSDF "one million points"
    alone takes minutes). What it observed is checked here; its own verdict must agree."""
    ctx = stress_contexts["model"] if name in MODEL_CASES else stress_contexts["plain"]
    if ctx is None:
        pytest.skip(f"needs the {STRESS_MODEL!r} model packaged (zoo.load({STRESS_MODEL!r}) failed)")
    record = run_case(name, dict(CASES)[name], ctx)
    observed = record["observed"]
    assert isinstance(observed, dict), observed  # a case that raised records its traceback as a string
    assert "skipped" not in json.dumps(observed)  # a model case that found no model did not run
    CHECKS[name](json.loads(json.dumps(observed)))  # a copy: the checks may take it apart
    assert record["ok"]  # the command's summary agrees


def test_stress_reports_extreme_training_batches_ok(tmp_path, monkeypatch):
    import sdfzoo.benches.stress as stress

    monkeypatch.setattr(stress, "CASES", [c for c in CASES if c[0] == "extreme training batches"])
    report = run_stress(tmp_path / "s.json")
    assert (report["passed"], report["failed"]) == (1, 0), json.dumps(report["cases"], indent=1)[:4000]
    _extreme_training(json.loads((tmp_path / "s.json").read_text())["cases"][0]["observed"])  # as written to the file


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
