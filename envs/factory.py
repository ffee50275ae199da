"""Importable env factories (picklable under the ``spawn`` start method).

``ParallelEnv`` and TorchRL's collectors start their workers with ``spawn``, so
the function that builds an env must be importable at module level. Use
:func:`functools.partial` to fix its arguments.
"""
from __future__ import annotations

from functools import partial

from torchrl.envs import Compose, InitTracker, ParallelEnv, SerialEnv, TransformedEnv

from envs.nav_env import PathFollowEnv
from envs.transforms import ActuationNoise, NoiseModel


def make_path_follow_env(noise: str | NoiseModel = "paper", init_tracker: bool = True, **env_kwargs) -> TransformedEnv:
    """A :class:`~envs.nav_env.PathFollowEnv` with actuation noise and (optionally) ``is_init``.

    Args:
        noise: an :data:`~envs.transforms.NOISE_PRESETS` name or a :class:`~envs.transforms.NoiseModel`.
        init_tracker: append :class:`~torchrl.envs.InitTracker` (recurrent policies need ``is_init``).
        **env_kwargs: passed to :class:`~envs.nav_env.PathFollowEnv` (e.g. ``task="homing"``,
            ``demo_length=100``, ``grid_size_cells=51``).

    Examples:
        >>> from functools import partial
        >>> make = partial(make_path_follow_env, noise="paper", split="train", num_houses=1, demo_length=5)
        >>> env = make()
        >>> "is_init" in env.observation_spec.keys()
        True
        >>> make_path_follow_env("paper", task="homing", num_houses=1, demo_length=5, render=False).base_env.task
        'homing'
    """
    split = env_kwargs.pop("split", "train")
    transforms = [ActuationNoise(noise)]
    if init_tracker:
        transforms.append(InitTracker())
    return TransformedEnv(PathFollowEnv(split, **env_kwargs), Compose(*transforms))


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
    batched = SerialEnv if serial else partial(ParallelEnv, mp_start_method="spawn")
    env = batched(num_workers, partial(PathFollowEnv, **env_kwargs))
    transforms = [ActuationNoise(noise)] + ([InitTracker()] if init_tracker else [])
    return TransformedEnv(env, Compose(*transforms))
