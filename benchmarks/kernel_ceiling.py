"""The FLOP-carrying kernels of a computation, replayed alone: what a step would cost if
nothing but its matmuls and convolutions ran.

:class:`KernelRecorder` records every call of an op that
:class:`torch.utils.flop_counter.FlopCounterMode` counts FLOPs for (matmuls,
convolutions and their backward passes, attention), by its arguments' shapes, strides
and dtypes. :func:`replay_kernels` runs each distinct call alone on fresh tensors of
those layouts and returns the FLOPs and the seconds of all recorded calls. The seconds
are a floor on any implementation of the same computation with the same kernels: the
step's FLOP/s can reach at most ``flops / seconds``, however the work between the
kernels (small element-wise ops, Python, the optimiser) is cut.

Examples:
    >>> import torch
    >>> layer = torch.nn.Linear(64, 32)
    >>> with KernelRecorder() as recorder:
    ...     layer(torch.randn(8, 64)).sum().backward()
    >>> replayed = replay_kernels(recorder.calls, min_seconds=0.0)
    >>> replayed["calls"], replayed["flops"] == 2 * (8 * 64 * 32) + 2 * (8 * 32 * 64)
    (2, True)
"""
from __future__ import annotations

import statistics
import time
from collections import Counter
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode, flop_registry

#: Least seconds each distinct call is timed for (at least :data:`MIN_CALLS` calls).
MIN_SECONDS = 0.02
#: Least timed calls of each distinct call, after one untimed.
MIN_CALLS = 3


class _Layout(tuple):
    """A recorded tensor argument: (shape, stride, dtype, device)."""


def _layout(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return _Layout((tuple(value.shape), tuple(value.stride()), value.dtype, str(value.device)))
    if isinstance(value, (list, tuple)):
        return type(value)(_layout(item) for item in value)
    return value


def _materialise(value: Any, generator: torch.Generator) -> Any:
    if isinstance(value, _Layout):
        shape, stride, dtype, device = value
        # the storage the layout spans (an expanded tensor's stride-0 dims share elements)
        size = 0 if 0 in shape else 1 + sum((dim - 1) * step for dim, step in zip(shape, stride))
        if dtype.is_floating_point:
            storage = torch.randn(size, generator=generator).to(dtype=dtype, device=device)
        else:
            storage = torch.zeros(size, dtype=dtype, device=device)
        return storage.as_strided(shape, stride)
    if isinstance(value, (list, tuple)):
        return type(value)(_materialise(item, generator) for item in value)
    return value


class KernelRecorder(TorchDispatchMode):
    """Records the calls of FLOP-counted ops (:data:`torch.utils.flop_counter.flop_registry`)
    made under it, forward and backward, as ``(op, args, kwargs)`` with tensors replaced
    by their layouts; the calls themselves run as usual.

    Examples:
        >>> import torch
        >>> with KernelRecorder() as recorder:
        ...     _ = torch.randn(4, 5) @ torch.randn(5, 6) + 1.0
        >>> [str(op) for op, _, _ in recorder.calls]
        ['aten.mm.default']
    """

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[Any, tuple, dict]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func._overloadpacket in flop_registry:
            self.calls.append((func, _layout(args), {key: _layout(value) for key, value in kwargs.items()}))
        return func(*args, **kwargs)


def _key(call: tuple[Any, tuple, dict]) -> tuple:
    op, args, kwargs = call
    return (op, repr(args), repr(sorted(kwargs.items())))


def replay_kernels(
    calls: list[tuple[Any, tuple, dict]], min_seconds: float = MIN_SECONDS, min_calls: int = MIN_CALLS, seed: int = 0
) -> dict:
    """Run each distinct recorded call alone and total over all calls.

    Args:
        calls: :attr:`KernelRecorder.calls`.
        min_seconds, min_calls: each distinct call is timed for at least this long and this
            many calls (after one untimed), its median kept.
        seed: seed of the random inputs.

    Returns:
        ``{"calls": n, "distinct": d, "flops": F, "seconds": S, "by_op": {op: {"flops", "seconds", "calls"}}}``,
        ``S`` the sum over every recorded call of its distinct call's median time.
    """
    if min_seconds < 0 or min_calls < 1:
        raise ValueError(f"min_seconds must be >= 0 and min_calls >= 1, got {min_seconds}, {min_calls}.")
    counts = Counter(_key(call) for call in calls)
    first = {}
    for call in calls:
        first.setdefault(_key(call), call)
    generator = torch.Generator().manual_seed(seed)
    total_flops = total_seconds = 0.0
    by_op: dict[str, dict[str, float]] = {}
    for key, (op, args, kwargs) in first.items():
        inputs, keywords = _materialise(args, generator), {name: _materialise(v, generator) for name, v in kwargs.items()}
        counter = FlopCounterMode(display=False)
        with torch.no_grad(), counter:
            op(*inputs, **keywords)  # untimed: counts the FLOPs, warms the kernel
        timings: list[float] = []
        with torch.no_grad():
            while len(timings) < min_calls or sum(timings) < min_seconds:
                start = time.perf_counter()
                op(*inputs, **keywords)
                timings.append(time.perf_counter() - start)
        count = counts[key]
        flops, seconds = counter.get_total_flops() * count, statistics.median(timings) * count
        total_flops += flops
        total_seconds += seconds
        entry = by_op.setdefault(str(op), {"flops": 0.0, "seconds": 0.0, "calls": 0})
        entry["flops"] += flops
        entry["seconds"] += seconds
        entry["calls"] += count
    return {"calls": len(calls), "distinct": len(first), "flops": int(total_flops), "seconds": total_seconds, "by_op": by_op}
