"""The one builder of env stacks, and importable env factories (picklable under ``spawn``).

:func:`make_env` builds every env stack of the project from an
:class:`~envs.episode_spec.EpisodeSpec`: a :class:`~envs.nav_env.PathFollowEnv` with
the spec's actuation noise, ``is_init`` and (optionally) a recurrent policy's primer.
Datasets, evaluations, collectors, pointer traces and taught routes all call it.

``ParallelEnv`` and TorchRL's collectors start their workers with ``spawn``, so
the function that builds an env must be importable at module level. Use
:func:`functools.partial` to fix its arguments.
"""
from __future__ import annotations

from functools import partial

from torchrl.envs import Compose, InitTracker, ParallelEnv, SerialEnv, TensorDictPrimer, Transform, TransformedEnv

from envs.episode_spec import SPEC_FIELDS, EpisodeSpec
from envs.nav_env import PathFollowEnv
from envs.transforms import ActuationNoise, NoiseModel
from envs.worker_processes import start_method


def make_env(
    episodes: EpisodeSpec,
    num_agents: int | None = None,
    *,
    demo_store=None,
    primer: TensorDictPrimer | Transform | None = None,
    episode_offset: int = 0,
    episode_stride: int = 1,
    init_tracker: bool = True,
    seeded: bool = False,
    static_seed: bool = False,
    **env_options,
) -> TransformedEnv:
    """The env stack that plays ``episodes``: a :class:`~envs.nav_env.PathFollowEnv` of
    ``num_agents`` agents, then :class:`~envs.transforms.ActuationNoise` of the spec's
    noise, :class:`~torchrl.envs.InitTracker` and ``primer``.

    Args:
        episodes: the episodes (:class:`~envs.episode_spec.EpisodeSpec`).
        num_agents: ``None`` (an unbatched env, e.g. a ``ParallelEnv`` worker) or N agents.
        demo_store: draw the demonstrations from this store (a :class:`~envs.demo_store.DemoStore`
            or its directory); the env then emits ``demo_id`` and, unless ``emit_demo_frames``
            says otherwise, no frames.
        primer: a recurrent policy's :class:`~torchrl.envs.TensorDictPrimer` (appended as a copy).
        episode_offset, episode_stride: the env's episode numbering (:mod:`envs.episode_numbering`).
        init_tracker: append :class:`~torchrl.envs.InitTracker` (recurrent policies need ``is_init``).
        seeded: seed the stack with the spec's seed (``static_seed`` as in ``set_seed``).
        static_seed: passed to ``set_seed`` with ``seeded``.
        **env_options: the env's other keyword arguments (``render``, ``with_expert``,
            ``emit_demo_frames``, ``expert``, ``demonstrations``, ...).

    Examples:
        >>> env = make_env(EpisodeSpec(num_houses=1, demo_length=5), num_agents=2, render=False, seeded=True)
        >>> env.batch_size, [type(t).__name__ for t in env.transform]
        (torch.Size([2]), ['ActuationNoise', 'InitTracker'])
    """
    if demo_store is not None:
        env_options.setdefault("emit_demo_frames", False)
    base = PathFollowEnv.from_spec(
        episodes, num_agents, demo_store=demo_store, episode_offset=episode_offset, episode_stride=episode_stride,
        **env_options,
    )
    transforms: list[Transform] = [ActuationNoise(episodes.noise)]
    if init_tracker:
        transforms.append(InitTracker())
    if primer is not None:
        transforms.append(primer.clone())
    env = TransformedEnv(base, Compose(*transforms))
    if seeded:
        env.set_seed(episodes.seed, static_seed=static_seed)
    return env


def make_path_follow_env(noise: str | NoiseModel = "paper", init_tracker: bool = True, **env_kwargs) -> TransformedEnv:
    """A :class:`~envs.nav_env.PathFollowEnv` with actuation noise and (optionally) ``is_init``.

    Args:
        noise: an :data:`~envs.transforms.NOISE_PRESETS` name or a :class:`~envs.transforms.NoiseModel`.
        init_tracker: append :class:`~torchrl.envs.InitTracker` (recurrent policies need ``is_init``).
        **env_kwargs: the fields of an :class:`~envs.episode_spec.EpisodeSpec` (``split``,
            ``demo_length=100``, ``task="homing"``, ``seed``, ...) and the env's other keyword
            arguments (``num_agents``, ``render``, ``grid_size_cells=51``, ...), built by
            :func:`make_env`.

    Examples:
        >>> from functools import partial
        >>> make = partial(make_path_follow_env, noise="paper", split="train", num_houses=1, demo_length=5)
        >>> env = make()
        >>> "is_init" in env.observation_spec.keys()
        True
        >>> make_path_follow_env("paper", task="homing", num_houses=1, demo_length=5, render=False).base_env.task
        'homing'
    """
    spec = {key: env_kwargs.pop(key) for key in SPEC_FIELDS if key in env_kwargs}
    seeded = "seed" in spec and spec["seed"] is not None
    if not seeded:
        spec.pop("seed", None)
    if spec.get("house_seeds") is not None:  # explicit houses replace the split's
        spec.pop("num_houses", None)
    num_agents = env_kwargs.pop("num_agents", None)
    return make_env(EpisodeSpec(noise=noise, **spec), num_agents, init_tracker=init_tracker, seeded=seeded, **env_kwargs)


def make_parallel_path_follow_env(
    num_workers: int,
    noise: str | NoiseModel = "paper",
    init_tracker: bool = True,
    serial: bool = False,
    **env_kwargs,
) -> TransformedEnv:
    """``num_workers`` single-agent envs in a :class:`~torchrl.envs.ParallelEnv` (or a
    :class:`~torchrl.envs.SerialEnv` with ``serial=True``), with actuation noise and
    ``is_init`` applied around it, in the parent process.

    Args:
        num_workers: worker envs (one agent each).
        noise: an :data:`~envs.transforms.NOISE_PRESETS` name or a :class:`~envs.transforms.NoiseModel`.
        init_tracker: append :class:`~torchrl.envs.InitTracker`.
        serial: step the envs in this process (``SerialEnv``) instead of worker processes.
        **env_kwargs: passed to every :class:`~envs.nav_env.PathFollowEnv`.

    Examples:
        >>> env = make_parallel_path_follow_env(2, noise="paper", serial=True, num_houses=1, demo_length=5, render=False)
        >>> env.batch_size, env.transform[0]
        (torch.Size([2]), ActuationNoise(noise='paper'))
    """
    batched = SerialEnv if serial else partial(ParallelEnv, mp_start_method=start_method())
    env = batched(num_workers, partial(PathFollowEnv, **env_kwargs))
    transforms = [ActuationNoise(noise)] + ([InitTracker()] if init_tracker else [])
    return TransformedEnv(env, Compose(*transforms))
