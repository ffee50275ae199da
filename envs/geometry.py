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

    def move(self, xy: np.ndarray, displacement: np.ndarray) -> tuple[np.ndarray, float]:
        """Move the disc from ``xy`` by ``displacement`` (metres), sliding along obstacles.

        Returns:
            the final position and the distance actually travelled (metres).
        """
        length = float(np.hypot(displacement[0], displacement[1]))
        if length == 0.0:
            return xy.copy(), 0.0
        num_substeps = max(1, int(np.ceil(length / MAX_SUBSTEP_M)))
        step = displacement / num_substeps
        position = xy.astype(np.float64).copy()
        travelled = 0.0
        for _ in range(num_substeps):
            for candidate in (step, np.array([step[0], 0.0]), np.array([0.0, step[1]])):
                if not candidate.any():
                    continue
                target = position + candidate
                if self.is_free(target):
                    position = target
                    travelled += float(np.hypot(candidate[0], candidate[1]))
                    break
            else:
                break  # blocked in every direction: stay
        return position, travelled


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

    def at(self, xy: np.ndarray) -> float:
        """Geodesic distance (metres) from ``xy`` to the goal.

        The distance of the node containing ``xy`` plus the straight offset to its
        centre; near walls, where that node may not be navigable, the best of its
        3x3 neighbourhood.
        """
        graph = self.graph
        res = graph.resolution_m
        col = int(np.clip(xy[0] // res, 0, graph.shape[1] - 1))
        row = int(np.clip(xy[1] // res, 0, graph.shape[0] - 1))
        best = np.inf
        for dr in (0, -1, 1):
            for dc in (0, -1, 1):
                r, c = row + dr, col + dc
                if 0 <= r < graph.shape[0] and 0 <= c < graph.shape[1]:
                    d = self.node_distance_m[r, c]
                    if np.isfinite(d):
                        centre_x, centre_y = (c + 0.5) * res, (r + 0.5) * res
                        best = min(best, d + float(np.hypot(xy[0] - centre_x, xy[1] - centre_y)))
            if dr == 0 and np.isfinite(best):
                break
        return float(best)

    def at_many(self, xy: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`at` for an ``(N, 2)`` array of positions (nearest navigable node)."""
        return np.array([self.at(p) for p in xy], dtype=np.float64)


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

    def node(self, xy: np.ndarray) -> int:
        """Index of the navigable node nearest to ``xy``."""
        col = int(np.clip(xy[0] // self.resolution_m, 0, self.shape[1] - 1))
        row = int(np.clip(xy[1] // self.resolution_m, 0, self.shape[0] - 1))
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
        distances = csgraph.dijkstra(self.matrix, directed=False, indices=self.node(goal_xy))
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
