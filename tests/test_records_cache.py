"""Tests for spf_rl/records_cache.py: the one per-episode result cache of run test records, Table 1 and the
route benchmark, keyed by the episodes, the env version, the arrival rule and a hash of the policy's weights."""
from __future__ import annotations

import json
import shutil

import pytest
import torch

import spf_rl.records_cache as records_cache
from envs.episode_spec import EpisodeSpec
from spf_rl.checkpoint import save_checkpoint
from spf_rl.evaluation import EvalConfig
from spf_rl.hub import policy_from_checkpoint
from spf_rl.modules import OpenLoopPolicy, SPFConfig
from spf_rl.modules.registry import build_policy
from spf_rl.modules.views import policy_for_length
from spf_rl.records_cache import (
    cached_records,
    changed_fields,
    policy_sha256,
    read_records,
    records_key,
    write_records,
)

CONFIG = SPFConfig(demo_length=5, feature_dim=8, hidden_size=8, image_size=(16, 16))
RECORDS = [{"episode_seed": i, "house_seed": i % 2, "success": i % 3 == 0, "spl": 0.5 * (i % 3 == 0)} for i in range(6)]


def checkpoint(path, seed: int = 0, model_type: str = "spf", **config):
    torch.manual_seed(seed)
    spf_config = SPFConfig(**{**CONFIG.__dict__, **config})
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, model_type, spf_config, {"model": build_policy(model_type, spf_config).state_dict()})
    return path


def test_the_weights_hash_follows_the_weights_not_the_file(tmp_path):
    a = checkpoint(tmp_path / "a.pt")
    moved = tmp_path / "elsewhere" / "renamed.pt"
    moved.parent.mkdir()
    shutil.copy(a, moved)
    resaved = checkpoint(tmp_path / "resaved.pt")  # the same weights written again: another file
    hashes = {path.name: policy_sha256(policy_from_checkpoint(path)[0]) for path in (a, moved, resaved)}
    assert len(set(hashes.values())) == 1
    assert policy_sha256(policy_from_checkpoint(checkpoint(tmp_path / "b.pt", seed=1))[0]) != hashes["a.pt"]  # other weights
    # the same weights read another way: another key (the model config and the memory's sparsity are not in the weights)
    assert policy_sha256(policy_from_checkpoint(checkpoint(tmp_path / "c.pt", k=3))[0]) != hashes["a.pt"]
    policy = policy_from_checkpoint(a)[0]
    assert policy_sha256(policy_for_length(policy, 7)) != hashes["a.pt"] == policy_sha256(policy_for_length(policy, 5))
    assert policy_sha256(OpenLoopPolicy()) is None


def test_a_random_sparsity_models_key_names_the_sparsity_it_reads_at(tmp_path):
    path = checkpoint(tmp_path / "r.pt", model_type="spf_random", sparsity_range=(0.2, 1.0))
    policy = policy_from_checkpoint(path)[0]
    at = {s: policy_sha256(policy.set_sparsity(s)) for s in (0.4, 0.8)}
    assert at[0.4] != at[0.8] == policy_sha256(policy_from_checkpoint(path)[0].set_sparsity(0.8))


def test_records_are_taken_again_only_under_the_same_key(tmp_path, monkeypatch):
    config = EvalConfig(EpisodeSpec(split="val", num_houses=1, demo_length=5, image_size=16), num_episodes=6)
    policy = policy_from_checkpoint(checkpoint(tmp_path / "a.pt"))[0]
    key = records_key(config, policy)
    path = tmp_path / "cache" / "records.json"
    write_records(path, key, RECORDS, ("episode_seed", "house_seed", "success"), line="x")
    kept = [{k: r[k] for k in ("episode_seed", "house_seed", "success")} for r in RECORDS]
    assert read_records(path, key) == kept
    assert json.loads(path.read_text())["line"] == "x" and not list(path.parent.glob(".*"))  # no temporary file left
    other_episodes = records_key(EvalConfig(config.episodes.replace(seed=9), num_episodes=6), policy)
    other_weights = records_key(config, policy_from_checkpoint(checkpoint(tmp_path / "b.pt", seed=1))[0])
    assert read_records(path, other_episodes) is None and read_records(path, other_weights) is None
    assert changed_fields(key, other_episodes) == ["episodes"] and changed_fields(key, other_weights) == ["policy_sha256"]
    how = EvalConfig(config.episodes, num_episodes=6, store_root=str(tmp_path / "stores"), num_collectors=2)
    assert records_key(how, policy) == key  # how the episodes are played, not which
    monkeypatch.setattr(records_cache, "ENV_VERSION", records_cache.ENV_VERSION + 1)
    assert changed_fields(key, records_key(config, policy)) == ["env_version"]
    monkeypatch.setattr(records_cache, "ARRIVAL_RULE", "another rule")
    assert read_records(path, records_key(config, policy)) is None
    assert read_records(tmp_path / "absent.json", key) is None


def test_an_unreadable_file_is_evaluated_again_and_replaced(tmp_path):
    path = tmp_path / "records.json"
    path.write_text("{not json")
    key = {"episodes": {"split": "val"}, "env_version": 3, "arrival": "a", "policy_sha256": "f00"}
    assert cached_records(path, key, lambda: RECORDS) == RECORDS
    assert read_records(path, key) == RECORDS


def test_extra_entries_may_not_hide_the_key_or_the_records(tmp_path):
    with pytest.raises(ValueError, match="may not be named"):
        write_records(tmp_path / "r.json", {}, RECORDS, columns="mine")
    assert not (tmp_path / "r.json").exists()
