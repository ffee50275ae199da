"""spf_rl.load_policy / list_checkpoints: shipped names, paths, clear errors."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

import spf_rl
from spf_rl import hub
from spf_rl.checkpoint import CheckpointError, file_sha256, save_checkpoint
from spf_rl.modules.policy import SPFConfig, SPFPolicy
from spf_rl.modules.registry import build_policy

SHIPPED = [
    "action_only-s0",
    "dagger-rpf-s1",
    "dagger-rpf_original-s1",
    "dagger-spf-s0.8",
    "dagger-spf_rpf_pointer-s0.8",
    "dagger-spf_rpf_pointer_long-s0.8",
    "homing-spf-s0.8",
    "lengths-spf-s0.8",
    "paper_symmetric-action_only-s0",
    "paper_symmetric-dagger-spf-s0.8",
    "paper_symmetric-rpf-s1",
    "paper_symmetric-spf-s0.4",
    "paper_symmetric-spf-s0.6",
    "paper_symmetric-spf-s0.8",
    "paper_symmetric-spf_random-s0.2-1",
    "ppo-spf-s0.8",
    "routes-spf",
    "rpf-s1",
    "rpf_original-s1",
    "spf-s0.4",
    "spf-s0.6",
    "spf-s0.8",
    "spf_random-s0.2-1",
    "spf_rpf_pointer-s0.8",
    "spf_rpf_pointer_long-s0.8",
]


def test_list_checkpoints_names_every_shipped_file():
    assert spf_rl.list_checkpoints() == SHIPPED


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_name_loads_a_ready_policy(name):
    policy, config = spf_rl.load_policy(name)
    assert isinstance(policy, SPFPolicy) and isinstance(config, SPFConfig)
    assert not policy.training
    assert config is policy.config
    # the route model follows routes of up to 100 steps; every other shipped policy, the paper's 30
    assert config.num_actions == 3 and config.image_size == (64, 64)
    assert config.demo_length == (100 if name == "routes-spf" else 30)


def test_config_has_the_memory_of_the_model_type():
    assert spf_rl.load_policy("rpf-s1").config.memory_mode == "full"
    original = spf_rl.load_policy("rpf_original-s1").config
    assert original.memory_mode == "full" and original.pointer_update == "rpf"
    assert spf_rl.load_policy("dagger-rpf_original-s1")[1] == original
    for name in ("spf_rpf_pointer-s0.8", "dagger-spf_rpf_pointer-s0.8", "spf_rpf_pointer_long-s0.8"):
        pointer = spf_rl.load_policy(name)[1]
        assert (pointer.memory_mode, pointer.sparsity, pointer.pointer_update) == ("sparse", 0.8, "rpf")
    assert spf_rl.load_policy("action_only-s0").config.memory_length == 0
    assert spf_rl.load_policy("spf-s0.4").config.memory_length == 12
    assert spf_rl.load_policy("spf_random-s0.2-1").config.sparsity_range == (0.2, 1.0)


def test_name_and_path_give_the_same_weights():
    by_name, _ = spf_rl.load_policy("spf-s0.8")
    by_path, _ = spf_rl.load_policy(hub.CHECKPOINT_DIR / "table1" / "spf-s0.8-seed2.pt")
    by_str, _ = spf_rl.load_policy(str(hub.CHECKPOINT_DIR / "table1" / "spf-s0.8-seed2.pt"))
    for other in (by_path, by_str):
        for (key, a), b in zip(by_name.state_dict().items(), other.state_dict().values()):
            assert torch.equal(a, b), key


def test_a_path_written_by_the_recipes_loads(tmp_path):
    config = SPFConfig(feature_dim=8, hidden_size=8, demo_length=10)
    trained = build_policy("spf", config)
    save_checkpoint(tmp_path / "best.pt", "spf", config, {"model": trained.state_dict()})
    policy, loaded = spf_rl.load_policy(tmp_path / "best.pt", model_type="spf")
    assert loaded.demo_length == 10 and not policy.training
    for a, b in zip(trained.state_dict().values(), policy.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(CheckpointError, match="'rpf' model was asked for"):
        spf_rl.load_policy(tmp_path / "best.pt", model_type="rpf")


def test_unknown_name_lists_the_shipped_names():
    with pytest.raises(ValueError, match="unknown checkpoint name 'spf-s0.9'") as info:
        spf_rl.load_policy("spf-s0.9")
    for name in SHIPPED:
        assert name in str(info.value)


@pytest.mark.parametrize("missing", ["runs/bc/nothing/best.pt", "nothing.pt", Path("nothing")])
def test_missing_path_is_a_file_not_found_error(missing):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        spf_rl.load_policy(missing)


def test_corrupt_file_is_a_checkpoint_error(tmp_path):
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        spf_rl.load_policy(tmp_path / "bad.pt")


def test_without_a_checkpoint_directory_names_fail_clearly(monkeypatch, tmp_path):
    monkeypatch.setattr(hub, "CHECKPOINT_DIR", tmp_path / "absent")
    with pytest.raises(FileNotFoundError, match="reinstall spf-rl, or pass the path of a checkpoint file"):
        spf_rl.list_checkpoints()
    with pytest.raises(FileNotFoundError, match="reinstall spf-rl, or pass the path of a checkpoint file"):
        spf_rl.load_policy("spf-s0.8")


def test_the_manifest_lists_every_shipped_file_once_with_its_hash():
    manifest = hub.read_manifest()
    on_disk = {path.relative_to(hub.CHECKPOINT_DIR).as_posix() for path in hub.CHECKPOINT_DIR.rglob("*.pt")}
    assert set(manifest["files"]) == on_disk
    for relative, digest in manifest["files"].items():
        assert file_sha256(hub.CHECKPOINT_DIR / relative) == digest, relative
    hashes = list(manifest["files"].values())
    assert len(set(hashes)) == len(hashes)  # each file's bytes are stored once
    assert set(manifest["names"].values()) <= set(manifest["files"])


def shipped_copy(tmp_path: Path, monkeypatch) -> Path:
    """A copy of the shipped directory (its manifest and the files of two names), used as the shipped one."""
    import shutil

    manifest = hub.read_manifest()
    names = {name: manifest["names"][name] for name in ("spf-s0.8", "rpf-s1")}
    directory = tmp_path / "checkpoints"
    for relative in names.values():
        (directory / relative).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(hub.CHECKPOINT_DIR / relative, directory / relative)
    hub.write_manifest(directory, names)
    monkeypatch.setattr(hub, "CHECKPOINT_DIR", directory)
    return directory


def test_a_shipped_file_that_differs_from_the_manifest_is_refused(tmp_path, monkeypatch):
    directory = shipped_copy(tmp_path, monkeypatch)
    assert spf_rl.load_policy("spf-s0.8").config.sparsity == 0.8
    target = directory / hub.read_manifest(directory)["names"]["spf-s0.8"]
    data = bytearray(target.read_bytes())
    data[-100] ^= 0xFF
    target.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"differs from manifest.json"):
        spf_rl.load_policy("spf-s0.8")
    with pytest.raises(CheckpointError, match=r"differs from manifest.json"):
        spf_rl.load_policy(target)  # by path too
    assert spf_rl.load_policy("rpf-s1").config.memory_mode == "full"  # the others still load


def test_an_unlisted_file_in_the_shipped_directory_is_refused_and_one_elsewhere_is_not(tmp_path, monkeypatch):
    directory = shipped_copy(tmp_path, monkeypatch)
    import shutil

    source = directory / hub.read_manifest(directory)["names"]["rpf-s1"]
    shutil.copyfile(source, directory / "extra.pt")
    with pytest.raises(CheckpointError, match="not in its manifest.json"):
        spf_rl.load_policy(directory / "extra.pt")
    shutil.copyfile(source, tmp_path / "mine.pt")
    assert spf_rl.load_policy(tmp_path / "mine.pt").config.memory_mode == "full"
