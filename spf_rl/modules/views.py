"""Views of a policy: its network at another demonstration length, the bytes it carries for a
demonstration, and the sequence input it reads from stored episodes.

Evaluation, the studies (:mod:`spf_rl.eval`), taught routes (:mod:`spf_rl.teach`) and training
all read a policy through these, so none of them imports another's training code.
"""
from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDict

from envs.house_grid import check_demo_length
from spf_rl.data import MEMORY_MISMATCHED_KEY, ROUTE_STEP_KEY
from spf_rl.device import to_device
from spf_rl.modules.memory import memory_bytes
from spf_rl.modules.policy import SPFPolicy


def policy_for_length(policy: SPFPolicy, demo_length: int) -> SPFPolicy:
    """``policy``'s network for demonstrations of ``demo_length`` steps, sharing its parameters.

    The view is a new :class:`~spf_rl.modules.SPFPolicy` of ``policy.config`` with
    ``demo_length`` replaced, whose parameters (and persistent buffers) are ``policy``'s
    own tensors: training either trains both, loading weights into ``policy`` loads
    them into the view. Only the length-dependent index buffers differ.

    Raises:
        ValueError: a non-positive length, or a policy with a custom encoder (its
            parameters do not match a default-built network).

    An exported policy (:class:`~spf_rl.modules.exported.ExportedPolicy`) gives its ``at_length``.

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> policy = SPFPolicy(SPFConfig(demo_length=30, feature_dim=8, hidden_size=8, image_size=(16, 16)))
        >>> long = policy_for_length(policy, 100)
        >>> long.config.demo_length, long.memory_length, long.cell.gru.weight_hh is policy.cell.gru.weight_hh
        (100, 80, True)
    """
    check_demo_length(demo_length)
    if demo_length == policy.config.demo_length:
        return policy
    if hasattr(policy, "at_length"):  # an export run by ONNX Runtime (spf_rl.modules.exported): any length
        return policy.at_length(demo_length)
    parameters = policy.state_dict(keep_vars=True)
    view = SPFPolicy(dataclasses.replace(policy.config, demo_length=demo_length))
    if set(view.state_dict()) != set(parameters):
        raise ValueError(
            "policy_for_length needs a policy built from its config (the default encoder); "
            "this policy's parameters differ from a default-built network's."
        )
    for name in list(view.state_dict()):
        module_name, _, attribute = name.rpartition(".")
        module = view.get_submodule(module_name)
        if attribute in module._parameters:
            module._parameters[attribute] = parameters[name]
        else:
            module._buffers[attribute] = parameters[name]
    device = parameters[next(iter(parameters))].device if parameters else torch.device("cpu")
    return view.to(device).train(policy.training)


def episodes_to_sequence(batch: TensorDict, device: torch.device | str | None = None) -> TensorDict:
    """Turn a batch of stored episodes ``[B]`` into the policy's sequence input ``[B, T]`` on ``device``.

    Demonstration frames and actions come once per episode (looked up by ``demo_id`` at
    sampling); they move to ``device`` once and are broadcast over time as views (no
    copy). ``T`` is cut to the longest episode (read on the batch's device, before the move).
    Their :data:`~spf_rl.data.MEMORY_MISMATCHED_KEY` (where the batch has it) is broadcast too (bool ``[B, T]``).

    Args:
        batch: stored episodes (:mod:`spf_rl.data` layout).
        device: where the sequence goes (``None``: where the batch is).

    Examples:
        >>> from tensordict import TensorDict
        >>> mask = torch.tensor([[True, True, False], [True, False, False]])
        >>> steps = TensorDict({"pixels": torch.zeros(2, 3, 8, 8, 3, dtype=torch.uint8), "mask": mask,
        ...     "is_init": torch.zeros(2, 3, 1, dtype=torch.bool), "expert_action": torch.zeros(2, 3, dtype=torch.long)}, [2, 3])
        >>> batch = TensorDict({"steps": steps, "demo_frames": torch.zeros(2, 4, 8, 8, 3, dtype=torch.uint8),
        ...     "demo_actions": torch.zeros(2, 4, dtype=torch.long)}, [2])
        >>> sequence = episodes_to_sequence(batch, device="meta")
        >>> sequence.batch_size, sequence["demo_frames"].shape, sequence["pixels"].device
        (torch.Size([2, 2]), torch.Size([2, 2, 4, 8, 8, 3]), device(type='meta'))
    """
    steps = batch.get("steps")
    length = int(steps.get("mask").sum(-1).max())
    steps = to_device(steps[:, :length], device)
    b, t = steps.batch_size
    demo_frames = batch.get("demo_frames")
    demo_actions = batch.get("demo_actions")
    demonstration = {"demo_frames": demo_frames, "demo_actions": demo_actions}
    if "demo_steps" in batch.keys():  # demonstrations of several lengths, padded
        demonstration["demo_steps"] = batch.get("demo_steps")
    if MEMORY_MISMATCHED_KEY in batch.keys():  # another route's frames shown (conditions)
        demonstration[MEMORY_MISMATCHED_KEY] = batch.get(MEMORY_MISMATCHED_KEY).reshape(-1)
    sequence = {
        key: (value if device is None else value.to(device)).unsqueeze(1).expand(b, t, *value.shape[1:])
        for key, value in demonstration.items()
    }
    return TensorDict(
        {
            "pixels": steps.get("pixels"),
            "is_init": steps.get("is_init"),
            **sequence,
            "expert_action": steps.get("expert_action"),
            "mask": steps.get("mask"),
            **({ROUTE_STEP_KEY: steps.get(ROUTE_STEP_KEY)} if ROUTE_STEP_KEY in steps.keys() else {}),
        },
        batch_size=[b, t],
        device=device,
    )


def model_memory_bytes(model_type: str, demo_length: int, sparsity: float, image_size: int) -> int:
    """Bytes the agent carries for one demonstration: memory frames (uint8) plus all actions.

    ``"spf_random"`` at ``sparsity`` carries what ``"spf"`` does: only the frames its
    mask keeps, although its network holds a slot for every frame.
    """
    frame_shape = (3, image_size, image_size)
    if model_type == "action_only":
        return demo_length  # one byte per action, no frames
    return memory_bytes(demo_length, 1.0 if model_type in ("rpf", "rpf_original") else sparsity, frame_shape)


__all__ = ["episodes_to_sequence", "model_memory_bytes", "policy_for_length"]
