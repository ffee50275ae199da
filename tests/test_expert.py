"""Tests for envs.expert and envs.demos: determinism and the expert's success rates."""
from __future__ import annotations

import numpy as np
import pytest
from torchrl.envs import TransformedEnv

from envs.demos import sample_demonstration
from envs.episodes import run_episodes
from envs.expert import FORWARD, TURN_LEFT, TURN_RIGHT, GeodesicExpert
from envs.nav_env import PathFollowEnv
from envs.scenes import build_house
from envs.scripted import ExpertPolicy, OpenLoopReplay
from envs.transforms import ActuationNoise

#: Episodes per rate: ``pytest --full-samples`` plays the full sample, by default a smaller one.
FULL_EPISODES = 500
SAMPLE_EPISODES = 150


def _rate(noise: str, policy, episodes: int, seed: int = 0) -> tuple[float, float]:
    env = TransformedEnv(PathFollowEnv("train", num_agents=50, with_expert=True, render=False, emit_demo_frames=False), ActuationNoise(noise))
    env.set_seed(seed)
    records = run_episodes(env, policy, episodes)
    return float(np.mean([r["success"] for r in records])), float(np.mean([r["spl"] for r in records]))


def test_demonstrations_are_deterministic():
    house = build_house(3)
    a = sample_demonstration(house, np.random.default_rng(11), 30)
    b = sample_demonstration(house, np.random.default_rng(11), 30)
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.actions, b.actions)
    assert a.shortest_length_m > 1.0
    with pytest.raises(ValueError, match="length must be a positive int"):
        sample_demonstration(house, np.random.default_rng(0), 0)


def test_expert_turns_towards_the_goal_and_moves_when_facing_it():
    house = build_house(0)
    start = house.spawn_xy
    field = house.graph.distance_field(start + np.array([0.0, 0.0]))
    # find a free position ~1 m from the goal in some direction, facing the goal
    for direction in ([1, 0], [-1, 0], [0, 1], [0, -1]):
        position = start + np.array(direction) * 1.0
        if house.occupancy.is_free(position) and field.at(position) < 1.2:
            break
    expert = GeodesicExpert(house.occupancy, field)
    towards = np.arctan2(*(start - position)[::-1])
    assert expert.action(np.array([*position, towards])) == FORWARD
    assert expert.action(np.array([*position, towards + np.pi / 2])) == TURN_RIGHT
    assert expert.action(np.array([*position, towards - np.pi / 2])) == TURN_LEFT


def test_expert_success_noise_free_and_under_paper_noise(full_samples):
    episodes = FULL_EPISODES if full_samples else SAMPLE_EPISODES
    noise_free, _ = _rate("none", ExpertPolicy(), episodes)
    paper, _ = _rate("paper", ExpertPolicy(), episodes)
    open_loop, _ = _rate("paper", OpenLoopReplay(), episodes)
    assert noise_free >= 0.99
    assert paper >= 0.95
    assert open_loop < paper - 0.2  # replaying the demo blindly fails clearly more often


def test_run_episodes_plays_the_same_numbered_episodes_whatever_the_number_of_agents():
    def play(num_agents: int) -> list[dict]:
        env = TransformedEnv(
            PathFollowEnv("train", num_houses=3, num_agents=num_agents, demo_length=6, max_steps=10, with_expert=True, render=False, emit_demo_frames=False),
            ActuationNoise("paper"),
        )
        env.set_seed(5)
        return run_episodes(env, OpenLoopReplay(), 9)

    two, four = play(2), play(4)
    assert [r["episode_index"] for r in two] == list(range(9))
    assert two == four  # same episodes, same outcomes, each counted once
    assert len({r["episode_seed"] for r in two}) == 9
