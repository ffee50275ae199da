"""Repeat conditions (envs.conditions): the agent's world changes, the demonstration never does."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from torchrl.envs import ParallelEnv, SerialEnv

from envs.conditions import (
    CONDITIONS,
    Condition,
    draw_repeat,
    house_variant,
    parse_conditions,
)
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec
from envs.factory import make_env as _make_env
from envs.follow import episode_for_seed
from envs.nav_env import PathFollowEnv
from envs.render import MAX_MODELS_PER_RENDERER, FirstPersonRenderer
from envs.scenes import build_house, split_seeds
from envs.worker_processes import start_method

SMALL = {"split": "test", "num_houses": 3, "demo_length": 12, "image_size": 24}
_OPEN: list = []


def make_env(*args, **kwargs):
    """:func:`envs.factory.make_env`, closed when the test ends (its GL context released before EGL goes)."""
    env = _make_env(*args, **kwargs)
    _OPEN.append(env)
    return env


@pytest.fixture(autouse=True)
def _close_envs():
    yield
    while _OPEN:
        _OPEN.pop().close(raise_if_closed=False)
CHANGED = ["light@0.5", "light@1", "paint@1", "camera@0.5", "camera@1", "sensor@0.5", "sensor@1"]


def _play(conditions=None, memory_mismatch=None, steps=4, agents=3, seed=5, **options):
    """Observations of a reset and ``steps`` forward steps under ``paper`` noise."""
    spec = EpisodeSpec(noise="paper", seed=seed, conditions=conditions, memory_mismatch=memory_mismatch, **SMALL)
    env = make_env(spec, agents, seeded=True, **options)
    td = env.reset()
    out = [td.clone()]
    for _ in range(steps):
        td = env.step(td.set("action", torch.zeros(agents, dtype=torch.int64)))["next"]
        out.append(td.clone())
    return out, env


@pytest.fixture(scope="module")
def teaching():
    return _play()[0]


def test_none_leaves_every_frame_and_value_as_it_was(teaching):
    played, env = _play("none")
    for ours, theirs in zip(played, teaching):
        for key in theirs.keys(include_nested=True, leaves_only=True):
            assert torch.equal(ours[key], theirs[key]), key
        assert (ours["condition"] == 0).all() and (ours["condition_strength"] == 0).all()
    assert "condition" in env.observation_spec.keys()


@pytest.mark.parametrize("conditions", CHANGED)
def test_a_condition_changes_the_agents_frames_and_never_the_demonstration(conditions, teaching):
    played, _ = _play(conditions)
    assert torch.equal(played[0]["demo_frames"], teaching[0]["demo_frames"])
    assert torch.equal(played[0]["demo_actions"], teaching[0]["demo_actions"])
    changed = [not torch.equal(ours["pixels"], theirs["pixels"]) for ours, theirs in zip(played, teaching)]
    assert all(changed), changed
    name, strength = conditions.split("@")
    assert (played[0]["condition"] == CONDITIONS.index(name)).all()
    assert torch.allclose(played[0]["condition_strength"], torch.full((3, 1), float(strength)))


def test_a_stronger_light_change_darkens_more(teaching):
    brightness = [played[0]["pixels"].float().mean() for played in (teaching, _play("light@0.5")[0], _play("light@1")[0])]
    assert brightness[0] > brightness[1] > brightness[2]


def test_paint_repaints_rooms_and_furniture_moves_pieces_in_a_variant_of_the_house():
    house = build_house(split_seeds("test")[0])
    painted = house_variant(house.seed, "paint", 1.0, 0)
    rooms = {str(x) for x in np.unique(house.room_labels)} - {"*", "."}
    assert set(painted.paint) == rooms and painted.furniture is house.furniture
    assert len(house_variant(house.seed, "paint", 0.5, 0).paint) == max(1, round(0.5 * len(rooms)))
    moved = house_variant(house.seed, "furniture", 1.0, 0)
    assert not np.array_equal(moved.occupancy.occupied, house.occupancy.occupied)
    assert moved.graph.components() == house.graph.components()  # nothing cut in two
    assert house.paint == {} and len(house.furniture) == len(build_house(house.seed).furniture)  # the house itself unchanged


def test_furniture_changes_keep_every_route_feasible_and_the_rules_use_the_changed_layout():
    spec = EpisodeSpec(split="test", demo_length=30, noise="none", seed=2, conditions="furniture@1")
    env = make_env(spec, 8, with_expert=True, render=False, seeded=True)
    successes, differing = [], 0
    for _ in range(3):
        td = env.reset()
        base = env.base_env
        for agent, (house, taught, demo) in enumerate(zip(base.houses, base.taught_houses, base.demonstrations)):
            assert house is not taught and house.seed == taught.seed
            start, end = demo.start_pose[:2], demo.end_xy
            assert house.occupancy.is_free(start) and house.occupancy.is_free(end)
            expected = house.graph.distance_field(end).at(start)
            assert np.isfinite(expected)
            assert float(td["goal_distance"][agent]) == pytest.approx(expected, abs=1e-5)
            differing += expected != taught.graph.distance_field(end).at(start)
        for _ in range(spec.step_limit):
            td = env.step(td.set("action", td["expert_action"]))["next"]
            if td["done"].all():
                break
        successes += td["success"].view(-1).tolist()
    # the goal expert, noise-free, in the changed layouts (a detour may outlast a short limit)
    assert np.mean(successes) >= 0.9
    assert differing > 0  # some changes lengthen or shorten the way


def test_the_route_expert_goes_around_a_piece_on_the_path_and_rejoins_it():
    spec = EpisodeSpec(split="test", demo_length=30, noise="none", seed=0, conditions="furniture@1", route_style="driven")
    env = make_env(spec, 16, with_expert=True, render=False, seeded=True)
    td = env.reset()
    for _ in range(spec.step_limit):
        td = env.step(td.set("action", td["expert_action"]))["next"]
        if td["done"].all():
            break
    assert td["success"].float().mean() >= 0.9
    assert td["ndtw"].mean() > 0.8  # still measured against the demonstrated path


def test_the_same_episode_seed_gives_the_same_change_in_any_layout():
    spec = EpisodeSpec(seed=9, conditions="light@1=1,camera@0.5=1,sensor@1=1,paint@0.5=1", **SMALL)
    batched = make_env(spec, 4, seeded=True).reset()
    serial = SerialEnv(2, lambda: make_env(spec, 2, seeded=False))
    _OPEN.append(serial)
    serial.set_seed(9)
    # agent i's k-th episode is number i + 4k in the batched env: play the same numbers one at a time
    single = make_env(spec, None, episode_stride=4, seeded=True)
    first = single.reset()
    assert first["episode_seed"].item() == batched["episode_seed"][0].item()
    assert first["condition"].item() == batched["condition"][0].item()
    assert torch.equal(first["pixels"], batched["pixels"][0])
    assert serial.reset()["condition"].shape == (2, 2, 1)
    # the change is a function of the episode alone
    for agent in range(4):
        house, demo = episode_for_seed(int(batched["episode_seed"][agent]), split_seeds("test", 3), 12, 0.6)
        repeat = draw_repeat(parse_conditions(spec.conditions), house, demo, int(batched["episode_seed"][agent]))
        assert repeat.condition.index == int(batched["condition"][agent])


@pytest.mark.parametrize("exposure, blur_px", [(1.5, 1.0), (0.75, 0.5), (1.25, 0.25)])
def test_the_sensors_exposure_and_blur_are_a_gaussian_filter_of_the_scaled_frame(exposure, blur_px):
    from scipy.ndimage import gaussian_filter

    from envs.conditions import BLUR_TRUNCATE, SensorChange

    frames = np.random.default_rng(0).integers(0, 256, (2, 20, 24, 3), dtype=np.uint8)
    changed = frames.copy()
    SensorChange(exposure, blur_px, noise=0.0).apply(changed, np.zeros(4 * 20 * 24 * 3, np.float32), np.random.default_rng(1))
    scaled = frames.astype(np.float32) * np.float32(exposure)
    expected = np.clip(np.rint(gaussian_filter(scaled, sigma=(0, blur_px, blur_px, 0), mode="nearest", truncate=BLUR_TRUNCATE)), 0, 255)
    assert np.abs(changed.astype(int) - expected.astype(int)).max() <= 1
    assert (changed != expected).mean() < 0.001


def test_the_sensors_noise_is_new_every_frame_with_the_drawn_spread_and_the_same_for_the_same_seed():
    from envs.conditions import SensorChange

    sensor = SensorChange(exposure=1.0, blur_px=1e-3, noise=8.0)
    grey = np.full((6, 32, 32, 3), 128, dtype=np.uint8)

    def sensed(seed):
        frames, rng = grey.copy(), np.random.default_rng(seed)
        sensor.apply(frames, sensor.noise_bank(grey.shape[1:], rng), rng)
        return frames.astype(float) - 128

    noise = sensed(4)
    assert np.array_equal(noise, sensed(4)) and not np.array_equal(noise, sensed(5))
    assert abs(noise.std() - 8.0) < 0.3 and abs(noise.mean()) < 0.3
    assert all(not np.array_equal(noise[i], noise[i + 1]) for i in range(5))
    assert abs(np.corrcoef(noise[0, :, :-1].ravel(), noise[0, :, 1:].ravel())[0, 1]) < 0.05  # neighbours independent


def test_conditions_work_through_a_parallel_env():
    spec = EpisodeSpec(seed=3, conditions="sensor@1", **SMALL)
    env = ParallelEnv(2, make_env_factory(spec), mp_start_method=start_method())
    try:
        env.set_seed(3)
        td = env.rollout(3)
        assert (td["condition"] == CONDITIONS.index("sensor")).all()
        assert set(env.observation_spec.keys()) >= {"condition", "condition_strength"}
    finally:
        env.close()


def make_env_factory(spec):
    from functools import partial

    return partial(_make_env, spec, None)


def test_a_mismatched_memory_shows_another_routes_frames_with_the_episodes_own_actions(teaching):
    played, _ = _play(memory_mismatch=1.0)
    assert played[0]["memory_mismatched"].all()
    assert torch.equal(played[0]["demo_actions"], teaching[0]["demo_actions"])
    for agent in range(3):
        assert not torch.equal(played[0]["demo_frames"][agent], teaching[0]["demo_frames"][agent])
    for ours, theirs in zip(played, teaching):  # the agent's own world is unchanged
        assert torch.equal(ours["pixels"], theirs["pixels"]) and torch.equal(ours["pose"], theirs["pose"])
    half, _ = _play(memory_mismatch=0.5, agents=8, seed=1)
    assert 0 < half[0]["memory_mismatched"].sum() < 8


def test_a_demo_store_serves_the_teaching_world_and_the_mismatched_frames(tmp_path):
    spec = EpisodeSpec(seed=4, conditions="camera@1", memory_mismatch=1.0, **SMALL)
    config = DemoStoreConfig.of(spec, 6)
    assert config.episodes.conditions is None and config.episodes.memory_mismatch is None  # a store is taught once
    store = DemoStore.build(tmp_path / "store", config, progress=False)
    env = make_env(spec, 3, demo_store=store, seeded=True, static_seed=True)
    td = env.reset()
    ids, shown = td["demo_id"].view(-1), td["memory_id"].view(-1)
    assert (ids != shown).all()
    assert torch.equal(td["demo_actions"], store.actions[ids])
    # the agent starts on its own route's first pose, seen through the changed camera
    plain = make_env(spec.replace(conditions=None, memory_mismatch=None), 3, demo_store=store, seeded=True, static_seed=True).reset()
    assert torch.equal(plain["pixels"], store.frames[ids, 0])
    assert not torch.equal(td["pixels"], plain["pixels"])
    framed = make_env(spec, 3, demo_store=store, seeded=True, static_seed=True, emit_demo_frames=True).reset()
    assert torch.equal(framed["demo_frames"], store.frames[shown])


def test_a_renderer_keeps_a_bounded_number_of_models_and_never_draws_a_stale_one():
    renderer = FirstPersonRenderer(16, 16)
    try:
        house = build_house(0)
        pose = np.array([*house.spawn_xy, 0.0])
        first = renderer.render(house, pose)
        for k in range(MAX_MODELS_PER_RENDERER + 2):
            renderer.render(house_variant(0, "paint", 1.0, k), pose)
        assert renderer.models_held() == MAX_MODELS_PER_RENDERER
        assert np.array_equal(renderer.render(house, pose), first)
    finally:
        renderer.close()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("fog@0.5", "unknown condition 'fog'; allowed names are none, light, paint, furniture, camera, sensor"),
        ("light@1.5", "the strength of 'light' must be a number in [0, 1], got 1.5"),
        ("light@0.5=-1", "the weight of 'light@0.5' must be a finite number >= 0, got -1.0"),
        ("light", "'light' needs a strength in [0, 1]"),
    ],
)
def test_bad_conditions_get_one_clear_error_before_any_work(value, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        EpisodeSpec(conditions=value)
    with pytest.raises(ValueError, match="conditions"):
        PathFollowEnv(conditions=value, render=False)


def test_bad_mismatch_fractions_are_refused():
    with pytest.raises(ValueError, match=r"memory_mismatch must be a number in \[0, 1\], got 2"):
        EpisodeSpec(memory_mismatch=2)


def test_a_mixture_has_one_spelling_and_enters_the_episodes_identity():
    spec = EpisodeSpec(conditions="light@.5=1, none")
    assert spec.conditions == "light@0.5=1.0,none=1.0"
    assert spec.identity()["conditions"] == spec.conditions
    assert "conditions" not in EpisodeSpec().identity()  # earlier records keep their identity
    assert parse_conditions(spec.conditions).probabilities[Condition("none")] == 0.5



def test_a_dataset_keeps_the_frames_a_mismatched_episode_was_shown_and_its_own_actions(tmp_path):
    from spf_rl.data import DatasetConfig, EpisodeDataset

    spec = EpisodeSpec(split="test", num_houses=2, demo_length=8, max_steps=10, image_size=16, seed=1,
                       conditions="light@1", memory_mismatch=0.5)
    config = DatasetConfig(episodes=spec, num_episodes=8, chunk_size=8, num_agents=4)
    assert "light1.0x1.0-mismatch0.5" in config.default_dir().name
    dataset = EpisodeDataset.build(tmp_path / "data", config, num_workers=1, progress=False)
    episodes = dataset.episodes
    mismatched = episodes["memory_id"] != episodes["demo_id"]
    assert 0 < int(mismatched.sum()) < 8
    batch = dataset[list(range(8))]
    demos = dataset.demos
    assert torch.equal(batch["demo_frames"], demos.frames[episodes["memory_id"]])
    assert torch.equal(batch["demo_actions"], demos.actions[episodes["demo_id"]])
    # training rows say which episodes were mismatched, in the layout of rows of sources without any
    assert torch.equal(batch["memory_mismatched"], mismatched) and "memory_id" not in batch.keys()
    plain = EpisodeDataset.build(tmp_path / "plain", DatasetConfig(episodes=spec.replace(conditions=None, memory_mismatch=None),
                                                                    num_episodes=4, chunk_size=4, num_agents=4), num_workers=1, progress=False)
    rows = plain[[0, 1]]
    assert not rows["memory_mismatched"].any() and set(rows.keys()) == set(batch.keys())
    assert torch.cat([rows, batch[:2]], 0).batch_size == (4,)


def test_a_store_with_one_demonstration_cannot_show_another_route(tmp_path):
    store = DemoStore.build(tmp_path / "one", DemoStoreConfig.of(EpisodeSpec(**SMALL), 1), progress=False)
    with pytest.raises(ValueError, match="memory_mismatch=1.0 needs a demo_store of at least 2 demonstrations"):
        PathFollowEnv(demo_store=store, memory_mismatch=1.0, emit_demo_frames=False, **{k: v for k, v in SMALL.items()})


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install '.[distributed]')")
def test_ray_actors_play_the_same_changed_episodes_as_a_local_collector(tmp_path, ray_cluster):
    from envs.episodes import gather_episode_steps
    from spf_rl.evaluation import FramesFromStore
    from spf_rl.modules import SPFConfig, make_spf_policy
    from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, make_collector
    from spf_rl.train.dagger import ExpertMixturePolicy

    spec = EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32, seed=2, conditions="camera@1=1,sensor@1=1",
                       memory_mismatch=0.5)
    env_config = CollectionEnvConfig(episodes=spec)
    store = DemoStore.build(tmp_path / "store", DemoStoreConfig.of(spec, 6), progress=False)
    policy = make_spf_policy(SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32))).eval()
    behaviour = ExpertMixturePolicy(FramesFromStore(policy, store, spec.frames_id_key), beta=0.0)

    def play(config):
        collector = make_collector(behaviour, env_config, config, frames_per_batch=config.total_agents * 5, seed=2, demo_store=store.root)
        try:
            with torch.no_grad():
                return gather_episode_steps(collector, 0, 6, ("pixels", "action", "condition"), 6, ("demo_id", "episode_seed", "memory_id"))
        finally:
            collector.shutdown()

    local = play(CollectorConfig(num_agents=2))
    remote = play(CollectorConfig(backend="ray", num_collectors=2, num_agents=2))
    for key in ("pixels", "action", "condition"):
        assert torch.equal(local["steps", key], remote["steps", key]), key
    assert torch.equal(local["memory_id"], remote["memory_id"]) and (local["memory_id"] != local["demo_id"]).any()
