"""Collection through TorchRL collectors (local and Ray), and numbered episodes of an episode store kept whole."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec
from envs.episodes import gather_episode_steps
from spf_rl.data import STEP_KEYS
from spf_rl.evaluation import FramesFromStore
from spf_rl.modules import SPFConfig, make_spf_policy
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, make_collection_env, make_collector
from spf_rl.train.dagger import ExpertMixturePolicy

TINY_ENV = CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32))


def tiny_policy():
    return make_spf_policy(SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32)))


def episode_store(root, count: int, seed: int) -> DemoStore:
    """The demonstrations of episodes ``0 .. count - 1`` of env seed ``seed`` in TINY_ENV's houses."""
    env = TINY_ENV.episodes
    config = DemoStoreConfig(
        episodes=EpisodeSpec(split=env.split, num_houses=env.num_houses, demo_length=env.demo_length, image_size=env.image_size, seed=seed),
        num_demos=count, numbered=True,
    )
    return DemoStore.build(root, config, progress=False)


def play_store(behaviour, store: DemoStore, count: int, seed: int, config: CollectorConfig):
    collector = make_collector(
        behaviour, TINY_ENV, config, frames_per_batch=config.total_agents * 5, seed=seed, demo_store=store.root
    )
    try:
        with torch.no_grad():
            return gather_episode_steps(collector, 0, count, STEP_KEYS, TINY_ENV.episodes.max_steps, ("demo_id", "episode_seed"))
    finally:
        collector.shutdown()


def test_collector_config_errors_name_the_parameter():
    with pytest.raises(ValueError, match="backend"):
        CollectorConfig(backend="slurm")
    with pytest.raises(ValueError, match="env_mode"):
        CollectorConfig(env_mode="threads")
    with pytest.raises(ValueError, match="num_agents"):
        CollectorConfig(num_agents=0)


def test_numbered_episodes_of_a_store_do_not_depend_on_the_collector_layout(tmp_path):
    """A recurrent learner with its frames looked up: the same episodes, steps and actions from one
    collector of 3 agents, of 2 agents, or 2 worker processes of 2 agents; each episode whole, from its start."""
    torch.manual_seed(0)
    policy = tiny_policy().eval()
    store = episode_store(tmp_path / "store", count=7, seed=4)
    behaviour = ExpertMixturePolicy(FramesFromStore(policy, store), beta=0.5)
    assert "demo_id" in behaviour.in_keys and "demo_frames" not in behaviour.in_keys
    layouts = [CollectorConfig(num_agents=3), CollectorConfig(num_agents=2), CollectorConfig(num_agents=2, num_collectors=2)]
    first, *others = [play_store(behaviour, store, 7, 4, layout) for layout in layouts]
    assert first["demo_id"].tolist() == list(range(7))  # episode j plays the store's demonstration j
    assert first["steps", "mask"][:, 0].all() and first["steps", "is_init"][:, 0].all()
    lengths = first["steps", "mask"].sum(-1)
    assert torch.equal(lengths, first["length"]) and (lengths >= 1).all()
    assert torch.equal(first["steps", "mask"], torch.arange(TINY_ENV.episodes.max_steps) < lengths[:, None])  # no gaps
    assert 0 < int(first["steps", "action"][first["steps", "mask"]].ne(first["steps", "expert_action"][first["steps", "mask"]]).sum())
    for other in others:
        for key in ("pixels", "action", "expert_action", "mask"):
            assert torch.equal(first["steps", key], other["steps", key]), key
        for key in ("demo_id", "episode_seed", "length", "success", "spl"):
            assert torch.equal(first[key], other[key]), key


def test_numbered_collection_refuses_resets_at_each_batch(tmp_path):
    store = episode_store(tmp_path / "store", count=2, seed=0)
    with pytest.raises(ValueError, match="reset_at_each_iter"):
        make_collector(
            ExpertMixturePolicy(FramesFromStore(tiny_policy().eval(), store), 0.0), TINY_ENV, CollectorConfig(num_agents=2),
            frames_per_batch=10, reset_at_each_iter=True, demo_store=store.root,
        )


@pytest.mark.parametrize("num_collectors", [1, 2])
def test_first_batch_is_a_function_of_the_seed_without_resets(num_collectors):
    """Collectors reset their envs when built, before the seed: the first batch must still be seeded."""
    forward = TensorDictModule(lambda p: torch.zeros(p.shape[0], dtype=torch.long), ["pixels"], ["action"])
    config = CollectorConfig(num_agents=2, num_collectors=num_collectors)

    def build(seed: int):
        return make_collector(forward, TINY_ENV, config, frames_per_batch=8 * num_collectors, seed=seed)

    def first_batch(collector):
        return next(iter(collector))["episode_seed"].flatten()

    collector = build(3)
    try:
        batches = iter(collector)  # one iterator: a multi-process collector's second iter() restarts badly
        built = next(batches)["episode_seed"].flatten()

        def reseeded_batch(seed: int):
            """The next batch of the collector seeded again and reset: a function of ``seed`` by construction."""
            collector.set_seed(seed)
            collector.reset()
            return next(batches)["episode_seed"].flatten()

        # the first batch of a newly built collector is the seeded one (an unseeded one would differ) ...
        assert torch.equal(built, reseeded_batch(3))
        # ... and another seed gives other episodes
        assert not torch.equal(built, reseeded_batch(4))
    finally:
        collector.shutdown()
    if num_collectors == 1:  # in this process, a second build is cheap: two builds of one seed agree
        second = build(3)
        try:
            assert torch.equal(built, first_batch(second))
        finally:
            second.shutdown()


def test_parallel_env_mode_matches_spec():
    env = make_collection_env(TINY_ENV, num_agents=2, env_mode="parallel", primer=tiny_policy().make_tensordict_primer())
    try:
        td = env.reset()
        assert td.batch_size == torch.Size([2])
        assert td["demo_frames"].shape == (2, 5, 32, 32, 3)
        assert "spf_hidden" in td.keys() and "expert_action" in td.keys()
    finally:
        env.close()


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install '.[distributed]')")
def test_ray_backend_collects_a_batch_on_a_local_cluster(tmp_path, ray_cluster):
    policy = tiny_policy().eval()
    behaviour = ExpertMixturePolicy(policy, beta=0.0)
    collector = make_collector(
        behaviour,
        TINY_ENV,
        CollectorConfig(backend="ray", num_collectors=1, num_agents=2),
        frames_per_batch=12,
        total_frames=12,
        seed=1,
        reset_at_each_iter=True,
    )
    batches = [batch for batch in collector]  # not list(): RayCollector.__len__ fails in torchrl 0.14
    collector.shutdown()
    assert len(batches) == 1
    batch = batches[0].reshape(-1, batches[0].shape[-1])
    assert batch.batch_size == torch.Size([2, 6])
    assert batch["is_init"][:, 0].all()
    assert "spf_hidden" in batch.keys() and "expert_action" in batch.keys()
    # beta=0: the actions are the remote learner's greedy actions; recomputing them here gives the same
    with torch.no_grad():
        local = policy(batch[:, :1].clone().squeeze(1))
    assert torch.equal(local["logits"].argmax(-1), batch["action"][:, 0])
    # the actuation noise reached the Ray actor's env: executed turns differ from the nominal ones
    from envs.demos import nominal_motion

    turned = (batch["next", "pose"][..., 2] - batch["pose"][..., 2]).numpy()
    nominal = nominal_motion(batch["action"].numpy())[..., 2]
    deviation = np.abs(np.angle(np.exp(1j * (turned - nominal))))
    assert TINY_ENV.episodes.noise == "paper" and (deviation > np.deg2rad(1.0)).mean() > 0.5
    # numbered episodes of an episode store: two Ray actors play the same episodes as one local collector
    store = episode_store(tmp_path / "store", count=5, seed=2)
    behaviour = ExpertMixturePolicy(FramesFromStore(policy, store), beta=0.0)
    local = play_store(behaviour, store, 5, 2, CollectorConfig(num_agents=2))
    remote = play_store(behaviour, store, 5, 2, CollectorConfig(backend="ray", num_collectors=2, num_agents=2))
    for key in ("pixels", "action", "mask"):
        assert torch.equal(local["steps", key], remote["steps", key]), key
    assert torch.equal(local["length"], remote["length"])


def test_primer_of_a_wrapped_recurrent_policy_is_found():
    from spf_rl.modules import make_actor

    actor = make_actor(tiny_policy().eval())
    assert not hasattr(actor, "make_tensordict_primer")
    collector = make_collector(actor, TINY_ENV, CollectorConfig(num_agents=2), frames_per_batch=12, total_frames=12, seed=0)
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    # the GRU state is carried: zero at episode starts, non-zero after a step
    hidden = batch["spf_hidden"]
    assert torch.all(hidden[batch["is_init"].squeeze(-1)] == 0)
    assert hidden[~batch["is_init"].squeeze(-1)].abs().sum() > 0
