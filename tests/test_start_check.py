"""The start check (spf_rl.modules.replay_gate, SPFConfig.start_check): a first frame unlike the memory's
first frame makes the whole episode blind replay, one like it leaves the network as it was; step and sequence
mode agree, a new episode is measured anew, an env's primer starts it unmeasured; the export carries it; the
calibration picks a threshold within its false-alarm cap and writes a checkpoint that loads; bad settings
are refused before any work (the recipe's bad arguments: tests/test_recipe_bad_values.py)."""
from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import nn
from torchrl.modules import set_recurrent_mode

from envs.episode_spec import EpisodeSpec
from spf_rl.eval.start_check import calibrate, start_cosines
from spf_rl.evaluation import EvalConfig, greedy, make_eval_env
from spf_rl.modules import SPFConfig, SPFPolicy
from spf_rl.modules.registry import build_policy
from spf_rl.modules.replay_gate import UNMEASURED, replay_opening

BASE = SPFConfig(demo_length=8, feature_dim=3, hidden_size=8, image_size=(16, 16), pointer_update="rpf", sparsity_range=(0.2, 1.0))
RED, BLUE = (255, 0, 0), (0, 0, 255)


class ColourMeans(nn.Module):
    """An encoder whose features are a frame's mean colour: a red and a blue frame are orthogonal."""

    feature_dim = 3

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return frames.float().mean((-3, -2)) / 255


def policy(start_check: float | None, seed: int = 0) -> SPFPolicy:
    torch.manual_seed(seed)
    built = SPFPolicy(dataclasses.replace(BASE, start_check=start_check), ColourMeans()).eval()
    with torch.no_grad():
        for parameter in built.parameters():  # larger weights than at initialisation: the network's own actions vary
            parameter.normal_(std=0.5)
    return built.set_sparsity(0.5)


def coloured(colour: tuple[int, int, int], *shape: int) -> torch.Tensor:
    return torch.tensor(colour, dtype=torch.uint8).expand(*shape, 16, 16, 3).clone()


def episodes(first: list[tuple[int, int, int]], steps: int = 7, restart: int | None = None) -> TensorDict:
    """Red memories; row i's first frame is ``first[i]``, its later frames red; with ``restart``, every row
    starts a new episode at that step (a red first frame)."""
    batch = len(first)
    pixels = coloured(RED, batch, steps)
    for row, colour in enumerate(first):
        pixels[row, 0] = coloured(colour)
    is_init = torch.zeros(batch, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    if restart is not None:
        is_init[:, restart] = True
    generator = torch.Generator().manual_seed(1)
    return TensorDict({
        "pixels": pixels,
        "demo_frames": coloured(RED, batch, 1, 8).expand(batch, steps, 8, 16, 16, 3),
        "demo_actions": torch.randint(0, 3, (batch, 1, 8), generator=generator).expand(batch, steps, 8),
        "is_init": is_init,
    }, [batch, steps])


def play_steps(played: SPFPolicy, sequence: TensorDict) -> TensorDict:
    """Step mode over the sequence's time axis, carrying the state as an env would."""
    state, outputs = {}, []
    with torch.no_grad():
        for t in range(sequence.shape[1]):
            out = played(sequence[:, t].clone().update(state))
            outputs.append(out.select("logits", "eta_used", ("next", "start_match"), strict=False).clone())
            state = {key: out["next", key] for key in out["next"].keys()}
    return torch.stack(outputs, 1)


def test_another_routes_start_makes_the_episode_blind_replay_and_its_own_start_leaves_the_network():
    checked, plain = policy(0.5), policy(None)
    sequence = episodes([BLUE, RED])
    played = play_steps(checked, sequence)
    assert played["next", "start_match"][0].flatten().tolist() == [0.0] * 7  # blue against red, carried
    assert torch.allclose(played["next", "start_match"][1], torch.ones(7, 1))
    steps = torch.arange(7)
    assert torch.equal(played["eta_used"][0, :, 0], steps.float())  # one route step per step
    assert torch.equal(played["logits"][0].argmax(-1), sequence["demo_actions"][0, 0, steps])  # the demonstrated actions
    alone = play_steps(plain, sequence)
    assert torch.allclose(played["logits"][1], F.log_softmax(alone["logits"][1], -1), atol=1e-6)
    assert torch.equal(played["eta_used"][1], alone["eta_used"][1])
    assert not torch.equal(alone["logits"][0].argmax(-1), sequence["demo_actions"][0, 0, steps])  # the network alone would differ


def test_step_and_sequence_mode_agree_and_a_new_episode_is_measured_anew():
    checked = policy(0.5, seed=3)
    sequence = episodes([BLUE, RED, BLUE], steps=8, restart=4)
    stepped = play_steps(checked, sequence)
    with torch.no_grad(), set_recurrent_mode(True):
        whole = checked(sequence.clone())
    assert torch.allclose(stepped["logits"], whole["logits"], atol=1e-5)
    assert torch.allclose(stepped["next", "start_match"], whole["next", "start_match"])
    assert whole["next", "start_match"][0, 3].item() == 0.0 and whole["next", "start_match"][0, 4].item() == pytest.approx(1.0)


def test_a_sequence_that_starts_mid_episode_keeps_the_stored_start_match():
    checked = policy(0.5, seed=4)
    sequence = episodes([RED, RED], steps=5)
    sequence["is_init"][:] = False
    sequence["start_match"] = torch.tensor([0.0, UNMEASURED]).reshape(2, 1, 1).expand(2, 5, 1).clone()
    with torch.no_grad(), set_recurrent_mode(True):
        out = checked(sequence)
    assert out["next", "start_match"][0].flatten().tolist() == [0.0] * 5  # stored: another route's, kept
    assert torch.allclose(out["next", "start_match"][1], torch.ones(5, 1))  # unmeasured: measured on the red frame


def test_the_opening_joins_the_learned_gate_and_the_check():
    hidden, confidence = torch.zeros(3, 2), torch.zeros(3, 1)
    gate = nn.Linear(3, 1)
    with torch.no_grad():
        gate.weight.zero_()
        gate.bias.fill_(0.0)  # r_g = 1/2
    start = torch.tensor([[0.5], [1.0], [-0.5]])
    log_open, log_shut = replay_opening(hidden, confidence, gate, start, 0.5)
    r_s = torch.sigmoid(50.0 * (0.5 - start))
    assert torch.allclose(log_open.exp(), 1 - 0.5 * (1 - r_s), atol=1e-6)
    assert torch.allclose(log_open.exp() + log_shut.exp(), torch.ones(3, 1), atol=1e-6)
    with pytest.raises(ValueError, match="a gate or a start-check threshold"):
        replay_opening(hidden, confidence, None)


def test_an_envs_primer_starts_the_match_unmeasured_and_the_policy_measures_another_routes_start():
    checked = build_policy("spf_random", SPFConfig(demo_length=30, feature_dim=8, hidden_size=8, sparsity_range=(0.2, 1.0),
                                                   pointer_update="rpf", start_check=0.999)).eval().set_sparsity(0.5)
    assert checked.make_tensordict_primer().default_value["start_match"] == UNMEASURED
    spec = EpisodeSpec(split="val", num_houses=2, demo_length=30, max_steps=40, seed=5, memory_mismatch=1.0)
    env = make_eval_env(EvalConfig(episodes=spec, num_episodes=2, num_agents=2), checked)
    with torch.no_grad():
        rollout = env.rollout(3, greedy(checked), break_when_any_done=False)
    env.close()
    assert torch.equal(rollout["start_match"][:, 0], torch.full((2, 1), UNMEASURED))
    measured = rollout["next", "start_match"][:, 0]
    assert (measured < 0.999).all()  # another route's frames
    assert torch.equal(rollout["next", "start_match"][:, 2], measured)  # carried


@pytest.mark.parametrize("value, message", [
    (1.0, r"start_check must be a cosine threshold in \(-1, 1\) or None, got 1.0"),
    (True, "start_check must be a cosine threshold"),
    ("0.5", "start_check must be a cosine threshold"),
])
def test_bad_start_check_values_are_refused_naming_them(value, message):
    with pytest.raises(ValueError, match=message):
        SPFConfig(start_check=value)


def test_a_start_check_needs_a_visual_memory_and_spfs_architecture():
    with pytest.raises(ValueError, match="start_check needs visual memory"):
        SPFConfig(memory_mode="none", start_check=0.5)
    with pytest.raises(ValueError, match="start_check needs visual memory"):
        SPFConfig(memory_mode="full", sparsity=1.0, architecture="rpf_original", pointer_update="rpf", start_check=0.5)


def test_a_model_without_a_check_keeps_its_identity_and_keys():
    assert "start_check" not in SPFConfig().to_dict() and SPFConfig(start_check=0.25).to_dict()["start_check"] == 0.25
    plain = build_policy("spf_random", BASE)
    assert "start_match" not in plain.in_keys and "start_cosine" not in plain.out_keys
    assert sorted(plain.make_tensordict_primer().primers.keys()) == ["eta", "memory_features", "spf_hidden"]


def test_the_start_cosine_is_the_encoders_of_the_first_frames():
    checked = build_policy("spf_random", SPFConfig(demo_length=30, feature_dim=8, hidden_size=8, sparsity_range=(0.2, 1.0),
                                                   start_check=0.5)).eval()
    own = start_cosines(checked, "val", episodes=3, seed=2)
    other = start_cosines(checked, "val", episodes=3, seed=2, mismatch=True)
    assert np.allclose(own, 1.0, atol=1e-5) and (other < 0.9999).all()
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        start_cosines(checked, "val", episodes=0, seed=2)


def test_calibration_keeps_every_conditions_false_alarms_within_the_cap():
    rng = np.random.default_rng(0)
    own = {"none": np.ones(200), "light@1": rng.uniform(0.3, 1.0, 200), "camera@1": rng.uniform(0.6, 1.0, 200)}
    mismatched = rng.uniform(0.0, 0.8, 200)
    threshold, stats = calibrate(own, mismatched, max_false_alarm=0.05)
    assert max(stats["false_alarms"].values()) <= 0.05 and stats["worst_false_alarm"] <= 0.05
    assert stats["false_alarms"]["light@1"] == pytest.approx((own["light@1"] < threshold).mean())
    assert stats["mismatch_caught"] == pytest.approx((mismatched < threshold).mean())
    next_up = np.sort(own["light@1"])[np.searchsorted(np.sort(own["light@1"]), threshold)]
    assert (own["light@1"] < next_up + 1e-9).mean() > 0.05  # any higher threshold flags more than the cap
    looser, _ = calibrate(own, mismatched, max_false_alarm=0.2)
    assert looser > threshold
    with pytest.raises(ValueError, match=r"max_false_alarm must be in \[0, 1\)"):
        calibrate(own, mismatched, max_false_alarm=1.0)


def test_the_recipe_writes_a_checkpoint_that_loads_with_the_check(tmp_path, monkeypatch, capsys):
    """(Its refusals of bad arguments are in tests/test_recipe_bad_values.py.)"""
    import importlib

    from spf_rl.checkpoint import save_checkpoint
    from spf_rl.hub import load_policy

    source = build_policy("spf_random", SPFConfig(demo_length=30, feature_dim=8, hidden_size=8, sparsity_range=(0.2, 1.0)))
    save_checkpoint(tmp_path / "in.pt", "spf_random", source.config, {"model": source.state_dict(), "round": 3})
    out, results = tmp_path / "out.pt", tmp_path / "out.json"
    monkeypatch.setattr(sys, "argv", ["start_check.py"])
    importlib.import_module("start_check").main([str(tmp_path / "in.pt"), "--out", str(out), "--results", str(results), "--episodes", "4"])
    assert json.loads(capsys.readouterr().out)["start_check"] == json.loads(results.read_text())["start_check"]
    written = json.loads(results.read_text())
    loaded = load_policy(out)
    assert loaded.config.start_check == written["start_check"] and -1.0 < written["start_check"] < 1.0
    assert written["worst_false_alarm"] <= 0.05 and set(written["false_alarms"]) >= {"none", "light@0.5", "sensor@1"}
    assert all(torch.equal(a, b) for a, b in zip(loaded.policy.state_dict().values(), source.state_dict().values()))
