"""The main job, measured: its budget against the previous one, or its speed against a baseline commit.

Runs ``python recipes/bc.py``'s job twice from scratch on this machine, one after the
other, each with its own dataset directory (both pay dataset generation, training,
validation and test):

* by default, ``previous`` (the main job before its budget was raised: 2,000 episodes,
  6 epochs = 750 gradient steps, 100 validation episodes after every epoch, 500 test
  episodes, the paper's recipe) and ``current`` (today's main job, ``--preset bc_main``); writes
  ``benchmarks/results/main_job.json``: each job's budget (gradient steps, episodes),
  wall seconds and test success, and the ratio of wall times (current / previous), the
  figure the budget is held to (at most 2x);
* with ``--baseline [COMMIT]``, ``baseline`` (the main job of ``COMMIT``, by default
  :data:`bench_baseline.BASELINE_COMMIT`, main when issue #30 was filed, run from a ``git
  worktree`` of it) and ``current`` (the working tree's), each as ``python recipes/bc.py``
  in a child process with its own dataset and evaluation stores; writes
  ``benchmarks/results/main_job_baseline.json``: each job's wall seconds and test scores,
  the speed-up (baseline wall / current wall) and the paired comparison of their test
  success on the same 500 episodes (current - baseline, :func:`spf_rl.eval.paired.compare`),
  the quality check of a speed change.

Wall seconds are only comparable within one run; machines of one kind differ by up to 4x.

Usage::

    python benchmarks/bench_main_job.py                 # two full main jobs (tens of minutes on 2 cores)
    python benchmarks/bench_main_job.py --baseline      # today's main job against a5a7302's
    python benchmarks/bench_main_job.py --quick         # tiny versions of both, for a smoke test
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_baseline import BASELINE_COMMIT, BASELINE_DIR, baseline_worktree, resolve_commit

from envs.atomic_io import atomic_write_json
from spf_rl.config import load_config

ROOT = Path(__file__).resolve().parents[1]

#: The main job before its budget was raised (commit 1bca04c and earlier), as overrides of today's.
PREVIOUS_MAIN_JOB = ["optim.epochs=6", "val.num_episodes=100", "val_every=1"]
#: --quick: both jobs scaled down (the same overrides on top), so the smoke test runs in a minute.
QUICK = [
    "data.num_episodes=16", "data.num_houses=1", "data.demo_length=10", "data.max_steps=17", "data.image_size=32",
    "model.feature_dim=16", "model.hidden_size=16",
    "val.num_episodes=4", "val.num_agents=4", "val.num_houses=1", "test.num_episodes=4", "test.num_agents=4", "test.num_houses=1",
]

#: Where each comparison is written.
RESULTS = "benchmarks/results/main_job.json"
BASELINE_RESULTS = "benchmarks/results/main_job_baseline.json"
#: Bootstrap resamples of the paired quality check.
PAIRED_RESAMPLES = 10_000

logger = logging.getLogger("bench_main_job")


def budget(config) -> dict:
    """A job's budget in gradient steps and episodes."""
    steps = -(-config.data.num_episodes // config.optim.batch_size) * config.optim.epochs
    validated = sum(config.validates_after(epoch) for epoch in range(1, config.optim.epochs + 1))
    return {
        "training_episodes": config.data.num_episodes,
        "epochs": config.optim.epochs,
        "gradient_steps": steps,
        "batch_size": config.optim.batch_size,
        "validation_episodes": config.val.num_episodes * validated,
        "test_episodes": config.test.num_episodes,
    }


def run_job(config) -> dict:
    """Train and test ``config`` from scratch; its budget, wall seconds and test scores."""
    from spf_rl.train.bc import train_bc

    start = time.perf_counter()
    results = train_bc(config)
    wall = time.perf_counter() - start
    test = results["test"]
    return {
        **budget(config),
        "wall_seconds": wall,
        "test_success": test["success"],
        "test_success_ci95": test["success_ci"],
        "test_spl": test["spl"],
        "best_epoch": results["best_epoch"],
    }


def run_child_job(tree: Path, workdir: Path, overrides: list[str]) -> dict:
    """``python recipes/bc.py`` of the tree at ``tree`` in a child process (its own packages), with its
    dataset, evaluation stores and run under ``workdir``; its wall seconds and test scores.

    Raises:
        RuntimeError: the job failed (its exit status and the end of its log are in the message).
    """
    run, data, stores = workdir / "run", workdir / "data", workdir / "episodes"
    argv = [
        sys.executable, "recipes/bc.py", f"output_dir={run.resolve()}", f"data_dir={data.resolve()}",
        f"val.store_root={stores.resolve()}", f"test.store_root={stores.resolve()}", "progress=false", *overrides,
    ]
    workdir.mkdir(parents=True, exist_ok=True)
    log = workdir / "job.log"
    start = time.perf_counter()
    with open(log, "w") as handle:
        result = subprocess.run(argv, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, stdout=handle, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"the main job in {tree} failed (exit status {result.returncode}):\n{log.read_text()[-4000:]}")
    test = json.loads((run / "results.json").read_text())["test"]
    return {
        "wall_seconds": wall,
        "test_success": test["success"],
        "test_success_ci95": test["success_ci"],
        "test_spl": test["spl"],
        "test_episodes_file": str(run / "test_episodes.json"),
    }


def against_previous(args: argparse.Namespace, extra: list[str]) -> dict:
    """The previous main job's budget and today's, in this process, one after the other."""
    import torch

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.bc import MAIN_JOB_PRESET, BCConfig

    workdir = Path(args.workdir)
    presets = {"previous": None, "current": MAIN_JOB_PRESET}  # the previous main job was the paper's recipe
    configs = {
        name: dataclasses.replace(
            load_config(BCConfig, "bc", [*overrides, *extra], preset=presets[name]),
            output_dir=str(workdir / name / "run"),
            data_dir=str(workdir / name / "data"),
            progress=False,
        )
        for name, overrides in (("previous", PREVIOUS_MAIN_JOB), ("current", []))
    }
    if workdir.exists():
        shutil.rmtree(workdir)
    jobs = {}
    for name, config in configs.items():
        logger.info("%s main job: %s", name, budget(config))
        jobs[name] = run_job(config)
        logger.info("%s: %.0f s, test success %.3f", name, jobs[name]["wall_seconds"], jobs[name]["test_success"])
    report = {
        "quick": args.quick,
        "command": "python benchmarks/bench_main_job.py" + (" --quick" if args.quick else ""),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "jobs": jobs,
        "wall_ratio_current_to_previous": jobs["current"]["wall_seconds"] / jobs["previous"]["wall_seconds"],
        "gradient_step_ratio": jobs["current"]["gradient_steps"] / jobs["previous"]["gradient_steps"],
    }
    logger.info("wall ratio current/previous %.2f", report["wall_ratio_current_to_previous"])
    return report


def against_baseline(args: argparse.Namespace, extra: list[str]) -> dict:
    """Today's main job against the baseline commit's, one child process each (baseline first)."""
    from spf_rl.eval.paired import compare

    workdir = Path(args.workdir)
    if workdir.exists():
        shutil.rmtree(workdir)
    with baseline_worktree(ROOT, args.baseline_sha, Path(args.baseline_dir)) as tree:
        jobs = {
            "baseline": run_child_job(tree, workdir / "baseline", extra),
            "current": run_child_job(ROOT, workdir / "current", extra),
        }
    paired = compare(jobs["current"].pop("test_episodes_file"), jobs["baseline"].pop("test_episodes_file"), PAIRED_RESAMPLES, 0)
    logger.info(
        "main job x%.2f the baseline's speed; test success %.3f vs %.3f",
        jobs["baseline"]["wall_seconds"] / jobs["current"]["wall_seconds"],
        jobs["current"]["test_success"], jobs["baseline"]["test_success"],
    )
    return {
        "quick": args.quick,
        "command": "python benchmarks/bench_main_job.py --baseline" + (" --quick" if args.quick else ""),
        "baseline_commit": args.baseline_sha,
        "cpu_count": os.cpu_count(),
        "jobs": jobs,
        "speedup_current_over_baseline": jobs["baseline"]["wall_seconds"] / jobs["current"]["wall_seconds"],
        "paired_current_minus_baseline": paired,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny versions of both jobs (a smoke test, not a result)")
    parser.add_argument(
        "--baseline", nargs="?", const=BASELINE_COMMIT, default=None, metavar="COMMIT",
        help=f"run today's main job against this commit's (default {BASELINE_COMMIT}) instead of the previous budget",
    )
    parser.add_argument("--baseline-dir", default=str(BASELINE_DIR), help="the baseline's worktree, reused if already there")
    parser.add_argument("--output", default=None, help=f"default {RESULTS} ({BASELINE_RESULTS} with --baseline)")
    parser.add_argument("--workdir", default="runs/bench_main_job", help="scratch directory, emptied first")
    args = parser.parse_args(argv)
    if args.baseline is not None:
        try:
            args.baseline_sha = resolve_commit(args.baseline, ROOT)
        except ValueError as err:
            parser.error(f"--baseline: {err}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    extra = QUICK if args.quick else []
    report = against_baseline(args, extra) if args.baseline is not None else against_previous(args, extra)
    output = Path(args.output or (BASELINE_RESULTS if args.baseline is not None else RESULTS))
    output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(output, report)
    return report

if __name__ == "__main__":
    main()
