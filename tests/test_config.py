"""zoo.config (dataclass <-> dict) and pipeline.presets (named configs): one mechanism for every stage."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from sdfzoo.pipeline.fit_sdf import PRESETS as FIT_PRESETS
from sdfzoo.pipeline.fit_sdf import FitConfig
from sdfzoo.pipeline.presets import Presets
from sdfzoo.pipeline.samples import SampleConfig
from sdfzoo.pipeline.train_detector import PRESETS as TRAIN_PRESETS
from sdfzoo.pipeline.train_detector import TrainConfig
from zoo.config import DictConfig, from_dict, to_dict
from zoo.errors import InputError
from zoo.neural import NeuralSDFConfig

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Inner(DictConfig):
    sizes: tuple[int, ...] = (1, 2)
    scale: float = 1.0


@dataclass(frozen=True)
class Outer(DictConfig):
    _config_name = "outer config"

    inner: Inner = field(default_factory=Inner)
    pair: tuple[float, float] = (0.5, 1.5)
    name: str = "x"


def test_nested_dataclasses_and_tuples_round_trip_through_json():
    c = Outer(Inner((3, 4, 5), 2.0), (0.25, 2.0), "y")
    d = json.loads(json.dumps(c.to_dict()))
    assert d == {"inner": {"sizes": [3, 4, 5], "scale": 2.0}, "pair": [0.25, 2.0], "name": "y"}
    back = Outer.from_dict(d)
    assert back == c and isinstance(back.pair, tuple) and isinstance(back.inner, Inner)
    assert Outer.from_dict({"pair": [1, 2]}).pair == (1.0, 2.0)  # the annotation's scalar type
    assert to_dict(c) == c.to_dict() and from_dict(Outer, d) == c


def test_unknown_keys_are_a_typed_error_naming_them():
    with pytest.raises(InputError, match=r"unknown outer config keys \['colour'\]"):
        Outer.from_dict({"colour": 1})
    with pytest.raises(InputError, match=r"unknown Inner keys \['depth'\]"):
        Outer.from_dict({"inner": {"depth": 1}})
    with pytest.raises(InputError, match="unknown fit config keys"):
        FitConfig.from_dict({"stepz": 10})
    with pytest.raises(InputError, match="needs a newer sdfzoo"):
        NeuralSDFConfig.from_dict({"n_codes": 8, "attention": True})
    assert NeuralSDFConfig.from_dict({"n_codes": 8, "type": "code-cloud", "n_params": 1}).n_codes == 8  # descriptive keys


def test_stage_configs_round_trip():
    for config in [*FIT_PRESETS.values(), *TRAIN_PRESETS.values(), SampleConfig()]:
        assert type(config).from_dict(json.loads(json.dumps(config.to_dict()))) == config
    assert TrainConfig.from_dict(TrainConfig().to_dict()).betas == (0.9, 0.999)


def test_shipped_package_configs_serialise_as_they_were_written():
    """config.json files (and their sha256s) stay what they are: reading and writing again changes no byte."""
    configs = sorted((ROOT / "zoo" / "pretrained").glob("*/config.json"))
    assert configs
    for path in configs:
        stored = json.loads(path.read_text())
        sdf = NeuralSDFConfig.from_dict(stored["sdf"]).to_dict()
        shared = [k for k in sdf if k in stored["sdf"]]  # older packages predate smooth_beta; n_params is descriptive
        assert json.dumps({k: sdf[k] for k in shared}) == json.dumps({k: stored["sdf"][k] for k in shared})
        fit = FitConfig.from_dict(stored["fit"]).to_dict()
        assert json.dumps({**fit, "sdf": None}, sort_keys=True) == json.dumps({**stored["fit"], "sdf": None}, sort_keys=True)


def test_one_preset_getter_with_one_error():
    table = Presets("demo", quick=Inner((1,), 0.5), default=Inner())
    assert table.lookup("quick") == Inner((1,), 0.5)
    assert table.lookup("quick", scale=3.0) == Inner((1,), 3.0)
    with pytest.raises(InputError, match=r"unknown demo preset 'slow'; choose one of default, quick"):
        table.lookup("slow")
    with pytest.raises(InputError, match="unknown fit preset"):
        FIT_PRESETS.lookup("nope")
