"""Behaviour cloning of one SPF model on demonstrations of several lengths (30, 50 and 100 steps).

Builds (or reuses) one expert-labelled dataset per length, trains one set of weights
on all of them (:mod:`spf_rl.train.lengths`), keeps the best checkpoint by the mean
validation success over the lengths, and tests it at each length: ``results.json``
(``test_by_length``) and ``success_by_length.png`` in the output directory. Run it
again with the same config to resume.

Usage::

    python recipes/bc_lengths.py                          # configs/bc_lengths.yaml: 5,236 gradient steps
    python recipes/bc_lengths.py --quick                  # the whole pipeline in minutes
    python recipes/bc_lengths.py lengths=[30,50] episodes=[4000,2400] device=cuda

The checkpoint (``best.pt``) is saved for the first length; load it at any length with
:func:`spf_rl.modules.views.policy_for_length`, or compare it with other checkpoints
with ``python recipes/success_by_length.py``.
"""
from __future__ import annotations

import argparse
import json
import logging

from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few-minute smoke run (configs/bc_lengths_quick.yaml)")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides (lengths=[30,50,100], optim.epochs=4, ...)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.lengths import MixedLengthConfig, train_bc_mixed

    preset = "bc_lengths_quick" if args.quick else None
    config = config_or_exit(parser, load_config, MixedLengthConfig, "bc_lengths", args.overrides, preset=preset)
    results = train_bc_mixed(config)
    summary = {
        "model": results["model"],
        "sparsity": results["sparsity"],
        "test_by_length": {
            row["demo_length"]: {"success": round(row["success"], 3), "spl": round(row["spl"], 3), "episodes": row["episodes"]}
            for row in results["test_by_length"]
        },
        "output_dir": config.output_dir,
    }
    print(json.dumps(summary, indent=2))
    return results


if __name__ == "__main__":
    main()
