"""Tests of spf_rl.train.ppo on a tiny configuration: recurrent log-prob replay, updates,
end-to-end run, resume, and config validation."""
from __future__ import annotations

import copy
import dataclasses
import importlib.util
import json
from pathlib import Path

import pytest
import torch
from ppo_finetune import expand_shorthands
from torchrl.modules import set_recurrent_mode
from torchrl.objectives.value import GAE

from envs.episode_spec import SIZE_FIELDS, EpisodeSpec
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.config import load_config
from spf_rl.evaluation import EvalConfig
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import build_policy
from spf_rl.train import ppo as ppo_module
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, make_collector
from spf_rl.train.ppo import train_ppo
from spf_rl.train.ppo_config import PPOConfig
from spf_rl.train.ppo_loss import SPFPPOLoss, compute_values, make_ppo_modules, recompute_log_prob

POLICY = SPFConfig(demo_length=5, sparsity=0.4, feature_dim=16, hidden_size=16, image_size=(32, 32))
ENV = CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=8, image_size=32), with_expert=False)
AGENTS = 2
STEPS = 12  # > max_steps: rows hold a second episode that starts mid-row (is_init)


@pytest.fixture
def checkpoint(tmp_path) -> Path:
    torch.manual_seed(0)
    path = tmp_path / "start.pt"
    save_checkpoint(path, "spf", POLICY, {"model": build_policy("spf", POLICY).state_dict()})
    return path


def tiny_config(tmp_path, checkpoint, iterations: int, **overrides) -> PPOConfig:
    env = overrides.pop("env", ENV)
    # val and test play episodes of the env's sizes and routes (the policy is built for them)
    sizes = {key: getattr(env.episodes, key) for key in SIZE_FIELDS}
    evaluation = dict(num_episodes=2, num_agents=2)
    values = dict(
        checkpoint=str(checkpoint),
        output_dir=str(tmp_path / "run"),
        device="cpu",  # the CPU suite everywhere; tests/test_device_cuda.py runs PPO on CUDA
        frames_per_batch=AGENTS * STEPS,
        total_frames=AGENTS * STEPS * iterations,
        ppo_epochs=2,
        minibatch_rows=1,
        val_every=1,
        critic_warmup_iters=1,
        store_demos=6,
        store_root=str(tmp_path / "stores"),
        progress=False,
        collector=CollectorConfig(num_agents=AGENTS),
        env=env,
        val=EvalConfig(EpisodeSpec(split="val", seed=1, num_houses=1, **sizes), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, num_houses=1, **sizes), **evaluation),
    )
    values.update(overrides)
    return PPOConfig(**values)


def collect(model_type: str = "spf", policy_config: SPFConfig = POLICY):
    """A policy (eval mode), its actor and critic, and one collected [AGENTS, STEPS] batch with expert labels."""
    torch.manual_seed(0)
    policy = build_policy(model_type, policy_config).eval()
    actor, critic = make_ppo_modules(policy)
    env = dataclasses.replace(ENV, with_expert=True)
    collector = make_collector(
        actor, env, CollectorConfig(num_agents=AGENTS), frames_per_batch=AGENTS * STEPS, total_frames=AGENTS * STEPS,
        seed=0, reset_at_each_iter=True,
    )
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    return policy, actor, critic, batch


@pytest.fixture(scope="module")
def collected_once():
    return collect()


@pytest.fixture
def collected(collected_once):
    """A fresh copy of the collected policy (and new actor, critic) and batch, for tests that change them."""
    policy, _, _, batch = collected_once
    policy = copy.deepcopy(policy)
    torch.manual_seed(1)
    actor, critic = make_ppo_modules(policy)
    return policy, actor, critic, batch.clone()


def test_recomputed_log_prob_in_sequence_mode_equals_collected(collected):
    policy, actor, _, batch = collected
    is_init = batch.get("is_init").squeeze(-1)
    assert is_init[:, 0].all() and is_init[:, 1:].any()  # segments restart mid-row too
    # the collector carried the recurrent state (not zeros at every step)
    assert batch.get("spf_hidden")[~is_init].abs().sum() > 0
    log_prob = recompute_log_prob(actor, batch)
    torch.testing.assert_close(log_prob, batch.get("action_log_prob"), atol=1e-5, rtol=0)
    # negative control: replaying without the stored state at the segment starts goes wrong
    wrong = batch.clone()
    wrong.set("is_init", torch.zeros_like(wrong.get("is_init")))
    wrong.set("spf_hidden", torch.ones_like(wrong.get("spf_hidden")))
    assert (recompute_log_prob(actor, wrong) - batch.get("action_log_prob")).abs().max() > 1e-3


def test_store_collection_carries_ids_and_replays_with_the_frames_looked_up(tmp_path):
    """PPO's path: envs emit demo_id only, the actor looks the frames up; the update looks them up
    where segments start (zeros elsewhere) and replays the collected log-probabilities exactly."""
    from envs.demo_store import DemoStore, DemoStoreConfig
    from spf_rl.evaluation import FramesFromStore, frames_lookup

    store = DemoStore.build(tmp_path / "store", DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=4), progress=False)
    torch.manual_seed(0)
    policy = build_policy("spf", POLICY).eval()
    actor, _ = make_ppo_modules(policy)
    collector = make_collector(
        FramesFromStore(actor, store), ENV, CollectorConfig(num_agents=AGENTS), frames_per_batch=AGENTS * STEPS,
        total_frames=AGENTS * STEPS, seed=0, reset_at_each_iter=True, demo_store=store.root,
    )
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    assert "demo_frames" not in batch.keys() and batch["demo_id"].max() < 4
    is_init = batch.get("is_init").squeeze(-1)
    assert is_init[:, 0].all() and is_init[:, 1:].any()
    lookup = frames_lookup(policy, store)
    assert lookup.in_keys == ["demo_id", "is_init"]  # the SPF policy carries its memory: segment starts only
    lookup(batch)
    assert (batch["demo_frames"][~is_init] == 0).all()
    assert torch.equal(batch["demo_frames"][is_init], store.frames[batch["demo_id"][is_init].reshape(-1)])
    torch.testing.assert_close(recompute_log_prob(actor, batch), batch.get("action_log_prob"), atol=1e-5, rtol=0)


def test_random_sparsity_model_replays_its_eval_mask():
    """'spf_random' picks its memory mask by policy.training: in eval mode collection and
    the sequence-mode replay both use the evaluation sparsity, so the log-probs agree."""
    config = dataclasses.replace(POLICY, sparsity_range=(0.2, 1.0))
    _, actor, _, batch = collect("spf_random", config)
    torch.testing.assert_close(recompute_log_prob(actor, batch), batch.get("action_log_prob"), atol=1e-5, rtol=0)


def test_first_minibatch_ratio_is_one_and_regularisers_start_at_zero(collected):
    policy, actor, critic, batch = collected
    compute_values(policy, critic, batch)
    GAE(gamma=0.99, lmbda=0.95, value_network=None)(batch)
    # the frozen reference equals the policy here: its logits in sequence mode are the policy's
    with torch.no_grad(), set_recurrent_mode(True):
        reference = policy(batch.exclude("logits", "features", "next").clone(False)).get("logits")
    batch.set(ppo_module.REF_LOGITS_KEY, reference)
    loss = SPFPPOLoss(actor, critic, kl_coef=0.5, bc_coef=0.5, clip_epsilon=0.2)
    out = loss(batch[:1])
    assert float(out["max_abs_log_ratio"]) < 1e-5
    assert float(out["kl_ref"]) < 1e-6
    assert float(out["loss_bc"].detach()) > 0
    assert {"loss_objective", "loss_critic", "loss_entropy", "loss_kl", "loss_bc"} <= set(out.keys())


def test_values_match_step_mode_and_bootstrap_next(collected):
    policy, _, critic, batch = collected
    compute_values(policy, critic, batch)
    value, next_value = batch.get("state_value"), batch.get(("next", "state_value"))
    done = batch.get(("next", "done")).squeeze(-1)
    inside = ~done[:, :-1]
    # within an episode V(s_{t+1}) is the next step's V(s_t)
    torch.testing.assert_close(next_value[:, :-1][inside], value[:, 1:][inside])
    # the cut-off step's next value is the step-mode value of the next observation
    last = batch[:, -1].get("next").select(*policy.in_keys).clone()
    with torch.no_grad():
        expected = critic.module(policy(last).get("features"))
    torch.testing.assert_close(next_value[:, -1], expected)


def test_update_lowers_the_loss_and_changes_the_parameters(collected):
    policy, actor, critic, batch = collected
    compute_values(policy, critic, batch)
    GAE(gamma=0.99, lmbda=0.95, value_network=None)(batch)
    loss = SPFPPOLoss(actor, critic, clip_epsilon=0.2, entropy_bonus=False, critic_coeff=1.0, normalize_advantage=False)
    optimizer = torch.optim.Adam(list(policy.parameters()) + list(critic.parameters()), lr=3e-3)
    before = {name: p.detach().clone() for name, p in policy.named_parameters()}

    def total() -> torch.Tensor:
        out = loss(batch)
        return out["loss_objective"] + out["loss_critic"]

    first = total()
    for _ in range(5):
        optimizer.zero_grad()
        value = total()
        value.backward()
        optimizer.step()
    assert total().item() < first.item() - 1e-3
    changed = [name for name, p in policy.named_parameters() if not torch.equal(p, before[name])]
    assert any(name.startswith("encoder") for name in changed) and any(name.startswith("cell.gru") for name in changed)


def test_end_to_end_interrupt_and_resume(tmp_path, checkpoint, monkeypatch):
    config = tiny_config(tmp_path, checkpoint, iterations=2, kl_coef=0.1, bc_coef=0.1)

    def stop_after_first(record):
        if record["iteration"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_ppo(config, callback=stop_after_first)
    run = Path(config.output_dir)
    last = load_checkpoint(run / "last.pt", expected_model_type="spf")
    assert last["iteration"] == 1 and [r["iteration"] for r in last["history"]] == [1]
    start = load_checkpoint(run / "best.pt")
    assert start["iteration"] == 0
    # iteration 1 only fitted the new value head: the policy is the start policy
    for key, value in start["model"].items():
        assert torch.equal(value, last["model"][key]), key
    assert any(not torch.equal(v, last["value_head"][k]) for k, v in start["value_head"].items())

    # started again with the same config: continues at iteration 2, start not re-evaluated
    calls = []
    evaluate = ppo_module.evaluate_policy
    monkeypatch.setattr(ppo_module, "evaluate_policy", lambda policy, cfg, **kw: calls.append(cfg.episodes.split) or evaluate(policy, cfg, **kw))
    results = train_ppo(config)
    assert [r["iteration"] for r in results["history"]] == [1, 2]
    assert results["history"][0] == last["history"][0]
    assert calls[0] == "val" and calls.count("val") == 1  # only iteration 2's validation
    second = results["history"][1]
    assert not second["critic_warmup"] and second["log_ratio_first"] < 1e-5
    assert {"loss_objective", "loss_critic", "loss_kl", "loss_bc", "kl_ref", "reward_per_step", "success"} <= set(second)

    saved = json.loads((run / "results.json").read_text())
    assert {"start", "after", "best_iteration", "val_history", "history", "test_success_change"} <= set(saved)
    for side in ("start", "after"):
        test = saved[side]["test"]
        assert test["episodes"] == 2 and test["success_ci"][0] <= test["success"] <= test["success_ci"][1]
    assert [r["iteration"] for r in saved["val_history"]] == [0, 1, 2]
    assert (run / "ppo.png").stat().st_size > 0 and list((run / "logs").rglob("*.csv"))
    best = load_checkpoint(run / "best.pt", expected_model_type="spf")
    build_policy(best["model_type"], best["model_config"]).load_state_dict(best["model"])

    with pytest.raises(ValueError, match="frames_per_batch"):
        train_ppo(tiny_config(tmp_path, checkpoint, iterations=2, frames_per_batch=AGENTS * STEPS * 2, total_frames=AGENTS * STEPS * 4))


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"clip_epsilon": 0.0}, "clip_epsilon"),
        ({"clip_epsilon": -0.2}, "clip_epsilon"),
        ({"gamma": 0.0}, "gamma"),
        ({"lmbda": 1.5}, "lmbda"),
        ({"lr": 0.0}, "lr"),
        ({"kl_coef": -1.0}, "kl_coef"),
        ({"ppo_epochs": 0}, "ppo_epochs"),
        ({"minibatch_rows": AGENTS + 1}, "minibatch_rows"),
        ({"frames_per_batch": AGENTS * STEPS + 1}, "frames_per_batch"),
        ({"total_frames": AGENTS}, "total_frames"),
        ({"store_demos": 0}, "store_demos"),
    ],
)
def test_bad_config_values_are_refused(tmp_path, checkpoint, overrides, match):
    with pytest.raises(ValueError, match=match):
        tiny_config(tmp_path, checkpoint, iterations=1, **overrides)


def test_bad_values_through_the_recipe_config(tmp_path, checkpoint):
    with pytest.raises(ValueError, match="collector.backend"):
        load_config(PPOConfig, "ppo", ["collector.backend=slurm"])
    with pytest.raises(ValueError, match="clip_epsilon"):
        load_config(PPOConfig, "ppo", ["clip_epsilon=0"])
    config = load_config(PPOConfig, "ppo", expand_shorthands(["noise=none", "collector.backend=ray"]))
    assert config.env.episodes.noise == config.val.episodes.noise == config.test.episodes.noise == "none"
    assert config.collector.backend == "ray"
    quick = load_config(PPOConfig, "ppo", [], preset="ppo_quick")
    assert quick.num_iterations < load_config(PPOConfig, "ppo", []).num_iterations
    with pytest.raises(ValueError, match=r"env.image_size must equal the checkpoint's image size \(32, 32\), got 64"):
        train_ppo(tiny_config(tmp_path, checkpoint, iterations=1, env=CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=50, image_size=64))))


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install '.[distributed]')")
def test_ray_collector_acts_with_the_updated_weights(tmp_path, checkpoint, ray_cluster):
    config = tiny_config(
        tmp_path, checkpoint, iterations=2, critic_warmup_iters=0, lr=3e-3, val_every=10, logger="",
        collector=CollectorConfig(backend="ray", num_collectors=1, num_agents=AGENTS),
    )
    history = train_ppo(config)["history"]
    # iteration 1 moved the policy away from the weights that collected its batch ...
    assert history[0]["max_abs_log_ratio"] > 1e-3
    # ... and the remote collector collected iteration 2's batch with the new weights
    assert history[1]["log_ratio_first"] < 1e-5


def test_non_finite_updates_are_skipped_not_applied(tmp_path, checkpoint, monkeypatch):
    forward = ppo_module.SPFPPOLoss.forward

    def poisoned(self, tensordict):
        out = forward(self, tensordict)
        out.set("loss_objective", out.get("loss_objective") * float("nan"))
        return out

    monkeypatch.setattr(ppo_module.SPFPPOLoss, "forward", poisoned)
    results = train_ppo(tiny_config(tmp_path, checkpoint, iterations=2))
    second = results["history"][1]
    assert not second["critic_warmup"] and second["skipped_updates"] == 2 * AGENTS  # ppo_epochs x minibatches
    start = load_checkpoint(checkpoint)["model"]
    last = load_checkpoint(Path(tmp_path / "run" / "last.pt"))["model"]
    assert all(torch.equal(value, last[key]) and torch.isfinite(value).all() for key, value in start.items())


def test_the_recipe_trains_the_dataclass_defaults():
    """One home for every default: ppo.yaml only names the run."""
    from dataclasses import asdict

    from spf_rl.config import load_config
    from spf_rl.train.ppo_config import PPOConfig

    recipe, library = asdict(load_config(PPOConfig, "ppo", [])), asdict(PPOConfig())
    recipe.pop("output_dir"), library.pop("output_dir")
    assert recipe == library
