"""Larger houses for long routes (envs.house_grid), the max_steps rule, and n = 100 in the SPF modules."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from envs import DemoStore, DemoStoreConfig, PathFollowEnv
from envs.episode_spec import EpisodeSpec
from envs.follow import MAX_STEPS_PER_DEMO_STEP, default_max_steps
from envs.geodesic import count_components
from envs.house_grid import (
    DEFAULT_GRID_SIZE_CELLS,
    GRID_SEED_STRIDE,
    default_grid_size_cells,
    house_seed,
    split_house_seed,
)
from envs.house_mesh import MIN_FAR_CLIP_M, far_clip_m, house_mjcf
from envs.render import FirstPersonRenderer
from envs.scenes import MAX_HOUSES_PER_SPLIT, SPLIT_SEED_OFFSETS, build_house, split_seeds

BIG = house_seed(3, 25)


def test_seed_encodes_the_grid_and_default_seeds_are_unchanged():
    assert GRID_SEED_STRIDE > max(SPLIT_SEED_OFFSETS.values()) + MAX_HOUSES_PER_SPLIT
    assert split_seeds("test", 3) == [200000, 200001, 200002] == split_seeds("test", 3, DEFAULT_GRID_SIZE_CELLS)
    for seed in (0, 5, 200_017):
        assert house_seed(seed) == seed and split_house_seed(seed) == (seed, DEFAULT_GRID_SIZE_CELLS)
    for base, grid in ((0, 17), (200_017, 51), (GRID_SEED_STRIDE - 1, 99)):
        assert split_house_seed(house_seed(base, grid)) == (base, grid)
    assert split_seeds("val", 2, 25) == [house_seed(100_000, 25), house_seed(100_001, 25)]
    assert house_seed(99, 99) < 2**31  # labmaze's seed is an int32


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: house_seed(1, 16), r"grid_size_cells must be an odd int in \[15, 99\]"),
        (lambda: house_seed(1, 13), r"grid_size_cells must be an odd int in \[15, 99\]"),
        (lambda: house_seed(GRID_SEED_STRIDE, 25), "base_seed must be below"),
        (lambda: house_seed(-1), "base_seed must be a non-negative int"),
        (lambda: build_house(4 * GRID_SEED_STRIDE + 1), r"the grid part of house seed 40000001 \(seed // 10000000\)"),
        (lambda: build_house(-3), "seed must be a non-negative int"),
        (lambda: split_seeds("train", 2, 20), "grid_size_cells must be an odd int"),
    ],
)
def test_bad_grids_and_seeds_are_refused(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_larger_house_is_larger_and_still_one_house():
    small, big = build_house(3), build_house(BIG)
    assert big.seed == BIG and big.size_m == (25.0, 25.0) and big.walls.shape == (25, 25)
    assert len(np.unique(big.room_labels)) > len(np.unique(small.room_labels))
    assert count_components(big.graph.navigable) == 1
    assert build_house(BIG) is big  # cached by seed, like default houses


def test_larger_house_compiles_and_renders():
    big = build_house(BIG)
    xml, _ = house_mjcf(big)
    assert f'zfar="{far_clip_m(big)}"' in xml and far_clip_m(big) == MIN_FAR_CLIP_M
    assert far_clip_m(build_house(house_seed(3, 51))) == math.ceil(51 * math.sqrt(2))
    assert 'zfar="40"' in house_mjcf(build_house(3))[0]  # default houses keep their MJCF
    renderer = FirstPersonRenderer(32, 32)
    try:
        frame = renderer.render(big, np.array([*big.spawn_xy, 0.3]))
    finally:
        renderer.close()
    assert frame.shape == (32, 32, 3) and frame.std() > 5


def test_max_steps_rule():
    assert MAX_STEPS_PER_DEMO_STEP == pytest.approx(5 / 3)
    assert [default_max_steps(n) for n in (6, 30, 50, 100)] == [10, 50, 84, 167]
    assert PathFollowEnv(num_houses=1, render=False).max_steps == 50
    assert PathFollowEnv(num_houses=1, demo_length=6, render=False).max_steps == 10
    assert PathFollowEnv(num_houses=1, demo_length=6, max_steps=40, render=False).max_steps == 40


@pytest.mark.parametrize("length, grid", [(50, 25), (100, 51)])
def test_long_routes_are_sampled_in_large_houses(length, grid):
    assert default_grid_size_cells(length) == grid
    env = PathFollowEnv(num_houses=2, num_agents=2, demo_length=length, render=False, seed=3)
    td = env.reset()
    assert td["demo_actions"].shape == (2, length) and env.max_steps == default_max_steps(length)
    assert all(split_house_seed(house.seed)[1] == grid for house in env.houses)
    assert all(house.size_m == (grid, grid) for house in env.houses)
    again = PathFollowEnv(num_houses=2, num_agents=2, demo_length=length, render=False, seed=3).reset()
    assert torch.equal(td["episode_seed"], again["episode_seed"]) and torch.equal(td["demo_actions"], again["demo_actions"])


def test_grid_can_be_chosen_but_not_with_house_seeds():
    env = PathFollowEnv(num_houses=1, demo_length=6, grid_size_cells=17, render=False, seed=0)
    env.reset()
    assert env.houses[0].size_m == (17.0, 17.0) and env.house_seeds == [house_seed(0, 17)]
    with pytest.raises(ValueError, match="grid_size_cells cannot be combined with house_seeds"):
        PathFollowEnv(house_seeds=[0], grid_size_cells=17)
    with pytest.raises(ValueError, match="grid_size_cells must be an odd int"):
        PathFollowEnv(num_houses=1, grid_size_cells=14)


def test_demo_store_follows_the_grid_rule(tmp_path):
    config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=16), num_demos=2, grid_size_cells=17)
    assert config.house_seeds == [house_seed(0, 17)] and DemoStoreConfig(episodes=EpisodeSpec(demo_length=40)).grid == 21
    store = DemoStore.build(tmp_path / "store", config, progress=False)
    env = PathFollowEnv(num_houses=1, demo_length=5, image_size=16, grid_size_cells=17, demo_store=store, render=False)
    env.reset()
    assert env.houses[0].size_m == (17.0, 17.0)
    with pytest.raises(ValueError, match=r"grid_size_cells=15 \(store: 17\)"):
        PathFollowEnv(num_houses=1, demo_length=5, image_size=16, demo_store=store)
    with pytest.raises(ValueError, match="DemoStoreConfig.grid_size_cells must be an odd int"):
        DemoStoreConfig(grid_size_cells=12)


def test_spf_modules_take_100_step_demonstrations():
    """The memory and pointer take n = 100 with the weights of an n = 30 model (no n-sized parameter)."""
    from spf_rl.modules.registry import ModelConfig, build_policy, spf_config

    small = ModelConfig(feature_dim=16, hidden_size=16)
    config30 = spf_config(small, demo_length=30, image_size=32)
    policy30 = build_policy("spf", config30)
    policy100 = build_policy("spf", dataclasses.replace(config30, demo_length=100))
    policy100.load_state_dict(policy30.state_dict())
    assert policy100.memory_length == 80
    b, t = 2, 4
    frames = torch.randint(0, 255, (b, 100, 32, 32, 3), dtype=torch.uint8)
    steps = TensorDict(
        {
            "pixels": torch.randint(0, 255, (b, t, 32, 32, 3), dtype=torch.uint8),
            "demo_frames": frames.unsqueeze(1).expand(b, t, *frames.shape[1:]),
            "demo_actions": torch.randint(0, 3, (b, t, 100)),
            "is_init": torch.zeros(b, t, 1, dtype=torch.bool).index_fill_(1, torch.tensor([0]), True),
        },
        [b, t],
    )
    with set_recurrent_mode(True):
        out = policy100(steps.clone())
    assert out["logits"].shape == (b, t, 3) and torch.isfinite(out["logits"]).all()
    assert (out["eta_used"] >= 0).all() and (out["eta_used"] <= 99).all()
    # step mode from the primer's zero state gives the sequence's first step
    first = steps[:, 0].clone().update(policy100.make_tensordict_primer().primers.zero().expand(b))
    assert torch.allclose(policy100(first)["logits"], out["logits"][:, 0], atol=1e-5)
