"""``PathFollowEnv``: follow a demonstrated route in a procedural house, as a TorchRL env.

Each episode samples a house of the split and a demonstration in it (see
:mod:`envs.demos`); the agent starts at the demonstration's first pose and must
reach its end under actuation noise (:class:`~envs.transforms.ActuationNoise`),
seeing only its first-person camera and the demonstration (frames and actions).
With ``task="homing"`` the agent starts at the route's end and must return to its
start; the demonstration is then the route driven back, its frames rendered
looking back along the route (:mod:`envs.homing`). Long routes are sampled in larger
houses (:func:`~envs.house_grid.default_grid_size_cells`) and get a longer step
limit (:func:`~envs.follow.default_max_steps`: ``ceil(5/3 n)``, 50 for n = 30).

Protocol (the paper's, Sec. 4.1; :mod:`envs.follow`): forward 0.3 m, turns of 20 deg
(and STOP with ``stop_action=True``); success, SPL, termination and the dense reward
are :class:`~envs.follow.FollowRules`' (a route that passes its end before reaching it
counts arrival only after its excursions, :func:`~envs.follow.route_excursions`); the final step reports ``success``, ``spl``,
``goal_distance`` and ``path_length``, and how closely the path followed the route
(:mod:`envs.path_fidelity`): ``ndtw`` and ``sdtw`` against the demonstrated positions,
with the success radius as threshold, and ``path_length_ratio`` (travelled over
demonstrated length); ``wall_hits`` counts the forward steps a wall cut short.

Per-episode data (``demo_frames``, ``demo_actions``) is emitted at every step
(``ParallelEnv`` drops keys that only ``_reset`` emits). ``success_lab`` is the RPF
lab code's criterion (:func:`~envs.follow.lab_success`), reported beside ours.

Demonstrations are sampled and rendered at each episode start, or, with
``demo_store``, drawn from a :class:`~envs.demo_store.DemoStore` of pre-rendered
demonstrations (nothing is rendered or planned at reset but the route's distance
field); the env then also emits ``demo_id``, and with ``emit_demo_frames=False``
emits it *instead of* ``demo_frames`` (30 frames less per step), for policies that
look the frames up in the store (:meth:`~envs.demo_store.DemoStore.lookup_module`).

Frames are HWC uint8, as TorchRL's pixel envs emit them (see :mod:`envs.specs`).
``pose``, ``goal_distance``, ``house_seed``, ``expert_action``, ``route_step`` and the episode metrics are
privileged keys (:data:`~envs.specs.PRIVILEGED_KEYS`) for metrics, plotting and
labelling; append :class:`~envs.specs.HidePrivileged` to hide them from a policy.

With ``num_agents=N`` the env is batched (``batch_size=[N]``): N agents, each in
its own episode and house, stepped and rendered in one process.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from envs.checks import check_action, check_actuation_noise, check_positive_int, resolve_houses
from envs.conditions import ConditionMixture, Repeat, check_mismatch, draw_repeat, draws_mismatch, parse_conditions
from envs.demo_store import DemoStore
from envs.demos import DEFAULT_DEMO_LENGTH, Demonstration, default_min_route_length_m, move_agents, nominal_motion
from envs.episode_numbering import EpisodeNumbering
from envs.episode_spec import EpisodeSpec
from envs.expert import WALL_CONTACT_TOLERANCE_M, GeodesicExpert
from envs.follow import (
    EXCURSION_REACH_M,
    PROGRESS_REWARD_PER_M,
    STEP_PENALTY,
    SUCCESS_FRACTION,
    SUCCESS_RADIUS_M,
    SUCCESS_REWARD,
    FollowRules,
    default_max_steps,
    lab_success,
    route_excursions,
)
from envs.homing import FOLLOW, check_task
from envs.house_grid import check_demo_length
from envs.path_fidelity import path_fidelity
from envs.playlist import DemonstrationPlaylist, EpisodeSource
from envs.render import FirstPersonRenderer
from envs.route_expert import EXPERTS, RouteExpert
from envs.route_styles import RouteMixture, route_mixture_for
from envs.scenes import House
from envs.specs import NUM_DEMO_ACTIONS, NUM_RGB_CHANNELS, path_follow_specs
from envs.transforms import ACTUATION_NOISE_KEY

logger = logging.getLogger(__name__)

#: Default first-person frame size, pixels.
DEFAULT_IMAGE_SIZE = 64
#: Follow-episode limit of the default demonstration length, steps (the paper's 50);
#: other lengths: :func:`~envs.follow.default_max_steps`.
DEFAULT_MAX_STEPS = default_max_steps(DEFAULT_DEMO_LENGTH)


class PathFollowEnv(EnvBase):
    """Visual path following in procedural labmaze houses (MuJoCo, headless).

    Args:
        split: ``"train"``, ``"val"`` or ``"test"``: the house seeds to sample from.

    Keyword Args:
        num_houses: houses in the split (default 61 / 11 / 18); may be larger.
        house_seeds: explicit house seeds (overrides ``split``/``num_houses``).
        num_agents: ``None`` for an unbatched env (``batch_size=[]``, for
            ``ParallelEnv`` workers) or N for a batched env of N agents.
        demo_length: demonstration length n, steps.
        max_steps: follow-episode limit, steps (``None``: ``ceil(5/3 n)``,
            :func:`~envs.follow.default_max_steps`; 50 for n = 30).
        task: ``"follow"`` (reach the route's end) or ``"homing"`` (start at its end,
            return to its start; :mod:`envs.homing`).
        grid_size_cells: labmaze grid of the split's houses, odd, cells of 1 m (``None``:
            15 up to n = 30, larger for longer routes,
            :func:`~envs.house_grid.default_grid_size_cells`); not with ``house_seeds``.
        image_size: side of the square first-person frames, pixels.
        stop_action: add a STOP action (index 3) that ends the episode.
        with_expert: also emit ``expert_action``, the action of ``expert`` at every step, and with
            the route expert ``route_step``, the demonstration step the agent has come to
            (:meth:`~envs.route_expert.RouteExpert.route_step`: a label for a policy's pointer).
        expert: ``"goal"``: the shortest way to the route's end (:class:`~envs.expert.GeodesicExpert`);
            ``"route"``: along the route's path (:class:`~envs.route_expert.RouteExpert`). ``None``
            (default): ``"route"`` with ``route_style`` or ``demonstrations``, ``"goal"`` for the
            planner's routes (on which both take the same path).
        render: render frames; ``False`` emits black frames (``pixels``, and the
            demonstration's frames unless they come from ``demo_store``) and never
            opens an OpenGL context (fast protocol statistics, expert labelling).
        success_radius_m: minimum success radius, metres.
        success_fraction: success radius as a fraction of the initial distance.
        demo_store: a :class:`~envs.demo_store.DemoStore` (or its directory) to draw
            each episode's demonstration from instead of sampling and rendering one;
            its split, house count, grid, ``demo_length``, ``image_size`` and ``task`` must
            match the env's. Adds the ``demo_id`` observation.
        emit_demo_frames: emit ``demo_frames`` at every step (default). ``False`` leaves them
            out; it needs ``demo_store`` (policies look them up by ``demo_id``) or ``render=False``.
        demonstrations: routes of 1 to ``demo_length`` steps to play instead of sampled ones
            (:class:`~envs.playlist.DemonstrationPlaylist`; ``reset(demonstration=demo)``);
            a homing env plays their homing demonstrations.
        route_style: the style of sampled routes (:mod:`envs.route_styles`): ``"planner"``,
            ``"tour"``, ``"driven"``, a mixture of them by weight (``{"planner": 0.5,
            "driven": 0.5}`` or ``"planner=0.5,driven=0.5"``) or a
            :class:`~envs.route_styles.RouteMixture`. ``None`` (default): the planner's
            routes as the paper samples them.
        route_lengths: ``(shortest, longest)`` steps of sampled routes with ``route_style``,
            each route's length drawn uniformly in it (``None``: ``demo_length`` exactly);
            ``longest`` is at most ``demo_length``, to which shorter demonstrations are padded.
        conditions: repeat conditions (:mod:`envs.conditions`: ``"light@0.5"``, a mixture
            ``"light@0.5=1,furniture@1=1"``, or a :class:`~envs.conditions.ConditionMixture`),
            one drawn per episode from its seed: the agent's world changes, the demonstration
            stays the teaching world's. Adds ``condition`` (its index in
            :data:`~envs.conditions.CONDITIONS`) and ``condition_strength``. ``None`` (default): none.
        memory_mismatch: the fraction of episodes (drawn from each episode's seed) whose
            demonstration frames are another route's, its actions the episode's own. Adds
            ``memory_mismatched``, and with ``demo_store`` ``memory_id`` (the stored
            demonstration whose frames are shown; ``demo_id`` stays the episode's). ``None``: none.
        episode_offset, episode_stride: episode numbering (:mod:`envs.episode_numbering`): agent
            ``i``'s ``k``-th episode is number ``offset + stride * (i + k * N)``, its seed a
            function of the env seed and that number alone; emitted as ``episode_index``. They
            live in ``env.numbering``: a new ``numbering.offset`` applies from the next ``set_seed``.
        seed: optional seed (same as calling :meth:`set_seed`).
        device: torch device of the outputs.

    Examples:
        >>> env = PathFollowEnv("train", num_houses=2, demo_length=10)
        >>> _ = env.set_seed(0)
        >>> td = env.reset()
        >>> td["pixels"].shape, td["demo_frames"].shape, td["demo_actions"].shape
        (torch.Size([64, 64, 3]), torch.Size([10, 64, 64, 3]), torch.Size([10]))
        >>> td = env.rand_step(td)
        >>> td["next", "reward"].shape
        torch.Size([1])
    """

    def __init__(
        self,
        split: str = "train",
        *,
        num_houses: int | None = None,
        house_seeds: Sequence[int] | None = None,
        num_agents: int | None = None,
        demo_length: int = DEFAULT_DEMO_LENGTH,
        max_steps: int | None = None,
        image_size: int = DEFAULT_IMAGE_SIZE,
        task: str = FOLLOW,
        grid_size_cells: int | None = None,
        stop_action: bool = False,
        with_expert: bool = False,
        expert: str | None = None,
        render: bool = True,
        success_radius_m: float = SUCCESS_RADIUS_M,
        success_fraction: float = SUCCESS_FRACTION,
        demo_store: DemoStore | str | os.PathLike | None = None,
        emit_demo_frames: bool = True,
        demonstrations: Sequence[Demonstration] | None = None,
        route_style: str | Mapping[str, float] | RouteMixture | None = None,
        route_lengths: tuple[int, int] | None = None,
        conditions: str | Mapping[str, float] | ConditionMixture | None = None,
        memory_mismatch: float | None = None,
        episode_offset: int = 0,
        episode_stride: int = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        check_demo_length(demo_length)
        if expert not in (*EXPERTS, None):
            raise ValueError(f"expert must be one of {', '.join(map(repr, EXPERTS))} or None, got {expert!r}.")
        route_mixture = route_mixture_for(route_style, route_lengths, demo_length)
        self.conditions = parse_conditions(conditions)
        self.memory_mismatch = check_mismatch(memory_mismatch)
        self._fixed_max_steps = max_steps is not None
        max_steps = default_max_steps(demo_length) if max_steps is None else max_steps
        check_positive_int("max_steps", max_steps)
        check_positive_int("image_size", image_size)
        self.task = check_task(task)
        if num_agents is not None:
            check_positive_int("num_agents", num_agents)
        if success_radius_m <= 0 or success_fraction < 0:
            raise ValueError(
                f"success_radius_m must be > 0 metres and success_fraction >= 0, got {success_radius_m}, {success_fraction}."
            )
        demo_store, house_seeds = resolve_houses(
            split, num_houses, house_seeds, demo_store, emit_demo_frames or not render, demo_length, image_size, success_radius_m,
            self.task, grid_size_cells, route_mixture,
        )
        if self.memory_mismatch and demo_store is not None and len(demo_store) < 2:
            raise ValueError(
                f"memory_mismatch={self.memory_mismatch} needs a demo_store of at least 2 demonstrations "
                f"(another route's frames), {demo_store.root} holds {len(demo_store)}."
            )
        self.route_style = route_mixture
        batch_size = torch.Size([] if num_agents is None else [num_agents])
        super().__init__(device=device, batch_size=batch_size)
        self.split = split
        self.house_seeds = house_seeds
        self.num_agents = num_agents
        self._count = 1 if num_agents is None else num_agents
        self.demo_length = int(demo_length)
        self.max_steps = int(max_steps)
        self.image_size = int(image_size)
        self.stop_action = bool(stop_action)
        self.with_expert = bool(with_expert)
        self.expert = expert or ("route" if route_mixture is not None or demonstrations is not None else "goal")
        self.render_frames = bool(render)
        self.success_radius_m = float(success_radius_m)
        self.success_fraction = float(success_fraction)
        self.rules = FollowRules(
            max_steps=self.max_steps,
            success_radius_m=self.success_radius_m,
            success_fraction=self.success_fraction,
            stop_action=self.stop_action,
            progress_reward_per_m=PROGRESS_REWARD_PER_M,
            success_reward=SUCCESS_REWARD,
            step_penalty=STEP_PENALTY,
        )
        self.demo_store = demo_store
        self.emit_demo_frames = bool(emit_demo_frames)
        self.num_actions = NUM_DEMO_ACTIONS + int(self.stop_action)
        self._renderer: FirstPersonRenderer | None = None  # created at the first reset
        self._playlist = DemonstrationPlaylist(demonstrations, self.demo_length, self._count, demo_store is not None, self.task)
        self._source = EpisodeSource(
            house_seeds, self.demo_length, default_min_route_length_m(self.demo_length, self.success_radius_m),
            self.task, self._playlist, demo_store, route_mixture,
        )
        self._cpu = self.device is not None and torch.device(self.device).type == "cpu"
        self.numbering = EpisodeNumbering(self._count, episode_offset, episode_stride)
        self._set_seed(seed)
        self._make_specs()
        self._init_state()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        specs = path_follow_specs(
            self.batch_size,
            image_size=self.image_size,
            demo_length=self.demo_length,
            num_actions=self.num_actions,
            emit_demo_frames=self.emit_demo_frames,
            with_demo_id=self.demo_store is not None,
            with_expert=self.with_expert,
            device=self.device,
            with_route_step=self.with_route_step,
            with_conditions=self.conditions is not None,
            with_mismatch=self.memory_mismatch is not None,
        )
        self.observation_spec = specs["observation"]
        self.action_spec = specs["action"]
        self.state_spec = specs["state"]
        self.reward_spec = specs["reward"]
        self.done_spec = specs["done"]

    def _init_state(self) -> None:
        count, n, size = self._count, self.demo_length, self.image_size
        self._houses: list[House | None] = [None] * count  # where the agent is (the repeat's layout)
        self._teach_houses: list[House | None] = [None] * count  # where the route was taught
        self._repeats: list[Repeat | None] = [None] * count
        self._condition = np.zeros(count, dtype=np.int64)
        self._condition_strength = np.zeros(count, dtype=np.float32)
        self._mismatched = np.zeros(count, dtype=bool)
        self._memory_id = np.zeros(count, dtype=np.int64)
        self._demos: list[Demonstration | None] = [None] * count
        self._experts: list[GeodesicExpert | RouteExpert | None] = [None] * count
        self._pose = np.zeros((count, 3))
        self._steps = np.zeros(count, dtype=np.int64)
        self._path_length = np.zeros(count)
        self._distance = np.zeros(count)
        self._initial_distance = np.ones(count)
        self._start_xy, self._end_xy, self._lab_success = np.zeros((count, 2)), np.zeros((count, 2)), np.zeros(count, dtype=bool)
        self._shortest = np.zeros(count)
        # each demonstration's own length (<= demo_length, to which it is padded) and episode limit
        self._demo_steps = np.full(count, n, dtype=np.int64)
        self._max_steps = np.full(count, self.max_steps, dtype=np.int64)
        self._episode_seed = np.zeros(count, dtype=np.int64)
        self._episode_index = np.zeros(count, dtype=np.int64)
        self._demo_id, self._house_seed = np.zeros(count, dtype=np.int64), np.zeros(count, dtype=np.int64)
        self._success, self._spl = np.zeros(count, dtype=bool), np.zeros(count)
        # positions since the episode's start (start included), and the path-fidelity scores
        self._trail = np.zeros((count, self.max_steps + 1, 2))
        self._fidelity = np.zeros((count, 3))  # ndtw, sdtw, path_length_ratio
        self._wall_hits = np.zeros(count, dtype=np.int64)
        # apexes of each route's excursions (envs.follow.route_excursions) and how many the agent has made
        self._excursions: list[np.ndarray] = [np.zeros((0, 2))] * count
        self._excursions_made = np.zeros(count, dtype=np.int64)
        self._excursion_counts = np.zeros(count, dtype=np.int64)
        # (count, 0, ...) when the frames are not emitted: the per-episode copies cost nothing
        self._demo_frames = torch.zeros(
            (count, n if self.emit_demo_frames else 0, size, size, NUM_RGB_CHANNELS), dtype=torch.uint8
        )
        self._demo_actions = torch.zeros((count, n), dtype=torch.int64)
        self._pixels = torch.zeros((count, size, size, NUM_RGB_CHANNELS), dtype=torch.uint8)
        self._zero_noise = torch.zeros((*self.batch_size, 3), dtype=torch.float32)

    @classmethod
    def from_spec(cls, episodes: EpisodeSpec, num_agents: int | None = None, **options) -> PathFollowEnv:
        """The env that plays ``episodes`` (an :class:`~envs.episode_spec.EpisodeSpec`): its houses,
        lengths, step limit, frame size, task and routes. The spec's noise is applied by
        :class:`~envs.transforms.ActuationNoise` around the env (:func:`envs.factory.make_env`
        builds the whole stack), and its seed by ``set_seed``.

        Args:
            episodes: the episodes.
            num_agents: ``None`` (unbatched) or the number of agents.
            **options: the env's other keyword arguments (``render``, ``with_expert``,
                ``demo_store``, ``episode_offset``, ...), never one the spec holds.

        Examples:
            >>> env = PathFollowEnv.from_spec(EpisodeSpec(num_houses=1, demo_length=5), num_agents=2, render=False)
            >>> env.batch_size, env.max_steps
            (torch.Size([2]), 9)
        """
        return cls(
            episodes.split,
            num_houses=episodes.num_houses,
            house_seeds=episodes.house_seeds,
            num_agents=num_agents,
            demo_length=episodes.demo_length,
            max_steps=episodes.max_steps,
            image_size=episodes.image_size,
            task=episodes.task,
            route_style=episodes.route_style,
            route_lengths=episodes.route_lengths,
            conditions=episodes.conditions,
            memory_mismatch=episodes.memory_mismatch,
            **options,
        )

    # ---------------------------------------------------------------- seeding
    def _set_seed(self, seed: int | None) -> None:
        # agent i's k-th episode is a fixed episode number, whatever the other agents do
        self.numbering.reset(self._source.env_seed(seed))
        self._playlist.restart()

    # ------------------------------------------------------------- rendering
    @property
    def renderer(self) -> FirstPersonRenderer:
        if self._renderer is None:
            self._renderer = FirstPersonRenderer(self.image_size, self.image_size)
        return self._renderer

    def _render(
        self, indices: Sequence[int], poses: np.ndarray | None = None, out: np.ndarray | None = None, houses: Sequence[House] | None = None
    ) -> np.ndarray:
        """Frames ``(len(indices), H, W, 3)`` of agents at their (or the given) poses, as each
        agent sees its repeat (:mod:`envs.conditions`), or, given ``houses``, as the teacher saw them.

        ``out`` may be any ``(len(indices), H, W, 3)`` uint8 array (e.g. a tensor's
        ``.numpy()`` view), so that frames land in their final place with one copy.
        """
        if out is None:
            out = np.zeros((len(indices), self.image_size, self.image_size, 3), dtype=np.uint8)
        if not self.render_frames:
            out[...] = 0
            return out
        poses = self._pose[list(indices)] if poses is None else poses
        if houses is not None:
            return self.renderer.render_many(houses, poses, out=out)
        repeats = [self._repeats[index] for index in indices]
        if all(repeat is None for repeat in repeats):
            return self.renderer.render_many([self._houses[index] for index in indices], poses, out=out)
        views = [None if repeat is None else repeat.view for repeat in repeats]
        self.renderer.render_many([self._houses[index] for index in indices], poses, out=out, views=views)
        for row, repeat in enumerate(repeats):
            if repeat is not None and repeat.sensor is not None:
                repeat.sense(out[row : row + 1])
        return out

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        partial = tensordict is not None and "_reset" in tensordict.keys()
        indices = np.flatnonzero(tensordict.get("_reset").reshape(self._count).cpu().numpy() if partial else np.ones(self._count))
        self._playlist.begin_reset(kwargs.get("demonstration"))
        if len(indices):
            # returned tensors are never mutated later: new ones, holding the other agents' data
            if len(indices) == self._count:
                demo_frames = torch.empty_like(self._demo_frames)
                demo_actions = torch.empty_like(self._demo_actions)
                pixels = torch.empty_like(self._pixels)
            else:
                demo_frames = self._demo_frames.clone()
                demo_actions = self._demo_actions.clone()
                pixels = self._pixels.clone()
            for index in indices:
                self._start_episode(int(index), demo_frames, demo_actions, pixels)
            self._demo_frames, self._demo_actions, self._pixels = demo_frames, demo_actions, pixels
        zeros = np.zeros(self._count, dtype=bool)
        return self._observation(zeros, zeros, zeros, reward=None)

    def _start_episode(self, index: int, demo_frames: torch.Tensor, demo_actions: torch.Tensor, pixels: torch.Tensor) -> None:
        self._episode_index[index], episode_seed = self.numbering.next(index)
        taught, taught_demo, self._demo_id[index] = self._source.episode(index, episode_seed, self._episode_index[index])
        repeat = None if self.conditions is None else draw_repeat(self.conditions, taught, taught_demo, episode_seed)
        # the agent's world: the repeat's layout and the route's distances in it
        house, demo = (taught, taught_demo) if repeat is None else (repeat.house, repeat.demonstration)
        self._repeats[index] = repeat if repeat is not None and repeat.changes_frames else None
        if repeat is not None:
            self._condition[index], self._condition_strength[index] = repeat.condition.index, repeat.condition.strength
        self._houses[index], self._teach_houses[index], self._house_seed[index] = house, taught, house.seed
        self._demos[index] = demo
        stop_radius_m = self.rules.radius(demo.shortest_length_m) if self.stop_action else None
        if self.expert == "goal":
            self._experts[index] = GeodesicExpert(house.occupancy, demo.end_field, stop_radius_m=stop_radius_m)
        else:
            self._experts[index] = RouteExpert(house, demo, stop_radius_m=stop_radius_m, check_replay=house is not taught)
        self._episode_seed[index] = episode_seed
        self._pose[index] = demo.start_pose
        self._steps[index] = 0
        self._path_length[index] = 0.0
        self._distance[index] = demo.end_field.at(demo.start_pose[:2])
        self._initial_distance[index] = self._distance[index]
        apexes = route_excursions(demo.end_field.at_many(demo.poses[:, :2]), self.rules.radius(self._distance[index]))
        self._excursions[index] = demo.poses[apexes, :2]
        self._excursion_counts[index], self._excursions_made[index] = len(apexes), 0
        self._start_xy[index], self._end_xy[index], self._lab_success[index] = demo.start_pose[:2], demo.end_xy, False
        self._shortest[index] = demo.shortest_length_m
        steps = self._demo_steps[index] = demo.length
        self._max_steps[index] = self.max_steps if self._fixed_max_steps else default_max_steps(steps)
        self._success[index] = False
        self._spl[index] = 0.0
        self._trail[index, 0] = demo.start_pose[:2]
        self._fidelity[index] = 0.0
        self._wall_hits[index] = 0
        demo_actions[index, :steps] = torch.from_numpy(demo.actions)
        demo_actions[index, steps:] = 0  # padding: demo_steps says where the demonstration ends
        mismatched = self._mismatched[index] = draws_mismatch(self.memory_mismatch, episode_seed)
        # the agent's first frame is the demonstration's first unless its world or the memory differ
        own_first_frame = self._repeats[index] is None and not mismatched
        if self.demo_store is not None:
            shown = self._memory_id[index] = self._source.mismatched_id(episode_seed, self._demo_id[index]) if mismatched else self._demo_id[index]
            stored = self.demo_store.frames[shown]
            if self.emit_demo_frames:
                demo_frames[index] = stored
            if own_first_frame or not self.render_frames:
                # the agent starts on the demo's first pose
                pixels[index] = self.demo_store.frames[self._demo_id[index], 0] if self.render_frames else 0
            else:
                self._render([index], demo.start_pose[None], out=pixels[index : index + 1].numpy())
            return
        if not self.emit_demo_frames:  # unrendered (checked): blank frames, none emitted
            pixels[index] = 0
            return
        # rendered straight into the (n, H, W, 3) tensor; black padding after the demonstration
        shown_house, shown = (taught, taught_demo) if not mismatched else self._source.mismatched_route(episode_seed)
        length = min(steps, shown.length)
        self._render([index] * length, shown.poses[:length], out=demo_frames[index, :length].numpy(), houses=[shown_house] * length)
        demo_frames[index, length:] = 0
        if own_first_frame:
            pixels[index] = demo_frames[index, 0]  # the agent starts on the demo's first pose
        else:
            self._render([index], demo.start_pose[None], out=pixels[index : index + 1].numpy())

    # ------------------------------------------------------------------- step
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if any(house is None for house in self._houses):
            raise RuntimeError("PathFollowEnv.step() was called before reset(): call env.reset() first.")
        action = check_action(tensordict.get("action", None), self._count, self.num_actions, self.stop_action)
        motion = nominal_motion(action)
        noise = tensordict.get(ACTUATION_NOISE_KEY, None)
        if noise is not None:
            motion += check_actuation_noise(noise, self._count, self.batch_size)
        previous = self._distance.copy()
        travelled = move_agents(self._houses, self._pose, motion)
        self._path_length += travelled
        self._wall_hits += travelled < np.hypot(motion[:, 0], motion[:, 1]) - WALL_CONTACT_TOLERANCE_M
        for index in range(self._count):
            self._distance[index] = self._demos[index].end_field.at(self._pose[index])
        for index in np.flatnonzero(self._excursions_made < self._excursion_counts):
            apexes, made = self._excursions[index], self._excursions_made[index]
            while made < len(apexes) and np.hypot(*(self._pose[index, :2] - apexes[made])) <= EXCURSION_REACH_M:
                made += 1
            self._excursions_made[index] = made
        self._steps += 1
        self._trail[np.arange(self._count), np.minimum(self._steps, self.max_steps)] = self._pose[:, :2]
        outcome = self.rules.score(
            action=action,
            distance_m=self._distance,
            previous_distance_m=previous,
            initial_distance_m=self._initial_distance,
            path_length_m=self._path_length,
            shortest_length_m=self._shortest,
            steps=self._steps,
            max_steps=self._max_steps,
            may_arrive=self._excursions_made >= self._excursion_counts,
        )
        self._success, self._spl = outcome.success, outcome.spl
        self._lab_success = outcome.done & lab_success(self._pose[:, :2], self._end_xy, self._start_xy)
        for index in np.flatnonzero(outcome.done):
            scores = path_fidelity(
                self._trail[index, : min(self._steps[index], self.max_steps) + 1], self._demos[index].poses[:, :2],
                bool(outcome.success[index]), self.success_radius_m,
            )
            self._fidelity[index] = scores["ndtw"], scores["sdtw"], scores["path_length_ratio"]
        pixels = torch.empty((self._count, self.image_size, self.image_size, NUM_RGB_CHANNELS), dtype=torch.uint8)
        self._render(range(self._count), out=pixels.numpy())
        self._pixels = pixels
        return self._observation(outcome.terminated, outcome.truncated, outcome.done, reward=outcome.reward)

    # ------------------------------------------------------------ observation
    def _observation(
        self, terminated: np.ndarray, truncated: np.ndarray, done: np.ndarray, reward: np.ndarray | None
    ) -> TensorDictBase:
        count = self._count
        # one array per dtype; every key is a view of one of them (casts as ``astype`` would)
        floats = np.empty((count, 12), dtype=np.float32)
        floats[:, 0] = self._distance
        floats[:, 1] = self._path_length
        floats[:, 2] = self._shortest
        floats[:, 3] = self._spl
        floats[:, 4:7] = self._pose
        floats[:, 7:10] = self._fidelity
        if reward is not None:
            floats[:, 10] = reward
        floats[:, 11] = self._condition_strength
        ints = np.empty((count, 9), dtype=np.int64)
        ints[:, 0] = self._steps
        ints[:, 1] = self._episode_seed
        ints[:, 2] = self._demo_id
        ints[:, 3] = self._episode_index
        ints[:, 4] = self._house_seed
        ints[:, 5] = self._wall_hits
        ints[:, 6] = self._demo_steps
        ints[:, 7] = self._condition
        ints[:, 8] = self._memory_id
        bools = np.empty((count, 6), dtype=bool)
        bools[:, 4] = self._lab_success
        bools[:, 5] = self._mismatched
        bools[:, 0] = self._success
        bools[:, 1] = done
        bools[:, 2] = terminated
        bools[:, 3] = truncated
        float_columns, int_columns, bool_columns = torch.from_numpy(floats), torch.from_numpy(ints), torch.from_numpy(bools)
        pixels, demo_frames, demo_actions = self._pixels, self._demo_frames, self._demo_actions
        if self.num_agents is None:
            float_columns, int_columns, bool_columns = float_columns[0], int_columns[0], bool_columns[0]
            pixels, demo_frames, demo_actions = pixels[0], demo_frames[0], demo_actions[0]
        out = {
            ACTUATION_NOISE_KEY: self._zero_noise,
            "pixels": pixels,
            "demo_actions": demo_actions,
            "demo_steps": int_columns[..., 6:7],
            "step_count": int_columns[..., 0:1],
            "episode_seed": int_columns[..., 1:2],
            "episode_index": int_columns[..., 3:4],
            "house_seed": int_columns[..., 4:5],
            "pose": float_columns[..., 4:7],
            "goal_distance": float_columns[..., 0:1],
            "path_length": float_columns[..., 1:2],
            "shortest_path_length": float_columns[..., 2:3],
            "spl": float_columns[..., 3:4],
            "success": bool_columns[..., 0:1],
            "done": bool_columns[..., 1:2],
            "terminated": bool_columns[..., 2:3],
            "truncated": bool_columns[..., 3:4],
            "success_lab": bool_columns[..., 4:5],
            "ndtw": float_columns[..., 7:8],
            "sdtw": float_columns[..., 8:9],
            "path_length_ratio": float_columns[..., 9:10],
            "wall_hits": int_columns[..., 5:6],
        }
        if reward is not None:
            out["reward"] = float_columns[..., 10:11]
        if self.emit_demo_frames:
            out["demo_frames"] = demo_frames
        if self.demo_store is not None:
            out["demo_id"] = int_columns[..., 2:3]
        if self.conditions is not None:
            out["condition"] = int_columns[..., 7:8]
            out["condition_strength"] = float_columns[..., 11:12]
        if self.memory_mismatch is not None:
            out["memory_mismatched"] = bool_columns[..., 5:6]
            if self.demo_store is not None:
                out["memory_id"] = int_columns[..., 8:9]
        if self.with_expert:
            expert = torch.from_numpy(self.expert_actions())
            out["expert_action"] = expert if self.num_agents is not None else expert[0]
        if self.with_route_step:  # after the actions, and leaving the experts as they are
            route_step = torch.from_numpy(self.route_steps()).unsqueeze(-1)
            out["route_step"] = route_step if self.num_agents is not None else route_step[0]
        if self._cpu:
            # every value is already a CPU tensor of the right shape: skip TensorDict's checks
            return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    # ---------------------------------------------------------------- helpers
    def expert_actions(self) -> np.ndarray:
        """The expert's action for every agent at its current pose, ``(N,)``."""
        return np.array(
            [expert.action(self._pose[i]) if expert is not None else 0 for i, expert in enumerate(self._experts)],
            dtype=np.int64,
        )

    def route_steps(self) -> np.ndarray:
        """The demonstration step every agent has come to along its route, ``(N,)`` (route expert only)."""
        return np.array(
            [expert.peek_route_step(self._pose[i]) if expert is not None else 0 for i, expert in enumerate(self._experts)],
            dtype=np.int64,
        )

    @property
    def with_route_step(self) -> bool:
        """Whether the env emits ``route_step``: with the expert's labels, when the expert is the route expert."""
        return self.with_expert and self.expert == "route"

    @property
    def demonstrations(self) -> list[Demonstration | None]:
        """The current demonstration of each agent."""
        return list(self._demos)

    @property
    def houses(self) -> list[House | None]:
        """The current house of each agent: the layout it moves in (with ``conditions``, the repeat's)."""
        return list(self._houses)

    @property
    def taught_houses(self) -> list[House | None]:
        """The house each agent's route was taught in (as :func:`~envs.scenes.build_house` makes it)."""
        return list(self._teach_houses)

    @property
    def repeats(self) -> list[Repeat | None]:
        """Each agent's :class:`~envs.conditions.Repeat` where its frames differ from the teaching world's, else ``None``."""
        return list(self._repeats)

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close(raise_if_closed=raise_if_closed)
