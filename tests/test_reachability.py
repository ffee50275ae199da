"""Every pose the collision model lets the agent reach has a finite geodesic distance.

Property test of envs.geometry over 1,000 houses (seeds of every split and seeds
outside them; 200 of them unless ``pytest --full-samples``): random walks and wall-hugging walks driven by the environment's own
:meth:`~envs.geometry.OccupancyMap.move` must only reach positions whose distance
to a goal in the same connected free region is finite, and each step may change
that distance by little more than the distance travelled (so a reward is never
``inf - inf`` and never jumps). Geometry only: no MuJoCo model is compiled and
nothing is rendered. Plus the reported case (issue #12): house 700009, where a
slide along a wall used to end at ``inf``.
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from scipy import ndimage

from envs import house_mesh
from envs.geodesic import DistanceField, GeodesicGraph
from envs.geometry import GEODESIC_RESOLUTION_M, OccupancyMap
from envs.scenes import House, build_house, split_seeds

logger = logging.getLogger(__name__)

#: Houses checked per group: seeds of the three splits and seeds outside them
#: (``pytest --full-samples``; by default every :data:`SAMPLE_STRIDE`-th seed of each).
SEED_GROUPS = {
    "train": split_seeds("train", 300),
    "val": split_seeds("val", 100),
    "test": split_seeds("test", 100),
    "outside": list(range(700_000, 700_500)),
}
SAMPLE_STRIDE = 5
#: Steps of each walk.
WALK_STEPS = 120
#: Forward step lengths drawn uniformly in this range, metres (nominal 0.3 m, noisy).
FORWARD_RANGE_M = (0.24, 0.36)
#: Nominal turn and its noise, degrees.
TURN_DEG = 20.0
TURN_NOISE_DEG = 5.0
#: Probability of a forward step in a random walk (the rest are turns).
FORWARD_PROBABILITY = 0.6
#: Heading noise added at every wall-hugging step, degrees (standard deviation).
HUG_HEADING_NOISE_DEG = 4.0
#: A wall-hugging walk turns away only once a step travels less than this, metres (stuck in a corner).
STUCK_M = 0.02
#: Range of the turn (either side) taken when stuck, degrees.
STUCK_TURN_DEG = (20.0, 100.0)
#: Largest change of distance-to-goal in one step beyond the distance travelled, metres:
#: the offsets to two node centres (half a node diagonal each) and one diagonal hop.
STEP_SLACK_M = 2 * GEODESIC_RESOLUTION_M * math.sqrt(2.0)


@pytest.fixture
def no_compiling(monkeypatch):
    """Geometry only: compiling a house's MuJoCo model fails the test."""

    def refuse(*args, **kwargs):
        raise AssertionError("the geometry checks compiled the MuJoCo model")

    monkeypatch.setattr(house_mesh, "compile_house", refuse)


def _free_labels(occupancy: OccupancyMap) -> np.ndarray:
    """Connected free regions: 8-connected components of the cells where the disc fits.

    One sub-step of :meth:`OccupancyMap.move` moves at most one cell along each axis
    onto a free cell, so whatever a walk reaches stays in its start's region.
    """
    return ndimage.label(occupancy.free, structure=np.ones((3, 3)))[0]


def _cells(occupancy: OccupancyMap, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of positions with :meth:`OccupancyMap.move`'s own rounding."""
    inverse = 1.0 / occupancy.resolution_m
    return (xy[:, 1] * inverse).astype(np.int64), (xy[:, 0] * inverse).astype(np.int64)


def _random_walk(occupancy: OccupancyMap, start_xy: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Noisy forward / turn actions. Returns ``(steps + 1, 2)`` positions and ``(steps,)`` distances travelled."""
    positions = np.empty((WALK_STEPS + 1, 2))
    travelled = np.zeros(WALK_STEPS)
    positions[0] = start_xy
    heading = rng.uniform(-math.pi, math.pi)
    forward = rng.random(WALK_STEPS) < FORWARD_PROBABILITY
    lengths = rng.uniform(*FORWARD_RANGE_M, size=WALK_STEPS)
    turns = np.deg2rad(rng.choice([-TURN_DEG, TURN_DEG], size=WALK_STEPS) + rng.normal(0.0, TURN_NOISE_DEG, WALK_STEPS))
    xy = positions[0]
    for step in range(WALK_STEPS):
        if forward[step]:
            xy, travelled[step] = occupancy.move(xy, lengths[step] * np.array([math.cos(heading), math.sin(heading)]))
        else:
            heading += turns[step]
        positions[step + 1] = xy
    return positions, travelled


def _wall_hugging_walk(
    occupancy: OccupancyMap, start_xy: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Forward steps that keep their heading, so they press into walls and slide along them.

    The heading only wobbles a little, so once a wall is hit every step pushes into
    it and slides (into corners and through gaps one cell wide); when a step hardly
    moves the walk turns by a random angle and carries on. Returns like :func:`_random_walk`.
    """
    positions = np.empty((WALK_STEPS + 1, 2))
    travelled = np.zeros(WALK_STEPS)
    positions[0] = start_xy
    heading = rng.uniform(-math.pi, math.pi)
    lengths = rng.uniform(*FORWARD_RANGE_M, size=WALK_STEPS)
    wobble = np.deg2rad(rng.normal(0.0, HUG_HEADING_NOISE_DEG, WALK_STEPS))
    escapes = np.deg2rad(rng.uniform(*STUCK_TURN_DEG, WALK_STEPS) * rng.choice([-1.0, 1.0], WALK_STEPS))
    xy = positions[0]
    for step in range(WALK_STEPS):
        heading += wobble[step]
        xy, travelled[step] = occupancy.move(xy, lengths[step] * np.array([math.cos(heading), math.sin(heading)]))
        if travelled[step] < STUCK_M:
            heading += escapes[step]
        positions[step + 1] = xy
    return positions, travelled


def _check_field(
    seed: int, field: DistanceField, labels: np.ndarray, walks: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    """Finite distances at every walked position and every free cell of the goal's region; bounded steps."""
    occupancy = field.graph.occupancy
    goal_cell = _cells(occupancy, field.goal_xy[None])
    goal_label = labels[goal_cell[0][0], goal_cell[1][0]]
    assert goal_label > 0, f"house {seed}: goal {field.goal_xy} is not in free space"
    rows, cols = np.nonzero(labels == goal_label)
    centres = (np.stack([cols, rows], axis=1) + 0.5) * occupancy.resolution_m
    bad = ~np.isfinite(field.at_many(centres))
    assert not bad.any(), f"house {seed}, goal {field.goal_xy}: {bad.sum()} free cells at inf, e.g. {centres[bad][:3]}"
    for positions, travelled in walks:
        if labels[_cells(occupancy, positions[:1])][0] != goal_label:
            continue
        distances = field.at_many(positions)
        bad = ~np.isfinite(distances)
        assert not bad.any(), f"house {seed}, goal {field.goal_xy}: walked to {positions[bad][0]}, distance inf"
        scalar = np.array([field.at(xy) for xy in positions])
        assert np.allclose(scalar, distances), f"house {seed}: at() and at_many() disagree"
        jumps = np.abs(np.diff(distances)) - travelled
        assert jumps.max() <= STEP_SLACK_M, (
            f"house {seed}, goal {field.goal_xy}: distance changed {jumps.max():.3f} m more than travelled "
            f"at {positions[int(np.argmax(jumps)) + 1]}"
        )


def _check_house(seed: int) -> None:
    # build_house's cache is left alone (1,000 houses would evict the other tests' houses)
    house: House = build_house.__wrapped__(seed)
    occupancy, graph = house.occupancy, house.graph
    labels = _free_labels(occupancy)
    rng = np.random.default_rng([seed, 12])
    free_rows, free_cols = np.nonzero(occupancy.free)
    pick = int(rng.integers(len(free_rows)))
    random_start = (np.array([free_cols[pick], free_rows[pick]]) + 0.5) * occupancy.resolution_m
    walks = [
        _random_walk(occupancy, house.spawn_xy, rng),
        _wall_hugging_walk(occupancy, house.spawn_xy, rng),
        _wall_hugging_walk(occupancy, random_start, rng),
    ]
    for positions, _ in walks:
        start_label = labels[_cells(occupancy, positions[:1])][0]
        assert (labels[_cells(occupancy, positions)] == start_label).all(), f"house {seed}: a walk left its free region"
    # goals as the env has them: a navigable node (a route's goal) and a walked pose (a route's end)
    navigable = np.flatnonzero(graph.navigable.ravel())
    goals = [graph.node_xy(int(rng.choice(navigable))), walks[1][0][-1]]
    for goal_xy in goals:
        _check_field(seed, graph.distance_field(goal_xy), labels, walks)


@pytest.mark.parametrize("group", sorted(SEED_GROUPS))
def test_every_reached_pose_has_a_finite_distance(group: str, full_samples: bool, no_compiling) -> None:
    seeds = SEED_GROUPS[group] if full_samples else SEED_GROUPS[group][::SAMPLE_STRIDE]
    for seed in seeds:
        _check_house(seed)
    logger.info("%s: %d houses checked", group, len(seeds))


def test_enough_houses_inside_and_outside_the_splits() -> None:
    all_seeds = [seed for seeds in SEED_GROUPS.values() for seed in seeds]
    assert len(set(all_seeds)) >= 1000
    assert len(SEED_GROUPS["outside"]) >= 100 and min(SEED_GROUPS["outside"]) >= 700_000


def test_house_700009_slide_along_a_wall_keeps_a_finite_distance() -> None:
    """Issue #12: a forward step slid ~0.1 m along a wall into a pose the old field called inf.

    The step from (7.165, 7.854) at 189 degrees crosses a one-cell-wide diagonal gap
    between two obstacles that the node-centre test of the old graph did not join.
    """
    house = build_house(700009)
    occupancy, graph = house.occupancy, house.graph
    start = np.array([7.165, 7.854])
    heading = math.radians(189.0)
    end, travelled = occupancy.move(start, 0.36 * np.array([math.cos(heading), math.sin(heading)]))
    assert np.allclose(end, [7.076, 7.798], atol=0.002) and 0.1 < travelled < 0.15
    assert occupancy.is_free(end)
    for goal_xy in (np.array([4.75, 9.35]), house.spawn_xy):
        field = graph.distance_field(goal_xy)
        before, after = field.at(start), field.at(end)
        assert math.isfinite(before) and math.isfinite(after)
        assert abs(after - before) <= travelled + STEP_SLACK_M
        assert np.allclose(field.at_many(np.stack([start, end])), [before, after])
    assert field.at(start) == pytest.approx(10.58, abs=0.01)


def test_building_the_house_compiles_no_model(no_compiling) -> None:
    house = build_house.__wrapped__(700_009)
    assert house.occupancy is not None and house.graph.distance_field(house.spawn_xy) is not None
    assert not hasattr(house, "model")  # a layout knows nothing of MuJoCo


def test_graph_joins_free_cells_that_touch_diagonally() -> None:
    """Two regions joined only by a one-cell diagonal gap between two corners are one region for Dijkstra too.

    The disc fits at no node centre in the gap and the old graph never cut a
    corner, so it had no path through; the collision model passes (a sub-step may
    move one cell along both axes). The gap is the house-700009 case in miniature.
    """
    occupied = np.zeros((60, 60), dtype=bool)  # 3 m x 3 m
    occupied[[0, -1], :] = True
    occupied[:, [0, -1]] = True
    occupied[30:, :30] = True  # x < 1.5 m, y > 1.5 m
    occupied[:24, 36:] = True  # x > 1.8 m, y < 1.2 m: corners 0.42 m apart, the disc 0.4 m wide
    occupancy = OccupancyMap(occupied, 0.05, 0.2)
    assert ndimage.label(occupancy.free)[1] > 1 and _free_labels(occupancy).max() == 1  # joined diagonally only
    start = np.array([1.15, 0.85])
    end, travelled = occupancy.move(start, np.array([1.0, 1.0]))
    assert np.allclose(end, start + 1.0) and travelled == pytest.approx(math.sqrt(2.0))
    graph = GeodesicGraph(occupancy, 0.1)
    assert graph.components() == 1
    field = graph.distance_field(np.array([2.5, 2.5]))
    assert math.isfinite(field.at(start)) and math.isfinite(field.at(np.array([0.5, 0.5])))
    # straight through the gap: the distance is about the straight line, not a detour
    assert field.at(start) == pytest.approx(np.hypot(*(np.array([2.5, 2.5]) - start)), abs=0.25)
