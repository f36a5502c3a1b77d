"""investigations/: the unshipped profiles and reference scripts, one runner (`python -m investigations NAME`) and one
report helper. Their measurements are tested where they are used (test_sim_scenarios.py); here, how they run."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from investigations.__main__ import main, names
from investigations.report import write_report

ROOT = Path(__file__).resolve().parents[1]


def test_a_report_records_the_runners_command_and_the_machine(tmp_path, monkeypatch):
    """The JSON holds the report, the machine and the command that runs it again: the arguments a caller passed,
    else the process's own after the runner's NAME."""
    write_report(tmp_path / "a.json", {"rows": [1, 2]}, "investigations.example", ["--out", "a.json"])
    report = json.loads((tmp_path / "a.json").read_text())
    assert report["rows"] == [1, 2] and report["command"] == "python -m investigations example --out a.json"
    assert report["machine"]["threads"] == torch.get_num_threads()
    monkeypatch.setattr("sys.argv", ["python -m investigations example", "--steps", "3"])  # as the runner leaves it
    write_report(tmp_path / "b.json", {}, "investigations.example")
    assert json.loads((tmp_path / "b.json").read_text())["command"] == "python -m investigations example --steps 3"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json"]  # no temporary file left behind


def test_the_runner_lists_every_investigation_and_refuses_an_unknown_one(capsys):
    listed = {p.stem for p in (ROOT / "investigations").glob("*.py")} - {"__init__", "__main__", "report"}
    assert set(names()) == listed and len(listed) >= 6
    assert main([]) == 0
    out = capsys.readouterr().out
    assert all(f"  {name} " in out for name in listed), out
    assert main(["no-such-thing"]) == 2
    assert "no investigation 'no-such-thing'" in capsys.readouterr().err


def test_an_investigation_runs_from_the_clones_root_and_its_report_reruns_it(tmp_path):
    """`python -m investigations sdf_queries ...` (a shipped model, bundled data), as docs/coherence.md cites it."""
    out = tmp_path / "q.json"
    args = ["--model", "mugs", "--shape", "hoi4d_mug_0001", "--repeats", "1", "--out", str(out)]
    done = subprocess.run([sys.executable, "-m", "investigations", "sdf_queries", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["command"] == " ".join(["python -m investigations sdf_queries", *args])
    assert [r["points"] for r in report["rows"]] == [8, 100, 1000]
    assert all(r[k] > 0 for r in report["rows"] for k in ("value_ms", "value_and_grad_ms", "value_and_grad_autograd_ms"))


def test_every_investigation_has_a_main_and_its_help_names_the_runner(capsys):
    for name in names():
        module = importlib.import_module(f"investigations.{name}")
        assert callable(module.main) and module.__doc__, name
        with pytest.raises(SystemExit) as info:
            main([name, "--help"])
        assert info.value.code == 0
        assert f"usage: python -m investigations {name}" in capsys.readouterr().out, name
