"""Homing: after a demonstration, return along the route to its start.

The env's ``task`` names what an episode asks of the agent (:data:`TASKS`):

* ``"follow"`` (the paper's path following): start where the route starts, reach its end;
* ``"homing"``: the demonstration has been driven to its end; start there and return
  to the route's **start**.

A homing episode is a follow episode of the route's *homing demonstration*
(:func:`homing_demonstration`), so the protocol, the expert, the noise, the success
radius rule, SPL and the reward need nothing new:

* **Frames**: the memory must show what the agent sees when it drives back. The
  homing demonstration's poses are the route's poses in reverse order with headings
  turned by 180 degrees (the demonstrator driving back faces the other way), and the
  env renders its frames at those poses. The recorded frames are never reversed:
  they look the wrong way.
* **Actions**: the actions of driving that reversed route, derived from the route so
  that they match the rendered frames step for step: the route's actions in reverse
  order with left and right swapped (forward stays forward). A turn is then exactly
  the rotation between two consecutive frames, and a forward step the translation
  between them, up to the collision model's sliding: where the route slid along a
  wall, driving the reversed step nominally lands a few centimetres off the earlier
  pose (at most 0.18 m, mean of the per-route maximum 0.05 m over 300 sampled routes),
  less than the actuation noise of one step. An expert planned from the end back to
  the start was the alternative; it was not taken, because it would neither retrace
  the taught route nor keep its length n, and the policy's memory holds exactly n
  steps. The expert still labels every step of a homing episode: it drives along the
  geodesic field of the route's start (:class:`~envs.expert.GeodesicExpert`).
* **Start and goal**: the agent starts at the route's end facing back along it (the
  homing demonstration's first pose); success means ending within the success radius
  of the route's start, whose initial distance is the geodesic from the end to the start.

Examples:
    >>> from envs.user_demos import demonstration_from_actions
    >>> route = demonstration_from_actions(0, (7.5, 1.5, 0.0), "FFFFLF")
    >>> back = homing_demonstration(route)
    >>> back.task, back.actions.tolist(), back.end_xy.tolist() == route.start_pose[:2].tolist()
    ('homing', [0, 2, 0, 0, 0, 0], True)
    >>> round(float(np.degrees(back.start_pose[2])), 1)
    -160.0
"""
from __future__ import annotations

import dataclasses

import numpy as np

from envs.demos import Demonstration, demonstration_from_route
from envs.expert import FORWARD, TURN_LEFT, TURN_RIGHT
from envs.scenes import House, build_house

#: The tasks an episode can pose: follow the route, or return along it to its start.
FOLLOW, HOMING = "follow", "homing"
TASKS = (FOLLOW, HOMING)
#: The action that undoes each demonstration action when the route is driven backwards
#: facing the other way (indexed by action: forward, turn left, turn right).
REVERSED_ACTION = np.array([FORWARD, TURN_RIGHT, TURN_LEFT], dtype=np.int64)


def check_task(task: object, name: str = "task") -> str:
    """``task`` if it is one of :data:`TASKS`, else a ``ValueError`` naming ``name`` and the allowed values.

    Examples:
        >>> check_task("homing")
        'homing'
        >>> check_task("home")
        Traceback (most recent call last):
        ...
        ValueError: task must be one of 'follow' (reach the route's end), 'homing' (return to the route's start), got 'home'.
    """
    if task not in TASKS:
        raise ValueError(
            f"{name} must be one of 'follow' (reach the route's end), 'homing' (return to the route's start), got {task!r}."
        )
    return str(task)


def reversed_poses(poses: np.ndarray) -> np.ndarray:
    """``(K, 3)`` poses (x m, y m, heading rad) in reverse order, headings turned by 180 degrees.

    Headings stay in ``[-pi, pi)``, as the simulator wraps them.

    Examples:
        >>> reversed_poses(np.array([[1.0, 2.0, 0.0], [1.3, 2.0, np.pi / 2]])).round(4).tolist()
        [[1.3, 2.0, -1.5708], [1.0, 2.0, -3.1416]]
    """
    out = np.array(poses, dtype=np.float64)[::-1].copy()
    out[:, 2] = np.mod(out[:, 2] + 2 * np.pi, 2 * np.pi) - np.pi
    return out


def homing_demonstration(route: Demonstration, house: House | None = None) -> Demonstration:
    """The demonstration of driving ``route`` back from its end to its start (see the module docstring).

    Args:
        route: the route as it was demonstrated (a follow demonstration).
        house: its house (``None``: built from ``route.house_seed``).

    Returns:
        a :class:`~envs.demos.Demonstration` with ``task="homing"``: reversed poses,
        reversed and mirrored actions, the distance field of the route's start, and the
        geodesic length from the route's end to its start.

    Raises:
        ValueError: ``route`` is already a homing demonstration.
    """
    if route.task != FOLLOW:
        raise ValueError(
            f"route is already a {route.task!r} demonstration; give the route as it was demonstrated "
            "(task 'follow') and the homing demonstration is derived from it."
        )
    house = build_house(route.house_seed) if house is None else house
    back = demonstration_from_route(house, reversed_poses(route.poses), REVERSED_ACTION[route.actions[::-1]])
    return dataclasses.replace(back, task=HOMING)


def task_demonstration(route: Demonstration, task: str, house: House | None = None) -> Demonstration:
    """The demonstration an episode of ``task`` plays for ``route``: itself (follow) or its homing demonstration.

    Examples:
        >>> from envs.user_demos import demonstration_from_actions
        >>> route = demonstration_from_actions(0, (7.5, 1.5, 0.0), "FFFFLF")
        >>> task_demonstration(route, "follow") is route, task_demonstration(route, "homing").task
        (True, 'homing')
    """
    return homing_demonstration(route, house) if check_task(task) == HOMING else route


__all__ = ["FOLLOW", "HOMING", "REVERSED_ACTION", "TASKS", "check_task", "homing_demonstration", "reversed_poses", "task_demonstration"]
