"""Collection through TorchRL collectors (local and Ray) and the episode layout of collected batches."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from spf_rl.modules import SPFConfig, make_spf_policy
from spf_rl.train.collection import (
    CollectionEnvConfig,
    CollectorConfig,
    batch_to_episodes,
    collect_episodes,
    make_collection_env,
    make_collector,
)
from spf_rl.train.dagger import ExpertMixturePolicy

TINY_ENV = CollectionEnvConfig(num_houses=1, demo_length=5, max_steps=6, image_size=32)


def tiny_policy():
    return make_spf_policy(SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32)))


def synthetic_batch(done: list[list[bool]]) -> TensorDict:
    n, t = len(done), len(done[0])
    done_t = torch.tensor(done).unsqueeze(-1)
    is_init = torch.zeros(n, t, 1, dtype=torch.bool)
    is_init[:, 0] = True
    is_init[:, 1:] = done_t[:, :-1]
    step = torch.arange(n * t).reshape(n, t)
    return TensorDict(
        {
            "pixels": step[..., None, None, None].expand(n, t, 3, 2, 2).to(torch.uint8),
            "action": step % 3,
            "expert_action": (step + 1) % 3,
            "is_init": is_init,
            "demo_frames": step[..., None, None, None, None].expand(n, t, 4, 3, 2, 2).to(torch.uint8),
            "demo_actions": torch.zeros(n, t, 4, dtype=torch.long),
            "episode_seed": step[..., None],
            "next": {
                "done": done_t,
                "success": done_t.clone(),
                "spl": done_t.float() * 0.5,
            },
        },
        batch_size=[n, t],
    )


def test_batch_to_episodes_cuts_pads_and_labels():
    batch = synthetic_batch([[False, True, False, False], [False, False, False, True]])
    episodes = batch_to_episodes(batch, max_steps=5)
    # row 0: an episode of 2 steps, then one cut short after 2; row 1: one episode of 4 steps
    assert episodes["length"].tolist() == [2, 2, 4]
    assert episodes["success"].tolist() == [True, False, True]
    assert episodes["spl"].tolist() == [0.5, 0.0, 0.5]
    assert episodes["steps"].batch_size == torch.Size([3, 5])
    assert episodes["steps", "mask"].sum(-1).tolist() == [2, 2, 4]
    # each episode keeps the demonstration of its first step, and its own steps in order
    assert episodes["demo_frames"][:, 0, 0, 0, 0].tolist() == [0, 2, 4]
    assert episodes["steps", "pixels"][1, :2, 0, 0, 0].tolist() == [2, 3]
    assert episodes["steps", "expert_action"][2, :4].tolist() == [2, 0, 1, 2]
    assert not episodes["steps", "mask"][0, 2:].any()


def test_batch_to_episodes_refuses_too_long_batches():
    with pytest.raises(ValueError, match="max_steps"):
        batch_to_episodes(synthetic_batch([[False] * 7]), max_steps=5)


def test_collector_config_errors_name_the_parameter():
    with pytest.raises(ValueError, match="backend"):
        CollectorConfig(backend="slurm")
    with pytest.raises(ValueError, match="env_mode"):
        CollectorConfig(env_mode="threads")
    with pytest.raises(ValueError, match="num_agents"):
        CollectorConfig(num_agents=0)


def test_local_collection_of_a_recurrent_policy_is_deterministic():
    torch.manual_seed(0)
    policy = tiny_policy().eval()
    behaviour = ExpertMixturePolicy(policy, beta=0.5)

    def collect():
        collector = make_collector(
            behaviour, TINY_ENV, CollectorConfig(num_agents=3), frames_per_batch=18, seed=4, reset_at_each_iter=True
        )
        try:
            with torch.no_grad():
                return collect_episodes(collector, TINY_ENV.max_steps, num_batches=2)
        finally:
            collector.shutdown()

    first, second = collect(), collect()
    assert first["steps", "mask"][:, 0].all() and first["steps", "is_init"][:, 0].all()
    assert int(first["length"].sum()) == 2 * 18  # every collected step is in one episode
    assert torch.equal(first["steps", "pixels"], second["steps", "pixels"])
    assert torch.equal(first["steps", "action"], second["steps", "action"])


@pytest.mark.parametrize("num_collectors", [1, 2])
def test_first_batch_is_a_function_of_the_seed_without_resets(num_collectors):
    """Collectors reset their envs when built, before the seed: the first batch must still be seeded."""
    forward = TensorDictModule(lambda p: torch.zeros(p.shape[0], dtype=torch.long), ["pixels"], ["action"])

    def first_batch(seed: int):
        config = CollectorConfig(num_agents=2, num_collectors=num_collectors)
        collector = make_collector(forward, TINY_ENV, config, frames_per_batch=8 * num_collectors, seed=seed)
        try:
            return next(iter(collector))["episode_seed"].flatten()
        finally:
            collector.shutdown()

    assert torch.equal(first_batch(3), first_batch(3))
    assert not torch.equal(first_batch(3), first_batch(4))


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
def test_ray_backend_collects_a_batch_on_a_local_cluster():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
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
        episodes = batch_to_episodes(batches[0], TINY_ENV.max_steps)
        assert int(episodes["length"].sum()) == 12
        # the actuation noise reached the Ray actor's env: executed turns differ from the nominal ones
        from envs.demos import nominal_motion

        turned = (batch["next", "pose"][..., 2] - batch["pose"][..., 2]).numpy()
        nominal = nominal_motion(batch["action"].numpy())[..., 2]
        deviation = np.abs(np.angle(np.exp(1j * (turned - nominal))))
        assert TINY_ENV.noise == "paper" and (deviation > np.deg2rad(1.0)).mean() > 0.5
    finally:
        ray.shutdown()


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
