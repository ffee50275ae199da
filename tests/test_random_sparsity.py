"""Tests for one SPF model trained with a random sparsity per episode (``SPFConfig.sparsity_range``,
model ``"spf_random"``): mask semantics, step/sequence agreement, random draws, checkpoints, recipes."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from test_policy import CFG as FIXED_CFG
from test_policy import DemoEnv, N, _make_trajectory, _random_td, _run_steps
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode

from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.config import load_config
from spf_rl.eval.table1_rows import RANDOM_EVAL_SPARSITIES, RANDOM_MODEL, ROW_BY_NAME, checkpoint_name, table_lines
from spf_rl.modules import SPFConfig, SPFPolicy, make_rpf_policy, memory_length, memory_mask
from spf_rl.modules.registry import MODEL_NAMES, ModelConfig, build_policy, spf_config
from spf_rl.modules.views import model_memory_bytes
from spf_rl.train.bc import BCConfig

RANGE = (0.2, 1.0)
CFG = dataclasses.replace(FIXED_CFG, sparsity_range=RANGE)  # n = 6, 16x16 frames, D = 16
EVAL_SPARSITIES = (0.4, 0.6, 0.8, 1.0)


def _policy(seed: int = 0, **kwargs) -> SPFPolicy:
    torch.manual_seed(seed)
    return SPFPolicy(dataclasses.replace(CFG, **kwargs))


def _segment_masks(out, traj) -> list[torch.Tensor]:
    """The memory mask of every segment of a [B, T] output, checking it is constant inside the segment."""
    masks = []
    for b in range(traj.shape[0]):
        starts = traj["is_init"][b, :, 0].nonzero().squeeze(-1).tolist() + [traj.shape[1]]
        for start, end in zip(starts[:-1], starts[1:]):
            seg = out["memory_mask"][b, start:end]
            assert (seg == seg[0]).all()
            masks.append(seg[0])
    return masks


# --------------------------------------------------------------------- config
def test_config_and_memory_layout():
    assert CFG.sparsity_range == RANGE
    assert SPFConfig(sparsity_range=[0.3, 0.7]).sparsity_range == (0.3, 0.7)
    with pytest.raises(ValueError, match=r"sparsity_range must be a pair \(low, high\).*0 < low <= high <= 1"):
        SPFConfig(sparsity_range=(0.8, 0.4))
    with pytest.raises(ValueError, match="sparsity_range needs memory_mode='sparse'"):
        SPFConfig(sparsity_range=RANGE, memory_mode="full")
    policy = _policy()
    assert policy.memory_length == N and policy.sparsity == CFG.sparsity
    assert policy.make_tensordict_primer().primers["memory_features"].shape == (N, 16)
    assert "memory_mask" in policy.out_keys and "memory_mask" not in SPFPolicy(FIXED_CFG).out_keys
    # same parameters as a fixed-sparsity SPF model; baselines drop the range
    assert policy.state_dict().keys() == SPFPolicy(FIXED_CFG).state_dict().keys()
    assert make_rpf_policy(CFG).config.sparsity_range is None


@pytest.mark.parametrize("bad", [0, 1.5, -0.2, float("nan"), True, "0.4"])
def test_set_sparsity_rejects_bad_values(bad):
    policy = _policy()
    with pytest.raises(ValueError, match=r"sparsity must be a number in the range \(0, 1\]"):
        policy.set_sparsity(bad)
    assert policy.sparsity == CFG.sparsity


def test_set_sparsity_needs_a_random_sparsity_policy():
    with pytest.raises(RuntimeError, match="sparsity_range"):
        SPFPolicy(FIXED_CFG).set_sparsity(0.5)


# --------------------------------------------------------------------- mask semantics
@pytest.mark.parametrize("sparsity", EVAL_SPARSITIES)
def test_only_the_kept_frames_reach_the_logits(sparsity):
    policy = _policy().set_sparsity(sparsity).eval()
    kept = memory_mask(N, sparsity)
    traj = _make_trajectory(inits=((0,), (0,)), T=3)
    with torch.no_grad():
        _, logits = _run_steps(policy, traj)
        noisy = traj.clone()
        noise = torch.randint(0, 256, noisy["demo_frames"][:, :, ~kept].shape, dtype=torch.uint8)
        noisy["demo_frames"][:, :, ~kept] = noise
        _, noisy_logits = _run_steps(policy, noisy)
        with set_recurrent_mode(True):
            seq_noisy = policy(noisy.clone())["logits"]
        changed = traj.clone()
        changed["demo_frames"][:, :, kept.nonzero()[-1]] = 255 - changed["demo_frames"][:, :, kept.nonzero()[-1]]
        _, changed_logits = _run_steps(policy, changed)
    assert torch.equal(noisy_logits, logits)
    torch.testing.assert_close(seq_noisy, logits, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(changed_logits, logits)


@pytest.mark.parametrize("sparsity", EVAL_SPARSITIES)
def test_evaluated_at_s_equals_a_fixed_model_that_carries_only_those_frames(sparsity):
    random_policy = _policy().set_sparsity(sparsity).eval()
    fixed = SPFPolicy(dataclasses.replace(FIXED_CFG, sparsity=sparsity)).eval()
    fixed.load_state_dict(random_policy.state_dict())  # same parameters, l slots instead of n
    traj = _make_trajectory()
    with torch.no_grad():
        _, random_logits = _run_steps(random_policy, traj)
        _, fixed_logits = _run_steps(fixed, traj)
    torch.testing.assert_close(random_logits, fixed_logits, rtol=1e-5, atol=1e-5)


def test_eval_mode_step_and_sequence_agree():
    policy = _policy().set_sparsity(0.6).eval()
    traj = _make_trajectory()  # starts: row 0 at t=0, 4; row 1 at t=0, 2
    with torch.no_grad():
        inputs, step_logits = _run_steps(policy, traj)
        with set_recurrent_mode(True):
            seq = policy(inputs.clone())
            part = policy(inputs[:, 1:].clone())  # a window starting mid-episode
    torch.testing.assert_close(seq["logits"], step_logits, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(part["logits"], step_logits[:, 1:], rtol=1e-5, atol=1e-5)
    assert (seq["memory_mask"] == memory_mask(N, 0.6)).all()


def test_step_mode_uses_the_evaluation_sparsity_even_in_training_mode():
    policy = _policy().set_sparsity(0.4)
    assert policy.training
    for seed in range(3):
        torch.manual_seed(seed)
        out = policy(_random_td([3], seed=seed))
        assert (out["memory_mask"] == memory_mask(N, 0.4)).all()
        assert out["next", "memory_features"].shape == (3, N, 16)


# --------------------------------------------------------------------- random draws in training
def test_training_sequence_mode_draws_a_sparsity_per_segment():
    policy = _policy()
    starts = tuple((0, 2, 4) for _ in range(6))
    traj = _make_trajectory(B=6, T=6, inits=starts)
    with torch.no_grad(), set_recurrent_mode(True):
        torch.manual_seed(1)
        out = policy(traj.clone())
        masks = _segment_masks(out, traj)
        torch.manual_seed(1)
        again = policy(traj.clone())
        torch.manual_seed(2)
        other = policy(traj.clone())
    assert len(masks) == 18
    assert len({tuple(m.tolist()) for m in masks}) > 1  # segments get different masks
    low, high = memory_length(N, RANGE[0]), memory_length(N, RANGE[1])
    for mask in masks:  # each one is M* of some sparsity in the range
        kept = int(mask.sum())
        assert low <= kept <= high and torch.equal(mask, memory_mask(N, kept / N))
    assert torch.equal(again["memory_mask"], out["memory_mask"])
    assert torch.equal(again["logits"], out["logits"])
    assert not torch.equal(other["memory_mask"], out["memory_mask"])
    # eval mode: every segment uses policy.sparsity
    policy.eval()
    with torch.no_grad(), set_recurrent_mode(True):
        evaluated = policy(traj.clone())
    assert (evaluated["memory_mask"] == memory_mask(N, CFG.sparsity)).all()


def test_training_draws_stay_in_a_narrow_range_and_gradients_flow():
    policy = _policy(sparsity_range=(0.5, 0.5))
    traj = _make_trajectory(B=2, T=4, inits=((0,), (0, 2)))
    with set_recurrent_mode(True):
        out = policy(traj)
    assert (out["memory_mask"] == memory_mask(N, 0.5)).all()
    out["logits"].sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.parameters())


def test_rollout_with_the_policy_primer():
    policy = _policy().set_sparsity(0.4).eval()
    env = TransformedEnv(DemoEnv(), Compose(InitTracker(), policy.make_tensordict_primer()))
    with torch.no_grad():
        rollout = env.rollout(4, policy)
    assert rollout["next", "memory_features"].shape == (4, N, 16)
    assert (rollout["memory_mask"] == memory_mask(N, 0.4)).all()


# --------------------------------------------------------------------- model name, checkpoints, recipes
def test_spf_random_model_checkpoint_round_trip(tmp_path):
    assert "spf_random" in MODEL_NAMES
    model = ModelConfig(name="spf_random", sparsity=0.6, feature_dim=16, hidden_size=16, sparsity_range=[0.3, 0.9])
    config = spf_config(model, demo_length=N, image_size=16)
    assert config.sparsity_range == (0.3, 0.9)
    assert spf_config(dataclasses.replace(model, name="spf"), demo_length=N, image_size=16).sparsity_range is None
    torch.manual_seed(0)
    policy = build_policy("spf_random", config)
    path = tmp_path / "spf_random.pt"
    save_checkpoint(path, "spf_random", config, {"model": policy.state_dict()})
    torch.load(path, weights_only=True)
    payload = load_checkpoint(path, expected_model_type="spf_random")
    assert payload["model_config"] == config
    clone = build_policy("spf_random", payload["model_config"])
    clone.load_state_dict(payload["model"])  # strict
    td = _random_td([2])
    with torch.no_grad():
        expected = policy.set_sparsity(0.4).eval()(td.clone())["logits"]
        assert torch.equal(clone.set_sparsity(0.4).eval()(td.clone())["logits"], expected)
    with pytest.raises(ValueError, match="model_type 'spf' needs config.sparsity_range None"):
        build_policy("spf", config)
    with pytest.raises(ValueError, match="model_type 'spf_random' needs config.sparsity_range set"):
        build_policy("spf_random", dataclasses.replace(config, sparsity_range=None))
    with pytest.raises(ValueError, match="sparsity_range must be a pair"):
        ModelConfig(name="spf_random", sparsity_range=[0.0, 1.0])


def test_memory_bytes_are_those_of_the_kept_frames():
    for sparsity in EVAL_SPARSITIES:
        assert model_memory_bytes("spf_random", 30, sparsity, 64) == model_memory_bytes("spf", 30, sparsity, 64)
    assert model_memory_bytes("spf_random", 30, 0.4, 64) < model_memory_bytes("spf_random", 30, 1.0, 64)


def test_bc_recipe_config_for_spf_random():
    config = load_config(BCConfig, "bc", ["model=spf_random"])
    assert config.model.name == "spf_random" and config.model.sparsity_range == [0.2, 1.0]
    config = load_config(BCConfig, "bc", ["model=spf_random", "model.sparsity_range=[0.4,0.9]"])
    assert spf_config(config.model, 30, 64).sparsity_range == (0.4, 0.9)
    with pytest.raises(ValueError, match="sparsity_range"):
        load_config(BCConfig, "bc", ["model.sparsity_range=[0.9,0.4]"])


def test_table1_lines_for_the_random_model():
    """One trained random-sparsity model (per seed) gives one table line per evaluated sparsity, with the
    memory of SPF at that sparsity; its shipped checkpoint is named by the range."""
    assert checkpoint_name(RANDOM_MODEL, (0.2, 1.0)) == "spf_random-s0.2-1.pt"
    assert checkpoint_name("spf", 0.4) == "spf-s0.4.pt"
    row = ROW_BY_NAME["spf_random-s0.2-1"]
    lines = table_lines([row, ROW_BY_NAME["spf-s0.4"]], demo_length=30, image_size=64)
    random_lines = [line for line in lines if line.model == RANDOM_MODEL]
    assert [line.sparsity for line in random_lines] == list(RANDOM_EVAL_SPARSITIES) == list(EVAL_SPARSITIES)
    assert {line.checkpoint_stem for line in random_lines} == {"spf_random-s0.2-1"}
    assert [line.memory_bytes for line in random_lines] == [model_memory_bytes("spf", 30, s, 64) for s in EVAL_SPARSITIES]
    assert lines[-1].name == "spf-s0.4" and lines[-1].memory_bytes == random_lines[0].memory_bytes
