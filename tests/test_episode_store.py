"""Episode stores: the demonstrations of a seed's episodes rendered once, played as the same episodes.

Evaluation (:func:`spf_rl.evaluation.evaluate_policy`) plays its episodes
from such a store, kept under ``store_root`` or temporary; every record must be what
the rendering path gives.
"""
from __future__ import annotations

import dataclasses
import tempfile
import threading

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import Compose, InitTracker, TransformedEnv

import envs.demo_store as demo_store_module
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec, from_flat
from envs.episodes import run_episodes
from envs.nav_env import PathFollowEnv
from envs.scripted import ExpertPolicy
from envs.transforms import ActuationNoise
from spf_rl.evaluation import EvalConfig, episode_store_name, evaluate_policy, greedy, make_eval_env
from spf_rl.modules.policy import SPFConfig
from spf_rl.modules.registry import build_policy

SIZES = dict(demo_length=6, image_size=32)
EPISODES, AGENTS, SEED = 7, 3, 11


def _store(root, episodes=EPISODES, seed=SEED, task="follow", **kwargs) -> DemoStore:
    config = DemoStoreConfig.of(EpisodeSpec(split="val", num_houses=2, seed=seed, task=task, **SIZES), num_demos=episodes)
    config = dataclasses.replace(config, **kwargs)
    return DemoStore.build(root, config, progress=False)


def _env(store=None, seed=SEED):
    env = TransformedEnv(
        PathFollowEnv("val", num_houses=2, num_agents=AGENTS, with_expert=True, demo_store=store, emit_demo_frames=store is None, **SIZES),
        Compose(ActuationNoise("paper"), InitTracker()),
    )
    env.set_seed(seed)
    return env


def test_episode_store_plays_the_episodes_of_its_seed(tmp_path):
    """Same episodes, noise and outcomes as the env that samples and renders each demonstration."""
    store = _store(tmp_path / "episodes")
    rendered = run_episodes(_env(), ExpertPolicy(), EPISODES)
    stored = run_episodes(_env(store), ExpertPolicy(), EPISODES)
    assert stored == rendered
    assert len({r["episode_seed"] for r in stored}) == EPISODES


def test_episode_store_frames_are_the_rendered_demonstrations(tmp_path):
    store = _store(tmp_path / "episodes")
    env = _env()
    first = env.reset()
    for agent in range(AGENTS):
        number = int(first["episode_index"][agent])
        assert torch.equal(store.frames[number], first["demo_frames"][agent])
        assert torch.equal(store.actions[number], first["demo_actions"][agent])


def test_env_refuses_a_seed_other_than_the_episode_store_s(tmp_path):
    store = _store(tmp_path / "episodes")
    with pytest.raises(ValueError, match=f"seed must be {SEED} for the episode store"):
        _env(store, seed=SEED + 1)


def test_unseeded_env_plays_the_episode_store_s_seed(tmp_path):
    store = _store(tmp_path / "episodes")
    env = PathFollowEnv("val", num_houses=2, num_agents=AGENTS, demo_store=store, **SIZES)
    seeded = PathFollowEnv("val", num_houses=2, num_agents=AGENTS, **SIZES)
    seeded.set_seed(SEED)
    assert torch.equal(env.reset()["episode_seed"], seeded.reset()["episode_seed"])


def test_episodes_past_the_store_wrap_around(tmp_path):
    store = _store(tmp_path / "episodes", episodes=2)
    env = PathFollowEnv("val", num_houses=2, num_agents=AGENTS, demo_store=store, **SIZES)
    reset = env.reset()
    assert reset["demo_id"].reshape(-1).tolist() == [0, 1, 0]
    assert reset["episode_index"].reshape(-1).tolist() == [0, 1, 2]


@pytest.mark.parametrize("bad", [-1, 1.5, True, "3"])
def test_episodes_seed_is_checked(bad):
    with pytest.raises(ValueError, match="seed must be an int >= 0"):
        DemoStoreConfig(episodes=EpisodeSpec(seed=bad), num_demos=2, numbered=True)


def test_a_store_with_other_route_lengths_cannot_be_an_episode_store(tmp_path):
    store = _store(tmp_path / "episodes", min_route_length_m=1.0)
    with pytest.raises(ValueError, match="an episode store must draw the env's own episodes"):
        PathFollowEnv("val", num_houses=2, demo_store=store, **SIZES)


def _eval_config(**kwargs) -> EvalConfig:
    base = dict(split="val", num_houses=2, num_episodes=EPISODES, num_agents=AGENTS, seed=SEED, max_steps=10, **SIZES)
    return from_flat(EvalConfig, {**base, **kwargs})


class FramesEveryStep(torch.nn.Module):
    """Reads the demonstration frames at every step (no recurrent memory): needs a lookup in every row."""

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        means = frames.float().mean(dim=(-1, -2, -3))  # [B, n]
        return torch.stack([means[:, 0], means[:, 1], means[:, 2]], dim=-1)


@pytest.mark.parametrize("kind", ["spf", "frames_every_step"])
def test_evaluation_scores_the_same_with_and_without_the_store(kind, tmp_path, monkeypatch):
    """A kept store, a temporary one (``store_root=None``) and the env that renders every
    demonstration give the same records."""
    if kind == "spf":
        torch.manual_seed(0)
        policy = build_policy("spf", SPFConfig(sparsity=0.5, feature_dim=8, hidden_size=8, demo_length=6, image_size=(32, 32)))
    else:
        policy = TensorDictModule(FramesEveryStep(), in_keys=["demo_frames"], out_keys=["logits"])
    config = _eval_config()
    policy.eval()
    env = make_eval_env(config, policy)  # no store: samples and renders each demonstration
    with torch.no_grad():
        rendered = run_episodes(env, greedy(policy), EPISODES)
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))
    summary_temporary, in_temporary = evaluate_policy(policy, config)
    assert list(temporary.iterdir()) == []  # the temporary store is gone
    summary_kept, kept = evaluate_policy(policy, _eval_config(store_root=str(tmp_path / "kept")))
    assert kept == in_temporary == rendered
    assert summary_kept == summary_temporary
    assert (tmp_path / "kept" / episode_store_name(config) / "meta.json").exists()


@pytest.mark.parametrize("kind", ["spf", "frames_every_step"])
def test_worker_processes_score_the_same_episodes(kind, tmp_path):
    """Two collector processes (their envs sharing one numbering, each with a CPU copy of the
    policy) record the episodes one process does, each once, whatever the agents per env."""
    if kind == "spf":
        torch.manual_seed(0)
        policy = build_policy("spf", SPFConfig(sparsity=0.5, feature_dim=8, hidden_size=8, demo_length=6, image_size=(32, 32)))
    else:
        policy = TensorDictModule(FramesEveryStep(), in_keys=["demo_frames"], out_keys=["logits"])
    root = str(tmp_path / "kept")
    one_summary, one = evaluate_policy(policy, _eval_config(store_root=root))
    two_summary, two = evaluate_policy(policy, _eval_config(store_root=root, num_collectors=2, num_agents=2))
    assert two == one and two_summary == one_summary
    assert [r["episode_index"] for r in two] == list(range(EPISODES))


def test_num_collectors_is_checked():
    with pytest.raises(ValueError, match="num_collectors"):
        _eval_config(num_collectors=0)


@pytest.mark.parametrize("kind", ["spf", "frames_every_step"])
def test_unrendered_evaluation_feeds_frame_readers_blank_frames(kind):
    """With ``render=False`` there is no store; a policy that reads ``demo_frames`` gets
    the env's blank frames (zeros), the same episodes as the expert plays."""
    seen = []

    class Recording(FramesEveryStep):
        def forward(self, frames):
            seen.append(frames)
            return super().forward(frames)

    if kind == "spf":
        torch.manual_seed(0)
        policy = build_policy("spf", SPFConfig(sparsity=0.5, feature_dim=8, hidden_size=8, demo_length=6, image_size=(32, 32)))
    else:
        policy = TensorDictModule(Recording(), in_keys=["demo_frames"], out_keys=["logits"])
    summary, records = evaluate_policy(policy, _eval_config(render=False))
    assert len(records) == EPISODES and 0.0 <= summary["success"] <= 1.0
    if kind != "spf":
        assert seen and all(int(frames.count_nonzero()) == 0 for frames in seen)


def test_a_kept_episode_store_is_built_once(tmp_path, monkeypatch):
    policy = TensorDictModule(FramesEveryStep(), in_keys=["demo_frames"], out_keys=["logits"])
    config = _eval_config(store_root=str(tmp_path), num_episodes=3)
    first = evaluate_policy(policy, config)[1]
    calls = []
    monkeypatch.setattr(demo_store_module, "make_demo_chunk", lambda *args: calls.append(args))
    assert evaluate_policy(policy, config)[1] == first
    assert calls == []
    other = dataclasses.replace(config, episodes=config.episodes.replace(seed=SEED + 1))
    assert episode_store_name(other) != episode_store_name(config)


def test_no_store_without_a_store_root_or_rendering(tmp_path):
    from spf_rl.evaluation import episode_store

    assert episode_store(_eval_config()) is None
    assert episode_store(_eval_config(store_root=str(tmp_path), render=False)) is None
    assert list(tmp_path.iterdir()) == []


def test_concurrent_builds_of_one_store_take_turns(tmp_path):
    root = tmp_path / "shared"
    results, errors = [], []

    def build():
        try:
            results.append(_store(root, episodes=3))
        except Exception as err:  # reported below
            errors.append(err)

    threads = [threading.Thread(target=build) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert len(results) == 2
    assert torch.equal(results[0].frames, results[1].frames)
    DemoStore(root)  # complete and verified


def test_episode_identity_ignores_how_episodes_are_played():
    from spf_rl.evaluation import episode_identity

    config = _eval_config()
    assert episode_identity(dataclasses.replace(config, store_root="elsewhere")) == episode_identity(config)
    assert episode_identity(dataclasses.replace(config, num_collectors=2)) == episode_identity(config)
    assert episode_identity(dataclasses.replace(config, episodes=config.episodes.replace(seed=SEED + 1))) != episode_identity(config)


def test_homing_episode_store_plays_the_homing_episodes(tmp_path):
    store = _store(tmp_path / "homing", task="homing")
    def env(store=None):
        env = TransformedEnv(
            PathFollowEnv("val", num_houses=2, num_agents=AGENTS, with_expert=True, task="homing", demo_store=store,
                          emit_demo_frames=store is None, **SIZES),
            Compose(ActuationNoise("paper"), InitTracker()),
        )
        env.set_seed(SEED)
        return env
    assert run_episodes(env(store), ExpertPolicy(), EPISODES) == run_episodes(env(), ExpertPolicy(), EPISODES)


def test_a_store_of_another_env_version_is_never_reopened(monkeypatch):
    import spf_rl.evaluation as evaluation

    name = episode_store_name(_eval_config())
    monkeypatch.setattr(evaluation, "ENV_VERSION", evaluation.ENV_VERSION + 1)
    assert episode_store_name(_eval_config()) != name


def test_an_existing_store_opens_without_a_lock(tmp_path, monkeypatch):
    import envs.tensor_store as tensor_store

    store = _store(tmp_path / "episodes", episodes=2)
    tmp_path.chmod(0o555)  # read-only parent: no lock file can be made
    try:
        monkeypatch.setattr(tensor_store, "FileLock", None)  # and no lock is taken
        assert torch.equal(_store(tmp_path / "episodes", episodes=2).frames, store.frames)
    finally:
        tmp_path.chmod(0o755)
