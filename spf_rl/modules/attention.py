"""Pointer attention over the sparse memory (paper Sec. 3.2, eq. 2).

``mu_t = psi( sum_j m_j exp(-|eta_t - M*(j)|), a[floor(eta_t)-k .. floor(eta_t)+k] )``:
soft attention over the memory features with un-normalised weights that decay
with the distance between the pointer ``eta_t`` and each memory frame's demo
index, a hard window of one-hot demo actions around the pointer, and a linear
fusion layer ``psi``. Indices and the pointer are 0-based here.

Optionally ``psi`` also takes the *soft action memory*
``sum_{j=0}^{n-1} exp(-|eta_t - j|) onehot(a_j)``: the same un-normalised weights
as eq. 2, over all ``n`` demonstration actions (every action is in memory). It is
differentiable in ``eta``, unlike the hard window (which only sees
``floor(eta)``); this is how the action-only baseline's pointer gets a gradient,
in the spirit of the action memory of RPF (Kumar et al. 2019).

A demonstration of ``n_i`` steps padded to ``n`` (the optional ``demo_steps`` input)
ends at ``n_i``: the window's centre is clamped to ``[0, n_i - 1]``, positions from
``n_i`` on are zero one-hots, the soft action memory sums over ``0 .. n_i - 1`` only,
and memory slots past the demonstration get weight 0 (``lengths`` below).
"""
from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from spf_rl.modules.anchor import PointerAnchor
from spf_rl.modules.memory import padded_memory_indices, validate_sparsity
from spf_rl.modules.replay_gate import start_cosine
from spf_rl.modules.td_utils import (
    ANCHOR_CONFIDENCE_KEY,
    ANCHOR_KEY,
    DEMO_STEPS_KEY,
    START_COSINE_KEY,
    demo_lengths,
    flat_or_zeros,
    init_flags,
    with_batch_dim,
)

logger = logging.getLogger(__name__)

__all__ = ["MemoryAttention", "PointerAttention", "action_window", "attention_weights", "soft_action_memory"]

#: Default half-width k of the hard action window (window size 2k+1).
DEFAULT_WINDOW_HALF_WIDTH = 2
#: Default number of action classes in the demonstration (forward, left, right).
DEFAULT_NUM_ACTION_CLASSES = 3


def attention_weights(
    eta: torch.Tensor, indices: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Soft weights ``w_j = exp(-|eta - M*(j)|)`` (un-normalised, eq. 2).

    Args:
        eta (torch.Tensor): pointer, shape ``[*, 1]`` (0-based, float).
        indices (torch.Tensor): memory indices ``M*``, shape ``[l]`` (0-based), or ``[*, l]``
            (one set per row, e.g. :func:`~spf_rl.modules.memory.padded_memory_indices`).
        mask (torch.Tensor, optional): boolean ``[*, l]`` (or broadcastable); the
            weights of the slots where it is false are exactly 0. Defaults to all
            slots kept.

    Returns:
        torch.Tensor: weights of shape ``[*, l]``.

    Examples:
        >>> import torch
        >>> attention_weights(torch.tensor([[1.0]]), torch.arange(3), torch.tensor([True, False, True]))
        tensor([[0.3679, 0.0000, 0.3679]])
    """
    weights = torch.exp(-(eta - indices.to(eta.dtype)).abs())
    if mask is not None:
        weights = weights.masked_fill(~mask.to(device=weights.device, dtype=torch.bool), 0.0)
    return weights


def action_window(
    demo_actions: torch.Tensor,
    eta: torch.Tensor,
    k: int,
    num_classes: int,
    lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """One-hot demo actions at ``floor(eta)-k .. floor(eta)+k``, zero-padded outside the demo.

    ``floor(eta)`` is clamped to ``[0, n - 1]`` first; window positions outside
    ``[0, n - 1]`` get an all-zero one-hot. With ``lengths``, each row's demonstration
    ends at its ``n_i``: ``n_i`` replaces ``n`` (the padding actions are never read).

    Args:
        demo_actions (torch.Tensor): int64 ``[*, n]`` demo actions.
        eta (torch.Tensor): pointer ``[*, 1]`` (0-based, float).
        k (int): half-width of the window.
        num_classes (int): number of action classes (one-hot size).
        lengths (torch.Tensor, optional): int ``[*, 1]``, each demonstration's number of
            steps ``n_i`` in ``[1, n]``. Defaults to ``n`` for every row.

    Returns:
        torch.Tensor: float tensor ``[*, 2k + 1, num_classes]``.

    Examples:
        >>> import torch
        >>> acts = torch.tensor([[0, 1, 2, 9]])  # 3 steps, padded with 9
        >>> action_window(acts, torch.tensor([[5.0]]), 1, 3, lengths=torch.tensor([[3]])).argmax(-1).tolist()
        [[1, 2, 0]]
        >>> action_window(acts, torch.tensor([[5.0]]), 1, 3, lengths=torch.tensor([[3]])).sum(-1).tolist()
        [[1.0, 1.0, 0.0]]
    """
    n = demo_actions.shape[-1]
    offsets = torch.arange(-k, k + 1, device=eta.device)
    if lengths is None:
        centre = eta.detach().floor().long().clamp(0, n - 1)  # [*, 1]
        pos = centre + offsets  # [*, 2k+1]
        valid = (pos >= 0) & (pos < n)
        acts = demo_actions.gather(-1, pos.clamp(0, n - 1))
    else:
        last = lengths.to(device=eta.device, dtype=torch.long) - 1  # [*, 1]
        centre = torch.minimum(eta.detach().floor().long().clamp(min=0), last)
        pos = centre + offsets
        valid = (pos >= 0) & (pos <= last)
        acts = demo_actions.gather(-1, torch.minimum(pos.clamp(min=0), last))
    onehot = F.one_hot(acts, num_classes).to(eta.dtype)
    return onehot * valid.unsqueeze(-1).to(eta.dtype)


def soft_action_memory(
    demo_actions: torch.Tensor, eta: torch.Tensor, num_classes: int, lengths: torch.Tensor | None = None
) -> torch.Tensor:
    """Soft-attended action memory ``sum_j exp(-|eta - j|) onehot(a_j)`` over all ``n`` demo actions.

    The weights are those of eq. 2 (un-normalised) with the memory indices
    ``0 .. n-1``. Unlike :func:`action_window` it is differentiable in ``eta``.

    Args:
        demo_actions (torch.Tensor): int64 ``[*, n]`` demo actions.
        eta (torch.Tensor): pointer ``[*, 1]`` (0-based, float).
        num_classes (int): number of action classes (one-hot size).
        lengths (torch.Tensor, optional): int ``[*, 1]``, each demonstration's number of
            steps ``n_i``: the sum runs over ``j < n_i`` (the padding is never read).
            Defaults to ``n`` for every row.

    Returns:
        torch.Tensor: float tensor ``[*, num_classes]``.

    Examples:
        >>> import torch
        >>> soft_action_memory(torch.tensor([[0, 1, 1]]), torch.tensor([[1.0]]), 2)
        tensor([[0.3679, 1.3679]])
        >>> soft_action_memory(torch.tensor([[0, 1, 7]]), torch.tensor([[1.0]]), 2, lengths=torch.tensor([[2]]))
        tensor([[0.3679, 1.0000]])
    """
    n = demo_actions.shape[-1]
    positions = torch.arange(n, device=eta.device)
    if lengths is None:
        weights = attention_weights(eta, positions)  # [*, n]
    else:
        steps = positions < lengths.to(eta.device)  # [*, n]
        weights = attention_weights(eta, positions, steps)
        demo_actions = demo_actions.masked_fill(~steps, 0)
    onehot = F.one_hot(demo_actions.long(), num_classes).to(eta.dtype)  # [*, n, C]
    return (weights.unsqueeze(-1) * onehot).sum(-2)


class PointerAttention(nn.Module):
    """Soft attention over memory features + hard action window, fused by a linear ``psi``.

    ``psi`` takes ``[attended memory (D, unless action_only), window ((2k+1) * C),
    soft action memory (C, if soft_action_memory)]`` concatenated in that order.

    Args:
        feature_dim (int): size ``D`` of a memory feature (ignored when ``action_only``).
        out_dim (int): size of the fused output ``mu``.
        k (int, optional): half-width of the action window. Defaults to 2.
        num_action_classes (int, optional): one-hot size of a demo action. Defaults to 3.
        action_only (bool, optional): if ``True`` there is no visual memory and ``psi``
            takes only the action part. Defaults to ``False``.
        soft_action_memory (bool, optional): if ``True``, ``psi`` also takes the soft
            action memory (:func:`soft_action_memory`, ``num_action_classes`` values),
            concatenated after the action window. Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from spf_rl.modules import PointerAttention
        >>> att = PointerAttention(feature_dim=8, out_dim=16)
        >>> mem = torch.randn(2, 4, 8)
        >>> idx = torch.tensor([0, 3, 6, 9])
        >>> acts = torch.randint(0, 3, (2, 10))
        >>> eta = torch.tensor([[0.0], [4.5]])
        >>> att(mem, idx, acts, eta).shape
        torch.Size([2, 16])
        >>> att.weights_and_window(idx, acts, eta)[1].shape  # window [B, 2k+1, classes]
        torch.Size([2, 5, 3])
    """

    def __init__(
        self,
        feature_dim: int,
        out_dim: int,
        k: int = DEFAULT_WINDOW_HALF_WIDTH,
        num_action_classes: int = DEFAULT_NUM_ACTION_CLASSES,
        action_only: bool = False,
        soft_action_memory: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(k, int) or k < 0:
            raise ValueError(f"k (action window half-width) must be an int >= 0, got {k!r}.")
        if not isinstance(num_action_classes, int) or num_action_classes < 1:
            raise ValueError(
                f"num_action_classes must be a positive int, got {num_action_classes!r}."
            )
        self.feature_dim = feature_dim
        self.out_dim = out_dim
        self.k = k
        self.num_action_classes = num_action_classes
        self.action_only = action_only
        self.soft_action_memory = bool(soft_action_memory)
        self.window_dim = (2 * k + 1) * num_action_classes
        in_dim = (
            self.window_dim
            + (0 if action_only else feature_dim)
            + (num_action_classes if self.soft_action_memory else 0)
        )
        self.psi = nn.Linear(in_dim, out_dim)

    def weights_and_window(
        self,
        indices: torch.Tensor | None,
        demo_actions: torch.Tensor,
        eta: torch.Tensor,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """Return the soft weights ``[*, l]`` (``None`` when action-only; 0 where ``mask``
        is false) and the window ``[*, 2k+1, C]`` (of demonstrations of ``lengths`` steps, if given)."""
        if demo_actions.dtype != torch.long:
            demo_actions = demo_actions.long()
        weights = (
            None if self.action_only or indices is None else attention_weights(eta, indices, mask)
        )
        return weights, action_window(demo_actions, eta, self.k, self.num_action_classes, lengths)

    def forward(
        self,
        memory_features: torch.Tensor | None,
        indices: torch.Tensor | None,
        demo_actions: torch.Tensor,
        eta: torch.Tensor,
        return_window: bool = False,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Compute ``mu``.

        Args:
            memory_features (torch.Tensor or None): ``[*, l, D]`` (``None`` when action-only).
            indices (torch.Tensor or None): memory indices ``M*`` ``[l]`` (or ``[*, l]``, per row).
            demo_actions (torch.Tensor): int64 ``[*, n]``.
            eta (torch.Tensor): pointer ``[*, 1]`` (0-based, float).
            return_window (bool, optional): also return the action window
                ``[*, 2k+1, C]``. Defaults to ``False``.
            mask (torch.Tensor, optional): boolean ``[*, l]``: memory slots to attend
                to. The weights of the other slots are exactly 0 (set before they
                multiply the features), so those features do not reach ``mu``.
                Defaults to all slots.
            lengths (torch.Tensor, optional): int ``[*, 1]``, each demonstration's number
                of steps ``n_i`` (demonstrations padded to ``n``): the action window and
                the soft action memory end at ``n_i`` (the memory slots past it are
                ``mask``'s to hide). Defaults to ``n`` for every row.

        Returns:
            torch.Tensor: ``mu`` of shape ``[*, out_dim]`` (and the window if asked).
        """
        weights, window = self.weights_and_window(indices, demo_actions, eta, mask, lengths)
        parts = []
        if not self.action_only:
            if memory_features is None or weights is None:
                raise ValueError(
                    "memory_features and indices are required unless action_only=True."
                )
            if memory_features.shape[-2] != weights.shape[-1]:
                raise ValueError(
                    f"memory_features has {memory_features.shape[-2]} frames but indices has "
                    f"{weights.shape[-1]}."
                )
            parts.append((weights.unsqueeze(-1) * memory_features).sum(-2))
        parts.append(window.flatten(-2))
        if self.soft_action_memory:
            parts.append(
                soft_action_memory(demo_actions.long(), eta, self.num_action_classes, lengths)
            )
        mu = self.psi(torch.cat(parts, -1))
        return (mu, window) if return_window else mu


class MemoryAttention(TensorDictModuleBase):
    """SPF's pointer attention as a TensorDict module (eq. 2): ``eta``, memory, demo actions -> ``mu``.

    Reads the pointer ``eta`` (reset to 0 where ``is_init``; a missing key counts as
    0), the memory features and their ``memory_mask`` (if any) and the demo actions;
    writes ``mu``, the hard ``action_window`` ``[2k+1, C]`` and ``eta_used``, the
    pointer this step read. The attention at step ``t`` reads the pointer of step
    ``t - 1``, so over a sequence it runs inside the recurrent loop of
    :class:`~spf_rl.modules.SPFPolicy` (:meth:`attend` on tensors); this module is
    its single-step form.

    With the optional ``demo_steps`` input (each row's demonstration length ``n_i``,
    demonstrations padded to ``n``), the demonstration ends at ``n_i``: the action
    window and soft action memory stop there (``lengths`` of
    :meth:`PointerAttention.forward`), and no slot past it is attended. The slots'
    demo indices are those :class:`~spf_rl.modules.SparseMemory` lays out: with
    ``sparsity`` (a fixed-sparsity memory), ``memory_indices(n_i, sparsity)`` in the
    first slots; without, ``indices`` (one slot per frame), those ``>= n_i`` masked.

    Args:
        attention (PointerAttention): the fusion layer psi and its settings.
        indices (torch.Tensor, optional): demo index of each memory slot (``M*``);
            ``None`` for the action-only baseline.

    Keyword Args:
        sparsity (float, optional): the fixed sparsity ``indices`` were chosen at
            (``indices == memory_indices(n, sparsity)``); ``None`` (default) for a memory
            with a slot per demo frame (random sparsity) or no memory.
        eta_key, is_init_key, memory_key, memory_mask_key, demo_actions_key (NestedKey): inputs.
        demo_steps_key (NestedKey, optional): optional input, each demonstration's length
            ``n_i`` (int64 ``[1]``); ``None``: never read. Defaults ``"demo_steps"``.
        mu_key, action_window_key, eta_used_key (NestedKey): outputs. Defaults ``"mu"``,
            ``"action_window"``, ``"eta_used"``.
        anchor (PointerAnchor, optional): also locate the current frame among the slots near
            the pointer (:mod:`spf_rl.modules.anchor`), reading ``pixel_features_key`` and
            writing ``anchor_key`` and ``anchor_confidence_key``. Defaults to ``None``.
        start_check (bool): also write ``start_cosine_key``, the cosine of the frame's features with
            the memory's first frame (:func:`~spf_rl.modules.replay_gate.start_cosine`), reading
            ``pixel_features_key``. Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spf_rl.modules import MemoryAttention, PointerAttention, memory_indices
        >>> attend = MemoryAttention(PointerAttention(feature_dim=8, out_dim=16), memory_indices(10, 0.4))
        >>> td = TensorDict({"eta": torch.zeros(2, 1), "memory_features": torch.randn(2, 4, 8),
        ...                  "demo_actions": torch.randint(0, 3, (2, 10))}, batch_size=[2])
        >>> attend(td)["mu"].shape, td["action_window"].shape
        (torch.Size([2, 16]), torch.Size([2, 5, 3]))
        >>> attend.in_keys
        ['eta', 'is_init', 'demo_actions', 'memory_features', 'demo_steps']
    """

    def __init__(
        self,
        attention: PointerAttention,
        indices: torch.Tensor | None,
        *,
        sparsity: float | None = None,
        eta_key: NestedKey = "eta",
        is_init_key: NestedKey = "is_init",
        memory_key: NestedKey = "memory_features",
        memory_mask_key: NestedKey | None = None,
        demo_actions_key: NestedKey = "demo_actions",
        mu_key: NestedKey = "mu",
        action_window_key: NestedKey = "action_window",
        eta_used_key: NestedKey = "eta_used",
        demo_steps_key: NestedKey | None = DEMO_STEPS_KEY,
        anchor: PointerAnchor | None = None,
        pixel_features_key: NestedKey = "pixel_features",
        anchor_key: NestedKey = ANCHOR_KEY,
        anchor_confidence_key: NestedKey = ANCHOR_CONFIDENCE_KEY,
        start_check: bool = False,
        start_cosine_key: NestedKey = START_COSINE_KEY,
    ) -> None:
        super().__init__()
        if anchor is not None and indices is None:
            raise ValueError("an anchor needs a visual memory to match the frame against; this attention is action-only.")
        if start_check and indices is None:
            raise ValueError("a start check needs a visual memory to match the frame against; this attention is action-only.")
        self.attention = attention
        self.anchor = anchor
        self.start_check, self.start_cosine_key = bool(start_check), start_cosine_key
        self.pixel_features_key, self.anchor_key, self.anchor_confidence_key = pixel_features_key, anchor_key, anchor_confidence_key
        self.sparsity = None if sparsity is None else validate_sparsity(sparsity)
        self.register_buffer("indices", None if indices is None else torch.as_tensor(indices, dtype=torch.long), persistent=False)
        self.eta_key, self.is_init_key, self.demo_actions_key = eta_key, is_init_key, demo_actions_key
        self.memory_key = None if indices is None else memory_key
        self.memory_mask_key = memory_mask_key
        self.mu_key, self.action_window_key, self.eta_used_key = mu_key, action_window_key, eta_used_key
        self.demo_steps_key = demo_steps_key
        optional = [key for key in (self.memory_key, memory_mask_key, demo_steps_key) if key is not None]
        reads_frame = anchor is not None or self.start_check
        self.in_keys = [eta_key, is_init_key, demo_actions_key, *optional] + ([pixel_features_key] if reads_frame else [])
        self.out_keys = (
            [mu_key, action_window_key, eta_used_key]
            + ([anchor_key, anchor_confidence_key] if anchor is not None else [])
            + ([start_cosine_key] if self.start_check else [])
        )

    def attend(
        self,
        memory: torch.Tensor | None,
        demo_actions: torch.Tensor,
        eta: torch.Tensor,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``mu`` ``[*, out_dim]`` and the action window ``[*, 2k+1, C]`` on tensors; ``lengths``
        (int ``[*, 1]``, optional): each row's demonstration length ``n_i``."""
        indices, mask = self.slots(demo_actions.shape[-1], mask, lengths)
        return self.attention(memory, indices, demo_actions, eta, return_window=True, mask=mask, lengths=lengths)

    def slots(
        self, demo_length: int, mask: torch.Tensor | None, lengths: torch.Tensor | None
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Each memory slot's route step (``[l]``, or ``[*, l]`` per row) and which slots hold the
        route's frames (``mask`` and the slots within each row's ``lengths``; ``None``: all)."""
        indices = self.indices
        if lengths is None or indices is None:
            return indices, mask
        lengths = lengths.to(indices.device)
        if self.sparsity is None:
            used = indices < lengths  # [*, l]
        else:
            indices, used = padded_memory_indices(lengths, demo_length, self.sparsity)
        return indices, used if mask is None else mask.to(dtype=torch.bool) & used

    def locate(
        self,
        memory: torch.Tensor,
        phi: torch.Tensor,
        eta: torch.Tensor,
        demo_length: int,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The anchor and its confidence ``[*, 1]`` (:meth:`PointerAnchor.locate`) of the frame's
        features ``phi`` among the slots of ``memory`` near ``eta``."""
        if self.anchor is None:
            raise RuntimeError("this attention has no anchor (SPFConfig.anchor_radius is None).")
        indices, used = self.slots(demo_length, mask, lengths)
        return self.anchor.locate(phi, memory, indices, used, eta)

    def start_cosine(
        self,
        memory: torch.Tensor,
        phi: torch.Tensor,
        demo_length: int,
        mask: torch.Tensor | None = None,
        lengths: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The cosine ``[*, 1]`` of the frame's features ``phi`` with the memory's first frame
        (:func:`~spf_rl.modules.replay_gate.start_cosine`)."""
        indices, used = self.slots(demo_length, mask, lengths)
        return start_cosine(phi, memory, indices, used)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One step: read ``eta`` (0 where ``is_init``), write ``mu``, ``action_window``, ``eta_used``."""
        return with_batch_dim(self._forward_step, tensordict)

    def _forward_step(self, td: TensorDictBase) -> TensorDictBase:
        batch = td.batch_size
        demo_actions = td.get(self.demo_actions_key).long()
        lengths = demo_lengths(td, self.demo_steps_key, demo_actions.shape[-1], batch)
        memory = td.get(self.memory_key) if self.memory_key is not None else None
        like = memory if memory is not None else torch.zeros((), device=demo_actions.device)
        eta = flat_or_zeros(td.get(self.eta_key, None), (*batch, 1), like)
        is_init = init_flags(td, self.is_init_key, eta.device)
        eta = torch.where(is_init.unsqueeze(-1), torch.zeros_like(eta), eta)
        mask = td.get(self.memory_mask_key) if self.memory_mask_key is not None else None
        mu, window = self.attend(memory, demo_actions, eta, mask, lengths)
        td.set(self.mu_key, mu)
        td.set(self.action_window_key, window)
        td.set(self.eta_used_key, eta)
        if self.anchor is not None or self.start_check:
            phi = td.get(self.pixel_features_key)
            flat = phi.reshape(-1, phi.shape[-1]).shape[0]
            flat_memory, flat_phi = memory.reshape(flat, *memory.shape[-2:]), phi.reshape(flat, -1)
            flat_mask = None if mask is None else mask.reshape(flat, -1)
            flat_lengths = None if lengths is None else lengths.reshape(flat, 1)
            if self.anchor is not None:
                place, confidence = self.locate(flat_memory, flat_phi, eta.reshape(flat, 1), demo_actions.shape[-1], flat_mask, flat_lengths)
                td.set(self.anchor_key, place.reshape(*batch, 1))
                td.set(self.anchor_confidence_key, confidence.reshape(*batch, 1))
            if self.start_check:
                cosine = self.start_cosine(flat_memory, flat_phi, demo_actions.shape[-1], flat_mask, flat_lengths)
                td.set(self.start_cosine_key, cosine.reshape(*batch, 1))
        return td
