"""The replay gate (spf_rl.modules.replay_gate): open, the policy is blind replay of the demonstrated actions;
shut, it is the network without the gate; step and sequence mode agree; the imitation loss opens it where
the demonstration is right and the network wrong; a shipped network grows one; bad settings are refused."""
from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from spf_rl.modules import SPFConfig, SPFPolicy
from spf_rl.modules.registry import build_policy
from spf_rl.modules.replay_gate import fall_back, replay_gate_layer, replay_opening
from spf_rl.train.dagger import start_policy

BASE = SPFConfig(demo_length=8, feature_dim=8, hidden_size=8, image_size=(16, 16), pointer_update="rpf", sparsity_range=(0.2, 1.0),
                 anchor_radius=3)
LENGTHS = (8, 5, 7)


def episodes(batch: int = 3, steps: int = 9, seed: int = 0) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    is_init = torch.zeros(batch, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    demo_frames = torch.randint(0, 256, (batch, 8, 16, 16, 3), dtype=torch.uint8, generator=generator)
    return TensorDict({
        "pixels": torch.randint(0, 256, (batch, steps, 16, 16, 3), dtype=torch.uint8, generator=generator),
        "demo_frames": demo_frames.unsqueeze(1).expand(batch, steps, *demo_frames.shape[1:]),
        "demo_actions": torch.randint(0, 3, (batch, 1, 8), generator=generator).expand(batch, steps, 8),
        "demo_steps": torch.tensor(LENGTHS)[:batch].reshape(batch, 1, 1).expand(batch, steps, 1),
        "is_init": is_init,
    }, [batch, steps])


def gated(gate_bias: float | None = None, seed: int = 0) -> SPFPolicy:
    """A policy with the replay gate and larger weights than at initialisation (the pointer moves both ways)."""
    torch.manual_seed(seed)
    policy = build_policy("spf_random", dataclasses.replace(BASE, replay_gate=True)).eval()
    with torch.no_grad():
        for parameter in policy.parameters():
            parameter.normal_(std=0.5)
        if gate_bias is not None:
            policy.cell.replay_gate.weight.zero_()
            policy.cell.replay_gate.bias.fill_(gate_bias)
    return policy.set_sparsity(0.5)


def play_steps(policy: SPFPolicy, sequence: TensorDict) -> TensorDict:
    """Step mode over the sequence's time axis, carrying the state as an env would."""
    state, outputs = {}, []
    with torch.no_grad():
        for t in range(sequence.shape[1]):
            out = policy(sequence[:, t].clone().update(state))
            outputs.append(out.select("logits", "eta_used").clone())
            state = {key: out["next", key] for key in out["next"].keys()}
    return torch.stack(outputs, 1)


def test_an_open_gate_is_blind_replay_of_the_demonstrated_actions():
    policy, sequence = gated(gate_bias=1e4), episodes()
    played = play_steps(policy, sequence)
    steps = torch.arange(sequence.shape[1])
    for row, length in enumerate(LENGTHS):
        expected_pointer = steps.clamp(max=length - 1).to(torch.float32)
        assert torch.equal(played["eta_used"][row, :, 0], expected_pointer)  # one route step per step, capped at n_i - 1
        shown = sequence["demo_actions"][row, 0, expected_pointer.long()]
        assert torch.equal(played["logits"][row].argmax(-1), shown)


def test_a_shut_gate_is_the_network_without_it():
    policy = gated(gate_bias=-1e4)
    plain = build_policy("spf_random", BASE).eval().set_sparsity(0.5)
    plain.load_state_dict({key: value for key, value in policy.state_dict().items() if "replay_gate" not in key})
    sequence = episodes()
    with torch.no_grad(), set_recurrent_mode(True):
        a, b = policy(sequence.clone()), plain(sequence.clone())
    assert torch.allclose(a["logits"], F.log_softmax(b["logits"], -1), atol=1e-6)
    assert torch.equal(a["eta_used"], b["eta_used"])


def test_step_and_sequence_mode_agree_with_a_replay_gate():
    policy, sequence = gated(), episodes()  # a gate partly open, differently per row and step
    stepped = play_steps(policy, sequence)
    with torch.no_grad(), set_recurrent_mode(True):
        whole = policy(sequence.clone())
    for key in ("logits", "eta_used"):
        assert torch.allclose(stepped[key], whole[key], atol=1e-5), key


@pytest.mark.parametrize("label, opens", [(2, True), (0, False)])
def test_the_imitation_loss_opens_the_gate_only_where_the_demonstration_is_right(label, opens):
    """The network prefers action 0 and the demonstration shows 2: an expert who says 2 opens the gate, one who
    says 0 shuts it."""
    gate = replay_gate_layer(2)
    window = F.one_hot(torch.tensor([[1, 2, 1]]), 3).float()
    logits, _ = fall_back(torch.tensor([[3.0, 0.0, 0.0]]), torch.tensor([[5.0]]), torch.tensor([[4.0]]), window,
                          replay_opening(torch.zeros(1, 2), torch.tensor([[0.2]]), gate))
    F.cross_entropy(logits, torch.tensor([label])).backward()
    assert (gate.bias.grad.item() < 0) == opens and gate.bias.grad.item() != 0


def test_a_window_without_a_demonstrated_action_keeps_the_network_distribution():
    gate = replay_gate_layer(2)
    with torch.no_grad():
        gate.bias.fill_(2.0)
    logits = torch.tensor([[1.0, -1.0, 0.5]])
    mixed, _ = fall_back(logits, torch.tensor([[5.0]]), torch.tensor([[4.0]]), torch.zeros(1, 5, 3),
                         replay_opening(torch.zeros(1, 2), torch.tensor([[0.2]]), gate))
    assert torch.allclose(F.log_softmax(mixed, -1), F.log_softmax(logits, -1), atol=1e-5) and torch.isfinite(mixed).all()


def test_an_anchored_network_grows_a_gate_and_keeps_its_weights():
    start = build_policy("spf_random", BASE)
    config, grown = start_policy("spf_random", BASE, start.state_dict(), None, seed=3, replay_gate=True)
    assert config.replay_gate and config.anchor_radius == 3
    weights = grown.state_dict()
    assert all(torch.equal(weights[key], value) for key, value in start.state_dict().items())
    assert set(weights) - set(start.state_dict()) == {"cell.replay_gate.weight", "cell.replay_gate.bias"}
    assert torch.sigmoid(grown.cell.replay_gate.bias).item() < 0.02 and not grown.cell.replay_gate.weight.any()
    unanchored = dataclasses.replace(BASE, anchor_radius=None)
    both_config, both = start_policy("spf_random", unanchored, build_policy("spf_random", unanchored).state_dict(), 4, 0, replay_gate=True)
    assert both_config.anchor_radius == 4 and both_config.replay_gate and both.cell.replay_gate is not None
    with pytest.raises(ValueError, match="has a replay gate"):
        start_policy("spf_random", config, weights, None, 0, replay_gate=False)
    with pytest.raises(ValueError, match="replay_gate needs anchor_radius"):
        start_policy("spf_random", unanchored, build_policy("spf_random", unanchored).state_dict(), None, 0, replay_gate=True)


@pytest.mark.parametrize("config, message", [
    ({"replay_gate": True, "anchor_radius": None}, "replay_gate needs anchor_radius"),
    ({"replay_gate": "yes"}, "replay_gate must be True or False"),
])
def test_bad_replay_gate_settings_are_refused_naming_them(config, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(BASE, **config)


def test_a_model_without_a_gate_keeps_its_identity():
    """Checkpoints and the result cache of models from before the gate existed keep their config dict."""
    assert "replay_gate" not in BASE.to_dict() and SPFConfig(anchor_radius=2, replay_gate=True).to_dict()["replay_gate"] is True


def training_batch(mismatched: bool) -> TensorDict:
    """Stored episodes (spf_rl.data layout) of the tiny policy's size, every step labelled."""
    sequence = episodes(batch=2, steps=5)
    steps = TensorDict({
        "pixels": sequence["pixels"], "expert_action": torch.randint(0, 3, (2, 5)), "mask": torch.ones(2, 5, dtype=torch.bool),
        "is_init": sequence["is_init"],
    }, [2, 5])
    return TensorDict({
        "steps": steps, "demo_frames": sequence["demo_frames"][:, 0], "demo_actions": sequence["demo_actions"][:, 0],
        "demo_steps": torch.tensor([[8], [5]]), "memory_mismatched": torch.full((2,), mismatched),
    }, [2])


@pytest.mark.parametrize("mismatched", [True, False])
def test_the_gate_loss_opens_the_gate_on_another_routes_frames_and_shuts_it_on_the_routes_own(mismatched):
    from spf_rl.train.bc import bc_loss

    policy = build_policy("spf_random", dataclasses.replace(BASE, replay_gate=True)).train()
    parts: dict = {}
    loss, _ = bc_loss(policy, training_batch(mismatched), replay_gate_coef=1.0, parts=parts)
    loss.backward()
    gradient = policy.cell.replay_gate.bias.grad.item()
    assert (gradient < 0) == mismatched  # a step downhill raises the bias (opens) only where the memory is another route's
    expected = -F.logsigmoid(torch.tensor(-4.0 if mismatched else 4.0)).item()  # the gate starts at sigmoid(-4), weights 0
    assert parts["replay_gate"] == pytest.approx(expected, rel=1e-5) and loss.item() > parts["cross_entropy"]


def test_a_gate_loss_without_a_gate_is_refused_naming_the_key():
    from spf_rl.train.bc import BCConfig, bc_loss
    from spf_rl.train.run import OptimConfig

    with pytest.raises(ValueError, match="optim.replay_gate_coef > 0 needs a policy with a replay gate"):
        bc_loss(build_policy("spf_random", BASE), training_batch(True), replay_gate_coef=0.5)
    with pytest.raises(ValueError, match="optim.replay_gate_coef > 0 needs a network with a replay gate"):
        BCConfig(optim=OptimConfig(replay_gate_coef=0.5))
