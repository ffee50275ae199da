"""Episode datasets on disk: perturbed follow episodes labelled by the expert.

A dataset is two :class:`~envs.tensor_store.TensorStore` directories (the project's
one on-disk store), read back through TorchRL's :class:`~torchrl.data.TensorStorage`::

    <root>/meta.json        kind, format and env versions, configuration, SHA-256 of every tensor
    <root>/data/            the follow episodes, memory-mapped
    <root>-demos/           their demonstrations: a DemoStore, frames stored once

The episodes are episodes ``0 .. E - 1`` of a batched env seeded with the dataset
seed (numbered episodes, :mod:`envs.episode_numbering`), their demonstrations those
of an episode store (a ``numbered`` :class:`~envs.demo_store.DemoStoreConfig`):
per episode, ``demo_id`` (its row in the store), the follow episode step by step
(``steps`` with batch ``[T]``: ``pixels``, the executed ``action``, the expert's
``expert_action`` label, ``mask`` for valid steps and ``is_init``; with a route style also
``route_step``, the route expert's place of the agent along the route), ``episode_seed``,
``length``, ``success`` and ``spl``. Sampling (:meth:`EpisodeDataset.replay_buffer`,
:meth:`EpisodeDataset.__getitem__`) adds ``demo_frames`` and ``demo_actions``, looked
up by ``demo_id``.

The behaviour policy (:class:`~envs.scripted.EpsilonExpertPolicy`) is stepped by a
TorchRL collector (:func:`~envs.episodes.play_episode_steps`), the env emitting
``demo_id`` instead of the frames. Episodes are generated in chunks, in parallel
worker processes; every episode is a pure function of ``(seed, its number)``, so an
interrupted run resumes where it stopped (from ``<root>.partial``) and gives the same
bytes as an uninterrupted one. A tensor whose bytes do not match its checksum, a
missing file, a shape that disagrees with the configuration, or data made by another
env version or format raises :class:`DatasetError`.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import SamplerWithoutReplacement, TensorDictReplayBuffer, TensorStorage
from torchrl.data.replay_buffers import ImmutableDatasetWriter

from envs.checks import check_positive_ints
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec, flat_dict, from_flat
from envs.follow import default_max_steps
from envs.homing import FOLLOW
from envs.specs import NUM_RGB_CHANNELS
from envs.tensor_store import StoreError, TensorStore, worker_pool
from envs.version import ENV_VERSION

logger = logging.getLogger(__name__)

#: Version of the on-disk layout; bumped when it changes.
DATASET_FORMAT_VERSION = 5
#: Suffix of the directory beside a dataset that holds its demonstrations.
DEMOS_SUFFIX = "-demos"
#: Keys of a dataset episode's steps, as the env emits them.
STEP_KEYS = ("pixels", "action", "expert_action")
#: The step key that episodes of a route style add: the demonstration step the agent has come
#: to (:meth:`~envs.route_expert.RouteExpert.route_step`), the label of the pointer loss.
ROUTE_STEP_KEY = "route_step"
#: The key a training episode carries once its demonstration is attached (:func:`attach_demonstrations`):
#: whether it was shown another route's frames (its ``memory_id`` is not its ``demo_id``), bool ``[*batch]``.
MEMORY_MISMATCHED_KEY = "memory_mismatched"


def episode_keys(episodes: EpisodeSpec) -> tuple[str, ...]:
    """The keys stored once per episode of ``episodes``: its stored route (``demo_id``) and seed, and
    with a mismatched memory the stored route whose frames it was shown (``memory_id``).

    Examples:
        >>> episode_keys(EpisodeSpec()), episode_keys(EpisodeSpec(memory_mismatch=0.25))[-1]
        (('demo_id', 'episode_seed'), 'memory_id')
    """
    return ("demo_id", "episode_seed") + (() if episodes.memory_mismatch is None else ("memory_id",))


def step_keys(route_style: str | None) -> tuple[str, ...]:
    """The keys stored at every step of episodes of ``route_style`` (``None``: the planner's routes).

    Examples:
        >>> step_keys(None), step_keys("driven")[-1]
        (('pixels', 'action', 'expert_action'), 'route_step')
    """
    return STEP_KEYS if route_style is None else (*STEP_KEYS, ROUTE_STEP_KEY)


class DatasetError(StoreError):
    """A dataset directory is missing, half-written, corrupt or of another configuration."""


def default_training_episodes() -> EpisodeSpec:
    """The episodes BC trains on by default: the paper's 30-step planner routes of the
    ``train`` split, 50 steps at most, under ``paper`` noise, seed 0."""
    return EpisodeSpec(split="train", max_steps=50, seed=0)


@dataclass
class DatasetConfig:
    """What a dataset holds and how it is generated.

    Args:
        episodes: the follow episodes (:class:`~envs.episode_spec.EpisodeSpec`): the
            dataset holds episodes ``0 .. num_episodes - 1`` of an env seeded with
            ``episodes.seed``. In YAML its keys may be written flat (``data.split``).
        num_episodes: number of follow episodes.
        random_action_prob: probability that the behaviour policy takes a uniformly
            random action instead of the expert's, so states off the route are seen
            (labels are always the expert's action).
        chunk_size: episodes per chunk, the unit of resuming and of parallel workers.
        num_agents: agents a batched env steps together (each plays several of a chunk's
            episodes in turn, so few agents idle while a chunk's last episodes end).
    """

    episodes: EpisodeSpec = field(default_factory=default_training_episodes)
    num_episodes: int = 2000
    random_action_prob: float = 0.2
    chunk_size: int = 64
    num_agents: int = 16

    def __post_init__(self) -> None:
        check_positive_ints(self, ("num_episodes", "chunk_size", "num_agents"))
        if not 0.0 <= self.random_action_prob <= 1.0:
            raise ValueError(f"random_action_prob must be in [0, 1], got {self.random_action_prob!r}.")

    @property
    def num_chunks(self) -> int:
        return -(-self.num_episodes // self.chunk_size)

    def demo_store_config(self) -> DemoStoreConfig:
        """The demonstrations of the dataset's episodes (an episode store of its seed)."""
        return DemoStoreConfig.of(self.episodes, self.num_episodes)

    def default_dir(self) -> Path:
        """The dataset's directory unless a recipe names one: ``data/<split>-<episodes>ep-<noise>-...``,
        with the data format and, for homing, the task in the name; the step limit is in it where it
        is not the rule's for ``demo_length`` (``-T<max_steps>``), so datasets that differ only in it
        never share a directory.

        Examples:
            >>> str(DatasetConfig().default_dir()).startswith("data/train-2000ep-paper-rand0.2-n30-64px-s0-")
            True
            >>> DatasetConfig(EpisodeSpec(max_steps=60)).default_dir().name.startswith("train-2000ep-paper-rand0.2-n30-T60-64px")
            True
        """
        d, e = self, self.episodes
        task = "" if e.task == FOLLOW else f"-{e.task}"
        # route styles are labelled by the route expert (envs.route_expert), which the name says
        routes = "" if e.route_style is None else f"{e.routes_tag}-routeexpert"
        houses = e.house_seeds_tag + e.conditions_tag
        limit = "" if e.max_steps in (None, default_max_steps(e.demo_length)) else f"-T{e.max_steps}"
        name = f"{e.split}{houses}-{d.num_episodes}ep-{e.noise}-rand{d.random_action_prob}-n{e.demo_length}{limit}{routes}-{e.image_size}px-s{e.seed}"
        return Path("data") / f"{name}-{format_tag()}{task}"


def _empty_episodes(config: DatasetConfig) -> TensorDict:
    e, t, s = config.num_episodes, config.episodes.step_limit, config.episodes.image_size
    steps = TensorDict(
        {
            "pixels": torch.zeros(e, t, s, s, NUM_RGB_CHANNELS, dtype=torch.uint8),
            "action": torch.zeros(e, t, dtype=torch.int64),
            "expert_action": torch.zeros(e, t, dtype=torch.int64),
            "mask": torch.zeros(e, t, dtype=torch.bool),
            "is_init": torch.zeros(e, t, 1, dtype=torch.bool),
        },
        batch_size=[e, t],
    )
    if config.episodes.route_style is not None:
        steps.set(ROUTE_STEP_KEY, torch.zeros(e, t, 1, dtype=torch.int64))
    return TensorDict(
        {
            "steps": steps,
            **{key: torch.zeros(e, dtype=torch.int64) for key in episode_keys(config.episodes)},
            "length": torch.zeros(e, dtype=torch.int64),
            "success": torch.zeros(e, dtype=torch.bool),
            "spl": torch.zeros(e, dtype=torch.float32),
        },
        batch_size=[e],
    )


def empty_training_episodes(config: DatasetConfig) -> TensorDict:
    """Zeroed episodes in the layout training reads (:func:`~spf_rl.train.bc.bc_loss`): a
    dataset's, each with its demonstration (``demo_frames``, ``demo_actions``) instead of a
    ``demo_id``; DAgger's rounds are stored in it.

    Examples:
        >>> empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=5, max_steps=50, image_size=32), num_episodes=2))["demo_frames"].shape
        torch.Size([2, 5, 32, 32, 3])
    """
    e, n, s = config.num_episodes, config.episodes.demo_length, config.episodes.image_size
    demonstrations = {
        "demo_frames": torch.zeros(e, n, s, s, NUM_RGB_CHANNELS, dtype=torch.uint8),
        "demo_actions": torch.zeros(e, n, dtype=torch.int64),
    }
    if config.episodes.route_style is not None:  # demonstrations of several lengths
        demonstrations["demo_steps"] = torch.zeros(e, 1, dtype=torch.int64)
    demonstrations[MEMORY_MISMATCHED_KEY] = torch.zeros(e, dtype=torch.bool)
    return _empty_episodes(config).exclude("demo_id", "memory_id").update(demonstrations)


def format_tag() -> str:
    """The tag that ends dataset directory names: the layout and env versions, so that
    data of an older version is never reopened by a run of this one.

    Examples:
        >>> format_tag() == f"format{DATASET_FORMAT_VERSION}-env{ENV_VERSION}"
        True
    """
    return f"format{DATASET_FORMAT_VERSION}-env{ENV_VERSION}"


def attach_demonstrations(episodes: TensorDictBase, demos: DemoStore) -> TensorDictBase:
    """``episodes`` (in place) with ``demo_frames`` and ``demo_actions`` looked up by their ``demo_id`` in ``demos``,
    and ``demo_steps`` where the store holds demonstrations of several lengths (a route style); the frames
    are those of ``memory_id`` where the episodes have one (a mismatched memory, :mod:`envs.conditions`),
    which then gives way to :data:`MEMORY_MISMATCHED_KEY` (set for every episode, so that episodes of
    sources with and without mismatched memories have one layout and batch together)."""
    ids = episodes.get("demo_id").reshape(-1)
    shown = episodes.get("memory_id").reshape(-1) if "memory_id" in episodes.keys() else ids
    episodes.set(MEMORY_MISMATCHED_KEY, (shown != ids).reshape(episodes.batch_size))
    if "memory_id" in episodes.keys():
        del episodes["memory_id"]
    episodes.set("demo_frames", demos.frames[shown].reshape(*episodes.batch_size, *demos.frames.shape[1:]))
    episodes.set("demo_actions", demos.actions[ids].reshape(*episodes.batch_size, -1))
    if demos.config.episodes.route_style is not None:
        episodes.set("demo_steps", demos.steps[ids].reshape(*episodes.batch_size, 1))
    return episodes


def demos_root(root: str | os.PathLike) -> Path:
    """The directory of a dataset's demonstrations: ``<root>-demos``."""
    root = Path(root)
    return root.with_name(root.name + DEMOS_SUFFIX)


def generate_chunk(config: DatasetConfig, chunk: int, demos: str | os.PathLike) -> TensorDict:
    """Episodes ``[chunk * chunk_size, ...)`` of a dataset (a pure function of ``config`` and their numbers).

    One batched env of ``num_agents`` agents (fewer for a smaller chunk), seeded with
    ``config.seed`` and drawing its demonstrations from the store at ``demos``, plays them
    with the behaviour policy
    (the expert, or a random action with probability ``random_action_prob``) through a
    TorchRL collector; every step is labelled with the expert's action.
    """
    from envs.episodes import play_episode_steps
    from envs.scripted import EpsilonExpertPolicy

    first = chunk * config.chunk_size
    count = min(config.chunk_size, config.num_episodes - first)
    env = _chunk_env(config, min(config.num_agents, count), first, str(demos))
    with torch.no_grad():
        return play_episode_steps(
            env, EpsilonExpertPolicy(config.random_action_prob), first, count, step_keys(config.episodes.route_style), config.episodes.step_limit,
            episode_keys=episode_keys(config.episodes),
        )


_CHUNK_ENVS: dict[tuple, object] = {}


def _chunk_env(config: DatasetConfig, count: int, first: int, demos: str):
    """The env playing episodes ``first .. first + count - 1``, seeded with the dataset seed.

    A worker process reuses one env per configuration across chunks (its GL contexts
    and compiled houses are the expensive part); each chunk moves its episode
    numbering to ``first`` and re-seeds it.
    """
    from envs.factory import make_env

    key = (config.episodes, count, demos)
    if key not in _CHUNK_ENVS:
        _CHUNK_ENVS[key] = make_env(
            config.episodes, count, demo_store=DemoStore(demos), with_expert=True, init_tracker=False
        )
    env = _CHUNK_ENVS[key]
    env.base_env.numbering.offset = first
    env.set_seed(config.episodes.seed, static_seed=True)
    return env


class EpisodeDataset(TensorStore):
    """An episode dataset directory (a :class:`~envs.tensor_store.TensorStore`): build, resume, verify, sample.

    Args:
        root: the dataset directory.
        verify: recompute the SHA-256 of every tensor and compare with ``meta.json``.

    Examples:
        >>> import tempfile
        >>> root = tempfile.mkdtemp() + "/tiny"
        >>> config = DatasetConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32), num_episodes=2, chunk_size=2)
        >>> dataset = EpisodeDataset.build(root, config, num_workers=1, progress=False)
        >>> dataset.episodes["steps", "pixels"].shape
        torch.Size([2, 6, 32, 32, 3])
        >>> dataset[[1]]["demo_frames"].shape  # looked up by demo_id
        torch.Size([1, 5, 32, 32, 3])
    """

    KIND = "dataset"
    FORMAT_VERSION = DATASET_FORMAT_VERSION
    ERROR = DatasetError
    FORMAT_HISTORY = (
        "(version 1 stored CHW frames; version 2 was built in place; version 3 stored every "
        "episode's demonstration frames and was generated by a hand-written loop; version 4 had no "
        "route_step in episodes of route styles)"
    )

    @staticmethod
    def config_from_dict(config: dict) -> DatasetConfig:
        return from_flat(DatasetConfig, config)

    @staticmethod
    def config_to_dict(config: DatasetConfig) -> dict:
        return flat_dict(config)

    @staticmethod
    def empty(config: DatasetConfig) -> TensorDict:
        return _empty_episodes(config)

    @property
    def episodes(self) -> TensorDict:
        """The episodes, ``[E]`` (memory-mapped, read-only), without their demonstrations
        (``demo_id`` refers to them; indexing the dataset adds them)."""
        return self.data

    @functools.cached_property
    def demos(self) -> DemoStore:
        """The store of the episodes' demonstrations (``<root>-demos``), checked against the dataset."""
        store = DemoStore(demos_root(self.root), verify=False)
        expected = self.config.demo_store_config()
        if store.config != expected:
            raise DatasetError(
                f"dataset {self.root}: its demonstration store {store.root} holds {store.config}, "
                f"expected {expected}. Delete both directories to rebuild them."
            )
        return store

    def with_demonstrations(self, episodes: TensorDictBase) -> TensorDictBase:
        """``episodes`` (rows of this dataset) with ``demo_frames`` and ``demo_actions`` looked up by ``demo_id``."""
        return attach_demonstrations(episodes, self.demos)

    def __getitem__(self, rows) -> TensorDict:
        """Episodes ``rows`` (in memory) with their demonstrations."""
        return self.with_demonstrations(self.episodes[rows].to_tensordict())

    @staticmethod
    def exists(root: str | os.PathLike) -> bool:
        """Whether ``root`` holds a complete dataset (its ``meta.json``)."""
        return (Path(root) / "meta.json").exists()

    @classmethod
    def build(
        cls,
        root: str | os.PathLike,
        config: DatasetConfig,
        num_workers: int = 2,
        progress: bool = True,
    ) -> EpisodeDataset:
        """Create the dataset at ``root``, or resume a partial one, then open it.

        The demonstrations are rendered first, into ``<root>-demos`` (a
        :class:`~envs.demo_store.DemoStore`); then chunks of ``config.chunk_size``
        episodes are generated into ``<root>.partial``, renamed to ``root`` when complete.
        Both builds run in the same ``num_workers`` ``spawn`` processes (started once, at the
        first chunk to build; 1: in this process), and both resume.

        Raises:
            DatasetError: if ``root`` holds a dataset of another configuration.
            DemoStoreError: if ``<root>-demos`` holds other demonstrations.
        """
        # one set of workers for both stores, so that they start once (1: in this process)
        with worker_pool(num_workers) if num_workers > 1 else contextlib.nullcontext() as pool:
            demos = DemoStore.build(demos_root(root), config.demo_store_config(), progress=progress, pool=pool)
            generate = functools.partial(generate_chunk, demos=str(demos.root))
            dataset = cls.create(root, config, generate, config.chunk_size, progress=progress, pool=pool)
        dataset.demos  # refuses a demonstration store of another configuration now
        return dataset

    def replay_buffer(
        self, batch_size: int, seed: int = 0, drop_last: bool = False, sampler: SamplerWithoutReplacement | None = None
    ) -> TensorDictReplayBuffer:
        """A read-only TorchRL replay buffer over whole episodes (one epoch without replacement at a time);
        its batches carry ``demo_frames`` and ``demo_actions`` (:meth:`with_demonstrations`).

        ``sampler`` replaces the default ``SamplerWithoutReplacement(drop_last=drop_last)``
        (e.g. a data-parallel rank's :class:`~spf_rl.train.distributed.ShardedSampler`)."""
        buffer = TensorDictReplayBuffer(
            storage=TensorStorage(self.episodes),
            writer=ImmutableDatasetWriter(),
            sampler=SamplerWithoutReplacement(drop_last=drop_last) if sampler is None else sampler,
            batch_size=batch_size,
            transform=self.with_demonstrations,
        )
        buffer.set_rng(torch.Generator().manual_seed(seed))
        return buffer

    def statistics(self) -> dict:
        """Episode count, behaviour-policy success rate and mean length."""
        return {
            "episodes": len(self),
            "behaviour_success": float(self.episodes["success"].float().mean()),
            "mean_length": float(self.episodes["length"].float().mean()),
        }


__all__ = ["MEMORY_MISMATCHED_KEY", "DatasetConfig", "DatasetError", "EpisodeDataset", "attach_demonstrations", "demos_root", "empty_training_episodes", "episode_keys", "format_tag", "generate_chunk", "step_keys"]
