"""pipeline.stages: a stage reruns exactly when its inputs, config, code or outputs changed."""

from __future__ import annotations

import json

import pytest

import pipeline.stages as stages
from pipeline.stages import Stage, canonical_json, code_closure, code_digest, config_hash, is_up_to_date, run_stage
from zoo.errors import DataError, InputError
from zoo.files import atomic_write_text


@pytest.fixture
def files(tmp_path):
    src = tmp_path / "in.txt"
    src.write_text("hello")
    return src, tmp_path / "out" / "result.txt"


def make_stage(src, out, config=None, code=("pipeline.stages",)):
    return Stage("upper", {"text": src}, config or {"repeat": 2}, {"result": out}, code=code)


def upper(stage, calls):
    def build():
        calls.append(1)
        atomic_write_text(stage.outputs["result"], stage.inputs["text"].read_text().upper() * stage.config["repeat"])
    return build


def test_a_stage_runs_once_then_skips(files):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    assert run_stage(stage, upper(stage, calls)) is True
    assert out.read_text() == "HELLOHELLO"
    assert run_stage(stage, upper(stage, calls)) is False
    assert calls == [1] and is_up_to_date(stage)
    lock = json.loads(stage.lock.read_text())
    assert lock["config"] == {"repeat": 2} and set(lock["inputs"]) == {"text"} and set(lock["outputs"]) == {"result"}
    assert stage.lock.parent == out.parent


def test_a_changed_input_reruns(files):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    run_stage(stage, upper(stage, calls))
    src.write_text("bye")
    assert run_stage(stage, upper(stage, calls)) is True
    assert out.read_text() == "BYEBYE"


def upper_edited(stage, calls):  # the same build as upper, edited: its source differs
    def build():
        calls.append(1)
        atomic_write_text(stage.outputs["result"], (stage.inputs["text"].read_text().upper()) * stage.config["repeat"])
    return build


def test_a_changed_config_or_code_reruns(files):
    src, out = files
    calls = []
    first = make_stage(src, out)
    run_stage(first, upper(first, calls))
    changed = make_stage(src, out, {"repeat": 3})
    assert run_stage(changed, upper(changed, calls)) is True
    assert out.read_text() == "HELLO" * 3
    edited = make_stage(src, out, {"repeat": 3}, code=("pipeline.stages", upper_edited))
    assert run_stage(edited, upper_edited(edited, calls)) is True
    assert run_stage(edited, upper_edited(edited, calls)) is False
    assert len(calls) == 3


def write_modules(root, modules: dict):
    for name, text in modules.items():
        path = root.joinpath(*name.split(".")).with_suffix(".py")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_editing_a_module_the_stage_imports_reruns_it_and_nothing_else_does(files, tmp_path, monkeypatch):
    """The lock holds the digest of the stage's module and of the project modules it imports, transitively."""
    src, out = files
    root = tmp_path / "project"
    write_modules(root, {"pipeline.__init__": "", "zoo.__init__": "from .geometry import area\n",
                         "zoo.geometry": "def area(): return 1\n", "zoo.unrelated": "X = 1\n",
                         "pipeline.shout": "import numpy\nfrom . import helper\n",
                         "pipeline.helper": "def f():\n    from zoo import area\n    return area()\n"})
    assert set(code_closure(["pipeline.shout"], root)) == {"pipeline", "pipeline.shout", "pipeline.helper", "zoo", "zoo.geometry"}
    monkeypatch.setattr(stages, "ROOT", root)
    calls = []
    stage = make_stage(src, out, code=("pipeline.shout",))
    assert run_stage(stage, upper(stage, calls)) is True
    assert run_stage(stage, upper(stage, calls)) is False  # unchanged: skipped
    write_modules(root, {"zoo.unrelated": "X = 2\n"})  # not imported by the stage
    assert run_stage(stage, upper(stage, calls)) is False
    write_modules(root, {"zoo.geometry": "def area(): return 2  # edited\n"})  # imported two steps away
    assert run_stage(stage, upper(stage, calls)) is True
    assert run_stage(stage, upper(stage, calls)) is False
    assert len(calls) == 2


def test_the_project_stages_hash_what_they_import():
    assert {"pipeline.samples", "pipeline.normalise", "pipeline.stages", "zoo.meshes"} <= set(code_closure(["pipeline.samples"]))
    assert {"pipeline.training", "zoo.neural"} <= set(code_closure(["pipeline.fit_sdf"]))
    assert code_digest(["pipeline.samples"]) == code_digest(["pipeline.samples"])
    assert code_digest(["pipeline.samples"]) != code_digest(["pipeline.fit_sdf"])
    with pytest.raises(InputError, match="names no code"):
        Stage("anonymous", {}, {}, {"x": "x.txt"})


@pytest.mark.parametrize("damage", ["delete", "edit"])
def test_a_deleted_or_edited_output_reruns(files, damage):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    run_stage(stage, upper(stage, calls))
    out.unlink() if damage == "delete" else out.write_text("tampered")
    assert run_stage(stage, upper(stage, calls)) is True
    assert out.read_text() == "HELLOHELLO"


def test_a_corrupt_lock_just_reruns(files):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    run_stage(stage, upper(stage, calls))
    stage.lock.write_text("{truncated")
    assert run_stage(stage, upper(stage, calls)) is True


def test_force_reruns(files):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    run_stage(stage, upper(stage, calls))
    assert run_stage(stage, upper(stage, calls), force=True) is True


def test_a_missing_input_or_output_is_a_data_error(files, tmp_path):
    src, out = files
    stage = make_stage(tmp_path / "absent.txt", out)
    with pytest.raises(DataError, match="absent.txt"):
        run_stage(stage, lambda: None)
    stage = make_stage(src, out)
    with pytest.raises(DataError, match="without writing"):
        run_stage(stage, lambda: None)
    assert not stage.lock.exists()


def test_config_hash_ignores_key_order_and_rejects_non_json():
    assert config_hash({"a": 1, "b": [1, 2]}) == config_hash({"b": [1, 2], "a": 1})
    assert canonical_json({"b": 1, "a": 2}) == '{"a":2,"b":1}'
    with pytest.raises(InputError):
        canonical_json({"x": float("nan")})
    with pytest.raises(InputError):
        Stage("empty", {}, {}, {})
