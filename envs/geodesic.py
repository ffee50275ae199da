"""Geodesic distances in a house that agree with the collision model of :mod:`envs.geometry`.

:class:`GeodesicGraph` is the 8-connected graph of the nodes of a grid coarser than
the occupancy grid; :meth:`GeodesicGraph.distance_field` runs
:func:`scipy.sparse.csgraph.dijkstra` from a goal and returns a
:class:`DistanceField` that answers geodesic distances (metres) at any position.

The distance field agrees with the collision model: every position the collision
model accepts (and so every position :meth:`~envs.geometry.OccupancyMap.move` can
reach) has a finite distance to any goal in the same connected free region
(8-connected component of free fine cells). The graph's nodes are the *reachable*
nodes, those holding at least one free fine cell; two nodes are joined when a free
fine cell of one touches (8-neighbourhood) a free fine cell of the other, which is
every way one sub-step of the motion can pass between them (one-cell-wide diagonal
squeezes included), and when both are *navigable* (the disc fits at the node
centre) and adjacent. So the graph's connected components are exactly the free
regions, and distances are shortest paths the collision model allows.

Distance at a position (:meth:`DistanceField.at`, :meth:`DistanceField.at_many`):
the Dijkstra distance of the node containing it plus the straight offset to that
node's centre. A node with no Dijkstra distance (it holds no free cell, e.g. a wall
node that a position on its border is rounded into) takes its best neighbour's
distance plus the hop to it. ``inf`` is left only for positions outside the goal's
free region.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from envs.geometry import AGENT_RADIUS_M, GEODESIC_RESOLUTION_M, OccupancyMap, clearance_grid


@dataclass
class DistanceField:
    """Geodesic distances (metres) to one goal over a :class:`GeodesicGraph`.

    Attributes:
        graph: the graph the distances were computed on.
        node_distance_m: ``(rows, cols)`` Dijkstra distances of every node (``inf`` at
            nodes that hold no free cell or lie in another free region than the goal).
        goal_xy: the goal position, metres.
    """

    graph: GeodesicGraph
    node_distance_m: np.ndarray
    goal_xy: np.ndarray

    def __post_init__(self) -> None:
        # A node with no Dijkstra distance (no free cell in it, e.g. a wall node that a
        # position on its border is rounded into) takes its best neighbour's distance
        # plus the hop to it, so positions there still get a finite, consistent distance.
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
        centre. A node's distance is its Dijkstra distance on the graph of reachable
        nodes (those holding a cell where the disc fits, the collision model's own
        test, joined wherever the collision model passes); a node with none (no free
        cell in it) takes its best neighbour's distance plus the hop to it. So every
        position :meth:`OccupancyMap.move` can reach from the goal's free region gets
        a finite distance; ``inf`` only outside that region.
        """
        res = self.graph.resolution_m
        rows, cols = self.graph.shape
        col = min(max(int(xy[0] // res), 0), cols - 1)
        row = min(max(int(xy[1] // res), 0), rows - 1)
        return float(self._filled[row, col] + math.hypot(xy[0] - (col + 0.5) * res, xy[1] - (row + 0.5) * res))

    def at_many(self, xy: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`at` for an ``(N, 2)`` array of positions (the same rule)."""
        res = self.graph.resolution_m
        rows, cols = self.graph.shape
        col = np.minimum(np.maximum((xy[:, 0] // res).astype(np.int64), 0), cols - 1)
        row = np.minimum(np.maximum((xy[:, 1] // res).astype(np.int64), 0), rows - 1)
        return self._filled[row, col] + np.hypot(xy[:, 0] - (col + 0.5) * res, xy[:, 1] - (row + 0.5) * res)


class GeodesicGraph:
    """Graph of the reachable nodes of a coarse grid, for geodesic distances.

    A node is *navigable* when the agent's disc fits at its centre, and *reachable*
    when the disc fits somewhere in it (one of its occupancy cells is free, the test
    :meth:`OccupancyMap.move` applies). Dijkstra runs over the reachable nodes; two
    are joined when a free cell of one touches a free cell of the other (every way
    the collision model passes between them) or, as before, when both are navigable
    and adjacent (a diagonal only if both orthogonal neighbours are navigable).
    The sparse matrices are built on first use, so a graph made only for
    :meth:`components` costs no more than that. :attr:`navigable` (used for spawn
    points, route ends and :meth:`components`) is unchanged by the reachable nodes.

    Args:
        occupancy: the house's :class:`OccupancyMap`.
        resolution_m: node spacing, metres (a multiple of the occupancy resolution).
        connectivity: 8 (default; diagonal moves cost sqrt(2) x resolution) or 4. With 4,
            diagonal squeezes between free cells are not joined, so the agreement with
            the collision model holds for 8 only.

    Examples:
        >>> grid = np.zeros((60, 60), dtype=bool); grid[[0, -1], :] = True; grid[:, [0, -1]] = True
        >>> graph = GeodesicGraph(OccupancyMap(grid, 0.05, 0.2), 0.1)
        >>> field = graph.distance_field(np.array([1.5, 1.5]))
        >>> round(field.at(np.array([0.5, 1.5])), 2)  # 1 m between node centres + 0.07 m to the centre
        1.07
    """

    def __init__(
        self, occupancy: OccupancyMap, resolution_m: float = GEODESIC_RESOLUTION_M, connectivity: int = 8
    ) -> None:
        factor = _node_factor(resolution_m, occupancy.resolution_m)
        if connectivity not in (4, 8):
            raise ValueError(f"connectivity must be 4 or 8, got {connectivity}.")
        self.occupancy = occupancy
        self.resolution_m = float(resolution_m)
        self.connectivity = connectivity
        self._factor = factor
        rows, cols = occupancy.shape[0] // factor, occupancy.shape[1] // factor
        self.shape = (rows, cols)
        # a node is navigable when the disc fits at its centre
        clearance = occupancy.clearance_m[np.ix_(*node_centre_cells(occupancy.shape, factor))]
        self.navigable = clearance >= occupancy.agent_radius_m

    @functools.cached_property
    def _blocks(self) -> np.ndarray:
        """Free occupancy cells as ``(rows, factor, cols, factor)``: ``[R, i, C, j]`` is cell
        ``(R * factor + i, C * factor + j)``, inside node ``(R, C)``. Cells past the last
        whole node (a grid side not a multiple of ``factor``) are left out; house grids
        are whole multiples, with walls at the border."""
        (rows, cols), factor = self.shape, self._factor
        return self.occupancy.free[: rows * factor, : cols * factor].reshape(rows, factor, cols, factor)

    @functools.cached_property
    def reachable(self) -> np.ndarray:
        """``(rows, cols)`` bool: nodes holding at least one cell where the disc fits."""
        return self._blocks.any(axis=(1, 3)) | self.navigable

    @functools.cached_property
    def matrix(self) -> sparse.csr_matrix:
        """Adjacency (edge weights in metres) of the reachable nodes, each edge stored once."""
        return grid_graph(self.navigable, self.resolution_m, self.connectivity, links=self._free_cell_links())

    def _free_cell_links(self) -> dict[tuple[int, int], np.ndarray]:
        """Node pairs joined by two touching free cells, per :func:`grid_graph` offset.

        Returns:
            for each offset ``(dr, dc)`` a bool grid over the same source nodes as
            :func:`grid_graph`'s slice for that offset.
        """
        blocks, last = self._blocks, self._factor - 1

        def touching(side_a: np.ndarray, side_b: np.ndarray, axis: int) -> np.ndarray:
            # a free cell on side_a touches one on side_b at the same or a next index along axis
            near = side_b.copy()
            lead = [slice(None)] * side_b.ndim
            follow = [slice(None)] * side_b.ndim
            lead[axis], follow[axis] = slice(1, None), slice(None, -1)
            near[tuple(follow)] |= side_b[tuple(lead)]
            near[tuple(lead)] |= side_b[tuple(follow)]
            return (side_a & near).any(axis=axis)

        links = {
            (0, 1): touching(blocks[:, :, :-1, last], blocks[:, :, 1:, 0], axis=1),
            (1, 0): touching(blocks[:-1, last, :, :], blocks[1:, 0, :, :], axis=2),
        }
        if self.connectivity == 8:
            links[(1, 1)] = blocks[:-1, last, :-1, last] & blocks[1:, 0, 1:, 0]
            links[(1, -1)] = blocks[:-1, last, 1:, 0] & blocks[1:, 0, :-1, last]
        return links

    @functools.cached_property
    def _search(self) -> tuple[np.ndarray, np.ndarray, sparse.csr_matrix]:
        """(reachable node indices, their position among them or -1, Dijkstra matrix)."""
        # Dijkstra runs on the reachable nodes only, edges stored both ways (directed=True
        # then needs no conversion per call): the same distances, about 1.5x faster
        rows, cols = self.shape
        nodes = np.flatnonzero(self.reachable.ravel())
        position = np.full(rows * cols, -1, dtype=np.int64)
        position[nodes] = np.arange(len(nodes))
        edges = self.matrix.tocoo()  # every edge joins two reachable nodes, stored once
        sources, targets = position[edges.row], position[edges.col]
        search_matrix = sparse.csr_matrix(
            (np.concatenate([edges.data, edges.data]), (np.concatenate([sources, targets]), np.concatenate([targets, sources]))),
            shape=(len(nodes), len(nodes)),
        )
        search_matrix.sort_indices()
        return nodes, position, search_matrix

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
        """Geodesic distances from every node to ``goal_xy`` (one Dijkstra run from its nearest navigable node)."""
        nodes, position, search_matrix = self._search
        found = csgraph.dijkstra(search_matrix, directed=True, indices=position[self.node(goal_xy)])
        distances = np.full(self.shape[0] * self.shape[1], np.inf)
        distances[nodes] = found
        return DistanceField(self, distances.reshape(self.shape), np.asarray(goal_xy, dtype=np.float64))

    def components(self) -> int:
        """:func:`count_components` of the navigable nodes (node centres, not the edges Dijkstra uses)."""
        return count_components(self.navigable)


def count_components(navigable: np.ndarray) -> int:
    """Number of 8-connected components (diagonal neighbours touch) of a boolean node grid."""
    return int(ndimage.label(navigable, structure=np.ones((3, 3)))[1])


def node_centre_cells(grid_shape: tuple[int, int], factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) indices of the occupancy cells at the centres of the graph nodes.

    Args:
        grid_shape: occupancy grid shape.
        factor: occupancy cells per node side.
    """
    rows, cols = grid_shape[0] // factor, grid_shape[1] // factor
    centre_rows = (np.arange(rows) * factor + factor // 2).clip(max=grid_shape[0] - 1)
    centre_cols = (np.arange(cols) * factor + factor // 2).clip(max=grid_shape[1] - 1)
    return centre_rows, centre_cols


def navigable_beside(
    obstacle: np.ndarray,
    resolution_m: float,
    node_resolution_m: float = GEODESIC_RESOLUTION_M,
    agent_radius_m: float = AGENT_RADIUS_M,
) -> np.ndarray:
    """Nodes whose centre leaves room for the agent's disc next to one obstacle.

    Clearance to a union of obstacles is the smaller of the clearances to each
    (exactly, cell by cell), so for obstacle grids ``a`` and ``b``
    ``GeodesicGraph(OccupancyMap(a | b, r)).navigable`` equals
    ``GeodesicGraph(OccupancyMap(a, r)).navigable & navigable_beside(b, r)``. This
    computes the clearance only in a window around ``b``, so adding one piece of
    furniture costs a small distance transform instead of one of the whole house.

    Args:
        obstacle: boolean occupancy grid of the obstacle alone.
        resolution_m: occupancy cell side, metres.
        node_resolution_m: graph node spacing, metres.
        agent_radius_m: radius of the agent's disc, metres.

    Returns:
        boolean ``(rows, cols)`` node grid, False where the disc at the node centre
        would touch the obstacle.
    """
    centre_rows, centre_cols = node_centre_cells(obstacle.shape, _node_factor(node_resolution_m, resolution_m))
    result = np.ones((len(centre_rows), len(centre_cols)), dtype=bool)
    occupied_rows = np.flatnonzero(obstacle.any(axis=1))
    occupied_cols = np.flatnonzero(obstacle.any(axis=0))
    if not len(occupied_rows):
        return result
    # beyond this many cells from every obstacle cell the clearance exceeds the radius
    margin = math.ceil(agent_radius_m / resolution_m) + 1
    low = np.maximum([occupied_rows[0] - margin, occupied_cols[0] - margin], 0)
    high = np.minimum([occupied_rows[-1] + margin + 1, occupied_cols[-1] + margin + 1], obstacle.shape)
    clearance = clearance_grid(obstacle[low[0] : high[0], low[1] : high[1]], resolution_m)
    rows_inside = (centre_rows >= low[0]) & (centre_rows < high[0])
    cols_inside = (centre_cols >= low[1]) & (centre_cols < high[1])
    window = np.ix_(centre_rows[rows_inside] - low[0], centre_cols[cols_inside] - low[1])
    result[np.ix_(rows_inside, cols_inside)] = clearance[window] >= agent_radius_m
    return result


def _node_factor(node_resolution_m: float, resolution_m: float) -> int:
    """Occupancy cells per graph-node side; raises unless the node spacing is a multiple of the cell side."""
    factor = node_resolution_m / resolution_m
    if node_resolution_m <= 0 or abs(factor - round(factor)) > 1e-6:
        raise ValueError(
            f"resolution_m must be a positive multiple of the occupancy resolution "
            f"({resolution_m} m), got {node_resolution_m}."
        )
    return int(round(factor))


def grid_graph(
    navigable: np.ndarray,
    resolution_m: float,
    connectivity: int = 8,
    links: dict[tuple[int, int], np.ndarray] | None = None,
) -> sparse.csr_matrix:
    """Sparse adjacency (edge weights in metres) of a grid restricted to navigable nodes.

    Args:
        navigable: boolean ``(rows, cols)`` grid.
        resolution_m: node spacing, metres.
        connectivity: 4 or 8. A diagonal edge is kept only if both orthogonal
            neighbours are navigable, so paths never cut a wall corner.
        links: extra edges, whatever ``navigable`` says: for an offset ``(dr, dc)``
            among ``(0, 1), (1, 0)`` and, with 8, ``(1, 1), (1, -1)``, a bool grid
            over the source nodes of that offset (rows ``0 .. rows - dr``, columns
            ``max(0, -dc) .. cols - max(0, dc)``), True where the node and its
            neighbour at the offset are joined.
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
        if links is not None and (dr, dc) in links:
            ok = ok | links[(dr, dc)]
        sources.append(index[r0:r1, c0:c1][ok])
        targets.append(index[r0 + dr : r1 + dr, c0 + dc : c1 + dc][ok])
        weights.append(np.full(int(ok.sum()), weight))
    src = np.concatenate(sources)
    dst = np.concatenate(targets)
    w = np.concatenate(weights)
    return sparse.csr_matrix((w, (src, dst)), shape=(rows * cols, rows * cols))
