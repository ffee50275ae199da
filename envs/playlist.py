"""Where each episode's demonstration comes from: given routes, a demo store, or sampling.

* :class:`DemonstrationPlaylist`: the demonstrations users give
  (``PathFollowEnv(demonstrations=[...])``, ``env.reset(demonstration=demo)``), in
  the order each agent plays them;
* :class:`EpisodeSource`: the house and demonstration of an agent's next episode,
  from the playlist, else from a :class:`~envs.demo_store.DemoStore`, else sampled
  from the episode seed (:func:`~envs.follow.episode_for_seed`), for the env's task
  (:mod:`envs.homing`).
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from envs.conditions import mismatch_seed
from envs.demo_store import DemoStore
from envs.demos import Demonstration
from envs.follow import MAX_EPISODE_SEED, episode_for_seed
from envs.geodesic import DistanceField
from envs.homing import FOLLOW, HOMING, check_task, task_demonstration
from envs.route_styles import RouteMixture
from envs.scenes import House, build_house
from envs.specs import NUM_DEMO_ACTIONS

#: Route distance fields kept per env in demo-store mode (about 0.2 MB each for default houses).
DISTANCE_FIELD_CACHE_SIZE = 256


class DemonstrationPlaylist:
    """The demonstrations a :class:`~envs.nav_env.PathFollowEnv` plays instead of sampling routes.

    Agent ``i`` of an env of ``N`` agents plays ``demonstrations[(k * N + i) % K]`` in
    its ``k``-th episode (counting from the last :meth:`restart`, which ``set_seed``
    calls), so that with ``K = N`` every agent starts on its own demonstration and
    with one demonstration every agent repeats it (each episode under its own noise,
    which the episode seed fixes). ``env.reset(demonstration=demo)`` plays ``demo``
    in the episodes that this reset starts, whatever the list holds (an env in this
    process: ``ParallelEnv`` does not forward reset kwargs to its workers; give those
    the list).

    Args:
        demonstrations: the list (``None`` or empty: the env samples its routes).
        demo_length: the env's demonstration length n: every one has 1 to n steps (padded to n).
        num_agents: agents of the env (1 for an unbatched env).
        with_store: the env draws from a demo store, which given demonstrations cannot join.
        task: the env's task: with ``"homing"`` each given route (a follow
            demonstration) plays as its homing demonstration
            (:func:`~envs.homing.homing_demonstration`, derived once per route).

    Examples:
        >>> from envs.user_demos import demonstration_from_actions
        >>> demo = demonstration_from_actions(0, (7.5, 1.5, 0.0), "FFFFLF")
        >>> playlist = DemonstrationPlaylist([demo], demo_length=6, num_agents=2)
        >>> playlist.next(0) is demo, playlist.next(1) is demo
        (True, True)
        >>> from envs import PathFollowEnv
        >>> env = PathFollowEnv(house_seeds=[0], demo_length=6, render=False)
        >>> td = env.reset(demonstration=demo)
        >>> td["demo_actions"].tolist() == demo.actions.tolist()
        True
    """

    def __init__(
        self,
        demonstrations: Sequence[Demonstration] | None,
        demo_length: int,
        num_agents: int,
        with_store: bool = False,
        task: str = FOLLOW,
    ) -> None:
        self.demo_length = demo_length
        self.num_agents = num_agents
        self.with_store = with_store
        self.task = check_task(task)
        self.demonstrations = tuple(
            task_demonstration(self.check(demo, f"demonstrations[{position}]"), self.task)
            for position, demo in enumerate(demonstrations or ())
        )
        self._override: Demonstration | None = None
        self.restart()

    def restart(self) -> None:
        """Start every agent's count of episodes again (the first episode plays the agent's first demonstration)."""
        self._episodes = np.zeros(self.num_agents, dtype=np.int64)

    def check(self, demonstration: object, name: str = "demonstration") -> Demonstration:
        """``demonstration`` if the env can play it, else a ``ValueError`` saying why."""
        if self.with_store:
            raise ValueError(f"{name} cannot be combined with demo_store: the store fixes the demonstrations.")
        if not isinstance(demonstration, Demonstration):
            raise ValueError(f"{name} must be an envs.demos.Demonstration, got {type(demonstration).__name__}.")
        length = demonstration.length
        if not 1 <= length <= self.demo_length or demonstration.poses.shape != (length + 1, 3):
            raise ValueError(
                f"{name} has {length} steps (poses {demonstration.poses.shape}); this env plays demonstrations of "
                f"1 to demo_length={self.demo_length} steps, padded to {self.demo_length} (demo_steps gives each "
                "one's own length): crop it, or build the env with a demo_length of at least its length."
            )
        actions = demonstration.actions
        if actions.min(initial=0) < 0 or actions.max(initial=0) >= NUM_DEMO_ACTIONS:
            raise ValueError(f"{name} holds actions outside 0 (forward), 1 (left), 2 (right): {actions.tolist()}.")
        if self.task == HOMING and demonstration.task != FOLLOW:
            raise ValueError(
                f"{name} is a {demonstration.task!r} demonstration; a task='homing' env plays the homing episode "
                "of a route: give the route as it was demonstrated (task 'follow')."
            )
        return demonstration

    def begin_reset(self, demonstration: Demonstration | None) -> None:
        """Start a reset: the demonstration given to it (checked, and its homing demonstration
        in a homing env), or ``None`` to play the list."""
        self._override = None if demonstration is None else task_demonstration(self.check(demonstration), self.task)

    def next(self, index: int) -> Demonstration | None:
        """The demonstration agent ``index``'s next episode plays (``None``: the env samples one)."""
        episode = int(self._episodes[index])
        self._episodes[index] += 1
        if self._override is not None:
            return self._override
        if not self.demonstrations:
            return None
        return self.demonstrations[(episode * self.num_agents + index) % len(self.demonstrations)]


class EpisodeSource:
    """The house and demonstration of each agent's next episode, for the env's task.

    Given demonstrations come first (the playlist), then the demo store (a uniformly
    drawn ``demo_id``, its distance field cached), then a route sampled from the
    episode seed. Every demonstration returned is the one the episode plays: for
    ``task="homing"``, a homing demonstration.

    Args:
        house_seeds: the houses sampled routes are drawn from.
        demo_length: demonstration length n, steps.
        min_route_length_m: sampled routes end farther than this from their start (geodesic, metres).
        task: ``"follow"`` or ``"homing"``.
        playlist: the given demonstrations.
        demo_store: the store to draw from (its task must be ``task``), or ``None``.
        route_style: sampled routes' styles and lengths (:class:`~envs.route_styles.RouteMixture`);
            ``None``: the planner's routes of ``demo_length`` steps.

    Examples:
        >>> playlist = DemonstrationPlaylist(None, demo_length=5, num_agents=1)
        >>> source = EpisodeSource([0], 5, 0.6, "homing", playlist)
        >>> house, demo, demo_id = source.episode(0, episode_seed=7, number=0)
        >>> demo.task, demo.length, demo_id
        ('homing', 5, 0)
    """

    def __init__(
        self,
        house_seeds: Sequence[int],
        demo_length: int,
        min_route_length_m: float,
        task: str,
        playlist: DemonstrationPlaylist,
        demo_store: DemoStore | None = None,
        route_style: RouteMixture | None = None,
    ) -> None:
        self.route_style = route_style
        self.house_seeds = list(house_seeds)
        self.demo_length = demo_length
        self.min_route_length_m = min_route_length_m
        self.task = check_task(task)
        self.playlist = playlist
        self.demo_store = demo_store
        self._field_cache: OrderedDict[int, DistanceField] = OrderedDict()

    def episode(self, index: int, episode_seed: int, number: int) -> tuple[House, Demonstration, int]:
        """``(house, demonstration, demo_id)`` of agent ``index``'s next episode, episode
        ``number`` (``demo_id`` 0 without a store). An episode store
        (``episodes_seed`` set) plays demonstration ``number``; past its end,
        ``number mod K`` (see :class:`~envs.demo_store.DemoStoreConfig`)."""
        if (given := self.playlist.next(index)) is not None:
            return build_house(given.house_seed), given, 0
        if self.demo_store is not None:
            if self.demo_store.config.episodes_seed is not None:
                demo_id = int(number) % len(self.demo_store)
            else:
                demo_id = int(np.random.default_rng(episode_seed).integers(len(self.demo_store)))
            demo = self.stored_demonstration(demo_id)
            return build_house(demo.house_seed), demo, demo_id
        house, demo = episode_for_seed(
            episode_seed, self.house_seeds, self.demo_length, self.min_route_length_m, self.task, self.route_style
        )
        return house, demo, 0

    def mismatched_route(self, episode_seed: int) -> tuple[House, Demonstration]:
        """The route whose frames a mismatched episode of ``episode_seed`` is shown: another
        route of the env's houses and routes, drawn from the episode seed
        (:func:`~envs.conditions.mismatch_seed`), as the teacher saw it."""
        return episode_for_seed(
            mismatch_seed(episode_seed) % MAX_EPISODE_SEED, self.house_seeds, self.demo_length, self.min_route_length_m,
            self.task, self.route_style,
        )

    def mismatched_id(self, episode_seed: int, demo_id: int) -> int:
        """The stored demonstration whose frames a mismatched episode of ``episode_seed`` (playing
        ``demo_id``) is shown: another one of the store, drawn from the episode seed."""
        count = len(self.demo_store)  # at least 2 (PathFollowEnv checks)
        other = mismatch_seed(episode_seed) % (count - 1)
        return int(other if other < demo_id else other + 1)

    def env_seed(self, seed: int | None) -> int | None:
        """The seed the env's episode numbering takes for ``set_seed(seed)``: an episode
        store's ``episodes_seed`` when ``seed`` is ``None``; the seed itself otherwise.

        Raises:
            ValueError: ``seed`` differs from the episode store's ``episodes_seed`` (its
                demonstrations would not be the episodes' own).
        """
        store_seed = None if self.demo_store is None else self.demo_store.config.episodes_seed
        if store_seed is None or seed is None:
            return store_seed if seed is None else seed
        if int(seed) != store_seed:
            raise ValueError(
                f"seed must be {store_seed} for the episode store {self.demo_store.root} (it holds the "
                f"demonstrations of that env seed's episodes), got {seed}. Envs sharing the store take "
                f"set_seed({store_seed}, static_seed=True)."
            )
        return seed

    def stored_demonstration(self, demo_id: int) -> Demonstration:
        """Demonstration ``demo_id`` of the store, its distance field cached (LRU)."""
        demo = self.demo_store.demonstration(demo_id, end_field=self._field_cache.pop(demo_id, None))
        self._field_cache[demo_id] = demo.end_field
        if len(self._field_cache) > DISTANCE_FIELD_CACHE_SIZE:
            self._field_cache.popitem(last=False)
        return demo


__all__ = ["DISTANCE_FIELD_CACHE_SIZE", "DemonstrationPlaylist", "EpisodeSource"]
