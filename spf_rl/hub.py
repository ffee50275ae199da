"""Shipped checkpoints by name, and a ready policy from a checkpoint in one call.

The repository ships trained policies in ``checkpoints/`` (next to the ``spf_rl``
package in a clone; inside it, as ``spf_rl/checkpoints``, in a wheel). Every file there is
stored once and listed in ``checkpoints/manifest.json`` with its SHA-256; the manifest
also maps each shipped name to its file: ``"spf-s0.8"`` is the Table 1 seed that was
best by validation, ``checkpoints/table1/spf-s0.8-seed2.pt``. A listed file whose bytes
differ from the manifest is refused before it is read.

Examples:
    >>> import spf_rl
    >>> "spf-s0.8" in spf_rl.list_checkpoints()
    True
    >>> policy, config = spf_rl.load_policy("spf-s0.8")
    >>> policy.training, config.sparsity, config.memory_length
    (False, 0.8, 24)
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import torch

from envs.atomic_io import atomic_write_json
from spf_rl.checkpoint import CheckpointError, file_sha256, load_checkpoint
from spf_rl.device import resolve_device
from spf_rl.modules.policy import SPFConfig, SPFPolicy
from spf_rl.modules.registry import build_policy

_PACKAGE = Path(__file__).resolve().parent
#: Where the shipped checkpoints live: inside the package when it is installed from a wheel
#: (``spf_rl/checkpoints``: the manifest and the files its names load, setup.py), else
#: ``checkpoints/`` at the root of the clone.
CHECKPOINT_DIR = _PACKAGE / "checkpoints" if (_PACKAGE / "checkpoints").is_dir() else _PACKAGE.parent / "checkpoints"
#: The shipped checkpoint that DAgger and PPO start from by default.
DEFAULT_START_CHECKPOINT = "spf-s0.8"
#: The manifest of a checkpoint directory: ``{"names": {name: file}, "files": {file: sha256}}``,
#: files relative to the directory.
MANIFEST_NAME = "manifest.json"


class LoadedPolicy(NamedTuple):
    """What :func:`load_policy` returns: unpack it as ``policy, config = load_policy(...)``."""

    #: the policy, in eval mode, with the checkpoint's weights.
    policy: SPFPolicy
    #: the policy's configuration (memory mode resolved: ``"full"`` for RPF, ``"none"`` for action-only).
    config: SPFConfig


def checkpoint_dir() -> Path:
    """The directory of the shipped checkpoints.

    Raises:
        FileNotFoundError: neither the installed package nor a clone holds them.
    """
    if not CHECKPOINT_DIR.is_dir():
        raise FileNotFoundError(
            f"the shipped checkpoints are not available: {CHECKPOINT_DIR} does not exist. They ship inside the "
            "wheel (spf_rl/checkpoints) and in a clone's checkpoints/ directory; reinstall spf-rl, or pass the "
            "path of a checkpoint file."
        )
    return CHECKPOINT_DIR


def read_manifest(directory: str | os.PathLike | None = None) -> dict[str, dict[str, str]]:
    """The manifest of a checkpoint directory (the shipped one by default)."""
    directory = checkpoint_dir() if directory is None else Path(directory)
    path = directory / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: the checkpoint directory has no manifest (write_manifest makes one).")
    return json.loads(path.read_text())


def write_manifest(directory: str | os.PathLike, names: dict[str, str]) -> dict[str, dict[str, str]]:
    """Write ``directory``'s manifest: every ``*.pt`` below it with its SHA-256, and ``names``
    (shipped name -> file relative to ``directory``), each of which must be one of the files.

    Examples:
        >>> import tempfile
        >>> directory = Path(tempfile.mkdtemp())
        >>> (directory / "table1").mkdir()
        >>> _ = (directory / "table1" / "a-seed0.pt").write_bytes(b"weights")
        >>> manifest = write_manifest(directory, {"a": "table1/a-seed0.pt"})
        >>> manifest["names"], list(manifest["files"])
        ({'a': 'table1/a-seed0.pt'}, ['table1/a-seed0.pt'])
    """
    directory = Path(directory)
    files = {path.relative_to(directory).as_posix(): file_sha256(path) for path in sorted(directory.rglob("*.pt"))}
    missing = sorted(set(names.values()) - set(files))
    if missing:
        raise ValueError(f"names point to files that are not in {directory}: {missing}")
    manifest = {"names": dict(sorted(names.items())), "files": files}
    atomic_write_json(directory / MANIFEST_NAME, manifest)
    return manifest


def verify_checkpoint_file(path: str | os.PathLike, directory: str | os.PathLike | None = None) -> None:
    """Refuse a file of the shipped checkpoint directory that its manifest does not list, or
    whose bytes differ from the listed SHA-256; files elsewhere pass unchecked.

    Raises:
        CheckpointError: an unlisted or changed shipped file.
    """
    directory = CHECKPOINT_DIR if directory is None else Path(directory)
    path = Path(path).resolve()
    if not path.is_relative_to(directory.resolve()):
        return
    relative = path.relative_to(directory.resolve()).as_posix()
    expected = read_manifest(directory)["files"].get(relative)
    if expected is None:
        raise CheckpointError(f"{path} is in {directory} but not in its {MANIFEST_NAME}: a shipped file must be listed.")
    actual = file_sha256(path)
    if actual != expected:
        raise CheckpointError(
            f"{path} differs from {MANIFEST_NAME} (sha256 {actual[:12]}..., listed {expected[:12]}...): "
            "restore it (git checkout -- checkpoints) or list it again with write_manifest."
        )


def shipped_file_sha256() -> frozenset[str]:
    """The SHA-256 of every shipped file (the manifest's; none where no checkpoints are shipped here): a file
    without an embedded checksum that is one of these is intact, wherever it lies
    (:func:`~spf_rl.checkpoint.load_checkpoint`)."""
    try:
        return frozenset(read_manifest()["files"].values())
    except FileNotFoundError:
        return frozenset()


def list_checkpoints() -> list[str]:
    """Names of the shipped checkpoints (``checkpoints/manifest.json``), sorted.

    Examples:
        >>> list_checkpoints()[:3]
        ['action_only-s0', 'dagger-rpf-s1', 'dagger-rpf_original-s1']
    """
    return sorted(read_manifest()["names"])


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
        if path.is_dir():
            raise FileNotFoundError(f"checkpoint file {text} is a directory, not a checkpoint file.")
        raise FileNotFoundError(f"checkpoint file {text} does not exist.")
    names = read_manifest()["names"]
    if text not in names:
        raise ValueError(
            f"unknown checkpoint name {text!r}; the shipped checkpoints are: {', '.join(sorted(names))} "
            "(or pass the path of a .pt file)."
        )
    return checkpoint_dir() / names[text]


def checked_checkpoint(path_or_name: str | os.PathLike) -> Path:
    """The file of a checkpoint given by path or shipped name (:func:`resolve_checkpoint`),
    checked against the manifest if it is a shipped file (:func:`verify_checkpoint_file`).

    Examples:
        >>> checked_checkpoint("spf-s0.8").relative_to(CHECKPOINT_DIR).as_posix()
        'table1/spf-s0.8-seed2.pt'
    """
    path = resolve_checkpoint(path_or_name)
    verify_checkpoint_file(path)
    return path


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
        CheckpointError: missing or corrupt file, unknown format, wrong model type, or a shipped
            file that differs from its manifest.
    """
    device = resolve_device(device)
    verify_checkpoint_file(path)
    payload = load_checkpoint(path, expected_model_type=expected_model_type, map_location=device,
                              known_file_sha256=shipped_file_sha256())

    def refused(err: Exception) -> CheckpointError:  # on one line: load_state_dict lists the keys over many
        reason = " ".join(line.strip() for line in str(err).splitlines() if line.strip())
        return CheckpointError(f"checkpoint {path} does not load into its {payload['model_type']!r} model ({type(err).__name__}: {reason}).")

    try:
        policy = build_policy(payload["model_type"], payload["model_config"])
    except ValueError as err:  # a memory layout its model type does not have
        raise refused(err) from err
    policy = policy.to(device)
    try:
        policy.load_state_dict(payload["model"])
    except (KeyError, RuntimeError) as err:  # no weights, or weights of another network
        raise refused(err) from err
    return policy.eval(), payload


class CheckedCheckpoint(NamedTuple):
    """What :func:`checkpoint_argument` returns."""

    #: the checkpoint file.
    path: Path
    #: its policy, on the CPU, in eval mode, with the checkpoint's weights.
    policy: SPFPolicy
    #: its payload, as :func:`~spf_rl.checkpoint.load_checkpoint` returns it.
    payload: dict[str, Any]


def checkpoint_argument(path_or_name: str | os.PathLike, argument: str, *, model_type: str | None = None) -> CheckedCheckpoint:
    """A checkpoint given on a command line or in a recipe's config (a path or a shipped name),
    checked before any work: the file exists, is a listed and unchanged shipped file if it is
    one, and loads into its policy (on the CPU).

    Args:
        path_or_name: the value given.
        argument: what gave it, leading the error message: ``"argument --checkpoint"``,
            ``"checkpoint"`` (a config key), ...
        model_type: if given, refuse a checkpoint of another model type.

    Raises:
        ValueError: ``"<argument>: <why>"`` on one line: a missing file or directory, an unknown
            shipped name (the message lists the shipped ones), an unreadable or corrupt file, a
            changed shipped file, or another model type.

    Examples:
        >>> checkpoint_argument("spf-s0.8", "argument --checkpoint").payload["model_type"]
        'spf'
        >>> checkpoint_argument("missing.pt", "argument --checkpoint")
        Traceback (most recent call last):
        ...
        ValueError: argument --checkpoint: checkpoint file missing.pt does not exist.
    """
    try:
        path = resolve_checkpoint(path_or_name)
        policy, payload = policy_from_checkpoint(path, expected_model_type=model_type)
    except (OSError, ValueError, CheckpointError) as err:  # OSError: FileNotFoundError, an unreadable file
        raise ValueError(f"{argument}: {err}") from None
    return CheckedCheckpoint(path, policy, payload)


def load_policy(
    path_or_name: str | os.PathLike, *, model_type: str | None = None, device: str | torch.device = "cpu"
) -> LoadedPolicy:
    """A ready policy from a shipped checkpoint name or a checkpoint path.

    Args:
        path_or_name: a name from :func:`list_checkpoints` (``"spf-s0.8"``,
            ``"rpf-s1"``, ``"dagger-spf-s0.8"``, ...), the path of a checkpoint
            written by the recipes (``runs/bc/<run>/best.pt``), or an export directory
            (``recipes/export.py``: an :class:`~spf_rl.modules.exported.ExportedPolicy`, on the CPU).
        model_type: if given, refuse a checkpoint of another model type
            (``"spf"``, ``"rpf"``, ``"action_only"``, ``"spf_random"``).
        device: where the policy goes (``"cpu"`` by default; ``"auto"``, ``"cuda"``,
            ``"cuda:N"``); feed it inputs on that device, or evaluate it with
            :func:`~spf_rl.evaluation.evaluate_policy`, which moves them.

    Returns:
        ``(policy, config)``: the policy in eval mode (step by step in a collector,
        or over whole episodes under :func:`torchrl.modules.set_recurrent_mode`)
        and its :class:`~spf_rl.modules.policy.SPFConfig`.

    Raises:
        ValueError: an unknown name, or a device this machine does not have.
        FileNotFoundError: a path that does not exist.
        CheckpointError: a corrupt file or another model type.
    """
    from spf_rl.modules.exported import ExportedPolicy, is_export

    if is_export(path_or_name):  # an export directory (recipes/export.py), run by ONNX Runtime on the CPU
        try:
            policy = ExportedPolicy(path_or_name)
        except ImportError as err:
            raise ValueError(f"{path_or_name} is an export: running it needs the runtime (pip install ./runtime)") from err
        exported_type = policy.model_type
        if model_type is not None and exported_type != model_type:
            raise CheckpointError(f"export {path_or_name} holds a {exported_type!r} model, but a {model_type!r} model was asked for.")
        return LoadedPolicy(policy, policy.config)
    policy, _ = policy_from_checkpoint(resolve_checkpoint(path_or_name), expected_model_type=model_type, device=device)
    return LoadedPolicy(policy, policy.config)


__all__ = [
    "CHECKPOINT_DIR",
    "DEFAULT_START_CHECKPOINT",
    "MANIFEST_NAME",
    "CheckedCheckpoint",
    "LoadedPolicy",
    "checked_checkpoint",
    "checkpoint_argument",
    "checkpoint_dir",
    "list_checkpoints",
    "read_manifest",
    "verify_checkpoint_file",
    "write_manifest",
    "load_policy",
    "policy_from_checkpoint",
    "resolve_checkpoint",
]
