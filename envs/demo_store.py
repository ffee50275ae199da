"""A store of pre-rendered demonstrations, shared by every env process through memory maps.

Sampling a demonstration at each episode start costs a route search and
``demo_length`` rendered frames (about 20 ms, as much as 50 agent steps), and
emitting its frames at every step makes each collected frame carry 30 more. A
:class:`DemoStore` does that work once: ``K`` demonstrations of a split are
sampled and rendered ahead of time and written to a directory as a
:class:`~envs.tensor_store.TensorStore` (TensorDict's memmap format; no pickle)::

    <root>/meta.json     kind, format and env versions, configuration, SHA-256 of every tensor
    <root>/data/         frames [K, n, H, W, 3] uint8, actions [K, n], poses [K, n + 1, 3],
                         house_seed [K], shortest_length_m [K]; with a route style, also
                         steps [K]: each demonstration's own length (padded to n: black
                         frames, action 0 and the end pose repeated)

A :class:`~envs.nav_env.PathFollowEnv` given ``demo_store=root`` draws each
episode's demonstration from the store (a uniformly drawn ``demo_id``), renders
nothing at reset, and emits ``demo_id`` at every step; with ``emit_demo_frames=False``
it emits the id instead of the frames, and the policy looks the frames up in the
store where it needs them (:meth:`DemoStore.lookup_module`). The store is a pure
function of its :class:`DemoStoreConfig` (demonstration ``k`` is drawn from the
generator seeded with ``(seed, k)``), is built in chunks into ``<root>.partial``
(an interrupted build resumes, to the same bytes) and renamed into place when
complete, and is verified against its checksums when opened by path
(``DemoStore(root)``, and envs given a directory).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from envs.demos import Demonstration, default_min_route_length_m, sample_demonstration
from envs.episode_numbering import episode_seed, seed_entropy
from envs.episode_spec import EpisodeSpec, flat_dict, from_flat
from envs.follow import episode_for_seed
from envs.geodesic import DistanceField
from envs.homing import FOLLOW, task_demonstration
from envs.house_grid import check_grid_size, default_grid_size_cells
from envs.render import FirstPersonRenderer
from envs.route_styles import RouteMixture
from envs.scenes import build_house, split_seeds
from envs.specs import NUM_RGB_CHANNELS
from envs.tensor_store import StoreError, TensorStore

logger = logging.getLogger(__name__)

#: Version of the on-disk layout; bumped when it changes.
DEMO_STORE_FORMAT_VERSION = 3
#: The noise preset of a store's :class:`~envs.episode_spec.EpisodeSpec`: demonstrations are driven without noise.
STORE_NOISE = "none"
#: Demonstrations rendered per chunk of a build (the unit an interrupted build resumes from).
DEMO_CHUNK_ROWS = 32


class DemoStoreError(StoreError):
    """A demo-store directory is missing, corrupt, stale, or of another configuration."""


@dataclass(frozen=True)
class DemoStoreConfig:
    """Which demonstrations a store holds.

    Args:
        episodes: the episodes whose demonstrations it holds (:class:`~envs.episode_spec.EpisodeSpec`:
            split or houses, ``demo_length``, ``image_size``, task, routes and seed).
            Demonstrations have neither actuation noise nor a step limit, and are the teaching
            world's, so the store's spec keeps neither, nor repeat conditions or a mismatched
            memory (:mod:`envs.conditions`; all set to ``"none"`` and ``None``): any noise, limit
            and conditions may play them.
        num_demos: number of demonstrations K.
        numbered: ``False`` (a pool of demonstrations, drawn uniformly by the env:
            demonstration ``k`` depends only on ``(episodes.seed, k)``) or ``True`` (an
            episode store: demonstration ``k`` is the one episode ``k`` of an env seeded
            with ``episodes.seed`` plays, :func:`~envs.follow.episode_for_seed`, and an
            env seeded with it plays demonstration ``k`` in episode ``k``: the same
            episodes as without the store, frames rendered once; evaluation sets).
            Episodes numbered ``K`` and beyond replay demonstration ``number mod K``
            with their own noise: not the rendering path's episodes, so size the
            store to the episodes kept (evaluation keeps ``0 .. K - 1`` only). Envs
            that share a numbering (``episode_offset``/``episode_stride``) must all
            get the same seed: ``set_seed(seed, static_seed=True)``.
        min_route_length_m: routes must end farther than this (geodesic, metres) from
            their start; ``None`` uses the env's default for ``demo_length``.
        grid_size_cells: the houses' labmaze grid, cells (``None``: the env's default
            for ``demo_length``, :func:`~envs.house_grid.default_grid_size_cells`).

    A homing store (``episodes.task="homing"``) holds the homing demonstrations of its
    sampled routes (:mod:`envs.homing`), frames rendered looking back along the route;
    envs of the same task only may draw from it.

    Examples:
        >>> config = DemoStoreConfig.of(EpisodeSpec(split="val", seed=7), num_demos=3)
        >>> config.episodes_seed, config.episodes.noise, config.min_route_length_m > 0
        (7, 'none', True)
    """

    episodes: EpisodeSpec = EpisodeSpec()
    num_demos: int = 1000
    numbered: bool = False
    min_route_length_m: float | None = None
    grid_size_cells: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.episodes, EpisodeSpec):
            raise ValueError(f"episodes must be an EpisodeSpec, got {type(self.episodes).__name__}.")
        # a store holds the teaching world's demonstrations: the repeat's noise, step limit,
        # conditions and memory (envs.conditions) are the env's, not the store's
        taught = {"noise": STORE_NOISE, "max_steps": None, "conditions": None, "memory_mismatch": None}
        if any(getattr(self.episodes, key) != value for key, value in taught.items()):
            object.__setattr__(self, "episodes", self.episodes.replace(**taught))
        if self.grid_size_cells is not None:
            check_grid_size(self.grid_size_cells, "DemoStoreConfig.grid_size_cells")
        if isinstance(self.num_demos, bool) or not isinstance(self.num_demos, int) or self.num_demos <= 0:
            raise ValueError(f"num_demos must be a positive int, got {self.num_demos!r}.")
        if not isinstance(self.numbered, bool):
            raise ValueError(f"numbered must be a bool, got {self.numbered!r}.")
        if self.min_route_length_m is None:
            object.__setattr__(self, "min_route_length_m", default_min_route_length_m(self.episodes.demo_length))
        elif not isinstance(self.min_route_length_m, (int, float)) or not self.min_route_length_m >= 0:
            raise ValueError(f"min_route_length_m must be a number >= 0 (metres) or None, got {self.min_route_length_m!r}.")

    @classmethod
    def of(cls, episodes: EpisodeSpec, num_demos: int) -> DemoStoreConfig:
        """The episode store of episodes ``0 .. num_demos - 1`` of ``episodes`` (``numbered``)."""
        return cls(episodes=episodes, num_demos=num_demos, numbered=True)

    @property
    def episodes_seed(self) -> int | None:
        """The env seed whose episodes a numbered store holds (``None``: a pool)."""
        return self.episodes.seed if self.numbered else None

    @property
    def grid(self) -> int:
        """The houses' grid, cells (``grid_size_cells``, or the default for ``demo_length``)."""
        return default_grid_size_cells(self.episodes.demo_length) if self.grid_size_cells is None else self.grid_size_cells

    @property
    def house_seeds(self) -> list[int]:
        if self.episodes.house_seeds is not None:
            return list(self.episodes.house_seeds)
        return split_seeds(self.episodes.split, self.episodes.num_houses, self.grid)

    def to_dict(self) -> dict:
        """The store's ``meta.json`` form: flat, in the keys of stores written before the
        episode description (``seed`` and ``episodes_seed`` as they were)."""
        out = flat_dict(self)
        for key in ("noise", "max_steps", "numbered"):
            out.pop(key)
        out["seed"], out["episodes_seed"] = (0, self.episodes.seed) if self.numbered else (self.episodes.seed, None)
        return out

    @classmethod
    def from_dict(cls, values: dict) -> DemoStoreConfig:
        """The configuration of a ``meta.json`` (:meth:`to_dict`'s form).

        Examples:
            >>> config = DemoStoreConfig.of(EpisodeSpec(split="val", seed=7, route_style="tour"), num_demos=3)
            >>> DemoStoreConfig.from_dict(config.to_dict()) == config
            True
        """
        values = dict(values)
        episodes_seed = values.pop("episodes_seed", None)
        numbered = episodes_seed is not None
        if numbered:
            values["seed"] = episodes_seed
        return from_flat(cls, {**values, "numbered": numbered})


def sample_store_demonstration(config: DemoStoreConfig, index: int) -> Demonstration:
    """Demonstration ``index`` of a store, for its task: a pure function of ``(episodes.seed, index)``,
    or, for a numbered store, of the seed of episode ``index`` of that env seed."""
    episodes = config.episodes
    if config.numbered:
        seed = episode_seed(seed_entropy(episodes.seed), index)
        return episode_for_seed(
            seed, config.house_seeds, episodes.demo_length, config.min_route_length_m, episodes.task, episodes.mixture
        )[1]
    rng = np.random.default_rng([episodes.seed, index])
    house = build_house(int(rng.choice(config.house_seeds)))
    if episodes.route_style is None:
        route = sample_demonstration(house, rng, episodes.demo_length, min_route_length_m=config.min_route_length_m)
    else:
        _, route = episodes.mixture.sample(house, rng)
    return task_demonstration(route, episodes.task, house)


def _empty(config: DemoStoreConfig) -> TensorDict:
    k, n, s = config.num_demos, config.episodes.demo_length, config.episodes.image_size
    tensors = {
        "frames": torch.zeros(k, n, s, s, NUM_RGB_CHANNELS, dtype=torch.uint8),
        "actions": torch.zeros(k, n, dtype=torch.int64),
        "poses": torch.zeros(k, n + 1, 3, dtype=torch.float64),
        "house_seed": torch.zeros(k, dtype=torch.int64),
        "shortest_length_m": torch.zeros(k, dtype=torch.float64),
    }
    if config.episodes.route_style is not None:  # routes of several lengths (stores without it: all n long)
        tensors["steps"] = torch.zeros(k, dtype=torch.int64)
    return TensorDict(tensors, batch_size=[k])


def make_demo_chunk(config: DemoStoreConfig, chunk: int) -> TensorDict:
    """Demonstrations ``[chunk * DEMO_CHUNK_ROWS, ...)`` of a store, sampled and rendered (a pure function)."""
    first = chunk * DEMO_CHUNK_ROWS
    indices = range(first, min(first + DEMO_CHUNK_ROWS, config.num_demos))
    out = _empty(dataclasses.replace(config, num_demos=len(indices)))
    renderer = _chunk_renderer(config.episodes.image_size)
    for row, index in enumerate(indices):
        demo = sample_store_demonstration(config, index)
        house = build_house(demo.house_seed)
        n = demo.length  # padded after it: black frames, action 0, the end pose repeated
        renderer.render_many([house] * n, demo.poses[:n], out=out["frames"][row, :n].numpy())
        out["actions"][row, :n] = torch.from_numpy(demo.actions)
        out["poses"][row] = torch.from_numpy(demo.poses[-1])
        out["poses"][row, : n + 1] = torch.from_numpy(demo.poses)
        if "steps" in out.keys():
            out["steps"][row] = n
        out["house_seed"][row] = demo.house_seed
        out["shortest_length_m"][row] = demo.shortest_length_m
    return out


_CHUNK_RENDERERS: dict[tuple[int, int], FirstPersonRenderer] = {}


def _chunk_renderer(image_size: int) -> FirstPersonRenderer:
    """The renderer a thread builds its store chunks with, kept across chunks and stores: a
    house's GL resources are uploaded once per thread, not once per chunk (closed at exit).
    One per thread: an EGL context can be current in one thread only."""
    key = (threading.get_ident(), image_size)
    if key not in _CHUNK_RENDERERS:
        _CHUNK_RENDERERS[key] = FirstPersonRenderer(image_size, image_size)
    return _CHUNK_RENDERERS[key]


class DemoStore(TensorStore):
    """Pre-rendered demonstrations in a directory, memory-mapped and shared between processes.

    Open an existing store with ``DemoStore(root)``; create one with
    :meth:`build` (which opens an existing, matching store instead of rebuilding
    it). A :class:`~envs.tensor_store.TensorStore`: it pickles as its path, so it can
    be passed to env factories that run in ``spawn`` worker processes, and every
    process maps the same files. Read its tensors (the env and :meth:`lookup` copy
    out of them), never write to them.

    Args:
        root: the store directory.
        verify: recompute the SHA-256 of every tensor and compare with ``meta.json``.

    Raises:
        DemoStoreError: if ``root`` is not a complete store, its metadata is
            corrupt, a tensor is missing, has another shape, or fails its checksum.

    Examples:
        >>> import tempfile
        >>> config = DemoStoreConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, image_size=32), num_demos=2)
        >>> store = DemoStore.build(tempfile.mkdtemp() + "/store", config, progress=False)
        >>> len(store), store.frames.shape
        (2, torch.Size([2, 5, 32, 32, 3]))
        >>> store.lookup(torch.tensor([[1], [0]])).shape
        torch.Size([2, 5, 32, 32, 3])
    """

    KIND = "demo"
    FORMAT_VERSION = DEMO_STORE_FORMAT_VERSION
    ERROR = DemoStoreError
    FORMAT_HISTORY = "(version 1 stored CHW frames; version 2 had no chunked, resumable build)"

    @staticmethod
    def config_from_dict(config: dict) -> DemoStoreConfig:
        return DemoStoreConfig.from_dict(config)

    @staticmethod
    def config_to_dict(config: DemoStoreConfig) -> dict:
        return config.to_dict()

    @staticmethod
    def empty(config: DemoStoreConfig) -> TensorDict:
        return _empty(config)

    @classmethod
    def build(
        cls,
        root: str | os.PathLike,
        config: DemoStoreConfig,
        progress: bool = True,
        num_workers: int = 1,
        pool: concurrent.futures.Executor | None = None,
    ) -> DemoStore:
        """Sample and render the store's demonstrations into ``root`` (or open it if it exists).

        Built in chunks of :data:`DEMO_CHUNK_ROWS` into ``<root>.partial`` and renamed to
        ``root`` when complete; an interrupted build resumes where it stopped. ``num_workers``
        processes build the chunks, or ``pool``'s (:meth:`~envs.tensor_store.TensorStore.create`).

        Raises:
            DemoStoreError: if ``root`` holds a store of another configuration.
        """
        return cls.create(
            root, config, make_demo_chunk, DEMO_CHUNK_ROWS, num_workers=num_workers, progress=progress, pool=pool
        )

    # ---------------------------------------------------------------- reading
    @property
    def frames(self) -> torch.Tensor:
        """``[K, n, H, W, 3]`` uint8 frames (memory-mapped)."""
        return self.data.get("frames")

    @property
    def actions(self) -> torch.Tensor:
        """``[K, n]`` int64 actions."""
        return self.data.get("actions")

    @property
    def poses(self) -> torch.Tensor:
        """``[K, n + 1, 3]`` float64 poses (x m, y m, heading rad) before each action, then the end pose."""
        return self.data.get("poses")

    @property
    def steps(self) -> torch.Tensor:
        """``[K]`` int64 length of each demonstration, steps (all ``n`` in a store without a route style)."""
        if "steps" in self.data.keys():
            return self.data.get("steps")
        return torch.full((len(self),), self.config.episodes.demo_length, dtype=torch.int64)

    @property
    def house_seeds(self) -> torch.Tensor:
        """``[K]`` house seed of each demonstration."""
        return self.data.get("house_seed")

    @property
    def shortest_lengths_m(self) -> torch.Tensor:
        """``[K]`` geodesic length (metres) from each route's start to its end."""
        return self.data.get("shortest_length_m")

    def lookup(self, demo_id: torch.Tensor) -> torch.Tensor:
        """Frames of demonstrations by id: ``[*, 1]`` int64 (the env's ``demo_id``) -> ``[*, n, H, W, 3]`` uint8 (a copy).

        Raises:
            ValueError: on ids of another shape or outside ``[0, K)``.
        """
        ids = self._checked_ids(demo_id)
        return self.frames[ids.reshape(-1).cpu()].reshape(*ids.shape, *self.frames.shape[1:]).to(demo_id.device)

    def _checked_ids(self, demo_id: torch.Tensor) -> torch.Tensor:
        """``[*, 1]`` ids -> ``[*]``, refusing other shapes and ids outside ``[0, K)``."""
        if demo_id.ndim == 0 or demo_id.shape[-1] != 1:
            raise ValueError(f"demo_id must have shape [*, 1] (the env's demo_id), got {tuple(demo_id.shape)}.")
        ids = demo_id.squeeze(-1)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= len(self)):
            raise ValueError(f"demo_id must be in [0, {len(self) - 1}] for store {self.root}, got {ids.tolist()}.")
        return ids

    def lookup_module(
        self, in_key: str = "demo_id", out_key: str = "demo_frames", only_where: str | None = None
    ) -> TensorDictModule:
        """A :class:`~tensordict.nn.TensorDictModule` writing ``out_key`` frames from ``in_key`` ids.

        Put it in front of a policy that reads ``demo_frames`` when the env emits
        only ``demo_id``: ``TensorDictSequential(store.lookup_module(), policy,
        selected_out_keys=policy.out_keys)`` keeps the frames out of the
        collected batches.

        Args:
            in_key: the ids' key.
            out_key: the frames' key.
            only_where: a boolean key (e.g. ``"is_init"``): frames are looked up only
                in rows where it is true, the other rows are zeros (allocated lazily by
                the OS, so rows nobody reads cost nothing). For step-by-step
                collection with the SPF policies, which encode the memory where
                ``is_init`` is true and carry it in their recurrent state otherwise;
                not for sequence-mode training, which reads every row's frames.
        """
        if only_where is None:
            return TensorDictModule(self.lookup, in_keys=[in_key], out_keys=[out_key])
        return TensorDictModule(self.lookup_rows, in_keys=[in_key, only_where], out_keys=[out_key])

    def lookup_rows(self, demo_id: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        """:meth:`lookup` in the rows where ``where`` (``[*]`` or ``[*, 1]`` bool) is true, zeros elsewhere."""
        ids = self._checked_ids(demo_id)
        if where.numel() != ids.numel():
            raise ValueError(
                f"where must hold one flag per demo_id row ([*] or [*, 1] with * = {tuple(ids.shape)}), "
                f"got shape {tuple(where.shape)}."
            )
        mask = where.reshape(ids.shape).to(torch.bool)
        out = torch.zeros(*ids.shape, *self.frames.shape[1:], dtype=self.frames.dtype, device=demo_id.device)
        if mask.any():
            out[mask] = self.frames[ids[mask].cpu()].to(demo_id.device)
        return out

    def demonstration(self, demo_id: int, end_field: DistanceField | None = None) -> Demonstration:
        """Demonstration ``demo_id`` (arrays copied out of the store).

        Args:
            demo_id: index in ``[0, K)``.
            end_field: its geodesic distance field to the route's end, if already known;
                otherwise computed (one Dijkstra run).
        """
        house_seed = int(self.house_seeds[demo_id])
        steps = int(self.steps[demo_id])
        poses = self.poses[demo_id, : steps + 1].numpy().copy()
        if end_field is None:
            end_field = build_house(house_seed).graph.distance_field(poses[-1, :2])
        return Demonstration(
            house_seed=house_seed,
            poses=poses,
            actions=self.actions[demo_id, :steps].numpy().copy(),
            end_field=end_field,
            shortest_length_m=float(self.shortest_lengths_m[demo_id]),
            task=self.config.episodes.task,
        )


def check_store_matches(
    store: DemoStore,
    split: str,
    num_houses: int | None,
    house_seeds: Sequence[int] | None,
    demo_length: int,
    image_size: int,
    success_radius_m: float,
    task: str = FOLLOW,
    grid_size_cells: int | None = None,
    route_style: RouteMixture | None = None,
) -> None:
    """Raise ``ValueError`` when the env's arguments disagree with the demo store's configuration.

    ``grid_size_cells`` is the env's grid (``None``: the default for ``demo_length``);
    ``route_style`` the env's routes (``None``: the planner's).
    """
    config = store.config
    spec = config.episodes
    if house_seeds is not None:
        raise ValueError("house_seeds cannot be combined with demo_store (the store fixes the houses).")
    mismatches = []
    if split != spec.split:
        mismatches.append(f"split={split!r} (store: {spec.split!r})")
    if num_houses is not None and len(split_seeds(split, num_houses)) != len(config.house_seeds):
        mismatches.append(f"num_houses={num_houses} (store: {len(config.house_seeds)})")
    grid = default_grid_size_cells(demo_length) if grid_size_cells is None else grid_size_cells
    if grid != config.grid:
        mismatches.append(f"grid_size_cells={grid} (store: {config.grid})")
    if task != spec.task:
        mismatches.append(f"task={task!r} (store: {spec.task!r})")
    if demo_length != spec.demo_length:
        mismatches.append(f"demo_length={demo_length} (store: {spec.demo_length})")
    if image_size != spec.image_size:
        mismatches.append(f"image_size={image_size} (store: {spec.image_size})")
    if route_style != spec.mixture:
        ours = None if route_style is None else f"{route_style.spec!r} of {route_style.min_length}-{route_style.max_length} steps"
        theirs = None if spec.route_style is None else f"{spec.route_style!r} of {spec.route_lengths[0]}-{spec.route_lengths[1]} steps"
        mismatches.append(f"route_style={ours} (store: {theirs})")
    needed = default_min_route_length_m(demo_length, success_radius_m)
    if config.min_route_length_m < needed - 1e-9:
        mismatches.append(
            f"success_radius_m={success_radius_m} needs routes longer than {needed:.2f} m "
            f"(store: min_route_length_m={config.min_route_length_m:.2f})"
        )
    elif config.episodes_seed is not None and config.min_route_length_m > needed + 1e-9:
        mismatches.append(
            f"success_radius_m={success_radius_m} draws routes longer than {needed:.2f} m, and an episode store "
            f"must draw the env's own episodes (store: min_route_length_m={config.min_route_length_m:.2f})"
        )
    if mismatches:
        raise ValueError(f"demo_store {store.root} does not match the env: {', '.join(mismatches)}.")
