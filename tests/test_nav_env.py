"""Tests for envs.nav_env.PathFollowEnv: specs, determinism, protocol, bad input."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv, check_env_specs

from envs.expert import STOP, TURN_LEFT
from envs.nav_env import PathFollowEnv
from envs.scripted import ExpertPolicy
from envs.transforms import ActuationNoise
from envs.worker_processes import start_method

SMALL = dict(num_houses=2, demo_length=6, max_steps=10, image_size=32)


def test_specs_single_and_batched():
    env = PathFollowEnv(**SMALL)
    env.set_seed(0)
    check_env_specs(env)
    batched = PathFollowEnv(num_agents=3, with_expert=True, **SMALL)
    batched.set_seed(0)
    check_env_specs(batched)
    assert batched.batch_size == torch.Size([3])


def test_specs_serial_and_parallel():
    serial = SerialEnv(2, partial(PathFollowEnv, **SMALL))
    serial.set_seed(0)
    check_env_specs(serial)
    serial.close()
    parallel = ParallelEnv(2, partial(PathFollowEnv, **SMALL), mp_start_method=start_method())
    parallel.set_seed(0)
    check_env_specs(parallel)
    rollout = parallel.rollout(4, break_when_any_done=False)
    assert rollout["demo_frames"].shape == (2, 4, 6, 32, 32, 3)
    parallel.close(raise_if_closed=False)


def _rollout(seed, noise="paper", steps=12):
    env = TransformedEnv(PathFollowEnv(**SMALL), ActuationNoise(noise))
    env.set_seed(seed)
    torch.manual_seed(0)
    return env.rollout(steps, break_when_any_done=False)


def test_same_seed_same_episodes():
    a, b, c = _rollout(3), _rollout(3), _rollout(4)
    for key in ("pixels", "demo_frames", "demo_actions", "pose", "episode_seed"):
        assert torch.equal(a[key], b[key]), key
    assert torch.equal(a["next", "pose"], b["next", "pose"])
    assert not torch.equal(a["episode_seed"], c["episode_seed"])


def test_first_view_is_first_demo_frame_and_frames_are_not_blank():
    env = PathFollowEnv(**SMALL)
    env.set_seed(1)
    td = env.reset()
    assert torch.equal(td["pixels"], td["demo_frames"][0])
    assert td["demo_frames"].float().std() > 10


def test_random_actions_under_strongest_noise_stay_in_free_space():
    env = TransformedEnv(PathFollowEnv(num_houses=3, demo_length=6, max_steps=40, render=False, num_agents=8), ActuationNoise("paper_unclipped"))
    env.set_seed(0)
    rollout = env.rollout(120, break_when_any_done=False)
    poses = rollout["next", "pose"].reshape(-1, 3).numpy()
    seeds = rollout["episode_seed"].reshape(-1).numpy()
    base = env.base_env
    # re-derive each pose's house from its episode seed
    from envs.scenes import build_house

    for pose, seed in zip(poses, seeds):
        house = build_house(int(np.random.default_rng(int(seed)).choice(base.house_seeds)))
        assert house.occupancy.clearance(pose[:2]) >= house.occupancy.agent_radius_m
        assert 0 < pose[0] < house.size_m[0] and 0 < pose[1] < house.size_m[1]


def test_expert_episode_reports_success_and_spl():
    env = PathFollowEnv(with_expert=True, render=False, **{**SMALL, "max_steps": 30})
    env.set_seed(0)
    rollout = env.rollout(30, ExpertPolicy())
    final = rollout[-1]["next"]
    assert final["done"].item() and final["terminated"].item() and not final["truncated"].item()
    assert final["success"].item()
    shortest, travelled = final["shortest_path_length"].item(), final["path_length"].item()
    assert final["spl"].item() == pytest.approx(shortest / max(shortest, travelled), rel=1e-5)
    assert final["goal_distance"].item() <= max(0.6, 0.1 * shortest)
    assert rollout["next", "reward"].sum() > 0  # progress plus the success bonus
    assert not rollout["next", "success"][:-1].any()  # success is reported on the final step only


def test_truncation_and_failure():
    env = PathFollowEnv(render=False, **SMALL)
    env.set_seed(0)
    td = env.reset()
    for step in range(SMALL["max_steps"]):
        td["action"] = torch.tensor(TURN_LEFT)  # spinning never gets anywhere
        td = env.step(td)
        if step < SMALL["max_steps"] - 1:
            assert not td["next", "done"].item()
        td = td["next"]
    assert td["truncated"].item() and td["done"].item() and not td["terminated"].item()
    assert not td["success"].item() and td["spl"].item() == 0.0


def test_stop_action_ends_the_episode():
    env = PathFollowEnv(stop_action=True, render=False, **SMALL)
    env.set_seed(0)
    assert env.action_spec.space.n == 4
    td = env.reset()
    td["action"] = torch.tensor(STOP)
    out = env.step(td)["next"]
    assert out["terminated"].item() and not out["success"].item()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(split="validation"), "split must be one of"),
        (dict(demo_length=0), r"demo_length must be an int in \[1, 198\] \(steps\), got 0"),
        (dict(demo_length=1000), r"demo_length must be an int in \[1, 198\] \(steps\), got 1000"),  # refused at construction, not at reset()
        (dict(max_steps=-1), "max_steps must be a positive int"),
        (dict(image_size=0), "image_size must be a positive int"),
        (dict(num_agents=0), "num_agents must be a positive int"),
        (dict(num_houses=0), "num_houses"),
        (dict(house_seeds=[]), "house_seeds"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PathFollowEnv(**kwargs)


@pytest.mark.parametrize("action", [3, -1, 7])
def test_wrong_action_value_is_refused(action):
    env = PathFollowEnv(render=False, **SMALL)
    env.set_seed(0)
    td = env.reset()
    td["action"] = torch.tensor(action)
    with pytest.raises(ValueError, match="action must be an integer in"):
        env.step(td)


def test_collector_over_batched_env():
    env = TransformedEnv(PathFollowEnv(num_agents=2, **SMALL), ActuationNoise("paper"))
    env.set_seed(0)
    collector = Collector(env, None, frames_per_batch=20, total_frames=40)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2 and batches[0].batch_size == torch.Size([2, 10])
    assert batches[0]["pixels"].dtype == torch.uint8


def test_episode_numbers_fix_the_episodes_whatever_the_number_of_agents():
    """Agent i's k-th episode is number i + k * N; episode j is the same episode for any N."""
    seeds = {}
    for num_agents in (1, 2, 3):
        env = PathFollowEnv(num_houses=2, demo_length=5, max_steps=3, image_size=32, render=False, num_agents=num_agents)
        env.set_seed(7)
        td = env.reset()
        played = {}
        for _ in range(4):
            for index, seed in zip(td["episode_index"].reshape(-1).tolist(), td["episode_seed"].reshape(-1).tolist()):
                played[index] = seed
            td["_reset"] = torch.ones(num_agents, 1, dtype=torch.bool)
            td = env.reset(td)
        assert sorted(played)[: 4 * num_agents] == list(range(4 * num_agents))
        seeds[num_agents] = played
    for number in range(4):
        assert seeds[1][number] == seeds[2][number] == seeds[3][number]


def test_episode_records_name_the_house_each_episode_was_played_in():
    """``house_seed`` (env output and :func:`~envs.episodes.run_episodes` record) is the house the agent drove in."""
    from envs.episodes import run_episodes
    from envs.scripted import OpenLoopReplay
    from envs.specs import PRIVILEGED_KEYS

    assert "house_seed" in PRIVILEGED_KEYS
    env = PathFollowEnv("test", num_houses=6, demo_length=5, max_steps=4, image_size=32, render=False, num_agents=3)
    env.set_seed(3)
    td = env.reset()
    assert td["house_seed"].reshape(-1).tolist() == [house.seed for house in env.houses]
    td = env.rand_step(td)
    assert td["next", "house_seed"].reshape(-1).tolist() == [house.seed for house in env.houses]
    check_env_specs(env)

    played = {}  # episode number -> house of the agent that played it, read from the env itself
    original = env._start_episode

    def spy(index, *args):
        original(index, *args)
        played[int(env._episode_index[index])] = env.houses[index].seed

    env._start_episode = spy
    env.set_seed(3)
    records = run_episodes(env, OpenLoopReplay(), 12)
    assert [r["house_seed"] for r in records] == [played[r["episode_index"]] for r in records]
    assert len({r["house_seed"] for r in records}) > 1  # several houses, so the check can fail


def _play(env: PathFollowEnv, actions) -> TensorDictBase:
    """Reset ``env`` (unbatched) and take ``actions`` until the episode ends; the last ``"next"``."""
    td = env.reset()
    for action in actions:
        td["action"] = torch.tensor(int(action))
        td = env.step(td)["next"]
        if td["done"].item():
            break
    return td


def test_path_fidelity_of_a_replay_a_shortcut_and_a_wall():
    from envs.path_fidelity import path_fidelity
    from envs.user_demos import demonstration_from_waypoints

    demo = demonstration_from_waypoints(0, [(7.5, 1.5), (9.5, 1.5), (9.5, 3.5)])  # an L: along x, then up
    replay_env = PathFollowEnv(demonstrations=[demo], demo_length=demo.length, render=False)
    replay = _play(replay_env, demo.actions)
    steps = int(replay["step_count"].item())
    expected = path_fidelity(demo.poses[: steps + 1, :2], demo.poses[:, :2], True, replay_env.success_radius_m)
    assert replay["success"].item() and replay["wall_hits"].item() == 0
    for key, value in expected.items():  # the env scores the positions it drove through
        assert replay[key].item() == pytest.approx(value, rel=1e-5), key
    assert replay["ndtw"].item() > 0.9 and replay["path_length_ratio"].item() <= 1.0

    expert_env = PathFollowEnv(demonstrations=[demo], demo_length=demo.length, render=False, with_expert=True, expert="goal")
    td, final = expert_env.reset(), None
    while final is None or not final["done"].item():  # the goal expert heads for the end: it cuts the corner
        td["action"] = td["expert_action"]
        final = td = expert_env.step(td)["next"]
    assert final["success"].item() and final["path_length_ratio"].item() < 0.9 * replay["path_length_ratio"].item()
    assert final["ndtw"].item() < replay["ndtw"].item() - 0.2  # success, but not the route that was shown
    assert final["sdtw"].item() == pytest.approx(final["ndtw"].item())

    # turn to face the wall 0.3 m behind the start, then press forward: the first step fits, the others hit
    wall = _play(replay_env, [TURN_LEFT] * 9 + [0] * 4)
    assert wall["wall_hits"].item() == 3
    spin = _play(replay_env, [TURN_LEFT] * replay_env.max_steps)  # fails: no SDTW, and a path of length 0
    assert not spin["success"].item() and spin["sdtw"].item() == 0.0 and spin["path_length_ratio"].item() == 0.0
    assert 0.0 < spin["ndtw"].item() < 0.5
