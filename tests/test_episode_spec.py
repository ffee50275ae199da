"""Tests for envs.episode_spec: the one description of episodes, its identity and flat form,
the configs that hold it, YAML keys (flat and nested), and the one env builder."""
from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from envs import DemoStore, DemoStoreConfig, EpisodeSpec, make_env
from envs.episode_spec import SIZE_FIELDS, check_sizes_match, flat_dict, from_flat, nest_flat_keys
from spf_rl.config import load_config
from spf_rl.data import DatasetConfig
from spf_rl.evaluation import EvalConfig, episode_identity
from spf_rl.train.bc import BCConfig
from spf_rl.train.collection import CollectionEnvConfig
from spf_rl.train.dagger import DAggerConfig
from spf_rl.train.dagger_rounds import RoundConfig


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(split="validation"), "split must be one of"),
        (dict(num_houses=0), "num_houses"),
        (dict(noise="loud"), "noise must be one of"),
        (dict(demo_length=0), r"demo_length must be an int in \[1, 198\]"),
        (dict(max_steps=0), "max_steps must be an int >= 1"),
        (dict(image_size=-64), "image_size must be an int >= 1"),
        (dict(task="fetch"), "task must be one of"),
        (dict(route_style="zigzag"), "zigzag"),
        (dict(route_lengths=(10, 20)), "route_lengths needs a route_style"),
        (dict(seed=-1), "seed must be an int >= 0"),
        (dict(seed=True), "seed must be an int >= 0"),
        (dict(house_seeds=()), "house_seeds must be None or a non-empty list"),
        (dict(house_seeds=(3,), num_houses=2), "house_seeds cannot be combined with num_houses"),
    ],
)
def test_bad_values_are_refused_naming_the_field(changes, match):
    with pytest.raises(ValueError, match=match):
        EpisodeSpec(**changes)


def test_one_spelling_of_routes_and_one_step_limit():
    spec = EpisodeSpec(demo_length=60, route_style="driven=1,tour=1", route_lengths=[10, 60], max_steps=None)
    assert (spec.route_style, spec.route_lengths) == ("tour=1.0,driven=1.0", (10, 60))  # the canonical order
    assert spec == EpisodeSpec(demo_length=60, route_style="driven=1.0,tour=1.0", route_lengths=(10, 60))
    assert spec.step_limit == 100 and spec.replace(max_steps=70).step_limit == 70
    assert hash(spec) == hash(EpisodeSpec(demo_length=60, route_style="driven=1.0,tour=1.0", route_lengths=(10, 60)))


def test_identity_writes_optional_fields_only_when_set():
    planner = EpisodeSpec().identity()
    assert not {"route_style", "route_lengths", "house_seeds"} & planner.keys()
    routes = EpisodeSpec(route_style="tour", house_seeds=[5, 7]).identity()
    assert routes["route_lengths"] == [30, 30] and routes["house_seeds"] == [5, 7]
    assert json.loads(json.dumps(routes)) == routes


def test_the_evaluation_identity_is_the_one_records_were_stored_with():
    """Stored per-episode records (Table 1's cache, run test records) are keyed by these flat
    fields: the episode description must not change them, or hours of evaluations are lost."""
    config = EvalConfig(EpisodeSpec(split="test", max_steps=50, seed=2), num_episodes=1000, store_root="data/episodes")
    assert episode_identity(config) == {
        "split": "test", "num_episodes": 1000, "noise": "paper", "seed": 2, "num_agents": 25, "demo_length": 30,
        "max_steps": 50, "image_size": 64, "num_houses": None, "render": True, "task": "follow",
    }


@pytest.mark.parametrize(
    "config",
    [
        EvalConfig(EpisodeSpec(split="val", route_style="driven", route_lengths=(10, 30), seed=4), num_episodes=7),
        DatasetConfig(EpisodeSpec(num_houses=3, task="homing"), num_episodes=5, random_action_prob=0.1),
        CollectionEnvConfig(EpisodeSpec(noise="locobot"), with_expert=False),
        RoundConfig(round_index=2, beta=0.5, num_episodes=4, episodes=EpisodeSpec(seed=9)),
    ],
    ids=["eval", "dataset", "collection", "round"],
)
def test_configs_round_trip_through_their_flat_form(config):
    flat = json.loads(json.dumps(flat_dict(config)))
    assert "episodes" not in flat and flat["split"] == config.episodes.split
    assert from_flat(type(config), flat) == config


def test_a_flat_form_misses_fields_from_the_config_s_own_default_episodes():
    assert from_flat(EvalConfig, {"num_episodes": 3}).episodes == EvalConfig().episodes
    assert from_flat(EvalConfig, {"noise": "none"}).episodes == EvalConfig().episodes.replace(noise="none")


def test_a_store_keeps_neither_noise_nor_a_step_limit_and_reads_its_old_meta():
    spec = EpisodeSpec(split="val", noise="locobot", max_steps=12, seed=5)
    store = DemoStoreConfig.of(spec, num_demos=3)
    assert store == DemoStoreConfig.of(spec.replace(noise="paper", max_steps=None), num_demos=3)
    old_meta = {"num_demos": 3, "split": "val", "num_houses": None, "demo_length": 30, "image_size": 64,
                "min_route_length_m": None, "seed": 0, "task": "follow", "grid_size_cells": None, "episodes_seed": 5,
                "route_style": None, "route_lengths": None}
    assert DemoStoreConfig.from_dict(old_meta) == store and store.episodes_seed == 5
    pool = DemoStoreConfig(EpisodeSpec(seed=5), num_demos=3)
    assert pool.episodes_seed is None and pool.to_dict()["seed"] == 5


def test_nested_and_flat_keys_are_the_same_config():
    flat = load_config(BCConfig, "bc", ["data.split=val", "test.noise=none", "data.num_episodes=10"])
    nested = load_config(BCConfig, "bc", ["data.episodes.split=val", "test.episodes.noise=none", "data.num_episodes=10"])
    assert flat == nested
    assert flat.data.episodes.split == "val" and flat.test.episodes.noise == "none" and flat.val.episodes.noise == "paper"
    assert nest_flat_keys({"data": {"seed": 3, "num_episodes": 4}}, BCConfig) == {"data": {"num_episodes": 4, "episodes": {"seed": 3}}}


def test_evaluations_follow_the_training_episodes_unless_set():
    config = load_config(BCConfig, "bc", ["data.demo_length=40", "data.route_style=tour", "val.max_steps=90"])
    for evaluation in (config.val, config.test):
        assert evaluation.episodes.demo_length == 40 and evaluation.episodes.route_style == "tour=1.0"
    assert config.val.episodes.max_steps == 90 and config.test.episodes.max_steps == 50
    assert config.val.episodes.split == "val" and config.test.episodes.split == "test"  # not sizes: their own
    dagger = load_config(DAggerConfig, "dagger", ["env.demo_length=20", "env.max_steps=null"])
    assert (dagger.test.episodes.demo_length, dagger.test.episodes.max_steps) == (20, None)
    assert set(SIZE_FIELDS) >= {"demo_length", "image_size"}


def test_a_policy_is_evaluated_on_episodes_of_its_sizes():
    with pytest.raises(ValueError, match=r"test.image_size=32 differs from data.image_size=64"):
        check_sizes_match(EpisodeSpec(), "data", val=EpisodeSpec(), test=EpisodeSpec(image_size=32))
    with pytest.raises(ValueError, match=r"val.demo_length=30 differs from data.demo_length=40"):
        BCConfig(data=DatasetConfig(EpisodeSpec(demo_length=40)))
    with pytest.raises(ValueError, match=r"invalid configuration: .*test.demo_length=20 differs"):
        load_config(BCConfig, "bc", ["test.demo_length=20"])


def test_make_env_builds_the_stack_from_the_description(tmp_path):
    spec = EpisodeSpec(split="val", num_houses=1, noise="none", demo_length=5, image_size=16, seed=3)
    env = make_env(spec, 2, with_expert=True, seeded=True)
    assert [type(t).__name__ for t in env.transform] == ["ActuationNoise", "InitTracker"]
    assert repr(env.transform[0]) == "ActuationNoise(noise='none')"
    assert (env.base_env.max_steps, env.base_env.image_size, env.base_env.split) == (spec.step_limit, 16, "val")
    first = env.reset()["episode_seed"].clone()
    assert torch.equal(make_env(spec, 2, seeded=True).reset()["episode_seed"], first)  # the spec's seed
    store = DemoStore.build(tmp_path / "store", DemoStoreConfig.of(spec, num_demos=2), progress=False)
    stored = make_env(spec, 2, demo_store=store, init_tracker=False, seeded=True)
    assert "demo_id" in stored.observation_spec.keys() and "demo_frames" not in stored.observation_spec.keys()
    assert torch.equal(stored.reset()["episode_seed"], first)  # the store's episodes are the spec's


def test_make_env_with_explicit_houses():
    env = make_env(EpisodeSpec(house_seeds=(7,), demo_length=5), 1, render=False)
    assert env.base_env.house_seeds == [7]
    assert dataclasses.replace(EpisodeSpec(), house_seeds=[7, 8]).house_seeds == (7, 8)
