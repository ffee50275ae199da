"""Homing (envs.homing): the route driven back, its frames looking backwards, the env's homing task."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import DemoStore, DemoStoreConfig, PathFollowEnv, demonstration_from_actions, make_path_follow_env
from envs.demos import apply_motion, nominal_motion
from envs.episode_spec import EpisodeSpec
from envs.episodes import run_episodes
from envs.expert import FORWARD, FORWARD_STEP_M, TURN_ANGLE_DEG, TURN_LEFT, TURN_RIGHT
from envs.homing import HOMING, check_task, homing_demonstration, reversed_poses
from envs.render import FirstPersonRenderer
from envs.scenes import build_house
from envs.scripted import ExpertPolicy

#: A route in house 0 (the corridor y in [1, 2] m is free from x = 7 to 12 m).
START = (7.5, 1.5, 0.0)
ROUTE = "FFFFFFFLLFRRF"
#: Forward steps of the homing demonstration land within this of the earlier pose
#: (the collision model's sliding; 0.18 m at most over 300 sampled routes).
SLIDE_TOLERANCE_M = 0.2
SMALL = dict(num_houses=2, demo_length=8, image_size=32)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


def test_homing_demonstration_reverses_the_route():
    route = demonstration_from_actions(0, START, ROUTE)
    back = homing_demonstration(route)
    assert back.task == HOMING and back.length == route.length and back.house_seed == route.house_seed
    np.testing.assert_allclose(back.poses[:, :2], route.poses[::-1, :2])
    np.testing.assert_allclose(angle_between(back.poses[:, 2], route.poses[::-1, 2] + np.pi), 0.0, atol=1e-12)
    assert (back.poses[:, 2] >= -np.pi).all() and (back.poses[:, 2] < np.pi).all()
    swap = {FORWARD: FORWARD, TURN_LEFT: TURN_RIGHT, TURN_RIGHT: TURN_LEFT}
    assert back.actions.tolist() == [swap[a] for a in route.actions[::-1].tolist()]
    np.testing.assert_allclose(back.end_xy, route.start_pose[:2])
    assert back.end_field.at(route.start_pose[:2]) < 0.1
    assert back.shortest_length_m == pytest.approx(route.shortest_length_m, abs=0.1)
    with pytest.raises(ValueError, match="already a 'homing' demonstration"):
        homing_demonstration(back)


@pytest.mark.parametrize("episode_seed", range(6))
def test_homing_actions_match_the_frames_poses(episode_seed):
    """Each action takes one rendered pose to the next: turns exactly, forward steps up to sliding."""
    env = PathFollowEnv(task="homing", num_houses=3, demo_length=30, render=False, seed=episode_seed)
    env.reset()
    back, house = env.demonstrations[0], env.houses[0]
    moved, _ = apply_motion(house, back.poses[:-1], nominal_motion(back.actions))
    turn = angle_between(back.poses[1:, 2], back.poses[:-1, 2])
    expected = np.where(back.actions == TURN_LEFT, 1, np.where(back.actions == TURN_RIGHT, -1, 0)) * np.deg2rad(TURN_ANGLE_DEG)
    np.testing.assert_allclose(turn, expected, atol=1e-9)
    np.testing.assert_allclose(angle_between(moved[:, 2], back.poses[1:, 2]), 0.0, atol=1e-9)
    gaps = np.hypot(*(moved[:, :2] - back.poses[1:, :2]).T)
    assert (gaps <= SLIDE_TOLERANCE_M).all()
    steps = np.hypot(*np.diff(back.poses[:, :2], axis=0).T)
    assert (steps[back.actions != FORWARD] < 1e-12).all() and (steps <= FORWARD_STEP_M + 1e-9).all()


def test_homing_episode_plays_the_follow_route_back():
    follow = PathFollowEnv(**SMALL, seed=4)
    homing = PathFollowEnv(**SMALL, task="homing", seed=4)
    td_follow, td_homing = follow.reset(), homing.reset()
    route, back = follow.demonstrations[0], homing.demonstrations[0]
    assert torch.equal(td_follow["episode_seed"], td_homing["episode_seed"])
    np.testing.assert_allclose(back.poses, reversed_poses(route.poses))
    # the agent starts at the route's end facing back along it, and must reach the route's start
    np.testing.assert_allclose(td_homing["pose"].numpy(), back.poses[0].astype(np.float32))
    np.testing.assert_allclose(back.poses[0, :2], route.poses[-1, :2])
    assert td_homing["goal_distance"].item() == pytest.approx(back.end_field.at(route.poses[-1, :2]), abs=1e-4)
    assert td_homing["demo_actions"].tolist() == back.actions.tolist()
    # the memory looks back along the route: frames rendered at the reversed poses, not the recorded frames reversed
    renderer = FirstPersonRenderer(32, 32)
    try:
        expected = renderer.render_many([homing.houses[0]] * 8, back.poses[:8])
    finally:
        renderer.close()
    assert np.array_equal(td_homing["demo_frames"].numpy(), expected)
    assert np.array_equal(td_homing["pixels"].numpy(), expected[0])
    flipped = td_follow["demo_frames"].numpy()[::-1]
    assert not np.array_equal(td_homing["demo_frames"].numpy(), flipped)
    assert np.abs(td_homing["demo_frames"].numpy().astype(int) - flipped).mean() > 5
    follow.close()
    homing.close()


def test_expert_brings_homing_episodes_home_under_paper_noise():
    env = make_path_follow_env("paper", task="homing", num_houses=4, num_agents=8, render=False, with_expert=True)
    env.set_seed(0)
    records = run_episodes(env, ExpertPolicy(), 16)
    assert all(r["success"] for r in records)
    assert np.mean([r["spl"] for r in records]) > 0.9


def test_same_seed_same_homing_episodes():
    def play():
        env = make_path_follow_env(
            "paper", task="homing", num_houses=2, num_agents=2, demo_length=6, render=False, with_expert=True
        )
        env.set_seed(11)
        return env.rollout(12, ExpertPolicy(), break_when_any_done=False)

    first, second = play(), play()
    for key in ("pose", "demo_actions", "episode_seed", "goal_distance"):
        assert torch.equal(first[key], second[key]), key


def test_given_routes_play_their_homing_episode():
    route = demonstration_from_actions(0, START, ROUTE)
    env = PathFollowEnv(house_seeds=[0], demo_length=route.length, task="homing", render=False, demonstrations=[route])
    td = env.reset()
    back = env.demonstrations[0]
    assert back.task == HOMING and td["demo_actions"].tolist() == homing_demonstration(route).actions.tolist()
    np.testing.assert_allclose(back.end_xy, route.start_pose[:2])
    td = env.reset(demonstration=route)
    np.testing.assert_allclose(td["pose"].numpy(), homing_demonstration(route).start_pose.astype(np.float32))
    with pytest.raises(ValueError, match="a task='homing' env plays the homing episode of a route"):
        env.reset(demonstration=back)
    # a follow env may follow a homing demonstration: it is a route like any other
    follower = PathFollowEnv(house_seeds=[0], demo_length=route.length, render=False)
    assert follower.reset(demonstration=back)["demo_actions"].tolist() == back.actions.tolist()


def test_demo_store_holds_homing_demonstrations(tmp_path):
    common = dict(num_demos=2, num_houses=1, demo_length=5, image_size=16)
    follow = DemoStore.build(tmp_path / "follow", DemoStoreConfig.from_dict(common), progress=False)
    homing = DemoStore.build(tmp_path / "homing", DemoStoreConfig.from_dict({**common, "task": "homing"}), progress=False)
    for k in range(2):
        np.testing.assert_allclose(homing.poses[k].numpy(), reversed_poses(follow.poses[k].numpy()))
        assert homing.demonstration(k).task == HOMING
        assert not torch.equal(homing.frames[k], follow.frames[k].flip(0))
    env = PathFollowEnv(num_houses=1, demo_length=5, image_size=16, task="homing", demo_store=homing, seed=0)
    td = env.reset()
    assert torch.equal(td["demo_frames"], homing.frames[td["demo_id"].item()])
    assert env.demonstrations[0].task == HOMING
    with pytest.raises(ValueError, match=r"task='follow' \(store: 'homing'\)"):
        PathFollowEnv(num_houses=1, demo_length=5, image_size=16, demo_store=homing)
    with pytest.raises(ValueError, match="task must be one of"):
        DemoStoreConfig(episodes=EpisodeSpec(task="return"))


def test_unknown_task_is_refused():
    with pytest.raises(ValueError, match=r"task must be one of 'follow' \(reach the route's end\), 'homing'"):
        PathFollowEnv(num_houses=1, task="back")
    assert check_task("follow") == "follow"
    assert build_house(0).seed == 0
