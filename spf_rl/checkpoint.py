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

Every checkpoint :func:`save_checkpoint` writes carries the SHA-256 of its own content
(:data:`CHECKSUM_KEY`, :func:`content_sha256`: every tensor's dtype, shape and bytes and every
other value, in a fixed order), and :func:`load_checkpoint` refuses a file whose content no
longer matches it, wherever the file lives: a flipped byte in the weights is an error that
names the file, not a silently different policy. A file written before the checksum existed is
accepted where its bytes are a shipped file's (``known_file_sha256``: the manifest's hashes, so a copy of a
shipped checkpoint anywhere is checked too); any other such file loads with a warning that names it.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Container
from pathlib import Path
from typing import Any

import torch

from envs.atomic_io import atomic_write
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import MODEL_NAMES

logger = logging.getLogger(__name__)

#: Version of the checkpoint layout.
CHECKPOINT_FORMAT_VERSION = 1
#: The payload key of a checkpoint's embedded SHA-256 of the rest of its content (:func:`content_sha256`).
CHECKSUM_KEY = "content_sha256"
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


def _moved(value: Any, device: torch.device) -> Any:
    """``value`` with every tensor (in nested dicts, lists and tuples) on ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return type(value)((key, _moved(item, device)) for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return type(value)(_moved(item, device) for item in value)
    return value


def content_sha256(value: Any) -> str:
    """The SHA-256 of a checkpoint's content, as hex: every tensor's dtype, shape and bytes, every
    other value as JSON, dict entries in the order of their keys. It does not depend on the file
    (``torch.save``'s container), the tensors' devices or the dicts' insertion order.

    Examples:
        >>> a = content_sha256({"w": torch.ones(2), "step": 3})
        >>> a == content_sha256({"step": 3, "w": torch.ones(2)}), a == content_sha256({"w": torch.ones(2), "step": 4})
        (True, False)
        >>> content_sha256({"w": torch.ones(2)}) == content_sha256({"w": torch.ones(2, dtype=torch.float64)})
        False
    """
    digest = hashlib.sha256()
    _feed(digest, value)
    return digest.hexdigest()


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, as hex (the shipped manifest lists each file's)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _feed(digest: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        tensor = value.detach().cpu().contiguous()
        digest.update(f"tensor {tensor.dtype} {tuple(tensor.shape)}:".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, dict):
        digest.update(f"dict {len(value)}:".encode())
        for key in sorted(value, key=repr):
            digest.update(f"{key!r}=".encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"list {len(value)}:".encode())
        for item in value:
            _feed(digest, item)
    else:
        digest.update(f"{json.dumps(value, default=repr)};".encode())


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
    config_dict = config.to_dict()
    config_dict["image_size"] = list(config_dict["image_size"])
    if config_dict["sparsity_range"] is not None:
        config_dict["sparsity_range"] = list(config_dict["sparsity_range"])
    payload = {
        "format_version": CHECKPOINT_FORMAT_VERSION,
        "model_type": model_type,
        "model_config": config_dict,
        **cpu_copy(state),
    }
    payload[CHECKSUM_KEY] = content_sha256(payload)
    atomic_write(path, lambda handle: torch.save(payload, handle), binary=True)


def load_checkpoint(
    path: str | os.PathLike,
    expected_model_type: str | None = None,
    map_location: str | torch.device = "cpu",
    known_file_sha256: Container[str] = (),
) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True`` and check its header.

    A file with an embedded checksum (:data:`CHECKSUM_KEY`, every file :func:`save_checkpoint` writes) is
    verified against it. A file from before checksums existed is accepted as it is where its SHA-256 is one
    of ``known_file_sha256`` (the shipped manifest's, :mod:`spf_rl.hub`: a copy of a shipped file anywhere);
    any other such file loads with a warning that names it: it cannot be verified.

    Args:
        path: the checkpoint file.
        expected_model_type: if given, refuse a checkpoint of another model type.
        map_location: the device its tensors are loaded onto (the CPU by default;
            ``module.load_state_dict`` copies them to the module's device anyway).
        known_file_sha256: SHA-256s of files known to be intact, for files without a checksum.

    Returns:
        the payload, with ``model_config`` turned back into an :class:`SPFConfig`.

    Raises:
        CheckpointError: missing, corrupt or damaged file (content unlike its embedded SHA-256), unknown
            format, wrong model type.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist.")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)  # checked on the CPU, then moved
    except Exception as err:  # any unpickling failure means a bad file
        raise CheckpointError(f"checkpoint {path} is corrupt or not a checkpoint ({type(err).__name__}: {first_sentence(err)}).") from err
    if not isinstance(payload, dict) or payload.get("format_version") != CHECKPOINT_FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has an unknown format (expected version {CHECKPOINT_FORMAT_VERSION}).")
    stored = payload.pop(CHECKSUM_KEY, None)
    if stored is None:
        if file_sha256(path) not in known_file_sha256:
            logger.warning("checkpoint %s carries no checksum (written before checkpoints had one) and is no shipped "
                           "file: it cannot be verified", path)
    elif content_sha256(payload) != stored:
        raise CheckpointError(
            f"checkpoint {path} is damaged: its content no longer matches the SHA-256 written into it "
            "(a changed or corrupted file); restore it, or train it again."
        )
    if torch.device(map_location).type != "cpu":
        payload = _moved(payload, torch.device(map_location))
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
