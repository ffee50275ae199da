"""Routes of several lengths (spf_rl.train.lengths): shared weights, mixed-length BC, success against length."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import success_by_length
import torch
from tensordict import TensorDict

from envs.episode_spec import EpisodeSpec
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.config import load_config
from spf_rl.data import DEMOS_SUFFIX, DatasetConfig, format_tag
from spf_rl.evaluation import EvalConfig
from spf_rl.modules import SPFConfig, SPFPolicy
from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
from spf_rl.modules.views import policy_for_length
from spf_rl.train.lengths import MixedLengthConfig, epoch_schedule, train_bc_mixed
from spf_rl.train.run import OptimConfig

TINY_MODEL = ModelConfig(sparsity=0.5, feature_dim=16, hidden_size=16)


def step_inputs(n: int, batch: int = 2) -> TensorDict:
    generator = torch.Generator().manual_seed(n)
    return TensorDict(
        {
            "pixels": torch.randint(0, 255, (batch, 32, 32, 3), dtype=torch.uint8, generator=generator),
            "demo_frames": torch.randint(0, 255, (batch, n, 32, 32, 3), dtype=torch.uint8, generator=generator),
            "demo_actions": torch.randint(0, 3, (batch, n), generator=generator),
            "is_init": torch.ones(batch, 1, dtype=torch.bool),
        },
        [batch],
    )


def test_policy_for_length_shares_the_weights():
    policy = build_policy("spf", spf_config(TINY_MODEL, demo_length=5, image_size=32))
    view = policy_for_length(policy, 9)
    assert policy_for_length(policy, 5) is policy and view.config.demo_length == 9 and view.memory_length == 4
    fresh = build_policy("spf", spf_config(TINY_MODEL, demo_length=9, image_size=32))
    fresh.load_state_dict(policy.state_dict())
    inputs = step_inputs(9)
    assert torch.equal(view(inputs.clone())["logits"], fresh(inputs.clone())["logits"])
    # one set of weights: a gradient through the view lands on the policy's parameters
    view(inputs.clone())["logits"].sum().backward()
    for parameter in (policy.cell.gru.weight_ih, policy.cell.logits_head.weight):
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0
    with torch.no_grad():
        policy.cell.gru.weight_hh.add_(1.0)
    assert torch.equal(view.cell.gru.weight_hh, policy.cell.gru.weight_hh)
    with pytest.raises(ValueError, match=r"demo_length must be an int in \[1, 198\] \(steps\)"):
        policy_for_length(policy, 0)


def test_policy_for_length_refuses_a_custom_encoder():
    class Flat(torch.nn.Module):
        feature_dim = 8

        def __init__(self):
            super().__init__()
            self.linear = torch.nn.Linear(32 * 32 * 3, 8)

        def forward(self, frames):
            return self.linear(frames.flatten(-3).float())

    policy = SPFPolicy(SPFConfig(demo_length=5, feature_dim=8, hidden_size=8, image_size=(32, 32)), Flat())
    with pytest.raises(ValueError, match="needs a policy built from its config"):
        policy_for_length(policy, 7)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(lengths=[]), "lengths must be distinct"),
        (dict(lengths=[30, 30], episodes=[1, 1]), "lengths must be distinct"),
        (dict(lengths=[30, 0], episodes=[1, 1]), r"lengths\[i\] must be an int in \[1, 198\]"),
        (dict(lengths=[30], episodes=[0]), r"episodes\[i\] must be a positive int"),
        (dict(device="gpu"), "device must be one of"),
        (dict(optim=OptimConfig(pointer_coef=0.1)), "optim.pointer_coef > 0 needs episodes of a route style"),
    ],
)
def test_mixed_length_config_is_validated(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MixedLengthConfig(**kwargs)


def test_epoch_schedule_visits_every_batch():
    order = epoch_schedule([5, 3, 1], seed=4)
    assert sorted(order.tolist()) == [0] * 5 + [1] * 3 + [2]
    assert order.tolist() == epoch_schedule([5, 3, 1], seed=4).tolist()


def tiny_mixed(tmp_path: Path, epochs: int) -> MixedLengthConfig:
    evaluation = dict(num_episodes=2, num_agents=2)
    return MixedLengthConfig(
        output_dir=str(tmp_path / "run"),
        data_root=str(tmp_path / "data"),
        device="cpu",
        num_workers=1,
        progress=False,
        lengths=[4, 6],
        episodes=[4, 4],
        data=DatasetConfig(episodes=EpisodeSpec(num_houses=1, max_steps=50, image_size=32), chunk_size=4),
        model=TINY_MODEL,
        optim=OptimConfig(batch_size=2, epochs=epochs, lr=3e-3),
        val=EvalConfig(EpisodeSpec(split="val", seed=1, num_houses=1, max_steps=50), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, num_houses=1, max_steps=50), **evaluation),
    )


def test_mixed_length_training_resumes_and_reports_by_length(tmp_path):
    one = train_bc_mixed(tiny_mixed(tmp_path, epochs=1))
    two = train_bc_mixed(tiny_mixed(tmp_path, epochs=2))
    assert [h["epoch"] for h in two["history"]] == [1, 2] and two["history"][0] == one["history"][0]
    assert two["history"][-1]["step"] == 2 * (2 + 2)  # 4 episodes of each length in batches of 2, 2 epochs
    rows = two["test_by_length"]
    assert [(r["demo_length"], r["max_steps"], r["episodes"]) for r in rows] == [(4, 7, 2), (6, 10, 2)]
    run = tmp_path / "run"
    saved = json.loads((run / "results.json").read_text())
    assert saved["test"]["success"] == pytest.approx(sum(r["success"] for r in rows) / 2)
    assert sorted(saved["test"]["by_length"]) == ["4", "6"]
    assert (run / "success_by_length.png").stat().st_size > 1000
    tag = format_tag()
    names = [f"train-4ep-paper-rand0.2-n4-32px-s0-{tag}", f"train-4ep-paper-rand0.2-n6-32px-s0-{tag}"]  # each limit the rule's
    stored = sorted(p.name for p in (tmp_path / "data").iterdir() if not p.name.endswith(".lock"))
    assert stored == sorted(names + [name + DEMOS_SUFFIX for name in names])  # each dataset beside its demonstrations
    payload = load_checkpoint(run / "best.pt", expected_model_type="spf")
    assert payload["model_config"].demo_length == 4 and "by_length" in payload["val"]
    # one result-cache file per length, keyed by that length's view of the best weights
    from spf_rl.evaluation import length_eval_config
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.modules.views import policy_for_length
    from spf_rl.records_cache import length_test_episodes_file, read_records, records_key

    best = policy_from_checkpoint(run / "best.pt")[0]
    config = tiny_mixed(tmp_path, epochs=2).test
    for row in rows:
        length = row["demo_length"]
        key = records_key(length_eval_config(config, length, 32), policy_for_length(best, length))
        records = read_records(run / length_test_episodes_file(length), key)
        assert len(records) == row["episodes"] and sum(r["success"] for r in records) / len(records) == pytest.approx(row["success"])


def test_success_by_length_recipe(tmp_path, capsys):
    policy = build_policy("spf", spf_config(TINY_MODEL, demo_length=5, image_size=32))
    checkpoint = tmp_path / "tiny" / "best.pt"
    checkpoint.parent.mkdir()
    save_checkpoint(checkpoint, "spf", policy.config, {"model": policy.state_dict()})
    argv = [str(checkpoint), "--lengths", "4", "6", "--episodes", "2", "--num-agents", "2", "--num-houses", "1"]
    content = success_by_length.main([*argv, "--no-render", "--quiet", "--out", str(tmp_path / "out")])
    rows = content["results"]["tiny/best"]
    assert [(r["demo_length"], r["max_steps"], r["episodes"]) for r in rows] == [(4, 7, 2), (6, 10, 2)]
    assert json.loads((tmp_path / "out" / "success_by_length.json").read_text()) == json.loads(json.dumps(content))
    assert (tmp_path / "out" / "success_by_length.png").stat().st_size > 1000
    assert "n=4 success" in capsys.readouterr().out
    for bad, message in (
        (["--lengths", "0"], "--lengths must be distinct positive ints"),
        (["--noise", "loud"], "noise must be one of"),
        (["--split", "dev"], "split must be one of"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            success_by_length.main([str(checkpoint), *bad, "--out", str(tmp_path / "bad")])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_length_and_homing_configs_load():
    full = load_config(MixedLengthConfig, "bc_lengths", [])
    assert full.lengths == [30, 50, 100] and full.episodes == [2000, 1200, 600]
    steps = sum(-(-count // full.optim.batch_size) for count in full.episodes) * full.optim.epochs
    assert steps >= 5000  # the common schedule of the Table 1 rows, in gradient steps
    assert full.dataset_config(2).episodes.max_steps == 167 and full.dataset_config(1).episodes.max_steps == 84
    quick = load_config(MixedLengthConfig, "bc_lengths", ["sparsity=0.6"], preset="bc_lengths_quick")
    assert quick.output_dir == "runs/bc_lengths_quick/spf-s0.6-seed0" and quick.optim.epochs == 1
    from spf_rl.train.bc import BCConfig

    homing = load_config(BCConfig, "bc", [], preset="bc_homing")
    row = load_config(BCConfig, "bc", [], preset="bc_row")
    assert (homing.data.episodes.task, homing.val.episodes.task, homing.test.episodes.task) == ("homing", "homing", "homing")
    assert str(homing.resolved_data_dir()).endswith("-homing") and homing.output_dir.startswith("runs/bc_homing/")
    # the homing model trains on the common row schedule, written once (base: bc_row)
    assert (homing.data.num_episodes, homing.optim.epochs, homing.val.num_episodes, homing.test.num_episodes) == (
        row.data.num_episodes, row.optim.epochs, row.val.num_episodes, row.test.num_episodes)
    assert row.data.num_episodes // row.optim.batch_size * row.optim.epochs >= 5000
