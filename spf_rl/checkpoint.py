"""Atomic, ``weights_only``-loadable checkpoints of policies and training state.

A checkpoint is a plain dict of tensors, numbers, strings, lists and dicts (so
:func:`torch.load` can read it with ``weights_only=True``) with a fixed header:
``format_version``, ``model_type`` (``"spf"``, ``"rpf"``, ``"action_only"``, ``"spf_random"``)
and ``model_config`` (the :class:`~spf_rl.modules.policy.SPFConfig` as a dict).
It is written to a temporary file in the same directory, flushed and fsynced,
then moved over the target with :func:`os.replace`, so a crash never leaves a
half-written checkpoint behind.

Checkpoints are device-neutral: every tensor is saved from a CPU copy (a run on a
GPU writes the same file a CPU run would), and :func:`load_checkpoint` maps the
tensors onto any device (``map_location``, the CPU by default).
"""
from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from envs.atomic_io import atomic_write
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import MODEL_NAMES

#: Version of the checkpoint layout.
CHECKPOINT_FORMAT_VERSION = 1
#: Model types a checkpoint may hold.
MODEL_TYPES = MODEL_NAMES


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupt, or holds another kind of model."""


def cpu_copy(value: Any) -> Any:
    """``value`` with every tensor (in nested dicts, lists and tuples) on the CPU.

    CPU tensors are kept as they are (no copy); others are copied to the CPU.

    Examples:
        >>> cpu_copy({"w": torch.ones(1), "opt": [{"step": torch.tensor(3.0)}], "epoch": 2})
        {'w': tensor([1.]), 'opt': [{'step': tensor(3.)}], 'epoch': 2}
    """
    if isinstance(value, torch.Tensor):
        return value if value.device.type == "cpu" else value.detach().cpu()
    if isinstance(value, dict):
        return type(value)((key, cpu_copy(item)) for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return type(value)(cpu_copy(item) for item in value)
    return value


def first_sentence(err: BaseException) -> str:
    """The first line of an error's message, cut to its first sentence if long: torch's unpickling
    errors run over many lines, and a refused checkpoint is reported on one.

    Examples:
        >>> first_sentence(RuntimeError("Weights only load failed. In PyTorch 2.6, we changed the default value of the "
        ...                             "`weights_only` argument in torch.load from False to True." + chr(10) + "Please file an issue."))
        'Weights only load failed'
        >>> first_sentence(KeyError("model_config"))
        "'model_config'"
    """
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    first = lines[0] if lines else ""
    return first.split(". ")[0] if len(first) > 100 else first


def save_checkpoint(path: str | os.PathLike, model_type: str, config: SPFConfig, state: dict[str, Any]) -> None:
    """Write ``state`` (``model`` state dict plus anything weights-only-safe) atomically.

    Args:
        path: target file.
        model_type: one of :data:`MODEL_TYPES`.
        config: the policy configuration.
        state: at least ``{"model": state_dict}``; may hold ``optimizer``, ``step``, metrics.
            Tensors on any device are saved from CPU copies.
    """
    if model_type not in MODEL_TYPES:
        raise ValueError(f"model_type must be one of {MODEL_TYPES}, got {model_type!r}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    config_dict = asdict(config)
    config_dict["image_size"] = list(config_dict["image_size"])
    if config_dict["sparsity_range"] is not None:
        config_dict["sparsity_range"] = list(config_dict["sparsity_range"])
    payload = {
        "format_version": CHECKPOINT_FORMAT_VERSION,
        "model_type": model_type,
        "model_config": config_dict,
        **cpu_copy(state),
    }
    atomic_write(path, lambda handle: torch.save(payload, handle), binary=True)


def load_checkpoint(
    path: str | os.PathLike,
    expected_model_type: str | None = None,
    map_location: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True`` and check its header.

    Args:
        path: the checkpoint file.
        expected_model_type: if given, refuse a checkpoint of another model type.
        map_location: the device its tensors are loaded onto (the CPU by default;
            ``module.load_state_dict`` copies them to the module's device anyway).

    Returns:
        the payload, with ``model_config`` turned back into an :class:`SPFConfig`.

    Raises:
        CheckpointError: missing or corrupt file, unknown format, wrong model type.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist.")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # any unpickling failure means a bad file
        raise CheckpointError(f"checkpoint {path} is corrupt or not a checkpoint ({type(err).__name__}: {first_sentence(err)}).") from err
    if not isinstance(payload, dict) or payload.get("format_version") != CHECKPOINT_FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has an unknown format (expected version {CHECKPOINT_FORMAT_VERSION}).")
    model_type = payload.get("model_type")
    if model_type not in MODEL_TYPES:
        raise CheckpointError(f"checkpoint {path} holds an unknown model type {model_type!r}; allowed: {MODEL_TYPES}.")
    if expected_model_type is not None and model_type != expected_model_type:
        raise CheckpointError(
            f"checkpoint {path} holds a {model_type!r} model, but a {expected_model_type!r} model was asked for."
        )
    try:
        config = dict(payload["model_config"])
        config["image_size"] = tuple(config["image_size"])
        payload["model_config"] = SPFConfig(**config)
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {path} holds no valid model_config ({type(err).__name__}: {err}).") from err
    return payload
