"""Argument checks shared by the env and the configs that describe its episodes.

Each raises ``ValueError`` naming the parameter and the allowed values, so a
recipe fails on a bad config before any work starts.
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Sequence

import numpy as np
import torch

from envs.demo_store import DemoStore, check_store_matches
from envs.house_grid import check_grid_size, default_grid_size_cells
from envs.route_styles import RouteMixture
from envs.scenes import split_seeds
from envs.transforms import ACTUATION_NOISE_KEY, make_noise_model


def check_positive_int(name: str, value: object) -> None:
    """Raise ``ValueError`` unless ``value`` is a positive int (bools refused).

    Examples:
        >>> check_positive_int("max_steps", 50)
        >>> check_positive_int("max_steps", 0)
        Traceback (most recent call last):
        ...
        ValueError: max_steps must be a positive int, got 0.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value!r}.")


def check_positive_ints(config: object, names: Iterable[str]) -> None:
    """:func:`check_positive_int` on each attribute ``names`` of ``config``."""
    for name in names:
        check_positive_int(name, getattr(config, name))


def check_episode_source(split: str, num_houses: int | None, noise: object) -> None:
    """Raise ``ValueError`` for an unknown split, a bad house count or an unknown noise preset.

    Examples:
        >>> check_episode_source("train", None, "paper")
        >>> check_episode_source("train", None, "lol")
        Traceback (most recent call last):
        ...
        ValueError: noise must be one of ['locobot', 'none', 'paper', 'paper_symmetric', 'paper_unclipped'] or a NoiseModel, got 'lol'.
    """
    split_seeds(split, num_houses)
    make_noise_model(noise)


def resolve_houses(
    split: str,
    num_houses: int | None,
    house_seeds: Sequence[int] | None,
    demo_store: DemoStore | str | os.PathLike | None,
    emit_demo_frames: bool,
    demo_length: int,
    image_size: int,
    success_radius_m: float,
    task: str = "follow",
    grid_size_cells: int | None = None,
    route_style: RouteMixture | None = None,
) -> tuple[DemoStore | None, list[int]]:
    """The env's demo store (opened and verified when given as a directory) and its house seeds.

    Without ``house_seeds``, the houses are the split's on a grid of ``grid_size_cells``
    cells (``None``: :func:`~envs.house_grid.default_grid_size_cells` of ``demo_length``).

    Raises:
        ValueError: for a wrong ``demo_store`` type, a store that disagrees with the
            env's arguments, ``emit_demo_frames=False`` without a store (pass ``True``
            where frames are not rendered), bad
            ``house_seeds``, ``house_seeds`` with ``grid_size_cells`` (house seeds name
            their grid), or a bad ``grid_size_cells``.
    """
    if grid_size_cells is not None:
        check_grid_size(grid_size_cells)
        if house_seeds is not None:
            raise ValueError(
                "grid_size_cells cannot be combined with house_seeds: a house seed names its grid "
                "(envs.house_grid.house_seed(base_seed, grid_size_cells)); give one or the other."
            )
    grid = default_grid_size_cells(demo_length) if grid_size_cells is None else grid_size_cells
    if demo_store is not None:
        if not isinstance(demo_store, (DemoStore, str, os.PathLike)):
            raise ValueError(
                f"demo_store must be a DemoStore, a store directory (str or path) or None, got {type(demo_store).__name__}."
            )
        # a directory is opened and verified (checksums) once per env process
        demo_store = demo_store if isinstance(demo_store, DemoStore) else DemoStore(demo_store)
        check_store_matches(
            demo_store, split, num_houses, house_seeds, demo_length, image_size, success_radius_m, task, grid, route_style
        )
        return demo_store, demo_store.config.house_seeds
    if not emit_demo_frames:
        raise ValueError(
            "emit_demo_frames=False needs a demo_store (the frames must be retrievable from demo_id) "
            "or render=False (blank frames); pass demo_store=<DemoStore or its directory>, render=False, "
            "or keep emit_demo_frames=True."
        )
    if house_seeds is not None:
        seeds = [int(s) for s in house_seeds]
        if not seeds or min(seeds) < 0:
            raise ValueError(f"house_seeds must be a non-empty list of non-negative ints, got {house_seeds!r}.")
        return None, seeds
    return None, split_seeds(split, num_houses, grid)


def check_action(action: torch.Tensor | None, count: int, num_actions: int, stop_action: bool) -> np.ndarray:
    """The ``(count,)`` actions of a step as a numpy array, or a ``ValueError`` naming the allowed values."""
    allowed = f"0 forward, 1 left, 2 right{', 3 stop' if stop_action else ''}"
    if action is None:
        raise KeyError(f"step() needs an 'action' key: an integer in [0, {num_actions - 1}] ({allowed}).")
    if action.numel() != count:
        raise ValueError(f"action must hold {count} value(s), one per agent, got shape {tuple(action.shape)}.")
    values = action.reshape(count).cpu().numpy()
    if values.dtype.kind not in "iu" or values.min() < 0 or values.max() >= num_actions:
        raise ValueError(f"action must be an integer in [0, {num_actions - 1}] ({allowed}), got {values.tolist()}.")
    return values


def check_actuation_noise(noise: torch.Tensor, count: int, batch_size: torch.Size) -> np.ndarray:
    """The ``(count, 3)`` actuation noise of a step as float64, or a ``ValueError`` (wrong shape, not finite)."""
    if noise.numel() != 3 * count:
        raise ValueError(
            f"{ACTUATION_NOISE_KEY} must have shape {(*batch_size, 3)} "
            f"(forward m, lateral m, rotation rad per agent), got {tuple(noise.shape)}."
        )
    values = noise.reshape(count, 3).cpu().numpy().astype(np.float64)
    if not np.isfinite(values).all():
        raise ValueError(f"{ACTUATION_NOISE_KEY} must be finite (forward m, lateral m, rotation rad), got {values.tolist()}.")
    return values
