"""The SPF policy and its baselines in the real ``PathFollowEnv`` (TorchRL collectors).

Small settings keep the file fast on CPU: 32x32 frames, 6-step demos, 8-step
episodes, one house. ``ParallelEnv`` uses ``spawn``, so every factory here is
module-level (``functools.partial`` of :func:`envs.factory.make_path_follow_env`).
"""
from __future__ import annotations

from functools import partial

import pytest
import torch
from conftest import CountingEncoder
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import set_recurrent_mode

from envs.factory import make_path_follow_env
from envs.worker_processes import start_method
from spf_rl.modules import (
    ImageEncoder,
    OpenLoopPolicy,
    SPFConfig,
    make_action_only_policy,
    make_actor,
    make_rpf_policy,
    make_spf_policy,
)

SIZE = 32
N = 6
MAX_STEPS = 8
ENV_KWARGS = dict(noise="paper", num_houses=1, image_size=SIZE, demo_length=N, max_steps=MAX_STEPS)
MAKE_ENV = partial(make_path_follow_env, **ENV_KWARGS)
MAKE_BATCHED_ENV = partial(make_path_follow_env, num_agents=3, **ENV_KWARGS)
CFG = SPFConfig(demo_length=N, sparsity=0.4, feature_dim=16, hidden_size=16, image_size=(SIZE, SIZE))
FACTORIES = {
    "spf": make_spf_policy,
    "rpf": make_rpf_policy,
    "action_only": make_action_only_policy,
}
# TransformedEnv(env, primer) on a TransformedEnv unwraps it (intended here)
pytestmark = pytest.mark.filterwarnings("ignore:Nested TransformedEnvs:UserWarning")
STATE_KEYS = ("logits", "action", "action_log_prob", "eta", "spf_hidden", "memory_features")



@pytest.fixture
def env():
    # a fresh env per test: TransformedEnv(env, primer) unwraps the nested
    # TransformedEnv and reuses its transforms, so envs are not shared between tests
    env = MAKE_ENV()
    env.set_seed(0)
    yield env
    env.close(raise_if_closed=False)


def _collect(create_env, actor, frames_per_batch, total_frames):
    collector = Collector(
        create_env,
        actor,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        auto_register_policy_transforms=True,
    )
    try:
        batches = [b.clone() for b in collector]
    finally:
        collector.shutdown()
    return batches


def _check_batch(data, policy):
    for key in STATE_KEYS:
        assert key in data.keys(), key
    init = data["is_init"].squeeze(-1)
    assert init.any()
    assert (data["eta"][init] == 0).all() and (data["spf_hidden"][init] == 0).all()
    # the memory in use: encoded where is_init (the primer's zeros replaced), then carried
    assert (data["memory_features"][init] != 0).any()
    torch.testing.assert_close(data["memory_features"], data["next", "memory_features"])
    assert data["memory_features"].shape[-2:] == (policy.memory_length, CFG.feature_dim)
    # inside an episode the state is carried: root at t+1 == next at t
    same = ~init[:, 1:]
    torch.testing.assert_close(data["eta"][:, 1:][same], data["next", "eta"][:, :-1][same])
    torch.testing.assert_close(
        data["memory_features"][:, 1:][same], data["next", "memory_features"][:, :-1][same]
    )
    assert data["pixels"].dtype == torch.uint8 and data["demo_frames"].dtype == torch.uint8
    assert data["demo_frames"].shape[-4:] == (N, SIZE, SIZE, 3)


def _check_sequence_replay(actor, data):
    """Recompute a collected [N, T] batch in sequence mode: same logits and log-probs."""
    with torch.no_grad(), set_recurrent_mode(True):
        replay = actor(data.clone().exclude("logits", "action", "action_log_prob"))
        dist = actor.get_dist(data.clone())
    torch.testing.assert_close(replay["logits"], data["logits"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(dist.log_prob(data["action"]), data["action_log_prob"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(replay["next", "eta"], data["next", "eta"], rtol=1e-5, atol=1e-5)


def test_parallel_env_collector_and_sequence_replay():
    torch.manual_seed(0)
    policy = make_spf_policy(CFG)
    actor = make_actor(policy, 3)
    env = ParallelEnv(2, MAKE_ENV, mp_start_method=start_method())
    batches = _collect(env, actor, frames_per_batch=20, total_frames=40)
    assert len(batches) == 2
    for data in batches:
        assert data.shape == (2, 10)
        _check_batch(data, policy)
        # the second batch starts mid-episode: t=0 restarts from the stored state
        _check_sequence_replay(actor, data)
    # trajectories continue across batches: the state carried into batch 2 is batch 1's last "next"
    first, second = batches
    cont = ~second["is_init"][:, 0, 0]
    torch.testing.assert_close(second["eta"][:, 0][cont], first["next", "eta"][:, -1][cont])


def test_batched_env_collector_encodes_memory_only_at_episode_starts():
    torch.manual_seed(0)
    enc = CountingEncoder(ImageEncoder(CFG.feature_dim, CFG.image_size))
    policy = make_spf_policy(CFG, encoder=enc)
    actor = make_actor(policy, 3)
    env = MAKE_BATCHED_ENV()
    env.set_seed(1)
    collector = Collector(
        env, actor, frames_per_batch=3 * 10, total_frames=3 * 20, auto_register_policy_transforms=True
    )
    counts, batches = [], []
    try:
        enc.frames = 0
        for data in collector:
            counts.append(enc.frames)
            enc.frames = 0
            batches.append(data.clone())
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for data, count in zip(batches, counts):
        assert data.shape == (3, 10)
        _check_batch(data, policy)
        # one observation per step plus l memory frames per (possibly partial) episode start
        assert count == data.numel() + policy.memory_length * int(data["is_init"].sum())
        _check_sequence_replay(actor, data)


@pytest.mark.parametrize("name", list(FACTORIES))
def test_check_env_specs_with_primer(env, name):
    policy = FACTORIES[name](CFG)
    primed = TransformedEnv(env, policy.make_tensordict_primer())
    check_env_specs(primed, seed=0)
    expected = {"spf_hidden", "eta"} | ({"memory_features"} if name != "action_only" else set())
    assert expected <= set(primed.observation_spec.keys())
    # one real step with the policy
    with torch.no_grad():
        td = make_actor(policy, 3)(primed.reset())
    assert td["logits"].shape == (3,) and (td["eta"] == 0).all()


def test_open_loop_policy_replays_demo_actions(env):
    policy = OpenLoopPolicy(3)
    primed = TransformedEnv(env, policy.make_tensordict_primer())
    primed.set_seed(3)
    with torch.no_grad():
        data = primed.rollout(12, make_actor(policy, 3), break_when_any_done=False)
    demo, step = data["demo_actions"], data["open_loop_step"].squeeze(-1)
    assert step[0] == 0 and data["is_init"][0].item()
    # the first episode: step t replays the demo's action t
    first = int(data["next", "done"].squeeze(-1).nonzero()[0]) + 1 if data["next", "done"].any() else 12
    k = min(first, N)
    assert step[:k].tolist() == list(range(k))
    assert data["action"][:k].tolist() == demo[0, :k].tolist()
    # everywhere: demo_actions[step] within the demo, turn left (1) after it
    expected = torch.where(step < N, demo.gather(-1, step.clamp(max=N - 1).unsqueeze(-1)).squeeze(-1), 1)
    assert data["action"].tolist() == expected.tolist()
    assert (step[data["is_init"].squeeze(-1)] == 0).all()


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])
