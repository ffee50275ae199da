"""The main job's budget, measured: the previous default beside the current one, in one run.

Runs ``python recipes/bc.py``'s job twice from scratch on this machine, one after the
other, each with its own dataset directory (both pay dataset generation, training,
validation and test):

* ``previous``: the main job before its budget was raised: 2,000 episodes, 6 epochs
  = 750 gradient steps, 100 validation episodes after every epoch, 500 test episodes;
* ``current``: today's defaults (``BCConfig()``).

Writes ``benchmarks/results/main_job.json`` (or ``--output``): each job's budget
(gradient steps, episodes), wall seconds and test success, and the ratio of wall times
(current / previous), the figure the budget is held to (at most 2x). Wall seconds
are only comparable within one run; machines of one kind differ by up to 4x.

Usage::

    python benchmarks/bench_main_job.py                 # two full main jobs (tens of minutes on 2 cores)
    python benchmarks/bench_main_job.py --quick         # tiny versions of both, for a smoke test
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shutil
import time
from pathlib import Path

from envs.atomic_io import atomic_write_json
from spf_rl.config import load_config

#: The main job before its budget was raised (commit 1bca04c and earlier), as overrides of today's.
PREVIOUS_MAIN_JOB = ["optim.epochs=6", "val.num_episodes=100", "val_every=1"]
#: --quick: both jobs scaled down (the same overrides on top), so the smoke test runs in a minute.
QUICK = [
    "data.num_episodes=16", "data.num_houses=1", "data.demo_length=5", "data.max_steps=8", "data.image_size=32",
    "model.feature_dim=16", "model.hidden_size=16",
    "val.num_episodes=4", "val.num_agents=4", "val.num_houses=1", "test.num_episodes=4", "test.num_agents=4", "test.num_houses=1",
]

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


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny versions of both jobs (a smoke test, not a result)")
    parser.add_argument("--output", default="benchmarks/results/main_job.json")
    parser.add_argument("--workdir", default="runs/bench_main_job", help="scratch directory, emptied first")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import torch

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.bc import BCConfig

    workdir = Path(args.workdir)
    extra = QUICK if args.quick else []
    configs = {
        name: dataclasses.replace(
            load_config(BCConfig, "bc", [*overrides, *extra]),
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
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(output, report)
    logger.info("wall ratio current/previous %.2f", report["wall_ratio_current_to_previous"])
    return report


if __name__ == "__main__":
    main()
