"""Route styles: seeded generators of demonstrated routes of three kinds, and mixtures of them.

Every style is a function ``(house, rng, length) -> Demonstration`` of exactly
``length`` actions, drawing everything from the ``rng`` it is given (the same seed
gives the same route):

* ``"planner"`` (:func:`planner_route`): today's routes,
  :func:`~envs.demos.sample_demonstration`: the noise-free expert's shortest route
  towards a far goal, cropped to ``length`` steps.
* ``"tour"`` (:func:`tour_route`): the planner's route through :data:`TOUR_WAYPOINTS`
  random waypoints on the house's navigable nodes
  (:func:`~envs.user_demos.demonstration_from_waypoints`), so it bends where a
  shortest path to its end would not.
* ``"driven"`` (:func:`driven_route`): the route a person teleoperating with the keys
  F / L / R would drive (:class:`DrivenStyle`) towards places they have in mind:
  runs of forward steps, turns in place of 20 to 100 degrees and turn-arounds,
  anywhere and not only at walls, detours, loops, driving back part of the way, and
  round trips back near the start. It is recorded with a
  :class:`~envs.user_demos.RouteRecorder`, so it is a taught route by construction:
  no forward step runs into a wall (at a wall the person turns).

:class:`RouteMixture` draws a style by weight and a length, and
:func:`parse_route_style` reads the ``route_style=`` of a config (``"driven"``,
``{"planner": 0.5, "driven": 0.5}`` or ``"planner=0.5,tour=0.25,driven=0.25"``).

Lengths lie in [:data:`MIN_STYLE_LENGTH`, :data:`MAX_STYLE_LENGTH`] steps. Long
routes need large houses, as for :func:`~envs.demos.sample_demonstration`: the
planner needs two points ``0.3 n + 1`` m apart (the houses of
:func:`~envs.house_grid.default_grid_size_cells`); tour and driven routes fit any
house. Routes that cannot be made (a tour the planner cannot join, a driven route
that ends too close to its start) are re-drawn from the same ``rng``, at most
:data:`MAX_ROUTE_ATTEMPTS` times.

Examples:
    >>> from envs.scenes import build_house
    >>> house = build_house(0)
    >>> demo = sample_route("driven", house, np.random.default_rng(0), 20)
    >>> demo.actions.shape, demo.poses.shape
    ((20,), (21, 3))
    >>> mixture = parse_route_style("planner=0.5,tour=0.25,driven=0.25", min_length=10, max_length=30)
    >>> style, demo = mixture.sample(house, np.random.default_rng(1))
    >>> style in ROUTE_STYLES, 10 <= demo.length <= 30
    (True, True)
    >>> sample_route("zigzag", house, np.random.default_rng(0), 20)
    Traceback (most recent call last):
    ...
    ValueError: style must be one of 'planner', 'tour', 'driven', got 'zigzag'.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from envs.demos import (
    Demonstration,
    _route_candidates,
    default_min_route_length_m,
    sample_demonstration,
)
from envs.expert import FORWARD, FORWARD_STEP_M, NUM_HEADINGS, TURN_LEFT, TURN_RIGHT, WALL_CONTACT_TOLERANCE_M, GeodesicExpert
from envs.geodesic import DistanceField
from envs.homing import REVERSED_ACTION
from envs.house_grid import MAX_DEMO_LENGTH
from envs.scenes import House
from envs.user_demos import (
    MIN_USER_ROUTE_M,
    RouteError,
    RouteRecorder,
    demonstration_from_actions,
    demonstration_from_waypoints,
    house_of,
)

logger = logging.getLogger(__name__)

PLANNER, TOUR, DRIVEN = "planner", "tour", "driven"
#: Route lengths the styles make, steps (the longest is within :data:`~envs.house_grid.MAX_DEMO_LENGTH`).
MIN_STYLE_LENGTH = 10
MAX_STYLE_LENGTH = min(100, MAX_DEMO_LENGTH)
#: Attempts at a tour or driven route (each from fresh draws of the same rng) before giving up.
MAX_ROUTE_ATTEMPTS = 20

#: Waypoints a tour passes through within its length, about (the planner turns at each).
TOUR_WAYPOINTS = 3
#: About this share of a planned route's steps are forward steps (the rest are turns): a
#: tour's legs are drawn so that ``TOUR_WAYPOINTS`` of them take about ``length`` steps.
TOUR_FORWARD_SHARE = 0.35
#: A leg's straight length (metres) is drawn uniformly in this range times the mean leg
#: ``length * FORWARD_STEP_M * TOUR_FORWARD_SHARE / TOUR_WAYPOINTS``, and at least :data:`TOUR_MIN_LEG_M`.
TOUR_LEG_RANGE = (0.5, 1.5)
#: The shortest mean leg, metres (a few forward steps beyond the waypoint radius).
TOUR_MIN_LEG_M = 1.0
#: The most waypoints a tour is padded to (waypoints past its ``length`` steps are never driven).
MAX_TOUR_WAYPOINTS = 12

#: Turn actions of a turn-around (180 degrees).
TURN_AROUND_STEPS = NUM_HEADINGS // 2


@dataclass(frozen=True)
class DrivenStyle:
    """How the simulated person drives a ``"driven"`` route (keys F / L / R; a turn is 20 degrees).

    The person has a destination in mind (a random place some way off; a new one once
    there) and alternates manoeuvres and runs of forward steps. A manoeuvre either
    steers towards the destination (turning as the expert would, sometimes one turn
    too far, corrected later) or wanders: a small correction (one turn), a turn of a
    few steps, often to the same side as the last (loops), or a turn-around, possibly
    followed by driving back part of the way just driven. A run ends after a geometric
    number of steps, or at a wall: there the person turns on the spot towards the side
    that clears the way soonest, until the next step is free. On a round trip the
    destination becomes the start once the steps left would just get the person
    home; once home, they wander with the steps left.

    Attributes:
        mean_run_steps: mean forward steps of a run (geometric, >= 1), steps of 0.3 m.
        wander_prob: probability that a manoeuvre ignores the destination (a detour).
        correction_prob: probability that a wandering manoeuvre is a one-step (20 degree) correction.
        turn_around_prob: probability that a wandering manoeuvre is a turn-around (9 turn actions).
        turn_steps: the other wandering manoeuvres turn uniformly between these turn actions (2-5: 40-100 degrees).
        same_side_prob: probability that a wandering turn goes to the side of the previous turn.
        backtrack_prob: probability that a turn-around is followed by driving back.
        backtrack_fraction: driving back retraces this fraction (uniform in the range) of the route so far.
        overshoot_prob: probability that a turn towards the destination takes one turn too many.
        destination_range: straight distance to a destination, as fractions of the route's
            straight length (``length * 0.3`` m), uniform in the range (shrunk to fit the house).
        arrival_radius_m: a destination (or, on a round trip, the start) is reached within
            this distance (geodesic, metres).
        round_trip_prob: probability that a route is a round trip, ending back near its start.
        home_steps_per_m: steps the person budgets per metre (geodesic) of the way home.
        glance_m: the person takes a forward step only if it keeps all but this much of its
            length (metres): they steer clear of walls rather than scrape along them, which a
            taught route allows up to :data:`~envs.expert.WALL_CONTACT_TOLERANCE_M`.

    Examples:
        >>> DrivenStyle().turn_steps
        (2, 5)
        >>> DrivenStyle(correction_prob=0.9, turn_around_prob=0.2)
        Traceback (most recent call last):
        ...
        ValueError: correction_prob + turn_around_prob must be at most 1 (probabilities of one manoeuvre), got 1.1.
    """

    mean_run_steps: float = 4.0
    wander_prob: float = 0.5
    correction_prob: float = 0.3
    turn_around_prob: float = 0.15
    turn_steps: tuple[int, int] = (2, 5)
    same_side_prob: float = 0.6
    backtrack_prob: float = 0.5
    backtrack_fraction: tuple[float, float] = (0.1, 0.4)
    overshoot_prob: float = 0.25
    destination_range: tuple[float, float] = (0.25, 0.75)
    arrival_radius_m: float = 1.0
    round_trip_prob: float = 0.3
    home_steps_per_m: float = 7.0
    glance_m: float = 0.05

    def __post_init__(self) -> None:
        probabilities = ("wander_prob", "correction_prob", "turn_around_prob", "same_side_prob", "backtrack_prob")
        for name in (*probabilities, "overshoot_prob", "round_trip_prob"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}.")
        if self.correction_prob + self.turn_around_prob > 1.0:
            raise ValueError(
                "correction_prob + turn_around_prob must be at most 1 (probabilities of one manoeuvre), "
                f"got {self.correction_prob + self.turn_around_prob:.3g}."
            )
        if not self.mean_run_steps >= 1.0:
            raise ValueError(f"mean_run_steps must be >= 1 (steps), got {self.mean_run_steps!r}.")
        low, high = self.turn_steps
        if not 1 <= low <= high <= TURN_AROUND_STEPS:
            raise ValueError(f"turn_steps must be (low, high) with 1 <= low <= high <= {TURN_AROUND_STEPS}, got {self.turn_steps!r}.")
        for name in ("backtrack_fraction", "destination_range"):
            low, high = getattr(self, name)
            if not 0.0 < low <= high <= 1.0:
                raise ValueError(f"{name} must be (low, high) with 0 < low <= high <= 1, got {getattr(self, name)!r}.")
        if not 0.0 <= self.glance_m <= WALL_CONTACT_TOLERANCE_M:
            raise ValueError(f"glance_m must be in [0, {WALL_CONTACT_TOLERANCE_M}] metres, got {self.glance_m!r}.")
        if not (self.home_steps_per_m > 0 and self.arrival_radius_m > 0):
            raise ValueError(
                f"home_steps_per_m and arrival_radius_m must be > 0, got {self.home_steps_per_m!r} and {self.arrival_radius_m!r}."
            )


def check_style_length(length: object, name: str = "length") -> int:
    """``length`` as an int, or a ``ValueError`` naming ``name`` and the allowed range.

    Examples:
        >>> check_style_length(30)
        30
        >>> check_style_length(5)
        Traceback (most recent call last):
        ...
        ValueError: length must be an int in [10, 100] (steps), got 5.
    """
    if isinstance(length, bool) or not isinstance(length, (int, np.integer)) or not MIN_STYLE_LENGTH <= length <= MAX_STYLE_LENGTH:
        raise ValueError(f"{name} must be an int in [{MIN_STYLE_LENGTH}, {MAX_STYLE_LENGTH}] (steps), got {length!r}.")
    return int(length)


def _check_rng(rng: object) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {type(rng).__name__}.")
    return rng


def _checked(house: House | int, rng: object, length: object) -> tuple[House, np.random.Generator, int]:
    """The arguments of a style, checked (cheap checks first, then the house is built)."""
    length = check_style_length(length)
    rng = _check_rng(rng)
    if isinstance(house, bool) or not isinstance(house, (House, int, np.integer)):
        raise ValueError(f"house must be an envs.scenes.House or a house seed (int), got {type(house).__name__}.")
    return house_of(int(house) if not isinstance(house, House) else house), rng, length


def planner_route(house: House | int, rng: np.random.Generator, length: int) -> Demonstration:
    """Today's routes: :func:`~envs.demos.sample_demonstration` with :func:`~envs.demos.default_min_route_length_m`.

    Examples:
        >>> planner_route(0, np.random.default_rng(0), 10).length
        10
    """
    house, rng, length = _checked(house, rng, length)
    return sample_demonstration(house, rng, length, min_route_length_m=default_min_route_length_m(length))


def tour_route(house: House | int, rng: np.random.Generator, length: int, waypoints: int = TOUR_WAYPOINTS) -> Demonstration:
    """The planner's route from a random start through ``waypoints`` random waypoints, cropped to ``length`` steps.

    The start and the waypoints are drawn on the house's roomy navigable nodes (where
    :func:`~envs.demos.sample_demonstration` starts its routes), each waypoint a leg of
    :data:`TOUR_LEG_RANGE` (straight distance) from the point before, so that the route
    passes about ``waypoints`` of them and bends there. Waypoints are added (up to
    :data:`MAX_TOUR_WAYPOINTS`) until the legs' straight lengths guarantee a plan of at
    least ``length`` steps; the plan is cropped there, so the later ones are never
    driven. The route starts facing its first waypoint (the convention of
    :func:`~envs.user_demos.demonstration_from_waypoints`), is checked as a taught route
    (:func:`~envs.user_demos.demonstration_from_actions`: the planner may glance along a
    wall more than a taught forward step may), and must end farther than
    :func:`~envs.demos.default_min_route_length_m` from its start, as planner routes do;
    else it is re-drawn.

    Raises:
        RuntimeError: no tour in :data:`MAX_ROUTE_ATTEMPTS` attempts.

    Examples:
        >>> demo = tour_route(0, np.random.default_rng(0), 30)
        >>> demo.length, demo.shortest_length_m > default_min_route_length_m(30)
        (30, True)
    """
    if isinstance(waypoints, bool) or not isinstance(waypoints, (int, np.integer)) or not 1 <= waypoints <= MAX_TOUR_WAYPOINTS:
        raise ValueError(f"waypoints must be an int in [1, {MAX_TOUR_WAYPOINTS}], got {waypoints!r}.")
    house, rng, length = _checked(house, rng, length)
    starts = house.graph.node_xy(_route_candidates(house)[0])
    leg_m = max(TOUR_MIN_LEG_M, length * FORWARD_STEP_M * TOUR_FORWARD_SHARE / waypoints)
    min_route_m = default_min_route_length_m(length)
    for attempt in range(1, MAX_ROUTE_ATTEMPTS + 1):
        points = [starts[rng.integers(len(starts))]]
        # pad the tour until no plan through it can be shorter than length
        while len(points) <= waypoints or (_least_steps(points) < length and len(points) <= MAX_TOUR_WAYPOINTS):
            points.append(_draw_waypoint(starts, points[-1], *(scale * leg_m for scale in TOUR_LEG_RANGE), rng=rng))
        try:
            plan = demonstration_from_waypoints(house, points, length=length, min_route_length_m=min_route_m)
            start = (*plan.start_pose[:2], math.degrees(plan.start_pose[2]))
            return demonstration_from_actions(house, start, plan.actions, min_route_length_m=min_route_m)
        except RouteError as error:
            logger.debug("house %d: tour of %d steps re-drawn (attempt %d): %s", house.seed, length, attempt, error)
    raise RuntimeError(f"house {house.seed}: no tour of {length} steps in {MAX_ROUTE_ATTEMPTS} attempts.")


def _least_steps(points: list[np.ndarray]) -> float:
    """Forward steps a plan through ``points`` takes at least: each leg's straight length
    less the waypoint radius at either end (a leg starts and ends within one step of its points)."""
    legs = np.hypot(*np.diff(np.asarray(points), axis=0).T)
    return float(np.sum(legs / FORWARD_STEP_M - 2.0))


def _draw_waypoint(candidates: np.ndarray, here: np.ndarray, low_m: float, high_m: float, rng: np.random.Generator) -> np.ndarray:
    """A candidate at a straight distance in ``[low_m, high_m]`` from ``here``, the range
    shrunk to the house where it holds no candidate."""
    distance = np.hypot(*(candidates - here).T)
    farthest = float(distance.max())
    low, high = min(low_m, 0.5 * farthest), min(high_m, farthest)
    band = np.flatnonzero((distance >= low) & (distance <= high))
    if not len(band):  # a gap in the candidates: the nearest beyond the range
        band = np.flatnonzero(distance >= low)
    return candidates[band[rng.integers(len(band))]]


def driven_route(house: House | int, rng: np.random.Generator, length: int, style: DrivenStyle | None = None) -> Demonstration:
    """The route a person teleoperating with F / L / R drives (:class:`DrivenStyle`), ``length`` actions.

    It starts at a random roomy node (where planner routes start) with a random
    heading, and must end farther than :data:`~envs.user_demos.MIN_USER_ROUTE_M`
    (geodesic) from its start, else it is re-drawn.

    Raises:
        RuntimeError: no route in :data:`MAX_ROUTE_ATTEMPTS` attempts.

    Examples:
        >>> demo = driven_route(0, np.random.default_rng(0), 30)
        >>> demo.length, bool((demo.actions != FORWARD).mean() > 0.3)
        (30, True)
    """
    style = DrivenStyle() if style is None else style
    if not isinstance(style, DrivenStyle):
        raise ValueError(f"style must be a DrivenStyle, got {type(style).__name__}.")
    house, rng, length = _checked(house, rng, length)
    places = house.graph.node_xy(_route_candidates(house)[0])
    for attempt in range(1, MAX_ROUTE_ATTEMPTS + 1):
        start = places[rng.integers(len(places))]
        recorder = RouteRecorder(house, (start[0], start[1], rng.uniform(-180.0, 180.0)), contact_tolerance_m=style.glance_m)
        round_trip = bool(rng.random() < style.round_trip_prob)
        try:
            _Driver(recorder, rng, style, length, places, round_trip).drive()
            return recorder.demonstration(length=length, min_route_length_m=MIN_USER_ROUTE_M)
        except RouteError as error:
            logger.debug("house %d: driven route of %d steps re-drawn (attempt %d): %s", house.seed, length, attempt, error)
    raise RuntimeError(f"house {house.seed}: no driven route of {length} steps in {MAX_ROUTE_ATTEMPTS} attempts.")


class _Driver:
    """One person driving one route into ``recorder`` until it holds ``length`` actions.

    ``places`` are where destinations are drawn; on a ``round_trip`` the start's
    distance field tells when to head home.
    """

    def __init__(
        self, recorder: RouteRecorder, rng: np.random.Generator, style: DrivenStyle, length: int, places: np.ndarray, round_trip: bool
    ) -> None:
        self.recorder, self.rng, self.style, self.length, self.places = recorder, rng, style, length, places
        self.graph = recorder.house.graph
        # the start's distance field on a round trip
        self.home: DistanceField | None = self.graph.distance_field(recorder.pose[:2]) if round_trip else None
        self.homeward = False  # heading home (for good)
        self.side = TURN_LEFT if rng.random() < 0.5 else TURN_RIGHT  # the side of the last turn
        self.target: GeodesicExpert  # steers towards the destination (or home)
        self.new_destination()

    @property
    def left(self) -> int:
        """Actions still to drive."""
        return self.length - self.recorder.length

    def new_destination(self) -> None:
        low, high = (fraction * self.length * FORWARD_STEP_M for fraction in self.style.destination_range)
        place = _draw_waypoint(self.places, self.recorder.pose[:2], low, high, self.rng)
        self.target = GeodesicExpert(self.recorder.house.occupancy, self.graph.distance_field(place))

    def drive(self) -> None:
        while self.left > 0:
            here = self.recorder.pose[:2]
            if self.home is not None and not self.homeward and self.left <= self.style.home_steps_per_m * self.home.at(here):
                self.target, self.homeward = GeodesicExpert(self.recorder.house.occupancy, self.home), True
            arrived = self.target.field.at(here) <= self.style.arrival_radius_m
            if arrived and not self.homeward:
                self.new_destination()
                arrived = False
            # no detours on the way home; once there, stay about, wandering
            if not arrived and (self.homeward or self.rng.random() >= self.style.wander_prob):
                self.steer()
            else:
                self.wander()
            self.run(int(self.rng.geometric(1.0 / self.style.mean_run_steps)))

    def act(self, action: int) -> bool:
        """Take ``action`` if steps are left and it is allowed (a forward step into a wall is not)."""
        if self.left <= 0:
            return False
        try:
            self.recorder.step(action)
        except RouteError:
            return False
        return True

    def turn(self, side: int, steps: int) -> None:
        self.side = side
        for _ in range(steps):
            self.act(side)

    def run(self, steps: int) -> None:
        """Up to ``steps`` forward steps; at a wall, turn until the way is clear."""
        for _ in range(steps):
            if self.left <= 0:
                return
            if not self.act(FORWARD):
                self.clear_wall()
                return

    def clear_wall(self) -> None:
        """Turn on the spot towards the side whose way clears in the fewest turns, until it is clear."""
        needed = {side: self.turns_to_clear(side) for side in (TURN_LEFT, TURN_RIGHT)}
        if needed[TURN_LEFT] == needed[TURN_RIGHT]:
            side = TURN_LEFT if self.rng.random() < 0.5 else TURN_RIGHT
        else:
            side = min(needed, key=needed.get)
        if needed[side] > TURN_AROUND_STEPS:
            raise RouteError(f"the driver is stuck at {self.recorder.pose[:2].round(2).tolist()}: no way is clear.")
        self.turn(side, needed[side])

    def turns_to_clear(self, side: int) -> int:
        """Turns to ``side`` after which a forward step is free (one more than a half turn: none is)."""
        recorder = self.recorder
        for turns in range(1, TURN_AROUND_STEPS + 1):
            recorder.step(side)
            try:
                recorder.step(FORWARD)
            except RouteError:
                continue
            recorder.undo()
            break
        else:
            turns = TURN_AROUND_STEPS + 1
        for _ in range(min(turns, TURN_AROUND_STEPS)):
            recorder.undo()
        return turns

    def steer(self) -> None:
        """Turn towards the destination as the expert would, sometimes one turn too far."""
        turned = False
        for _ in range(TURN_AROUND_STEPS):
            action = self.target.action(self.recorder.pose)
            if action == FORWARD:
                break
            self.turn(action, 1)
            turned = True
        if turned and self.rng.random() < self.style.overshoot_prob:
            self.turn(self.side, 1)

    def wander(self) -> None:
        """A correction, a turn of a few steps, or a turn-around (maybe driving back)."""
        style, rng = self.style, self.rng
        draw = rng.random()
        if draw < style.correction_prob:
            self.turn(TURN_LEFT if rng.random() < 0.5 else TURN_RIGHT, 1)
        elif draw < style.correction_prob + style.turn_around_prob:
            driven = self.recorder.actions
            self.turn(TURN_LEFT if rng.random() < 0.5 else TURN_RIGHT, TURN_AROUND_STEPS)
            if rng.random() < style.backtrack_prob:
                self.backtrack(driven)
        else:
            side = self.side if rng.random() < style.same_side_prob else int(REVERSED_ACTION[self.side])
            low, high = style.turn_steps
            self.turn(side, int(rng.integers(low, high + 1)))

    def backtrack(self, driven: np.ndarray) -> None:
        """After a turn-around, retrace the end of ``driven`` (the route before it), stopping at a wall."""
        count = math.ceil(self.rng.uniform(*self.style.backtrack_fraction) * len(driven))
        for action in REVERSED_ACTION[driven[len(driven) - count :][::-1]].tolist():
            if self.left <= 0:
                return
            if not self.act(action):
                self.clear_wall()
                return


#: The route styles by name: each ``(house, rng, length) -> Demonstration``.
ROUTE_STYLES: Mapping[str, Callable[[House | int, np.random.Generator, int], Demonstration]] = MappingProxyType(
    {PLANNER: planner_route, TOUR: tour_route, DRIVEN: driven_route}
)
_STYLE_NAMES = ", ".join(repr(name) for name in ROUTE_STYLES)


def _check_style(style: object, name: str = "style") -> str:
    if not isinstance(style, str) or style not in ROUTE_STYLES:
        raise ValueError(f"{name} must be one of {_STYLE_NAMES}, got {style!r}.")
    return style


def sample_route(style: str, house: House | int, rng: np.random.Generator, length: int) -> Demonstration:
    """A route of ``style`` (one of :data:`ROUTE_STYLES`) and ``length`` steps in ``house``, from ``rng``.

    Raises:
        ValueError: an unknown style, a length outside [10, 100], an ``rng`` that is not a
            ``numpy.random.Generator``, before any work.

    Examples:
        >>> demo = sample_route("tour", 0, np.random.default_rng(3), 10)
        >>> demo.length, demo.house_seed
        (10, 0)
    """
    _check_style(style)
    check_style_length(length)
    _check_rng(rng)
    return ROUTE_STYLES[style](house, rng, length)


@dataclass(frozen=True)
class RouteMixture:
    """Routes of several styles: a style drawn by weight, a length uniformly in ``[min_length, max_length]``.

    The houses it samples in must hold its longest planner routes (a 15 m house holds
    about 40 steps): houses of ``default_grid_size_cells(max_length)`` cells
    (:func:`~envs.house_grid.default_grid_size_cells`), else
    :func:`~envs.demos.sample_demonstration` raises its ``RuntimeError``.

    Args:
        weights: style name -> weight (>= 0, summing to > 0; normalised when drawing).
        min_length: the shortest route, steps.
        max_length: the longest route, steps.

    Examples:
        >>> mixture = RouteMixture({"planner": 3, "driven": 1}, min_length=30, max_length=30)
        >>> mixture.probabilities
        {'planner': 0.75, 'driven': 0.25}
        >>> mixture.spec
        'planner=3.0,driven=1.0'
        >>> RouteMixture({"planner": -1.0})
        Traceback (most recent call last):
        ...
        ValueError: weights['planner'] must be a finite number >= 0, got -1.0.
    """

    weights: Mapping[str, float]
    min_length: int = MIN_STYLE_LENGTH
    max_length: int = MAX_STYLE_LENGTH
    _probabilities: np.ndarray = field(init=False, repr=False, compare=False)

    def __hash__(self) -> int:
        return hash((tuple(self.weights.items()), self.min_length, self.max_length))

    def __post_init__(self) -> None:
        if not isinstance(self.weights, Mapping) or not self.weights:
            raise ValueError(f"weights must be a non-empty mapping of style names ({_STYLE_NAMES}) to weights, got {self.weights!r}.")
        weights = {}
        for style, weight in self.weights.items():
            _check_style(style, f"weights key {style!r}: a style")
            if isinstance(weight, bool) or not isinstance(weight, (int, float, np.integer, np.floating)) or not 0 <= weight < math.inf:
                raise ValueError(f"weights[{style!r}] must be a finite number >= 0, got {weight!r}.")
            weights[style] = float(weight)
        if sum(weights.values()) <= 0:
            raise ValueError(f"weights must sum to more than 0, got {weights!r}.")
        min_length = check_style_length(self.min_length, "min_length")
        max_length = check_style_length(self.max_length, "max_length")
        if min_length > max_length:
            raise ValueError(f"min_length must be at most max_length ({max_length}), got {min_length}.")
        # canonical order (that of ROUTE_STYLES), read-only
        object.__setattr__(self, "weights", MappingProxyType({s: weights[s] for s in ROUTE_STYLES if s in weights}))
        object.__setattr__(self, "min_length", min_length)
        object.__setattr__(self, "max_length", max_length)
        total = sum(self.weights.values())
        object.__setattr__(self, "_probabilities", np.array([w / total for w in self.weights.values()]))

    @property
    def probabilities(self) -> dict[str, float]:
        """Style name -> probability of drawing it."""
        return dict(zip(self.weights, self._probabilities.tolist()))

    @property
    def spec(self) -> str:
        """The weights as :func:`parse_route_style` reads them: ``"planner=0.5,driven=0.5"``."""
        return ",".join(f"{style}={weight!r}" for style, weight in self.weights.items())

    def sample(self, house: House | int, rng: np.random.Generator) -> tuple[str, Demonstration]:
        """``(style, route)``: a style drawn by weight and a route of it with a uniformly drawn length.

        Examples:
            >>> RouteMixture({"driven": 1.0}, 12, 12).sample(0, np.random.default_rng(0))[1].length
            12
        """
        _check_rng(rng)
        style = list(self.weights)[int(rng.choice(len(self._probabilities), p=self._probabilities))]
        length = int(rng.integers(self.min_length, self.max_length + 1))
        return style, sample_route(style, house, rng, length)


def parse_route_style(
    route_style: str | Mapping[str, float] | RouteMixture, *, min_length: int = MIN_STYLE_LENGTH, max_length: int = MAX_STYLE_LENGTH
) -> RouteMixture:
    """The :class:`RouteMixture` of a config's ``route_style``.

    Args:
        route_style: a style name (``"driven"``), a weight mapping
            (``{"planner": 0.5, "driven": 0.5}``), the same as a string
            (``"planner=0.5,driven=0.5"``, as :attr:`RouteMixture.spec` writes it), or a
            :class:`RouteMixture` (returned as it is).
        min_length, max_length: the lengths of its routes, steps (a config of one
            ``demo_length`` n gives both as n).

    Examples:
        >>> parse_route_style("driven", min_length=30, max_length=30)
        RouteMixture(weights=mappingproxy({'driven': 1.0}), min_length=30, max_length=30)
        >>> parse_route_style({"tour": 1, "planner": 1}).spec
        'planner=1.0,tour=1.0'
        >>> parse_route_style("planner=0.5,tour=x")
        Traceback (most recent call last):
        ...
        ValueError: route_style must be a style (one of 'planner', 'tour', 'driven') or 'style=weight' pairs joined by commas, got 'planner=0.5,tour=x'.
    """
    if isinstance(route_style, RouteMixture):
        return route_style
    if isinstance(route_style, Mapping):
        return RouteMixture(dict(route_style), min_length, max_length)
    if not isinstance(route_style, str):
        raise ValueError(
            f"route_style must be a style name, a mapping of styles to weights or a 'style=weight,...' string, "
            f"got {type(route_style).__name__}."
        )
    text = route_style.replace(" ", "")
    if "=" not in text:
        return RouteMixture({_check_style(text, "route_style"): 1.0}, min_length, max_length)
    weights: dict[str, float] = {}
    for pair in text.split(","):
        style, equals, weight = pair.partition("=")
        try:
            value = float(weight) if equals else None
        except ValueError:
            value = None
        if value is None:
            raise ValueError(
                f"route_style must be a style (one of {_STYLE_NAMES}) or 'style=weight' pairs joined by commas, got {route_style!r}."
            )
        if _check_style(style, "route_style") in weights:
            raise ValueError(f"route_style names {style!r} twice, in {route_style!r}.")
        weights[style] = value
    return RouteMixture(weights, min_length, max_length)


def route_mixture_for(
    route_style: str | Mapping[str, float] | RouteMixture | None,
    route_lengths: Sequence[int] | None,
    demo_length: int,
) -> RouteMixture | None:
    """The :class:`RouteMixture` an env (or a store) of ``demo_length`` steps samples from.

    Args:
        route_style: as :func:`parse_route_style` reads it, or ``None`` (the planner's routes
            as the paper samples them: no mixture).
        route_lengths: ``(shortest, longest)`` route lengths, steps (``None``: ``demo_length``,
            or the mixture's own lengths when ``route_style`` is one).
        demo_length: the env's demonstration length, to which shorter routes are padded.

    Raises:
        ValueError: ``route_lengths`` without ``route_style``, or with a :class:`RouteMixture`
            (which has its lengths), or lengths outside ``[10, demo_length]``.

    Examples:
        >>> route_mixture_for("driven", (10, 60), demo_length=60).max_length
        60
        >>> route_mixture_for(None, None, 30) is None
        True
        >>> route_mixture_for("tour", (10, 60), demo_length=30)
        Traceback (most recent call last):
        ...
        ValueError: route_lengths must lie in [10, demo_length=30] steps (routes are padded to demo_length), got (10, 60).
    """
    if route_style is None:
        if route_lengths is not None:
            raise ValueError(f"route_lengths needs a route_style (the lengths of its sampled routes), got {tuple(route_lengths)!r}.")
        return None
    if isinstance(route_style, RouteMixture):
        if route_lengths is not None:
            raise ValueError("route_lengths cannot be combined with a RouteMixture route_style, which has its own lengths.")
        mixture = route_style
    else:
        if route_lengths is None:
            low = high = demo_length
        elif not (isinstance(route_lengths, Sequence) and len(route_lengths) == 2):
            raise ValueError(f"route_lengths must be (shortest, longest) steps, got {route_lengths!r}.")
        else:
            low, high = route_lengths
        if isinstance(low, (int, np.integer)) and isinstance(high, (int, np.integer)) and high > demo_length:
            raise ValueError(
                f"route_lengths must lie in [{MIN_STYLE_LENGTH}, demo_length={demo_length}] steps (routes are padded to "
                f"demo_length), got {(low, high)!r}."
            )
        mixture = parse_route_style(route_style, min_length=low, max_length=high)
    if mixture.max_length > demo_length:
        raise ValueError(
            f"route_style's routes are up to {mixture.max_length} steps, longer than demo_length={demo_length}: "
            "give a demo_length of at least the longest route."
        )
    return mixture


__all__ = [
    "DRIVEN",
    "MAX_STYLE_LENGTH",
    "MIN_STYLE_LENGTH",
    "PLANNER",
    "ROUTE_STYLES",
    "TOUR",
    "DrivenStyle",
    "RouteMixture",
    "check_style_length",
    "driven_route",
    "parse_route_style",
    "route_mixture_for",
    "planner_route",
    "sample_route",
    "tour_route",
]
