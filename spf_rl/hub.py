"""Shipped checkpoints by name, and a ready policy from a checkpoint in one call.

The repository ships trained policies in ``checkpoints/`` (next to the
``spf_rl`` package in a clone installed with ``pip install -e .``). A shipped
checkpoint is named by its file stem: ``"spf-s0.8"`` is ``checkpoints/spf-s0.8.pt``.

Examples:
    >>> import spf_rl
    >>> "spf-s0.8" in spf_rl.list_checkpoints()
    True
    >>> policy, config = spf_rl.load_policy("spf-s0.8")
    >>> policy.training, config.sparsity, config.memory_length
    (False, 0.8, 24)
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import torch

from spf_rl.checkpoint import load_checkpoint
from spf_rl.device import resolve_device
from spf_rl.modules.policy import SPFConfig, SPFPolicy
from spf_rl.modules.registry import build_policy

#: Where the shipped checkpoints live: ``checkpoints/`` at the root of the repository.
CHECKPOINT_DIR = Path(__file__).resolve().parent.parent / "checkpoints"


class LoadedPolicy(NamedTuple):
    """What :func:`load_policy` returns: unpack it as ``policy, config = load_policy(...)``."""

    #: the policy, in eval mode, with the checkpoint's weights.
    policy: SPFPolicy
    #: the policy's configuration (memory mode resolved: ``"full"`` for RPF, ``"none"`` for action-only).
    config: SPFConfig


def checkpoint_dir() -> Path:
    """The directory of the shipped checkpoints.

    Raises:
        FileNotFoundError: the package is not installed from a clone of the repository,
            so there is no ``checkpoints/`` directory next to it.
    """
    if not CHECKPOINT_DIR.is_dir():
        raise FileNotFoundError(
            f"the shipped checkpoints are not available: {CHECKPOINT_DIR} does not exist. They ship in the "
            "repository's checkpoints/ directory; install spf-rl from a clone (pip install -e .) to load them "
            "by name, or pass the path of a checkpoint file."
        )
    return CHECKPOINT_DIR


def list_checkpoints() -> list[str]:
    """Names of the shipped checkpoints (file stems of ``checkpoints/*.pt``), sorted.

    Examples:
        >>> list_checkpoints()[:3]
        ['action_only-s0', 'dagger-rpf-s1', 'dagger-rpf_original-s1']
    """
    return sorted(path.stem for path in checkpoint_dir().glob("*.pt"))


def resolve_checkpoint(path_or_name: str | os.PathLike) -> Path:
    """The file of a checkpoint given by path or by shipped name.

    An existing file is taken as it is. A :class:`~pathlib.Path`, or a string that
    ends in ``.pt`` or holds a directory separator, is a path and must exist;
    any other string is a shipped name (see :func:`list_checkpoints`).

    Raises:
        FileNotFoundError: a path that does not exist, or no shipped checkpoints.
        ValueError: an unknown name (the message lists the shipped ones).
    """
    path = Path(path_or_name)
    if path.is_file():
        return path
    text = os.fspath(path_or_name)
    if not isinstance(path_or_name, str) or text.endswith(".pt") or os.sep in text or "/" in text:
        raise FileNotFoundError(f"checkpoint file {text} does not exist.")
    names = list_checkpoints()
    if text not in names:
        raise ValueError(
            f"unknown checkpoint name {text!r}; the shipped checkpoints are: {', '.join(names)} "
            "(or pass the path of a .pt file)."
        )
    return checkpoint_dir() / f"{text}.pt"


def policy_from_checkpoint(
    path: str | os.PathLike,
    expected_model_type: str | None = None,
    device: str | torch.device = "cpu",
) -> tuple[SPFPolicy, dict[str, Any]]:
    """Build the policy a checkpoint file holds and load its weights (eval mode) on ``device``.

    Args:
        path: a checkpoint file.
        expected_model_type: refuse a checkpoint of another model type.
        device: where the policy goes: ``"cpu"`` (default), ``"auto"``, ``"cuda"``,
            ``"cuda:N"`` (see :func:`~spf_rl.device.resolve_device`); any checkpoint
            loads on any of them.

    Returns:
        (the policy, the checkpoint's payload as :func:`~spf_rl.checkpoint.load_checkpoint` returns it).

    Raises:
        CheckpointError: missing or corrupt file, unknown format, wrong model type.
    """
    device = resolve_device(device)
    payload = load_checkpoint(path, expected_model_type=expected_model_type, map_location=device)
    policy = build_policy(payload["model_type"], payload["model_config"]).to(device)
    policy.load_state_dict(payload["model"])
    return policy.eval(), payload


def load_policy(
    path_or_name: str | os.PathLike, *, model_type: str | None = None, device: str | torch.device = "cpu"
) -> LoadedPolicy:
    """A ready policy from a shipped checkpoint name or a checkpoint path.

    Args:
        path_or_name: a name from :func:`list_checkpoints` (``"spf-s0.8"``,
            ``"rpf-s1"``, ``"dagger-spf-s0.8"``, ...) or the path of a checkpoint
            written by the recipes (``runs/bc/<run>/best.pt``).
        model_type: if given, refuse a checkpoint of another model type
            (``"spf"``, ``"rpf"``, ``"action_only"``, ``"spf_random"``).
        device: where the policy goes (``"cpu"`` by default; ``"auto"``, ``"cuda"``,
            ``"cuda:N"``); feed it inputs on that device, or evaluate it with
            :func:`~spf_rl.train.evaluation.evaluate_policy`, which moves them.

    Returns:
        ``(policy, config)``: the policy in eval mode (step by step in a collector,
        or over whole episodes under :func:`torchrl.modules.set_recurrent_mode`)
        and its :class:`~spf_rl.modules.policy.SPFConfig`.

    Raises:
        ValueError: an unknown name, or a device this machine does not have.
        FileNotFoundError: a path that does not exist.
        CheckpointError: a corrupt file or another model type.
    """
    policy, _ = policy_from_checkpoint(resolve_checkpoint(path_or_name), expected_model_type=model_type, device=device)
    return LoadedPolicy(policy, policy.config)


__all__ = [
    "CHECKPOINT_DIR",
    "LoadedPolicy",
    "checkpoint_dir",
    "list_checkpoints",
    "load_policy",
    "policy_from_checkpoint",
    "resolve_checkpoint",
]
