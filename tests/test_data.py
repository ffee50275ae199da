"""Tests for spf_rl.data: dataset generation, determinism, resume, corruption detection, distribution."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from envs.demo_store import DemoStoreError
from envs.episode_spec import EpisodeSpec, from_flat
from envs.version import ENV_VERSION
from spf_rl.data import DatasetConfig, DatasetError, EpisodeDataset, demos_root, generate_chunk

TINY = dict(num_episodes=6, num_houses=1, demo_length=5, max_steps=8, image_size=32, chunk_size=2)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds") / "tiny"
    return EpisodeDataset.build(root, from_flat(DatasetConfig, TINY), num_workers=1, progress=False)


def test_layout_and_labels(built):
    episodes = built.episodes
    assert episodes.batch_size == torch.Size([6])
    assert episodes["steps", "pixels"].shape == (6, 8, 32, 32, 3)
    assert "demo_frames" not in episodes.keys()  # stored once, in the demonstration store
    assert episodes["demo_id"].tolist() == list(range(6))  # episode k plays demonstration k
    rows = built[[4, 1]]
    assert rows["demo_frames"].shape == (2, 5, 32, 32, 3)
    assert torch.equal(rows["demo_frames"], built.demos.frames[[4, 1]])
    assert torch.equal(rows["demo_actions"], built.demos.actions[[4, 1]])
    assert rows["demo_frames"].float().std() > 5
    mask = episodes["steps", "mask"]
    assert torch.equal(mask.sum(1), episodes["length"])
    assert episodes["steps", "is_init"][:, 0].all() and not episodes["steps", "is_init"][:, 1:].any()
    labels = episodes["steps", "expert_action"][mask]
    assert labels.min() >= 0 and labels.max() <= 2
    assert (episodes["steps", "pixels"][mask].float().std()) > 5


def test_chunks_are_deterministic(built):
    config = from_flat(DatasetConfig, TINY)
    again = generate_chunk(config, 1, demos_root(built.root))
    assert torch.equal(again["steps", "pixels"], built.episodes[2:4]["steps", "pixels"])
    assert torch.equal(again["steps", "expert_action"], built.episodes[2:4]["steps", "expert_action"])


def test_episodes_do_not_depend_on_the_chunking(built, tmp_path):
    # every episode is a function of the seed and its number: chunks of 3 episodes played by 2 agents
    # (one of them plays two episodes of each chunk) give the bytes of chunks of 2 played by 2
    other_config = from_flat(DatasetConfig, {**TINY, "chunk_size": 3, "num_agents": 2})
    other = EpisodeDataset.build(tmp_path / "three", other_config, num_workers=1, progress=False)
    for key in built.episodes.keys(include_nested=True, leaves_only=True):
        assert torch.equal(other.episodes[key], built.episodes[key]), key
    random_steps = built.episodes["steps", "action"] != built.episodes["steps", "expert_action"]
    assert random_steps[built.episodes["steps", "mask"]].any()  # the behaviour policy's random actions


def test_a_missing_or_foreign_demonstration_store_is_refused(built, tmp_path):
    root = tmp_path / "nodemos"
    shutil.copytree(built.root, root)
    with pytest.raises(DemoStoreError, match="nodemos-demos"):
        root_dataset = EpisodeDataset(root)
        root_dataset.replay_buffer(batch_size=2).sample()
    shutil.copytree(demos_root(built.root), demos_root(root))
    meta = json.loads((demos_root(root) / "meta.json").read_text())
    meta["config"]["episodes_seed"] = 99
    (demos_root(root) / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="demonstration store .* holds"):
        EpisodeDataset(root)[[0]]


def test_interrupted_build_resumes_to_the_same_bytes(built, tmp_path, monkeypatch):
    import spf_rl.data as data_module

    root = tmp_path / "resumed"
    real = data_module.generate_chunk
    calls: list[int] = []

    def stop_at_last_chunk(config, chunk, demos):
        calls.append(chunk)
        if chunk == 2:
            raise RuntimeError("stopped")  # as if the run were killed here
        return real(config, chunk, demos)

    monkeypatch.setattr(data_module, "generate_chunk", stop_at_last_chunk)
    with pytest.raises(RuntimeError, match="stopped"):
        EpisodeDataset.build(root, from_flat(DatasetConfig, TINY), num_workers=1, progress=False)
    assert not root.exists() and (tmp_path / "resumed.partial").exists()
    with pytest.raises(DatasetError, match="resume"):
        EpisodeDataset(root)
    calls.clear()
    monkeypatch.setattr(data_module, "generate_chunk", lambda config, chunk, demos: calls.append(chunk) or real(config, chunk, demos))
    resumed = EpisodeDataset.build(root, from_flat(DatasetConfig, TINY), num_workers=1, progress=False)
    assert calls == [2]  # chunks 0 and 1 were kept
    for key in built.episodes.keys(include_nested=True, leaves_only=True):
        assert torch.equal(resumed.episodes[key], built.episodes[key]), key
    resumed.verify()


def test_corruption_is_detected(built, tmp_path):
    root = tmp_path / "corrupt"
    shutil.copytree(built.root, root)
    dataset = EpisodeDataset(root, verify=False)
    dataset.episodes["steps", "expert_action"][3, 0] = (dataset.episodes["steps", "expert_action"][3, 0] + 1) % 3
    with pytest.raises(DatasetError, match="'steps/expert_action' is corrupt"):
        EpisodeDataset(root)


def test_missing_and_mismatched_datasets(built, tmp_path):
    with pytest.raises(DatasetError, match="not a dataset store"):
        EpisodeDataset(tmp_path / "nothing")
    other = from_flat(DatasetConfig, {**TINY, "noise": "locobot"})
    with pytest.raises(DatasetError, match="another configuration"):
        EpisodeDataset.build(built.root, other, num_workers=1, progress=False)
    root = tmp_path / "badmeta"
    shutil.copytree(built.root, root)
    (root / "meta.json").write_text("{not json")
    with pytest.raises(DatasetError, match="corrupt"):
        EpisodeDataset(root)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(num_episodes=0), "num_episodes"),
        (dict(chunk_size=-1), "chunk_size"),
        (dict(random_action_prob=1.5), "random_action_prob"),
        (dict(noise="lol"), r"noise must be one of \['locobot', 'none', 'paper', 'paper_symmetric', 'paper_unclipped'\]"),
        (dict(split="dev"), r"split must be one of \['test', 'train', 'val'\]"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        from_flat(DatasetConfig, kwargs)


def test_replay_buffer_yields_each_episode_once_per_epoch(built):
    buffer = built.replay_buffer(batch_size=3, seed=0)
    seeds = torch.cat([buffer.sample()["episode_seed"] for _ in range(2)])
    assert sorted(seeds.tolist()) == sorted(built.episodes["episode_seed"].tolist())
    with pytest.raises(RuntimeError):
        buffer.extend(built.episodes[:1])  # read-only dataset
    assert np.isfinite(built.statistics()["mean_length"])


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(format_version=1), "version 1 stored CHW frames"),
        (dict(format_version=3), "version 3 stored every episode's demonstration frames"),
        (dict(env_version=1), f"made by env version 1, but this env is version {ENV_VERSION}"),
        (dict(env_version=None), "made by env version None"),
    ],
    ids=["old-layout", "hand-loop-layout", "old-env", "no-env-version"],
)
def test_stale_datasets_are_refused(built, tmp_path, changes, match):
    root = tmp_path / "stale"
    shutil.copytree(built.root, root)
    meta = json.loads((root / "meta.json").read_text())
    (root / "meta.json").write_text(json.dumps({**meta, **changes}))
    with pytest.raises(DatasetError, match=match):
        EpisodeDataset(root)
    with pytest.raises(DatasetError, match=match):  # and never resumed into
        EpisodeDataset.build(root, from_flat(DatasetConfig, TINY), num_workers=1, progress=False)


def test_homing_datasets_and_evaluations_play_homing_episodes(tmp_path):
    from spf_rl.data import _chunk_env
    from spf_rl.evaluation import EvalConfig, make_eval_env

    config = from_flat(DatasetConfig, {**TINY, "num_episodes": 2, "task": "homing"})
    dataset = EpisodeDataset.build(tmp_path / "homing", config, num_workers=1, progress=False)
    assert dataset.demos.config.episodes.task == "homing"
    assert _chunk_env(config, 2, 0, str(dataset.demos.root)).base_env.task == "homing"
    env = make_eval_env(EvalConfig(episodes=EpisodeSpec(split="test", num_houses=1, demo_length=5, max_steps=8, image_size=32, task="homing", seed=1234), num_episodes=2, num_agents=2, render=False))
    assert env.base_env.task == "homing"
    with pytest.raises(ValueError, match="task"):
        DatasetConfig(episodes=EpisodeSpec(max_steps=50, task="fetch"))
    with pytest.raises(ValueError, match="task"):
        EvalConfig(episodes=EpisodeSpec(split="test", max_steps=50, task="fetch", seed=1234))


#: The 4,000-episode dataset of the bc_row runs, made by the hand-written loop before the
#: collectors (its statistics as runs/bc_row/spf-s0.8-seed0/results.json recorded them; that
#: run directory is in git history only), and the dataset settings that made it.
HAND_LOOP_DATASET = {"episodes": 4000, "behaviour_success": 0.99, "mean_length": 33.5905}
def test_two_workers_build_both_stores_in_one_pool_and_the_same_bytes(built, tmp_path, monkeypatch):
    """The demonstrations and the episodes are built in one pool of worker processes, which
    start once, and give the bytes of the one-process build."""
    import spf_rl.data as data_module

    pools = []

    def counted(num_workers):
        pools.append(num_workers)
        return real(num_workers)

    real = data_module.worker_pool
    monkeypatch.setattr(data_module, "worker_pool", counted)
    two = EpisodeDataset.build(tmp_path / "two", from_flat(DatasetConfig, TINY), num_workers=2, progress=False)
    assert pools == [2]
    for key in built.episodes.keys(include_nested=True, leaves_only=True):
        assert torch.equal(two.episodes[key], built.episodes[key]), key
    assert torch.equal(two.demos.frames, built.demos.frames)


HAND_LOOP_DATASET_CONFIG = {
    "split": "train", "num_houses": None, "noise": "paper", "random_action_prob": 0.2, "demo_length": 30,
    "max_steps": 50, "image_size": 64, "seed": 0, "task": "follow",
}


def test_collected_datasets_match_the_hand_loop_datasets_in_distribution(tmp_path):
    """Behaviour success and mean length of the collector-made dataset against those of the
    4,000-episode dataset the previous generator (a hand-written loop) made for the bc_row runs,
    as its committed results record them."""
    old = HAND_LOOP_DATASET
    config = from_flat(DatasetConfig, {**HAND_LOOP_DATASET_CONFIG, "num_episodes": 96, "chunk_size": 32})
    new = EpisodeDataset.build(tmp_path / "new", config, num_workers=1, progress=False).episodes
    lengths = new["length"].double()
    standard_error = float(lengths.std()) / len(lengths) ** 0.5
    assert abs(float(lengths.mean()) - old["mean_length"]) < 4 * standard_error
    failures = int((~new["success"]).sum())  # old rate 0.99: 96 episodes fail at most 6 times with p > 0.999
    assert failures <= 6


def test_episodes_the_numbering_never_reaches_are_an_error_not_a_hang(built):
    from envs.episodes import play_episode_steps
    from envs.scripted import EpsilonExpertPolicy
    from spf_rl.data import STEP_KEYS, _chunk_env

    config = from_flat(DatasetConfig, TINY)
    env = _chunk_env(config, 2, 4, str(demos_root(built.root)))  # plays episodes 4, 5, 6, ...
    with pytest.raises(RuntimeError, match=r"never reaches episodes \[0, 1\]"):
        play_episode_steps(env, EpsilonExpertPolicy(0.0), 0, 2, STEP_KEYS, config.episodes.max_steps)
