"""Data-parallel training under ``torchrun``: which rank this process is, its shard of every batch,
and the loss weight that makes the ranks' gradients those of the whole batch.

A BC or DAgger run started with ``torchrun --nproc_per_node N recipes/bc.py ...`` trains one
model on ``N`` processes with :class:`~torch.nn.parallel.DistributedDataParallel`
(the ``gloo`` back-end on the CPU, ``nccl`` on CUDA, one GPU per rank:
``cuda:LOCAL_RANK``). Every rank draws the same global batch of
``optim.batch_size`` episodes (the same seeded sampler) and keeps its slice
``r, r + N, ...`` of it (:class:`ShardedSampler`, the order of
:class:`torch.utils.data.DistributedSampler`), so it reads only its own episodes
from the memory-mapped store. Each rank's mean loss is weighted by its share of the
batch's labelled steps (:func:`global_mean_weight`), so the averaged gradient is the
gradient of the whole batch's mean: the run follows the single-process run with the
same global batch, up to float rounding. Rank 0 validates, tests and writes every
file (and collects DAgger's rounds, which the others read from its store); the others
train and wait.

Examples:
    >>> Ranks()
    Ranks(rank=0, world_size=1, local_rank=0)
    >>> Ranks().is_main
    True
    >>> shard_indices(torch.arange(6), Ranks(rank=1, world_size=2, local_rank=1))
    tensor([1, 3, 5])
    >>> shard_indices(torch.arange(3), Ranks(rank=1, world_size=2, local_rank=1))  # padded as DistributedSampler does
    tensor([1, 0])
"""
from __future__ import annotations

import datetime
import logging
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torchrl.data import SamplerWithoutReplacement

logger = logging.getLogger(__name__)

#: How long the other ranks may wait on rank 0 (validation, testing, DAgger's collection)
#: before the process group gives up.
WAIT_FOR_RANK_0 = datetime.timedelta(hours=3)
#: The environment variables ``torchrun`` sets for each process.
RANK_ENV, WORLD_SIZE_ENV, LOCAL_RANK_ENV = "RANK", "WORLD_SIZE", "LOCAL_RANK"


@dataclass(frozen=True)
class Ranks:
    """This process's place in a data-parallel run (one process: rank 0 of 1).

    Args:
        rank: the process's rank, ``0 .. world_size - 1``.
        world_size: the number of processes.
        local_rank: the rank on this machine (the GPU a CUDA rank uses).

    Examples:
        >>> second = Ranks(rank=1, world_size=2, local_rank=1)
        >>> second.is_main, second.distributed, Ranks().distributed
        (False, True, False)
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """Whether this is rank 0, which validates, tests and writes the run's files."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        """Whether more than one process trains."""
        return self.world_size > 1

    @classmethod
    def from_env(cls) -> Ranks:
        """The ranks ``torchrun`` set in the environment (none set: one process).

        Raises:
            ValueError: a variable is not an integer, or the ranks are out of range.
        """
        values = {}
        for name, default in ((RANK_ENV, 0), (WORLD_SIZE_ENV, 1), (LOCAL_RANK_ENV, 0)):
            raw = os.environ.get(name, str(default))
            try:
                values[name] = int(raw)
            except ValueError:
                raise ValueError(f"the environment variable {name} must be an integer (torchrun sets it), got {raw!r}.") from None
        ranks = cls(values[RANK_ENV], values[WORLD_SIZE_ENV], values[LOCAL_RANK_ENV])
        if ranks.world_size < 1 or not 0 <= ranks.rank < ranks.world_size or ranks.local_rank < 0:
            raise ValueError(f"{WORLD_SIZE_ENV} must be >= 1 and 0 <= {RANK_ENV} < {WORLD_SIZE_ENV}, got {ranks}.")
        return ranks


def init_distributed(device: torch.device) -> tuple[Ranks, torch.device]:
    """Join the process group ``torchrun`` set up, if any, and return the ranks and this rank's device.

    ``gloo`` on the CPU, ``nccl`` on CUDA, where each rank takes ``cuda:LOCAL_RANK``. One
    process (no ``WORLD_SIZE`` above 1): nothing to join, ``device`` unchanged.
    """
    ranks = Ranks.from_env()
    if not ranks.distributed:
        return ranks, device
    if device.type == "cuda":
        device = torch.device("cuda", ranks.local_rank)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=WAIT_FOR_RANK_0)
    logger.info("rank %d of %d on %s", ranks.rank, ranks.world_size, device)
    return ranks, device


def shard_indices(indices: torch.Tensor, ranks: Ranks) -> torch.Tensor:
    """This rank's slice ``r, r + N, ...`` of a global batch's ``indices``, padded first (by repeating
    its first indices, as :class:`torch.utils.data.DistributedSampler` pads) to a multiple of ``N``."""
    if not ranks.distributed:
        return indices
    padding = -len(indices) % ranks.world_size
    if padding and len(indices):
        indices = torch.cat([indices, indices.repeat(-(-padding // len(indices)))[:padding]])
    return indices[ranks.rank :: ranks.world_size]


class ShardedSampler(SamplerWithoutReplacement):
    """TorchRL's :class:`~torchrl.data.SamplerWithoutReplacement` that keeps this rank's shard of each batch.

    Every rank holds one with the same seed, so all draw the same global batch (the
    single-process run's); each then reads only its own episodes (:func:`shard_indices`).

    Args:
        ranks: this process's ranks.
        drop_last: as in :class:`~torchrl.data.SamplerWithoutReplacement`.

    Examples:
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> shards = []
        >>> for rank in range(2):
        ...     buffer = ReplayBuffer(storage=LazyTensorStorage(8), sampler=ShardedSampler(Ranks(rank, 2, rank)), batch_size=4)
        ...     _ = buffer.extend(torch.arange(8))
        ...     buffer.set_rng(torch.Generator().manual_seed(0))
        ...     shards.append(buffer.sample().tolist())
        >>> len(shards[0]), len(shards[1]), len(set(shards[0]) | set(shards[1]))
        (2, 2, 4)
    """

    def __init__(self, ranks: Ranks, drop_last: bool = False) -> None:
        super().__init__(drop_last=drop_last)
        self.ranks = ranks

    def sample(self, storage, batch_size: int):
        index, info = super().sample(storage, batch_size)
        return shard_indices(torch.as_tensor(index), self.ranks), info


def global_mean_weight(labelled: int, ranks: Ranks, device: torch.device) -> tuple[float, int]:
    """The weight of this rank's mean loss over its ``labelled`` steps, and the batch's labelled steps.

    DistributedDataParallel averages the ranks' gradients; weighting rank ``r``'s mean by
    ``N * n_r / sum(n)`` makes that average the gradient of the mean over the whole batch.
    One process: ``(1.0, labelled)``.
    """
    if not ranks.distributed:
        return 1.0, labelled
    total = torch.tensor([labelled], dtype=torch.int64, device=device)
    dist.all_reduce(total)
    total_labelled = int(total.item())
    return ranks.world_size * labelled / max(total_labelled, 1), total_labelled


def all_ranks_sum(value: float, ranks: Ranks, device: torch.device) -> float:
    """``value`` summed over the ranks (itself in one process)."""
    if not ranks.distributed:
        return value
    total = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(total)
    return float(total.item())


def backward_on_shard(
    loss: torch.Tensor, accuracy: torch.Tensor, batch, ranks: Ranks, device: torch.device
) -> tuple[float, float]:
    """``loss.backward()`` for this rank's shard of a batch, and the whole batch's mean loss and accuracy.

    ``loss`` and ``accuracy`` are means over the shard's labelled steps (``batch["steps", "mask"]``);
    with more than one rank the loss is weighted first (:func:`global_mean_weight`), so that
    DistributedDataParallel's averaged gradient is the whole batch's.
    """
    if not ranks.distributed:
        loss.backward()
        return loss.item(), accuracy.item()
    labelled = int(batch.get(("steps", "mask")).sum())
    weight, _ = global_mean_weight(labelled, ranks, device)
    (loss * weight).backward()
    return batch_mean(loss.item(), batch, ranks, device), batch_mean(accuracy.item(), batch, ranks, device)


def batch_mean(value: float, batch, ranks: Ranks, device: torch.device) -> float:
    """The whole batch's mean of a per-step mean ``value`` over this rank's shard of ``batch``
    (weighted by each shard's labelled steps, ``batch["steps", "mask"]``); ``value`` itself in
    one process."""
    if not ranks.distributed:
        return value
    labelled = int(batch.get(("steps", "mask")).sum())
    total = all_ranks_sum(float(labelled), ranks, device)
    return all_ranks_sum(value * labelled, ranks, device) / max(total, 1.0)


def barrier(ranks: Ranks) -> None:
    """Wait for every rank (nothing to wait for in one process)."""
    if ranks.distributed:
        dist.barrier()


__all__ = [
    "Ranks",
    "ShardedSampler",
    "all_ranks_sum",
    "backward_on_shard",
    "barrier",
    "batch_mean",
    "global_mean_weight",
    "init_distributed",
    "shard_indices",
]
