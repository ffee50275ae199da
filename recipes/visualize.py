"""Figures of what an agent does: map with routes and memory frames, pointer plot, rollout GIF.

For a checkpoint (a file, a shipped name such as ``spf-s0.8``, or ``open_loop``), plays a few test episodes and writes per episode:

* ``map_<i>.png``: the top-down map with the demonstration, the followed path and
  the positions of the memory frames;
* ``pointer_<i>.png``: the pointer eta over time against the demo index the agent
  is actually nearest to (privileged information, for the plot only);
* ``rollout_<i>.gif``: the first-person view beside the map, step by step.

Usage::

    python recipes/visualize.py runs/bc/spf-s0.8-seed0/best.pt --episodes 3 --out figures/spf08
    python recipes/visualize.py spf-s0.8 --episodes 1 --out figures/shipped
"""
from __future__ import annotations

import argparse

from envs.scenes import SPLIT_SEED_OFFSETS
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from spf_rl.cli import ArgumentParser

SPLITS = tuple(SPLIT_SEED_OFFSETS)


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a checkpoint file, a shipped name (spf_rl.list_checkpoints()) or 'open_loop'")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--split", default="test", choices=SPLITS, help="house split (default: test)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, choices=sorted(NOISE_PRESETS), help="actuation-noise preset")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", default="figures/rollouts")
    parser.add_argument("--no-gif", action="store_true")
    args = parser.parse_args(argv)
    if args.episodes <= 0:
        parser.error(f"--episodes must be > 0, got {args.episodes}")

    import envs  # noqa: F401
    from spf_rl.hub import checkpoint_argument
    from spf_rl.modules.open_loop import OpenLoopPolicy
    from spf_rl.viz import watch

    if args.checkpoint == "open_loop":
        policy, label = OpenLoopPolicy(), "open loop"
    else:
        try:  # a missing, unreadable or unknown checkpoint: one line, before any episode is played
            _, policy, payload = checkpoint_argument(args.checkpoint, "argument checkpoint")
        except ValueError as err:
            parser.error(str(err))
        label = f"{payload['model_type']} (sparsity {policy.sparsity:g})"
    for episode in range(args.episodes):
        record = watch(
            policy, args.out, split=args.split, noise=args.noise, seed=args.seed + episode,
            index=episode, label=label, gif=not args.no_gif,
        )
        outcome = f"{'success' if record['success'] else 'failure'}, SPL {record['spl']:.2f}"
        print(f"episode {episode}: {outcome} -> {args.out}")


if __name__ == "__main__":
    main()
