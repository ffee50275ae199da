"""House sizes: the labmaze grid of a house, carried by its seed, and the grid long routes need.

A house is a pure function of one int, its *house seed* (:func:`envs.scenes.build_house`).
Houses of the default grid, :data:`DEFAULT_GRID_SIZE_CELLS` = 15 cells of 1 m (the
paper-sized houses of every split, store and checkpoint so far), keep their plain
seeds. A house of another grid of ``g`` cells has the seed
``g * GRID_SEED_STRIDE + base_seed`` (:func:`house_seed`), so the grid travels with
the seed through everything that stores one (demonstrations, demo stores,
evaluation records) and ``build_house(seed)`` always rebuilds the same house.

Long routes need large houses: a demonstration of ``n`` steps is sampled towards a
goal at least ``0.3 n + 1`` m away in a straight line, which a 15 m house cannot
hold for ``n`` much above 30. :func:`default_grid_size_cells` is the one rule the
env and the demo store use when no grid is given: 15 cells up to ``n = 30``, then
``ceil(n / 2)`` cells rounded up to odd (labmaze grids are odd): 25 for ``n = 50``,
51 for ``n = 100``. Larger grids hold proportionally more rooms
(:func:`max_rooms`: the default 6 rooms per 15 x 15 cells), so rooms keep their size
and density.

Examples:
    >>> house_seed(3, 51), split_house_seed(510_000_003)
    (510000003, (3, 51))
    >>> default_grid_size_cells(30), default_grid_size_cells(50), default_grid_size_cells(100)
    (15, 25, 51)
"""
from __future__ import annotations

import math

import numpy as np

#: The default labmaze grid, cells (odd, as labmaze requires): 15 m x 15 m houses.
DEFAULT_GRID_SIZE_CELLS = 15
#: The largest grid a house seed can name, cells.
MAX_GRID_SIZE_CELLS = 99
#: House seeds of a non-default grid ``g`` are ``g * GRID_SEED_STRIDE + base``; base
#: seeds stay below it (split seeds end at 3 x 100,000), and the largest seed fits in
#: int32 (labmaze's seed).
GRID_SEED_STRIDE = 10_000_000
#: Rooms labmaze may place per default-grid area (15 x 15 cells).
DEFAULT_MAX_ROOMS = 6
#: Routes up to this many steps use the default grid; longer ones ``ceil(n * cells/step)`` cells.
DEFAULT_GRID_MAX_DEMO_LENGTH = 30
GRID_CELLS_PER_DEMO_STEP = 0.5


def check_grid_size(grid_size_cells: object, name: str = "grid_size_cells") -> int:
    """``grid_size_cells`` as an int, or a ``ValueError`` naming ``name`` and the allowed values.

    Examples:
        >>> check_grid_size(25)
        25
        >>> check_grid_size(20)
        Traceback (most recent call last):
        ...
        ValueError: grid_size_cells must be an odd int in [15, 99] (labmaze cells of 1 m), got 20.
    """
    if (
        isinstance(grid_size_cells, bool)
        or not isinstance(grid_size_cells, (int, np.integer))
        or not DEFAULT_GRID_SIZE_CELLS <= grid_size_cells <= MAX_GRID_SIZE_CELLS
        or grid_size_cells % 2 == 0
    ):
        raise ValueError(
            f"{name} must be an odd int in [{DEFAULT_GRID_SIZE_CELLS}, {MAX_GRID_SIZE_CELLS}] "
            f"(labmaze cells of 1 m), got {grid_size_cells!r}."
        )
    return int(grid_size_cells)


def house_seed(base_seed: int, grid_size_cells: int | None = None) -> int:
    """The house seed of house ``base_seed`` on a grid of ``grid_size_cells`` cells (``None``: the default grid).

    Raises:
        ValueError: a negative base seed, one not below :data:`GRID_SEED_STRIDE` for a
            non-default grid, or a grid :func:`check_grid_size` refuses.

    Examples:
        >>> house_seed(7), house_seed(7, 15), house_seed(7, 25)
        (7, 7, 250000007)
    """
    if isinstance(base_seed, bool) or not isinstance(base_seed, (int, np.integer)) or base_seed < 0:
        raise ValueError(f"base_seed must be a non-negative int, got {base_seed!r}.")
    grid = DEFAULT_GRID_SIZE_CELLS if grid_size_cells is None else check_grid_size(grid_size_cells)
    if grid == DEFAULT_GRID_SIZE_CELLS:
        return int(base_seed)
    if base_seed >= GRID_SEED_STRIDE:
        raise ValueError(f"base_seed must be below {GRID_SEED_STRIDE} for a grid of {grid} cells, got {base_seed}.")
    return grid * GRID_SEED_STRIDE + int(base_seed)


def split_house_seed(seed: int) -> tuple[int, int]:
    """``(base seed, grid size in cells)`` of a house seed (the inverse of :func:`house_seed`).

    Raises:
        ValueError: a negative seed, or one whose grid part is not an allowed grid.

    Examples:
        >>> split_house_seed(100_003), split_house_seed(250_000_007)
        ((100003, 15), (7, 25))
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}.")
    grid, base = divmod(int(seed), GRID_SEED_STRIDE)
    if grid == 0:
        return base, DEFAULT_GRID_SIZE_CELLS
    check_grid_size(grid, f"the grid part of house seed {seed} (seed // {GRID_SEED_STRIDE})")
    return base, grid


#: The longest demonstration, steps: the largest grid holds routes of this many steps
#: (:func:`default_grid_size_cells`).
MAX_DEMO_LENGTH = int(MAX_GRID_SIZE_CELLS / GRID_CELLS_PER_DEMO_STEP)


def check_demo_length(demo_length: object, name: str = "demo_length") -> int:
    """``demo_length`` as an int, or a ``ValueError`` naming ``name`` and the allowed range.

    Examples:
        >>> check_demo_length(30)
        30
        >>> check_demo_length(1000)
        Traceback (most recent call last):
        ...
        ValueError: demo_length must be an int in [1, 198] (steps), got 1000.
    """
    if (
        isinstance(demo_length, bool)
        or not isinstance(demo_length, (int, np.integer))
        or not 1 <= demo_length <= MAX_DEMO_LENGTH
    ):
        raise ValueError(f"{name} must be an int in [1, {MAX_DEMO_LENGTH}] (steps), got {demo_length!r}.")
    return int(demo_length)


def default_grid_size_cells(demo_length: int) -> int:
    """The grid (cells) of the houses demonstrations of ``demo_length`` steps are sampled in.

    The default grid up to :data:`DEFAULT_GRID_MAX_DEMO_LENGTH` steps, then
    ``ceil(n * GRID_CELLS_PER_DEMO_STEP)`` rounded up to odd, at most :data:`MAX_GRID_SIZE_CELLS`.

    Examples:
        >>> [default_grid_size_cells(n) for n in (5, 30, 31, 40, 100, 300)]
        [15, 15, 17, 21, 51, 99]
    """
    if demo_length <= DEFAULT_GRID_MAX_DEMO_LENGTH:
        return DEFAULT_GRID_SIZE_CELLS
    cells = math.ceil(demo_length * GRID_CELLS_PER_DEMO_STEP)
    return min(MAX_GRID_SIZE_CELLS, max(DEFAULT_GRID_SIZE_CELLS, cells + (cells % 2 == 0)))


def max_rooms(grid_size_cells: int) -> int:
    """Rooms labmaze may place on a grid: :data:`DEFAULT_MAX_ROOMS` per 15 x 15 cells.

    Examples:
        >>> max_rooms(15), max_rooms(25), max_rooms(51)
        (6, 17, 69)
    """
    return max(1, round(DEFAULT_MAX_ROOMS * (grid_size_cells / DEFAULT_GRID_SIZE_CELLS) ** 2))


__all__ = [
    "DEFAULT_GRID_SIZE_CELLS",
    "GRID_SEED_STRIDE",
    "MAX_GRID_SIZE_CELLS",
    "check_grid_size",
    "default_grid_size_cells",
    "house_seed",
    "max_rooms",
    "split_house_seed",
]
