"""Demonstrations that users give, and the env's playlist of given demonstrations.

A user shows a route in one of two ways:

* a start pose and actions (:func:`demonstration_from_actions`, or step by step
  with a :class:`RouteRecorder`, as the keyboard of ``recipes/teach.py`` does):
  every action is driven noise-free with the simulator's motion
  (:func:`~envs.demos.apply_motion`);
* waypoints on the top-down map (:func:`demonstration_from_waypoints`): the
  noise-free expert (:func:`~envs.demos.drive_expert`) plans from each waypoint to
  the next along the house's geodesic graph, as it plans sampled demonstrations.

Both end in :func:`~envs.demos.demonstration_from_route`, as sampled
demonstrations do, so a given route is a :class:`~envs.demos.Demonstration` like
any other: poses, actions, the end's distance field, the shortest length.

Units: positions in metres in the house frame (the top-down map's axes), start
headings in **degrees** (0 = +x, counter-clockwise; :attr:`Demonstration.poses
<envs.demos.Demonstration.poses>` store radians). Steps and waypoints are numbered
from 1 in error messages.

Typed input (a command line's text) is read by :func:`parse_pose` (``"x,y,heading"``),
:func:`parse_waypoints` (``"x,y;x,y;..."``) and :func:`parse_actions` (``"FFLR..."``).

A route that is refused raises :class:`RouteError` (a ``ValueError``) naming the
step or waypoint and why: a start or waypoint outside the house or inside a wall
or furniture, a forward step that runs into a wall (the collision model shortens
it by more than :data:`~envs.expert.WALL_CONTACT_TOLERANCE_M`), waypoints the planner cannot
join, or a route whose end lies within the success radius of its start (geodesic;
an agent would succeed without moving).

Lengths: Table 1's policies follow demonstrations of exactly their ``demo_length`` n (30);
``routes-spf`` (trained on 10 to 100 steps) follows each at its own length.
With ``length=n``, an action route must have exactly n actions (a clear error names
n otherwise); a waypoint route is planned and then cropped to its first n steps,
as :func:`~envs.demos.sample_demonstration` crops planned routes (an error if the
plan is shorter than n). Without ``length`` a route keeps its own length.

The env plays given demonstrations with ``PathFollowEnv(..., demonstrations=[...])``
(see :class:`~envs.playlist.DemonstrationPlaylist`) or
``env.reset(demonstration=demo)``; with ``task="homing"`` it plays their homing
demonstrations (:mod:`envs.homing`).

Examples:
    >>> demo = demonstration_from_actions(0, (7.5, 1.5, 0.0), "FFFFLF")
    >>> demo.length, demo.end_xy.round(2).tolist()
    (6, [8.98, 1.6])
    >>> demonstration_from_actions(0, (7.5, 1.5, 180.0), "FFF")
    Traceback (most recent call last):
    ...
    envs.user_demos.RouteError: step 2 of 3 (F, forward) from (7.20, 1.50) heading 180 deg runs into a wall or furniture: it moves 0.00 m of 0.30 m.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from envs.demos import (
    DEFAULT_SUCCESS_RADIUS_M,
    Demonstration,
    apply_motion,
    demonstration_from_route,
    drive_expert,
    nominal_motion,
    wrap_angle,
)
from envs.expert import FORWARD, FORWARD_STEP_M, NUM_HEADINGS, TURN_LEFT, TURN_RIGHT, WALL_CONTACT_TOLERANCE_M
from envs.scenes import House, build_house
from envs.specs import NUM_DEMO_ACTIONS

logger = logging.getLogger(__name__)

#: Action letters of a typed route (case-insensitive): F forward, L turn left, R turn right.
ACTION_LETTERS: dict[str, int] = {"F": FORWARD, "L": TURN_LEFT, "R": TURN_RIGHT}
#: The letter and the name of each demonstration action, for messages.
ACTION_LABELS = {FORWARD: "F, forward", TURN_LEFT: "L, turn left", TURN_RIGHT: "R, turn right"}
#: A waypoint counts as reached when the planned route comes this close to it
#: (geodesic, metres): one forward step, the planner's resolution.
WAYPOINT_RADIUS_M = FORWARD_STEP_M
#: Steps the planner may spend on a leg beyond the straight count (a full turn on
#: the spot plus slack), before the waypoint counts as unreachable.
LEG_SLACK_STEPS = 2 * NUM_HEADINGS
#: Shortest route (geodesic, metres) a given demonstration may have: the follow
#: protocol's minimum success radius, so that its start is outside the radius.
MIN_USER_ROUTE_M = DEFAULT_SUCCESS_RADIUS_M
#: Cells of a typed pose "x,y,heading": metres, metres, degrees.
POSE_FIELDS = 3


class RouteError(ValueError):
    """A route that cannot be a demonstration; the message names the step or waypoint and why.

    Examples:
        >>> try:
        ...     demonstration_from_actions(0, (7.5, 1.5, 0.0), "FFX")
        ... except RouteError as err:
        ...     print(type(err).__name__, isinstance(err, ValueError))
        RouteError True
    """



def check_exact_length(steps: int, length: int | None) -> None:
    """Refuse a route of ``steps`` steps where ``length`` (the policy's ``demo_length``) are required.

    Raises:
        RouteError: naming both, unless ``length`` is ``None`` or equal to ``steps``.

    Examples:
        >>> check_exact_length(24, None), check_exact_length(30, 30)
        (None, None)
        >>> check_exact_length(24, 30)
        Traceback (most recent call last):
        ...
        envs.user_demos.RouteError: the route has 24 steps; demonstrations must have exactly 30 steps here (length=30): give 30 actions.
    """
    if length is not None and steps != length:
        raise RouteError(
            f"the route has {steps} steps; demonstrations must have exactly {length} steps here "
            f"(length={length}): give {length} actions."
        )

def house_of(house: House | int) -> House:
    """``house`` itself, or the house of a seed (:func:`~envs.scenes.build_house`)."""
    return house if isinstance(house, House) else build_house(house)


def pose_from_degrees(start: Sequence[float]) -> np.ndarray:
    """``(x m, y m, heading deg)`` -> ``(x m, y m, heading rad)`` as the poses of a demonstration store them.

    Examples:
        >>> pose_from_degrees((1.0, 2.0, 90.0)).round(4).tolist()
        [1.0, 2.0, 1.5708]
    """
    values = np.asarray(start, dtype=np.float64).reshape(-1)
    if values.shape != (POSE_FIELDS,) or not np.isfinite(values).all():
        raise RouteError(f"start must be three finite numbers (x m, y m, heading deg), got {list(start)!r}.")
    return np.array([values[0], values[1], wrap_angle(math.radians(values[2]))])


def default_start(house: House | int) -> tuple[float, float, float]:
    """A start (x m, y m, heading deg) for routes given without one: the house's spawn point, facing +x."""
    xy = house_of(house).spawn_xy
    return float(xy[0]), float(xy[1]), 0.0


def parse_actions(actions: str | Sequence[int]) -> np.ndarray:
    """Actions from letters (``"FFLR"``; case, spaces and commas ignored) or from ints (0 F, 1 L, 2 R).

    Raises:
        RouteError: a letter or value that is not an action, naming its position (from 1).

    Examples:
        >>> parse_actions("ff l,R").tolist()
        [0, 0, 1, 2]
        >>> parse_actions("FFX")
        Traceback (most recent call last):
        ...
        envs.user_demos.RouteError: action 3 is 'X'; actions are F (forward), L (turn left), R (turn right).
    """
    if isinstance(actions, str):
        letters = [c for c in actions.upper() if not c.isspace() and c != ","]
        for position, letter in enumerate(letters, start=1):
            if letter not in ACTION_LETTERS:
                raise RouteError(
                    f"action {position} is {letter!r}; actions are F (forward), L (turn left), R (turn right)."
                )
        return np.array([ACTION_LETTERS[c] for c in letters], dtype=np.int64)
    values = np.asarray(actions).reshape(-1)
    for position, value in enumerate(values.tolist(), start=1):
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < NUM_DEMO_ACTIONS:
            raise RouteError(f"action {position} is {value!r}; actions are 0 (forward), 1 (turn left), 2 (turn right).")
    return values.astype(np.int64)


def parse_numbers(text: str, count: int, what: str) -> tuple[float, ...]:
    """``count`` finite comma-separated numbers typed by a user (``"7.5, 1.5,90"``).

    Args:
        text: the numbers, comma-separated (spaces ignored).
        count: how many there must be.
        what: how the message names the input (``"--start (x m, y m, heading deg)"``).

    Raises:
        RouteError: not ``count`` finite numbers; the message names ``what`` and the form.

    Examples:
        >>> parse_numbers("7.5, 1.5,90", 3, "--start (x,y,heading)")
        (7.5, 1.5, 90.0)
        >>> parse_numbers("7.5,1.5", 3, "start")
        Traceback (most recent call last):
        ...
        envs.user_demos.RouteError: start: expected 3 comma-separated numbers, got '7.5,1.5'.
    """
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise RouteError(f"{what}: expected {count} comma-separated numbers, got {text!r}.")
    return values


def parse_pose(text: str, what: str = "start (x m, y m, heading deg)") -> tuple[float, float, float]:
    """A typed start pose ``"x,y,heading"`` (metres, metres, degrees) -> ``(x, y, heading deg)``.

    Raises:
        RouteError: not three finite numbers, naming ``what`` (:func:`parse_numbers`).

    Examples:
        >>> parse_pose("7.5,1.5,0")
        (7.5, 1.5, 0.0)
    """
    x, y, heading = parse_numbers(text, POSE_FIELDS, what)
    return x, y, heading


def parse_waypoints(text: str, what: str = "waypoints") -> list[tuple[float, float]]:
    """Typed waypoints ``"x,y;x,y;..."`` (metres) -> a list of points; empty items are skipped.

    Raises:
        RouteError: a point that is not two finite numbers, named ``<what> point <i>`` (from 1).

    Examples:
        >>> parse_waypoints("7.5,1.5; 9.5,1.5")
        [(7.5, 1.5), (9.5, 1.5)]
    """
    return [parse_numbers(p, 2, f"{what} point {i}") for i, p in enumerate(text.split(";"), 1) if p.strip()]


def check_position(house: House, xy: Sequence[float], what: str) -> None:
    """Raise :class:`RouteError` unless the agent's disc fits at ``xy`` (metres) inside the house.

    Args:
        house: the house.
        xy: the position, metres.
        what: how the message names the position (``"start"``, ``"waypoint 2"``).

    Examples:
        >>> check_position(build_house(0), (7.5, 1.5), "start")
        >>> check_position(build_house(0), (16.0, 1.5), "waypoint 2")
        Traceback (most recent call last):
        ...
        envs.user_demos.RouteError: waypoint 2 (16.00, 1.50) is outside the house: x and y must lie in [0, 15) m and [0, 15) m.
    """
    x, y = float(xy[0]), float(xy[1])
    width, depth = house.size_m
    if not (0.0 <= x < width and 0.0 <= y < depth):
        raise RouteError(
            f"{what} ({x:.2f}, {y:.2f}) is outside the house: x and y must lie in [0, {width:g}) m and [0, {depth:g}) m."
        )
    occupancy = house.occupancy
    clearance = occupancy.clearance(np.array([x, y]))
    if clearance < occupancy.agent_radius_m:
        raise RouteError(
            f"{what} ({x:.2f}, {y:.2f}) is inside a wall or furniture: the agent's disc "
            f"(radius {occupancy.agent_radius_m:g} m) has {max(clearance, 0.0):.2f} m of clearance there."
        )


def _check_length(route_length_m: float, steps: int, min_route_length_m: float) -> None:
    if route_length_m <= min_route_length_m:
        raise RouteError(
            f"the route is too short: after its {steps} step(s) it ends {route_length_m:.2f} m (geodesic) from its "
            f"start, not farther than the success radius {min_route_length_m:.2f} m, so an agent would succeed "
            "without moving; add forward steps."
        )


class RouteRecorder:
    """A route built action by action, each checked as it is taken (the keyboard's model).

    Args:
        house: the house (or its seed).
        start: ``(x m, y m, heading deg)``.
        max_steps: the most actions the route may hold (``None``: no limit).
        contact_tolerance_m: a forward step may lose this much of its length to a glancing
            contact (metres; default :data:`~envs.expert.WALL_CONTACT_TOLERANCE_M`); a step shortened
            more runs into a wall.

    Raises:
        RouteError: a start outside the house or inside a wall or furniture.

    Examples:
        >>> recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=30)
        >>> recorder.step(0).round(2).tolist(), recorder.length
        ([7.8, 1.5, 0.0], 1)
        >>> recorder.undo(), recorder.length
        (True, 0)
    """

    def __init__(
        self,
        house: House | int,
        start: Sequence[float],
        max_steps: int | None = None,
        *,
        contact_tolerance_m: float = WALL_CONTACT_TOLERANCE_M,
    ) -> None:
        if not 0.0 <= contact_tolerance_m < FORWARD_STEP_M:
            raise ValueError(
                f"contact_tolerance_m must be in [0, {FORWARD_STEP_M}) metres (a forward step's length), got {contact_tolerance_m!r}."
            )
        self.contact_tolerance_m = float(contact_tolerance_m)
        self.house = house_of(house)
        pose = pose_from_degrees(start)
        check_position(self.house, pose[:2], "start")
        self.max_steps = max_steps
        self._poses = [pose]
        self._actions: list[int] = []

    @property
    def length(self) -> int:
        """Actions recorded so far."""
        return len(self._actions)

    @property
    def pose(self) -> np.ndarray:
        """The current pose (x m, y m, heading rad)."""
        return self._poses[-1]

    @property
    def poses(self) -> np.ndarray:
        """``(length + 1, 3)`` poses: the start, then after each action."""
        return np.stack(self._poses)

    @property
    def actions(self) -> np.ndarray:
        """``(length,)`` int64 actions."""
        return np.array(self._actions, dtype=np.int64)

    def step(self, action: int, total: int | None = None) -> np.ndarray:
        """Take ``action`` (0 forward, 1 left, 2 right) from the current pose; returns the new pose.

        Args:
            action: the action.
            total: the route's full length, for messages (``step 3 of 12``).

        Raises:
            RouteError: not an action, the route is full, or a forward step that leaves
                the house or runs into a wall or furniture. The route is left unchanged.
        """
        number = f"step {self.length + 1}" + (f" of {total}" if total is not None else "")
        if isinstance(action, bool) or not isinstance(action, (int, np.integer)) or action not in ACTION_LABELS:
            raise RouteError(f"{number}: {action!r} is not an action; actions are 0 (forward), 1 (turn left), 2 (turn right).")
        action = int(action)
        if self.max_steps is not None and self.length >= self.max_steps:
            raise RouteError(f"{number}: the route already has {self.max_steps} steps, the most it may have.")
        pose = self.pose
        new_pose, travelled = apply_motion(self.house, pose[None], nominal_motion(np.array([action])))
        where = f"from ({pose[0]:.2f}, {pose[1]:.2f}) heading {math.degrees(pose[2]) % 360:.0f} deg"
        if action == FORWARD:
            target = pose[:2] + FORWARD_STEP_M * np.array([math.cos(pose[2]), math.sin(pose[2])])
            width, depth = self.house.size_m
            if not (0.0 <= target[0] < width and 0.0 <= target[1] < depth):
                raise RouteError(f"{number} ({ACTION_LABELS[action]}) {where} leaves the house.")
            if travelled[0] < FORWARD_STEP_M - self.contact_tolerance_m:
                raise RouteError(
                    f"{number} ({ACTION_LABELS[action]}) {where} runs into a wall or furniture: "
                    f"it moves {travelled[0]:.2f} m of {FORWARD_STEP_M:.2f} m."
                )
        self._poses.append(new_pose[0])
        self._actions.append(int(action))
        return new_pose[0]

    def undo(self) -> bool:
        """Drop the last action; ``False`` when there is none."""
        if not self._actions:
            return False
        self._actions.pop()
        self._poses.pop()
        return True

    def demonstration(self, length: int | None = None, min_route_length_m: float = MIN_USER_ROUTE_M) -> Demonstration:
        """The recorded route as a :class:`~envs.demos.Demonstration`.

        Args:
            length: if given, the number of steps the route must have (the policy's ``demo_length``).
            min_route_length_m: the route's end must be farther than this from its start (geodesic, metres).

        Raises:
            RouteError: a route of another length than ``length``, or too short.
        """
        check_exact_length(self.length, length)
        demo = demonstration_from_route(self.house, self.poses, self.actions)
        _check_length(demo.shortest_length_m, demo.length, min_route_length_m)
        return demo


def demonstration_from_actions(
    house: House | int,
    start: Sequence[float],
    actions: str | Sequence[int],
    *,
    length: int | None = None,
    min_route_length_m: float = MIN_USER_ROUTE_M,
) -> Demonstration:
    """The demonstration of driving ``actions`` noise-free from ``start``.

    Args:
        house: the house (or its seed).
        start: ``(x m, y m, heading deg)``.
        actions: letters (``"FFLR"``) or ints (0 forward, 1 turn left, 2 turn right).
        length: if given, the exact number of actions required (the policy's ``demo_length``).
        min_route_length_m: the route's end must be farther than this from its start (geodesic, metres).

    Raises:
        RouteError: the first problem: a bad action, the wrong length, a start outside
            the house or in a wall, a step into a wall, a route that is too short.

    Examples:
        >>> demo = demonstration_from_actions(0, (7.5, 1.5, 0.0), [0, 0, 0, 0, 0, 0])
        >>> demo.actions.tolist(), round(demo.shortest_length_m, 1)
        ([0, 0, 0, 0, 0, 0], 2.0)
    """
    actions = parse_actions(actions)
    check_exact_length(len(actions), length)
    recorder = RouteRecorder(house, start)
    for action in actions.tolist():
        recorder.step(action, total=len(actions))
    return recorder.demonstration(min_route_length_m=min_route_length_m)


def demonstration_from_waypoints(
    house: House | int,
    waypoints: Sequence[Sequence[float]],
    *,
    start: Sequence[float] | None = None,
    length: int | None = None,
    min_route_length_m: float = MIN_USER_ROUTE_M,
) -> Demonstration:
    """The demonstration the noise-free expert plans through ``waypoints``, in order.

    Each leg is driven by :func:`~envs.demos.drive_expert` towards the next waypoint
    until the route is within :data:`WAYPOINT_RADIUS_M` of it (geodesic).

    Args:
        house: the house (or its seed).
        waypoints: ``(K, 2)`` positions (x m, y m) on the top-down map.
        start: ``(x m, y m, heading deg)`` where the route starts, before the first
            waypoint. ``None``: it starts at the first waypoint, facing the second.
        length: if given, the route is cropped to its first ``length`` steps (an error
            if the plan is shorter), as sampled demonstrations are.
        min_route_length_m: the route's end must be farther than this from its start (geodesic, metres).

    Raises:
        RouteError: a waypoint outside the house, in a wall, or that the planner cannot
            reach from the one before; a plan shorter than ``length``; a route too short.

    Examples:
        >>> demo = demonstration_from_waypoints(0, [(7.5, 1.5), (9.5, 1.5), (9.5, 3.5)])
        >>> demo.length, demo.end_xy.round(1).tolist()
        (18, [9.5, 3.2])
    """
    house = house_of(house)
    points = np.asarray(waypoints, dtype=np.float64)
    minimum = 1 if start is not None else 2
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < minimum or not np.isfinite(points).all():
        raise RouteError(
            f"waypoints must be at least {minimum} finite (x m, y m) pairs"
            f"{' (the first is the start)' if start is None else ''}, got {np.asarray(waypoints).tolist()!r}."
        )
    for number, xy in enumerate(points, start=1):
        check_position(house, xy, f"waypoint {number}")
    if start is None:
        heading = math.degrees(math.atan2(*(points[1] - points[0])[::-1]))
        start, points, first = (points[0, 0], points[0, 1], heading), points[1:], 2
    else:
        first = 1
    pose = pose_from_degrees(start)
    check_position(house, pose[:2], "start")
    poses, actions = [pose[None]], []
    steps = 0
    for offset, goal in enumerate(points):
        number = first + offset
        if length is not None and steps >= length:
            logger.debug("route cropped to %d steps before waypoint %d", length, number)
            break
        field = house.graph.distance_field(goal)
        distance = field.at(pose[:2])
        if not np.isfinite(distance):
            raise RouteError(
                f"waypoint {number} ({goal[0]:.2f}, {goal[1]:.2f}) cannot be reached from the waypoint before it: "
                "they lie in separate free regions of the house."
            )
        budget = math.ceil(distance / FORWARD_STEP_M) + LEG_SLACK_STEPS
        leg_poses, leg_actions = drive_expert(house, field, pose, budget, arrival_radius_m=WAYPOINT_RADIUS_M)
        if field.at(leg_poses[-1, :2]) > WAYPOINT_RADIUS_M:
            raise RouteError(
                f"the planner did not reach waypoint {number} ({goal[0]:.2f}, {goal[1]:.2f}) in {budget} steps "
                f"(it stopped {field.at(leg_poses[-1, :2]):.2f} m away); move the waypoint into open space."
            )
        poses.append(leg_poses[1:])
        actions.append(leg_actions)
        pose = leg_poses[-1]
        steps += len(leg_actions)
    route_poses, route_actions = np.concatenate(poses), np.concatenate(actions) if actions else np.zeros(0, np.int64)
    if length is not None:
        if len(route_actions) < length:
            raise RouteError(
                f"the waypoints give a planned route of {len(route_actions)} steps; demonstrations must have exactly "
                f"{length} steps here (length={length}): add a waypoint or move the last one farther away."
            )
        route_poses, route_actions = route_poses[: length + 1], route_actions[:length]
    demo = demonstration_from_route(house, route_poses, route_actions)
    _check_length(demo.shortest_length_m, demo.length, min_route_length_m)
    return demo


__all__ = [
    "ACTION_LETTERS",
    "RouteError",
    "RouteRecorder",
    "check_position",
    "default_start",
    "demonstration_from_actions",
    "demonstration_from_waypoints",
    "parse_actions",
    "parse_numbers",
    "parse_pose",
    "parse_waypoints",
    "pose_from_degrees",
]

