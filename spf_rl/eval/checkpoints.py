"""Checkpoints (or open-loop replay) evaluated on a split with a fixed seed, one JSON each
(``recipes/evaluate.py`` is the command line).

* :func:`expand_targets`: the paths given -> what is evaluated (directories become their
  ``*.pt`` files, sorted; :data:`OPEN_LOOP` and files or shipped names stay as given);
* :func:`evaluate_checkpoint`: one target's results: success, SPL, 95% bootstrap intervals,
  mean distance to goal, memory bytes, the evaluation config and per-episode records
  (:func:`spf_rl.evaluation.evaluate_policy`);
* :func:`output_name`: the JSON file a target's results are written to;
* :func:`evaluate_checkpoints`: every target in turn, each written as soon as it is scored.

Every target evaluated with the same split, episodes and seed plays the same episodes.
The policy runs on :attr:`EvalOptions.device`; the env and its rendering on the CPU.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from envs.atomic_io import atomic_write_json
from envs.episode_spec import EpisodeSpec
from envs.transforms import DEFAULT_NOISE
from spf_rl.evaluation import TEST_SEED
from spf_rl.hub import CHECKPOINT_DIR, list_checkpoints
from spf_rl.modules.exported import is_export

logger = logging.getLogger(__name__)

#: The target that evaluates open-loop replay (no checkpoint, no training).
OPEN_LOOP = "open_loop"
#: Route length of :data:`OPEN_LOOP` without ``demo_length``: the paper's, steps.
OPEN_LOOP_DEMO_LENGTH = 30


@dataclass(frozen=True)
class EvalOptions:
    """How :func:`evaluate_checkpoint` evaluates a target (``recipes/evaluate.py``'s options).

    Attributes:
        split: house split.
        episodes: episodes played (the same ones for every target).
        noise: actuation-noise preset.
        seed: seed of the episodes.
        num_agents: agents stepped together.
        max_steps: episode limit, steps; ``None``: ``ceil(5/3 n)`` for routes of ``n`` steps
            (:func:`~envs.follow.default_max_steps`).
        demo_length: route length, steps; ``None``: the checkpoint's own (30 for :data:`OPEN_LOOP`).
            A checkpoint runs at another length with the same weights
            (:func:`~spf_rl.modules.views.policy_for_length`): a Table 1 policy at 50 steps, or
            ``routes-spf`` (100) on 30-step routes.
        image_size: frame side, pixels, for :data:`OPEN_LOOP` only.
        sparsity: the memory sparsity to evaluate a random-sparsity (``spf_random``) model
            at; ``None``: the model's own. A fixed-sparsity model refuses it.
        model_type: refuse checkpoints of another model type (``None``: any).
        device: where the policy runs.
        store_root: directory of the episode stores (``None`` or ``""``: rendered at every
            episode start; the scores are the same).
        num_collectors: processes playing the episodes (the same episodes and scores).
        progress: show progress bars.
        conditions: the world of the repeat (:mod:`envs.conditions`, e.g. ``"light@0.5"``; ``None``:
            the teaching world).
        memory_mismatch: the fraction of episodes shown another route's frames (``None``: none).
    """

    split: str = "test"
    episodes: int = 500
    noise: str = DEFAULT_NOISE
    seed: int = TEST_SEED
    num_agents: int = 25
    max_steps: int | None = None
    demo_length: int | None = None
    image_size: int = 64
    sparsity: float | None = None
    model_type: str | None = None
    device: str | torch.device = "cpu"
    store_root: str | None = None
    num_collectors: int = 1
    progress: bool = True
    conditions: str | None = None
    memory_mismatch: float | None = None


def expand_targets(paths: Sequence[str]) -> list[str]:
    """What ``paths`` name: :data:`OPEN_LOOP`, files, export directories (:func:`is_export`) or shipped names as
    given, another directory's ``*.pt`` (sorted, recursive).

    Raises:
        ValueError: a directory that holds no ``*.pt`` file.

    Examples:
        >>> expand_targets(["open_loop", "spf-s0.8"])
        ['open_loop', 'spf-s0.8']
    """
    targets: list[str] = []
    for path in paths:
        if path != OPEN_LOOP and Path(path).is_dir() and not is_export(path):
            found = sorted(str(p) for p in Path(path).rglob("*.pt"))
            if not found:
                raise ValueError(f"directory {path} holds no *.pt checkpoint")
            targets += found
        else:
            targets.append(path)
    return targets


def output_name(target: str, options: EvalOptions, shipped: frozenset[str] | set[str] = frozenset()) -> str:
    """The JSON file name of ``target``'s results: a shipped name is ``checkpoints_<name>``, a file its path.

    Args:
        target: :data:`OPEN_LOOP`, a shipped name or a checkpoint path.
        options: the evaluation (split, noise, seed and, for a model, the sparsity name the file).
        shipped: the shipped names (:func:`spf_rl.hub.list_checkpoints`).

    Examples:
        >>> options = EvalOptions(split="test", noise="paper", seed=2)
        >>> output_name("runs/bc/spf-s0.8-seed0/best.pt", options)
        'runs_bc_spf-s0.8-seed0_best-test-paper-seed2.json'
        >>> output_name("spf_random-s0.2-1", EvalOptions(sparsity=0.6), {"spf_random-s0.2-1"})
        'checkpoints_spf_random-s0.2-1-at0.6-test-paper-seed2.json'
        >>> output_name("open_loop", EvalOptions(sparsity=0.6))
        'open_loop-test-paper-seed2.json'
        >>> output_name("spf-s0.8", EvalOptions(conditions="light@0.5"), {"spf-s0.8"})
        'checkpoints_spf-s0.8-test-paper-light0.5x1.0-seed2.json'
    """
    if target == OPEN_LOOP:
        name = target
    elif target in shipped:
        name = f"checkpoints_{target}"
    else:
        name = Path(target).with_suffix("").as_posix().replace("/", "_").strip("_.")
    if options.sparsity is not None and target != OPEN_LOOP:
        name += f"-at{options.sparsity:g}"
    world = EpisodeSpec(conditions=options.conditions, memory_mismatch=options.memory_mismatch).conditions_tag
    return f"{name}-{options.split}-{options.noise}{world}-seed{options.seed}.json"


def evaluate_checkpoint(target: str, options: EvalOptions) -> dict:
    """Evaluate one checkpoint file or shipped name (or :data:`OPEN_LOOP`) and return its results.

    Returns:
        ``checkpoint``, ``model``, ``sparsity``, ``memory_bytes``, ``device``, the summary of
        :func:`~spf_rl.evaluation.evaluate_policy` (``success``, ``success_ci``, ``spl``, ...),
        ``eval`` (the :class:`~spf_rl.evaluation.EvalConfig`) and ``episodes_records``.

    Raises:
        ValueError: :attr:`EvalOptions.sparsity` for a model of fixed sparsity.
        CheckpointError: a checkpoint of another model type than :attr:`EvalOptions.model_type`.
    """
    import envs  # noqa: F401  (selects the headless GL back-end first)
    from envs.follow import default_max_steps
    from spf_rl.device import module_device
    from spf_rl.evaluation import EvalConfig, config_dict, evaluate_policy
    from spf_rl.hub import policy_from_checkpoint, resolve_checkpoint
    from spf_rl.modules.open_loop import OpenLoopPolicy
    from spf_rl.modules.views import model_memory_bytes, policy_for_length

    if target == OPEN_LOOP:
        demo_length = OPEN_LOOP_DEMO_LENGTH if options.demo_length is None else options.demo_length
        policy, model_type, image_size, sparsity = OpenLoopPolicy(), OPEN_LOOP, options.image_size, 0.0
        memory = demo_length
    elif is_export(target):  # an exported policy, run by ONNX Runtime (the runtime's graphs, the same episodes)
        from spf_rl.modules.exported import ExportedPolicy

        policy = ExportedPolicy(target, demo_length=options.demo_length, sparsity=options.sparsity)
        model_type, demo_length, sparsity = policy.model_type, policy.demo_length, policy.sparsity
        image_size = policy.export.image_size[0]
        memory = model_memory_bytes(model_type, demo_length, sparsity, image_size)
    else:
        policy, payload = policy_from_checkpoint(
            resolve_checkpoint(target), expected_model_type=options.model_type, device=options.device
        )
        config = payload["model_config"]
        model_type = payload["model_type"]
        demo_length, image_size, sparsity = config.demo_length, config.image_size[0], config.effective_sparsity
        if options.sparsity is not None:
            if config.sparsity_range is None:
                raise ValueError(
                    f"--sparsity applies to random-sparsity models (model type 'spf_random') only; {target} holds a "
                    f"{model_type!r} model with a fixed sparsity {sparsity:g}."
                )
            policy.set_sparsity(options.sparsity)
            sparsity = options.sparsity
        if options.demo_length is not None and options.demo_length != demo_length:
            policy = policy_for_length(policy, options.demo_length)  # the same weights, another route length
            if config.sparsity_range is not None:  # the sparsity is set per view, not in the weights
                policy.set_sparsity(sparsity)
            demo_length = options.demo_length
        memory = model_memory_bytes(model_type, demo_length, sparsity, image_size)
    episodes = EpisodeSpec(
        split=options.split,
        noise=options.noise,
        seed=options.seed,
        demo_length=demo_length,
        max_steps=default_max_steps(demo_length) if options.max_steps is None else options.max_steps,
        image_size=image_size,
        conditions=options.conditions,
        memory_mismatch=options.memory_mismatch,
    )
    eval_config = EvalConfig(
        episodes,
        num_episodes=options.episodes,
        num_agents=options.num_agents,
        render=target != OPEN_LOOP,
        store_root=options.store_root or None,
        num_collectors=options.num_collectors,
    )
    summary, records = evaluate_policy(policy, eval_config, progress=options.progress)
    return {
        "checkpoint": target,
        "model": model_type,
        "sparsity": sparsity,
        "memory_bytes": memory,
        "device": str(module_device(policy)),  # the CPU for open-loop replay, which has no weights
        **summary,
        "eval": config_dict(eval_config),
        "episodes_records": records,
    }


def evaluate_checkpoints(targets: Sequence[str], options: EvalOptions, out: Path) -> Iterator[tuple[str, dict, Path]]:
    """Evaluate every target in turn, writing each one's JSON to ``out`` (:func:`output_name`) as soon as it is scored.

    Yields:
        ``(target, its results, the JSON written)``, in target order.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shipped = set(list_checkpoints()) if CHECKPOINT_DIR.is_dir() else set()
    for target in targets:
        logger.debug("evaluating %s", target)
        result = evaluate_checkpoint(target, options)
        destination = out / output_name(target, options, shipped)
        atomic_write_json(destination, result)
        yield target, result, destination
