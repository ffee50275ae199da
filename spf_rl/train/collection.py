"""Collect follow episodes with a policy through TorchRL collectors, locally or on Ray.

DAgger and PPO fine-tuning both roll the learner out in
:class:`~envs.nav_env.PathFollowEnv`; this module builds the env and the collector
for them from two small configs:

* :class:`CollectionEnvConfig`: which episodes (split, noise, sizes, expert labels);
* :class:`CollectorConfig`: how they are stepped: ``backend="local"`` (one
  in-process :class:`~torchrl.collectors.Collector`, or a
  :class:`~torchrl.collectors.MultiSyncCollector` over ``num_collectors`` worker
  processes) or ``backend="ray"`` (TorchRL's
  :class:`~torchrl.collectors.distributed.RayCollector`, one Ray actor per
  collector; ``pip install .[distributed]``), each collector over one batched env of
  ``num_agents`` agents (``env_mode="batched"``) or a
  :class:`~torchrl.envs.ParallelEnv` of ``num_agents`` single-agent workers
  (``env_mode="parallel"``).

With ``demo_store`` (an episode store), :func:`make_collector`'s envs play that
store's numbered episodes and emit ``demo_id`` instead of the frames (the policy
looks them up); :func:`~envs.episodes.gather_episode_steps` keeps each episode's
steps, in the layout of :mod:`spf_rl.data`, whatever the number of collectors: the
path of DAgger's rounds.
"""
from __future__ import annotations

import functools
import importlib.util
import logging
import os
from dataclasses import dataclass, field
from typing import Literal

import torch
from torchrl.collectors import Collector
from torchrl.envs import Compose, InitTracker, ParallelEnv, TensorDictPrimer, TransformedEnv
from torchrl.modules.utils import get_primers_from_module

from envs.demo_store import DemoStore
from envs.episode_spec import EpisodeSpec
from envs.factory import make_env
from envs.worker_processes import start_method
from spf_rl.device import DEFAULT_DEVICE, resolve_device

logger = logging.getLogger(__name__)

BACKENDS = ("local", "ray")
ENV_MODES = ("batched", "parallel")
_HAS_RAY = importlib.util.find_spec("ray") is not None
#: ``total_frames`` given to a Ray collector asked never to stop (``-1``).
RAY_ENDLESS_FRAMES = 2**62


def default_collection_episodes() -> EpisodeSpec:
    """The episodes collectors play by default: 30-step planner routes of the ``train`` split,
    50 steps at most, under ``paper`` noise."""
    return EpisodeSpec(split="train", max_steps=50)


@dataclass
class CollectionEnvConfig:
    """The episodes a collector plays.

    Args:
        episodes: the episodes (:class:`~envs.episode_spec.EpisodeSpec`); the collector seeds
            its envs, so ``episodes.seed`` is used only by envs that draw numbered episodes
            from a store. In YAML its keys may be written flat (``env.split``).
        with_expert: emit the expert's action (``"expert_action"``) at every step.
    """

    episodes: EpisodeSpec = field(default_factory=default_collection_episodes)
    with_expert: bool = True


@dataclass
class CollectorConfig:
    """How episodes are collected.

    Args:
        backend: ``"local"`` (this machine's processes) or ``"ray"`` (TorchRL's Ray
            collector; needs ``pip install .[distributed]``).
        num_collectors: collectors stepping in parallel (``1`` with the local
            backend: in this process; more: one worker process or Ray actor each).
        env_mode: ``"batched"`` (one env stepping ``num_agents`` agents in one
            process, the fast path) or ``"parallel"`` (a ``ParallelEnv`` of
            ``num_agents`` single-agent workers).
        num_agents: agents per collector. 32 by default: a DAgger round collects 1.41x as
            many frames/s as with 8, and 64 adds little more (1.46x; docs/performance.md).
        ray_address: address of an existing Ray cluster (``None``: attach to a
            running one or start a local one).
        ray_num_cpus: CPUs reserved per Ray collector actor.
    """

    backend: str = "local"
    num_collectors: int = 1
    env_mode: str = "batched"
    num_agents: int = 32
    ray_address: str | None = None
    ray_num_cpus: float = 1.0

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"collector.backend must be one of {BACKENDS}, got {self.backend!r}.")
        if self.env_mode not in ENV_MODES:
            raise ValueError(f"collector.env_mode must be one of {ENV_MODES}, got {self.env_mode!r}.")
        for name in ("num_collectors", "num_agents"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"collector.{name} must be a positive int, got {value!r}.")
        if self.ray_num_cpus <= 0:
            raise ValueError(f"collector.ray_num_cpus must be > 0, got {self.ray_num_cpus!r}.")

    @property
    def total_agents(self) -> int:
        """Agents stepped together over all collectors."""
        return self.num_collectors * self.num_agents


def collection_device(setting: str | torch.device, config: CollectorConfig) -> torch.device:
    """The learner's device for a run that collects with ``config``: :func:`~spf_rl.device.resolve_device`,
    except that ``"auto"`` means the CPU with the Ray backend (its actors act on the CPU).

    Examples:
        >>> collection_device("auto", CollectorConfig(backend="ray"))
        device(type='cpu')
        >>> collection_device("cpu", CollectorConfig())
        device(type='cpu')
    """
    device = resolve_device(setting)
    if config.backend == "ray" and setting == DEFAULT_DEVICE and device.type != "cpu":
        logger.info("collector.backend='ray' acts on CPU actors: device=%s resolves to the CPU", DEFAULT_DEVICE)
        return torch.device("cpu")
    return device


@dataclass(frozen=True)
class _StoreEpisodes:
    """Envs whose demonstrations come from a :class:`~envs.demo_store.DemoStore`: its
    directory, and for an episode store (numbered episodes) the seed every env shares and
    this env's numbering (``offset``, ``stride``); ``seed=None``: seeded by the collector."""

    demo_store: str
    seed: int | None = None
    offset: int = 0
    stride: int = 1

    def agent(self, index: int, num_agents: int) -> _StoreEpisodes:
        """The numbering of single-agent env ``index`` of ``num_agents`` (a ``ParallelEnv``'s workers)."""
        return _StoreEpisodes(self.demo_store, self.seed, self.offset + self.stride * index, self.stride * num_agents)


def _env(
    env_config: CollectionEnvConfig, num_agents: int | None, store: _StoreEpisodes | None, init_tracker: bool,
    primer: TensorDictPrimer | None = None,
) -> TransformedEnv:
    """The env stack of :func:`envs.factory.make_env` for ``env_config``'s episodes (seeded here
    only for numbered episodes of a store)."""
    spec = env_config.episodes
    options = {} if store is None else dict(demo_store=store.demo_store, episode_offset=store.offset, episode_stride=store.stride)
    if store is not None and store.seed is not None:
        spec = spec.replace(seed=store.seed)
    return make_env(
        spec, num_agents, primer=primer, init_tracker=init_tracker, with_expert=env_config.with_expert,
        seeded=store is not None and store.seed is not None, **options,
    )


def _single_agent_env(env_config: CollectionEnvConfig, store: _StoreEpisodes | None = None) -> TransformedEnv:
    return _env(env_config, None, store, init_tracker=False)


def make_collection_env(
    env_config: CollectionEnvConfig,
    num_agents: int,
    env_mode: Literal["batched", "parallel"] = "batched",
    primer: TensorDictPrimer | None = None,
    store: _StoreEpisodes | None = None,
) -> TransformedEnv:
    """The env one collector steps: ``num_agents`` agents with noise, ``is_init`` and
    (optionally) a recurrent policy's primer. Importable, so a
    :func:`functools.partial` of it is a picklable env factory.

    Args:
        env_config: the episodes.
        num_agents: agents in the env.
        env_mode: ``"batched"`` or ``"parallel"`` (see :class:`CollectorConfig`).
        primer: the policy's :class:`~torchrl.envs.TensorDictPrimer` (its recurrent state).
        store: draw the demonstrations from a store (see :func:`make_collector`'s
            ``demo_store``); for numbered episodes the envs are seeded here.

    Examples:
        >>> env = make_collection_env(CollectionEnvConfig(EpisodeSpec(num_houses=1, demo_length=5, image_size=32)), num_agents=2)
        >>> env.batch_size, "expert_action" in env.observation_spec.keys()
        (torch.Size([2]), True)
    """
    if env_mode not in ENV_MODES:
        raise ValueError(f"env_mode must be one of {ENV_MODES}, got {env_mode!r}.")
    if env_mode == "batched":
        return _env(env_config, num_agents, store, init_tracker=True, primer=primer)
    factories = [
        functools.partial(_single_agent_env, env_config, None if store is None else store.agent(i, num_agents))
        for i in range(num_agents)
    ]
    transforms = [InitTracker()] + ([primer.clone()] if primer is not None else [])
    return TransformedEnv(ParallelEnv(num_agents, factories, mp_start_method=start_method()), Compose(*transforms))


def make_collector(
    policy,
    env_config: CollectionEnvConfig,
    config: CollectorConfig,
    *,
    frames_per_batch: int,
    total_frames: int = -1,
    seed: int = 0,
    reset_at_each_iter: bool = False,
    device: torch.device | str | None = None,
    storing_device: torch.device | str | None = None,
    demo_store: str | os.PathLike | None = None,
):
    """A TorchRL collector running ``policy`` in the path-following env.

    The envs (and their rendering) run on the CPU; the policy runs on ``device``
    (TorchRL's ``policy_device``; ``env_device`` is the CPU): the collector moves each
    step's data to the policy's device and its output back. Move the policy to
    ``device`` first (``policy.to(device)``), so that the collector acts with the
    learner's own weights instead of a copy.

    Args:
        policy: a TensorDict module writing ``"action"``; its recurrent-state primer
            (its own ``make_tensordict_primer``, else those of its submodules, as for a
            :class:`~torchrl.modules.ProbabilisticActor` around an SPF policy) is added
            to every env.
        env_config: the episodes.
        config: backend, number of collectors, env mode and agents.

    Keyword Args:
        frames_per_batch: frames per yielded batch (over all collectors).
        total_frames: frames before the collector stops (``-1``: never).
        seed: seed of the envs (each collector's envs get their own seed from it); the
            batches are a function of it (the envs are reset once seeded).
        reset_at_each_iter: reset every env at the start of each batch (batches
            then hold whole episodes from their start).
        device: where the policy runs (``None``: the CPU, as is).
        storing_device: where the yielded batches are stored (``None``: ``device``
            for the local backend, so that a learner on a GPU gets its batch there;
            pass ``"cpu"`` for batches that go to disk).
        demo_store: a :class:`~envs.demo_store.DemoStore`'s directory: the envs draw their
            demonstrations from it and emit ``demo_id`` instead of the frames, which
            ``policy`` looks up itself (:class:`~spf_rl.evaluation.FramesFromStore`).
            An episode store (a ``numbered`` :class:`~envs.demo_store.DemoStoreConfig`,
            :meth:`~envs.demo_store.DemoStoreConfig.of`, of env seed ``seed``) is played as numbered episodes: every env seeded with
            ``seed``, collector ``w`` of ``W`` playing episode numbers ``w, w + W, ...``
            (:func:`~envs.episodes.gather_episode_steps` keeps them). Any other store: a
            random demonstration of it per episode, the envs seeded by the collector.
            ``None``: each env renders a random demonstration at every reset.

    Returns:
        a :class:`~torchrl.collectors.Collector`, :class:`~torchrl.collectors.MultiSyncCollector`
        or :class:`~torchrl.collectors.distributed.RayCollector`.

    Raises:
        ImportError: for ``backend="ray"`` without ray installed.
        ValueError: ``backend="ray"`` with a ``device`` other than the CPU (the Ray
            actors act on the CPU; use the local backend for a GPU learner), or
            an episode store with ``reset_at_each_iter`` (resets would skip numbered episodes).

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> forward = TensorDictModule(lambda p: torch.zeros(p.shape[0], dtype=torch.long), ["pixels"], ["action"])
        >>> env_config = CollectionEnvConfig(EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32))
        >>> collector = make_collector(forward, env_config, CollectorConfig(num_agents=2), frames_per_batch=12, total_frames=12)
        >>> [batch.batch_size for batch in collector]
        [torch.Size([2, 6])]
        >>> collector.shutdown()
    """
    if hasattr(policy, "make_tensordict_primer"):
        primer = policy.make_tensordict_primer()
    else:  # e.g. a ProbabilisticActor around a recurrent policy: the primers of its submodules
        primer = get_primers_from_module(policy, warn=False) if isinstance(policy, torch.nn.Module) else None
    numbered = demo_store is not None and DemoStore(demo_store, verify=False).config.episodes_seed is not None
    if numbered and reset_at_each_iter:
        raise ValueError(
            "make_collector: an episode store as demo_store (numbered episodes) cannot be combined with reset_at_each_iter=True."
        )
    env_factories = [
        functools.partial(
            make_collection_env,
            env_config,
            num_agents=config.num_agents,
            env_mode=config.env_mode,
            primer=primer,
            store=None if demo_store is None else (
                _StoreEpisodes(str(demo_store), seed, w, config.num_collectors) if numbered else _StoreEpisodes(str(demo_store))
            ),
        )
        for w in range(config.num_collectors)
    ]
    common = dict(
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        reset_at_each_iter=reset_at_each_iter,
    )
    device = None if device is None else torch.device(device)
    if device is not None and config.backend != "ray":
        storing_device = device if storing_device is None else torch.device(storing_device)
        common.update(policy_device=device, env_device=torch.device("cpu"), storing_device=storing_device)
    if config.backend == "ray":
        if device is not None and device.type != "cpu":
            raise ValueError(
                f"collector.backend='ray' acts on CPU-only Ray actors, but the policy is on {device}: "
                "use device=cpu with the Ray backend, or collector.backend=local for a GPU learner."
            )
        if not _HAS_RAY:
            raise ImportError("collector.backend='ray' needs ray: pip install '.[distributed]' (or pip install ray).")
        ray_init_config = {"address": config.ray_address} if config.ray_address else {}
        if total_frames < 0:  # "never stop": TorchRL's RayCollector would yield nothing for -1
            common["total_frames"] = RAY_ENDLESS_FRAMES
        collector = Collector(
            env_factories,
            policy,
            backend="ray",
            num_collectors=config.num_collectors,
            sync=True,
            backend_options={
                "collector_class": Collector,
                "collector_kwargs": {"auto_register_policy_transforms": False, "reset_at_each_iter": reset_at_each_iter},
                "ray_init_config": ray_init_config,
                "remote_configs": {"num_cpus": config.ray_num_cpus, "num_gpus": 0},
            },
            **common,
        )
    elif config.num_collectors > 1:
        collector = Collector(
            env_factories,
            policy,
            num_collectors=config.num_collectors,
            sync=True,
            auto_register_policy_transforms=False,
            **common,
        )
    else:
        collector = Collector(env_factories[0](), policy, auto_register_policy_transforms=False, **common)
    if numbered:  # the envs were seeded as they were built, and reset once since
        return collector
    collector.set_seed(seed)
    if config.backend != "ray":
        # the collector reset its envs when it was built, before they had a seed: start the
        # first batch from seeded episodes too (Ray's collectors have no reset; there, pass
        # reset_at_each_iter=True for batches that are a function of the seed)
        collector.reset()
    elif not reset_at_each_iter:
        logger.warning("collector.backend='ray' without reset_at_each_iter: the first batch starts from unseeded episodes")
    return collector


__all__ = [
    "CollectionEnvConfig",
    "CollectorConfig",
    "collection_device",
    "make_collection_env",
    "make_collector",
]
