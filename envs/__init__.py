"""Indoor path-following environments built on MuJoCo and labmaze, for TorchRL.

Importing :mod:`envs` changes nothing in the process environment: the headless
OpenGL back-end (``MUJOCO_GL``) is selected at the first render, and envs with
``render=False`` never need one (see :func:`envs.render.select_gl_backend`).

Examples:
    >>> from envs import PathFollowEnv, ActuationNoise, make_path_follow_env
    >>> env = make_path_follow_env(noise="paper", num_houses=1, demo_length=5, render=False)
    >>> env.rollout(3, break_when_any_done=False)["pixels"].shape
    torch.Size([3, 64, 64, 3])
"""
from __future__ import annotations

from envs.conditions import CONDITIONS, parse_conditions
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec
from envs.factory import make_env, make_parallel_path_follow_env, make_path_follow_env
from envs.nav_env import PathFollowEnv
from envs.playlist import DemonstrationPlaylist
from envs.specs import PRIVILEGED_KEYS, HidePrivileged
from envs.transforms import NOISE_PRESETS, ActuationNoise, NoiseModel
from envs.user_demos import RouteError, RouteRecorder, demonstration_from_actions, demonstration_from_waypoints
from envs.version import ENV_VERSION

__all__ = [
    "CONDITIONS",
    "ENV_VERSION",
    "NOISE_PRESETS",
    "PRIVILEGED_KEYS",
    "ActuationNoise",
    "DemoStore",
    "DemoStoreConfig",
    "DemonstrationPlaylist",
    "EpisodeSpec",
    "HidePrivileged",
    "NoiseModel",
    "PathFollowEnv",
    "RouteError",
    "RouteRecorder",
    "demonstration_from_actions",
    "demonstration_from_waypoints",
    "make_env",
    "make_parallel_path_follow_env",
    "make_path_follow_env",
    "parse_conditions",
]
