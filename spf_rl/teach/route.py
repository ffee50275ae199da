"""The route to teach, from whichever of its three forms is given: actions, waypoints or the keyboard.

:func:`teach_route` is the choice ``recipes/teach.py`` makes among ``--actions``,
``--waypoints`` and the keyboard, on values already read from their text
(:func:`envs.user_demos.parse_actions`, :func:`~envs.user_demos.parse_waypoints`,
:func:`~envs.user_demos.parse_pose`):

* actions are driven from ``start`` (the house's spawn point facing +x without one,
  :func:`~envs.user_demos.default_start`);
* waypoints are joined by the planner; the route starts at ``start`` if given, else
  at the first waypoint facing the second;
* with neither, the route is recorded with the keyboard in this terminal
  (:func:`spf_rl.teach.keyboard.record_with_keyboard`), from ``start`` or the spawn point.

A route keeps the length it was given, up to :data:`MAX_TAUGHT_STEPS` (a policy follows
it at its own length, :func:`spf_rl.teach.repeat.teach_and_repeat`); with ``length``, it
must have exactly that many steps (waypoint plans are cropped to it).

Examples:
    >>> from envs.user_demos import parse_actions
    >>> demo = teach_route(0, (7.5, 1.5, 0.0), actions=parse_actions("FFFFLF"))
    >>> demo.length, route_source(parse_actions("FFFFLF"), None)
    (6, 'actions')
    >>> teach_route(0, (7.5, 1.5, 0.0), actions=parse_actions("FFF"), length=6)
    Traceback (most recent call last):
    ...
    envs.user_demos.RouteError: the route has 3 steps; demonstrations must have exactly 6 steps here (length=6): give 6 actions.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from envs.demos import Demonstration
from envs.house_grid import MAX_DEMO_LENGTH
from envs.scenes import House
from envs.user_demos import RouteError, default_start, demonstration_from_actions, demonstration_from_waypoints, house_of

logger = logging.getLogger(__name__)

#: The longest route that can be taught, steps (the env's longest demonstration).
MAX_TAUGHT_STEPS = MAX_DEMO_LENGTH


def route_source(actions: Sequence[int] | None, waypoints: Sequence[Sequence[float]] | None) -> str:
    """How :func:`teach_route` takes the route: ``"actions"`` (typed) first, then ``"waypoints"``, else ``"keyboard"``.

    Examples:
        >>> route_source(None, [(7.5, 1.5), (9.5, 1.5)]), route_source(None, None)
        ('waypoints', 'keyboard')
    """
    if actions is not None:
        return "actions"
    return "waypoints" if waypoints is not None else "keyboard"


def teach_route(
    house: House | int,
    start: Sequence[float] | None = None,
    actions: Sequence[int] | np.ndarray | None = None,
    waypoints: Sequence[Sequence[float]] | None = None,
    *,
    length: int | None = None,
) -> Demonstration | None:
    """The demonstration of the route given by ``actions``, ``waypoints`` or the keyboard.

    Args:
        house: the house (or its seed).
        start: ``(x m, y m, heading deg)``, or ``None`` (actions and the keyboard: the
            house's spawn point facing +x; waypoints: the first waypoint facing the second).
        actions: the route's actions (ints, :func:`~envs.user_demos.parse_actions`), or ``None``.
        waypoints: points ``(x m, y m)`` joined by the planner, or ``None`` (used when
            ``actions`` is ``None``).
        length: the steps the demonstration must have (``None``: its own, 1 to
            :data:`MAX_TAUGHT_STEPS`).

    Returns:
        The demonstration, or ``None`` when the keyboard's user cancelled.

    Raises:
        RouteError: a refused route (into a wall, out of the house, too short, not
            ``length`` steps, or longer than :data:`MAX_TAUGHT_STEPS`), the message naming
            the step or waypoint.
    """
    source = route_source(actions, waypoints)
    logger.debug("route from %s", source)
    if source == "actions":
        _check_steps(len(actions))  # before driving it
    if source == "waypoints":
        demo = demonstration_from_waypoints(house, waypoints, start=start, length=length)
    elif source == "actions":
        demo = demonstration_from_actions(house, default_start(house) if start is None else start, actions, length=length)
    else:
        from spf_rl.teach.keyboard import record_with_keyboard  # curses, only for the keyboard

        start = default_start(house) if start is None else start
        return record_with_keyboard(house_of(house), start, MAX_TAUGHT_STEPS if length is None else length, exact=length is not None)
    _check_steps(demo.length)
    return demo


def _check_steps(steps: int) -> None:
    if steps > MAX_TAUGHT_STEPS:
        raise RouteError(
            f"the route has {steps} steps; a taught route may have at most {MAX_TAUGHT_STEPS} "
            "(envs.house_grid.MAX_DEMO_LENGTH): split it in two."
        )
