"""TensorDict modules of the SPF path-following policy: encoder, memory, attention, policy."""
from __future__ import annotations

from spf_rl.modules.attention import (
    PointerAttention,
    action_window,
    attention_weights,
    soft_action_memory,
)
from spf_rl.modules.encoder import ImageEncoder
from spf_rl.modules.memory import (
    MemoryEncoder,
    memory_bytes,
    memory_indices,
    memory_length,
    memory_mask,
    validate_sparsity,
    validate_sparsity_range,
)
from spf_rl.modules.policy import (
    OpenLoopPolicy,
    SPFConfig,
    SPFPolicy,
    make_action_only_policy,
    make_actor,
    make_rpf_policy,
    make_spf_policy,
)

__all__ = [
    "ImageEncoder",
    "MemoryEncoder",
    "OpenLoopPolicy",
    "PointerAttention",
    "SPFConfig",
    "SPFPolicy",
    "action_window",
    "attention_weights",
    "make_action_only_policy",
    "make_actor",
    "make_rpf_policy",
    "make_spf_policy",
    "memory_bytes",
    "memory_indices",
    "memory_length",
    "memory_mask",
    "soft_action_memory",
    "validate_sparsity",
    "validate_sparsity_range",
]
