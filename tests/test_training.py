"""pipeline.training's checkpoints: tensors and dicts, read without unpickling arbitrary objects."""

from __future__ import annotations

import pytest
import torch

from sdfzoo.pipeline.training import Checkpoint, CheckpointWarning

RAN = []


class Payload:
    """An object whose unpickling would run code: a checkpoint must never unpickle it."""

    def __reduce__(self):
        return (RAN.append, ("unpickled",))


def test_a_checkpoint_round_trips_tensors_and_dicts(tmp_path):
    checkpoint = Checkpoint(tmp_path / "run.pt", "abc", every=1, total=2)
    state = {"step": 3, "model": {"w": torch.arange(4.0)}, "history": {"loss": [0.5, 0.25]},
             "generator": torch.Generator().get_state(), "stems": ["a", "b"]}
    checkpoint.save(state)
    loaded = checkpoint.load()
    assert loaded["fingerprint"] == "abc" and loaded["step"] == 3 and loaded["stems"] == ["a", "b"]
    torch.testing.assert_close(loaded["model"]["w"], torch.arange(4.0))
    assert loaded["history"] == {"loss": [0.5, 0.25]}


def test_a_checkpoint_holding_a_pickled_object_is_not_unpickled(tmp_path):
    path = tmp_path / "run.pt"
    torch.save({"fingerprint": "abc", "step": 1, "payload": Payload()}, path)
    with pytest.warns(CheckpointWarning, match="cannot be read"):
        assert Checkpoint(path, "abc", every=1, total=2).load() is None
    assert RAN == []
