"""Success and SPL of the scripted policies: the geodesic expert and open-loop replay.

Writes ``benchmarks/results/expert_stats.json`` and prints a markdown table.
Each (policy, noise) pair is scored with :func:`envs.scripted.run_episodes` on
the same episodes (a batched env with a fixed seed: agent ``i``'s k-th episode
depends only on the seed, ``i`` and ``k``), without rendering
(``render=False``, ``with_expert=True``). Means come with 95% percentile
bootstrap confidence intervals (numpy, fixed seed).

Usage::

    python recipes/expert_stats.py                       # train and test, 500 episodes each
    python recipes/expert_stats.py --splits train --episodes 100
    python recipes/expert_stats.py --task homing --episodes 100 --runs expert:paper   # -> expert_stats_homing_n30.json
    python recipes/expert_stats.py --demo-length 100 --episodes 100 --runs expert:paper  # -> expert_stats_follow_n100.json

Runs of another task or demonstration length than the paper's (follow, n = 30) write
``expert_stats_<task>_n<n>.json`` beside it unless ``--output`` is given.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

import envs  # noqa: F401  (selects the headless GL back-end first)
from envs.atomic_io import atomic_write_json
from envs.demos import DEFAULT_DEMO_LENGTH
from envs.factory import make_path_follow_env
from envs.homing import FOLLOW, TASKS
from envs.scenes import SPLIT_SEED_OFFSETS, build_house
from envs.transforms import NOISE_PRESETS
from spf_rl.eval.scripted import DEFAULT_RUNS, NOTES, POLICIES, run_one

logger = logging.getLogger("expert_stats")

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "expert_stats.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (runs are independent)")
    parser.add_argument("--output", type=Path, default=None, help=f"default {RESULTS_PATH.name}, or expert_stats_<task>_n<n>.json")
    args = parser.parse_args()
    if args.demo_length is not None and args.demo_length <= 0:
        parser.error(f"--demo-length must be a positive int, got {args.demo_length}")
    if args.output is None:
        length = args.demo_length or DEFAULT_DEMO_LENGTH
        paper = args.task == FOLLOW and length == DEFAULT_DEMO_LENGTH
        args.output = RESULTS_PATH if paper else RESULTS_PATH.with_name(f"expert_stats_{args.task}_n{length}.json")
    for run in args.runs:  # the whole config first, before any episode is played
        policy_name, _, noise = run.partition(":")
        if policy_name not in POLICIES or noise not in NOISE_PRESETS:
            parser.error(f"--runs: {run!r} must be POLICY:NOISE with POLICY in (expert, open_loop) and NOISE in {sorted(NOISE_PRESETS)}")
    for split in args.splits:
        if split not in SPLIT_SEED_OFFSETS:
            parser.error(f"--splits: {split!r} is not one of {list(SPLIT_SEED_OFFSETS)}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)

    env_kwargs: dict = {"num_agents": args.num_agents, "render": False, "emit_demo_frames": False, "with_expert": True, "task": args.task}
    if args.demo_length is not None:
        env_kwargs["demo_length"] = args.demo_length
    results: list[dict] = []
    base = make_path_follow_env("none", split=args.splits[0], **{**env_kwargs, "num_agents": 1}).base_env
    output = {
        "recipe": "recipes/expert_stats.py",
        "setup": {
            "episodes_per_run": args.episodes,
            "num_agents": args.num_agents,
            "seed": args.seed,
            "task": base.task,
            "demo_length": base.demo_length,
            "max_steps": base.max_steps,
            "house_size_m": list(build_house(base.house_seeds[0]).size_m),
            "stop_action": base.stop_action,
            "success_radius": f"max({base.success_radius_m} m, {base.success_fraction} x initial geodesic distance)",
            "render": False,
            "ci": f"95% percentile bootstrap of the mean, {args.resamples} resamples, numpy default_rng(seed)",
            "episodes": "identical across policies and noise presets of a split (same env seed and batch size; "
            "episode_seeds_checksum is equal within a split)",
            "open_loop": "replays the demonstration's actions, then turns left after the demonstration",
        },
        "notes": list(NOTES),
        "results": results,
    }

    def save() -> None:  # after every run, so a partial run still leaves its results
        args.output.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.output, output)

    tasks = [(split, *run.split(":")) for split in args.splits for run in args.runs]
    common = (args.episodes, env_kwargs, args.seed, args.resamples)

    def collect(rows) -> None:
        for row in rows:  # in task order
            results.append(row)
            logger.info(
                "%s %s %s: success %.3f, SPL %.3f (%.0f s)",
                row["split"], row["policy"], row["noise"], row["success"], row["spl"], row["seconds"],
            )
            save()

    if args.jobs <= 1:
        collect(run_one(*task, *common, True) for task in tasks)
    else:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs) as pool:
            collect(pool.map(run_one, *zip(*[(*task, *common, False) for task in tasks])))

    print("\n| split | policy | noise | success [95% CI] | SPL [95% CI] | mean steps |")
    print("|---|---|---|---|---|---|")
    for row in results:
        (sl, sh), (pl, ph) = row["success_ci95"], row["spl_ci95"]
        print(
            f"| {row['split']} | {row['policy']} | {row['noise']} | {row['success']:.3f} [{sl:.3f}, {sh:.3f}] | "
            f"{row['spl']:.3f} [{pl:.3f}, {ph:.3f}] | {row['mean_steps']:.1f} |"
        )
    print(f"\nwrote {args.output}")


if __name__ == "__main__":
    main()
