"""Occupancy and collision with sliding in a house; geodesic distances are in :mod:`envs.geodesic`.

Everything here works on a house's 2-D free-space map:

* :class:`OccupancyMap` holds a fine occupancy grid (walls and furniture) and its
  clearance (Euclidean distance to the nearest obstacle, from
  :func:`scipy.ndimage.distance_transform_edt`). The agent is a disc; a position
  is valid when its clearance is at least the agent radius (:attr:`OccupancyMap.free`,
  one flag per fine cell).
* :meth:`OccupancyMap.move` moves the disc along a displacement in small
  sub-steps and slides along walls: a blocked sub-step is retried along x alone,
  then y alone, so the agent never ends up inside an obstacle.

The geodesic graph and distance fields over this map are in :mod:`envs.geodesic`.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

#: Side of an occupancy cell, metres.
OCCUPANCY_RESOLUTION_M = 0.05
#: Side of a geodesic-graph node, metres.
GEODESIC_RESOLUTION_M = 0.1
#: Radius of the agent's footprint, metres.
AGENT_RADIUS_M = 0.2
#: Longest collision-checked sub-step of a motion, metres (at most one occupancy cell).
MAX_SUBSTEP_M = 0.05


class OccupancyMap:
    """Obstacle grid with clearance, collision checks and sliding motion.

    Args:
        occupied: boolean ``(rows, cols)`` grid, True where an obstacle is; row 0 is
            at y = 0 and column 0 at x = 0 (world = grid index * resolution).
        resolution_m: side of a cell, metres.
        agent_radius_m: radius of the agent's disc, metres.

    Examples:
        >>> grid = np.zeros((40, 40), dtype=bool); grid[:, :2] = True
        >>> occ = OccupancyMap(grid, 0.05, 0.2)
        >>> occ.is_free(np.array([1.0, 1.0])), occ.is_free(np.array([0.15, 1.0]))
        (True, False)
    """

    def __init__(self, occupied: np.ndarray, resolution_m: float, agent_radius_m: float = AGENT_RADIUS_M) -> None:
        if occupied.ndim != 2:
            raise ValueError(f"occupied must be a 2-D grid, got shape {occupied.shape}.")
        if resolution_m <= 0 or agent_radius_m <= 0:
            raise ValueError(
                f"resolution_m and agent_radius_m must be > 0 metres, got {resolution_m} and {agent_radius_m}."
            )
        self.occupied = occupied.astype(bool)
        self.resolution_m = float(resolution_m)
        self.agent_radius_m = float(agent_radius_m)
        # distance from each cell centre to the nearest obstacle cell's edge (conservative)
        self.clearance_m = clearance_grid(self.occupied, self.resolution_m)
        self.shape = self.occupied.shape
        self._inverse_resolution = 1.0 / self.resolution_m
        #: ``(rows, cols)`` bool, True at cells where the disc fits (the test of :meth:`move`)
        self.free = self.clearance_m >= self.agent_radius_m
        # the same flags as row-major bytes for the inlined check in move
        self._free_cells = self.free.astype(np.uint8).tobytes()
        self.extent_m = (self.shape[1] * self.resolution_m, self.shape[0] * self.resolution_m)

    def cell(self, xy: np.ndarray) -> tuple[int, int]:
        """Grid (row, col) of a world position (clipped to the grid)."""
        col = int(min(max(xy[0] / self.resolution_m, 0), self.shape[1] - 1))
        row = int(min(max(xy[1] / self.resolution_m, 0), self.shape[0] - 1))
        return row, col

    def clearance(self, xy: np.ndarray) -> float:
        """Distance (metres) from ``xy`` to the nearest obstacle; negative inside one or outside the map."""
        if not (0.0 <= xy[0] < self.extent_m[0] and 0.0 <= xy[1] < self.extent_m[1]):
            return -1.0
        return float(self.clearance_m[self.cell(xy)])

    def is_free(self, xy: np.ndarray) -> bool:
        """Whether the agent's disc centred at ``xy`` touches no obstacle."""
        return self.clearance(xy) >= self.agent_radius_m

    def clearance_many(self, xy: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`clearance` for an ``(..., 2)`` array of positions."""
        cols = np.floor(xy[..., 0] * (1.0 / self.resolution_m)).astype(np.int64)
        rows = np.floor(xy[..., 1] * (1.0 / self.resolution_m)).astype(np.int64)
        inside = (cols >= 0) & (cols < self.shape[1]) & (rows >= 0) & (rows < self.shape[0])
        values = self.clearance_m[np.minimum(np.maximum(rows, 0), self.shape[0] - 1), np.minimum(np.maximum(cols, 0), self.shape[1] - 1)]
        return np.where(inside, values, -1.0)

    def move(self, xy: np.ndarray, displacement: np.ndarray) -> tuple[np.ndarray, float]:
        """Move the disc from ``xy`` by ``displacement`` (metres), sliding along obstacles.

        The motion is split into sub-steps of at most ``MAX_SUBSTEP_M``. A sub-step
        that would collide is retried along x alone, then along y alone (sliding);
        if all three collide the disc stops there.

        Returns:
            the final position and the distance actually travelled (metres).
        """
        x, y = float(xy[0]), float(xy[1])
        dx, dy = float(displacement[0]), float(displacement[1])
        length = math.hypot(dx, dy)
        if length == 0.0:
            return np.array([x, y]), 0.0
        num_substeps = max(1, math.ceil(length / MAX_SUBSTEP_M))
        sx, sy = dx / num_substeps, dy / num_substeps
        # _is_free_scalar inlined (the hot loop of every step and of the expert)
        free_cells, inverse, rows, cols = self._free_cells, self._inverse_resolution, self.shape[0], self.shape[1]

        def free(px: float, py: float) -> bool:
            col = int(px * inverse) if px >= 0 else -1
            row = int(py * inverse) if py >= 0 else -1
            return 0 <= col < cols and 0 <= row < rows and free_cells[row * cols + col] == 1

        travelled = 0.0
        for _ in range(num_substeps):
            if free(x + sx, y + sy):
                x, y = x + sx, y + sy
                travelled += length / num_substeps
            elif sx and free(x + sx, y):
                x += sx
                travelled += abs(sx)
            elif sy and free(x, y + sy):
                y += sy
                travelled += abs(sy)
            else:
                break
        return np.array([x, y]), travelled

    def move_many(self, xy: np.ndarray, displacement: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`move` for ``(N, 2)`` positions and displacements.

        Returns:
            ``(N, 2)`` final positions and ``(N,)`` distances travelled, metres.
        """
        positions = np.empty((len(xy), 2))
        travelled = np.empty(len(xy))
        for index in range(len(xy)):
            positions[index], travelled[index] = self.move(xy[index], displacement[index])
        return positions, travelled

    def _is_free_scalar(self, x: float, y: float) -> bool:
        col = int(x * self._inverse_resolution) if x >= 0 else -1
        row = int(y * self._inverse_resolution) if y >= 0 else -1
        if col < 0 or row < 0 or col >= self.shape[1] or row >= self.shape[0]:
            return False
        return self.clearance_m[row, col] >= self.agent_radius_m


def clearance_grid(occupied: np.ndarray, resolution_m: float) -> np.ndarray:
    """Clearance (metres, float32) of every cell of an obstacle grid.

    The distance from a cell's centre to the nearest obstacle cell, less half a cell
    (conservative): :attr:`OccupancyMap.clearance_m`.
    """
    return (ndimage.distance_transform_edt(~occupied) * resolution_m - 0.5 * resolution_m).astype(np.float32)
