"""Tests for envs.transforms.ActuationNoise: presets, determinism, TorchRL transform checklist."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, InitTracker, ParallelEnv, SerialEnv, TransformedEnv, check_env_specs

from envs.demos import nominal_motion
from envs.expert import FORWARD, TURN_LEFT, TURN_RIGHT
from envs.factory import make_path_follow_env
from envs.nav_env import PathFollowEnv
from envs.transforms import NOISE_PRESETS, ActuationNoise, NoiseModel, make_noise_model
from envs.worker_processes import start_method

TURN = np.deg2rad(20.0)
SMALL = dict(num_houses=1, demo_length=6, max_steps=8, image_size=32)


def sample(preset, actions, seeds=None, steps=None):
    actions = np.asarray(actions)
    seeds = np.arange(len(actions)) if seeds is None else seeds
    steps = np.zeros(len(actions), dtype=np.int64) if steps is None else steps
    return make_noise_model(preset).sample(actions, seeds, steps)


def test_none_is_nominal():
    motion = sample("none", [FORWARD, TURN_LEFT, TURN_RIGHT])
    assert np.allclose(motion, [[0.3, 0, 0], [0, 0, TURN], [0, 0, -TURN]])


def test_paper_symmetric_is_clipped_to_20_percent():
    forward = sample("paper_symmetric", [FORWARD] * 2000)
    assert forward[:, 0].min() >= 0.24 - 1e-9 and forward[:, 0].max() <= 0.36 + 1e-9
    assert forward[:, 0].std() > 0.03  # the clip binds: steps pile up at 0.24 and 0.36
    assert np.allclose(forward[:, 1:], 0)
    left = sample("paper_symmetric", [TURN_LEFT] * 2000)
    assert left[:, 2].min() >= 0.8 * TURN - 1e-9 and left[:, 2].max() <= 1.2 * TURN + 1e-9
    assert np.allclose(left[:, :2], 0)  # no translation on a turn
    right = sample("paper_symmetric", [TURN_RIGHT] * 2000)[:, 2]
    assert right.max() <= -0.8 * TURN + 1e-9 and right.min() >= -1.2 * TURN - 1e-9


def test_paper_is_the_first_authors_noisy_action():
    """NoisyAction.py (clip ratio 0.2): forward clip(0.3 + N(0.3, 0.5^2), 0.24, 0.36) m, clip(s, -4, 4) deg;
    turns clip(N(0, 0.5^2), 0, 0.06) m, clip(+-20 + s, 16, 24) deg; s = N(0, 1) rad."""
    count = 20000
    forward = sample("paper", [FORWARD] * count)
    assert forward[:, 0].min() >= 0.24 - 1e-9 and forward[:, 0].max() <= 0.36 + 1e-9
    # the mean counts twice: P(0.6 + 0.5 z >= 0.36) = P(z >= -0.48) = 0.684 of steps are 0.36 m
    assert abs(np.isclose(forward[:, 0], 0.36).mean() - 0.684) < 0.015
    assert abs(np.isclose(forward[:, 0], 0.24).mean() - 0.236) < 0.015  # P(0.6 + 0.5 z <= 0.24) = P(z <= -0.72)
    rotation_deg = np.rad2deg(forward[:, 2])
    assert rotation_deg.min() >= -4 - 1e-9 and rotation_deg.max() <= 4 + 1e-9
    assert abs(np.isclose(np.abs(rotation_deg), 4).mean() - 0.944) < 0.01  # P(|z| >= 4 deg in rad)
    assert np.allclose(forward[:, 1], 0)
    for action, sign in ((TURN_LEFT, 1), (TURN_RIGHT, -1)):
        turn = sample("paper", [action] * count)
        assert turn[:, 0].min() >= 0 and turn[:, 0].max() <= 0.06 + 1e-9
        assert abs((turn[:, 0] == 0).mean() - 0.5) < 0.015  # N(0, 0.5^2) below 0 half the time
        degrees = sign * np.rad2deg(turn[:, 2])
        assert degrees.min() >= 16 - 1e-9 and degrees.max() <= 24 + 1e-9
        assert np.allclose(turn[:, 1], 0)
    # translation and rotation are drawn independently
    moved = forward[:, 0] > 0.3
    assert abs(np.mean(rotation_deg[moved] > 0) - np.mean(rotation_deg[~moved] > 0)) < 0.03


def test_explicit_bounds_validation():
    from envs.transforms import GaussianMotionNoise

    with pytest.raises(ValueError, match="forward_bounds_m"):
        GaussianMotionNoise(forward_bounds_m=(0.3, 0.2))
    with pytest.raises(ValueError, match="clip_fraction and explicit motion bounds"):
        NoiseModel(linear=GaussianMotionNoise(forward_bounds_m=(0.2, 0.3)), clip_fraction=0.2)


def test_paper_unclipped_is_the_literal_gaussian():
    forward = sample("paper_unclipped", [FORWARD] * 4000)[:, 0]
    assert abs(forward.mean() - 0.3) < 0.03 and abs(forward.std() - 0.5) < 0.03
    turn = sample("paper_unclipped", [TURN_LEFT] * 4000)[:, 2]
    assert abs(turn.std() - 1.0) < 0.05


def test_locobot_truncated_gaussians():
    forward = sample("locobot", [FORWARD] * 4000)
    std = np.sqrt(0.006)
    assert forward[:, 0].min() >= 0.3 + 0.014 - 3 * std - 1e-9
    assert forward[:, 0].max() <= 0.3 + 0.014 + 3 * std + 1e-9
    assert abs(forward[:, 0].mean() - 0.314) < 0.01
    right = sample("locobot", [TURN_RIGHT] * 4000)[:, 2]
    assert right.max() <= -0.05 * TURN + 1e-9  # never reversed
    assert right.mean() < -TURN  # overshoots on average, like habitat-sim


def test_custom_noise_and_validation():
    model = NoiseModel.custom(forward_std_m=0.1, rotation_std_rad=0.0)
    forward = model.sample(np.full(3000, FORWARD), np.arange(3000), np.zeros(3000, dtype=np.int64))
    assert abs(forward[:, 0].std() - 0.1) < 0.01
    with pytest.raises(ValueError, match="std must be >= 0"):
        NoiseModel.custom(forward_std_m=-1.0)
    with pytest.raises(ValueError, match="noise must be one of"):
        ActuationNoise("strong")


def test_noise_is_a_function_of_seed_step_and_action():
    a = sample("paper_unclipped", [FORWARD] * 3, seeds=np.array([1, 1, 2]), steps=np.array([0, 1, 0]))
    b = sample("paper_unclipped", [FORWARD] * 3, seeds=np.array([1, 1, 2]), steps=np.array([0, 1, 0]))
    assert np.array_equal(a, b)
    assert len({tuple(row) for row in a}) == 3


def test_philox_draws_match_the_reference_generator():
    from envs.transforms import _philox_uniforms, philox_uniforms

    rng = np.random.default_rng(0)
    seeds = np.concatenate([[0, 1, 2**62 - 1], rng.integers(0, 2**62, size=50)])
    steps = np.concatenate([[0, 0, 49], rng.integers(0, 1000, size=50)])
    fast = philox_uniforms(seeds, steps, 3)
    reference = np.stack([_philox_uniforms(int(s), int(k), 3) for s, k in zip(seeds, steps)])
    assert np.array_equal(fast, reference)
    assert fast.min() > 0 and fast.max() < 1


@pytest.mark.parametrize("preset", sorted(NOISE_PRESETS))
def test_batch_of_agents_draws_as_one_agent_at_a_time(preset):
    rng = np.random.default_rng(1)
    actions = rng.integers(0, 4, size=40)
    seeds = rng.integers(0, 2**62, size=40)
    steps = rng.integers(0, 60, size=40)
    model = make_noise_model(preset)
    batch = model.sample(actions, seeds, steps)
    one_by_one = np.concatenate([model.sample(actions[i : i + 1], seeds[i : i + 1], steps[i : i + 1]) for i in range(40)])
    assert np.array_equal(batch, one_by_one)
    shuffled = rng.permutation(40)
    assert np.array_equal(model.sample(actions[shuffled], seeds[shuffled], steps[shuffled]), batch[shuffled])
    # the same draws through the transform, batched or not
    transform = ActuationNoise(preset)
    td = TensorDict(
        action=torch.as_tensor(actions), episode_seed=torch.as_tensor(seeds)[:, None], step_count=torch.as_tensor(steps)[:, None], batch_size=[40]
    )
    batched = transform.inv(td)["actuation_noise"]
    single = torch.stack([transform.inv(td[i])["actuation_noise"] for i in range(40)])
    assert torch.equal(batched, single)
    assert torch.equal(batched, torch.as_tensor(batch - nominal_motion(actions), dtype=torch.float32))


def test_transform_no_env_and_inverse():
    transform = ActuationNoise("paper")
    td = TensorDict(
        action=torch.tensor([0, 1]), episode_seed=torch.tensor([[3], [4]]), step_count=torch.tensor([[0], [0]]), batch_size=[2]
    )
    out = transform.inv(td)
    assert out["actuation_noise"].shape == (2, 3)
    assert "actuation_noise" not in td.keys()  # inverse works on a copy: the policy's data is untouched
    assert torch.equal(out["action"], td["action"])


@pytest.mark.parametrize("preset", sorted(NOISE_PRESETS))
def test_single_trans_env_check(preset):
    env = TransformedEnv(PathFollowEnv(**SMALL), ActuationNoise(preset))
    env.set_seed(0)
    check_env_specs(env)


def test_transform_compose_and_executed_motion():
    env = TransformedEnv(PathFollowEnv(**SMALL), Compose(ActuationNoise("paper"), InitTracker()))
    env.set_seed(0)
    td = env.reset()
    td["action"] = torch.tensor(FORWARD)
    out = env.step(td)
    travelled = out["next", "path_length"].item()
    assert out["action"].item() == FORWARD  # stored action is the policy's
    assert travelled in (pytest.approx(0.24, abs=1e-4), pytest.approx(0.36, abs=1e-4)) or travelled < 0.24


def test_serial_trans_env_check():
    env = SerialEnv(2, partial(make_path_follow_env, noise="paper", **SMALL))
    env.set_seed(0)
    check_env_specs(env)
    env.close()


def test_parallel_trans_env_check():
    env = ParallelEnv(2, partial(make_path_follow_env, noise="locobot", **SMALL), mp_start_method=start_method())
    env.set_seed(0)
    check_env_specs(env)
    env.close(raise_if_closed=False)


def test_trans_serial_env_check():
    env = TransformedEnv(SerialEnv(2, partial(PathFollowEnv, **SMALL)), ActuationNoise("paper"))
    env.set_seed(0)
    check_env_specs(env)
    env.close()


def test_transform_rb():
    rb = ReplayBuffer(storage=LazyTensorStorage(10), transform=ActuationNoise("paper"))
    td = TensorDict(
        action=torch.tensor([0, 2]), episode_seed=torch.tensor([[3], [4]]), step_count=torch.tensor([[0], [5]]), batch_size=[2]
    )
    rb.extend(td)
    stored = rb[:2]
    assert stored["actuation_noise"].shape == (2, 3)
    realised_turn_deg = np.rad2deg(float(stored["actuation_noise"][1, 2]) - TURN)  # a right turn
    assert -24 - 1e-4 <= realised_turn_deg <= -16 + 1e-4
