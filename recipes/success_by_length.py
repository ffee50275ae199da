"""Success against route length: evaluate checkpoints on demonstrations of 30, 50 and 100 steps.

Each checkpoint's weights run at every length (:func:`spf_rl.modules.views.policy_for_length`:
SPF's weights do not depend on the demonstration length); episodes of ``n`` steps are
sampled in houses large enough for them and end after ``ceil(5/3 n)`` steps. Every
checkpoint plays the same episodes at a length (same seed). Written to ``--out``:

* ``success_by_length.json``: the set-up and, per checkpoint, one row per length
  (success, SPL, 95% CIs, episodes, ``max_steps``, the houses' grid);
* ``success_by_length.png``: success and SPL against the length, one line per checkpoint.

Usage::

    python recipes/success_by_length.py spf-s0.8                                    # a shipped checkpoint
    python recipes/success_by_length.py runs/bc_lengths/spf-s0.8-seed0/best.pt spf-s0.8 --episodes 500
    python recipes/success_by_length.py spf-s0.8 --lengths 30 50 --noise paper_symmetric --out results/lengths-sym
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.scenes import SPLIT_SEED_OFFSETS
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from spf_rl.cli import ArgumentParser
from spf_rl.evaluation import TEST_SEED


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", help="shipped checkpoint names or .pt paths")
    parser.add_argument("--lengths", type=int, nargs="+", default=[30, 50, 100], help="demonstration lengths, steps")
    parser.add_argument("--episodes", type=int, default=200, help="episodes per length and checkpoint (default 200)")
    parser.add_argument("--split", default="test", help=f"house split: {', '.join(SPLIT_SEED_OFFSETS)} (default test)")
    parser.add_argument("--num-houses", type=int, default=None, help="houses of the split (default: all of it)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"actuation noise: {', '.join(sorted(NOISE_PRESETS))}")
    parser.add_argument("--seed", type=int, default=TEST_SEED, help="seed of the episodes (default %(default)s, the test seed)")
    parser.add_argument("--num-agents", type=int, default=25, help="agents stepped together (default 25)")
    parser.add_argument("--device", default="cpu", help="where the policies run: cpu, auto, cuda, cuda:N")
    parser.add_argument("--no-render", action="store_true", help="black frames (a pipeline check, not a result)")
    parser.add_argument("--out", default="results/lengths", help="output directory (default results/lengths)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> dict:
    """Run the recipe; returns the JSON content it writes."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if any(length <= 0 for length in args.lengths) or len(set(args.lengths)) != len(args.lengths):
        parser.error(f"--lengths must be distinct positive ints (steps), got {args.lengths}.")
    if args.episodes <= 0 or args.num_agents <= 0:
        parser.error(f"--episodes and --num-agents must be positive ints, got {args.episodes}, {args.num_agents}.")
    from envs.episode_spec import EpisodeSpec
    from spf_rl.device import resolve_device
    from spf_rl.eval.by_length import load_policies, success_by_length
    from spf_rl.evaluation import EvalConfig
    from spf_rl.hub import checkpoint_argument

    try:  # every argument, and every checkpoint's loading, before any episode is played
        episodes = EpisodeSpec(split=args.split, noise=args.noise, seed=args.seed, num_houses=args.num_houses, max_steps=50)
        config = EvalConfig(episodes, num_episodes=args.episodes, num_agents=args.num_agents, render=not args.no_render)
        device = resolve_device(args.device, name="--device")
        for checkpoint in args.checkpoints:
            checkpoint_argument(checkpoint, "argument checkpoints")
    except ValueError as err:
        parser.error(str(err))
    policies = load_policies(args.checkpoints, device=device)

    content = success_by_length(policies, args.lengths, config, Path(args.out), progress=not args.quiet)
    for label, rows in content["results"].items():
        print(label + ": " + ", ".join(f"n={row['demo_length']} success {row['success']:.2f} SPL {row['spl']:.2f}" for row in rows))
    return content


if __name__ == "__main__":
    main()
