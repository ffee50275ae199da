"""TensorDict modules of the SPF path-following policy: encoder, sparse memory, memory attention, cell, policy."""
from __future__ import annotations

from spf_rl.modules.anchor import PointerAnchor
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
from spf_rl.modules.factories import (
    make_action_only_policy,
    make_actor,
    make_rpf_original_policy,
    make_rpf_policy,
    make_spf_policy,
)
from spf_rl.modules.memory import (
    MemoryEncoder,
    memory_bytes,
    memory_indices,
    memory_length,
    memory_mask,
    padded_memory_indices,
    padded_memory_mask,
    validate_sparsity,
    validate_sparsity_range,
)
from spf_rl.modules.open_loop import OpenLoopPolicy
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.rpf import RPFAttention, SlotMLP
from spf_rl.modules.sparse_memory import SparseMemory
from spf_rl.modules.td_utils import DEMO_STEPS_KEY

__all__ = [
    "DEMO_STEPS_KEY",
    "ImageEncoder",
    "MemoryAttention",
    "MemoryEncoder",
    "OpenLoopPolicy",
    "PointerAnchor",
    "PointerAttention",
    "RPFAttention",
    "SPFCell",
    "SPFConfig",
    "SPFPolicy",
    "SlotMLP",
    "SparseMemory",
    "action_window",
    "attention_weights",
    "make_action_only_policy",
    "make_actor",
    "make_rpf_original_policy",
    "make_rpf_policy",
    "make_spf_policy",
    "memory_bytes",
    "memory_indices",
    "memory_length",
    "memory_mask",
    "padded_memory_indices",
    "padded_memory_mask",
    "soft_action_memory",
    "validate_sparsity",
    "validate_sparsity_range",
]
