"""The route expert (envs.route_expert): replays a route on it, returns to it off it, follows it under noise."""
from __future__ import annotations

import numpy as np
import pytest
from torchrl.envs import TransformedEnv

from envs.demos import move_agents, nominal_motion
from envs.episodes import run_episodes
from envs.expert import FORWARD, TURN_LEFT, GeodesicExpert
from envs.house_grid import default_grid_size_cells
from envs.nav_env import PathFollowEnv
from envs.path_fidelity import ndtw
from envs.route_expert import LOOKAHEAD_WAYPOINTS, RouteExpert
from envs.route_styles import sample_route
from envs.scenes import build_house, split_seeds
from envs.scripted import ExpertPolicy
from envs.transforms import ActuationNoise

STYLES = ("planner", "tour", "driven")
SUCCESS_RADIUS_M = 0.6


def drive(house, expert, start_pose: np.ndarray, steps: int) -> tuple[np.ndarray, list[int]]:
    """Noise-free poses and actions of ``expert`` driven for ``steps`` steps from ``start_pose``."""
    pose, poses, actions = np.array(start_pose, dtype=np.float64)[None], [np.array(start_pose, dtype=np.float64)], []
    for _ in range(steps):
        actions.append(expert.action(pose[0]))
        move_agents([house], pose, nominal_motion(np.array(actions[-1:])))
        poses.append(pose[0].copy())
    return np.array(poses), actions


@pytest.mark.parametrize("length", [10, 40, 100])
@pytest.mark.parametrize("style", STYLES)
def test_noise_free_it_replays_the_demonstration(style, length):
    seeds = split_seeds("train", 3, grid_size_cells=default_grid_size_cells(length))
    for i in range(3):
        house = build_house(seeds[i])
        demo = sample_route(style, house, np.random.default_rng(10 * i + length), length)
        expert = RouteExpert(house, demo)
        poses, actions = drive(house, expert, demo.start_pose, demo.length)
        # the demonstration's actions up to the last stretch, where it heads straight for the end
        moved = np.r_[True, np.any(np.diff(demo.poses[:, :2], axis=0) != 0, axis=1)]
        start_of_last_stretch = np.flatnonzero(moved)[max(0, expert.last_waypoint - LOOKAHEAD_WAYPOINTS - 1)]
        assert actions[:start_of_last_stretch] == demo.actions[:start_of_last_stretch].tolist()
        assert ndtw(poses[:, :2], demo.poses[:, :2], SUCCESS_RADIUS_M) > 0.8
        assert demo.end_field.at(poses[-1, :2]) <= SUCCESS_RADIUS_M


def test_a_route_over_the_same_place_twice_is_followed_in_its_order(unobstructed_route):
    # 5 steps out, round on the spot, 4 back: its end lies 0.3 m out, on the way out
    house, demo = unobstructed_route([FORWARD] * 5 + [TURN_LEFT] * 9 + [FORWARD] * 4)
    route_poses, route_actions = drive(house, RouteExpert(house, demo), demo.start_pose, demo.length)
    goal_poses, _ = drive(house, GeodesicExpert(house.occupancy, demo.end_field), demo.start_pose, demo.length)
    assert route_actions[:14] == demo.actions[:14].tolist()  # out past the end, and round
    assert np.hypot(*(route_poses[:, :2] - demo.start_pose[:2]).T).max() > 1.4
    assert np.hypot(*(goal_poses[:, :2] - demo.start_pose[:2]).T).max() < 0.7  # stops at the end


def test_pushed_off_the_route_it_returns_to_it_and_reaches_the_end():
    seeds = split_seeds("train")
    for i in range(4):
        house = build_house(seeds[i])
        demo = sample_route("driven", house, np.random.default_rng(i), 40)
        # a third of the way along, 0.4 m to one side and turned 60 degrees away
        x, y, heading = demo.poses[demo.length // 3]
        sides = [np.array([x, y]) + 0.4 * np.array([np.cos(heading + s), np.sin(heading + s)]) for s in (np.pi / 2, -np.pi / 2)]
        side = next((xy for xy in sides if house.occupancy.is_free(xy)), np.array([x, y]))
        expert = RouteExpert(house, demo)
        expert.action(demo.start_pose)  # it was on the route's start
        poses, _ = drive(house, expert, np.array([*side, heading + np.deg2rad(60)]), 2 * demo.length)
        assert expert.progress == expert.last_waypoint
        assert demo.end_field.at(poses[-1, :2]) <= SUCCESS_RADIUS_M


def test_the_same_pose_twice_gives_the_same_action_and_progress():
    house = build_house(split_seeds("train")[1])
    demo = sample_route("tour", house, np.random.default_rng(3), 30)
    expert = RouteExpert(house, demo)
    pose = demo.poses[0] + np.array([0.15, -0.1, 0.3])
    first = expert.action(pose), expert.progress, expert.matched
    assert (expert.action(pose), expert.progress, expert.matched) == first


def follow_records(expert: str, style: str, length: int) -> list[dict]:
    seeds = split_seeds("train", 4, grid_size_cells=default_grid_size_cells(length))
    demos = [sample_route(style, build_house(seeds[i % 4]), np.random.default_rng(100 + i), length) for i in range(8)]
    env = TransformedEnv(
        PathFollowEnv(house_seeds=seeds, demo_length=length, num_agents=len(demos), with_expert=True, expert=expert,
                      render=False, emit_demo_frames=False, demonstrations=demos),
        ActuationNoise("paper"),
    )
    env.set_seed(0)
    records = run_episodes(env, ExpertPolicy(), len(demos))
    env.close()
    return records


@pytest.mark.parametrize("style", ["tour", "driven"])
def test_under_paper_noise_it_follows_the_path_where_the_goal_expert_cuts_across(style):
    route, goal = follow_records("route", style, 80), follow_records("goal", style, 80)
    assert np.mean([r["success"] for r in route]) >= 7 / 8
    route_ratio = np.array([r["path_length_ratio"] for r in route])
    goal_ratio = np.array([r["path_length_ratio"] for r in goal])
    assert np.mean(route_ratio) > np.mean(goal_ratio) + 0.1, (route_ratio, goal_ratio)
    assert np.mean([r["ndtw"] for r in route]) > np.mean([r["ndtw"] for r in goal]) + 0.1


def test_the_env_picks_the_route_expert_for_routes_people_teach():
    assert PathFollowEnv(num_houses=1, demo_length=5, render=False).expert == "goal"
    assert PathFollowEnv(num_houses=1, demo_length=30, render=False, route_style="driven", route_lengths=(10, 30)).expert == "route"
    with pytest.raises(ValueError, match="expert must be one of 'goal', 'route' or None, got 'shortest'"):
        PathFollowEnv(num_houses=1, demo_length=5, render=False, expert="shortest")


def test_peeking_at_the_route_step_never_changes_the_actions():
    """The env labels route_step beside the action at every pose: that must not move the expert on."""
    rng = np.random.default_rng(0)
    seeds = split_seeds("train", 3, grid_size_cells=default_grid_size_cells(60))
    for i in range(12):
        house = build_house(seeds[i % 3])
        demo = sample_route(STYLES[i % 3], house, np.random.default_rng(i), 60)
        # poses near the route, in its order, as a noisy follower visits them (some twice)
        poses = np.repeat(demo.poses, rng.integers(1, 3, len(demo.poses)), axis=0)
        poses = poses + np.c_[rng.normal(0, 0.08, (len(poses), 2)), rng.normal(0, 0.1, len(poses))]
        quiet, labelling = RouteExpert(house, demo), RouteExpert(house, demo)
        steps = []
        for pose in poses:
            assert labelling.action(pose) == quiet.action(pose)
            steps.append(labelling.peek_route_step(pose))
            assert (labelling.progress, labelling.matched) == (quiet.progress, quiet.matched)
        assert 0 < max(steps) <= demo.length
