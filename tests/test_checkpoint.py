"""Tests for spf_rl.checkpoint: atomic writes, weights_only loading, bad files."""
from __future__ import annotations

import pytest
import torch

from spf_rl.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from spf_rl.modules.policy import SPFConfig
from spf_rl.modules.registry import build_policy

CONFIG = SPFConfig(demo_length=6, sparsity=0.5, feature_dim=8, hidden_size=8, image_size=(16, 16))


def test_round_trip_is_weights_only(tmp_path):
    policy = build_policy("spf", CONFIG)
    path = tmp_path / "model.pt"
    save_checkpoint(path, "spf", CONFIG, {"model": policy.state_dict(), "epoch": 3, "history": [{"loss": 0.5}]})
    torch.load(path, weights_only=True)  # must not need pickled classes
    payload = load_checkpoint(path, expected_model_type="spf")
    assert payload["epoch"] == 3 and payload["model_config"] == CONFIG
    clone = build_policy("spf", payload["model_config"])
    clone.load_state_dict(payload["model"])
    for a, b in zip(policy.parameters(), clone.parameters()):
        assert torch.equal(a, b)
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_wrong_model_type_is_refused(tmp_path):
    path = tmp_path / "rpf.pt"
    save_checkpoint(path, "rpf", CONFIG, {"model": build_policy("rpf", CONFIG).state_dict()})
    with pytest.raises(CheckpointError, match="holds a 'rpf' model, but a 'spf' model"):
        load_checkpoint(path, expected_model_type="spf")


def test_corrupt_and_missing_checkpoints(tmp_path):
    path = tmp_path / "bad.pt"
    path.write_bytes(b"definitely not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)
    good = tmp_path / "good.pt"
    save_checkpoint(good, "spf", CONFIG, {"model": build_policy("spf", CONFIG).state_dict()})
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(truncated)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="model_type must be one of"):
        save_checkpoint(good, "transformer", CONFIG, {})
