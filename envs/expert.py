"""The expert: the best discrete action at any pose to reach the end of a route.

The expert follows the geodesic distance field of the route's end. At a pose it
tries ``NUM_HEADINGS`` headings spaced by the turn angle around the current one,
moves the agent's disc forward one step along each with the simulator's own
collision and sliding rule (so moves into walls are rejected, and it never stalls
at a corner), and keeps the heading whose step gets closest to the goal. It then
moves forward if that heading is the current one (within ``FORWARD_TOLERANCE_M``
of the best progress) and otherwise turns towards it.

Noise-free, starting on a route, this traces a shortest path; from a perturbed
pose it returns to the route and continues along it, which is what perturbed
training episodes are labelled with.
"""
from __future__ import annotations

import numpy as np

from envs.geodesic import DistanceField
from envs.geometry import OccupancyMap

#: Action indices shared by the environment, the expert and the policies.
FORWARD, TURN_LEFT, TURN_RIGHT, STOP = 0, 1, 2, 3
ACTION_NAMES = ("forward", "turn_left", "turn_right", "stop")
#: Nominal forward step, metres, and turn, degrees (the paper's action space).
FORWARD_STEP_M = 0.3
TURN_ANGLE_DEG = 20.0
#: A forward step may lose this much of its length to the collision model (a glancing
#: contact that slides along a wall), metres; a step shortened more runs into a wall.
#: Half a step: the planner's own routes slide along walls by up to 0.13 m.
WALL_CONTACT_TOLERANCE_M = FORWARD_STEP_M / 2
#: Number of candidate headings examined (360 / 20 degrees).
NUM_HEADINGS = 18
#: Headings whose straight move is checked against collisions, best predicted first.
VERIFIED_CANDIDATES = 3
#: Forward is kept when its progress is within this of the best heading's, metres.
FORWARD_TOLERANCE_M = 0.03


class GeodesicExpert:
    """Greedy one-step-lookahead expert on a geodesic distance field.

    Args:
        occupancy: the house's :class:`~envs.geometry.OccupancyMap` (collisions).
        field: distances to the route's end (:class:`~envs.geodesic.DistanceField`).
        forward_step_m: nominal forward step, metres.
        turn_angle_rad: nominal turn, radians.
        stop_radius_m: if given, :data:`STOP` is returned within this distance of the goal.

    Examples:
        >>> from envs.scenes import build_house
        >>> house = build_house(0)
        >>> field = house.graph.distance_field(house.spawn_xy + np.array([2.0, 0.0]))
        >>> expert = GeodesicExpert(house.occupancy, field)
        >>> expert.action(np.array([*house.spawn_xy, 0.0])) in (FORWARD, TURN_LEFT, TURN_RIGHT)
        True
    """

    def __init__(
        self,
        occupancy: OccupancyMap,
        field: DistanceField,
        forward_step_m: float = FORWARD_STEP_M,
        turn_angle_rad: float = np.deg2rad(TURN_ANGLE_DEG),
        stop_radius_m: float | None = None,
    ) -> None:
        self.occupancy = occupancy
        self.field = field
        self.forward_step_m = float(forward_step_m)
        self.turn_angle_rad = float(turn_angle_rad)
        self.stop_radius_m = stop_radius_m
        half = NUM_HEADINGS // 2
        # candidate turn counts ordered by |k| then left first: 0, 1, -1, 2, -2, ...
        self._turns = np.array(sorted(range(-half + 1, half + 1), key=lambda k: (abs(k), -k)))
        self._turn_offsets = self._turns * self.turn_angle_rad

    def action(self, pose: np.ndarray) -> int:
        """The expert action at ``pose`` = (x metres, y metres, heading radians)."""
        return int(self.actions(np.asarray(pose, dtype=np.float64)[None])[0])

    def actions(self, poses: np.ndarray) -> np.ndarray:
        """Expert actions for ``(N, 3)`` poses."""
        poses = np.asarray(poses, dtype=np.float64)
        return np.array([self._action(pose) for pose in poses], dtype=np.int64)

    def _action(self, pose: np.ndarray) -> int:
        turns = self._turns
        now = self.field.at(pose[:2])
        if self.stop_radius_m is not None and now <= self.stop_radius_m:
            return STOP
        headings = pose[2] + self._turn_offsets
        displacement = np.empty((len(turns), 2))
        np.cos(headings, out=displacement[:, 0])
        np.sin(headings, out=displacement[:, 1])
        displacement *= self.forward_step_m
        # cheap ranking: distance at each straight end point, ignoring collisions
        predicted = self.field.at_many(pose[None, :2] + displacement)
        order = np.argsort(predicted, kind="stable")  # ties: smallest |k|, left first
        # verify the best few with the simulator's own motion (collisions, sliding)
        candidates = order[:VERIFIED_CANDIDATES]
        if 0 not in candidates.tolist():
            candidates = np.append(candidates, 0)
        real = self._real_distances(pose, displacement, candidates)
        valid = real <= predicted[candidates] + FORWARD_TOLERANCE_M
        if not valid[candidates != 0].any() and not valid[candidates == 0].any():
            # every cheap guess collides: evaluate all headings with the real motion
            candidates = np.arange(len(turns))
            real = self._real_distances(pose, displacement, candidates)
            valid = np.ones(len(turns), dtype=bool)
        score = np.where(valid, real, np.inf)
        best = candidates[int(np.argmin(score))]
        forward_real = score[candidates == 0]
        if len(forward_real) and forward_real[0] < now and forward_real[0] <= score.min() + FORWARD_TOLERANCE_M:
            return FORWARD
        if turns[best] == 0:
            return FORWARD if score.min() < now else TURN_LEFT
        return TURN_LEFT if turns[best] > 0 else TURN_RIGHT

    def _real_distances(self, pose: np.ndarray, displacement: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Distances to the goal after really moving one step along each candidate heading."""
        end = np.empty((len(candidates), 2))
        move = self.occupancy.move
        start = pose[:2]
        for row, candidate in enumerate(candidates.tolist()):
            end[row], _ = move(start, displacement[candidate])
        return self.field.at_many(end)
