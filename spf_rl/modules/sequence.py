"""Sequence mode of :class:`~spf_rl.modules.SPFPolicy`: attention and GRU cell unrolled together over time.

The attention at step ``t`` reads the pointer the cell wrote at step ``t - 1``,
so the two cannot run over all steps one after the other; frames and memories
are encoded for every step at once, then the loop runs on tensors (no
TensorDict work per step).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase

from spf_rl.modules.td_utils import flat_or_zeros, init_flags, next_key

if TYPE_CHECKING:
    from spf_rl.modules.policy import SPFPolicy


def unroll_sequence(policy: SPFPolicy, tensordict: TensorDictBase, valid: torch.Tensor | None = None) -> TensorDictBase:
    """Run ``policy`` over a ``[*B, T]`` sequence (time last), writing its outputs for every step.

    A segment (``t = 0`` or ``is_init``) starts from the stored ``h`` and ``eta`` of
    that step, as in :class:`~torchrl.modules.GRUModule`.

    ``valid`` (``[*B, T]`` bool, e.g. a training batch's ``mask``): only these steps'
    frames are encoded; the others get zero features. For padding *after* an
    episode's last step: every output is causal, so the valid steps' outputs are
    those of the full sequence, and the padded steps' outputs are meaningless.
    """
    if tensordict.batch_dims == 0:
        raise ValueError(
            "SPFPolicy in recurrent mode needs an input with a time dimension "
            "(batch shape [*B, T]); got a 0-d tensordict."
        )
    policy.check_inputs(tensordict)
    policy.encode_pixels(tensordict, valid)
    segments = policy.memory.encode_segments(tensordict) if policy.use_memory else None
    td = tensordict.reshape(-1, tensordict.shape[-1])
    rows, steps = td.batch_size
    # per-step views by unbind and per-segment gathers: their backward passes stack and
    # index-add small tensors, where t-slices of [B, T, ...] tensors would each
    # accumulate a zero-filled gradient of the whole sequence
    phi = td.get(policy.encoder.out_keys[0]).reshape(rows, steps, -1).unbind(1)
    demo_actions = td.get(policy.demo_actions_key).reshape(rows, steps, -1).long().unbind(1)
    start = init_flags(td, policy.is_init_key, phi[0].device).clone()
    start[:, 0] = True
    h0 = flat_or_zeros(td.get(policy.hidden_key, None), (rows, steps, policy.config.hidden_size), phi[0])
    eta0 = flat_or_zeros(td.get(policy.eta_key, None), (rows, steps, 1), phi[0])
    h, eta = h0[:, 0], eta0[:, 0]
    outputs: dict[str, list[torch.Tensor]] = {name: [] for name in ("logits", "h", "eta_used", "eta_next", "mu", "window")}
    for t in range(steps):
        segment_start = start[:, t].unsqueeze(-1)
        h = torch.where(segment_start, h0[:, t], h)
        eta = torch.where(segment_start, eta0[:, t], eta)
        memory = mask = None
        if segments is not None:
            feats, segment, masks = segments
            memory = feats.index_select(0, segment[:, t])
            mask = masks.index_select(0, segment[:, t]) if masks is not None else None
        mu, window = policy.attention.attend(memory, demo_actions[t], eta, mask)
        logits, h, eta_next = policy.cell.step(mu, phi[t], window, eta, h)
        for name, value in zip(outputs, (logits, h, eta, eta_next, mu, window)):
            outputs[name].append(value)
        eta = eta_next
    stacked = {name: torch.stack(values, 1) for name, values in outputs.items()}
    out = {
        policy.logits_key: stacked["logits"],
        policy.features_key: stacked["h"],
        policy.eta_used_key: stacked["eta_used"],
        policy.attention.mu_key: stacked["mu"],
        policy.attention.action_window_key: stacked["window"],
        next_key(policy.hidden_key): stacked["h"],
        next_key(policy.eta_key): stacked["eta_next"],
    }
    shape = tensordict.batch_size
    for key, value in out.items():
        tensordict.set(key, value.reshape(*shape, *value.shape[2:]))
    if segments is not None:
        policy.memory.write_segments(tensordict, *segments)
    return tensordict
