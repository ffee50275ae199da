"""The follow protocol shared by the environment faces: episodes from a seed, success, SPL, reward.

:class:`~envs.nav_env.PathFollowEnv` (TorchRL) and :mod:`envs.dmc` (dm_control)
run the same task; this module holds the pieces of it that do not depend on the
framework, as plain numpy functions that work on one agent or on a batch:

* :func:`episode_for_seed`: the house and demonstration of an episode seed (for
  the ``follow`` or the ``homing`` task, :mod:`envs.homing`);
* :func:`default_max_steps`: the episode limit of demonstrations of ``n`` steps;
* :class:`FollowRules`: the success radius, the end of an episode (success, STOP,
  step limit), SPL (Anderson et al. 2018) and the dense reward of a step.

Protocol (the paper's, Sec. 4.1): success means ending within
``max(success_radius_m, success_fraction * initial distance)`` (geodesic) of the
route's end; without STOP the episode terminates as soon as the agent is inside
that radius, with STOP when the agent stops; it is truncated after ``max_steps``.

Routes that pass their end before they reach it (:func:`route_excursions`): a tour
or a driven route may come to its end's success radius, leave it and come back (a
third to two fifths of the 31-100-step ones enter it, on average a third of the
way along). Arriving there early is not following the route, so such an episode counts
the agent as arrived only once it has also come within :data:`EXCURSION_REACH_M`
of the far point (apex) of every such excursion, in order. The planner's routes
approach their end monotonically and have none: for them the protocol is the paper's.
The reward is ``progress_reward_per_m`` per metre of geodesic progress, plus
``success_reward`` on success, minus ``step_penalty`` per step.

Episode limit: when no ``max_steps`` is given, it is :func:`default_max_steps`, the
one place the rule lives: ``ceil(MAX_STEPS_PER_DEMO_STEP * n)`` with the ratio 5/3
of the paper's 50 steps for n = 30 (84 for n = 50, 167 for n = 100).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from envs.demos import DEFAULT_SUCCESS_RADIUS_M, Demonstration, sample_demonstration
from envs.expert import STOP
from envs.homing import FOLLOW, task_demonstration
from envs.route_styles import RouteMixture
from envs.scenes import House, build_house

#: Success: within max(SUCCESS_RADIUS_M, SUCCESS_FRACTION x initial distance) of the end.
SUCCESS_RADIUS_M = DEFAULT_SUCCESS_RADIUS_M
SUCCESS_FRACTION = 0.1
#: Dense reward terms: per metre of geodesic progress, on success, per step.
PROGRESS_REWARD_PER_M = 1.0
SUCCESS_REWARD = 2.5
STEP_PENALTY = 0.01
#: The RPF lab code's success, reported beside ours: the horizontal Euclidean distance to the
#: route's end under LAB_SUCCESS_RADIUS_M, or under LAB_SUCCESS_FRACTION x its initial value.
LAB_SUCCESS_RADIUS_M = 0.8
LAB_SUCCESS_FRACTION = 0.1
#: Episode seeds are drawn in [0, MAX_EPISODE_SEED) (they also key the actuation noise).
MAX_EPISODE_SEED = 2**62
#: SPL's denominator never goes below this, metres (a zero-length route and path).
MIN_SPL_DENOMINATOR_M = 1e-9
#: Follow-episode steps allowed per demonstrated step (the paper: 50 steps for n = 30).
MAX_STEPS_PER_DEMO_STEP = Fraction(5, 3)
#: A route passes its end when it comes within this of the success radius (geodesic metres:
#: an agent under noise beside the route may be inside where the route was not) and then
#: leaves that band again: an excursion.
EXCURSION_MARGIN_M = 1.0
#: The agent has made an excursion once it has been within this of its apex, metres.
EXCURSION_REACH_M = 1.0
#: The arrival rule's name, in the identity of results it changes (routes with excursions).
ARRIVAL_RULE = "after-excursions"



def success_radius(
    initial_distance_m: float | np.ndarray, radius_m: float = SUCCESS_RADIUS_M, fraction: float = SUCCESS_FRACTION
) -> float | np.ndarray:
    """Success radius, metres, of an episode starting ``initial_distance_m`` (geodesic) from the route's
    end: ``max(radius_m, fraction x initial_distance_m)`` (the follow protocol's, by default).

    Examples:
        >>> float(success_radius(2.0)), float(success_radius(10.0))
        (0.6, 1.0)
    """
    return np.maximum(radius_m, fraction * initial_distance_m)

def route_excursions(distances_m: np.ndarray, radius_m: float) -> np.ndarray:
    """Indices of the apexes of a route's excursions, in route order.

    A route passes its end when a pose comes within ``radius_m + EXCURSION_MARGIN_M`` of
    it. An excursion is a run of poses outside that band after such a pose (the route came
    near its end and went away again); its apex is its pose farthest from the end. A route
    that approaches its end monotonically, as the planner's do, has none.

    Args:
        distances_m: ``(n + 1,)`` geodesic distance of each demonstrated pose to the route's end.
        radius_m: the success radius of the route, metres.

    Examples:
        >>> route_excursions(np.array([5.0, 3.0, 0.5, 2.0, 3.0, 1.0, 0.0]), 0.6).tolist()  # past the end, out and back
        [4]
        >>> route_excursions(np.array([5.0, 1.2, 4.0, 2.0, 0.0]), 0.6).tolist()  # close by, not inside
        [2]
        >>> route_excursions(np.array([5.0, 3.0, 1.0, 0.5, 0.0]), 0.6).tolist()  # a planner's route
        []
        >>> route_excursions(np.array([5.0, 0.5, 1.4, 0.5, 0.0]), 0.6).tolist()  # a wiggle near the end
        []
    """
    distances_m = np.asarray(distances_m, dtype=np.float64)
    near = distances_m <= radius_m + EXCURSION_MARGIN_M
    apexes: list[int] = []
    i = int(np.argmax(near)) if near.any() else len(near)
    while i < len(near):
        while i < len(near) and near[i]:
            i += 1
        j = i
        while j < len(near) and not near[j]:
            j += 1
        if j == len(near):  # the route ends away from its end's band: nothing to come back from
            break
        apexes.append(i + int(np.argmax(distances_m[i:j])))
        i = j
    return np.array(apexes, dtype=np.int64)


def default_max_steps(demo_length: int) -> int:
    """The episode limit, steps, of demonstrations of ``demo_length`` steps: ``ceil(5/3 * n)``.

    Examples:
        >>> default_max_steps(30), default_max_steps(50), default_max_steps(100)
        (50, 84, 167)
    """
    return math.ceil(MAX_STEPS_PER_DEMO_STEP * int(demo_length))


def episode_for_seed(
    episode_seed: int,
    house_seeds: Sequence[int],
    demo_length: int,
    min_route_length_m: float,
    task: str = FOLLOW,
    route_style: RouteMixture | None = None,
) -> tuple[House, Demonstration]:
    """The house and demonstration of an episode seed.

    The house is drawn from ``house_seeds`` and the route sampled in it, both from
    ``np.random.default_rng(episode_seed)``, so one seed gives the same episode in
    every face of the task; a homing episode plays the homing demonstration of the
    route the follow episode of its seed plays.

    Args:
        episode_seed: the episode's seed, in ``[0, MAX_EPISODE_SEED)``.
        house_seeds: the houses to draw from (a split's seeds).
        demo_length: demonstration length n, steps (with ``route_style``: the longest).
        min_route_length_m: routes ending this close to their start (geodesic, metres)
            are re-drawn (planner routes without ``route_style``).
        task: ``"follow"`` or ``"homing"`` (:mod:`envs.homing`).
        route_style: ``None``: the planner's routes of ``demo_length`` steps, as the paper
            samples them; a :class:`~envs.route_styles.RouteMixture`: a style drawn by its
            weights and a length drawn in its range (:mod:`envs.route_styles`).

    Examples:
        >>> house, demo = episode_for_seed(7, [0, 1], demo_length=5, min_route_length_m=0.6)
        >>> house.seed in (0, 1), demo.actions.shape
        (True, (5,))
        >>> episode_for_seed(7, [0, 1], 5, 0.6, task="homing")[1].end_xy.tolist() == demo.start_pose[:2].tolist()
        True
    """
    rng = np.random.default_rng(episode_seed)
    house = build_house(int(rng.choice(house_seeds)))
    if route_style is None:
        route = sample_demonstration(house, rng, demo_length, min_route_length_m=min_route_length_m)
    else:
        _, route = route_style.sample(house, rng)
    return house, task_demonstration(route, task, house)


@dataclass(frozen=True)
class StepOutcome:
    """What a step means under :class:`FollowRules` (arrays of the agents' shape, or scalars).

    Attributes:
        terminated: success (without STOP) or STOP: a true end, no bootstrapping.
        truncated: the step limit was reached without termination.
        success: the episode ended inside the success radius.
        spl: success weighted by path length, 0 unless ``success``.
        reward: the step's dense reward.
    """

    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    spl: np.ndarray
    reward: np.ndarray

    @property
    def done(self) -> np.ndarray:
        return self.terminated | self.truncated


@dataclass(frozen=True)
class FollowRules:
    """Success, episode end, SPL and reward of the follow protocol.

    Args:
        max_steps: follow-episode limit, steps.
        success_radius_m: minimum success radius, metres.
        success_fraction: success radius as a fraction of the initial distance.
        stop_action: episodes end on STOP (action 3) instead of on arrival.
        progress_reward_per_m: reward per metre of geodesic progress.
        success_reward: reward on success.
        step_penalty: reward subtracted at every step.

    Examples:
        >>> rules = FollowRules(max_steps=50, success_radius_m=0.6, success_fraction=0.1, stop_action=False,
        ...                     progress_reward_per_m=1.0, success_reward=2.5, step_penalty=0.01)
        >>> outcome = rules.score(action=0, distance_m=0.5, previous_distance_m=0.8, initial_distance_m=9.0,
        ...                       path_length_m=9.3, shortest_length_m=9.0, steps=31)
        >>> bool(outcome.success), round(float(outcome.spl), 3), round(float(outcome.reward), 2)
        (True, 0.968, 2.79)
    """

    max_steps: int
    success_radius_m: float
    success_fraction: float
    stop_action: bool
    progress_reward_per_m: float
    success_reward: float
    step_penalty: float

    def radius(self, initial_distance_m: float | np.ndarray) -> float | np.ndarray:
        """Success radius, metres, of episodes starting ``initial_distance_m`` (geodesic) from the end
        (:func:`success_radius` with these rules' radius and fraction)."""
        return success_radius(initial_distance_m, self.success_radius_m, self.success_fraction)

    def score(
        self,
        *,
        action: int | np.ndarray,
        distance_m: float | np.ndarray,
        previous_distance_m: float | np.ndarray,
        initial_distance_m: float | np.ndarray,
        path_length_m: float | np.ndarray,
        shortest_length_m: float | np.ndarray,
        steps: int | np.ndarray,
        max_steps: int | np.ndarray | None = None,
        may_arrive: bool | np.ndarray = True,
    ) -> StepOutcome:
        """Score a step that has just been taken.

        Args:
            action: the action taken (STOP matters only with ``stop_action``).
            distance_m: geodesic distance to the route's end after the step, metres.
            previous_distance_m: the same before the step, metres.
            initial_distance_m: the same at the episode's start, metres.
            path_length_m: length travelled since the start, this step included, metres.
            shortest_length_m: geodesic length of the route, metres.
            steps: steps taken, this one included.
            max_steps: the episode limit, steps, where it is not :attr:`max_steps` (per
                agent, for demonstrations of several lengths: :func:`default_max_steps`).
            may_arrive: whether being inside the radius counts (``False`` until the agent has made
                its route's excursions, :func:`route_excursions`).
        """
        inside = (np.asarray(distance_m) <= self.radius(initial_distance_m)) & np.asarray(may_arrive)
        terminated = (np.asarray(action) == STOP) if self.stop_action else inside
        limit = self.max_steps if max_steps is None else np.asarray(max_steps)
        truncated = (np.asarray(steps) >= limit) & ~terminated
        success = (terminated | truncated) & inside
        denominator = np.maximum(np.maximum(path_length_m, shortest_length_m), MIN_SPL_DENOMINATOR_M)
        spl = np.where(success, shortest_length_m / denominator, 0.0)
        reward = (
            self.progress_reward_per_m * (np.asarray(previous_distance_m) - distance_m)
            + self.success_reward * success
            - self.step_penalty
        )
        return StepOutcome(terminated=terminated, truncated=truncated, success=success, spl=spl, reward=reward)


def lab_success(xy: np.ndarray, end_xy: np.ndarray, start_xy: np.ndarray) -> np.ndarray:
    """The success criterion of the RPF lab code (``bareblackfoot/RobustPathFollow``), per agent.

    Within :data:`LAB_SUCCESS_RADIUS_M` of the route's end, or within
    :data:`LAB_SUCCESS_FRACTION` of the start's distance to it, both horizontal and
    Euclidean. (The lab's ``runner.py`` takes ``position[:2]``, which in Habitat's y-up
    frame is x and height; this is the intended horizontal version.) Ours
    (:class:`FollowRules`) is geodesic.

    Examples:
        >>> lab_success(np.array([[0.0, 0.7], [0.0, 1.0]]), np.zeros((2, 2)), np.array([[0.0, 5.0], [0.0, 20.0]]))
        array([ True,  True])
    """
    distance = np.linalg.norm(np.asarray(xy) - end_xy, axis=-1)
    initial = np.linalg.norm(np.asarray(start_xy) - end_xy, axis=-1)
    return (distance < LAB_SUCCESS_RADIUS_M) | (distance < LAB_SUCCESS_FRACTION * initial)
