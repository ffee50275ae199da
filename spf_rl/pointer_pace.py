"""The pointer's pace: how many demonstration steps a policy's attention pointer moves per step.

SPF's pointer follows the paper's eq. 4, ``eta_{t+1} = eta_t + tanh(b)``, so it may move
backwards. Behaviour cloning can drive ``tanh(b)`` towards -1 early in training (the
pointer head's bias starts at ``atanh(initial_pointer_step)``, then Adam moves it): the
pointer then leaves the memory through its first frame within a few steps of every
episode, the memory no longer reaches the logits, and the trained policy follows routes
worse than open-loop replay whatever its sparsity. RPF's rule, ``eta_t + 1 + tanh(b)``,
cannot move backwards.

:func:`pointer_pace` feeds a policy stored episodes (teacher-forced: the expert's
observations, in sequence mode and eval mode) and returns the mean of
``eta_{t+1} - eta_t`` over their valid steps: about 1 for a pointer that keeps pace with
a demonstration of the episode's length, below :data:`BACKWARD_PACE` for one that runs
backwards. ``recipes/table1.py`` reports it for every checkpoint it scores.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.modules import set_recurrent_mode

#: A mean pace below this (demonstration steps per step) means the pointer runs backwards.
BACKWARD_PACE = 0.0
#: Episodes per forward pass.
DEFAULT_BATCH_SIZE = 32


def pointer_pace(policy: torch.nn.Module, episodes: TensorDictBase, batch_size: int = DEFAULT_BATCH_SIZE) -> float:
    """Mean pointer increment ``eta_{t+1} - eta_t`` over the valid steps of ``episodes``.

    Args:
        policy: an SPF-family policy (its outputs hold ``eta_used`` and ``("next", "eta")``);
            it is switched to eval mode.
        episodes: stored episodes with their demonstrations ``[E]`` (the layout of
            :func:`spf_rl.data.empty_training_episodes`, or a dataset's batch).
        batch_size: episodes per forward pass.

    Returns:
        The mean increment, demonstration steps per step.

    Raises:
        ValueError: ``batch_size`` below 1, no valid step, or a policy without a pointer.

    Examples:
        >>> from envs import EpisodeSpec
        >>> from spf_rl.data import DatasetConfig, empty_training_episodes
        >>> from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
        >>> config = spf_config(ModelConfig(name="spf", feature_dim=8, hidden_size=8, initial_pointer_step=-0.5),
        ...                     demo_length=5, image_size=32)
        >>> episodes = empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=5, max_steps=6, image_size=32), num_episodes=2))
        >>> episodes["steps", "mask"][:, :4] = True
        >>> round(pointer_pace(build_policy("spf", config), episodes), 3)  # untrained: tanh(b) is the initial step
        -0.5
    """
    from spf_rl.modules.views import episodes_to_sequence

    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
    if not bool(episodes.get(("steps", "mask")).any()):
        raise ValueError("episodes have no valid step (steps.mask is all false).")
    if not {"eta_used", ("next", "eta")} <= set(getattr(policy, "out_keys", ())):
        raise ValueError(f"policy {type(policy).__name__} has no attention pointer (no 'eta_used' and ('next', 'eta') outputs).")
    device = next(policy.parameters(), torch.empty(0)).device
    policy.eval()
    total, count = 0.0, 0
    with torch.no_grad(), set_recurrent_mode(True):
        for start in range(0, episodes.shape[0], batch_size):
            batch = episodes[start : start + batch_size]
            if not bool(batch.get(("steps", "mask")).any()):
                continue
            sequence = episodes_to_sequence(batch, device)
            out = policy(sequence, valid=sequence.get("mask"))
            mask = out.get("mask")
            steps = (out.get(("next", "eta")) - out.get("eta_used")).squeeze(-1)[mask]
            total, count = total + float(steps.double().sum()), count + int(mask.sum())
    return total / count


__all__ = ["BACKWARD_PACE", "DEFAULT_BATCH_SIZE", "pointer_pace"]
