"""Evaluate trained checkpoints (or the open-loop baseline) on a split, with a fixed seed.

Every model evaluated with the same ``--split``, ``--episodes`` and ``--seed``
plays the same episodes. Writes one JSON per model: success, SPL, 95% bootstrap
confidence intervals, mean distance to goal, memory bytes, per-episode records.

Usage::

    python recipes/evaluate.py runs/bc/spf-s0.8-seed0/best.pt
    python recipes/evaluate.py spf-s0.8 dagger-spf-s0.8   # shipped names (spf_rl.list_checkpoints())
    python recipes/evaluate.py checkpoints/ --split test --episodes 500 --noise paper --out results/eval
    python recipes/evaluate.py open_loop --split test
    python recipes/evaluate.py spf_random-s0.2-1 --sparsity 0.6   # one model, any sparsity
    python recipes/evaluate.py routes-spf --demo-length 30        # the same weights on 30-step routes
    python recipes/evaluate.py exports/spf-s0.8                   # an export (recipes/export.py), run by ONNX Runtime
    python recipes/evaluate.py checkpoints/ --device cpu     # default --device auto: CUDA if available
    python recipes/evaluate.py spf-s0.8 --conditions light@0.5   # repeated at dusk (envs.conditions)

A shipped name's JSON is named ``checkpoints_<name>-...``, a file's after its path.
The policy runs on ``--device``; the env and its rendering on the CPU.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.episode_spec import EpisodeSpec
from envs.scenes import SPLIT_SEED_OFFSETS
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from spf_rl.cli import ArgumentParser
from spf_rl.device import DEFAULT_DEVICE, DEVICE_CHOICES, resolve_device
from spf_rl.eval.checkpoints import OPEN_LOOP, EvalOptions, evaluate_checkpoints, expand_targets
from spf_rl.evaluation import TEST_SEED
from spf_rl.modules.registry import MODEL_NAMES

SPLITS = tuple(SPLIT_SEED_OFFSETS)


def check_target(target: str, model_type: str | None, sparsity: float | None) -> None:
    """Refuse a checkpoint that is missing, unreadable, of another ``--model-type``, or of a fixed
    sparsity with ``--sparsity`` (``ValueError``, one line naming the argument)."""
    from spf_rl.eval.checkpoints import is_export
    from spf_rl.hub import checkpoint_argument

    if is_export(target):  # an export directory: its files match its manifest, and its model type is the one asked
        from spf_rl_runtime import Export

        manifest = Export(target).manifest
        if model_type is not None and manifest["model_type"] != model_type:
            raise ValueError(f"argument paths: {target} exports a {manifest['model_type']!r} model, not {model_type!r}")
        if sparsity is not None and manifest["model_type"] != "spf_random":
            raise ValueError(f"argument --sparsity: applies to random-sparsity models (model type 'spf_random') only; "
                             f"{target} exports a {manifest['model_type']!r} model")
        return
    payload = checkpoint_argument(target, "argument paths", model_type=model_type).payload
    config = payload["model_config"]
    if sparsity is not None and config.sparsity_range is None:
        raise ValueError(
            f"argument --sparsity: applies to random-sparsity models (model type 'spf_random') only; {target} holds a "
            f"{payload['model_type']!r} model with a fixed sparsity {config.effective_sparsity:g}."
        )


def main(argv: list[str] | None = None) -> list[dict]:
    from spf_rl.evaluation import episode_store_root

    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="checkpoint files, directories of *.pt, export directories, or 'open_loop'")
    parser.add_argument("--split", default="test", choices=SPLITS, help="house split (default: test)")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--noise", default=DEFAULT_NOISE, choices=sorted(NOISE_PRESETS), help="actuation-noise preset")
    parser.add_argument("--seed", type=int, default=TEST_SEED, help="seed of the episodes (default %(default)s, the test seed)")
    parser.add_argument("--num-agents", type=int, default=25)
    parser.add_argument("--max-steps", type=int, default=None, help="episode limit, steps (default: ceil(5/3 x the route length))")
    parser.add_argument(
        "--demo-length", type=int, default=None,
        help="route length, steps (default: the checkpoint's own, 30 for open_loop); a checkpoint runs at another length with the same weights",
    )
    parser.add_argument("--image-size", type=int, default=64, help="for open_loop only")
    parser.add_argument(
        "--sparsity", type=float, default=None, help="memory sparsity to evaluate a random-sparsity (spf_random) model at"
    )
    parser.add_argument("--model-type", default=None, help="refuse checkpoints of another model type")
    parser.add_argument(
        "--device", default=DEFAULT_DEVICE, help=f"where the policy runs: {DEVICE_CHOICES} (default: %(default)s, CUDA if available)"
    )
    parser.add_argument("--out", default="results/eval", help="output directory for the JSON files")
    parser.add_argument(
        "--store-root",
        default=episode_store_root(),
        help="directory keeping the episode stores (demonstrations rendered once, reused by later evaluations of "
        "the same episodes; the scores do not change); '' renders them at every episode start (default: %(default)s)",
    )
    parser.add_argument(
        "--num-collectors", type=int, default=1,
        help="processes playing the episodes, each with a CPU copy of the policy (same episodes and scores; default: 1)",
    )
    parser.add_argument("--conditions", help="repeat in a changed world (envs.conditions): name@strength, name one of "
                        "light, paint, furniture, camera, sensor, strength in [0, 1], or a mixture 'light@0.5=1,paint@1=1'")
    parser.add_argument("--memory-mismatch", type=float, help="fraction of episodes shown another route's frames with their own actions")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.episodes <= 0:
        parser.error(f"--episodes must be > 0, got {args.episodes}")
    if args.num_collectors <= 0:
        parser.error(f"--num-collectors must be a positive int, got {args.num_collectors}")
    for name, value in (("--demo-length", args.demo_length), ("--max-steps", args.max_steps)):
        if value is not None and value <= 0:
            parser.error(f"{name} must be a positive number of steps, got {value}")
    for name, value in (("--num-agents", args.num_agents), ("--image-size", args.image_size)):
        if value <= 0:
            parser.error(f"{name} must be a positive int, got {value}")
    if args.model_type is not None and args.model_type not in MODEL_NAMES:
        parser.error(f"argument --model-type: must be one of {', '.join(MODEL_NAMES)}, got {args.model_type!r}")
    if args.sparsity is not None and not 0.0 < args.sparsity <= 1.0:
        parser.error(f"--sparsity must be in (0, 1] (the fraction of the demonstration's frames kept), got {args.sparsity}")
    try:
        EpisodeSpec(conditions=args.conditions, memory_mismatch=args.memory_mismatch)
    except ValueError as err:
        parser.error(f"--{str(err).replace('memory_mismatch', 'memory-mismatch')}")
    try:
        device = resolve_device(args.device, name="--device")
        targets = expand_targets(args.paths)
        for target in targets:  # every checkpoint loads, before any episode is played or file written
            if target != OPEN_LOOP:
                check_target(target, args.model_type, args.sparsity)
    except ValueError as err:
        parser.error(str(err))
    options = EvalOptions(
        split=args.split, episodes=args.episodes, noise=args.noise, seed=args.seed, num_agents=args.num_agents,
        max_steps=args.max_steps, demo_length=args.demo_length, image_size=args.image_size, sparsity=args.sparsity,
        model_type=args.model_type, device=device, store_root=args.store_root, num_collectors=args.num_collectors,
        progress=not args.no_progress, conditions=args.conditions, memory_mismatch=args.memory_mismatch,
    )
    results = []
    for target, result, destination in evaluate_checkpoints(targets, options, Path(args.out)):
        print(f"{target}: success {result['success']:.3f} {result['success_ci']}  SPL {result['spl']:.3f} -> {destination}")
        results.append(result)
    return results


if __name__ == "__main__":
    main()
