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

A shipped name's JSON is named ``checkpoints_<name>-...``, a file's after its path.
    python recipes/evaluate.py checkpoints/ --device cpu     # default --device auto: CUDA if available

The policy runs on ``--device``; the env and its rendering on the CPU.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.atomic_io import atomic_write_json
from envs.scenes import SPLIT_SEED_OFFSETS
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from spf_rl.device import DEFAULT_DEVICE, DEVICE_CHOICES, module_device, resolve_device
from spf_rl.hub import CHECKPOINT_DIR, list_checkpoints

SPLITS = tuple(SPLIT_SEED_OFFSETS)


def evaluate_path(path: str, args: argparse.Namespace) -> dict:
    """Evaluate one checkpoint file (or ``open_loop``) and return its results dict."""
    import envs  # noqa: F401
    from spf_rl.hub import policy_from_checkpoint, resolve_checkpoint
    from spf_rl.modules.open_loop import OpenLoopPolicy
    from spf_rl.train.bc import model_memory_bytes
    from spf_rl.train.evaluation import EvalConfig, evaluate_policy

    if path == "open_loop":
        policy, model_type, demo_length, image_size, sparsity = OpenLoopPolicy(), "open_loop", args.demo_length, args.image_size, 0.0
        memory = demo_length
    else:
        policy, payload = policy_from_checkpoint(
            resolve_checkpoint(path), expected_model_type=args.model_type, device=args.device
        )
        config = payload["model_config"]
        model_type = payload["model_type"]
        demo_length, image_size, sparsity = config.demo_length, config.image_size[0], config.effective_sparsity
        if args.sparsity is not None:
            if config.sparsity_range is None:
                raise ValueError(
                    f"--sparsity applies to random-sparsity models (model type 'spf_random') only; {path} holds a "
                    f"{model_type!r} model with a fixed sparsity {sparsity:g}."
                )
            policy.set_sparsity(args.sparsity)
            sparsity = args.sparsity
        memory = model_memory_bytes(model_type, demo_length, sparsity, image_size)
    eval_config = EvalConfig(
        split=args.split,
        num_episodes=args.episodes,
        noise=args.noise,
        seed=args.seed,
        num_agents=args.num_agents,
        demo_length=demo_length,
        max_steps=args.max_steps,
        image_size=image_size,
        render=path != "open_loop",
        store_root=args.store_root or None,
        num_collectors=args.num_collectors,
    )
    summary, records = evaluate_policy(policy, eval_config, progress=not args.no_progress)
    return {
        "checkpoint": path,
        "model": model_type,
        "sparsity": sparsity,
        "memory_bytes": memory,
        "device": str(module_device(policy)),  # the CPU for open-loop replay, which has no weights
        **summary,
        "eval": vars(eval_config),
        "episodes_records": records,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    from spf_rl.train.evaluation import episode_store_root

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="checkpoint files, directories of *.pt, or 'open_loop'")
    parser.add_argument("--split", default="test", choices=SPLITS, help="house split (default: test)")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--noise", default=DEFAULT_NOISE, choices=sorted(NOISE_PRESETS), help="actuation-noise preset")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--num-agents", type=int, default=25)
    parser.add_argument("--max-steps", type=int, default=50)
    parser.add_argument("--demo-length", type=int, default=30, help="for open_loop only")
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
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.episodes <= 0:
        parser.error(f"--episodes must be > 0, got {args.episodes}")
    if args.num_collectors <= 0:
        parser.error(f"--num-collectors must be a positive int, got {args.num_collectors}")
    try:
        args.device = resolve_device(args.device, name="--device")
    except ValueError as err:
        parser.error(str(err))

    targets: list[str] = []
    for path in args.paths:
        if path == "open_loop":
            targets.append(path)
        elif Path(path).is_dir():
            found = sorted(str(p) for p in Path(path).rglob("*.pt"))
            if not found:
                parser.error(f"directory {path} holds no *.pt checkpoint")
            targets += found
        else:
            targets.append(path)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shipped = set(list_checkpoints()) if CHECKPOINT_DIR.is_dir() else set()
    results = []
    for target in targets:
        result = evaluate_path(target, args)
        if target == "open_loop":
            name = target
        elif target in shipped:
            name = f"checkpoints_{target}"
        else:
            name = Path(target).with_suffix("").as_posix().replace("/", "_").strip("_.")
        if args.sparsity is not None and target != "open_loop":
            name += f"-at{args.sparsity:g}"
        destination = out / f"{name}-{args.split}-{args.noise}-seed{args.seed}.json"
        atomic_write_json(destination, result)
        print(f"{target}: success {result['success']:.3f} {result['success_ci']}  SPL {result['spl']:.3f} -> {destination}")
        results.append(result)
    return results


if __name__ == "__main__":
    main()
