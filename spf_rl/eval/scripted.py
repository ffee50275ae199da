"""Success and SPL of the scripted policies, the geodesic expert and open-loop replay, on
the same episodes (``recipes/expert_stats.py`` runs it and writes
``benchmarks/results/expert_stats*.json``).

Each (split, policy, noise) run plays :func:`envs.scripted.run_episodes` on a batched
env with a fixed seed (agent ``i``'s k-th episode depends only on the seed, ``i`` and
``k``), without rendering. Means come with 95% percentile bootstrap intervals
(:func:`spf_rl.stats.bootstrap_ci`).
"""
from __future__ import annotations

import time

import numpy as np
import torch

from envs.factory import make_path_follow_env
from envs.scripted import ExpertPolicy, OpenLoopReplay, run_episodes
from spf_rl.stats import bootstrap_ci

#: The policies :func:`run_one` scores.
POLICIES = ("expert", "open_loop")
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


def score(records: list[dict], seed: int, resamples: int) -> dict:
    """Mean success / SPL with bootstrap CIs, plus episode summaries."""
    success = np.array([r["success"] for r in records], dtype=np.float64)
    spl = np.array([r["spl"] for r in records], dtype=np.float64)
    return {
        "episodes": len(records),
        "success": float(success.mean()),
        "success_ci95": bootstrap_ci(success, num_resamples=resamples, seed=seed),
        "spl": float(spl.mean()),
        "spl_ci95": bootstrap_ci(spl, num_resamples=resamples, seed=seed),
        "mean_steps": float(np.mean([r["steps"] for r in records])),
        "mean_final_goal_distance_m": float(np.mean([r["goal_distance"] for r in records])),
        "mean_path_length_m": float(np.mean([r["path_length"] for r in records])),
        "mean_shortest_path_length_m": float(np.mean([r["shortest_path_length"] for r in records])),
    }


def run_one(split: str, policy_name: str, noise: str, episodes: int, env_kwargs: dict, seed: int, resamples: int, progress: bool) -> dict:
    """Score one (split, policy, noise) run; module-level so worker processes can run it.

    Raises:
        ValueError: a ``policy_name`` not in :data:`POLICIES` (before any work; the env checks
            ``split``, ``noise`` and ``env_kwargs``).
    """
    if policy_name not in POLICIES:
        raise ValueError(f"policy_name must be one of {POLICIES}, got {policy_name!r}.")
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
