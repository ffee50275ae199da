"""A run directory's ``config.json``, and the check that a resumed run keeps its settings.

A run (BC or DAgger) resumes from ``<output_dir>/last.pt``. Resuming under settings
that change what the run computes (another start checkpoint, another validation
set, another learning rate) would mix two experiments in one history, so
:func:`write_run_config` compares the new config with the ``config.json`` the run
was started with and refuses such a resume before any work. Settings that only
change how the run is executed (progress bars, worker counts, the device) may
differ.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Collection
from pathlib import Path
from typing import Any

from envs.atomic_io import atomic_write_json
from envs.episode_spec import flat_dict

logger = logging.getLogger(__name__)

#: File of a run directory that marks a run in progress (or finished) that a new call resumes.
RESUME_FILE = "last.pt"
#: File of a run directory that holds its config.
CONFIG_FILE = "config.json"
#: Settings that may change between a run and its resume in every recipe: they change how it runs, not what
#: (``store_root``: where evaluation episodes are cached).
EXECUTION_KEYS = ("output_dir", "device", "num_workers", "logger", "progress", "val.store_root", "test.store_root")
#: Settings a resumed BC run may change (beyond how it executes): more epochs, where and how the data is stored,
#: kept epoch copies.
BC_RESUME_FREE = ("optim.epochs", "data_dir", "data.chunk_size", "keep_epochs")
#: Settings a resumed DAgger run may change (beyond how it executes): more rounds, test scoring, collection layout.
DAGGER_RESUME_FREE = ("rounds", "test_every_round", "collector", "bc_data_dir", "bc_data.chunk_size")


def config_dict(config: Any) -> dict:
    """``config`` (a dataclass) as the JSON-ready dict ``config.json`` holds: tuples become lists, and
    each episode description is written flat in the config that holds it (:func:`~envs.episode_spec.flat_dict`),
    as YAML writes it (``"val": {"split": "val", "num_episodes": 300, ...}``)."""
    return json.loads(json.dumps(flat_dict(config), default=str))


def changed_settings(old: dict, new: dict, free: Collection[str] = (), prefix: str = "") -> list[str]:
    """Dotted names of the settings whose values differ between ``old`` and ``new``.

    Only keys present in both are compared (a key added to the config after ``old`` was
    written has no old value to compare with); keys named in ``free`` (dotted) are skipped.

    Examples:
        >>> old = {"seed": 0, "progress": True, "val": {"seed": 1, "episodes": 300}}
        >>> changed_settings(old, {"seed": 0, "progress": False, "val": {"seed": 3, "episodes": 300}}, free=["progress"])
        ['val.seed']
        >>> changed_settings(old, {**old, "new_field": 1})
        []
    """
    changed = []
    for key in old.keys() & new.keys():
        name = f"{prefix}{key}"
        if name in free:
            continue
        if isinstance(old[key], dict) and isinstance(new[key], dict):
            changed += changed_settings(old[key], new[key], free, prefix=f"{name}.")
        elif old[key] != new[key]:
            changed.append(name)
    return sorted(changed)


def write_run_config(output: Path, config: Any, free: Collection[str] = ()) -> None:
    """Write ``output/config.json``; if the run there is resumed, first check that its settings are kept.

    Args:
        output: the run directory (created if missing).
        config: the run's config dataclass.
        free: dotted settings (beyond :data:`EXECUTION_KEYS`) that a resume may change.

    Raises:
        ValueError: ``output`` holds a run (``last.pt``) whose ``config.json`` differs from
            ``config`` in a setting outside ``free``; the message names each setting with its
            old and new value. Nothing is written.
    """
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    path, new = output / CONFIG_FILE, config_dict(config)
    if (output / RESUME_FILE).exists() and path.exists():
        old = json.loads(path.read_text())
        changed = changed_settings(old, new, (*EXECUTION_KEYS, *free))
        if changed:
            def value(tree: dict, name: str) -> Any:
                for part in name.split("."):
                    tree = tree[part]
                return tree

            details = "; ".join(f"{name}: {value(old, name)!r} -> {value(new, name)!r}" for name in changed)
            raise ValueError(
                f"{output} holds a run started with other settings, and resuming it would mix two experiments "
                f"({details}). Keep the run's settings, or give a new output_dir (or delete {output / RESUME_FILE})."
            )
        logger.debug("resuming %s with its settings unchanged", output)
    atomic_write_json(path, new)
