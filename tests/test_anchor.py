"""The pointer's anchor (spf_rl.modules.anchor): the pointer can go back to where the frame says the agent
is; shut, it changes nothing; step and sequence mode agree; a shipped network grows one; its loss."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from spf_rl.modules import SPFConfig, SPFPolicy
from spf_rl.modules.anchor import PointerAnchor, anchor_gate, reanchor
from spf_rl.modules.registry import build_policy
from spf_rl.train.bc import pointer_loss
from spf_rl.train.dagger import start_policy

BASE = SPFConfig(demo_length=8, feature_dim=8, hidden_size=8, image_size=(16, 16), pointer_update="rpf", sparsity_range=(0.2, 1.0))


def episodes(batch: int = 3, steps: int = 6, seed: int = 0) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    is_init = torch.zeros(batch, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    demo_frames = torch.randint(0, 256, (batch, 8, 16, 16, 3), dtype=torch.uint8, generator=generator)
    return TensorDict({
        "pixels": torch.randint(0, 256, (batch, steps, 16, 16, 3), dtype=torch.uint8, generator=generator),
        "demo_frames": demo_frames.unsqueeze(1).expand(batch, steps, *demo_frames.shape[1:]),
        "demo_actions": torch.randint(0, 3, (batch, 1, 8), generator=generator).expand(batch, steps, 8),
        "demo_steps": torch.tensor([[8], [5], [7]])[:batch].unsqueeze(1).expand(batch, steps, 1),
        "is_init": is_init,
    }, [batch, steps])


def anchored(seed: int = 0, **config) -> SPFPolicy:
    torch.manual_seed(seed)
    policy = build_policy("spf_random", dataclasses.replace(BASE, anchor_radius=3, **config)).eval()
    with torch.no_grad():
        for parameter in policy.parameters():  # weights that move the pointer and open the gate
            parameter.normal_(std=0.5)
    return policy.set_sparsity(0.5)


def play_steps(policy: SPFPolicy, sequence: TensorDict) -> TensorDict:
    """Step mode over the sequence's time axis, carrying the state as an env would."""
    state, outputs = {}, []
    with torch.no_grad():
        for t in range(sequence.shape[1]):
            td = sequence[:, t].clone().update(state)
            out = policy(td)
            outputs.append(out.select("logits", "eta_used", "anchor", "anchor_confidence").clone())
            state = {key: out["next", key] for key in out["next"].keys()}
    return torch.stack(outputs, 1)


def test_step_and_sequence_mode_agree_with_an_anchor():
    policy, sequence = anchored(), episodes()
    stepped = play_steps(policy, sequence)
    with torch.no_grad(), set_recurrent_mode(True):
        whole = policy(sequence.clone())
    for key in ("logits", "eta_used", "anchor", "anchor_confidence"):
        assert torch.allclose(stepped[key], whole[key], atol=1e-5), key
    assert {"anchor", "anchor_confidence"} <= set(policy.out_keys)


def test_a_shut_gate_is_the_network_without_an_anchor():
    policy = anchored()
    with torch.no_grad():
        policy.cell.anchor_gate.bias.fill_(-1e4)
    plain = build_policy("spf_random", BASE).eval().set_sparsity(0.5)
    plain.load_state_dict({k: v for k, v in policy.state_dict().items() if "anchor" not in k})
    sequence = episodes()
    with torch.no_grad(), set_recurrent_mode(True):
        a, b = policy(sequence.clone()), plain(sequence.clone())
    assert torch.equal(a["logits"], b["logits"]) and torch.equal(a["eta_used"], b["eta_used"])


def test_an_open_gate_brings_the_pointer_back_to_the_slot_the_frame_matches():
    anchor = PointerAnchor(feature_dim=4, radius=6.0, key_dim=4)
    with torch.no_grad():
        for layer in (anchor.query, anchor.key):
            layer.weight.copy_(torch.eye(4))
            layer.bias.zero_()
    memory = torch.eye(4).expand(1, 4, 4)  # slots at route steps 0, 2, 4, 6, each its own feature
    place, confidence = anchor.locate(memory[:, 1], memory, torch.tensor([0, 2, 4, 6]), None, torch.tensor([[6.0]]))
    assert place.item() == pytest.approx(2.0, abs=1e-3) and confidence.item() == pytest.approx(1.0, abs=1e-3)
    gate = anchor_gate(2)
    with torch.no_grad():
        gate.bias.fill_(50.0)
    eta_next = reanchor(torch.tensor([[7.0]]), torch.tensor([[6.0]]), place, confidence, torch.zeros(1, 2), gate, 6.0)
    assert eta_next.item() == pytest.approx(3.0, abs=1e-3)  # back 4 steps to the frame's place, then the rule's step
    # a frame that matches no slot: the expected cosine is low, the place the band's middle
    _, low = anchor.locate(-memory[:, 1], memory, torch.tensor([0, 2, 4, 6]), None, torch.tensor([[6.0]]))
    assert low.item() < 0.5


def test_a_network_without_an_anchor_grows_one_and_keeps_its_weights():
    start = build_policy("spf_random", BASE)
    config, grown = start_policy("spf_random", BASE, start.state_dict(), 8, seed=3)
    again = start_policy("spf_random", BASE, start.state_dict(), 8, seed=3)[1]
    assert config.anchor_radius == 8 and grown.anchors
    weights, others = grown.state_dict(), start.state_dict()
    assert all(torch.equal(weights[key], value) for key, value in others.items())
    assert all(torch.equal(value, again.state_dict()[key]) for key, value in weights.items())  # the seed fixes the new layers
    assert torch.sigmoid(grown.cell.anchor_gate.bias).item() < 0.02 and not grown.cell.anchor_gate.weight.any()
    with pytest.raises(ValueError, match="already anchors with radius 8"):
        start_policy("spf_random", config, grown.state_dict(), 4, seed=0)


def test_the_pointer_loss_teaches_the_anchor_on_the_routes_own_frames_only():
    policy, sequence = anchored(), episodes()
    sequence["mask"] = torch.ones(sequence.shape, dtype=torch.bool)
    sequence["route_step"] = torch.arange(6).expand(3, 6).unsqueeze(-1)
    with set_recurrent_mode(True):
        out = policy(sequence.clone())
    with_anchor, pointer_only = pointer_loss(out, 3), pointer_loss(out)
    assert with_anchor > pointer_only
    with_anchor.backward()
    assert policy.attention.anchor.query.weight.grad.abs().sum() > 0
    mismatched = out.clone()
    mismatched["memory_mismatched"] = torch.ones(out.shape, dtype=torch.bool)
    assert torch.equal(pointer_loss(mismatched.detach(), 3), pointer_loss(out.detach()))


def test_the_anchor_loss_is_added_under_data_parallel_training_too(monkeypatch):
    """bc_loss reads the anchor's radius from the policy that DistributedDataParallel wraps (a 1-process gloo
    group here): the same pointer loss as the bare policy's, the anchor's part included."""
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    from spf_rl.train import bc

    policy, sequence = anchored().train(), episodes(batch=2, steps=5)
    steps = TensorDict({"pixels": sequence["pixels"], "expert_action": torch.randint(0, 3, (2, 5)), "is_init": sequence["is_init"],
                        "mask": torch.ones(2, 5, dtype=torch.bool), "route_step": torch.arange(5).expand(2, 5)}, [2, 5])
    batch = TensorDict({"steps": steps, "demo_frames": sequence["demo_frames"][:, 0], "demo_actions": sequence["demo_actions"][:, 0],
                        "demo_steps": torch.tensor([[8], [5]])}, [2])

    def pointer_part(module) -> float:
        parts: dict = {}
        torch.manual_seed(1)  # the same memory masks for every pass
        bc.bc_loss(module, batch, pointer_coef=1.0, parts=parts)
        return parts["pointer"]

    bare = pointer_part(policy)
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        wrapped = pointer_part(DistributedDataParallel(policy))
    finally:
        dist.destroy_process_group()
    monkeypatch.setattr(bc, "anchor_loss", lambda *args: torch.zeros(()))
    assert wrapped == pytest.approx(bare, rel=1e-6) and bare > pointer_part(policy)  # the anchor's part counted


@pytest.mark.parametrize("config, message", [
    ({"anchor_radius": 0}, "anchor_radius must be a positive int"),
    ({"anchor_radius": 2.5}, "anchor_radius must be a positive int"),
    ({"anchor_radius": 4, "memory_mode": "none", "sparsity_range": None}, "anchor_radius needs visual memory"),
])
def test_bad_anchor_settings_are_refused_naming_them(config, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(BASE, **config)


def test_a_model_without_an_anchor_keeps_its_identity():
    """The result cache's key and the checkpoints' config of models shipped before the anchor existed are unchanged."""
    from spf_rl.checkpoint import content_sha256
    from spf_rl.records_cache import policy_sha256

    policy = build_policy("spf_random", BASE)
    before = {key: value for key, value in dataclasses.asdict(policy.config).items() if key not in ("anchor_radius", "normalize_frames", "replay_gate", "start_check")}
    assert policy.config.to_dict() == before and "anchor_radius" in anchored().config.to_dict()
    assert policy_sha256(policy) == content_sha256({"weights": dict(policy.state_dict()), "config": before, "sparsity": policy.sparsity})
