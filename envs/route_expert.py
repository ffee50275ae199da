"""The route expert: the best discrete action at any pose to follow a demonstrated route's path.

:class:`~envs.expert.GeodesicExpert` heads for the end of a route by the shortest
path. On the planner's routes that is the route itself; on a tour or a route a
person drove (:mod:`envs.route_styles`) it is a shortcut: under ``paper`` noise on
61-100-step routes it scores nDTW 0.28 (tours) and 0.38 (driven) against the
demonstrated path, with a path 0.5x as long. Labels from it teach a model to cut
across a route it is shown, which is not what a user who teaches a route wants.

:class:`RouteExpert` follows the path instead, in two modes:

* **On the route**, where the agent's pose matches one of the demonstration's
  next poses (within ``MATCH_RADIUS_M`` and ``MATCH_HEADING_DEG``), it gives the
  action the demonstration took there. Noise-free from the route's start it
  replays the demonstration exactly; under noise it is replay that keeps
  re-synchronising to where the agent really is.
* **Off the route**, it steers back and along it: the route's positions, repeats
  dropped (turns on the spot), are its waypoints; a progress index along them
  moves only forward, to the nearest of the next ``WINDOW_WAYPOINTS``, so a route
  that loops back over a place is followed in its order, not short-cut to the
  later pass; the expert heads, with the geodesic expert's rule and collision
  check, for the waypoint ``LOOKAHEAD_WAYPOINTS`` ahead (further while that one
  lies within ``MIN_TARGET_M``). Each waypoint's distance field is computed once,
  when first needed.
* **On the last stretch**, once the route's end is the target, it heads for the end
  as :class:`~envs.expert.GeodesicExpert` does (under ``paper`` noise, replaying
  the last steps overshoots the end, and a 10-step route's limit has little slack).
"""
from __future__ import annotations

import numpy as np

from envs.demos import Demonstration
from envs.expert import FORWARD, FORWARD_STEP_M, TURN_LEFT, TURN_RIGHT, WALL_CONTACT_TOLERANCE_M, GeodesicExpert
from envs.path_fidelity import drop_repeats
from envs.scenes import House

#: The experts an env can label with: ``"goal"`` (:class:`~envs.expert.GeodesicExpert`), ``"route"`` (:class:`RouteExpert`).
EXPERTS = ("goal", "route")
#: Waypoints ahead of the progress index searched for the nearest (1.2 m of forward steps).
WINDOW_WAYPOINTS = 4
#: The target is this many waypoints past the progress index (0.6 m of forward steps).
LOOKAHEAD_WAYPOINTS = 2
#: A target closer than this, metres, is passed over for the next waypoint.
MIN_TARGET_M = FORWARD_STEP_M
#: A demonstrated pose matches the agent's within this distance, metres (the ``paper``
#: noise makes forward steps up to 0.06 m long, so replay drifts about that much a step) ...
MATCH_RADIUS_M = 0.2
#: ... and this heading difference, degrees (half a turn).
MATCH_HEADING_DEG = 10.0
#: Turning back on a turn without having moved this far, metres, is an oscillation (see :meth:`RouteExpert.action`).
OSCILLATION_RADIUS_M = 0.1
#: Demonstrated poses past the last matched one that may match (a run of turns on the spot is at most 9).
MATCH_WINDOW_POSES = 12


class RouteExpert:
    """Follows a demonstration's path in its order, returning to it when pushed off.

    Stateful: it remembers how far along the route the agent has come, so call
    :meth:`action` with the agent's successive poses of one episode (calling it
    twice at the same pose gives the same action and leaves the progress as it is).

    Args:
        house: the house the route is in (its occupancy and geodesic graph).
        demonstration: the route; its ``end_field`` steers the last stretch.
        stop_radius_m: if given, :data:`~envs.expert.STOP` is returned within this
            distance (geodesic) of the route's end once the last waypoint is the target.
        check_replay: for a layout that differs from the one the route was demonstrated in
            (:mod:`envs.conditions`' furniture): a demonstrated forward step that ``house``
            cuts short is not replayed, and waypoints the agent cannot stand on are passed
            over, so the expert goes around a piece on the path and rejoins it.

    Examples:
        >>> from envs.route_styles import driven_route
        >>> from envs.scenes import build_house
        >>> from envs.demos import move_agents, nominal_motion
        >>> house = build_house(3)
        >>> demo = driven_route(house, np.random.default_rng(0), 30)
        >>> expert, pose = RouteExpert(house, demo), demo.start_pose.copy()[None]
        >>> for _ in range(60):
        ...     _ = move_agents([house], pose, nominal_motion(np.array([expert.action(pose[0])])))
        >>> expert.progress == expert.last_waypoint
        True
    """

    def __init__(
        self,
        house: House,
        demonstration: Demonstration,
        stop_radius_m: float | None = None,
        check_replay: bool = False,
    ) -> None:
        self.house = house
        self.check_replay = bool(check_replay)
        poses = np.asarray(demonstration.poses, dtype=np.float64)
        self.poses, self.demo_actions = poses, np.asarray(demonstration.actions, dtype=np.int64)
        self.waypoints = drop_repeats(poses[:, :2])
        # the first demonstrated pose at each waypoint
        moved = np.ones(len(poses), dtype=bool)
        moved[1:] = np.any(poses[1:, :2] != poses[:-1, :2], axis=1)
        self._waypoint_pose = np.flatnonzero(moved)
        self.progress = 0
        self.matched = 0
        self._last_turn: tuple[int, np.ndarray] | None = None
        self._experts: dict[int, GeodesicExpert] = {
            self.last_waypoint: GeodesicExpert(house.occupancy, demonstration.end_field, stop_radius_m=stop_radius_m)
        }

    @property
    def last_waypoint(self) -> int:
        """Index of the route's end among :attr:`waypoints`."""
        return len(self.waypoints) - 1

    def target(self, pose: np.ndarray) -> int:
        """Advance the progress index to ``pose`` and return the index of the waypoint to steer to."""
        xy = np.asarray(pose, dtype=np.float64)[:2]
        window = self.waypoints[self.progress : self.progress + WINDOW_WAYPOINTS + 1]
        self.progress += int(np.argmin(np.hypot(*(window - xy).T)))
        target = min(self.progress + LOOKAHEAD_WAYPOINTS, self.last_waypoint)
        while target < self.last_waypoint and (
            np.hypot(*(self.waypoints[target] - xy)) < MIN_TARGET_M
            or (self.check_replay and not self.house.occupancy.is_free(self.waypoints[target]))
        ):
            target += 1
        return target

    def route_step(self, pose: np.ndarray) -> int:
        """Advance the progress index to ``pose`` and return the demonstration step the agent has
        come to along the route, in the route's order: the step whose pose it matches
        (:meth:`match`, heading included, so turns on the spot count), else the first step at
        the progress waypoint or the last matched step, whichever is later (so it never goes back).

        Examples:
            >>> from envs.route_styles import planner_route
            >>> from envs.scenes import build_house
            >>> house = build_house(3)
            >>> demo = planner_route(house, np.random.default_rng(0), 12)
            >>> expert = RouteExpert(house, demo)
            >>> [expert.route_step(pose) for pose in demo.poses[:12]] == list(range(12))
            True
        """
        pose = np.asarray(pose, dtype=np.float64)
        self.target(pose)
        matched = self.match(pose)
        return max(self.matched, int(self._waypoint_pose[self.progress])) if matched is None else matched

    def peek_route_step(self, pose: np.ndarray) -> int:
        """:meth:`route_step` that leaves the expert as it was: for a label beside :meth:`action`
        at the same pose. (:meth:`target` and :meth:`match` may move on a second call at a pose,
        to a nearer point past the first call's window, which would change later actions.)"""
        saved = (self.progress, self.matched)
        try:
            return self.route_step(pose)
        finally:
            self.progress, self.matched = saved

    def match(self, pose: np.ndarray) -> int | None:
        """The index of the demonstrated pose that ``pose`` matches (``None``: off the route).

        Candidates are the :data:`MATCH_WINDOW_POSES` poses from the last match, or from
        the first pose at the current waypoint if that is later; of those within
        :data:`MATCH_RADIUS_M` and :data:`MATCH_HEADING_DEG` the nearest wins, the
        earliest on ties. The route's end pose (no action) never matches.
        """
        start = max(self.matched, int(self._waypoint_pose[self.progress]))
        stop = min(start + MATCH_WINDOW_POSES, len(self.demo_actions))
        if start >= stop:
            return None
        candidates = self.poses[start:stop]
        distance = np.hypot(candidates[:, 0] - pose[0], candidates[:, 1] - pose[1])
        heading = np.abs((candidates[:, 2] - pose[2] + np.pi) % (2 * np.pi) - np.pi)
        distance[(distance > MATCH_RADIUS_M) | (heading > np.deg2rad(MATCH_HEADING_DEG))] = np.inf
        best = int(np.argmin(distance))
        if not np.isfinite(distance[best]):
            return None
        self.matched = start + best
        return self.matched

    def action(self, pose: np.ndarray) -> int:
        """The expert action at ``pose`` = (x metres, y metres, heading radians)."""
        pose = np.asarray(pose, dtype=np.float64)
        target = self.target(pose)
        # the last stretch goes straight for the end: replaying it under noise overshoots
        matched = self.match(pose) if target < self.last_waypoint else None
        if matched is not None and not (self.check_replay and self._blocked(pose, int(self.demo_actions[matched]))):
            return int(self.demo_actions[matched])
        expert = self._experts.get(target)
        if expert is None:
            field = self.house.graph.distance_field(self.waypoints[target])
            expert = self._experts[target] = GeodesicExpert(self.house.occupancy, field)
        action = expert.action(pose)
        if action in (TURN_LEFT, TURN_RIGHT):
            last = self._last_turn
            if last is not None and action != last[0] and np.hypot(*(pose[:2] - last[1])) < OSCILLATION_RADIUS_M:
                # a near target between two headings makes the greedy rule turn back and forth:
                # go forward if that gets closer, else keep turning the way it turned
                ahead, _ = self.house.occupancy.move(pose[:2], FORWARD_STEP_M * np.array([np.cos(pose[2]), np.sin(pose[2])]))
                action = FORWARD if expert.field.at(ahead) < expert.field.at(pose[:2]) else last[0]
            if action != FORWARD:
                self._last_turn = (action, pose[:2].copy())
        return action

    def _blocked(self, pose: np.ndarray, action: int) -> bool:
        """Whether ``house`` cuts a forward step from ``pose`` short (a turn is never blocked)."""
        if action != FORWARD:
            return False
        step = FORWARD_STEP_M * np.array([np.cos(pose[2]), np.sin(pose[2])])
        _, travelled = self.house.occupancy.move(pose[:2], step)
        return travelled < FORWARD_STEP_M - WALL_CONTACT_TOLERANCE_M

    def actions(self, poses: np.ndarray) -> np.ndarray:
        """Expert actions for the ``(N, 3)`` successive poses of one episode."""
        return np.array([self.action(pose) for pose in np.asarray(poses, dtype=np.float64)], dtype=np.int64)
