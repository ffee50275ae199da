"""Sampled routes of a style (envs.route_styles) in the env and in demo stores: lengths padded, played at their own."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec
from envs.follow import default_max_steps, episode_for_seed
from envs.nav_env import PathFollowEnv
from envs.route_styles import RouteMixture

SMALL = {"split": "train", "num_houses": 3, "image_size": 16, "render": False}


def test_env_samples_the_routes_of_its_style_at_lengths_in_range():
    env = PathFollowEnv(route_style="driven=0.5,tour=0.5", route_lengths=(10, 30), demo_length=30, num_agents=6, **SMALL)
    env.set_seed(3)
    td = env.reset()
    steps = td["demo_steps"].squeeze(-1)
    assert ((steps >= 10) & (steps <= 30)).all() and len(set(steps.tolist())) > 1
    mixture = RouteMixture({"driven": 0.5, "tour": 0.5}, 10, 30)
    for agent, demo in enumerate(env.demonstrations):
        # the route is the mixture's draw from the episode seed, as episode_for_seed makes it
        _, expected = episode_for_seed(int(td["episode_seed"][agent]), env.house_seeds, 30, 0.0, route_style=mixture)
        assert np.array_equal(demo.actions, expected.actions) and demo.length == steps[agent]
        assert td["demo_actions"][agent, : demo.length].tolist() == demo.actions.tolist()
        assert not td["demo_actions"][agent, demo.length :].any()
    again = PathFollowEnv(route_style={"tour": 0.5, "driven": 0.5}, route_lengths=(10, 30), demo_length=30, num_agents=6, **SMALL)
    again.set_seed(3)
    assert again.reset()["demo_actions"].tolist() == td["demo_actions"].tolist()  # same seed, same episodes


def test_each_route_gets_its_own_episode_limit():
    env = PathFollowEnv(route_style="planner", route_lengths=(10, 12), demo_length=30, num_agents=4, **SMALL)
    env.set_seed(0)
    td = env.reset()
    limits = [default_max_steps(int(n)) for n in td["demo_steps"].squeeze(-1)]
    td["action"] = td["demo_actions"][:, 0] * 0 + 1  # spin until truncated
    ended = {}
    for step in range(1, max(limits) + 1):
        td = env.step(td)["next"]
        for agent in np.flatnonzero(td["truncated"].squeeze(-1).numpy()):
            ended.setdefault(int(agent), step)
        td["action"] = td["demo_actions"][:, 0] * 0 + 1
    assert [ended[agent] for agent in range(4)] == limits


def test_a_demo_store_of_a_route_style_pads_its_routes(tmp_path):
    config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=2, demo_length=20, image_size=16, route_style="driven", route_lengths=[10, 20]), num_demos=4)
    assert config.episodes.route_style == "driven=1.0" and config.episodes.route_lengths == (10, 20)  # one spelling
    store = DemoStore.build(tmp_path / "store", config, progress=False)
    steps = store.steps
    assert ((steps >= 10) & (steps <= 20)).all()
    for demo_id, n in enumerate(steps.tolist()):
        demo = store.demonstration(demo_id)
        assert demo.length == n and demo.poses.shape == (n + 1, 3)
        assert not store.frames[demo_id, n:].any() and store.frames[demo_id, :n].any()
    env = PathFollowEnv("train", num_houses=2, demo_length=20, image_size=16, demo_store=store, route_style="driven", route_lengths=(10, 20))
    env.set_seed(0)
    td = env.reset()
    assert td["demo_steps"].item() == steps[td["demo_id"].item()].item()
    with pytest.raises(ValueError, match=r"route_style=None \(store: 'driven=1.0' of 10-20 steps\)"):
        PathFollowEnv("train", num_houses=2, demo_length=20, image_size=16, demo_store=store)


def test_the_route_expert_labels_the_agents_place_on_its_route():
    env = PathFollowEnv(route_style="driven=1,tour=1", route_lengths=(10, 20), demo_length=20, num_agents=3,
                        with_expert=True, **SMALL)
    assert "route_step" in env.observation_spec.keys() and env.observation_spec["route_step"].shape == (3, 1)
    env.set_seed(1)
    td = env.reset()
    lengths = td["demo_steps"].squeeze(-1).clone()
    places = [[int(td["route_step"][agent])] for agent in range(3)]
    ended = torch.zeros(3, dtype=torch.bool)
    while not ended.all():  # noise-free, the expert replays each route: its place is step t at step t
        td["action"] = td["expert_action"]
        td = env.step(td)["next"]
        for agent in np.flatnonzero((~ended).numpy()):
            if td["done"][agent]:
                ended[agent] = True
            else:
                places[agent].append(int(td["route_step"][agent]))
    for agent, n in enumerate(lengths.tolist()):
        assert places[agent] == list(range(len(places[agent]))) and len(places[agent]) <= n
    assert "route_step" not in PathFollowEnv(demo_length=20, with_expert=True, **SMALL).observation_spec.keys()  # goal expert


def test_labelling_the_route_step_never_changes_the_experts_actions():
    from torchrl.envs import TransformedEnv

    from envs.route_expert import RouteExpert
    from envs.transforms import ActuationNoise

    env = TransformedEnv(PathFollowEnv(route_style="driven=1,tour=1,planner=1", route_lengths=(10, 30), demo_length=30,
                                       num_agents=4, with_expert=True, **SMALL), ActuationNoise("paper"))
    env.set_seed(5)
    td = env.reset()
    base = env.base_env
    experts = [RouteExpert(base.houses[i], demo) for i, demo in enumerate(base.demonstrations)]  # never asked for labels
    for _ in range(20):  # under noise, poses that match the route again and again
        live = ~td["done"].squeeze(-1) if "done" in td.keys() else torch.ones(4, dtype=torch.bool)
        for agent in np.flatnonzero(live.numpy()):
            assert experts[agent].action(td["pose"][agent].numpy()) == int(td["expert_action"][agent])
        td["action"] = td["expert_action"]
        td = env.step(td)["next"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"route_lengths": (10, 30)}, "route_lengths needs a route_style"),
        ({"route_style": "driven", "route_lengths": (10, 60)}, r"route_lengths must lie in \[10, demo_length=30\]"),
        ({"route_style": "walk"}, "route_style must be one of 'planner', 'tour', 'driven'"),
        ({"route_style": RouteMixture({"tour": 1.0}, 10, 20), "route_lengths": (10, 20)}, "cannot be combined with a RouteMixture"),
    ],
)
def test_bad_route_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PathFollowEnv(demo_length=30, **{**SMALL, **kwargs})


def test_a_dataset_and_an_evaluation_of_a_route_style(tmp_path):
    from spf_rl.data import DatasetConfig, EpisodeDataset
    from spf_rl.evaluation import EvalConfig, episode_store_name, evaluate_policy
    from spf_rl.modules.open_loop import OpenLoopPolicy
    from spf_rl.modules.views import episodes_to_sequence

    data = DatasetConfig(episodes=EpisodeSpec(num_houses=2, demo_length=16, max_steps=None, image_size=16, route_style="driven=1,planner=1", route_lengths=[10, 16]), num_episodes=6, chunk_size=6)
    assert data.episodes.route_style == "planner=1.0,driven=1.0" and data.episodes.step_limit == default_max_steps(16)
    dataset = EpisodeDataset.build(tmp_path / "data", data, num_workers=1, progress=False)
    batch = dataset[list(range(6))]
    steps = batch["demo_steps"].squeeze(-1)
    assert ((steps >= 10) & (steps <= 16)).all()
    lengths = dataset.episodes["length"]
    assert (lengths <= torch.tensor([default_max_steps(int(n)) for n in steps])).all()  # each route's own limit
    sequence = episodes_to_sequence(batch)
    assert torch.equal(sequence["demo_steps"][:, 0], batch["demo_steps"])  # carried to the policy at every step
    # the pointer's label: the agent's place on the route, from 0, onwards, at most the route's end
    route_step, mask = batch["steps", "route_step"].squeeze(-1), batch["steps", "mask"]
    assert (route_step[:, 0] == 0).all() and (route_step <= steps[:, None]).all() and route_step.max() > 0
    onwards = torch.cat([r[m].diff() >= 0 for r, m in zip(route_step, mask)])
    assert onwards.float().mean() > 0.95  # it may step back where a later look re-matches the route
    assert torch.equal(sequence["route_step"], batch["steps", "route_step"][:, : sequence.shape[1]])

    config = EvalConfig(episodes=EpisodeSpec(split="val", num_houses=2, demo_length=16, max_steps=None, image_size=16, route_style="tour", route_lengths=(10, 16), seed=3), num_episodes=4, num_agents=2, render=False)
    assert episode_store_name(config).startswith("val-2houses-follow-n16-tour1.0-10to16-16px")
    summary, records = evaluate_policy(OpenLoopPolicy(), config, progress=False)
    assert summary["episodes"] == 4 and all(0.0 < r["ndtw"] <= 1.0 for r in records)
    assert all(r["steps"] <= default_max_steps(16) for r in records)


def test_dagger_rounds_of_a_route_style(tmp_path):
    from spf_rl.checkpoint import save_checkpoint
    from spf_rl.evaluation import EvalConfig
    from spf_rl.modules.config import SPFConfig
    from spf_rl.modules.registry import build_policy
    from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig
    from spf_rl.train.dagger import DAggerConfig, train_dagger
    from spf_rl.train.dagger_rounds import RoundStore
    from spf_rl.train.run import OptimConfig

    torch.manual_seed(0)
    config = SPFConfig(demo_length=12, sparsity_range=(0.2, 1.0), feature_dim=8, hidden_size=8, image_size=(16, 16))
    save_checkpoint(tmp_path / "bc.pt", "spf_random", config, {"model": build_policy("spf_random", config).state_dict()})
    routes = {"demo_length": 12, "max_steps": None, "image_size": 16, "num_houses": 1, "route_style": "driven", "route_lengths": (10, 12)}
    evaluation = dict(num_episodes=2, num_agents=2)
    results = train_dagger(DAggerConfig(
        checkpoint=str(tmp_path / "bc.pt"), output_dir=str(tmp_path / "dagger"), device="cpu", rounds=1, episodes_per_round=4,
        beta0=0.5, steps_per_round=None, window_rounds=None, aggregate_bc_data=False, logger="", progress=False,
        env=CollectionEnvConfig(EpisodeSpec(**routes)), collector=CollectorConfig(num_agents=2),
        optim=OptimConfig(lr=3e-4, cosine_schedule=False, pointer_coef=0.1),  # the rounds carry the pointer's labels
        val=EvalConfig(EpisodeSpec(split="val", seed=1, **routes), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, **routes), **evaluation),
    ))
    assert [r["round"] for r in results["history"]] == [0, 1]
    stored = RoundStore(tmp_path / "dagger" / "rounds" / "round-01")
    assert stored.config.episodes.route_style == "driven=1.0" and stored.config.episodes.route_lengths == (10, 12)
    rows = stored[torch.arange(4)]
    steps = rows["demo_steps"].squeeze(-1)
    assert ((steps >= 10) & (steps <= 12)).all()  # the round's routes, each with its own length
    assert (rows["length"] <= torch.tensor([default_max_steps(int(n)) for n in steps])).all()
    assert (rows["steps", "route_step"].squeeze(-1) <= steps[:, None]).all() and rows["steps", "route_step"].max() > 0


def play(house, demo, actions) -> dict:
    env = PathFollowEnv(house_seeds=[house.seed], demo_length=demo.length, render=False, emit_demo_frames=False, demonstrations=[demo])
    env.set_seed(0)
    env.reset()
    for step, action in enumerate(actions, start=1):
        out = env.step(TensorDictAction(action))["next"]
        if out["done"].item():
            return {"steps": step, "success": bool(out["success"].item()), "ndtw": float(out["ndtw"].item())}
    raise AssertionError("the episode did not end")


def TensorDictAction(action: int):
    from tensordict import TensorDict

    return TensorDict({"action": torch.tensor(action)}, batch_size=[])


def test_a_route_that_passes_its_end_counts_arrival_only_after_its_excursion(unobstructed_route):
    from envs.expert import FORWARD, TURN_LEFT
    from envs.follow import route_excursions

    # it passes its end after 3 steps, drives on 7, turns round and comes back to it
    house, demo = unobstructed_route([FORWARD] * 10 + [TURN_LEFT] * 9 + [FORWARD] * 7)
    radius = max(0.6, 0.1 * demo.shortest_length_m)
    assert route_excursions(demo.end_field.at_many(demo.poses[:, :2]), radius).tolist() == [10]  # out to the turn
    replay = play(house, demo, demo.actions.tolist() + [0] * 100)
    assert replay["success"] and replay["steps"] >= demo.length - 2  # not at step 3, where it first passed the end
    shortcut = play(house, demo, [0, 0, 0] + [1] * 100)  # to the end, then spin there
    assert not shortcut["success"] and shortcut["steps"] == default_max_steps(demo.length)


def test_the_planners_routes_have_no_excursions():
    from envs.follow import route_excursions
    from envs.route_styles import planner_route
    from envs.scenes import build_house, split_seeds

    for i, seed in enumerate(split_seeds("train", 20)):
        house = build_house(seed)
        for length in (10, 30):
            demo = planner_route(house, np.random.default_rng(i), length)
            radius = max(0.6, 0.1 * demo.shortest_length_m)
            assert len(route_excursions(demo.end_field.at_many(demo.poses[:, :2]), radius)) == 0
