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
import json
import logging
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

import envs  # noqa: E402,F401
from envs.demos import DEFAULT_DEMO_LENGTH  # noqa: E402
from envs.factory import make_path_follow_env  # noqa: E402
from envs.homing import FOLLOW, TASKS  # noqa: E402
from envs.scenes import SPLIT_SEED_OFFSETS, build_house  # noqa: E402
from envs.scripted import ExpertPolicy, OpenLoopReplay, run_episodes  # noqa: E402
from envs.transforms import NOISE_PRESETS  # noqa: E402

logger = logging.getLogger("expert_stats")

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "expert_stats.json"
#: (policy, noise preset) pairs scored by default.
DEFAULT_RUNS = (
    ("expert", "none"),
    ("expert", "paper"),
    ("expert", "paper_symmetric"),
    ("expert", "paper_unclipped"),
    ("expert", "locobot"),
    ("open_loop", "none"),
    ("open_loop", "paper"),
    ("open_loop", "paper_symmetric"),
    ("open_loop", "paper_unclipped"),
    ("open_loop", "locobot"),
)


#: Caveats written into the JSON with the numbers.
NOTES = (
    "SPL saturates at 1 for near-optimal agents: without STOP the episode ends as soon as the agent is within "
    "max(0.6 m, 10% of the initial geodesic distance) of the route's end, while SPL compares the path taken with the "
    "full start-to-end geodesic length (mean_path_length_m is below mean_shortest_path_length_m). A detour shorter "
    "than the success radius costs no SPL, so expert SPL = 1.000 does not mean the expert's paths are optimal.",
    "Open-loop replay without noise succeeds by construction: the demonstration is replayed from its own start pose "
    "with the nominal motion that produced it, so it reaches the goal.",
    "Episodes whose agents finish their quota early keep stepping (their extra episodes are discarded), so 'seconds' "
    "is not a per-episode cost.",
)


def bootstrap_ci(values: np.ndarray, rng: np.random.Generator, resamples: int = 10_000, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of the mean."""
    values = np.asarray(values, dtype=np.float64)
    indices = rng.integers(0, len(values), size=(resamples, len(values)))
    means = values[indices].mean(axis=1)
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


def score(records: list[dict], seed: int, resamples: int) -> dict:
    """Mean success / SPL with bootstrap CIs, plus episode summaries."""
    success = np.array([r["success"] for r in records], dtype=np.float64)
    spl = np.array([r["spl"] for r in records], dtype=np.float64)
    rng = np.random.default_rng(seed)
    return {
        "episodes": len(records),
        "success": float(success.mean()),
        "success_ci95": bootstrap_ci(success, rng, resamples),
        "spl": float(spl.mean()),
        "spl_ci95": bootstrap_ci(spl, rng, resamples),
        "mean_steps": float(np.mean([r["steps"] for r in records])),
        "mean_final_goal_distance_m": float(np.mean([r["goal_distance"] for r in records])),
        "mean_path_length_m": float(np.mean([r["path_length"] for r in records])),
        "mean_shortest_path_length_m": float(np.mean([r["shortest_path_length"] for r in records])),
    }


def run_one(split: str, policy_name: str, noise: str, episodes: int, env_kwargs: dict, seed: int, resamples: int, progress: bool) -> dict:
    """Score one (split, policy, noise) run; module-level so worker processes can run it."""
    torch.set_num_threads(1)
    env = make_path_follow_env(noise, split=split, **env_kwargs)
    env.set_seed(seed)
    policy = ExpertPolicy() if policy_name == "expert" else OpenLoopReplay()
    start = time.perf_counter()
    records = run_episodes(env, policy, episodes, progress=progress)
    elapsed = time.perf_counter() - start
    env.close(raise_if_closed=False)
    row = {"split": split, "policy": policy_name, "noise": noise, **score(records, seed, resamples)}
    row["seconds"] = elapsed
    row["episode_seeds_checksum"] = int(sum(r["episode_seed"] % 1_000_003 for r in records))
    return row


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
        if policy_name not in ("expert", "open_loop") or noise not in NOISE_PRESETS:
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
        args.output.write_text(json.dumps(output, indent=2) + "\n")

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
