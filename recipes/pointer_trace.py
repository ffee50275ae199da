"""Pointer trace: where a route-following policy fails, and whether its pointer was to blame.

A policy with RPF's pointer rule plays ``--episodes`` routes of each style (one agent
each, greedy, under ``--noise``). At every step the pointer it used is set against the
agent's place on the route and its distance from the path. Written to ``--out``: per
style and outcome, the pointer's error, the share of failures that left the path, the
pointer's error when they did (and how often it lay outside the attention window), and
where along the route they left it; the figure (``.png``) is written next to it.
The work is :mod:`spf_rl.eval.pointer_trace`'s.

Usage::

    python recipes/pointer_trace.py --checkpoint checkpoints/routes/spf_random-seed0.pt
    python recipes/pointer_trace.py --checkpoint checkpoints/routes/spf_random-seed0.pt --styles driven --route-lengths 61 100 --episodes 64
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from spf_rl.cli import ArgumentParser
from spf_rl.evaluation import TEST_SEED

DEFAULT_OUT = Path("results/pointer_trace.json")


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="a shipped name or a .pt path (RPF pointer rule)")
    parser.add_argument("--styles", default="planner,tour,driven", help="route styles (default planner,tour,driven)")
    parser.add_argument("--route-lengths", type=int, nargs=2, default=(10, 100), metavar=("SHORTEST", "LONGEST"),
                        help="route lengths, steps (default 10 100)")
    parser.add_argument("--episodes", type=int, default=32, help="routes per style (default 32)")
    parser.add_argument("--split", default="test", help="house split (default test)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"actuation noise preset (default {DEFAULT_NOISE})")
    parser.add_argument("--sparsity", type=float, help="sparsity of a random-sparsity model (default: its config's)")
    parser.add_argument("--seed", type=int, default=TEST_SEED, help="seed of the routes and noise (default %(default)s, the test seed)")
    parser.add_argument("--conditions", default=None,
                        help="repeat the routes in a changed world, e.g. light@0.5 or 'light@1=1,sensor@1=1' (envs.conditions; default: the teaching world)")
    parser.add_argument("--memory-mismatch", type=float, default=None,
                        help="the fraction of routes shown another route's frames with their own actions (default: none)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"the JSON (default {DEFAULT_OUT})")
    return parser


def main(argv: list[str] | None = None) -> dict:
    """Run the recipe; returns the JSON content it writes."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from envs.atomic_io import atomic_write_json
    from envs.episode_spec import EpisodeSpec
    from envs.route_styles import route_mixture_for
    from envs.scenes import SPLIT_SEED_OFFSETS
    from spf_rl.eval.pointer_trace import check_rpf_pointer, plot_traces, summarize_traces, trace_routes
    from spf_rl.eval.route_bench import STYLES, parse_list
    from spf_rl.hub import checkpoint_argument

    try:  # everything is checked before any episode is played
        styles = parse_list(args.styles, STYLES, "--styles")
        if args.episodes < 1:
            raise ValueError(f"--episodes must be a positive int, got {args.episodes}.")
        if args.noise not in NOISE_PRESETS:
            raise ValueError(f"--noise must be one of {', '.join(sorted(NOISE_PRESETS))}, got {args.noise!r}.")
        if args.split not in SPLIT_SEED_OFFSETS:
            raise ValueError(f"--split must be one of {sorted(SPLIT_SEED_OFFSETS)}, got {args.split!r}.")
        if args.sparsity is not None and not 0.0 < args.sparsity <= 1.0:
            raise ValueError(f"--sparsity must be in (0, 1] (the fraction of the demonstration's frames kept), got {args.sparsity}.")
        lengths = tuple(args.route_lengths)
        try:  # one spelling of the repeat's world, checked as every episode description checks it
            conditions = EpisodeSpec(conditions=args.conditions, memory_mismatch=args.memory_mismatch).conditions
        except ValueError as err:
            raise ValueError(f"--{str(err).replace('memory_mismatch', 'memory-mismatch')}") from None
        policy = checkpoint_argument(args.checkpoint, "argument --checkpoint").policy
        try:
            check_rpf_pointer(policy)
        except ValueError as err:
            raise ValueError(f"argument --checkpoint: {args.checkpoint}: {err}") from None
        for style in styles:
            route_mixture_for(style, lengths, policy.config.demo_length)
        random = policy.config.sparsity_range is not None
        if args.sparsity is not None and not random:
            raise ValueError(f"--sparsity is for random-sparsity models; {args.checkpoint} has a fixed sparsity.")
        sparsity = (args.sparsity if args.sparsity is not None else policy.config.sparsity) if random else policy.config.sparsity
        if random:
            policy.set_sparsity(sparsity)
    except ValueError as err:
        parser.error(str(err))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")

    traces = {}
    content: dict = {
        "recipe": "recipes/pointer_trace.py",
        "setup": {"checkpoint": str(args.checkpoint), "sparsity": float(sparsity), "styles": list(styles),
                  "route_lengths": list(lengths), "episodes_per_style": args.episodes, "split": args.split,
                  "noise": args.noise, "seed": args.seed, "window_k": int(policy.config.k),
                  "conditions": conditions, "memory_mismatch": args.memory_mismatch,
                  "anchor_radius": policy.config.anchor_radius, "replay_gate": policy.config.replay_gate},
        "summary": {},
        "episodes": {},
    }
    for style in styles:
        traces[style] = trace_routes(policy, style=style, route_lengths=lengths, episodes=args.episodes,
                                     split=args.split, noise=args.noise, seed=args.seed,
                                     conditions=conditions, memory_mismatch=args.memory_mismatch)
        content["summary"][style] = summarize_traces(traces[style], window=int(policy.config.k))
        content["episodes"][style] = [
            {"success": bool(t.record["success"]), "ndtw": float(t.record["ndtw"]), "demo_steps": int(t.record["demo_steps"]),
             "steps": len(t.pointer), "left_path_at": t.left_path_at,
             "pointer_at_end": float(t.pointer[-1]), "route_step_at_end": int(t.route_step[-1])}
            for t in traces[style]
        ]
        logging.info("%s: %s", style, content["summary"][style])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out, content)
    plot_traces(traces, args.out.with_suffix(".png"))
    logging.info("wrote %s and %s", args.out, args.out.with_suffix(".png"))
    return content


if __name__ == "__main__":
    main()
