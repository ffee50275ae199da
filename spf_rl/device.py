"""Where the policy runs: one default, one resolver, and the moves between devices.

Every recipe takes a device (``device=...`` in the OmegaConf recipes, ``--device`` in
the argparse ones) with the default :data:`DEFAULT_DEVICE`, ``"auto"``: CUDA when
:func:`torch.cuda.is_available`, else the CPU. :func:`resolve_device` turns the
setting into a :class:`torch.device`, and refuses a misspelt value or a CUDA device
that this machine lacks with a message that names the parameter and the allowed
values, before any work starts.

The split is always the same: the policy, the value head and their optimisers live on
the device; envs and rendering stay on the CPU. Collectors get ``policy_device`` (the
device) and ``env_device`` (the CPU), as TorchRL documents it
(:func:`~spf_rl.train.collection.make_collector`); evaluation moves each step's
policy inputs to the device and its outputs back (:func:`act_on_device`); training
batches move with :func:`to_device`.

Mixed precision (``amp``, off by default) is bf16 :func:`torch.autocast` on the
device's type (:func:`autocast`): on CUDA for speed; on the CPU it is allowed (and
used by the tests) but is usually slower than float32 on CPUs without native bf16.
bf16 keeps float32's exponent range, so no gradient scaler is needed. Without
``amp``, training on CUDA is full float32 (:func:`exact_float32` turns TF32 off), so
that step mode and sequence mode agree as closely as on the CPU (PPO's ratio check
relies on it).

Examples:
    >>> resolve_device("cpu")
    device(type='cpu')
    >>> resolve_device("tpu")
    Traceback (most recent call last):
    ...
    ValueError: device must be one of 'auto', 'cpu', 'cuda' or 'cuda:N' (N = 0, 1, ...), got 'tpu'.
"""
from __future__ import annotations

import contextlib
import logging
import os
import platform
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn

logger = logging.getLogger(__name__)

#: The device every recipe uses unless told otherwise: CUDA if available, else the CPU.
DEFAULT_DEVICE = "auto"
#: How the allowed values are named in error messages and help texts.
DEVICE_CHOICES = "'auto', 'cpu', 'cuda' or 'cuda:N' (N = 0, 1, ...)"
#: The dtype of mixed precision (``amp=True``).
AMP_DTYPE = torch.bfloat16
_SPELLING = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")

__all__ = [
    "AMP_DTYPE",
    "DEFAULT_DEVICE",
    "DEVICE_CHOICES",
    "act_on_device",
    "autocast",
    "check_device",
    "exact_float32",
    "machine_info",
    "module_device",
    "resolve_device",
    "to_device",
]


def check_device(value: str | torch.device, name: str = "device") -> str | torch.device:
    """Check the spelling of a device setting (no CUDA look-up); return it unchanged.

    Config dataclasses call it in ``__post_init__`` so that a typo fails when the
    config is read. A :class:`torch.device` passes as it is (tests use ``meta``).

    Args:
        value: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a :class:`torch.device`.
        name: the parameter's name in the error message (``"device"``, ``"--device"``).

    Raises:
        ValueError: any other value.

    Examples:
        >>> check_device("cuda:1")
        'cuda:1'
        >>> check_device("gpu", name="--device")
        Traceback (most recent call last):
        ...
        ValueError: --device must be one of 'auto', 'cpu', 'cuda' or 'cuda:N' (N = 0, 1, ...), got 'gpu'.
    """
    if isinstance(value, torch.device):
        return value
    if not isinstance(value, str) or not _SPELLING.match(value):
        raise ValueError(f"{name} must be one of {DEVICE_CHOICES}, got {value!r}.")
    return value


def resolve_device(value: str | torch.device = DEFAULT_DEVICE, name: str = "device") -> torch.device:
    """The :class:`torch.device` of a device setting.

    ``"auto"`` is CUDA (the current CUDA device) when :func:`torch.cuda.is_available`,
    else the CPU. ``"cuda"`` / ``"cuda:N"`` must exist on this machine.

    Args:
        value: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a :class:`torch.device`
            (returned as it is).
        name: the parameter's name in error messages.

    Raises:
        ValueError: a value outside the allowed ones, a CUDA device on a machine
            without CUDA, or a CUDA index this machine does not have.

    Examples:
        >>> resolve_device("auto") == (torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu"))
        True
        >>> resolve_device(torch.device("meta"))
        device(type='meta')
    """
    value = check_device(value, name)
    if isinstance(value, torch.device):
        return value
    if value == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    if value == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise ValueError(
            f"{name}={value!r} needs CUDA, but torch.cuda.is_available() is False on this machine "
            f"(torch {torch.__version__}, "
            f"{f'built for CUDA {torch.version.cuda}, no GPU visible' if torch.version.cuda else 'a CPU-only build'}). "
            f"Use {name}=cpu, or {name}=auto to take CUDA only where it is available."
        )
    device = torch.device(value)
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise ValueError(f"{name}={value!r}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}.")
    return device


def module_device(module: nn.Module) -> torch.device:
    """The device of a module's first parameter (or buffer); the CPU for a module without either.

    Examples:
        >>> module_device(nn.Linear(2, 2)), module_device(nn.Identity())
        (device(type='cpu'), device(type='cpu'))
    """
    for tensor in module.parameters():
        return tensor.device
    for tensor in module.buffers():
        return tensor.device
    return torch.device("cpu")


def to_device(tensordict: TensorDictBase, device: torch.device | str | None) -> TensorDictBase:
    """``tensordict`` with every leaf on ``device`` (``None``, or already there: unchanged).

    The one move of training batches and policy inputs; CUDA copies are non-blocking
    (pinned-memory sources overlap with compute).

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"a": torch.zeros(2), ("n", "b"): torch.ones(2, 1)}, [2])
        >>> {leaf.device.type for leaf in to_device(td, torch.device("meta")).values(True, True)}
        {'meta'}
        >>> to_device(td, "cpu") is td
        True
    """
    if device is None:
        return tensordict
    device = torch.device(device)
    if tensordict.device == device:
        return tensordict
    if tensordict.device is None and all(leaf.device == device for leaf in tensordict.values(True, True)):
        return tensordict
    return tensordict.to(device, non_blocking=device.type == "cuda")


def autocast(device: torch.device | str, enabled: bool) -> contextlib.AbstractContextManager:
    """bf16 :func:`torch.autocast` on ``device``'s type when ``enabled``, else a no-op context.

    Wraps forward passes and losses (not the backward pass or the optimiser step).

    Examples:
        >>> with autocast("cpu", True):
        ...     (torch.ones(2, 2) @ torch.ones(2, 2)).dtype
        torch.bfloat16
        >>> with autocast("cpu", False):
        ...     (torch.ones(2, 2) @ torch.ones(2, 2)).dtype
        torch.float32
    """
    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(device_type=torch.device(device).type, dtype=AMP_DTYPE)


@contextlib.contextmanager
def exact_float32(device: torch.device | str, enabled: bool = True) -> Iterator[None]:
    """Full float32 convolutions and matrix products on CUDA inside (no TF32); restored after.

    Training loops enter it with ``enabled=not amp``: mixed precision is the fast path.

    PyTorch lets cuDNN convolutions use TF32 (10-bit mantissa) by default; step mode
    (one frame per row) and sequence mode (all frames at once) may then pick other
    kernels and differ by ~1e-3. Nothing changes on other devices.

    Examples:
        >>> with exact_float32("cpu"):
        ...     torch.ones(1).dtype
        torch.float32
    """
    if not enabled or torch.device(device).type != "cuda":
        yield
        return
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@contextlib.contextmanager
def torch_threads_kept() -> Iterator[None]:
    """Keep this process's torch intra-op threads across the block.

    TorchRL's multi-process collectors lower the parent's threads when they start (to the
    threads left beside their workers) and, when they shut down, set them to the threads they
    found plus one per worker, up to the count at import. A process that ran with fewer threads
    than that (one of several sharing a machine, ``OMP_NUM_THREADS=1``) then trains on more
    threads after a multi-process evaluation or DAgger round than before it, and its float
    sums, ordered otherwise, differ: a resumed run would not end where an uninterrupted one does.

    Examples:
        >>> threads = torch.get_num_threads()
        >>> with torch_threads_kept():
        ...     torch.set_num_threads(threads + 1)
        >>> torch.get_num_threads() == threads
        True
    """
    threads = torch.get_num_threads()
    try:
        yield
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def act_on_device(
    policy: Callable[[TensorDictBase], TensorDictBase],
    device: torch.device | None,
    in_keys: list | None = None,
    out_keys: list | None = None,
) -> Callable[[TensorDictBase], TensorDictBase]:
    """Wrap a step-mode policy so that an env on another device (the CPU) can call it.

    The wrapper moves the policy's ``in_keys`` of each step to ``device``, runs the
    policy there, and writes its ``out_keys`` back into the env's tensordict on the
    env's device. Only those keys travel: the observation (frames, demonstration,
    recurrent state) to the device, the logits, action and next recurrent state back.
    With ``device=None``, or the tensordict already there, the policy is called as it is.

    Args:
        policy: a TensorDict policy (``in_keys`` / ``out_keys`` read from it unless given).
        device: where the policy's weights are (:func:`module_device`).
        in_keys: keys the policy reads (default ``policy.in_keys``).
        out_keys: keys written back (default ``policy.out_keys``).

    Examples:
        >>> from tensordict import TensorDict
        >>> seen = []
        >>> def policy(td):  # records where its inputs are; answers on the CPU
        ...     seen.extend(sorted({leaf.device.type for leaf in td.values(True, True)}))
        ...     return TensorDict({"action": torch.zeros(td.shape[0], dtype=torch.long)}, td.batch_size)
        >>> td = TensorDict({"obs": torch.ones(2, 3), "other": torch.ones(2)}, [2], device="cpu")
        >>> act = act_on_device(policy, torch.device("meta"), in_keys=["obs"], out_keys=["action"])
        >>> act(td)["action"].device, seen
        (device(type='cpu'), ['meta'])
    """
    in_keys = list(policy.in_keys if in_keys is None else in_keys)
    out_keys = list(policy.out_keys if out_keys is None else out_keys)

    def act(tensordict: TensorDictBase) -> TensorDictBase:
        home = tensordict.device
        if device is None or home == device:
            return policy(tensordict)
        inputs = to_device(tensordict.select(*in_keys, strict=False), device)
        outputs = policy(inputs).select(*out_keys, strict=False)
        tensordict.update(outputs.to(home if home is not None else torch.device("cpu")))
        return tensordict

    return act


def machine_info() -> dict:
    """The machine a run or benchmark ran on: CPU model (with its family/model/stepping) and count, the SIMD level
    torch's CPU kernels dispatch to, library versions, GL back-end, thread settings and the load average now.

    A seed's training result is bit-identical on one CPU model but not across them (float32 kernels accumulate in
    another order), so every run's ``results.json`` records this beside its numbers (``machine_this_run``).

    Examples:
        >>> info = machine_info()
        >>> info["cpu_count"] == os.cpu_count() and info["torch"] == torch.__version__
        True
        >>> info["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()  # e.g. "AVX2" or "AVX512"
        True
    """
    import mujoco
    import tensordict
    import torchrl

    cpu_model, cpuinfo = platform.processor(), {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            cpuinfo.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    cpu_model = cpuinfo.get("model name", cpu_model)
    # one model name ("AMD EPYC") covers several generations: family/model/stepping tell them apart
    cpu_id = "/".join(cpuinfo.get(key, "?") for key in ("cpu family", "model", "stepping")) if cpuinfo else None
    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model,
        "cpu_family_model_stepping": cpu_id,
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cuda_device": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "tensordict": tensordict.__version__,
        "mujoco": mujoco.__version__,
        "MUJOCO_GL": os.environ.get("MUJOCO_GL"),
        "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"),
        "torch_num_threads": torch.get_num_threads(),
        "load_average_1_5_15": [round(x, 2) for x in os.getloadavg()],
    }
