"""pipeline.stages: a stage reruns exactly when its inputs, config, code or outputs changed."""

from __future__ import annotations

import json

import pytest

import sdfzoo.pipeline.stages as stages
import zoo
from sdfzoo.pipeline.stages import (
    Stage,
    canonical_json,
    code_closure,
    code_digest,
    config_hash,
    is_up_to_date,
    run_stage,
    source_digest,
)
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
    """The lock holds the digest of the stage's module and of the project modules importing it imports, transitively;
    a module imported only inside a function (which the stage may never call) is not part of it."""
    src, out = files
    root = tmp_path / "project"
    write_modules(root, {"pipeline.__init__": "", "zoo.__init__": "from .geometry import area\n",
                         "zoo.geometry": "def area(): return 1\n", "zoo.unrelated": "X = 1\n",
                         "pipeline.shout": "import numpy\nfrom . import helper\n",
                         "pipeline.helper": "from zoo import area\n\ndef g():\n    from zoo import unrelated\n"})
    assert set(code_closure(["pipeline.shout"], root)) == {"pipeline", "pipeline.shout", "pipeline.helper", "zoo", "zoo.geometry"}
    monkeypatch.setattr(stages, "ROOT", root)
    calls = []
    stage = make_stage(src, out, code=("pipeline.shout",))
    assert run_stage(stage, upper(stage, calls)) is True
    assert run_stage(stage, upper(stage, calls)) is False  # unchanged: skipped
    write_modules(root, {"zoo.unrelated": "X = 2\n"})  # imported only when helper.g() runs
    assert run_stage(stage, upper(stage, calls)) is False
    write_modules(root, {"zoo.geometry": "def area(): return 2  # edited\n"})  # imported two steps away
    assert run_stage(stage, upper(stage, calls)) is True
    assert run_stage(stage, upper(stage, calls)) is False
    assert len(calls) == 2


def test_a_new_library_version_reruns_a_stage(files, monkeypatch):
    src, out = files
    calls = []
    stage = make_stage(src, out)
    assert run_stage(stage, upper(stage, calls)) is True
    assert json.loads(stage.lock.read_text())["libraries"]["torch"] == stages.library_versions()["torch"]
    assert run_stage(stage, upper(stage, calls)) is False
    now = stages.library_versions()
    monkeypatch.setattr(stages, "library_versions", lambda: {**now, "libigl": "9.9.9"})
    assert run_stage(stage, upper(stage, calls)) is True


def test_the_lock_records_which_sdfzoo_wrote_it(files):
    src, out = files
    stage = make_stage(src, out)
    run_stage(stage, upper(stage, []))
    written = json.loads(stage.lock.read_text())["sdfzoo"]
    assert written["version"] == zoo.__version__ and written == stages.provenance()


def test_the_project_stages_hash_what_they_import():
    assert {"pipeline.samples", "pipeline.normalise", "pipeline.stages", "zoo.meshes"} <= set(code_closure(["pipeline.samples"]))
    # the detector, the model and their kin are no part of sampling: editing them reruns no sample
    for stage in ("pipeline.samples", "pipeline.normalise", "pipeline.fit_sdf"):
        assert not {"zoo.detector", "zoo.model", "zoo.amortized", "zoo.completion"} & set(code_closure([stage])), stage
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


def copy_sources(root):
    """The project's zoo/ and pipeline/ Python sources under ``root`` (a scratch copy to edit)."""
    for package in stages.PROJECT_PACKAGES:
        for path in (stages.ROOT / package).rglob("*.py"):
            target = root / path.relative_to(stages.ROOT)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(path.read_bytes())


def edit(path, old, new):
    text = path.read_text()
    assert old in text, f"{path}: {old!r} not found; the test's edit needs updating"
    path.write_text(text.replace(old, new, 1))


def test_the_fit_stage_digest_covers_the_code_it_runs_and_nothing_else(tmp_path):
    """pipeline.fit_sdf's digest: unchanged by edits of modules it never imports (coherence, collision,
    zoo.sim) and by comments and docstrings in its own module; changed by a code edit there or in
    zoo.neural, which it runs."""
    root = tmp_path / "project"
    copy_sources(root)
    closure = set(code_closure(["pipeline.fit_sdf"], root))
    assert {"pipeline.fit_sdf", "pipeline.training", "zoo.neural"} <= closure
    assert not closure & {"zoo.coherence", "zoo.collision", "zoo.voxel"}
    assert not any(m.startswith("zoo.sim") for m in closure)
    before = code_digest(["pipeline.fit_sdf"], root)
    edit(root / "zoo" / "coherence.py", "def ", "def unused_helper():\n    return 1\n\n\ndef ")
    edit(root / "zoo" / "collision.py", "def ", "def unused_helper():\n    return 2\n\n\ndef ")
    (root / "zoo" / "sim" / "extra.py").write_text("X = 1\n")
    edit(root / "zoo" / "sim" / "__init__.py", "\n", "\nY = 2\n")
    fit = root / "pipeline" / "fit_sdf.py"
    edit(fit, "\nimport json\n", "\n# a comment about json\nimport json  # and another\n\n")
    edit(fit, '"""', '"""An edited docstring. ')
    assert code_digest(["pipeline.fit_sdf"], root) == before
    edit(fit, "\nimport os\n", "\nimport os\nEDITED = 1\n")
    after = code_digest(["pipeline.fit_sdf"], root)
    assert after != before
    edit(root / "zoo" / "neural.py", "\nimport ", "\nEDITED = 1\nimport ")
    assert code_digest(["pipeline.fit_sdf"], root) != after


def test_source_digest_ignores_comments_and_docstrings_not_code():
    base = source_digest('"""Module."""\nclass A:\n    """Doc."""\n    def f(self):\n        "doc"\n        return 1\n')
    assert base == source_digest('class A:  # why\n\n    def f(self):\n        # note\n        return 1\n')
    assert base != source_digest('class A:\n    def f(self):\n        return 2\n')
    assert base != source_digest('class A:\n    def f(self):\n        x = "not a docstring"\n        return 1\n')
    assert source_digest("def f():\n    'only a docstring'\n") == source_digest("def f():\n    pass\n")
