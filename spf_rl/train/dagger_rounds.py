"""DAgger's rounds on disk: each round's episodes, and the window of rounds retraining sees.

A round plays the numbered episodes ``0 .. E - 1`` of its collection seed. Their
demonstrations are rendered once, before the round, into
``<run>/rounds/round-XX-demos`` (a :class:`~envs.demo_store.DemoStore` of those
episodes, :func:`round_demo_config`); the envs emit ``demo_id`` and the learner looks
the frames up. ``<run>/rounds/round-XX`` is a :class:`RoundStore`, a
:class:`~envs.tensor_store.TensorStore` like the demo store and the BC datasets:
``meta.json`` (round, collection seed, beta, episodes, sizes, env version, SHA-256 of
every tensor) beside the memory-mapped episodes in the layout of a BC dataset
(:mod:`spf_rl.data`: steps, ``demo_id``), built in ``round-XX.partial`` and renamed
into place, so a round on disk is complete. Indexing a round adds the demonstrations.
A stored round of another collection (another seed, beta, split or size), a corrupt
one, one of an older layout, one whose demonstration store holds other episodes, or
one made by another env version is refused with a :class:`RoundError`.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from envs.checks import check_positive_ints
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec, flat_dict, from_flat
from envs.homing import FOLLOW
from envs.tensor_store import StoreError, TensorStore
from spf_rl.data import DatasetConfig, EpisodeDataset, attach_demonstrations, demos_root

logger = logging.getLogger(__name__)

#: Rows written per chunk of a round.
ROUND_CHUNK_ROWS = 64


class RoundError(StoreError):
    """A stored DAgger round is missing, corrupt, stale, or of another collection."""


@dataclass(frozen=True)
class RoundConfig:
    """What one stored round holds.

    Args:
        round_index: the round (1-based).
        beta: the expert's probability in the round's behaviour policy.
        num_episodes: episodes stored.
        episodes: the round's episodes (:class:`~envs.episode_spec.EpisodeSpec`):
            episodes ``0 .. num_episodes - 1`` of its collection seed ``episodes.seed``.
            DAgger rounds follow the demonstrated route (``task="follow"``).
    """

    round_index: int
    beta: float
    num_episodes: int
    episodes: EpisodeSpec

    def __post_init__(self) -> None:
        check_positive_ints(self, ("round_index", "num_episodes"))
        if not isinstance(self.episodes, EpisodeSpec):
            raise ValueError(f"episodes must be an EpisodeSpec, got {type(self.episodes).__name__}.")
        if self.episodes.task != FOLLOW:
            raise ValueError(f"DAgger rounds follow the demonstrated route: episodes.task must be {FOLLOW!r}, got {self.episodes.task!r}.")
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {self.beta!r}.")

    @property
    def seed(self) -> int:
        """The round's collection seed (``episodes.seed``)."""
        return self.episodes.seed

    def collection(self) -> dict:
        """The fields that fix the round's episodes (all of them), flat (:func:`~envs.episode_spec.flat_dict`)."""
        return flat_dict(self)


def round_demo_config(config: RoundConfig) -> DemoStoreConfig:
    """The demonstrations of a round's episodes: an episode store of its seed.

    Examples:
        >>> round_demo_config(RoundConfig(round_index=1, beta=0.0, num_episodes=3,
        ...     episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=7))).episodes_seed
        7
    """
    return DemoStoreConfig.of(config.episodes, config.num_episodes)


class RoundStore(TensorStore):
    """One DAgger round's episodes on disk (a :class:`~envs.tensor_store.TensorStore`).

    Args:
        root: the round directory.
        verify: recompute the SHA-256 of every tensor and compare with ``meta.json``.

    Examples:
        >>> import tempfile
        >>> config = RoundConfig(round_index=1, beta=0.0, num_episodes=3, episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=7))
        >>> root = tempfile.mkdtemp() + "/round-01"
        >>> episodes = RoundStore.empty(config)
        >>> RoundStore.write(root, config, episodes).episodes["steps", "pixels"].shape
        torch.Size([3, 5, 8, 8, 3])
        >>> RoundStore(root).config.seed
        7
    """

    KIND = "dagger_round"
    FORMAT_VERSION = 3
    ERROR = RoundError
    FORMAT_HISTORY = (
        "(version 2 had no route_step in rounds of route styles; version 1 stored every episode's "
        "demonstration frames; rounds before version 1 were plain memory-mapped TensorDicts)"
    )

    @staticmethod
    def config_from_dict(config: dict) -> RoundConfig:
        return from_flat(RoundConfig, config)

    @staticmethod
    def config_to_dict(config: RoundConfig) -> dict:
        return config.collection()

    @staticmethod
    def empty(config: RoundConfig) -> TensorDict:
        return EpisodeDataset.empty(DatasetConfig(episodes=config.episodes, num_episodes=config.num_episodes))

    @property
    def episodes(self) -> TensorDict:
        """The round's episodes, ``[E]`` (memory-mapped, read-only)."""
        return self.data

    @functools.cached_property
    def demos(self) -> DemoStore:
        """The store of the round's demonstrations (``round-XX-demos``), checked against the round."""
        root, expected = demos_root(self.root), round_demo_config(self.config)
        if not (root / "meta.json").exists():
            raise RoundError(f"dagger_round store {self.root}: its demonstrations {root} are missing; delete the run to start over.")
        store = DemoStore(root, verify=False)
        if store.config != expected:
            raise RoundError(
                f"dagger_round store {self.root}: its demonstration store {root} holds {store.config}, expected "
                f"{expected}. Delete the run to start over."
            )
        return store

    def __getitem__(self, rows) -> TensorDict:
        """Episodes ``rows`` (in memory) with their demonstrations (``demo_frames``, ``demo_actions``)."""
        return attach_demonstrations(self.episodes[rows].to_tensordict(), self.demos)

    @classmethod
    def write(cls, root: str | Path, config: RoundConfig, episodes: TensorDictBase) -> RoundStore:
        """Store ``episodes`` (``config.num_episodes`` of them) as the round at ``root`` and open it."""
        if episodes.batch_size != (config.num_episodes,):
            raise ValueError(f"episodes must have batch size [{config.num_episodes}], got {list(episodes.batch_size)}.")

        def chunk(_config: RoundConfig, index: int) -> TensorDictBase:
            return episodes[index * ROUND_CHUNK_ROWS : (index + 1) * ROUND_CHUNK_ROWS]

        return cls.create(root, config, chunk, ROUND_CHUNK_ROWS, num_workers=1, progress=False)

    @classmethod
    def read(cls, root: str | Path, collection: dict) -> RoundStore:
        """Open the round at ``root``; raise :class:`RoundError` unless it was collected as
        ``collection`` says (:meth:`RoundConfig.collection`'s fields)."""
        store = cls(root)
        if store.config.collection() != collection:
            raise RoundError(
                f"dagger_round store {root} holds round {store.config.collection()}, but this run's round is "
                f"{collection}: it belongs to another run. Use another output_dir, or delete the run to start over."
            )
        return store


def round_directory(output: Path, round_index: int) -> Path:
    """``<output>/rounds/round-XX``."""
    return output / "rounds" / f"round-{round_index:02d}"


def learner_path(output: Path, round_index: int) -> Path:
    """``<output>/learners/learner-XX.pt``: the learner's weights after round ``XX`` (``00``: the
    starting checkpoint), the policy that collects round ``XX + 1``. With them a run can
    collect its window of rounds again where their stored episodes are missing (another
    machine): collection is a function of the learner, the round's seed and the config."""
    return output / "learners" / f"learner-{round_index:02d}.pt"


def training_sources(
    bc_data: EpisodeDataset | None, output: Path, round_index: int, window: int | None
) -> list[EpisodeDataset | RoundStore]:
    """The episodes retraining sees after round ``round_index``: the BC dataset and the window of
    rounds (each indexable by rows, :func:`source_rows`)."""
    first = 1 if window is None else max(1, round_index - window + 1)
    paths = [round_directory(output, r) for r in range(first, round_index + 1)]
    if missing := [path for path in paths if not (path / "meta.json").exists()]:  # e.g. last.pt copied without the rounds
        raise FileNotFoundError(
            f"DAgger round data {missing[0]} is missing or incomplete, and so is the learner that collected it "
            f"({output / 'learners'}), so {output} cannot resume; delete it to start over."
        )
    return ([bc_data] if bc_data is not None else []) + [RoundStore(path) for path in paths]


def source_rows(source: EpisodeDataset | RoundStore, rows: torch.Tensor) -> TensorDict:
    """Episodes ``rows`` of a training source, in memory, in the layout training reads
    (:func:`~spf_rl.data.empty_training_episodes`: demonstrations instead of ``demo_id``)."""
    return source[rows].exclude("demo_id")


__all__ = [
    "RoundConfig",
    "RoundError",
    "RoundStore",
    "learner_path",
    "round_demo_config",
    "round_directory",
    "source_rows",
    "training_sources",
]
