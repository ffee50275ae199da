"""Sparse visual memory of a demonstration (paper Sec. 3.2 eq. 1 and Sec. 4.1).

The memory of an ``n``-step demonstration is ``SP(p) = {M, a, M*}``: ``l`` frames
``M`` at indices ``M*`` evenly spaced over the demonstration, plus *all* ``n``
demonstration actions ``a``. This file computes ``M*``, the memory size in bytes,
and the memory features (the frames at ``M*`` passed through the encoder phi).
"""
from __future__ import annotations

import functools
import logging
import math
import numbers

import torch
from torch import nn

logger = logging.getLogger(__name__)

__all__ = [
    "MemoryEncoder",
    "memory_bytes",
    "memory_indices",
    "memory_length",
    "memory_mask",
    "padded_memory_indices",
    "padded_memory_mask",
    "validate_sparsity",
    "validate_sparsity_range",
]

#: Default frame shape (channels, height, width) used for byte budgets.
DEFAULT_FRAME_SHAPE = (64, 64, 3)
#: Bytes per uint8 pixel value.
UINT8_BYTES = 1


def validate_sparsity(sparsity: float) -> float:
    """Check that ``sparsity`` is a real number in ``(0, 1]`` and return it as float."""
    if (
        isinstance(sparsity, bool)
        or not isinstance(sparsity, numbers.Real)
        or math.isnan(sparsity)
        or not 0.0 < sparsity <= 1.0
    ):
        raise ValueError(
            f"sparsity must be a number in the range (0, 1] (fraction of the demo frames kept), "
            f"got {sparsity!r}."
        )
    return float(sparsity)


def validate_sparsity_range(sparsity_range: tuple[float, float] | list[float]) -> tuple[float, float]:
    """Check that ``sparsity_range`` is a pair ``(low, high)`` with ``0 < low <= high <= 1``.

    Args:
        sparsity_range (tuple or list of two floats): the range a random sparsity is
            drawn from.

    Returns:
        tuple of float: ``(low, high)``.

    Examples:
        >>> validate_sparsity_range([0.2, 1])
        (0.2, 1.0)
    """
    pair = tuple(sparsity_range) if isinstance(sparsity_range, (list, tuple)) else None
    if (
        pair is None
        or len(pair) != 2
        or any(isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isnan(v) for v in pair)
        or not 0.0 < pair[0] <= pair[1] <= 1.0
    ):
        raise ValueError(
            f"sparsity_range must be a pair (low, high) of numbers with 0 < low <= high <= 1, "
            f"got {sparsity_range!r}."
        )
    return float(pair[0]), float(pair[1])


def _validate_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise ValueError(
            f"n (the demonstration length) must be a positive int, got {n!r}."
        )
    return int(n)


def memory_length(n: int, sparsity: float) -> int:
    """Number of memory frames ``l = max(1, round(sparsity * n))``.

    ``round`` is Python's (half to even), as in the paper's "multiplying n with a sparsity".

    Args:
        n (int): demonstration length (number of frames), positive.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.

    Examples:
        >>> memory_length(30, 0.4)
        12
    """
    n = _validate_n(n)
    sparsity = validate_sparsity(sparsity)
    return max(1, min(n, round(sparsity * n)))


def memory_indices(n: int, sparsity: float) -> torch.LongTensor:
    """0-based indices ``M*`` of the demonstration frames kept in memory.

    ``l = memory_length(n, sparsity)`` indices evenly spaced over ``[0, n - 1]``:
    ``round(i * (n - 1) / (l - 1))`` for ``i = 0 .. l - 1``, computed exactly in integers and
    rounded half to even. The first frame (0) is always included and, when ``l > 1``, the
    last frame (``n - 1``) too. The indices are unique and sorted because the
    spacing ``(n - 1) / (l - 1)`` is at least 1 when ``l <= n``. Exact integers make the
    rule the same on every machine and in the torch-free runtime (``spf_rl_runtime``):
    ``torch.linspace`` in float64, used before, broke a few exact ties (211 pairs ``(n, l)``
    with ``n <= 200``, none of them a shipped model's) by its CPU kernel's rounding.

    How this differs from the paper (Sec. 4.1): the paper writes, 1-based,
    ``M* = {floor(i * n / (l - 1)) | i = 1..l-1} U {1}``. For ``l = 1`` that divides
    by zero, and when ``n / (l - 1) < 2`` the first term ``floor(n / (l - 1))`` is 1
    and duplicates the frame ``{1}``, so the set holds fewer than ``l`` frames: with
    ``n = 30, l = 30`` (sparsity 1.0) it keeps 29 frames and skips frame 29. The
    paper's grid also starts one stride after the first frame. The form used here
    always returns exactly ``l`` distinct frames spread symmetrically from the first
    to the last frame.

    Args:
        n (int): demonstration length (number of frames), positive.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.

    Returns:
        torch.LongTensor: shape ``[l]``, sorted 0-based frame indices.

    Examples:
        >>> memory_indices(30, 0.2).tolist()
        [0, 6, 12, 17, 23, 29]
        >>> memory_indices(26, 0.9).tolist()[11]  # 11 * 25 / 22 = 12.5 exactly: half to even
        12
    """
    length = memory_length(n, sparsity)
    if length == 1:
        return torch.zeros(1, dtype=torch.long)
    numerator = torch.arange(length, dtype=torch.long) * (n - 1)
    denominator = length - 1
    quotient, remainder = numerator // denominator, numerator % denominator
    up = (2 * remainder > denominator) | ((2 * remainder == denominator) & (quotient % 2 == 1))
    return quotient + up.long()


def memory_mask(n: int, sparsity: float) -> torch.BoolTensor:
    """Boolean mask over the ``n`` demonstration frames, true at :func:`memory_indices`.

    A random-sparsity policy (``SPFConfig.sparsity_range``) holds a memory slot for
    every demo frame and attends only to the slots where this mask is true.

    Args:
        n (int): demonstration length (number of frames), positive.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.

    Returns:
        torch.BoolTensor: shape ``[n]`` with ``memory_length(n, sparsity)`` true entries.

    Examples:
        >>> memory_mask(6, 0.5).tolist()
        [True, False, True, False, False, True]
    """
    mask = torch.zeros(_validate_n(n), dtype=torch.bool)
    mask[memory_indices(n, sparsity)] = True
    return mask


@functools.lru_cache(maxsize=32)
def _padded_tables(demo_length: int, sparsity: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Row ``n`` (1..demo_length) of each: ``M*(n, s)`` padded with 0 to ``l``, its validity, ``memory_mask(n, s)`` padded."""
    slots = memory_length(demo_length, sparsity)
    indices = torch.zeros(demo_length + 1, slots, dtype=torch.long)
    valid = torch.zeros(demo_length + 1, slots, dtype=torch.bool)
    masks = torch.zeros(demo_length + 1, demo_length, dtype=torch.bool)
    for n in range(1, demo_length + 1):
        kept = memory_indices(n, sparsity)
        indices[n, : kept.numel()] = kept
        valid[n, : kept.numel()] = True
        masks[n, kept] = True
    return indices, valid, masks


def padded_memory_indices(
    lengths: torch.Tensor, demo_length: int, sparsity: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each demonstration's memory indices ``M*(n_i, sparsity)`` in the ``l`` slots of a ``demo_length``-step memory.

    For demonstrations padded to ``demo_length`` steps: a fixed-sparsity memory has
    ``l = memory_length(demo_length, sparsity)`` slots; one of ``n_i`` steps fills the
    first ``memory_length(n_i, sparsity) <= l`` of them with the frames at
    ``memory_indices(n_i, sparsity)``, as a policy built for ``n_i`` steps would.

    Args:
        lengths (torch.Tensor): int ``[*, 1]``, the demonstrations' lengths ``n_i`` in ``[1, demo_length]``.
        demo_length (int): the padded length.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.

    Returns:
        tuple of torch.Tensor: ``indices`` ``[*, l]`` (int64, 0 in the unused slots) and
        ``valid`` ``[*, l]`` (bool, true in the used slots), on ``lengths``' device.

    Examples:
        >>> indices, valid = padded_memory_indices(torch.tensor([[3], [6]]), 6, 0.5)
        >>> indices.tolist(), valid.tolist()
        ([[0, 2, 0], [0, 2, 5]], [[True, True, False], [True, True, True]])
    """
    indices, valid, _ = _padded_tables(_validate_n(demo_length), validate_sparsity(sparsity))
    rows = lengths.reshape(lengths.shape[:-1]).long()
    return indices.to(lengths.device)[rows], valid.to(lengths.device)[rows]


def padded_memory_mask(lengths: torch.Tensor, demo_length: int, sparsity: float) -> torch.Tensor:
    """:func:`memory_mask` of each demonstration of ``n_i`` steps, padded with false to ``demo_length``.

    The slot mask of a random-sparsity memory (one slot per frame of the padded
    demonstration): true at ``memory_indices(n_i, sparsity)``, false from ``n_i`` on.

    Args:
        lengths (torch.Tensor): int ``[*, 1]``, the demonstrations' lengths ``n_i`` in ``[1, demo_length]``.
        demo_length (int): the padded length.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.

    Returns:
        torch.BoolTensor: ``[*, demo_length]`` on ``lengths``' device.

    Examples:
        >>> padded_memory_mask(torch.tensor([[3], [6]]), 6, 0.5).int().tolist()
        [[1, 0, 1, 0, 0, 0], [1, 0, 1, 0, 0, 1]]
    """
    _, _, masks = _padded_tables(_validate_n(demo_length), validate_sparsity(sparsity))
    return masks.to(lengths.device)[lengths.reshape(lengths.shape[:-1]).long()]


def memory_bytes(
    n: int,
    sparsity: float,
    frame_shape: tuple[int, ...] = DEFAULT_FRAME_SHAPE,
    bytes_per_pixel: int = UINT8_BYTES,
    bytes_per_action: int = UINT8_BYTES,
) -> int:
    """Size in bytes of a sparse memory: ``l`` raw frames plus all ``n`` actions.

    Args:
        n (int): demonstration length (number of frames), positive.
        sparsity (float): fraction of frames kept, in ``(0, 1]``.
        frame_shape (tuple of int, optional): shape of one frame, ``(height, width,
            channels)`` in pixels. Defaults to ``(64, 64, 3)``.
        bytes_per_pixel (int, optional): bytes per stored pixel value. Defaults to 1 (uint8).
        bytes_per_action (int, optional): bytes per stored action. Defaults to 1.

    Examples:
        >>> memory_bytes(30, 0.4)  # 12 frames of 3*64*64 bytes + 30 actions
        147486
    """
    length = memory_length(n, sparsity)
    if any(int(s) < 1 for s in frame_shape):
        raise ValueError(f"frame_shape must hold positive sizes, got {frame_shape!r}.")
    if bytes_per_pixel < 0 or bytes_per_action < 0:
        raise ValueError(
            f"bytes_per_pixel and bytes_per_action must be >= 0, got {bytes_per_pixel!r}, {bytes_per_action!r}."
        )
    return int(length * math.prod(frame_shape) * bytes_per_pixel + n * bytes_per_action)


class MemoryEncoder(nn.Module):
    """Gathers the memory frames ``demo_frames[..., M*, :, :, :]`` and encodes them.

    Args:
        encoder (nn.Module): image encoder phi mapping ``[*, H, W, 3]`` to ``[*, D]``.
        indices (torch.Tensor): 0-based memory indices ``M*`` of shape ``[l]``
            (see :func:`memory_indices`).

    Examples:
        >>> import torch
        >>> from spf_rl.modules import ImageEncoder, MemoryEncoder, memory_indices
        >>> enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
        >>> mem = MemoryEncoder(enc, memory_indices(10, 0.4))
        >>> demo = torch.randint(0, 256, (2, 10, 16, 16, 3), dtype=torch.uint8)
        >>> mem(demo).shape
        torch.Size([2, 4, 8])
    """

    def __init__(self, encoder: nn.Module, indices: torch.Tensor) -> None:
        super().__init__()
        indices = torch.as_tensor(indices, dtype=torch.long)
        if indices.ndim != 1 or indices.numel() == 0 or (indices < 0).any():
            raise ValueError(
                f"indices must be a non-empty 1-d tensor of non-negative frame indices, got {indices!r}."
            )
        self.encoder = encoder
        self.register_buffer("indices", indices, persistent=False)

    @property
    def num_frames(self) -> int:
        """Number of memory frames ``l``."""
        return int(self.indices.numel())

    def gather(self, demo_frames: torch.Tensor) -> torch.Tensor:
        """Select ``demo_frames[..., M*, :, :, :]``: ``[*, n, H, W, 3] -> [*, l, H, W, 3]``."""
        self._check_length(demo_frames)
        return demo_frames.index_select(-4, self.indices.to(demo_frames.device))

    def forward(
        self,
        demo_frames: torch.Tensor,
        batch_index: tuple[torch.Tensor, ...] | None = None,
    ) -> torch.Tensor:
        """Encode the memory frames.

        Args:
            demo_frames (torch.Tensor): ``[*, n, H, W, 3]`` demonstration frames (may be
                an expanded view).
            batch_index (tuple of torch.Tensor, optional): one 1-d index tensor per
                leading batch dim of ``demo_frames``; only those rows are gathered and
                encoded (without copying the other rows). Defaults to all rows.

        Returns:
            torch.Tensor: ``[*, l, D]``, or ``[K, l, D]`` with ``K`` rows picked by
            ``batch_index``.
        """
        if batch_index is None:
            return self.encoder(self.gather(demo_frames))
        self._check_length(demo_frames, len(batch_index))
        idx = self.indices.to(demo_frames.device)
        index = tuple(i.unsqueeze(-1) for i in batch_index) + (idx.unsqueeze(0),)
        return self.encoder(demo_frames[index])

    def _check_length(self, demo_frames: torch.Tensor, batch_dims: int | None = None) -> None:
        if demo_frames.ndim < 4 or (
            batch_dims is not None and demo_frames.ndim != batch_dims + 4
        ):
            raise ValueError(
                f"demo_frames must have shape [*, n, H, W, 3], got {tuple(demo_frames.shape)}."
            )
        num_demo = demo_frames.shape[-4]
        largest = int(self.indices.max())
        if num_demo <= largest:
            raise ValueError(
                f"The demonstration has {num_demo} frames but the memory needs frame index "
                f"{largest} (memory longer than the demo): check demo_length / sparsity "
                f"against the env's demo length."
            )
