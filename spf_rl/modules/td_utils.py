"""Small helpers shared by the SPF TensorDict modules: next-step keys, state defaults, 0-d inputs, demo lengths."""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

#: Optional per-episode input: the demonstration's own number of steps ``n_i`` (int64
#: ``[*batch, 1]``, ``1 <= n_i <= demo_length``); ``demo_frames`` and ``demo_actions`` are
#: padded after it. Absent, every demonstration is ``demo_length`` steps long.
DEMO_STEPS_KEY = "demo_steps"
#: Keys of the pointer's anchor (:mod:`spf_rl.modules.anchor`): the route step the current frame
#: matches near the pointer, and how well it matches (an expected cosine), ``[*batch, 1]`` each.
ANCHOR_KEY = "anchor"
ANCHOR_CONFIDENCE_KEY = "anchor_confidence"
#: The start check's keys (:mod:`spf_rl.modules.replay_gate`): this step's cosine of the frame with the
#: memory's first frame, and the recurrent start match (the first step's cosine), ``[*batch, 1]`` each.
START_COSINE_KEY = "start_cosine"
START_MATCH_KEY = "start_match"


def next_key(key: NestedKey) -> tuple[str, ...]:
    """``("next", *key)``: where a module writes the next step's value of a state key.

    Examples:
        >>> next_key("eta"), next_key(("agent", "h"))
        (('next', 'eta'), ('next', 'agent', 'h'))
    """
    return ("next", *((key,) if isinstance(key, str) else tuple(key)))


def flat_or_zeros(value: torch.Tensor | None, shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """``value`` reshaped to ``shape`` in ``like``'s dtype, or zeros when the key was missing."""
    if value is None:
        return like.new_zeros(shape)
    return value.reshape(shape).to(like.dtype)


def init_flags(tensordict: TensorDictBase, key: NestedKey, device: torch.device) -> torch.Tensor:
    """``is_init`` as a batch-shaped bool tensor (all false when the key is missing)."""
    value = tensordict.get(key, None)
    if value is None:
        return torch.zeros(tensordict.batch_size, dtype=torch.bool, device=device)
    return value.reshape(tensordict.batch_size)


def with_batch_dim(forward: Callable[[TensorDictBase], TensorDictBase], tensordict: TensorDictBase) -> TensorDictBase:
    """Run a step-mode ``forward`` that needs a batch dim on a possibly 0-d ``tensordict`` (in place)."""
    if tensordict.batch_dims:
        return forward(tensordict)
    out = forward(tensordict.unsqueeze(0))
    tensordict.update(out.squeeze(0))
    return tensordict


def demo_lengths(
    tensordict: TensorDictBase, key: NestedKey | None, demo_length: int, batch_shape: torch.Size | tuple[int, ...]
) -> torch.Tensor | None:
    """Each row's demonstration length ``n_i`` read at ``key`` (:data:`DEMO_STEPS_KEY`), checked.

    Args:
        tensordict: the input.
        key: where the lengths are (``None``: not read).
        demo_length: the padded length ``n_max`` (``SPFConfig.demo_length``).
        batch_shape: the rows' shape.

    Returns:
        int64 ``[*batch_shape, 1]``, or ``None`` where every demonstration is ``demo_length``
        steps long: the key is ``None`` or absent, or every ``n_i`` equals ``demo_length``
        (the fixed-length computation then runs, bit for bit).

    Raises:
        ValueError: the value is not one integer per row, or an ``n_i`` lies outside ``[1, demo_length]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"demo_steps": torch.tensor([[3], [6]])}, [2])
        >>> demo_lengths(td, DEMO_STEPS_KEY, 6, td.batch_size).tolist()
        [[3], [6]]
        >>> demo_lengths(td, DEMO_STEPS_KEY, 3, td.batch_size)
        Traceback (most recent call last):
        ...
        ValueError: demo_steps must hold each demonstration's number of steps, an integer in [1, 3] (1 to demo_length); got 3 to 6.
    """
    value = None if key is None else tensordict.get(key, None)
    if value is None:
        return None
    name = key if isinstance(key, str) else ".".join(key)
    rows = math.prod(batch_shape)
    if value.dtype == torch.bool or value.is_floating_point() or value.is_complex() or value.numel() != rows:
        raise ValueError(
            f"{name} must be an integer tensor of shape [*batch, 1] (one demonstration length per row, "
            f"batch {tuple(batch_shape)}), got dtype {value.dtype} and shape {tuple(value.shape)}."
        )
    if rows == 0:
        return None
    low, high = (int(v) for v in torch.aminmax(value))
    if low < 1 or high > demo_length:
        raise ValueError(
            f"{name} must hold each demonstration's number of steps, an integer in [1, {demo_length}] "
            f"(1 to demo_length); got {low} to {high}."
        )
    if low == demo_length:
        return None
    return value.reshape(*batch_shape, 1).long()
