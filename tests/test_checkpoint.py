"""Tests for spf_rl.checkpoint: atomic writes, weights_only loading, bad files."""
from __future__ import annotations

import pytest
import torch

from spf_rl.checkpoint import CHECKSUM_KEY, CheckpointError, content_sha256, load_checkpoint, save_checkpoint
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


def test_a_checkpoint_carries_the_sha256_of_its_content(tmp_path):
    path = tmp_path / "model.pt"
    state = {"model": build_policy("spf", CONFIG).state_dict(), "epoch": 3}
    save_checkpoint(path, "spf", CONFIG, state)
    raw = torch.load(path, weights_only=True)
    stored = raw.pop(CHECKSUM_KEY)
    assert stored == content_sha256(raw) and len(stored) == 64
    again = tmp_path / "again.pt"
    save_checkpoint(again, "spf", CONFIG, state)
    assert again.read_bytes() == path.read_bytes()  # deterministic, checksum included
    assert CHECKSUM_KEY not in load_checkpoint(path)


def test_a_changed_weight_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "model.pt"
    save_checkpoint(path, "spf", CONFIG, {"model": build_policy("spf", CONFIG).state_dict()})
    raw = torch.load(path, weights_only=True)
    name = next(iter(raw["model"]))
    raw["model"][name].view(-1)[0] += 1.0  # the content changed, the embedded checksum did not
    torch.save(raw, path)
    with pytest.raises(CheckpointError, match=f"checkpoint {path} is damaged"):
        load_checkpoint(path)


def test_a_byte_flipped_in_the_weights_of_a_file_anywhere_is_refused(tmp_path):
    """A checkpoint the recipes wrote, kept outside checkpoints/: spf_rl.load_policy must not load
    it silently once one byte in the middle of its weights has changed."""
    import spf_rl

    policy = build_policy("spf", CONFIG)
    path = tmp_path / "elsewhere" / "best.pt"
    save_checkpoint(path, "spf", CONFIG, {"model": policy.state_dict()})
    weights = max(policy.state_dict().values(), key=lambda t: t.numel())
    data = bytearray(path.read_bytes())
    at = bytes(data).find(weights.contiguous().numpy().tobytes())
    assert at > 0
    data[at + weights.numel() * weights.element_size() // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=f"checkpoint {path} is (damaged|corrupt)"):
        spf_rl.load_policy(path)


def test_a_checkpoint_without_a_checksum_still_loads_with_a_warning_unless_it_is_a_known_file(tmp_path, caplog):
    from spf_rl.checkpoint import file_sha256

    path = tmp_path / "old.pt"
    save_checkpoint(path, "spf", CONFIG, {"model": build_policy("spf", CONFIG).state_dict()})
    raw = torch.load(path, weights_only=True)
    raw.pop(CHECKSUM_KEY)
    torch.save(raw, path)  # as written before checkpoints carried one
    with caplog.at_level("WARNING", logger="spf_rl.checkpoint"):
        assert load_checkpoint(path)["model_config"] == CONFIG
    assert f"checkpoint {path} carries no checksum" in caplog.text and "cannot be verified" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="spf_rl.checkpoint"):
        assert load_checkpoint(path, known_file_sha256={file_sha256(path)})["model_config"] == CONFIG
    assert caplog.text == ""  # the bytes of a shipped file: intact wherever it lies


def test_a_copy_of_a_shipped_file_loads_by_path_without_a_warning(tmp_path, caplog):
    import shutil

    import spf_rl
    from spf_rl.hub import checked_checkpoint

    copy = tmp_path / "copied.pt"
    shutil.copy(checked_checkpoint("spf-s0.8"), copy)
    with caplog.at_level("WARNING", logger="spf_rl.checkpoint"):
        spf_rl.load_policy(copy)
    assert "cannot be verified" not in caplog.text
