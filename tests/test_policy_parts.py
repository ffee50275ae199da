"""The SPF policy's parts as TensorDict modules: keys, recombination, parameter names."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import set_recurrent_mode

from spf_rl.modules import (
    MemoryAttention,
    SPFCell,
    SPFConfig,
    SPFPolicy,
    make_action_only_policy,
    make_rpf_original_policy,
    make_rpf_policy,
)

CFG = SPFConfig(demo_length=6, sparsity=0.5, feature_dim=16, hidden_size=16, image_size=(16, 16))


def _inputs(batch: tuple[int, ...] = (3,), seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "pixels": torch.randint(0, 256, (*batch, 16, 16, 3), dtype=torch.uint8, generator=g),
            "demo_frames": torch.randint(0, 256, (*batch, 6, 16, 16, 3), dtype=torch.uint8, generator=g),
            "demo_actions": torch.randint(0, 3, (*batch, 6), generator=g),
            "is_init": torch.ones(*batch, 1, dtype=torch.bool),
        },
        batch_size=batch,
    )


@pytest.mark.parametrize("make", [SPFPolicy, make_rpf_policy, make_action_only_policy], ids=["spf", "rpf", "action_only"])
def test_the_policy_is_the_sequence_of_its_parts(make) -> None:
    torch.manual_seed(0)
    policy = make(CFG)
    parts = [policy.encoder] + ([policy.memory] if policy.memory is not None else []) + [policy.attention, policy.cell]
    assert isinstance(policy.encoder, TensorDictModule)
    assert isinstance(policy.attention, MemoryAttention) and isinstance(policy.cell, SPFCell)
    by_hand = TensorDictSequential(*parts)(_inputs())
    whole = policy(_inputs())
    torch.testing.assert_close(by_hand["logits"], whole["logits"], rtol=0, atol=0)
    torch.testing.assert_close(by_hand["next", "eta"], whole["next", "eta"], rtol=0, atol=0)
    # every key a part writes is declared, and every key it reads is an input or an earlier output
    # ("demo_steps", each demonstration's length, is an optional input)
    available = {"pixels", "demo_frames", "demo_actions", "demo_steps", "is_init", "spf_hidden", "eta", "memory_features"}
    for part in parts:
        assert set(part.in_keys) <= available, (type(part).__name__, part.in_keys)
        available |= set(part.out_keys)
        assert all(whole.get(key, None) is not None for key in part.out_keys), type(part).__name__


def test_memory_is_encoded_only_where_an_episode_starts() -> None:
    policy = SPFPolicy(CFG)
    calls: list[int] = []
    policy.memory.encoder.register_forward_hook(lambda module, args, out: calls.append(out.shape[0]))
    td = _inputs((4,))
    first = policy(td.clone())
    assert calls == [4]
    td = _inputs((4,), seed=1)
    td["is_init"] = torch.tensor([[True], [False], [False], [True]])
    td["memory_features"] = first["next", "memory_features"]
    out = policy(td)
    assert calls == [4, 2]
    torch.testing.assert_close(out["memory_features"][1:3], first["memory_features"][1:3])


def test_parts_work_with_renamed_keys_in_a_users_sequence() -> None:
    torch.manual_seed(0)
    encoder = TensorDictModule(nn.Flatten(-3), in_keys=["rgb"], out_keys=["phi"])  # [*, 16*16*3]
    encoder.module.feature_dim = 768
    policy = SPFPolicy(dataclasses.replace(CFG, feature_dim=768), encoder)
    td = _inputs()
    td["rgb"] = td.pop("pixels").float() / 255
    out = policy(td)
    assert out["phi"].shape == (3, 768) and out["logits"].shape == (3, 3)
    assert "rgb" in policy.in_keys and "pixels" not in policy.in_keys


def test_sequence_mode_matches_step_mode_through_the_parts() -> None:
    torch.manual_seed(0)
    policy = SPFPolicy(CFG).eval()
    steps = torch.stack([_inputs((2,), seed=t) for t in range(5)], dim=1)  # [2, 5]
    steps["demo_frames"] = steps["demo_frames"][:, :1].expand(-1, 5, -1, -1, -1, -1).clone()
    steps["demo_actions"] = steps["demo_actions"][:, :1].expand(-1, 5, -1).clone()
    steps["is_init"] = torch.zeros(2, 5, 1, dtype=torch.bool)
    steps["is_init"][:, 0] = True
    with torch.no_grad(), set_recurrent_mode(True):
        sequence = policy(steps.clone())
    state = TensorDict({}, batch_size=[2])
    with torch.no_grad():
        for t in range(5):
            td = steps[:, t].clone().update(state)
            out = policy(td)
            torch.testing.assert_close(out["logits"], sequence["logits"][:, t])
            state = out["next"].select("spf_hidden", "eta", "memory_features")


def test_parameter_names_from_before_the_split_into_parts_are_refused() -> None:
    """Every shipped file uses today's names (the last legacy ones were rewritten), so old names are
    an error naming the keys, not silently renamed."""
    policy = SPFPolicy(CFG)
    legacy = {key.replace("cell.", "", 1): value for key, value in policy.state_dict().items()}
    assert "gru.weight_ih" in legacy
    with pytest.raises(RuntimeError, match="gru.weight_ih"):
        SPFPolicy(CFG).load_state_dict(legacy)


def test_rpf_original_memory_network() -> None:
    """bareblackfoot/RobustPathFollow: MLP slots over [phi, onehot(a)], GRU on [phi, mu], eta <- min(eta + 1 + tanh(b), n - 1)."""
    torch.manual_seed(0)
    policy = make_rpf_original_policy(dataclasses.replace(CFG, mu_dim=12))
    assert policy.memory_length == CFG.demo_length and policy.config.pointer_update == "rpf"
    assert policy.cell.gru.input_size == 12 + 16  # mu and phi, no action window
    assert isinstance(policy.cell.logits_head, nn.Sequential) and isinstance(policy.cell.pointer_head, nn.Sequential)
    out = policy(_inputs())
    assert out["memory_features"].shape == (3, 6, 12) and out["action_window"].shape == (3, 0, 3)
    eta = out["next", "eta"]
    assert ((eta >= 0) & (eta <= CFG.demo_length - 1)).all()
    # the memory depends on the demo actions
    other = _inputs()
    other["demo_actions"] = (other["demo_actions"] + 1) % 3
    assert not torch.allclose(policy(other)["memory_features"], out["memory_features"])
    with pytest.raises(ValueError, match="rpf_original"):
        SPFConfig(architecture="rpf_original")


def test_rpf_original_sequence_mode_matches_step_mode() -> None:
    torch.manual_seed(0)
    policy = make_rpf_original_policy(CFG).eval()
    steps = torch.stack([_inputs((2,), seed=t) for t in range(4)], dim=1)
    steps["demo_frames"] = steps["demo_frames"][:, :1].expand(-1, 4, -1, -1, -1, -1).clone()
    steps["demo_actions"] = steps["demo_actions"][:, :1].expand(-1, 4, -1).clone()
    steps["is_init"] = torch.zeros(2, 4, 1, dtype=torch.bool)
    steps["is_init"][:, 0] = True
    with torch.no_grad(), set_recurrent_mode(True):
        sequence = policy(steps.clone())
    state = TensorDict({}, batch_size=[2])
    with torch.no_grad():
        for t in range(4):
            out = policy(steps[:, t].clone().update(state))
            torch.testing.assert_close(out["logits"], sequence["logits"][:, t])
            state = out["next"].select("spf_hidden", "eta", "memory_features")


def test_rpf_original_is_a_model_type_that_round_trips_a_checkpoint(tmp_path) -> None:
    from spf_rl.checkpoint import load_checkpoint, save_checkpoint
    from spf_rl.modules.registry import ModelConfig, build_policy, spf_config

    config = spf_config(ModelConfig(name="rpf_original", feature_dim=16, hidden_size=16), demo_length=6, image_size=16)
    policy = build_policy("rpf_original", config)
    assert policy.config.architecture == "rpf_original"
    save_checkpoint(tmp_path / "rpf.pt", "rpf_original", config, {"model": policy.state_dict()})
    payload = load_checkpoint(tmp_path / "rpf.pt", expected_model_type="rpf_original")
    loaded = build_policy("rpf_original", payload["model_config"])
    loaded.load_state_dict(payload["model"])
    torch.testing.assert_close(loaded(_inputs())["logits"], policy(_inputs())["logits"])
