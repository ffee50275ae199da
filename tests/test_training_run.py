"""Tests for spf_rl.train.run.TrainingRun, the one training loop of BC, the lengths run, DAgger and PPO:
its gradient step, picking the best period, and resuming (the algorithms' own resume tests live beside them)."""
from __future__ import annotations

import pytest
import torch

from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import build_policy
from spf_rl.train.run import OptimConfig, TrainingRun

CONFIG = SPFConfig(demo_length=4, feature_dim=8, hidden_size=8, image_size=(16, 16))


def make_run(tmp_path, **kwargs) -> TrainingRun:
    torch.manual_seed(0)
    policy = build_policy("spf", CONFIG)
    return TrainingRun(tmp_path, "spf", CONFIG, policy, OptimConfig(lr=0.1), **kwargs)


def weights(run: TrainingRun) -> dict:
    return {key: value.clone() for key, value in run.policy.state_dict().items()}


@pytest.mark.filterwarnings("ignore:Detected call of `lr_scheduler.step\\(\\)` before")  # the skipped first step
def test_a_non_finite_step_is_skipped_and_the_schedule_goes_on(tmp_path):
    run = make_run(tmp_path, total_steps=4)
    before = weights(run)
    parameter = next(run.policy.parameters())
    loss = (parameter * float("nan")).sum()
    run.gradient_step(loss, torch.tensor(0.5), batch=None)
    assert all(torch.equal(value, run.policy.state_dict()[key]) for key, value in before.items())
    assert run.step == 1 and run.scheduler.last_epoch == 1  # the cosine schedule keeps its length
    run.gradient_step((parameter ** 2).sum() + 1.0, torch.tensor(0.5), batch=None)
    assert not torch.equal(parameter, before[next(name for name, p in run.policy.named_parameters() if p is parameter)])
    assert run.step == 2 and all(torch.isfinite(value).all() for value in run.policy.state_dict().values())


def test_the_best_period_is_the_first_of_equals_and_only_validated_ones_count(tmp_path):
    run = make_run(tmp_path, unit="iteration")
    assert not run.end_period(1, {"iteration": 1}, None)  # not validated: never the best
    assert not run.best_path.exists()
    assert run.end_period(2, {"iteration": 2}, {"success": 0.5, "spl": 0.3})
    assert not run.end_period(3, {"iteration": 3}, {"success": 0.5, "spl": 0.3})  # equal: the first stays
    assert run.end_period(4, {"iteration": 4}, {"success": 0.5, "spl": 0.4})
    best, last = load_checkpoint(run.best_path), load_checkpoint(run.last_path)
    assert best["iteration"] == 4 and best["val"] == {"success": 0.5, "spl": 0.4}
    assert last["iteration"] == 4 and [r["iteration"] for r in last["history"]] == [1, 2, 3, 4]


def test_resume_restores_every_optimiser_module_and_the_algorithms_own_state(tmp_path):
    head = torch.nn.Linear(3, 1)
    run = make_run(tmp_path, unit="iteration", modules={"value_head": head},
                   optimizers={"policy_optimizer": (build_policy("spf", CONFIG).parameters(), 0.1, 0.0),
                               "critic_optimizer": (head.parameters(), 0.2, 0.0)})
    run.state = {"start": {"val": {"success": 0.25}}}
    head.weight.data.fill_(0.7)
    run.end_period(1, {"iteration": 1, "val_success": 0.25, "val_spl": 0.1}, {"success": 0.25, "spl": 0.1})

    other_head = torch.nn.Linear(3, 1)
    again = make_run(tmp_path, unit="iteration", modules={"value_head": other_head},
                     optimizers={"policy_optimizer": (build_policy("spf", CONFIG).parameters(), 0.1, 0.0),
                                 "critic_optimizer": (other_head.parameters(), 0.2, 0.0)})
    seen = []
    assert again.resume(check=seen.append, state_keys=("start",)) == 1
    assert seen and torch.equal(other_head.weight, torch.full_like(other_head.weight, 0.7))
    assert again.state == {"start": {"val": {"success": 0.25}}} and again.best["iteration"] == 1
    assert again.optimizers["critic_optimizer"].param_groups[0]["lr"] == 0.2


def test_a_last_checkpoint_without_a_best_entry_gets_its_best_from_the_history(tmp_path):
    """DAgger's last.pt from before the one training loop held no ``best``: the history's best round is taken."""
    run = make_run(tmp_path, unit="round")
    history = [{"round": 0, "val_success": 0.5, "val_spl": 0.4}, {"round": 1, "val_success": 0.6, "val_spl": 0.2},
               {"round": 2, "val_success": 0.6, "val_spl": 0.2}]
    save_checkpoint(run.last_path, "spf", CONFIG,
                    {"model": run.policy.state_dict(), "optimizer": run.optimizer.state_dict(), "round": 2, "history": history})
    assert run.resume() == 2 and run.best == {"success": 0.6, "spl": 0.2, "round": 1}
