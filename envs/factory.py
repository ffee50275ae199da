"""Importable env factories (picklable under the ``spawn`` start method).

``ParallelEnv`` and TorchRL's collectors start their workers with ``spawn``, so
the function that builds an env must be importable at module level. Use
:func:`functools.partial` to fix its arguments.
"""
from __future__ import annotations

from torchrl.envs import Compose, InitTracker, TransformedEnv

from envs.nav_env import PathFollowEnv
from envs.transforms import ActuationNoise, NoiseModel


def make_path_follow_env(noise: str | NoiseModel = "paper", init_tracker: bool = True, **env_kwargs) -> TransformedEnv:
    """A :class:`~envs.nav_env.PathFollowEnv` with actuation noise and (optionally) ``is_init``.

    Args:
        noise: an :data:`~envs.transforms.NOISE_PRESETS` name or a :class:`~envs.transforms.NoiseModel`.
        init_tracker: append :class:`~torchrl.envs.InitTracker` (recurrent policies need ``is_init``).
        **env_kwargs: passed to :class:`~envs.nav_env.PathFollowEnv`.

    Examples:
        >>> from functools import partial
        >>> make = partial(make_path_follow_env, noise="paper", split="train", num_houses=1, demo_length=5)
        >>> env = make()
        >>> "is_init" in env.observation_spec.keys()
        True
    """
    split = env_kwargs.pop("split", "train")
    transforms = [ActuationNoise(noise)]
    if init_tracker:
        transforms.append(InitTracker())
    return TransformedEnv(PathFollowEnv(split, **env_kwargs), Compose(*transforms))
