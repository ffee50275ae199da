"""Success and SPL of the scripted policies, the geodesic expert and open-loop replay, on
the same episodes (``recipes/expert_stats.py`` runs it and writes
``benchmarks/results/expert_stats*.json``).

Each (split, policy, noise) run plays :func:`envs.episodes.run_episodes` on a batched
env with a fixed seed (agent ``i``'s k-th episode depends only on the seed, ``i`` and
``k``), without rendering. Means come with 95% percentile bootstrap intervals
(:func:`spf_rl.stats.bootstrap_ci`).

* :func:`run_one`: one run; :func:`run_study`: every (split, run) pair, serially or in
  worker processes, the JSON rewritten after each run (a partial study keeps its rows);
* :func:`parse_runs`, :func:`check_splits`, :func:`default_output`: the study's options;
* :func:`study_setup`: the set-up written with the numbers; :func:`markdown_table`: the rows as a table.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from envs.atomic_io import atomic_write_json
from envs.demos import DEFAULT_DEMO_LENGTH
from envs.episodes import run_episodes
from envs.factory import make_path_follow_env
from envs.homing import FOLLOW
from envs.scenes import SPLIT_SEED_OFFSETS, build_house
from envs.scripted import ExpertPolicy, OpenLoopReplay
from envs.transforms import NOISE_PRESETS
from spf_rl.stats import bootstrap_ci

logger = logging.getLogger(__name__)

#: The recipe named in the JSON.
RECIPE = "recipes/expert_stats.py"
#: File name of the paper's study (follow, n = 30); others are ``expert_stats_<task>_n<n>.json`` beside it.
RESULTS_NAME = "expert_stats.json"

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
        "ndtw": float(np.mean([r["ndtw"] for r in records])),
        "mean_path_length_ratio": float(np.mean([r["path_length_ratio"] for r in records])),
    }


def run_one(split: str, policy_name: str, noise: str, episodes: int, env_kwargs: dict, seed: int, resamples: int, progress: bool) -> dict:
    """Score one (split, policy, noise) run; module-level so worker processes can run it.

    Raises:
        ValueError: a ``policy_name`` not in :data:`POLICIES` (before any work; the env checks
            ``split``, ``noise`` and ``env_kwargs``).
    """
    if policy_name not in POLICIES:
        raise ValueError(f"policy_name must be one of {POLICIES}, got {policy_name!r}.")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one core per run: the runs share the machine's cores
    try:
        env = make_path_follow_env(noise, split=split, **env_kwargs)
        env.set_seed(seed)
        policy = ExpertPolicy() if policy_name == "expert" else OpenLoopReplay()
        start = time.perf_counter()
        records = run_episodes(env, policy, episodes, progress=progress)
        elapsed = time.perf_counter() - start
        env.close(raise_if_closed=False)
    finally:  # the caller's thread count back, e.g. when run in-process
        torch.set_num_threads(threads)
    row = {"split": split, "policy": policy_name, "noise": noise, **score(records, seed, resamples)}
    row["seconds"] = elapsed
    row["episode_seeds_checksum"] = int(sum(r["episode_seed"] % 1_000_003 for r in records))
    return row


def parse_runs(runs: Iterable[str]) -> list[tuple[str, str]]:
    """``"policy:noise"`` items -> ``(policy, noise)`` pairs, every one checked before any episode is played.

    Raises:
        ValueError: an item that is not ``POLICY:NOISE`` with a policy of :data:`POLICIES` and a noise preset.

    Examples:
        >>> parse_runs(["expert:paper", "open_loop:none"])
        [('expert', 'paper'), ('open_loop', 'none')]
    """
    pairs = []
    for run in runs:
        policy_name, _, noise = run.partition(":")
        if policy_name not in POLICIES or noise not in NOISE_PRESETS:
            raise ValueError(
                f"--runs: {run!r} must be POLICY:NOISE with POLICY in (expert, open_loop) and NOISE in {sorted(NOISE_PRESETS)}"
            )
        pairs.append((policy_name, noise))
    return pairs


def check_splits(splits: Iterable[str]) -> None:
    """Raise ``ValueError`` naming the first split that is not a house split.

    Examples:
        >>> check_splits(["train", "test"])
        >>> check_splits(["train", "dev"])
        Traceback (most recent call last):
        ...
        ValueError: --splits: 'dev' is not one of ['train', 'val', 'test']
    """
    for split in splits:
        if split not in SPLIT_SEED_OFFSETS:
            raise ValueError(f"--splits: {split!r} is not one of {list(SPLIT_SEED_OFFSETS)}")


def default_output(results_path: Path, task: str, demo_length: int | None) -> Path:
    """``results_path`` for the paper's study (follow, n = 30), else ``expert_stats_<task>_n<n>.json`` beside it.

    Examples:
        >>> default_output(Path("results/expert_stats.json"), "homing", None).name
        'expert_stats_homing_n30.json'
        >>> default_output(Path("results/expert_stats.json"), "follow", 30).name
        'expert_stats.json'
    """
    length = demo_length or DEFAULT_DEMO_LENGTH
    paper = task == FOLLOW and length == DEFAULT_DEMO_LENGTH
    return results_path if paper else results_path.with_name(f"expert_stats_{task}_n{length}.json")


def study_env_kwargs(
    num_agents: int, task: str, demo_length: int | None = None, route_style: str | None = None,
    route_lengths: tuple[int, int] | None = None, expert: str | None = None,
) -> dict:
    """Keyword arguments of the study's envs: no rendering, the expert's labels, the rest if given.

    Examples:
        >>> study_env_kwargs(25, "follow", 50)["demo_length"], study_env_kwargs(25, "follow")["render"]
        (50, False)
    """
    env_kwargs: dict = {"num_agents": num_agents, "render": False, "emit_demo_frames": False, "with_expert": True, "task": task}
    optional = {"demo_length": demo_length, "route_style": route_style, "route_lengths": route_lengths, "expert": expert}
    env_kwargs.update({key: value for key, value in optional.items() if value is not None})
    return env_kwargs


def study_setup(split: str, env_kwargs: dict, episodes: int, seed: int, resamples: int) -> dict:
    """The set-up written with the numbers, read off an env of ``split`` made with ``env_kwargs``."""
    base = make_path_follow_env("none", split=split, **{**env_kwargs, "num_agents": 1}).base_env
    return {
        "episodes_per_run": episodes,
        "num_agents": env_kwargs["num_agents"],
        "seed": seed,
        "task": base.task,
        "demo_length": base.demo_length,
        "max_steps": base.max_steps,
        "house_size_m": list(build_house(base.house_seeds[0]).size_m),
        "stop_action": base.stop_action,
        "route_style": None if base.route_style is None else base.route_style.spec,
        "route_lengths": None if base.route_style is None else [base.route_style.min_length, base.route_style.max_length],
        "expert": base.expert,
        "success_radius": f"max({base.success_radius_m} m, {base.success_fraction} x initial geodesic distance)",
        "render": False,
        "ci": f"95% percentile bootstrap of the mean, {resamples} resamples, numpy default_rng(seed)",
        "episodes": "identical across policies and noise presets of a split (same env seed and batch size; "
        "episode_seeds_checksum is equal within a split)",
        "open_loop": "replays the demonstration's actions, then turns left after the demonstration",
    }


def run_study(
    splits: Sequence[str],
    runs: Sequence[tuple[str, str]],
    output: Path,
    *,
    episodes: int,
    env_kwargs: dict,
    seed: int = 0,
    resamples: int = 10_000,
    jobs: int = 1,
) -> dict:
    """Score every (split, policy, noise) run and write the JSON to ``output`` after each one.

    Args:
        splits: house splits (:func:`check_splits`).
        runs: ``(policy, noise)`` pairs (:func:`parse_runs`).
        output: the JSON file, rewritten after every run so that a partial study keeps its rows.
        episodes: episodes per run.
        env_kwargs: the envs' keyword arguments (:func:`study_env_kwargs`).
        seed: env seed (fixes the episodes) and bootstrap seed.
        resamples: bootstrap resamples.
        jobs: worker processes (runs are independent); ``1``: this process, with progress bars.

    Returns:
        The JSON content: ``recipe``, ``setup`` (:func:`study_setup`), ``notes`` and ``results``
        (one row per run, split-major, in the order given).
    """
    results: list[dict] = []
    content = {
        "recipe": RECIPE,
        "setup": study_setup(splits[0], env_kwargs, episodes, seed, resamples),
        "notes": list(NOTES),
        "results": results,
    }
    tasks = [(split, policy_name, noise) for split in splits for policy_name, noise in runs]
    common = (episodes, env_kwargs, seed, resamples)

    def collect(rows: Iterable[dict]) -> None:
        for row in rows:  # in task order
            results.append(row)
            logger.info(
                "%s %s %s: success %.3f, SPL %.3f (%.0f s)",
                row["split"], row["policy"], row["noise"], row["success"], row["spl"], row["seconds"],
            )
            output.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_json(output, content)

    if jobs <= 1:
        collect(run_one(*task, *common, True) for task in tasks)
    else:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs) as pool:
            collect(pool.map(run_one, *zip(*[(*task, *common, False) for task in tasks])))
    return content


def markdown_table(rows: Iterable[dict]) -> str:
    """The rows of :func:`run_study` as a markdown table: success and SPL with their intervals, mean steps.

    Examples:
        >>> row = {"split": "test", "policy": "expert", "noise": "paper", "success": 0.98, "success_ci95": [0.97, 0.99],
        ...        "spl": 0.95, "spl_ci95": [0.94, 0.96], "mean_steps": 21.04}
        >>> print(markdown_table([row]))
        | split | policy | noise | success [95% CI] | SPL [95% CI] | mean steps |
        |---|---|---|---|---|---|
        | test | expert | paper | 0.980 [0.970, 0.990] | 0.950 [0.940, 0.960] | 21.0 |
    """
    lines = ["| split | policy | noise | success [95% CI] | SPL [95% CI] | mean steps |", "|---|---|---|---|---|---|"]
    for row in rows:
        (sl, sh), (pl, ph) = row["success_ci95"], row["spl_ci95"]
        lines.append(
            f"| {row['split']} | {row['policy']} | {row['noise']} | {row['success']:.3f} [{sl:.3f}, {sh:.3f}] | "
            f"{row['spl']:.3f} [{pl:.3f}, {ph:.3f}] | {row['mean_steps']:.1f} |"
        )
    return "\n".join(lines)
