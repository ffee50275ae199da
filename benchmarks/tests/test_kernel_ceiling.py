"""benchmarks/kernel_ceiling.py: what is recorded, that the replay carries the computation's FLOPs,
and that repeated calls are timed once."""
from __future__ import annotations

import pytest
import torch
from kernel_ceiling import KernelRecorder, replay_kernels
from torch.utils.flop_counter import FlopCounterMode


def _step(model: torch.nn.Module, frames: torch.Tensor) -> None:
    model(frames).square().mean().backward()


def _net() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Sequential(
        torch.nn.Conv2d(3, 8, 4, stride=4), torch.nn.ReLU(), torch.nn.Flatten(), torch.nn.Linear(8 * 4 * 4, 5)
    )


def test_replay_carries_the_flops_of_a_forward_and_backward_pass():
    model, frames = _net(), torch.rand(6, 3, 16, 16)
    counter, recorder = FlopCounterMode(display=False), KernelRecorder()
    with counter, recorder:
        _step(model, frames)
    ops = sorted({str(op) for op, _, _ in recorder.calls})
    # only FLOP-carrying ops: no ReLU, no reductions, no element-wise work
    assert ops == ["aten.addmm.default", "aten.convolution.default", "aten.convolution_backward.default", "aten.mm.default"]
    replayed = replay_kernels(recorder.calls, min_seconds=0.0, min_calls=1)
    assert replayed["flops"] == counter.get_total_flops() > 0
    assert replayed["seconds"] > 0 and replayed["calls"] == len(recorder.calls)
    assert sum(entry["flops"] for entry in replayed["by_op"].values()) == replayed["flops"]


def test_repeated_calls_are_timed_once_and_counted_every_time():
    model, frames = _net(), torch.rand(6, 3, 16, 16)
    with KernelRecorder() as once:
        _step(model, frames)
    with KernelRecorder() as thrice:
        for _ in range(3):
            _step(model, frames)
    one, three = (replay_kernels(r.calls, min_seconds=0.0, min_calls=1) for r in (once, thrice))
    assert three["calls"] == 3 * one["calls"] and three["distinct"] == one["distinct"] == one["calls"]
    assert three["flops"] == 3 * one["flops"]
    # an expanded gradient (stride 0) is replayed on a tensor of the same layout
    with KernelRecorder() as expanded:
        torch.ones(4, 1).expand(4, 3) @ torch.randn(3, 2)
    assert replay_kernels(expanded.calls, min_seconds=0.0)["flops"] == 2 * 4 * 3 * 2


@pytest.mark.parametrize("kwargs", [{"min_seconds": -1.0}, {"min_calls": 0}])
def test_bad_timing_options_are_refused(kwargs):
    with pytest.raises(ValueError, match="min_seconds must be >= 0 and min_calls >= 1"):
        replay_kernels([], **kwargs)
