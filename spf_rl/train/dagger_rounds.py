"""DAgger's rounds on disk: each round's episodes, and the window of rounds retraining sees.

``<run>/rounds/round-XX`` holds one round's episodes as a memory-mapped TensorDict,
written to a temporary directory and renamed, so a round on disk is complete.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from tensordict import TensorDict, TensorDictBase


def store_round(directory: Path, episodes: TensorDict) -> None:
    """Write one round's episodes as a memory-mapped TensorDict, atomically (temp dir + rename)."""
    tmp = directory.with_name(f".{directory.name}.tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    episodes.memmap(tmp)
    os.replace(tmp, directory)


def training_sources(
    bc_episodes: TensorDictBase | None, output: Path, round_index: int, window: int | None
) -> list[TensorDictBase]:
    """The episodes retraining sees after round ``round_index``: the BC data and the window of rounds."""
    first = 1 if window is None else max(1, round_index - window + 1)
    paths = [output / "rounds" / f"round-{r:02d}" for r in range(first, round_index + 1)]
    if missing := [path for path in paths if not path.is_dir()]:  # e.g. last.pt copied without the rounds
        raise FileNotFoundError(f"DAgger round data {missing[0]} is missing, so {output} cannot resume; delete it to start over.")
    return ([bc_episodes] if bc_episodes is not None else []) + [TensorDict.load_memmap(path) for path in paths]
