"""TensorDict modules of the SPF path-following policy: encoder, sparse memory, memory attention, cell, policy."""
from __future__ import annotations

from spf_rl.modules.attention import (
    MemoryAttention,
    PointerAttention,
    action_window,
    attention_weights,
    soft_action_memory,
)
from spf_rl.modules.cell import SPFCell
from spf_rl.modules.config import SPFConfig
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
from spf_rl.modules.open_loop import OpenLoopPolicy
from spf_rl.modules.sparse_memory import SparseMemory
from spf_rl.modules.policy import (
    SPFPolicy,
    make_action_only_policy,
    make_actor,
    make_rpf_policy,
    make_spf_policy,
)

__all__ = [
    "ImageEncoder",
    "MemoryAttention",
    "MemoryEncoder",
    "OpenLoopPolicy",
    "PointerAttention",
    "SPFCell",
    "SPFConfig",
    "SPFPolicy",
    "SparseMemory",
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
