"""Success and SPL of the scripted policies: the geodesic expert and open-loop replay.

Writes ``benchmarks/results/expert_stats.json`` and prints a markdown table.
Each (policy, noise) pair is scored with :func:`envs.episodes.run_episodes` on
the same episodes (a batched env with a fixed seed: agent ``i``'s k-th episode
depends only on the seed, ``i`` and ``k``), without rendering
(``render=False``, ``with_expert=True``). Means come with 95% percentile
bootstrap confidence intervals (numpy, fixed seed).

Usage::

    python recipes/expert_stats.py                       # train and test, 500 episodes each
    python recipes/expert_stats.py --splits train --episodes 100
    python recipes/expert_stats.py --task homing --episodes 100 --runs expert:paper   # -> expert_stats_homing_n30.json
    python recipes/expert_stats.py --demo-length 100 --episodes 100 --runs expert:paper  # -> expert_stats_follow_n100.json
    python recipes/expert_stats.py --splits test --demo-length 100 --route-style driven --route-lengths 61 100 \
        --expert goal --runs expert:paper --episodes 64 --output benchmarks/results/expert_route_driven_goal.json

Runs of another task or demonstration length than the paper's (follow, n = 30) write
``expert_stats_<task>_n<n>.json`` beside it unless ``--output`` is given.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

import envs  # noqa: F401  (selects the headless GL back-end first)
from envs.demos import DEFAULT_DEMO_LENGTH
from envs.homing import FOLLOW, TASKS
from envs.route_expert import EXPERTS
from envs.route_styles import route_mixture_for
from spf_rl.cli import ArgumentParser
from spf_rl.eval.scripted import (
    DEFAULT_RUNS,
    RESULTS_NAME,
    check_splits,
    default_output,
    markdown_table,
    parse_runs,
    run_study,
    study_env_kwargs,
)

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / RESULTS_NAME


def main() -> None:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=500, help="episodes per (split, policy, noise)")
    parser.add_argument("--splits", nargs="+", default=["train", "test"])
    parser.add_argument("--num-agents", type=int, default=25, help="agents of the batched env")
    parser.add_argument("--demo-length", type=int, default=None, help="default: the env's")
    parser.add_argument("--task", default=FOLLOW, choices=TASKS, help="follow the route, or return to its start (homing)")
    parser.add_argument("--seed", type=int, default=0, help="env seed (fixes the episodes) and bootstrap seed")
    parser.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples")
    parser.add_argument(
        "--runs", nargs="+", default=[f"{p}:{n}" for p, n in DEFAULT_RUNS], help="policy:noise pairs (expert|open_loop)"
    )
    parser.add_argument("--route-style", default=None, help="route style or mixture (envs.route_styles), e.g. driven or planner=1,driven=1")
    parser.add_argument("--route-lengths", type=int, nargs=2, default=None, metavar=("SHORTEST", "LONGEST"), help="route lengths, steps")
    parser.add_argument("--expert", default=None, choices=EXPERTS, help="the env's expert (default: route with --route-style)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (runs are independent)")
    parser.add_argument("--output", type=Path, default=None, help=f"default {RESULTS_PATH.name}, or expert_stats_<task>_n<n>.json")
    args = parser.parse_args()
    if args.demo_length is not None and args.demo_length <= 0:
        parser.error(f"--demo-length must be a positive int, got {args.demo_length}")
    for name, value in (("--episodes", args.episodes), ("--num-agents", args.num_agents), ("--resamples", args.resamples), ("--jobs", args.jobs)):
        if value <= 0:
            parser.error(f"{name} must be a positive int, got {value}")
    output = args.output or default_output(RESULTS_PATH, args.task, args.demo_length)
    try:  # the whole config first, before any episode is played
        runs = parse_runs(args.runs)
        check_splits(args.splits)
        route_mixture_for(args.route_style, args.route_lengths, args.demo_length or DEFAULT_DEMO_LENGTH)
    except ValueError as err:
        parser.error(str(err))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)

    route_lengths = None if args.route_lengths is None else tuple(args.route_lengths)
    env_kwargs = study_env_kwargs(args.num_agents, args.task, args.demo_length, args.route_style, route_lengths, args.expert)
    content = run_study(args.splits, runs, output, episodes=args.episodes, env_kwargs=env_kwargs, seed=args.seed,
                        resamples=args.resamples, jobs=args.jobs)
    print("\n" + markdown_table(content["results"]))
    print(f"\nwrote {output}")


if __name__ == "__main__":
    main()
