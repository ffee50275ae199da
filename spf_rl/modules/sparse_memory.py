"""The SPF memory as a TensorDict module: the demonstration's frames at ``M*``, encoded once per episode.

:class:`SparseMemory` reads ``demo_frames`` and ``is_init`` and the carried
``memory_features`` state, and writes the memory in use at this step to
``memory_features`` and to ``("next", "memory_features")``. Frames are encoded
only where a new episode (or, in sequence mode, a new segment) starts; elsewhere
the carried features are used, so a collector step costs no memory encoding.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.modules.tensordict_module.rnn import recurrent_mode

from spf_rl.modules.memory import (
    MemoryEncoder,
    memory_indices,
    memory_mask,
    padded_memory_indices,
    padded_memory_mask,
    validate_sparsity,
)
from spf_rl.modules.td_utils import DEMO_STEPS_KEY, demo_lengths, init_flags, next_key, with_batch_dim

__all__ = ["SparseMemory"]


class SparseMemory(TensorDictModuleBase):
    """Encodes the demonstration frames at the memory indices ``M*`` and carries them through an episode.

    **Step mode**: where ``is_init`` is true (or the ``memory_features`` state is
    missing) the frames at ``M*`` are encoded; elsewhere the carried state is used.
    **Sequence mode** (inside ``torchrl.modules.set_recurrent_mode(True)``, input
    ``[*B, T]``): the memory is encoded at ``t = 0`` and wherever ``is_init`` is
    true, and held over each segment.

    **Random sparsity** (``sparsity_range`` given): the memory holds a slot for every
    one of the ``n`` demo frames, and a boolean ``memory_mask`` ``[n]`` marks the
    slots at ``memory_indices(n, s)``. In training-mode sequence mode ``s`` is drawn
    from ``Uniform(*sparsity_range)`` per segment (torch's global RNG); otherwise
    ``s`` is :attr:`sparsity`.

    **Demonstrations shorter than** ``n`` (the optional ``demo_steps`` input, ``n_i``
    per row, frames padded after it): the memory is that of an ``n_i``-step
    demonstration, laid out in the same slots. A fixed-sparsity memory holds the
    frames at ``memory_indices(n_i, s)`` in its first ``memory_length(n_i, s)`` slots
    (:func:`~spf_rl.modules.memory.padded_memory_indices`); a random-sparsity one holds
    frames ``0 .. n_i - 1`` and its mask is ``memory_mask(n_i, s)`` padded with false
    (:func:`~spf_rl.modules.memory.padded_memory_mask`). The other slots are zeros:
    padding frames are never encoded. Without the key (or with every ``n_i = n``)
    nothing changes.

    Args:
        encoder (nn.Module): image encoder phi, ``[*, H, W, 3] -> [*, D]`` (shared with
            the observation encoder in :class:`~spf_rl.modules.SPFPolicy`).
        demo_length (int): demonstration length ``n``.
        sparsity (float): fraction of demo frames in memory, in ``(0, 1]``.
        sparsity_range (tuple of float, optional): ``(low, high)`` for random sparsity.

    Keyword Args:
        feature_dim (int, optional): size ``D`` of a feature; defaults to ``encoder.feature_dim``.
        slot_mlp (nn.Module, optional): maps ``(features [*, D], actions [*])`` to a memory
            slot (the RPF lab code's memory, :class:`~spf_rl.modules.rpf.SlotMLP`); the
            module then also reads ``demo_actions`` and ``D`` is ``slot_mlp.feature_dim``.
        demo_actions_key (NestedKey): read only with ``slot_mlp``. Defaults ``"demo_actions"``.
        demo_frames_key, is_init_key (NestedKey): inputs. Defaults ``"demo_frames"``, ``"is_init"``.
        memory_key (NestedKey): the memory state ``[l, D]`` (``[n, D]`` with random
            sparsity). Defaults ``"memory_features"``.
        memory_mask_key (NestedKey): output with random sparsity. Defaults ``"memory_mask"``.
        demo_steps_key (NestedKey, optional): optional input, each demonstration's length
            ``n_i`` (int64 ``[1]``); ``None``: never read. Defaults ``"demo_steps"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spf_rl.modules import ImageEncoder, SparseMemory
        >>> memory = SparseMemory(ImageEncoder(feature_dim=8, image_size=(16, 16)), demo_length=10, sparsity=0.4)
        >>> td = TensorDict({"demo_frames": torch.randint(0, 256, (2, 10, 16, 16, 3), dtype=torch.uint8),
        ...                  "is_init": torch.ones(2, 1, dtype=torch.bool)}, batch_size=[2])
        >>> memory(td)["memory_features"].shape, memory.in_keys
        (torch.Size([2, 4, 8]), ['demo_frames', 'is_init', 'memory_features', 'demo_steps'])
        >>> # a 5-step demonstration (padded to 10): its frames 0 and 4 (memory_indices(5, 0.4)), then zero slots
        >>> td["demo_steps"] = torch.tensor([[10], [5]])
        >>> [t.tolist() for t in memory.slot_layout(td["demo_steps"][1:])]
        [[[0, 4, 0, 0]], [[True, True, False, False]]]
        >>> bool((memory(td)["memory_features"][1, 2:] == 0).all())
        True
    """

    def __init__(
        self,
        encoder: nn.Module,
        demo_length: int,
        sparsity: float,
        sparsity_range: tuple[float, float] | None = None,
        *,
        feature_dim: int | None = None,
        slot_mlp: nn.Module | None = None,
        demo_actions_key: NestedKey = "demo_actions",
        demo_frames_key: NestedKey = "demo_frames",
        is_init_key: NestedKey = "is_init",
        memory_key: NestedKey = "memory_features",
        memory_mask_key: NestedKey = "memory_mask",
        demo_steps_key: NestedKey | None = DEMO_STEPS_KEY,
    ) -> None:
        super().__init__()
        self.demo_length = int(demo_length)
        self.sparsity_range = sparsity_range
        self.random_sparsity = sparsity_range is not None
        slots = torch.arange(self.demo_length) if self.random_sparsity else memory_indices(self.demo_length, sparsity)
        self.encoder = MemoryEncoder(encoder, slots)
        self.feature_dim = int(feature_dim if feature_dim is not None else getattr(encoder, "feature_dim"))
        self.slot_mlp = slot_mlp
        if slot_mlp is not None:
            self.feature_dim = int(slot_mlp.feature_dim)
        self.demo_actions_key = demo_actions_key
        self._sparsity = validate_sparsity(sparsity)
        self.demo_frames_key, self.is_init_key = demo_frames_key, is_init_key
        self.memory_key, self.memory_mask_key = memory_key, memory_mask_key
        self.demo_steps_key = demo_steps_key
        self.in_keys = (
            [demo_frames_key, is_init_key, memory_key]
            + ([demo_actions_key] if slot_mlp is not None else [])
            + ([demo_steps_key] if demo_steps_key is not None else [])
        )
        self.out_keys = [memory_key, next_key(memory_key)] + ([memory_mask_key] if self.random_sparsity else [])

    @property
    def num_slots(self) -> int:
        """Memory slots: ``l`` (``n`` with random sparsity)."""
        return self.encoder.num_frames

    @property
    def indices(self) -> torch.Tensor:
        """Demo index of each slot (``M*``, or ``0..n-1`` with random sparsity)."""
        return self.encoder.indices

    @property
    def sparsity(self) -> float:
        """Sparsity the memory is read at in step and eval mode."""
        return self._sparsity

    def set_sparsity(self, sparsity: float) -> SparseMemory:
        """Set the evaluation sparsity of a random-sparsity memory (see :meth:`SPFPolicy.set_sparsity`)."""
        sparsity = validate_sparsity(sparsity)
        if not self.random_sparsity:
            raise RuntimeError(
                f"set_sparsity needs a policy built with SPFConfig.sparsity_range (model "
                f"'spf_random'); this policy keeps a fixed memory of sparsity {self._sparsity}."
            )
        self._sparsity = sparsity
        return self

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the memory state (zeroed at reset; the module re-encodes where ``is_init``)."""
        return TensorDictPrimer({self.memory_key: Unbounded(shape=(self.num_slots, self.feature_dim))}, expand_specs=True)

    def check_demo_frames(self, demo_frames: torch.Tensor, batch_dims: int) -> None:
        """Raise a ``ValueError`` unless ``demo_frames`` is ``[*batch, n, H, W, 3]``."""
        n = self.demo_length
        if demo_frames.ndim != batch_dims + 4 or demo_frames.shape[batch_dims] != n:
            raise ValueError(
                f"demo_frames must have shape [*batch, n={n}, H, W, 3] (n = SPFConfig.demo_length), "
                f"got {tuple(demo_frames.shape)} for {batch_dims} batch dim(s)."
            )
        check = getattr(self.encoder.encoder, "check_frames", None)
        if check is not None:
            check(demo_frames, "demo_frames")

    def demo_lengths(self, td: TensorDictBase) -> torch.Tensor | None:
        """Each row's demonstration length ``[*batch, 1]`` (``None``: all are ``n`` long); checked."""
        return demo_lengths(td, self.demo_steps_key, self.demo_length, td.batch_size)

    def slot_layout(self, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Demo index ``[*, slots]`` and use ``[*, slots]`` (bool) of each slot for demonstrations of ``lengths`` ``[*, 1]`` steps."""
        if not self.random_sparsity:
            return padded_memory_indices(lengths, self.demo_length, self._sparsity)
        frames = torch.arange(self.demo_length, device=lengths.device)
        return frames.expand(*lengths.shape[:-1], -1), frames < lengths

    def masks(
        self, count: int, device: torch.device, draw: bool, lengths: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``[count, n]`` slot masks: sparsities drawn from ``sparsity_range`` if ``draw``, else :attr:`sparsity`;
        with ``lengths`` (``[count, 1]``), those of demonstrations of ``n_i`` steps, padded with false."""
        n = self.demo_length
        if not draw:
            if lengths is not None:
                return padded_memory_mask(lengths, n, self._sparsity).to(device)
            return memory_mask(n, self._sparsity).to(device).repeat(count, 1)
        low, high = self.sparsity_range
        draws = low + (high - low) * torch.rand(count, dtype=torch.float64)
        if lengths is None:
            return torch.stack([memory_mask(n, s) for s in draws.tolist()]).to(device)
        masks = torch.zeros(count, n, dtype=torch.bool)
        for row, (steps, s) in enumerate(zip(lengths.reshape(-1).tolist(), draws.tolist())):
            masks[row, :steps] = memory_mask(steps, s)
        return masks.to(device)

    def encode_where(self, td: TensorDictBase, where: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Memory ``[K, slots, D]`` of the ``K`` rows of ``td`` where the batch-shaped ``where`` is true;
        with ``lengths`` (``[*batch, 1]``, each row's demonstration length), laid out by :meth:`slot_layout`."""
        demo_frames = td.get(self.demo_frames_key)
        self.check_demo_frames(demo_frames, where.ndim)
        if lengths is not None:
            return self._encode_lengths(td, demo_frames, where, lengths)
        features = self.encoder(demo_frames, where.nonzero(as_tuple=True))
        if self.slot_mlp is None:
            return features
        actions = td.get(self.demo_actions_key)[where].index_select(-1, self.indices.to(features.device))
        return self.slot_mlp(features, actions)

    def _encode_lengths(
        self, td: TensorDictBase, demo_frames: torch.Tensor, where: torch.Tensor, lengths: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`encode_where` for demonstrations of ``n_i`` steps: only the used slots' frames are encoded."""
        rows = where.nonzero(as_tuple=True)
        index, used = self.slot_layout(lengths.to(where.device)[rows])  # [K, slots]
        slot_row, slot = used.nonzero(as_tuple=True)
        frame_index = (*(r[slot_row] for r in rows), index[slot_row, slot])
        encoded = self.encoder.encoder(demo_frames[frame_index])  # [V, D]
        if self.slot_mlp is not None:
            encoded = self.slot_mlp(encoded, td.get(self.demo_actions_key)[frame_index])
        features = encoded.new_zeros(*used.shape, encoded.shape[-1])
        features[slot_row, slot] = encoded
        return features

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the memory in use (step mode) or per step of a ``[*B, T]`` sequence (recurrent mode)."""
        if recurrent_mode():
            return self._forward_sequence(tensordict)
        return with_batch_dim(self._forward_step, tensordict)

    def _dtype(self) -> torch.dtype:
        parameter = next(self.encoder.parameters(), None)
        return torch.get_default_dtype() if parameter is None else parameter.dtype

    def _forward_step(self, td: TensorDictBase) -> TensorDictBase:
        batch, device = td.batch_size, td.device or self.indices.device
        lengths = self.demo_lengths(td)
        is_init = init_flags(td, self.is_init_key, device)
        stored = td.get(self.memory_key, None)
        shape = (*batch, self.num_slots, self.feature_dim)
        if stored is None:
            fresh, memory = torch.ones_like(is_init), torch.zeros(shape, dtype=self._dtype(), device=device)
        else:
            fresh, memory = is_init, stored.reshape(shape).to(self._dtype())
        if fresh.any():
            feats = self.encode_where(td, fresh, lengths)
            memory = memory.clone()
            memory[fresh] = feats.to(memory.dtype)
            td.set(self.memory_key, memory)
        elif memory is not stored:  # reshaped or cast: write the memory in use
            td.set(self.memory_key, memory)
        td.set(next_key(self.memory_key), memory)
        if self.random_sparsity:  # step mode: always the evaluation sparsity
            rows = is_init.numel()
            flat = None if lengths is None else lengths.reshape(rows, 1)
            td.set(self.memory_mask_key, self.masks(rows, memory.device, draw=False, lengths=flat).reshape(*batch, self.demo_length))
        return td

    def encode_segments(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The memory of each segment of a ``[*B, T]`` sequence, encoded once.

        A segment starts at ``t = 0`` and wherever ``is_init`` is true; its demonstration
        length is the ``demo_steps`` of its first step.

        Returns:
            ``(features [K, slots, D], segment [B', T] (the segment of each step, B' = prod(*B)),
            masks [K, n] or None)``.
        """
        if tensordict.batch_dims == 0:
            raise ValueError("SparseMemory in recurrent mode needs a time dimension (batch shape [*B, T]).")
        td = tensordict.reshape(-1, tensordict.shape[-1])
        lengths = self.demo_lengths(td)
        start = init_flags(td, self.is_init_key, self.indices.device).clone()
        start[:, 0] = True
        feats = self.encode_where(td, start, lengths)  # [K, slots, D]
        segment = (start.reshape(-1).long().cumsum(0) - 1).reshape(start.shape)
        masks = None
        if self.random_sparsity:
            starts = None if lengths is None else lengths[start.to(lengths.device)]
            masks = self.masks(feats.shape[0], feats.device, draw=self.training, lengths=starts)
        return feats, segment, masks

    def write_segments(
        self, tensordict: TensorDictBase, feats: torch.Tensor, segment: torch.Tensor, masks: torch.Tensor | None
    ) -> TensorDictBase:
        """Write each step's memory (and mask) of :meth:`encode_segments`' output into ``tensordict``."""
        shape = tensordict.batch_size
        memory = feats.index_select(0, segment.reshape(-1)).reshape(*shape, self.num_slots, self.feature_dim)
        tensordict.set(self.memory_key, memory)
        tensordict.set(next_key(self.memory_key), memory)
        if masks is not None:
            tensordict.set(self.memory_mask_key, masks.index_select(0, segment.reshape(-1)).reshape(*shape, self.demo_length))
        return tensordict

    def _forward_sequence(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.write_segments(tensordict, *self.encode_segments(tensordict))
