"""Demonstrations of different lengths in one batch (the optional ``demo_steps`` input): padded, masked,
and each followed as the network built for its own length (``policy_for_length``) follows it."""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

import pytest
import torch
import torch.nn.functional as F
from conftest import CountingEncoder
from tensordict import TensorDict
from test_policy import _run_steps
from torchrl.modules import set_recurrent_mode

from spf_rl.modules import (
    DEMO_STEPS_KEY,
    ImageEncoder,
    MemoryAttention,
    OpenLoopPolicy,
    PointerAttention,
    SparseMemory,
    SPFCell,
    SPFConfig,
    SPFPolicy,
    action_window,
    make_action_only_policy,
    make_rpf_original_policy,
    make_rpf_policy,
    memory_indices,
    memory_length,
    padded_memory_mask,
    soft_action_memory,
)
from spf_rl.modules.views import policy_for_length

H = W = 16
N_MAX = 12
T = 12
CFG = SPFConfig(demo_length=N_MAX, sparsity=0.5, k=2, feature_dim=16, hidden_size=16, image_size=(H, W))
#: Per row, its episodes as (first step, demonstration length): one row changes demonstration mid-sequence.
EPISODES = (((0, 5), (7, 12)), ((0, 9),), ((0, 12), (4, 1)))
FULL_LENGTH = (((0, N_MAX), (7, N_MAX)), ((0, N_MAX),), ((0, N_MAX), (4, N_MAX)))

MODELS: dict[str, Callable[[], SPFPolicy]] = {
    "spf": lambda: SPFPolicy(CFG),
    "spf_rpf_rule_soft_actions": lambda: SPFPolicy(dataclasses.replace(CFG, pointer_update="rpf", soft_action_memory=True)),
    "spf_random": lambda: SPFPolicy(dataclasses.replace(CFG, sparsity=0.6, sparsity_range=(0.2, 1.0))).eval(),
    "rpf": lambda: make_rpf_policy(dataclasses.replace(CFG, pointer_update="rpf")),
    "action_only": lambda: make_action_only_policy(CFG),
    "rpf_original": lambda: make_rpf_original_policy(CFG),
}


def _model(name: str) -> SPFPolicy:
    torch.manual_seed(0)
    return MODELS[name]()


def _trajectory(
    episodes=EPISODES, seed: int = 0, garbage_seed: int = 1, with_key: bool = True
) -> tuple[TensorDict, list[tuple]]:
    """``[B, T]`` steps whose demonstrations are padded to ``N_MAX`` with garbage (frames, and actions
    out of the action range), and the episodes ``(row, start, end, frames, actions)`` unpadded."""
    g, junk = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(garbage_seed)
    rows = len(episodes)
    pixels = torch.randint(0, 256, (rows, T, H, W, 3), dtype=torch.uint8, generator=g)
    demo_frames = torch.randint(0, 256, (rows, T, N_MAX, H, W, 3), dtype=torch.uint8, generator=junk)
    demo_actions = torch.randint(-3, 10, (rows, T, N_MAX), generator=junk)
    demo_steps = torch.zeros(rows, T, 1, dtype=torch.long)
    is_init = torch.zeros(rows, T, 1, dtype=torch.bool)
    records = []
    for row, row_episodes in enumerate(episodes):
        bounds = [start for start, _ in row_episodes] + [T]
        for (start, n), end in zip(row_episodes, bounds[1:]):
            frames = torch.randint(0, 256, (n, H, W, 3), dtype=torch.uint8, generator=g)
            actions = torch.randint(0, 3, (n,), generator=g)
            demo_frames[row, start:end, :n], demo_actions[row, start:end, :n] = frames, actions
            demo_steps[row, start:end], is_init[row, start] = n, True
            records.append((row, start, end, frames, actions))
    traj = TensorDict(
        pixels=pixels, demo_frames=demo_frames, demo_actions=demo_actions, is_init=is_init, batch_size=[rows, T]
    )
    if with_key:
        traj.set(DEMO_STEPS_KEY, demo_steps)
    return traj, records


def _reference_logits(policy: SPFPolicy, traj: TensorDict, records: list[tuple]) -> torch.Tensor:
    """Each episode alone, unpadded, through ``policy_for_length(policy, n_i)``, step by step."""
    logits = torch.full((*traj.shape, policy.config.num_actions), float("nan"))
    for row, start, end, frames, actions in records:
        steps = end - start
        alone = TensorDict(
            pixels=traj["pixels"][row, start:end],
            demo_frames=frames.expand(steps, *frames.shape),
            demo_actions=actions.expand(steps, -1),
            is_init=torch.arange(steps).eq(0).unsqueeze(-1),
            batch_size=[steps],
        ).unsqueeze(0)
        _, own = _run_steps(policy_for_length(policy, frames.shape[0]), alone)
        logits[row, start:end] = own[0]
    return logits


def _sequence(policy: SPFPolicy, inputs: TensorDict) -> TensorDict:
    with set_recurrent_mode(True):
        return policy(inputs.clone())


# --------------------------------------------------------------------- the central property
@pytest.mark.parametrize("name", list(MODELS))
def test_each_row_follows_its_demonstration_at_its_own_length(name):
    policy = _model(name)
    traj, records = _trajectory()
    with torch.no_grad():
        reference = _reference_logits(policy, traj, records)
        inputs, step_logits = _run_steps(policy, traj)
        sequence = _sequence(policy, inputs)
        part = _sequence(policy, inputs[:, 3:])  # a window starting mid-episode, from the stored state
    torch.testing.assert_close(step_logits, reference, rtol=0, atol=1e-6)
    torch.testing.assert_close(sequence["logits"], reference, rtol=0, atol=1e-6)
    torch.testing.assert_close(sequence["logits"], step_logits, rtol=0, atol=1e-6)
    torch.testing.assert_close(part["logits"], step_logits[:, 3:], rtol=0, atol=1e-6)
    # the lengths matter: a full-length reading of the same padded batch gives other logits
    with torch.no_grad():
        _, unaware = _run_steps(policy, _clip_actions(traj.exclude(DEMO_STEPS_KEY)))
    assert not torch.allclose(unaware[0, :7], reference[0, :7], atol=1e-3)


def _clip_actions(traj: TensorDict) -> TensorDict:
    """``traj`` with its padding actions clipped into the action range (for a reading without ``demo_steps``)."""
    traj = traj.clone()
    traj.set("demo_actions", traj["demo_actions"].clamp(0, 2))
    return traj


@pytest.mark.parametrize("name", list(MODELS))
def test_the_padding_never_changes_the_logits(name):
    policy = _model(name)
    first, _ = _trajectory(garbage_seed=1)
    second, _ = _trajectory(garbage_seed=2)
    zeros, _ = _trajectory(garbage_seed=1)
    steps = zeros["demo_steps"]
    zeros["demo_frames"][torch.arange(N_MAX) >= steps] = 0
    zeros["demo_actions"][torch.arange(N_MAX) >= steps] = 0
    assert not torch.equal(first["demo_frames"], second["demo_frames"])
    with torch.no_grad():
        runs = [_run_steps(policy, traj) for traj in (first, second, zeros)]
        sequences = [_sequence(policy, inputs) for inputs, _ in runs]
    for (_, logits), sequence in zip(runs[1:], sequences[1:]):
        assert torch.equal(logits, runs[0][1])
        assert torch.equal(sequence["logits"], sequences[0]["logits"])


@pytest.mark.parametrize("name", list(MODELS))
def test_no_key_is_bit_identical_to_every_demonstration_at_full_length(name):
    policy = _model(name)
    with_key, _ = _trajectory(FULL_LENGTH)
    without, _ = _trajectory(FULL_LENGTH, with_key=False)
    assert (with_key[DEMO_STEPS_KEY] == N_MAX).all()
    with torch.no_grad():
        (inputs_key, logits_key), (inputs_bare, logits_bare) = _run_steps(policy, with_key), _run_steps(policy, without)
        outputs = _sequence(policy, inputs_key), _sequence(policy, inputs_bare)
    assert torch.equal(logits_key, logits_bare)
    for key in outputs[1].keys(include_nested=True, leaves_only=True):
        assert torch.equal(outputs[0][key], outputs[1][key]), key


# --------------------------------------------------------------------- the parts
def test_the_rpf_pointer_stops_at_each_demonstrations_last_step():
    policy = _model("rpf")  # the RPF rule: eta + 1 + tanh(b), tanh(b) = 0.9 untrained
    traj, _ = _trajectory()
    with torch.no_grad():
        out = _sequence(policy, _run_steps(policy, traj)[0])
    last = (traj[DEMO_STEPS_KEY] - 1).float()
    assert (out["next", "eta"] <= last).all() and (out["eta_used"] <= last).all()
    assert out["next", "eta"][0, 6].item() == 4.0  # 5 steps: stopped at 4, not at N_MAX - 1
    assert out["next", "eta"][2, T - 1].item() == 0.0  # 1 step: never moves
    cell = policy.cell
    b = torch.full((3, 1), 20.0)  # tanh(b) = 1
    eta = torch.full((3, 1), 7.5)
    capped = cell.update_pointer(eta, b, torch.tensor([[1], [8], [12]]))
    assert capped.squeeze(-1).tolist() == [0.0, 7.0, 9.5]
    assert torch.equal(cell.update_pointer(eta, b), cell.update_pointer(eta, b, torch.full((3, 1), N_MAX)))


def test_the_action_window_ends_with_a_short_demonstration():
    actions = torch.tensor([[2, 0, 1, 1, 2, 7, -1, 0, 0, 0, 0, 0]])  # 5 steps, then padding
    lengths = torch.tensor([[5]])
    for eta, centre in ((10.3, 4), (4.0, 4), (3.2, 3), (-2.0, 0)):
        window = action_window(actions, torch.tensor([[eta]]), 2, 3, lengths)
        assert torch.equal(window, action_window(actions[:, :5], torch.tensor([[eta]]), 2, 3)), eta
        expected = torch.zeros(5, 3)
        for slot, position in enumerate(range(centre - 2, centre + 3)):
            if 0 <= position < 5:
                expected[slot, actions[0, position]] = 1.0
        assert torch.equal(window[0], expected), eta
    # through the policy: late in a 5-step demonstration the pointer (0.9 a step) is past its end
    policy = _model("spf")
    traj, records = _trajectory()
    with torch.no_grad():
        out = _sequence(policy, _run_steps(policy, traj)[0])
    assert out["eta_used"][0, 6].item() > 5
    first_actions = records[0][4]
    expected = torch.cat([F.one_hot(first_actions[2:5], 3).float(), torch.zeros(2, 3)])
    assert torch.equal(out["action_window"][0, 6], expected)


def test_the_soft_action_memory_ends_with_a_short_demonstration():
    actions = torch.tensor([[2, 0, 1, 5, -4, 9], [1, 1, 0, 2, 2, 0]])
    lengths = torch.tensor([[3], [6]])
    eta = torch.tensor([[2.5], [1.25]])
    soft = soft_action_memory(actions, eta, 3, lengths)
    torch.testing.assert_close(soft[:1], soft_action_memory(actions[:1, :3], eta[:1], 3), rtol=0, atol=1e-7)
    assert torch.equal(soft[1:], soft_action_memory(actions[1:], eta[1:], 3))


def test_the_memory_holds_each_demonstrations_own_frames():
    traj, records = _trajectory()
    first = traj[:, 0].clone()  # lengths 5, 9, 12
    for name, slots in (("spf", [memory_length(n, 0.5) for n in (5, 9, 12)]), ("spf_random", [5, 9, 12])):
        torch.manual_seed(0)
        counter = CountingEncoder(ImageEncoder(16, (H, W)))
        config = dataclasses.replace(CFG, sparsity=0.6, sparsity_range=(0.2, 1.0)) if name == "spf_random" else CFG
        policy = SPFPolicy(config, counter).eval()
        with torch.no_grad():
            out = policy(first.clone())
        # only the frames of the demonstrations are encoded (plus the 3 observations), never the padding
        assert counter.frames == 3 + sum(slots), name
        memory = out["memory_features"]
        for row, used in enumerate(slots):
            assert (memory[row, used:] == 0).all() and (memory[row, :used].abs().sum(-1) > 0).any(), name
        if name == "spf_random":
            assert torch.equal(out["memory_mask"], padded_memory_mask(first[DEMO_STEPS_KEY], N_MAX, 0.6))
            assert not out["memory_mask"][0, 5:].any()
    # a fixed-sparsity row of 5 steps holds phi at memory_indices(5, 0.5), in its first slots
    frames = records[0][3]
    torch.manual_seed(0)
    policy = SPFPolicy(CFG).eval()
    with torch.no_grad():
        memory = policy(first.clone())["memory_features"]
        expected = policy.encoder.module(frames[memory_indices(5, 0.5)])
    torch.testing.assert_close(memory[0, : expected.shape[0]], expected, rtol=0, atol=1e-6)


def test_training_draws_a_mask_of_each_demonstrations_length():
    torch.manual_seed(0)
    policy = SPFPolicy(dataclasses.replace(CFG, sparsity_range=(0.2, 1.0))).train()
    traj, _ = _trajectory()
    with set_recurrent_mode(True):
        out = policy(traj.clone())
    out["logits"].sum().backward()
    assert policy.encoder.module.head[0].weight.grad.abs().sum() > 0
    for row, start in ((0, 0), (0, 7), (1, 0), (2, 0), (2, 4)):
        n = int(traj[DEMO_STEPS_KEY][row, start])
        mask = out["memory_mask"][row, start]
        assert not mask[n:].any() and mask[0]
        assert memory_length(n, 0.2) <= int(mask.sum()) <= n


def test_open_loop_takes_its_after_demo_action_after_n_i_steps():
    policy = OpenLoopPolicy(3)
    actions = torch.tensor([[0, 2, 9, 9], [2, 2, 0, 2], [0, 0, 2, -7]])  # 2, 4 and 3 steps, padded
    td = TensorDict(
        demo_actions=actions, demo_steps=torch.tensor([[2], [4], [3]]), is_init=torch.ones(3, 1, dtype=torch.bool),
        batch_size=[3],
    )
    replayed = []
    for _ in range(6):
        out = policy(td.clone())
        replayed.append(out["action"].tolist())
        assert (out["logits"].argmax(-1) == out["action"]).all()
        td.set("open_loop_step", out["next", "open_loop_step"])
        td.set("is_init", torch.zeros(3, 1, dtype=torch.bool))
    after = 1  # turn left
    assert [r[0] for r in replayed] == [0, 2, after, after, after, after]
    assert [r[1] for r in replayed] == [2, 2, 0, 2, after, after]
    assert [r[2] for r in replayed] == [0, 0, 2, after, after, after]
    assert OpenLoopPolicy(4)(td.clone())["action"].tolist() == [3, 3, 3]  # STOP after every demonstration


# --------------------------------------------------------------------- keys and errors
def test_the_key_is_declared_and_can_be_renamed():
    policy = SPFPolicy(CFG)
    assert policy.demo_steps_key == DEMO_STEPS_KEY == "demo_steps"
    for module in (policy, policy.memory, policy.attention, policy.cell, OpenLoopPolicy(3)):
        assert DEMO_STEPS_KEY in module.in_keys, type(module).__name__
        assert DEMO_STEPS_KEY not in module.out_keys
    traj, _ = _trajectory()
    first = traj[:, 0].clone()
    renamed = SPFPolicy(CFG, demo_steps_key="n_steps")
    renamed.load_state_dict(policy.state_dict())
    assert "n_steps" in renamed.in_keys and DEMO_STEPS_KEY not in renamed.in_keys
    moved = first.clone()
    moved.set("n_steps", moved.pop(DEMO_STEPS_KEY))
    with torch.no_grad():
        assert torch.equal(renamed(moved)["logits"], policy(first.clone())["logits"])
        ignoring = SPFPolicy(CFG, demo_steps_key=None)
        ignoring.load_state_dict(policy.state_dict())
        clipped = _clip_actions(first)
        assert torch.equal(ignoring(clipped.clone())["logits"], policy(clipped.exclude(DEMO_STEPS_KEY))["logits"])
    assert DEMO_STEPS_KEY not in ignoring.in_keys


@pytest.mark.parametrize("bad", [0, -1, N_MAX + 1])
def test_demo_steps_outside_its_range_raise_before_any_work(bad):
    counter = CountingEncoder(ImageEncoder(16, (H, W)))
    policy = SPFPolicy(CFG, counter)
    traj, _ = _trajectory()
    traj[DEMO_STEPS_KEY][1, 2] = bad
    message = rf"demo_steps must hold .* an integer in \[1, {N_MAX}\]"
    with pytest.raises(ValueError, match=message):
        policy(traj[:, 2].clone())
    with pytest.raises(ValueError, match=message), set_recurrent_mode(True):
        policy(traj.clone())
    assert counter.frames == 0
    step = traj[:, 2].clone()
    memory = SparseMemory(ImageEncoder(16, (H, W)), N_MAX, 0.5)
    attention = MemoryAttention(PointerAttention(16, 16), memory.indices, sparsity=0.5)
    cell = SPFCell((16, 16, 15), 16, 3, N_MAX)
    step.update({"memory_features": torch.zeros(3, 6, 16), "eta_used": torch.zeros(3, 1), "mu": torch.zeros(3, 16),
                 "pixel_features": torch.zeros(3, 16), "action_window": torch.zeros(3, 5, 3)})
    for part in (memory, attention, cell, OpenLoopPolicy(3)):
        with pytest.raises(ValueError, match=message):
            part(step.clone())


@pytest.mark.parametrize(
    "value", [torch.full((3, 1), 4.0), torch.full((3, 1), True), torch.full((3, 2), 4)], ids=["float", "bool", "shape"]
)
def test_demo_steps_of_the_wrong_type_or_shape_raise(value):
    traj, _ = _trajectory()
    step = traj[:, 0].clone()
    step.set(DEMO_STEPS_KEY, value)
    with pytest.raises(ValueError, match=r"demo_steps must be an integer tensor of shape \[\*batch, 1\]"):
        SPFPolicy(CFG)(step)
