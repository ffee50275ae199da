"""Demonstrations: shortest routes driven by the noise-free expert, cropped to n steps.

A demonstration is sampled from a seed: a start pose on the house's navigable
space, a far goal at least ``n`` forward steps away along the geodesic, and the
first ``n`` actions of the noise-free :class:`~envs.expert.GeodesicExpert` driving
from the start towards that goal. The route's end (where the agent must arrive
when following it) is the pose after those ``n`` actions. Frames are rendered by
the environment along the recorded poses.

:func:`drive_expert` (the noise-free expert driving towards a goal) and
:func:`demonstration_from_route` (poses and actions -> :class:`Demonstration`) are
the route logic shared with the demonstrations users give (:mod:`envs.user_demos`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from envs.expert import FORWARD_STEP_M, TURN_ANGLE_DEG, GeodesicExpert
from envs.geodesic import DistanceField
from envs.scenes import House

#: Default demonstration length (the paper crops demonstrations to 30 steps).
DEFAULT_DEMO_LENGTH = 30
#: Extra clearance (metres) a start position keeps from obstacles.
START_MARGIN_M = 0.1
#: Attempts at finding a start with a far-enough goal before giving up.
MAX_SAMPLING_ATTEMPTS = 50
#: Routes must end this many success radii from their start (no trivial episodes); short
#: demonstrations need only half their straight length, and never less than one radius.
MIN_ROUTE_FACTOR = 2.0
#: The follow protocol's minimum success radius (two forward steps), metres.
DEFAULT_SUCCESS_RADIUS_M = 2 * FORWARD_STEP_M


def default_min_route_length_m(demo_length: int, success_radius_m: float = DEFAULT_SUCCESS_RADIUS_M) -> float:
    """Shortest route (geodesic, metres) a demonstration of ``demo_length`` steps may have.

    Routes must start outside the success radius; short demonstrations cannot reach
    ``MIN_ROUTE_FACTOR`` radii, so they need only half their straight length.
    """
    return max(success_radius_m, min(MIN_ROUTE_FACTOR * success_radius_m, 0.5 * demo_length * FORWARD_STEP_M))


@dataclass
class Demonstration:
    """One demonstrated route.

    Attributes:
        house_seed: the house it was recorded in.
        poses: ``(n + 1, 3)`` poses (x m, y m, heading rad) before each action, then the end pose.
        actions: ``(n,)`` int64 actions.
        end_field: geodesic distances to the route's end.
        shortest_length_m: geodesic length from the start to the route's end.
        task: ``"follow"`` for a route as it was demonstrated, ``"homing"`` for the
            route driven back to its start (:func:`envs.homing.homing_demonstration`).
    """

    house_seed: int
    poses: np.ndarray
    actions: np.ndarray
    end_field: DistanceField
    shortest_length_m: float
    task: str = "follow"

    @property
    def length(self) -> int:
        return len(self.actions)

    @property
    def start_pose(self) -> np.ndarray:
        return self.poses[0]

    @property
    def end_xy(self) -> np.ndarray:
        return self.poses[-1, :2]


def nominal_motion(action: int | np.ndarray) -> np.ndarray:
    """Nominal (forward m, lateral m, rotation rad) of actions; STOP and unknown give 0."""
    action = np.asarray(action)
    motion = np.zeros(action.shape + (3,))
    motion[..., 0] = np.where(action == 0, FORWARD_STEP_M, 0.0)
    turn = np.deg2rad(TURN_ANGLE_DEG)
    motion[..., 2] = np.where(action == 1, turn, np.where(action == 2, -turn, 0.0))
    return motion



def wrap_angle(radians: float | np.ndarray) -> float | np.ndarray:
    """Headings wrapped into ``[-pi, pi)``, radians (every pose's heading).

    Examples:
        >>> round(float(wrap_angle(3 * np.pi / 2)), 4), round(float(wrap_angle(np.pi)), 4)
        (-1.5708, -3.1416)
    """
    return np.mod(radians + np.pi, 2 * np.pi) - np.pi

def apply_motion(house: House, poses: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply agent-frame motions ``(N, 3)`` = (forward m, lateral m, rotation rad) to ``(N, 3)`` poses.

    Translation first (along the current heading, lateral to the left), with
    collision and sliding, then rotation.

    Returns:
        new poses ``(N, 3)`` and distances travelled ``(N,)``, metres.
    """
    heading = poses[:, 2]
    c, s = np.cos(heading), np.sin(heading)
    displacement = np.stack([c * motion[:, 0] - s * motion[:, 1], s * motion[:, 0] + c * motion[:, 1]], axis=1)
    xy, travelled = house.occupancy.move_many(poses[:, :2], displacement)
    new_heading = wrap_angle(heading + motion[:, 2])
    return np.concatenate([xy, new_heading[:, None]], axis=1), travelled


def move_agents(houses: Sequence[House], poses: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """:func:`apply_motion` for agents each in its own house: ``(N, 3)`` ``poses`` are updated in place.

    The same float64 operations as :func:`apply_motion`, element by element, with each
    agent's collision check in its own house.

    Returns:
        distances travelled ``(N,)``, metres.

    Examples:
        >>> from envs.scenes import build_house
        >>> poses = np.array([[7.5, 1.5, 0.0]])
        >>> move_agents([build_house(0)], poses, nominal_motion(np.array([0]))).round(2).tolist(), poses[0, :2].round(2).tolist()
        ([0.3], [7.8, 1.5])
    """
    heading = poses[:, 2]
    c, s = np.cos(heading), np.sin(heading)
    dx = c * motion[:, 0] - s * motion[:, 1]
    dy = s * motion[:, 0] + c * motion[:, 1]
    new_heading = wrap_angle(heading + motion[:, 2])
    travelled = np.empty(len(poses))
    for index, house in enumerate(houses):
        poses[index, :2], travelled[index] = house.occupancy.move(poses[index, :2], (dx[index], dy[index]))
        poses[index, 2] = new_heading[index]
    return travelled


def sample_demonstration(
    house: House,
    rng: np.random.Generator,
    length: int = DEFAULT_DEMO_LENGTH,
    min_route_length_m: float = 0.0,
) -> Demonstration:
    """Sample a demonstration of ``length`` steps in ``house``.

    Args:
        house: the house.
        rng: the generator that fixes start, heading and goal.
        length: number of demonstrated steps n (> 0).
        min_route_length_m: routes whose end is not farther than this (geodesic,
            metres) from their start are re-drawn (e.g. a route of turns only).

    Raises:
        ValueError: on a non-positive ``length``.
        RuntimeError: if the house has no pair of points far enough apart.

    Examples:
        >>> from envs.scenes import build_house
        >>> demo = sample_demonstration(build_house(0), np.random.default_rng(0), length=10)
        >>> demo.actions.shape, demo.poses.shape
        ((10,), (11, 3))
    """
    if not isinstance(length, (int, np.integer)) or length <= 0:
        raise ValueError(f"length must be a positive int (steps), got {length!r}.")
    starts, nodes, node_xy = _route_candidates(house)
    for _ in range(MAX_SAMPLING_ATTEMPTS):
        demo = _sample_route(house, rng, length, starts, nodes, node_xy)
        if demo.shortest_length_m > min_route_length_m:
            return demo
    raise RuntimeError(
        f"house {house.seed}: no route of {length} steps ends more than {min_route_length_m} m from its start."
    )


def _route_candidates(house: House) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start nodes, navigable nodes, their positions) of a house, computed once per house object."""
    cached = getattr(house, "_route_candidates", None)
    if cached is None:
        graph = house.graph
        occupancy = house.occupancy
        nodes = np.flatnonzero(graph.navigable.ravel())
        node_xy = graph.node_xy(nodes)
        roomy = occupancy.clearance_many(node_xy) >= occupancy.agent_radius_m + START_MARGIN_M
        starts = nodes[roomy] if roomy.any() else nodes
        for array in (starts, nodes, node_xy):
            array.setflags(write=False)
        cached = (starts, nodes, node_xy)
        house._route_candidates = cached  # a plain attribute on the (cached) House
    return cached


def _sample_route(
    house: House, rng: np.random.Generator, length: int, starts: np.ndarray, nodes: np.ndarray, node_xy: np.ndarray
) -> Demonstration:
    graph = house.graph
    min_goal_distance = length * FORWARD_STEP_M + 1.0
    for _ in range(MAX_SAMPLING_ATTEMPTS):
        start_xy = graph.node_xy(int(rng.choice(starts)))
        # geodesic >= straight-line distance, so this needs no graph search
        far = nodes[np.hypot(*(node_xy - start_xy).T) >= min_goal_distance]
        if len(far):
            break
    else:
        raise RuntimeError(
            f"house {house.seed} has no two points {min_goal_distance:.1f} m apart; use a shorter demo length."
        )
    goal_xy = graph.node_xy(int(rng.choice(far)))
    heading = rng.uniform(-np.pi, np.pi)
    start_pose = np.array([start_xy[0], start_xy[1], heading])
    poses, actions = drive_expert(house, graph.distance_field(goal_xy), start_pose, length)
    return demonstration_from_route(house, poses, actions)


def drive_expert(
    house: House, field: DistanceField, start_pose: np.ndarray, max_steps: int, arrival_radius_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Drive the noise-free :class:`~envs.expert.GeodesicExpert` from ``start_pose`` towards ``field``'s goal.

    Each step takes the expert's action at the current pose and applies its nominal
    motion (:func:`nominal_motion`, :func:`apply_motion`: collisions and sliding).

    Args:
        house: the house.
        field: geodesic distances to the goal (``house.graph.distance_field(goal_xy)``).
        start_pose: (x m, y m, heading rad).
        max_steps: steps driven at most.
        arrival_radius_m: if given, stop as soon as the pose is within this distance
            (geodesic, metres) of the goal; otherwise drive exactly ``max_steps`` steps.

    Returns:
        ``(k + 1, 3)`` poses (the start, then after each action) and ``(k,)`` int64
        actions, with ``k <= max_steps`` steps.

    Examples:
        >>> from envs.scenes import build_house
        >>> house = build_house(0)
        >>> field = house.graph.distance_field(np.array([10.5, 1.5]))
        >>> poses, actions = drive_expert(house, field, np.array([7.5, 1.5, 0.0]), 30, arrival_radius_m=0.3)
        >>> actions.tolist(), poses[-1].round(2).tolist()
        ([0, 0, 0, 0, 0, 0, 0, 0, 0], [10.2, 1.5, 0.0])
    """
    expert = GeodesicExpert(house.occupancy, field)
    poses = np.zeros((max_steps + 1, 3))
    poses[0] = start_pose
    actions = np.zeros(max_steps, dtype=np.int64)
    for step in range(max_steps):
        if arrival_radius_m is not None and field.at(poses[step, :2]) <= arrival_radius_m:
            return poses[: step + 1], actions[:step]
        actions[step] = expert.action(poses[step])
        poses[step + 1] = apply_motion(house, poses[step : step + 1], nominal_motion(actions[step : step + 1]))[0][0]
    return poses, actions


def demonstration_from_route(house: House, poses: np.ndarray, actions: np.ndarray) -> Demonstration:
    """The :class:`Demonstration` of a driven route: its end's distance field and its shortest length.

    Args:
        house: the house the route was driven in.
        poses: ``(n + 1, 3)`` poses (x m, y m, heading rad): the start, then after each action.
        actions: ``(n,)`` actions.

    Examples:
        >>> from envs.scenes import build_house
        >>> house = build_house(0)
        >>> poses = np.array([[7.5, 1.5, 0.0], [7.8, 1.5, 0.0], [8.1, 1.5, 0.0]])
        >>> demo = demonstration_from_route(house, poses, np.array([0, 0]))
        >>> demo.length, demo.end_xy.tolist(), bool(0.5 < demo.shortest_length_m < 0.7)
        (2, [8.1, 1.5], True)
    """
    end_field = house.graph.distance_field(poses[-1, :2])
    return Demonstration(
        house_seed=house.seed,
        poses=poses,
        actions=np.asarray(actions, dtype=np.int64),
        end_field=end_field,
        shortest_length_m=end_field.at(poses[0, :2]),
    )
