"""The per-episode result cache: one policy's records on one set of episodes, and the key that says
what they are of.

Evaluating a policy on a thousand episodes takes minutes to hours, so every recipe that scores a
policy keeps its per-episode records and takes them again where they are of the very same policy on
the very same episodes, scored the same way:

- a training run's test records beside its results (:data:`TEST_EPISODES_FILE`, ``recipes/bc.py``,
  ``recipes/dagger.py``; the lengths run writes one file per length);
- Table 1's evaluations (``results/eval/table1/<set>/<line>-seed<S>.json``, ``recipes/table1.py``);
- the route benchmark's cells (its ``--out`` JSON, ``recipes/route_bench.py``).

All three use :func:`records_key` as the key and compare it with :func:`changed_fields`:

- ``episodes``: the episodes' identity (:func:`~spf_rl.evaluation.episode_identity`: the
  :class:`~envs.episode_spec.EpisodeSpec`'s identity, the number of episodes and whether frames
  were rendered);
- ``env_version``: :data:`~envs.version.ENV_VERSION` (scenes, renderer, noise, numbering);
- ``arrival``: :data:`~envs.follow.ARRIVAL_RULE`, the rule that scores arrival on a route;
- ``policy_sha256``: :func:`policy_sha256`, a hash of the policy's weights, its model config and
  the sparsity it reads its memory at, never of a file or its path, so moving or rewriting a
  checkpoint keeps its evaluations, and a view of the same weights at another demonstration
  length or sparsity has its own. ``None``: a policy without weights (open-loop replay).

A cache file is one JSON object (:func:`write_records`): the key under ``"key"``, the records as
per-episode columns under ``"columns"``, and whatever the writer adds beside them (the line, the
round, the checkpoint's path: information, never part of the key). ``recipes/paired.py`` reads
these files as they are.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from envs.atomic_io import atomic_write_json
from envs.follow import ARRIVAL_RULE
from envs.version import ENV_VERSION
from spf_rl.checkpoint import content_sha256
from spf_rl.evaluation import EvalConfig, episode_identity

logger = logging.getLogger(__name__)

#: A run's per-episode test records, beside its ``results.json`` (``recipes/bc.py``, ``recipes/dagger.py``).
TEST_EPISODES_FILE = "test_episodes.json"


def length_test_episodes_file(demo_length: int) -> str:
    """The name of the lengths run's test records at one demonstration length.

    Examples:
        >>> length_test_episodes_file(60)
        'test_episodes-n60.json'
    """
    return f"test_episodes-n{demo_length}.json"

#: The parts of a key that fix the episodes and their scoring (the route benchmark keys a cell with them).
EPISODE_KEY_FIELDS = ("episodes", "env_version", "arrival")


def policy_sha256(policy: Any) -> str | None:
    """The SHA-256 of what decides ``policy``'s actions: its weights (``state_dict``), its model config
    (``policy.config``, where it has one) and the sparsity it reads its memory at (``policy.sparsity``:
    a random-sparsity model's :meth:`~spf_rl.modules.policy.SPFPolicy.set_sparsity` is not in its
    weights); ``None`` for a policy without weights (open-loop replay); for a policy that names what decides
    its actions itself (``cache_identity()``: an export run by ONNX Runtime), the hash of that. The same
    weights loaded from another file, path or device give the same hash (:func:`~spf_rl.checkpoint.content_sha256`).

    Examples:
        >>> from spf_rl.modules import OpenLoopPolicy, SPFConfig, SPFPolicy
        >>> policy = SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8, image_size=(16, 16), sparsity_range=(0.2, 1.0)))
        >>> a = policy_sha256(policy)
        >>> a == policy_sha256(policy), a == policy_sha256(policy.set_sparsity(0.4)), policy_sha256(OpenLoopPolicy())
        (True, False, None)
    """
    identity = getattr(policy, "cache_identity", None)
    if identity is not None:  # a policy whose weights live elsewhere (an export run by ONNX Runtime)
        return content_sha256({"identity": identity()})
    weights = policy.state_dict()
    if not weights:
        return None
    config = getattr(policy, "config", None)
    sparsity = getattr(policy, "sparsity", None)
    if hasattr(config, "to_dict"):  # SPFConfig: fields added since models shipped count only when set
        config = config.to_dict()
    elif dataclasses.is_dataclass(config):
        config = dataclasses.asdict(config)
    return content_sha256({
        "weights": dict(weights),
        "config": config if isinstance(config, dict) else None,
        "sparsity": None if sparsity is None else float(sparsity),
    })


def episodes_key(config: EvalConfig) -> dict:
    """The part of :func:`records_key` that fixes the episodes and their scoring, as JSON stores it.

    Examples:
        >>> sorted(episodes_key(EvalConfig()))
        ['arrival', 'env_version', 'episodes']
    """
    return {"episodes": json.loads(json.dumps(episode_identity(config))), "env_version": ENV_VERSION, "arrival": ARRIVAL_RULE}


def records_key(config: EvalConfig, policy: Any) -> dict:
    """What the records of ``policy`` on ``config``'s episodes are of: :func:`episodes_key` and
    :func:`policy_sha256`, and the device type where the policy is not on the CPU (its float kernels
    differ). Stored records are taken again only where it is unchanged.

    Examples:
        >>> from spf_rl.modules import OpenLoopPolicy
        >>> records_key(EvalConfig(), OpenLoopPolicy())["policy_sha256"] is None
        True
    """
    key = {**episodes_key(config), "policy_sha256": policy_sha256(policy)}
    parameter = next(policy.parameters(), None) if hasattr(policy, "parameters") else None
    if parameter is not None and parameter.device.type != "cpu":  # another device's float kernels: another key
        key["device"] = parameter.device.type
    return key


def changed_fields(stored: dict | None, key: dict) -> list[str]:
    """The fields in which a stored key differs from ``key`` (all of them where nothing is stored).

    Examples:
        >>> changed_fields({"env_version": 2, "arrival": "a"}, {"env_version": 3, "arrival": "a"})
        ['env_version']
        >>> changed_fields(None, {"env_version": 3})
        ['env_version']
    """
    stored = stored if isinstance(stored, dict) else {}
    return sorted(name for name in set(key) | set(stored) if key.get(name) != stored.get(name))


def to_columns(records: Sequence[dict], fields: Sequence[str] | None = None) -> dict[str, list]:
    """Per-episode records as one list per field (``fields``: those kept; default: the first record's).

    Examples:
        >>> to_columns([{"success": True, "spl": 0.5}, {"success": False, "spl": 0.0}])
        {'success': [True, False], 'spl': [0.5, 0.0]}
    """
    fields = list(records[0]) if fields is None and records else list(fields or ())
    return {name: [record[name] for record in records] for name in fields}


def from_columns(columns: dict[str, list]) -> list[dict]:
    """The records of :func:`to_columns`' columns.

    Examples:
        >>> from_columns({"success": [True, False], "spl": [0.5, 0.0]})
        [{'success': True, 'spl': 0.5}, {'success': False, 'spl': 0.0}]
    """
    return [dict(zip(columns, values)) for values in zip(*columns.values())]


def write_records(path: str | os.PathLike, key: dict, records: Sequence[dict], fields: Sequence[str] | None = None,
                  **extra: Any) -> None:
    """Write ``records`` (``fields`` of them; default: all) under ``key`` to ``path``, atomically, with
    ``extra`` entries beside them (information such as a line, a round or a checkpoint's path)."""
    clash = {"key", "columns"} & set(extra)
    if clash:
        raise ValueError(f"write_records: extra entries may not be named {sorted(clash)} (the key and the records)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, {**extra, "key": key, "columns": to_columns(records, fields)}, indent=1, default=str)


def read_records(path: str | os.PathLike, key: dict) -> list[dict] | None:
    """The records at ``path`` if they were stored under ``key``; ``None`` (the reason logged) where the file
    is missing, unreadable, holds no records or was made with another key."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        payload = json.loads(path.read_text())
        columns = payload["columns"]
        stored = payload.get("key")
    except (ValueError, KeyError, TypeError) as err:
        logger.warning("%s is unreadable (%s): evaluating again", path, err)
        return None
    changed = changed_fields(stored, key)
    if changed:
        logger.info("%s was made with other %s: evaluating again", path, ", ".join(changed))
        return None
    records = from_columns(columns) if isinstance(columns, dict) else []
    return records or None


def cached_records(path: str | os.PathLike, key: dict, evaluate: Callable[[], list[dict]],
                   fields: Sequence[str] | None = None, **extra: Any) -> list[dict]:
    """The records stored at ``path`` under ``key``, else ``evaluate()``'s, stored there first.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "records.json"
        >>> calls = []
        >>> def evaluate():
        ...     calls.append(1)
        ...     return [{"success": True}]
        >>> key = {"episodes": {"split": "test"}, "env_version": 3, "arrival": "a", "policy_sha256": "f00"}
        >>> cached_records(path, key, evaluate) == cached_records(path, key, evaluate), len(calls)
        (True, 1)
        >>> _ = cached_records(path, {**key, "policy_sha256": "ba5"}, evaluate); len(calls)
        2
    """
    records = read_records(path, key)
    if records is None:
        records = evaluate()
        write_records(path, key, records, fields, **extra)
    return records
