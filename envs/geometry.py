"""Occupancy, collision with sliding, and geodesic distances in a house.

Everything here works on a house's 2-D free-space map:

* :class:`OccupancyMap` holds a fine occupancy grid (walls and furniture) and its
  clearance (Euclidean distance to the nearest obstacle, from
  :func:`scipy.ndimage.distance_transform_edt`). The agent is a disc; a position
  is valid when its clearance is at least the agent radius.
* :meth:`OccupancyMap.move` moves the disc along a displacement in small
  sub-steps and slides along walls: a blocked sub-step is retried along x alone,
  then y alone, so the agent never ends up inside an obstacle.
* :class:`GeodesicGraph` is the 8-connected graph of navigable nodes on a coarser
  grid; :meth:`GeodesicGraph.distance_field` runs :func:`scipy.sparse.csgraph.dijkstra`
  from a goal and returns a :class:`DistanceField` that answers geodesic distances
  (metres) at any position.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

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
        self.clearance_m = (
            ndimage.distance_transform_edt(~self.occupied) * self.resolution_m - 0.5 * self.resolution_m
        ).astype(np.float32)
        self.shape = self.occupied.shape
        self._inverse_resolution = 1.0 / self.resolution_m
        # row-major bytes, 1 where the disc fits (the same comparison as _is_free_scalar)
        self._free_cells = (self.clearance_m >= self.agent_radius_m).astype(np.uint8).tobytes()
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


@dataclass
class DistanceField:
    """Geodesic distances (metres) to one goal over a :class:`GeodesicGraph`.

    Attributes:
        graph: the graph the distances were computed on.
        node_distance_m: ``(rows, cols)`` distances of every node (``inf`` where unreachable).
        goal_xy: the goal position, metres.
    """

    graph: GeodesicGraph
    node_distance_m: np.ndarray
    goal_xy: np.ndarray

    def __post_init__(self) -> None:
        # Non-navigable nodes (next to walls) take the best neighbour's distance plus the
        # hop to it, so positions there still get a finite, consistent distance.
        distances = self.node_distance_m
        res = self.graph.resolution_m
        padded = np.pad(distances, 1, constant_values=np.inf)
        rows, cols = distances.shape
        filled = distances.copy()
        shifted = np.empty_like(distances)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:  # the (0, 0) shift adds 0: min(d, d + 0) = d
                    np.add(padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols], res * math.hypot(dr, dc), out=shifted)
                    np.minimum(filled, shifted, out=filled)
        self._filled = np.where(np.isfinite(distances), distances, filled)

    def at(self, xy: np.ndarray) -> float:
        """Geodesic distance (metres) from ``xy`` to the goal.

        The distance of the node containing ``xy`` plus the straight offset to its
        centre. A node next to a wall, where the disc does not fit, takes its best
        neighbour's distance plus the hop to it (``inf`` if none is reachable).
        """
        res = self.graph.resolution_m
        rows, cols = self.graph.shape
        col = min(max(int(xy[0] // res), 0), cols - 1)
        row = min(max(int(xy[1] // res), 0), rows - 1)
        return float(self._filled[row, col] + math.hypot(xy[0] - (col + 0.5) * res, xy[1] - (row + 0.5) * res))

    def at_many(self, xy: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`at` for an ``(N, 2)`` array of positions."""
        res = self.graph.resolution_m
        rows, cols = self.graph.shape
        col = np.minimum(np.maximum((xy[:, 0] // res).astype(np.int64), 0), cols - 1)
        row = np.minimum(np.maximum((xy[:, 1] // res).astype(np.int64), 0), rows - 1)
        return self._filled[row, col] + np.hypot(xy[:, 0] - (col + 0.5) * res, xy[:, 1] - (row + 0.5) * res)


class GeodesicGraph:
    """8-connected graph of navigable nodes (agent disc fits) for geodesic distances.

    Args:
        occupancy: the house's :class:`OccupancyMap`.
        resolution_m: node spacing, metres (a multiple of the occupancy resolution).
        connectivity: 8 (default; diagonal moves cost sqrt(2) x resolution) or 4.

    Examples:
        >>> grid = np.zeros((60, 60), dtype=bool); grid[[0, -1], :] = True; grid[:, [0, -1]] = True
        >>> graph = GeodesicGraph(OccupancyMap(grid, 0.05, 0.2), 0.1)
        >>> field = graph.distance_field(np.array([1.5, 1.5]))
        >>> round(field.at(np.array([0.5, 1.5])), 2)
        1.0
    """

    def __init__(
        self, occupancy: OccupancyMap, resolution_m: float = GEODESIC_RESOLUTION_M, connectivity: int = 8
    ) -> None:
        factor = resolution_m / occupancy.resolution_m
        if resolution_m <= 0 or abs(factor - round(factor)) > 1e-6:
            raise ValueError(
                f"resolution_m must be a positive multiple of the occupancy resolution "
                f"({occupancy.resolution_m} m), got {resolution_m}."
            )
        factor = int(round(factor))
        self.resolution_m = float(resolution_m)
        rows, cols = occupancy.shape[0] // factor, occupancy.shape[1] // factor
        self.shape = (rows, cols)
        # a node is navigable when the disc fits at its centre
        centre_rows = (np.arange(rows) * factor + factor // 2).clip(max=occupancy.shape[0] - 1)
        centre_cols = (np.arange(cols) * factor + factor // 2).clip(max=occupancy.shape[1] - 1)
        clearance = occupancy.clearance_m[np.ix_(centre_rows, centre_cols)]
        self.navigable = clearance >= occupancy.agent_radius_m
        self.matrix = grid_graph(self.navigable, self.resolution_m, connectivity)
        # Dijkstra runs on the navigable nodes only, edges stored both ways (directed=True
        # then needs no conversion per call): the same distances, about 1.5x faster
        self._nodes = np.flatnonzero(self.navigable.ravel())
        self._position = np.full(rows * cols, -1, dtype=np.int64)
        self._position[self._nodes] = np.arange(len(self._nodes))
        both_ways = (self.matrix + self.matrix.T).tocsr()
        self._search_matrix = both_ways[self._nodes][:, self._nodes].tocsr()
        self._search_matrix.sort_indices()

    def node(self, xy: np.ndarray) -> int:
        """Index of the navigable node nearest to ``xy``."""
        col = int(min(max(xy[0] // self.resolution_m, 0), self.shape[1] - 1))
        row = int(min(max(xy[1] // self.resolution_m, 0), self.shape[0] - 1))
        if self.navigable[row, col]:
            return row * self.shape[1] + col
        rows, cols = np.nonzero(self.navigable)
        nearest = np.argmin((rows - row) ** 2 + (cols - col) ** 2)
        return int(rows[nearest] * self.shape[1] + cols[nearest])

    def node_xy(self, node: int | np.ndarray) -> np.ndarray:
        """World position (metres) of node centres."""
        row, col = np.divmod(np.asarray(node), self.shape[1])
        return np.stack([(col + 0.5) * self.resolution_m, (row + 0.5) * self.resolution_m], axis=-1)

    def distance_field(self, goal_xy: np.ndarray) -> DistanceField:
        """Geodesic distances from every node to ``goal_xy`` (one Dijkstra run)."""
        found = csgraph.dijkstra(self._search_matrix, directed=True, indices=self._position[self.node(goal_xy)])
        distances = np.full(self.shape[0] * self.shape[1], np.inf)
        distances[self._nodes] = found
        return DistanceField(self, distances.reshape(self.shape), np.asarray(goal_xy, dtype=np.float64))

    def components(self) -> int:
        """Number of connected components of the navigable space."""
        return int(ndimage.label(self.navigable, structure=np.ones((3, 3)))[1])


def grid_graph(navigable: np.ndarray, resolution_m: float, connectivity: int = 8) -> sparse.csr_matrix:
    """Sparse adjacency (edge weights in metres) of a grid restricted to navigable nodes.

    Args:
        navigable: boolean ``(rows, cols)`` grid.
        resolution_m: node spacing, metres.
        connectivity: 4 or 8. A diagonal edge is kept only if both orthogonal
            neighbours are navigable, so paths never cut a wall corner.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity}.")
    rows, cols = navigable.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    sources, targets, weights = [], [], []
    diagonal = np.sqrt(2.0) * resolution_m
    offsets = [(0, 1, resolution_m), (1, 0, resolution_m)]
    if connectivity == 8:
        offsets += [(1, 1, diagonal), (1, -1, diagonal)]
    for dr, dc, weight in offsets:
        r0, r1 = 0, rows - dr
        c0, c1 = max(0, -dc), cols - max(0, dc)
        a = navigable[r0:r1, c0:c1]
        b = navigable[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
        ok = a & b
        if dr and dc:
            ok &= navigable[r0 + dr : r1 + dr, c0:c1] & navigable[r0:r1, c0 + dc : c1 + dc]
        sources.append(index[r0:r1, c0:c1][ok])
        targets.append(index[r0 + dr : r1 + dr, c0 + dc : c1 + dc][ok])
        weights.append(np.full(int(ok.sum()), weight))
    src = np.concatenate(sources)
    dst = np.concatenate(targets)
    w = np.concatenate(weights)
    return sparse.csr_matrix((w, (src, dst)), shape=(rows * cols, rows * cols))
