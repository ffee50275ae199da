"""Demonstrations given by users (envs.user_demos) and the env playing them."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv

from envs import PathFollowEnv, RouteError, RouteRecorder, demonstration_from_actions, demonstration_from_waypoints
from envs.demos import drive_expert
from envs.expert import FORWARD, TURN_LEFT
from envs.follow import default_max_steps
from envs.playlist import DemonstrationPlaylist
from envs.scenes import build_house
from envs.scripted import OpenLoopReplay
from envs.transforms import ActuationNoise
from envs.user_demos import WAYPOINT_RADIUS_M, parse_actions

HOUSE = 0
#: In house 0 the corridor y in [1, 2] m is free from x = 7 to 12 m.
START = (7.5, 1.5, 0.0)
ROUTE = "FFFFFFFLLLLFFF"  # 7 forward along the corridor, turn to face back, 3 forward


def route_demo():
    return demonstration_from_actions(HOUSE, START, ROUTE)


def test_actions_drive_noise_free():
    demo = route_demo()
    assert demo.length == len(ROUTE) and demo.house_seed == HOUSE
    np.testing.assert_allclose(demo.poses[0], [7.5, 1.5, 0.0])
    np.testing.assert_allclose(demo.poses[7, :2], [7.5 + 7 * 0.3, 1.5], atol=1e-9)
    assert demo.actions[:7].tolist() == [FORWARD] * 7 and demo.actions[7] == TURN_LEFT
    assert demo.shortest_length_m > 0.6


def test_letters_and_ints_agree():
    assert parse_actions(ROUTE).tolist() == parse_actions(list(parse_actions(ROUTE))).tolist()
    with pytest.raises(RouteError, match=r"action 3 is 'X'.*F \(forward\)"):
        parse_actions("FFX")
    with pytest.raises(RouteError, match="action 2 is 5"):
        parse_actions([0, 5])


def test_step_into_wall_names_the_step():
    # facing -x from x = 7.5: the wall at x = 7 stops the second forward step
    with pytest.raises(RouteError, match=r"step 2 of 3 \(F, forward\) from \(7\.20, 1\.50\) heading 180 deg runs into a wall"):
        demonstration_from_actions(HOUSE, (7.5, 1.5, 180.0), "FFF")


def test_start_out_of_the_house_or_in_a_wall():
    with pytest.raises(RouteError, match=r"start \(16\.00, 1\.50\) is outside the house"):
        demonstration_from_actions(HOUSE, (16.0, 1.5, 0.0), "FFFF")
    with pytest.raises(RouteError, match=r"start \(7\.50, 0\.50\) is inside a wall or furniture"):
        demonstration_from_actions(HOUSE, (7.5, 0.5, 0.0), "FFFF")


def test_too_short():
    with pytest.raises(RouteError, match=r"too short: after its 3 step\(s\).*success radius 0\.60 m"):
        demonstration_from_actions(HOUSE, START, "FLR")
    with pytest.raises(RouteError, match="too short"):
        demonstration_from_actions(HOUSE, START, "")


def test_length_is_required_exactly():
    with pytest.raises(RouteError, match="has 14 steps; demonstrations must have exactly 30 steps"):
        demonstration_from_actions(HOUSE, START, ROUTE, length=30)
    assert demonstration_from_actions(HOUSE, START, ROUTE, length=len(ROUTE)).length == len(ROUTE)


def test_recorder_refuses_a_step_and_keeps_the_route():
    recorder = RouteRecorder(HOUSE, (7.5, 1.5, 180.0), max_steps=3)
    recorder.step(FORWARD)
    with pytest.raises(RouteError, match="step 2 .*runs into a wall"):
        recorder.step(FORWARD)
    assert recorder.length == 1
    recorder.step(TURN_LEFT)
    recorder.step(TURN_LEFT)
    with pytest.raises(RouteError, match="already has 3 steps"):
        recorder.step(TURN_LEFT)
    assert recorder.undo() and recorder.length == 2


def test_waypoints_follow_the_planner():
    house = build_house(HOUSE)
    demo = demonstration_from_waypoints(HOUSE, [(7.5, 1.5), (9.5, 1.5), (9.5, 3.5)])
    # the same legs, driven by hand with the planner
    pose = np.array([7.5, 1.5, 0.0])  # facing the second waypoint
    legs = []
    for goal in [(9.5, 1.5), (9.5, 3.5)]:
        poses, actions = drive_expert(house, house.graph.distance_field(np.array(goal)), pose, 100, WAYPOINT_RADIUS_M)
        legs.append(actions)
        pose = poses[-1]
    assert demo.actions.tolist() == np.concatenate(legs).tolist()
    np.testing.assert_allclose(demo.poses[-1], pose)
    assert np.hypot(*(demo.end_xy - (9.5, 3.5))) < 0.5


def test_waypoints_with_start_and_cropping():
    start = (7.5, 1.5, 90.0)
    demo = demonstration_from_waypoints(HOUSE, [(9.5, 3.5), (4.5, 3.5)], start=start, length=30)
    assert demo.length == 30 and demo.poses.shape == (31, 3)
    np.testing.assert_allclose(demo.poses[0], [7.5, 1.5, np.pi / 2])
    with pytest.raises(RouteError, match="planned route of .* steps; demonstrations must have exactly 30"):
        demonstration_from_waypoints(HOUSE, [(7.5, 1.5), (9.5, 1.5)], length=30)


def test_bad_waypoints():
    with pytest.raises(RouteError, match=r"waypoint 2 \(16\.00, 1\.50\) is outside the house"):
        demonstration_from_waypoints(HOUSE, [(7.5, 1.5), (16.0, 1.5)])
    with pytest.raises(RouteError, match=r"waypoint 3 \(10\.50, 2\.50\) is inside a wall"):
        demonstration_from_waypoints(HOUSE, [(7.5, 1.5), (9.5, 1.5), (10.5, 2.5)])
    with pytest.raises(RouteError, match="at least 2"):
        demonstration_from_waypoints(HOUSE, [(7.5, 1.5)])
    with pytest.raises(RouteError, match="too short"):
        demonstration_from_waypoints(HOUSE, [(7.5, 1.5), (7.8, 1.5)])


def replay(demo, seed, noise="paper", num_agents=None):
    """Play ``demo`` open loop under ``noise``; the followed poses."""
    env = TransformedEnv(
        PathFollowEnv(house_seeds=[HOUSE], demo_length=demo.length, num_agents=num_agents, render=False, demonstrations=[demo]),
        Compose(ActuationNoise(noise), InitTracker()),
    )
    env.set_seed(seed)
    rollout = env.rollout(demo.length, OpenLoopReplay(), break_when_any_done=False)
    return rollout["next", "pose"]


def test_env_plays_the_given_demonstration():
    demo = route_demo()
    poses = replay(demo, seed=0, noise="none")
    # the replay of the first steps, noise-free, is the demonstration itself (until success ends it)
    np.testing.assert_allclose(poses[:5].numpy(), demo.poses[1:6].astype(np.float32), atol=1e-5)


def test_replay_is_deterministic_in_the_seed():
    demo = route_demo()
    first, again, other = replay(demo, 3), replay(demo, 3), replay(demo, 4)
    assert torch.equal(first, again)
    assert not torch.equal(first, other)


def test_agents_repeat_one_demonstration_under_their_own_noise():
    demo = route_demo()
    poses = replay(demo, seed=1, num_agents=3)
    assert poses.shape[0] == 3
    assert not torch.equal(poses[0], poses[1])


def test_playlist_cycles_and_reset_overrides():
    demo_a = route_demo()
    demo_b = demonstration_from_actions(HOUSE, START, "FFFFFFFLLLLFFL")
    env = PathFollowEnv(house_seeds=[HOUSE], num_agents=2, demo_length=demo_a.length, render=False, demonstrations=[demo_a, demo_b])
    env.set_seed(0)
    td = env.reset()
    assert td["demo_actions"][0].tolist() == demo_a.actions.tolist()
    assert td["demo_actions"][1].tolist() == demo_b.actions.tolist()
    td = env.reset(demonstration=demo_b)
    assert td["demo_actions"][0].tolist() == demo_b.actions.tolist()
    assert env.demonstrations[0] is demo_b


def test_given_demonstrations_are_checked():
    demo = route_demo()
    with pytest.raises(ValueError, match=r"demonstrations\[0\] has 14 steps .*; this env plays demonstrations of 1 to demo_length=5"):
        PathFollowEnv(house_seeds=[HOUSE], demo_length=5, render=False, demonstrations=[demo])
    env = PathFollowEnv(house_seeds=[HOUSE], demo_length=5, render=False)
    with pytest.raises(ValueError, match="demonstration has 14 steps"):
        env.reset(demonstration=demo)
    with pytest.raises(ValueError, match="must be an envs.demos.Demonstration"):
        env.reset(demonstration="FFF")
    with pytest.raises(ValueError, match="cannot be combined with demo_store"):
        DemonstrationPlaylist([demo], demo_length=demo.length, num_agents=1, with_store=True)


def test_shorter_demonstrations_are_padded_and_played_at_their_own_length():
    demo = route_demo()  # 14 steps
    short, padded = (PathFollowEnv(house_seeds=[HOUSE], demo_length=n, demonstrations=[demo]) for n in (demo.length, 30))
    td_short, td = short.reset(), padded.reset()
    assert td["demo_steps"].item() == demo.length == td_short["demo_steps"].item()
    assert td["demo_frames"].shape[0] == 30 and torch.equal(td["demo_frames"][: demo.length], td_short["demo_frames"])
    assert not td["demo_frames"][demo.length :].any() and not td["demo_actions"][demo.length :].any()
    assert td["demo_actions"][: demo.length].tolist() == demo.actions.tolist()
    assert padded.observation_spec["demo_steps"].is_in(td["demo_steps"])
    for _ in range(default_max_steps(demo.length)):  # the limit is the demonstration's own: ceil(5/3 * 14) = 24
        td["action"] = torch.tensor(1)  # spinning: truncated at the limit
        td = padded.step(td)["next"]
    assert td["truncated"].item() and td["step_count"].item() == 24
