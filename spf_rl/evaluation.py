"""Roll a policy out in :class:`~envs.nav_env.PathFollowEnv` and score it (success, SPL).

Every policy evaluated with the same ``seed``, split and number of episodes
plays the same episodes (the env gives each agent its own episode stream), so
scores are comparable across models and reproducible.

With ``store_root`` set, the episodes' demonstrations are rendered once into an
episode store (a numbered :class:`~envs.demo_store.DemoStore`) kept
there by configuration: every later evaluation of the same episodes (each
validation of a training run, each checkpoint of Table 1) skips the route search
and the demonstration renders at every episode start, the env emits ``demo_id``
instead of 30 frames at every step, and the frames are looked up for the policy
where it reads them (for the SPF policies, only where ``is_init``). The episodes,
and so the scores, are the same as without the store.

The env and its rendering run on the CPU; the policy runs where its weights are
(move it with ``policy.to(device)`` first): each step's inputs go to that device and
the logits, action and next recurrent state come back
(:func:`~spf_rl.device.act_on_device`). Evaluation is always float32, also for runs
trained with mixed precision. With ``num_collectors`` above 1, worker processes play
the episodes through a TorchRL multi-process collector, each with a CPU copy of the
policy (:class:`GreedyActor`), their envs sharing one episode numbering: the same
episodes, each recorded once.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.utils import get_primers_from_module

from envs.checks import check_positive_ints
from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec, flat_dict
from envs.episodes import STEPS_PER_BATCH, record_episodes, run_episodes
from envs.factory import make_env
from envs.follow import default_max_steps
from envs.house_grid import default_grid_size_cells
from envs.version import ENV_VERSION
from spf_rl.device import act_on_device, module_device, torch_threads_kept
from spf_rl.metrics import summarize
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.views import policy_for_length

#: Seed of the test episodes every evaluation of a trained policy plays (Table 1, the route bench, recipes/evaluate.py).
TEST_SEED = 2
#: Seed of the validation episodes on which BC picks its epoch (DAgger picks its rounds on others).
VAL_SEED = 1


def default_eval_episodes() -> EpisodeSpec:
    """The episodes :class:`EvalConfig` plays by default: 30-step planner routes of the ``test``
    split, 50 steps at most, under ``paper`` noise, seed 1234."""
    return EpisodeSpec(split="test", max_steps=50, seed=1234)


@dataclass
class EvalConfig:
    """How a policy is evaluated.

    Args:
        episodes: the episodes (:class:`~envs.episode_spec.EpisodeSpec`): episodes
            ``0 .. num_episodes - 1`` of an env seeded with ``episodes.seed``, the same ones
            for every policy. In YAML its keys may be written flat (``test.split``).
        num_episodes: episodes played.
        num_agents: agents stepped together in one batched env.
        render: render frames (policies that ignore the camera, like open-loop
            replay, can skip it; the episodes are the same).
        store_root: directory of episode stores (the demonstrations of the
            episodes, rendered once), kept by configuration and reused by later
            evaluations (the training recipes use :func:`episode_store_root`). ``None``:
            :func:`evaluate_policy` builds the store in a temporary directory and
            deletes it afterwards. The episodes and scores are the same either way.
            Used only where ``render`` is true.
        num_collectors: processes playing the episodes: ``1`` in this process; more: a
            TorchRL multi-process collector whose workers each step a batched env of
            ``num_agents`` agents with a CPU copy of the policy. The episodes and scores
            are the same for any number.
    """

    episodes: EpisodeSpec = field(default_factory=default_eval_episodes)
    num_episodes: int = 500
    num_agents: int = 25
    render: bool = True
    store_root: str | None = None
    num_collectors: int = 1

    def __post_init__(self) -> None:
        check_positive_ints(self, ("num_episodes", "num_agents", "num_collectors"))


#: Fields of :class:`EvalConfig` that choose how episodes are played, never which.
HOW_FIELDS = ("store_root", "num_collectors")


def config_dict(config: EvalConfig) -> dict:
    """``config``'s fields as JSON writes them, flat (:func:`~envs.episode_spec.flat_dict`): the
    route fields only when a route style is set, so the JSON of the planner's episodes is what it
    was before route styles existed.

    Examples:
        >>> "route_style" in config_dict(EvalConfig()), config_dict(EvalConfig(EpisodeSpec(route_style="tour")))["route_lengths"]
        (False, [30, 30])
    """
    return flat_dict(config)


def episode_identity(config: EvalConfig) -> dict:
    """The fields of ``config`` that fix its episodes and scores (all but :data:`HOW_FIELDS`):
    the key of cached per-episode records. The route fields appear only when a route style is
    set, so the key of the planner's episodes is what it was before route styles existed.

    Examples:
        >>> episode_identity(EvalConfig(store_root="a")) == episode_identity(EvalConfig())
        True
        >>> "route_style" in episode_identity(EvalConfig()), episode_identity(EvalConfig(EpisodeSpec(route_style="tour")))["route_style"]
        (False, 'tour=1.0')
    """
    return {key: value for key, value in config_dict(config).items() if key not in HOW_FIELDS}


def greedy(policy: TensorDictModuleBase):
    """Wrap ``policy`` so that it writes the arg-max of its ``"logits"`` as ``"action"``
    (policies that write ``"action"`` themselves are left as they are)."""

    def act(tensordict):
        tensordict = policy(tensordict)
        if "logits" in tensordict.keys() and "action" not in policy.out_keys:
            tensordict.set("action", tensordict.get("logits").argmax(-1))
        return tensordict

    return act


class FramesFromStore(TensorDictModuleBase):
    """``policy`` fed its ``demo_frames`` from ``demo_id`` in ``demo_store``
    (:func:`frames_lookup`'s rule), the frames dropped after it: a policy for envs that
    emit ``demo_id`` only (``emit_demo_frames=False``), so collected batches carry the id
    and not 30 frames a step. Picklable, for worker processes and Ray actors.

    Args:
        policy: a TensorDict policy.
        demo_store: the store the env draws from (``None``: the env emits the frames, and
            ``policy`` runs as it is).
        in_key: the key of the stored demonstration whose frames are shown
            (:attr:`~envs.episode_spec.EpisodeSpec.frames_id_key`: ``memory_id`` with a mismatched memory).

    Examples:
        >>> import tempfile
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from envs.demo_store import DemoStore, DemoStoreConfig
        >>> store = DemoStore.build(tempfile.mkdtemp() + "/store", DemoStoreConfig(
        ...     EpisodeSpec(num_houses=1, demo_length=4, image_size=16), num_demos=2), progress=False)
        >>> reader = TensorDictModule(lambda f: f.float().mean((-4, -3, -2, -1)), ["demo_frames"], ["logits"])
        >>> fed = FramesFromStore(reader, store)
        >>> fed.in_keys
        ['demo_id']
        >>> out = fed(TensorDict({"demo_id": torch.tensor([[1], [0]])}, [2]))
        >>> "demo_frames" in out.keys(), bool(out["logits"][0] == store.frames[1].float().mean())
        (False, True)
    """

    def __init__(self, policy: TensorDictModuleBase, demo_store: DemoStore | None = None, in_key: str = "demo_id") -> None:
        super().__init__()
        self.policy = policy
        self.lookup = frames_lookup(policy, demo_store, in_key)
        extra = list(self.lookup.in_keys) if self.lookup is not None else []
        self.in_keys = list(dict.fromkeys([k for k in policy.in_keys if self.lookup is None or k != "demo_frames"] + extra))
        self.out_keys = list(policy.out_keys)

    def make_tensordict_primer(self):
        """``policy``'s recurrent-state primer (its own, else those of its submodules), if any."""
        if hasattr(self.policy, "make_tensordict_primer"):
            return self.policy.make_tensordict_primer()
        return get_primers_from_module(self.policy, warn=False)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.lookup is None:
            return self.policy(tensordict)
        return self.policy(self.lookup(tensordict)).exclude("demo_frames", inplace=True)


class GreedyActor(TensorDictModuleBase):
    """A picklable greedy actor: ``policy``'s arg-max action, fed ``demo_frames`` looked up
    by ``demo_id`` in ``demo_store`` where it reads them (:class:`FramesFromStore`).
    What the workers of a multi-process evaluation run.

    Args:
        policy: a TensorDict policy writing ``"logits"`` (or ``"action"``).
        demo_store: the episode store the env draws from (``None``: the env emits the frames).

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> actor = GreedyActor(TensorDictModule(torch.nn.Linear(2, 3), ["obs"], ["logits"]))
        >>> actor(TensorDict({"obs": torch.ones(4, 2)}, [4]))["action"].shape
        torch.Size([4])
    """

    def __init__(self, policy: TensorDictModuleBase, demo_store: DemoStore | None = None, in_key: str = "demo_id") -> None:
        super().__init__()
        self.policy = policy
        self.fed = FramesFromStore(policy, demo_store, in_key)
        self.in_keys = list(self.fed.in_keys)
        self.out_keys = list(dict.fromkeys([*policy.out_keys, "action"]))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return greedy(self.fed)(tensordict)


def greedy_on_device(policy: TensorDictModuleBase):
    """:func:`greedy` run on the device of ``policy``'s weights, for an env on the CPU.

    The arg-max is taken on that device; the logits, the action and the next
    recurrent state come back to the env's device. A policy without weights (open-loop
    replay) or on the CPU is called as :func:`greedy` calls it.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> policy = TensorDictModule(torch.nn.Linear(2, 3), ["obs"], ["logits"])
        >>> greedy_on_device(policy)(TensorDict({"obs": torch.ones(4, 2)}, [4], device="cpu"))["action"].shape
        torch.Size([4])
    """
    device = module_device(policy) if isinstance(policy, torch.nn.Module) else None
    out_keys = list(dict.fromkeys([*policy.out_keys, "action"]))
    return act_on_device(greedy(policy), device, in_keys=policy.in_keys, out_keys=out_keys)


#: Where the training recipes keep their evaluation episode stores, unless the
#: environment variable :data:`EPISODE_STORE_ROOT_ENV` names another directory.
EPISODE_STORE_ROOT = "data/episodes"
EPISODE_STORE_ROOT_ENV = "SPF_RL_EPISODE_STORES"


def episode_store_root() -> str:
    """The training recipes' ``store_root``: ``$SPF_RL_EPISODE_STORES``, else ``data/episodes``.

    Examples:
        >>> import os
        >>> os.environ.get(EPISODE_STORE_ROOT_ENV, EPISODE_STORE_ROOT) == episode_store_root()
        True
    """
    return os.environ.get(EPISODE_STORE_ROOT_ENV) or EPISODE_STORE_ROOT


def make_eval_env(
    config: EvalConfig,
    policy: TensorDictModuleBase | None = None,
    demo_store: DemoStore | None = None,
    worker: int = 0,
    workers: int = 1,
) -> TransformedEnv:
    """Batched env with noise, ``is_init`` and the policy's recurrent-state primer
    (:func:`envs.factory.make_env`), seeded with the episodes' seed.

    With ``demo_store`` (an episode store of ``config``, :func:`episode_store`) it
    emits ``demo_id`` instead of the demonstration frames; with ``render=False``, no
    frames (they would be blank) unless ``policy`` reads ``demo_frames``. The env of
    worker ``worker`` of ``workers`` plays episode numbers ``worker``, ``worker + workers``, ...
    """
    reads_frames = policy is not None and "demo_frames" in policy.in_keys
    primer = policy.make_tensordict_primer() if policy is not None and hasattr(policy, "make_tensordict_primer") else None
    return make_env(
        config.episodes,
        min(config.num_agents, config.num_episodes),
        demo_store=demo_store,
        primer=primer,
        episode_offset=worker,
        episode_stride=workers,
        seeded=True,
        render=config.render,
        emit_demo_frames=demo_store is None and (config.render or reads_frames),
    )


def episode_store_config(config: EvalConfig) -> DemoStoreConfig:
    """The episode store of ``config``: the demonstrations of its episodes ``0 .. E - 1``."""
    return DemoStoreConfig.of(config.episodes, config.num_episodes)


def episode_store_name(config: EvalConfig) -> str:
    """The directory name of ``config``'s episode store under ``store_root`` (with the env
    version, so that a store of an older environment is never reopened).

    Examples:
        >>> episode_store_name(EvalConfig(EpisodeSpec(split="val", seed=1), num_episodes=300)).startswith("val-follow-n30-64px-seed1-300ep-env")
        True
    """
    e = config.episodes
    houses = e.house_seeds_tag or ("" if e.num_houses is None else f"-{e.num_houses}houses")
    routes = e.routes_tag
    return (
        f"{e.split}{houses}-{e.task}-n{e.demo_length}{routes}-{e.image_size}px"
        f"-seed{e.seed}-{config.num_episodes}ep-env{ENV_VERSION}"
    )


def episode_store(config: EvalConfig, root: str | os.PathLike | None = None) -> DemoStore | None:
    """The episode store of ``config`` (built on first use) under ``root``, by default
    ``config.store_root``; ``None`` where nothing is to be looked up (no root, or
    ``render=False``)."""
    root = config.store_root if root is None else root
    if root is None or not config.render:
        return None
    return DemoStore.build(Path(root) / episode_store_name(config), episode_store_config(config), progress=False)


def frames_lookup(policy: TensorDictModuleBase, store: DemoStore | None, in_key: str = "demo_id") -> TensorDictModule | None:
    """The module that feeds ``policy`` its ``demo_frames`` from ``in_key`` (``demo_id``, or
    ``memory_id`` with a mismatched memory: :attr:`~envs.episode_spec.EpisodeSpec.frames_id_key`) in ``store``
    (:meth:`~envs.demo_store.DemoStore.lookup_module`), or ``None`` where there is nothing
    to look up (no store, or a policy that does not read the frames).

    Only where ``is_init`` for policies that carry their memory in a recurrent state
    (a ``memory_key`` of theirs or of a submodule, e.g. the SPF policy inside a
    :class:`~torchrl.modules.ProbabilisticActor`, among their ``in_keys``); in every
    row for other policies reading ``demo_frames``.

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> frames_lookup(TensorDictModule(torch.nn.Linear(2, 3), ["obs"], ["logits"]), None) is None
        True
    """
    if store is None or "demo_frames" not in policy.in_keys:
        return None
    carriers = [m for m in policy.modules() if getattr(m, "memory_key", None) in policy.in_keys] if isinstance(
        policy, torch.nn.Module
    ) else []
    return store.lookup_module(in_key=in_key, only_where=getattr(carriers[0], "is_init_key", "is_init") if carriers else None)


def with_store_lookup(
    act: Callable[[TensorDictBase], TensorDictBase], policy: TensorDictModuleBase, store: DemoStore | None, in_key: str = "demo_id"
) -> Callable[[TensorDictBase], TensorDictBase]:
    """``act`` (a callable running ``policy``) fed ``demo_frames`` looked up from
    ``demo_id`` in ``store`` (on the CPU, before it runs, :func:`frames_lookup`), the
    frames dropped after it.
    """
    lookup = frames_lookup(policy, store, in_key)
    if lookup is None:
        return act

    def act_with_frames(tensordict: TensorDictBase) -> TensorDictBase:
        return act(lookup(tensordict)).exclude("demo_frames", inplace=True)

    return act_with_frames


def evaluate_policy(policy: TensorDictModuleBase, config: EvalConfig, progress: bool = False) -> tuple[dict, list[dict]]:
    """Play ``config.num_episodes`` episodes greedily (arg-max action) and summarise them.

    Args:
        policy: a module writing ``"logits"`` (then the arg-max is taken) or ``"action"``;
            it runs on the device of its weights, the env on the CPU.
        config: the evaluation set-up.
        progress: show a progress bar.

    Returns:
        (summary with success, SPL, 95% CIs, mean goal distance; per-episode records).
    """
    was_training = policy.training
    policy.eval()
    try:
        with contextlib.ExitStack() as stack:
            # without a store_root, the episode store lives as long as this evaluation
            root = None if config.store_root is not None else stack.enter_context(tempfile.TemporaryDirectory())
            store = episode_store(config, root)
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                if config.num_collectors == 1:
                    env = make_eval_env(config, policy, store)
                    stack.callback(env.close)
                    act = with_store_lookup(greedy_on_device(policy), policy, store, config.episodes.frames_id_key)
                    records = run_episodes(env, act, config.num_episodes, progress=progress)
                else:
                    stack.enter_context(torch_threads_kept())  # restored after the shutdown below
                    collector = _worker_collector(policy, config, store)
                    stack.callback(collector.shutdown)
                    records = record_episodes(collector, config.num_episodes, progress=progress)
    finally:
        policy.train(was_training)
    return summarize_episodes(records), records


def length_eval_config(config: EvalConfig, demo_length: int, image_size: int) -> EvalConfig:
    """``config`` for demonstrations of ``demo_length`` steps: the rule's ``max_steps``, the policy's frame size."""
    episodes = config.episodes.replace(demo_length=demo_length, max_steps=default_max_steps(demo_length), image_size=image_size)
    return dataclasses.replace(config, episodes=episodes)


def evaluate_lengths(
    policy: SPFPolicy, lengths: list[int], config: EvalConfig, progress: bool = False
) -> tuple[list[dict], dict[int, list[dict]]]:
    """Success and SPL of ``policy`` at each demonstration length (:func:`policy_for_length`).

    Args:
        policy: an SPF-family policy (any ``demo_length``).
        lengths: the demonstration lengths, steps.
        config: the evaluation set-up; ``demo_length``, ``max_steps`` (the rule:
            :func:`~envs.follow.default_max_steps`) and ``image_size`` (the policy's)
            are set per length; every length plays ``config.num_episodes`` episodes.
        progress: show progress bars.

    Returns:
        (one row per length: ``demo_length``, ``max_steps``, ``grid_size_cells`` and the
        summary of :func:`~spf_rl.evaluation.evaluate_policy`; the episode records by length).

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> policy = SPFPolicy(SPFConfig(demo_length=5, feature_dim=8, hidden_size=8, image_size=(16, 16)))
        >>> from envs import EpisodeSpec
        >>> config = EvalConfig(EpisodeSpec(split="val", num_houses=1), num_episodes=2, num_agents=2, render=False)
        >>> rows, _ = evaluate_lengths(policy, [4, 6], config)
        >>> [(row["demo_length"], row["max_steps"], row["episodes"]) for row in rows]
        [(4, 7, 2), (6, 10, 2)]
    """
    rows, records = [], {}
    for length in lengths:
        length_config = length_eval_config(config, length, policy.config.image_size[0])
        summary, records[length] = evaluate_policy(policy_for_length(policy, length), length_config, progress=progress)
        rows.append(
            {
                "demo_length": length,
                "max_steps": length_config.episodes.max_steps,
                "grid_size_cells": default_grid_size_cells(length),
                **summary,
            }
        )
    return rows, records


def summarize_episodes(records: list[dict]) -> dict:
    """:func:`evaluate_policy`'s summary of per-episode records: :func:`~spf_rl.metrics.summarize` and the
    mean distance to the goal, metres."""
    summary = summarize(records)
    summary["mean_goal_distance_m"] = float(sum(r["goal_distance"] for r in records) / len(records))
    return summary


def _worker_collector(policy: TensorDictModuleBase, config: EvalConfig, store: DemoStore | None) -> Collector:
    """A multi-process collector of ``config.num_collectors`` workers, each stepping a batched
    env (episode numbers ``w, w + W, ...``) with a CPU copy of ``policy`` (:class:`GreedyActor`)."""
    workers = config.num_collectors
    actor = GreedyActor(copy.deepcopy(policy).cpu().eval(), store, config.episodes.frames_id_key)
    factories = [functools.partial(make_eval_env, config, actor.policy, store, w, workers) for w in range(workers)]
    agents = min(config.num_agents, config.num_episodes)
    return Collector(
        factories,
        actor,
        num_collectors=workers,
        sync=True,
        frames_per_batch=workers * agents * STEPS_PER_BATCH,
        total_frames=-1,
        exploration_type=ExplorationType.DETERMINISTIC,
        auto_register_policy_transforms=False,
    )


def record_rollout(policy: TensorDictModuleBase, config: EvalConfig) -> dict:
    """Play one episode greedily and keep what the figures need.

    Returns:
        dict with ``frames`` (T, H, W, 3) uint8, ``poses`` (T + 1, 3), ``eta`` (T,)
        (absent for policies without a pointer), ``demo_poses`` (n + 1, 3),
        ``demo_frames`` (n, H, W, 3), ``house_seed``, ``success``, ``spl``.
    """
    config = dataclasses.replace(config, num_agents=1, num_episodes=1)
    env = make_eval_env(config, policy)

    act = greedy_on_device(policy)
    policy.eval()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(config.episodes.step_limit, act, break_when_any_done=True)[0]
    demo = env.base_env.demonstrations[0]
    final = rollout[-1]["next"]
    poses = torch.cat([rollout["pose"], final["pose"][None]]).numpy()
    record = {
        "frames": rollout["pixels"].numpy(),
        "poses": poses,
        "demo_poses": demo.poses,
        "demo_frames": rollout[0]["demo_frames"].numpy(),
        "house_seed": demo.house_seed,
        "success": bool(final["success"].item()),
        "spl": float(final["spl"].item()),
    }
    if "eta_used" in rollout.keys():
        record["eta"] = rollout["eta_used"].reshape(-1).numpy()
    env.close()
    return record
