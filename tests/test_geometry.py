"""Tests for envs.geometry: geodesic distances against brute force, collisions, sliding."""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from scipy.sparse import csgraph

from envs.geodesic import GeodesicGraph, grid_graph
from envs.geometry import OccupancyMap
from envs.scenes import build_house


def bfs_steps(navigable: np.ndarray, source: tuple[int, int]) -> np.ndarray:
    """Brute-force 4-connected BFS in steps (-1 unreachable)."""
    steps = np.full(navigable.shape, -1)
    steps[source] = 0
    queue = deque([source])
    while queue:
        r, c = queue.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nr, nc = r + dr, c + dc
            if 0 <= nr < navigable.shape[0] and 0 <= nc < navigable.shape[1] and navigable[nr, nc] and steps[nr, nc] < 0:
                steps[nr, nc] = steps[r, c] + 1
                queue.append((nr, nc))
    return steps


def bellman_ford(navigable: np.ndarray, source: tuple[int, int], resolution: float) -> np.ndarray:
    """Brute-force 8-connected shortest paths (no corner cutting) by repeated relaxation."""
    rows, cols = navigable.shape
    dist = np.full(navigable.shape, np.inf)
    dist[source] = 0.0
    moves = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    changed = True
    while changed:
        changed = False
        for r in range(rows):
            for c in range(cols):
                if not navigable[r, c] or not np.isfinite(dist[r, c]):
                    continue
                for dr, dc in moves:
                    nr, nc = r + dr, c + dc
                    if not (0 <= nr < rows and 0 <= nc < cols) or not navigable[nr, nc]:
                        continue
                    if dr and dc and not (navigable[r + dr, c] and navigable[r, c + dc]):
                        continue
                    candidate = dist[r, c] + resolution * np.hypot(dr, dc)
                    if candidate < dist[nr, nc] - 1e-12:
                        dist[nr, nc] = candidate
                        changed = True
    return dist


@pytest.mark.parametrize("seed", range(6))
def test_geodesic_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    navigable = rng.random((9, 11)) > 0.3
    navigable[0, 0] = True
    steps = bfs_steps(navigable, (0, 0))
    four = csgraph.dijkstra(grid_graph(navigable, 0.1, connectivity=4), directed=False, indices=0).reshape(navigable.shape)
    assert np.allclose(np.where(steps >= 0, steps * 0.1, np.inf), four)
    eight = csgraph.dijkstra(grid_graph(navigable, 0.1, connectivity=8), directed=False, indices=0).reshape(navigable.shape)
    assert np.allclose(bellman_ford(navigable, (0, 0), 0.1), eight)


def test_connectivity_must_be_4_or_8():
    with pytest.raises(ValueError, match="connectivity must be 4 or 8"):
        grid_graph(np.ones((3, 3), dtype=bool), 0.1, connectivity=6)


def test_distance_field_in_a_corridor():
    grid = np.zeros((40, 100), dtype=bool)  # 2 m x 5 m box with walls around
    grid[[0, -1], :] = True
    grid[:, [0, -1]] = True
    graph = GeodesicGraph(OccupancyMap(grid, 0.05, 0.2), 0.1)
    field = graph.distance_field(np.array([4.55, 1.05]))
    assert field.at(np.array([1.05, 1.05])) == pytest.approx(3.5, abs=0.11)
    assert np.allclose(field.at_many(np.array([[1.05, 1.05], [4.55, 1.05]])), [field.at(np.array([1.05, 1.05])), field.at(np.array([4.55, 1.05]))])


def test_random_motions_never_enter_walls():
    house = build_house(2)
    occupancy = house.occupancy
    rng = np.random.default_rng(0)
    position = house.spawn_xy.copy()
    for _ in range(3000):
        displacement = rng.normal(0, 0.6, size=2)  # includes steps far longer than a cell
        position, travelled = occupancy.move(position, displacement)
        assert occupancy.clearance(position) >= occupancy.agent_radius_m
        assert travelled <= np.hypot(*displacement) + 1e-9
        width, depth = house.size_m
        assert 0 < position[0] < width and 0 < position[1] < depth


def test_sliding_along_a_wall():
    grid = np.zeros((40, 40), dtype=bool)
    grid[:4, :] = True  # wall along y < 0.2 m
    occupancy = OccupancyMap(grid, 0.05, 0.2)
    start = np.array([1.0, 0.45])
    end, travelled = occupancy.move(start, np.array([0.3, -0.3]))  # diagonal into the wall
    assert end[0] > start[0] + 0.25  # slid along x
    assert occupancy.is_free(end)
    assert 0.25 < travelled < 0.45
