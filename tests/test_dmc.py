"""Tests for envs.dmc: the dm_control face of the path-following task (and envs.follow)."""
from __future__ import annotations

import dm_env
import numpy as np
import pytest
import torch
from dm_env import specs
from torchrl.envs import DMControlWrapper
from torchrl.envs.utils import check_env_specs

from envs.demos import nominal_motion
from envs.dmc import POLICY_OBSERVATIONS, PRIVILEGED_OBSERVATIONS, PathFollowTask, load
from envs.dmc_physics import HousePhysics, agent_house_model
from envs.expert import FORWARD, STOP, TURN_LEFT, TURN_RIGHT
from envs.follow import FollowRules, episode_for_seed
from envs.nav_env import PathFollowEnv
from envs.scenes import build_house
from envs.transforms import make_noise_model

SMALL = dict(num_houses=2, demo_length=5, max_steps=8, image_size=32)


@pytest.fixture
def env():
    environment = load("train", seed=0, **SMALL)
    yield environment
    environment.close()


def _observations_match_spec(observation, spec) -> None:
    assert list(observation) == list(spec)
    for key, value in observation.items():
        spec[key].validate(value)


def test_reset_and_step_follow_dm_env_conventions(env):
    first = env.reset()
    assert first.step_type == dm_env.StepType.FIRST and first.reward is None and first.discount is None
    _observations_match_spec(first.observation, env.observation_spec())
    assert np.array_equal(first.observation["pixels"], first.observation["demo_frames"][0])  # starts on the route
    assert first.observation["pixels"].std() > 0  # a real frame, not a blank one
    second = env.step(np.int64(FORWARD))
    assert second.step_type == dm_env.StepType.MID and second.discount == 1.0
    assert isinstance(second.reward, float)
    _observations_match_spec(second.observation, env.observation_spec())
    assert int(second.observation["step_count"]) == 1
    assert second.observation["demo_frames"] is first.observation["demo_frames"]  # shared within an episode


def test_specs():
    env = load("train", seed=0, stop_action=True, with_expert=True, **SMALL)
    action_spec = env.action_spec()
    assert isinstance(action_spec, specs.DiscreteArray) and action_spec.num_values == 4
    spec = env.observation_spec()
    assert list(spec) == [*POLICY_OBSERVATIONS, *PRIVILEGED_OBSERVATIONS, "expert_action"]
    assert spec["pixels"].shape == (32, 32, 3) and spec["pixels"].dtype == np.uint8
    assert spec["demo_frames"].shape == (5, 32, 32, 3)
    assert spec["demo_actions"].shape == (5,) and spec["demo_actions"].maximum == 2
    env.close()
    policy_only = load("train", seed=0, privileged_observations=False, **SMALL)
    assert policy_only.action_spec().num_values == 3
    assert tuple(policy_only.observation_spec()) == POLICY_OBSERVATIONS
    assert tuple(policy_only.reset().observation) == POLICY_OBSERVATIONS
    policy_only.close()


def _play(seed, actions, **kwargs):
    env = load("train", seed=seed, **{**SMALL, **kwargs})
    steps = [env.reset()] + [env.step(action) for action in actions]
    env.close()
    return steps


def test_same_seed_same_episodes():
    actions = [FORWARD, TURN_LEFT, FORWARD, TURN_RIGHT, FORWARD] * 3
    a, b, c = _play(3, actions), _play(3, actions), _play(4, actions)
    for x, y in zip(a, b):
        assert x.step_type == y.step_type and x.reward == y.reward
        for key in x.observation:
            assert np.array_equal(x.observation[key], y.observation[key]), key
    assert int(a[0].observation["episode_seed"]) != int(c[0].observation["episode_seed"])


class _FixedEpisodeSeed(np.random.RandomState):
    """A random state whose episode seed draws return one value."""

    def __init__(self, episode_seed: int) -> None:
        super().__init__(0)
        self.episode_seed = episode_seed

    def randint(self, *args, **kwargs):
        return self.episode_seed


def test_matches_path_follow_env_for_the_same_episode_seed():
    torchrl_env = PathFollowEnv(**SMALL)
    torchrl_env.set_seed(5)
    td = torchrl_env.reset()
    episode_seed = int(td["episode_seed"])
    env = load("train", seed=_FixedEpisodeSeed(episode_seed), **SMALL)
    observation = env.reset().observation
    assert np.array_equal(observation["demo_frames"], td["demo_frames"].numpy())
    assert np.array_equal(observation["demo_actions"], td["demo_actions"].numpy())
    assert np.array_equal(observation["pixels"], td["pixels"].numpy())
    for action in [FORWARD, FORWARD, TURN_RIGHT, FORWARD, TURN_LEFT, FORWARD, FORWARD, FORWARD]:
        td = torchrl_env.step(td.set("action", torch.tensor(action)))["next"]
        timestep = env.step(action)
        observation = timestep.observation
        assert np.array_equal(observation["pixels"], td["pixels"].numpy())
        np.testing.assert_allclose(observation["pose"], td["pose"].numpy(), atol=1e-5)
        np.testing.assert_allclose(timestep.reward, float(td["reward"]), atol=1e-5)
        np.testing.assert_allclose(observation["goal_distance"], float(td["goal_distance"]), atol=1e-5)
        assert (timestep.step_type == dm_env.StepType.LAST) == bool(td["done"])
        if bool(td["done"]):
            assert timestep.discount == (0.0 if bool(td["terminated"]) else 1.0)
            assert bool(observation["success"]) == bool(td["success"])
            np.testing.assert_allclose(observation["spl"], float(td["spl"]), atol=1e-5)
            break
    torchrl_env.close()
    env.close()


def test_pose_is_physics_state_and_the_eye_rides_on_the_agent(env):
    env.reset()
    physics = env.physics
    assert isinstance(physics, HousePhysics)
    state = physics.get_state()
    start = env.task.get_observation(physics)
    env.step(FORWARD)
    env.step(TURN_LEFT)
    moved = physics.agent_pose()
    assert not np.allclose(moved, start["pose"])
    with physics.reset_context():
        physics.set_state(state)  # back to the start pose: the observation follows the physics
    again = env.task.get_observation(physics)
    assert np.array_equal(again["pose"], start["pose"]) and np.array_equal(again["pixels"], start["pixels"])
    # dm_control's own renderer sees the same view (it filters textures differently)
    dm_frame = physics.render(32, 32, camera_id="eye")
    assert np.abs(dm_frame.astype(float) - start["pixels"]).mean() < 12.0
    # stepping the physics leaves a kinematic pose where the task put it
    physics.step(10)
    assert np.array_equal(physics.agent_pose(), start["pose"])


def test_episode_ends_by_success_or_step_limit():
    expert = load("train", seed=1, with_expert=True, **{**SMALL, "max_steps": 30})
    timestep = expert.reset()
    for _ in range(30):
        timestep = expert.step(timestep.observation["expert_action"])
        if timestep.last():
            break
    assert timestep.last() and timestep.discount == 0.0 and bool(timestep.observation["success"])
    assert 0.0 < float(timestep.observation["spl"]) <= 1.0
    assert expert.step(FORWARD).first()  # dm_control resets after the last step
    expert.close()
    spinning = load("train", seed=1, **SMALL)
    spinning.reset()
    steps = [spinning.step(TURN_LEFT) for _ in range(8)]
    assert [s.last() for s in steps] == [False] * 7 + [True]
    assert steps[-1].discount == 1.0 and not bool(steps[-1].observation["success"])  # truncation
    spinning.close()


def test_stop_action_ends_the_episode():
    env = load("train", seed=2, stop_action=True, **SMALL)
    env.reset()
    timestep = env.step(STOP)
    assert timestep.last() and timestep.discount == 0.0 and not bool(timestep.observation["success"])
    env.close()


def test_actuation_noise_follows_the_noise_model():
    nominal = _play(6, [FORWARD])
    noisy = _play(6, [FORWARD], noise="paper")
    seed = int(noisy[0].observation["episode_seed"])
    house, demo = episode_for_seed(seed, [0, 1], 5, 0.75)
    expected = make_noise_model("paper").sample(np.array([FORWARD]), np.array([seed]), np.array([0]))
    assert not np.allclose(expected, nominal_motion(np.array([FORWARD])))
    travelled = float(noisy[1].observation["path_length"])
    assert not np.isclose(travelled, float(nominal[1].observation["path_length"]))
    assert travelled <= np.hypot(expected[0, 0], expected[0, 1]) + 1e-9  # the realised step, less when sliding
    turned = np.angle(np.exp(1j * (noisy[1].observation["pose"][2] - demo.start_pose[2])))
    np.testing.assert_allclose(turned, expected[0, 2], atol=1e-9)


def test_house_switch_reloads_the_physics():
    env = load("train", seed=0, **{**SMALL, "num_houses": 3})
    seen = set()
    for _ in range(6):
        env.reset()
        house_seed = env.task.demonstration.house_seed
        assert env.physics.house.seed == house_seed
        assert env.physics.model.ptr is agent_house_model(house_seed)
        seen.add(house_seed)
    assert len(seen) > 1
    env.close()


def test_dmcontrol_wrapper_passes_check_env_specs_and_rolls_out():
    wrapped = DMControlWrapper(load("train", noise="paper", with_expert=True, **SMALL))
    wrapped.set_seed(0)
    check_env_specs(wrapped)
    assert wrapped.observation_spec["pixels"].shape == (32, 32, 3)
    wrapped.set_seed(0)
    torch.manual_seed(0)
    rollout = wrapped.rollout(20, break_when_any_done=False)
    assert rollout["next", "pixels"].shape == (20, 32, 32, 3) and rollout["next", "pixels"].dtype == torch.uint8
    assert rollout["demo_frames"].shape == (20, 5, 32, 32, 3)
    done = rollout["next", "done"].squeeze(-1)
    assert done.any()  # 8-step limit: at least two episodes
    assert torch.equal(done, rollout["next", "terminated"].squeeze(-1) | rollout["next", "truncated"].squeeze(-1))
    assert torch.equal(rollout["next", "success"].squeeze(-1) & ~done, torch.zeros_like(done))
    # set_seed fixes the episodes through the wrapper
    again = DMControlWrapper(load("train", noise="paper", with_expert=True, **SMALL))
    again.set_seed(0)
    torch.manual_seed(0)
    assert torch.equal(again.rollout(20, break_when_any_done=False)["next", "pixels"], rollout["next", "pixels"])
    wrapped.close()
    again.close()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"split": "training"}, r"split must be one of \['test', 'train', 'val'\]"),
        ({"num_houses": 0}, r"num_houses must be an int in \[1, "),
        ({"demo_length": 0}, r"demo_length must be an int in \[1, 198\] \(steps\), got 0"),
        ({"demo_length": 199}, r"demo_length must be an int in \[1, 198\] \(steps\), got 199"),
        ({"image_size": 1.5}, "image_size must be a positive int"),
        ({"max_steps": True}, "max_steps must be a positive int"),
        ({"noise": "loud"}, r"noise must be one of \['locobot', 'none', 'paper'"),
        ({"house_seeds": []}, "house_seeds must be a non-empty sequence of non-negative ints"),
        ({"house_seeds": [1], "num_houses": 2}, "either house_seeds or num_houses"),
        ({"success_radius_m": 0.0}, r"success_radius_m must be > 0 \(metres\)"),
        ({"success_fraction": -0.1}, "success_fraction must be >= 0"),
        ({"seed": "zero"}, "random must be None, an int seed or a numpy RandomState"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        load(**kwargs)


@pytest.mark.parametrize("action", [3, -1, 1.0, np.array([0, 1]), "left"])
def test_bad_actions_are_refused(env, action):
    env.reset()
    allowed = r"action must be one integer in \[0, 2\] \(0 forward, 1 turn_left, 2 turn_right\)"
    with pytest.raises(ValueError, match=allowed):
        env.step(action)


def test_unknown_task_argument_is_a_type_error():
    with pytest.raises(TypeError, match="colour"):
        load(colour="red")


def test_before_step_without_an_episode_is_refused():
    task = PathFollowTask([0], demo_length=5)
    with pytest.raises(RuntimeError, match="call env.reset"):
        task.before_step(FORWARD, HousePhysics.from_house(build_house(0)))


def test_follow_rules_truncation_and_stop():
    rules = FollowRules(
        max_steps=3,
        success_radius_m=0.6,
        success_fraction=0.1,
        stop_action=True,
        progress_reward_per_m=1.0,
        success_reward=2.5,
        step_penalty=0.01,
    )
    common = dict(previous_distance_m=1.0, initial_distance_m=5.0, path_length_m=1.0, shortest_length_m=5.0)
    inside_no_stop = rules.score(action=FORWARD, distance_m=0.5, steps=1, **common)
    assert not inside_no_stop.done  # with STOP, arriving does not end the episode
    stopped = rules.score(
        action=np.array([STOP, STOP]), distance_m=np.array([0.5, 2.0]), steps=np.array([2, 2]), **common
    )
    assert stopped.terminated.tolist() == [True, True] and stopped.success.tolist() == [True, False]
    limit = rules.score(action=FORWARD, distance_m=0.5, steps=3, **common)
    assert bool(limit.truncated) and bool(limit.success)  # inside at the limit counts, as in PathFollowEnv


def test_step_limit_follows_the_route_length_as_in_path_follow_env():
    from envs.follow import default_max_steps

    assert load("train", seed=0, num_houses=1, demo_length=30).task.rules.max_steps == 50
    assert load("train", seed=0, num_houses=1, demo_length=12).task.rules.max_steps == default_max_steps(12)
