"""Behaviour cloning of the SPF policy: the project's main job.

Builds (or reuses) the expert-labelled dataset, trains on whole episodes, keeps
the best checkpoint by validation success, evaluates it on the test split under
``paper`` noise and writes ``results.json`` and ``training_curves.png`` to the
output directory. Run it again with the same config to resume.

Usage::

    python recipes/bc.py                       # the main job: SPF 0.8 with a pointer loss, 1,500 gradient steps on 2,000 episodes
    python recipes/bc.py --preset bc_paper     # the paper's recipe exactly, on the same budget
    python recipes/bc.py --quick               # the whole pipeline in a few minutes
    python recipes/bc.py --preset bc_long      # 20,000 gradient steps on 8,000 episodes (hours on 2 CPU cores)
    python recipes/bc.py --preset bc_row model=rpf   # the common 5,000-step schedule of the other Table 1 rows
    python recipes/bc.py --preset bc_homing    # the bc_row schedule on homing episodes (returning to the route's start)
    python recipes/bc.py model=rpf             # full memory baseline
    python recipes/bc.py model=spf sparsity=0.4 noise=paper optim.epochs=4
    python recipes/bc.py device=cuda optim.amp=true   # GPU, bf16 mixed precision (default device=auto)
    torchrun --standalone --nproc_per_node 2 recipes/bc.py   # data-parallel: 2 processes, the same global batch
"""
from __future__ import annotations

import argparse
import json
import logging

from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config

#: Schedules in recipes/configs/ that --preset accepts.
PRESETS = ("bc_main", "bc_paper", "bc_quick", "bc_long", "bc_row", "bc_table1", "bc_homing", "bc_pointer_long", "bc_routes",
           "bc_routes_pointer")


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small preset that runs in a few minutes (= --preset bc_quick)")
    parser.add_argument(
        "--preset",
        choices=PRESETS,
        default=None,
        help="a schedule from recipes/configs/ (default bc_main, the main job: the paper's SPF with a pointer loss): "
        "bc_paper (the paper's recipe on the main job's budget), bc_quick (smoke run), bc_long (20,000 gradient steps on 8,000 "
        "episodes), bc_row (5,000 gradient steps on 4,000 episodes, the earlier Table 1 rows), bc_table1 (bc_long in runs/table1/: Table 1's one budget, every row), bc_homing (bc_row on homing episodes), bc_pointer_long (bc_long with RPF's pointer rule), bc_routes (the routes model: bc_row on a mixture of route styles of 10 to 100 steps) or bc_routes_pointer (bc_routes with a pointer loss, optim.pointer_coef 0.1)",
    )
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.bc import MAIN_JOB_PRESET, BCConfig, train_bc

    if args.quick and args.preset not in (None, "bc_quick"):
        parser.error(f"--quick is --preset bc_quick; it cannot be combined with --preset {args.preset}")
    preset = "bc_quick" if args.quick else (args.preset or MAIN_JOB_PRESET)
    config = config_or_exit(parser, load_config, BCConfig, "bc", args.overrides, preset=preset)
    results = train_bc(config)
    if "test" not in results:  # a rank other than 0 of a torchrun run: rank 0 reports
        return results
    test = results["test"]
    summary = {
        "model": results["model"],
        "sparsity": results["sparsity"],
        "test_success": round(test["success"], 3),
        "test_success_ci95": [round(x, 3) for x in test["success_ci"]],
        "test_spl": round(test["spl"], 3),
        "test_spl_ci95": [round(x, 3) for x in test["spl_ci"]],
        "episodes": test["episodes"],
        "memory_bytes": results["memory_bytes"],
        "output_dir": config.output_dir,
    }
    print(json.dumps(summary, indent=2))
    return results


if __name__ == "__main__":
    main()
