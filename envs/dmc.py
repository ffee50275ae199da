"""A dm_control face of the path-following task: ``Physics``, ``Task`` and :func:`load`.

The same task as :class:`~envs.nav_env.PathFollowEnv` (same houses, demonstrations,
motion, success, SPL and reward, see :mod:`envs.follow`), offered as a
:class:`dm_control.rl.control.Environment` for dm_control, dm_env and acme users,
and for TorchRL through :class:`torchrl.envs.DMControlWrapper`.

* :class:`~envs.dmc_physics.HousePhysics`: a :class:`dm_control.mujoco.Physics` of a house model
  (:func:`~envs.house_mesh.house_mjcf`) with a kinematic agent added: a body with two
  slide joints and a hinge, so ``qpos`` = (x m, y m, heading rad) is the agent's
  pose and part of ``physics.get_state()``; the house's ``"eye"`` camera rides on
  it, so ``physics.render(camera_id="eye")`` shows the agent's view. Nothing
  collides and there is no gravity: ``physics.step()`` leaves the pose as the task
  set it. A new house per episode reloads the physics with that house's model
  (compiled once per process, :data:`MODEL_CACHE_SIZE` houses kept).
* :class:`PathFollowTask`: at each episode start, draws an episode seed from
  ``task.random`` (what ``DMControlWrapper.set_seed`` replaces), samples the
  house and demonstration of that seed (:func:`~envs.follow.episode_for_seed`)
  and puts the agent at the route's start. Each step moves the agent by the
  action's nominal motion (:func:`~envs.demos.nominal_motion`), or by a motion
  drawn from a :class:`~envs.transforms.NoiseModel` keyed by (episode seed, step)
  like :class:`~envs.transforms.ActuationNoise`, with the house's collision and
  sliding (:func:`~envs.demos.apply_motion`), then scores it
  (:class:`~envs.follow.FollowRules`).

Actions: ``DiscreteArray(3)``: 0 forward 0.3 m, 1 turn left 20 deg, 2 turn right
20 deg (and 3 STOP with ``stop_action=True``). Rewards are dense (geodesic
progress, success bonus, step cost). Following dm_env, the first time step has
no reward and no discount; a step that succeeds (or STOPs) ends the episode with
discount 0, the step limit (``max_steps``) ends it with discount 1 (a truncation,
which ``DMControlWrapper`` reports as ``truncated``).

Observations (:data:`POLICY_OBSERVATIONS`, then :data:`PRIVILEGED_OBSERVATIONS`,
which policies must not read; ``privileged_observations=False`` leaves them out):

* ``pixels`` ``(H, W, 3)`` uint8, the first-person frame;
* ``demo_frames`` ``(n, H, W, 3)`` uint8 and ``demo_actions`` ``(n,)`` int64, the
  demonstration: the same arrays at every step of an episode (do not write into them);
* ``pose`` (x m, y m, heading rad), ``goal_distance`` (geodesic, m),
  ``path_length`` (m), ``shortest_path_length`` (m), ``success``, ``spl``
  (final at the last step), ``step_count``, ``episode_seed``; and, with
  ``with_expert=True``, ``expert_action``.

Rendering: frames are drawn by :class:`~envs.render.FirstPersonRenderer` from
the physics' own model at the physics' pose, in one GL context per task created
at the first reset (a process that only reads specs opens none). It is an order
of magnitude faster than ``physics.render`` at 64 px (dm_control's ``Camera``
builds and frees a scene per call; the same-run ratio is
``render_first_person_over_render_physics`` in ``benchmarks/results/dmc.json``)
and its frames are the very pixels :class:`~envs.nav_env.PathFollowEnv` and the
demo store emit (the same texture filtering); ``physics.render`` keeps working, in
dm_control's own context, for other cameras or sizes. ``pixels`` is already an
observation: wrap with ``DMControlWrapper(env)``, not ``from_pixels=True`` (which
would render again, with dm_control, under the same key). dm_control picks its GL
back-end when imported, so importing this module first exports the project's
choice (:func:`~envs.render.select_gl_backend`: ``MUJOCO_GL``, ``PYOPENGL_PLATFORM``).

Examples:
    >>> from torchrl.envs import DMControlWrapper
    >>> env = DMControlWrapper(load("train", seed=0, num_houses=2, demo_length=5))
    >>> rollout = env.rollout(3)
    >>> rollout["next", "pixels"].shape, rollout["demo_frames"].shape
    (torch.Size([3, 64, 64, 3]), torch.Size([3, 5, 64, 64, 3]))
    >>> env.close()
"""
from __future__ import annotations

import collections
import logging
from collections.abc import Sequence

import numpy as np

from envs.render import FirstPersonRenderer, RendererUnavailableError, select_gl_backend

logger = logging.getLogger(__name__)

# dm_control picks its GL back-end once, when imported (GLFW first, which fails headless):
# export the project's choice (MUJOCO_GL, PYOPENGL_PLATFORM) before importing it.
try:
    select_gl_backend()
except RendererUnavailableError as error:  # rendering will raise the same advice
    logger.warning("envs.dmc: %s", error)

from dm_control.rl import control
from dm_env import specs

from envs.checks import check_positive_int
from envs.demos import DEFAULT_DEMO_LENGTH, Demonstration, apply_motion, default_min_route_length_m, nominal_motion
from envs.dmc_physics import HousePhysics
from envs.expert import ACTION_NAMES, GeodesicExpert
from envs.follow import (
    MAX_EPISODE_SEED,
    PROGRESS_REWARD_PER_M,
    STEP_PENALTY,
    SUCCESS_FRACTION,
    SUCCESS_RADIUS_M,
    SUCCESS_REWARD,
    FollowRules,
    StepOutcome,
    default_max_steps,
    episode_for_seed,
)
from envs.house_grid import check_demo_length
from envs.nav_env import DEFAULT_IMAGE_SIZE
from envs.scenes import build_house, split_seeds
from envs.specs import NUM_DEMO_ACTIONS, NUM_RGB_CHANNELS
from envs.transforms import NoiseModel, make_noise_model

#: Observations a policy may read, and privileged ones (metrics, plots, labels).
POLICY_OBSERVATIONS = ("pixels", "demo_frames", "demo_actions")
PRIVILEGED_OBSERVATIONS = (
    "pose",
    "goal_distance",
    "path_length",
    "shortest_path_length",
    "success",
    "spl",
    "step_count",
    "episode_seed",
)
#: The noise preset that means "nominal motion" (no draws are made).
NO_NOISE = "none"


class PathFollowTask(control.Task):
    """Follow a demonstrated route in procedural houses (a dm_control ``Task``).

    Args:
        house_seeds: the houses episodes are drawn from (e.g. :func:`~envs.scenes.split_seeds`).

    Keyword Args:
        demo_length: demonstration length n, steps.
        max_steps: follow-episode limit, steps; ``None``: :func:`~envs.follow.default_max_steps`
            of ``demo_length`` (``ceil(5/3 n)``, 50 for n = 30), as for :class:`~envs.nav_env.PathFollowEnv`.
        image_size: side of the square first-person frames, pixels.
        noise: actuation noise: a preset name of :data:`~envs.transforms.NOISE_PRESETS`
            (``"none"``: nominal motion) or a :class:`~envs.transforms.NoiseModel`.
        stop_action: add a STOP action (3) that ends the episode.
        with_expert: add the ``expert_action`` observation (the expert's action now).
        privileged_observations: emit :data:`PRIVILEGED_OBSERVATIONS`.
        success_radius_m: minimum success radius, metres.
        success_fraction: success radius as a fraction of the initial distance.
        random: a ``numpy.random.RandomState``, an int seed or ``None`` (dm_control
            suite convention); ``task.random`` draws every episode.

    Examples:
        >>> task = PathFollowTask([0, 1], demo_length=5, random=0)
        >>> task.action_spec(None).num_values
        3
    """

    def __init__(
        self,
        house_seeds: Sequence[int],
        *,
        demo_length: int = DEFAULT_DEMO_LENGTH,
        max_steps: int | None = None,
        image_size: int = DEFAULT_IMAGE_SIZE,
        noise: str | NoiseModel = NO_NOISE,
        stop_action: bool = False,
        with_expert: bool = False,
        privileged_observations: bool = True,
        success_radius_m: float = SUCCESS_RADIUS_M,
        success_fraction: float = SUCCESS_FRACTION,
        random: np.random.RandomState | int | None = None,
    ) -> None:
        check_demo_length(demo_length)
        max_steps = default_max_steps(demo_length) if max_steps is None else max_steps
        for name, value in (("max_steps", max_steps), ("image_size", image_size)):
            check_positive_int(name, value)
        house_seeds = list(house_seeds)
        if not house_seeds or not all(_is_int(s) and s >= 0 for s in house_seeds):
            raise ValueError(f"house_seeds must be a non-empty sequence of non-negative ints, got {house_seeds!r}.")
        if not success_radius_m > 0:
            raise ValueError(f"success_radius_m must be > 0 (metres), got {success_radius_m!r}.")
        if not success_fraction >= 0:
            raise ValueError(f"success_fraction must be >= 0, got {success_fraction!r}.")
        if not (random is None or _is_int(random) or isinstance(random, np.random.RandomState)):
            raise ValueError(f"random must be None, an int seed or a numpy RandomState, got {random!r}.")
        self.house_seeds = [int(s) for s in house_seeds]
        self.demo_length = int(demo_length)
        self.image_size = int(image_size)
        self.noise_model = make_noise_model(noise)
        self._noisy = self.noise_model != make_noise_model(NO_NOISE)
        self.with_expert = bool(with_expert)
        self.privileged_observations = bool(privileged_observations)
        self.num_actions = NUM_DEMO_ACTIONS + int(stop_action)
        self.rules = FollowRules(
            max_steps=int(max_steps),
            success_radius_m=float(success_radius_m),
            success_fraction=float(success_fraction),
            stop_action=bool(stop_action),
            progress_reward_per_m=PROGRESS_REWARD_PER_M,
            success_reward=SUCCESS_REWARD,
            step_penalty=STEP_PENALTY,
        )
        self._min_route_length_m = default_min_route_length_m(self.demo_length, self.rules.success_radius_m)
        self._random = random if isinstance(random, np.random.RandomState) else np.random.RandomState(random)
        self._renderer: FirstPersonRenderer | None = None  # created at the first render
        self._demo: Demonstration | None = None

    @property
    def random(self) -> np.random.RandomState:
        """The task's random state (``DMControlWrapper.set_seed`` replaces ``task._random``)."""
        return self._random

    @property
    def demonstration(self) -> Demonstration | None:
        """The current episode's demonstration (``None`` before the first reset)."""
        return self._demo

    # ------------------------------------------------------------------ specs
    def action_spec(self, physics: HousePhysics | None) -> specs.DiscreteArray:
        """``DiscreteArray(3)`` (``4`` with STOP): forward 0.3 m, left 20 deg, right 20 deg (, stop)."""
        return specs.DiscreteArray(self.num_actions, dtype=np.int64, name="action")

    def observation_spec(self, physics: HousePhysics | None) -> collections.OrderedDict:
        """Specs of :data:`POLICY_OBSERVATIONS` (and privileged ones when enabled)."""
        frame = (self.image_size, self.image_size, NUM_RGB_CHANNELS)
        spec = collections.OrderedDict(
            pixels=specs.Array(frame, np.uint8, name="pixels"),
            demo_frames=specs.Array((self.demo_length, *frame), np.uint8, name="demo_frames"),
            demo_actions=specs.BoundedArray(
                (self.demo_length,), np.int64, minimum=0, maximum=NUM_DEMO_ACTIONS - 1, name="demo_actions"
            ),
        )
        if self.privileged_observations:
            spec["pose"] = specs.Array((3,), np.float64, name="pose")
            for name in ("goal_distance", "path_length", "shortest_path_length"):
                spec[name] = specs.Array((), np.float64, name=name)
            spec["success"] = specs.Array((), np.bool_, name="success")
            spec["spl"] = specs.Array((), np.float64, name="spl")
            spec["step_count"] = specs.Array((), np.int64, name="step_count")
            spec["episode_seed"] = specs.Array((), np.int64, name="episode_seed")
        if self.with_expert:
            spec["expert_action"] = specs.BoundedArray(
                (), np.int64, minimum=0, maximum=self.num_actions - 1, name="expert_action"
            )
        return spec

    # ---------------------------------------------------------------- episode
    def initialize_episode(self, physics: HousePhysics) -> None:
        """Draw an episode seed from :attr:`random`, load its house and place the agent at the route's start."""
        episode_seed = int(self._random.randint(MAX_EPISODE_SEED, dtype=np.int64))
        house, demo = episode_for_seed(episode_seed, self.house_seeds, self.demo_length, self._min_route_length_m)
        physics.load_house(house)
        physics.set_agent_pose(demo.start_pose)
        self._house, self._demo, self._episode_seed = house, demo, episode_seed
        self._view = physics.first_person_view
        self._expert = GeodesicExpert(
            house.occupancy,
            demo.end_field,
            stop_radius_m=self.rules.radius(demo.shortest_length_m) if self.rules.stop_action else None,
        )
        self._steps = 0
        self._path_length_m = 0.0
        self._distance_m = demo.end_field.at(demo.start_pose[:2])
        self._initial_distance_m = self._distance_m
        self._outcome: StepOutcome | None = None
        self._travelled_m = 0.0
        self._action = 0
        # new arrays per episode, never written afterwards: every time step of the episode shares them
        self._demo_frames = self.renderer.render_many([self._view] * self.demo_length, demo.poses[: self.demo_length])
        self._demo_actions = demo.actions.astype(np.int64)

    def before_step(self, action: int | np.ndarray, physics: HousePhysics) -> None:
        """Move the agent by ``action``'s (noisy) motion, with collisions and sliding."""
        if self._demo is None:
            raise RuntimeError(
                "PathFollowTask.before_step() was called before an episode started: call env.reset() first."
            )
        self._action = self._checked_action(action)
        if self._noisy:
            motion = self.noise_model.sample(
                np.array([self._action]), np.array([self._episode_seed]), np.array([self._steps])
            )
        else:
            motion = nominal_motion(np.array([self._action]))
        pose, travelled = apply_motion(self._house, physics.agent_pose()[None], motion)
        physics.set_agent_pose(pose[0])
        self._travelled_m = float(travelled[0])

    def after_step(self, physics: HousePhysics) -> None:
        """Measure the step from the physics' pose and score it."""
        previous = self._distance_m
        self._distance_m = self._demo.end_field.at(physics.agent_pose()[:2])
        self._path_length_m += self._travelled_m
        self._steps += 1
        self._outcome = self.rules.score(
            action=self._action,
            distance_m=self._distance_m,
            previous_distance_m=previous,
            initial_distance_m=self._initial_distance_m,
            path_length_m=self._path_length_m,
            shortest_length_m=self._demo.shortest_length_m,
            steps=self._steps,
        )

    def get_reward(self, physics: HousePhysics) -> float:
        """The last step's dense reward (progress, success bonus, step cost)."""
        return float(self._outcome.reward)

    def get_termination(self, physics: HousePhysics) -> float | None:
        """``0.0`` on success (or STOP), ``1.0`` at the step limit (a truncation), else ``None``."""
        outcome = self._outcome
        if outcome is None or not outcome.done:
            return None
        return 0.0 if outcome.terminated else 1.0

    def get_observation(self, physics: HousePhysics) -> collections.OrderedDict:
        """The first-person frame at the physics' pose, the demonstration, and privileged values."""
        pose = physics.agent_pose()
        observation = collections.OrderedDict(
            pixels=self.renderer.render(self._view, pose),
            demo_frames=self._demo_frames,
            demo_actions=self._demo_actions,
        )
        if self.privileged_observations:
            outcome = self._outcome
            observation["pose"] = pose
            observation["goal_distance"] = np.float64(self._distance_m)
            observation["path_length"] = np.float64(self._path_length_m)
            observation["shortest_path_length"] = np.float64(self._demo.shortest_length_m)
            observation["success"] = np.bool_(outcome is not None and outcome.success)
            observation["spl"] = np.float64(0.0 if outcome is None else outcome.spl)
            observation["step_count"] = np.int64(self._steps)
            observation["episode_seed"] = np.int64(self._episode_seed)
        if self.with_expert:
            observation["expert_action"] = np.int64(self._expert.action(pose))
        return observation

    # -------------------------------------------------------------- rendering
    @property
    def renderer(self) -> FirstPersonRenderer:
        """The task's first-person renderer (its GL context is created at the first render)."""
        if self._renderer is None:
            self._renderer = FirstPersonRenderer(self.image_size, self.image_size)
        return self._renderer

    def close(self) -> None:
        """Free the renderer's GL context (a later render creates a new one)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _checked_action(self, action: int | np.ndarray) -> int:
        array = np.asarray(action)
        if array.size != 1 or array.dtype.kind not in "iu" or not 0 <= int(array.reshape(())) < self.num_actions:
            allowed = ", ".join(f"{index} {name}" for index, name in enumerate(ACTION_NAMES[: self.num_actions]))
            raise ValueError(f"action must be one integer in [0, {self.num_actions - 1}] ({allowed}), got {action!r}.")
        return int(array.reshape(()))


class PathFollowEnvironment(control.Environment):
    """A :class:`dm_control.rl.control.Environment` whose :meth:`close` frees the task's renderer."""

    def close(self) -> None:
        """Free the renderer's GL context and the physics (the environment cannot be used afterwards)."""
        self.task.close()
        self.physics.free()


def load(
    split: str = "train",
    seed: np.random.RandomState | int | None = None,
    *,
    num_houses: int | None = None,
    house_seeds: Sequence[int] | None = None,
    environment_kwargs: dict | None = None,
    **task_kwargs,
) -> PathFollowEnvironment:
    """The path-following task as a dm_control environment (``suite.load`` style).

    Args:
        split: ``"train"``, ``"val"`` or ``"test"``: the house seeds to draw from.
        seed: the task's random state or its seed (``None``: fresh entropy).

    Keyword Args:
        num_houses: houses in the split (default 61 / 11 / 18); may be larger.
        house_seeds: explicit house seeds (instead of ``split``/``num_houses``).
        environment_kwargs: passed to :class:`dm_control.rl.control.Environment`
            (e.g. ``time_limit``, ``legacy_step``).
        **task_kwargs: passed to :class:`PathFollowTask` (``demo_length``,
            ``max_steps``, ``image_size``, ``noise``, ``stop_action``, ``with_expert``,
            ``privileged_observations``, ``success_radius_m``, ``success_fraction``).

    Examples:
        >>> env = load("train", seed=0, num_houses=2, demo_length=5)
        >>> timestep = env.reset()
        >>> timestep.observation["pixels"].shape, timestep.observation["demo_frames"].shape
        ((64, 64, 3), (5, 64, 64, 3))
        >>> timestep = env.step(0)
        >>> timestep.discount, int(timestep.observation["step_count"])
        (1.0, 1)
        >>> env.close()
    """
    if house_seeds is not None:
        if num_houses is not None:
            raise ValueError("pass either house_seeds or num_houses, not both (house_seeds fixes the houses).")
    else:
        house_seeds = split_seeds(split, num_houses)
    task = PathFollowTask(house_seeds, random=seed, **task_kwargs)
    physics = HousePhysics.from_house(build_house(task.house_seeds[0]))
    return PathFollowEnvironment(physics, task, **(environment_kwargs or {}))


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)
