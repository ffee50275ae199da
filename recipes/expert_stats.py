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

import envs  # noqa: E402,F401
import numpy as np  # noqa: E402
import torch  # noqa: E402

from envs.factory import make_path_follow_env  # noqa: E402
from envs.scripted import ExpertPolicy, OpenLoopReplay, run_episodes  # noqa: E402

logger = logging.getLogger("expert_stats")

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "expert_stats.json"
#: (policy, noise preset) pairs scored by default.
DEFAULT_RUNS = (
    ("expert", "none"),
    ("expert", "paper"),
    ("expert", "locobot"),
    ("open_loop", "none"),
    ("open_loop", "paper"),
    ("open_loop", "locobot"),
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=500, help="episodes per (split, policy, noise)")
    parser.add_argument("--splits", nargs="+", default=["train", "test"])
    parser.add_argument("--num-agents", type=int, default=25, help="agents of the batched env")
    parser.add_argument("--demo-length", type=int, default=None, help="default: the env's")
    parser.add_argument("--seed", type=int, default=0, help="env seed (fixes the episodes) and bootstrap seed")
    parser.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples")
    parser.add_argument("--output", type=Path, default=RESULTS_PATH)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)

    env_kwargs: dict = {"num_agents": args.num_agents, "render": False, "with_expert": True}
    if args.demo_length is not None:
        env_kwargs["demo_length"] = args.demo_length
    results: list[dict] = []
    base = make_path_follow_env("none", split=args.splits[0], num_agents=1, render=False, with_expert=True).base_env
    output = {
        "recipe": "recipes/expert_stats.py",
        "setup": {
            "episodes_per_run": args.episodes,
            "num_agents": args.num_agents,
            "seed": args.seed,
            "demo_length": base.demo_length,
            "max_steps": base.max_steps,
            "stop_action": base.stop_action,
            "success_radius": f"max({base.success_radius_m} m, {base.success_fraction} x initial geodesic distance)",
            "render": False,
            "ci": f"95% percentile bootstrap of the mean, {args.resamples} resamples, numpy default_rng(seed)",
            "episodes": "identical across policies and noise presets of a split (same env seed and batch size; "
            "episode_seeds_checksum is equal within a split)",
            "open_loop": "replays the demonstration's actions, then turns left after the demonstration",
        },
        "results": results,
    }

    def save() -> None:  # after every run, so a partial run still leaves its results
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(output, indent=2) + "\n")

    for split in args.splits:
        for policy_name, noise in DEFAULT_RUNS:
            env = make_path_follow_env(noise, split=split, **env_kwargs)
            env.set_seed(args.seed)
            policy = ExpertPolicy() if policy_name == "expert" else OpenLoopReplay()
            start = time.perf_counter()
            records = run_episodes(env, policy, args.episodes, progress=True)
            elapsed = time.perf_counter() - start
            row = {"split": split, "policy": policy_name, "noise": noise, **score(records, args.seed, args.resamples)}
            row["seconds"] = elapsed
            row["episode_seeds_checksum"] = int(sum(r["episode_seed"] % 1_000_003 for r in records))
            results.append(row)
            logger.info(
                "%s %s %s: success %.3f, SPL %.3f (%.0f s)", split, policy_name, noise, row["success"], row["spl"], elapsed
            )
            env.close(raise_if_closed=False)
            save()

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
