"""Small helpers shared by the SPF TensorDict modules: next-step keys, state defaults, 0-d inputs."""
from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


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
