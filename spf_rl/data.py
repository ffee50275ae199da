"""Episode datasets on disk: perturbed follow episodes labelled by the expert.

A dataset is a :class:`~envs.tensor_store.TensorStore` (the project's one on-disk
store, shared with the demo store) holding one memory-mapped TensorDict of ``E``
episodes, read back through TorchRL's :class:`~torchrl.data.TensorStorage`::

    <root>/meta.json     kind, format and env versions, configuration, SHA-256 of every tensor
    <root>/data/         the memory-mapped tensors

Per episode it stores the demonstration once (``demo_frames [n, H, W, 3]``,
``demo_actions [n]``) and the follow episode step by step (``steps`` with batch
``[T]``: ``pixels``, the executed ``action``, the expert's ``expert_action``
label, ``mask`` for valid steps and ``is_init``).

Episodes are generated in chunks, in parallel worker processes; chunk ``c`` is a
pure function of ``(seed, c)``, so an interrupted run resumes where it stopped
(from ``<root>.partial``) and gives the same bytes as an uninterrupted one. A
tensor whose bytes do not match its checksum, a missing file, a shape that
disagrees with the configuration, or data made by another env version raises
:class:`DatasetError`.
"""
from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import SamplerWithoutReplacement, TensorDictReplayBuffer, TensorStorage
from torchrl.data.replay_buffers import ImmutableDatasetWriter

from envs.checks import check_episode_source, check_positive_ints
from envs.homing import FOLLOW, check_task
from envs.specs import NUM_RGB_CHANNELS
from envs.transforms import DEFAULT_NOISE
from envs.tensor_store import StoreError, TensorStore

logger = logging.getLogger(__name__)

#: Version of the on-disk layout; bumped when it changes.
DATASET_FORMAT_VERSION = 3
NUM_DEMO_ACTIONS = 3


class DatasetError(StoreError):
    """A dataset directory is missing, half-written, corrupt or of another configuration."""


@dataclass
class DatasetConfig:
    """What a dataset holds and how it is generated.

    Args:
        num_episodes: number of follow episodes.
        split: house split the episodes are drawn from.
        num_houses: houses of the split (``None``: the split's default).
        noise: actuation-noise preset of the follow episodes.
        random_action_prob: probability that the behaviour policy takes a uniformly
            random action instead of the expert's, so states off the route are seen
            (labels are always the expert's action).
        demo_length: demonstration length n, steps.
        max_steps: follow-episode limit, steps.
        image_size: frame side, pixels.
        chunk_size: episodes generated together (one batched env of this many agents).
        seed: dataset seed; chunk ``c`` uses ``(seed, c)``.
        task: ``"follow"`` or ``"homing"`` (:mod:`envs.homing`).
    """

    num_episodes: int = 2000
    split: str = "train"
    num_houses: int | None = None
    noise: str = DEFAULT_NOISE
    random_action_prob: float = 0.2
    demo_length: int = 30
    max_steps: int = 50
    image_size: int = 64
    chunk_size: int = 16
    seed: int = 0
    task: str = FOLLOW

    def __post_init__(self) -> None:
        check_task(self.task, "data.task")
        check_episode_source(self.split, self.num_houses, self.noise)
        check_positive_ints(self, ("num_episodes", "demo_length", "max_steps", "image_size", "chunk_size"))
        if not 0.0 <= self.random_action_prob <= 1.0:
            raise ValueError(f"random_action_prob must be in [0, 1], got {self.random_action_prob!r}.")

    @property
    def num_chunks(self) -> int:
        return -(-self.num_episodes // self.chunk_size)


def _empty_episodes(config: DatasetConfig) -> TensorDict:
    e, t, n, s = config.num_episodes, config.max_steps, config.demo_length, config.image_size
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
    return TensorDict(
        {
            "steps": steps,
            "demo_frames": torch.zeros(e, n, s, s, NUM_RGB_CHANNELS, dtype=torch.uint8),
            "demo_actions": torch.zeros(e, n, dtype=torch.int64),
            "episode_seed": torch.zeros(e, dtype=torch.int64),
            "length": torch.zeros(e, dtype=torch.int64),
            "success": torch.zeros(e, dtype=torch.bool),
            "spl": torch.zeros(e, dtype=torch.float32),
        },
        batch_size=[e],
    )


def generate_chunk(config: DatasetConfig, chunk: int) -> TensorDict:
    """Generate chunk ``chunk`` of a dataset (a pure function of ``(config, chunk)``).

    One batched env holds ``chunk_size`` agents; each plays exactly one episode
    driven by the behaviour policy (expert, or a random action with probability
    ``random_action_prob``), every step labelled with the expert's action.
    """
    first = chunk * config.chunk_size
    count = min(config.chunk_size, config.num_episodes - first)
    env = _chunk_env(config, count)
    chunk_seed = int(np.random.SeedSequence([config.seed, chunk]).generate_state(1)[0])
    env.set_seed(chunk_seed)
    generator = torch.Generator().manual_seed(chunk_seed)
    out = _empty_episodes(DatasetConfig(**{**asdict(config), "num_episodes": count}))
    td = env.reset()
    out["demo_frames"] = td["demo_frames"]
    out["demo_actions"] = td["demo_actions"]
    out["episode_seed"] = td["episode_seed"].reshape(count)
    active = torch.ones(count, dtype=torch.bool)
    with torch.no_grad():
        for step in range(config.max_steps):
            expert = td["expert_action"]
            random_action = torch.randint(0, NUM_DEMO_ACTIONS, (count,), generator=generator)
            take_random = torch.rand(count, generator=generator) < config.random_action_prob
            td["action"] = torch.where(take_random, random_action, expert)
            out["steps", "pixels"][:, step] = td["pixels"]
            out["steps", "action"][:, step] = td["action"]
            out["steps", "expert_action"][:, step] = expert
            out["steps", "mask"][:, step] = active
            out["steps", "is_init"][:, step] = step == 0
            td = env.step(td)
            done = td["next", "done"].reshape(count) & active
            out["length"][done] = step + 1
            out["success"][done] = td["next", "success"].reshape(count)[done]
            out["spl"][done] = td["next", "spl"].reshape(count)[done]
            active &= ~done
            if not active.any():
                break
            td = td["next"]
    return out


_CHUNK_ENVS: dict[tuple, object] = {}


def _chunk_env(config: DatasetConfig, count: int):
    """The batched env of a worker process, reused across chunks (its GL context and
    compiled houses are the expensive part); each chunk re-seeds it."""
    from torchrl.envs import TransformedEnv

    from envs.nav_env import PathFollowEnv
    from envs.transforms import ActuationNoise

    key = (config.split, config.num_houses, config.noise, config.demo_length, config.max_steps, config.image_size, count, config.task)
    if key not in _CHUNK_ENVS:
        _CHUNK_ENVS[key] = TransformedEnv(
            PathFollowEnv(
                config.split,
                num_houses=config.num_houses,
                num_agents=count,
                demo_length=config.demo_length,
                max_steps=config.max_steps,
                image_size=config.image_size,
                with_expert=True,
                task=config.task,
            ),
            ActuationNoise(config.noise),
        )
    return _CHUNK_ENVS[key]


class EpisodeDataset(TensorStore):
    """An episode dataset directory (a :class:`~envs.tensor_store.TensorStore`): build, resume, verify, sample.

    Args:
        root: the dataset directory.
        verify: recompute the SHA-256 of every tensor and compare with ``meta.json``.

    Examples:
        >>> import tempfile
        >>> root = tempfile.mkdtemp() + "/tiny"
        >>> config = DatasetConfig(num_episodes=2, num_houses=1, demo_length=5, max_steps=6, image_size=32, chunk_size=2)
        >>> dataset = EpisodeDataset.build(root, config, num_workers=1, progress=False)
        >>> dataset.episodes["steps", "pixels"].shape
        torch.Size([2, 6, 32, 32, 3])
    """

    KIND = "dataset"
    FORMAT_VERSION = DATASET_FORMAT_VERSION
    ERROR = DatasetError
    FORMAT_HISTORY = "(version 1 stored CHW frames; version 2 was built in place)"

    @staticmethod
    def config_from_dict(config: dict) -> DatasetConfig:
        return DatasetConfig(**config)

    @staticmethod
    def empty(config: DatasetConfig) -> TensorDict:
        return _empty_episodes(config)

    @property
    def episodes(self) -> TensorDict:
        """The episodes, ``[E]`` (memory-mapped, read-only)."""
        return self.data

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

        Chunks of ``config.chunk_size`` episodes are generated in ``num_workers``
        ``spawn`` processes into ``<root>.partial``, renamed to ``root`` when complete.

        Raises:
            DatasetError: if ``root`` holds a dataset of another configuration.
        """
        return cls.create(root, config, generate_chunk, config.chunk_size, num_workers=num_workers, progress=progress)

    def replay_buffer(self, batch_size: int, seed: int = 0, drop_last: bool = False) -> TensorDictReplayBuffer:
        """A read-only TorchRL replay buffer over whole episodes (one epoch without replacement at a time)."""
        buffer = TensorDictReplayBuffer(
            storage=TensorStorage(self.episodes),
            writer=ImmutableDatasetWriter(),
            sampler=SamplerWithoutReplacement(drop_last=drop_last),
            batch_size=batch_size,
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


__all__ = ["DatasetConfig", "DatasetError", "EpisodeDataset", "generate_chunk"]
