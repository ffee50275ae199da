"""The memory network of RPF as its authors' lab code builds it (GitHub ``bareblackfoot/RobustPathFollow``).

Kumar et al.'s RPF keeps every demonstration frame in memory. The lab code
(``models/model_rpf.py``) differs from SPF's memory in three ways, reproduced here:

* each memory slot is a 2-layer MLP (ReLU after both layers, 512 hidden units) over
  ``[phi(demo frame j), onehot(a_j)]``: :class:`SlotMLP`;
* ``mu_t = sum_j exp(-|eta_t - j|) m_j`` is the attended memory itself, with no
  fusion layer and no hard action window, and the GRU reads ``[phi(o_t), mu_t]``:
  :class:`RPFAttention`;
* the pointer moves by ``1 + tanh(b)`` and is capped at ``n - 1``, and the action
  and pointer heads are 2-layer MLPs with 256 hidden units.

:func:`make_rpf_original_policy` builds it from the same parts as SPF
(:class:`~spf_rl.modules.SPFPolicy`). The encoder is this project's, not the lab
code's VGG-like CNN.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from spf_rl.modules.attention import attention_weights

__all__ = ["RPFAttention", "SlotMLP"]

#: Hidden units of the memory-slot MLP (``visual_memory_fc`` in the lab code).
RPF_SLOT_HIDDEN = 512
#: Hidden units of the action and pointer heads (``GRU_out_fc``, ``GRU_attention_fc``).
RPF_HEAD_HIDDEN = 256


class SlotMLP(nn.Module):
    """One memory slot from a frame's features and its action: ``ReLU(W2 ReLU(W1 [phi, onehot(a)]))``.

    Args:
        feature_dim (int): size of ``phi``.
        num_action_classes (int): one-hot size of an action.
        memory_dim (int): size of a memory slot.
        hidden (int, optional): hidden units. Defaults to 512.

    Examples:
        >>> import torch
        >>> slot = SlotMLP(feature_dim=8, num_action_classes=3, memory_dim=16)
        >>> slot(torch.randn(2, 5, 8), torch.randint(0, 3, (2, 5))).shape
        torch.Size([2, 5, 16])
    """

    def __init__(self, feature_dim: int, num_action_classes: int, memory_dim: int, hidden: int = RPF_SLOT_HIDDEN) -> None:
        super().__init__()
        self.num_action_classes = num_action_classes
        self.feature_dim = memory_dim
        self.net = nn.Sequential(
            nn.Linear(feature_dim + num_action_classes, hidden), nn.ReLU(), nn.Linear(hidden, memory_dim), nn.ReLU()
        )

    def forward(self, features: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``[*, D]`` features and ``[*]`` actions -> ``[*, memory_dim]`` slots."""
        onehot = F.one_hot(actions.long(), self.num_action_classes).to(features.dtype)
        return self.net(torch.cat([features, onehot], -1))


class RPFAttention(nn.Module):
    """``mu = sum_j exp(-|eta - j|) m_j``: the attended memory, with no fusion layer and no action window.

    Has :class:`~spf_rl.modules.PointerAttention`'s interface; its window is empty
    (``[*, 0, C]``), so the GRU input is ``[mu, phi(o)]``.

    Args:
        memory_dim (int): size of a memory slot (and of ``mu``).
        num_action_classes (int): one-hot size of a demo action.

    Examples:
        >>> import torch
        >>> attend = RPFAttention(memory_dim=4, num_action_classes=3)
        >>> mu, window = attend(torch.ones(2, 6, 4), torch.arange(6), torch.zeros(2, 6, dtype=torch.long),
        ...                     torch.zeros(2, 1), return_window=True)
        >>> mu.shape, window.shape
        (torch.Size([2, 4]), torch.Size([2, 0, 3]))
    """

    action_only = False
    soft_action_memory = False
    window_dim = 0

    def __init__(self, memory_dim: int, num_action_classes: int) -> None:
        super().__init__()
        self.out_dim = memory_dim
        self.num_action_classes = num_action_classes

    def forward(
        self,
        memory_features: torch.Tensor,
        indices: torch.Tensor,
        demo_actions: torch.Tensor,
        eta: torch.Tensor,
        return_window: bool = False,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """The attended memory ``[*, memory_dim]`` (and an empty window if asked).

        ``lengths`` (each row's demonstration length) is not read: there is no action
        window, and ``mask`` hides the slots past a shorter demonstration."""
        weights = attention_weights(eta, indices, mask)
        mu = (weights.unsqueeze(-1) * memory_features).sum(-2)
        if not return_window:
            return mu
        return mu, mu.new_zeros(*mu.shape[:-1], 0, self.num_action_classes)
